//! The calibration and statistics sections of the page.
use std::fmt::Write as _;

use super::markup::{escape, flag_list, fmt, image, pct, sequence_id, status_word};
use super::StatsSection;
use crate::catalog::polarimetric_calibration::FilterCalibration;
use crate::catalog::{Catalog, Provenance};
use crate::stats::format_p;
use crate::stats::predictions::source_name;

/// "x ± s" with `d` decimals.
fn pm(x: Option<f64>, s: Option<f64>, d: usize) -> String {
    format!("{} ± {}", fmt(x, d), fmt(s, d))
}

/// Flats, the calibration per filter (c, theta0, parity, the telescope's polarization),
/// the standards with their residuals, and the telescope's polarization removed from each
/// target over the night.
pub fn calibration(h: &mut String, cat: &Catalog) {
    h.push_str("<section id=\"calibration\"><h2>Calibration</h2>\n");
    flats(h, &cat.provenance);
    match &cat.calibration {
        None => h.push_str("<p>No instrumental calibration was applied (no standards, or <code>--no-calibration</code>): the components are flagged <code>uncalibrated</code>.</p>\n"),
        Some(cal) => {
            let _ = writeln!(
                h,
                "<p>Calibration from: <strong>{}</strong>{}.</p>",
                escape(cal.source.as_deref().unwrap_or("–")),
                cal.stokes_method.as_ref().map_or(String::new(), |m| format!("; Stokes method {}", escape(m)))
            );
            h.push_str("<div class=\"scroll\"><table id=\"calibration-filters\"><thead><tr><th>filter</th><th class=\"num\">offset c</th>\
                <th class=\"num\">θ₀ [deg]</th><th class=\"num\">parity</th><th class=\"num\">p_tel [%]</th><th class=\"num\">ψ_tel [deg]</th>\
                <th>standards</th><th>notes</th></tr></thead><tbody>\n");
            for f in cal.calibration().into_iter().flat_map(|c| &c.filters) {
                filter_row(h, f);
            }
            h.push_str("</tbody></table></div>\n");
        }
    }
    standards(h, cat);
    photometry(h, cat);
    telescope_over_night(h, cat);
    h.push_str("</section>\n");
}

/// One filter's row of the calibration table.
fn filter_row(h: &mut String, f: &FilterCalibration) {
    let notes: Vec<String> = [
        ("incomplete", &f.incomplete),
        (
            "telescope from the mirror's prior (the standards alone did not separate it)",
            &f.telescope_from_prior,
        ),
        ("telescope_uncorrected", &f.telescope_uncorrected),
    ]
    .into_iter()
    .filter_map(|(k, t)| t.as_ref().map(|t| format!("{k}: {}", escape(t))))
    .collect();
    let (o, a, t) = (f.offset.as_ref(), f.angles.as_ref(), f.telescope.as_ref());
    let _ = writeln!(
        h,
        "<tr><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td>\
         <td class=\"num\">{} ± {}</td><td class=\"num\">{}</td><td>{} for c, {} for θ₀</td><td class=\"prose\">{}</td></tr>",
        escape(&f.filter),
        pm(o.map(|o| o.c), o.map(|o| o.sigma_c), 5),
        pm(a.map(|a| a.theta0_deg), a.map(|a| a.sigma_theta0_deg), 2),
        a.map_or_else(|| "–".into(), |a| a.parity.to_string()),
        pct(t.map(|t| t.p_tel)),
        pct(t.map(|t| t.sigma_p_tel)),
        pm(t.map(|t| t.psi_tel_deg), t.map(|t| t.sigma_psi_tel_deg), 1),
        f.offset_standards.len(),
        f.angle_standards.len(),
        notes.join("; ")
    );
}

fn flats(h: &mut String, prov: &Provenance) {
    let _ = writeln!(
        h,
        "<h3>Flats</h3>\n<p>Mode: <strong>{}</strong>.</p>",
        escape(prov.flat_mode())
    );
    let list = prov.flat_list();
    if list.is_empty() {
        return;
    }
    h.push_str("<div class=\"scroll\"><table id=\"flats\"><thead><tr><th>kind</th><th>filter</th><th class=\"num\">POSANG [deg]</th>\
        <th class=\"num\">frames</th><th class=\"num\">bad pixels</th><th>detail</th></tr></thead><tbody>\n");
    for f in list {
        let detail = if f.detail.is_empty() {
            f.file.as_deref().unwrap_or("")
        } else {
            &f.detail
        };
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"prose\">{}</td></tr>",
            escape(&f.kind),
            escape(f.filter.as_deref().unwrap_or("")),
            fmt(f.posang_deg, 1),
            f.frames.len(),
            f.bad_pixels,
            escape(detail)
        );
    }
    h.push_str("</tbody></table></div>\n");
}

fn standards(h: &mut String, cat: &Catalog) {
    h.push_str("<h3>Standard stars</h3>\n");
    if cat.standards.is_empty() {
        h.push_str("<p>No standard star in this catalog.</p>\n");
        return;
    }
    h.push_str("<div class=\"scroll\"><table id=\"standards\"><thead><tr><th>star</th><th>status</th><th>filter</th>\
        <th class=\"num\">P [%]</th><th class=\"num\">γ [deg]</th><th class=\"num\">table P [%]</th><th class=\"num\">table γ [deg]</th>\
        <th class=\"num\">ΔP [σ]</th><th class=\"num\">Δγ [deg]</th><th class=\"num\">χ²(q,u=0)</th><th>used for</th><th>flags</th></tr></thead><tbody>\n");
    for s in &cat.standards {
        let m = s.measured.as_ref();
        let t = s.table.as_ref();
        let _ = write!(
            h,
            "<tr><td><strong>{}</strong><br><span class=\"muted seq\">{}</span></td><td class=\"st-{st}\">{st}</td><td>{}</td>\
             <td class=\"num\">{} ± {}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td>\
             <td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td>{}</td><td>",
            escape(&s.name),
            sequence_id(&s.sequence),
            escape(&s.filter),
            pct(m.map(|c| c.p)),
            pct(m.map(|c| c.sigma_p)),
            pm(m.map(|c| c.gamma_deg), m.map(|c| c.sigma_gamma_deg), 1),
            pct(t.map(|t| t.p)),
            fmt(t.map(|t| t.gamma_deg), 1),
            fmt(s.residual_p_sigma, 2),
            fmt(s.residual_gamma_deg, 1),
            fmt(s.residual_qu_chi2, 2),
            escape(&s.used_for.join(", ")),
            st = status_word(s.status)
        );
        let all: Vec<&crate::catalog::Flag> = s.flags.iter().collect();
        flag_list(h, &all);
        h.push_str("</td></tr>\n");
    }
    h.push_str("</tbody></table></div>\n");
}

/// The photometric zero-point per filter and the standards it came from, or why the
/// components have no magnitude (one line).
fn photometry(h: &mut String, cat: &Catalog) {
    h.push_str("<h3>Photometric zero-point</h3>\n");
    let lines = cat.calibration.as_ref().map_or_else(
        || vec!["no magnitudes: no calibration (fluxes in ADU only)".to_string()],
        |c| c.photometry_lines(),
    );
    let zps = cat
        .calibration
        .as_ref()
        .and_then(|c| c.photometry.as_ref())
        .map(|p| &p.filters[..])
        .unwrap_or_default();
    if !zps.is_empty() {
        h.push_str(
            "<div class=\"scroll\"><table id=\"photometry\"><thead><tr><th>filter</th><th>standard</th>\
            <th class=\"num\">table mag</th><th class=\"num\">rate [ADU/s]</th><th class=\"num\">airmass</th>\
            <th class=\"num\">ZP [mag]</th></tr></thead><tbody>\n",
        );
        for z in zps {
            for s in &z.standards {
                let _ = writeln!(
                    h,
                    "<tr><td>{}</td><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
                    escape(&z.filter),
                    escape(&s.name),
                    pm(Some(s.mag), Some(s.sigma_mag), 3),
                    pm(Some(s.rate_adu_per_s), Some(s.sigma_rate_adu_per_s), 1),
                    fmt(s.airmass, 3),
                    pm(Some(s.zero_point_mag), Some(s.sigma_zero_point_mag), 3)
                );
            }
        }
        h.push_str("</tbody></table></div>\n");
    }
    h.push_str("<ul>\n");
    for l in lines {
        let _ = writeln!(h, "<li>{}</li>", escape(&l));
    }
    h.push_str("</ul>\n");
}

/// The telescope's polarization removed from each target (component A's `telescope_qu`, sky
/// frame at the mean parallactic angle of its frames), in the order of the night.
fn telescope_over_night(h: &mut String, cat: &Catalog) {
    let mut rows: Vec<(&str, &str, [f64; 2])> = cat
        .targets
        .iter()
        .filter_map(|t| {
            let qu = t.components.iter().find_map(|c| c.telescope_qu)?;
            Some((t.tpl_start.as_deref().unwrap_or(""), t.object.as_str(), qu))
        })
        .collect();
    h.push_str("<h3>Telescope polarization over the night</h3>\n");
    if rows.is_empty() {
        h.push_str("<p>The telescope's polarization was not removed from any target.</p>\n");
        return;
    }
    rows.sort_by(|a, b| a.0.cmp(b.0));
    h.push_str("<div class=\"scroll\"><table id=\"telescope\"><thead><tr><th>start</th><th>target</th><th class=\"num\">q_tel [%]</th>\
        <th class=\"num\">u_tel [%]</th><th class=\"num\">p_tel [%]</th><th class=\"num\">angle [deg]</th></tr></thead><tbody>\n");
    for (start, object, [q, u]) in rows {
        let angle = (0.5 * u.atan2(q).to_degrees()).rem_euclid(180.0);
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
            escape(start),
            escape(object),
            fmt(Some(100.0 * q), 3),
            fmt(Some(100.0 * u), 3),
            fmt(Some(100.0 * q.hypot(u)), 3),
            fmt(Some(angle), 1)
        );
    }
    h.push_str("</tbody></table></div>\n");
}

/// The verdict, the tests, the comparisons with the models and the ISM levels, the figures.
pub fn statistics(h: &mut String, stats: &crate::error::Result<StatsSection>) {
    h.push_str("<section id=\"statistics\"><h2>Alignment statistics (Δγ)</h2>\n");
    let s = match stats {
        Err(e) => {
            let _ = writeln!(
                h,
                "<p>The statistics could not be computed: {}</p>\n</section>",
                escape(&e.to_string())
            );
            return;
        }
        Ok(s) => s,
    };
    let r = &s.report;
    for w in &s.sample.warnings {
        let _ = writeln!(h, "<p class=\"warning\">{}</p>", escape(w));
    }
    let _ = writeln!(
        h,
        "<p>Sample: {} binaries with both components above the cut; {} targets excluded. \
         As <code>sofipol stats</code> computes them (Monte Carlo: {}).</p>\n<div class=\"verdict\" id=\"verdict\">{}</div>",
        s.sample.len(),
        s.sample.excluded.len(),
        escape(&r.mc_description),
        escape(&r.verdict)
    );
    if let (Some(ks), Some(kp), Some(bt)) = (&r.ks_uniform, &r.kuiper_uniform, &r.below_threshold) {
        let _ = writeln!(
            h,
            "<ul><li>KS against uniform: D = {:.3}, p = {}</li><li>Kuiper against uniform: V = {:.3}, p = {}</li>\
             <li>{} of {} below {}°: binomial p = {}</li><li>mean Δγ = {}°</li></ul>",
            ks.statistic,
            escape(&format_p(ks.p_value)),
            kp.statistic,
            escape(&format_p(kp.p_value)),
            bt.k,
            bt.n,
            r.threshold_deg,
            escape(&format_p(bt.p_greater)),
            fmt(r.mean_delta_gamma_deg, 1)
        );
    }
    for f in &s.figures {
        image(h, &f.caption, &f.png, f.href.as_deref());
    }
    if !r.models.is_empty() {
        h.push_str("<h3>Against the alignment models</h3>\n<div class=\"scroll\"><table id=\"models\"><thead><tr><th>model</th>\
            <th class=\"num\">mean Δγ [deg]</th><th class=\"num\">fraction &lt; 30°</th><th class=\"num\">KS p</th>\
            <th class=\"num\">KS p with errors</th></tr></thead><tbody>\n");
        for m in &r.models {
            let w = m.with_errors.as_ref().map(|c| &c.prediction);
            let _ = writeln!(
                h,
                "<tr><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
                escape(&m.label),
                fmt(Some(m.prediction.mean_deg), 1),
                fmt(Some(m.prediction.fraction_below_threshold), 3),
                escape(&format_p(m.prediction.ks.p_value)),
                w.map_or("–".into(), |p| escape(&format_p(p.ks.p_value)))
            );
        }
        h.push_str("</tbody></table></div>\n");
    }
    if !r.ism.is_empty() {
        let _ = writeln!(
            h,
            "<h3>Against random disks with interstellar polarization</h3>\n<p class=\"muted\">{}</p>\
             <div class=\"scroll\"><table id=\"ism\"><thead><tr><th class=\"num\">P_ism [%]</th><th class=\"num\">fraction &lt; 30°</th>\
             <th class=\"num\">KS D</th><th class=\"num\">KS p</th><th class=\"num\">own p</th></tr></thead><tbody>",
            escape(&s.mc)
        );
        for c in r.ism.iter().chain(&r.own_foreground) {
            let level = match &c.foreground {
                Some(f) => format!("own: {f}"),
                None => c.p_ism_percent.to_string(),
            };
            let _ = writeln!(
                h,
                "<tr><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
                escape(&level),
                fmt(Some(c.mc_fraction_below_threshold), 3),
                fmt(Some(c.ks.statistic), 3),
                escape(&format_p(c.ks.p_value)),
                c.per_binary.as_ref().map_or("–".into(), |t| escape(&format_p(t.p_value)))
            );
        }
        h.push_str("</tbody></table></div>\n");
    }
    if !s.sample.binaries.is_empty() {
        h.push_str("<h3>Δγ per binary</h3>\n<div class=\"scroll\"><table id=\"sample\"><thead><tr><th>object</th><th class=\"num\">Δγ [deg]</th>\
            <th class=\"num\">σ [deg]</th><th class=\"num\">68 % interval [deg]</th><th>error from</th></tr></thead><tbody>\n");
        for b in &s.sample.binaries {
            let _ = writeln!(
                h,
                "<tr><td>{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td>{}</td></tr>",
                escape(&b.object),
                fmt(Some(b.delta_gamma_deg), 1),
                fmt(b.sigma_delta_gamma_deg, 1),
                b.delta_gamma_interval_deg
                    .map_or("–".into(), |[lo, hi]| format!("[{lo:.1}, {hi:.1}]")),
                escape(source_name(b.sigma_source))
            );
        }
        h.push_str("</tbody></table></div>\n");
    }
    if !s.sample.excluded.is_empty() {
        h.push_str("<h3>Excluded from the sample</h3>\n<ul>\n");
        for e in &s.sample.excluded {
            let _ = writeln!(
                h,
                "<li><strong>{}</strong>: {}</li>",
                escape(&e.object),
                escape(&e.reason)
            );
        }
        h.push_str("</ul>\n");
    }
    h.push_str("</section>\n");
}
