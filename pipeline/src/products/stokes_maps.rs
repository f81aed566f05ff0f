//! Stokes I, Q, U maps of one target from its combined o and e cut-outs.
//!
//! 1. One grid for every image: the target at its centre pixel c = (h, h). Each
//!    orientation's o stack holds the target at `t_o` (within half a pixel of c: the
//!    dithers were registered by whole pixels, a different half pixel at each
//!    orientation), its e stack at `t_e = t_o + s`, where `s` is the measured e-o offset
//!    less the whole-pixel registration difference of the dithers,
//!    `s = eo - mean_d (E_d - O_d)` ([`e_to_o_shift`]; the e stack follows the o stack's
//!    registration, E_d - O_d = round(eo), so |s| <= 0.5 px). Both are resampled onto the
//!    common grid,
//!    `o'(x, y) = o(x + t_o - c)` and `e'(x, y) = e(x + t_o + s - c)`, by **Lanczos-3
//!    interpolation** (separable, 6 x 6 taps `L(t) = sinc(t) sinc(t/3)`, |t| < 3, each axis
//!    normalised to sum 1: flux is conserved). Lanczos rather than bilinear: bilinear
//!    interpolation smooths by an amount that depends on the sub-pixel shift (a
//!    half-pixel shift widens a 3 px FWHM star by ~10 %), different for o and e, which moves
//!    flux out of a small aperture in one beam more than in the other and biases F (by ~1 %
//!    within 1 FWHM); Lanczos-3 keeps a well-sampled star's shape. The variance is
//!    `sum_k w_k var_k`: what a sum over an aperture of many pixels carries (each input
//!    pixel's weights sum to 1 over the output pixels), where the variance of one
//!    interpolated pixel alone, `sum_k w_k^2 var_k`, would hide the covariance that
//!    interpolation creates between neighbours. A pixel is masked when a tap with non-zero
//!    weight is masked or off the cut-out (a border of 2 to 3 px; none
//!    at a whole-pixel shift).
//! 2. Per orientation k (analyzer angle phi_k): `S_k = o' + e'`, `D_k = o' - e'`, both with
//!    variance `V_k = var_o' + var_e'`, times `a_k = mean_j T_j / T_k`, `T_k` the target's
//!    o + e flux in the combined cut-outs (the reduction's per-dither fluxes of A, weighted
//!    as the dithers were combined): a transparency change between orientations cancels as
//!    it does in the catalog's per-dither normalised difference `F = (o - e)/(o + e)`.
//! 3. Per pixel, the catalog's inversion: `D_k = Q cos 2phi_k + U sin 2phi_k`, i.e. F = q cos
//!    2phi + u sin 2phi multiplied by I, solved by the catalog's weighted least squares
//!    ([`fit_qu`]) over the orientations usable at that pixel, with one weight per
//!    orientation, `W_k = 1 / B_k`, B_k the median of a_k^2 V_k over the grid (the
//!    background's variance; weights from each pixel's own variance would hold the star's
//!    photon noise and bias the star's Q and U, as in the combination of the dithers). Q and
//!    U are then fixed linear combinations `Q = sum_k c_k D_k` (for 0 and 45 deg: Q = D(0),
//!    U = D(45)), so `Var Q = sum_k c_k^2 a_k^2 V_k` (likewise Var U, Cov(Q, U)), and
//!    `I = sum_k W_k S_k / sum_k W_k`, `Var I = sum_k W_k^2 a_k^2 V_k / (sum_k W_k)^2`.
//!    Summed over an aperture, `sum Q / sum I` is the least-squares q of the aperture's F_k
//!    = sum D_k / sum S_k: the catalog's uncalibrated q of the star in it.
//!
//! The maps are instrumental: the night's calibration (offset c, zero-point theta0 and
//! parity of the analyzer angles, telescope polarization) is applied later to the catalog
//! and not to them; the analyzer angles are the profile's.
use std::collections::HashMap;

use ndarray::Array2;

use super::combine::BeamStack;
use crate::stokes::inversion::fit_qu;

/// An image on another grid: values, variances, mask (1 = unusable).
#[derive(Debug, Clone)]
pub struct Resampled {
    /// Values, ADU.
    pub data: Array2<f32>,
    /// Variances, ADU^2 (module docs: `sum_k w_k var_k`).
    pub variance: Array2<f32>,
    /// 1 where unusable.
    pub mask: Array2<u8>,
}

/// The shift `s` that brings the e stack's target onto the o stack's (module docs):
/// `eo - mean_d (E_d - O_d)` over the dithers combined in both beams, (E_d, O_d) their
/// whole-pixel anchors. `None` when no dither is in both.
pub fn e_to_o_shift(o: &BeamStack, e: &BeamStack, eo_offset_px: (f64, f64)) -> Option<(f64, f64)> {
    let mut n = 0.0;
    let (mut sx, mut sy) = (0.0, 0.0);
    for a in &o.anchors {
        if let Some(b) = e.anchors.iter().find(|b| b.index == a.index) {
            sx += (b.origin.0 - a.origin.0) as f64;
            sy += (b.origin.1 - a.origin.1) as f64;
            n += 1.0;
        }
    }
    (n > 0.0 && eo_offset_px.0.is_finite() && eo_offset_px.1.is_finite())
        .then(|| (eo_offset_px.0 - sx / n, eo_offset_px.1 - sy / n))
}

/// The Lanczos-3 kernel, `sinc(t) sinc(t / 3)` for |t| < 3, else 0.
pub fn lanczos3(t: f64) -> f64 {
    let sinc = |x: f64| {
        if x == 0.0 {
            1.0
        } else {
            let px = std::f64::consts::PI * x;
            px.sin() / px
        }
    };
    if t.fract() == 0.0 {
        // Exactly 0 at the other pixels (sin(pi k) is not, in floating point).
        return f64::from(u8::from(t == 0.0));
    }
    if t.abs() < 3.0 {
        sinc(t) * sinc(t / 3.0)
    } else {
        0.0
    }
}

/// The 6 taps of a Lanczos-3 interpolation at fractional position `f` in [0, 1): the
/// weights of the pixels -2..=3 from the one below, normalised to sum to 1.
fn taps(f: f64) -> [f64; 6] {
    let mut w = [0.0; 6];
    for (m, w) in w.iter_mut().enumerate() {
        *w = lanczos3(f - (m as f64 - 2.0));
    }
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}

/// `stack` resampled at `(x + s_x, y + s_y)` by Lanczos-3 interpolation (module docs).
pub fn shift_image(stack: &BeamStack, shift: (f64, f64)) -> Resampled {
    let (ny, nx) = stack.data.dim();
    let mut data = Array2::from_elem((ny, nx), f32::NAN);
    let mut variance = Array2::from_elem((ny, nx), f32::NAN);
    let mut mask = Array2::from_elem((ny, nx), 1u8);
    // One shift for the whole image: the same taps at every pixel.
    let (x0, y0) = (shift.0.floor(), shift.1.floor());
    let (wx, wy) = (taps(shift.0 - x0), taps(shift.1 - y0));
    let (x0, y0) = (x0 as i64, y0 as i64);
    for j in 0..ny {
        for i in 0..nx {
            let mut acc = (0.0f64, 0.0f64);
            let mut ok = true;
            'taps: for (n, &wy) in wy.iter().enumerate() {
                for (m, &wx) in wx.iter().enumerate() {
                    let w = wx * wy;
                    if w == 0.0 {
                        continue;
                    }
                    let (yy, xx) = (j as i64 + y0 + n as i64 - 2, i as i64 + x0 + m as i64 - 2);
                    if yy < 0
                        || xx < 0
                        || yy >= ny as i64
                        || xx >= nx as i64
                        || stack.mask[[yy as usize, xx as usize]] != 0
                    {
                        ok = false;
                        break 'taps;
                    }
                    let (yy, xx) = (yy as usize, xx as usize);
                    acc.0 += w * stack.data[[yy, xx]] as f64;
                    acc.1 += w * stack.variance[[yy, xx]] as f64;
                }
            }
            if ok {
                data[[j, i]] = acc.0 as f32;
                variance[[j, i]] = acc.1 as f32;
                mask[[j, i]] = 0;
            }
        }
    }
    Resampled { data, variance, mask }
}

/// One orientation's beams on the common grid.
#[derive(Debug, Clone)]
pub struct OrientationBeams {
    /// Analyzer angle, deg.
    pub analyzer_deg: f64,
    /// The combined o cut-out, resampled.
    pub o: Resampled,
    /// The combined e cut-out, resampled.
    pub e: Resampled,
}

impl OrientationBeams {
    /// The o and e stacks of one orientation onto the grid whose centre pixel holds the
    /// target (module docs, step 1); `shift` is [`e_to_o_shift`].
    pub fn centred(analyzer_deg: f64, o: &BeamStack, e: &BeamStack, shift: (f64, f64)) -> OrientationBeams {
        let (t, c) = (o.target_xy(), o.half as f64);
        OrientationBeams {
            analyzer_deg,
            o: shift_image(o, (t.0 - c, t.1 - c)),
            e: shift_image(e, (t.0 + shift.0 - c, t.1 + shift.1 - c)),
        }
    }

    /// Whether pixel (j, i) is usable in both beams.
    fn usable(&self, j: usize, i: usize) -> bool {
        self.o.mask[[j, i]] == 0 && self.e.mask[[j, i]] == 0
    }

    /// `V = var_o' + var_e'` at (j, i).
    fn var(&self, j: usize, i: usize) -> f64 {
        self.o.variance[[j, i]] as f64 + self.e.variance[[j, i]] as f64
    }
}

/// The transparency normalisation `a_k = mean_j T_j / T_k` (module docs) from the
/// orientations' target fluxes `t`. `Err(reason)` (and no normalisation) when a flux is not
/// finite and positive.
pub fn transparency_scales(t: &[f64]) -> Result<Vec<f64>, String> {
    if let Some((k, tk)) = t.iter().enumerate().find(|(_, tk)| !(tk.is_finite() && **tk > 0.0)) {
        return Err(format!("the target's o + e flux at orientation {} is {tk} ADU", k + 1));
    }
    let mean = t.iter().sum::<f64>() / t.len() as f64;
    Ok(t.iter().map(|tk| mean / tk).collect())
}

/// The weight `W_k = 1 / B_k` of each orientation (module docs, step 3): B_k the median over
/// the usable pixels of `a_k^2 V_k`.
pub fn orientation_weights(orients: &[OrientationBeams], scales: &[f64]) -> Vec<f64> {
    orients
        .iter()
        .zip(scales)
        .map(|(o, &a)| {
            let mut v: Vec<f64> =
                o.o.mask
                    .indexed_iter()
                    .filter(|&((j, i), _)| o.usable(j, i))
                    .map(|((j, i), _)| a * a * o.var(j, i))
                    .filter(|v| v.is_finite() && *v > 0.0)
                    .collect();
            1.0 / crate::numeric::median_in_place(&mut v)
        })
        .collect()
}

/// Stokes I, Q, U maps (ADU) with their variances, Cov(Q, U) and a mask.
#[derive(Debug, Clone)]
pub struct StokesMaps {
    /// I.
    pub i: Array2<f32>,
    /// Q.
    pub q: Array2<f32>,
    /// U.
    pub u: Array2<f32>,
    /// Var I.
    pub var_i: Array2<f32>,
    /// Var Q.
    pub var_q: Array2<f32>,
    /// Var U.
    pub var_u: Array2<f32>,
    /// Cov(Q, U).
    pub cov_qu: Array2<f32>,
    /// 1 where the orientations usable at that pixel do not constrain Q and U.
    pub mask: Array2<u8>,
}

/// Per orientation used (its index), the coefficients (cq, cu) of its D in Q and U.
type QuCoefficients = Vec<(usize, f64, f64)>;

/// The least-squares solution as linear coefficients, `Q = sum_k cq_k D_k`, `U = sum_k
/// cu_k D_k`, for the orientations `set` (a bit per orientation): [`fit_qu`] of each unit
/// vector with the weights `weights`. `None` when the set does not constrain Q and U.
fn qu_coefficients(set: u64, orients: &[OrientationBeams], weights: &[f64]) -> Option<QuCoefficients> {
    let ks: Vec<usize> = (0..orients.len()).filter(|k| (set >> k) & 1 == 1).collect();
    if ks.len() < 2 {
        return None;
    }
    let phi: Vec<f64> = ks.iter().map(|&k| orients[k].analyzer_deg).collect();
    let sigma: Vec<f64> = ks.iter().map(|&k| weights[k].recip().sqrt()).collect();
    ks.iter()
        .enumerate()
        .map(|(n, &k)| {
            let unit: Vec<f64> = (0..ks.len()).map(|m| f64::from(u8::from(m == n))).collect();
            fit_qu(&phi, &unit, &sigma).map(|f| (k, f.q, f.u))
        })
        .collect()
}

/// Per pixel, I, Q, U from the orientations' beams, each scaled by `scales` (module docs,
/// steps 2 and 3). At most 64 orientations.
pub fn stokes_maps(orients: &[OrientationBeams], scales: &[f64]) -> StokesMaps {
    let dim = orients.first().map_or((0, 0), |o| o.o.data.dim());
    let nan = || Array2::from_elem(dim, f32::NAN);
    let mut m = StokesMaps {
        i: nan(),
        q: nan(),
        u: nan(),
        var_i: nan(),
        var_q: nan(),
        var_u: nan(),
        cov_qu: nan(),
        mask: Array2::from_elem(dim, 1u8),
    };
    let orients = &orients[..orients.len().min(64)];
    let weights = orientation_weights(orients, scales);
    let mut solutions: HashMap<u64, Option<QuCoefficients>> = HashMap::new();
    for ((j, i), mask) in m.mask.indexed_iter_mut() {
        let set = (0..orients.len())
            .filter(|&k| orients[k].usable(j, i) && weights[k].is_finite() && weights[k] > 0.0)
            .fold(0u64, |s, k| s | 1 << k);
        let Some(coef) = solutions
            .entry(set)
            .or_insert_with(|| qu_coefficients(set, orients, &weights))
        else {
            continue;
        };
        let (mut q, mut u, mut vq, mut vu, mut cqu) = (0.0, 0.0, 0.0, 0.0, 0.0);
        let (mut sw, mut sws, mut sw2v) = (0.0, 0.0, 0.0);
        for &(k, cq, cu) in coef.iter() {
            let (o, a, w) = (&orients[k], scales[k], weights[k]);
            let (vo, ve) = (o.o.data[[j, i]] as f64, o.e.data[[j, i]] as f64);
            let v = a * a * o.var(j, i);
            let d = a * (vo - ve);
            q += cq * d;
            u += cu * d;
            vq += cq * cq * v;
            vu += cu * cu * v;
            cqu += cq * cu * v;
            sw += w;
            sws += w * a * (vo + ve);
            sw2v += w * w * v;
        }
        *mask = 0;
        m.q[[j, i]] = q as f32;
        m.u[[j, i]] = u as f32;
        m.var_q[[j, i]] = vq as f32;
        m.var_u[[j, i]] = vu as f32;
        m.cov_qu[[j, i]] = cqu as f32;
        m.i[[j, i]] = (sws / sw) as f32;
        m.var_i[[j, i]] = (sw2v / (sw * sw)) as f32;
    }
    m
}

#[cfg(test)]
mod tests {
    use super::super::combine::DitherAnchor;
    use super::*;

    /// A stack of one dither whose target was measured at `pos` (so that its anchor puts the
    /// target at `h + frac(pos)`), with a constant variance `var`.
    fn stack(data: Array2<f32>, var: f32, pos: (f64, f64)) -> BeamStack {
        let dim = data.dim();
        let half = dim.0 / 2;
        BeamStack {
            half,
            data,
            variance: Array2::from_elem(dim, var),
            mask: Array2::zeros(dim),
            n_combined: Array2::from_elem(dim, 1),
            anchors: vec![DitherAnchor {
                index: 0,
                position: pos,
                origin: super::super::combine::origin_of(pos, half),
                weight: 1.0,
            }],
        }
    }

    /// A Gaussian star of total flux `flux` at (x, y) on an n x n grid (pixel-centre samples).
    fn star(n: usize, x: f64, y: f64, flux: f64) -> Array2<f32> {
        let s2 = 1.5f64 * 1.5;
        Array2::from_shape_fn((n, n), |(j, i)| {
            let r2 = (i as f64 - x).powi(2) + (j as f64 - y).powi(2);
            (flux * (-r2 / (2.0 * s2)).exp() / (2.0 * std::f64::consts::PI * s2)) as f32
        })
    }

    /// Flux-weighted centroid of the usable pixels.
    fn centroid(r: &Resampled) -> (f64, f64) {
        let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for ((j, i), &v) in r.data.indexed_iter() {
            if r.mask[[j, i]] == 0 {
                s += v as f64;
                sx += v as f64 * i as f64;
                sy += v as f64 * j as f64;
            }
        }
        (sx / s, sy / s)
    }

    #[test]
    fn the_shift_follows_the_anchors_and_the_offset() {
        let mk = |origins: &[(i64, i64)]| BeamStack {
            anchors: origins
                .iter()
                .enumerate()
                .map(|(index, &origin)| DitherAnchor {
                    index,
                    position: (0.0, 0.0),
                    origin,
                    weight: 1.0,
                })
                .collect(),
            ..stack(Array2::zeros((3, 3)), 1.0, (1.0, 1.0))
        };
        let o = mk(&[(10, 20), (96, 20), (182, 21)]);
        let e = mk(&[(12, -321), (99, -321), (184, -320)]);
        // Registration differences (2, -341), (3, -341), (2, -341): mean (7/3, -341).
        let s = e_to_o_shift(&o, &e, (2.4, -340.8)).unwrap();
        assert!(
            (s.0 - (2.4 - 7.0 / 3.0)).abs() < 1e-12 && (s.1 - 0.2).abs() < 1e-12,
            "{s:?}"
        );
    }

    /// Second moment about the centroid, per axis, px^2.
    fn width2(r: &Resampled) -> f64 {
        let (cx, cy) = centroid(r);
        let (mut s, mut m2) = (0.0, 0.0);
        for ((j, i), &v) in r.data.indexed_iter() {
            if r.mask[[j, i]] == 0 {
                s += v as f64;
                m2 += v as f64 * ((i as f64 - cx).powi(2) + (j as f64 - cy).powi(2)) / 2.0;
            }
        }
        m2 / s
    }

    /// A star at t + s lands at t after the resampling (its centroid, measured
    /// independently), keeps its flux and its width (a 1.5 px sigma star: bilinear
    /// interpolation at a half-pixel shift would add 0.25 px^2 to sigma^2 in each axis), and
    /// the variance map is sum w var; a whole-pixel shift copies the pixels.
    #[test]
    fn resampling_moves_the_star_by_the_shift_and_keeps_its_flux_and_shape() {
        let n = 41;
        let t = (20.3, 19.6);
        let unshifted = shift_image(&stack(star(n, t.0, t.1, 1000.0), 4.0, (20.0, 20.0)), (0.0, 0.0));
        for s in [(0.37, -0.41), (0.5, 0.5), (-1.2, 0.9)] {
            let e = stack(star(n, t.0 + s.0, t.1 + s.1, 1000.0), 4.0, (20.0, 20.0));
            let r = shift_image(&e, s);
            let sum: f64 = r
                .data
                .iter()
                .zip(&r.mask)
                .filter(|p| *p.1 == 0)
                .map(|p| *p.0 as f64)
                .sum();
            assert!((sum - 1000.0).abs() < 1.0, "{s:?}: flux {sum}");
            // Lanczos-3 reproduces a linear ramp to ~1 %: the centroid to ~0.02 px.
            let (cx, cy) = centroid(&r);
            assert!((cx - t.0).abs() < 0.025 && (cy - t.1).abs() < 0.025, "{s:?}: {cx} {cy}");
            let (w, w0) = (width2(&r), width2(&unshifted));
            assert!((w / w0 - 1.0).abs() < 0.01, "{s:?}: sigma^2 {w} vs {w0}");
            // Constant variance 4: sum_k w_k 4 = 4 everywhere inside.
            assert!((r.variance[[20, 20]] - 4.0).abs() < 1e-5);
        }
        // Shift y in (-1, 0): taps from 3 rows below to 2 above, 2 and 3 columns.
        let r = shift_image(&stack(star(n, 20.0, 20.0, 1000.0), 4.0, (20.0, 20.0)), (0.37, -0.41));
        assert_eq!(
            [0, 1, 2, 3, n - 3, n - 2, n - 1].map(|j| r.mask[[j, 20]]),
            [1, 1, 1, 0, 0, 1, 1]
        );
        assert_eq!([1, 2, n - 4, n - 3].map(|i| r.mask[[20, i]]), [1, 0, 0, 1]);
        let e = stack(star(n, 20.0, 20.0, 1000.0), 4.0, (20.0, 20.0));
        let r = shift_image(&e, (2.0, -1.0));
        assert_eq!(r.data[[10, 10]], e.data[[9, 12]]);
    }

    /// Each orientation's target, half a pixel off the centre in its own way, and the e
    /// star at t_o + s, land on the grid's centre pixel.
    #[test]
    fn every_orientation_is_centred_on_the_target() {
        let n = 41;
        for (pos, s) in [((300.3f64, 120.6f64), (0.4, -0.27)), ((511.62, 98.45), (-0.6, 0.31))] {
            let o = stack(
                star(n, 20.0 + pos.0 - pos.0.round(), 20.0 + pos.1 - pos.1.round(), 900.0),
                1.0,
                pos,
            );
            let t = o.target_xy();
            let e = stack(star(n, t.0 + s.0, t.1 + s.1, 700.0), 1.0, (20.0, 20.0));
            let b = OrientationBeams::centred(0.0, &o, &e, s);
            for (what, r) in [("o", &b.o), ("e", &b.e)] {
                let (cx, cy) = centroid(r);
                assert!(
                    (cx - 20.0).abs() < 0.025 && (cy - 20.0).abs() < 0.025,
                    "{what}: {cx} {cy}"
                );
            }
        }
    }

    /// Orientations at the analyzer angles `phis` of a star with polarization (q, u),
    /// through the forward model (o = T I/2 (1 + F), e = T I/2 (1 - F), F = q cos 2phi + u sin
    /// 2phi, T the transparency), with the star's photon noise in the variance over a sky
    /// variance that differs between orientations, the target at a different sub-pixel
    /// position in each orientation and the e image shifted by `s`.
    fn observe(phis: &[f64], q: f64, u: f64, transparency: &[f64]) -> Vec<OrientationBeams> {
        let n = 41;
        phis.iter()
            .zip(transparency)
            .enumerate()
            .map(|(k, (&p, &tr))| {
                let f = q * (2.0 * p.to_radians()).cos() + u * (2.0 * p.to_radians()).sin();
                let pos = (100.0 + 0.31 * k as f64, 50.0 - 0.23 * k as f64);
                let t = (20.0 + pos.0 - pos.0.round(), 20.0 + pos.1 - pos.1.round());
                let sky = 10.0 + 5.0 * k as f32;
                let s = (0.4 - 0.17 * k as f64, 0.2 + 0.1 * k as f64);
                let mk = |x: f64, y: f64, flux: f64, pos: (f64, f64)| {
                    let img = star(n, x, y, flux);
                    let var = img.mapv(|v| sky + v);
                    BeamStack {
                        variance: var,
                        ..stack(img, 0.0, pos)
                    }
                };
                let o = mk(t.0, t.1, tr * 5000.0 * 0.5 * (1.0 + f), pos);
                let e = mk(t.0 + s.0, t.1 + s.1, tr * 5000.0 * 0.5 * (1.0 - f), (20.0, 20.0));
                OrientationBeams::centred(p, &o, &e, s)
            })
            .collect()
    }

    /// Summed over an aperture, Q / I and U / I are the star's q and u, for two, four and
    /// three uneven orientations, whatever the pixels' own variances; a transparency change
    /// between orientations is normalised away.
    #[test]
    fn the_maps_summed_over_an_aperture_give_the_stars_q_and_u() {
        let (q, u) = (0.04, -0.025);
        for (phis, tr) in [
            (vec![0.0, 45.0], vec![1.0, 0.8]),
            (vec![0.0, 45.0, 90.0, 135.0], vec![1.0, 0.95, 0.9, 1.0]),
            (vec![10.0, 70.0, 130.0], vec![1.0, 1.0, 0.85]),
        ] {
            let ors = observe(&phis, q, u, &tr);
            let fluxes: Vec<f64> = tr.iter().map(|t| t * 5000.0).collect();
            let scales = transparency_scales(&fluxes).unwrap();
            let m = stokes_maps(&ors, &scales);
            let sum = |a: &Array2<f32>| -> f64 {
                a.indexed_iter()
                    .filter(|((j, i), _)| (*i as f64 - 20.0).hypot(*j as f64 - 20.0) <= 12.0)
                    .map(|(_, &v)| v as f64)
                    .sum()
            };
            let (si, sq, su) = (sum(&m.i), sum(&m.q), sum(&m.u));
            assert!(
                (sq / si - q).abs() < 2e-5 && (su / si - u).abs() < 2e-5,
                "{phis:?}: {} {}",
                sq / si,
                su / si
            );
            assert!(
                (si / 5000.0 - tr.iter().sum::<f64>() / tr.len() as f64).abs() < 2e-3,
                "{phis:?}: I {si}"
            );
        }
        assert!(transparency_scales(&[1.0, f64::NAN]).is_err() && transparency_scales(&[1.0, 0.0]).is_err());
    }

    /// Pixel by pixel the maps are the least squares of the catalog (fit_qu) on D_k with the
    /// orientations' weights, and the variances are propagated through its coefficients:
    /// for 0/45/90/135 with equal weights Q = (D0 - D90)/2, Var Q = (V0 + V90)/4.
    #[test]
    fn the_maps_are_the_least_squares_pixel_by_pixel() {
        let ors = observe(&[0.0, 45.0, 90.0, 135.0], 0.03, 0.01, &[1.0; 4]);
        // Equal sky variances: the weights differ (10, 15, 20, 25); make them equal.
        let ors: Vec<OrientationBeams> = ors
            .into_iter()
            .map(|mut o| {
                o.o.variance.mapv_inplace(|_| 3.0);
                o.e.variance.mapv_inplace(|_| 2.0);
                o
            })
            .collect();
        let m = stokes_maps(&ors, &[1.0; 4]);
        for (j, i) in [(20, 20), (18, 23), (5, 30)] {
            let d = |k: usize| ors[k].o.data[[j, i]] as f64 - ors[k].e.data[[j, i]] as f64;
            let s = |k: usize| ors[k].o.data[[j, i]] as f64 + ors[k].e.data[[j, i]] as f64;
            let close = |a: f32, b: f64| (a as f64 - b).abs() <= 1e-4 * b.abs().max(1e-2);
            assert!(close(m.q[[j, i]], (d(0) - d(2)) / 2.0), "Q at {j},{i}");
            assert!(close(m.u[[j, i]], (d(1) - d(3)) / 2.0), "U at {j},{i}");
            assert!(close(m.i[[j, i]], (0..4).map(s).sum::<f64>() / 4.0), "I at {j},{i}");
            assert!(
                close(m.var_q[[j, i]], 2.5) && close(m.var_u[[j, i]], 2.5),
                "Var Q, U at {j},{i}"
            );
            assert!(close(m.var_i[[j, i]], 5.0 / 4.0), "Var I at {j},{i}");
            assert!(m.cov_qu[[j, i]].abs() < 1e-6);
        }
        // Two orientations 90 deg apart do not constrain U: masked.
        let two = observe(&[0.0, 90.0], 0.03, 0.01, &[1.0; 2]);
        let m = stokes_maps(&two, &[1.0; 2]);
        assert!(m.mask.iter().all(|&v| v == 1) && m.q.iter().all(|v| v.is_nan()));
    }
}
