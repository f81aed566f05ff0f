//! FITS I/O through the `fitsio` crate (bundled cfitsio). STUB: being implemented.
use std::path::Path;

use crate::error::Result;
use crate::frame::Frame;
use crate::header::Header;

/// On-disk pixel type of a written image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Bitpix {
    /// BITPIX = -32.
    #[default]
    F32,
    /// BITPIX = 16 with BZERO = 32768, BSCALE = 1 (values rounded, clipped to 0..65535).
    I16,
}

/// How to write a frame.
#[derive(Debug, Clone, Default)]
pub struct WriteOptions {
    /// Pixel type.
    pub bitpix: Bitpix,
    /// Rice tile compression (.fz layout: empty primary, image in HDU 1).
    pub compress: bool,
    /// Also write VARIANCE and MASK image extensions (when present).
    pub with_variance_and_mask: bool,
}

/// Read the header of the image HDU only.
pub fn read_header(path: &Path) -> Result<Header> {
    let _ = path;
    unimplemented!()
}

/// Read a frame.
pub fn read_frame(path: &Path) -> Result<Frame> {
    let _ = path;
    unimplemented!()
}

/// Write a frame atomically.
pub fn write_frame(path: &Path, frame: &Frame, opts: &WriteOptions) -> Result<()> {
    let _ = (path, frame, opts);
    unimplemented!()
}
