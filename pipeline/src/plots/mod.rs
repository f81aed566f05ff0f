//! PNG and SVG figures: a small, reusable plotting API on top of `plotters` (bitmap and SVG
//! backends, no system fonts: DejaVu Sans is embedded through the `dejavu` crate).
//!
//! Figures are laid out for print: a [`Figure`] has a printed width in mm (a journal's
//! single column, [`SINGLE_COLUMN_MM`], or the full page, [`DOUBLE_COLUMN_MM`]), PNGs are
//! rendered at [`DPI`] (written into the file's pHYs chunk), SVGs state the same width in
//! mm, and every font, line and margin is given in points at that printed size
//! ([`TICK_PT`], [`LABEL_PT`], ...). Scaled to its column a figure's tick labels are
//! [`TICK_PT`]; on screen the PNGs are large and sharp.
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
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::FontStyle;

pub mod glyphs;
pub mod png_rgb;
pub mod quality;
pub mod target;

/// Errors of the plotting module (defined with the crate's other errors).
pub use crate::error::PlotError as Error;

/// Result of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// The family name the embedded font is registered under.
const FONT: &str = "sans-serif";

/// Resolution of the PNGs, dots per inch (written into their pHYs chunk).
pub const DPI: f64 = 300.0;
/// Printed width of a single-column figure, mm (A&A 88 mm, MNRAS 84 mm, ApJ 85 mm).
pub const SINGLE_COLUMN_MM: f64 = 88.0;
/// Printed width of a full-page (two-column) figure, mm.
pub const DOUBLE_COLUMN_MM: f64 = 180.0;
/// Tick labels, points at the printed width (em size, as in a word processor).
pub const TICK_PT: f64 = 7.5;
/// Legend entries and notes, points.
pub const LEGEND_PT: f64 = 7.0;
/// Axis labels, points.
pub const LABEL_PT: f64 = 8.5;
/// Panel titles, points.
pub const PANEL_TITLE_PT: f64 = 8.5;
/// The figure's title (bold), points.
pub const TITLE_PT: f64 = 9.0;
/// Row names of [`Panel::y_names`] shrink to fit their rows, but not below this, points.
pub const MIN_NAME_PT: f64 = 2.0;

/// Pixels per point at [`DPI`] (the SVG uses the same pixel grid as its user units).
const PX_PER_PT: f64 = DPI / 72.0;

/// `mm` at [`DPI`], pixels.
pub fn mm_to_px(mm: f64) -> u32 {
    (mm / 25.4 * DPI).round() as u32
}

/// `pt` at [`DPI`], pixels.
fn pt_px(pt: f64) -> f64 {
    pt * PX_PER_PT
}

/// `pt` at [`DPI`], whole pixels (at least 1).
fn pt_px_u(pt: f64) -> u32 {
    pt_px(pt).round().max(1.0) as u32
}

/// The backend a figure is drawn on: plotters' font size means a different thing on each.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Target {
    /// Bitmap: `ab_glyph` scales the line height (ascent - descent: (1901 + 483) / 2048 em
    /// in DejaVu Sans) to the size.
    Png,
    /// SVG: plotters writes `font-size` = size / 1.24.
    Svg,
}

impl Target {
    /// plotters' font size for an em of `pt` points.
    fn font_size(self, pt: f64) -> f64 {
        let em = pt_px(pt);
        match self {
            Target::Png => em * 2384.0 / 2048.0,
            Target::Svg => em * 1.24,
        }
    }
    fn font(self, pt: f64) -> FontDesc<'static> {
        (FONT, self.font_size(pt)).into_font()
    }
    /// The bold face (made bold: plotters' `FontDesc::style` keeps the face, and its
    /// metrics, of the font it is called on).
    fn bold_font(self, pt: f64) -> FontDesc<'static> {
        FontDesc::new(FontFamily::Name(FONT), self.font_size(pt), FontStyle::Bold)
    }
}

/// Width in pixels of `text` in `font` (DejaVu metrics; on SVG a little wider than drawn).
fn text_width(font: &FontDesc<'_>, text: &str) -> f64 {
    let bold = match font.get_style() {
        FontStyle::Normal => Some(false),
        FontStyle::Bold => Some(true),
        _ => None,
    };
    match bold {
        Some(bold)
            if font.get_family().as_str() == FONT
                && matches!(font.get_transform(), plotters::style::FontTransform::None) =>
        {
            f64::from(glyphs::text_size(bold, font.get_size(), text).0)
        }
        _ => font.box_size(text).map_or(0.0, |(w, _)| f64::from(w)),
    }
}

/// `text` broken at spaces into lines no wider than `max_px` in `font` (a word longer than
/// the line stands alone).
fn wrap(font: &FontDesc<'_>, text: &str, max_px: f64) -> Vec<String> {
    let mut lines: Vec<String> = Vec::new();
    for word in text.split(' ') {
        match lines.last_mut() {
            Some(line) if text_width(font, &format!("{line} {word}")) <= max_px => {
                line.push(' ');
                line.push_str(word);
            }
            _ => lines.push(word.to_string()),
        }
    }
    lines
}

/// Draw `lines` centred at the top of `area` (line height 1.25 em); returns the height used.
fn draw_centered<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    lines: &[String],
    font: &FontDesc<'_>,
    em_px: f64,
) -> Result<u32>
where
    DB::ErrorType: 'static,
{
    let line_h = 1.25 * em_px;
    let cx = area.dim_in_pixel().0 as i32 / 2;
    for (k, line) in lines.iter().enumerate() {
        let y = (0.25 * em_px + k as f64 * line_h).round() as i32;
        let style = font.clone().color(&BLACK).pos(Pos::new(HPos::Center, VPos::Top));
        area.draw(&Text::new(line.as_str(), (cx, y), style))
            .map_err(draw_err("title"))?;
    }
    Ok(text_band(lines.len(), em_px))
}

/// Height of a band of `n` centred lines of `em_px` (see [`draw_centered`]).
fn text_band(n: usize, em_px: f64) -> u32 {
    if n == 0 {
        0
    } else {
        (0.5 * em_px + 1.25 * em_px * n as f64).ceil() as u32
    }
}

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
    /// Polyline through (x, y) (stroke width in half points: 2 is a 1 pt line).
    Line(u32),
    /// Dashed polyline (stroke width in half points).
    Dashed(u32),
    /// Histogram outline: `x` are the bin edges (one more than `y`); width in half points.
    Steps(u32),
    /// Filled histogram bars: `x` are the bin edges (one more than `y`).
    Bars,
    /// Markers at (x, y) (radius in half points).
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

/// A grid of panels with a printed size, rendered to PNG or SVG.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// Overall title (None: no title band); wrapped to the width.
    pub title: Option<String>,
    /// Panels, row by row.
    pub panels: Vec<Panel>,
    /// Panels per row.
    pub cols: usize,
    /// Printed width of the whole figure, mm ([`SINGLE_COLUMN_MM`], [`DOUBLE_COLUMN_MM`]).
    pub width_mm: f64,
    /// Printed height of one row of panels, mm (the title band comes on top).
    pub panel_height_mm: f64,
}

/// Height of a single-panel figure, mm (aspect 0.7 on a single column).
pub const SINGLE_PANEL_HEIGHT_MM: f64 = 62.0;

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
    /// One panel on a single column ([`SINGLE_COLUMN_MM`] x [`SINGLE_PANEL_HEIGHT_MM`]).
    pub fn single(panel: Panel) -> Self {
        Self {
            title: None,
            panels: vec![panel],
            cols: 1,
            width_mm: SINGLE_COLUMN_MM,
            panel_height_mm: SINGLE_PANEL_HEIGHT_MM,
        }
    }

    /// A grid of panels with `cols` per row, `width_mm` wide, rows `panel_height_mm` high.
    pub fn grid(title: Option<String>, panels: Vec<Panel>, cols: usize, width_mm: f64, panel_height_mm: f64) -> Self {
        Self {
            title,
            panels,
            cols: cols.max(1),
            width_mm,
            panel_height_mm,
        }
    }

    /// The title's lines at the figure's width (measured with the PNG's font metrics).
    fn title_lines(&self) -> Vec<String> {
        let font = Target::Png.bold_font(TITLE_PT);
        let max = f64::from(mm_to_px(self.width_mm)) - 2.0 * pt_px(6.0);
        self.title.as_deref().map_or_else(Vec::new, |t| wrap(&font, t, max))
    }

    /// Pixel size of the rendered figure (width, height) at [`DPI`].
    pub fn pixel_size(&self) -> Result<(u32, u32)> {
        ensure_font()?;
        let cols = self.cols.min(self.panels.len().max(1));
        let rows = self.panels.len().div_ceil(cols).max(1);
        let title_h = text_band(self.title_lines().len(), pt_px(TITLE_PT));
        Ok((
            mm_to_px(self.width_mm),
            mm_to_px(self.panel_height_mm) * rows as u32 + title_h,
        ))
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
        let (w, h) = self.pixel_size()?;
        Ok((rows, cols, w, h))
    }

    /// Draw the figure on any plotters backend.
    fn draw_on<DB: DrawingBackend>(
        &self,
        root: DrawingArea<DB, plotters::coord::Shift>,
        rows: usize,
        cols: usize,
        target: Target,
    ) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(draw_err("background"))?;
        let lines = self.title_lines();
        let area = if lines.is_empty() {
            root.clone()
        } else {
            let font = target.bold_font(TITLE_PT);
            let band = draw_centered(&root, &lines, &font, pt_px(TITLE_PT))?;
            root.split_vertically(band).1
        };
        let cells = area.split_evenly((rows, cols));
        for (panel, cell) in self.panels.iter().zip(cells.iter()) {
            draw_panel(panel, cell, target)?;
        }
        root.present().map_err(draw_err("figure"))?;
        Ok(())
    }

    /// Render as an SVG document (vector figure for papers; text as SVG `<text>`, no font
    /// file embedded: the viewer's sans-serif is used). Its `width` and `height` are the
    /// printed size in mm (the viewBox the same pixels as the PNG): the fonts print at the
    /// same points as the PNG's.
    pub fn render_svg(&self) -> Result<String> {
        let (rows, cols, w, h) = self.layout()?;
        let mut out = String::new();
        {
            let root = SVGBackend::with_string(&mut out, (w, h)).into_drawing_area();
            self.draw_on(root, rows, cols, Target::Svg)?;
        }
        let mm = |px: u32| f64::from(px) / DPI * 25.4;
        let unitless = format!("width=\"{w}\" height=\"{h}\"");
        let printed = format!("width=\"{:.2}mm\" height=\"{:.2}mm\"", mm(w), mm(h));
        Ok(out.replacen(&unitless, &printed, 1))
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
            self.draw_on(root, rows, cols, Target::Png)?;
        }
        Ok((w, h, buf))
    }

    /// Render to PNG bytes, with the resolution ([`DPI`]) in a pHYs chunk: a page-layout
    /// program places the figure at its printed width.
    pub fn render_png(&self) -> Result<Vec<u8>> {
        let (w, h, buf) = self.render_rgb()?;
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, w, h);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let ppm = (DPI / 0.0254).round() as u32;
            enc.set_pixel_dims(Some(png::PixelDimensions {
                xppu: ppm,
                yppu: ppm,
                unit: png::Unit::Meter,
            }));
            let encode = |e: png::EncodingError| Error::Encode(e.to_string());
            let mut writer = enc.write_header().map_err(encode)?;
            writer.write_image_data(&buf).map_err(encode)?;
            writer.finish().map_err(encode)?;
        }
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

fn draw_panel<DB: DrawingBackend>(
    panel: &Panel,
    cell: &DrawingArea<DB, plotters::coord::Shift>,
    target: Target,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let ((x0, x1), (y0, y1)) = panel.ranges();
    // The title: centred, wrapped to the cell (plotters' caption would run past its edges).
    let title_font = target.font(PANEL_TITLE_PT);
    let measure = Target::Png.font(PANEL_TITLE_PT);
    let (cell_w, cell_h) = cell.dim_in_pixel();
    let title_lines = if panel.title.is_empty() {
        Vec::new()
    } else {
        wrap(&measure, &panel.title, f64::from(cell_w) - 2.0 * pt_px(3.0))
    };
    let band = draw_centered(cell, &title_lines, &title_font, pt_px(PANEL_TITLE_PT))?;
    let body = cell.split_vertically(band).1;
    // Row names: one tick per integer (plotters would otherwise choose ~10), the font no
    // taller than a row (the plot area is the cell less the title and the x axis), from
    // MIN_NAME_PT to TICK_PT: small with many rows, legible when the SVG is zoomed.
    let names = &panel.y_names;
    let x_area = pt_px(TICK_PT + LABEL_PT) * 1.45;
    let (y_ticks, y_pt) = match names.len() {
        0 => (10, TICK_PT),
        _ => {
            let plot_h = (f64::from(cell_h) - f64::from(band) - x_area - pt_px(8.0)).max(pt_px(20.0));
            let rows = (y1 - y0).max(1.0);
            let row_pt = plot_h / rows / PX_PER_PT;
            (rows.ceil() as usize + 2, row_pt.clamp(MIN_NAME_PT, TICK_PT))
        }
    };
    let y_area = if names.is_empty() {
        pt_px(TICK_PT) * 2.6 + pt_px(LABEL_PT) * 1.4
    } else {
        let font = Target::Png.font(y_pt);
        let widest = names
            .iter()
            .map(|n| text_width(&font, &truncate_label(n, NAME_LABEL_CHARS)))
            .fold(0.0, f64::max);
        widest + pt_px(4.0) + pt_px(LABEL_PT) * 1.4
    };
    let mut chart = ChartBuilder::on(&body)
        .margin_top(pt_px_u(2.0))
        .margin_bottom(pt_px_u(1.0))
        .margin_left(pt_px_u(3.0))
        .margin_right(pt_px_u(5.0))
        .x_label_area_size(x_area.round() as u32)
        .y_label_area_size(y_area.round() as u32)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(draw_err(&panel.title))?;
    let fmt = |v: &f64| tick(*v);
    let integer_y = panel.integer_y || !names.is_empty();
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
    // A light major grid only (one line per labelled tick), no minor grid: quiet in print.
    chart
        .configure_mesh()
        .x_desc(panel.xlabel.as_str())
        .y_desc(panel.ylabel.as_str())
        .x_labels(8)
        .y_labels(y_ticks)
        .max_light_lines(0)
        .label_style(target.font(TICK_PT))
        .y_label_style(target.font(y_pt))
        .axis_desc_style(target.font(LABEL_PT))
        .x_label_formatter(&fmt)
        .y_label_formatter(&yfmt)
        .set_all_tick_mark_size(pt_px_u(2.5))
        .axis_style(BLACK.stroke_width(pt_px_u(0.6)))
        .bold_line_style(RGBColor(225, 225, 225).stroke_width(pt_px_u(0.3)))
        .draw()
        .map_err(draw_err(&panel.title))?;
    let half_pt = |w: u32| pt_px_u(0.5 * f64::from(w));
    let mut labelled = false;
    for (i, s) in panel.series.iter().enumerate() {
        let color = s.color.unwrap_or_else(|| palette(i)).to_plotters();
        let anno = match s.style {
            Style::Line(wd) | Style::Steps(wd) => chart
                .draw_series(LineSeries::new(s.outline(), color.stroke_width(half_pt(wd))))
                .map_err(draw_err(&panel.title))?,
            Style::Dashed(wd) => chart
                .draw_series(DashedLineSeries::new(
                    s.outline(),
                    pt_px_u(3.0),
                    pt_px_u(2.0),
                    color.stroke_width(half_pt(wd)),
                ))
                .map_err(draw_err(&panel.title))?,
            Style::Bars => {
                let rects = s.y.iter().enumerate().flat_map(|(k, &v)| {
                    let (a, b) = (s.x[k], s.x[k + 1]);
                    [
                        Rectangle::new([(a, 0.0), (b, v)], color.mix(0.45).filled()),
                        Rectangle::new([(a, 0.0), (b, v)], color.stroke_width(half_pt(1))),
                    ]
                });
                chart.draw_series(rects).map_err(draw_err(&panel.title))?
            }
            Style::Points(r) => chart
                .draw_series(
                    s.x.iter()
                        .zip(&s.y)
                        .map(|(&x, &y)| Circle::new((x, y), half_pt(r), color.filled())),
                )
                .map_err(draw_err(&panel.title))?,
        };
        if let Some(label) = &s.label {
            labelled = true;
            let style = s.style;
            let (len, half_h, stroke) = (pt_px_u(10.0) as i32, pt_px_u(2.5) as i32, pt_px_u(1.2));
            anno.label(label.as_str()).legend(move |(x, y)| match style {
                Style::Bars => {
                    Rectangle::new([(x, y - half_h), (x + len, y + half_h)], color.mix(0.45).filled()).into_dyn()
                }
                _ => PathElement::new(vec![(x, y), (x + len, y)], color.stroke_width(stroke)).into_dyn(),
            });
        }
    }
    let plot = chart.plotting_area().dim_in_pixel();
    let (plot_w, plot_h) = (f64::from(plot.0.max(1)), f64::from(plot.1.max(1)));
    let legend_font = Target::Png.font(LEGEND_PT);
    let (legend_margin, legend_symbol) = (pt_px(3.0), pt_px(13.0));
    let labels: Vec<&str> = panel.series.iter().filter_map(|s| s.label.as_deref()).collect();
    let legend_drawn = labelled && panel.legend != LegendPos::None;
    if legend_drawn {
        let pos = match panel.legend {
            LegendPos::UpperLeft => SeriesLabelPosition::UpperLeft,
            LegendPos::LowerRight => SeriesLabelPosition::LowerRight,
            _ => SeriesLabelPosition::UpperRight,
        };
        chart
            .configure_series_labels()
            .position(pos)
            .margin(legend_margin.round() as u32)
            .legend_area_size(legend_symbol.round() as u32)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(150, 150, 150).stroke_width(pt_px_u(0.3)))
            .label_font(target.font(LEGEND_PT))
            .draw()
            .map_err(draw_err(&panel.title))?;
    }
    // Notes: top left of the plot area, wrapped to its width, one line per 1.3 em; below
    // the legend when they would run into it.
    let em = pt_px(LEGEND_PT);
    let notes: Vec<String> = panel
        .notes
        .iter()
        .flat_map(|n| wrap(&legend_font, n, 0.96 * plot_w))
        .collect();
    let notes_w = notes.iter().map(|n| text_width(&legend_font, n)).fold(0.0, f64::max);
    let legend_w =
        labels.iter().map(|l| text_width(&legend_font, l)).fold(0.0, f64::max) + legend_symbol + 2.0 * legend_margin;
    let on_top = matches!(panel.legend, LegendPos::UpperLeft | LegendPos::UpperRight);
    let below_legend = legend_drawn && on_top && notes_w + legend_w + pt_px(8.0) > plot_w;
    let top_px = if below_legend {
        labels.len() as f64 * 1.6 * em + 2.0 * legend_margin + pt_px(6.0)
    } else {
        0.03 * plot_h
    };
    let at_y = |k: usize| y1 - (top_px + 1.3 * em * k as f64) / plot_h * (y1 - y0);
    for (k, text) in notes.iter().enumerate() {
        let at = (x0 + 0.02 * (x1 - x0), at_y(k));
        chart
            .draw_series(std::iter::once(Text::new(
                text.clone(),
                at,
                target.font(LEGEND_PT).color(&BLACK),
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
