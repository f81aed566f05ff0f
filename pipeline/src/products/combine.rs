//! The dithers of one beam at one orientation, registered on the target and combined into
//! one cut-out.
//!
//! Registration by whole pixels. Dither d's target position (x_d, y_d) (the reduction's
//! fitted position of component A in that beam) is rounded to the pixel (X_d, Y_d) =
//! (round x_d, round y_d), and the cut-out pixel (i, j) of that dither is the frame's pixel
//! (X_d - h + i, Y_d - h + j), h the half-size: no interpolation, so each cut-out pixel of a
//! dither is one raw pixel and the noise of different pixels stays independent. The target
//! then sits within half a pixel of (h, h) in every dither. The e beam follows the o beam
//! ([`combine_following`]): dither d's e cut-out starts at `O_d + round(eo)`, eo the
//! measured e-o offset, so that the o and e stacks carry the same registration (each
//! dither's sub-pixel offset from the centre is the same in both, up to the constant
//! `eo - round(eo)`): their stars have the same shape, which a per-beam rounding would not
//! give (a dither's o and e positions round differently), and F = (o - e)/(o + e) taken in
//! a small aperture of the two stacks is not biased by a difference of blur.
//!
//! Combination, pixel by pixel over the dithers d whose pixel is usable (not BAD, COSMIC,
//! SATURATED or OFF_STRIP, finite, with a finite positive variance), an inverse-variance
//! weighted mean with one weight per dither:
//!
//! ```text
//!   w_d = 1 / b_d,   value = sum_d w_d v_d / sum_d w_d,   variance = sum_d w_d^2 var_d / (sum_d w_d)^2
//! ```
//!
//! b_d the dither's background variance (the median of its variance map over the cut-out),
//! var_d the pixel's variance: where the sky dominates (var_d = b_d) this is the familiar
//! `1 / sum_d w_d`. The weights are the dither's, not each pixel's own variance: that holds
//! the star's photon noise, so a dither whose star is sharper (better seeing) would weigh
//! less in the core and more in the wings and the combined star would lose flux (3 % in a
//! simulated 3-dither orientation whose FWHM went from 2.3 to 3.0 px). With one weight per
//! dither the combination is linear, and an aperture sum on it is the weighted mean of the
//! dithers' aperture sums. A pixel no dither covers is NaN, its variance NaN and its MASK 1.
use ndarray::Array2;
use sofipol_calib::Frame;

use crate::reduce::sources::UNUSABLE;

/// Smallest half-size of a cut-out, px (a 33 x 33 px cut-out).
pub const MIN_HALF_PX: usize = 16;
/// Largest half-size of a cut-out, px (a 201 x 201 px cut-out).
pub const MAX_HALF_PX: usize = 100;
/// Room beyond the companion's sky annulus, px (as the photometry's own cut-outs).
pub const MARGIN_PX: f64 = 4.0;

/// Half-size h of the cut-outs (side 2h + 1) that hold the pair and every aperture and
/// annulus around it: `h = ceil(separation + annulus outer radius + margin)`, the outer
/// radius `annulus_outer_fwhm x FWHM`, the margin [`MARGIN_PX`]; at least [`MIN_HALF_PX`],
/// at most [`MAX_HALF_PX`]. `separation_px` is 0 without a companion.
pub fn cutout_half_size(fwhm_px: f64, annulus_outer_fwhm: f64, separation_px: f64) -> usize {
    let reach = separation_px.max(0.0) + annulus_outer_fwhm * fwhm_px + MARGIN_PX;
    if !reach.is_finite() {
        return MIN_HALF_PX;
    }
    (reach.ceil() as usize).clamp(MIN_HALF_PX, MAX_HALF_PX)
}

/// Where one dither went into a [`BeamStack`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DitherAnchor {
    /// Index of the dither (frame) in its orientation.
    pub index: usize,
    /// The target's measured position in the frame (x, y), px.
    pub position: (f64, f64),
    /// The frame pixel of the cut-out's pixel (0, 0): (X - h, Y - h).
    pub origin: (i64, i64),
    /// Its weight in the combination, 1 / its background variance (ADU^-2; 0: not used).
    pub weight: f64,
}

/// One beam's dithers at one orientation, registered and combined (module docs).
#[derive(Debug, Clone)]
pub struct BeamStack {
    /// Half-size h: the cut-out is (2h + 1) x (2h + 1) px, the target near (h, h).
    pub half: usize,
    /// Inverse-variance weighted mean, ADU (NaN where no dither is usable).
    pub data: Array2<f32>,
    /// Its variance, ADU^2: 1 / sum of the weights (NaN where no dither is usable).
    pub variance: Array2<f32>,
    /// 1 where no dither is usable, else 0.
    pub mask: Array2<u8>,
    /// How many dithers each pixel combines.
    pub n_combined: Array2<u8>,
    /// The dithers combined, in order.
    pub anchors: Vec<DitherAnchor>,
}

impl BeamStack {
    /// The target's mean position in the cut-out (x, y), 0-based pixel coordinates: the mean
    /// over the dithers of h + (x_d - X_d), h + (y_d - Y_d).
    pub fn target_xy(&self) -> (f64, f64) {
        let n = self.anchors.len() as f64;
        let h = self.half as f64;
        let (sx, sy) = self.anchors.iter().fold((0.0, 0.0), |(sx, sy), a| {
            (
                sx + a.position.0 - a.origin.0 as f64,
                sy + a.position.1 - a.origin.1 as f64,
            )
        });
        if n > 0.0 {
            (sx / n, sy / n)
        } else {
            (h, h)
        }
    }
}

/// The frame pixel of cut-out pixel (0, 0) for a target at `position`: (round x - h,
/// round y - h).
pub fn origin_of(position: (f64, f64), half: usize) -> (i64, i64) {
    let h = half as i64;
    (position.0.round() as i64 - h, position.1.round() as i64 - h)
}

/// Register the dithers `frames` on the target's positions `positions` (same order; `None`
/// or non-finite: the dither is left out) by whole pixels and combine them (module docs).
/// `None` when no dither has a position.
pub fn combine_beam(frames: &[&Frame], positions: &[Option<(f64, f64)>], half: usize) -> Option<BeamStack> {
    let anchors = frames
        .iter()
        .zip(positions)
        .enumerate()
        .filter_map(|(index, (_, p))| {
            let p = (*p)?;
            (p.0.is_finite() && p.1.is_finite()).then(|| DitherAnchor {
                index,
                position: p,
                origin: origin_of(p, half),
                weight: 0.0,
            })
        })
        .collect();
    combine_anchored(frames, anchors, half)
}

/// The other beam of the dithers of `first` (the o beam's stack), whose target lies at
/// `offset` from the first's (the measured e-o offset): each dither registered with the
/// first beam's whole-pixel shift plus the whole-pixel part of the offset, `E_d = O_d +
/// round(offset)`, and combined (module docs). Both beams then carry the same registration
/// (the same sub-pixel scatter of the dithers about the centre, the same blur), and the
/// target sits at the first's position + `offset - round(offset)`.
pub fn combine_following(first: &BeamStack, frames: &[&Frame], offset: (f64, f64)) -> Option<BeamStack> {
    if !(offset.0.is_finite() && offset.1.is_finite()) {
        return None;
    }
    let whole = (offset.0.round() as i64, offset.1.round() as i64);
    let anchors = first
        .anchors
        .iter()
        .map(|a| DitherAnchor {
            index: a.index,
            position: (a.position.0 + offset.0, a.position.1 + offset.1),
            origin: (a.origin.0 + whole.0, a.origin.1 + whole.1),
            weight: 0.0,
        })
        .collect();
    combine_anchored(frames, anchors, first.half)
}

/// Combine the dithers at their anchors (module docs), each weighted by the inverse of its
/// background variance; `None` when no dither has a usable background.
fn combine_anchored(frames: &[&Frame], anchors: Vec<DitherAnchor>, half: usize) -> Option<BeamStack> {
    let side = 2 * half + 1;
    let anchors: Vec<DitherAnchor> = anchors
        .into_iter()
        .map(|a| DitherAnchor {
            weight: 1.0 / background_variance(frames[a.index], a.origin, side),
            ..a
        })
        .filter(|a| a.weight.is_finite() && a.weight > 0.0)
        .collect();
    if anchors.is_empty() {
        return None;
    }
    let mut sum_w = Array2::<f64>::zeros((side, side));
    let mut sum_wv = Array2::<f64>::zeros((side, side));
    let mut sum_w2var = Array2::<f64>::zeros((side, side));
    let mut count = Array2::<u8>::zeros((side, side));
    for a in &anchors {
        let (f, w) = (frames[a.index], a.weight);
        for j in 0..side {
            for i in 0..side {
                let Some((v, var)) = usable_pixel(f, a.origin.0 + i as i64, a.origin.1 + j as i64) else {
                    continue;
                };
                sum_w[[j, i]] += w;
                sum_wv[[j, i]] += w * v;
                sum_w2var[[j, i]] += w * w * var;
                count[[j, i]] = count[[j, i]].saturating_add(1);
            }
        }
    }
    let data = ndarray::Zip::from(&sum_wv)
        .and(&sum_w)
        .map_collect(|&wv, &w| if w > 0.0 { (wv / w) as f32 } else { f32::NAN });
    let variance =
        ndarray::Zip::from(&sum_w2var)
            .and(&sum_w)
            .map_collect(|&w2v, &w| if w > 0.0 { (w2v / (w * w)) as f32 } else { f32::NAN });
    let mask = count.mapv(|n| u8::from(n == 0));
    Some(BeamStack {
        half,
        data,
        variance,
        mask,
        n_combined: count,
        anchors,
    })
}

/// The value and variance of frame pixel (x, y) when it is usable (inside the frame, not
/// BAD, COSMIC, SATURATED or OFF_STRIP, finite, with a finite positive variance).
fn usable_pixel(f: &Frame, x: i64, y: i64) -> Option<(f64, f64)> {
    let (ny, nx) = f.shape();
    if x < 0 || y < 0 || x >= nx as i64 || y >= ny as i64 {
        return None;
    }
    let (y, x) = (y as usize, x as usize);
    let v = f.data[[y, x]];
    let var = f.variance.as_ref()?[[y, x]];
    (f.mask[[y, x]] & UNUSABLE == 0 && v.is_finite() && var.is_finite() && var > 0.0).then_some((v as f64, var as f64))
}

/// A dither's background variance: the median variance of its usable pixels in the
/// `side` x `side` cut-out at `origin` (NaN when none is usable).
pub fn background_variance(f: &Frame, origin: (i64, i64), side: usize) -> f64 {
    let mut v: Vec<f64> = (0..side * side)
        .filter_map(|k| usable_pixel(f, origin.0 + (k % side) as i64, origin.1 + (k / side) as i64))
        .map(|(_, var)| var)
        .collect();
    if v.is_empty() {
        return f64::NAN;
    }
    crate::numeric::median_in_place(&mut v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use sofipol_calib::frame::mask as mbits;
    use sofipol_calib::Header;

    fn frame(data: Array2<f32>, var: Array2<f32>) -> Frame {
        let mut f = Frame::new(data, Header::new(""));
        f.variance = Some(var);
        f
    }

    /// A slow, obviously correct version: each dither's background variance as the median
    /// of its cut-out's usable variances (sorted list), then for every cut-out pixel the
    /// dithers' usable values listed by explicit coordinates and averaged by those weights.
    fn reference(frames: &[&Frame], pos: &[(f64, f64)], h: usize) -> (Vec<f64>, Vec<f64>) {
        let side = 2 * h + 1;
        let pixel = |f: &Frame, p: (f64, f64), i: usize, j: usize| -> Option<(f64, f64)> {
            let x = p.0.round() as i64 - h as i64 + i as i64;
            let y = p.1.round() as i64 - h as i64 + j as i64;
            let (ny, nx) = f.shape();
            if x < 0 || y < 0 || x >= nx as i64 || y >= ny as i64 {
                return None;
            }
            let (x, y) = (x as usize, y as usize);
            (f.mask[[y, x]] & UNUSABLE == 0)
                .then(|| (f.data[[y, x]] as f64, f.variance.as_ref().unwrap()[[y, x]] as f64))
        };
        let b: Vec<f64> = frames
            .iter()
            .zip(pos)
            .map(|(f, &p)| {
                let mut v: Vec<f64> = (0..side)
                    .flat_map(|j| (0..side).map(move |i| (i, j)))
                    .filter_map(|(i, j)| pixel(f, p, i, j).map(|t| t.1))
                    .collect();
                v.sort_by(f64::total_cmp);
                let n = v.len();
                if n % 2 == 1 {
                    v[n / 2]
                } else {
                    0.5 * (v[n / 2 - 1] + v[n / 2])
                }
            })
            .collect();
        let (mut val, mut var) = (vec![f64::NAN; side * side], vec![f64::NAN; side * side]);
        for j in 0..side {
            for i in 0..side {
                let terms: Vec<(f64, f64, f64)> = frames
                    .iter()
                    .zip(pos)
                    .zip(&b)
                    .filter_map(|((f, &p), &b)| pixel(f, p, i, j).map(|(v, var)| (v, var, 1.0 / b)))
                    .collect();
                if !terms.is_empty() {
                    let sw: f64 = terms.iter().map(|t| t.2).sum();
                    val[j * side + i] = terms.iter().map(|t| t.2 * t.0).sum::<f64>() / sw;
                    var[j * side + i] = terms.iter().map(|t| t.2 * t.2 * t.1).sum::<f64>() / (sw * sw);
                }
            }
        }
        (val, var)
    }

    /// A star of `flux` ADU (Gaussian, sigma `s` px) at (x, y) on a sky of variance `sky_var`,
    /// with the photon noise of the star in the variance (gain 1), noiseless values.
    fn star_frame(n: usize, x: f64, y: f64, flux: f64, s: f64, sky_var: f32) -> Frame {
        let img = Array2::from_shape_fn((n, n), |(j, i)| {
            let r2 = (i as f64 - x).powi(2) + (j as f64 - y).powi(2);
            (flux * (-r2 / (2.0 * s * s)).exp() / (2.0 * std::f64::consts::PI * s * s)) as f32
        });
        let var = img.mapv(|v| sky_var + v);
        frame(img, var)
    }

    /// The seeing changes between dithers: the combined star keeps the dithers' flux (one
    /// weight per dither), where weights from each pixel's own variance (star photon noise
    /// included) lose it.
    #[test]
    fn the_combination_keeps_the_flux_when_the_seeing_changes() {
        let (n, flux) = (61, 50_000.0);
        let sharp = star_frame(n, 20.3, 30.1, flux, 1.0, 30.0);
        let broad = star_frame(n, 40.6, 29.8, flux, 1.6, 30.0);
        let h = 14;
        let s = combine_beam(&[&sharp, &broad], &[Some((20.3, 30.1)), Some((40.6, 29.8))], h).unwrap();
        let sum: f64 = s.data.iter().map(|&v| v as f64).sum();
        assert!((sum / flux - 1.0).abs() < 1e-4, "combined flux {sum} of {flux}");
        // Per-pixel weights 1/var on the same dithers: the flux is biased low.
        let mut per_pixel = 0.0;
        for j in 0..2 * h + 1 {
            for i in 0..2 * h + 1 {
                let (a, b) = (
                    (
                        sharp.data[[30 - h + j, 20 - h + i]] as f64,
                        sharp.variance.as_ref().unwrap()[[30 - h + j, 20 - h + i]] as f64,
                    ),
                    (
                        broad.data[[30 - h + j, 41 - h + i]] as f64,
                        broad.variance.as_ref().unwrap()[[30 - h + j, 41 - h + i]] as f64,
                    ),
                );
                per_pixel += (a.0 / a.1 + b.0 / b.1) / (1.0 / a.1 + 1.0 / b.1);
            }
        }
        assert!(per_pixel / flux < 0.97, "per-pixel weights: {per_pixel} of {flux}");
    }

    #[test]
    fn the_stack_is_the_weighted_mean_of_the_registered_pixels() {
        let (ny, nx) = (40, 60);
        let mk = |seed: f32, vscale: f32| {
            frame(
                Array2::from_shape_fn((ny, nx), |(y, x)| {
                    (seed * (x as f32 * 0.37 + y as f32 * 1.3)).sin() * 50.0
                }),
                Array2::from_shape_fn((ny, nx), |(y, x)| vscale * (1.0 + ((x + 2 * y) % 7) as f32)),
            )
        };
        let mut f1 = mk(1.0, 1.0);
        let f2 = mk(2.0, 3.0);
        let f3 = mk(3.0, 0.5);
        f1.mask[[21, 13]] |= mbits::COSMIC;
        f1.mask[[22, 14]] |= mbits::NONLINEAR; // usable
        let pos = [(12.6, 20.2), (30.4, 21.5), (47.9, 19.49)];
        let frames = [&f1, &f2, &f3];
        let h = 9;
        let s = combine_beam(&frames, &pos.map(Some), h).unwrap();
        let (val, var) = reference(&frames, &pos, h);
        for (k, ((&a, &b), (&va, &vb))) in s.data.iter().zip(&val).zip(s.variance.iter().zip(&var)).enumerate() {
            assert!((a as f64 - b).abs() <= 1e-5 * b.abs().max(1.0), "pixel {k}: {a} vs {b}");
            assert!((va as f64 - vb).abs() <= 1e-6 * vb, "pixel {k}: variance {va} vs {vb}");
        }
        // The target of every dither is within half a pixel of the centre.
        let (tx, ty) = s.target_xy();
        let want_x = pos.iter().map(|p| h as f64 + p.0 - p.0.round()).sum::<f64>() / 3.0;
        let want_y = pos.iter().map(|p| h as f64 + p.1 - p.1.round()).sum::<f64>() / 3.0;
        assert!((tx - want_x).abs() < 1e-12 && (ty - want_y).abs() < 1e-12);
        // The cosmic-ray pixel of dither 1 is left out of its cut-out pixel: 2 dithers there.
        let (i, j) = (13 - (13 - h as i64) as usize, 21 - (20 - h as i64) as usize);
        assert_eq!(s.n_combined[[j, i]], 2);
        assert_eq!(s.n_combined[[h, h]], 3);
    }

    #[test]
    fn a_pixel_no_dither_covers_is_masked_and_a_dither_without_position_is_left_out() {
        let f = frame(Array2::from_elem((20, 20), 5.0), Array2::from_elem((20, 20), 2.0));
        let g = frame(Array2::from_elem((20, 20), 9.0), Array2::from_elem((20, 20), 2.0));
        // Near the corner: the cut-out reaches past the frame's edge.
        let s = combine_beam(&[&f, &g], &[Some((2.2, 3.0)), None], 5).unwrap();
        assert_eq!(s.anchors.len(), 1);
        assert_eq!(s.mask[[0, 0]], 1);
        assert!(s.data[[0, 0]].is_nan() && s.variance[[0, 0]].is_nan());
        assert_eq!(s.mask[[5, 5]], 0);
        assert_eq!(s.data[[5, 5]], 5.0);
        assert_eq!(s.variance[[5, 5]], 2.0);
        assert!(combine_beam(&[&f], &[Some((f64::NAN, 1.0))], 5).is_none());
    }

    /// The e beam follows the o beam's registration plus round(eo): every dither's e cut-out
    /// is its o cut-out's origin + (0, 167) for eo = (0.4, 166.6), whatever the dither's
    /// sub-pixel position, and the e target sits at the o target + (0.4, -0.4).
    #[test]
    fn the_e_beam_follows_the_o_registration() {
        let (ny, nx) = (400, 120);
        let f1 = frame(
            Array2::from_shape_fn((ny, nx), |(y, x)| (x + 3 * y) as f32),
            Array2::from_elem((ny, nx), 2.0),
        );
        let f2 = frame(
            Array2::from_shape_fn((ny, nx), |(y, x)| (2 * x + y) as f32),
            Array2::from_elem((ny, nx), 4.0),
        );
        let pos = [Some((30.3, 40.1)), Some((70.8, 39.4))];
        let h = 10;
        let o = combine_beam(&[&f1, &f2], &pos, h).unwrap();
        let e = combine_following(&o, &[&f1, &f2], (0.4, 166.6)).unwrap();
        for (a, b) in o.anchors.iter().zip(&e.anchors) {
            assert_eq!((b.origin.0 - a.origin.0, b.origin.1 - a.origin.1), (0, 167));
        }
        let (to, te) = (o.target_xy(), e.target_xy());
        assert!(
            (te.0 - to.0 - 0.4).abs() < 1e-9 && (te.1 - to.1 + 0.4).abs() < 1e-9,
            "{to:?} {te:?}"
        );
        // Weights 1/2 and 1/4: the e stack's pixel (0, 0) is (2/3) f1 + (1/3) f2 at the
        // e origins (30 - 10, 40 - 10 + 167) and (71 - 10, 39 - 10 + 167).
        let want = (2.0 * (20 + 3 * 197) as f64 + (2 * 61 + 196) as f64) / 3.0;
        assert!(
            (e.data[[0, 0]] as f64 - want).abs() < 1e-3,
            "{} vs {want}",
            e.data[[0, 0]]
        );
        assert!((e.variance[[0, 0]] as f64 - 4.0 / 3.0).abs() < 1e-6);
        assert!(combine_following(&o, &[&f1, &f2], (f64::NAN, 1.0)).is_none());
    }

    #[test]
    fn the_half_size_holds_the_pair_and_the_annulus() {
        // 14 px separation, 2.8 px FWHM, annulus to 6 FWHM: 14 + 16.8 + 4 -> 35.
        assert_eq!(cutout_half_size(2.8, 6.0, 14.0), 35);
        assert_eq!(cutout_half_size(1.0, 2.0, 0.0), MIN_HALF_PX);
        assert_eq!(cutout_half_size(f64::NAN, 6.0, 14.0), MIN_HALF_PX);
        assert_eq!(cutout_half_size(20.0, 6.0, 300.0), MAX_HALF_PX);
    }
}
