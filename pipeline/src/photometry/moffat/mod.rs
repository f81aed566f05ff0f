//! Pixel-integrated circular Moffat star model, by Gauss-Legendre quadrature per pixel.
//!
//! A star of total flux `F` at `(x, y)` has the surface brightness
//! `F (beta - 1)/(pi alpha^2) (1 + r^2/alpha^2)^-beta` (unit integral over the plane for
//! `beta > 1`); its FWHM is `2 alpha sqrt(2^(1/beta) - 1)`. The content of a pixel has no
//! closed form: it is integrated with a tensor Gauss-Legendre rule whose order depends on the
//! distance `d` of the pixel centre from the star (in units of `alpha`):
//!
//! | region | nodes |
//! |---|---|
//! | `d < 2 alpha` | 4 x 4 |
//! | `2 alpha <= d < 5 alpha` | 3 x 3 |
//! | `5 alpha <= d < 12 alpha` | 2 x 2 |
//! | `d >= 12 alpha` | 1 (midpoint) |
//!
//! Against a 20 x 20 rule (FWHM 2-4 px, beta 2.5-4; test
//! `photometry_moffat_pixel_quadrature_accuracy`): worst relative error 9.1e-7 within
//! 1.5 FWHM, and 8.5e-7 of the peak pixel anywhere. These zones are the cheapest found that
//! keep the noiseless inversion at <= 5e-8 (docs/accuracy.md); they set ~45 % of the cost of
//! a night.
//!
//! plus, for very narrow stars (`alpha < 1.2 px`, FWHM below ~1.2 px at beta 3), a 2 x 2
//! split of the pixels within 2 px of the centre, each half integrated with 4 nodes.
//! The order switches are discontinuities of the model of < 1e-6 of the peak pixel, far below
//! any noise. Derivatives with respect to the star's position, `alpha` and `beta` are
//! computed by differentiating under the integral at the same nodes, so they are the exact
//! derivatives of the quadrature (what the Levenberg-Marquardt fit needs).
//!
//! The pixel integral by the rule of its zone, with `t = r^2/alpha^2` at a node, `u = 1 + t`,
//! weights `w` and the node's offset `(X, Y)` from the star:
//!
//! ```text
//!   P          = (beta - 1)/(pi alpha^2) sum w u^-beta
//!   dP/dx      = -dP/dX  = 2 beta (beta - 1)/(pi alpha^4) sum w u^-beta X/u   (y alike)
//!   dP/dalpha  = (beta - 1)/(pi alpha^2) 2/alpha (beta sum w u^-beta t/u - sum w u^-beta)
//!   dP/dbeta   = (beta - 1)/(pi alpha^2) (sum w u^-beta / (beta - 1) - sum w u^-beta ln u)
//! ```
//!
//! An **elliptical** star replaces `r^2` by the form `(1 - e1) X^2 - 2 e2 X Y + (1 + e1) Y^2`
//! (ellipticity `(e1, e2)`, `|e| < 1`: axis ratio `sqrt((1 - |e|)/(1 + |e|))`, major axis at
//! `atan2(e2, e1)/2` from +x towards +y; [`moffat_ellipticity`]) and multiplies the
//! normalisation by `sqrt(det)`, `det = 1 - e1^2 - e2^2`, so the flux stays the integral.
//! Its rule is chosen by the distance in that metric. Two more sums, of `w p (X^2 - Y^2)/u`
//! (`sd`) and `w p 2 X Y/u` (`sc`), give the derivatives in the ellipticity; the position
//! derivatives mix `sx` and `sy`:
//!
//! ```text
//!   dP/dx      = c ((1 - e1) sx - e2 sy),   dP/dy = c ((1 + e1) sy - e2 sx)
//!   dP/de1     = norm (beta sd/alpha^2 - e1 s0/det),   dP/de2 = norm (beta sc/alpha^2 - e2 s0/det)
//! ```
//!
//! with `norm = (beta - 1) sqrt(det)/(pi alpha^2)`, `c = 2 beta norm/alpha^2`; `dP/dalpha`
//! and `dP/dbeta` keep their form.
//!
//! The sums over the nodes are the costly part: `moffat/kernel.rs` computes them for many
//! pixels at once, vectorised ([`moffat_pixels`], [`moffat_pixels_derivs`]; one pixel goes
//! through it too), with the elementary functions of `moffat/ln_exp.rs`.

use ndarray::ArrayViewMut2;

use crate::numeric::{GL1_W, GL1_X, GL2_W, GL2_X, GL3_W, GL3_X, GL4_W, GL4_X};

mod kernel;
mod ln_exp;

pub(crate) use kernel::moffat_pixels_derivs_any;
pub use kernel::{moffat_pixels, moffat_pixels_derivs, moffat_pixels_derivs_elliptical, moffat_pixels_elliptical};

/// 4 nodes on each half of `[-1/2, 1/2]` (composite rule for the cores of narrow stars).
const GL4X2_X: [f64; 8] = [
    -0.25 + 0.5 * -0.430_568_155_797_026_3,
    -0.25 + 0.5 * -0.169_990_521_792_428_1,
    -0.25 + 0.5 * 0.169_990_521_792_428_1,
    -0.25 + 0.5 * 0.430_568_155_797_026_3,
    0.25 + 0.5 * -0.430_568_155_797_026_3,
    0.25 + 0.5 * -0.169_990_521_792_428_1,
    0.25 + 0.5 * 0.169_990_521_792_428_1,
    0.25 + 0.5 * 0.430_568_155_797_026_3,
];
/// Weights of [`GL4X2_X`] (sum 1).
const GL4X2_W: [f64; 8] = [
    0.5 * 0.173_927_422_568_726_9,
    0.5 * 0.326_072_577_431_273_1,
    0.5 * 0.326_072_577_431_273_1,
    0.5 * 0.173_927_422_568_726_9,
    0.5 * 0.173_927_422_568_726_9,
    0.5 * 0.326_072_577_431_273_1,
    0.5 * 0.326_072_577_431_273_1,
    0.5 * 0.173_927_422_568_726_9,
];

/// FWHM (px) of a Moffat profile with parameters `alpha` (px) and `beta`.
pub fn moffat_fwhm(alpha: f64, beta: f64) -> f64 {
    2.0 * alpha * (2f64.powf(1.0 / beta) - 1.0).sqrt()
}

/// `alpha` (px) of the Moffat profile of FWHM `fwhm` (px) and index `beta`.
pub fn moffat_alpha(fwhm: f64, beta: f64) -> f64 {
    fwhm / (2.0 * (2f64.powf(1.0 / beta) - 1.0).sqrt())
}

/// Unit-flux Moffat surface brightness (1/px^2) at squared distance `r2` (px^2).
pub fn moffat_profile(r2: f64, alpha: f64, beta: f64) -> f64 {
    let ia2 = 1.0 / (alpha * alpha);
    (beta - 1.0) / std::f64::consts::PI * ia2 * (-beta * (r2 * ia2).ln_1p()).exp()
}

/// Fraction of a unit-flux Moffat's light outside radius `r` (px), `(1 + r^2/alpha^2)^(1-beta)`.
pub fn moffat_outside(r: f64, alpha: f64, beta: f64) -> f64 {
    ((1.0 - beta) * (r * r / (alpha * alpha)).ln_1p()).exp()
}

/// The quadrature rule for a pixel whose centre is `(dx, dy)` from the star.
#[inline]
fn rule(dx: f64, dy: f64, alpha: f64) -> (&'static [f64], &'static [f64]) {
    rule_of(dx * dx + dy * dy, alpha)
}

/// The quadrature rule for a pixel whose centre is at squared distance `d2` (px^2; in the
/// star's metric for an elliptical star) from the star.
#[inline]
fn rule_of(d2: f64, alpha: f64) -> (&'static [f64], &'static [f64]) {
    let a2 = alpha * alpha;
    if d2 < 4.0 * a2 {
        if alpha < 1.2 && d2 < 4.0 {
            (&GL4X2_X, &GL4X2_W)
        } else {
            (&GL4_X, &GL4_W)
        }
    } else if d2 < 25.0 * a2 {
        (&GL3_X, &GL3_W)
    } else if d2 < 144.0 * a2 {
        (&GL2_X, &GL2_W)
    } else {
        // Far wings (beyond 12 alpha): the midpoint rule. Its relative error there is
        // ~ beta(2 beta + 1)/(12 r^2/alpha^2) < 0.3 % of a pixel value below 1e-6 of the
        // flux, i.e. < 3e-9 of the flux per pixel.
        (&GL1_X, &GL1_W)
    }
}

/// The pixel value `P` from the sum `s0 = sum w u^-beta` over its nodes (`ia2 = 1/alpha^2`).
#[inline(always)]
fn value_of_sum(s0: f64, ia2: f64, beta: f64) -> f64 {
    // The operations of derivs_of_sums' value, in its order: the same value bit for bit.
    (beta - 1.0) / std::f64::consts::PI * ia2 * s0
}

/// `[P, dP/dx, dP/dy, dP/dalpha, dP/dbeta]` of a pixel from the sums over its nodes of
/// `w p`, `w p X/u`, `w p Y/u`, `w p t/u`, `w p ln u` (`p = u^-beta`; see the module's
/// formulas).
#[inline(always)]
fn derivs_of_sums([s0, sx, sy, st, sl]: [f64; 5], alpha: f64, ia2: f64, beta: f64) -> [f64; 5] {
    let norm = (beta - 1.0) / std::f64::consts::PI * ia2;
    let c = 2.0 * beta * ia2 * norm;
    [
        norm * s0,
        c * sx,
        c * sy,
        norm * 2.0 / alpha * (beta * st - s0),
        norm * (s0 / (beta - 1.0) - sl),
    ]
}

/// The pixel value of an elliptical star from `s0 = sum w u^-beta` (`det = 1 - e1^2 - e2^2`
/// scales the circular normalisation by `sqrt(det)`).
#[inline(always)]
fn value_of_sum_elliptical(s0: f64, ia2: f64, beta: f64, e: [f64; 2]) -> f64 {
    (beta - 1.0) / std::f64::consts::PI * ia2 * (1.0 - e[0] * e[0] - e[1] * e[1]).sqrt() * s0
}

/// `[P, dP/dx, dP/dy, dP/dalpha, dP/dbeta, dP/de1, dP/de2]` of a pixel of an elliptical star
/// from the sums over its nodes of `w p`, `w p X/u`, `w p Y/u`, `w p t/u`, `w p ln u`,
/// `w p (X^2 - Y^2)/u`, `w p 2 X Y/u` (see the module's formulas).
#[inline(always)]
fn derivs_of_sums_elliptical(
    [s0, sx, sy, st, sl, sd, sc]: [f64; 7],
    alpha: f64,
    ia2: f64,
    beta: f64,
    [e1, e2]: [f64; 2],
) -> [f64; 7] {
    let det = 1.0 - e1 * e1 - e2 * e2;
    let norm = (beta - 1.0) / std::f64::consts::PI * ia2 * det.sqrt();
    let c = 2.0 * beta * ia2 * norm;
    [
        norm * s0,
        c * ((1.0 - e1) * sx - e2 * sy),
        c * ((1.0 + e1) * sy - e2 * sx),
        norm * 2.0 / alpha * (beta * st - s0),
        norm * (s0 / (beta - 1.0) - sl),
        norm * (beta * ia2 * sd - e1 / det * s0),
        norm * (beta * ia2 * sc - e2 / det * s0),
    ]
}

/// The fraction of a unit-flux elliptical Moffat (`alpha`, `beta`, ellipticity `e`; see the
/// module's doc) falling in the pixel whose centre is at `(dx, dy)` px from the star.
pub fn moffat_pixel_elliptical(dx: f64, dy: f64, alpha: f64, beta: f64, e: [f64; 2]) -> f64 {
    let mut v = [0.0];
    moffat_pixels_elliptical(&[(dx, dy)], alpha, beta, e, &mut v);
    v[0]
}

/// [`moffat_pixel_elliptical`] and its derivatives: `[P, dP/dx, dP/dy, dP/dalpha, dP/dbeta,
/// dP/de1, dP/de2]` (`x`, `y` the star's centre).
pub fn moffat_pixel_derivs_elliptical(dx: f64, dy: f64, alpha: f64, beta: f64, e: [f64; 2]) -> [f64; 7] {
    let mut d = [[0.0; 7]];
    moffat_pixels_derivs_elliptical(&[(dx, dy)], alpha, beta, e, &mut d);
    d[0]
}

/// The ellipticity `(e1, e2)` of an elliptical Moffat whose axes have the ratio `ratio`
/// (minor/major, in (0, 1]) and whose major axis is at `pa_deg` from +x towards +y:
/// `|e| = (1 - ratio^2)/(1 + ratio^2)` along `2 pa`.
pub fn moffat_ellipticity(ratio: f64, pa_deg: f64) -> [f64; 2] {
    let m = (1.0 - ratio * ratio) / (1.0 + ratio * ratio);
    let (s, c) = (2.0 * pa_deg.to_radians()).sin_cos();
    [m * c, m * s]
}

/// The axis ratio (minor/major) and the major axis' angle (deg from +x towards +y, in
/// [0, 180)) of the ellipticity `e`: the inverse of [`moffat_ellipticity`].
pub fn moffat_axes(e: [f64; 2]) -> (f64, f64) {
    let m = e[0].hypot(e[1]);
    let ratio = ((1.0 - m) / (1.0 + m)).sqrt();
    let pa = (0.5 * e[1].atan2(e[0]).to_degrees()).rem_euclid(180.0);
    (ratio, pa)
}

/// Fraction of a unit-flux Moffat `(alpha, beta)` falling in the pixel whose centre is at
/// `(dx, dy)` px from the star's centre (`dx = ix - x`).
pub fn moffat_pixel(dx: f64, dy: f64, alpha: f64, beta: f64) -> f64 {
    let mut v = [0.0];
    moffat_pixels(&[(dx, dy)], alpha, beta, &mut v);
    v[0]
}

/// [`moffat_pixel`] and its derivatives: `[P, dP/dx, dP/dy, dP/dalpha, dP/dbeta]`, where `x`,
/// `y` are the star's centre (so `dP/dx = -dP/d(dx)`).
pub fn moffat_pixel_derivs(dx: f64, dy: f64, alpha: f64, beta: f64) -> [f64; 5] {
    // One pixel: no allocation (the batch form copies through a buffer of 7 entries).
    let mut d = [[0.0; 7]];
    moffat_pixels_derivs_any(&[(dx, dy)], alpha, beta, None, &mut d);
    [d[0][0], d[0][1], d[0][2], d[0][3], d[0][4]]
}

/// Adds a pixel-integrated Moffat star (total flux `flux` ADU, centre `(x, y)` px, `alpha` px,
/// `beta > 1`) to `img` (indexed `[y, x]`), over the pixels within the radius enclosing all
/// but 1e-9 of the flux (clipped to the image). A negative flux subtracts the star.
pub fn add_moffat(img: &mut ArrayViewMut2<f32>, flux: f64, x: f64, y: f64, alpha: f64, beta: f64) {
    add_moffat_where(img, flux, x, y, alpha, beta, |_, _| true);
}

/// [`add_moffat`] on the pixels `(ix, iy)` for which `keep(ix, iy)` holds only (the others
/// are left as they are); those get the values [`add_moffat`] gives them, bit for bit.
pub fn add_moffat_where(
    img: &mut ArrayViewMut2<f32>,
    flux: f64,
    x: f64,
    y: f64,
    alpha: f64,
    beta: f64,
    keep: impl Fn(usize, usize) -> bool,
) {
    add_star(img, flux, (x, y), alpha, beta, None, keep);
}

/// [`add_moffat`] for an elliptical star of ellipticity `e` (see the module's doc; `|e| < 1`).
pub fn add_moffat_elliptical(
    img: &mut ArrayViewMut2<f32>,
    flux: f64,
    x: f64,
    y: f64,
    alpha: f64,
    beta: f64,
    e: [f64; 2],
) {
    add_star(img, flux, (x, y), alpha, beta, Some(e), |_, _| true);
}

/// An elliptical Moffat star to draw ([`add_moffat_elliptical_where`]): its flux, where it
/// is and its shape, the arguments of [`add_moffat_elliptical`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MoffatStar {
    /// Total flux (the sum of its pixel values over the whole plane), image units.
    pub flux: f64,
    /// Centre, x (column), px (0-based, pixel centres at integers).
    pub x_px: f64,
    /// Centre, y (row), px.
    pub y_px: f64,
    /// Width alpha, px.
    pub alpha_px: f64,
    /// Power-law index beta (> 1).
    pub beta: f64,
    /// Ellipticity (e1, e2), `|e| < 1` (see the module's doc).
    pub e: [f64; 2],
}

/// [`add_moffat_elliptical`] of `star` on the pixels `(ix, iy)` for which `keep(ix, iy)`
/// holds only; those get the values [`add_moffat_elliptical`] gives them, bit for bit.
pub fn add_moffat_elliptical_where(
    img: &mut ArrayViewMut2<f32>,
    star: MoffatStar,
    keep: impl Fn(usize, usize) -> bool,
) {
    add_star(
        img,
        star.flux,
        (star.x_px, star.y_px),
        star.alpha_px,
        star.beta,
        Some(star.e),
        keep,
    );
}

/// Adds a circular (`e` None) or elliptical star, over the pixels within the ellipse (in
/// the star's metric) enclosing all but 1e-9 of the flux, where `keep` holds.
fn add_star(
    img: &mut ArrayViewMut2<f32>,
    flux: f64,
    (x, y): (f64, f64),
    alpha: f64,
    beta: f64,
    e: Option<[f64; 2]>,
    keep: impl Fn(usize, usize) -> bool,
) {
    let (ny, nx) = img.dim();
    let e_ok = e.is_none_or(|e| e[0].hypot(e[1]) < 1.0);
    let ok =
        nx > 0 && ny > 0 && alpha > 0.0 && alpha.is_finite() && beta > 1.0 && x.is_finite() && y.is_finite() && e_ok;
    if !ok {
        return;
    }
    // (1 + R^2/alpha^2)^(1 - beta) = 1e-9.
    let t = (9.0 * std::f64::consts::LN_10 / (beta - 1.0)).exp_m1();
    let rmax = (alpha * t.sqrt()).min(1e5) + 1.0;
    // The ellipse's major semi-axis is rmax/sqrt(1 - |e|) (the form's smaller eigenvalue).
    let reach = match e {
        None => rmax,
        Some(e) => (rmax / (1.0 - e[0].hypot(e[1])).sqrt()).min(1e5),
    };
    let span = |c: f64, n: usize| -> (usize, usize) {
        let lo = (c - reach).floor().max(0.0).min(n as f64 - 1.0) as usize;
        let hi = (c + reach).ceil().max(0.0).min(n as f64 - 1.0) as usize;
        (lo, hi)
    };
    let (x_lo, x_hi) = span(x, nx);
    let (y_lo, y_hi) = span(y, ny);
    // The pixels to change, then their values from the batched kernel.
    let (mut at, mut offsets) = (Vec::new(), Vec::new());
    for iy in y_lo..=y_hi {
        let dy = iy as f64 - y;
        for ix in x_lo..=x_hi {
            let dx = ix as f64 - x;
            let d2 = match e {
                None => dx * dx + dy * dy,
                Some([e1, e2]) => (1.0 - e1) * (dx * dx) - 2.0 * e2 * dx * dy + (1.0 + e1) * (dy * dy),
            };
            if d2 > rmax * rmax || !keep(ix, iy) {
                continue;
            }
            at.push((iy, ix));
            offsets.push((dx, dy));
        }
    }
    let mut values = vec![0.0; offsets.len()];
    match e {
        None => moffat_pixels(&offsets, alpha, beta, &mut values),
        Some(e) => moffat_pixels_elliptical(&offsets, alpha, beta, e, &mut values),
    }
    for (&(iy, ix), m) in at.iter().zip(values) {
        let v = &mut img[[iy, ix]];
        *v = (*v as f64 + flux * m) as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    /// Reference pixel integral: 20 x 20 Gauss-Legendre nodes (computed here by Newton's
    /// iteration on the Legendre polynomial, independently of the tables above).
    fn reference_pixel(dx: f64, dy: f64, alpha: f64, beta: f64) -> f64 {
        let (xs, ws) = gauss_legendre(20);
        let mut s = 0.0;
        for (a, wa) in xs.iter().zip(&ws) {
            for (b, wb) in xs.iter().zip(&ws) {
                let r2 = (dx + a).powi(2) + (dy + b).powi(2);
                s += wa * wb * (1.0 + r2 / (alpha * alpha)).powf(-beta);
            }
        }
        s * (beta - 1.0) / (std::f64::consts::PI * alpha * alpha)
    }

    /// n-point Gauss-Legendre nodes and weights on [-1/2, 1/2] (weights sum to 1).
    fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
        let (mut xs, mut ws) = (Vec::new(), Vec::new());
        for i in 0..n {
            let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, z);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (z * p1 - p0) / (z * z - 1.0);
                let dz = p1 / dp;
                z -= dz;
                if dz.abs() < 1e-16 {
                    break;
                }
            }
            xs.push(0.5 * z);
            ws.push(1.0 / ((1.0 - z * z) * dp * dp));
        }
        (xs, ws)
    }

    #[test]
    fn photometry_moffat_tables_match_computed_nodes() {
        for (n, tx, tw) in [
            (2, &GL2_X[..], &GL2_W[..]),
            (3, &GL3_X[..], &GL3_W[..]),
            (4, &GL4_X[..], &GL4_W[..]),
        ] {
            let (mut xs, ws) = gauss_legendre(n);
            let mut order: Vec<usize> = (0..n).collect();
            order.sort_by(|&a, &b| xs[a].total_cmp(&xs[b]));
            xs = order.iter().map(|&i| xs[i]).collect();
            let ws: Vec<f64> = order.iter().map(|&i| ws[i]).collect();
            for i in 0..n {
                assert!(
                    (xs[i] - tx[i]).abs() < 1e-15 && (ws[i] - tw[i]).abs() < 1e-15,
                    "n {n}: {xs:?} {ws:?}"
                );
            }
        }
        assert!((GL4X2_W.iter().sum::<f64>() - 1.0).abs() < 1e-15);
    }

    /// The per-pixel quadrature is within 1e-5 (relative) of a 20 x 20 rule near the core, for
    /// FWHM 2-4 px and beta 2.5-4, and sums to the enclosed flux.
    #[test]
    fn photometry_moffat_pixel_quadrature_accuracy() {
        let mut worst_core = 0.0f64;
        let mut worst_all = 0.0f64;
        for &(fwhm, beta) in &[(2.0, 2.5), (2.0, 4.0), (2.8, 3.0), (3.3, 3.5), (4.0, 2.5), (4.0, 4.0)] {
            let alpha = moffat_alpha(fwhm, beta);
            assert!((moffat_fwhm(alpha, beta) - fwhm).abs() < 1e-12);
            let peak = reference_pixel(0.0, 0.0, alpha, beta);
            for j in -12..=12 {
                for i in -12..=12 {
                    let (dx, dy) = (i as f64 - 0.137, j as f64 + 0.311);
                    let r = reference_pixel(dx, dy, alpha, beta);
                    let e = (moffat_pixel(dx, dy, alpha, beta) / r - 1.0).abs();
                    if dx.hypot(dy) < 1.5 * fwhm {
                        worst_core = worst_core.max(e);
                    }
                    worst_all = worst_all.max(e * r / peak);
                }
            }
        }
        eprintln!("Moffat pixel quadrature: worst relative error within 1.5 FWHM {worst_core:.1e}, anywhere relative to the peak {worst_all:.1e}");
        assert!(worst_core < 1e-5, "{worst_core}");
        assert!(worst_all < 2e-6, "{worst_all}");
        // Narrow star (FWHM 1 px): the split core keeps 1e-5.
        let alpha = moffat_alpha(1.0, 3.0);
        for &(dx, dy) in &[(0.0, 0.0), (0.3, -0.2), (1.1, 0.4), (-0.6, 1.7)] {
            let e = (moffat_pixel(dx, dy, alpha, 3.0) / reference_pixel(dx, dy, alpha, 3.0) - 1.0).abs();
            assert!(e < 1e-5, "FWHM 1 px ({dx}, {dy}): {e}");
        }
        // The whole image holds 1 - (outside fraction): add_moffat on a large image.
        let mut img = Array2::<f32>::zeros((401, 401));
        add_moffat(&mut img.view_mut(), 1.0, 200.3, 199.8, 2.0, 3.5);
        let tot: f64 = img.iter().map(|&v| v as f64).sum();
        let expect = 1.0 - moffat_outside(200.0, 2.0, 3.5); // square > disc of 200 px
        assert!((tot - expect).abs() < 2e-6, "{tot} {expect}");
    }

    #[test]
    fn photometry_moffat_derivatives_match_differences() {
        for &(dx, dy, alpha, beta) in &[
            (0.2, -0.3, 2.7, 3.0),
            (3.4, 1.2, 1.9, 2.5),
            (9.5, -8.0, 2.0, 4.0),
            (20.1, 3.0, 2.5, 3.0),
            (0.4, 0.9, 1.0, 3.0),
        ] {
            let d = moffat_pixel_derivs(dx, dy, alpha, beta);
            assert_eq!(d[0], moffat_pixel(dx, dy, alpha, beta));
            let h = 1e-5;
            let f = |dx: f64, dy: f64, a: f64, b: f64| moffat_pixel(dx, dy, a, b);
            let num = [
                (f(dx - h, dy, alpha, beta) - f(dx + h, dy, alpha, beta)) / (2.0 * h),
                (f(dx, dy - h, alpha, beta) - f(dx, dy + h, alpha, beta)) / (2.0 * h),
                (f(dx, dy, alpha + h, beta) - f(dx, dy, alpha - h, beta)) / (2.0 * h),
                (f(dx, dy, alpha, beta + h) - f(dx, dy, alpha, beta - h)) / (2.0 * h),
            ];
            for i in 0..4 {
                let scale = d[0] + num[i].abs();
                assert!(
                    (d[i + 1] - num[i]).abs() < 1e-6 * scale,
                    "({dx},{dy},{alpha},{beta}) d{i}: {} vs {}",
                    d[i + 1],
                    num[i]
                );
            }
        }
    }

    /// Reference pixel integral of an elliptical star: 20 x 20 Gauss-Legendre nodes of the
    /// profile written out with its axes (`ratio`, `pa`), independently of the (e1, e2) form.
    fn reference_pixel_elliptical(dx: f64, dy: f64, alpha: f64, beta: f64, ratio: f64, pa_deg: f64) -> f64 {
        // Axes alpha_major = alpha / sqrt(1 - |e|), alpha_minor = alpha / sqrt(1 + |e|).
        let m = (1.0 - ratio * ratio) / (1.0 + ratio * ratio);
        let (a_major, a_minor) = (alpha / (1.0 - m).sqrt(), alpha / (1.0 + m).sqrt());
        let (sn, cs) = pa_deg.to_radians().sin_cos();
        let (xs, ws) = gauss_legendre(20);
        let mut s = 0.0;
        for (a, wa) in xs.iter().zip(&ws) {
            for (b, wb) in xs.iter().zip(&ws) {
                let (x, y) = (dx + a, dy + b);
                let (u, v) = (x * cs + y * sn, -x * sn + y * cs);
                s += wa * wb * (1.0 + (u / a_major).powi(2) + (v / a_minor).powi(2)).powf(-beta);
            }
        }
        s * (beta - 1.0) / (std::f64::consts::PI * a_major * a_minor)
    }

    /// The elliptical pixel quadrature against a 20 x 20 rule of the profile written with its
    /// axes (axis ratios 0.6-0.95 at several angles, FWHM 2-4 px, beta 2.5-4): within 1e-5
    /// (relative) within 1.5 FWHM and 2e-6 of the peak anywhere; the image sum is the
    /// enclosed flux; [`moffat_ellipticity`] and [`moffat_axes`] invert each other.
    #[test]
    fn photometry_moffat_elliptical_pixel_quadrature_accuracy() {
        let (mut worst_core, mut worst_all) = (0.0f64, 0.0f64);
        for &(fwhm, beta, ratio, pa) in &[
            (2.0, 2.5, 0.9, 0.0),
            (2.0, 4.0, 0.6, 33.0),
            (2.8, 3.0, 0.8, 90.0),
            (3.3, 3.5, 0.95, 127.0),
            (4.0, 2.5, 0.7, 160.0),
        ] {
            let alpha = moffat_alpha(fwhm, beta);
            let e = moffat_ellipticity(ratio, pa);
            let (r, p) = moffat_axes(e);
            assert!((r - ratio).abs() < 1e-12 && (p - pa).abs() < 1e-9, "{r} {p}");
            let peak = reference_pixel_elliptical(0.0, 0.0, alpha, beta, ratio, pa);
            for j in -12..=12 {
                for i in -12..=12 {
                    let (dx, dy) = (i as f64 - 0.137, j as f64 + 0.311);
                    let want = reference_pixel_elliptical(dx, dy, alpha, beta, ratio, pa);
                    let err = (moffat_pixel_elliptical(dx, dy, alpha, beta, e) / want - 1.0).abs();
                    if dx.hypot(dy) < 1.5 * fwhm {
                        worst_core = worst_core.max(err);
                    }
                    worst_all = worst_all.max(err * want / peak);
                }
            }
            let mut img = Array2::<f32>::zeros((301, 301));
            add_moffat_elliptical(&mut img.view_mut(), 1.0, 150.3, 149.8, alpha, beta, e);
            let tot: f64 = img.iter().map(|&v| v as f64).sum();
            // The image holds all but the light beyond ~150 px along the major axis.
            let outside = moffat_outside(150.0 * (1.0 - e[0].hypot(e[1])).sqrt(), alpha, beta);
            assert!((tot - 1.0).abs() < outside + 2e-6, "{tot} (outside {outside:e})");
        }
        eprintln!("elliptical Moffat quadrature: worst relative error within 1.5 FWHM {worst_core:.1e}, anywhere relative to the peak {worst_all:.1e}");
        assert!(worst_core < 1e-5, "{worst_core}");
        assert!(worst_all < 2e-6, "{worst_all}");
    }

    /// The elliptical derivatives (position, alpha, beta, e1, e2) against central differences.
    #[test]
    fn photometry_moffat_elliptical_derivatives_match_differences() {
        for &(dx, dy, alpha, beta, e) in &[
            (0.2, -0.3, 2.7, 3.0, [0.1, -0.05]),
            (3.4, 1.2, 1.9, 2.5, [-0.2, 0.15]),
            (9.5, -8.0, 2.0, 4.0, [0.3, 0.3]),
            (20.1, 3.0, 2.5, 3.0, [0.0, -0.4]),
            (0.4, 0.9, 1.0, 3.0, [0.05, 0.0]),
        ] {
            let d = moffat_pixel_derivs_elliptical(dx, dy, alpha, beta, e);
            let f = |dx: f64, dy: f64, a: f64, b: f64, e: [f64; 2]| moffat_pixel_elliptical(dx, dy, a, b, e);
            let h = 1e-5;
            let num = [
                (f(dx - h, dy, alpha, beta, e) - f(dx + h, dy, alpha, beta, e)) / (2.0 * h),
                (f(dx, dy - h, alpha, beta, e) - f(dx, dy + h, alpha, beta, e)) / (2.0 * h),
                (f(dx, dy, alpha + h, beta, e) - f(dx, dy, alpha - h, beta, e)) / (2.0 * h),
                (f(dx, dy, alpha, beta + h, e) - f(dx, dy, alpha, beta - h, e)) / (2.0 * h),
                (f(dx, dy, alpha, beta, [e[0] + h, e[1]]) - f(dx, dy, alpha, beta, [e[0] - h, e[1]])) / (2.0 * h),
                (f(dx, dy, alpha, beta, [e[0], e[1] + h]) - f(dx, dy, alpha, beta, [e[0], e[1] - h])) / (2.0 * h),
            ];
            for i in 0..6 {
                let scale = d[0] + num[i].abs();
                assert!(
                    (d[i + 1] - num[i]).abs() < 1e-6 * scale,
                    "({dx},{dy},{alpha},{beta},{e:?}) d{i}: {} vs {}",
                    d[i + 1],
                    num[i]
                );
            }
        }
    }

    /// Against the simulator's elliptical Moffat (its own parametrisation: axes alpha/sqrt(r)
    /// and alpha sqrt(r), rendered by its own quadrature and truncation): the same star,
    /// pixel by pixel, within 2e-4 of the peak (the simulator's 4-node rule and 1e-5 wing
    /// truncation set the difference).
    #[test]
    fn photometry_moffat_elliptical_is_the_simulators() {
        use crate::sim::psf::{render, Psf};
        for &(alpha_sim, beta, ratio, pa) in &[(2.2, 3.0, 0.9, 20.0), (1.8, 2.6, 0.75, 115.0)] {
            let psf = Psf::Moffat {
                alpha_px: alpha_sim,
                beta,
            }
            .with_ellipticity(ratio, pa);
            let (cx, cy) = (20.37, 19.71);
            let st = render(psf, cx, cy);
            // Our parametrisation: the same metric scaled to trace 2.
            let alpha = alpha_sim * (2.0 / (ratio + 1.0 / ratio)).sqrt();
            let e = moffat_ellipticity(ratio, pa);
            let mut img = Array2::<f32>::zeros((41, 41));
            add_moffat_elliptical(&mut img.view_mut(), 1.0, cx, cy, alpha, beta, e);
            let peak = img.iter().fold(0.0f32, |a, &b| a.max(b)) as f64;
            let mut worst = 0.0f64;
            for ((j, i), &v) in st.values.indexed_iter() {
                let (x, y) = (st.x0 + i as i64, st.y0 + j as i64);
                if (0..41).contains(&x) && (0..41).contains(&y) {
                    worst = worst.max((img[[y as usize, x as usize]] as f64 - v).abs() / peak);
                }
            }
            assert!(worst < 2e-4, "ratio {ratio} pa {pa}: {worst:e}");
        }
    }

    /// Deterministic uniform numbers in [0, 1) (xorshift64*), for reproducible random cases
    /// (the kernel's tests too).
    pub(super) struct Rng(pub(super) u64);
    impl Rng {
        pub(super) fn next(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
        }
    }
}
