//! The statistics figures are sized for a journal column: measured on the written files
//! (PNG pixels and SVG text), not compared with snapshots.
//!
//! Printed widths: a single column is 88 mm, the full page 180 mm (docs/statistics.md,
//! "Figures"). A figure without a physical width (a unitless SVG, a PNG without pHYs) is
//! measured as if printed on a single column, as an observer would place it.
use std::path::Path;

use plotters::prelude::*;
use plotters::style::FontStyle;
use sofipol_pipeline::plots::{Figure, Panel};
use sofipol_pipeline::stats::figures::{mc_figure, models_figure, paper_models, simulate_models};
use sofipol_pipeline::stats::{simulate, AlignmentModel, McConfig};

const COLUMN_MM: [f64; 2] = [88.0, 180.0];
const MM_PER_PT: f64 = 25.4 / 72.0;

fn register_font() {
    // The same DejaVu Sans the figures use (registering twice is harmless).
    plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular()).ok();
    plotters::style::register_font("sans-serif", FontStyle::Bold, dejavu::sans::bold()).ok();
}

/// Width of `text` in pixels for a font of `em_px` pixels per em (DejaVu's line height is
/// (1901 + 483) / 2048 em, the scale `ab_glyph` takes).
fn text_width(text: &str, em_px: f64, bold: bool) -> f64 {
    register_font();
    let style = if bold { FontStyle::Bold } else { FontStyle::Normal };
    let font = ("sans-serif", em_px * 2384.0 / 2048.0).into_font().style(style);
    f64::from(font.box_size(text).unwrap().0)
}

fn attr(tag: &str, name: &str) -> Option<String> {
    let key = format!(" {name}=\"");
    let start = tag.find(&key)? + key.len();
    Some(tag[start..].split('"').next()?.to_string())
}

fn unescape(s: &str) -> String {
    s.replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&quot;", "\"")
        .replace("&apos;", "'")
        .replace("&amp;", "&")
}

/// One `<text>` of an SVG.
#[derive(Debug)]
struct SvgText {
    text: String,
    x: f64,
    size: f64,
    anchor: String,
    bold: bool,
    rotated: bool,
}

/// (viewBox width, printed width in mm, texts).
fn svg_texts(svg: &str) -> (f64, f64, Vec<SvgText>) {
    let head = &svg[svg.find("<svg").unwrap()..];
    let head = &head[..head.find('>').unwrap()];
    let view_w: f64 = attr(head, "viewBox")
        .unwrap()
        .split_whitespace()
        .nth(2)
        .unwrap()
        .parse()
        .unwrap();
    let width = attr(head, "width").unwrap();
    let printed_mm = match width.strip_suffix("mm") {
        Some(mm) => mm.parse().unwrap(),
        None => COLUMN_MM[0],
    };
    let texts = svg
        .split("<text")
        .skip(1)
        .map(|t| {
            let (tag, rest) = t.split_once('>').unwrap();
            SvgText {
                text: unescape(rest.split("</text>").next().unwrap().trim()),
                x: attr(tag, "x").unwrap().parse().unwrap(),
                size: attr(tag, "font-size").unwrap().parse().unwrap(),
                anchor: attr(tag, "text-anchor").unwrap_or_default(),
                bold: attr(tag, "font-weight").is_some_and(|w| w == "bold"),
                rotated: attr(tag, "transform").is_some(),
            }
        })
        .collect();
    (view_w, printed_mm, texts)
}

/// Small Monte-Carlo rows of the models figure.
fn model_rows() -> Vec<sofipol_pipeline::stats::figures::ModelRow> {
    simulate_models(&paper_models(), &McConfig::geometry(AlignmentModel::Random, 20_000, 7)).unwrap()
}

const ERRORS_NOTE: &str = "dashed: convolved with the measured errors of 12 binaries (median σ(Δγ) = 4.2°)";

/// Every figure the statistics write, as SVG: (name, document).
fn stats_svgs(dir: &Path) -> Vec<(String, String)> {
    let rows = model_rows();
    models_figure(&dir.join("models.svg"), &rows, Some(ERRORS_NOTE)).unwrap();
    let runs: Vec<(String, _)> = [0.5, 1.0, 2.0]
        .iter()
        .map(|&p| {
            let mut cfg = McConfig::geometry(AlignmentModel::Random, 20_000, 3);
            cfg.ism = Some(sofipol_pipeline::stats::Ism {
                p_percent: p,
                angle_deg: 0.0,
            });
            (format!("P_ism = {p} %"), simulate(&cfg).unwrap())
        })
        .collect();
    mc_figure(
        &dir.join("pi_delta_gamma.svg"),
        &runs,
        "Π(Δγ), 2×10⁴ pairs, random disks, Pᵢₙₜ sin²i (max 6 %)",
    )
    .unwrap();
    ["models.svg", "pi_delta_gamma.svg"]
        .iter()
        .map(|n| (n.to_string(), std::fs::read_to_string(dir.join(n)).unwrap()))
        .collect()
}

/// The models figure's title (and every other centred text) lies inside the image: its
/// extent, measured with the figure's own font, fits between the borders.
#[test]
fn models_figure_title_is_not_clipped() {
    let dir = tempfile::tempdir().unwrap();
    for (name, svg) in stats_svgs(dir.path()) {
        let (w, _, texts) = svg_texts(&svg);
        let title_words = texts
            .iter()
            .filter(|t| t.text.contains("Alignment") || t.text.contains("convolved"));
        if name == "models.svg" {
            assert!(title_words.count() >= 1, "no title in {name}");
        }
        for t in texts.iter().filter(|t| !t.rotated && !t.text.is_empty()) {
            let width = text_width(&t.text, t.size, t.bold);
            let (left, right) = match t.anchor.as_str() {
                "middle" => (t.x - width / 2.0, t.x + width / 2.0),
                "end" => (t.x - width, t.x),
                _ => (t.x, t.x + width),
            };
            assert!(
                left >= 0.0 && right <= w,
                "{name}: '{}' spans {left:.0} .. {right:.0} px of a {w} px wide figure",
                t.text
            );
        }
    }
    // The PNG: no ink in the outermost columns (a clipped title leaves its glyphs there).
    let png = dir.path().join("models.png");
    models_figure(&png, &model_rows(), Some(ERRORS_NOTE)).unwrap();
    let img = image::open(&png).unwrap().to_rgb8();
    let (w, h) = img.dimensions();
    for x in [0, 1, 2, w - 3, w - 2, w - 1] {
        let ink = (0..h)
            .filter(|&y| img.get_pixel(x, y).0.iter().any(|&c| c < 200))
            .count();
        assert_eq!(ink, 0, "column {x} of models.png ({w} x {h}) has {ink} dark pixels");
    }
}

/// Printed at the figure's column width, every text of the statistics figures is at least
/// 7 pt and the axis labels and titles at least 8 pt (SVG font sizes).
#[test]
fn svg_text_is_at_least_7_pt_at_the_column_width() {
    let dir = tempfile::tempdir().unwrap();
    for (name, svg) in stats_svgs(dir.path()) {
        let (w, printed_mm, texts) = svg_texts(&svg);
        let pt_per_unit = printed_mm / MM_PER_PT / w;
        assert!(!texts.is_empty());
        for t in &texts {
            let pt = t.size * pt_per_unit;
            let is_label = t.text.contains("[deg]") || t.text.contains("uniform") || t.text.contains("Π(");
            let min = if is_label { 8.0 } else { 7.0 };
            // 0.01 pt: the printed width is whole pixels at 300 dpi (180 mm = 2126 px).
            assert!(
                pt >= min - 0.01,
                "{name}: '{}' is {pt:.2} pt at {printed_mm} mm (font-size {} of {w})",
                t.text,
                t.size
            );
        }
        assert!(
            COLUMN_MM.iter().any(|&c| (printed_mm - c).abs() < 0.5),
            "{name}: printed width {printed_mm} mm"
        );
        let head = &svg[svg.find("<svg").unwrap()..];
        assert!(
            attr(&head[..head.find('>').unwrap()], "width").unwrap().ends_with("mm"),
            "{name}: the SVG states its printed width in mm"
        );
    }
}

/// The dpi written into a PNG (pHYs chunk, pixels per metre), if any.
fn png_dpi(bytes: &[u8]) -> Option<f64> {
    let at = bytes.windows(4).position(|w| w == b"pHYs")? + 4;
    let ppm_x = u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap());
    let ppm_y = u32::from_be_bytes(bytes[at + 4..at + 8].try_into().unwrap());
    assert_eq!(ppm_x, ppm_y, "square pixels");
    assert_eq!(bytes[at + 8], 1, "unit: metre");
    Some(f64::from(ppm_x) * 0.0254)
}

/// The PNGs carry their resolution, and pixels / dpi is the documented column width.
#[test]
fn png_pixel_size_and_dpi_give_the_column_width() {
    let dir = tempfile::tempdir().unwrap();
    let models = dir.path().join("models.png");
    models_figure(&models, &model_rows(), None).unwrap();
    let single = dir.path().join("pi.png");
    let run = simulate(&McConfig::geometry(AlignmentModel::Random, 10_000, 1)).unwrap();
    mc_figure(&single, &[("random".into(), run)], "Π(Δγ)").unwrap();
    for (path, column_mm) in [(&models, 180.0), (&single, 88.0)] {
        let bytes = std::fs::read(path).unwrap();
        let dpi = png_dpi(&bytes).unwrap_or_else(|| panic!("{}: no pHYs chunk (no dpi)", path.display()));
        assert!((dpi - 300.0).abs() < 0.5, "{}: {dpi} dpi", path.display());
        let w = image::open(path).unwrap().width();
        let mm = f64::from(w) / dpi * 25.4;
        assert!(
            (mm - column_mm).abs() < 0.3,
            "{}: {w} px at {dpi} dpi = {mm:.1} mm",
            path.display()
        );
    }
}

/// An empty single-column panel (ticks only) rendered to RGB: (width, height, pixels).
fn empty_panel() -> (u32, u32, Vec<u8>) {
    let panel = Panel::new("", "", "").x_range(0.0, 90.0).y_range(0.0, 1.0);
    Figure::single(panel).render_rgb().unwrap()
}

fn px(rgb: &[u8], w: u32, x: u32, y: u32) -> [u8; 3] {
    let i = 3 * (y * w + x) as usize;
    [rgb[i], rgb[i + 1], rgb[i + 2]]
}

/// The y axis (the column with most dark pixels) and the x axis (the row with most).
fn axes(w: u32, h: u32, rgb: &[u8]) -> (u32, u32) {
    let dark = |p: [u8; 3]| p.iter().all(|&c| c < 100);
    let col = (0..w)
        .max_by_key(|&x| (0..h).filter(|&y| dark(px(rgb, w, x, y))).count())
        .unwrap();
    let row = (0..h)
        .max_by_key(|&y| (0..w).filter(|&x| dark(px(rgb, w, x, y))).count())
        .unwrap();
    (col, row)
}

/// The PNG's tick labels, measured in pixels: the digits' ink height is 0.73 em in DejaVu
/// Sans (0.76 em with the overshoot of "0", used here: the smaller em), at the printed width
/// of a single column (the single-panel figures' width) at least 7 pt.
#[test]
fn png_tick_labels_are_at_least_7_pt_at_the_column_width() {
    let (w, h, rgb) = empty_panel();
    let (axis_x, axis_y) = axes(w, h, &rgb);
    // Rows with ink left of the y axis, above the label "0" (which meets the x labels).
    let limit = axis_y - h / 20;
    let ink_rows: Vec<u32> = (0..limit)
        .filter(|&y| (0..axis_x.saturating_sub(4)).any(|x| px(&rgb, w, x, y).iter().any(|&c| c < 128)))
        .collect();
    let mut runs = Vec::new();
    let mut start = None;
    for (i, &y) in ink_rows.iter().enumerate() {
        start.get_or_insert(y);
        if ink_rows.get(i + 1) != Some(&(y + 1)) {
            runs.push(y + 1 - start.take().unwrap());
        }
    }
    assert!(runs.len() >= 4, "tick labels found: {runs:?}");
    let digit_px = f64::from(*runs.iter().max().unwrap());
    let em_px = digit_px / 0.76;
    let pt = em_px / f64::from(w) * COLUMN_MM[0] / MM_PER_PT;
    assert!(
        pt >= 7.0,
        "tick digits {digit_px} px high in {w} px: {pt:.2} pt at 88 mm"
    );
}

/// No minor grid: a row through the empty plot area crosses only the major grid lines (one
/// per labelled tick, about ten), and they are light.
#[test]
fn no_minor_grid_and_a_light_major_grid() {
    let (w, h, rgb) = empty_panel();
    let (axis_x, axis_y) = axes(w, h, &rgb);
    // Halfway between two y grid lines near the middle: a row of the empty plot area.
    let y = axis_y / 2 + h / 50;
    let mut lines = 0;
    let mut inside = false;
    for x in axis_x + 4..w - 4 {
        let p = px(&rgb, w, x, y);
        let drawn = p.iter().any(|&c| c < 250);
        if drawn && !inside {
            lines += 1;
            assert!(p.iter().all(|&c| c >= 190), "grid line at x = {x} too dark: {p:?}");
        }
        inside = drawn;
    }
    assert!((1..=12).contains(&lines), "{lines} vertical lines cross the plot area");
}
