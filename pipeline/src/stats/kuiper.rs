//! Kuiper's test (V = D+ + D-), which statrs does not provide.
//!
//! p-value: the asymptotic distribution with Stephens' (1970) finite-n correction,
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
    let p = kuiper_sf(v, n);
    TestOutcome {
        statistic: v,
        p_value: p,
        n,
        method: "asymptotic Q_KP with Stephens (1970) correction".into(),
    }
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
