//! Exact binomial test (e.g. of the fraction of binaries with Delta gamma < 30 deg, whose
//! probability under random orientation is 30/90 = 1/3).
use serde::{Deserialize, Serialize};

/// Outcome of an exact binomial test.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BinomialOutcome {
    /// Successes.
    pub k: u64,
    /// Trials.
    pub n: u64,
    /// Success probability under the null hypothesis.
    pub p0: f64,
    /// One-sided p-value P(X >= k) (alternative: probability > p0, i.e. alignment).
    pub p_greater: f64,
    /// Two-sided p-value: sum of P(X = i) over all i with P(X = i) <= P(X = k) (the
    /// "minimum likelihood" rule of scipy.stats.binomtest, relative tolerance 1e-7).
    pub p_two_sided: f64,
}

/// ln P(X = i) for X ~ Binomial(n, p).
fn ln_pmf(i: u64, n: u64, p: f64) -> f64 {
    use statrs::function::gamma::ln_gamma;
    let lc = ln_gamma(n as f64 + 1.0) - ln_gamma(i as f64 + 1.0) - ln_gamma((n - i) as f64 + 1.0);
    let a = if i == 0 { 0.0 } else { i as f64 * p.ln() };
    let b = if i == n { 0.0 } else { (n - i) as f64 * (-p).ln_1p() };
    lc + a + b
}

/// Exact binomial test of k successes in n trials against p0 (0 < p0 < 1, k <= n).
pub fn binomial_test(k: u64, n: u64, p0: f64) -> BinomialOutcome {
    assert!(
        k <= n && p0 > 0.0 && p0 < 1.0,
        "binomial test needs k <= n and 0 < p0 < 1"
    );
    let pmf: Vec<f64> = (0..=n).map(|i| ln_pmf(i, n, p0).exp()).collect();
    let p_greater: f64 = pmf[k as usize..].iter().sum::<f64>().min(1.0);
    let d = pmf[k as usize];
    let p_two_sided: f64 = pmf.iter().filter(|&&x| x <= d * (1.0 + 1e-7)).sum::<f64>().min(1.0);
    BinomialOutcome {
        k,
        n,
        p0,
        p_greater,
        p_two_sided,
    }
}
