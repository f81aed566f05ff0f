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
//! Speed: every node needs `ln(1 + t)` and `(1 + t)^-beta`. They are computed for all nodes of
//! a pixel at once by a branch-free kernel (fdlibm's `log` with its division shared with
//! `1/(1 + t)`, a Taylor `exp` after Cody-Waite reduction) that the compiler vectorises, built
//! three times: for SSE2 and, chosen at run time, for AVX2 and AVX-512 (same operations, no
//! FMA contraction: the values are bit-identical on every x86-64 CPU). Against libm:
//! `ln(1 + t)` and `1/(1 + t)` within 2.2e-16 relative, `(1 + t)^-beta` within
//! 3.7e-16 x (1 + beta ln(1 + t)) (the conditioning of any `exp`), pixel values and
//! derivatives within 3e-14 of their scale (tests `photometry_moffat_*_matches_libm*`). The
//! PSF fits of `sofipol night` on the 49-target bench night: 0.88 -> 0.61 CPU-s (perf
//! samples), measure stage 3.09 -> 2.34 s (medians of 5, same run). Many pixels at once
//! ([`moffat_pixels`], [`moffat_pixels_derivs`]): their nodes fill whole vectors (the wings'
//! 1 to 9 nodes per pixel would fill one partly and wait on its latency), the same values
//! bit for bit; measure stage 0.45 -> 0.35 s.

use ndarray::ArrayViewMut2;

use crate::numeric::{GL1_W, GL1_X, GL2_W, GL2_X, GL3_W, GL3_X, GL4_W, GL4_X};
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

/// Lanes of the batched node kernel (the compiler maps `[f64; LANES]` loops to vector code).
const LANES: usize = 4;

/// `1.5 * 2^52`: adding it rounds a small f64 to an integer held in the low mantissa bits.
const ROUND_MAGIC: f64 = 6_755_399_441_055_744.0;

/// `(ln(u), 1/u)` for finite `u >= 1`: fdlibm's `__ieee754_log` made branch-free (error
/// ~1 ulp), its one division `f / (2 + f)` shared with `1 / u` (one reciprocal for both).
#[inline(always)]
#[allow(clippy::excessive_precision)] // fdlibm's constants, digits as published
fn ln_recip_kernel(u: f64) -> (f64, f64) {
    const LN2_HI: f64 = 6.931_471_803_691_238_164_90e-01;
    const LN2_LO: f64 = 1.908_214_929_270_587_700_02e-10;
    const LG1: f64 = 6.666_666_666_666_735_130e-01;
    const LG2: f64 = 3.999_999_999_940_941_908e-01;
    const LG3: f64 = 2.857_142_874_366_239_149e-01;
    const LG4: f64 = 2.222_219_843_214_978_396e-01;
    const LG5: f64 = 1.818_357_216_161_805_012e-01;
    const LG6: f64 = 1.531_383_769_920_937_332e-01;
    const LG7: f64 = 1.479_819_860_511_658_591e-01;
    let bits = u.to_bits();
    let hx = bits >> 32;
    let k = hx >> 20; // biased exponent (u >= 1: sign bit clear)
    let hm = hx & 0x000f_ffff;
    // u = 2^kb m with m in [sqrt(2)/2, sqrt(2)): i = 0x100000 when the mantissa is >= sqrt(2).
    let i = (hm + 0x95f64) & 0x0010_0000;
    let m = f64::from_bits(((hm | (i ^ 0x3ff0_0000)) << 32) | (bits & 0xffff_ffff));
    // kb = k - 1023 + (i >> 20), exactly, as an f64 (integer to float without a conversion).
    let dk = f64::from_bits(ROUND_MAGIC.to_bits() + k + (i >> 20)) - (ROUND_MAGIC + 1023.0);
    let f = m - 1.0;
    let d = 2.0 + f;
    let rec = 1.0 / (d * u);
    let s = f * (u * rec);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG2 + w * (LG4 + w * LG6));
    let t2 = z * (LG1 + w * (LG3 + w * (LG5 + w * LG7)));
    let r = t2 + t1;
    let hfsq = 0.5 * f * f;
    (dk * LN2_HI - ((hfsq - (s * (hfsq + r) + dk * LN2_LO)) - f), d * rec)
}

/// `exp(x)`, branch-free: Cody-Waite reduction `x = k ln 2 + r` (`|r| <= ln 2 / 2`) and the
/// Taylor polynomial of degree 13 for `exp(r)` (truncation < 2e-18 relative), no division;
/// error ~1 ulp. `x` is clamped to `[-1400, 709]`, so results below ~1e-608 are 0; NaN stays NaN.
#[inline(always)]
#[allow(clippy::excessive_precision)] // fdlibm's constants, digits as published
fn exp_kernel(x: f64) -> f64 {
    const LN2_HI: f64 = 6.931_471_803_691_238_164_90e-01;
    const LN2_LO: f64 = 1.908_214_929_270_587_700_02e-10;
    // 1/k!, k = 2..13.
    const C: [f64; 12] = [
        1.0 / 2.0,
        1.0 / 6.0,
        1.0 / 24.0,
        1.0 / 120.0,
        1.0 / 720.0,
        1.0 / 5040.0,
        1.0 / 40320.0,
        1.0 / 362880.0,
        1.0 / 3628800.0,
        1.0 / 39916800.0,
        1.0 / 479001600.0,
        1.0 / 6227020800.0,
    ];
    let x = x.clamp(-1400.0, 709.0); // NaN stays NaN
                                     // k = round(x / ln 2), in [-2020, 1023], as f64 and as integer bits.
    let kr = x * std::f64::consts::LOG2_E + ROUND_MAGIC;
    let kf = kr - ROUND_MAGIC;
    // r = x - k ln 2 in two parts: hi is exact (k has <= 11 bits, LN2_HI 32), lo tiny.
    let hi = x - kf * LN2_HI;
    let lo = kf * LN2_LO;
    let r = hi - lo;
    let mut q = C[11];
    for &c in C[..11].iter().rev() {
        q = q * r + c;
    }
    // exp(r) = 1 + r + r^2 q(r), with the low part of r kept: (hi - lo) rounded is r.
    let y = 1.0 + (r + r * r * q);
    // 2^k as 2^k1 * 2^k2 with both factors normal (k1 = floor((k + 2048) / 2) - 1024).
    let kk = kr.to_bits().wrapping_sub(ROUND_MAGIC.to_bits()).wrapping_add(2048); // k + 2048 >= 28
    let k1 = (kk >> 1).wrapping_sub(1024);
    let k2 = kk.wrapping_sub(2048).wrapping_sub(k1);
    let s1 = f64::from_bits(k1.wrapping_add(1023) << 52);
    let s2 = f64::from_bits(k2.wrapping_add(1023) << 52);
    y * s1 * s2
}

/// For `t >= 0` (finite): `(ln(1 + t), (1 + t)^-beta, 1 / (1 + t))`, with `ln(1 + t)` to
/// ~1 ulp like `ln_1p` (the rounding of `1 + t` is corrected to first order).
#[inline(always)]
fn node_kernel(t: f64, beta: f64) -> (f64, f64, f64) {
    let u = 1.0 + t;
    let (ln_u, iu) = ln_recip_kernel(u);
    // u - 1 is exact (u >= 1) and t - (u - 1) is the rounding error of u, exactly.
    let lu = ln_u + (t - (u - 1.0)) * iu;
    (lu, exp_kernel(-beta * lu), iu)
}

/// The quadrature rule for a pixel whose centre is `(dx, dy)` from the star.
#[inline]
fn rule(dx: f64, dy: f64, alpha: f64) -> (&'static [f64], &'static [f64]) {
    let d2 = dx * dx + dy * dy;
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

/// Sums over the `N = n x n` nodes `(xs, ws)` of a pixel at `(dx, dy)` from the star of
/// `w p`, `w p X/u`, `w p Y/u`, `w p t/u`, `w p ln u` (with `t = r^2/alpha^2`, `u = 1 + t`,
/// `p = u^-beta`, `(X, Y)` = node - star), or only the first when `!DERIVS`. The nodes are
/// processed as arrays so that the compiler vectorises the `ln`/`exp` kernel over them. The
/// definition of a pixel's sums, one pixel at a time: the tests' reference for the batched
/// kernel below, which gives the same values bit for bit.
#[cfg(test)]
#[inline(always)]
fn node_sums<const N: usize, const DERIVS: bool>(
    dx: f64,
    dy: f64,
    ia2: f64,
    beta: f64,
    xs: &[f64],
    ws: &[f64],
) -> [f64; 5] {
    let n = xs.len();
    debug_assert_eq!(n * n, N);
    let (mut t, mut w, mut x, mut y) = ([0.0; N], [0.0; N], [0.0; N], [0.0; N]);
    for i in 0..n {
        let u = dx + xs[i];
        let u2 = u * u;
        for j in 0..n {
            let v = dy + xs[j];
            let k = i * n + j;
            t[k] = (u2 + v * v) * ia2;
            w[k] = ws[i] * ws[j];
            x[k] = u;
            y[k] = v;
        }
    }
    let (mut lu, mut wp, mut iu) = ([0.0; N], [0.0; N], [0.0; N]);
    for k in 0..N {
        let (l, p, i) = node_kernel(t[k], beta);
        lu[k] = l;
        wp[k] = w[k] * p;
        iu[k] = i;
    }
    // One partial sum per lane (fixed order: the same values on every call).
    let (mut s0, mut sx, mut sy, mut st, mut sl) =
        ([0.0; LANES], [0.0; LANES], [0.0; LANES], [0.0; LANES], [0.0; LANES]);
    for k in 0..N {
        let l = k % LANES;
        s0[l] += wp[k];
        if DERIVS {
            let wpu = wp[k] * iu[k];
            sx[l] += wpu * x[k];
            sy[l] += wpu * y[k];
            st[l] += wpu * t[k];
            sl[l] += wp[k] * lu[k];
        }
    }
    let sum = |a: [f64; LANES]| (a[0] + a[1]) + (a[2] + a[3]);
    [sum(s0), sum(sx), sum(sy), sum(st), sum(sl)]
}

/// [`node_sums`] with the rule of the pixel at `(dx, dy)`.
#[cfg(test)]
#[inline(always)]
fn pixel_sums_generic<const DERIVS: bool>(dx: f64, dy: f64, alpha: f64, ia2: f64, beta: f64) -> [f64; 5] {
    let (xs, ws) = rule(dx, dy, alpha);
    match xs.len() {
        1 => node_sums::<1, DERIVS>(dx, dy, ia2, beta, xs, ws),
        2 => node_sums::<4, DERIVS>(dx, dy, ia2, beta, xs, ws),
        3 => node_sums::<9, DERIVS>(dx, dy, ia2, beta, xs, ws),
        4 => node_sums::<16, DERIVS>(dx, dy, ia2, beta, xs, ws),
        _ => node_sums::<64, DERIVS>(dx, dy, ia2, beta, xs, ws),
    }
}

/// Node capacity of one batch of [`batch_sums`] (a pixel has at most 64 nodes; a
/// multiple of 8, the widest vector).
const BATCH_NODES: usize = 256;

/// The node sums of [`node_sums`] for many pixels at once: the nodes of up to
/// [`BATCH_NODES`] at a time go through `node_kernel` in one vectorised loop (whole vectors
/// even for the 1-, 4- and 9-node pixels of the wings, which alone would fill a vector
/// partly and wait on its latency), then each pixel's sums are taken in `node_sums`' order.
/// `out[i]` gets pixel `i`'s sums, bit for bit those of `node_sums` (test
/// `photometry_moffat_batch_is_the_per_pixel_kernel`); only `out[i][0]` when `!DERIVS`.
#[inline(always)]
fn batch_sums_generic<const DERIVS: bool>(
    offsets: &[(f64, f64)],
    alpha: f64,
    ia2: f64,
    beta: f64,
    out: &mut [[f64; 5]],
) {
    debug_assert_eq!(offsets.len(), out.len());
    let (mut t, mut lu, mut p, mut iu) = (
        [0.0; BATCH_NODES],
        [0.0; BATCH_NODES],
        [0.0; BATCH_NODES],
        [0.0; BATCH_NODES],
    );
    let mut first = 0;
    while first < offsets.len() {
        // Fill: the nodes of as many pixels as fit, in node_sums' order (k = i n + j).
        let mut used = 0;
        let mut last = first;
        while last < offsets.len() {
            let (dx, dy) = offsets[last];
            let (xs, _) = rule(dx, dy, alpha);
            let n = xs.len();
            if used + n * n > BATCH_NODES {
                break;
            }
            let tp = &mut t[used..used + n * n];
            match n {
                1 => fill_nodes::<1>(dx, dy, xs, ia2, tp),
                2 => fill_nodes::<2>(dx, dy, xs, ia2, tp),
                3 => fill_nodes::<3>(dx, dy, xs, ia2, tp),
                4 => fill_nodes::<4>(dx, dy, xs, ia2, tp),
                _ => fill_nodes::<8>(dx, dy, xs, ia2, tp),
            }
            used += n * n;
            last += 1;
        }
        // The kernel over whole vectors (the tail's stale nodes are finite and unused).
        for c in (0..used).step_by(8) {
            let tc: &[f64; 8] = t[c..c + 8].try_into().expect("8 nodes");
            let (mut l8, mut p8, mut i8) = ([0.0; 8], [0.0; 8], [0.0; 8]);
            for k in 0..8 {
                (l8[k], p8[k], i8[k]) = node_kernel(tc[k], beta);
            }
            lu[c..c + 8].copy_from_slice(&l8);
            p[c..c + 8].copy_from_slice(&p8);
            iu[c..c + 8].copy_from_slice(&i8);
        }
        // Per pixel, the sums of node_sums in its order.
        let mut k0 = 0;
        for (&(dx, dy), o) in offsets[first..last].iter().zip(&mut out[first..last]) {
            let (xs, ws) = rule(dx, dy, alpha);
            let n = xs.len();
            *o = match n {
                1 => reduce_nodes::<1, DERIVS>(dx, dy, xs, ws, &t[k0..], &lu[k0..], &p[k0..], &iu[k0..]),
                2 => reduce_nodes::<2, DERIVS>(dx, dy, xs, ws, &t[k0..], &lu[k0..], &p[k0..], &iu[k0..]),
                3 => reduce_nodes::<3, DERIVS>(dx, dy, xs, ws, &t[k0..], &lu[k0..], &p[k0..], &iu[k0..]),
                4 => reduce_nodes::<4, DERIVS>(dx, dy, xs, ws, &t[k0..], &lu[k0..], &p[k0..], &iu[k0..]),
                _ => reduce_nodes::<8, DERIVS>(dx, dy, xs, ws, &t[k0..], &lu[k0..], &p[k0..], &iu[k0..]),
            };
            k0 += n * n;
        }
        first = last;
    }
}

/// `t = r^2/alpha^2` at the `M x M` nodes of a pixel, in `node_sums`' order and operations.
#[inline(always)]
fn fill_nodes<const M: usize>(dx: f64, dy: f64, xs: &[f64], ia2: f64, t: &mut [f64]) {
    let (xs, t) = (&xs[..M], &mut t[..M * M]);
    for i in 0..M {
        let u = dx + xs[i];
        let u2 = u * u;
        for j in 0..M {
            let v = dy + xs[j];
            t[i * M + j] = (u2 + v * v) * ia2;
        }
    }
}

/// The sums of [`node_sums`] for one pixel of `M x M` nodes whose kernel values start the
/// slices: the same products, added to the same lanes in the same order.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn reduce_nodes<const M: usize, const DERIVS: bool>(
    dx: f64,
    dy: f64,
    xs: &[f64],
    ws: &[f64],
    t: &[f64],
    lu: &[f64],
    p: &[f64],
    iu: &[f64],
) -> [f64; 5] {
    let (xs, ws) = (&xs[..M], &ws[..M]);
    let (t, lu, p, iu) = (&t[..M * M], &lu[..M * M], &p[..M * M], &iu[..M * M]);
    let (mut s0, mut sx, mut sy, mut st, mut sl) =
        ([0.0; LANES], [0.0; LANES], [0.0; LANES], [0.0; LANES], [0.0; LANES]);
    for i in 0..M {
        let u = dx + xs[i];
        for j in 0..M {
            let k = i * M + j;
            let l = k % LANES;
            let wp = (ws[i] * ws[j]) * p[k];
            s0[l] += wp;
            if DERIVS {
                let v = dy + xs[j];
                let wpu = wp * iu[k];
                sx[l] += wpu * u;
                sy[l] += wpu * v;
                st[l] += wpu * t[k];
                sl[l] += wp * lu[k];
            }
        }
    }
    let sum = |a: [f64; LANES]| (a[0] + a[1]) + (a[2] + a[3]);
    [sum(s0), sum(sx), sum(sy), sum(st), sum(sl)]
}

/// [`batch_sums_generic`] compiled for AVX2 (4 lanes instead of SSE2's 2). Only the vector
/// width differs: no FMA contraction, so the values are bit-identical to the generic code's
/// (test `photometry_moffat_avx2_path_is_bit_identical`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn batch_sums_avx2<const DERIVS: bool>(offsets: &[(f64, f64)], alpha: f64, ia2: f64, beta: f64, out: &mut [[f64; 5]]) {
    batch_sums_generic::<DERIVS>(offsets, alpha, ia2, beta, out)
}

/// [`batch_sums_generic`] compiled for AVX-512 (8 lanes); bit-identical like the AVX2 build.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn batch_sums_avx512<const DERIVS: bool>(
    offsets: &[(f64, f64)],
    alpha: f64,
    ia2: f64,
    beta: f64,
    out: &mut [[f64; 5]],
) {
    batch_sums_generic::<DERIVS>(offsets, alpha, ia2, beta, out)
}

/// [`batch_sums_generic`] with the widest vector code this CPU runs.
fn batch_sums<const DERIVS: bool>(offsets: &[(f64, f64)], alpha: f64, ia2: f64, beta: f64, out: &mut [[f64; 5]]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports AVX-512F (checked just above).
            #[allow(unsafe_code)]
            return unsafe { batch_sums_avx512::<DERIVS>(offsets, alpha, ia2, beta, out) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            #[allow(unsafe_code)]
            return unsafe { batch_sums_avx2::<DERIVS>(offsets, alpha, ia2, beta, out) };
        }
    }
    batch_sums_generic::<DERIVS>(offsets, alpha, ia2, beta, out)
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
    let mut d = [[0.0; 5]];
    moffat_pixels_derivs(&[(dx, dy)], alpha, beta, &mut d);
    d[0]
}

/// The pixel value and derivatives from the node sums.
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

/// [`moffat_pixel`] for many pixels at once (faster: their nodes fill whole vectors):
/// `out[i]` is `moffat_pixel(offsets[i].0, offsets[i].1, alpha, beta)`, bit for bit.
/// Panics if the lengths differ.
pub fn moffat_pixels(offsets: &[(f64, f64)], alpha: f64, beta: f64, out: &mut [f64]) {
    assert_eq!(offsets.len(), out.len(), "one output per pixel");
    let ia2 = 1.0 / (alpha * alpha);
    // Same operations and order as moffat_pixels_derivs' value: bit-identical values.
    let norm = |s: &[f64; 5]| (beta - 1.0) / std::f64::consts::PI * ia2 * s[0];
    if let [one] = out {
        // One pixel (a fit's start, a model value): no allocation.
        let mut s = [[0.0; 5]];
        batch_sums::<false>(offsets, alpha, ia2, beta, &mut s);
        *one = norm(&s[0]);
        return;
    }
    let mut sums = vec![[0.0; 5]; offsets.len()];
    batch_sums::<false>(offsets, alpha, ia2, beta, &mut sums);
    for (o, s) in out.iter_mut().zip(&sums) {
        *o = norm(s);
    }
}

/// [`moffat_pixel_derivs`] for many pixels at once: `out[i]` is
/// `moffat_pixel_derivs(offsets[i].0, offsets[i].1, alpha, beta)`, bit for bit. Panics if
/// the lengths differ.
pub fn moffat_pixels_derivs(offsets: &[(f64, f64)], alpha: f64, beta: f64, out: &mut [[f64; 5]]) {
    assert_eq!(offsets.len(), out.len(), "one output per pixel");
    let ia2 = 1.0 / (alpha * alpha);
    batch_sums::<true>(offsets, alpha, ia2, beta, out);
    for o in out.iter_mut() {
        *o = derivs_of_sums(*o, alpha, ia2, beta);
    }
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
    let (ny, nx) = img.dim();
    let ok = nx > 0 && ny > 0 && alpha > 0.0 && alpha.is_finite() && beta > 1.0 && x.is_finite() && y.is_finite();
    if !ok {
        return;
    }
    // (1 + R^2/alpha^2)^(1 - beta) = 1e-9.
    let t = (9.0 * std::f64::consts::LN_10 / (beta - 1.0)).exp_m1();
    let rmax = (alpha * t.sqrt()).min(1e5) + 1.0;
    let span = |c: f64, n: usize| -> (usize, usize) {
        let lo = (c - rmax).floor().max(0.0).min(n as f64 - 1.0) as usize;
        let hi = (c + rmax).ceil().max(0.0).min(n as f64 - 1.0) as usize;
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
            if dx * dx + dy * dy > rmax * rmax || !keep(ix, iy) {
                continue;
            }
            at.push((iy, ix));
            offsets.push((dx, dy));
        }
    }
    let mut values = vec![0.0; offsets.len()];
    moffat_pixels(&offsets, alpha, beta, &mut values);
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
    /// Deterministic uniform numbers in [0, 1) (xorshift64*), for reproducible random cases.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// The vectorised node kernel against libm (`ln_1p`, `exp`, division) over t in [0, 1e12]
    /// (log-uniform, plus 0, tiny t and powers of two) and beta in [1.01, 20]: `ln(1 + t)` and
    /// `1/(1 + t)` to a few ulp; `(1 + t)^-beta` to a few ulp of its argument `beta ln(1 + t)`
    /// (the conditioning of any `exp`: libm's own value has the same uncertainty).
    #[test]
    fn photometry_moffat_node_kernel_matches_libm() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        let (mut e_ln, mut e_p, mut e_iu) = (0.0f64, 0.0f64, 0.0f64);
        let mut cases: Vec<f64> = vec![
            0.0, 1e-300, 1e-17, 1.1e-16, 2.3e-16, 1e-12, 1e-8, 0.4142, 1.0, 1e4, 1e12,
        ];
        cases.extend((-30..40).map(|e| 2f64.powi(e)));
        cases.extend((-30..40).map(|e| 2f64.powi(e) * (1.0 + f64::EPSILON)));
        cases.extend((0..200_000).map(|_| 10f64.powf(-18.0 + 30.0 * rng.next())));
        for (n, &t) in cases.iter().enumerate() {
            let beta = if n % 7 == 0 {
                1.01
            } else if n % 7 == 1 {
                20.0
            } else {
                1.01 + 19.0 * rng.next()
            };
            let (lu, p, iu) = node_kernel(t, beta);
            let lu_ref = t.ln_1p();
            let p_ref = (-beta * lu_ref).exp();
            let iu_ref = 1.0 / (1.0 + t);
            if lu_ref > 0.0 {
                e_ln = e_ln.max((lu / lu_ref - 1.0).abs());
            } else {
                assert_eq!(lu, 0.0, "t {t}");
            }
            e_p = e_p.max((p / p_ref - 1.0).abs() / (1.0 + beta * lu_ref));
            e_iu = e_iu.max((iu / iu_ref - 1.0).abs());
        }
        eprintln!(
            "node kernel vs libm: ln(1+t) {e_ln:.1e}, (1+t)^-beta {e_p:.1e} x (1 + beta ln(1+t)), 1/(1+t) {e_iu:.1e}"
        );
        assert!(e_ln < 5e-16, "ln(1+t): {e_ln:e}");
        assert!(e_p < 5e-16, "(1+t)^-beta: {e_p:e}");
        assert!(e_iu < 5e-16, "1/(1+t): {e_iu:e}");
    }

    /// `exp_kernel` over its whole range, subnormal results included, and its clamping.
    #[test]
    fn photometry_moffat_exp_kernel_matches_libm() {
        let mut rng = Rng(12345);
        let mut worst = 0.0f64;
        for i in 0..100_000 {
            let x = if i < 50_000 {
                -745.0 + 1454.0 * rng.next()
            } else {
                -1.0 + 2.0 * rng.next()
            };
            let (e, r) = (exp_kernel(x), x.exp());
            if r >= f64::MIN_POSITIVE {
                worst = worst.max((e / r - 1.0).abs());
            } else {
                assert!((e - r).abs() <= 2.0 * 4.9e-324, "x {x}: {e:e} vs {r:e}");
            }
        }
        eprintln!("exp kernel vs libm: worst relative difference {worst:.1e}");
        assert!(worst < 4e-16, "{worst:e}");
        assert_eq!(exp_kernel(0.0), 1.0);
        assert_eq!(exp_kernel(-2000.0), 0.0);
        assert!(exp_kernel(f64::NAN).is_nan());
    }

    /// [`moffat_pixel_derivs`] with the same nodes, summed straightforwardly with libm
    /// (`ln_1p`, `exp`, `powf`), and the sums of the absolute values of each term (the scale of
    /// the rounding errors of any evaluation).
    fn libm_pixel_derivs(dx: f64, dy: f64, alpha: f64, beta: f64) -> ([f64; 5], [f64; 5]) {
        let ia2 = 1.0 / (alpha * alpha);
        let (xs, ws) = rule(dx, dy, alpha);
        let (mut s, mut a) = ([0.0f64; 5], [0.0f64; 5]);
        for (&ax, &wa) in xs.iter().zip(ws) {
            for (&by, &wb) in xs.iter().zip(ws) {
                let (u, v) = (dx + ax, dy + by);
                let t = (u * u + v * v) * ia2;
                let wp = wa * wb * (1.0 + t).powf(-beta);
                let lu = t.ln_1p();
                let terms = [wp, wp * u / (1.0 + t), wp * v / (1.0 + t), wp * t / (1.0 + t), wp * lu];
                for i in 0..5 {
                    s[i] += terms[i];
                    a[i] += terms[i].abs();
                }
            }
        }
        let norm = (beta - 1.0) / std::f64::consts::PI * ia2;
        let c = 2.0 * beta * ia2 * norm;
        let val = [
            norm * s[0],
            c * s[1],
            c * s[2],
            norm * 2.0 / alpha * (beta * s[3] - s[0]),
            norm * (s[0] / (beta - 1.0) - s[4]),
        ];
        let scale = [
            norm * a[0],
            c * a[1],
            c * a[2],
            norm * 2.0 / alpha * (beta * a[3] + a[0]),
            norm * (a[0] / (beta - 1.0) + a[4]),
        ];
        (val, scale)
    }

    /// The vectorised pixel kernels against the straightforward libm formula over random
    /// (dx, dy, alpha, beta) — alpha 0.3-30 px, beta 1.01-20, pixels from the core to the far
    /// wings (every quadrature zone, the split core of narrow stars included): each value and
    /// derivative within 1e-13 of its scale (sum of |terms|), and `moffat_pixel` bit-identical
    /// to the value of `moffat_pixel_derivs`.
    #[test]
    fn photometry_moffat_pixel_kernel_matches_libm_formula() {
        let mut rng = Rng(0xdead_beef);
        let mut worst = [0.0f64; 5];
        let mut worst_rel_value = 0.0f64;
        for n in 0..40_000 {
            let alpha = match n % 5 {
                0 => 0.3 + 0.9 * rng.next(),
                1 => 30.0,
                _ => 0.3 * 100f64.powf(rng.next()),
            };
            let beta = match n % 4 {
                0 => 1.01,
                1 => 20.0,
                _ => 1.01 + 19.0 * rng.next(),
            };
            // Distances up to 20 alpha (and a few far wings at up to 300 px).
            let r = if n % 10 == 0 {
                300.0 * rng.next()
            } else {
                20.0 * alpha * rng.next().powi(2)
            };
            let phi = std::f64::consts::TAU * rng.next();
            let (dx, dy) = (r * phi.cos(), r * phi.sin());
            let d = moffat_pixel_derivs(dx, dy, alpha, beta);
            assert_eq!(d[0].to_bits(), moffat_pixel(dx, dy, alpha, beta).to_bits());
            let (val, scale) = libm_pixel_derivs(dx, dy, alpha, beta);
            for i in 0..5 {
                worst[i] = worst[i].max((d[i] - val[i]).abs() / scale[i]);
            }
            worst_rel_value = worst_rel_value.max((d[0] / val[0] - 1.0).abs());
        }
        eprintln!("pixel kernel vs libm formula: worst |diff|/scale [P, dx, dy, alpha, beta] {:.1e} {:.1e} {:.1e} {:.1e} {:.1e}; P relative {worst_rel_value:.1e}", worst[0], worst[1], worst[2], worst[3], worst[4]);
        for (i, w) in worst.iter().enumerate() {
            assert!(*w < 1e-13, "component {i}: {w:e}");
        }
        assert!(worst_rel_value < 1e-13, "{worst_rel_value:e}");
    }

    /// The AVX2 and AVX-512 builds of the kernel give the generic (SSE2) build's values bit
    /// for bit, so results do not depend on the CPU.
    #[test]
    fn photometry_moffat_avx2_path_is_bit_identical() {
        #[cfg(target_arch = "x86_64")]
        {
            if !std::arch::is_x86_feature_detected!("avx2") {
                eprintln!("no AVX2 on this CPU: nothing to compare");
                return;
            }
            let avx512 = std::arch::is_x86_feature_detected!("avx512f");
            eprintln!(
                "comparing the SSE2 build with AVX2{}",
                if avx512 { " and AVX-512" } else { "" }
            );
            let mut rng = Rng(7);
            for n in 0..400 {
                let alpha = 0.3 * 100f64.powf(rng.next());
                let beta = 1.01 + 19.0 * rng.next();
                let ia2 = 1.0 / (alpha * alpha);
                let offsets: Vec<(f64, f64)> = (0..(rng.next() * 120.0) as usize)
                    .map(|_| ((rng.next() - 0.5) * 8.0 * alpha, (rng.next() - 0.5) * 8.0 * alpha))
                    .collect();
                let mut g = vec![[0.0; 5]; offsets.len()];
                batch_sums_generic::<true>(&offsets, alpha, ia2, beta, &mut g);
                let mut v = vec![[0.0; 5]; offsets.len()];
                // SAFETY: AVX2 checked above.
                #[allow(unsafe_code)]
                unsafe {
                    batch_sums_avx2::<true>(&offsets, alpha, ia2, beta, &mut v)
                };
                for (i, (a, b)) in g.iter().zip(&v).enumerate() {
                    for c in 0..5 {
                        assert_eq!(a[c].to_bits(), b[c].to_bits(), "AVX2 batch {n} pixel {i} component {c}");
                    }
                }
                if avx512 {
                    // SAFETY: AVX-512F checked above.
                    #[allow(unsafe_code)]
                    unsafe {
                        batch_sums_avx512::<true>(&offsets, alpha, ia2, beta, &mut v)
                    };
                    for (i, (a, b)) in g.iter().zip(&v).enumerate() {
                        for c in 0..5 {
                            assert_eq!(
                                a[c].to_bits(),
                                b[c].to_bits(),
                                "AVX-512 batch {n} pixel {i} component {c}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// The batched kernel gives the per-pixel kernel's values and derivatives bit for bit:
    /// batches of 0 to 300 pixels mixing every rule (the narrow stars' 64-node cores too),
    /// so that batches cross the node capacity at every kind of pixel.
    #[test]
    fn photometry_moffat_batch_is_the_per_pixel_kernel() {
        let mut rng = Rng(11);
        let mut rules = [0usize; 5];
        for case in 0..400 {
            let alpha = 0.5 * 20f64.powf(rng.next());
            let beta = 1.05 + 9.0 * rng.next();
            let n = (rng.next() * 300.0) as usize;
            let offsets: Vec<(f64, f64)> = (0..n)
                .map(|_| {
                    // Distances from the core out to ~15 alpha.
                    let r = alpha * 15.0 * rng.next().powi(2);
                    let a = std::f64::consts::TAU * rng.next();
                    (r * a.cos(), r * a.sin())
                })
                .collect();
            for &(dx, dy) in &offsets {
                let m = rule(dx, dy, alpha).0.len();
                rules[if m == 8 { 4 } else { m - 1 }] += 1;
            }
            let mut values = vec![f64::NAN; n];
            let mut derivs = vec![[f64::NAN; 5]; n];
            moffat_pixels(&offsets, alpha, beta, &mut values);
            moffat_pixels_derivs(&offsets, alpha, beta, &mut derivs);
            let ia2 = 1.0 / (alpha * alpha);
            for (i, &(dx, dy)) in offsets.iter().enumerate() {
                // The per-pixel definition (node_sums), and the one-pixel functions.
                let s = pixel_sums_generic::<true>(dx, dy, alpha, ia2, beta);
                let want_value = (beta - 1.0) / std::f64::consts::PI * ia2 * s[0];
                let want = derivs_of_sums(s, alpha, ia2, beta);
                assert_eq!(values[i].to_bits(), want_value.to_bits(), "case {case} pixel {i}");
                assert_eq!(
                    moffat_pixel(dx, dy, alpha, beta).to_bits(),
                    want_value.to_bits(),
                    "case {case} pixel {i}"
                );
                let one = moffat_pixel_derivs(dx, dy, alpha, beta);
                for c in 0..5 {
                    assert_eq!(
                        derivs[i][c].to_bits(),
                        want[c].to_bits(),
                        "case {case} pixel {i} component {c}"
                    );
                    assert_eq!(
                        one[c].to_bits(),
                        want[c].to_bits(),
                        "case {case} pixel {i} component {c}"
                    );
                }
            }
        }
        // Every rule was exercised many times.
        assert!(rules.iter().all(|&r| r > 1000), "{rules:?}");
    }
}
