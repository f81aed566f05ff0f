//! p-values against references computed independently of the code under test: the exact
//! small-n Kolmogorov distribution by a slow, obviously-correct sweep (no Marsaglia-Tsang-
//! Wang matrix), and scipy's exact `kstwo` where the asymptotic formula is used.
use super::ks::{kolmogorov_sf, ks_uniform, EXACT_MAX_N};

/// P(D_n < d) for n iid uniforms, by sweeping the counting process N(t) = #{U <= t}.
///
/// D_n < d holds iff every order statistic lies in its band: i/n - d < U_(i) < (i-1)/n + d,
/// i.e. N(i/n - d) <= i - 1 and N((i-1)/n + d) >= i. Between consecutive breakpoints the
/// number of new points, given N(prev) = k, is binomial(n - k, (c - prev)/(1 - prev)). The
/// distribution of N is carried from breakpoint to breakpoint and cut by the constraints.
fn ks_cdf_by_sweep(d: f64, n: usize) -> f64 {
    let nf = n as f64;
    // (breakpoint, max allowed N, min required N)
    let mut cons: Vec<(f64, usize, usize)> = Vec::new();
    for i in 1..=n {
        let a = i as f64 / nf - d;
        if a > 0.0 {
            cons.push((a, i - 1, 0));
        }
        let b = (i - 1) as f64 / nf + d;
        if b < 1.0 {
            cons.push((b, n, i));
        }
    }
    cons.push((1.0, n, n));
    cons.sort_by(|x, y| x.0.total_cmp(&y.0));
    let binom = |m: usize, k: usize| -> f64 { (0..k).fold(1.0, |acc, j| acc * (m - j) as f64 / (j + 1) as f64) };
    let mut dist = vec![0.0f64; n + 1];
    dist[0] = 1.0;
    let mut prev = 0.0f64;
    for &(c, hi, lo) in &cons {
        let p = if prev < 1.0 {
            ((c - prev) / (1.0 - prev)).clamp(0.0, 1.0)
        } else {
            1.0
        };
        let mut next = vec![0.0f64; n + 1];
        for (k, &w) in dist.iter().enumerate() {
            if w == 0.0 {
                continue;
            }
            let left = n - k;
            for j in 0..=left {
                next[k + j] += w * binom(left, j) * p.powi(j as i32) * (1.0 - p).powi((left - j) as i32);
            }
        }
        for (k, v) in next.iter_mut().enumerate() {
            if k > hi || k < lo {
                *v = 0.0;
            }
        }
        dist = next;
        prev = c;
    }
    dist[n]
}

/// The sweep itself is right: n = 1 (D = max(U, 1 - U), so P(D < d) = 2d - 1 for d > 1/2)
/// and the closed form P(D_n < d) = n! (2d - 1/n)^n for 1/(2n) <= d <= 1/n.
#[test]
fn ks_sweep_reference_matches_closed_forms() {
    for d in [0.55, 0.7, 0.93] {
        assert!((ks_cdf_by_sweep(d, 1) - (2.0 * d - 1.0)).abs() < 1e-14, "n 1, d {d}");
    }
    for n in [3usize, 9] {
        let nf = n as f64;
        let fact: f64 = (1..=n).map(|k| k as f64).product();
        for t in [0.55, 0.7, 0.95] {
            let d = t / nf;
            let want = fact * (2.0 * d - 1.0 / nf).powi(n as i32);
            let got = ks_cdf_by_sweep(d, n);
            assert!(
                (got - want).abs() < 1e-12 * want.max(1e-300) + 1e-15,
                "n {n} d {d}: {got} vs {want}"
            );
        }
    }
}

/// At n = 9 (the size of a small sample of binaries) the p-value equals the slow exact
/// distribution, and scipy's `kstwo`. Reference values from scipy 1.17.1:
///
/// ```text
/// python3 -c "from scipy import stats; [print(d, repr(float(stats.kstwo.sf(d, 9))))
///             for d in [0.15, 0.25, 0.3, 0.4, 0.55, 0.7]]"
/// ```
#[test]
fn ks_p_value_at_n9_matches_slow_exact_and_scipy() {
    const SCIPY_KSTWO_SF_N9: [(f64, f64); 6] = [
        (0.15, 0.9694262000514743),
        (0.25, 0.5469168777360245),
        (0.3, 0.32439191684739876),
        (0.4, 0.08218195263787098),
        (0.55, 0.004390191199619032),
        (0.7, 6.058470997658576e-05),
    ];
    for (d, scipy) in SCIPY_KSTWO_SF_N9 {
        let (p, method) = kolmogorov_sf(d, 9);
        let slow = 1.0 - ks_cdf_by_sweep(d, 9);
        assert!(
            (slow - scipy).abs() <= 1e-10 * scipy,
            "d {d}: sweep {slow} vs scipy {scipy}"
        );
        assert!(
            (p - slow).abs() <= 1e-9 * slow,
            "d {d}: {p} ({method}) vs slow exact {slow}"
        );
    }
    // Through the data path: nine angles on [0, 90) whose D is known.
    let data = [3.0, 7.5, 12.0, 20.0, 24.0, 31.0, 40.0, 52.0, 88.0];
    let t = ks_uniform(&data, 0.0, 90.0);
    let d_brute = (1..=9)
        .map(|i| {
            let f = data[i - 1] / 90.0;
            (i as f64 / 9.0 - f).max(f - (i - 1) as f64 / 9.0)
        })
        .fold(0.0f64, f64::max);
    assert!((t.statistic - d_brute).abs() < 1e-15);
    let slow = 1.0 - ks_cdf_by_sweep(d_brute, 9);
    assert!((t.p_value - slow).abs() <= 1e-9 * slow, "{} vs {slow}", t.p_value);
}

/// Above [`EXACT_MAX_N`] the p-value is the Kolmogorov limit at Stephens' corrected
/// lambda = (sqrt n + 0.12 + 0.11/sqrt n) D. Its relative error shrinks as 1/sqrt(n): at
/// the conventional levels it is 0.019/sqrt(n) (p = 0.05) and -0.16 to -0.17/sqrt(n)
/// (p = 0.01) here, checked against 0.035/sqrt(n) and 0.2/sqrt(n). A constant off by 0.01
/// (0.13) gives -0.055/sqrt(n) and -0.27/sqrt(n), and fails. Reference values (D rounded to 6 digits, then
/// the exact sf at that D), scipy 1.17.1:
///
/// ```text
/// python3 -c "from scipy import stats
/// for n in [1001, 2000, 5000]:
///     for p in [0.05, 0.01]:
///         d = round(float(stats.kstwo.isf(p, n)), 6); print(n, d, repr(float(stats.kstwo.sf(d, n))))"
/// ```
#[test]
fn ks_asymptotic_p_value_matches_scipy_kstwo_at_conventional_levels() {
    const SCIPY: [(usize, f64, f64); 6] = [
        (1001, 0.042755, 0.05000184967759236),
        (1001, 0.051269, 0.00999927622081567),
        (2000, 0.030283, 0.050004509136691966),
        (2000, 0.036308, 0.010000603429626985),
        (5000, 0.019173, 0.049995223944897194),
        (5000, 0.022984, 0.009999644581154262),
    ];
    const { assert!(EXACT_MAX_N < 1001) };
    for (n, d, exact) in SCIPY {
        let (p, method) = kolmogorov_sf(d, n);
        assert!(method.starts_with("asymptotic"), "{method}");
        let tol = if exact > 0.03 { 0.035 } else { 0.2 } / (n as f64).sqrt();
        assert!(
            (p / exact - 1.0).abs() < tol,
            "n {n} d {d}: {p} vs scipy kstwo {exact} (rel {:.2e})",
            p / exact - 1.0
        );
    }
}

/// `ks_uniform` on [lo, hi] tests (x - lo)/(hi - lo) against U(0, 1), also when lo != 0
/// (the alignment test uses [0, 90]; a sample of angles on [10, 100] must give the same
/// outcome as the same angles shifted to [0, 90]): an evenly filled sample has D = 1/(2n)
/// exactly and is not rejected; the same sample against [0, 90] unshifted is.
#[test]
fn ks_uniform_tests_the_sample_on_its_own_interval() {
    let n = 20;
    let on = |lo: f64, hi: f64| -> Vec<f64> { (0..n).map(|i| lo + (hi - lo) * (i as f64 + 0.5) / n as f64).collect() };
    let shifted = ks_uniform(&on(10.0, 100.0), 10.0, 100.0);
    let at_zero = ks_uniform(&on(0.0, 90.0), 0.0, 90.0);
    assert!(
        (shifted.statistic - 0.5 / n as f64).abs() < 1e-12,
        "D {}",
        shifted.statistic
    );
    assert!((shifted.statistic - at_zero.statistic).abs() < 1e-12);
    assert!((shifted.p_value - at_zero.p_value).abs() < 1e-12 && shifted.p_value > 0.99);
    // The interval matters: the same angles tested against [0, 90] are off by 10 deg.
    let wrong = ks_uniform(&on(10.0, 100.0), 0.0, 90.0);
    assert!(wrong.statistic > 0.1, "D {}", wrong.statistic);
}

/// A two-sample test (either form) with either sample empty has nothing to compare: D = 0,
/// p = 1, said so.
#[test]
fn ks_two_sample_with_an_empty_sample_is_trivial() {
    let some = [0.1, 0.5, 0.9];
    for (a, b) in [(&some[..], &[][..]), (&[][..], &some[..]), (&[][..], &[][..])] {
        for t in [
            super::ks::ks_two_sample(a, b),
            super::ks::ks_two_sample_against_large(a, b),
        ] {
            assert_eq!(
                (t.statistic, t.p_value, t.n, t.method.as_str()),
                (0.0, 1.0, 0, "empty sample")
            );
        }
    }
}
