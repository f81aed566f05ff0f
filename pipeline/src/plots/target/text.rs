//! The text columns: numbers, wrapped lines, component, measurement and status blocks.
use super::*;

pub(super) fn finite(v: f64) -> bool {
    v.is_finite()
}

pub(super) fn fmt(v: f64, prec: usize) -> String {
    if v.is_finite() {
        format!("{v:.prec$}")
    } else {
        "—".into()
    }
}

pub(super) use crate::numeric::median_finite as median;

pub(super) fn status_word(s: Status) -> &'static str {
    match s {
        Status::Ok => "ok",
        Status::Partial => "partial",
        Status::Failed => "failed",
    }
}

pub(super) fn status_color(s: Status) -> RGBColor {
    match s {
        Status::Ok => RGBColor(0, 140, 70),
        Status::Partial => RGBColor(200, 120, 0),
        Status::Failed => RGBColor(200, 0, 0),
    }
}

/// One line of the text band.
#[derive(Clone)]
pub(super) struct Line {
    pub(super) text: String,
    pub(super) color: RGBColor,
    pub(super) bold: bool,
}

impl Line {
    fn plain(t: impl Into<String>) -> Self {
        Line {
            text: t.into(),
            color: BLACK,
            bold: false,
        }
    }
    fn head(t: impl Into<String>) -> Self {
        Line {
            text: t.into(),
            color: BLACK,
            bold: true,
        }
    }
    fn col(t: impl Into<String>, c: RGBColor) -> Self {
        Line {
            text: t.into(),
            color: c,
            bold: false,
        }
    }
}

/// Width of `t` in the figure's text font, px (as plotters lays it out, from the cached
/// glyphs).
pub(super) fn text_width(t: &str, bold: bool) -> u32 {
    crate::plots::glyphs::text_size(bold, TEXT_FONT as f64, t).0
}

/// Wrap `line` at word (or comma) boundaries to `width` px; continuation lines indented.
pub(super) fn wrap(line: Line, width: u32, out: &mut Vec<Line>) {
    if text_width(&line.text, line.bold) <= width {
        out.push(line);
        return;
    }
    let mut cur = String::new();
    for word in line.text.split_inclusive([' ', ',']) {
        let cand = format!("{cur}{word}");
        if !cur.trim().is_empty() && text_width(cand.trim_end(), line.bold) > width {
            out.push(Line {
                text: cur.trim_end().to_string(),
                ..line.clone()
            });
            cur = format!("    {word}");
        } else {
            cur = cand;
        }
        // A single word longer than the column: cut it by characters.
        while text_width(cur.trim_end(), line.bold) > width && cur.chars().count() > 8 {
            let mut head = String::new();
            for ch in cur.chars() {
                if text_width(&format!("{head}{ch}"), line.bold) > width {
                    break;
                }
                head.push(ch);
            }
            if head.trim().is_empty() {
                break;
            }
            let rest: String = cur.chars().skip(head.chars().count()).collect();
            out.push(Line {
                text: head,
                ..line.clone()
            });
            cur = format!("    {rest}");
        }
    }
    if !cur.trim().is_empty() {
        out.push(Line {
            text: cur.trim_end().to_string(),
            ..line
        });
    }
}

pub(super) fn component_lines(nums: &FigureNumbers, out: &mut Vec<Line>) {
    out.push(Line::head("Polarization (sky frame)"));
    if nums.components.is_empty() {
        out.push(Line::plain("no component measured"));
    }
    for (i, c) in nums.components.iter().enumerate() {
        let col = comp_color(i, false);
        let pct = |v: f64| fmt(100.0 * v, 2);
        out.push(Line::col(
            format!(
                "{}:  P = {} ± {} %    γ = {} ± {}°",
                c.name,
                pct(c.p),
                pct(c.sigma_p),
                fmt(c.gamma_deg, 1),
                fmt(c.sigma_gamma_deg, 1)
            ),
            col,
        ));
        let snr = c.p / c.sigma_p;
        out.push(Line::col(
            format!(
                "      P/σ = {}    P_deb = {} %    cut: {}",
                fmt(snr, 1),
                pct(c.p_debiased),
                if c.passes_cut { "passes" } else { "fails" }
            ),
            col,
        ));
        out.push(Line::col(
            format!(
                "      q = {} ± {} %,  u = {} ± {} %",
                pct(c.q),
                pct(c.sigma_q),
                pct(c.u),
                pct(c.sigma_u)
            ),
            col,
        ));
        if !c.flags.is_empty() {
            wrap(
                Line::col(format!("      flags: {}", join(&c.flags, ", ")), col),
                COL_W,
                out,
            );
        }
    }
    delta_gamma_lines(nums, out);
}

/// Delta-gamma with its error and its central 68 % interval (the catalog's
/// `sigma_delta_gamma_deg` and `delta_gamma_interval_deg`).
pub(super) fn delta_gamma_lines(nums: &FigureNumbers, out: &mut Vec<Line>) {
    let Some(d) = nums.delta_gamma_deg.filter(|d| d.is_finite()) else {
        out.push(Line::head("Δγ: — (needs two components passing the cut)"));
        return;
    };
    let sigma = nums
        .sigma_delta_gamma_deg
        .filter(|s| s.is_finite())
        .map_or(String::new(), |s| format!(" ± {s:.1}"));
    out.push(Line::head(format!("Δγ = |γA − γB| = {d:.1}{sigma}°")));
    if let Some([lo, hi]) = nums
        .delta_gamma_interval_deg
        .filter(|v| v.iter().all(|x| x.is_finite()))
    {
        out.push(Line::plain(format!("      68 % interval of Δγ: [{lo:.1}°, {hi:.1}°]")));
    }
}

pub(super) fn measurement_lines(
    target: &Target,
    ors: &[OrientationSketch],
    nums: &FigureNumbers,
    m: Option<&Measured>,
    out: &mut Vec<Line>,
) {
    let analyzer_deg = &nums.analyzer_deg;
    out.push(Line::head("Measurement"));
    let Some(m) = m else {
        out.push(Line::plain("no measurement"));
        return;
    };
    match m.geometry {
        Some((sep, pa)) => out.push(Line::plain(format!(
            "B from A: ρ = {}″, PA = {}°",
            fmt(sep, 3),
            fmt(pa, 1)
        ))),
        None => out.push(Line::plain("companion not found")),
    }
    out.push(Line::plain(format!(
        "FWHM {} px;  aperture r = {} px ({})",
        fmt(m.fwhm_px, 2),
        fmt(m.aperture_px, 2),
        m.photometry
    )));
    out.push(Line::plain(format!(
        "e − o offset: ({}, {}) px",
        fmt(m.eo_offset_px.0, 2),
        fmt(m.eo_offset_px.1, 2)
    )));
    if ors.iter().any(|o| o.posang_deg.is_finite()) {
        let pas: Vec<String> = ors.iter().map(|o| fmt(o.posang_deg, 1).to_string()).collect();
        let phis: Vec<String> = analyzer_deg.iter().map(|&phi| fmt(phi, 1).to_string()).collect();
        wrap(
            Line::plain(format!("POSANG {}°;  φ {}°", pas.join(", "), phis.join(", "))),
            COL_W,
            out,
        );
    }
    for (c, comp) in m.dithers.iter().enumerate() {
        let total: usize = comp.iter().map(|o| o.len()).sum();
        let used: usize = comp
            .iter()
            .flat_map(|o| o.iter())
            .filter(|d| d.rejected.is_none())
            .count();
        // Rejected dithers grouped by reason: "bad_pixels: 0°#3, 45°#3".
        let mut why: Vec<(String, Vec<String>)> = Vec::new();
        for (k, o) in comp.iter().enumerate() {
            for (i, d) in o.iter().enumerate() {
                if let Some(r) = &d.rejected {
                    let r = r.split(':').next_back().unwrap_or(r).trim().to_string();
                    let at = format!(
                        "{}°#{}",
                        ors.get(k)
                            .filter(|o| o.posang_deg.is_finite())
                            .map(|o| fmt(o.posang_deg, 0))
                            .unwrap_or(format!("{k}")),
                        i + 1
                    );
                    match why.iter_mut().find(|w| w.0 == r) {
                        Some(w) => w.1.push(at),
                        None => why.push((r, vec![at])),
                    }
                }
            }
        }
        let mut text = format!("{}: {used} of {total} dithers used", COMP_NAMES[c.min(1)]);
        if !why.is_empty() {
            let parts: Vec<String> = why.iter().map(|(r, v)| format!("{r} {}", v.join(" "))).collect();
            text += &format!("; rejected: {}", parts.join("; "));
        }
        wrap(Line::col(text, comp_color(c, false)), COL_W, out);
    }
    if !m.dithers.is_empty() {
        let grey = RGBColor(90, 90, 90);
        out.push(Line::col("F plots: ● used, red ○ rejected;", grey));
        let with_t = nums
            .components
            .iter()
            .any(|c| c.telescope_f.iter().any(Option::is_some));
        let model = if with_t {
            "dashed: model q cos2φ + u sin2φ + c + T, T the telescope's polarization at the orientation's parallactic angle (value above the panel); dotted: the model without T"
        } else {
            "dashed: model q cos2φ + u sin2φ + c (no telescope term)"
        };
        wrap(Line::col(format!("  {model}"), grey), COL_W, out);
    }
    if let Some(v) = &target.sequence {
        wrap(Line::plain(format!("sequence {v}")), COL_W, out);
    }
}

pub(super) fn status_lines(target: &Target, m: Option<&Measured>, out: &mut Vec<Line>) {
    out.push(Line {
        text: format!("Status: {}", status_word(target.status)),
        color: status_color(target.status),
        bold: true,
    });
    if let Some(e) = &target.error {
        wrap(
            Line::col(format!("error: {e}"), status_color(target.status)),
            COL_W,
            out,
        );
    }
    let mut flags: Vec<Flag> = m.map(|m| m.flags.clone()).unwrap_or_default();
    for f in target.target_flags() {
        if !flags.iter().any(|g| g == f) {
            flags.push(f.clone());
        }
    }
    if flags.is_empty() {
        out.push(Line::plain("target flags: none"));
    } else {
        out.push(Line::plain("target flags:"));
        for f in flags.iter().take(12) {
            wrap(Line::plain(format!("  • {f}")), COL_W, out);
        }
        if flags.len() > 12 {
            out.push(Line::plain(format!("  … and {} more", flags.len() - 12)));
        }
    }
}
