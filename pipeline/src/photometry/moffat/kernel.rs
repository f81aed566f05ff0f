//! The node sums of the Moffat pixel integral ([`super`]) for many pixels at once, and the
//! entry points built on them: [`moffat_pixels`], [`moffat_pixels_derivs`].
//!
//! Every node needs `ln(1 + t)` and `(1 + t)^-beta` ([`node_kernel`], branch-free). The nodes
//! of many pixels go through it in one loop that the compiler vectorises: whole vectors even
//! for the 1 to 9 nodes of a pixel in the wings, which alone would fill one partly and wait
//! on its latency. Then each pixel's sums are taken in a fixed order, so the values are those
//! of the per-pixel definition (`node_sums`, kept for the tests) bit for bit. The loop is
//! built three times: for SSE2 and, chosen at the first call by `multiversion`, for AVX2 and
//! AVX-512 (same operations, no FMA contraction: the values are bit-identical on every
//! x86-64 CPU). Against libm: pixel values and derivatives within 3e-14 of their scale
//! (test `photometry_moffat_pixel_kernel_matches_libm_formula`).
//!
//! Speed: the PSF fits of `sofipol night` on the 49-target bench night: 0.88 -> 0.61 CPU-s
//! with the vectorised `ln`/`exp` (perf samples), measure stage 3.09 -> 2.34 s (medians of 5,
//! same run); the batches of many pixels: measure stage 0.45 -> 0.35 s.

use multiversion::multiversion;

use super::ln_exp::node_kernel;
use super::{derivs_of_sums, derivs_of_sums_elliptical, rule, rule_of, value_of_sum, value_of_sum_elliptical};

/// Lanes of the batched node kernel (the compiler maps `[f64; LANES]` loops to vector code).
const LANES: usize = 4;

/// The node sums of one pixel: `w p`, `w p X/u`, `w p Y/u`, `w p t/u`, `w p ln u`, and for
/// an elliptical star `w p (X^2 - Y^2)/u`, `w p 2 X Y/u` (0 otherwise).
pub(crate) type Sums = [f64; 7];

/// `t alpha^2` at the node offset `(u, v)` from the star: `u^2 + v^2`, or the elliptical
/// form `(1 - e1) u^2 - 2 e2 u v + (1 + e1) v^2` when `ELL`.
#[inline(always)]
fn form<const ELL: bool>(u: f64, v: f64, e: [f64; 2]) -> f64 {
    if ELL {
        (1.0 - e[0]) * (u * u) - 2.0 * e[1] * u * v + (1.0 + e[0]) * (v * v)
    } else {
        u * u + v * v
    }
}

/// The quadrature rule of the pixel at `(dx, dy)`, by its distance in the star's metric.
#[inline(always)]
fn rule_for<const ELL: bool>(dx: f64, dy: f64, alpha: f64, e: [f64; 2]) -> (&'static [f64], &'static [f64]) {
    if ELL {
        rule_of(form::<true>(dx, dy, e), alpha)
    } else {
        rule(dx, dy, alpha)
    }
}

/// Sums over the `N = n x n` nodes `(xs, ws)` of a pixel at `(dx, dy)` from the star of
/// `w p`, `w p X/u`, `w p Y/u`, `w p t/u`, `w p ln u` and, when `ELL`, `w p (X^2 - Y^2)/u`,
/// `w p 2 X Y/u` (with `t` the [`form`] over `alpha^2`, `u = 1 + t`, `p = u^-beta`, `(X, Y)` =
/// node - star), or only the first when `!DERIVS`. The nodes are processed as arrays so that
/// the compiler vectorises the `ln`/`exp` kernel over them. The definition of a pixel's
/// sums, one pixel at a time: the tests' reference for the batched kernel below, which gives
/// the same values bit for bit.
#[cfg(test)]
#[inline(always)]
pub(crate) fn node_sums<const N: usize, const DERIVS: bool, const ELL: bool>(
    dx: f64,
    dy: f64,
    ia2: f64,
    beta: f64,
    e: [f64; 2],
    xs: &[f64],
    ws: &[f64],
) -> Sums {
    let n = xs.len();
    debug_assert_eq!(n * n, N);
    let (mut t, mut w, mut x, mut y) = ([0.0; N], [0.0; N], [0.0; N], [0.0; N]);
    for i in 0..n {
        let u = dx + xs[i];
        for j in 0..n {
            let v = dy + xs[j];
            let k = i * n + j;
            t[k] = form::<ELL>(u, v, e) * ia2;
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
    let mut s = [[0.0; LANES]; 7];
    for k in 0..N {
        let l = k % LANES;
        s[0][l] += wp[k];
        if DERIVS {
            let wpu = wp[k] * iu[k];
            s[1][l] += wpu * x[k];
            s[2][l] += wpu * y[k];
            s[3][l] += wpu * t[k];
            s[4][l] += wp[k] * lu[k];
            if ELL {
                s[5][l] += wpu * (x[k] * x[k] - y[k] * y[k]);
                s[6][l] += wpu * (2.0 * x[k] * y[k]);
            }
        }
    }
    s.map(|a| (a[0] + a[1]) + (a[2] + a[3]))
}

/// [`node_sums`] with the rule of the pixel at `(dx, dy)`.
#[cfg(test)]
#[inline(always)]
pub(crate) fn pixel_sums_generic<const DERIVS: bool, const ELL: bool>(
    dx: f64,
    dy: f64,
    alpha: f64,
    ia2: f64,
    beta: f64,
    e: [f64; 2],
) -> Sums {
    let (xs, ws) = rule_for::<ELL>(dx, dy, alpha, e);
    match xs.len() {
        1 => node_sums::<1, DERIVS, ELL>(dx, dy, ia2, beta, e, xs, ws),
        2 => node_sums::<4, DERIVS, ELL>(dx, dy, ia2, beta, e, xs, ws),
        3 => node_sums::<9, DERIVS, ELL>(dx, dy, ia2, beta, e, xs, ws),
        4 => node_sums::<16, DERIVS, ELL>(dx, dy, ia2, beta, e, xs, ws),
        _ => node_sums::<64, DERIVS, ELL>(dx, dy, ia2, beta, e, xs, ws),
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
pub(crate) fn batch_sums_generic<const DERIVS: bool, const ELL: bool>(
    offsets: &[(f64, f64)],
    alpha: f64,
    ia2: f64,
    beta: f64,
    e: [f64; 2],
    out: &mut [Sums],
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
            let (xs, _) = rule_for::<ELL>(dx, dy, alpha, e);
            let n = xs.len();
            if used + n * n > BATCH_NODES {
                break;
            }
            let tp = &mut t[used..used + n * n];
            match n {
                1 => fill_nodes::<1, ELL>(dx, dy, xs, ia2, e, tp),
                2 => fill_nodes::<2, ELL>(dx, dy, xs, ia2, e, tp),
                3 => fill_nodes::<3, ELL>(dx, dy, xs, ia2, e, tp),
                4 => fill_nodes::<4, ELL>(dx, dy, xs, ia2, e, tp),
                _ => fill_nodes::<8, ELL>(dx, dy, xs, ia2, e, tp),
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
            let (xs, ws) = rule_for::<ELL>(dx, dy, alpha, e);
            let n = xs.len();
            let nodes = Nodes {
                t: &t[k0..],
                lu: &lu[k0..],
                p: &p[k0..],
                iu: &iu[k0..],
            };
            *o = match n {
                1 => reduce_nodes::<1, DERIVS, ELL>(dx, dy, xs, ws, nodes),
                2 => reduce_nodes::<2, DERIVS, ELL>(dx, dy, xs, ws, nodes),
                3 => reduce_nodes::<3, DERIVS, ELL>(dx, dy, xs, ws, nodes),
                4 => reduce_nodes::<4, DERIVS, ELL>(dx, dy, xs, ws, nodes),
                _ => reduce_nodes::<8, DERIVS, ELL>(dx, dy, xs, ws, nodes),
            };
            k0 += n * n;
        }
        first = last;
    }
}

/// `t` ([`form`] over `alpha^2`) at the `M x M` nodes of a pixel, in `node_sums`' order and
/// operations.
#[inline(always)]
fn fill_nodes<const M: usize, const ELL: bool>(dx: f64, dy: f64, xs: &[f64], ia2: f64, e: [f64; 2], t: &mut [f64]) {
    let (xs, t) = (&xs[..M], &mut t[..M * M]);
    for i in 0..M {
        let u = dx + xs[i];
        for j in 0..M {
            let v = dy + xs[j];
            t[i * M + j] = form::<ELL>(u, v, e) * ia2;
        }
    }
}

/// The kernel's values at a pixel's nodes (the slices start at its first node).
#[derive(Clone, Copy)]
struct Nodes<'a> {
    t: &'a [f64],
    lu: &'a [f64],
    p: &'a [f64],
    iu: &'a [f64],
}

/// The sums of [`node_sums`] for one pixel of `M x M` nodes whose kernel values start the
/// slices: the same products, added to the same lanes in the same order.
#[inline(always)]
fn reduce_nodes<const M: usize, const DERIVS: bool, const ELL: bool>(
    dx: f64,
    dy: f64,
    xs: &[f64],
    ws: &[f64],
    nodes: Nodes,
) -> Sums {
    let (xs, ws) = (&xs[..M], &ws[..M]);
    let (t, lu, p, iu) = (
        &nodes.t[..M * M],
        &nodes.lu[..M * M],
        &nodes.p[..M * M],
        &nodes.iu[..M * M],
    );
    let mut s = [[0.0; LANES]; 7];
    for i in 0..M {
        let u = dx + xs[i];
        for j in 0..M {
            let k = i * M + j;
            let l = k % LANES;
            let wp = (ws[i] * ws[j]) * p[k];
            s[0][l] += wp;
            if DERIVS {
                let v = dy + xs[j];
                let wpu = wp * iu[k];
                s[1][l] += wpu * u;
                s[2][l] += wpu * v;
                s[3][l] += wpu * t[k];
                s[4][l] += wp * lu[k];
                if ELL {
                    s[5][l] += wpu * (u * u - v * v);
                    s[6][l] += wpu * (2.0 * u * v);
                }
            }
        }
    }
    s.map(|a| (a[0] + a[1]) + (a[2] + a[3]))
}

/// [`batch_sums_generic`] compiled for the widest vector extension this CPU has, chosen at
/// the first call: AVX-512 (8 lanes; `multiversion` asks for the extensions of Ice Lake and
/// later, where AVX-512 code no longer lowers the clock), AVX2 (4 lanes), else the baseline
/// SSE2 (2 lanes). Only the vector width differs: no FMA contraction, so every build gives
/// the same values bit for bit (test `photometry_moffat_every_build_is_bit_identical`).
// The dispatcher multiversion writes calls a vector build (unsafe) only after checking that
// the CPU has its features, once (then it reads the choice from an atomic).
#[multiversion(targets("x86_64+avx512f", "x86_64+avx2"))]
fn batch_sums<const DERIVS: bool, const ELL: bool>(
    offsets: &[(f64, f64)],
    alpha: f64,
    ia2: f64,
    beta: f64,
    e: [f64; 2],
    out: &mut [Sums],
) {
    batch_sums_generic::<DERIVS, ELL>(offsets, alpha, ia2, beta, e, out)
}

/// The values of `offsets` (`None`: circular) into `out`.
fn pixel_values(offsets: &[(f64, f64)], alpha: f64, beta: f64, e: Option<[f64; 2]>, out: &mut [f64]) {
    assert_eq!(offsets.len(), out.len(), "one output per pixel");
    let ia2 = 1.0 / (alpha * alpha);
    let sums = |s: &mut [Sums]| match e {
        None => batch_sums::<false, false>(offsets, alpha, ia2, beta, [0.0; 2], s),
        Some(e) => batch_sums::<false, true>(offsets, alpha, ia2, beta, e, s),
    };
    let value = |s0: f64| match e {
        None => value_of_sum(s0, ia2, beta),
        Some(e) => value_of_sum_elliptical(s0, ia2, beta, e),
    };
    if let [one] = out {
        // One pixel (a fit's start, a model value): no allocation.
        let mut s = [[0.0; 7]];
        sums(&mut s);
        *one = value(s[0][0]);
        return;
    }
    let mut s = vec![[0.0; 7]; offsets.len()];
    sums(&mut s);
    for (o, s) in out.iter_mut().zip(&s) {
        *o = value(s[0]);
    }
}

/// [`moffat_pixel`](super::moffat_pixel) for many pixels at once (faster: their nodes fill
/// whole vectors): `out[i]` is `moffat_pixel(offsets[i].0, offsets[i].1, alpha, beta)`, bit
/// for bit. Panics if the lengths differ.
pub fn moffat_pixels(offsets: &[(f64, f64)], alpha: f64, beta: f64, out: &mut [f64]) {
    pixel_values(offsets, alpha, beta, None, out);
}

/// [`moffat_pixel_elliptical`](super::moffat_pixel_elliptical) for many pixels at once:
/// `out[i]` is its value at `offsets[i]`, bit for bit. Panics if the lengths differ.
pub fn moffat_pixels_elliptical(offsets: &[(f64, f64)], alpha: f64, beta: f64, e: [f64; 2], out: &mut [f64]) {
    pixel_values(offsets, alpha, beta, Some(e), out);
}

/// [`moffat_pixel_derivs`](super::moffat_pixel_derivs) for many pixels at once: `out[i]` is
/// `moffat_pixel_derivs(offsets[i].0, offsets[i].1, alpha, beta)`, bit for bit. Panics if
/// the lengths differ.
pub fn moffat_pixels_derivs(offsets: &[(f64, f64)], alpha: f64, beta: f64, out: &mut [[f64; 5]]) {
    assert_eq!(offsets.len(), out.len(), "one output per pixel");
    let mut d = vec![[0.0; 7]; offsets.len()];
    moffat_pixels_derivs_any(offsets, alpha, beta, None, &mut d);
    for (o, d) in out.iter_mut().zip(&d) {
        o.copy_from_slice(&d[..5]);
    }
}

/// [`moffat_pixel_derivs_elliptical`](super::moffat_pixel_derivs_elliptical) for many pixels
/// at once: `out[i]` is its value at `offsets[i]`, bit for bit. Panics if the lengths differ.
pub fn moffat_pixels_derivs_elliptical(
    offsets: &[(f64, f64)],
    alpha: f64,
    beta: f64,
    e: [f64; 2],
    out: &mut [[f64; 7]],
) {
    moffat_pixels_derivs_any(offsets, alpha, beta, Some(e), out);
}

/// The values and derivatives of a circular (`e` None; the last two entries 0) or
/// elliptical star at `offsets`: `[P, dP/dx, dP/dy, dP/dalpha, dP/dbeta, dP/de1, dP/de2]`.
pub(crate) fn moffat_pixels_derivs_any(
    offsets: &[(f64, f64)],
    alpha: f64,
    beta: f64,
    e: Option<[f64; 2]>,
    out: &mut [[f64; 7]],
) {
    assert_eq!(offsets.len(), out.len(), "one output per pixel");
    let ia2 = 1.0 / (alpha * alpha);
    match e {
        None => {
            batch_sums::<true, false>(offsets, alpha, ia2, beta, [0.0; 2], out);
            for o in out.iter_mut() {
                let d = derivs_of_sums([o[0], o[1], o[2], o[3], o[4]], alpha, ia2, beta);
                *o = [d[0], d[1], d[2], d[3], d[4], 0.0, 0.0];
            }
        }
        Some(e) => {
            batch_sums::<true, true>(offsets, alpha, ia2, beta, e, out);
            for o in out.iter_mut() {
                *o = derivs_of_sums_elliptical(*o, alpha, ia2, beta, e);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::Rng;
    use super::super::{moffat_pixel, moffat_pixel_derivs, moffat_pixel_derivs_elliptical, moffat_pixel_elliptical};
    use super::*;
    use crate::photometry::moffat::rule_of;

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

    /// A random ellipticity, |e| up to 0.6.
    fn ellipticity(rng: &mut Rng) -> [f64; 2] {
        let (m, a) = (0.6 * rng.next(), std::f64::consts::TAU * rng.next());
        [m * a.cos(), m * a.sin()]
    }

    /// Which build of [`batch_sums`] this CPU runs (the same targets, so the same choice):
    /// 2 AVX-512, 1 AVX2, 0 the baseline.
    #[multiversion(targets("x86_64+avx512f", "x86_64+avx2"))]
    fn build_this_cpu_runs() -> usize {
        multiversion::target::match_target! {
            "x86_64+avx512f" => 2,
            "x86_64+avx2" => 1,
            _ => 0,
        }
    }

    /// [`batch_sums_generic`] compiled as [`batch_sums`]' AVX2 build is (the same target,
    /// hence the same code): compared even on a CPU whose dispatcher picks AVX-512.
    #[multiversion::target("x86_64+avx2")]
    fn batch_sums_avx2<const DERIVS: bool, const ELL: bool>(
        offsets: &[(f64, f64)],
        alpha: f64,
        ia2: f64,
        beta: f64,
        e: [f64; 2],
        out: &mut [Sums],
    ) {
        batch_sums_generic::<DERIVS, ELL>(offsets, alpha, ia2, beta, e, out)
    }

    /// [`batch_sums_generic`] compiled as [`batch_sums`]' AVX-512 build is.
    #[multiversion::target("x86_64+avx512f")]
    fn batch_sums_avx512<const DERIVS: bool, const ELL: bool>(
        offsets: &[(f64, f64)],
        alpha: f64,
        ia2: f64,
        beta: f64,
        e: [f64; 2],
        out: &mut [Sums],
    ) {
        batch_sums_generic::<DERIVS, ELL>(offsets, alpha, ia2, beta, e, out)
    }

    /// The sums of `offsets` by the baseline build, the dispatched one and every vector build
    /// this CPU runs (`widest` from [`build_this_cpu_runs`]), by name.
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_variables))]
    fn every_build<const DERIVS: bool, const ELL: bool>(
        offsets: &[(f64, f64)],
        alpha: f64,
        ia2: f64,
        beta: f64,
        e: [f64; 2],
        widest: usize,
    ) -> Vec<(&'static str, Vec<Sums>)> {
        let run = |f: &dyn Fn(&mut [Sums])| {
            let mut v = vec![[0.0; 7]; offsets.len()];
            f(&mut v);
            v
        };
        #[allow(unused_mut)]
        let mut builds = vec![
            (
                "SSE2",
                run(&|v| batch_sums_generic::<DERIVS, ELL>(offsets, alpha, ia2, beta, e, v)),
            ),
            (
                "dispatched",
                run(&|v| batch_sums::<DERIVS, ELL>(offsets, alpha, ia2, beta, e, v)),
            ),
        ];
        #[cfg(target_arch = "x86_64")]
        {
            if widest >= 1 {
                // SAFETY: this CPU runs the AVX2 build: it has AVX2.
                #[allow(unsafe_code)]
                let v = run(&|v| unsafe { batch_sums_avx2::<DERIVS, ELL>(offsets, alpha, ia2, beta, e, v) });
                builds.push(("AVX2", v));
            }
            if widest >= 2 {
                // SAFETY: this CPU runs the AVX-512 build: it has its features.
                #[allow(unsafe_code)]
                let v = run(&|v| unsafe { batch_sums_avx512::<DERIVS, ELL>(offsets, alpha, ia2, beta, e, v) });
                builds.push(("AVX-512", v));
            }
        }
        builds
    }

    /// Every build of the kernel this CPU runs (the dispatched one, and the AVX2 build on a
    /// CPU with AVX-512) gives the baseline (SSE2) build's sums bit for bit, values only and
    /// with derivatives, so results do not depend on the CPU.
    #[test]
    fn photometry_moffat_every_build_is_bit_identical() {
        let widest = build_this_cpu_runs();
        eprintln!("this CPU runs the {} build", ["SSE2", "AVX2", "AVX-512"][widest]);
        let mut rng = Rng(7);
        for n in 0..400 {
            let alpha = 0.3 * 100f64.powf(rng.next());
            let beta = 1.01 + 19.0 * rng.next();
            let ia2 = 1.0 / (alpha * alpha);
            let offsets: Vec<(f64, f64)> = (0..(rng.next() * 120.0) as usize)
                .map(|_| ((rng.next() - 0.5) * 8.0 * alpha, (rng.next() - 0.5) * 8.0 * alpha))
                .collect();
            let e = ellipticity(&mut rng);
            for builds in [
                every_build::<false, false>(&offsets, alpha, ia2, beta, [0.0; 2], widest),
                every_build::<true, false>(&offsets, alpha, ia2, beta, [0.0; 2], widest),
                every_build::<false, true>(&offsets, alpha, ia2, beta, e, widest),
                every_build::<true, true>(&offsets, alpha, ia2, beta, e, widest),
            ] {
                let (_, want) = &builds[0];
                for (name, got) in &builds[1..] {
                    for (i, (a, b)) in want.iter().zip(got).enumerate() {
                        for c in 0..7 {
                            assert_eq!(
                                a[c].to_bits(),
                                b[c].to_bits(),
                                "{name} batch {n} pixel {i} component {c}"
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
                let s = pixel_sums_generic::<true, false>(dx, dy, alpha, ia2, beta, [0.0; 2]);
                let want_value = (beta - 1.0) / std::f64::consts::PI * ia2 * s[0];
                let want = derivs_of_sums([s[0], s[1], s[2], s[3], s[4]], alpha, ia2, beta);
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

    /// The same for an elliptical star (|e| up to 0.6): the batched values and derivatives
    /// are the per-pixel definition's bit for bit; with e = 0 the elliptical kernel gives the
    /// circular one's values and derivatives bit for bit (and 0 for the ellipticity's
    /// derivatives' symmetric parts at the centre line).
    #[test]
    fn photometry_moffat_elliptical_batch_is_the_per_pixel_kernel() {
        let mut rng = Rng(23);
        for case in 0..300 {
            let alpha = 0.5 * 20f64.powf(rng.next());
            let beta = 1.05 + 9.0 * rng.next();
            let e = if case % 10 == 0 {
                [0.0; 2]
            } else {
                ellipticity(&mut rng)
            };
            let n = (rng.next() * 300.0) as usize;
            let offsets: Vec<(f64, f64)> = (0..n)
                .map(|_| {
                    let r = alpha * 15.0 * rng.next().powi(2);
                    let a = std::f64::consts::TAU * rng.next();
                    (r * a.cos(), r * a.sin())
                })
                .collect();
            let mut values = vec![f64::NAN; n];
            let mut derivs = vec![[f64::NAN; 7]; n];
            moffat_pixels_elliptical(&offsets, alpha, beta, e, &mut values);
            moffat_pixels_derivs_elliptical(&offsets, alpha, beta, e, &mut derivs);
            let ia2 = 1.0 / (alpha * alpha);
            for (i, &(dx, dy)) in offsets.iter().enumerate() {
                let s = pixel_sums_generic::<true, true>(dx, dy, alpha, ia2, beta, e);
                let want = derivs_of_sums_elliptical(s, alpha, ia2, beta, e);
                let want_value = value_of_sum_elliptical(s[0], ia2, beta, e);
                assert_eq!(want_value.to_bits(), want[0].to_bits(), "case {case} pixel {i}");
                assert_eq!(values[i].to_bits(), want_value.to_bits(), "case {case} pixel {i}");
                assert_eq!(
                    moffat_pixel_elliptical(dx, dy, alpha, beta, e).to_bits(),
                    want_value.to_bits(),
                    "case {case} pixel {i}"
                );
                let one = moffat_pixel_derivs_elliptical(dx, dy, alpha, beta, e);
                for c in 0..7 {
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
                if e == [0.0; 2] {
                    assert_eq!(values[i].to_bits(), moffat_pixel(dx, dy, alpha, beta).to_bits());
                    let circ = moffat_pixel_derivs(dx, dy, alpha, beta);
                    for c in 0..5 {
                        assert_eq!(
                            derivs[i][c].to_bits(),
                            circ[c].to_bits(),
                            "case {case} pixel {i} component {c}"
                        );
                    }
                }
            }
        }
    }

    /// The elliptical kernel against the straightforward libm formula (the quadratic form,
    /// `powf`, the derivatives written out): each value and derivative within 1e-13 of its
    /// scale over random stars, |e| up to 0.6.
    #[test]
    fn photometry_moffat_elliptical_kernel_matches_libm_formula() {
        let mut rng = Rng(0x0e11);
        let mut worst = [0.0f64; 7];
        for _ in 0..20_000 {
            let alpha = 0.3 * 100f64.powf(rng.next());
            let beta = 1.01 + 19.0 * rng.next();
            let e = ellipticity(&mut rng);
            let [e1, e2] = e;
            let r = 20.0 * alpha * rng.next().powi(2);
            let phi = std::f64::consts::TAU * rng.next();
            let (dx, dy) = (r * phi.cos(), r * phi.sin());
            let d = moffat_pixel_derivs_elliptical(dx, dy, alpha, beta, e);
            let ia2 = 1.0 / (alpha * alpha);
            let q = |u: f64, v: f64| (1.0 - e1) * u * u - 2.0 * e2 * u * v + (1.0 + e1) * v * v;
            let (xs, ws) = rule_of(q(dx, dy), alpha);
            let det = 1.0 - e1 * e1 - e2 * e2;
            let norm = (beta - 1.0) / std::f64::consts::PI * ia2 * det.sqrt();
            let (mut val, mut scale) = ([0.0f64; 7], [0.0f64; 7]);
            for (&ax, &wa) in xs.iter().zip(ws) {
                for (&by, &wb) in xs.iter().zip(ws) {
                    let (u, v) = (dx + ax, dy + by);
                    let t = q(u, v) * ia2;
                    let p = wa * wb * (1.0 + t).powf(-beta);
                    let pu = p / (1.0 + t);
                    // d/d(star position) = -d/d(node offset).
                    let terms = [
                        norm * p,
                        norm * beta * pu * 2.0 * ia2 * ((1.0 - e1) * u - e2 * v),
                        norm * beta * pu * 2.0 * ia2 * ((1.0 + e1) * v - e2 * u),
                        norm * 2.0 / alpha * (beta * pu * t - p),
                        norm * (p / (beta - 1.0) - p * t.ln_1p()),
                        norm * (beta * pu * ia2 * (u * u - v * v) - e1 / det * p),
                        norm * (beta * pu * ia2 * 2.0 * u * v - e2 / det * p),
                    ];
                    // The rounding scale: the parts the kernel sums separately, in absolute value.
                    let parts = [
                        norm * p,
                        norm * beta * pu * 2.0 * ia2 * ((1.0 - e1).abs() * u.abs() + e2.abs() * v.abs()),
                        norm * beta * pu * 2.0 * ia2 * ((1.0 + e1).abs() * v.abs() + e2.abs() * u.abs()),
                        norm * 2.0 / alpha * (beta * pu * t + p),
                        norm * (p / (beta - 1.0) + p * t.ln_1p()),
                        norm * (beta * pu * ia2 * (u * u + v * v) + (e1 / det).abs() * p),
                        norm * (beta * pu * ia2 * 2.0 * (u * v).abs() + (e2 / det).abs() * p),
                    ];
                    for i in 0..7 {
                        val[i] += terms[i];
                        scale[i] += parts[i];
                    }
                }
            }
            for i in 0..7 {
                worst[i] = worst[i].max((d[i] - val[i]).abs() / scale[i]);
            }
        }
        eprintln!("elliptical kernel vs libm formula: worst |diff|/scale {worst:?}");
        for (i, w) in worst.iter().enumerate() {
            assert!(*w < 1e-13, "component {i}: {w:e}");
        }
    }
}
