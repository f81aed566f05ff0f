//! # Sample statistics: are the two disks of a binary aligned?
//!
//! ```text
//!  catalog ─▶ sample (both components pass P/sigma) ─▶ Delta-gamma values
//!                                                        │
//!   ┌─ one-sample KS and Kuiper vs uniform on [0, 90] ◀──┤
//!   ├─ exact binomial test of the fraction < 30 deg ◀────┤
//!   └─ two-sample KS vs the Monte Carlo ◀────────────────┘
//!         ▲
//!  mc: Pi(alpha) model ─▶ projection on the sky ─▶ (+ intrinsic P, ISM, noise, cut)
//!      ─▶ Pi(Delta gamma), seeded, chunked, identical for any thread count
//! ```
//!
//! Modules: [`rng`] (xoshiro256++ streams), [`model`] (Pi(alpha)), [`mc`] (the Monte
//! Carlo), [`hist`], [`ks`], [`kuiper`], [`binomial`], [`sample`] (catalog -> sample),
//! [`errors`] (Delta-gamma errors, convolution of predictions), [`alignment`] (tests + verdict), [`setup`] (the analysis of a catalog's sample as `sofipol stats` runs it), [`figures`] (the paper-style PNGs).
//! Conventions, methods and references: docs/statistics.md.
// `!(x > 0.0)` is used on purpose: it also rejects NaN. `n % k != 0` keeps the code
// within the workspace's rust-version (1.86; `is_multiple_of` is 1.87).
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::manual_is_multiple_of)]

use serde::{Deserialize, Serialize};

pub mod alignment;
pub mod binomial;
pub mod calibration;
pub mod errors;
pub mod figures;
pub mod foreground;
pub mod hist;
pub mod ks;
pub mod kuiper;
pub mod mc;
pub mod model;
pub mod predictions;
pub mod rng;
pub mod sample;
pub mod setup;

#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_errors;
#[cfg(test)]
mod tests_pvalues;

pub use alignment::{analyse, AlignmentReport, AnalysisParams, IsmComparison};
pub use binomial::{binomial_test, BinomialOutcome};
pub use hist::Histogram;
pub use ks::{ks_one_sample, ks_two_sample, ks_uniform};
pub use kuiper::{kuiper_one_sample, kuiper_uniform};
pub use mc::{simulate, simulate_samples, Ism, McConfig, McOutput, PIntDist, PofITable};
pub use model::{AlignmentModel, AlphaMeasure, AlphaTable};
pub use sample::BinarySample;

/// Errors of the statistics module (defined with the crate's other errors).
pub use crate::error::StatsError as Error;

/// Result of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// The text of a table file (a regular file of at most
/// [`sofipol_calib::input::MAX_OPTION_FILE_BYTES`]); the error names the file.
pub(crate) fn read_text(path: &std::path::Path) -> Result<String> {
    sofipol_calib::input::read_to_string(path, sofipol_calib::input::MAX_OPTION_FILE_BYTES).map_err(|e| Error::Io {
        path: path.to_path_buf(),
        source: e,
    })
}

/// Outcome of a goodness-of-fit test.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TestOutcome {
    /// The statistic (D for KS, V for Kuiper).
    pub statistic: f64,
    /// The p-value (probability of a statistic at least as large under the null).
    pub p_value: f64,
    /// Sample size used for the p-value (effective size for two-sample KS).
    pub n: usize,
    /// How the p-value was computed.
    pub method: String,
}

/// p-value as text: 4 decimals, or scientific below 1e-4; a p-value that came out 0 (the
/// distribution's tail below the smallest double) as `< 1e-300`, never "0.0e0", which reads
/// as a certainty the test cannot give.
pub fn format_p(p: f64) -> String {
    if p <= 0.0 {
        "< 1e-300".into()
    } else if p < 1e-4 {
        format!("{p:.1e}")
    } else {
        format!("{p:.4}")
    }
}
