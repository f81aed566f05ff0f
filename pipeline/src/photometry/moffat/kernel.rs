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
use super::{derivs_of_sums, rule, value_of_sum};

/// Lanes of the batched node kernel (the compiler maps `[f64; LANES]` loops to vector code).
const LANES: usize = 4;

/// Sums over the `N = n x n` nodes `(xs, ws)` of a pixel at `(dx, dy)` from the star of
/// `w p`, `w p X/u`, `w p Y/u`, `w p t/u`, `w p ln u` (with `t = r^2/alpha^2`, `u = 1 + t`,
/// `p = u^-beta`, `(X, Y)` = node - star), or only the first when `!DERIVS`. The nodes are
/// processed as arrays so that the compiler vectorises the `ln`/`exp` kernel over them. The
/// definition of a pixel's sums, one pixel at a time: the tests' reference for the batched
/// kernel below, which gives the same values bit for bit.
#[cfg(test)]
#[inline(always)]
pub(crate) fn node_sums<const N: usize, const DERIVS: bool>(
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
pub(crate) fn pixel_sums_generic<const DERIVS: bool>(dx: f64, dy: f64, alpha: f64, ia2: f64, beta: f64) -> [f64; 5] {
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
pub(crate) fn batch_sums_generic<const DERIVS: bool>(
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

/// [`batch_sums_generic`] compiled for the widest vector extension this CPU has, chosen at
/// the first call: AVX-512 (8 lanes; `multiversion` asks for the extensions of Ice Lake and
/// later, where AVX-512 code no longer lowers the clock), AVX2 (4 lanes), else the baseline
/// SSE2 (2 lanes). Only the vector width differs: no FMA contraction, so every build gives
/// the same values bit for bit (test `photometry_moffat_every_build_is_bit_identical`).
// The dispatcher multiversion writes calls a vector build (unsafe) only after checking that
// the CPU has its features, once (then it reads the choice from an atomic).
#[multiversion(targets("x86_64+avx512f", "x86_64+avx2"))]
fn batch_sums<const DERIVS: bool>(offsets: &[(f64, f64)], alpha: f64, ia2: f64, beta: f64, out: &mut [[f64; 5]]) {
    batch_sums_generic::<DERIVS>(offsets, alpha, ia2, beta, out)
}

/// [`moffat_pixel`](super::moffat_pixel) for many pixels at once (faster: their nodes fill
/// whole vectors): `out[i]` is `moffat_pixel(offsets[i].0, offsets[i].1, alpha, beta)`, bit
/// for bit. Panics if the lengths differ.
pub fn moffat_pixels(offsets: &[(f64, f64)], alpha: f64, beta: f64, out: &mut [f64]) {
    assert_eq!(offsets.len(), out.len(), "one output per pixel");
    let ia2 = 1.0 / (alpha * alpha);
    if let [one] = out {
        // One pixel (a fit's start, a model value): no allocation.
        let mut s = [[0.0; 5]];
        batch_sums::<false>(offsets, alpha, ia2, beta, &mut s);
        *one = value_of_sum(s[0][0], ia2, beta);
        return;
    }
    let mut sums = vec![[0.0; 5]; offsets.len()];
    batch_sums::<false>(offsets, alpha, ia2, beta, &mut sums);
    for (o, s) in out.iter_mut().zip(&sums) {
        *o = value_of_sum(s[0], ia2, beta);
    }
}

/// [`moffat_pixel_derivs`](super::moffat_pixel_derivs) for many pixels at once: `out[i]` is
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

#[cfg(test)]
mod tests {
    use super::super::tests::Rng;
    use super::super::{moffat_pixel, moffat_pixel_derivs};
    use super::*;

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
    fn batch_sums_avx2<const DERIVS: bool>(
        offsets: &[(f64, f64)],
        alpha: f64,
        ia2: f64,
        beta: f64,
        out: &mut [[f64; 5]],
    ) {
        batch_sums_generic::<DERIVS>(offsets, alpha, ia2, beta, out)
    }

    /// [`batch_sums_generic`] compiled as [`batch_sums`]' AVX-512 build is.
    #[multiversion::target("x86_64+avx512f")]
    fn batch_sums_avx512<const DERIVS: bool>(
        offsets: &[(f64, f64)],
        alpha: f64,
        ia2: f64,
        beta: f64,
        out: &mut [[f64; 5]],
    ) {
        batch_sums_generic::<DERIVS>(offsets, alpha, ia2, beta, out)
    }

    /// The sums of `offsets` by the baseline build, the dispatched one and every vector build
    /// this CPU runs (`widest` from [`build_this_cpu_runs`]), by name.
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_variables))]
    fn every_build<const DERIVS: bool>(
        offsets: &[(f64, f64)],
        alpha: f64,
        ia2: f64,
        beta: f64,
        widest: usize,
    ) -> Vec<(&'static str, Vec<[f64; 5]>)> {
        let run = |f: &dyn Fn(&mut [[f64; 5]])| {
            let mut v = vec![[0.0; 5]; offsets.len()];
            f(&mut v);
            v
        };
        #[allow(unused_mut)]
        let mut builds = vec![
            (
                "SSE2",
                run(&|v| batch_sums_generic::<DERIVS>(offsets, alpha, ia2, beta, v)),
            ),
            (
                "dispatched",
                run(&|v| batch_sums::<DERIVS>(offsets, alpha, ia2, beta, v)),
            ),
        ];
        #[cfg(target_arch = "x86_64")]
        {
            if widest >= 1 {
                // SAFETY: this CPU runs the AVX2 build: it has AVX2.
                #[allow(unsafe_code)]
                let v = run(&|v| unsafe { batch_sums_avx2::<DERIVS>(offsets, alpha, ia2, beta, v) });
                builds.push(("AVX2", v));
            }
            if widest >= 2 {
                // SAFETY: this CPU runs the AVX-512 build: it has its features.
                #[allow(unsafe_code)]
                let v = run(&|v| unsafe { batch_sums_avx512::<DERIVS>(offsets, alpha, ia2, beta, v) });
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
            for builds in [
                every_build::<false>(&offsets, alpha, ia2, beta, widest),
                every_build::<true>(&offsets, alpha, ia2, beta, widest),
            ] {
                let (_, want) = &builds[0];
                for (name, got) in &builds[1..] {
                    for (i, (a, b)) in want.iter().zip(got).enumerate() {
                        for c in 0..5 {
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
