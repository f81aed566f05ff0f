//! Reading: the image HDU, its header cards and pixels, the VARIANCE and MASK extensions.
use std::path::Path;

use fitsio::hdu::HduInfo;
use fitsio::FitsFile;
use ndarray::Array2;

use crate::error::{Error, Result};
use crate::frame::{Frame, PixelSummary};
use crate::header::{Header, HeaderValue};

use super::cards::*;
use super::cfitsio::*;
use super::keys::{is_compressed, raw_int, raw_value};
use super::{to_array, LEGACY_VARIANCE_EXTNAME, MASK_EXTNAME, VARIANCE_EXTNAME, VARIANCE_UTYPE};

/// Read the header of the image HDU only (see the module documentation for which HDU).
///
/// Structural keywords (SIMPLE, BITPIX, NAXISn, EXTEND, BZERO, BSCALE, PCOUNT, GCOUNT,
/// XTENSION, EXTNAME, EXTVER, BLANK, CHECKSUM, DATASUM, the Z* and T* keywords of tile
/// compression...) are not returned, nor are COMMENT and HISTORY cards (see
/// [`read_frame`] for HISTORY). `HIERARCH ESO ADA POSANG` is stored as `ESO ADA POSANG`.
/// Values are typed: strings (CONTINUE long strings joined), integers, floats, logicals.
/// When a keyword occurs twice the first occurrence wins, as in cfitsio look-ups.
///
/// ```
/// let path = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"),
///     "/../testdata/fits/sofi_pol_64x64_i16.fits"));
/// let h = sofipol_calib::fits::read_header(path)?;
/// assert_eq!(h.get_f64("ESO ADA POSANG")?, 45.0);
/// assert_eq!(h.get_str("INSTRUME")?, "SOFI");
/// # Ok::<(), sofipol_calib::Error>(())
/// ```
pub fn read_header(path: &Path) -> Result<Header> {
    if let Some(p) = super::raw::plain_primary(path) {
        // The checks find_image_hdu makes (e.g. an unsigned 64-bit image is refused here).
        image_dims(&p.cards, path)?;
        return Ok(parse_cards(&p.cards, path).0);
    }
    let mut f = open(path)?;
    let (index, cards) = find_image_hdu(&mut f, path)?;
    let mut header = parse_cards(&cards, path).0;
    header.image_hdu = index;
    Ok(header)
}

/// The (NAXIS2, NAXIS1) of the image HDU, from its header (no pixels read): the size of
/// the whole image when only some rows were read ([`read_frame_rows`]).
pub fn read_image_shape(path: &Path) -> Result<(usize, usize)> {
    if let Some(p) = super::raw::plain_primary(path) {
        return image_dims(&p.cards, path);
    }
    let mut f = open(path)?;
    let (_, cards) = find_image_hdu(&mut f, path)?;
    image_dims(&cards, path)
}

/// Read a frame: the image as `f32` (`[y, x]`, row 0 = FITS row 1), its header, HISTORY
/// cards as provenance records, and VARIANCE / MASK extensions when present.
///
/// HISTORY cards of the form `sofipol <stage>: <detail>` (as written by [`super::write_frame`],
/// continuation cards joined) become records of that stage; any other HISTORY card
/// becomes a record of stage `"file"`. Without a MASK extension the mask is all zeros.
///
/// Errors name the file: missing, unreadable, truncated or non-FITS files, and images
/// that are not 2-D or are empty ([`Error::BadImage`] with the NAXIS values).
///
/// ```
/// let path = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"),
///     "/../testdata/fits/sofi_pol_64x64_i16.fits.fz"));
/// let frame = sofipol_calib::fits::read_frame(path)?;
/// assert_eq!(frame.shape(), (64, 64));
/// assert_eq!(frame.header.get_str("ESO TPL ID")?, "SOFI_img_obs_Polarimetry");
/// # Ok::<(), sofipol_calib::Error>(())
/// ```
pub fn read_frame(path: &Path) -> Result<Frame> {
    read_frame_rows(path, None)
}

/// [`read_frame`] of the rows `[r0, r1)` only (cfitsio reads just those rows of the image
/// and of the VARIANCE / MASK extensions): the same frame as
/// `read_frame(path)?.crop_rows(r0, r1)`, history record included, at a fraction of the
/// cost. An image with fewer than `r1` rows (or `r0 >= r1`) is read whole and uncropped, as
/// the reduction's cropping leaves such frames. `None`: the whole image.
pub fn read_frame_rows(path: &Path, rows: Option<(usize, usize)>) -> Result<Frame> {
    read_rows_inner(path, rows, false).map(|(f, _)| f)
}

/// [`read_frame_rows`] and the [`PixelSummary`] of the image's pixels as read (non-finite
/// count, finite minimum and maximum), which the night's frames get almost for free from
/// their conversion pass.
pub fn read_frame_rows_with_summary(path: &Path, rows: Option<(usize, usize)>) -> Result<(Frame, PixelSummary)> {
    read_rows_inner(path, rows, true).map(|(f, s)| {
        let s = s.unwrap_or_else(|| PixelSummary::of(f.data.as_slice().expect("standard layout")));
        (f, s)
    })
}

/// The frame, and the pixels' summary when the conversion gave it (or `want_summary`).
fn read_rows_inner(
    path: &Path,
    rows: Option<(usize, usize)>,
    want_summary: bool,
) -> Result<(Frame, Option<PixelSummary>)> {
    // A night frame (one plain primary image) is read without cfitsio.
    if let Some(p) = super::raw::plain_primary(path) {
        if let Some(plain) = super::raw::PlainImage::at(&p.cards, p.start) {
            let (header, history) = parse_cards(&p.cards, path);
            let (ny_full, nx) = image_dims(&p.cards, path)?;
            let rows = rows.filter(|&(r0, r1)| r0 < r1 && r1 <= ny_full);
            let ny = rows.map_or(ny_full, |(r0, r1)| r1 - r0);
            let (data, summary) = plain.read_rows(path, nx, rows.map_or(0, |r| r.0), ny)?;
            let frame = Frame {
                mask: Array2::zeros((ny, nx)),
                data,
                variance: None,
                header,
                history,
            };
            return Ok((with_crop_record(frame, rows), Some(summary)));
        }
    }
    let mut f = open(path)?;
    let (hdu_index, cards) = find_image_hdu(&mut f, path)?;
    let (mut header, history) = parse_cards(&cards, path);
    header.image_hdu = hdu_index;
    let (ny_full, nx) = image_dims(&cards, path)?;
    check_size_against_file(&cards, path, ny_full, nx)?;
    let rows = rows.filter(|&(r0, r1)| r0 < r1 && r1 <= ny_full);
    let ny = rows.map_or(ny_full, |(r0, r1)| r1 - r0);
    let read = |f: &mut FitsFile, i: usize| -> Result<Array2<f32>> {
        match rows {
            None => read_f32(f, path, i, ny_full, nx),
            Some((r0, _)) => read_f32_rows(f, path, i, (ny_full, nx), r0, ny),
        }
    };

    // The usual night frame (plain BITPIX 16 or -32) is read straight from the file.
    let (data, summary) = match super::raw::plain_image(&mut f, path, hdu_index, &cards)? {
        Some(plain) => {
            let (d, s) = plain.read_rows(path, nx, rows.map_or(0, |r| r.0), ny)?;
            (d, Some(s))
        }
        None => {
            let d = read(&mut f, hdu_index)?;
            let s = want_summary.then(|| PixelSummary::of(d.as_slice().expect("standard layout")));
            (d, s)
        }
    };

    // Look for VARIANCE / MASK extensions after the image HDU.
    let mut variance = None;
    let mut mask = None;
    let mut i = hdu_index + 1;
    while let Some(cards) = hdu_cards(&mut f, path, i)? {
        match extname(&cards).as_deref() {
            Some(name @ (VARIANCE_EXTNAME | LEGACY_VARIANCE_EXTNAME)) if variance.is_none() => {
                check_same_shape(&cards, path, name, (ny_full, nx))?;
                let kind = uncertainty_kind(&cards, name, path)?;
                variance = Some(kind.to_variance(read(&mut f, i)?));
            }
            Some(MASK_EXTNAME) if mask.is_none() => {
                check_same_shape(&cards, path, MASK_EXTNAME, (ny_full, nx))?;
                let hdu = f.hdu(i).map_err(|e| fits_err(path, &format!("HDU {i} (MASK)"), e))?;
                let v: Vec<u8> = match rows {
                    None => hdu.read_image(&mut f),
                    Some((r0, _)) => hdu.read_rows(&mut f, r0, ny),
                }
                .map_err(|e| fits_err(path, "reading the MASK extension", e))?;
                mask = Some(to_array(v, ny, nx, path)?);
            }
            _ => {}
        }
        i += 1;
    }

    let frame = Frame {
        mask: mask.unwrap_or_else(|| Array2::zeros((ny, nx))),
        data,
        variance,
        header,
        history,
    };
    Ok((with_crop_record(frame, rows), summary))
}

/// The frame with the record [`Frame::crop_rows`] writes when only `rows` were read.
fn with_crop_record(frame: Frame, rows: Option<(usize, usize)>) -> Frame {
    match rows {
        None => frame,
        Some((r0, r1)) => frame.with_history(
            "crop",
            format!("rows [{r0}, {r1}) of the detector; row {r0} is row 0 here"),
        ),
    }
}

/// Opens `path` for reading; a file the OS cannot open, or whose primary header is
/// malformed, is reported in those words rather than in cfitsio's.
fn open(path: &Path) -> Result<FitsFile> {
    let meta = std::fs::metadata(path).map_err(|e| Error::Io {
        path: path.to_path_buf(),
        source: e,
    })?;
    if !meta.is_file() {
        return Err(Error::Io {
            path: path.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a regular file"),
        });
    }
    let name = cfitsio_name(path)?;
    // Opened by the OS first: a file that cannot be opened (permission denied, too many
    // open files) is reported with the OS's reason, not cfitsio's "could not open".
    super::gzip::check_compressed(path)?;
    FitsFile::open(&name).map_err(|e| match super::diagnose::primary_keyword_problem(path) {
        Some(problem) => Error::BadImage {
            path: path.to_path_buf(),
            reason: format!("not a valid FITS header: {problem}"),
        },
        None => fits_err(path, "opening as FITS", e),
    })
}

/// Header cards of HDU `index` (0-based), or `None` past the last HDU.
pub(super) fn hdu_cards(f: &mut FitsFile, path: &Path, index: usize) -> Result<Option<Vec<String>>> {
    match cfitsio_raw(f, RawOp::ReadCards(index)) {
        Ok(c) => Ok(Some(c)),
        // END_OF_FILE: no such HDU. (A file truncated inside a later HDU's header ends the
        // scan here too; the image HDU itself was read in full before.)
        Err(fitsio::errors::Error::Fits(fe)) if index > 0 && fe.status == END_OF_FILE => Ok(None),
        Err(fitsio::errors::Error::Fits(fe)) if index > 0 && matches!(fe.status, NOT_AN_EXTENSION | READ_ERROR) => {
            match super::diagnose::trailing_junk(f, path, index) {
                Some(reason) => Err(Error::BadImage {
                    path: path.to_path_buf(),
                    reason,
                }),
                None => Err(fits_err(
                    path,
                    &format!("reading the header of HDU {index}"),
                    fitsio::errors::Error::Fits(fe),
                )),
            }
        }
        Err(e) => Err(fits_err(path, &format!("reading the header of HDU {index}"), e)),
    }
}

pub(super) const END_OF_FILE: i32 = 107;
/// cfitsio's "1st key not SIMPLE or XTENSION" (UNKNOWN_REC) where an extension should start.
const NOT_AN_EXTENSION: i32 = 252;
/// cfitsio's READ_ERROR: also what less than a block of bytes after the last HDU gives.
const READ_ERROR: i32 = 108;

/// Find the image HDU: the primary if it has NAXIS > 0, else the first image extension
/// (plain or tile-compressed) with NAXIS > 0. The image must be 2-D and non-empty.
pub(super) fn find_image_hdu(f: &mut FitsFile, path: &Path) -> Result<(usize, Vec<String>)> {
    let primary = hdu_cards(f, path, 0)?.unwrap_or_default();
    if naxis_values(&primary).0 > 0 {
        image_dims(&primary, path)?;
        return Ok((0, primary));
    }
    let mut i = 1;
    while let Some(cards) = hdu_cards(f, path, i)? {
        if is_image_hdu(&cards) && naxis_values(&cards).0 > 0 {
            image_dims(&cards, path)?;
            return Ok((i, cards));
        }
        i += 1;
    }
    Err(Error::BadImage {
        path: path.to_path_buf(),
        reason: "no image: the primary HDU has NAXIS = 0 and there is no image extension".into(),
    })
}

pub(super) fn is_image_hdu(cards: &[String]) -> bool {
    is_compressed(cards)
        || matches!(raw_value(cards, "XTENSION"), Some(HeaderValue::Str(s)) if s.trim() == "IMAGE")
        || raw_value(cards, "SIMPLE").is_some()
}

/// (NAXIS, [NAXIS1, NAXIS2, ...]) of an image or tile-compressed image HDU, and the
/// keyword prefix used ("NAXIS" or "ZNAXIS").
pub(super) fn naxis_values(cards: &[String]) -> (i64, Vec<i64>, &'static str) {
    let prefix = if is_compressed(cards) { "ZNAXIS" } else { "NAXIS" };
    let n = raw_int(cards, prefix).unwrap_or(0);
    let axes = (1..=n.clamp(0, 999))
        .map(|i| raw_int(cards, &format!("{prefix}{i}")).unwrap_or(-1))
        .collect();
    (n, axes, prefix)
}

/// (ny, nx) of a 2-D non-empty image, else [`Error::BadImage`] naming the NAXIS values.
pub(super) fn image_dims(cards: &[String], path: &Path) -> Result<(usize, usize)> {
    let (n, axes, prefix) = naxis_values(cards);
    let listing = axes
        .iter()
        .enumerate()
        .map(|(i, a)| format!("{prefix}{} = {a}", i + 1))
        .collect::<Vec<_>>()
        .join(", ");
    let describe = if listing.is_empty() {
        format!("{prefix} = {n}")
    } else {
        format!("{prefix} = {n} ({listing})")
    };
    if n != 2 {
        return Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!("not a 2-D image: {describe}"),
        });
    }
    if axes.iter().any(|&a| a <= 0) {
        return Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!("empty image: {describe}"),
        });
    }
    // fitsio panics on the one pixel type it does not know (unsigned 64-bit): refuse it.
    let bitpix_key = if prefix == "ZNAXIS" { "ZBITPIX" } else { "BITPIX" };
    if raw_int(cards, bitpix_key) == Some(64) {
        if let Some(z) = raw_value(cards, "BZERO") {
            if !matches!(z, HeaderValue::Int(0)) && z != HeaderValue::Float(0.0) {
                return Err(Error::BadImage {
                    path: path.to_path_buf(),
                    reason: format!("unsupported pixel type: {bitpix_key} = 64 with BZERO = {z}"),
                });
            }
        }
    }
    Ok((axes[1] as usize, axes[0] as usize))
}

/// Most output bytes (f32 pixels) allowed per byte of a compressed file (tile-compressed or
/// gzip): far above what real frames reach (noise does not compress 1000 times).
pub const MAX_COMPRESSION_RATIO: u64 = 1000;

/// Refuse, before allocating, an image whose header promises more data than the file can
/// hold: a corrupt NAXIS1 = NAXIS2 = 100000 in a 4 MB file asked for a 40 GB allocation
/// and aborted the process. An uncompressed image needs NAXIS1 x NAXIS2 x |BITPIX|/8
/// bytes of file; a compressed one (tile compression, gzip) at most
/// [`MAX_COMPRESSION_RATIO`] output bytes per file byte.
pub(super) fn check_size_against_file(cards: &[String], path: &Path, ny: usize, nx: usize) -> Result<()> {
    let file_len = std::fs::metadata(path)
        .map_err(|e| Error::Io {
            path: path.to_path_buf(),
            source: e,
        })?
        .len();
    let gz = std::fs::File::open(path)
        .and_then(|mut f| {
            let mut m = [0u8; 2];
            std::io::Read::read_exact(&mut f, &mut m).map(|_| m == [0x1f, 0x8b])
        })
        .unwrap_or(false);
    let pixels = (nx as u64).checked_mul(ny as u64);
    let (need, limit, what) = if is_compressed(cards) || gz {
        (
            pixels.and_then(|p| p.checked_mul(4)),
            file_len.saturating_mul(MAX_COMPRESSION_RATIO),
            format!("{MAX_COMPRESSION_RATIO} x the compressed file"),
        )
    } else {
        let bytes = raw_int(cards, "BITPIX")
            .map(|b| b.unsigned_abs() / 8)
            .unwrap_or(4)
            .max(1);
        (
            pixels.and_then(|p| p.checked_mul(bytes)),
            file_len,
            "the file".to_string(),
        )
    };
    let too_many = pixels.is_some_and(|p| p > super::MAX_IMAGE_PIXELS);
    match need {
        Some(n) if n <= limit && !too_many => Ok(()),
        Some(n) if n <= limit => Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!(
                "image is NAXIS1 x NAXIS2 = {nx} x {ny} px, more than the {side} x {side} px sofipol reads: refused before reading",
                side = crate::profile::MAX_DETECTOR_SIDE_PX
            ),
        }),
        _ => Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!(
                "corrupt header: NAXIS1 x NAXIS2 = {nx} x {ny} needs {} bytes of data, more than {what} holds ({file_len} bytes)",
                need.map(|n| n.to_string()).unwrap_or_else(|| "over 2^64".into())
            ),
        }),
    }
}

pub(super) fn check_same_shape(cards: &[String], path: &Path, name: &str, want: (usize, usize)) -> Result<()> {
    let got = image_dims(cards, path).map_err(|e| match e {
        Error::BadImage { path, reason } => Error::BadImage {
            path,
            reason: format!("{name} extension: {reason}"),
        },
        e => e,
    })?;
    check_extension_shape(path, name, got, want)
}

pub(super) fn check_extension_shape(path: &Path, name: &str, got: (usize, usize), want: (usize, usize)) -> Result<()> {
    if got != want {
        return Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!(
                "{name} extension is {} x {} pixels (nx x ny) but the image is {} x {}",
                got.1, got.0, want.1, want.0
            ),
        });
    }
    Ok(())
}

/// What an uncertainty extension holds, as astropy's `UTYPE` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum UncertaintyKind {
    /// `VarianceUncertainty` (sofipol's, and `VARIANCE` extensions).
    Variance,
    /// `StdDevUncertainty` (astropy's default for an `UNCERT` without `UTYPE`).
    StdDev,
    /// `InverseVariance`.
    InverseVariance,
}

impl UncertaintyKind {
    /// The extension's values as variances.
    pub(super) fn to_variance(self, mut v: Array2<f32>) -> Array2<f32> {
        match self {
            UncertaintyKind::Variance => {}
            UncertaintyKind::StdDev => v.mapv_inplace(|s| s * s),
            UncertaintyKind::InverseVariance => v.mapv_inplace(|w| 1.0 / w),
        }
        v
    }
}

/// The kind of the uncertainty extension `name` from its `UTYPE` card: `VARIANCE` holds
/// variances; `UNCERT` what its `UTYPE` says, a standard deviation without one (as astropy
/// reads it). Another `UTYPE` is refused, naming the file and the value.
pub(super) fn uncertainty_kind(cards: &[String], name: &str, path: &Path) -> Result<UncertaintyKind> {
    let utype = match raw_value(cards, "UTYPE") {
        Some(HeaderValue::Str(s)) => Some(s.trim().to_string()),
        _ => None,
    };
    match (name, utype.as_deref()) {
        (_, Some(VARIANCE_UTYPE)) => Ok(UncertaintyKind::Variance),
        (LEGACY_VARIANCE_EXTNAME, None) => Ok(UncertaintyKind::Variance),
        (_, Some("StdDevUncertainty")) | (_, None) => Ok(UncertaintyKind::StdDev),
        (_, Some("InverseVariance")) => Ok(UncertaintyKind::InverseVariance),
        (_, Some(other)) => Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!(
                "{name} extension: UTYPE = '{other}' is not an uncertainty sofipol reads \
                 (VarianceUncertainty, StdDevUncertainty or InverseVariance)"
            ),
        }),
    }
}

pub(super) fn extname(cards: &[String]) -> Option<String> {
    match raw_value(cards, "EXTNAME")? {
        HeaderValue::Str(s) => Some(s.trim().to_ascii_uppercase()),
        _ => None,
    }
}

pub(super) fn read_f32(f: &mut FitsFile, path: &Path, index: usize, ny: usize, nx: usize) -> Result<Array2<f32>> {
    let hdu = f
        .hdu(index)
        .map_err(|e| fits_err(path, &format!("moving to HDU {index}"), e))?;
    match &hdu.info {
        HduInfo::ImageInfo { shape, .. } if shape.as_slice() == [ny, nx] => {}
        other => {
            return Err(Error::BadImage {
                path: path.to_path_buf(),
                reason: format!("HDU {index}: cfitsio reports {other:?}, expected a {nx} x {ny} image"),
            })
        }
    }
    // One allocation, filled by cfitsio (scaled by BZERO/BSCALE), moved into the array.
    let v: Vec<f32> = hdu
        .read_image(f)
        .map_err(|e| fits_err(path, &format!("reading image data of HDU {index}"), e))?;
    to_array(v, ny, nx, path)
}

/// Rows `[r0, r0 + n)` of the image HDU `index` of shape `full` (ny, nx), as `f32`.
fn read_f32_rows(
    f: &mut FitsFile,
    path: &Path,
    index: usize,
    full: (usize, usize),
    r0: usize,
    n: usize,
) -> Result<Array2<f32>> {
    let hdu = f
        .hdu(index)
        .map_err(|e| fits_err(path, &format!("moving to HDU {index}"), e))?;
    match &hdu.info {
        HduInfo::ImageInfo { shape, .. } if shape.as_slice() == [full.0, full.1] => {}
        other => {
            return Err(Error::BadImage {
                path: path.to_path_buf(),
                reason: format!(
                    "HDU {index}: cfitsio reports {other:?}, expected a {} x {} image",
                    full.1, full.0
                ),
            })
        }
    }
    let v: Vec<f32> = hdu
        .read_rows(f, r0, n)
        .map_err(|e| fits_err(path, &format!("reading rows [{r0}, {}) of HDU {index}", r0 + n), e))?;
    to_array(v, n, full.1, path)
}
