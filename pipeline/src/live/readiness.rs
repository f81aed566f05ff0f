//! Whether a frame that has appeared in the night's folder is complete: a file still being
//! copied or written by the instrument is waited for, not reported as broken.
//!
//! A FITS file is a sequence of HDUs, each a header of 2880-byte blocks ending with the
//! `END` card followed by its data, `|BITPIX|/8 * GCOUNT * (PCOUNT + NAXIS1 * ... * NAXISn)`
//! bytes padded to a multiple of 2880. The file is complete when every HDU's header and
//! data are there. A gzip file is complete when its stream decompresses to the end (the
//! trailer carries the length and CRC of the data). A file that does not start like FITS
//! or gzip is complete as it is: the scan reports it for what it is.
use std::io::Read;
use std::path::Path;

/// FITS block size, bytes.
const BLOCK: u64 = 2880;

/// What the folder holds under a frame's name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Readiness {
    /// Whole: it can be read.
    Complete,
    /// Still arriving: what is missing.
    Incomplete(Incomplete),
}

/// What a file still being written lacks (its `Display` is the reason shown while the
/// frame is waited for).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Incomplete {
    /// The file cannot be opened (yet), with the system's reason when there is one.
    #[error("cannot be opened yet{}", .reason.as_ref().map(|r| format!(": {r}")).unwrap_or_default())]
    CannotOpen {
        /// The system's reason, if any.
        reason: Option<String>,
    },
    /// The file has no bytes yet.
    #[error("empty")]
    Empty,
    /// A gzip stream that ends before its trailer.
    #[error("gzip stream not finished")]
    GzipUnfinished,
    /// The header of an HDU is not all there (or cannot be sized).
    #[error("HDU {hdu}: {problem}")]
    Header {
        /// HDU number, 1-based (as FITS counts them).
        hdu: usize,
        /// What is missing.
        problem: HeaderProblem,
    },
    /// The data of an HDU are not all there.
    #[error("HDU {hdu}: {present_bytes} of its {expected_bytes} data bytes present")]
    Data {
        /// HDU number, 1-based.
        hdu: usize,
        /// Data bytes the file holds, bytes.
        present_bytes: u64,
        /// Data bytes the header announces (unpadded), bytes.
        expected_bytes: u64,
    },
    /// Every HDU is whole but none has data: a file cut after its primary header.
    #[error("headers only, no data yet")]
    HeadersOnly,
}

/// What is missing from an HDU's header.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HeaderProblem {
    /// The file could not be positioned at the header (the system's reason).
    #[error("{0}")]
    Seek(String),
    /// The file ends before the END card.
    #[error("header not finished (no END card yet)")]
    NoEndYet,
    /// A header block could not be read whole.
    #[error("header not finished")]
    ShortBlock,
    /// No END card in the first 1000 blocks: not a header still being written.
    #[error("no END card in 1000 header blocks")]
    NoEnd,
    /// A keyword that sizes the data is absent (`BITPIX`, `NAXIS`, `NAXISn`).
    #[error("no {0}")]
    MissingKeyword(String),
}

/// Whether the file at `path` is complete ([`Readiness`]).
pub fn readiness(path: &Path) -> Readiness {
    let mut f = match std::fs::File::open(path) {
        Ok(f) => f,
        Err(e) => {
            return Readiness::Incomplete(Incomplete::CannotOpen {
                reason: Some(e.to_string()),
            })
        }
    };
    let len = f.metadata().map(|m| m.len()).unwrap_or(0);
    let mut head = [0u8; 9];
    let n = read_up_to(&mut f, &mut head);
    if n == 0 {
        return Readiness::Incomplete(Incomplete::Empty);
    }
    if head[..n.min(2)] == [0x1f, 0x8b][..n.min(2)] {
        return gzip_readiness(path);
    }
    if !b"SIMPLE  =".starts_with(&head[..n]) {
        return Readiness::Complete;
    }
    match fits_length(&mut std::fs::File::open(path).ok(), len) {
        Ok(()) => Readiness::Complete,
        Err(why) => Readiness::Incomplete(why),
    }
}

/// Read into `buf` until it is full or the file ends; the number of bytes read.
fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> usize {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) | Err(_) => break,
            Ok(k) => n += k,
        }
    }
    n
}

/// A gzip stream is complete when it decompresses to its end without error.
fn gzip_readiness(path: &Path) -> Readiness {
    let Ok(f) = std::fs::File::open(path) else {
        return Readiness::Incomplete(Incomplete::CannotOpen { reason: None });
    };
    let mut d = flate2::read::MultiGzDecoder::new(std::io::BufReader::new(f));
    match std::io::copy(&mut d, &mut std::io::sink()) {
        Ok(_) => Readiness::Complete,
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Readiness::Incomplete(Incomplete::GzipUnfinished),
        // Corrupt rather than unfinished: the scan says so.
        Err(_) => Readiness::Complete,
    }
}

/// Walk the HDUs of a FITS file of `len` bytes: `Ok` when every header and data unit is
/// there, else what is missing.
fn fits_length(file: &mut Option<std::fs::File>, len: u64) -> Result<(), Incomplete> {
    let Some(f) = file.as_mut() else {
        return Err(Incomplete::CannotOpen { reason: None });
    };
    let mut offset = 0u64;
    let mut hdu = 0;
    let mut data = 0u64;
    while offset < len {
        let (header_len, data_len) =
            read_hdu_header(f, offset, len).map_err(|problem| Incomplete::Header { hdu: hdu + 1, problem })?;
        let end = offset + header_len + data_len.div_ceil(BLOCK) * BLOCK;
        if end > len {
            return Err(Incomplete::Data {
                hdu: hdu + 1,
                present_bytes: len.saturating_sub(offset + header_len),
                expected_bytes: data_len,
            });
        }
        offset = end;
        data += data_len;
        hdu += 1;
    }
    // A frame has pixels: headers alone are a file cut after its primary header (a
    // tile-compressed frame keeps its image in the extension that follows).
    if data == 0 {
        return Err(Incomplete::HeadersOnly);
    }
    Ok(())
}

/// The header of the HDU at `offset`: its length in bytes (whole blocks) and its data
/// length (unpadded).
fn read_hdu_header(f: &mut std::fs::File, offset: u64, len: u64) -> Result<(u64, u64), HeaderProblem> {
    use std::io::Seek;
    f.seek(std::io::SeekFrom::Start(offset))
        .map_err(|e| HeaderProblem::Seek(e.to_string()))?;
    let mut block = [0u8; BLOCK as usize];
    let mut cards = HduCards::default();
    let mut header_len = 0u64;
    loop {
        if offset + header_len + BLOCK > len {
            return Err(HeaderProblem::NoEndYet);
        }
        if read_up_to(f, &mut block) < BLOCK as usize {
            return Err(HeaderProblem::ShortBlock);
        }
        header_len += BLOCK;
        for card in block.chunks(80) {
            if card.starts_with(b"END     ") || card == b"END" {
                return Ok((header_len, cards.data_bytes()?));
            }
            cards.read(card);
        }
        if header_len > 1000 * BLOCK {
            return Err(HeaderProblem::NoEnd);
        }
    }
}

/// The header values that size an HDU's data.
#[derive(Default)]
struct HduCards {
    bitpix: Option<i64>,
    naxis: Option<usize>,
    axes: Vec<(usize, u64)>,
    pcount: u64,
    gcount: Option<u64>,
}

impl HduCards {
    /// Take the value of a card that sizes the data.
    fn read(&mut self, card: &[u8]) {
        let text = String::from_utf8_lossy(card);
        let (key, rest) = text.split_at(8.min(text.len()));
        let Some(value) = rest.strip_prefix("= ") else { return };
        let value = value.split('/').next().unwrap_or("").trim();
        let key = key.trim_end();
        let int = || value.parse::<i64>().ok();
        match key {
            "BITPIX" => self.bitpix = int(),
            "NAXIS" => self.naxis = int().and_then(|n| usize::try_from(n).ok()),
            "PCOUNT" => self.pcount = int().and_then(|n| u64::try_from(n).ok()).unwrap_or(0),
            "GCOUNT" => self.gcount = int().and_then(|n| u64::try_from(n).ok()),
            k => {
                if let (Some(i), Some(n)) = (
                    k.strip_prefix("NAXIS").and_then(|i| i.parse::<usize>().ok()),
                    int().and_then(|n| u64::try_from(n).ok()),
                ) {
                    self.axes.push((i, n));
                }
            }
        }
    }

    /// `|BITPIX|/8 * GCOUNT * (PCOUNT + NAXIS1 * ... * NAXISn)`, 0 without axes.
    fn data_bytes(&self) -> Result<u64, HeaderProblem> {
        let missing = |k: &str| HeaderProblem::MissingKeyword(k.to_string());
        let bitpix = self.bitpix.ok_or_else(|| missing("BITPIX"))?;
        let naxis = self.naxis.ok_or_else(|| missing("NAXIS"))?;
        if naxis == 0 {
            return Ok(0);
        }
        let mut n = 1u64;
        for i in 1..=naxis {
            let (_, v) = self
                .axes
                .iter()
                .find(|(k, _)| *k == i)
                .ok_or_else(|| missing(&format!("NAXIS{i}")))?;
            n = n.saturating_mul(*v);
        }
        Ok((bitpix.unsigned_abs() / 8)
            .saturating_mul(self.gcount.unwrap_or(1))
            .saturating_mul(self.pcount.saturating_add(n)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A FITS file written by cfitsio (through the project's writer).
    fn written(dir: &Path, name: &str, compress: bool) -> std::path::PathBuf {
        use sofipol_calib::fits::{write_frame, Bitpix, WriteOptions};
        let path = dir.join(name);
        let data = ndarray::Array2::<f32>::from_shape_fn((37, 530), |(i, j)| ((i * 53 + j) % 977) as f32);
        let mut header = sofipol_calib::Header::new("");
        header.set("OBJECT", "HK Tau");
        let frame = sofipol_calib::Frame::new(data, header);
        let opts = WriteOptions {
            bitpix: Bitpix::I16,
            compress,
            ..Default::default()
        };
        write_frame(&path, &frame, &opts).unwrap();
        path
    }

    /// A FITS file cut at many lengths: complete only whole; a tile-compressed one (a
    /// binary-table extension with a heap) too.
    #[test]
    fn a_fits_file_is_complete_only_when_whole() {
        let dir = tempfile::tempdir().unwrap();
        let fz = written(dir.path(), "f.fits.fz", true);
        let fz_bytes = std::fs::read(&fz).unwrap();
        assert_eq!(readiness(&fz), Readiness::Complete);
        let cut = dir.path().join("cut.fits.fz");
        for n in [100, 2880, 2 * 2880 + 5, fz_bytes.len() - 1] {
            std::fs::write(&cut, &fz_bytes[..n]).unwrap();
            assert!(
                matches!(readiness(&cut), Readiness::Incomplete(_)),
                "fz: {n} of {}",
                fz_bytes.len()
            );
        }
        let path = written(dir.path(), "f.fits", false);
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(bytes.len() as u64 % BLOCK, 0);
        assert_eq!(readiness(&path), Readiness::Complete);
        let cut = dir.path().join("cut.fits");
        for n in [
            1,
            9,
            80,
            2879,
            2880,
            2881,
            bytes.len() / 2,
            bytes.len() - 2880,
            bytes.len() - 1,
        ] {
            std::fs::write(&cut, &bytes[..n]).unwrap();
            assert!(
                matches!(readiness(&cut), Readiness::Incomplete(_)),
                "{n} of {} bytes taken for complete",
                bytes.len()
            );
        }
        // What is missing is told apart: the data of the primary HDU, its header.
        std::fs::write(&cut, &bytes[..bytes.len() - 2880]).unwrap();
        assert!(
            matches!(readiness(&cut), Readiness::Incomplete(Incomplete::Data { hdu: 1, .. })),
            "{:?}",
            readiness(&cut)
        );
        std::fs::write(&cut, &bytes[..2879]).unwrap();
        assert_eq!(
            readiness(&cut),
            Readiness::Incomplete(Incomplete::Header {
                hdu: 1,
                problem: HeaderProblem::NoEndYet
            })
        );
        // An extension appended and cut: incomplete; whole: complete.
        let mut two = bytes.clone();
        two.extend_from_slice(&bytes);
        two[bytes.len()..bytes.len() + 9].copy_from_slice(b"XTENSION=");
        std::fs::write(&cut, &two[..two.len() - 100]).unwrap();
        assert!(matches!(readiness(&cut), Readiness::Incomplete(_)));
        std::fs::write(&cut, &two).unwrap();
        assert_eq!(readiness(&cut), Readiness::Complete);
    }

    #[test]
    fn gzip_is_complete_at_the_end_of_its_stream() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        let payload: Vec<u8> = (0..200_000u32).map(|i| (i * 7 % 251) as u8).collect();
        e.write_all(&payload).unwrap();
        let gz = e.finish().unwrap();
        let p = dir.path().join("f.fits.gz");
        std::fs::write(&p, &gz).unwrap();
        assert_eq!(readiness(&p), Readiness::Complete);
        std::fs::write(&p, &gz[..gz.len() - 4]).unwrap();
        assert!(matches!(readiness(&p), Readiness::Incomplete(_)));
        std::fs::write(&p, &gz[..gz.len() / 2]).unwrap();
        assert!(matches!(readiness(&p), Readiness::Incomplete(_)));
    }

    #[test]
    fn empty_is_waited_for_and_foreign_is_handed_on() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.fits");
        std::fs::write(&p, b"").unwrap();
        assert!(matches!(readiness(&p), Readiness::Incomplete(_)));
        std::fs::write(&p, b"this is not FITS at all").unwrap();
        assert_eq!(readiness(&p), Readiness::Complete);
        std::fs::write(&p, b"SIMP").unwrap();
        assert!(matches!(readiness(&p), Readiness::Incomplete(_)));
    }
}
