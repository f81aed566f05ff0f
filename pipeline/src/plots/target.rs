//! The per-target diagnostic figure: what one reduced sequence looks like, on one PNG.
//!
//! ```text
//! +--------------------------------------------------------------------------+
//! | object — status — sequence                                                |
//! +----------------------------------+----------------------------------+----+
//! | POSANG 0°: o cut-out | e cut-out | POSANG 45°: o cut-out | e cut-out |    |
//! |  (median of the registered dithers, asinh stretch, apertures A/B)    | pol|
//! | F per dither (error bars, rejected | F per dither ...                 | on |
//! |  hollow red, dashed: fitted q,u)   |                                  | sky|
//! +----------------------------------+----------------------------------+----+
//! | polarization table | measurement details | status, error, flags           |
//! +--------------------------------------------------------------------------+
//! ```
//!
//! Cut-outs are in detector orientation (row 0 of the frame at the bottom, as in DS9),
//! labelled with POSANG and a small N/E compass; the polarization panel is on the sky (north
//! up, east left). Orientations are laid out two per row. A target without frames or
//! measurements (failed) gets a text-only figure. Rendering never panics: a drawing
//! failure falls back to a text-only figure. The width is fixed ([`WIDTH`]); the height
//! depends on the number of orientations and lines of text.
use std::io;
use std::path::Path;

use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::FontStyle;
use sofipol_calib::frame::mask as mbits;
use sofipol_calib::Frame;

use super::{ensure_font, write_atomic, Error, FONT};
use crate::catalog::{Component, Status, Target};
use crate::reduce::run::TargetOutcome;
use crate::reduce::{CalibratedOrientation, DitherValue, Measured};

/// Width of every target figure, px.
pub const WIDTH: u32 = 1200;
const TITLE_H: u32 = 46;
/// Displayed size of one cut-out tile, px.
const TILE: u32 = 180;
const TILE_GAP: u32 = 10;
const CELL_W: u32 = 395;
const CELL_LABEL_H: u32 = 24;
const F_H: u32 = 200;
const CELL_H: u32 = CELL_LABEL_H + TILE + 6 + F_H;
const POL_X: u32 = 2 * CELL_W + 12;
const POL_S: u32 = WIDTH - POL_X - 12;
const LINE_H: u32 = 20;
const TEXT_FONT: u32 = 15;
const COL_X: [u32; 3] = [12, 408, 800];
const COL_W: u32 = 385;

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

fn de<E: std::fmt::Display>(e: E) -> io::Error {
    io::Error::other(e.to_string())
}

fn to_io(e: Error) -> io::Error {
    match e {
        Error::Io { source, .. } => source,
        other => io::Error::other(other.to_string()),
    }
}

/// Colour of component `c` (A orange, B blue); `dark` for drawing on the grey-scale tiles.
fn comp_color(c: usize, dark: bool) -> RGBColor {
    match (c, dark) {
        (0, false) => RGBColor(213, 94, 0),
        (0, true) => RGBColor(255, 170, 40),
        (_, false) => RGBColor(0, 114, 178),
        (_, true) => RGBColor(90, 200, 255),
    }
}

const REJECT: RGBColor = RGBColor(220, 20, 20);
const COMP_NAMES: [&str; 2] = ["A", "B"];

/// Write the diagnostic figure of one reduced target to `path` (atomically).
pub fn target_png(path: &Path, target: &Target, cal: &[CalibratedOrientation], m: &Measured) -> io::Result<()> {
    target_png_opt(path, target, Some(cal), Some(m))
}

/// [`target_png`] of a [`TargetOutcome`] (kept frames and measurements when present; a
/// failed target gets the text-only figure).
pub fn outcome_png(path: &Path, outcome: &TargetOutcome) -> io::Result<()> {
    target_png_opt(
        path,
        &outcome.target,
        outcome.calibrated.as_deref(),
        outcome.measured.as_ref(),
    )
}

/// [`target_png`] when the frames or the measurements may be missing.
pub fn target_png_opt(
    path: &Path,
    target: &Target,
    cal: Option<&[CalibratedOrientation]>,
    m: Option<&Measured>,
) -> io::Result<()> {
    let (w, h, rgb) = render_target_rgb(target, cal, m)?;
    let mut png = Vec::new();
    image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut png),
        &rgb,
        w,
        h,
        image::ExtendedColorType::Rgb8,
    )
    .map_err(de)?;
    write_atomic(path, &png).map_err(to_io)
}

/// Render the figure to an RGB8 buffer (width, height, pixels). Falls back to a text-only
/// figure when the full one cannot be drawn.
pub fn render_target_rgb(
    target: &Target,
    cal: Option<&[CalibratedOrientation]>,
    m: Option<&Measured>,
) -> io::Result<(u32, u32, Vec<u8>)> {
    ensure_font().map_err(to_io)?;
    let full = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| render(target, cal, m)));
    match full {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => render(target, None, None).map_err(|_| e),
        Err(_) => render(target, None, None),
    }
}

// ---------------------------------------------------------------------------------------
// Numbers and text

fn finite(v: f64) -> bool {
    v.is_finite()
}

fn fmt(v: f64, prec: usize) -> String {
    if v.is_finite() {
        format!("{v:.prec$}")
    } else {
        "—".into()
    }
}

fn median(v: &mut [f64]) -> Option<f64> {
    let mut n = 0;
    for i in 0..v.len() {
        if v[i].is_finite() {
            v.swap(n, i);
            n += 1;
        }
    }
    let v = &mut v[..n];
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

fn status_word(s: Status) -> &'static str {
    match s {
        Status::Ok => "ok",
        Status::Partial => "partial",
        Status::Failed => "failed",
    }
}

fn status_color(s: Status) -> RGBColor {
    match s {
        Status::Ok => RGBColor(0, 140, 70),
        Status::Partial => RGBColor(200, 120, 0),
        Status::Failed => RGBColor(200, 0, 0),
    }
}

/// One line of the text band.
#[derive(Clone)]
struct Line {
    text: String,
    color: RGBColor,
    bold: bool,
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

fn text_width(t: &str, bold: bool) -> u32 {
    let style = if bold { FontStyle::Bold } else { FontStyle::Normal };
    let font = FontDesc::new(FontFamily::Name(FONT), TEXT_FONT as f64, style);
    font.box_size(t)
        .map(|(w, _)| w)
        .unwrap_or((t.chars().count() as u32) * TEXT_FONT * 6 / 10)
}

/// Wrap `line` at word (or comma) boundaries to `width` px; continuation lines indented.
fn wrap(line: Line, width: u32, out: &mut Vec<Line>) {
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

fn component_lines(target: &Target, out: &mut Vec<Line>) {
    out.push(Line::head("Polarization (sky frame)"));
    if target.components.is_empty() {
        out.push(Line::plain("no component measured"));
    }
    for (i, c) in target.components.iter().enumerate() {
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
                Line::col(format!("      flags: {}", c.flags.join(", ")), col),
                COL_W,
                out,
            );
        }
    }
    let dg = match target.delta_gamma_deg {
        Some(d) if d.is_finite() => format!("Δγ = |γA − γB| = {d:.1}°"),
        _ => "Δγ: — (needs two components passing the cut)".into(),
    };
    out.push(Line::head(dg));
}

fn measurement_lines(
    target: &Target,
    cal: Option<&[CalibratedOrientation]>,
    m: Option<&Measured>,
    out: &mut Vec<Line>,
) {
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
    if let Some(cal) = cal.filter(|c| !c.is_empty()) {
        let pas: Vec<String> = cal.iter().map(|o| format!("{}", fmt(o.posang_deg, 1))).collect();
        let phis: Vec<String> = cal.iter().map(|o| format!("{}", fmt(o.analyzer_deg, 1))).collect();
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
                        cal.and_then(|c| c.get(k))
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
        out.push(Line::col(
            "F plots: ● used, red ○ rejected, dashed: fitted q, u",
            RGBColor(90, 90, 90),
        ));
    }
    if let Some(v) = target.extra.get("sequence").and_then(|v| v.as_str()) {
        wrap(Line::plain(format!("sequence {v}")), COL_W, out);
    }
}

fn status_lines(target: &Target, m: Option<&Measured>, out: &mut Vec<Line>) {
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
    let mut flags: Vec<String> = m.map(|m| m.flags.clone()).unwrap_or_default();
    if let Some(arr) = target.extra.get("flags").and_then(|v| v.as_array()) {
        for f in arr.iter().filter_map(|v| v.as_str()) {
            if !flags.iter().any(|g| g == f) {
                flags.push(f.to_string());
            }
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

// ---------------------------------------------------------------------------------------
// Cut-outs

/// Median of the registered dithers of one beam around the binary.
struct Stack {
    /// Side, px (odd).
    n: usize,
    /// Values, row 0 at the bottom; NaN where nothing usable.
    pix: Vec<f32>,
    /// Component positions in cut-out pixel coordinates.
    stars: Vec<(f64, f64)>,
    /// Dithers that went into the stack.
    used: usize,
}

fn sample(f: &Frame, x: f64, y: f64) -> Option<f32> {
    let (ny, nx) = f.shape();
    if !(x >= 0.0 && y >= 0.0 && x <= (nx - 1) as f64 && y <= (ny - 1) as f64) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(nx - 1), (y0 + 1).min(ny - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let bad = mbits::BAD | mbits::COSMIC | mbits::OFF_STRIP;
    let mut acc = 0.0f32;
    for (yy, xx, w) in [
        (y0, x0, (1.0 - fx) * (1.0 - fy)),
        (y0, x1, fx * (1.0 - fy)),
        (y1, x0, (1.0 - fx) * fy),
        (y1, x1, fx * fy),
    ] {
        if w <= 0.0 {
            continue;
        }
        let v = f.data[[yy, xx]];
        if f.mask[[yy, xx]] & bad != 0 || !v.is_finite() {
            return None;
        }
        acc += w * v;
    }
    Some(acc)
}

fn beam_xy(d: &DitherValue, e_beam: bool) -> (f64, f64) {
    if e_beam {
        d.e.xy
    } else {
        d.o.xy
    }
}

/// Stack of beam `e_beam` of orientation `k` (None when no dither has a measured position).
fn stack(o: &CalibratedOrientation, m: &Measured, k: usize, e_beam: bool) -> Option<Stack> {
    let a: &[DitherValue] = m.dithers.first()?.get(k)?;
    let b: Option<&[DitherValue]> = m.dithers.get(1).and_then(|c| c.get(k)).map(|v| v.as_slice());
    let anchors: Vec<Option<(f64, f64)>> = (0..o.frames.len())
        .map(|i| {
            a.get(i)
                .map(|d| beam_xy(d, e_beam))
                .filter(|p| finite(p.0) && finite(p.1))
        })
        .collect();
    if anchors.iter().all(|p| p.is_none()) {
        return None;
    }
    // Offset of B from A in this beam: median over dithers.
    let rel = b.and_then(|b| {
        let (mut dx, mut dy): (Vec<f64>, Vec<f64>) = a
            .iter()
            .zip(b)
            .map(|(da, db)| {
                let (pa, pb) = (beam_xy(da, e_beam), beam_xy(db, e_beam));
                (pb.0 - pa.0, pb.1 - pa.1)
            })
            .unzip();
        Some((median(&mut dx)?, median(&mut dy)?))
    });
    let ap = if m.aperture_px.is_finite() && m.aperture_px > 0.0 {
        m.aperture_px.min(30.0)
    } else {
        3.0
    };
    let r = rel.map(|r| r.0.hypot(r.1)).unwrap_or(0.0).min(100.0);
    let h = ((0.5 * r + ap + 8.0).ceil() as usize).clamp(24, 60);
    let n = 2 * h + 1;
    let mid = rel.map(|r| (0.5 * r.0, 0.5 * r.1)).unwrap_or((0.0, 0.0));
    let mut pix = vec![f32::NAN; n * n];
    let mut vals: Vec<f32> = Vec::with_capacity(anchors.len());
    let used = anchors.iter().filter(|p| p.is_some()).count();
    for j in 0..n {
        for i in 0..n {
            vals.clear();
            for (f, p) in o.frames.iter().zip(&anchors) {
                let Some(p) = p else { continue };
                let x = p.0 + mid.0 + i as f64 - h as f64;
                let y = p.1 + mid.1 + j as f64 - h as f64;
                if let Some(v) = sample(f, x, y) {
                    vals.push(v);
                }
            }
            if !vals.is_empty() {
                vals.sort_by(|a, b| a.total_cmp(b));
                let q = vals.len();
                pix[j * n + i] = if q % 2 == 1 {
                    vals[q / 2]
                } else {
                    0.5 * (vals[q / 2 - 1] + vals[q / 2])
                };
            }
        }
    }
    let pa = (h as f64 - mid.0, h as f64 - mid.1);
    let mut stars = vec![pa];
    if let Some(r) = rel {
        stars.push((pa.0 + r.0, pa.1 + r.1));
    }
    Some(Stack { n, pix, stars, used })
}

/// asinh stretch parameters (low, soft, high) shared by the tiles of one orientation.
fn stretch(stacks: &[&Stack]) -> (f32, f32, f32) {
    let mut all: Vec<f64> = stacks
        .iter()
        .flat_map(|s| s.pix.iter())
        .filter(|v| v.is_finite())
        .map(|&v| v as f64)
        .collect();
    let Some(bg) = median(&mut all) else {
        return (0.0, 1.0, 1.0);
    };
    let mut dev: Vec<f64> = all.iter().map(|v| (v - bg).abs()).collect();
    let noise = 1.4826 * median(&mut dev).unwrap_or(0.0);
    let peak = all.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lo = bg - noise;
    let span = (peak - lo).max(1e-6);
    let soft = (3.0 * noise).max(span * 1e-2).max(1e-9);
    (lo as f32, soft as f32, (peak) as f32)
}

/// Paint a tile (nearest-neighbour upscaling, row 0 of the stack at the bottom).
fn paint_tile(buf: &mut [u8], width: u32, x0: u32, y0: u32, s: &Stack, (lo, soft, hi): (f32, f32, f32)) {
    let norm = ((hi - lo) / soft).asinh().max(1e-6);
    let n = s.n;
    for py in 0..TILE {
        let row = n - 1 - ((py as usize * n) / TILE as usize).min(n - 1);
        for px in 0..TILE {
            let col = ((px as usize * n) / TILE as usize).min(n - 1);
            let v = s.pix[row * n + col];
            let rgb = if v.is_finite() {
                let t = (((v - lo) / soft).asinh() / norm).clamp(0.0, 1.0);
                let g = (255.0 * t).round() as u8;
                [g, g, g]
            } else {
                [70, 20, 20]
            };
            let at = (((y0 + py) * width + x0 + px) * 3) as usize;
            if at + 3 <= buf.len() {
                buf[at..at + 3].copy_from_slice(&rgb);
            }
        }
    }
}

/// Tile pixel position of cut-out coordinates (x, y).
fn tile_xy(s: &Stack, x0: u32, y0: u32, (x, y): (f64, f64)) -> (i32, i32) {
    let k = TILE as f64 / s.n as f64;
    (
        x0 as i32 + ((x + 0.5) * k).round() as i32,
        y0 as i32 + (TILE as f64 - (y + 0.5) * k).round() as i32,
    )
}

fn draw_tile_overlay(root: &Area, s: &Stack, x0: u32, y0: u32, ap: f64, beam: &str, posang: f64) -> io::Result<()> {
    let k = TILE as f64 / s.n as f64;
    let r = if ap.is_finite() && ap > 0.0 {
        (ap * k).round().max(2.0) as i32
    } else {
        (3.0 * k) as i32
    };
    let centre = s.stars.iter().fold((0.0, 0.0), |a, p| {
        (a.0 + p.0 / s.stars.len() as f64, a.1 + p.1 / s.stars.len() as f64)
    });
    for (c, &p) in s.stars.iter().enumerate() {
        let (x, y) = tile_xy(s, x0, y0, p);
        let col = comp_color(c, true);
        root.draw(&Circle::new((x, y), r, col.stroke_width(2))).map_err(de)?;
        // Label on the side away from the other star (up-right for a single star).
        let (mut dx, mut dy) = (p.0 - centre.0, -(p.1 - centre.1));
        let len = dx.hypot(dy);
        if len < 1e-6 {
            (dx, dy) = (0.7, -0.7);
        } else {
            (dx, dy) = (dx / len, dy / len);
        }
        let d = r as f64 + 11.0;
        let at = ((x as f64 + dx * d) as i32, (y as f64 + dy * d) as i32);
        let style = (FONT, 17)
            .into_font()
            .style(FontStyle::Bold)
            .color(&col)
            .pos(Pos::new(HPos::Center, VPos::Center));
        root.draw(&Text::new(COMP_NAMES[c.min(1)], at, style)).map_err(de)?;
    }
    let lab = (FONT, 15).into_font().color(&WHITE);
    root.draw(&Text::new(
        beam.to_string(),
        (x0 as i32 + 6, y0 as i32 + 4),
        lab.clone(),
    ))
    .map_err(de)?;
    let sz = (FONT, 11)
        .into_font()
        .color(&RGBColor(200, 200, 200))
        .pos(Pos::new(HPos::Left, VPos::Bottom));
    root.draw(&Text::new(
        format!("{0}×{0} px", s.n),
        (x0 as i32 + 5, (y0 + TILE) as i32 - 3),
        sz,
    ))
    .map_err(de)?;
    // Compass: PA psi is along detector (-sin(psi - theta), cos(psi - theta)).
    if posang.is_finite() {
        let c = ((x0 + TILE) as i32 - 30, (y0 + TILE) as i32 - 30);
        for (psi, name) in [(0.0f64, "N"), (90.0, "E")] {
            let a = (psi - posang).to_radians();
            let (dx, dy) = (-a.sin(), -a.cos()); // screen y down
            let tip = (c.0 + (dx * 14.0) as i32, c.1 + (dy * 14.0) as i32);
            root.draw(&PathElement::new(vec![c, tip], RGBColor(160, 220, 160).stroke_width(1)))
                .map_err(de)?;
            let lp = (c.0 + (dx * 21.0) as i32, c.1 + (dy * 21.0) as i32);
            let st = (FONT, 10)
                .into_font()
                .color(&RGBColor(160, 220, 160))
                .pos(Pos::new(HPos::Center, VPos::Center));
            root.draw(&Text::new(name, lp, st)).map_err(de)?;
        }
    }
    Ok(())
}

fn empty_tile(root: &Area, x0: u32, y0: u32, msg: &str) -> io::Result<()> {
    root.draw(&Rectangle::new(
        [(x0 as i32, y0 as i32), ((x0 + TILE) as i32, (y0 + TILE) as i32)],
        RGBColor(225, 225, 225).filled(),
    ))
    .map_err(de)?;
    let st = (FONT, 13)
        .into_font()
        .color(&RGBColor(90, 90, 90))
        .pos(Pos::new(HPos::Center, VPos::Center));
    root.draw(&Text::new(
        msg.to_string(),
        ((x0 + TILE / 2) as i32, (y0 + TILE / 2) as i32),
        st,
    ))
    .map_err(de)?;
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Per-dither F

fn f_panel(
    root: &Area,
    x0: u32,
    y0: u32,
    w: u32,
    h: u32,
    m: &Measured,
    k: usize,
    phi: f64,
    target: &Target,
) -> io::Result<()> {
    let area = root.clone().shrink((x0, y0), (w, h));
    let per: Vec<&[DitherValue]> = m
        .dithers
        .iter()
        .filter_map(|c| c.get(k).map(|v| v.as_slice()))
        .collect();
    let nd = per.iter().map(|v| v.len()).max().unwrap_or(0);
    // Model F from the fitted q, u of each component.
    let model: Vec<Option<f64>> = (0..per.len())
        .map(|c| {
            let comp: &Component = target.components.get(c)?;
            let t = 2.0 * phi.to_radians();
            let v = comp.q * t.cos() + comp.u * t.sin();
            v.is_finite().then_some(100.0 * v)
        })
        .collect();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for d in per.iter().flat_map(|v| v.iter()) {
        let (f, s) = (100.0 * d.f, 100.0 * d.sigma_f);
        if f.is_finite() && f.abs() < 200.0 {
            let s = if s.is_finite() && s < 100.0 { s } else { 0.0 };
            lo = lo.min(f - s);
            hi = hi.max(f + s);
        }
    }
    for v in model.iter().flatten() {
        lo = lo.min(*v);
        hi = hi.max(*v);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        (lo, hi) = (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.12).max(0.05);
    let (lo, hi) = (lo - pad, hi + pad);
    let xmax = nd.max(1) as f64 + 0.5;
    let mut chart = ChartBuilder::on(&area)
        .margin_right(8)
        .margin_top(4)
        .x_label_area_size(34)
        .y_label_area_size(52)
        .build_cartesian_2d(0.5..xmax, lo..hi)
        .map_err(de)?;
    let xfmt = |v: &f64| {
        if (v - v.round()).abs() < 1e-6 {
            format!("{}", v.round() as i64)
        } else {
            String::new()
        }
    };
    let yfmt = |v: &f64| super::tick(*v);
    chart
        .configure_mesh()
        .x_labels(nd.max(1) + 1)
        .y_labels(6)
        .x_label_formatter(&xfmt)
        .y_label_formatter(&yfmt)
        .x_desc("dither")
        .y_desc("F = (o−e)/(o+e) [%]")
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 13))
        .light_line_style(RGBColor(240, 240, 240))
        .bold_line_style(RGBColor(215, 215, 215))
        .draw()
        .map_err(de)?;
    let nc = per.len();
    for (c, vals) in per.iter().enumerate() {
        let col = comp_color(c, false);
        if let Some(v) = model[c] {
            chart
                .draw_series(DashedLineSeries::new(
                    vec![(0.5, v), (xmax, v)],
                    6,
                    4,
                    col.mix(0.8).stroke_width(1),
                ))
                .map_err(de)?;
        }
        let shift = if nc > 1 {
            (c as f64 - 0.5 * (nc - 1) as f64) * 0.14
        } else {
            0.0
        };
        for (i, d) in vals.iter().enumerate() {
            let (f, s) = (100.0 * d.f, 100.0 * d.sigma_f);
            if !f.is_finite() {
                continue;
            }
            let f = f.clamp(lo, hi);
            let x = i as f64 + 1.0 + shift;
            let rej = d.rejected.is_some();
            let ecol = if rej { REJECT } else { col };
            if s.is_finite() && s > 0.0 {
                let (a, b) = ((f - s).max(lo), (f + s).min(hi));
                chart
                    .draw_series(std::iter::once(PathElement::new(
                        vec![(x, a), (x, b)],
                        ecol.stroke_width(1),
                    )))
                    .map_err(de)?;
                for y in [a, b] {
                    chart
                        .draw_series(std::iter::once(PathElement::new(
                            vec![(x - 0.05, y), (x + 0.05, y)],
                            ecol.stroke_width(1),
                        )))
                        .map_err(de)?;
                }
            }
            if rej {
                chart
                    .draw_series(std::iter::once(Circle::new((x, f), 4, WHITE.filled())))
                    .map_err(de)?;
                chart
                    .draw_series(std::iter::once(Circle::new((x, f), 4, REJECT.stroke_width(2))))
                    .map_err(de)?;
            } else {
                chart
                    .draw_series(std::iter::once(Circle::new((x, f), 4, col.filled())))
                    .map_err(de)?;
            }
        }
    }
    if nd == 0 {
        let st = (FONT, 13)
            .into_font()
            .color(&RGBColor(120, 120, 120))
            .pos(Pos::new(HPos::Center, VPos::Center));
        area.draw(&Text::new("no per-dither values", ((w / 2) as i32, (h / 2) as i32), st))
            .map_err(de)?;
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Polarization on the sky

fn nice_ceil(v: f64) -> f64 {
    if !(v > 0.0 && v.is_finite()) {
        return 1.0;
    }
    let e = 10f64.powf(v.log10().floor());
    for k in [1.0, 2.0, 2.5, 5.0, 10.0] {
        if k * e >= v * (1.0 - 1e-9) {
            return k * e;
        }
    }
    10.0 * e
}

/// Screen direction (y down) for a star's label: off the polarization vector's axis
/// (`gamma_deg` east of north, drawn with north up and east left) and away from the other
/// star.
fn label_dir(star: (f64, f64), other: Option<(f64, f64)>, gamma_deg: Option<f64>) -> (f64, f64) {
    let away = other.map(|o| {
        let (dx, dy) = (star.0 - o.0, star.1 - o.1);
        let l = dx.hypot(dy).max(1e-9);
        (dx / l, dy / l)
    });
    let mut best = (f64::NEG_INFINITY, (0.7, 0.7));
    for k in 0..16 {
        let a = (k as f64 * 22.5).to_radians();
        let d = (a.cos(), a.sin());
        let mut score = 0.0;
        if let Some(g) = gamma_deg {
            // Angle between the label direction and the (axial) vector, 0..90 deg.
            let gv = (-g.to_radians().sin(), -g.to_radians().cos());
            let c = (d.0 * gv.0 + d.1 * gv.1).abs().min(1.0);
            score += c.acos().to_degrees();
        }
        if let Some(w) = away {
            score += 40.0 * (d.0 * w.0 + d.1 * w.1);
        }
        // Slight preference for the right-hand side (text reads better there).
        score += 2.0 * d.0;
        if score > best.0 {
            best = (score, d);
        }
    }
    best.1
}

fn pol_panel(root: &Area, x0: u32, y0: u32, s: u32, target: &Target, m: Option<&Measured>) -> io::Result<()> {
    let (x0i, y0i, si) = (x0 as i32, y0 as i32, s as i32);
    let title = (FONT, 16)
        .into_font()
        .style(FontStyle::Bold)
        .color(&BLACK)
        .pos(Pos::new(HPos::Center, VPos::Top));
    root.draw(&Text::new("Polarization on the sky", (x0i + si / 2, y0i), title))
        .map_err(de)?;
    let top = y0i + 24;
    let side = si - 24;
    let left = x0i + (si - side) / 2;
    root.draw(&Rectangle::new(
        [(left, top), (left + side, top + side)],
        RGBColor(250, 250, 250).filled(),
    ))
    .map_err(de)?;
    root.draw(&Rectangle::new(
        [(left, top), (left + side, top + side)],
        RGBColor(150, 150, 150).stroke_width(1),
    ))
    .map_err(de)?;
    let grey = RGBColor(110, 110, 110);
    // Compass, top left: north up, east left.
    let c = (left + 54, top + 46);
    for ((dx, dy), name) in [((0, -26), "N"), ((-26, 0), "E")] {
        let tip = (c.0 + dx, c.1 + dy);
        root.draw(&PathElement::new(vec![c, tip], grey.stroke_width(2)))
            .map_err(de)?;
        let lp = (c.0 + dx * 3 / 2 - if dx != 0 { 2 } else { 0 }, c.1 + dy * 3 / 2);
        root.draw(&Text::new(
            name,
            lp,
            (FONT, 13)
                .into_font()
                .color(&grey)
                .pos(Pos::new(HPos::Center, VPos::Center)),
        ))
        .map_err(de)?;
    }
    let comps = &target.components;
    if comps.is_empty() {
        let st = (FONT, 14)
            .into_font()
            .color(&grey)
            .pos(Pos::new(HPos::Center, VPos::Center));
        root.draw(&Text::new(
            "no polarization measured",
            (left + side / 2, top + side / 2),
            st,
        ))
        .map_err(de)?;
        return Ok(());
    }
    let cx = (left + side / 2) as f64;
    let cy = (top + side / 2) as f64;
    let geometry = m
        .and_then(|m| m.geometry)
        .filter(|g| g.0.is_finite() && g.1.is_finite());
    let dstar = 0.40 * side as f64;
    let pos: Vec<(f64, f64)> = match comps.len() {
        1 => vec![(cx, cy)],
        _ => {
            let (ux, uy) = match geometry {
                Some((_, pa)) => (-pa.to_radians().sin(), -pa.to_radians().cos()),
                None => (1.0, 0.0),
            };
            let a = (cx - ux * dstar / 2.0, cy - uy * dstar / 2.0);
            let b = (cx + ux * dstar / 2.0, cy + uy * dstar / 2.0);
            let mut v = vec![a, b];
            v.extend((2..comps.len()).map(|_| (cx, cy)));
            v
        }
    };
    let ps: Vec<f64> = comps
        .iter()
        .map(|c| c.p)
        .filter(|p| p.is_finite() && *p > 0.0 && *p < 1.0)
        .collect();
    let pmax = ps.iter().copied().fold(0.0, f64::max);
    let scale_p = nice_ceil(pmax);
    let full = if comps.len() == 1 { 0.7 } else { 0.38 } * side as f64; // length of a scale_p vector
    for (i, comp) in comps.iter().enumerate().take(2) {
        let col = comp_color(i, false);
        let (sx, sy) = pos[i];
        let ok = comp.p.is_finite() && comp.p > 0.0 && comp.p < 1.0 && comp.gamma_deg.is_finite();
        if ok {
            let half = 0.5 * full * comp.p / scale_p;
            let g = comp.gamma_deg.to_radians();
            let (dx, dy) = (-g.sin(), -g.cos()); // east left, north up (screen y down)
                                                 // Error wedge ±sigma_gamma, both ends (axial).
            let sg = if comp.sigma_gamma_deg.is_finite() {
                comp.sigma_gamma_deg.clamp(0.0, 90.0)
            } else {
                90.0
            };
            let rw = half.max(10.0);
            if sg > 0.05 {
                for end in [0.0, 180.0] {
                    let mut poly = vec![(sx as i32, sy as i32)];
                    let steps = ((2.0 * sg / 3.0).ceil() as usize).clamp(2, 60);
                    for t in 0..=steps {
                        let a = (comp.gamma_deg + end - sg + 2.0 * sg * t as f64 / steps as f64).to_radians();
                        poly.push(((sx - rw * a.sin()).round() as i32, (sy - rw * a.cos()).round() as i32));
                    }
                    root.draw(&Polygon::new(poly, col.mix(0.22).filled())).map_err(de)?;
                }
            }
            let a = ((sx - dx * half).round() as i32, (sy - dy * half).round() as i32);
            let b = ((sx + dx * half).round() as i32, (sy + dy * half).round() as i32);
            let style = if comp.passes_cut {
                col.stroke_width(4)
            } else {
                col.mix(0.55).stroke_width(3)
            };
            root.draw(&PathElement::new(vec![a, b], style)).map_err(de)?;
        }
        root.draw(&Circle::new((sx as i32, sy as i32), 6, col.filled()))
            .map_err(de)?;
        root.draw(&Circle::new((sx as i32, sy as i32), 6, BLACK.stroke_width(1)))
            .map_err(de)?;
        // Name next to the star: away from the other star and off the vector's axis.
        let other = if pos.len() > 1 { Some(pos[1 - i.min(1)]) } else { None };
        let axis = if ok { Some(comp.gamma_deg) } else { None };
        let (ox, oy) = label_dir((sx, sy), other, axis);
        let lp = ((sx + ox * 22.0) as i32, (sy + oy * 22.0) as i32);
        let st = (FONT, 17)
            .into_font()
            .style(FontStyle::Bold)
            .color(&col)
            .pos(Pos::new(HPos::Center, VPos::Center));
        root.draw(&Text::new(comp.name.clone(), lp, st)).map_err(de)?;
        if !ok {
            let st = (FONT, 12)
                .into_font()
                .color(&col)
                .pos(Pos::new(HPos::Center, VPos::Top));
            root.draw(&Text::new("P undefined", ((sx) as i32, (sy + 10.0) as i32), st))
                .map_err(de)?;
        }
    }
    // Scale bar, bottom left.
    let bar = (if comps.len() == 1 { 0.7 } else { 0.38 } * side as f64 * 0.5).round() as i32;
    let by = top + side - 18;
    let bx = left + 14;
    root.draw(&PathElement::new(vec![(bx, by), (bx + bar, by)], BLACK.stroke_width(3)))
        .map_err(de)?;
    let st = (FONT, 13)
        .into_font()
        .color(&BLACK)
        .pos(Pos::new(HPos::Left, VPos::Center));
    root.draw(&Text::new(
        format!("P = {} %", super::tick(50.0 * scale_p)),
        (bx + bar + 8, by),
        st,
    ))
    .map_err(de)?;
    let st = (FONT, 12)
        .into_font()
        .color(&grey)
        .pos(Pos::new(HPos::Right, VPos::Bottom));
    let note = match (comps.len(), geometry) {
        (1, _) => "wedge: ±σγ".to_string(),
        (_, Some((sep, pa))) => format!("B at ρ = {sep:.2}″, PA {pa:.1}° (not to scale); wedge ±σγ"),
        (_, None) => "B position unknown; wedge ±σγ".to_string(),
    };
    root.draw(&Text::new(note, (left + side - 6, top + side - 34), st))
        .map_err(de)?;
    Ok(())
}

// ---------------------------------------------------------------------------------------
// The figure

fn render(
    target: &Target,
    cal: Option<&[CalibratedOrientation]>,
    m: Option<&Measured>,
) -> io::Result<(u32, u32, Vec<u8>)> {
    let cal = cal.unwrap_or(&[]);
    let n_or = match m {
        Some(m) => cal.len().max(
            m.dithers
                .first()
                .filter(|c| c.iter().any(|o| !o.is_empty()))
                .map(|c| c.len())
                .unwrap_or(0),
        ),
        None => 0,
    }
    .min(16);
    let rows = n_or.div_ceil(2) as u32;
    let body_h = if n_or == 0 {
        70
    } else {
        (rows * CELL_H).max(POL_S + 26) + 10
    };

    // Text band: three columns.
    let mut cols: [Vec<Line>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    component_lines(target, &mut cols[0]);
    measurement_lines(target, Some(cal), m, &mut cols[1]);
    status_lines(target, m, &mut cols[2]);
    for c in cols.iter_mut() {
        c.truncate(40);
    }
    let nlines = cols.iter().map(|c| c.len()).max().unwrap_or(1) as u32;
    let band_h = nlines * LINE_H + 20;
    let (w, h) = (WIDTH, TITLE_H + body_h + band_h);

    let mut buf = vec![255u8; (w * h * 3) as usize];
    // Grey-scale cut-outs go straight into the buffer; overlays are drawn afterwards.
    struct Cell {
        x: u32,
        y: u32,
        tiles: [Option<Stack>; 2],
    }
    let mut cells: Vec<Cell> = Vec::new();
    for k in 0..n_or {
        let x = (k as u32 % 2) * CELL_W + 8;
        let y = TITLE_H + (k as u32 / 2) * CELL_H;
        let tiles = match (cal.get(k), m) {
            (Some(o), Some(m)) => [stack(o, m, k, false), stack(o, m, k, true)],
            _ => [None, None],
        };
        let refs: Vec<&Stack> = tiles.iter().flatten().collect();
        let st = stretch(&refs);
        for (b, t) in tiles.iter().enumerate() {
            if let Some(t) = t {
                paint_tile(&mut buf, w, x + b as u32 * (TILE + TILE_GAP), y + CELL_LABEL_H, t, st);
            }
        }
        cells.push(Cell { x, y, tiles });
    }

    {
        let root: Area = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        // Title band.
        root.draw(&Rectangle::new(
            [(0, 0), (w as i32, TITLE_H as i32 - 6)],
            RGBColor(240, 243, 247).filled(),
        ))
        .map_err(de)?;
        let title = format!("{}  —  {}", target.object, status_word(target.status));
        let st = (FONT, 24)
            .into_font()
            .style(FontStyle::Bold)
            .color(&BLACK)
            .pos(Pos::new(HPos::Left, VPos::Center));
        root.draw(&Text::new(title.clone(), (14, (TITLE_H as i32 - 6) / 2), st))
            .map_err(de)?;
        let tw = FontDesc::new(FontFamily::Name(FONT), 24.0, FontStyle::Bold)
            .box_size(&title)
            .map(|s| s.0)
            .unwrap_or(300) as i32;
        root.draw(&Circle::new(
            (tw + 28, (TITLE_H as i32 - 6) / 2),
            8,
            status_color(target.status).filled(),
        ))
        .map_err(de)?;
        if let Some(seq) = target.extra.get("sequence").and_then(|v| v.as_str()) {
            let st = (FONT, 14)
                .into_font()
                .color(&RGBColor(90, 90, 90))
                .pos(Pos::new(HPos::Right, VPos::Center));
            root.draw(&Text::new(
                seq.to_string(),
                (w as i32 - 14, (TITLE_H as i32 - 6) / 2),
                st,
            ))
            .map_err(de)?;
        }

        if n_or == 0 {
            let msg = match (cal.is_empty(), m.is_none()) {
                (true, _) => "No calibrated frames to show (the reduction stopped before photometry).",
                (false, true) => "No measurement to show.",
                _ => "No orientation measured.",
            };
            let st = (FONT, 18)
                .into_font()
                .color(&RGBColor(110, 110, 110))
                .pos(Pos::new(HPos::Left, VPos::Center));
            root.draw(&Text::new(msg, (14, (TITLE_H + body_h / 2) as i32), st))
                .map_err(de)?;
        }

        for (k, cell) in cells.iter().enumerate() {
            let o = cal.get(k);
            let posang = o.map(|o| o.posang_deg).unwrap_or(f64::NAN);
            let phi = o.map(|o| o.analyzer_deg).unwrap_or(f64::NAN);
            let nfr = o.map(|o| o.frames.len()).unwrap_or(0);
            let used = cell.tiles.iter().flatten().map(|t| t.used).max().unwrap_or(0);
            let label = format!("POSANG {}°   (φ = {}°)", fmt(posang, 1), fmt(phi, 1));
            let st = (FONT, 15).into_font().style(FontStyle::Bold).color(&BLACK);
            root.draw(&Text::new(label, (cell.x as i32 + 2, cell.y as i32 + 3), st))
                .map_err(de)?;
            let st = (FONT, 12)
                .into_font()
                .color(&RGBColor(90, 90, 90))
                .pos(Pos::new(HPos::Right, VPos::Top));
            let right = (cell.x + 2 * TILE + TILE_GAP) as i32;
            root.draw(&Text::new(
                format!("median of {used}/{nfr} dithers"),
                (right, cell.y as i32 + 5),
                st,
            ))
            .map_err(de)?;
            let ap = m.map(|m| m.aperture_px).unwrap_or(f64::NAN);
            for (b, t) in cell.tiles.iter().enumerate() {
                let tx = cell.x + b as u32 * (TILE + TILE_GAP);
                let ty = cell.y + CELL_LABEL_H;
                let beam = if b == 0 { "o" } else { "e" };
                match t {
                    Some(t) => draw_tile_overlay(&root, t, tx, ty, ap, beam, posang)?,
                    None if nfr == 0 => empty_tile(&root, tx, ty, &format!("{beam}: no frames"))?,
                    None => empty_tile(&root, tx, ty, &format!("{beam}: no position measured"))?,
                }
            }
            if let Some(m) = m {
                f_panel(
                    &root,
                    cell.x,
                    cell.y + CELL_LABEL_H + TILE + 6,
                    2 * TILE + TILE_GAP,
                    F_H,
                    m,
                    k,
                    phi,
                    target,
                )?;
            }
        }
        if n_or > 0 {
            pol_panel(&root, POL_X, TITLE_H, POL_S, target, m)?;
        }

        // Text band.
        let ty = TITLE_H + body_h;
        root.draw(&PathElement::new(
            vec![(8, ty as i32 - 4), (w as i32 - 8, ty as i32 - 4)],
            RGBColor(200, 200, 200).stroke_width(1),
        ))
        .map_err(de)?;
        for (c, lines) in cols.iter().enumerate() {
            for (i, l) in lines.iter().enumerate() {
                let style = if l.bold { FontStyle::Bold } else { FontStyle::Normal };
                let st = FontDesc::new(FontFamily::Name(FONT), TEXT_FONT as f64, style).color(&l.color);
                root.draw(&Text::new(
                    l.text.clone(),
                    (COL_X[c] as i32, (ty + 6 + i as u32 * LINE_H) as i32),
                    st,
                ))
                .map_err(de)?;
            }
        }
        root.present().map_err(de)?;
    }
    Ok((w, h, buf))
}
