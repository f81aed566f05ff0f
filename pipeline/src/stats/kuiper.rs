//! Kuiper's test (V = D+ + D-), which statrs does not provide.
//!
//! p-value for n <= [`EXACT_MAX_N`]: exact ([`kuiper_cdf_exact`], derivation in
//! docs/statistics.md): rotating the circle so that the minimum of F_n(x) - x falls on a
//! data point turns P(V_n <= v) into n times a rectangle probability of n - 1 uniform
//! order statistics, summed over the counts of points between breakpoints (positive
//! terms only, no cancellation).
//!
//! p-value above that: the asymptotic distribution with Stephens' (1970) finite-n correction,
//! P(V > v) ~= Q_KP(lambda), lambda = (sqrt n + 0.155 + 0.24/sqrt n) v
//! (Stephens 1970, JRSS B 32, 115; Numerical Recipes 3rd ed., 14.3.4), where
//!
//!   Q_KP(lambda) = 2 sum_{j>=1} (4 j^2 lambda^2 - 1) exp(-2 j^2 lambda^2).
//!
//! That series converges quickly only for lambda >~ 1 and is useless at small lambda
//! (alternating large terms; Q -> 1). Poisson summation gives the dual form used below
//! lambda = 1 (derivation in docs/statistics.md):
//!
//!   1 - Q_KP(lambda) = (sqrt(2 pi) pi^2 / lambda^3) sum_{m>=1} m^2 exp(-pi^2 m^2 / (2 lambda^2)),
//!
//! which converges fast there. Both are accurate to double precision in their ranges and
//! agree at the switch (tested).
use super::TestOutcome;

/// Kuiper test of `data` against a continuous CDF.
pub fn kuiper_one_sample(data: &[f64], cdf: impl Fn(f64) -> f64) -> TestOutcome {
    let (_, dp, dm) = super::ks::ks_statistics(data, &cdf);
    let v = dp + dm;
    let n = data.len();
    let (p, method) = kuiper_p(v, n);
    TestOutcome {
        statistic: v,
        p_value: p,
        n,
        method: method.into(),
    }
}

/// Largest n for which the p-value is computed exactly (cost ~ n^3 / 2 flops, 1 ms at 100).
pub const EXACT_MAX_N: usize = 200;

/// Method string of the exact p-value (also in the JSON of `sofipol stats`).
pub const METHOD_EXACT: &str = "exact (finite-n distribution of V_n: rotation to the minimum of F_n(x) - x and the \
     rectangle probability of n - 1 uniform order statistics; absolute error < 1e-13)";
/// Method string of the asymptotic p-value.
pub const METHOD_STEPHENS: &str = "asymptotic Q_KP with Stephens (1970) correction (n > 200)";

/// P(V_n >= v) and the method used: exact for n <= [`EXACT_MAX_N`], Stephens above.
pub fn kuiper_p(v: f64, n: usize) -> (f64, &'static str) {
    if n <= EXACT_MAX_N {
        ((1.0 - kuiper_cdf_exact(v, n)).clamp(0.0, 1.0), METHOD_EXACT)
    } else {
        (kuiper_sf(v, n), METHOD_STEPHENS)
    }
}

/// Exact P(V_n <= v) for n iid uniform points (any n, cost O(n^3); meant for n <= 200).
///
/// V is invariant under rotations of the circle, and rotating to the data point after
/// which W_i = i/n - U_(i) is smallest makes that point 0 and its W = 1/n the minimum.
/// Of the n rotations to a data point exactly one has this property, so with
/// z_1 < ... < z_{n-1} the order statistics of n - 1 iid uniforms (the other points):
///
///   P(V_n <= v) = n P( max(0, (k+1)/n - v) <= z_k <= k/n, k = 1 ... n-1 ).
///
/// The rectangle probability is computed on the sorted breakpoints c_j of all bounds:
/// N(c) = #{z <= c} must satisfy #{k: b_k <= c} <= N(c) <= #{k: a_k < c}; the number of
/// points in (c_{j-1}, c_j] given N(c_{j-1}) is binomial(m - N, dc / (1 - c_{j-1})).
pub fn kuiper_cdf_exact(v: f64, n: usize) -> f64 {
    if n == 0 {
        return 1.0;
    }
    let nf = n as f64;
    if !(v >= 1.0 / nf) {
        return 0.0;
    }
    if v >= 1.0 {
        return 1.0;
    }
    let m = n - 1;
    let a: Vec<f64> = (1..=m).map(|k| ((k + 1) as f64 / nf - v).max(0.0)).collect();
    let b: Vec<f64> = (1..=m).map(|k| k as f64 / nf).collect();
    if a.iter().zip(&b).any(|(lo, hi)| lo > hi) {
        return 0.0;
    }
    let mut cuts: Vec<f64> = a
        .iter()
        .chain(b.iter())
        .copied()
        .chain([1.0])
        .filter(|&c| c > 0.0)
        .collect();
    cuts.sort_by(f64::total_cmp);
    cuts.dedup();
    // ln k! for the binomial coefficients.
    let mut lnfact = vec![0.0f64; m + 1];
    for k in 1..=m {
        lnfact[k] = lnfact[k - 1] + (k as f64).ln();
    }
    // f[c] = P(N(current breakpoint) = c and all constraints so far).
    let mut f = vec![0.0f64; m + 1];
    f[0] = 1.0;
    let mut g = vec![0.0f64; m + 1];
    let mut prev = 0.0f64;
    for &c in &cuts {
        let rest = 1.0 - prev;
        let p = if rest > 0.0 {
            ((c - prev) / rest).clamp(0.0, 1.0)
        } else {
            1.0
        };
        g.iter_mut().for_each(|x| *x = 0.0);
        let (lp, lq) = (p.ln(), (1.0 - p).ln());
        for (c0, &w) in f.iter().enumerate() {
            if w == 0.0 {
                continue;
            }
            let left = m - c0;
            if p >= 1.0 {
                g[m] += w;
                continue;
            }
            if p <= 0.0 {
                g[c0] += w;
                continue;
            }
            for k in 0..=left {
                let ln_pmf = lnfact[left] - lnfact[k] - lnfact[left - k] + k as f64 * lp + (left - k) as f64 * lq;
                g[c0 + k] += w * ln_pmf.exp();
            }
        }
        let lower = b.iter().filter(|&&x| x <= c).count();
        let upper = a.iter().filter(|&&x| x < c).count();
        for (cnt, x) in g.iter_mut().enumerate() {
            if cnt < lower || cnt > upper {
                *x = 0.0;
            }
        }
        std::mem::swap(&mut f, &mut g);
        prev = c;
    }
    (nf * f[m]).clamp(0.0, 1.0)
}

/// Kuiper test against the uniform distribution on [lo, hi].
pub fn kuiper_uniform(data: &[f64], lo: f64, hi: f64) -> TestOutcome {
    kuiper_one_sample(data, |x| ((x - lo) / (hi - lo)).clamp(0.0, 1.0))
}

/// P(V_n >= v) with Stephens' correction.
pub fn kuiper_sf(v: f64, n: usize) -> f64 {
    if n == 0 || v <= 0.0 {
        return 1.0;
    }
    let sn = (n as f64).sqrt();
    kuiper_q((sn + 0.155 + 0.24 / sn) * v)
}

/// The asymptotic Kuiper tail Q_KP(lambda).
pub fn kuiper_q(lambda: f64) -> f64 {
    if lambda <= 0.0 {
        return 1.0;
    }
    if lambda < 1.0 {
        1.0 - kuiper_cdf_dual(lambda)
    } else {
        kuiper_q_series(lambda)
    }
}

/// 2 sum (4 j^2 l^2 - 1) exp(-2 j^2 l^2), summed until the terms vanish.
fn kuiper_q_series(lambda: f64) -> f64 {
    let l2 = lambda * lambda;
    let mut s = 0.0;
    for j in 1..=200 {
        let j2 = (j * j) as f64;
        let t = (4.0 * j2 * l2 - 1.0) * (-2.0 * j2 * l2).exp();
        s += t;
        if t.abs() <= 1e-17 * s.abs() || t == 0.0 {
            break;
        }
    }
    (2.0 * s).clamp(0.0, 1.0)
}

/// (sqrt(2 pi) pi^2 / l^3) sum m^2 exp(-pi^2 m^2 / (2 l^2)).
fn kuiper_cdf_dual(lambda: f64) -> f64 {
    use std::f64::consts::PI;
    let c = PI * PI / (2.0 * lambda * lambda);
    let mut s = 0.0;
    for m in 1..=200 {
        let m2 = (m * m) as f64;
        let t = m2 * (-c * m2).exp();
        s += t;
        if t <= 1e-17 * s || t == 0.0 {
            break;
        }
    }
    ((2.0 * PI).sqrt() * PI * PI / (lambda * lambda * lambda) * s).clamp(0.0, 1.0)
}

#[cfg(test)]
pub(crate) fn kuiper_q_series_for_tests(lambda: f64) -> f64 {
    kuiper_q_series(lambda)
}

#[cfg(test)]
pub(crate) fn kuiper_cdf_dual_for_tests(lambda: f64) -> f64 {
    kuiper_cdf_dual(lambda)
}
