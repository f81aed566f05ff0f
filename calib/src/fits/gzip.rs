//! Compressed files are bounded before cfitsio opens them: cfitsio inflates a gzip file
//! whole into memory when it opens it (even to read a header), so a 4 MB file that
//! expands 250 times took a gigabyte before any check could run. The stream is inflated
//! here first, counting bytes in a small buffer, and refused past an absolute bound:
//! the largest image sofipol reads ([`MAX_IMAGE_PIXELS`]) with a VARIANCE and a MASK
//! extension, plus headers. Other compressions cfitsio would inflate (Unix compress,
//! pack, zip) are refused by name.
use std::io::Read;
use std::path::Path;

use crate::error::{Error, Result};

/// Most pixels of an image sofipol reads: a 4096 x 4096 detector
/// ([`crate::profile::MAX_DETECTOR_SIDE_PX`] squared; SOFI's is 1024 x 1024).
pub const MAX_IMAGE_PIXELS: u64 = (crate::profile::MAX_DETECTOR_SIDE_PX * crate::profile::MAX_DETECTOR_SIDE_PX) as u64;

/// Most bytes a gzip-compressed FITS file may inflate to: a float image of
/// [`MAX_IMAGE_PIXELS`] with float VARIANCE and byte MASK extensions (9 bytes a pixel),
/// plus 4 MiB of headers.
pub const MAX_GZIP_BYTES: u64 = 9 * MAX_IMAGE_PIXELS + (4 << 20);

/// Refuse, before cfitsio opens `path`, a gzip file that inflates to more than
/// [`MAX_GZIP_BYTES`] (counted in a 64 kB buffer) or a file in another compression
/// cfitsio would inflate into memory. Plain files pass untouched.
pub(super) fn check_compressed(path: &Path) -> Result<()> {
    // The OS's reason, said as such; running out of file handles keeps its error code
    // (the scan stops on it: `sofipol_pipeline::scan::is_out_of_file_handles`).
    let io = |source: std::io::Error| Error::Io {
        path: path.to_path_buf(),
        source: match source.raw_os_error() {
            Some(23 | 24) => source,
            _ => std::io::Error::new(source.kind(), format!("cannot be opened: {source}")),
        },
    };
    let mut magic = [0u8; 4];
    let mut f = std::fs::File::open(path).map_err(io)?;
    let n = read_up_to(&mut f, &mut magic).map_err(io)?;
    let magic = &magic[..n];
    let other = match magic {
        [0x1f, 0x9d, ..] => Some("Unix compress (.Z)"),
        [0x1f, 0x1e, ..] => Some("pack (.z)"),
        [0x1f, 0xa0, ..] => Some("LZH"),
        [b'P', b'K', 3, 4] => Some("zip"),
        _ => None,
    };
    if let Some(kind) = other {
        return Err(Error::BadImage {
            path: path.to_path_buf(),
            reason: format!(
                "compressed with {kind}: sofipol reads gzip (.fits.gz) and tile-compressed (.fz) FITS only"
            ),
        });
    }
    if !magic.starts_with(&[0x1f, 0x8b]) {
        return Ok(());
    }
    let f = std::fs::File::open(path).map_err(io)?;
    let mut gz = flate2::read::MultiGzDecoder::new(std::io::BufReader::new(f));
    let mut buf = vec![0u8; 64 << 10];
    let mut total: u64 = 0;
    loop {
        let k = match gz.read(&mut buf) {
            Ok(0) => return Ok(()),
            Ok(k) => k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => {
                return Err(Error::BadImage {
                    path: path.to_path_buf(),
                    reason: format!("gzip data unreadable after {total} inflated bytes: {e}"),
                })
            }
        };
        total += k as u64;
        if total > MAX_GZIP_BYTES {
            return Err(Error::BadImage {
                path: path.to_path_buf(),
                reason: format!(
                    "gzip file inflates to more than {MAX_GZIP_BYTES} bytes ({} MB), more than a {side} x {side} px frame \
                     with its extensions needs: refused before reading (a corrupt or hostile file)",
                    MAX_GZIP_BYTES / 1_000_000,
                    side = crate::profile::MAX_DETECTOR_SIDE_PX
                ),
            });
        }
    }
}

fn read_up_to(f: &mut std::fs::File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}
