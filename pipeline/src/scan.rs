//! Finding and classifying input files.
use std::path::{Path, PathBuf};

use sofipol_calib::classify::{classify_file, Classification, ScienceInfo};
use sofipol_calib::Profile;

use crate::catalog::Failure;

/// File names sofipol reads: `.fits`, `.fit`, `.fits.gz`, `.fit.gz`, `.fz` (any case).
pub fn is_fits_name(p: &Path) -> bool {
    let n = p
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    !n.starts_with('.')
        && [".fits", ".fit", ".fits.gz", ".fit.gz", ".fz"]
            .iter()
            .any(|e| n.ends_with(e))
}

/// Every FITS-named file under `root` (recursively; a file is taken as given), sorted.
pub fn find_files(root: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    if root.is_file() {
        out.push(root.to_path_buf());
        return Ok(out);
    }
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d)? {
            let p = e?.path();
            if p.is_dir() {
                stack.push(p);
            } else if is_fits_name(&p) {
                out.push(p);
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The outcome of classifying a set of files.
#[derive(Debug, Default)]
pub struct Scan {
    /// Polarimetric science frames.
    pub science: Vec<ScienceInfo>,
    /// Readable FITS files that are not polarimetric science (flats, darks, other
    /// instruments...), with the reason.
    pub other: Vec<Failure>,
    /// Files that could not be read.
    pub unreadable: Vec<Failure>,
}

/// Classify files by header (in parallel; the order of the result does not depend on it).
pub fn classify_all(files: &[PathBuf], profile: &Profile) -> Scan {
    use rayon::prelude::*;
    let results: Vec<(PathBuf, sofipol_calib::Result<Classification>)> = files
        .par_iter()
        .map(|f| (f.clone(), classify_file(f, profile)))
        .collect();
    let mut s = Scan::default();
    for (f, r) in results {
        match r {
            Ok(Classification::Science(info)) => s.science.push(*info),
            Ok(Classification::Rejected { reason }) => s.other.push(Failure {
                file: f.display().to_string(),
                error: reason,
            }),
            Err(e) => s.unreadable.push(Failure {
                file: f.display().to_string(),
                error: e.to_string(),
            }),
        }
    }
    s
}
