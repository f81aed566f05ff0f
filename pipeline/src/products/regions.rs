//! DS9 region files: per frame, both components in both beams with the photometry aperture
//! and the sky annulus, where the reduction measured them. Load one onto its raw frame (or
//! its sky-subtracted intermediate) in DS9: `ds9 SOFI_0001.fits -regions SOFI_0001.reg`.
//!
//! Format: DS9 version 4.1, `image` coordinates (1-based: the centre of the first pixel is
//! (1, 1); sofipol's positions are 0-based pixel centres on the detector, so 1 is added to
//! both). Colours: A green, B cyan (solid circle: the aperture; dashed annulus: the sky);
//! a dither left out of a component's F is drawn red with the reason. Tag `o` / `e` names
//! the beam, so DS9's region groups select them.
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::ProductError;
use crate::reduce::run::TargetOutcome;
use crate::reduce::{MeasureParams, Measured};

/// One region file: where it goes (a name relative to the products folder) and its text.
#[derive(Debug, Clone, PartialEq)]
pub struct RegionFile {
    /// `<frame name without .fits/.fit/.gz/.fz>.reg`.
    pub name: String,
    /// The file's text.
    pub text: String,
}

/// The region files of a reduced target: one per frame measured (none when the target
/// failed before its measurement).
pub fn target_regions(out: &TargetOutcome, params: &MeasureParams, software: &str) -> Vec<RegionFile> {
    let Some(m) = &out.measured else {
        return Vec::new();
    };
    let mut files = Vec::new();
    for (k, frames) in out.frame_files.iter().enumerate() {
        for (d, frame) in frames.iter().enumerate() {
            files.push(RegionFile {
                name: format!("{}.reg", frame_stem(frame)),
                text: frame_regions(
                    m,
                    k,
                    d,
                    out.row_offset,
                    params,
                    &header(software, &out.target.object, frame),
                ),
            });
        }
    }
    files
}

/// Write `files` into `dir` (created), each atomically; every file's outcome.
pub fn write_regions(dir: &Path, files: &[RegionFile]) -> Vec<(PathBuf, Result<(), ProductError>)> {
    if let Err(source) = std::fs::create_dir_all(dir) {
        let path = dir.to_path_buf();
        return vec![(path.clone(), Err(ProductError::Io { path, source }))];
    }
    files
        .iter()
        .map(|f| {
            let p = dir.join(&f.name);
            let r = crate::io::write_atomic(&p, f.text.as_bytes()).map_err(|source| ProductError::Write {
                path: p.clone(),
                source,
            });
            (p, r)
        })
        .collect()
}

/// A frame's name without its FITS and compression extensions.
fn frame_stem(frame: &Path) -> String {
    let name = frame
        .file_name()
        .map_or_else(|| "frame".into(), |n| n.to_string_lossy().into_owned());
    let mut stem = name.as_str();
    for ext in [".gz", ".fz", ".fits", ".fit", ".fts"] {
        stem = stem.strip_suffix(ext).unwrap_or(stem);
    }
    stem.to_string()
}

fn header(software: &str, object: &str, frame: &Path) -> String {
    let clean = |s: &str| sofipol_calib::text::printable(&s.replace(['\n', '\r'], " ")).into_owned();
    format!(
        "# Region file format: DS9 version 4.1\n# {} : {} on {}\n",
        clean(software),
        clean(object),
        clean(&frame.display().to_string())
    )
}

/// The regions of dither `d` of orientation `k`: per component and beam, the aperture
/// (radius `m.aperture_px`) and the sky annulus (`params.annulus_fwhm` x `m.fwhm_px`).
fn frame_regions(m: &Measured, k: usize, d: usize, row_offset: usize, params: &MeasureParams, head: &str) -> String {
    let mut s = String::from(head);
    s.push_str(
        "global color=green dashlist=8 3 width=1 font=\"helvetica 10 normal roman\" select=1 \
         highlite=1 dash=0 fixed=0 edit=1 move=1 delete=1 include=1 source=1\nimage\n",
    );
    let r_ap = m.aperture_px;
    let (r_in, r_out) = params.annulus_px(m.fwhm_px);
    for (c, per_orient) in m.dithers.iter().enumerate() {
        let Some(dv) = per_orient.get(k).and_then(|o| o.get(d)) else {
            continue;
        };
        let name = if c == 0 { "A" } else { "B" };
        let (colour, note) = match &dv.rejected {
            Some(why) => ("red", format!(" left out: {why}")),
            None => (if c == 0 { "green" } else { "cyan" }, String::new()),
        };
        for (beam, b) in [("o", &dv.o), ("e", &dv.e)] {
            let (x, y) = b.xy;
            if !(x.is_finite() && y.is_finite()) {
                continue;
            }
            // 0-based detector pixel centres -> DS9's 1-based image coordinates.
            let (x, y) = (x + 1.0, y + row_offset as f64 + 1.0);
            let _ = writeln!(
                s,
                "circle({x:.3},{y:.3},{r_ap:.3}) # color={colour} text={{{name} {beam}{note}}} tag={{{beam}}} tag={{{name}}}"
            );
            if r_out > r_in && r_in > 0.0 {
                let _ = writeln!(
                    s,
                    "annulus({x:.3},{y:.3},{r_in:.3},{r_out:.3}) # color={colour} dash=1 tag={{{beam}}} tag={{{name}}}"
                );
            }
        }
    }
    s
}

#[cfg(test)]
mod tests;
