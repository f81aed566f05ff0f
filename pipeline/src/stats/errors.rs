//! Measurement errors of Delta gamma, and model predictions convolved with them.
//!
//! A model predicts the true Delta gamma of a pair; what is observed is that angle plus the
//! measurement error of gamma_A - gamma_B, folded back into [0, 90] deg. The convolution
//! here does the same to every simulated pair: it draws an error sigma from the observed
//! binaries' sigma_delta_gamma (uniformly, one per pair), adds a Gaussian angle error of
//! that sigma and folds:
//!
//! ```text
//!     Delta gamma' = fold(Delta gamma + sigma_j z),   z ~ N(0, 1),  j uniform in 1..n
//!     fold(x) = min(x mod 180, 180 - x mod 180)
//! ```
//!
//! Adding the error to the folded value is the same in distribution as adding it to
//! gamma_A - gamma_B before folding (the error is symmetric). Two exact properties, tested:
//! a uniform Delta gamma stays uniform (random orientation is unchanged by any angle
//! error), and a point mass at 0 becomes the half-normal of sigma (for sigma << 90 deg).
//!
//! Determinism: values are cut into chunks of [`CHUNK_PAIRS`]; chunk i draws from its own
//! stream, so the result is identical for any number of threads.
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::rng::{mix64, Xoshiro256pp, CHUNK_PAIRS};
use crate::catalog::fold_delta_gamma;

/// A binary whose Delta-gamma error is larger than this (deg) is listed as a large error.
pub const LARGE_SIGMA_DEG: f64 = 20.0;
/// A binary whose 68.27 % interval is wider than this (deg) is listed as a large error.
pub const LARGE_INTERVAL_DEG: f64 = 40.0;

/// Where a binary's Delta-gamma error comes from (best first).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorSource {
    /// The catalog's `sigma_delta_gamma_deg` (delta method, both components together).
    Propagated,
    /// The components' `sigma_gamma_stat_deg` in quadrature (measurement only).
    ComponentStat,
    /// The components' `sigma_gamma_deg` in quadrature: includes the calibration zero-point,
    /// which is common to both components and cancels in Delta gamma, so it overestimates.
    ComponentTotal,
}

/// A binary with a large Delta-gamma error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LargeError {
    /// Object name.
    pub object: String,
    /// Delta gamma, deg.
    pub delta_gamma_deg: f64,
    /// 1-sigma error, deg.
    pub sigma_deg: Option<f64>,
    /// Central 68.27 % interval, deg.
    pub interval_deg: Option<[f64; 2]>,
}

/// The Delta-gamma errors of a sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct SampleErrors {
    /// The 1-sigma errors of the binaries that have one, deg (sample order): what the
    /// model predictions are convolved with.
    pub sigmas_deg: Vec<f64>,
    /// Binaries without any error.
    pub n_without_error: usize,
    /// Binaries whose error is the catalog's `sigma_delta_gamma_deg`.
    pub n_propagated: usize,
    /// Binaries whose error is the components' statistical angle errors in quadrature.
    pub n_component_stat: usize,
    /// Binaries whose error is the components' total angle errors in quadrature
    /// (overestimates: includes the common zero-point).
    pub n_component_total: usize,
    /// Binaries with sigma > [`LARGE_SIGMA_DEG`] or an interval wider than
    /// [`LARGE_INTERVAL_DEG`].
    pub large: Vec<LargeError>,
}

impl SampleErrors {
    /// Median of the errors, deg.
    pub fn median_deg(&self) -> Option<f64> {
        crate::numeric::median_finite(&self.sigmas_deg)
    }

    /// Largest error, deg.
    pub fn max_deg(&self) -> Option<f64> {
        self.sigmas_deg.iter().cloned().reduce(f64::max)
    }

    /// True when at least one binary has an error (the predictions can be convolved).
    pub fn any(&self) -> bool {
        !self.sigmas_deg.is_empty()
    }
}

/// True when the binary's error or interval is large enough to be listed.
pub fn is_large(sigma_deg: Option<f64>, interval_deg: Option<[f64; 2]>) -> bool {
    sigma_deg.is_some_and(|s| s > LARGE_SIGMA_DEG) || interval_deg.is_some_and(|[lo, hi]| hi - lo > LARGE_INTERVAL_DEG)
}

/// Fold an angle difference (deg, any real value) into [0, 90]: axial angles.
#[inline]
pub fn fold_deg(x: f64) -> f64 {
    fold_delta_gamma(x, 0.0)
}

/// The RNG seed of the convolution of prediction number `which` of a run seeded `seed`
/// (kept apart from the streams of the Monte Carlo itself).
pub fn convolution_seed(seed: u64, which: u64) -> u64 {
    mix64(seed ^ 0xC0A7_E11A_5EED_0001) ^ which
}

/// `values` (deg in [0, 90]) each with a Gaussian angle error of a sigma drawn uniformly
/// from `sigmas_deg`, folded back into [0, 90]. An empty `sigmas_deg` returns the values
/// unchanged. Identical for any rayon pool size.
pub fn convolve_with_errors(values: &[f64], sigmas_deg: &[f64], seed: u64) -> Vec<f64> {
    let mut out = values.to_vec();
    if sigmas_deg.is_empty() {
        return out;
    }
    let n_sigma = sigmas_deg.len() as u64;
    out.par_chunks_mut(CHUNK_PAIRS as usize)
        .enumerate()
        .for_each(|(chunk, vals)| {
            let mut rng = Xoshiro256pp::for_stream(seed, chunk as u64);
            for pair in vals.chunks_mut(2) {
                let (z0, z1) = rng.normal_pair();
                for (v, z) in pair.iter_mut().zip([z0, z1]) {
                    let sigma = sigmas_deg[rng.below(n_sigma) as usize];
                    *v = fold_deg(*v + sigma * z);
                }
            }
        });
    out
}

/// Exact CDF of fold(mu + sigma z), z ~ N(0, 1): the distribution of the measured Delta
/// gamma of a pair whose true value is `mu`, at `x` in [0, 90] deg. Sum over the images of
/// [-x, x] modulo 180: P = sum_k [Phi((x - mu + 180 k)/sigma) - Phi((-x - mu + 180 k)/sigma)].
pub fn folded_normal_cdf(x: f64, mu: f64, sigma: f64) -> f64 {
    if sigma <= 0.0 {
        return if fold_deg(mu) <= x { 1.0 } else { 0.0 };
    }
    let phi = |t: f64| 0.5 * (1.0 + statrs::function::erf::erf(t / std::f64::consts::SQRT_2));
    let reach = (10.0 * sigma / 180.0).ceil() as i64 + 1;
    (-reach..=reach)
        .map(|k| {
            let c = 180.0 * k as f64;
            phi((x - mu + c) / sigma) - phi((-x - mu + c) / sigma)
        })
        .sum()
}
