//! Finding and classifying input files.
use std::path::{Path, PathBuf};

use sofipol_calib::classify::{classify, Classification, ScienceInfo};
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
    /// Dome-flat frames (DPR TYPE 'FLAT' with a valid lamp keyword): calibration for the
    /// flat builder, not failures.
    pub dome_flats: Vec<PathBuf>,
}

/// Classify files by header (in parallel; the order of the result does not depend on it).
pub fn classify_all(files: &[PathBuf], profile: &Profile) -> Scan {
    use rayon::prelude::*;
    let results: Vec<(PathBuf, sofipol_calib::Result<(Classification, bool)>)> = files
        .par_iter()
        .map(|f| {
            let r = sofipol_calib::fits::read_header(f).map(|h| {
                let c = classify(&h, profile);
                // A rejected frame that is a dome flat goes to the flat builder; a flat with
                // a bad lamp keyword stays a failure with that reason.
                if let Classification::Rejected { .. } = &c {
                    match sofipol_calib::flat::dome_flat_info(&h, profile) {
                        Ok(Some(_)) => return (c, true),
                        Err(e) => return (Classification::Rejected { reason: e.to_string() }, false),
                        Ok(None) => {}
                    }
                }
                (c, false)
            });
            (f.clone(), r)
        })
        .collect();
    let mut s = Scan::default();
    for (f, r) in results {
        match r {
            Ok((_, true)) => s.dome_flats.push(f),
            Ok((Classification::Science(info), false)) => s.science.push(*info),
            Ok((Classification::Rejected { reason }, false)) => s.other.push(Failure {
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
