//! Writing: float32 or int16 images, optionally tile compressed, with VARIANCE and MASK
//! extensions, through a temporary file renamed into place.
use std::path::Path;

use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;
use ndarray::Array2;

use crate::atomic::TempFile;
use crate::error::{Error, Result};
use crate::frame::Frame;

use super::cards::*;
use super::cfitsio::*;
use super::read::check_extension_shape;
use super::{Bitpix, WriteOptions, MASK_EXTNAME, VARIANCE_EXTNAME, VARIANCE_UTYPE};

/// Write a frame atomically: the file is written to a temporary file in a fresh private
/// directory next to `path` ([`crate::atomic::TempFile`]: random name, mode 0700),
/// flushed, synced and renamed over `path`, so a crash never leaves a half-written file,
/// an existing file is replaced only by a complete one, and nothing but `path` is ever
/// written (`path` must be absent or a regular file: a symbolic link or device there is
/// refused).
///
/// Header: every card of `frame.header` (keys longer than 8 characters or with spaces
/// as `HIERARCH` cards; strings longer than a card with the CONTINUE convention; floats
/// with the shortest representation that reads back bit-exactly; comments when they
/// fit), then one HISTORY entry per `frame.history` record (`record.line()`, split into
/// cards of at most [`super::HISTORY_CHUNK`] characters; continuation cards start with
/// [`super::HISTORY_CONTINUATION`]). Structural keywords in `frame.header` are ignored (the
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

    let mut tmp = TempFile::new(path)?;
    let tmp_name = match tmp.ascii_path() {
        Some(p) => p,
        None => cfitsio_name(&tmp.path)?,
    };
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
                    .map_err(|e| ferr("creating UNCERT", e))?;
                h.write_key(&mut f, "UTYPE", VARIANCE_UTYPE)
                    .map_err(|e| ferr("writing UTYPE", e))?;
                h.write_image(&mut f, &contiguous(v))
                    .map_err(|e| ferr("writing UNCERT", e))?;
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

pub(super) fn contiguous<T: Clone>(a: &Array2<T>) -> std::borrow::Cow<'_, [T]> {
    match a.as_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(a.iter().cloned().collect()),
    }
}

pub(super) fn to_u16(v: f32) -> u16 {
    if v.is_nan() {
        0
    } else {
        v.round().clamp(0.0, 65535.0) as u16
    }
}

/// The pixels of one HDU written by [`write_images`].
#[derive(Debug, Clone, Copy)]
pub enum ImagePixels<'a> {
    /// BITPIX = -32 (NaN allowed: a float image's blank).
    F32(&'a Array2<f32>),
    /// BITPIX = 8 (unsigned bytes: masks, counts).
    U8(&'a Array2<u8>),
}

impl ImagePixels<'_> {
    fn dim(&self) -> (usize, usize) {
        match self {
            ImagePixels::F32(a) => a.dim(),
            ImagePixels::U8(a) => a.dim(),
        }
    }
}

/// One image HDU of a file written by [`write_images`]: its name (`EXTNAME`; none for the
/// primary), its cards (formatted as [`write_frame`] formats a header) and HISTORY records,
/// and its pixels.
#[derive(Debug, Clone, Copy)]
pub struct ImageHdu<'a> {
    /// `EXTNAME` of an extension (ignored for the first HDU, the primary).
    pub extname: &'a str,
    /// Header cards (structural keywords ignored: the layout decides them).
    pub header: &'a crate::Header,
    /// HISTORY records, one entry each (split over cards as [`write_frame`] does).
    pub history: &'a [crate::HistoryRecord],
    /// The image.
    pub pixels: ImagePixels<'a>,
}

/// Write several images into one FITS file atomically, as [`write_frame`] writes one: the
/// first HDU is the primary image, each following one an image extension named by its
/// `extname`; every HDU gets its own cards and HISTORY. Cards are formatted before
/// anything touches the disk (a bad keyword leaves no trace); the file is written to a
/// temporary in a private directory, flushed, synced and renamed over `path`.
pub fn write_images(path: &Path, hdus: &[ImageHdu]) -> Result<()> {
    let bad = |reason: String| Error::BadImage {
        path: path.to_path_buf(),
        reason,
    };
    let Some(first) = hdus.first() else {
        return Err(bad("no image to write".into()));
    };
    let mut cards = Vec::with_capacity(hdus.len());
    for h in hdus {
        let (ny, nx) = h.pixels.dim();
        if ny == 0 || nx == 0 {
            return Err(bad(format!(
                "cannot write an empty image ({ny} x {nx} pixels) in HDU '{}'",
                h.extname
            )));
        }
        let mut c = format_header(h.header, path)?;
        c.extend(format_history(h.history));
        cards.push(c);
    }
    let mut tmp = TempFile::new(path)?;
    let tmp_name = match tmp.ascii_path() {
        Some(p) => p,
        None => cfitsio_name(&tmp.path)?,
    };
    let tpath = tmp.path.clone();
    let ferr = |what: &str, e: fitsio::errors::Error| fits_err(&tpath, what, e);
    let desc_of = |p: &ImagePixels| -> ImageType {
        match p {
            ImagePixels::F32(_) => ImageType::Float,
            ImagePixels::U8(_) => ImageType::UnsignedByte,
        }
    };
    {
        let (ny, nx) = first.pixels.dim();
        let shape = [ny, nx];
        let desc = ImageDescription {
            data_type: desc_of(&first.pixels),
            dimensions: &shape,
        };
        let mut f = FitsFile::create(&tmp_name)
            .with_custom_primary(&desc)
            .open()
            .map_err(|e| ferr("creating", e))?;
        let primary = f.primary_hdu().map_err(|e| ferr("primary HDU", e))?;
        // fitsio names the primary '_PRIMARY': drop it, a primary needs no name.
        cfitsio_raw(&mut f, RawOp::Delete("EXTNAME")).map_err(|e| ferr("deleting EXTNAME", e))?;
        // Header before data: appending cards later would make cfitsio shift the data.
        cfitsio_raw(&mut f, RawOp::Append(&cards[0])).map_err(|e| ferr("writing header cards", e))?;
        write_pixels(&mut f, &primary, first.pixels).map_err(|e| ferr("writing the primary image", e))?;
        for (h, c) in hdus.iter().zip(&cards).skip(1) {
            let (ny, nx) = h.pixels.dim();
            let shape = [ny, nx];
            let desc = ImageDescription {
                data_type: desc_of(&h.pixels),
                dimensions: &shape,
            };
            let what = |s: &str| format!("{s} {}", h.extname);
            let hdu = f
                .create_image(h.extname, &desc)
                .map_err(|e| ferr(&what("creating"), e))?;
            cfitsio_raw(&mut f, RawOp::Append(c)).map_err(|e| ferr(&what("writing the cards of"), e))?;
            write_pixels(&mut f, &hdu, h.pixels).map_err(|e| ferr(&what("writing"), e))?;
        }
        // Drop (fits_close_file) cannot report errors: flush explicitly first.
        cfitsio_raw(&mut f, RawOp::Flush).map_err(|e| ferr("flushing", e))?;
    }
    tmp.commit(path)
}

fn write_pixels(f: &mut FitsFile, hdu: &fitsio::hdu::FitsHdu, p: ImagePixels) -> fitsio::errors::Result<()> {
    match p {
        ImagePixels::F32(a) => hdu.write_image(f, &contiguous(a)),
        ImagePixels::U8(a) => hdu.write_image(f, &contiguous(a)),
    }
}
