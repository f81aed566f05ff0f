//! The page: head (inline CSS, the self-test hook), summary, targets table, per-target
//! figures, calibration and statistics (`sections.rs`), provenance, inline script.
use std::fmt::Write as _;

use super::markup::{escape, flag_list, fmt, image, pct, status_word};
use super::ReportInput;
use crate::catalog::Flag;
use crate::catalog::{Catalog, Component, Status, Target};

const CSS: &str = include_str!("page.css");
const SCRIPT: &str = include_str!("page.js");
const SELFTEST: &str = include_str!("selftest.js");

/// Nothing is fetched: images are `data:` URIs, style and scripts inline.
const CSP: &str = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'";

/// The whole page.
pub fn render(input: &ReportInput) -> String {
    let cat = &input.catalog;
    let mut h = String::with_capacity(64 * 1024);
    let title = format!("sofipol night report: {}", input.catalog_path);
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n\
         <meta http-equiv=\"Content-Security-Policy\" content=\"{CSP}\">\n<title>{}</title>\n\
         <style>\n{CSS}</style>\n<script id=\"sofipol-selftest\">\n{SELFTEST}</script>\n</head>\n<body>\n",
        escape(&title)
    );
    let _ = write!(
        h,
        "<header><h1>Night report</h1><p class=\"muted\">catalog <code>{}</code></p>\n\
         <nav><a href=\"#summary\">Summary</a><a href=\"#targets-section\">Targets</a>\
         <a href=\"#figures\">Figures</a><a href=\"#quality\">Quality</a><a href=\"#calibration\">Calibration</a>\
         <a href=\"#statistics\">Statistics</a><a href=\"#provenance\">Provenance</a></nav></header>\n<main>\n",
        escape(&input.catalog_path)
    );
    summary(&mut h, cat);
    targets_table(&mut h, cat);
    foreground_table(&mut h, cat);
    super::half_wave_plate::section(&mut h, cat);
    target_figures(&mut h, input);
    super::quality::quality(&mut h, cat, input.quality_figure.as_ref());
    super::sections::calibration(&mut h, cat);
    super::sections::statistics(&mut h, &input.stats);
    provenance(&mut h, input);
    let _ = write!(
        h,
        "</main>\n<pre id=\"selftest\" hidden></pre>\n<script>\n{SCRIPT}</script>\n</body>\n</html>\n"
    );
    h
}

/// The class of a summary count: its status colour when there is any, none at zero (a red
/// "0 failed" reads as an alarm).
fn count_class(n: usize, class: &str) -> String {
    if n > 0 {
        format!(" class=\"{class}\"")
    } else {
        String::new()
    }
}

fn summary(h: &mut String, cat: &Catalog) {
    let count = |s: Status| cat.targets.iter().filter(|t| t.status == s).count();
    let (ok, partial, failed) = (count(Status::Ok), count(Status::Partial), count(Status::Failed));
    let _ = write!(
        h,
        "<section id=\"summary\"><h2>Summary</h2>\n<ul class=\"counts\">\
         <li>{} targets</li><li{}>{} ok</li><li{}>{} partial</li>\
         <li{}>{} failed</li><li{}>{} inputs not used</li></ul>\n",
        cat.targets.len(),
        count_class(ok, "st-ok"),
        ok,
        count_class(partial, "st-partial"),
        partial,
        count_class(failed, "st-failed"),
        failed,
        count_class(cat.failures.len(), "st-partial"),
        cat.failures.len()
    );
    let uncalibrated = crate::calibration::uncalibrated_components(cat);
    if uncalibrated > 0 {
        let _ = writeln!(
            h,
            "<p class=\"uncalibrated\" id=\"uncalibrated\"><strong>UNCALIBRATED</strong>: {uncalibrated} \
             component(s) have no instrumental calibration (no standards, none that fix the offset c, or \
             the telescope's polarization neither removed nor carried: see their flags): \
             their q, u and angles are biased, they never pass the cut unless reduced with \
             <code>--allow-uncalibrated</code>, and the statistics leave their binaries out.</p>"
        );
    }
    let troubled: Vec<&Target> = cat.targets.iter().filter(|t| t.status != Status::Ok).collect();
    if !troubled.is_empty() {
        h.push_str("<h3>Targets not fully reduced</h3>\n<ul>\n");
        for t in troubled {
            let _ = writeln!(
                h,
                "<li><span class=\"st-{s}\">{s}</span> <strong>{}</strong>: {}</li>",
                escape(&t.object),
                escape(t.error.as_deref().unwrap_or("(no message)")),
                s = status_word(t.status)
            );
        }
        h.push_str("</ul>\n");
    }
    if cat.targets.is_empty() {
        h.push_str("<p>The catalog has no targets.</p>\n");
    }
    if cat.failures.is_empty() {
        h.push_str("<p>Every input was used.</p>\n");
    } else {
        h.push_str("<h3>Inputs not used</h3>\n<div class=\"scroll\"><table id=\"failures\"><thead><tr><th>file</th><th>why</th></tr></thead><tbody>\n");
        for f in &cat.failures {
            let _ = writeln!(
                h,
                "<tr><td><code>{}</code></td><td class=\"prose\">{}</td></tr>",
                escape(&f.file),
                escape(&f.error)
            );
        }
        h.push_str("</tbody></table></div>\n");
    }
    h.push_str("</section>\n");
}

/// Columns of the targets table: key (for the self-test and the CSS), header, numeric.
const COLUMNS: [(&str, &str, bool); 14] = [
    ("target", "Target", false),
    ("status", "Status", false),
    ("comp", "Comp.", false),
    ("p", "P [%]", true),
    ("sigma_p", "σP [%]", true),
    ("gamma", "γ [deg]", true),
    ("sigma_gamma", "σγ [deg]", true),
    ("snr", "P/σ", true),
    ("cut", "Cut", false),
    ("dgamma", "Δγ [deg]", true),
    ("sigma_dgamma", "σΔγ [deg]", true),
    ("mag", "Mag", true),
    ("filter", "Filter", false),
    ("flags", "Flags", false),
];

fn targets_table(h: &mut String, cat: &Catalog) {
    h.push_str(
        "<section id=\"targets-section\"><h2>Targets and components</h2>\n\
         <p class=\"muted\">One row per component. Click a column header to sort (again to reverse); \
         P is debiased, γ east of north, Δγ = |γA − γB| folded into [0°, 90°] when both components pass the P/σ cut; \
         Mag from the night's photometric zero-point (Calibration), – without one.</p>\n\
         <div class=\"controls\"><label><input type=\"checkbox\" id=\"hide-failed\"> hide failed targets</label>\
         <label>filter <input type=\"search\" id=\"filter\" placeholder=\"object, flag, status…\"></label>\
         <span id=\"shown\" class=\"muted\"></span></div>\n\
         <div class=\"scroll\"><table id=\"targets\"><thead><tr>",
    );
    for (key, label, numeric) in COLUMNS {
        let _ = write!(
            h,
            "<th data-key=\"{key}\"{}><button type=\"button\">{label}</button></th>",
            if numeric {
                " data-type=\"num\" class=\"num\""
            } else {
                ""
            }
        );
    }
    h.push_str("</tr></thead>\n<tbody>\n");
    for t in &cat.targets {
        if t.components.is_empty() {
            target_row(h, t, None);
        }
        for c in &t.components {
            target_row(h, t, Some(c));
        }
    }
    h.push_str("</tbody></table></div>\n");
    if cat.targets.is_empty() {
        h.push_str("<p>No targets.</p>\n");
    }
    h.push_str("</section>\n");
}

/// The start of the targets table's cell of column `col`: its header as `data-label` (the
/// phone's card layout shows it before the value) and its attributes.
fn open_cell(h: &mut String, col: usize, attrs: &str) {
    let _ = write!(h, "<td data-label=\"{}\"{attrs}>", COLUMNS[col].1);
}

/// A numeric cell of column `col`: the shown text and the raw value (`data-v`) it sorts by.
fn num_cell(h: &mut String, col: usize, shown: String, value: Option<f64>) {
    let v = value.filter(|v| v.is_finite()).map_or(String::new(), |v| v.to_string());
    open_cell(h, col, &format!(" class=\"num\" data-v=\"{v}\""));
    let _ = write!(h, "{shown}</td>");
}

/// A text cell of column `col` (`text` already escaped), with its class if any.
fn text_cell(h: &mut String, col: usize, class: &str, text: &str) {
    let attrs = if class.is_empty() {
        String::new()
    } else {
        format!(" class=\"{class}\"")
    };
    open_cell(h, col, &attrs);
    let _ = write!(h, "{text}</td>");
}

fn target_row(h: &mut String, t: &Target, c: Option<&Component>) {
    let st = status_word(t.status);
    let _ = write!(
        h,
        "<tr data-status=\"{st}\" data-target=\"{}\" data-comp=\"{}\">",
        escape(&t.object),
        escape(c.map_or("", |c| &c.name)),
    );
    let object = format!(
        "<strong>{}</strong><br><span class=\"muted\">{}</span>",
        escape(&t.object),
        escape(t.tpl_start.as_deref().unwrap_or(""))
    );
    text_cell(h, 0, "obj", &object);
    text_cell(h, 1, &format!("st-{st}"), st);
    text_cell(h, 2, "", &escape(c.map_or("–", |c| &c.name)));
    let p = c.map(|c| c.p_debiased);
    num_cell(h, 3, pct(p), p.map(|v| 100.0 * v));
    let sp = c.map(|c| c.sigma_p);
    num_cell(h, 4, pct(sp), sp.map(|v| 100.0 * v));
    let g = c.map(|c| c.gamma_deg);
    num_cell(h, 5, fmt(g, 1), g);
    let sg = c.map(|c| c.sigma_gamma_deg);
    num_cell(h, 6, fmt(sg, 1), sg);
    let snr = c.map(|c| c.snr.unwrap_or(c.p / c.sigma_p));
    num_cell(h, 7, fmt(snr, 1), snr);
    let cut = match c {
        Some(c) if c.passes_cut => "pass",
        Some(_) => "fail",
        None => "–",
    };
    text_cell(h, 8, "", cut);
    num_cell(h, 9, fmt(t.delta_gamma_deg, 1), t.delta_gamma_deg);
    num_cell(h, 10, fmt(t.sigma_delta_gamma_deg, 1), t.sigma_delta_gamma_deg);
    let mag = c.and_then(|c| c.mag);
    let shown = match (mag, c.and_then(|c| c.sigma_mag)) {
        (Some(m), Some(s)) => format!("{} ± {}", fmt(Some(m), 2), fmt(Some(s), 2)),
        _ => "–".into(),
    };
    num_cell(h, 11, shown, mag);
    text_cell(h, 12, "", &escape(t.filter.as_deref().unwrap_or("")));
    let mut all: Vec<&Flag> = t.target_flags().iter().collect();
    if let Some(c) = c {
        all.extend(&c.flags);
    }
    open_cell(h, 13, " class=\"flags-cell\"");
    if let (None, Some(e)) = (c, &t.error) {
        let _ = write!(h, "<span class=\"st-failed\">{}</span>", escape(e));
    }
    flag_list(h, &all);
    h.push_str("</td></tr>\n");
}

/// The targets with an interstellar foreground: the foreground, its field stars, and
/// Delta-gamma before and after subtracting it (nothing when no target has one).
fn foreground_table(h: &mut String, cat: &Catalog) {
    let with: Vec<&Target> = cat.targets.iter().filter(|t| t.foreground.is_some()).collect();
    let too_few: Vec<String> = cat
        .targets
        .iter()
        .filter(|t| {
            t.target_flags()
                .iter()
                .any(|f| f.is(crate::catalog::FlagCode::ForegroundTooFewFieldStars))
        })
        .map(|t| escape(&t.object))
        .collect();
    if with.is_empty() && too_few.is_empty() {
        return;
    }
    h.push_str(
        "<section id=\"foreground\"><h2>Interstellar foreground</h2>\n<p class=\"muted\">The foreground \
         (q, u) at each target from its field stars, subtracted from both components; Δγ after: the \
         foreground's error is common to both stars and included in σ (docs/polarimetry.md).</p>\n\
         <div class=\"scroll\"><table id=\"foreground-table\"><thead><tr><th>target</th><th>q<sub>fg</sub> [%]</th>\
         <th>u<sub>fg</sub> [%]</th><th>field stars used</th><th>rejected</th><th>Δγ [deg]</th>\
         <th>Δγ after [deg]</th><th>68 % interval after [deg]</th><th>source</th></tr></thead><tbody>\n",
    );
    for t in with {
        let f = t.foreground.as_ref().expect("filtered");
        let interval = t.delta_gamma_fg_corrected_interval_deg.map_or_else(
            || "–".to_string(),
            |[lo, hi]| format!("{} – {}", fmt(Some(lo), 1), fmt(Some(hi), 1)),
        );
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{} ± {}</td><td>{} ± {}</td><td>{}</td><td>{}</td><td>{} ± {}</td><td>{} ± {}</td><td>{}</td><td>{}</td></tr>",
            escape(&t.object),
            pct(Some(f.q)),
            pct(Some(f.sigma_q)),
            pct(Some(f.u)),
            pct(Some(f.sigma_u)),
            f.n_used.map_or_else(|| "–".to_string(), |n| n.to_string()),
            f.rejected.len(),
            fmt(t.delta_gamma_deg, 1),
            fmt(t.sigma_delta_gamma_deg, 1),
            fmt(t.delta_gamma_fg_corrected_deg, 1),
            fmt(t.sigma_delta_gamma_fg_corrected_deg, 1),
            interval,
            escape(f.source.as_deref().unwrap_or("–")),
        );
    }
    h.push_str("</tbody></table></div>\n");
    if !too_few.is_empty() {
        let _ = writeln!(
            h,
            "<p>Too few usable field stars for a foreground (not subtracted): {}.</p>",
            too_few.join(", ")
        );
    }
    h.push_str("</section>\n");
}

fn target_figures(h: &mut String, input: &ReportInput) {
    h.push_str("<section id=\"figures\"><h2>Per-target figures</h2>\n");
    let Some(dir) = &input.figures_dir else {
        h.push_str("<p>None: the night was reduced without figures (<code>--no-png</code>).</p>\n</section>\n");
        return;
    };
    let _ = writeln!(
        h,
        "<p class=\"muted\">From <code>{}</code>; click a figure to open its PNG file at full size.</p>",
        escape(dir)
    );
    if input.target_figures.is_empty() {
        h.push_str("<p>No per-target figures were found (the night was reduced with <code>--no-png</code>, or its products folder is elsewhere: <code>sofipol report --figures DIR</code>).</p>\n");
    } else {
        h.push_str("<div class=\"grid\">\n");
        for t in &input.catalog.targets {
            let id = t.sequence_id();
            if let Some(f) = input.target_figures.get(id) {
                image(h, &format!("{} ({})", t.object, id), &f.png, Some(&f.href));
            }
        }
        h.push_str("</div>\n");
        let missing: Vec<String> = input
            .catalog
            .targets
            .iter()
            .filter(|t| !input.target_figures.contains_key(t.sequence_id()))
            .map(|t| escape(&t.object))
            .collect();
        if !missing.is_empty() {
            let _ = writeln!(h, "<p>No figure for: {}.</p>", missing.join(", "));
        }
    }
    h.push_str("</section>\n");
}

fn provenance(h: &mut String, input: &ReportInput) {
    let p = &input.catalog.provenance;
    let values = |v: Vec<String>| if v.is_empty() { "–".to_string() } else { v.join(" ") };
    let words = |v: &Option<Vec<String>>| v.as_ref().map_or_else(|| "–".to_string(), |w| w.join(" "));
    h.push_str("<section id=\"provenance\"><h2>Provenance</h2>\n<dl class=\"kv\">\n");
    let rows = [
        ("catalog", input.catalog_path.clone()),
        ("schema version", input.catalog.schema_version.clone()),
        ("reduced with", values(p.softwares())),
        ("its commit", values(p.commits())),
        ("reduced (UTC)", p.created_utc.clone().unwrap_or_else(|| "–".into())),
        ("its command line", words(&p.command_line)),
        ("inputs", words(&p.inputs)),
        (
            "page written by",
            format!(
                "sofipol {} (commit {})",
                env!("CARGO_PKG_VERSION"),
                crate::build_info::commit()
            ),
        ),
        ("page command line", input.command_line.clone()),
    ];
    for (k, v) in rows {
        let _ = writeln!(h, "<dt>{k}</dt><dd><code>{}</code></dd>", escape(&v));
    }
    h.push_str("</dl>\n");
    if !p.is_empty() {
        let json = serde_json::to_string_pretty(p).unwrap_or_default();
        let _ = writeln!(
            h,
            "<details><summary>The catalog's whole provenance (JSON)</summary><pre>{}</pre></details>",
            escape(&json)
        );
    }
    h.push_str("</section>\n");
}
