//! The per-target diagnostic figure: what one reduced sequence looks like, on one PNG.
//!
//! ```text
//! +--------------------------------------------------------------------------+
//! | object — status — sequence                                                |
//! +----------------------------------+----------------------------------+----+
//! | POSANG 0°: o cut-out | e cut-out | POSANG 45°: o cut-out | e cut-out |    |
//! |  (median of the registered dithers, asinh stretch, apertures A/B)    | pol|
//! | F per dither (error bars, rejected | F per dither ...                 | on |
//! |  hollow red, dashed: model of F)   |                                  | sky|
//! +----------------------------------+----------------------------------+----+
//! | polarization table | measurement details | status, error, flags           |
//! +--------------------------------------------------------------------------+
//! ```
//!
//! Cut-outs are in detector orientation (row 0 of the frame at the bottom, as in DS9),
//! labelled with POSANG and a small N/E compass. Each orientation's F panel draws each star's
//! model of F there, q cos 2phi + u sin 2phi + c + T (dashed), T the telescope's term at that
//! orientation's parallactic angle when the calibration removed it from the star, and then the
//! model without T (dotted), T written above the plot: T turns with the parallactic angle, so
//! the model is one value per orientation, not one curve of phi. The polarization panel is on
//! the sky (north up, east left). Orientations are laid out two per row. A target without
//! frames or measurements (failed) gets a text-only figure. Rendering never panics: a drawing
//! failure falls back to a text-only figure. The width is fixed ([`WIDTH`]); the height
//! depends on the number of orientations and lines of text.
mod figure;
mod panels;
mod text;
mod tiles;

pub use figure::{ComponentNumbers, FigureInputs, FigureNumbers, OrientationSketch, TargetFigure};

use std::io;
use std::path::Path;

use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::FontStyle;
use sofipol_calib::frame::mask as mbits;
use sofipol_calib::Frame;

use super::{ensure_font, write_atomic, Error, FONT};
use crate::catalog::flags::join;
use crate::catalog::{Flag, Status, Target};
use crate::reduce::run::TargetOutcome;
use crate::reduce::{DitherValue, Measured, SkySubtractedOrientation};
use panels::*;
use text::*;
use tiles::*;

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

type Area<'a> = DrawingArea<crate::plots::glyphs::CachedText<'a>, plotters::coord::Shift>;

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

/// Write the diagnostic figure of one reduced target to `path` (atomically), with the
/// numbers of `target` as given (no calibration).
pub fn target_png(path: &Path, target: &Target, cal: &[SkySubtractedOrientation], m: &Measured) -> io::Result<()> {
    target_png_opt(path, target, Some(cal), Some(m))
}

/// [`target_png`] of a [`TargetOutcome`] (kept frames and measurements when present; a
/// failed target gets the text-only figure). The numbers are the outcome's, before any
/// calibration: a night draws its figures from the calibrated catalog instead
/// ([`TargetFigure`]).
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
    cal: Option<&[SkySubtractedOrientation]>,
    m: Option<&Measured>,
) -> io::Result<()> {
    let inputs = FigureInputs::new(cal, m);
    TargetFigure {
        target,
        inputs: &inputs,
        calibration: None,
    }
    .png(path)
}

/// Render the figure to an RGB8 buffer (width, height, pixels). Falls back to a text-only
/// figure when the full one cannot be drawn.
pub fn render_target_rgb(
    target: &Target,
    cal: Option<&[SkySubtractedOrientation]>,
    m: Option<&Measured>,
) -> io::Result<(u32, u32, Vec<u8>)> {
    let inputs = FigureInputs::new(cal, m);
    TargetFigure {
        target,
        inputs: &inputs,
        calibration: None,
    }
    .rgb()
}

// ---------------------------------------------------------------------------------------
// The figure

/// Draw the figure of `target` from the prepared pixels `inputs` and the catalog values
/// `nums` (every number drawn comes from `nums`).
fn render(target: &Target, inputs: &FigureInputs, nums: &FigureNumbers) -> io::Result<(u32, u32, Vec<u8>)> {
    let m = inputs.measured.as_ref();
    let ors = &inputs.orientations;
    let n_or = ors.len();
    let rows = n_or.div_ceil(2) as u32;
    let body_h = if n_or == 0 {
        70
    } else {
        (rows * CELL_H).max(POL_S + 26) + 10
    };

    // Text band: three columns.
    let mut cols: [Vec<Line>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    component_lines(nums, &mut cols[0]);
    measurement_lines(target, ors, nums, m, &mut cols[1]);
    status_lines(target, m, &mut cols[2]);
    for c in cols.iter_mut() {
        c.truncate(40);
    }
    let nlines = cols.iter().map(|c| c.len()).max().unwrap_or(1) as u32;
    let band_h = nlines * LINE_H + 20;
    let (w, h) = (WIDTH, TITLE_H + body_h + band_h);

    let mut buf = vec![255u8; (w * h * 3) as usize];
    // Grey-scale cut-outs go straight into the buffer; overlays are drawn afterwards.
    let mut cells: Vec<Cell> = Vec::new();
    for (k, o) in ors.iter().enumerate() {
        let x = (k as u32 % 2) * CELL_W + 8;
        let y = TITLE_H + (k as u32 / 2) * CELL_H;
        let refs: Vec<&Stack> = o.tiles.iter().flatten().collect();
        let st = stretch(&refs);
        for (b, t) in o.tiles.iter().enumerate() {
            if let Some(t) = t {
                paint_tile(&mut buf, w, x + b as u32 * (TILE + TILE_GAP), y + CELL_LABEL_H, t, st);
            }
        }
        cells.push(Cell { x, y });
    }

    {
        let root: Area = crate::plots::glyphs::CachedText::with_buffer(&mut buf, (w, h)).into_drawing_area();
        draw_title(&root, target, w)?;

        if n_or == 0 {
            let msg = match m {
                None => "No calibrated frames to show (the reduction stopped before photometry).",
                Some(_) => "No orientation measured.",
            };
            let st = (FONT, 18)
                .into_font()
                .color(&RGBColor(110, 110, 110))
                .pos(Pos::new(HPos::Left, VPos::Center));
            root.draw(&Text::new(msg, (14, (TITLE_H + body_h / 2) as i32), st))
                .map_err(de)?;
        }

        for (k, cell) in cells.iter().enumerate() {
            draw_cell(&root, cell, k, &ors[k], nums, m)?;
        }
        if n_or > 0 {
            pol_panel(&root, POL_X, TITLE_H, POL_S, nums, m)?;
        }

        draw_text_band(&root, &cols, TITLE_H + body_h, w)?;
        root.present().map_err(de)?;
    }
    Ok((w, h, buf))
}

/// Where one orientation's cell (two tiles, o and e, and the F panel below them) goes.
struct Cell {
    x: u32,
    y: u32,
}

/// The title band: object, status word and colour, sequence id.
fn draw_title(root: &Area, target: &Target, w: u32) -> io::Result<()> {
    // Title band.
    root.draw(&Rectangle::new(
        [(0, 0), (w as i32, TITLE_H as i32 - 6)],
        RGBColor(240, 243, 247).filled(),
    ))
    .map_err(de)?;
    let title = format!("{}  —  {}", target.object, status_word(target.status));
    let st = FontDesc::new(FontFamily::Name(FONT), 24.0, FontStyle::Bold)
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
    if let Some(seq) = &target.sequence {
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
    Ok(())
}

/// Labels, tile overlays and the F panel of orientation `k`.
fn draw_cell(
    root: &Area,
    cell: &Cell,
    k: usize,
    o: &OrientationSketch,
    nums: &FigureNumbers,
    m: Option<&Measured>,
) -> io::Result<()> {
    let posang = o.posang_deg;
    let phi = nums.analyzer_deg.get(k).copied().unwrap_or(f64::NAN);
    let nfr = o.n_frames;
    let used = o.tiles.iter().flatten().map(|t| t.used).max().unwrap_or(0);
    let label = format!("POSANG {}°   (φ = {}°)", fmt(posang, 1), fmt(phi, 1));
    let st = FontDesc::new(FontFamily::Name(FONT), 15.0, FontStyle::Bold).color(&BLACK);
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
    for (b, t) in o.tiles.iter().enumerate() {
        let tx = cell.x + b as u32 * (TILE + TILE_GAP);
        let ty = cell.y + CELL_LABEL_H;
        let beam = if b == 0 { "o" } else { "e" };
        match t {
            Some(t) => draw_tile_overlay(root, t, tx, ty, ap, beam, posang)?,
            None if nfr == 0 => empty_tile(root, tx, ty, &format!("{beam}: no frames"))?,
            None => empty_tile(root, tx, ty, &format!("{beam}: no position measured"))?,
        }
    }
    if let Some(m) = m {
        let place = PanelPlace {
            x0_px: cell.x,
            y0_px: cell.y + CELL_LABEL_H + TILE + 6,
            w_px: 2 * TILE + TILE_GAP,
            h_px: F_H,
        };
        f_panel(root, place, m, k, nums)?;
    }
    Ok(())
}

/// The text band at height `ty`: three columns of lines.
fn draw_text_band(root: &Area, cols: &[Vec<Line>; 3], ty: u32, w: u32) -> io::Result<()> {
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
    Ok(())
}

#[cfg(test)]
mod tests;
