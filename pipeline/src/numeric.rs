//! Small numeric helpers shared by every stage (one implementation each): medians, the
//! SplitMix64 mixer of the seeded random streams, and Gauss-Legendre pixel-integration
//! tables.

/// Median of `v` (reordered in place): the middle value, or the mean of the two middle
/// values for an even count, in the total order of `f64::total_cmp`; NaN when empty.
/// The same value, bit for bit, as sorting and taking the middle.
pub fn median_in_place(v: &mut [f64]) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    let (lower, mid, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let mid = *mid;
    if n % 2 == 1 {
        mid
    } else {
        let below = lower.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (below + mid)
    }
}

/// Median of the finite values (None when there is none).
pub fn median_finite(values: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    (!v.is_empty()).then(|| median_in_place(&mut v))
}

/// The SplitMix64 finaliser (Steele, Lea & Flood 2014): a bijective 64-bit mixer.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// One SplitMix64 step from state `z`: add the golden-ratio increment, then [`mix64`].
#[inline]
pub fn splitmix64(z: u64) -> u64 {
    mix64(z.wrapping_add(0x9E37_79B9_7F4A_7C15))
}

/// 1-point rule (midpoint) on `[-1/2, 1/2]`.
pub const GL1_X: [f64; 1] = [0.0];
/// Its weight.
pub const GL1_W: [f64; 1] = [1.0];
/// 2-point Gauss-Legendre nodes on `[-1/2, 1/2]` (`±1/(2 sqrt 3)`).
pub const GL2_X: [f64; 2] = [-0.288_675_134_594_812_9, 0.288_675_134_594_812_9];
/// Weights of [`GL2_X`].
pub const GL2_W: [f64; 2] = [0.5, 0.5];
/// 3-point Gauss-Legendre nodes on `[-1/2, 1/2]` (`±sqrt(3/5)/2`, 0).
pub const GL3_X: [f64; 3] = [-0.387_298_334_620_741_7, 0.0, 0.387_298_334_620_741_7];
/// Weights of [`GL3_X`]: 5/18, 8/18, 5/18.
pub const GL3_W: [f64; 3] = [
    0.277_777_777_777_777_8,
    0.444_444_444_444_444_4,
    0.277_777_777_777_777_8,
];
/// 4-point Gauss-Legendre nodes on `[-1/2, 1/2]`.
pub const GL4_X: [f64; 4] = [
    -0.430_568_155_797_026_3,
    -0.169_990_521_792_428_1,
    0.169_990_521_792_428_1,
    0.430_568_155_797_026_3,
];
/// Weights of [`GL4_X`] (sum 1).
pub const GL4_W: [f64; 4] = [
    0.173_927_422_568_726_9,
    0.326_072_577_431_273_1,
    0.326_072_577_431_273_1,
    0.173_927_422_568_726_9,
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_matches_sorting() {
        let mut state = 1u64;
        for n in 1..40 {
            let v: Vec<f64> = (0..n)
                .map(|_| {
                    state = splitmix64(state);
                    (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
                })
                .collect();
            let mut s = v.clone();
            s.sort_by(f64::total_cmp);
            let want = if n % 2 == 1 {
                s[n / 2]
            } else {
                0.5 * (s[n / 2 - 1] + s[n / 2])
            };
            assert_eq!(median_in_place(&mut v.clone()).to_bits(), want.to_bits(), "n = {n}");
        }
        assert_eq!(median_finite(&[f64::NAN, 3.0, 1.0, f64::INFINITY]), Some(2.0));
        assert_eq!(median_finite(&[f64::NAN]), None);
        assert!(median_in_place(&mut []).is_nan());
    }

    #[test]
    fn splitmix_reference_outputs() {
        // splitmix64.c seeded with 1234567: the state advances by the increment, each
        // output is the mixed state (Rosetta Code, "Pseudo-random numbers/Splitmix64").
        let mut s = 1234567u64;
        let mut out = Vec::new();
        for _ in 0..3 {
            out.push(splitmix64(s));
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        }
        assert_eq!(out, [6457827717110365317, 3203168211198807973, 9817491932198370423]);
    }

    #[test]
    fn gauss_legendre_rules_integrate_polynomials_exactly() {
        // An n-point rule is exact for degree 2n - 1: integral of x^k over [-1/2, 1/2].
        let rules: [(&[f64], &[f64]); 4] = [(&GL1_X, &GL1_W), (&GL2_X, &GL2_W), (&GL3_X, &GL3_W), (&GL4_X, &GL4_W)];
        for (xs, ws) in rules {
            let n = xs.len() as i32;
            for k in 0..2 * n {
                let exact = if k % 2 == 1 {
                    0.0
                } else {
                    2.0 * 0.5f64.powi(k + 1) / (k + 1) as f64
                };
                let q: f64 = xs.iter().zip(ws).map(|(x, w)| w * x.powi(k)).sum();
                assert!((q - exact).abs() < 1e-15, "n = {n}, k = {k}: {q} vs {exact}");
            }
        }
    }
}
