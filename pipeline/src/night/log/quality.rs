//! The night log's frame-quality table: every science frame of the targets and standards
//! in time order with its airmass, seeing, sky level and transparency, the night's medians,
//! and the frames whose seeing or transparency is an outlier marked.
use std::fmt::Write as _;

use crate::catalog::frame_quality::{night_frames, NightMedians, OUTLIER_SIGMA};
use crate::catalog::Catalog;

/// A number with `d` decimals, "-" when absent or not finite.
fn num(x: Option<f64>, d: usize) -> String {
    match x {
        Some(v) if v.is_finite() => format!("{v:.d$}"),
        _ => "-".into(),
    }
}

/// The UT time of day of an MJD, `hh:mm:ss` ("-" without one).
pub fn ut(mjd: Option<f64>) -> String {
    match mjd {
        Some(m) if m.is_finite() => {
            let s = (m.rem_euclid(1.0) * 86400.0).round() as u64 % 86400;
            format!("{:02}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
        }
        _ => "-".into(),
    }
}

/// Append the table to `s`; `shown` gives a frame's name as the log shows it. Nothing when
/// no target or standard has per-frame quality (a catalog written before it was kept).
pub fn quality_table(s: &mut String, cat: &Catalog, shown: &dyn Fn(&str) -> String) {
    let rows = night_frames(cat);
    if rows.is_empty() {
        return;
    }
    let m = NightMedians::of(rows.iter().map(|r| r.quality));
    let _ = writeln!(
        s,
        "\n## Frame quality: {} frames of the targets and standards\n",
        rows.len()
    );
    let _ = writeln!(
        s,
        "night medians: airmass {}, seeing {}\", sky {} ADU, transparency {}",
        num(m.airmass, 3),
        num(m.fwhm_arcsec, 2),
        num(m.sky_adu, 1),
        num(m.transparency, 3)
    );
    let _ = writeln!(
        s,
        "outliers (marked): seeing above {}\", transparency below {} (the median -+ {OUTLIER_SIGMA} robust sigma)\n\
         transparency: the star's o+e flux in the frame over its median over the sequence's frames\n",
        num(m.fwhm_limit_arcsec, 2),
        num(m.transparency_limit, 3)
    );
    let names: Vec<String> = rows.iter().map(|r| shown(&r.quality.file)).collect();
    let sources: Vec<String> = rows
        .iter()
        .map(|r| super::one_line(&format!("{}{}", r.source, if r.standard { " (std)" } else { "" })))
        .collect();
    let w = names.iter().map(|n| n.chars().count()).max().unwrap_or(5).max(5);
    let wt = sources.iter().map(|n| n.chars().count()).max().unwrap_or(6).max(6);
    let _ = writeln!(
        s,
        "{:<w$}  {:<wt$}  UT        AIRMASS  SEEING \"  SKY ADU   TRANSP.  OUTLIER",
        "FRAME", "TARGET"
    );
    for ((r, name), source) in rows.iter().zip(&names).zip(&sources) {
        let q = r.quality;
        let mark = m.outlier(q).words();
        let line = format!(
            "{name:<w$}  {source:<wt$}  {:<8}  {:>7}  {:>8}  {:>8}  {:>7}  {}",
            ut(q.mjd),
            num(q.airmass, 3),
            num(q.fwhm_arcsec, 2),
            num(q.sky_adu, 1),
            num(q.transparency, 3),
            if mark.is_empty() {
                String::new()
            } else {
                format!("* {mark}")
            }
        );
        let _ = writeln!(s, "{}", line.trim_end());
    }
}
