//! The cut-out tiles: median of the registered dithers per beam, stretch, apertures and labels.
use super::*;

/// Median of the registered dithers of one beam around the binary.
#[derive(Clone)]
pub(super) struct Stack {
    /// Side, px (odd).
    pub(super) n: usize,
    /// Values, row 0 at the bottom; NaN where nothing usable.
    pub(super) pix: Vec<f32>,
    /// Component positions in cut-out pixel coordinates.
    pub(super) stars: Vec<(f64, f64)>,
    /// Dithers that went into the stack.
    pub(super) used: usize,
}

#[cfg(test)]
pub(super) fn sample(f: &Frame, x: f64, y: f64) -> Option<f32> {
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

/// The `n x n` window of `f` whose pixel (0, 0) is at `origin` (x, y), bilinearly
/// interpolated as [`sample`] does (a tap of zero weight is not read; a masked or non-finite
/// tap gives nothing), row 0 first; NaN where it gives nothing. One set of weights serves
/// the whole window: it moves by whole pixels.
pub(super) fn window(f: &Frame, origin: (f64, f64), n: usize) -> Vec<f32> {
    let mut out = vec![f32::NAN; n * n];
    let (ny, nx) = f.shape();
    if !(origin.0.is_finite() && origin.1.is_finite()) || nx == 0 || ny == 0 {
        return out;
    }
    let (bx, by) = (origin.0.floor(), origin.1.floor());
    let (fx, fy) = ((origin.0 - bx) as f32, (origin.1 - by) as f32);
    let (bx, by) = (bx as i64, by as i64);
    let bad = mbits::BAD | mbits::COSMIC | mbits::OFF_STRIP;
    let w = [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy];
    // Row-major slices (a copy only for a frame not in standard layout, never one read
    // from a file).
    let (data, mask) = (f.data.as_standard_layout(), f.mask.as_standard_layout());
    let (data, mask) = (
        data.as_slice().expect("standard layout"),
        mask.as_slice().expect("standard layout"),
    );
    let tap = |k: usize| -> Option<f32> {
        let d = data[k];
        (mask[k] & bad == 0 && d.is_finite()).then_some(d)
    };
    for (j, row) in out.chunks_exact_mut(n).enumerate() {
        let y0 = by + j as i64;
        // The point's y within [0, ny - 1]: y0 >= 0 and y0 + fy <= ny - 1.
        if y0 < 0 || y0 > ny as i64 - 1 || (y0 == ny as i64 - 1 && fy > 0.0) {
            continue;
        }
        let r0 = y0 as usize * nx;
        let r1 = (y0 as usize + 1).min(ny - 1) * nx;
        for (i, v) in row.iter_mut().enumerate() {
            let x0 = bx + i as i64;
            if x0 < 0 || x0 > nx as i64 - 1 || (x0 == nx as i64 - 1 && fx > 0.0) {
                continue;
            }
            let x0 = x0 as usize;
            let x1 = (x0 + 1).min(nx - 1);
            // A tap of zero weight is not read (as in `sample`).
            let value = (|| {
                let mut acc = w[0] * tap(r0 + x0)?;
                if w[1] > 0.0 {
                    acc += w[1] * tap(r0 + x1)?;
                }
                if w[2] > 0.0 {
                    acc += w[2] * tap(r1 + x0)?;
                }
                if w[3] > 0.0 {
                    acc += w[3] * tap(r1 + x1)?;
                }
                Some(acc)
            })();
            if let Some(s) = value {
                *v = s;
            }
        }
    }
    out
}

pub(super) fn beam_xy(d: &DitherValue, e_beam: bool) -> (f64, f64) {
    if e_beam {
        d.e.xy
    } else {
        d.o.xy
    }
}

/// Median of NaN-free, non-empty `v` (even counts: the mean of the two middle values),
/// reordering it. A stack holds a few dithers: five by a selection network, up to 32
/// sorted by insertion, more by `sort_unstable_by`.
fn median_in_place(v: &mut [f32]) -> f32 {
    // Five dithers, none masked (most pixels): a selection network without branches
    // (the median of e and the two middle candidates of the pairs (a, b), (c, d)).
    if let &mut [a, b, c, d, e] = v {
        let (lo, hi) = (a.min(b).max(c.min(d)), a.max(b).min(c.max(d)));
        return e.min(lo).max(e.max(lo).min(hi));
    }
    if v.len() <= 32 {
        for i in 1..v.len() {
            let x = v[i];
            let mut j = i;
            while j > 0 && v[j - 1] > x {
                v[j] = v[j - 1];
                j -= 1;
            }
            v[j] = x;
        }
    } else {
        v.sort_unstable_by(|a, b| a.total_cmp(b));
    }
    let q = v.len();
    if q % 2 == 1 {
        v[q / 2]
    } else {
        0.5 * (v[q / 2 - 1] + v[q / 2])
    }
}

/// Stack of beam `e_beam` of orientation `k` (None when no dither has a measured position).
pub(super) fn stack(o: &SkySubtractedOrientation, m: &Measured, k: usize, e_beam: bool) -> Option<Stack> {
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
        let (dx, dy): (Vec<f64>, Vec<f64>) = a
            .iter()
            .zip(b)
            .map(|(da, db)| {
                let (pa, pb) = (beam_xy(da, e_beam), beam_xy(db, e_beam));
                (pb.0 - pa.0, pb.1 - pa.1)
            })
            .unzip();
        Some((median(&dx)?, median(&dy)?))
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
    // Each dither's window, sampled row by row (one bilinear weight set per dither: the
    // window moves by whole pixels from one output pixel to the next), then the median
    // over the dithers per pixel.
    let windows: Vec<Vec<f32>> = o
        .frames
        .iter()
        .zip(&anchors)
        .filter_map(|(f, p)| p.map(|p| window(f, (p.0 + mid.0 - h as f64, p.1 + mid.1 - h as f64), n)))
        .collect();
    let used = windows.len();
    let mut pix = vec![f32::NAN; n * n];
    let mut vals = vec![0f32; windows.len()];
    for (k, v) in pix.iter_mut().enumerate() {
        let mut q = 0;
        for w in &windows {
            if !w[k].is_nan() {
                vals[q] = w[k];
                q += 1;
            }
        }
        if q > 0 {
            *v = median_in_place(&mut vals[..q]);
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
pub(super) fn stretch(stacks: &[&Stack]) -> (f32, f32, f32) {
    let all: Vec<f64> = stacks
        .iter()
        .flat_map(|s| s.pix.iter())
        .filter(|v| v.is_finite())
        .map(|&v| v as f64)
        .collect();
    let Some(bg) = median(&all) else {
        return (0.0, 1.0, 1.0);
    };
    let dev: Vec<f64> = all.iter().map(|v| (v - bg).abs()).collect();
    let noise = 1.4826 * median(&dev).unwrap_or(0.0);
    let peak = all.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lo = bg - noise;
    let span = (peak - lo).max(1e-6);
    let soft = (3.0 * noise).max(span * 1e-2).max(1e-9);
    (lo as f32, soft as f32, (peak) as f32)
}

/// Paint a tile (nearest-neighbour upscaling, row 0 of the stack at the bottom).
pub(super) fn paint_tile(buf: &mut [u8], width: u32, x0: u32, y0: u32, s: &Stack, (lo, soft, hi): (f32, f32, f32)) {
    let norm = ((hi - lo) / soft).asinh().max(1e-6);
    let n = s.n;
    // The colour of each cut-out pixel once (a tile pixel repeats its source pixel's; the
    // stretch per tile pixel cost ~(TILE/n)^2 as many asinh).
    let colours: Vec<[u8; 3]> = s
        .pix
        .iter()
        .map(|&v| {
            if v.is_finite() {
                let t = (((v - lo) / soft).asinh() / norm).clamp(0.0, 1.0);
                let g = (255.0 * t).round() as u8;
                [g, g, g]
            } else {
                [70, 20, 20]
            }
        })
        .collect();
    let cols: Vec<usize> = (0..TILE)
        .map(|px| ((px as usize * n) / TILE as usize).min(n - 1))
        .collect();
    // One tile row per source row, copied into every image row it covers (the part inside
    // the image).
    let (x0, width) = (x0 as usize, width as usize);
    let inside = (TILE as usize).min(width.saturating_sub(x0));
    let mut line = vec![0u8; TILE as usize * 3];
    let mut line_of = usize::MAX;
    for py in 0..TILE {
        let row = n - 1 - ((py as usize * n) / TILE as usize).min(n - 1);
        if row != line_of {
            for (px, &col) in line.chunks_exact_mut(3).zip(&cols) {
                px.copy_from_slice(&colours[row * n + col]);
            }
            line_of = row;
        }
        let at = ((y0 + py) as usize * width + x0) * 3;
        if let Some(dst) = buf.get_mut(at..at + inside * 3) {
            dst.copy_from_slice(&line[..inside * 3]);
        }
    }
}

/// Tile pixel position of cut-out coordinates (x, y).
pub(super) fn tile_xy(s: &Stack, x0: u32, y0: u32, (x, y): (f64, f64)) -> (i32, i32) {
    let k = TILE as f64 / s.n as f64;
    (
        x0 as i32 + ((x + 0.5) * k).round() as i32,
        y0 as i32 + (TILE as f64 - (y + 0.5) * k).round() as i32,
    )
}

pub(super) fn draw_tile_overlay(
    root: &Area,
    s: &Stack,
    x0: u32,
    y0: u32,
    ap: f64,
    beam: &str,
    posang: f64,
) -> io::Result<()> {
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
        let style = FontDesc::new(FontFamily::Name(FONT), 17.0, FontStyle::Bold)
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

pub(super) fn empty_tile(root: &Area, x0: u32, y0: u32, msg: &str) -> io::Result<()> {
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

#[cfg(test)]
mod median_tests {
    use super::median_in_place;

    /// The obvious median: sort a copy, take the middle (or the mean of the two middle).
    fn reference(v: &[f32]) -> f32 {
        let mut s = v.to_vec();
        s.sort_by(|a, b| a.total_cmp(b));
        let q = s.len();
        if q % 2 == 1 {
            s[q / 2]
        } else {
            0.5 * (s[q / 2 - 1] + s[q / 2])
        }
    }

    #[test]
    fn median_in_place_is_the_sorted_middle_at_every_length_with_ties() {
        let mut x = 0x9e3779b97f4a7c15u64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Few distinct values (ties), signs mixed, some large.
            ((x % 41) as f32 - 20.0) * if (x >> 5) & 7 == 0 { 1e6 } else { 0.25 }
        };
        for len in 1..=40 {
            for _ in 0..if len == 5 { 5000 } else { 50 } {
                let v: Vec<f32> = (0..len).map(|_| next()).collect();
                let mut w = v.clone();
                assert_eq!(median_in_place(&mut w), reference(&v), "{v:?}");
            }
        }
    }
}
