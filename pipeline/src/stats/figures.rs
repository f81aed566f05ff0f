//! Figures in the spirit of the reference study (Wolf et al. 2001): Pi(alpha) next to the
//! Pi(Delta gamma) it produces for models (a)-(d); Pi(Delta gamma) for the interstellar
//! polarization levels; the observed histograms of P_l and Delta gamma.
//!
//! Pi(Delta gamma) is drawn relative to the uniform law (flat = 1, i.e. density x 90 deg),
//! Pi(alpha) per unit solid angle relative to isotropy (flat = 1), both folded to [0, 90].
use std::path::Path;

use super::alignment::IsmComparison;
use super::format_p;
use super::hist::Histogram;
use super::mc::{simulate, McConfig, McOutput};
use super::model::AlignmentModel;
use super::sample::BinarySample;
use super::Result;
use crate::plots::{palette, sequential, Figure, LegendPos, Panel, Series, Style, DOUBLE_COLUMN_MM};

const DG: &str = "Δγ [deg]";
const PI_DG: &str = "Π(Δγ) / uniform";

/// The four models of the paper-style figure: (a) random, (b) and (c) von Mises-Fisher
/// spreads of 60 and 25 deg, (d) uniform inside a 30 deg cone.
pub fn paper_models() -> Vec<(String, AlignmentModel)> {
    vec![
        ("(a) random".into(), AlignmentModel::Random),
        ("(b) spread σ = 60°".into(), AlignmentModel::Spread { sigma_deg: 60.0 }),
        ("(c) spread σ = 25°".into(), AlignmentModel::Spread { sigma_deg: 25.0 }),
        ("(d) uniform, α ≤ 30°".into(), AlignmentModel::Cone { alpha0_deg: 30.0 }),
    ]
}

/// Relative density (uniform = 1) of a Delta-gamma histogram as a steps series.
fn relative_steps(label: &str, h: &Histogram) -> Series {
    let rel: Vec<f64> = h.density().iter().map(|d| d * (h.hi - h.lo)).collect();
    Series::steps(label, h.edges(), rel)
}

/// Relative density (uniform = 1) of a Delta-gamma histogram as a line through the bin
/// centres (for a dashed curve next to the steps of another histogram).
fn relative_line(label: &str, h: &Histogram) -> Series {
    let rel: Vec<f64> = h.density().iter().map(|d| d * (h.hi - h.lo)).collect();
    Series::line(label, h.centers(), rel)
}

fn uniform_line() -> Series {
    Series::line("uniform", vec![0.0, 90.0], vec![1.0, 1.0])
        .style(Style::Dashed(1))
        .color(palette(6))
        .unlabelled()
}

/// Pi(alpha) of `model` sampled on [0, 90] deg for plotting (None for perfect alignment).
fn pi_alpha_series(model: &AlignmentModel) -> Series {
    match model {
        AlignmentModel::Aligned => Series::line("Π(α): δ(α)", vec![0.0, 0.0], vec![0.0, 10.0]),
        _ => {
            let x: Vec<f64> = (0..=360).map(|i| 0.25 * i as f64).collect();
            let y = x.iter().map(|&a| model.pi_alpha_relative(a).unwrap_or(0.0)).collect();
            Series::line("Π(α)", x, y).unlabelled()
        }
    }
}

/// One row of the models figure: label, model, its simulated Pi(Delta gamma) and, if
/// the sample has measurement errors, the same convolved with them.
pub type ModelRow = (String, AlignmentModel, McOutput, Option<Histogram>);

/// Simulate `models` with the pairs, seed and bins of `base` (its model is replaced): rows
/// for [`models_figure`] without convolution.
pub fn simulate_models(models: &[(String, AlignmentModel)], base: &McConfig) -> Result<Vec<ModelRow>> {
    models
        .iter()
        .map(|(label, model)| {
            let mut cfg = base.clone();
            cfg.model = model.clone();
            Ok((label.clone(), model.clone(), simulate(&cfg)?, None))
        })
        .collect()
}

/// Models (a)-(d): Pi(alpha) (left) and the simulated Pi(Delta gamma) (right), one row each;
/// with a dashed curve of the prediction convolved with the measurement errors where given.
pub fn models_figure(path: &Path, rows: &[ModelRow], errors_note: Option<&str>) -> Result<()> {
    let mut panels = Vec::new();
    for (i, (label, model, out, convolved)) in rows.iter().enumerate() {
        let c = palette(i);
        panels.push(
            Panel::new(format!("{label}: Π(α)"), "α [deg]", "Π(α) per solid angle / isotropic")
                .x_range(0.0, 90.0)
                .with(pi_alpha_series(model).color(c))
                .legend(LegendPos::None),
        );
        let mut right = Panel::new(format!("{label}: Π(Δγ)"), DG, PI_DG)
            .x_range(0.0, 90.0)
            .with(uniform_line())
            .with(relative_steps("no errors", &out.histogram).color(c))
            .legend(LegendPos::None)
            .note(format!("{} pairs", format_count(out.accepted)));
        if let Some(h) = convolved {
            right = right.with(
                relative_line("with measured errors", h)
                    .color(c)
                    .style(Style::Dashed(2)),
            );
        }
        panels.push(right);
    }
    let title = "Alignment Π(α) and the projected position-angle difference Π(Δγ)";
    // Full page width, two panels of 90 mm per row (4 rows: 200 mm and the title).
    let fig = Figure::grid(
        Some(errors_note.map_or(title.to_string(), |n| format!("{title}; {n}"))),
        panels,
        2,
        DOUBLE_COLUMN_MM,
        50.0,
    );
    fig.save(path)?;
    Ok(())
}

/// Pi(Delta gamma) of random disks for each interstellar polarization level, with the
/// observed histogram (if any) as bars.
pub fn ism_figure(
    path: &Path,
    comparisons: &[IsmComparison],
    observed: &[f64],
    observed_bins: usize,
    subtitle: &str,
) -> Result<()> {
    let mut panel = Panel::new("Π(Δγ) of random disks + interstellar polarization", DG, PI_DG)
        .x_range(0.0, 90.0)
        .note(subtitle.to_string());
    if !observed.is_empty() {
        let (h, _) = Histogram::from_values(0.0, 90.0, observed_bins, observed);
        panel = panel.with(
            relative_steps(&format!("observed (n = {}, ±√N)", observed.len()), &h)
                .style(Style::Bars)
                .color(GREY),
        );
        let scale = observed_bins as f64 / observed.len() as f64;
        for s in poisson_bars(&h, scale) {
            panel = panel.with(s);
        }
    }
    panel = panel.with(uniform_line());
    let n = comparisons.len();
    for (i, c) in comparisons.iter().enumerate() {
        let h = c.mc.histogram.clone();
        // Thin 1-deg steps are noisy to the eye at 10^6 pairs: show 5-deg bins when possible.
        let h = if h.bins() % 18 == 0 {
            h.rebin(h.bins() / 18).unwrap_or(h)
        } else {
            h
        };
        let label = if observed.is_empty() {
            format!("Pᵢₛₘ = {} %", c.p_ism_percent)
        } else {
            format!("Pᵢₛₘ = {} % (KS p = {})", c.p_ism_percent, format_p(c.ks.p_value))
        };
        panel = panel.with(
            relative_steps(&label, &h)
                .color(level_color(i, n))
                .style(Style::Steps(2)),
        );
    }
    // Full page width: the legend of up to ten levels and the note sit side by side.
    Figure::grid(None, vec![panel], 1, DOUBLE_COLUMN_MM, 80.0).save(path)?;
    Ok(())
}

/// "a x 10^k" with a Unicode superscript exponent for round counts >= 10^4 (10⁷, 2×10⁶).
pub fn format_count(n: u64) -> String {
    if n < 10_000 {
        return n.to_string();
    }
    let mut k = 0;
    let mut m = n;
    while m % 10 == 0 {
        m /= 10;
        k += 1;
    }
    if m >= 10 || k < 4 {
        return n.to_string();
    }
    const SUP: [char; 10] = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
    let e: String = k
        .to_string()
        .chars()
        .map(|c| SUP[c.to_digit(10).unwrap() as usize])
        .collect();
    if m == 1 {
        format!("10{e}")
    } else {
        format!("{m}×10{e}")
    }
}

/// Distinct colours for levels: the Okabe-Ito palette (without black and yellow) up to 6
/// levels, Tableau 10 (grey replaced by navy: grey is the observed histogram, black the
/// uniform line) up to 10, the sequential ramp beyond.
fn level_color(i: usize, n: usize) -> crate::plots::Rgb {
    use crate::plots::Rgb;
    const T10: [Rgb; 10] = [
        Rgb(31, 119, 180),
        Rgb(255, 127, 14),
        Rgb(44, 160, 44),
        Rgb(214, 39, 40),
        Rgb(148, 103, 189),
        Rgb(140, 86, 75),
        Rgb(227, 119, 194),
        Rgb(0, 0, 128),
        Rgb(188, 189, 34),
        Rgb(23, 190, 207),
    ];
    if n <= 6 {
        palette(i)
    } else if n <= T10.len() {
        T10[i]
    } else {
        sequential(i, n)
    }
}

/// Poisson (sqrt N) error bars of a count histogram, scaled by `scale`, as vertical segments.
fn poisson_bars(h: &Histogram, scale: f64) -> Vec<Series> {
    h.centers()
        .iter()
        .zip(&h.counts)
        .filter(|(_, &c)| c > 0)
        .map(|(&x, &c)| {
            let (v, e) = (c as f64 * scale, (c as f64).sqrt() * scale);
            Series::line("", vec![x, x], vec![v - e, v + e])
                .color(crate::plots::Rgb(0, 0, 0))
                .style(Style::Line(1))
                .unlabelled()
        })
        .collect()
}

const GREY: crate::plots::Rgb = crate::plots::Rgb(120, 120, 120);

/// Observed histograms: P_l of the components (percent) and Delta gamma of the binaries.
/// `notes` are printed in panel B (e.g. the test results).
pub fn observed_figure(path: &Path, sample: &BinarySample, dg_bins: usize, notes: &[String]) -> Result<()> {
    let p = sample.p_percent();
    let pmax = p.iter().cloned().fold(0.0f64, f64::max).max(1.0).ceil();
    let p_bins = (pmax as usize).clamp(1, 40);
    let (hp, _) = Histogram::from_values(0.0, pmax, p_bins, &p);
    let dg = sample.delta_gamma_deg();
    let (hd, _) = Histogram::from_values(0.0, 90.0, dg_bins, &dg);
    let expected = dg.len() as f64 / dg_bins as f64;
    let to_f = |h: &Histogram| h.counts.iter().map(|&c| c as f64).collect::<Vec<_>>();
    let mut a = Panel::new(format!("[A] Pₗ of {} components", p.len()), "Pₗ (debiased) [%]", "N")
        .with(Series::bars("", hp.edges(), to_f(&hp)).unlabelled().color(palette(0)))
        .legend(LegendPos::None);
    a.integer_y = true;
    for s in poisson_bars(&hp, 1.0) {
        a = a.with(s);
    }
    let noun = if dg.len() == 1 { "binary" } else { "binaries" };
    let mut b = Panel::new(format!("[B] Δγ of {} {noun}", dg.len()), DG, "N")
        .x_range(0.0, 90.0)
        .with(Series::bars("observed (±√N)", hd.edges(), to_f(&hd)).color(palette(1)))
        .with(
            Series::line("random orientation", vec![0.0, 90.0], vec![expected, expected])
                .style(Style::Dashed(2))
                .color(palette(6)),
        );
    for s in poisson_bars(&hd, 1.0) {
        b = b.with(s);
    }
    b.integer_y = true;
    b.notes = notes.to_vec();
    if !notes.is_empty() {
        // Leave room above the bars for the notes.
        let top = hd
            .counts
            .iter()
            .map(|&c| c as f64 + (c as f64).sqrt())
            .fold(1.0, f64::max);
        // Room for the legend's two lines and the notes under it (a third of the panel).
        b = b.y_range(0.0, top * (1.3 + 0.1 * (notes.len() + 2) as f64));
    }
    let mut panels = vec![a, b];
    if sample
        .binaries
        .iter()
        .any(|b| b.sigma_delta_gamma_deg.is_some() || b.delta_gamma_interval_deg.is_some())
    {
        panels.push(error_bar_panel(sample));
    }
    // Full page width: two or three panels side by side.
    let cols = panels.len();
    Figure::grid(None, panels, cols, DOUBLE_COLUMN_MM, 70.0).save(path)?;
    Ok(())
}

/// The broad pale bar of a binary's 68.27 % interval in [C] (orange-tinted when large).
const INTERVAL_BAR: crate::plots::Rgb = crate::plots::Rgb(160, 200, 235);
const INTERVAL_BAR_LARGE: crate::plots::Rgb = crate::plots::Rgb(245, 195, 150);
/// Half-height of the end ticks of +-sigma in [C] for `n` binaries, in rows: 1.2 % of the
/// axis (about 0.6 mm in the printed panel), at most 0.3 of a row.
fn sigma_tick(n: usize) -> f64 {
    (0.012 * (n + 1) as f64).clamp(0.05, 0.3)
}

/// [C]: each binary's Delta gamma (sorted) with both of its errors: the catalog's central
/// 68.27 % interval as a broad pale bar, +-sigma (clipped to [0, 90]) as a thin line with
/// end ticks over it; orange where either is large.
fn error_bar_panel(sample: &BinarySample) -> Panel {
    let mut rows: Vec<_> = sample.binaries.iter().collect();
    rows.sort_by(|x, y| x.delta_gamma_deg.total_cmp(&y.delta_gamma_deg));
    let n = rows.len();
    let mut c = Panel::new(
        format!("[C] Δγ per binary: ±σ and 68 % interval (n = {n})"),
        DG,
        "binary (sorted by Δγ)",
    )
    .x_range(0.0, 90.0)
    // The top quarter holds the key (the notes below, wrapped to the panel's width).
    .y_range(0.0, (n as f64 + 1.0) * 1.35)
    .legend(LegendPos::None);
    c.integer_y = true;
    // Each row named by its object, so that a reader finds a binary without the table.
    c.y_names = rows.iter().map(|b| b.object.clone()).collect();
    let segment = |x: [f64; 2], y: [f64; 2], color, width| {
        Series::line("", x.to_vec(), y.to_vec())
            .color(color)
            .style(Style::Line(width))
            .unlabelled()
    };
    let tick = sigma_tick(n);
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for (k, b) in rows.iter().enumerate() {
        let y = k as f64 + 1.0;
        let dg = b.delta_gamma_deg;
        let large = super::errors::is_large(b.sigma_delta_gamma_deg, b.delta_gamma_interval_deg);
        if let Some([lo, hi]) = b.delta_gamma_interval_deg {
            let bar = if large { INTERVAL_BAR_LARGE } else { INTERVAL_BAR };
            c = c.with(segment([lo, hi], [y, y], bar, 5));
        }
        if let Some(s) = b.sigma_delta_gamma_deg.filter(|s| s.is_finite()) {
            let (lo, hi) = ((dg - s).max(0.0), (dg + s).min(90.0));
            let color = if large { palette(1) } else { crate::plots::Rgb(0, 0, 0) };
            c = c.with(segment([lo, hi], [y, y], color, 1));
            for x in [lo, hi] {
                c = c.with(segment([x, x], [y - tick, y + tick], color, 1));
            }
        }
        xs.push(dg);
        ys.push(y);
    }
    c.with(
        Series::line("", xs, ys)
            .color(palette(0))
            .style(Style::Points(3))
            .unlabelled(),
    )
    .note("pale bar: 68 % interval; |—|: ±σ")
    .note(format!(
        "orange: σ > {}° or interval > {}°",
        super::errors::LARGE_SIGMA_DEG,
        super::errors::LARGE_INTERVAL_DEG
    ))
}

/// Pi(Delta gamma) of one or more Monte-Carlo runs (the figure of `sofipol mc`).
pub fn mc_figure(path: &Path, runs: &[(String, McOutput)], title: &str) -> Result<()> {
    let mut panel = Panel::new(title, DG, PI_DG).x_range(0.0, 90.0).with(uniform_line());
    let n = runs.len();
    for (i, (label, out)) in runs.iter().enumerate() {
        let color = level_color(i, n);
        let label = label.replace("P_ism", "Pᵢₛₘ");
        panel = panel.with(
            relative_steps(&label, &out.histogram)
                .color(color)
                .style(Style::Steps(2)),
        );
    }
    if n == 1 {
        panel.legend = LegendPos::None;
    }
    if n <= 4 {
        Figure::single(panel).save(path)?;
    } else {
        // A legend of many levels: the full page width, and the top third of the axis kept
        // for it (the curves flatten to about 1 on its side).
        let top = panel
            .series
            .iter()
            .flat_map(|s| s.y.iter().copied())
            .filter(|v| v.is_finite())
            .fold(1.0, f64::max);
        panel = panel.y_range(0.0, 1.5 * top);
        Figure::grid(None, vec![panel], 1, DOUBLE_COLUMN_MM, 80.0).save(path)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::sample::SampleBinary;

    fn binary(object: &str, dg: f64, sigma: Option<f64>, interval: Option<[f64; 2]>) -> SampleBinary {
        SampleBinary {
            object: object.into(),
            delta_gamma_deg: dg,
            p_percent: [2.0, 3.0],
            sigma_p_percent: [0.1, 0.1],
            sigma_delta_gamma_deg: sigma,
            sigma_source: None,
            delta_gamma_interval_deg: interval,
            delta_gamma_fg_corrected_deg: None,
            foreground_percent: None,
        }
    }

    /// The horizontal segments of row `y` of panel [C]: (x from, x to, width).
    fn segments_at(p: &Panel, y: f64) -> Vec<(f64, f64, u32)> {
        p.series
            .iter()
            .filter_map(|s| match s.style {
                Style::Line(w) if s.y == [y, y] => Some((s.x[0], s.x[1], w)),
                _ => None,
            })
            .collect()
    }

    /// Panel [C] names each row by its binary (sorted by Delta-gamma), not 1..n: the names
    /// are the y tick labels of the drawn figure.
    #[test]
    fn panel_c_names_the_binaries() {
        let sample = BinarySample {
            binaries: vec![
                binary("HK Tau", 40.0, Some(3.0), Some([37.2, 43.1])),
                binary("V773 Tau", 4.0, Some(6.0), Some([1.5, 11.0])),
                binary("A very long binary name", 60.0, Some(2.0), None),
            ],
            excluded: vec![],
            warnings: vec![],
            all_sigma_p_percent: vec![],
        };
        let c = error_bar_panel(&sample);
        assert_eq!(c.y_names, ["V773 Tau", "HK Tau", "A very long binary name"]);
        let svg = crate::plots::Figure {
            title: None,
            panels: vec![c],
            cols: 1,
            width_mm: 100.0,
            panel_height_mm: 70.0,
        }
        .render_svg()
        .unwrap();
        let labels: Vec<&str> = svg
            .split("<text")
            .skip(1)
            .filter_map(|t| t.split('>').nth(1).and_then(|x| x.split('<').next()))
            .map(str::trim)
            .collect();
        for name in ["V773 Tau", "HK Tau", "A very long b…"] {
            assert!(labels.contains(&name), "{name} not among the labels {labels:?}");
        }
        // No row numbered instead.
        for k in ["1", "2", "3"] {
            assert!(!labels.contains(&k), "row number {k} drawn: {labels:?}");
        }
    }

    /// Panel [C] draws each binary's +-sigma and its 68 % interval, both: an asymmetric
    /// interval near the fold at 0 (where sigma says less) and one in the middle.
    #[test]
    fn panel_c_shows_sigma_and_the_interval_of_each_binary() {
        let sample = BinarySample {
            binaries: vec![
                binary("Middle", 40.0, Some(3.0), Some([37.2, 43.1])),
                binary("Near zero", 4.0, Some(6.0), Some([1.5, 11.0])),
                binary("Sigma only", 60.0, Some(2.0), None),
            ],
            excluded: vec![],
            warnings: vec![],
            all_sigma_p_percent: vec![],
        };
        let c = error_bar_panel(&sample);
        // Sorted by Delta-gamma: Near zero (row 1), Middle (2), Sigma only (3).
        let near = segments_at(&c, 1.0);
        assert!(near.contains(&(1.5, 11.0, 5)), "interval bar: {near:?}");
        assert!(near.contains(&(0.0, 10.0, 1)), "sigma clipped at 0: {near:?}");
        let middle = segments_at(&c, 2.0);
        assert!(middle.contains(&(37.2, 43.1, 5)), "{middle:?}");
        assert!(middle.contains(&(37.0, 43.0, 1)), "{middle:?}");
        let only = segments_at(&c, 3.0);
        assert_eq!(only, vec![(58.0, 62.0, 1)], "no interval: sigma alone");
        // The ends of +-sigma are ticked; the notes say what is drawn.
        let ticks = c
            .series
            .iter()
            .filter(|s| s.x.len() == 2 && s.x[0] == s.x[1] && s.y == [2.0 - sigma_tick(3), 2.0 + sigma_tick(3)])
            .count();
        assert_eq!(ticks, 2);
        assert!(
            c.notes.iter().any(|n| n.contains("68 % interval") && n.contains("±σ")),
            "{:?}",
            c.notes
        );
        // It renders.
        Figure::single(c).render_rgb().unwrap();
    }
}
