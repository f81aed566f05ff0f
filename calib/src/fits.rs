//! FITS I/O through the `fitsio` crate (bundled, reentrant cfitsio).
//!
//! * [`read_header`] / [`read_frame`] find the image HDU (the primary when it holds an
//!   image, else the first image extension: tile-compressed `.fz` files keep the image in
//!   HDU 1), read every header card and the pixels as `f32` (cfitsio applies BZERO/BSCALE;
//!   `.fz` and `.fits.gz` are read transparently).
//! * [`write_frame`] writes float32 or raw-like int16 images, optionally tile compressed,
//!   with HIERARCH keywords and one HISTORY entry per provenance record, atomically
//!   (temporary file in the same directory, then rename).
//!
//! Header cards are read and written as raw 80-character records, parsed and formatted
//! here, because the safe `fitsio` API can neither enumerate keywords nor write HISTORY
//! cards, logical values or full-precision doubles. All direct cfitsio calls sit in the
//! single function `cfitsio_raw` at the end of this file.
//!
//! Pixel layout: arrays are indexed `[y, x]`; row 0 is FITS row 1 (the bottom of the
//! image), column 0 is FITS column 1.
//!
//! `FitsFile` is neither `Send` nor `Sync`: every function opens and closes its own
//! handle, so different files may be read or written from different threads.
use std::ffi::{c_char, c_int, CString};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use fitsio::hdu::HduInfo;
use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;
use ndarray::Array2;

use crate::error::{Error, Result};
use crate::frame::{Frame, HistoryRecord};
use crate::header::{normalize_key, Card, Header, HeaderValue};

/// On-disk pixel type of a written image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Bitpix {
    /// BITPIX = -32: exact for every `f32` value (NaN included).
    #[default]
    F32,
    /// BITPIX = 16 with BZERO = 32768, BSCALE = 1, i.e. unsigned 16-bit integers, like raw
    /// detector data. Values are rounded to the nearest integer (halves away from zero)
    /// and clipped to `0..=65535`; NaN is written as 0.
    I16,
}

/// How to write a frame.
#[derive(Debug, Clone, Default)]
pub struct WriteOptions {
    /// Pixel type.
    pub bitpix: Bitpix,
    /// Tile compression (`.fz` layout: empty primary HDU, image in HDU 1, one tile per
    /// row). Rice when every image of the file is integer (lossless); GZIP without
    /// quantization when the file holds float images (data in `F32`, or the VARIANCE
    /// extension): also lossless, because Rice on floats needs cfitsio's lossy
    /// quantization. The file name is not changed: call it `*.fz` yourself.
    pub compress: bool,
    /// Also write VARIANCE (float32) and MASK (uint8) image extensions. VARIANCE is
    /// written only when the frame has one; MASK always.
    pub with_variance_and_mask: bool,
}

/// EXTNAME of the variance extension written by [`write_frame`].
pub const VARIANCE_EXTNAME: &str = "VARIANCE";
/// EXTNAME of the mask extension written by [`write_frame`].
pub const MASK_EXTNAME: &str = "MASK";
/// Maximum number of characters of text written on one HISTORY card.
pub const HISTORY_CHUNK: usize = 70;
/// Prefix of a HISTORY card that continues the previous sofipol record (long lines are
/// split over several cards).
pub const HISTORY_CONTINUATION: &str = "sofipol& ";

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
    let mut f = open(path)?;
    let (_, cards) = find_image_hdu(&mut f, path)?;
    Ok(parse_cards(&cards, path).0)
}

/// Read a frame: the image as `f32` (`[y, x]`, row 0 = FITS row 1), its header, HISTORY
/// cards as provenance records, and VARIANCE / MASK extensions when present.
///
/// HISTORY cards of the form `sofipol <stage>: <detail>` (as written by [`write_frame`],
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
    let mut f = open(path)?;
    let (hdu_index, cards) = find_image_hdu(&mut f, path)?;
    let (header, history) = parse_cards(&cards, path);
    let (ny, nx) = image_dims(&cards, path)?;

    let data = read_f32(&mut f, path, hdu_index, ny, nx)?;

    // Look for VARIANCE / MASK extensions after the image HDU.
    let mut variance = None;
    let mut mask = None;
    let mut i = hdu_index + 1;
    while let Some(cards) = hdu_cards(&mut f, path, i)? {
        match extname(&cards).as_deref() {
            Some(VARIANCE_EXTNAME) if variance.is_none() => {
                check_same_shape(&cards, path, VARIANCE_EXTNAME, (ny, nx))?;
                variance = Some(read_f32(&mut f, path, i, ny, nx)?);
            }
            Some(MASK_EXTNAME) if mask.is_none() => {
                check_same_shape(&cards, path, MASK_EXTNAME, (ny, nx))?;
                let hdu = f.hdu(i).map_err(|e| fits_err(path, &format!("HDU {i} (MASK)"), e))?;
                let v: Vec<u8> = hdu
                    .read_image(&mut f)
                    .map_err(|e| fits_err(path, "reading the MASK extension", e))?;
                mask = Some(to_array(v, ny, nx, path)?);
            }
            _ => {}
        }
        i += 1;
    }

    Ok(Frame {
        mask: mask.unwrap_or_else(|| Array2::zeros((ny, nx))),
        data,
        variance,
        header,
        history,
    })
}

/// Write a frame atomically: the file is written to a temporary file in the same
/// directory (`.<name>.tmp-<pid>-<n>`), flushed, synced and renamed over `path`, so a
/// crash never leaves a half-written file and an existing file is replaced only by a
/// complete one.
///
/// Header: every card of `frame.header` (keys longer than 8 characters or with spaces
/// as `HIERARCH` cards; strings longer than a card with the CONTINUE convention; floats
/// with the shortest representation that reads back bit-exactly; comments when they
/// fit), then one HISTORY entry per `frame.history` record (`record.line()`, split into
/// cards of at most [`HISTORY_CHUNK`] characters; continuation cards start with
/// [`HISTORY_CONTINUATION`]). Structural keywords in `frame.header` are ignored (the
/// file layout decides them). Non-ASCII characters in comments and HISTORY become `?`;
/// in keyword names or string values they are an error, as are non-finite floats.
///
/// ```
/// use sofipol_calib::fits::{read_frame, write_frame, Bitpix, WriteOptions};
/// use sofipol_calib::{Frame, Header};
/// let dir = tempfile::tempdir().unwrap();
/// let path = dir.path().join("raw.fits.fz");
/// let mut header = Header::new("");
/// header.set("ESO ADA POSANG", 45.0);
/// let frame = Frame::new(ndarray::Array2::from_elem((8, 16), 1234.0), header)
///     .with_history("sim", "seed=1");
/// let opts = WriteOptions { bitpix: Bitpix::I16, compress: true, ..Default::default() };
/// write_frame(&path, &frame, &opts)?;
/// let back = read_frame(&path)?;
/// assert_eq!(back.data, frame.data);
/// assert_eq!(back.history, frame.history);
/// # Ok::<(), sofipol_calib::Error>(())
/// ```
pub fn write_frame(path: &Path, frame: &Frame, opts: &WriteOptions) -> Result<()> {
    let (ny, nx) = frame.shape();
    if ny == 0 || nx == 0 {
        return Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!("cannot write an empty image ({ny} x {nx} pixels)"),
        });
    }
    let variance = if opts.with_variance_and_mask {
        frame.variance.as_ref()
    } else {
        None
    };
    if let Some(v) = variance {
        check_extension_shape(path, VARIANCE_EXTNAME, v.dim(), (ny, nx))?;
    }
    if opts.with_variance_and_mask {
        check_extension_shape(path, MASK_EXTNAME, frame.mask.dim(), (ny, nx))?;
    }
    if path.to_string_lossy().ends_with(".gz") {
        return Err(Error::Fits {
            path: path.to_path_buf(),
            message: "writing gzip-compressed files is not supported; use tile compression \
                      (WriteOptions::compress, a .fz file)"
                .into(),
        });
    }
    // Format every card before touching the disk: a bad keyword leaves no trace.
    let mut cards = format_header(&frame.header, path)?;
    cards.extend(format_history(&frame.history));

    let tmp = TempFile::new(path)?;
    let tmp_name = cfitsio_name(&tmp.path)?;
    let float_inside = opts.bitpix == Bitpix::F32 || variance.is_some();
    let create_name = match (opts.compress, float_inside) {
        (false, _) => tmp_name,
        (true, false) => format!("{tmp_name}[compress R]"),
        // "q 0": no quantization, i.e. lossless GZIP for float tiles.
        (true, true) => format!("{tmp_name}[compress G; q 0]"),
    };
    let image_type = match opts.bitpix {
        Bitpix::F32 => ImageType::Float,
        Bitpix::I16 => ImageType::UnsignedShort,
    };
    let shape = [ny, nx];
    let desc = ImageDescription {
        data_type: image_type,
        dimensions: &shape,
    };
    let tpath = tmp.path.clone();
    let ferr = |what: &str, e: fitsio::errors::Error| fits_err(&tpath, what, e);
    {
        let mut f;
        let hdu;
        if opts.compress {
            // Empty primary (written directly, never compressed), image in HDU 1.
            f = FitsFile::create(&create_name).open().map_err(|e| ferr("creating", e))?;
            hdu = f
                .create_image("COMPRESSED_IMAGE", &desc)
                .map_err(|e| ferr("creating the compressed image HDU", e))?;
        } else {
            f = FitsFile::create(&create_name)
                .with_custom_primary(&desc)
                .open()
                .map_err(|e| ferr("creating", e))?;
            hdu = f.primary_hdu().map_err(|e| ferr("primary HDU", e))?;
            // fitsio names the primary '_PRIMARY': drop it, a primary needs no name.
            cfitsio_raw(&mut f, RawOp::Delete("EXTNAME")).map_err(|e| ferr("deleting EXTNAME", e))?;
        }
        // Header before data: appending cards later would make cfitsio shift the data.
        cfitsio_raw(&mut f, RawOp::Append(&cards)).map_err(|e| ferr("writing header cards", e))?;
        match opts.bitpix {
            Bitpix::F32 => {
                let data = contiguous(&frame.data);
                hdu.write_image(&mut f, &data)
                    .map_err(|e| ferr("writing image data", e))?;
            }
            Bitpix::I16 => {
                let data: Vec<u16> = frame.data.iter().map(|&v| to_u16(v)).collect();
                hdu.write_image(&mut f, &data)
                    .map_err(|e| ferr("writing image data", e))?;
            }
        }
        if opts.with_variance_and_mask {
            if let Some(v) = variance {
                let d = ImageDescription {
                    data_type: ImageType::Float,
                    dimensions: &shape,
                };
                let h = f
                    .create_image(VARIANCE_EXTNAME, &d)
                    .map_err(|e| ferr("creating VARIANCE", e))?;
                h.write_image(&mut f, &contiguous(v))
                    .map_err(|e| ferr("writing VARIANCE", e))?;
            }
            let d = ImageDescription {
                data_type: ImageType::UnsignedByte,
                dimensions: &shape,
            };
            let h = f.create_image(MASK_EXTNAME, &d).map_err(|e| ferr("creating MASK", e))?;
            h.write_image(&mut f, &contiguous(&frame.mask))
                .map_err(|e| ferr("writing MASK", e))?;
        }
        // Drop (fits_close_file) cannot report errors: flush explicitly first.
        cfitsio_raw(&mut f, RawOp::Flush).map_err(|e| ferr("flushing", e))?;
    }
    tmp.commit(path)
}

// ---------------------------------------------------------------------------------------
// Reading helpers

fn fits_err(path: &Path, what: &str, e: fitsio::errors::Error) -> Error {
    let message = match e {
        fitsio::errors::Error::Fits(fe) => {
            let hint = match fe.status {
                107 | 108 => " (is the file truncated?)",
                221 | 225 | 251 | 252 => " (not a FITS file?)",
                _ => "",
            };
            format!("{what}: cfitsio status {}: {}{hint}", fe.status, fe.message)
        }
        other => format!("{what}: {other}"),
    };
    Error::Fits {
        path: path.to_path_buf(),
        message,
    }
}

/// The file name as cfitsio must see it. cfitsio parses an "extended file name syntax"
/// (`file.fits[1]`, `file(template)`, `!file`, `-` for stdin, `file+1`...): names it
/// would misread are refused instead of silently opening something else.
fn cfitsio_name(path: &Path) -> Result<String> {
    let bad = |why: &str| Error::Fits {
        path: path.to_path_buf(),
        message: format!("unsupported file name: {why}"),
    };
    let s = path.to_str().ok_or_else(|| bad("not valid UTF-8"))?;
    if s.contains(['[', ']', '(', ')']) {
        return Err(bad(
            "contains brackets or parentheses, which cfitsio reads as its extended file-name syntax",
        ));
    }
    if s.contains("://") {
        return Err(bad("looks like a URL"));
    }
    if let Some((_, tail)) = s.rsplit_once('+') {
        if !tail.is_empty() && tail.bytes().all(|b| b.is_ascii_digit()) {
            return Err(bad("ends in '+<digits>', which cfitsio reads as an HDU number"));
        }
    }
    if s.starts_with(['-', '!']) || s.starts_with(' ') {
        return Ok(format!("./{s}"));
    }
    Ok(s.to_string())
}

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
    FitsFile::open(&name).map_err(|e| fits_err(path, "opening as FITS", e))
}

/// Header cards of HDU `index` (0-based), or `None` past the last HDU.
fn hdu_cards(f: &mut FitsFile, path: &Path, index: usize) -> Result<Option<Vec<String>>> {
    match cfitsio_raw(f, RawOp::ReadCards(index)) {
        Ok(c) => Ok(Some(c)),
        // END_OF_FILE: no such HDU. (A file truncated inside a later HDU's header ends the
        // scan here too; the image HDU itself was read in full before.)
        Err(fitsio::errors::Error::Fits(fe)) if index > 0 && fe.status == END_OF_FILE => Ok(None),
        Err(e) => Err(fits_err(path, &format!("reading the header of HDU {index}"), e)),
    }
}

const END_OF_FILE: i32 = 107;

/// Find the image HDU: the primary if it has NAXIS > 0, else the first image extension
/// (plain or tile-compressed) with NAXIS > 0. The image must be 2-D and non-empty.
fn find_image_hdu(f: &mut FitsFile, path: &Path) -> Result<(usize, Vec<String>)> {
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

/// The value of a structural keyword straight from the raw cards.
fn raw_value(cards: &[String], key: &str) -> Option<HeaderValue> {
    cards.iter().find_map(|c| match parse_card(c) {
        Parsed::Key { key: k, value, .. } if k == key => Some(value),
        _ => None,
    })
}

fn raw_int(cards: &[String], key: &str) -> Option<i64> {
    match raw_value(cards, key)? {
        HeaderValue::Int(i) => Some(i),
        _ => None,
    }
}

fn is_compressed(cards: &[String]) -> bool {
    matches!(raw_value(cards, "ZIMAGE"), Some(HeaderValue::Bool(true)))
}

fn is_image_hdu(cards: &[String]) -> bool {
    is_compressed(cards)
        || matches!(raw_value(cards, "XTENSION"), Some(HeaderValue::Str(s)) if s.trim() == "IMAGE")
        || raw_value(cards, "SIMPLE").is_some()
}

/// (NAXIS, [NAXIS1, NAXIS2, ...]) of an image or tile-compressed image HDU, and the
/// keyword prefix used ("NAXIS" or "ZNAXIS").
fn naxis_values(cards: &[String]) -> (i64, Vec<i64>, &'static str) {
    let prefix = if is_compressed(cards) { "ZNAXIS" } else { "NAXIS" };
    let n = raw_int(cards, prefix).unwrap_or(0);
    let axes = (1..=n.clamp(0, 999))
        .map(|i| raw_int(cards, &format!("{prefix}{i}")).unwrap_or(-1))
        .collect();
    (n, axes, prefix)
}

/// (ny, nx) of a 2-D non-empty image, else [`Error::BadImage`] naming the NAXIS values.
fn image_dims(cards: &[String], path: &Path) -> Result<(usize, usize)> {
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

fn check_same_shape(cards: &[String], path: &Path, name: &str, want: (usize, usize)) -> Result<()> {
    let got = image_dims(cards, path).map_err(|e| match e {
        Error::BadImage { path, reason } => Error::BadImage {
            path,
            reason: format!("{name} extension: {reason}"),
        },
        e => e,
    })?;
    check_extension_shape(path, name, got, want)
}

fn check_extension_shape(path: &Path, name: &str, got: (usize, usize), want: (usize, usize)) -> Result<()> {
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

fn extname(cards: &[String]) -> Option<String> {
    match raw_value(cards, "EXTNAME")? {
        HeaderValue::Str(s) => Some(s.trim().to_ascii_uppercase()),
        _ => None,
    }
}

fn read_f32(f: &mut FitsFile, path: &Path, index: usize, ny: usize, nx: usize) -> Result<Array2<f32>> {
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

fn to_array<T>(v: Vec<T>, ny: usize, nx: usize, path: &Path) -> Result<Array2<T>> {
    let n = v.len();
    Array2::from_shape_vec((ny, nx), v).map_err(|_| Error::BadImage {
        path: path.to_path_buf(),
        reason: format!("read {n} pixels, expected {nx} x {ny}"),
    })
}

// ---------------------------------------------------------------------------------------
// Header cards: parsing

/// One parsed 80-character card.
#[derive(Debug, Clone, PartialEq)]
enum Parsed {
    /// `KEY = value / comment` (HIERARCH prefix removed from the key).
    Key {
        key: String,
        value: HeaderValue,
        comment: Option<String>,
    },
    /// A keyword with an empty (undefined) value.
    Undefined,
    /// `HISTORY text`.
    History(String),
    /// `CONTINUE  'text'` of a long string.
    Continue { text: String, comment: Option<String> },
    /// COMMENT, blank and anything else without a value.
    Commentary,
}

/// Keywords that describe the file layout rather than the data.
fn is_structural(key: &str) -> bool {
    const EXACT: &[&str] = &[
        "SIMPLE", "BITPIX", "NAXIS", "EXTEND", "BZERO", "BSCALE", "BLANK", "PCOUNT", "GCOUNT", "XTENSION", "EXTNAME",
        "EXTVER", "EXTLEVEL", "INHERIT", "TFIELDS", "THEAP", "CHECKSUM", "DATASUM", "BLOCKED", "END", "LONGSTRN",
        "ZIMAGE", "ZBITPIX", "ZNAXIS", "ZCMPTYPE", "ZQUANTIZ", "ZDITHER0", "ZSIMPLE", "ZEXTEND", "ZBLOCKED",
        "ZTENSION", "ZPCOUNT", "ZGCOUNT", "ZHECKSUM", "ZDATASUM", "ZMASKCMP", "ZSCALE", "ZZERO", "ZBLANK", "ZTHEAP",
    ];
    const NUMBERED: &[&str] = &[
        "NAXIS", "ZNAXIS", "ZTILE", "ZNAME", "ZVAL", "TTYPE", "TFORM", "TUNIT", "TDIM", "TSCAL", "TZERO", "TNULL",
        "TDISP",
    ];
    EXACT.contains(&key)
        || NUMBERED.iter().any(|p| {
            key.strip_prefix(p)
                .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
        })
}

/// Parse a quoted FITS string starting at `s[0] == '\''`: (value, rest after the quote).
/// `''` is an escaped quote; trailing blanks of the value are not significant.
fn parse_quoted(s: &str) -> (String, &str) {
    let b = s.as_bytes();
    let mut out = String::new();
    let mut i = 1;
    while i < b.len() {
        if b[i] == b'\'' {
            if b.get(i + 1) == Some(&b'\'') {
                out.push('\'');
                i += 2;
                continue;
            }
            return (out.trim_end().to_string(), &s[i + 1..]);
        }
        out.push(b[i] as char);
        i += 1;
    }
    // Unterminated string: take what there is.
    (out.trim_end().to_string(), "")
}

fn parse_comment(rest: &str) -> Option<String> {
    let c = rest.trim_start().strip_prefix('/')?.trim();
    (!c.is_empty()).then(|| c.to_string())
}

/// Parse the value field (everything after `=`).
fn parse_value(field: &str) -> (Option<HeaderValue>, Option<String>) {
    let t = field.trim_start();
    if t.starts_with('\'') {
        let (s, rest) = parse_quoted(t);
        return (Some(HeaderValue::Str(s)), parse_comment(rest));
    }
    let (v, comment) = match t.find('/') {
        Some(i) => (t[..i].trim(), parse_comment(&t[i..])),
        None => (t.trim(), None),
    };
    if v.is_empty() {
        return (None, comment);
    }
    let value = match v {
        "T" => HeaderValue::Bool(true),
        "F" => HeaderValue::Bool(false),
        _ => {
            let digits = v.strip_prefix(['+', '-']).unwrap_or(v);
            let numeric = !digits.is_empty() && v.bytes().all(|b| b"0123456789+-.EeDd".contains(&b));
            if numeric && digits.bytes().all(|b| b.is_ascii_digit()) {
                match v.parse::<i64>() {
                    Ok(i) => HeaderValue::Int(i),
                    Err(_) => v
                        .parse::<f64>()
                        .map(HeaderValue::Float)
                        .unwrap_or_else(|_| HeaderValue::Str(v.into())),
                }
            } else if numeric {
                match v.replace(['D', 'd'], "E").parse::<f64>() {
                    Ok(x) => HeaderValue::Float(x),
                    Err(_) => HeaderValue::Str(v.to_string()),
                }
            } else {
                // Complex numbers and other oddities: keep the text.
                HeaderValue::Str(v.to_string())
            }
        }
    };
    (Some(value), comment)
}

fn parse_card(raw: &str) -> Parsed {
    // Cards are ASCII by the standard; make any stray byte harmless for slicing.
    let card: String = raw.chars().map(|c| if c.is_ascii() { c } else { '?' }).collect();
    let name8 = card.get(..8).unwrap_or(&card).trim_end().to_ascii_uppercase();
    if name8 == "HISTORY" {
        return Parsed::History(card.get(8..).unwrap_or("").trim_end().to_string());
    }
    if name8 == "CONTINUE" {
        let t = card.get(8..).unwrap_or("").trim_start();
        if t.starts_with('\'') {
            let (text, rest) = parse_quoted(t);
            return Parsed::Continue {
                text,
                comment: parse_comment(rest),
            };
        }
        return Parsed::Commentary;
    }
    if name8 == "HIERARCH" && card.as_bytes().get(8) == Some(&b' ') {
        return match card.find('=') {
            Some(eq) => {
                let key = normalize_key(&card[..eq]);
                match parse_value(&card[eq + 1..]) {
                    (Some(value), comment) if !key.is_empty() => Parsed::Key { key, value, comment },
                    _ => Parsed::Undefined,
                }
            }
            None => Parsed::Commentary,
        };
    }
    if name8.is_empty() || name8 == "COMMENT" || card.as_bytes().get(8) != Some(&b'=') {
        return Parsed::Commentary;
    }
    match parse_value(&card[9..]) {
        (Some(value), comment) => Parsed::Key {
            key: name8,
            value,
            comment,
        },
        _ => Parsed::Undefined,
    }
}

/// Turn HISTORY texts into provenance records (see [`read_frame`]).
fn history_record(text: &str, records: &mut Vec<HistoryRecord>, continuing: &mut bool) {
    if let Some(rest) = text.strip_prefix(HISTORY_CONTINUATION) {
        if *continuing {
            if let Some(last) = records.last_mut() {
                last.detail.push_str(rest);
                return;
            }
        }
    }
    *continuing = false;
    if let Some(rest) = text.strip_prefix("sofipol ") {
        if let Some((stage, detail)) = rest.split_once(':') {
            if !stage.is_empty() && !stage.contains(' ') {
                let detail = detail.strip_prefix(' ').unwrap_or(detail);
                records.push(HistoryRecord::new(stage, detail));
                *continuing = true;
                return;
            }
        }
    }
    records.push(HistoryRecord::new("file", text));
}

/// Header (structural keys, COMMENT and HISTORY removed) and history records.
fn parse_cards(cards: &[String], path: &Path) -> (Header, Vec<HistoryRecord>) {
    let mut header = Header::new(path);
    let mut history = Vec::new();
    let mut continuing = false;
    // Index of the card a CONTINUE card extends, when its string ended in '&'.
    let mut open_string: Option<usize> = None;
    for raw in cards {
        let parsed = parse_card(raw);
        if !matches!(parsed, Parsed::Continue { .. }) {
            open_string = None;
        }
        match parsed {
            Parsed::Key { key, value, comment } => {
                if is_structural(&key) || header.cards.iter().any(|c| c.key == key) {
                    continue;
                }
                if let HeaderValue::Str(s) = &value {
                    if s.ends_with('&') {
                        open_string = Some(header.cards.len());
                    }
                }
                header.cards.push(Card { key, value, comment });
            }
            Parsed::Continue { text, comment } => {
                if let Some(i) = open_string {
                    let card = &mut header.cards[i];
                    if let HeaderValue::Str(s) = &mut card.value {
                        s.pop(); // the '&'
                        s.push_str(&text);
                        if !text.ends_with('&') {
                            open_string = None;
                        }
                    }
                    if comment.is_some() {
                        card.comment = comment;
                    }
                }
            }
            Parsed::History(text) => history_record(&text, &mut history, &mut continuing),
            Parsed::Undefined | Parsed::Commentary => {}
        }
    }
    (header, history)
}

// ---------------------------------------------------------------------------------------
// Header cards: formatting

const CARD: usize = 80;

fn is_standard_key(key: &str) -> bool {
    !key.is_empty()
        && key.len() <= 8
        && key
            .bytes()
            .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'-' || b == b'_')
}

fn ascii_sanitize(s: &str) -> String {
    s.chars()
        .map(|c| if (' '..='~').contains(&c) { c } else { '?' })
        .collect()
}

/// A float in FITS syntax with the shortest digits that read back bit-exactly.
fn format_f64(x: f64) -> Option<String> {
    if !x.is_finite() {
        return None;
    }
    // Rust's Debug output is the shortest round-trip representation, with ".0" for
    // integral values and an exponent for very small or large magnitudes.
    let s = format!("{x:?}");
    Some(match s.split_once('e') {
        Some((m, e)) => {
            let m = if m.contains('.') {
                m.to_string()
            } else {
                format!("{m}.0")
            };
            format!("{m}E{e}")
        }
        None => s,
    })
}

fn bad_key(path: &Path, card: &Card, reason: &str) -> Error {
    Error::BadKeyword {
        path: path.to_path_buf(),
        keyword: card.key.clone(),
        value: card.value.to_string(),
        reason: reason.to_string(),
    }
}

/// Append ` / comment` when it fits (comments are informational: cut to fit).
fn with_comment(mut card: String, comment: Option<&str>) -> String {
    if let Some(c) = comment {
        let c = ascii_sanitize(c.trim());
        if !c.is_empty() && card.len() + 4 < CARD {
            card.push_str(" / ");
            let room = CARD - card.len();
            card.push_str(&c[..c.len().min(room)]);
        }
    }
    card
}

fn format_card(card: &Card, path: &Path) -> Result<Vec<String>> {
    let key = normalize_key(&card.key);
    if key.is_empty() || key.contains('=') || !key.chars().all(|c| (' '..='~').contains(&c)) {
        return Err(bad_key(path, card, "keyword names must be printable ASCII without '='"));
    }
    let prefix = if is_standard_key(&key) {
        format!("{key:<8}= ")
    } else {
        format!("HIERARCH {key} = ")
    };
    let comment = card.comment.as_deref();
    let too_long = || bad_key(path, card, "keyword name too long for an 80-character card");
    match &card.value {
        HeaderValue::Str(s) => {
            if !s.chars().all(|c| (' '..='~').contains(&c)) {
                return Err(bad_key(path, card, "FITS strings must be printable ASCII"));
            }
            // Escaped pieces, one per character, so that '' is never split.
            let pieces: Vec<String> = s
                .chars()
                .map(|c| if c == '\'' { "''".into() } else { c.to_string() })
                .collect();
            let escaped: String = pieces.concat();
            if prefix.len() + escaped.len().max(8) + 2 <= CARD {
                let padded = if escaped.len() < 8 {
                    format!("{escaped:<8}")
                } else {
                    escaped
                };
                return Ok(vec![with_comment(format!("{prefix}'{padded}'"), comment)]);
            }
            // Long string: CONTINUE convention; every card but the last ends in '&'.
            let mut out = Vec::new();
            let mut lead = prefix.clone();
            let mut it = pieces.iter().peekable();
            while it.peek().is_some() {
                let room = CARD
                    .checked_sub(lead.len() + 3)
                    .filter(|&r| r > 1)
                    .ok_or_else(too_long)?;
                let mut chunk = String::new();
                while let Some(p) = it.peek() {
                    if chunk.len() + p.len() > room {
                        break;
                    }
                    chunk.push_str(p);
                    it.next();
                }
                if it.peek().is_some() {
                    out.push(format!("{lead}'{chunk}&'"));
                } else {
                    let last = format!("{lead}'{chunk}'");
                    let comment_len = comment.map_or(0, |c| c.trim().len());
                    if comment_len > 0 && last.len() + 3 + comment_len > CARD {
                        // No room for the comment: give it a card of its own.
                        out.push(format!("{lead}'{chunk}&'"));
                        out.push(with_comment("CONTINUE  ''".to_string(), comment));
                    } else {
                        out.push(with_comment(last, comment));
                    }
                }
                lead = "CONTINUE  ".to_string();
            }
            Ok(out)
        }
        v => {
            let text = match v {
                HeaderValue::Bool(b) => (if *b { "T" } else { "F" }).to_string(),
                HeaderValue::Int(i) => i.to_string(),
                HeaderValue::Float(x) => {
                    format_f64(*x).ok_or_else(|| bad_key(path, card, "FITS cannot store a non-finite number"))?
                }
                HeaderValue::Str(_) => unreachable!(),
            };
            // Fixed format (value right-justified in column 30) for standard keys.
            let line = if prefix.len() == 10 && text.len() <= 20 {
                format!("{prefix}{text:>20}")
            } else {
                format!("{prefix}{text}")
            };
            if line.len() > CARD {
                return Err(too_long());
            }
            Ok(vec![with_comment(line, comment)])
        }
    }
}

/// Commentary card(s) for a COMMENT or HISTORY text, at most 72 characters each.
fn commentary(name: &str, text: &str) -> Vec<String> {
    let text = ascii_sanitize(text);
    if text.is_empty() {
        return vec![name.to_string()];
    }
    text.as_bytes()
        .chunks(72)
        .map(|c| format!("{name:<8}{}", String::from_utf8_lossy(c)))
        .collect()
}

/// All cards of a header, in order (structural keywords skipped).
fn format_header(header: &Header, path: &Path) -> Result<Vec<String>> {
    let mut out = Vec::with_capacity(header.cards.len() + 8);
    for card in &header.cards {
        let key = normalize_key(&card.key);
        if is_structural(&key) {
            continue;
        }
        if key == "COMMENT" || key == "HISTORY" {
            let text = match &card.value {
                HeaderValue::Str(s) => s.clone(),
                v => v.to_string(),
            };
            out.extend(commentary(&key, &text));
            continue;
        }
        out.extend(format_card(card, path)?);
    }
    Ok(out)
}

/// Split a history line into pieces of at most [`HISTORY_CHUNK`] characters. cfitsio
/// drops trailing blanks of a card, so a piece never ends in a blank when avoidable.
fn split_history(line: &str) -> Vec<String> {
    let line = ascii_sanitize(line);
    let mut out = Vec::new();
    let mut rest: &str = &line;
    let mut first = true;
    loop {
        let room = if first {
            HISTORY_CHUNK
        } else {
            HISTORY_CHUNK - HISTORY_CONTINUATION.len()
        };
        if rest.len() <= room {
            out.push(rest.to_string());
            break;
        }
        let mut cut = room;
        while cut > 0 && rest.as_bytes()[cut - 1] == b' ' {
            cut -= 1;
        }
        if cut == 0 {
            cut = room;
        }
        out.push(rest[..cut].to_string());
        rest = &rest[cut..];
        first = false;
    }
    out.into_iter()
        .enumerate()
        .map(|(i, piece)| {
            if i == 0 {
                piece
            } else {
                format!("{HISTORY_CONTINUATION}{piece}")
            }
        })
        .collect()
}

fn format_history(history: &[HistoryRecord]) -> Vec<String> {
    history
        .iter()
        .flat_map(|r| split_history(&r.line()))
        .map(|t| format!("HISTORY {t}"))
        .collect()
}

// ---------------------------------------------------------------------------------------
// Writing helpers

fn contiguous<T: Clone>(a: &Array2<T>) -> std::borrow::Cow<'_, [T]> {
    match a.as_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(a.iter().cloned().collect()),
    }
}

fn to_u16(v: f32) -> u16 {
    if v.is_nan() {
        0
    } else {
        v.round().clamp(0.0, 65535.0) as u16
    }
}

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A temporary file next to the destination, removed unless committed.
struct TempFile {
    path: PathBuf,
    committed: bool,
}

impl TempFile {
    fn new(dest: &Path) -> Result<TempFile> {
        let name = dest.file_name().ok_or_else(|| Error::Io {
            path: dest.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file name"),
        })?;
        // Only plain characters: the name goes through cfitsio's file-name parser.
        let safe: String = name
            .to_string_lossy()
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || "._-".contains(c) {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
        let tmp_name = format!(".{safe}.tmp-{}-{n}", std::process::id());
        let path = match dest.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.join(tmp_name),
            _ => PathBuf::from(tmp_name),
        };
        // A stale file of this name (from a crashed process with a recycled pid) would
        // make cfitsio refuse to create: it is ours to remove.
        let _ = std::fs::remove_file(&path);
        Ok(TempFile { path, committed: false })
    }

    fn commit(mut self, dest: &Path) -> Result<()> {
        let io = |p: &Path, e| Error::Io {
            path: p.to_path_buf(),
            source: e,
        };
        // Data on disk before the rename makes it visible.
        std::fs::File::open(&self.path)
            .and_then(|f| f.sync_all())
            .map_err(|e| io(&self.path, e))?;
        std::fs::rename(&self.path, dest).map_err(|e| io(dest, e))?;
        self.committed = true;
        if let Some(dir) = dest.parent().filter(|p| !p.as_os_str().is_empty()) {
            // Best effort: make the rename itself durable.
            let _ = std::fs::File::open(dir).and_then(|d| d.sync_all());
        }
        Ok(())
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

// ---------------------------------------------------------------------------------------
// The only direct cfitsio calls of the crate.

/// Header operations that the safe `fitsio` API lacks.
enum RawOp<'a> {
    /// Move to HDU `i` (0-based) and return all its header cards except END.
    ReadCards(usize),
    /// Append 80-character cards to the header of the current HDU.
    Append(&'a [String]),
    /// Delete the first occurrence of a keyword from the current HDU.
    Delete(&'a str),
    /// Close out the current HDU and flush every buffer to disk.
    Flush,
}

/// Run one raw header operation on an open file.
#[allow(unsafe_code)]
fn cfitsio_raw(f: &mut FitsFile, op: RawOp<'_>) -> fitsio::errors::Result<Vec<String>> {
    use fitsio::sys;
    const FLEN_CARD: usize = 81;
    // SAFETY: `f` is an open cfitsio file owned by the `FitsFile`, borrowed mutably for
    // the whole call, so the pointer is valid and not used concurrently. Every buffer
    // passed to cfitsio is either a NUL-terminated `CString` that outlives the call or a
    // FLEN_CARD (81) byte buffer, the size cfitsio documents for ffgrec. cfitsio reports
    // failures through `status`, checked after each call.
    let fptr = unsafe { f.as_raw() };
    let mut status: c_int = 0;
    let mut out = Vec::new();
    match op {
        RawOp::ReadCards(index) => {
            let mut hdutype: c_int = 0;
            let mut nkeys: c_int = 0;
            let mut nmore: c_int = 0;
            let hdunum = c_int::try_from(index + 1).unwrap_or(c_int::MAX);
            // SAFETY: see above; out-parameters are local integers.
            unsafe {
                sys::ffmahd(fptr, hdunum, &mut hdutype, &mut status);
                sys::ffghsp(fptr, &mut nkeys, &mut nmore, &mut status);
            }
            fitsio::errors::check_status(status)?;
            out.reserve(nkeys.max(0) as usize);
            let mut buf = [0 as c_char; FLEN_CARD];
            for n in 1..=nkeys {
                // SAFETY: see above; `buf` holds FLEN_CARD bytes.
                unsafe { sys::ffgrec(fptr, n, buf.as_mut_ptr(), &mut status) };
                fitsio::errors::check_status(status)?;
                let bytes: Vec<u8> = buf.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
                out.push(String::from_utf8_lossy(&bytes).into_owned());
            }
        }
        RawOp::Append(cards) => {
            for card in cards {
                let c = CString::new(card.as_str())?;
                // SAFETY: see above; `c` is NUL-terminated and lives through the call.
                unsafe { sys::ffprec(fptr, c.as_ptr(), &mut status) };
                fitsio::errors::check_status(status)?;
            }
        }
        RawOp::Delete(key) => {
            let c = CString::new(key)?;
            // SAFETY: see above.
            unsafe { sys::ffdkey(fptr, c.as_ptr(), &mut status) };
            fitsio::errors::check_status(status)?;
        }
        RawOp::Flush => {
            // SAFETY: see above.
            unsafe { sys::ffflus(fptr, &mut status) };
            fitsio::errors::check_status(status)?;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn card(key: &str, value: impl Into<HeaderValue>, comment: Option<&str>) -> Card {
        Card {
            key: key.into(),
            value: value.into(),
            comment: comment.map(String::from),
        }
    }

    fn roundtrip(c: &Card) -> Card {
        let lines = format_card(c, Path::new("t.fits")).unwrap();
        for l in &lines {
            assert!(l.len() <= 80, "{l:?}");
        }
        let (h, _) = parse_cards(&lines, Path::new("t.fits"));
        assert_eq!(h.cards.len(), 1, "{lines:?}");
        h.cards[0].clone()
    }

    #[test]
    fn cards_round_trip() {
        for c in [
            card("OBJECT", "HK Tau", Some("target")),
            card("ESO ADA POSANG", 45.0, Some("deg")),
            card("ESO OBS TARG NAME", "it's a 'quoted' name", None),
            card("NDIT", 6i64, None),
            card("ESO DET NDIT", -7i64, Some("x")),
            card("FLAG", true, None),
            card("ESO SEQ FLAG", false, None),
            card("EMPTY", "", None),
            card("LEADING", "  padded", None),
            card("TINY", 1.2345678901234567e-300, None),
            card("HUGE", -9.87654321e250, None),
            card("THIRD", 1.0 / 3.0, None),
            card("MJD-OBS", 51240.09112345679, None),
            card("DATE-OBS", "1999-03-03T02:11:05.123", None),
        ] {
            assert_eq!(roundtrip(&c), c, "{c:?}");
        }
    }

    #[test]
    fn long_strings_use_continue() {
        let long: String = (0..300)
            .map(|i| {
                if i % 7 == 0 {
                    '\''
                } else {
                    (b'a' + (i % 26) as u8) as char
                }
            })
            .collect();
        for key in ["LONGSTR", "ESO SOME VERY LONG HIERARCH KEYWORD NAME"] {
            let c = card(key, long.as_str(), Some("end"));
            let lines = format_card(&c, Path::new("t.fits")).unwrap();
            assert!(lines.len() > 3);
            assert!(lines[1].starts_with("CONTINUE  '"));
            assert_eq!(roundtrip(&c), c);
        }
    }

    #[test]
    fn parses_foreign_cards() {
        let cards: Vec<String> = [
            "SIMPLE  =                    T / conforms",
            "BITPIX  =                   16",
            "NAXIS1  =                 1024",
            "HIERARCH ESO DET DIT         =    10.0000000 / Integration Time",
            "HIERARCH ESO INS OPTI3 ID = 'WOLLASTON' / OPTIi ID",
            "EXPTIME =              1.0D+01 / Fortran exponent",
            "BIGINT  = 123456789012345678901234",
            "UNDEF   =",
            "CPLX    = (1.0, 2.0)",
            "COMMENT this is a comment = with equals",
            "HISTORY some foreign step",
            "        blank keyword card",
            "ZTILE1  =                 1024",
            "ZENITH  =                 12.5",
            "NEGFRAC =                  -.5",
            "PLUSEXP =             +1.0E+01",
            "TRAIL   =                   5.",
            "NOTNUM  =                  NaN",
            "DUP     =                    1",
            "DUP     =                    2",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        let (h, hist) = parse_cards(&cards, Path::new("x.fits"));
        let keys: Vec<&str> = h.cards.iter().map(|c| c.key.as_str()).collect();
        assert_eq!(
            keys,
            [
                "ESO DET DIT",
                "ESO INS OPTI3 ID",
                "EXPTIME",
                "BIGINT",
                "CPLX",
                "ZENITH",
                "NEGFRAC",
                "PLUSEXP",
                "TRAIL",
                "NOTNUM",
                "DUP"
            ]
        );
        assert_eq!(h.get("NEGFRAC"), Some(&HeaderValue::Float(-0.5)));
        assert_eq!(h.get("PLUSEXP"), Some(&HeaderValue::Float(10.0)));
        assert_eq!(h.get("TRAIL"), Some(&HeaderValue::Float(5.0)));
        assert_eq!(h.get("NOTNUM"), Some(&HeaderValue::Str("NaN".into())));
        assert_eq!(h.get("DUP"), Some(&HeaderValue::Int(1)));
        assert_eq!(h.get("ESO DET DIT"), Some(&HeaderValue::Float(10.0)));
        assert_eq!(h.cards[0].comment.as_deref(), Some("Integration Time"));
        assert_eq!(h.get_str("ESO INS OPTI3 ID").unwrap(), "WOLLASTON");
        assert_eq!(h.get("EXPTIME"), Some(&HeaderValue::Float(10.0)));
        assert_eq!(h.get("BIGINT"), Some(&HeaderValue::Float(1.2345678901234568e23)));
        assert_eq!(hist, vec![HistoryRecord::new("file", "some foreign step")]);
    }

    #[test]
    fn history_split_and_join() {
        let recs = vec![
            HistoryRecord::new("sky", "x".repeat(69) + "  two spaces then more" + &"y".repeat(150)),
            HistoryRecord::new("badpix", ""),
            HistoryRecord::new("flat", "short: with colon"),
        ];
        let cards = format_history(&recs);
        assert!(cards.iter().all(|c| c.len() <= 8 + HISTORY_CHUNK), "{cards:#?}");
        // cfitsio trims trailing blanks of every card.
        let trimmed: Vec<String> = cards.iter().map(|c| c.trim_end().to_string()).collect();
        let (_, back) = parse_cards(&trimmed, Path::new("x.fits"));
        assert_eq!(back[0], recs[0]);
        assert_eq!(back[1], recs[1]);
        assert_eq!(back[2], recs[2]);
    }

    #[test]
    fn bad_keywords_are_errors() {
        let p = Path::new("out.fits");
        let e = format_card(&card("ESO X", f64::NAN, None), p).unwrap_err().to_string();
        assert!(e.contains("out.fits") && e.contains("ESO X"), "{e}");
        let e = format_card(&card("OBJECT", "Ωmega", None), p).unwrap_err().to_string();
        assert!(e.contains("OBJECT") && e.contains("ASCII"), "{e}");
        let long_key = "ESO ".to_string() + &"K".repeat(80);
        assert!(format_card(&card(&long_key, 1i64, None), p).is_err());
    }

    #[test]
    fn cfitsio_names() {
        assert!(cfitsio_name(Path::new("a[1].fits")).is_err());
        assert!(cfitsio_name(Path::new("x.fits+1")).is_err());
        assert_eq!(cfitsio_name(Path::new("-x.fits")).unwrap(), "./-x.fits");
        assert_eq!(cfitsio_name(Path::new("/d/x.fits")).unwrap(), "/d/x.fits");
    }

    #[test]
    fn u16_conversion() {
        assert_eq!(to_u16(-3.0), 0);
        assert_eq!(to_u16(1.5), 2);
        assert_eq!(to_u16(2.49), 2);
        assert_eq!(to_u16(70000.0), 65535);
        assert_eq!(to_u16(f32::NAN), 0);
    }
}
