//! The Monte Carlo of each observed binary with its own noise and its own foreground.
//!
//! Binary i of the sample was measured with its own errors (sigma_P of A and B) and passed
//! the cut P/sigma > K with them; it lies behind its own interstellar foreground. Its
//! prediction F_i is the distribution of the measured Delta gamma of random pairs simulated
//! with exactly that noise, that foreground and that cut, **conditional on passing the
//! cut**. The sample's prediction is the equal-weight mixture (1/n) sum_i F_i, and the
//! calibrated test is the one-sample KS of the probability transforms u_i = F_i(Delta
//! gamma_i), which are iid uniform under the null whatever the F_i (docs/statistics.md,
//! "Each binary's own noise and foreground").
//!
//! Determinism: binary i draws from its own seed (the run's seed, the prediction's
//! `stream` and i), in chunks of [`CHUNK_PAIRS`] with one stream per chunk; chunks and
//! binaries are concatenated in order, so the result is identical for any thread count.
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::kernel::Kernel;
use super::{ForegroundQu, McConfig, CHUNK_PAIRS};
use crate::stats::rng::mix64;
use crate::stats::{Error, Result};

/// A binary's simulation is extended (in steps of its first batch, at most
/// [`MAX_BATCHES`] batches) until at least this many pairs passed its cut.
pub const MIN_ACCEPTED: u64 = 2000;
/// Most batches of pairs simulated for one binary (see [`MIN_ACCEPTED`]).
pub const MAX_BATCHES: u64 = 20;
/// Fewest pairs simulated per binary, whatever the budget.
pub const MIN_PAIRS_PER_BINARY: u64 = 4000;

/// The Monte-Carlo set-up of one observed binary.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BinarySetup {
    /// Noise sigma of q and u of component A and B, percent (their measured sigma_P).
    pub noise_percent: [f64; 2],
    /// Its foreground.
    pub foreground: ForegroundQu,
}

/// The simulated Delta gamma of one binary: every accepted pair, in chunk order.
#[derive(Debug, Clone, PartialEq)]
pub struct BinarySim {
    /// Accepted Delta gamma, degrees in [0, 90].
    pub values: Vec<f64>,
    /// Pairs simulated.
    pub simulated: u64,
}

impl BinarySim {
    /// The empirical CDF at `x`, ties counted half: F(x-) + (F(x) - F(x-))/2. NaN when no
    /// pair passed.
    pub fn cdf_mid(&self, x: f64) -> f64 {
        let n = self.values.len();
        if n == 0 {
            return f64::NAN;
        }
        let below = self.values.iter().filter(|&&v| v < x).count();
        let equal = self.values.iter().filter(|&&v| v == x).count();
        (below as f64 + 0.5 * equal as f64) / n as f64
    }
}

/// The seed of binary `index` of prediction `stream` of a run seeded `seed`.
pub fn binary_seed(seed: u64, stream: u64, index: u64) -> u64 {
    mix64(mix64(seed ^ 0xB1A7_0F0E_5EED_0002) ^ stream) ^ mix64(index.wrapping_add(0x9E37_79B9_7F4A_7C15))
}

/// Pairs simulated per binary for a budget of `pairs` shared by `n` binaries: pairs / n,
/// at least [`MIN_PAIRS_PER_BINARY`].
pub fn pairs_per_binary(pairs: u64, n: usize) -> u64 {
    (pairs / n.max(1) as u64).max(MIN_PAIRS_PER_BINARY)
}

/// Simulate each binary of `binaries` with its own noise and foreground (the model, the
/// intrinsic P, the perpendicular fraction and the cut of `cfg`; its `ism` and
/// `noise_percent` are not used): `pairs` pairs each, extended batch by batch while fewer
/// than [`MIN_ACCEPTED`] passed the cut (at most [`MAX_BATCHES`] batches). `stream` tells
/// predictions apart. Identical for any rayon pool size.
pub fn simulate_per_binary(
    cfg: &McConfig,
    binaries: &[BinarySetup],
    pairs: u64,
    stream: u64,
) -> Result<Vec<BinarySim>> {
    cfg.validate()?;
    for (i, b) in binaries.iter().enumerate() {
        b.foreground.validate(&format!("binary {i}"))?;
        for s in b.noise_percent {
            if !(s >= 0.0 && s.is_finite()) {
                return Err(Error::InvalidParameter {
                    name: format!("binary {i}: noise (%)"),
                    value: s.to_string(),
                    reason: "must be finite and >= 0".into(),
                });
            }
        }
    }
    if pairs == 0 || pairs.saturating_mul(MAX_BATCHES) > super::MAX_SAMPLE_PAIRS {
        return Err(Error::InvalidParameter {
            name: "pairs per binary".into(),
            value: pairs.to_string(),
            reason: format!("must be in 1..={}", super::MAX_SAMPLE_PAIRS / MAX_BATCHES),
        });
    }
    binaries
        .par_iter()
        .enumerate()
        .map(|(i, b)| {
            let bcfg = McConfig {
                seed: binary_seed(cfg.seed, stream, i as u64),
                ..cfg.clone()
            };
            let fg = b.foreground;
            let kernel = Kernel::with(&bcfg, (fg.q_percent, fg.u_percent), fg.cholesky(), b.noise_percent);
            let per_batch = pairs.div_ceil(CHUNK_PAIRS);
            let mut values = Vec::new();
            let mut simulated = 0;
            for batch in 0..MAX_BATCHES {
                let parts: Vec<Vec<f64>> = (0..per_batch)
                    .into_par_iter()
                    .map(|k| {
                        let n = CHUNK_PAIRS.min(pairs - k * CHUNK_PAIRS);
                        let mut v = Vec::new();
                        kernel.run_chunk(batch * per_batch + k, n, &mut |dg| v.push(dg));
                        v
                    })
                    .collect();
                values.extend(parts.into_iter().flatten());
                simulated += pairs;
                if values.len() as u64 >= MIN_ACCEPTED {
                    break;
                }
            }
            Ok(BinarySim { values, simulated })
        })
        .collect()
}

/// The accepted Delta gamma of `n` pairs (at most [`CHUNK_PAIRS`]) of one binary drawn
/// from stream `seed` (no extension: fewer or none may pass its cut). Used to simulate
/// observed samples.
pub fn draw_pairs(cfg: &McConfig, b: &BinarySetup, n: u64, seed: u64) -> Vec<f64> {
    let bcfg = McConfig { seed, ..cfg.clone() };
    let fg = b.foreground;
    let kernel = Kernel::with(&bcfg, (fg.q_percent, fg.u_percent), fg.cholesky(), b.noise_percent);
    let mut v = Vec::new();
    kernel.run_chunk(0, n.min(CHUNK_PAIRS), &mut |dg| v.push(dg));
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::mc::{Ism, PIntDist};
    use crate::stats::model::AlignmentModel;

    fn cfg(seed: u64) -> McConfig {
        McConfig {
            p_int: PIntDist::parse("fixed:2").unwrap(),
            noise_percent: Some(0.5),
            snr_cut: Some(3.0),
            ..McConfig::geometry(AlignmentModel::Random, 1, seed)
        }
    }

    /// The same binary with equal noise and a fixed foreground is the ordinary Monte
    /// Carlo with that noise and ISM, pair for pair (same kernel, its own seed).
    #[test]
    fn a_binary_with_equal_noise_and_a_fixed_foreground_is_the_ordinary_monte_carlo() {
        let ism = Ism {
            p_percent: 1.0,
            angle_deg: 20.0,
        };
        let b = BinarySetup {
            noise_percent: [0.5; 2],
            foreground: ForegroundQu::fixed(ism),
        };
        let sims = simulate_per_binary(&cfg(7), &[b, b], 100_000, 3).unwrap();
        for (i, s) in sims.iter().enumerate() {
            let plain = McConfig {
                pairs: 100_000,
                seed: binary_seed(7, 3, i as u64),
                ism: Some(ism),
                ..cfg(7)
            };
            let (v, _) = super::super::simulate_samples(&plain).unwrap();
            assert_eq!(s.values, v);
            assert_eq!(s.simulated, 100_000);
        }
        assert_ne!(sims[0].values, sims[1].values);
    }

    /// A noisier component passes its cut less often: with P_int fixed at 2 % and no
    /// foreground, the measured P of a component is Rice(2 %, sigma); the acceptance of the
    /// pair is the product of the two Rice tails at 3 sigma_A and 3 sigma_B (quadrature).
    #[test]
    fn each_component_passes_its_own_cut() {
        let rice_tail = |nu: f64, s: f64, t: f64| {
            // P(R > t), R = |nu + s (z1, z2)|: 1 - integral_0^t of the Rice density.
            let steps = 20_000;
            let h = t / steps as f64;
            let pdf = |r: f64| {
                let x = r * nu / (s * s);
                // I0(x) e^{-x} by its series/asymptotic via statrs is not available: use the
                // integral I0(x) = (1/pi) int_0^pi e^{x cos th} dth, scaled.
                let m = 400;
                let i0s: f64 = (0..m)
                    .map(|k| {
                        let th = std::f64::consts::PI * (k as f64 + 0.5) / m as f64;
                        (x * (th.cos() - 1.0)).exp()
                    })
                    .sum::<f64>()
                    / m as f64;
                r / (s * s) * (-(r - nu) * (r - nu) / (2.0 * s * s)).exp() * i0s
            };
            1.0 - (0..steps).map(|k| pdf((k as f64 + 0.5) * h) * h).sum::<f64>()
        };
        let b = BinarySetup {
            noise_percent: [0.3, 0.6],
            foreground: ForegroundQu::NONE,
        };
        let pairs = 200_000;
        let s = &simulate_per_binary(&cfg(11), &[b], pairs, 0).unwrap()[0];
        let want = rice_tail(2.0, 0.3, 0.9) * rice_tail(2.0, 0.6, 1.8);
        let got = s.values.len() as f64 / pairs as f64;
        let se = (want * (1.0 - want) / pairs as f64).sqrt();
        assert!(
            (got - want).abs() < 4.0 * se,
            "acceptance {got} vs Rice {want} (se {se})"
        );
        // One sigma for both (the old treatment) would give a different acceptance.
        let same = rice_tail(2.0, 0.45, 1.35).powi(2);
        assert!((same - want).abs() > 20.0 * se, "{same} vs {want}");
    }

    /// A Gaussian foreground adds its covariance: with no intrinsic polarization the
    /// measured (q, u) of A is the foreground plus noise, so the angle of A follows the
    /// foreground's scatter. Checked through the pair: with P_int = 0, no noise and a
    /// foreground of covariance diag(v, v) about 0, both components see the same vector:
    /// Delta gamma is exactly 0 for every pair.
    #[test]
    fn the_foreground_is_common_to_both_components() {
        let b = BinarySetup {
            noise_percent: [0.0; 2],
            foreground: ForegroundQu {
                q_percent: 0.0,
                u_percent: 0.0,
                cov_percent2: [1.0, 0.3, 2.0],
            },
        };
        let c = McConfig {
            p_int: PIntDist::parse("fixed:0").unwrap(),
            noise_percent: None,
            snr_cut: None,
            ..cfg(1)
        };
        let s = &simulate_per_binary(&c, &[b], 10_000, 0).unwrap()[0];
        assert_eq!(s.values.len(), 10_000);
        assert!(s.values.iter().all(|&v| v == 0.0));
        // Cholesky reproduces the covariance.
        let [a, b2, d] = b.foreground.cholesky().unwrap();
        assert!((a * a - 1.0).abs() < 1e-12 && (a * b2 - 0.3).abs() < 1e-12 && (b2 * b2 + d * d - 2.0).abs() < 1e-12);
    }

    #[test]
    fn bad_foregrounds_are_refused_naming_the_binary_and_key() {
        for (fg, key) in [
            ([f64::NAN, 0.0, 0.0, 0.0, 0.0], "q, u"),
            ([0.1, 0.0, -1.0, 0.0, 1.0], "variances"),
            ([0.1, 0.0, 1.0, 2.0, 1.0], "cov_qu"),
        ] {
            let f = ForegroundQu {
                q_percent: fg[0],
                u_percent: fg[1],
                cov_percent2: [fg[2], fg[3], fg[4]],
            };
            let e = f.validate("HD 1").unwrap_err().to_string();
            assert!(e.contains("HD 1") && e.contains(key), "{e}");
        }
    }

    #[test]
    fn per_binary_results_are_identical_for_any_thread_count() {
        let bs: Vec<BinarySetup> = (0..5)
            .map(|i| BinarySetup {
                noise_percent: [0.1 + 0.3 * i as f64, 0.2],
                foreground: ForegroundQu {
                    q_percent: 0.5,
                    u_percent: -0.2,
                    cov_percent2: [0.04, 0.0, 0.04],
                },
            })
            .collect();
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| simulate_per_binary(&cfg(5), &bs, 70_000, 1).unwrap())
        };
        assert_eq!(run(1), run(2));
    }
}
