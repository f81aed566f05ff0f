//! File names for cfitsio (its extended file-name syntax kept out), error messages, and the
//! only direct cfitsio calls of the crate.
use std::ffi::{c_char, c_int, CString};
use std::path::Path;

use fitsio::FitsFile;

use crate::error::{Error, Result};

pub(super) fn fits_err(path: &Path, what: &str, e: fitsio::errors::Error) -> Error {
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
pub(super) fn cfitsio_name(path: &Path) -> Result<String> {
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

/// Header operations that the safe `fitsio` API lacks.
pub(super) enum RawOp<'a> {
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
pub(super) fn cfitsio_raw(f: &mut FitsFile, op: RawOp<'_>) -> fitsio::errors::Result<Vec<String>> {
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

/// Byte offset in the file of the end of HDU `index` (0-based: its header and padded data),
/// from cfitsio's HDU map.
#[allow(unsafe_code)]
pub(super) fn hdu_end(f: &mut FitsFile, index: usize) -> fitsio::errors::Result<u64> {
    use fitsio::sys;
    let hdunum = c_int::try_from(index + 1).unwrap_or(c_int::MAX);
    let (mut hdutype, mut status): (c_int, c_int) = (0, 0);
    let (mut head, mut data, mut end): (sys::LONGLONG, sys::LONGLONG, sys::LONGLONG) = (0, 0, 0);
    // SAFETY: as in `data_start`.
    unsafe {
        let fptr = f.as_raw();
        sys::ffmahd(fptr, hdunum, &mut hdutype, &mut status);
        sys::ffghadll(fptr, &mut head, &mut data, &mut end, &mut status);
    }
    fitsio::errors::check_status(status)?;
    u64::try_from(end).map_err(|_| fitsio::errors::Error::Message(format!("negative HDU end {end}")))
}

/// Byte offset in the file of the data of HDU `index` (0-based), from cfitsio's HDU map.
#[allow(unsafe_code)]
pub(super) fn data_start(f: &mut FitsFile, index: usize) -> fitsio::errors::Result<u64> {
    use fitsio::sys;
    let hdunum = c_int::try_from(index + 1).unwrap_or(c_int::MAX);
    let (mut hdutype, mut status): (c_int, c_int) = (0, 0);
    let (mut head, mut data, mut end): (sys::LONGLONG, sys::LONGLONG, sys::LONGLONG) = (0, 0, 0);
    // SAFETY: as in `cfitsio_raw`: `f` is an open file borrowed mutably for the call; the
    // out-parameters are local integers; `status` is checked after the calls.
    unsafe {
        let fptr = f.as_raw();
        sys::ffmahd(fptr, hdunum, &mut hdutype, &mut status);
        sys::ffghadll(fptr, &mut head, &mut data, &mut end, &mut status);
    }
    fitsio::errors::check_status(status)?;
    u64::try_from(data).map_err(|_| fitsio::errors::Error::Message(format!("negative data offset {data}")))
}
