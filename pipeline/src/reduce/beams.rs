//! The two beams: the e-o offset between the ordinary and extraordinary images of the
//! target, measured from the data (cross-correlation, then refined by per-frame fits).
use ndarray::{s, Array2, ArrayView2};
use sofipol_calib::Profile;

use super::sources::Primary;
use super::{MeasureError, SkySubtractedOrientation};
use crate::catalog::{Flag, FlagCode};

/// The (o, e) centroids of one frame, px.
pub type CentroidPair = ((f64, f64), (f64, f64));

/// Median e-o offset from per-frame (o, e) centroids.
pub fn median_offset(pairs: &[CentroidPair]) -> Option<(f64, f64)> {
    if pairs.is_empty() {
        return None;
    }
    let med = |mut v: Vec<f64>| crate::numeric::median_in_place(&mut v);
    Some((
        med(pairs.iter().map(|(o, e)| e.0 - o.0).collect()),
        med(pairs.iter().map(|(o, e)| e.1 - o.1).collect()),
    ))
}

/// A cut-out view helper: rows of a strip.
pub fn strip_rows(img: &Array2<f32>, rows: [usize; 2]) -> ArrayView2<'_, f32> {
    img.slice(s![rows[0]..rows[1], ..])
}

/// The e-o beam offset by cross-correlation of ordinary and extraordinary cut-outs of the
/// target (summed over frames): the two beams show the same pair with fluxes that differ
/// only by the polarization, so the correlation peaks at the true offset even when the
/// brighter star in one beam is the fainter in the other (a brightest-peak match would
/// then jump between the components). Integer search within `search` px of `start`, then
/// a parabola through the peak and its neighbours on each axis.
pub fn eo_offset_by_correlation(
    frames: &[(&Array2<f32>, &Array2<u8>)],
    centres: &[(f64, f64)],
    start: (f64, f64),
    h: usize,
    search: i64,
) -> Option<(f64, f64)> {
    let score = correlation_scores(frames, centres, start, h, search)?;
    Some(peak_offset(&score, start, search))
}

/// The correlation of [`eo_offset_by_correlation`] at every integer shift, row-major over
/// (dy, dx) in `-search..=search`; `None` when no frame has its windows inside the image.
fn correlation_scores(
    frames: &[(&Array2<f32>, &Array2<u8>)],
    centres: &[(f64, f64)],
    start: (f64, f64),
    h: usize,
    search: i64,
) -> Option<Vec<f64>> {
    let n = 2 * search as usize + 1;
    let mut score = vec![0.0f64; n * n];
    let mut used = 0;
    let hh = h as i64;
    for (&(img, mask), &c) in frames.iter().zip(centres) {
        let Some((ox, oy, ex0, ey0)) = windows(img.dim(), c, start, h, search) else {
            continue;
        };
        used += 1;
        // The o window and the e region it slides over, as f64 with masked pixels 0: a
        // product with a masked pixel then adds +-0, which leaves every sum (never -0: it
        // starts at +0) exactly as skipping the pixel does; the values are finite here.
        let side = 2 * h + 1;
        let eside = side + 2 * search as usize;
        let cut = |x0: i64, y0: i64, w: usize| -> Vec<f64> {
            let mut v = Vec::with_capacity(w * w);
            for y in y0..y0 + w as i64 {
                for x in x0..x0 + w as i64 {
                    let (yy, xx) = (y as usize, x as usize);
                    v.push(if mask[[yy, xx]] == 0 { img[[yy, xx]] as f64 } else { 0.0 });
                }
            }
            v
        };
        let o = cut(ox - hh, oy - hh, side);
        let e = cut(ex0 - hh - search, ey0 - hh - search, eside);
        for sy in 0..n {
            for sx in 0..n {
                // Summed in the pixel-by-pixel order: rows, then pixels along a row.
                let mut acc = 0.0;
                for j in 0..side {
                    let orow = &o[j * side..(j + 1) * side];
                    let erow = &e[(j + sy) * eside + sx..][..side];
                    for (a, b) in orow.iter().zip(erow) {
                        acc += a * b;
                    }
                }
                score[sy * n + sx] += acc;
            }
        }
    }
    (used > 0).then_some(score)
}

/// The centre pixels of the o window (the star at `c`, rounded) and of the e region
/// before the shift (the o centre moved by the rounded `start`), when both windows (half-width `h`, the e one widened by `search`)
/// lie inside an image of `(ny, nx)` pixels.
fn windows(
    (ny, nx): (usize, usize),
    (cx, cy): (f64, f64),
    start: (f64, f64),
    h: usize,
    search: i64,
) -> Option<(i64, i64, i64, i64)> {
    let (ox, oy) = (cx.round() as i64, cy.round() as i64);
    // The e region is the o window moved by the rounded start, so that a shift s of the
    // search is the offset round(start) + s in every frame (rounding cx + start instead
    // moved it by a pixel in the frames where the fractions add up past one half, and the
    // summed scores mixed two offsets).
    let (ex0, ey0) = (ox + start.0.round() as i64, oy + start.1.round() as i64);
    let hh = h as i64;
    let inside = |x: i64, y: i64, r: i64| x - r >= 0 && y - r >= 0 && x + r < nx as i64 && y + r < ny as i64;
    (inside(ox, oy, hh) && inside(ex0, ey0, hh + search)).then_some((ox, oy, ex0, ey0))
}

/// The offset at the best score: the integer shift, refined by a parabola through the
/// peak and its neighbours on each axis (at most half a pixel).
fn peak_offset(score: &[f64], start: (f64, f64), search: i64) -> (f64, f64) {
    let n = 2 * search as usize + 1;
    let (mut bi, mut bv) = (0, f64::NEG_INFINITY);
    for (k, &v) in score.iter().enumerate() {
        if v > bv {
            bv = v;
            bi = k;
        }
    }
    let (by, bx) = (bi / n, bi % n);
    let para = |m: f64, c: f64, p: f64| {
        let d = m - 2.0 * c + p;
        if d < 0.0 {
            0.5 * (m - p) / d
        } else {
            0.0
        }
    };
    let dx = if bx > 0 && bx + 1 < n {
        para(score[by * n + bx - 1], bv, score[by * n + bx + 1])
    } else {
        0.0
    };
    let dy = if by > 0 && by + 1 < n {
        para(score[(by - 1) * n + bx], bv, score[(by + 1) * n + bx])
    } else {
        0.0
    };
    let fx = (start.0).round() + (bx as f64 - search as f64) + dx.clamp(-0.5, 0.5) - start.0;
    let fy = (start.1).round() + (by as f64 - search as f64) + dy.clamp(-0.5, 0.5) - start.1;
    (start.0 + fx, start.1 + fy)
}

/// Stage 2: the e-o offset, by cross-correlating the o and e images of the target in every
/// frame where the primary was found. Flags an offset more than 3 px from the profile's.
pub fn measure_eo_offset(
    orients: &[SkySubtractedOrientation],
    primary: &Primary,
    masks: &[Vec<Array2<u8>>],
    profile: &Profile,
    flags: &mut Vec<Flag>,
) -> Result<(f64, f64), MeasureError> {
    let g = &profile.geometry;
    let (mut fr, mut cc) = (Vec::new(), Vec::new());
    for (k, (o, ms)) in orients.iter().zip(masks).enumerate() {
        let (f, c) = primary.found_in(k, o, ms);
        fr.extend(f);
        cc.extend(c);
    }
    let h_corr = (2.5 * primary.fwhm_guess).ceil() as usize + 4;
    let eo =
        eo_offset_by_correlation(&fr, &cc, (g.eo_offset_px[0], g.eo_offset_px[1]), h_corr, 5).ok_or_else(|| {
            MeasureError::new("could not measure the e-o beam offset (target too close to the strip edges)")
        })?;
    if (eo.0 - g.eo_offset_px[0]).hypot(eo.1 - g.eo_offset_px[1]) > 3.0 {
        flags.push(Flag::with_detail(
            FlagCode::EoOffsetDiffersFromProfile,
            format!("({:.2}, {:.2}) px", eo.0, eo.1),
        ));
    }
    Ok(eo)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The correlation scores as first written: every product read through the masks,
    /// pixel by pixel (the slow, obviously right version).
    fn reference(
        frames: &[(&Array2<f32>, &Array2<u8>)],
        centres: &[(f64, f64)],
        start: (f64, f64),
        h: usize,
        search: i64,
    ) -> Option<Vec<f64>> {
        let n = 2 * search as usize + 1;
        let mut score = vec![0.0f64; n * n];
        let mut used = 0;
        for (&(img, mask), &c) in frames.iter().zip(centres) {
            let hh = h as i64;
            let Some((ox, oy, ex0, ey0)) = windows(img.dim(), c, start, h, search) else {
                continue;
            };
            used += 1;
            for sy in -search..=search {
                for sx in -search..=search {
                    let mut acc = 0.0;
                    for j in -hh..=hh {
                        for i in -hh..=hh {
                            let (oyy, oxx) = ((oy + j) as usize, (ox + i) as usize);
                            let (eyy, exx) = ((ey0 + sy + j) as usize, (ex0 + sx + i) as usize);
                            if mask[[oyy, oxx]] == 0 && mask[[eyy, exx]] == 0 {
                                acc += img[[oyy, oxx]] as f64 * img[[eyy, exx]] as f64;
                            }
                        }
                    }
                    score[((sy + search) as usize) * n + (sx + search) as usize] += acc;
                }
            }
        }
        (used > 0).then_some(score)
    }

    /// The windowed correlation gives the reference's scores bit for bit: noise with a
    /// star pair in each beam, a quarter of the pixels masked (masked values huge, so a
    /// masked product that counted would show), zeros and negative values, several frames,
    /// frames too near the edge skipped.
    #[test]
    fn the_windowed_correlation_is_the_pixel_by_pixel_one() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(0x2545_f491_4f6c_dd1d);
        let mut rnd = move || rng.random::<f64>();
        for trial in 0..6 {
            let (ny, nx) = (90, 80);
            let mut frames = Vec::new();
            let mut centres = Vec::new();
            for k in 0..4 {
                let (cx, cy) = (20.0 + 30.0 * rnd(), 15.0 + 10.0 * rnd());
                let (dx, dy) = (rnd() * 4.0 - 2.0, 40.0 + rnd() * 4.0 - 2.0);
                let img = Array2::from_shape_fn((ny, nx), |(y, x)| {
                    let star = |x0: f64, y0: f64, f: f64| {
                        f * (-((x as f64 - x0).powi(2) + (y as f64 - y0).powi(2)) / 4.0).exp()
                    };
                    let v = rnd() * 20.0 - 10.0
                        + star(cx, cy, 500.0)
                        + star(cx + 2.5, cy + 1.0, 200.0)
                        + star(cx + dx, cy + dy, 300.0)
                        + star(cx + dx + 2.5, cy + dy + 1.0, 350.0);
                    if (x + y + k) % 17 == 0 {
                        0.0
                    } else {
                        v as f32
                    }
                });
                let mask = Array2::from_shape_fn((ny, nx), |_| u8::from(rnd() < 0.25));
                let img = Array2::from_shape_fn((ny, nx), |(y, x)| if mask[[y, x]] != 0 { 1e30 } else { img[[y, x]] });
                frames.push((img, mask));
                // One frame in three with its centre too near the edge for the window.
                centres.push(if k == 3 && trial % 3 == 0 { (3.0, 3.0) } else { (cx, cy) });
            }
            let refs: Vec<(&Array2<f32>, &Array2<u8>)> = frames.iter().map(|(i, m)| (i, m)).collect();
            for (h, search) in [(9, 5), (6, 3)] {
                let want = reference(&refs, &centres, (0.0, 40.0), h, search).unwrap();
                let got = correlation_scores(&refs, &centres, (0.0, 40.0), h, search).unwrap();
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "trial {trial}");
            }
        }
    }

    /// The windows fit exactly when every pixel of the o window (half-width h) and of the
    /// e region (half-width h + search, around the star shifted by the rounded start) lies
    /// in the image: one pixel further out on any side and the frame is not used.
    #[test]
    fn the_windows_reach_every_edge_of_the_image_and_no_further() {
        let (dim, h, search) = ((50, 40), 4, 2);
        // o at (10, 20) rounded from (9.6, 20.4), e at (10 + 3, 20 + 21) from start (3.3, 20.8).
        assert_eq!(
            windows(dim, (9.6, 20.4), (3.3, 20.8), h, search),
            Some((10, 20, 13, 41))
        );
        let ok = |c: (f64, f64), start: (f64, f64)| windows(dim, c, start, h, search).is_some();
        // The o window at the low edges (x - 4 = 0, y - 4 = 0), the e region well inside.
        assert!(ok((4.0, 4.0), (10.0, 10.0)));
        assert!(!ok((3.0, 10.0), (10.0, 10.0)) && !ok((10.0, 3.0), (10.0, 10.0)));
        // The o window at the high edges (x + 4 = 39, y + 4 = 49).
        assert!(ok((35.0, 45.0), (-10.0, -10.0)));
        assert!(!ok((36.0, 30.0), (-10.0, -10.0)) && !ok((20.0, 46.0), (-10.0, -10.0)));
        // The e region (half-width 6) at each edge, the o window inside.
        assert!(ok((20.0, 20.0), (-14.0, -14.0)));
        assert!(!ok((20.0, 20.0), (-15.0, -10.0)) && !ok((20.0, 20.0), (-10.0, -15.0)));
        assert!(ok((20.0, 20.0), (13.0, 23.0)));
        assert!(!ok((20.0, 20.0), (14.0, 10.0)) && !ok((20.0, 20.0), (10.0, 24.0)));
    }

    /// The scores of a 5 x 5 search (search 2): zero but for `peak` at (row, col) and its
    /// neighbours along both axes (left, right, up, down).
    fn scores(peak: (usize, usize), v: f64, nb: [f64; 4]) -> Vec<f64> {
        let mut s = vec![0.0; 25];
        let (r, c) = peak;
        s[r * 5 + c] = v;
        if c > 0 {
            s[r * 5 + c - 1] = nb[0];
        }
        if c < 4 {
            s[r * 5 + c + 1] = nb[1];
        }
        if r > 0 {
            s[(r - 1) * 5 + c] = nb[2];
        }
        if r < 4 {
            s[(r + 1) * 5 + c] = nb[3];
        }
        s
    }

    /// The peak's offset: its integer shift from the rounded start, refined by the vertex
    /// of the parabola through it and its two neighbours on each axis,
    /// 0.5 (m - p)/(m - 2c + p); on the edge of the search, where one neighbour is missing,
    /// no refinement; the first of equal maxima.
    #[test]
    fn the_peak_is_refined_by_a_parabola_inside_the_search_only() {
        let start: (f64, f64) = (0.3, 166.8);
        let base = (start.0.round(), start.1.round());
        // Interior (row 1, column 3): dx = 0.5 (8 - 2)/(8 - 20 + 2) = -0.3,
        // dy = 0.5 (4 - 9)/(4 - 20 + 9) = 5/14.
        let (x, y) = peak_offset(&scores((1, 3), 10.0, [8.0, 2.0, 4.0, 9.0]), start, 2);
        assert!((x - (base.0 + 1.0 - 0.3)).abs() < 1e-12, "{x}");
        assert!((y - (base.1 - 1.0 + 5.0 / 14.0)).abs() < 1e-12, "{y}");
        // A neighbour nearly as high: the vertex near half a pixel, 0.5 * 9.9/(9.9 - 20).
        let (x, _) = peak_offset(&scores((2, 2), 10.0, [9.9, 0.0, 0.0, 0.0]), start, 2);
        assert!((x - (base.0 - 0.5 * 9.9 / 10.1)).abs() < 1e-12, "{x}");
        // On each edge of the search the offset is the integer shift, whatever the one
        // neighbour there is (and whatever lies in the next row or column).
        for (peak, want) in [
            ((2, 0), (-2.0, 0.0)),
            ((2, 4), (2.0, 0.0)),
            ((0, 2), (0.0, -2.0)),
            ((4, 2), (0.0, 2.0)),
        ] {
            let mut s = scores(peak, 10.0, [7.0, 3.0, 6.0, 2.0]);
            // Large values beside the edges, where an index past the edge would land.
            for (i, v) in s.iter_mut().enumerate() {
                if *v == 0.0 {
                    *v = 5.0 + (i % 3) as f64;
                }
            }
            let (x, y) = peak_offset(&s, start, 2);
            let (dx, dy) = (x - base.0 - want.0, y - base.1 - want.1);
            let on_x_edge = peak.1 == 0 || peak.1 == 4;
            let (edge, other) = if on_x_edge { (dx, dy) } else { (dy, dx) };
            assert!(edge.abs() < 1e-12, "{peak:?}: ({x}, {y})");
            // Along the other axis both neighbours are there: refined (not zero).
            assert!(other.abs() > 0.01 && other.abs() <= 0.5, "{peak:?}: ({x}, {y})");
        }
        // Equal maxima: the first in row-major order (row 1, column 1), unrefined where its
        // neighbours are equal on both sides.
        let mut s = vec![1.0; 25];
        s[6] = 10.0;
        s[18] = 10.0;
        let (x, y) = peak_offset(&s, start, 2);
        assert!(
            (x - (base.0 - 1.0)).abs() < 1e-12 && (y - (base.1 - 1.0)).abs() < 1e-12,
            "({x}, {y})"
        );
    }
}
