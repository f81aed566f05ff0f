//! The elementary functions of a quadrature node of the Moffat kernel: `ln(1 + t)`,
//! `(1 + t)^-beta` and `1 / (1 + t)` at once ([`node_kernel`]), branch-free so that the
//! compiler vectorises them over many nodes: fdlibm's `log` with its division shared with
//! `1 / (1 + t)`, and a Taylor `exp` after Cody-Waite reduction. No FMA contraction, so the
//! values are the same on every x86-64 CPU whatever the vector width. Against libm:
//! `ln(1 + t)` and `1 / (1 + t)` within 2.2e-16 relative, `(1 + t)^-beta` within
//! 3.7e-16 x (1 + beta ln(1 + t)) (the conditioning of any `exp`; tests
//! `photometry_moffat_node_kernel_matches_libm`, `photometry_moffat_exp_kernel_matches_libm`).

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
pub(super) fn node_kernel(t: f64, beta: f64) -> (f64, f64, f64) {
    let u = 1.0 + t;
    let (ln_u, iu) = ln_recip_kernel(u);
    // u - 1 is exact (u >= 1) and t - (u - 1) is the rounding error of u, exactly.
    let lu = ln_u + (t - (u - 1.0)) * iu;
    (lu, exp_kernel(-beta * lu), iu)
}

#[cfg(test)]
mod tests {
    use super::super::tests::Rng;
    use super::*;

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
}
