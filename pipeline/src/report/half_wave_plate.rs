//! The half-wave-plate targets' own results on the night's page (`Target.half_wave_plate`,
//! docs/instruments.md): the zero point and where it comes from, each complete cycle, the
//! cycles combined and the least squares, in the instrument frame and on the sky, how far
//! the cycles agree and the frames in no complete cycle. Nothing for a SOFI catalog.
use std::fmt::Write as _;

use super::markup::{escape, fmt, pct};
use crate::catalog::half_wave_plate::{Pol, FROM_CYCLES};
use crate::catalog::Catalog;

/// The section (nothing when no target has half-wave-plate results).
pub fn section(h: &mut String, cat: &Catalog) {
    let with: Vec<_> = cat
        .targets
        .iter()
        .filter_map(|t| t.half_wave_plate.as_ref().map(|hw| (t, hw)))
        .collect();
    if with.is_empty() {
        return;
    }
    h.push_str(
        "<section id=\"half-wave-plate\"><h2>Half-wave plate</h2>\n<p class=\"muted\">Each target's \
         complete plate cycles (0, 22.5, 45, 67.5 deg), their combination and the least squares over \
         every frame, in the instrument frame (zero point 0) and on the sky. The component in the \
         table above is the row marked ★. Errors of q and u: the larger of the propagated and the \
         cycle-to-cycle scatter; the angle's error here is statistical, the zero point's comes on top \
         of it (in σγ above).</p>\n",
    );
    for (t, hw) in with {
        let _ = writeln!(
            h,
            "<h3>{} {}</h3>\n<p>{} frame(s), {} complete cycle(s); profile {} ({}, {}); zero point {} ± {} deg: {}; \
             {} dark(s), {} sky frame(s), {} of them in the flat, {} bad pixels.</p>",
            escape(&t.object),
            escape(t.filter.as_deref().unwrap_or("")),
            hw.frames.len(),
            hw.cycles.len(),
            escape(&hw.profile),
            escape(&hw.modulation),
            escape(&hw.field_rotation),
            fmt(Some(hw.zero_point.deg), 1),
            fmt(Some(hw.zero_point.sigma_deg), 1),
            escape(&hw.zero_point.source),
            hw.darks.len(),
            hw.skies.len(),
            hw.flat_from.len(),
            hw.bad_pixels
        );
        h.push_str(
            "<div class=\"scroll\"><table class=\"hwp\"><thead><tr><th>result</th><th>frame</th><th>q [%]</th>\
             <th>u [%]</th><th>P [%]</th><th>angle [deg]</th><th>χ² / dof</th></tr></thead><tbody>\n",
        );
        let cycles_main = hw.component_from == FROM_CYCLES;
        let mut row = |what: &str, frame: &str, p: &Pol, chi2: String, main: bool| {
            let _ = writeln!(
                h,
                "<tr><td>{}{}</td><td>{frame}</td><td>{} ± {}</td><td>{} ± {}</td><td>{} ± {}</td><td>{} ± {}</td><td>{chi2}</td></tr>",
                escape(what),
                if main { " ★" } else { "" },
                pct(Some(p.q)),
                pct(Some(p.sigma_q)),
                pct(Some(p.u)),
                pct(Some(p.sigma_u)),
                pct(Some(p.p)),
                pct(Some(p.sigma_p)),
                fmt(Some(p.angle_deg), 1),
                fmt(Some(p.sigma_angle_deg), 1)
            );
        };
        let agreement = hw.cycle_agreement.as_ref().map_or_else(
            || "–".to_string(),
            |a| format!("q {}, u {} / {}", fmt(Some(a.chi2_q), 1), fmt(Some(a.chi2_u), 1), a.dof),
        );
        // The cycles are compared where the star stands still: on the sky when the field
        // turns (pupil tracking), else in the instrument frame.
        let on_sky = hw.field_rotation.starts_with("pupil_tracking");
        if let Some(p) = &hw.instrument {
            let chi2 = if on_sky { "–".to_string() } else { agreement.clone() };
            row("cycles combined", "instrument", p, chi2, false);
        }
        if let Some(p) = &hw.sky {
            let chi2 = if on_sky { agreement } else { "–".to_string() };
            row("cycles combined", "sky", p, chi2, cycles_main);
        }
        for (k, c) in hw.cycles.iter().enumerate() {
            row(
                &format!("cycle {}", k + 1),
                "instrument",
                &c.instrument,
                "–".into(),
                false,
            );
            row(&format!("cycle {}", k + 1), "sky", &c.sky, "–".into(), false);
        }
        for (frame, ls, main) in [
            ("instrument", &hw.least_squares_instrument, false),
            ("sky", &hw.least_squares_sky, !cycles_main),
        ] {
            if let Some(ls) = ls {
                let chi2 = format!("{} / {}", fmt(Some(ls.chi2), 1), ls.dof);
                row("least squares over the frames", frame, &ls.pol, chi2, main);
            }
        }
        h.push_str("</tbody></table></div>\n");
        if let Some(a) = &hw.cycle_agreement {
            let list = |v: &[f64]| v.iter().map(|x| fmt(Some(*x), 1)).collect::<Vec<_>>().join(", ");
            let _ = writeln!(
                h,
                "<p>Consecutive cycles differ by {} σ in q and {} σ in u (photometric errors, {}).</p>",
                list(&a.q_difference_sigma),
                list(&a.u_difference_sigma),
                if on_sky { "on the sky" } else { "instrument frame" }
            );
        }
        if !hw.left_out.is_empty() {
            let _ = writeln!(
                h,
                "<p>In no complete cycle (the least squares only): {}.</p>",
                escape(&hw.left_out.join(", "))
            );
        }
    }
    h.push_str("</section>\n");
}
