//! The night's observing conditions against time: seeing, sky level and transparency of
//! every science frame (one point each), coloured by target, the standards in grey, with
//! the night's median (dashed) and the outlier limits of the night log (dotted grey).
use super::{palette, Figure, LegendPos, Panel, Result, Rgb, Series, Style};
use crate::catalog::frame_quality::{NightFrame, NightMedians};

/// The standards' colour.
const STANDARD: Rgb = Rgb(110, 110, 110);
/// The median's and limits' colour.
const GUIDE: Rgb = Rgb(150, 150, 150);
/// Targets named in the legend at most; a night of more has no legend.
const MAX_LEGEND: usize = 10;

/// The figure of `rows` (the night's frames, [`crate::catalog::frame_quality::night_frames`]):
/// three panels stacked, x the UT hours from 0 h of the first frame's MJD day. `None` when
/// no frame has an MJD.
pub fn quality_figure(rows: &[NightFrame]) -> Option<Figure> {
    let day = rows
        .iter()
        .filter_map(|r| r.quality.mjd)
        .filter(|m| m.is_finite())
        .fold(f64::INFINITY, f64::min);
    if !day.is_finite() {
        return None;
    }
    let day = day.floor();
    let hours = |r: &NightFrame| r.quality.mjd.map_or(f64::NAN, |m| (m - day) * 24.0);
    let m = NightMedians::of(rows.iter().map(|r| r.quality));
    // Targets in order of first appearance, each its own colour; the standards as one.
    let mut sources: Vec<&str> = Vec::new();
    for r in rows.iter().filter(|r| !r.standard) {
        if !sources.contains(&r.source) {
            sources.push(r.source);
        }
    }
    let legend = sources.len() <= MAX_LEGEND;
    let xlabel = format!("UT [h] from MJD {day:.0} 0h");
    let panel = |title: &str, ylabel: &str, value: fn(&NightFrame) -> Option<f64>, guides: [Option<f64>; 2]| {
        let mut p = Panel::new(title, xlabel.as_str(), ylabel).legend(if legend {
            LegendPos::UpperRight
        } else {
            LegendPos::None
        });
        let points = |keep: &dyn Fn(&NightFrame) -> bool| -> (Vec<f64>, Vec<f64>) {
            rows.iter()
                .filter(|r| keep(r))
                .filter_map(|r| Some((hours(r), value(r)?)))
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .unzip()
        };
        let (x_all, y_all) = points(&|_| true);
        let (lo, hi) = x_all
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        for (i, s) in sources.iter().enumerate() {
            let (x, y) = points(&|r| !r.standard && r.source == *s);
            let series = Series::line(*s, x, y).style(Style::Points(4)).color(palette(i));
            p = p.with(if legend { series } else { series.unlabelled() });
        }
        let (x, y) = points(&|r| r.standard);
        if !x.is_empty() {
            p = p.with(Series::line("standards", x, y).style(Style::Points(4)).color(STANDARD));
        }
        if lo.is_finite() {
            for (k, g) in guides.iter().enumerate() {
                if let Some(g) = g.filter(|g| g.is_finite()) {
                    let style = if k == 0 { Style::Dashed(2) } else { Style::Dashed(1) };
                    p = p.with(
                        Series::line("", vec![lo, hi], vec![g, g])
                            .style(style)
                            .color(GUIDE)
                            .unlabelled(),
                    );
                }
            }
        }
        // The data's range with a margin (and the guides), not from 0: the changes show.
        let ys = y_all.iter().chain(guides.iter().flatten()).filter(|v| v.is_finite());
        let (ylo, yhi) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        if ylo.is_finite() {
            let pad = (0.1 * (yhi - ylo)).max(0.02 * yhi.abs()).max(1e-6);
            p = p.y_range(ylo - pad, yhi + 2.5 * pad);
        }
        if lo.is_finite() {
            let pad = (0.03 * (hi - lo)).max(0.05);
            p = p.x_range(lo - pad, hi + pad);
        }
        if !legend {
            p = p.note(format!(
                "{} targets, one colour each (cycled); standards grey",
                sources.len()
            ));
        }
        p
    };
    let panels = vec![
        panel(
            "Seeing (FWHM of the star's PSF fit)",
            "FWHM [arcsec]",
            |r| r.quality.fwhm_arcsec,
            [m.fwhm_arcsec, m.fwhm_limit_arcsec],
        ),
        panel("Sky level", "sky [ADU]", |r| r.quality.sky_adu, [m.sky_adu, None]),
        panel(
            "Transparency (star's o+e flux / its sequence's median)",
            "transparency",
            |r| r.quality.transparency,
            [m.transparency, m.transparency_limit],
        ),
    ];
    Some(Figure::grid(None, panels, 1, super::DOUBLE_COLUMN_MM, 55.0))
}

/// [`quality_figure`] as PNG bytes (`None`: no frame has an MJD).
pub fn quality_png(rows: &[NightFrame]) -> Result<Option<Vec<u8>>> {
    quality_figure(rows).map(|f| f.render_png()).transpose()
}
