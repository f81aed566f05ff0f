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
//! cards, logical values or full-precision doubles. All direct cfitsio calls sit in
//! `cfitsio.rs` (`cfitsio_raw`, and `data_start` for the plain reads of `raw.rs`).
//!
//! Pixel layout: arrays are indexed `[y, x]`; row 0 is FITS row 1 (the bottom of the
//! image), column 0 is FITS column 1.
//!
//! `FitsFile` is neither `Send` nor `Sync`: every function opens and closes its own
//! handle, so different files may be read or written from different threads.
//!
//! Files: `read.rs` (finding the image HDU, pixels, extensions), `write.rs` (images,
//! extensions, compression), `cards.rs` (parsing and formatting 80-character header cards,
//! HISTORY records), `cfitsio.rs` (opening files, error messages, the raw cfitsio calls),
//! `raw.rs` (plain 16-bit and float images read straight from the file, the night's
//! frames: cfitsio locates the data, the bytes are converted in one pass).
//! The temporary file of the atomic write is [`crate::atomic::TempFile`].
mod cards;
mod cfitsio;
mod convert;
mod diagnose;
mod gzip;
mod keys;
mod raw;
mod read;
#[cfg(test)]
mod tests;
mod write;

pub use gzip::{MAX_GZIP_BYTES, MAX_IMAGE_PIXELS};
pub use read::{read_frame, read_frame_rows, read_frame_rows_with_summary, read_header, read_image_shape};
pub use write::{write_frame, write_images, ImageHdu, ImagePixels};

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

/// EXTNAME of the variance extension written by [`write_frame`] and the products: astropy's
/// `CCDData.read` takes the extension `UNCERT` as the uncertainty of the primary image, of the
/// kind its `UTYPE` card names ([`VARIANCE_UTYPE`]).
pub const VARIANCE_EXTNAME: &str = "UNCERT";
/// `UTYPE` of the variance extension: astropy's class of a variance.
pub const VARIANCE_UTYPE: &str = "VarianceUncertainty";
/// The variance extension's name in files sofipol wrote before (still read, as a variance).
pub const LEGACY_VARIANCE_EXTNAME: &str = "VARIANCE";
/// EXTNAME of the mask extension written by [`write_frame`].
pub const MASK_EXTNAME: &str = "MASK";
/// Maximum number of characters of text written on one HISTORY card.
pub const HISTORY_CHUNK: usize = 70;
/// Prefix of a HISTORY card that continues the previous sofipol record (long lines are
/// split over several cards).
pub const HISTORY_CONTINUATION: &str = "sofipol& ";

/// `v` as an `ny` x `nx` array, or [`crate::Error::BadImage`] naming the file when the
/// count is not `ny * nx`.
fn to_array<T>(v: Vec<T>, ny: usize, nx: usize, path: &std::path::Path) -> crate::Result<ndarray::Array2<T>> {
    let n = v.len();
    ndarray::Array2::from_shape_vec((ny, nx), v).map_err(|_| crate::Error::BadImage {
        path: path.to_path_buf(),
        reason: format!("read {n} pixels, expected {nx} x {ny}"),
    })
}
