//! The projection / interstellar-polarization Monte Carlo of Pi(Delta gamma).
//!
//! One pair: the first spin axis n1 is isotropic; the second is drawn from the alignment
//! model (Pi(alpha) about n1 with a uniform azimuth, or independently for random pairs);
//! both are projected on the sky (line of sight z, sky axes x = north, y = east).
//!
//! * Geometry only (no ISM, no noise): Delta gamma is the angle between the two projected
//!   axes as lines, atan2(|v1 x v2|, |v1 . v2|), in [0, 90] deg: one atan2, no other trig.
//! * With ISM and/or noise: each component gets an intrinsic (q, u) = P_int (cos 2g, sin 2g)
//!   with g = PA(projected spin axis) + 90 deg (polarization along the long axis of the
//!   projected disk, the reference study's convention), computed without trigonometry as
//!   cos 2g = -(x^2 - y^2)/r^2, sin 2g = -2xy/r^2; then (q_ism, u_ism) is added to both,
//!   then independent Gaussian noise of sigma to each q and u; optionally both components
//!   must pass P / sigma > cut; Delta gamma = half the angle between the (q, u) vectors.
//!
//! Only the effects the configuration asks for are simulated.
//!
//! Determinism: the pairs are split into chunks of [`CHUNK_PAIRS`]; chunk i draws from its
//! own generator `Xoshiro256pp::for_stream(seed, i)` and fills its own integer histogram;
//! chunk histograms are summed (integer sums do not depend on order), and samples are
//! concatenated in chunk order. The result is bit-identical for any number of threads.
//!
//! Files: [`p_int`] (distributions of the intrinsic P), [`pofi`] (P(i) tables),
//! [`per_binary`] (each observed binary with its own noise and foreground), `kernel`
//! (one pair: axes, projection, polarization, cut, Delta gamma); this file holds the
//! configuration, the chunking and the drivers [`simulate`] and [`simulate_samples`].
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::hist::Histogram;
use super::model::AlignmentModel;
use super::{Error, Result};

mod kernel;
pub mod p_int;
pub mod per_binary;
pub mod pofi;

pub use super::rng::CHUNK_PAIRS;
/// The foreground types, defined in [`crate::stats::foreground`] (the sample reads them too).
pub use crate::stats::foreground::{ForegroundQu, Ism};
use kernel::Kernel;
#[cfg(test)]
pub(crate) use kernel::{delta_gamma_axes, delta_gamma_qu, intrinsic_qu};
pub use p_int::PIntDist;
pub use per_binary::{simulate_per_binary, BinarySetup, BinarySim};
pub use pofi::PofITable;

/// Default number of pairs (the reference study used 10^7).
pub const DEFAULT_PAIRS: u64 = 10_000_000;
/// Most pairs of one run (about 100 CPU-seconds per 10^9 pairs; the reference study used
/// 10^7). More is refused by name before anything is allocated.
pub const MAX_PAIRS: u64 = 10_000_000_000;
/// Most Delta-gamma bins on [0, 90] deg (0.01 deg each).
pub const MAX_BINS: usize = 9000;
/// Chunks simulated in parallel before their results are added (in chunk order): bounds the
/// memory of a run by `BATCH_CHUNKS` histograms whatever the number of pairs.
const BATCH_CHUNKS: u64 = 1024;
/// Most pairs [`simulate_samples`] keeps in memory (800 MB).
pub const MAX_SAMPLE_PAIRS: u64 = 100_000_000;
/// Default seed.
pub const DEFAULT_SEED: u64 = 20010101;
/// Default number of Delta-gamma bins on [0, 90] deg (1 deg each).
pub const DEFAULT_BINS: usize = 90;
/// The interstellar polarization degrees of the reference study's figure, percent.
pub const PAPER_ISM_LEVELS_PERCENT: [f64; 10] = [0.1, 0.2, 0.4, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0];
/// Default intrinsic-polarization model of `sofipol mc`: P = 6 % sin^2 i.
pub const DEFAULT_P_INT: &str = "sin2i:6";

/// A validated Monte-Carlo configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct McConfig {
    /// Pi(alpha).
    pub model: AlignmentModel,
    /// Number of simulated pairs.
    pub pairs: u64,
    /// Seed.
    pub seed: u64,
    /// Number of Delta-gamma bins on [0, 90] deg.
    pub bins: usize,
    /// Intrinsic polarization degrees (used only with ISM or noise).
    pub p_int: PIntDist,
    /// Interstellar polarization, if any.
    pub ism: Option<Ism>,
    /// Gaussian measurement noise sigma of q and u of each component, percent, if any.
    pub noise_percent: Option<f64>,
    /// Keep a pair only when both measured P / sigma exceed this (needs noise).
    pub snr_cut: Option<f64>,
    /// Fraction of disks polarized **perpendicular** to the long axis of their projection
    /// (polarization angle rotated by 90 deg: edge-on, multiple-scattering disks), drawn
    /// independently for component A (`[0]`) and B (`[1]`); the CLI sets both to
    /// `--perpendicular-fraction`. 0 and 1 draw no random number.
    pub perpendicular_fraction: [f64; 2],
}

impl McConfig {
    /// Geometry-only configuration with the defaults.
    pub fn geometry(model: AlignmentModel, pairs: u64, seed: u64) -> Self {
        Self {
            model,
            pairs,
            seed,
            bins: DEFAULT_BINS,
            p_int: PIntDist::Sin2i { p_max_percent: 6.0 },
            ism: None,
            noise_percent: None,
            snr_cut: None,
            perpendicular_fraction: [0.0; 2],
        }
    }

    /// Check every parameter (the Monte Carlo refuses an invalid configuration).
    pub fn validate(&self) -> Result<()> {
        let bad = |name: &str, value: String, reason: &str| {
            Err(Error::InvalidParameter {
                name: name.into(),
                value,
                reason: reason.into(),
            })
        };
        self.model.validate()?;
        self.p_int.validate()?;
        if self.pairs == 0 || self.pairs > MAX_PAIRS {
            return bad("pairs", self.pairs.to_string(), "must be in 1..=1e10");
        }
        if self.bins == 0 || self.bins > MAX_BINS {
            return bad("bins", self.bins.to_string(), "must be in 1..=9000");
        }
        if let Some(ism) = self.ism {
            if !(ism.p_percent >= 0.0 && ism.p_percent.is_finite()) {
                return bad("p-ism (%)", ism.p_percent.to_string(), "must be >= 0");
            }
            if !ism.angle_deg.is_finite() {
                return bad("ism-angle (deg)", ism.angle_deg.to_string(), "must be finite");
            }
        }
        for f in self.perpendicular_fraction {
            if !(0.0..=1.0).contains(&f) {
                return bad("perpendicular-fraction", f.to_string(), "must be in [0, 1]");
            }
        }
        if let Some(s) = self.noise_percent {
            if !(s >= 0.0 && s.is_finite()) {
                return bad("noise (%)", s.to_string(), "must be >= 0");
            }
        }
        if let Some(k) = self.snr_cut {
            if !(k >= 0.0 && k.is_finite()) {
                return bad("snr-cut", k.to_string(), "must be >= 0");
            }
            if !matches!(self.noise_percent, Some(s) if s > 0.0) {
                return bad("snr-cut", k.to_string(), "a P/sigma cut needs --noise > 0");
            }
        }
        Ok(())
    }

    /// True when the polarization (not only the geometry) has to be simulated.
    pub fn simulates_polarization(&self) -> bool {
        self.ism.is_some() || self.noise_percent.is_some()
    }
}

/// Result of a Monte-Carlo run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct McOutput {
    /// Pi(Delta gamma) counts on [0, 90] deg.
    pub histogram: Histogram,
    /// Pairs simulated.
    pub simulated: u64,
    /// Pairs that passed the P/sigma cut (all of them without a cut).
    pub accepted: u64,
    /// Mean Delta gamma of the accepted pairs (deg), from the pairs themselves (not bin
    /// centres); per-chunk sums added in chunk order, so independent of the thread count.
    pub mean_delta_gamma_deg: f64,
}

fn chunks(pairs: u64) -> Vec<(u64, u64)> {
    let n = pairs.div_ceil(CHUNK_PAIRS);
    (0..n).map(|i| (i, CHUNK_PAIRS.min(pairs - i * CHUNK_PAIRS))).collect()
}

/// Run the Monte Carlo and return the Pi(Delta gamma) histogram. Uses the current rayon
/// pool; the result does not depend on its size.
pub fn simulate(cfg: &McConfig) -> Result<McOutput> {
    simulate_with_progress(cfg, &|_| {})
}

/// [`simulate`], calling `progress(n)` from the worker threads each time a chunk of `n`
/// pairs is done (for a progress bar; the result is the same).
pub fn simulate_with_progress(cfg: &McConfig, progress: &(dyn Fn(u64) + Sync)) -> Result<McOutput> {
    cfg.validate()?;
    let kernel = Kernel::new(cfg);
    let bins = cfg.bins;
    let inv_width = bins as f64 / 90.0;
    let (mut counts, mut accepted, mut sum) = (vec![0u64; bins], 0u64, 0.0f64);
    let n_chunks = cfg.pairs.div_ceil(CHUNK_PAIRS);
    let mut first = 0;
    while first < n_chunks {
        let last = n_chunks.min(first + BATCH_CHUNKS);
        let parts: Vec<(Vec<u64>, u64, f64)> = (first..last)
            .into_par_iter()
            .map(|chunk| {
                let n = CHUNK_PAIRS.min(cfg.pairs - chunk * CHUNK_PAIRS);
                let mut counts = vec![0u64; bins];
                let mut sum = 0.0;
                let accepted = kernel.run_chunk(chunk, n, &mut |dg| {
                    counts[((dg * inv_width) as usize).min(bins - 1)] += 1;
                    sum += dg;
                });
                progress(n);
                (counts, accepted, sum)
            })
            .collect();
        // In chunk order: the float sum does not depend on the thread count.
        for (c, a, s) in parts {
            for (x, y) in counts.iter_mut().zip(&c) {
                *x += *y;
            }
            accepted += a;
            sum += s;
        }
        first = last;
    }
    Ok(McOutput {
        histogram: Histogram {
            lo: 0.0,
            hi: 90.0,
            counts,
        },
        simulated: cfg.pairs,
        accepted,
        mean_delta_gamma_deg: if accepted > 0 { sum / accepted as f64 } else { f64::NAN },
    })
}

/// Run the Monte Carlo and also return every accepted Delta gamma (degrees) in a fixed
/// order (chunk by chunk), for two-sample tests. Memory: 8 bytes per pair, so at most
/// [`MAX_SAMPLE_PAIRS`] pairs (refused above, before allocating; the histogram of
/// [`simulate`] has no such limit).
pub fn simulate_samples(cfg: &McConfig) -> Result<(Vec<f64>, McOutput)> {
    cfg.validate()?;
    if cfg.pairs > MAX_SAMPLE_PAIRS {
        return Err(Error::InvalidParameter {
            name: "pairs".into(),
            value: cfg.pairs.to_string(),
            reason: format!(
                "a two-sample test keeps every simulated Delta gamma (8 bytes each): at most {MAX_SAMPLE_PAIRS} pairs"
            ),
        });
    }
    let kernel = Kernel::new(cfg);
    let parts: Vec<Vec<f64>> = chunks(cfg.pairs)
        .into_par_iter()
        .map(|(chunk, n)| {
            let mut v = Vec::with_capacity(n as usize);
            kernel.run_chunk(chunk, n, &mut |dg| v.push(dg));
            v
        })
        .collect();
    let samples: Vec<f64> = parts.concat();
    let (histogram, _) = Histogram::from_values(0.0, 90.0, cfg.bins, &samples);
    let accepted = samples.len() as u64;
    let mean_delta_gamma_deg = parts_mean(&samples);
    Ok((
        samples,
        McOutput {
            histogram,
            simulated: cfg.pairs,
            accepted,
            mean_delta_gamma_deg,
        },
    ))
}

fn parts_mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

#[cfg(test)]
mod hard_case_tests {
    use super::*;

    #[test]
    fn a_billion_pairs_are_counted_exactly_and_samples_refused_before_allocating() {
        // 10^9 pairs: the chunking covers every pair once (u64 throughout), without
        // running 10^9 draws; `simulate_samples` (8 GB) refuses before allocating.
        let pairs = 1_000_000_000u64;
        let c = chunks(pairs);
        assert_eq!(c.len() as u64, pairs.div_ceil(CHUNK_PAIRS));
        assert_eq!(c.iter().map(|&(_, n)| n).sum::<u64>(), pairs);
        assert!(c
            .iter()
            .enumerate()
            .all(|(i, &(k, n))| k == i as u64 && (1..=CHUNK_PAIRS).contains(&n)));
        assert_eq!(c.last().unwrap().1, pairs - (c.len() as u64 - 1) * CHUNK_PAIRS);
        let cfg = McConfig::geometry(AlignmentModel::Random, pairs, 1);
        let e = simulate_samples(&cfg).unwrap_err().to_string();
        assert!(e.contains("pairs") && e.contains("1000000000"), "{e}");
    }

    #[test]
    fn progress_reports_every_pair_once_and_does_not_change_the_result() {
        // 3.5 chunks: the last chunk is partial.
        let pairs = 3 * CHUNK_PAIRS + CHUNK_PAIRS / 2;
        let cfg = McConfig::geometry(AlignmentModel::Random, pairs, 5);
        let done = std::sync::atomic::AtomicU64::new(0);
        let calls = std::sync::atomic::AtomicU64::new(0);
        let out = simulate_with_progress(&cfg, &|n| {
            done.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
            calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        })
        .unwrap();
        assert_eq!(done.into_inner(), pairs);
        assert_eq!(calls.into_inner(), 4);
        assert_eq!(out, simulate(&cfg).unwrap());
    }
}
