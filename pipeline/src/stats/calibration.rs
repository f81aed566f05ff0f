//! Calibration of the random disks + ISM p-values under their own null: many simulated
//! observed samples whose binaries are **randomly oriented** behind a known foreground and
//! measured with their own errors, each tested as `sofipol stats` tests a catalog, with the
//! one-median-noise treatment and with the per-binary treatment. A calibrated test gives
//! p-values uniform on [0, 1] over the samples (docs/statistics.md, "Calibration of the
//! p-values").
//!
//! One simulated sample: targets are drawn one after another, each with a noise sigma_P of
//! its components log-uniform in `sigma_range_percent` (A and B within a factor
//! `exp(+-0.2)` of the target's level), random disk orientations, intrinsic P from
//! `p_int`, the foreground `ism`, Gaussian (q, u) noise and the cut P/sigma > `snr_cut` on
//! both components, until `binaries` of them pass. The failed targets' sigma_P count in
//! the median of the old treatment, as the catalog's would (`--noise auto`).
//!
//! Seeded: sample s draws from streams of (seed, s) only, so the p-values are identical
//! for any thread count.
use rayon::prelude::*;

use super::ks::ks_uniform;
use super::mc::per_binary::{binary_seed, draw_pairs, pairs_per_binary};
use super::mc::{simulate_per_binary, simulate_samples, BinarySetup, ForegroundQu, Ism, McConfig, PIntDist};
use super::model::AlignmentModel;
use super::predictions::{mixture_sample, per_binary_test, predict};
use super::rng::{mix64, Xoshiro256pp};
use super::Result;

/// The simulated samples and the tests' Monte Carlo.
#[derive(Debug, Clone, PartialEq)]
pub struct NullSetup {
    /// Binaries per sample (that passed the cut).
    pub binaries: usize,
    /// Range of the components' sigma_P, percent (log-uniform).
    pub sigma_range_percent: [f64; 2],
    /// Intrinsic P of the disks (the same in the samples and in the predictions).
    pub p_int: PIntDist,
    /// The foreground of every binary (the same in the samples and in the predictions).
    pub ism: Ism,
    /// P/sigma cut of both components.
    pub snr_cut: f64,
    /// Monte-Carlo pairs of a prediction (the old treatment's run; shared among the
    /// binaries in the new one, as `sofipol stats --pairs`).
    pub pairs: u64,
    /// Seed.
    pub seed: u64,
    /// The per-binary predictions take each binary's noise times this (1: the right
    /// model; other values are a deliberately wrong prediction, to show that the
    /// calibration check can fail).
    pub prediction_noise_scale: f64,
}

impl Default for NullSetup {
    /// 40 binaries, sigma_P 0.1-2 %, P_int = 6 % sin^2 i, a foreground of 1.5 % at 0 deg,
    /// P/sigma > 3, 2 x 10^5 pairs.
    fn default() -> Self {
        NullSetup {
            binaries: 40,
            sigma_range_percent: [0.1, 2.0],
            p_int: PIntDist::Sin2i { p_max_percent: 6.0 },
            ism: Ism {
                p_percent: 1.5,
                angle_deg: 0.0,
            },
            snr_cut: 3.0,
            pairs: 200_000,
            seed: 20261129,
            prediction_noise_scale: 1.0,
        }
    }
}

/// The p-values of the three tests over the simulated samples (sample order).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NullPValues {
    /// One noise for every binary (the median sigma_P of all measured components, as
    /// `--noise auto`): two-sample KS against that Monte Carlo.
    pub median_noise: Vec<f64>,
    /// Per binary: two-sample KS against the equal-weight mixture of the binaries' own
    /// predictions.
    pub mixture: Vec<f64>,
    /// Per binary: one-sample KS of u_i = F_i(Delta gamma_i) (what the verdict reads).
    pub per_binary: Vec<f64>,
    /// Targets drawn per sample to get the binaries (passing or not), summed.
    pub targets_drawn: u64,
    /// Median over samples of the old treatment's noise, percent.
    pub median_noise_percent: f64,
    /// Median over samples of the median sigma_P of the binaries in the sample, percent.
    pub median_sample_sigma_percent: f64,
}

/// How uniform a set of p-values is: the fractions below 0.05 and 0.01 and the KS test of
/// the p-values against uniform on [0, 1].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    /// Number of p-values.
    pub n: usize,
    /// Fraction below 0.05.
    pub below_005: f64,
    /// Fraction below 0.01.
    pub below_001: f64,
    /// KS D of the p-values against uniform.
    pub ks_d: f64,
    /// Its p-value.
    pub ks_p: f64,
}

impl Calibration {
    /// Of `p` (p-values).
    pub fn of(p: &[f64]) -> Self {
        let n = p.len();
        let frac = |a: f64| p.iter().filter(|&&x| x < a).count() as f64 / n.max(1) as f64;
        let ks = ks_uniform(p, 0.0, 1.0);
        Calibration {
            n,
            below_005: frac(0.05),
            below_001: frac(0.01),
            ks_d: ks.statistic,
            ks_p: ks.p_value,
        }
    }

    /// Exact two-sided binomial p-values of the counts below 0.05 and below 0.01 (against
    /// probabilities 0.05 and 0.01).
    pub fn binomial_p(&self) -> [f64; 2] {
        let n = self.n as u64;
        [(self.below_005, 0.05), (self.below_001, 0.01)]
            .map(|(f, a)| super::binomial::binomial_test((f * n as f64).round() as u64, n, a).p_two_sided)
    }

    /// True when neither count below 0.05 or 0.01 nor the KS of the p-values rejects
    /// uniformity at `alpha` (each test on its own).
    pub fn is_uniform(&self, alpha: f64) -> bool {
        let [b5, b1] = self.binomial_p();
        b5 > alpha && b1 > alpha && self.ks_p > alpha
    }
}

/// One simulated observed sample: each binary's Delta gamma and noise, and the sigma_P of
/// every measured component (passing or not).
struct Sample {
    delta_gamma_deg: Vec<f64>,
    noise_percent: Vec<[f64; 2]>,
    all_sigma_percent: Vec<f64>,
    targets: u64,
}

fn mc_config(setup: &NullSetup, seed: u64) -> McConfig {
    McConfig {
        p_int: setup.p_int.clone(),
        noise_percent: Some(1.0),
        snr_cut: Some(setup.snr_cut),
        ..McConfig::geometry(AlignmentModel::Random, setup.pairs, seed)
    }
}

fn draw_sample(setup: &NullSetup, s: u64) -> Sample {
    let cfg = mc_config(setup, setup.seed);
    let mut rng = Xoshiro256pp::for_stream(mix64(setup.seed ^ 0xCA11_B8A7_E000_0003), s);
    let [lo, hi] = setup.sigma_range_percent;
    let fg = ForegroundQu::fixed(setup.ism);
    let mut out = Sample {
        delta_gamma_deg: Vec::new(),
        noise_percent: Vec::new(),
        all_sigma_percent: Vec::new(),
        targets: 0,
    };
    while out.delta_gamma_deg.len() < setup.binaries {
        let level = lo * (hi / lo).powf(rng.uniform());
        let noise = [0, 1].map(|_| level * (0.2 * rng.uniform_pm1()).exp());
        let b = BinarySetup {
            noise_percent: noise,
            foreground: fg,
        };
        // One pair from the target's own stream: kept when it passes the cut.
        let pair = draw_pairs(&cfg, &b, 1, binary_seed(setup.seed ^ 0x5A3F, s, out.targets));
        out.targets += 1;
        out.all_sigma_percent.extend(noise);
        if let Some(&dg) = pair.first() {
            out.delta_gamma_deg.push(dg);
            out.noise_percent.push(noise);
        }
    }
    out
}

/// The outcome of one simulated sample: the three p-values (median noise, mixture, per
/// binary), the targets drawn, the old treatment's noise and the binaries' median sigma_P.
struct OneSample {
    p: [f64; 3],
    targets: u64,
    median_noise: f64,
    sample_median: f64,
}

/// Simulate `samples` observed samples under the null of `setup` and test each with the
/// three treatments. Identical for any rayon pool size.
pub fn null_p_values(setup: &NullSetup, samples: usize) -> Result<NullPValues> {
    let per_sample: Vec<Result<OneSample>> = (0..samples as u64)
        .into_par_iter()
        .map(|s| {
            let smp = draw_sample(setup, s);
            let mut observed = smp.delta_gamma_deg.clone();
            observed.sort_by(|a, b| a.total_cmp(b));
            let seed = mix64(setup.seed ^ 0x7E57_0000_0000_0004) ^ s;
            // Old: one Monte Carlo with the median sigma_P of every measured component.
            let median_noise = crate::numeric::median_finite(&smp.all_sigma_percent).unwrap_or(0.0);
            let old_cfg = McConfig {
                noise_percent: Some(median_noise),
                ism: Some(setup.ism),
                ..mc_config(setup, seed)
            };
            let (mut sim, _) = simulate_samples(&old_cfg)?;
            let old_p = predict(&observed, &mut sim, 30.0).ks.p_value;
            // New: each binary with its own noise, cut and foreground.
            let fg = ForegroundQu::fixed(setup.ism);
            let setups: Vec<BinarySetup> = smp
                .noise_percent
                .iter()
                .map(|&noise| BinarySetup {
                    noise_percent: noise.map(|s| s * setup.prediction_noise_scale),
                    foreground: fg,
                })
                .collect();
            let pairs = pairs_per_binary(setup.pairs, setups.len());
            let sims = simulate_per_binary(&mc_config(setup, seed), &setups, pairs, 0)?;
            let pb = per_binary_test(&smp.delta_gamma_deg, &sims).map_or(f64::NAN, |t| t.p_value);
            let mut mix = mixture_sample(&sims);
            let mix_p = predict(&observed, &mut mix, 30.0).ks.p_value;
            let sample_median =
                crate::numeric::median_finite(&smp.noise_percent.iter().flatten().cloned().collect::<Vec<_>>())
                    .unwrap_or(f64::NAN);
            Ok(OneSample {
                p: [old_p, mix_p, pb],
                targets: smp.targets,
                median_noise,
                sample_median,
            })
        })
        .collect();
    let mut out = NullPValues::default();
    let (mut noises, mut sample_sigmas) = (Vec::new(), Vec::new());
    for r in per_sample {
        let one = r?;
        let [a, b, c] = one.p;
        out.median_noise.push(a);
        out.mixture.push(b);
        out.per_binary.push(c);
        out.targets_drawn += one.targets;
        noises.push(one.median_noise);
        sample_sigmas.push(one.sample_median);
    }
    out.median_noise_percent = crate::numeric::median_finite(&noises).unwrap_or(f64::NAN);
    out.median_sample_sigma_percent = crate::numeric::median_finite(&sample_sigmas).unwrap_or(f64::NAN);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(name: &str, c: &Calibration) -> String {
        let [b5, b1] = c.binomial_p();
        format!(
            "{name:<34} n = {:4}  f(p < 0.05) = {:.3} (binomial p {b5:.2e})  f(p < 0.01) = {:.3} (binomial p {b1:.2e})  KS of the p-values: D = {:.3}, p = {:.2e}",
            c.n, c.below_005, c.below_001, c.ks_d, c.ks_p
        )
    }

    /// Where the noise matters most: P_int = P_ism = 2 % (a binary's measured P runs from 0
    /// to 4 %, so its cut at 3 sigma_P in 0.3-6 % selects strongly).
    fn strong_selection() -> NullSetup {
        NullSetup {
            p_int: PIntDist::Fixed { p_percent: 2.0 },
            ism: Ism {
                p_percent: 2.0,
                angle_deg: 0.0,
            },
            pairs: 40_000,
            ..NullSetup::default()
        }
    }

    /// The per-binary test is calibrated under its null (random disks behind a 2 %
    /// foreground, P_int = 2 %, sigma_P 0.1-2 %, 40 binaries): over 600 simulated samples
    /// neither the counts of p below 0.05 and 0.01 (exact binomial) nor the KS of the
    /// p-values against uniform reject at 0.001. The same check fails for predictions made
    /// without the binaries' noise (and so without their cut), over 150 samples, which shows
    /// that it can fail.
    #[test]
    fn per_binary_p_values_are_uniform_under_the_null_and_fail_without_the_noise() {
        let samples = 600;
        let p = null_p_values(&strong_selection(), samples).unwrap();
        let (old, mix, new) = (
            Calibration::of(&p.median_noise),
            Calibration::of(&p.mixture),
            Calibration::of(&p.per_binary),
        );
        let text = [
            report("median noise, two-sample KS", &old),
            report("per binary, mixture two-sample KS", &mix),
            report("per binary, KS of F_i(dg_i)", &new),
        ]
        .join("\n");
        eprintln!("{text}");
        assert!(new.is_uniform(1e-3), "per-binary test miscalibrated:\n{text}");
        let wrong = null_p_values(
            &NullSetup {
                prediction_noise_scale: 0.0,
                ..strong_selection()
            },
            150,
        )
        .unwrap();
        let bad = Calibration::of(&wrong.per_binary);
        eprintln!("{}", report("per binary, predicted without noise", &bad));
        assert!(!bad.is_uniform(1e-3), "a wrong prediction passes the check: {bad:?}");
    }

    /// The long version, with the figures of docs/statistics.md:
    /// `cargo test --release -p sofipol-pipeline --lib calibration -- --ignored --nocapture`.
    #[test]
    #[ignore = "long: 2 x 1000 simulated samples (a few minutes on 2 cores)"]
    fn calibration_figures_for_the_docs() {
        for (label, setup) in [
            ("P_int 6 % sin^2 i, P_ism 1.5 %", NullSetup::default()),
            (
                "P_int 2 %, P_ism 2 %",
                NullSetup {
                    pairs: 200_000,
                    ..strong_selection()
                },
            ),
        ] {
            let t = std::time::Instant::now();
            let n = 1000;
            let p = null_p_values(&setup, n).unwrap();
            println!(
                "{label}: {n} samples of {} binaries ({} targets drawn), median noise of the old treatment {:.3} %, median sigma_P of the binaries {:.3} %, {:.0} s",
                setup.binaries,
                p.targets_drawn,
                p.median_noise_percent,
                p.median_sample_sigma_percent,
                t.elapsed().as_secs_f64()
            );
            for (name, v) in [
                ("median noise, two-sample KS", &p.median_noise),
                ("per binary, mixture two-sample KS", &p.mixture),
                ("per binary, KS of F_i(dg_i)", &p.per_binary),
            ] {
                println!("  {}", report(name, &Calibration::of(v)));
            }
        }
    }

    #[test]
    fn null_p_values_are_identical_for_any_thread_count() {
        let setup = NullSetup {
            pairs: 20_000,
            binaries: 10,
            ..NullSetup::default()
        };
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| null_p_values(&setup, 6).unwrap())
        };
        assert_eq!(run(1), run(2));
    }
}
