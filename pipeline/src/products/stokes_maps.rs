//! Stokes I, Q, U maps of one target from its combined o and e cut-outs
//! (docs/products.md, "Stokes I, Q, U").
//!
//! 1. One sky grid for every image, north up and east left, the target at its centre pixel
//!    c = (h, h). Each orientation's o stack holds the target at `t_o` (within half a pixel
//!    of c: the dithers were registered by whole pixels), its e stack at `t_e = t_o + s`,
//!    where `s` is the measured e-o offset less the whole-pixel registration difference of
//!    the dithers, `s = eo - mean_d (E_d - O_d)` ([`e_to_o_shift`], |s| <= 0.5 px). Both
//!    are resampled onto the detector grid centred on the target, `o'(x, y) = o(x + t_o -
//!    c)` and `e'(x, y) = e(x + t_o + s - c)` ([`OrientationBeams::centred`]), then both
//!    turned about c by the rotator angle onto the sky grid ([`OrientationBeams::on_sky`],
//!    [`sky_to_detector`]), by **Lanczos-3 interpolation** (taps `L(t) = sinc(t)
//!    sinc(t/3)`, |t| < 3, at each point, each axis normalised to sum 1: flux is
//!    conserved). Lanczos rather than bilinear: bilinear interpolation smooths by an amount
//!    that depends on the sub-pixel shift (a half-pixel shift widens a 3 px FWHM star by ~10
//!    %), different for o and e, which moves flux out of a small aperture in one beam more
//!    than in the other and biases F (by ~1 % within 1 FWHM); Lanczos-3 keeps a
//!    well-sampled star's shape, and the rotation samples o' and e' at the same points. The
//!    variance is `sum_k w_k var_k`: what a sum over an aperture of many pixels carries (each
//!    input pixel's weights sum to 1 over the output pixels), where the variance of one
//!    interpolated pixel alone, `sum_k w_k^2 var_k`, would hide the covariance that
//!    interpolation creates between neighbours. A pixel is masked when a tap with non-zero
//!    weight is masked or off the cut-out.
//! 2. The orientations' PSFs matched ([`match_psfs`]): each orientation whose star is more
//!    concentrated than the broadest orientation's is convolved (o' and e' alike) with the
//!    Gaussian that brings it to the broadest's, so that the orientations' I agree in any
//!    aperture.
//! 3. Per orientation k (analyzer angle phi_k): `S_k = o' + e'`, `D_k = o' - e' - f_k S_k`
//!    (`f_k`: what the calibration takes from F, 0 for instrumental maps), times `a_k =
//!    mean_j T_j / T_k`, `T_k` the target's o' + e' flux in an aperture
//!    ([`aperture_fluxes`]): a transparency change between orientations cancels as it does
//!    in the catalog's per-dither normalised difference `F = (o - e)/(o + e)`.
//! 4. Per pixel, the catalog's inversion: `D_k = Q cos 2phi_k + U sin 2phi_k`, i.e. F - f_k =
//!    q cos 2phi + u sin 2phi multiplied by I, solved by the catalog's weighted least squares
//!    ([`fit_qu`]) over the orientations usable at that pixel, with one weight per
//!    orientation, `W_k = 1 / B_k`, B_k the median of a_k^2 V_k over the grid (the
//!    background's variance; weights from each pixel's own variance would hold the star's
//!    photon noise and bias the star's Q and U, as in the combination of the dithers). Q and
//!    U are then fixed linear combinations `Q = sum_k c_k D_k` (for 0 and 45 deg: Q = D(0),
//!    U = D(45)), so `Var Q = sum_k c_k^2 a_k^2 V_k` (likewise Var U, Cov(Q, U)), and
//!    `I = sum_k W_k S_k / sum_k W_k`, `Var I = sum_k W_k^2 a_k^2 (var_o' + var_e') / (sum_k
//!    W_k)^2`. Summed over an aperture, `sum Q / sum I` is the least-squares q of the
//!    aperture's F_k - f_k: the catalog's q of the star in it.
//!
//! The night's calibration (analyzer angles with its zero-point theta0 and parity, the
//! offset c, the telescope's polarization) enters as each orientation's phi_k and f_k
//! ([`OrientationBeams::calibrate`], from [`crate::solve::orientation_corrections`]); the
//! maps are made once the calibration is known.
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
    resample((&stack.data, &stack.variance, &stack.mask), |x, y| {
        (x + shift.0, y + shift.1)
    })
}

/// `stack` resampled by Lanczos-3 interpolation at the point `at(x, y)` of every output
/// pixel (x, y) (module docs): the taps of each point's fractional position, normalised
/// per axis; masked where a tap with non-zero weight is masked or off the cut-out.
fn resample(
    (data_in, variance_in, mask_in): (&Array2<f32>, &Array2<f32>, &Array2<u8>),
    at: impl Fn(f64, f64) -> (f64, f64),
) -> Resampled {
    let (ny, nx) = data_in.dim();
    let mut data = Array2::from_elem((ny, nx), f32::NAN);
    let mut variance = Array2::from_elem((ny, nx), f32::NAN);
    let mut mask = Array2::from_elem((ny, nx), 1u8);
    // The taps of the last fractional position, reused while it repeats (a pure shift
    // has one for the whole image).
    let mut cache: [(f64, [f64; 6]); 2] = [(f64::NAN, [0.0; 6]); 2];
    let mut taps_of = |axis: usize, f: f64| -> [f64; 6] {
        if cache[axis].0 != f {
            cache[axis] = (f, taps(f));
        }
        cache[axis].1
    };
    for j in 0..ny {
        for i in 0..nx {
            let (sx, sy) = at(i as f64, j as f64);
            if !(sx.is_finite() && sy.is_finite()) {
                continue;
            }
            let (x0, y0) = (sx.floor(), sy.floor());
            let (wx, wy) = (taps_of(0, sx - x0), taps_of(1, sy - y0));
            let (x0, y0) = (x0 as i64, y0 as i64);
            let mut acc = (0.0f64, 0.0f64);
            let mut ok = true;
            'taps: for (n, &wy) in wy.iter().enumerate() {
                for (m, &wx) in wx.iter().enumerate() {
                    let w = wx * wy;
                    if w == 0.0 {
                        continue;
                    }
                    let (yy, xx) = (y0 + n as i64 - 2, x0 + m as i64 - 2);
                    if yy < 0
                        || xx < 0
                        || yy >= ny as i64
                        || xx >= nx as i64
                        || mask_in[[yy as usize, xx as usize]] != 0
                    {
                        ok = false;
                        break 'taps;
                    }
                    let (yy, xx) = (yy as usize, xx as usize);
                    acc.0 += w * data_in[[yy, xx]] as f64;
                    acc.1 += w * variance_in[[yy, xx]] as f64;
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

/// The detector offset, at rotator angle `posang_deg`, of the sky offset that is `(dx, dy)`
/// px on a north-up, east-left grid (the frame contract's rotation: `R(-POSANG)`, so that
/// a star at separation r and PA psi, `(-r sin psi, r cos psi)` on the sky grid, lands at
/// `(-r sin(psi - POSANG), r cos(psi - POSANG))`).
pub fn sky_to_detector(posang_deg: f64, (dx, dy): (f64, f64)) -> (f64, f64) {
    let (s, c) = posang_deg.to_radians().sin_cos();
    (c * dx + s * dy, -s * dx + c * dy)
}

/// One orientation's beams on the common grid.
#[derive(Debug, Clone)]
pub struct OrientationBeams {
    /// Analyzer angle, deg: the profile's, or the calibration's once applied
    /// ([`OrientationBeams::calibrate`]).
    pub analyzer_deg: f64,
    /// What is taken from this orientation's normalised difference F before the solve: the
    /// calibration's offset c and the telescope's term (0: instrumental).
    pub f_offset: f64,
    /// The combined o cut-out, resampled.
    pub o: Resampled,
    /// The combined e cut-out, resampled.
    pub e: Resampled,
}

impl OrientationBeams {
    /// The o and e stacks of one orientation onto the grid whose centre pixel holds the
    /// target (module docs, step 1); `shift` is [`e_to_o_shift`]. The grid is the
    /// detector's (no rotation).
    pub fn centred(analyzer_deg: f64, o: &BeamStack, e: &BeamStack, shift: (f64, f64)) -> OrientationBeams {
        let (t, c) = (o.target_xy(), o.half as f64);
        OrientationBeams {
            analyzer_deg,
            f_offset: 0.0,
            o: shift_image(o, (t.0 - c, t.1 - c)),
            e: shift_image(e, (t.0 + shift.0 - c, t.1 + shift.1 - c)),
        }
    }

    /// The o and e stacks of one orientation, taken at rotator angle `posang_deg`, onto the
    /// sky grid: north up, east left, the target on the centre pixel c (module docs, step
    /// 1). First both onto the detector grid centred on the target ([`Self::centred`]), then
    /// both turned about c by the same rotation: output pixel p takes the centred images at
    /// `c + R(-POSANG) (p - c)` ([`sky_to_detector`]). The rotation samples o and e at the
    /// same sub-pixel points, so it smooths them alike and keeps F = (o - e)/(o + e) of a
    /// star in any aperture (sampling each stack at its own points, a sub-pixel apart,
    /// biases F in a one-FWHM aperture by ~1e-3).
    pub fn on_sky(
        analyzer_deg: f64,
        posang_deg: f64,
        o: &BeamStack,
        e: &BeamStack,
        shift: (f64, f64),
    ) -> OrientationBeams {
        let mut b = Self::centred(analyzer_deg, o, e, shift);
        if posang_deg.rem_euclid(360.0) != 0.0 {
            let c = o.half as f64;
            let turn = |r: &Resampled| {
                resample((&r.data, &r.variance, &r.mask), |x, y| {
                    let d = sky_to_detector(posang_deg, (x - c, y - c));
                    (c + d.0, c + d.1)
                })
            };
            b.o = turn(&b.o);
            b.e = turn(&b.e);
        }
        b
    }

    /// The calibration of this orientation applied: its analyzer angle and what it takes
    /// from F (`f_offset`).
    pub fn calibrate(&mut self, analyzer_deg: f64, f_offset: f64) {
        self.analyzer_deg = analyzer_deg;
        self.f_offset = f_offset;
    }

    /// Whether pixel (j, i) is usable in both beams.
    fn usable(&self, j: usize, i: usize) -> bool {
        self.o.mask[[j, i]] == 0 && self.e.mask[[j, i]] == 0
    }

    /// The variance of `D - f_offset S` at (j, i): `(1 - f)^2 var_o' + (1 + f)^2 var_e'`
    /// (`var_o' + var_e'` for instrumental maps).
    fn var(&self, j: usize, i: usize) -> f64 {
        let f = self.f_offset;
        (1.0 - f).powi(2) * self.o.variance[[j, i]] as f64 + (1.0 + f).powi(2) * self.e.variance[[j, i]] as f64
    }
}

/// The normalised taps of a Gaussian of `sigma` px, out to 3 sigma (one tap of 1 at 0).
fn gaussian_taps(sigma: f64) -> Vec<f64> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let n = (3.0 * sigma).ceil() as i64;
    let w: Vec<f64> = (-n..=n).map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp()).collect();
    let sum: f64 = w.iter().sum();
    w.into_iter().map(|v| v / sum).collect()
}

/// `r` convolved with a Gaussian of `sigma` px (separable; variance `sum w var`, what an
/// aperture sum carries, as in the resampling); a pixel is masked when a tap is masked or
/// off the grid.
fn convolve(r: &Resampled, sigma: f64) -> Resampled {
    let w = gaussian_taps(sigma);
    if w.len() == 1 {
        return r.clone();
    }
    let h = (w.len() / 2) as i64;
    let pass = |src: &Resampled, along_x: bool| -> Resampled {
        let (ny, nx) = src.data.dim();
        let mut out = Resampled {
            data: Array2::from_elem((ny, nx), f32::NAN),
            variance: Array2::from_elem((ny, nx), f32::NAN),
            mask: Array2::from_elem((ny, nx), 1u8),
        };
        for j in 0..ny {
            'px: for i in 0..nx {
                let (mut d, mut v) = (0.0f64, 0.0f64);
                for (k, &wk) in w.iter().enumerate() {
                    let o = k as i64 - h;
                    let (jj, ii) = if along_x {
                        (j as i64, i as i64 + o)
                    } else {
                        (j as i64 + o, i as i64)
                    };
                    if jj < 0 || ii < 0 || jj >= ny as i64 || ii >= nx as i64 {
                        continue 'px;
                    }
                    let (jj, ii) = (jj as usize, ii as usize);
                    if src.mask[[jj, ii]] != 0 {
                        continue 'px;
                    }
                    d += wk * src.data[[jj, ii]] as f64;
                    v += wk * src.variance[[jj, ii]] as f64;
                }
                out.data[[j, i]] = d as f32;
                out.variance[[j, i]] = v as f32;
                out.mask[[j, i]] = 0;
            }
        }
        out
    };
    pass(&pass(r, true), false)
}

/// Sum of `o + e` over the pixels within `radius` of `(c, c)` usable in `usable`.
fn aperture_sum(b: &OrientationBeams, c: f64, radius: f64, usable: &Array2<u8>) -> f64 {
    let mut s = 0.0;
    for ((j, i), &u) in usable.indexed_iter() {
        if u == 0 && (i as f64 - c).hypot(j as f64 - c) <= radius {
            s += b.o.data[[j, i]] as f64 + b.e.data[[j, i]] as f64;
        }
    }
    s
}

/// 0 where every orientation's two beams are usable, else 1.
fn usable_everywhere(orients: &[OrientationBeams]) -> Array2<u8> {
    let dim = orients.first().map_or((0, 0), |o| o.o.data.dim());
    Array2::from_shape_fn(dim, |(j, i)| u8::from(!orients.iter().all(|o| o.usable(j, i))))
}

/// The star's concentration in one orientation: the share of its `o + e` flux within
/// `inner` of the centre `c` of that within `outer` (pixels usable in every orientation).
fn concentration(b: &OrientationBeams, c: f64, (inner, outer): (f64, f64), usable: &Array2<u8>) -> f64 {
    aperture_sum(b, c, inner, usable) / aperture_sum(b, c, outer, usable)
}

/// Match the orientations' PSFs (module docs, step 2): each orientation sharper than the
/// broadest (a larger share of the star's flux within `inner` of the centre `c` than
/// within `outer`) has its o and e convolved with the Gaussian that brings its share to the
/// broadest's (found by bisection, to 1e-4 px). o and e of an orientation get the same
/// kernel, so a star's F = (o - e)/(o + e) is unchanged; the orientations' I then agree in
/// an aperture of any size, and the least squares of the maps summed over an aperture is
/// that of the aperture's F. Returns the Gaussian sigma applied to each orientation, px.
pub fn match_psfs(orients: &mut [OrientationBeams], c: f64, (inner, outer): (f64, f64)) -> Vec<f64> {
    let usable = usable_everywhere(orients);
    let shares: Vec<f64> = orients
        .iter()
        .map(|b| concentration(b, c, (inner, outer), &usable))
        .collect();
    let Some(target) = shares.iter().copied().filter(|v| v.is_finite()).reduce(f64::min) else {
        return vec![0.0; orients.len()];
    };
    orients
        .iter_mut()
        .zip(&shares)
        .map(|(b, &share)| {
            if !(share.is_finite() && share > target * (1.0 + 1e-6)) {
                return 0.0;
            }
            let smoothed = |sigma: f64| OrientationBeams {
                o: convolve(&b.o, sigma),
                e: convolve(&b.e, sigma),
                ..b.clone()
            };
            let (mut lo, mut hi) = (0.0f64, inner.max(1.0));
            while concentration(&smoothed(hi), c, (inner, outer), &usable) > target && hi < 4.0 * outer {
                hi *= 2.0;
            }
            while hi - lo > 1e-4 {
                let mid = 0.5 * (lo + hi);
                if concentration(&smoothed(mid), c, (inner, outer), &usable) > target {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let sigma = 0.5 * (lo + hi);
            *b = smoothed(sigma);
            sigma
        })
        .collect()
}

/// The target's `o + e` flux of each orientation within `radius` of the centre `c`, over
/// the pixels usable in every orientation: what [`transparency_scales`] normalises.
pub fn aperture_fluxes(orients: &[OrientationBeams], c: f64, radius: f64) -> Vec<f64> {
    let usable = usable_everywhere(orients);
    orients.iter().map(|b| aperture_sum(b, c, radius, &usable)).collect()
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
            // F - f_offset for the star in an aperture: D - f_offset S.
            let d = a * ((vo - ve) - o.f_offset * (vo + ve));
            q += cq * d;
            u += cu * d;
            vq += cq * cq * v;
            vu += cu * cu * v;
            cqu += cq * cu * v;
            sw += w;
            sws += w * a * (vo + ve);
            sw2v += w * w * a * a * (o.o.variance[[j, i]] as f64 + o.e.variance[[j, i]] as f64);
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

    /// A Gaussian star of `sigma` px (total flux `flux`) at (x, y) on an n x n grid.
    fn star_sigma(n: usize, (x, y): (f64, f64), flux: f64, sigma: f64) -> Array2<f32> {
        let s2 = sigma * sigma;
        Array2::from_shape_fn((n, n), |(j, i)| {
            let r2 = (i as f64 - x).powi(2) + (j as f64 - y).powi(2);
            (flux * (-r2 / (2.0 * s2)).exp() / (2.0 * std::f64::consts::PI * s2)) as f32
        })
    }

    /// On the sky grid, a companion at separation 6 px and position angle 30 deg sits at
    /// (-6 sin 30, 6 cos 30) px from the target whatever the rotator angle: on the detector
    /// it was at the frame contract's (-r sin(psi - POSANG), r cos(psi - POSANG)).
    #[test]
    fn on_the_sky_grid_north_is_up_and_east_left_at_every_rotator_angle() {
        let (n, h) = (41usize, 20.0);
        let (r, psi) = (6.0f64, 30f64.to_radians());
        for posang in [0.0f64, 45.0, 90.0, 135.0, -60.0] {
            let th = posang.to_radians();
            let t = (h + 0.3, h - 0.2);
            let b = (t.0 - r * (psi - th).sin(), t.1 + r * (psi - th).cos());
            let img = &star_sigma(n, t, 1000.0, 1.3) + &star_sigma(n, b, 500.0, 1.3);
            let o = stack(img.clone(), 1.0, (100.0 + 0.3, 50.0 - 0.2));
            let e = stack(img, 1.0, (20.0, 20.0));
            let beams = OrientationBeams::on_sky(0.0, posang, &o, &e, (0.0, 0.0));
            let want = (h - r * psi.sin(), h + r * psi.cos());
            // Centroids within 3 px of where each star should be.
            let near = |x: f64, y: f64| {
                let mut r = beams.o.clone();
                for ((j, i), v) in r.data.indexed_iter_mut() {
                    if (i as f64 - x).hypot(j as f64 - y) > 3.0 {
                        *v = 0.0;
                    }
                }
                centroid(&r)
            };
            let (bx, by) = near(want.0, want.1);
            assert!(
                (bx - want.0).hypot(by - want.1) < 0.05,
                "POSANG {posang}: B at ({bx:.3}, {by:.3}), want ({:.3}, {:.3})",
                want.0,
                want.1
            );
            let (ax, ay) = near(h, h);
            assert!(
                (ax - h).abs() < 0.05 && (ay - h).abs() < 0.05,
                "POSANG {posang}: A at ({ax}, {ay})"
            );
        }
    }

    /// Two orientations seen through different seeing (Gaussian sigma 1.2 and 1.9 px) and
    /// transparency: summed over a small aperture (1.5 px), the maps give the star's q and u
    /// once the PSFs are matched (the sharper orientation smoothed to sigma ~ sqrt(1.9^2 -
    /// 1.2^2)), and are off by several 1e-3 without it.
    #[test]
    fn matched_psfs_make_a_small_aperture_give_the_stars_q_and_u() {
        let (q, u) = (0.04, -0.03);
        let n = 41;
        let make = |phi: f64, sigma: f64, tr: f64| {
            let f = q * (2.0 * phi.to_radians()).cos() + u * (2.0 * phi.to_radians()).sin();
            let img = |frac: f64| {
                let d = star_sigma(n, (20.0, 20.0), tr * 8000.0 * frac, sigma);
                BeamStack {
                    variance: d.mapv(|v| 5.0 + v),
                    ..stack(d, 0.0, (100.0, 50.0))
                }
            };
            OrientationBeams::on_sky(phi, 0.0, &img(0.5 * (1.0 + f)), &img(0.5 * (1.0 - f)), (0.0, 0.0))
        };
        let beams = vec![make(0.0, 1.2, 1.0), make(45.0, 1.9, 0.85)];
        let in_aperture = |m: &StokesMaps| {
            let sum = |a: &Array2<f32>| -> f64 {
                a.indexed_iter()
                    .filter(|((j, i), _)| (*i as f64 - 20.0).hypot(*j as f64 - 20.0) <= 1.5)
                    .map(|(_, &v)| v as f64)
                    .sum()
            };
            (sum(&m.q) / sum(&m.i), sum(&m.u) / sum(&m.i))
        };
        let unmatched = stokes_maps(
            &beams,
            &transparency_scales(&aperture_fluxes(&beams, 20.0, 9.0)).unwrap(),
        );
        let (uq, uu) = in_aperture(&unmatched);
        assert!((uq - q).abs().max((uu - u).abs()) > 3e-3, "unmatched: {uq} {uu}");
        let mut matched = beams.clone();
        let sigmas = match_psfs(&mut matched, 20.0, (1.5, 9.0));
        let expect = (1.9f64.powi(2) - 1.2f64.powi(2)).sqrt();
        assert!(
            sigmas[1] == 0.0 && (sigmas[0] - expect).abs() < 0.05,
            "{sigmas:?} vs {expect}"
        );
        let m = stokes_maps(
            &matched,
            &transparency_scales(&aperture_fluxes(&matched, 20.0, 9.0)).unwrap(),
        );
        let (mq, mu) = in_aperture(&m);
        assert!((mq - q).abs() < 3e-4 && (mu - u).abs() < 3e-4, "matched: {mq} {mu}");
    }

    /// With the calibration applied (analyzer angles moved by theta0, f_k taken from each
    /// orientation's F), the maps summed over an aperture give the star's q, u on the sky.
    #[test]
    fn calibrated_orientations_give_the_sky_q_and_u() {
        let (q, u, theta0, c) = (0.03, 0.02, 3.0f64, 0.018);
        let tel = [0.004, -0.002, 0.001, 0.003];
        let phis = [0.0, 45.0, 90.0, 135.0];
        // F_k = q cos 2(phi_k + theta0) + u sin 2(phi_k + theta0) + c + T_k.
        let mut beams: Vec<OrientationBeams> = phis
            .iter()
            .zip(tel)
            .map(|(&p, t)| {
                let phi = (p + theta0).to_radians();
                let f = q * (2.0 * phi).cos() + u * (2.0 * phi).sin() + c + t;
                let img = |frac: f64| {
                    let d = star_sigma(41, (20.0, 20.0), 5000.0 * frac, 1.5);
                    stack(d, 1.0, (100.0, 50.0))
                };
                OrientationBeams::on_sky(p, 0.0, &img(0.5 * (1.0 + f)), &img(0.5 * (1.0 - f)), (0.0, 0.0))
            })
            .collect();
        for (b, (&p, t)) in beams.iter_mut().zip(phis.iter().zip(tel)) {
            b.calibrate(p + theta0, c + t);
        }
        let m = stokes_maps(&beams, &[1.0; 4]);
        let sum = |a: &Array2<f32>| -> f64 { a.iter().filter(|v| v.is_finite()).map(|&v| v as f64).sum() };
        let (mq, mu) = (sum(&m.q) / sum(&m.i), sum(&m.u) / sum(&m.i));
        assert!((mq - q).abs() < 1e-5 && (mu - u).abs() < 1e-5, "{mq} {mu}");
    }
}
