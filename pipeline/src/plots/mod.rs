//! PNG figures: a small, reusable plotting API on top of `plotters` (bitmap backend, no
//! system fonts: DejaVu Sans is embedded through the `dejavu` crate).
//!
//! A [`Figure`] is a grid of [`Panel`]s; a panel holds [`Series`] drawn as lines, steps
//! (histogram outlines) or filled bars, with an optional legend. Files are written
//! atomically (temporary file in the same directory, then rename): a reader never sees a
//! half-written PNG. Convenience wrappers: [`histogram_png`], [`line_png`].
//!
//! ```no_run
//! use sofipol_pipeline::plots::{Figure, Panel, Series};
//! let edges: Vec<f64> = (0..=9).map(|i| 10.0 * i as f64).collect();
//! let panel = Panel::new("Observed", "Δγ [deg]", "N")
//!     .with(Series::bars("34 binaries", edges, vec![9.0, 7.0, 5.0, 4.0, 3.0, 2.0, 2.0, 1.0, 1.0]));
//! Figure::single(panel).save_png(std::path::Path::new("dg.png")).unwrap();
//! ```
use std::path::Path;
use std::sync::OnceLock;

use plotters::prelude::*;
use plotters::style::FontStyle;

pub mod glyphs;
pub mod quality;
pub mod target;

/// Errors of the plotting module (defined with the crate's other errors).
pub use crate::error::PlotError as Error;

/// Result of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// The family name the embedded font is registered under.
const FONT: &str = "sans-serif";

fn ensure_font() -> Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok()
            && plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold()).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(Error::Font)
    }
}

/// The PNG encoder of every figure: fast deflate and the Paeth filter on every row (the
/// adaptive choice per row costs a quarter more time for 6 % smaller files).
pub fn png_encoder<W: std::io::Write>(w: W) -> image::codecs::png::PngEncoder<W> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    PngEncoder::new_with_quality(w, CompressionType::Fast, FilterType::Paeth)
}

/// An RGB colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rgb(pub u8, pub u8, pub u8);

impl Rgb {
    fn to_plotters(self) -> RGBColor {
        RGBColor(self.0, self.1, self.2)
    }
}

/// Qualitative colours (Okabe & Ito 2008, colour-blind safe), cycled by index.
pub fn palette(i: usize) -> Rgb {
    const P: [Rgb; 8] = [
        Rgb(0, 114, 178),
        Rgb(213, 94, 0),
        Rgb(0, 158, 115),
        Rgb(204, 121, 167),
        Rgb(230, 159, 0),
        Rgb(86, 180, 233),
        Rgb(0, 0, 0),
        Rgb(240, 228, 66),
    ];
    P[i % P.len()]
}

/// Colour `i` of `n` along a viridis-like ramp (ordered series, e.g. P_ism levels).
pub fn sequential(i: usize, n: usize) -> Rgb {
    let t = if n <= 1 { 0.0 } else { i as f64 / (n - 1) as f64 };
    // viridis, stopping short of its light yellow end (poor contrast on white)
    let t = 0.92 * t;
    let stops = [
        (68.0, 1.0, 84.0),
        (59.0, 82.0, 139.0),
        (33.0, 145.0, 140.0),
        (94.0, 201.0, 98.0),
        (253.0, 231.0, 37.0),
    ];
    let x = t * (stops.len() - 1) as f64;
    let k = (x as usize).min(stops.len() - 2);
    let f = x - k as f64;
    let lerp = |a: f64, b: f64| (a + (b - a) * f).round() as u8;
    Rgb(
        lerp(stops[k].0, stops[k + 1].0),
        lerp(stops[k].1, stops[k + 1].1),
        lerp(stops[k].2, stops[k + 1].2),
    )
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Style {
    /// Polyline through (x, y) (stroke width in pixels).
    Line(u32),
    /// Dashed polyline (stroke width in pixels).
    Dashed(u32),
    /// Histogram outline: `x` are the bin edges (one more than `y`).
    Steps(u32),
    /// Filled histogram bars: `x` are the bin edges (one more than `y`).
    Bars,
    /// Markers at (x, y) (radius in pixels).
    Points(u32),
}

/// One data series of a panel.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text (none: not in the legend).
    pub label: Option<String>,
    /// x values (bin edges for steps and bars).
    pub x: Vec<f64>,
    /// y values.
    pub y: Vec<f64>,
    /// Drawing style.
    pub style: Style,
    /// Colour (None: taken from [`palette`] by position in the panel).
    pub color: Option<Rgb>,
}

impl Series {
    /// A line through (x, y).
    pub fn line(label: impl Into<String>, x: Vec<f64>, y: Vec<f64>) -> Self {
        Self {
            label: Some(label.into()),
            x,
            y,
            style: Style::Line(2),
            color: None,
        }
    }
    /// A histogram outline over bin `edges`.
    pub fn steps(label: impl Into<String>, edges: Vec<f64>, values: Vec<f64>) -> Self {
        Self {
            label: Some(label.into()),
            x: edges,
            y: values,
            style: Style::Steps(2),
            color: None,
        }
    }
    /// Filled histogram bars over bin `edges`.
    pub fn bars(label: impl Into<String>, edges: Vec<f64>, values: Vec<f64>) -> Self {
        Self {
            label: Some(label.into()),
            x: edges,
            y: values,
            style: Style::Bars,
            color: None,
        }
    }
    /// Set the colour.
    pub fn color(mut self, c: Rgb) -> Self {
        self.color = Some(c);
        self
    }
    /// Set the style.
    pub fn style(mut self, s: Style) -> Self {
        self.style = s;
        self
    }
    /// Remove from the legend.
    pub fn unlabelled(mut self) -> Self {
        self.label = None;
        self
    }

    fn check(&self) -> Result<()> {
        let ok = match self.style {
            Style::Steps(_) | Style::Bars => self.x.len() == self.y.len() + 1,
            _ => self.x.len() == self.y.len(),
        };
        if ok {
            Ok(())
        } else {
            Err(Error::Input(format!(
                "series '{}': {} x values for {} y values",
                self.label.as_deref().unwrap_or(""),
                self.x.len(),
                self.y.len()
            )))
        }
    }

    /// The polyline of a steps series (or the points of a line).
    fn outline(&self) -> Vec<(f64, f64)> {
        match self.style {
            Style::Steps(_) | Style::Bars => {
                let mut pts = Vec::with_capacity(2 * self.y.len() + 2);
                pts.push((self.x[0], 0.0));
                for (i, &v) in self.y.iter().enumerate() {
                    pts.push((self.x[i], v));
                    pts.push((self.x[i + 1], v));
                }
                pts.push((*self.x.last().unwrap(), 0.0));
                pts
            }
            _ => self.x.iter().copied().zip(self.y.iter().copied()).collect(),
        }
    }
}

/// Where the legend goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LegendPos {
    /// Upper right corner.
    UpperRight,
    /// Upper left corner.
    UpperLeft,
    /// Lower right corner.
    LowerRight,
    /// No legend.
    None,
}

/// One chart: axes, labels, series.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// Title above the chart.
    pub title: String,
    /// x-axis label.
    pub xlabel: String,
    /// y-axis label.
    pub ylabel: String,
    /// x range (None: from the data).
    pub x_range: Option<(f64, f64)>,
    /// y range (None: from 0, or the data minimum if negative, to 8 % above the maximum).
    pub y_range: Option<(f64, f64)>,
    /// The series, drawn in order.
    pub series: Vec<Series>,
    /// Legend position.
    pub legend: LegendPos,
    /// Free text lines drawn in the upper left of the plot area (e.g. test results).
    pub notes: Vec<String>,
    /// Label only integer y ticks (count axes).
    pub integer_y: bool,
    /// Names of the rows y = 1, 2, ...: every integer y tick is labelled with its name
    /// instead of the number (one row per object, e.g. binaries); empty: numbers.
    pub y_names: Vec<String>,
}

impl Panel {
    /// An empty panel.
    pub fn new(title: impl Into<String>, xlabel: impl Into<String>, ylabel: impl Into<String>) -> Self {
        Self {
            title: title.into(),
            xlabel: xlabel.into(),
            ylabel: ylabel.into(),
            x_range: None,
            y_range: None,
            series: Vec::new(),
            legend: LegendPos::UpperRight,
            notes: Vec::new(),
            integer_y: false,
            y_names: Vec::new(),
        }
    }
    /// Add a series.
    pub fn with(mut self, s: Series) -> Self {
        self.series.push(s);
        self
    }
    /// Fix the x range.
    pub fn x_range(mut self, lo: f64, hi: f64) -> Self {
        self.x_range = Some((lo, hi));
        self
    }
    /// Fix the y range.
    pub fn y_range(mut self, lo: f64, hi: f64) -> Self {
        self.y_range = Some((lo, hi));
        self
    }
    /// Set the legend position.
    pub fn legend(mut self, pos: LegendPos) -> Self {
        self.legend = pos;
        self
    }
    /// Add a note line.
    pub fn note(mut self, text: impl Into<String>) -> Self {
        self.notes.push(text.into());
        self
    }

    fn ranges(&self) -> ((f64, f64), (f64, f64)) {
        let finite = |v: &&f64| v.is_finite();
        let xs = self.series.iter().flat_map(|s| s.x.iter()).filter(finite);
        let (xmin, xmax) = xs.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        let ys = self.series.iter().flat_map(|s| s.y.iter()).filter(finite);
        let (ymin, ymax) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        let widen = |(lo, hi): (f64, f64)| {
            if !(lo.is_finite() && hi.is_finite()) {
                (0.0, 1.0)
            } else if hi > lo {
                (lo, hi)
            } else {
                (lo - 0.5, hi + 0.5)
            }
        };
        let x = self.x_range.unwrap_or_else(|| widen((xmin, xmax)));
        let y = self.y_range.unwrap_or_else(|| {
            let (lo, hi) = widen((ymin.min(0.0), ymax));
            (lo, hi + 0.08 * (hi - lo))
        });
        (x, y)
    }
}

/// A grid of panels, rendered to PNG.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// Overall title (None: no title band).
    pub title: Option<String>,
    /// Panels, row by row.
    pub panels: Vec<Panel>,
    /// Panels per row.
    pub cols: usize,
    /// Size of one panel in pixels.
    pub panel_size: (u32, u32),
}

/// Tick labels without trailing zeros ("10", "0.25", "1e-05").
fn tick(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-3..1e5).contains(&a) {
        return format!("{v:.0e}");
    }
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    s.to_string()
}

fn draw_err<E: std::fmt::Display>(what: &str) -> impl Fn(E) -> Error + '_ {
    move |e| Error::Draw {
        what: what.to_string(),
        reason: e.to_string(),
    }
}

impl Figure {
    /// One panel, 800 x 560 pixels.
    pub fn single(panel: Panel) -> Self {
        Self {
            title: None,
            panels: vec![panel],
            cols: 1,
            panel_size: (800, 560),
        }
    }

    /// A grid of panels with `cols` per row, each `panel_size` pixels.
    pub fn grid(title: Option<String>, panels: Vec<Panel>, cols: usize, panel_size: (u32, u32)) -> Self {
        Self {
            title,
            panels,
            cols: cols.max(1),
            panel_size,
        }
    }

    /// Check the series and return (rows, cols, width, height).
    fn layout(&self) -> Result<(usize, usize, u32, u32)> {
        ensure_font()?;
        for p in &self.panels {
            for s in &p.series {
                s.check()?;
            }
        }
        let cols = self.cols.min(self.panels.len().max(1));
        let rows = self.panels.len().div_ceil(cols).max(1);
        let title_h: u32 = if self.title.is_some() { 44 } else { 0 };
        let (w, h) = (
            self.panel_size.0 * cols as u32,
            self.panel_size.1 * rows as u32 + title_h,
        );
        Ok((rows, cols, w, h))
    }

    /// Draw the figure on any plotters backend.
    fn draw_on<DB: DrawingBackend>(
        &self,
        root: DrawingArea<DB, plotters::coord::Shift>,
        rows: usize,
        cols: usize,
    ) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(draw_err("background"))?;
        let area = match &self.title {
            Some(t) => root
                .titled(t, (FONT, 26).into_font().style(FontStyle::Bold))
                .map_err(draw_err("title"))?,
            None => root.clone(),
        };
        let cells = area.split_evenly((rows, cols));
        for (panel, cell) in self.panels.iter().zip(cells.iter()) {
            draw_panel(panel, cell)?;
        }
        root.present().map_err(draw_err("figure"))?;
        Ok(())
    }

    /// Render as an SVG document (vector figure for papers; text as SVG `<text>`, no font
    /// file embedded: the viewer's sans-serif is used).
    pub fn render_svg(&self) -> Result<String> {
        let (rows, cols, w, h) = self.layout()?;
        let mut out = String::new();
        {
            let root = SVGBackend::with_string(&mut out, (w, h)).into_drawing_area();
            self.draw_on(root, rows, cols)?;
        }
        Ok(out)
    }

    /// Render and write an SVG atomically.
    pub fn save_svg(&self, path: &Path) -> Result<()> {
        let svg = self.render_svg()?;
        write_atomic(path, svg.as_bytes())
    }

    /// Write a PNG, or an SVG when the file name ends in `.svg`, atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("svg")) {
            self.save_svg(path)
        } else {
            self.save_png(path)
        }
    }

    /// Render to an RGB8 buffer (width, height, pixels).
    pub fn render_rgb(&self) -> Result<(u32, u32, Vec<u8>)> {
        let (rows, cols, w, h) = self.layout()?;
        let mut buf = vec![255u8; (w * h * 3) as usize];
        {
            let root = glyphs::CachedText::with_buffer(&mut buf, (w, h)).into_drawing_area();
            self.draw_on(root, rows, cols)?;
        }
        Ok((w, h, buf))
    }

    /// Render to PNG bytes.
    pub fn render_png(&self) -> Result<Vec<u8>> {
        let (w, h, buf) = self.render_rgb()?;
        let mut out = Vec::new();
        image::ImageEncoder::write_image(png_encoder(&mut out), &buf, w, h, image::ExtendedColorType::Rgb8)
            .map_err(|e| Error::Encode(e.to_string()))?;
        Ok(out)
    }

    /// Render and write a PNG atomically.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        let png = self.render_png()?;
        write_atomic(path, &png)
    }
}

/// Characters of a row name on the y axis ([`Panel::y_names`]).
const NAME_LABEL_CHARS: usize = 14;

/// `s` cut to `n` characters, the cut marked with an ellipsis.
fn truncate_label(s: &str, n: usize) -> String {
    if s.chars().count() <= n {
        s.to_string()
    } else {
        s.chars().take(n - 1).chain(std::iter::once('…')).collect()
    }
}

fn draw_panel<DB: DrawingBackend>(panel: &Panel, cell: &DrawingArea<DB, plotters::coord::Shift>) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let ((x0, x1), (y0, y1)) = panel.ranges();
    let mut chart = ChartBuilder::on(cell)
        .caption(&panel.title, (FONT, 20))
        .margin(12)
        .x_label_area_size(44)
        .y_label_area_size(if panel.y_names.is_empty() { 64 } else { 118 })
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(draw_err(&panel.title))?;
    let fmt = |v: &f64| tick(*v);
    let integer_y = panel.integer_y || !panel.y_names.is_empty();
    let names = &panel.y_names;
    let yfmt = move |v: &f64| {
        if integer_y && (v.fract().abs() > 1e-9) {
            String::new()
        } else if !names.is_empty() {
            // Row k (1-based) by name, cut to what the label area holds.
            let k = v.round() as i64;
            usize::try_from(k - 1)
                .ok()
                .and_then(|i| names.get(i))
                .map(|n| truncate_label(n, NAME_LABEL_CHARS))
                .unwrap_or_default()
        } else {
            tick(*v)
        }
    };
    // Every row named: one tick per integer (plotters would otherwise choose ~10), the font
    // no taller than a row (the plot area is the cell less ~100 px of caption and axis), at
    // least 5 px: small in a PNG of many rows, legible when the SVG is zoomed.
    let (y_ticks, y_font) = match names.len() {
        0 => (10, 15),
        n => {
            let row_px = (f64::from(cell.dim_in_pixel().1) - 100.0).max(50.0) / (n + 1) as f64;
            (n + 2, row_px.clamp(5.0, 15.0).floor() as u32)
        }
    };
    chart
        .configure_mesh()
        .x_desc(panel.xlabel.as_str())
        .y_desc(panel.ylabel.as_str())
        .y_labels(y_ticks)
        .label_style((FONT, 15))
        .y_label_style((FONT, y_font))
        .axis_desc_style((FONT, 17))
        .x_label_formatter(&fmt)
        .y_label_formatter(&yfmt)
        .light_line_style(RGBColor(246, 246, 246))
        .bold_line_style(RGBColor(228, 228, 228))
        .draw()
        .map_err(draw_err(&panel.title))?;
    let mut labelled = false;
    for (i, s) in panel.series.iter().enumerate() {
        let color = s.color.unwrap_or_else(|| palette(i)).to_plotters();
        let anno = match s.style {
            Style::Line(wd) | Style::Steps(wd) => chart
                .draw_series(LineSeries::new(s.outline(), color.stroke_width(wd)))
                .map_err(draw_err(&panel.title))?,
            Style::Dashed(wd) => chart
                .draw_series(DashedLineSeries::new(s.outline(), 8, 5, color.stroke_width(wd)))
                .map_err(draw_err(&panel.title))?,
            Style::Bars => {
                let rects = s.y.iter().enumerate().flat_map(|(k, &v)| {
                    let (a, b) = (s.x[k], s.x[k + 1]);
                    [
                        Rectangle::new([(a, 0.0), (b, v)], color.mix(0.45).filled()),
                        Rectangle::new([(a, 0.0), (b, v)], color.stroke_width(1)),
                    ]
                });
                chart.draw_series(rects).map_err(draw_err(&panel.title))?
            }
            Style::Points(r) => chart
                .draw_series(
                    s.x.iter()
                        .zip(&s.y)
                        .map(|(&x, &y)| Circle::new((x, y), r, color.filled())),
                )
                .map_err(draw_err(&panel.title))?,
        };
        if let Some(label) = &s.label {
            labelled = true;
            let style = s.style;
            anno.label(label.as_str()).legend(move |(x, y)| match style {
                Style::Bars => Rectangle::new([(x, y - 5), (x + 18, y + 5)], color.mix(0.45).filled()).into_dyn(),
                _ => PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(3)).into_dyn(),
            });
        }
    }
    if labelled && panel.legend != LegendPos::None {
        let pos = match panel.legend {
            LegendPos::UpperLeft => SeriesLabelPosition::UpperLeft,
            LegendPos::LowerRight => SeriesLabelPosition::LowerRight,
            _ => SeriesLabelPosition::UpperRight,
        };
        chart
            .configure_series_labels()
            .position(pos)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(150, 150, 150))
            .label_font((FONT, 14))
            .draw()
            .map_err(draw_err(&panel.title))?;
    }
    // Notes: top left of the plot area, one line per 7 % of the height (data coordinates).
    for (k, line) in panel.notes.iter().enumerate() {
        let at = (x0 + 0.02 * (x1 - x0), y1 - (0.03 + 0.065 * k as f64) * (y1 - y0));
        chart
            .draw_series(std::iter::once(Text::new(
                line.clone(),
                at,
                (FONT, 14).into_font().color(&BLACK),
            )))
            .map_err(draw_err(&panel.title))?;
    }
    Ok(())
}

/// Write `bytes` to `path` atomically (the workspace's one writer, [`crate::io::write_atomic`]),
/// its error as this module's.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    crate::io::write_atomic(path, bytes).map_err(|e| match e {
        sofipol_calib::Error::Io { path, source } => Error::Io { path, source },
        other => Error::Io {
            path: path.to_path_buf(),
            source: std::io::Error::other(other.to_string()),
        },
    })
}

/// One histogram as filled bars, written to `path`.
pub fn histogram_png(
    path: &Path,
    edges: &[f64],
    values: &[f64],
    title: &str,
    xlabel: &str,
    ylabel: &str,
) -> Result<()> {
    let panel = Panel::new(title, xlabel, ylabel)
        .with(Series::bars("", edges.to_vec(), values.to_vec()).unlabelled())
        .legend(LegendPos::None);
    Figure::single(panel).save_png(path)
}

/// Line/steps series on one panel, written to `path`.
pub fn line_png(path: &Path, series: Vec<Series>, title: &str, xlabel: &str, ylabel: &str) -> Result<()> {
    let mut panel = Panel::new(title, xlabel, ylabel);
    panel.series = series;
    Figure::single(panel).save_png(path)
}

#[cfg(test)]
mod tests;
