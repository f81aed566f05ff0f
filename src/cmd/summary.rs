//! The human summary shared by `target`, `night` and `demo`.
use sofipol_calib::text::printable;
use sofipol_pipeline::catalog::{Catalog, Flag, FlagCode, Status};

/// A component flag as the table shows it: `bad_pixels: k of n dithers dropped (...)` as
/// `bad_pixels(k/n)`, the others as the catalog writes them.
fn short_flag(f: &Flag) -> String {
    let counts = Some(f)
        .filter(|f| f.is(FlagCode::BadPixels))
        .and_then(|f| f.detail.as_deref())
        .and_then(|d| d.split_once(" dithers dropped"))
        .and_then(|(c, _)| c.split_once(" of "));
    match counts {
        Some((k, n)) => format!("{}({k}/{n})", FlagCode::BadPixels.name()),
        None => f.to_string(),
    }
}

/// A table of the catalog for a terminal: P is not debiased, Pdb debiased (the
/// catalog's `p_debiased`).
pub fn summary(cat: &Catalog) -> String {
    let mut s = String::new();
    if let Some(l) = uncalibrated_line(cat) {
        s += &l;
        s.push('\n');
    }
    s += &format!(
        "{:<16} {:<7} {:>4} {:>8} {:>8} {:>7} {:>7} {:>6} {:>5} {:>6}  {}\n",
        "object", "status", "comp", "P [%]", "Pdb [%]", "sig_P", "gamma", "sig_g", "cut", "dgamma", "flags"
    );
    for t in &cat.targets {
        let st = match t.status {
            Status::Ok => "ok",
            Status::Partial => "partial",
            Status::Failed => "FAILED",
        };
        if t.components.is_empty() {
            s += &format!(
                "{:<16} {:<7}  {}\n",
                printable(&t.object),
                st,
                printable(t.error.as_deref().unwrap_or(""))
            );
            continue;
        }
        for (i, c) in t.components.iter().enumerate() {
            let dg = match (i, t.delta_gamma_deg) {
                (0, Some(d)) => format!("{d:6.1}"),
                _ => "     -".into(),
            };
            s += &format!(
                "{:<16} {:<7} {:>4} {:>8.3} {:>8.3} {:>7.3} {:>7.1} {:>6.1} {:>5} {}  {}\n",
                if i == 0 { printable(&t.object) } else { "".into() },
                if i == 0 { st } else { "" },
                c.name,
                100.0 * c.p,
                100.0 * c.p_debiased,
                100.0 * c.sigma_p,
                c.gamma_deg,
                c.sigma_gamma_deg,
                if c.passes_cut { "pass" } else { "-" },
                dg,
                printable(&c.flags.iter().map(short_flag).collect::<Vec<_>>().join(","))
            );
        }
    }
    if !cat.failures.is_empty() {
        s += &format!("\n{} input(s) not used:\n", cat.failures.len());
        for f in &cat.failures {
            s += &format!("  {}: {}\n", printable(&f.file), printable(&f.error));
        }
    }
    s
}

/// The first line of a night's summary when components have no instrumental calibration:
/// how many, why it matters, and whether they pass the cut. `None` when all are calibrated.
pub fn uncalibrated_line(cat: &Catalog) -> Option<String> {
    let n = sofipol_pipeline::calibration::uncalibrated_components(cat);
    if n == 0 {
        return None;
    }
    let passing = cat
        .targets
        .iter()
        .flat_map(|t| &t.components)
        .filter(|c| c.passes_cut && sofipol_pipeline::calibration::is_uncalibrated(c))
        .count();
    Some(format!(
        "UNCALIBRATED: {n} component(s) have no instrumental calibration (no standards, or none that fix \
         the offset c; or the telescope's polarization neither removed nor carried): their q, u and angles \
         are biased; {}",
        if passing > 0 {
            format!("{passing} pass the cut only because of --allow-uncalibrated (flagged)")
        } else {
            "none passes the cut (observe standards, use --calib CALDIR, or --allow-uncalibrated)".to_string()
        }
    ))
}

/// Whether a night reduced with these settings must exit 2 for its calibration: some
/// component is uncalibrated and `--allow-uncalibrated` was not given.
pub fn uncalibrated_exit(cat: &Catalog, allowed: bool) -> bool {
    !allowed && sofipol_pipeline::calibration::uncalibrated_components(cat) > 0
}
