//! Kolmogorov-Smirnov tests, one- and two-sample, with carefully chosen p-value methods.
//!
//! p-values (two-sided):
//! * one-sample, n <= [`EXACT_MAX_N`]: the exact distribution of D_n by Marsaglia, Tsang &
//!   Wang (2003, J. Stat. Softw. 8(18)), except in the far tail (p < [`TAIL_SWITCH`]),
//!   where 1 - K(d) loses relative precision and 2 P(D+ >= d) (Birnbaum & Tingey 1951,
//!   exact for the one-sided statistic) is used instead: the two differ by
//!   P(D+ >= d and D- >= d), which is of order p^2 there (it agrees with scipy's kstwo to
//!   1e-7 relative in the reference tests, down to p = 3e-12);
//! * one-sample, n > EXACT_MAX_N: the Kolmogorov limit Q_KS(lambda) with Stephens' (1970)
//!   correction lambda = (sqrt n + 0.12 + 0.11/sqrt n) D (Numerical Recipes 14.3);
//! * two-sample: the one-sample distribution at the effective size
//!   n_e = round(n1 n2 / (n1 + n2)), exactly what scipy's `ks_2samp(method="asymp")` does;
//!   when one sample is a large Monte Carlo (n2 >> n1) this is the exact one-sample law
//!   for the observed sample.
use rayon::prelude::*;

use super::TestOutcome;

/// Largest n for which the one-sample p-value is exact (Marsaglia-Tsang-Wang).
pub const EXACT_MAX_N: usize = 1000;
/// Below this p-value the far-tail formula replaces 1 - K(d).
pub const TAIL_SWITCH: f64 = 1e-6;

/// One-sample KS test of `data` against a continuous CDF.
pub fn ks_one_sample(data: &[f64], cdf: impl Fn(f64) -> f64) -> TestOutcome {
    let (d, _, _) = ks_statistics(data, &cdf);
    let n = data.len();
    let (p, method) = kolmogorov_sf(d, n);
    TestOutcome {
        statistic: d,
        p_value: p,
        n,
        method: method.into(),
    }
}

/// One-sample KS test against the uniform distribution on [lo, hi].
pub fn ks_uniform(data: &[f64], lo: f64, hi: f64) -> TestOutcome {
    ks_one_sample(data, |x| ((x - lo) / (hi - lo)).clamp(0.0, 1.0))
}

/// (D, D+, D-) of a sample against a CDF: D+ = max(i/n - F(x_(i))),
/// D- = max(F(x_(i)) - (i-1)/n). NaNs must have been removed by the caller.
pub fn ks_statistics(data: &[f64], cdf: &impl Fn(f64) -> f64) -> (f64, f64, f64) {
    let n = data.len();
    if n == 0 {
        return (0.0, 0.0, 0.0);
    }
    let mut f: Vec<f64> = data.iter().map(|&x| cdf(x)).collect();
    f.sort_by(|a, b| a.total_cmp(b));
    let nf = n as f64;
    let (mut dp, mut dm) = (0.0f64, 0.0f64);
    for (i, &fi) in f.iter().enumerate() {
        dp = dp.max((i + 1) as f64 / nf - fi);
        dm = dm.max(fi - i as f64 / nf);
    }
    (dp.max(dm), dp, dm)
}

/// Two-sample KS test (two-sided). Ties across the samples are handled by stepping both
/// empirical CDFs past a tied value before comparing.
pub fn ks_two_sample(a: &[f64], b: &[f64]) -> TestOutcome {
    let (n1, n2) = (a.len(), b.len());
    if n1 == 0 || n2 == 0 {
        return TestOutcome {
            statistic: 0.0,
            p_value: 1.0,
            n: n1.min(n2),
            method: "empty sample".into(),
        };
    }
    let mut x = a.to_vec();
    let mut y = b.to_vec();
    x.sort_by(|p, q| p.total_cmp(q));
    y.sort_by(|p, q| p.total_cmp(q));
    ks_two_sample_presorted(&x, &y)
}

/// Two-sample KS test of two sorted, non-empty samples: D, the effective size
/// n_e = n1 n2 / (n1 + n2) and the Kolmogorov p-value at n_e.
pub fn ks_two_sample_presorted(x: &[f64], y: &[f64]) -> TestOutcome {
    let (n1, n2) = (x.len(), y.len());
    let d = ks_two_sample_sorted(x, y);
    let ne = ((n1 as f64 * n2 as f64) / (n1 as f64 + n2 as f64)).round().max(1.0) as usize;
    let (p, method) = kolmogorov_sf(d, ne);
    TestOutcome {
        statistic: d,
        p_value: p,
        n: ne,
        method: format!("two-sample, n_e = {ne}: {method}"),
    }
}

/// Two-sample KS test of a small sorted sample `x` against a large unsorted one `y`, as
/// [`ks_two_sample_presorted`] but without sorting `y`: both empirical CDFs are
/// right-continuous steps, so D is the largest of |F_x - F_y| at each distinct value u of
/// `x` and just below it, and F_y(u) = #{y <= u}/n2, F_y(u-) = #{y < u}/n2 are counted
/// with two binary searches of each y among the distinct u. O(n2 log n1).
pub fn ks_two_sample_against_large(x: &[f64], y: &[f64]) -> TestOutcome {
    let (n1, n2) = (x.len(), y.len());
    if n1 == 0 || n2 == 0 {
        return ks_two_sample(x, y);
    }
    let mut u = x.to_vec();
    u.dedup();
    let k = u.len();
    // le_from[j]: the y whose first distinct value >= y is u_j (y <= u_i for every i >= j);
    // lt_from[j]: the y whose first distinct value > y is u_j (y < u_i for every i >= j).
    let (le_from, lt_from) = y
        .par_chunks(1 << 16)
        .map(|c| {
            let (mut le, mut lt) = (vec![0u64; k + 1], vec![0u64; k + 1]);
            for &v in c {
                le[u.partition_point(|&w| w < v)] += 1;
                lt[u.partition_point(|&w| w <= v)] += 1;
            }
            (le, lt)
        })
        .reduce(
            || (vec![0u64; k + 1], vec![0u64; k + 1]),
            |(mut a, mut b), (c, e)| {
                a.iter_mut().zip(&c).for_each(|(p, q)| *p += q);
                b.iter_mut().zip(&e).for_each(|(p, q)| *p += q);
                (a, b)
            },
        );
    let (nf1, nf2) = (n1 as f64, n2 as f64);
    let (mut y_le, mut y_lt, mut d) = (0u64, 0u64, 0.0f64);
    for (j, &uj) in u.iter().enumerate() {
        y_le += le_from[j];
        y_lt += lt_from[j];
        let x_lt = x.partition_point(|&w| w < uj);
        let x_le = x.partition_point(|&w| w <= uj);
        d = d
            .max((x_le as f64 / nf1 - y_le as f64 / nf2).abs())
            .max((x_lt as f64 / nf1 - y_lt as f64 / nf2).abs());
    }
    let ne = ((nf1 * nf2) / (nf1 + nf2)).round().max(1.0) as usize;
    let (p, method) = kolmogorov_sf(d, ne);
    TestOutcome {
        statistic: d,
        p_value: p,
        n: ne,
        method: format!("two-sample, n_e = {ne}: {method}"),
    }
}

/// D of two sorted samples.
pub fn ks_two_sample_sorted(x: &[f64], y: &[f64]) -> f64 {
    let (n1, n2) = (x.len() as f64, y.len() as f64);
    let (mut i, mut j) = (0, 0);
    let mut d = 0.0f64;
    while i < x.len() && j < y.len() {
        let v = x[i].min(y[j]);
        while i < x.len() && x[i] <= v {
            i += 1;
        }
        while j < y.len() && y[j] <= v {
            j += 1;
        }
        d = d.max((i as f64 / n1 - j as f64 / n2).abs());
    }
    d
}

/// P(D_n >= d), two-sided, and the name of the method used.
pub fn kolmogorov_sf(d: f64, n: usize) -> (f64, &'static str) {
    if n == 0 || d <= 0.0 {
        return (1.0, "trivial");
    }
    if d >= 1.0 {
        return (0.0, "trivial");
    }
    if n > EXACT_MAX_N {
        let sn = (n as f64).sqrt();
        return (
            kolmogorov_q((sn + 0.12 + 0.11 / sn) * d),
            "asymptotic Kolmogorov, Stephens (1970) correction",
        );
    }
    let tail = 2.0 * smirnov_sf(d, n);
    if tail < TAIL_SWITCH {
        return (tail, "exact tail: 2 x Birnbaum-Tingey one-sided");
    }
    (
        (1.0 - mtw_cdf(d, n)).clamp(0.0, 1.0),
        "exact (Marsaglia, Tsang & Wang 2003)",
    )
}

/// Q_KS(lambda) = 2 sum_{j>=1} (-1)^{j-1} exp(-2 j^2 lambda^2), the limiting P(sqrt(n) D > lambda).
/// For small lambda the dual (Jacobi theta) form
/// 1 - sqrt(2 pi)/lambda sum_{j>=1} exp(-(2j-1)^2 pi^2 / (8 lambda^2)) converges fast.
pub fn kolmogorov_q(lambda: f64) -> f64 {
    if lambda <= 0.0 {
        return 1.0;
    }
    if lambda < 1.0 {
        let pi2 = std::f64::consts::PI * std::f64::consts::PI;
        let mut s = 0.0;
        for j in 1..=20 {
            let k = (2 * j - 1) as f64;
            let t = (-k * k * pi2 / (8.0 * lambda * lambda)).exp();
            s += t;
            if t < 1e-18 * s {
                break;
            }
        }
        return (1.0 - (2.0 * std::f64::consts::PI).sqrt() / lambda * s).clamp(0.0, 1.0);
    }
    let mut s = 0.0;
    let mut sign = 1.0;
    for j in 1..=100 {
        let jf = j as f64;
        let t = (-2.0 * jf * jf * lambda * lambda).exp();
        s += sign * t;
        if t < 1e-18 * s.abs() {
            break;
        }
        sign = -sign;
    }
    (2.0 * s).clamp(0.0, 1.0)
}

/// P(D+_n >= d), exact (Birnbaum & Tingey 1951), summed in log space.
pub fn smirnov_sf(d: f64, n: usize) -> f64 {
    if d <= 0.0 {
        return 1.0;
    }
    if d >= 1.0 {
        return 0.0;
    }
    let nf = n as f64;
    let jmax = (nf * (1.0 - d)).floor() as usize;
    let ln_n_fact = ln_factorial(n);
    let mut sum = 0.0;
    for j in 0..=jmax {
        let a = d + j as f64 / nf;
        let b = 1.0 - a;
        if b <= 0.0 {
            // j/n = 1 - d exactly: the term is 0^(n-j) = 0 unless n = j (excluded since d > 0).
            continue;
        }
        let ln_term =
            ln_n_fact - ln_factorial(j) - ln_factorial(n - j) + (j as f64 - 1.0) * a.ln() + (nf - j as f64) * b.ln();
        sum += ln_term.exp();
    }
    (d * sum).clamp(0.0, 1.0)
}

fn ln_factorial(n: usize) -> f64 {
    statrs::function::gamma::ln_gamma(n as f64 + 1.0)
}

/// P(D_n < d), Marsaglia, Tsang & Wang (2003), without their right-tail shortcut.
fn mtw_cdf(d: f64, n: usize) -> f64 {
    let nf = n as f64;
    let k = (nf * d) as usize + 1;
    let m = 2 * k - 1;
    let h = k as f64 - nf * d;
    let mut hm = vec![0.0f64; m * m];
    for i in 0..m {
        for j in 0..m {
            if i + 1 >= j {
                hm[i * m + j] = 1.0;
            }
        }
    }
    for i in 0..m {
        hm[i * m] -= h.powi(i as i32 + 1);
        hm[(m - 1) * m + i] -= h.powi((m - i) as i32);
    }
    if 2.0 * h - 1.0 > 0.0 {
        hm[(m - 1) * m] += (2.0 * h - 1.0).powi(m as i32);
    }
    for i in 0..m {
        for j in 0..m {
            if i + 1 > j {
                for g in 1..=(i + 1 - j) {
                    hm[i * m + j] /= g as f64;
                }
            }
        }
    }
    let (q, mut eq) = matrix_power(&hm, 0, m, n);
    let mut s = q[(k - 1) * m + k - 1];
    for i in 1..=n {
        s = s * i as f64 / nf;
        if s < 1e-140 {
            s *= 1e140;
            eq -= 140;
        }
    }
    s * 10f64.powi(eq)
}

fn matrix_multiply(a: &[f64], b: &[f64], m: usize) -> Vec<f64> {
    let mut c = vec![0.0; m * m];
    for i in 0..m {
        for k in 0..m {
            let aik = a[i * m + k];
            if aik == 0.0 {
                continue;
            }
            let (row_b, row_c) = (&b[k * m..(k + 1) * m], &mut c[i * m..(i + 1) * m]);
            for (cj, bj) in row_c.iter_mut().zip(row_b) {
                *cj += aik * bj;
            }
        }
    }
    c
}

/// A^n with a decimal exponent kept aside against overflow (MTW's mPower).
fn matrix_power(a: &[f64], ea: i32, m: usize, n: usize) -> (Vec<f64>, i32) {
    if n == 1 {
        return (a.to_vec(), ea);
    }
    let (v, ev) = matrix_power(a, ea, m, n / 2);
    let b = matrix_multiply(&v, &v, m);
    let eb = 2 * ev;
    let (mut v, mut ev) = if n % 2 == 0 {
        (b, eb)
    } else {
        (matrix_multiply(a, &b, m), ea + eb)
    };
    if v[(m / 2) * m + m / 2] > 1e140 {
        for x in v.iter_mut() {
            *x *= 1e-140;
        }
        ev += 140;
    }
    (v, ev)
}
