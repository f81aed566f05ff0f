//! What is wrong with a file cfitsio refused, in words: cfitsio's status codes say "illegal
//! NAXISn keyword value" without the value, and "not a FITS file?" for a good image
//! followed by junk. These read the file's first header or its tail themselves.
use std::io::Read;
use std::path::Path;

use fitsio::FitsFile;

use crate::header::HeaderValue;

use super::keys::raw_value;

/// The first header of a file that starts with `SIMPLE  =` (at most 64 blocks, up to END),
/// as 80-character cards.
fn first_header(path: &Path) -> Option<Vec<String>> {
    let mut f = std::fs::File::open(path).ok()?;
    let mut cards = Vec::new();
    let mut block = [0u8; 2880];
    for b in 0..64 {
        f.read_exact(&mut block).ok()?;
        if b == 0 && !block.starts_with(b"SIMPLE  =") {
            return None;
        }
        for card in block.chunks_exact(80) {
            let text = String::from_utf8_lossy(card).trim_end().to_string();
            if card.starts_with(b"END     ") {
                return Some(cards);
            }
            cards.push(text);
        }
    }
    Some(cards)
}

/// The first mandatory keyword of the primary header that is missing or out of the FITS
/// standard's range (SIMPLE = T, BITPIX one of 8, 16, 32, 64, -32, -64, NAXIS in
/// 0..=999, each NAXISn an integer >= 0), named with its value; None when they are
/// fine or the file does not start like FITS.
pub(super) fn primary_keyword_problem(path: &Path) -> Option<String> {
    let cards = first_header(path)?;
    let int = |key: &str| match raw_value(&cards, key) {
        Some(HeaderValue::Int(v)) => Ok(v),
        Some(v) => Err(format!("{key} = {v} is not an integer")),
        None => Err(format!("keyword {key} is missing from the primary header")),
    };
    if raw_value(&cards, "SIMPLE") != Some(HeaderValue::Bool(true)) {
        return Some("SIMPLE is not T: the file does not declare itself standard FITS".into());
    }
    match int("BITPIX") {
        Ok(8 | 16 | 32 | 64 | -32 | -64) => {}
        Ok(b) => {
            return Some(format!(
                "BITPIX = {b} is not a FITS pixel type (8, 16, 32, 64, -32 or -64)"
            ))
        }
        Err(e) => return Some(e),
    }
    let n = match int("NAXIS") {
        Ok(n @ 0..=999) => n,
        Ok(n) => return Some(format!("NAXIS = {n} is out of range (0..=999)")),
        Err(e) => return Some(e),
    };
    for i in 1..=n {
        match int(&format!("NAXIS{i}")) {
            Ok(v) if v >= 0 => {}
            Ok(v) => return Some(format!("NAXIS{i} = {v} is negative: an axis has a length >= 0")),
            Err(e) => return Some(e),
        }
    }
    None
}

/// Why HDU `index` (> 0) could not be read when cfitsio says its header does not start
/// like an extension or cannot be read: the bytes after HDU `index - 1` do not start with
/// `XTENSION` (junk appended to the file), with where they start and how many there are.
/// None when they do (a truncated extension: cfitsio's message says so).
pub(super) fn trailing_junk(f: &mut FitsFile, path: &Path, index: usize) -> Option<String> {
    use std::io::{Seek, SeekFrom};
    let end = super::cfitsio::hdu_end(f, index.checked_sub(1)?).ok()?;
    let len = std::fs::metadata(path).ok()?.len();
    let mut first = [0u8; 8];
    let mut file = std::fs::File::open(path).ok()?;
    file.seek(SeekFrom::Start(end)).ok()?;
    let n = file.read(&mut first).ok()?;
    (len > end && !first[..n].starts_with(b"XTENSION")).then(|| {
        format!(
            "the file goes on for {} bytes after its last HDU (HDU {}, ending at byte {end}) and they are not a \
             FITS extension: junk appended to the file (the image itself is complete)",
            len - end,
            index - 1
        )
    })
}
