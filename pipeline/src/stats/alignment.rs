//! The alignment tests of a Delta-gamma sample and the verdict in plain words.
use serde::{Deserialize, Serialize};

use super::binomial::{binomial_test, BinomialOutcome};
use super::errors::{convolution_seed, SampleErrors};
use super::hist::Histogram;
use super::ks::ks_uniform;
use super::kuiper::kuiper_uniform;
use super::mc::per_binary::pairs_per_binary;
use super::mc::{simulate_per_binary, simulate_samples, BinarySetup, ForegroundQu, Ism, McConfig, McOutput};
use super::model::AlignmentModel;
use super::predictions::{
    broadening_line, describe_errors, mixture_sample, per_binary_test, predict, predict_convolved, Convolved,
    ModelComparison,
};
use super::{format_p, Result, TestOutcome};

/// Default significance level of the verdict.
pub const DEFAULT_SIGNIFICANCE: f64 = 0.05;
/// Default threshold of the binomial test, degrees (probability 1/3 under the null).
pub const DEFAULT_THRESHOLD_DEG: f64 = 30.0;
/// Most pairs simulated per alignment model for the model comparisons: the KS test of a
/// few dozen binaries does not need more (the simulated CDF is then known to ~0.001).
pub const MODEL_PAIRS: u64 = 200_000;
/// Fewer binaries than this: no test is run (the verdict says so).
pub const MIN_N_FOR_TESTS: usize = 2;

/// What to test and how to simulate the interstellar-polarization predictions.
#[derive(Debug, Clone, PartialEq)]
pub struct AnalysisParams {
    /// Significance level used in the verdict.
    pub significance: f64,
    /// Threshold of the binomial test, degrees (0 < t < 90).
    pub threshold_deg: f64,
    /// Interstellar polarization degrees to compare with, percent.
    pub ism_levels_percent: Vec<f64>,
    /// Common ISM angle, degrees.
    pub ism_angle_deg: f64,
    /// Base Monte-Carlo configuration (its `ism` is replaced by each level).
    pub mc: McConfig,
    /// Alignment models to compare with (geometry only: no ISM, no noise), with labels;
    /// simulated with the seed and bins of `mc` and min(its pairs, [`MODEL_PAIRS`]) pairs.
    pub models: Vec<(String, AlignmentModel)>,
    /// The sample's Delta-gamma errors: the predictions are also compared convolved with
    /// them (those that do not simulate measurement noise themselves).
    pub errors: SampleErrors,
    /// Each binary's own noise and foreground: the random disks + ISM predictions are made
    /// per binary and tested per binary (None: one Monte Carlo with the noise of `mc` for
    /// the whole sample).
    pub per_binary: Option<PerBinary>,
}

/// Each binary's own noise and foreground (sample order), for the random disks + ISM
/// predictions.
#[derive(Debug, Clone, PartialEq)]
pub struct PerBinary {
    /// Noise sigma of q and u of A and B of each binary, percent.
    pub noise_percent: Vec<[f64; 2]>,
    /// Each binary's own foreground, percent, where measured.
    pub foreground: Vec<Option<ForegroundQu>>,
    /// The foreground of the binaries without their own in the own-foreground prediction
    /// (None: no foreground).
    pub fallback: Option<Ism>,
}

impl PerBinary {
    /// The Monte-Carlo set-up of each binary, its foreground given by `fg`.
    fn setups(&self, fg: impl Fn(usize) -> ForegroundQu) -> Vec<BinarySetup> {
        self.noise_percent
            .iter()
            .enumerate()
            .map(|(i, &noise_percent)| BinarySetup {
                noise_percent,
                foreground: fg(i),
            })
            .collect()
    }

    /// Binaries with their own foreground.
    pub fn n_own_foreground(&self) -> usize {
        self.foreground.iter().flatten().count()
    }

    /// The own-foreground prediction's foregrounds in words.
    pub fn describe_foreground(&self) -> String {
        let n = self.foreground.len();
        let k = self.n_own_foreground();
        let rest = match self.fallback {
            Some(ism) => format!("P_ism = {} % at {} deg", ism.p_percent, ism.angle_deg),
            None => "no foreground (P_ism = 0)".into(),
        };
        if k == n {
            format!("each binary's own foreground ({k} of {n} measured)")
        } else {
            format!(
                "each binary's own foreground where measured ({k} of {n}); the other {}: {rest}",
                n - k
            )
        }
    }
}

/// Comparison of the observed Delta gamma with one ISM level of the Monte Carlo.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IsmComparison {
    /// P_ism, percent.
    pub p_ism_percent: f64,
    /// Two-sample KS, observed vs simulated.
    pub ks: TestOutcome,
    /// Simulated fraction below the threshold.
    pub mc_fraction_below_threshold: f64,
    /// Median simulated Delta gamma, deg.
    pub mc_median_delta_gamma_deg: f64,
    /// The simulated Pi(Delta gamma).
    pub mc: McOutput,
    /// The prediction convolved with the measured Delta-gamma errors: None when no binary
    /// has an error, or when the Monte Carlo already draws (q, u) noise (convolving again
    /// would count the measurement error twice).
    pub with_errors: Option<Convolved>,
    /// With per-binary predictions: the one-sample KS of the probability transforms
    /// u_i = F_i(Delta gamma_i), each binary against its own prediction (the calibrated
    /// test; `ks` is then the two-sample KS against the equal-weight mixture of the F_i,
    /// and `mc` the mixture).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub per_binary: Option<TestOutcome>,
    /// With per-binary predictions: the fewest simulated pairs that passed one binary's cut.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_accepted_per_binary: Option<u64>,
    /// The foreground of the prediction in words, when it is not one level for the sample.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub foreground: Option<String>,
}

impl IsmComparison {
    /// The p-value the verdict reads: the per-binary test when there is one, else the
    /// two-sample KS.
    pub fn p_value(&self) -> f64 {
        self.per_binary.as_ref().map_or(self.ks.p_value, |t| t.p_value)
    }
}

/// Delta-gamma after subtracting each binary's own foreground, against uniform.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FgCorrected {
    /// Binaries with a foreground-subtracted Delta-gamma.
    pub n: usize,
    /// Their Delta-gamma before the subtraction, mean, deg.
    pub mean_before_deg: f64,
    /// After the subtraction, mean, deg (45 for random disks).
    pub mean_after_deg: f64,
    /// KS of the values before the subtraction against uniform on [0, 90].
    pub ks_before: TestOutcome,
    /// KS of the values after the subtraction against uniform on [0, 90].
    pub ks_after: TestOutcome,
    /// Kuiper of the values after the subtraction against uniform on [0, 90].
    pub kuiper_after: TestOutcome,
}

impl FgCorrected {
    /// The test on pairs (before, after) of the binaries with a subtracted Delta-gamma;
    /// None when there is none.
    pub fn from_pairs(pairs: &[(f64, f64)]) -> Option<FgCorrected> {
        if pairs.is_empty() {
            return None;
        }
        let before: Vec<f64> = pairs.iter().map(|p| p.0).collect();
        let after: Vec<f64> = pairs.iter().map(|p| p.1).collect();
        let n = pairs.len();
        Some(FgCorrected {
            n,
            mean_before_deg: before.iter().sum::<f64>() / n as f64,
            mean_after_deg: after.iter().sum::<f64>() / n as f64,
            ks_before: ks_uniform(&before, 0.0, 90.0),
            ks_after: ks_uniform(&after, 0.0, 90.0),
            kuiper_after: kuiper_uniform(&after, 0.0, 90.0),
        })
    }
}

/// Everything `sofipol stats` reports.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlignmentReport {
    /// Number of binaries in the sample.
    pub n: usize,
    /// Mean Delta gamma, degrees (45 under the null).
    pub mean_delta_gamma_deg: Option<f64>,
    /// Threshold of the binomial test, degrees.
    pub threshold_deg: f64,
    /// Binomial test of the fraction below the threshold (p0 = threshold / 90).
    pub below_threshold: Option<BinomialOutcome>,
    /// One-sample KS against uniform on [0, 90].
    pub ks_uniform: Option<TestOutcome>,
    /// Kuiper against uniform on [0, 90].
    pub kuiper_uniform: Option<TestOutcome>,
    /// Two-sample KS against each ISM level.
    pub ism: Vec<IsmComparison>,
    /// Random disks behind each binary's own foreground (where the catalog has one; the
    /// others as [`PerBinary::fallback`]); None when no binary has its own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub own_foreground: Option<IsmComparison>,
    /// The same sample after subtracting each binary's own foreground (the binaries whose
    /// catalog entry has `delta_gamma_fg_corrected_deg`), tested against uniform: the
    /// prediction of random disks once the foreground is removed. None when no binary has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fg_corrected: Option<FgCorrected>,
    /// Two-sample KS against each alignment model, without and with the errors.
    pub models: Vec<ModelComparison>,
    /// The sample's Delta-gamma errors.
    pub errors: SampleErrors,
    /// Significance level of the verdict.
    pub significance: f64,
    /// The Monte-Carlo set-up in words.
    pub mc_description: String,
    /// The verdict in plain words.
    pub verdict: String,
}

/// Run every test on `delta_gamma_deg` (degrees in [0, 90]) and write the verdict.
pub fn analyse(delta_gamma_deg: &[f64], params: &AnalysisParams) -> Result<AlignmentReport> {
    let n = delta_gamma_deg.len();
    let t = params.threshold_deg;
    let mc_description = describe_mc(&params.mc, params.per_binary.as_ref());
    let mut report = AlignmentReport {
        n,
        mean_delta_gamma_deg: (n > 0).then(|| delta_gamma_deg.iter().sum::<f64>() / n as f64),
        threshold_deg: t,
        below_threshold: None,
        ks_uniform: None,
        kuiper_uniform: None,
        ism: Vec::new(),
        own_foreground: None,
        fg_corrected: None,
        models: Vec::new(),
        errors: params.errors.clone(),
        significance: params.significance,
        mc_description,
        verdict: String::new(),
    };
    if n >= MIN_N_FOR_TESTS {
        let k = delta_gamma_deg.iter().filter(|&&d| d < t).count() as u64;
        report.below_threshold = Some(binomial_test(k, n as u64, t / 90.0));
        report.ks_uniform = Some(ks_uniform(delta_gamma_deg, 0.0, 90.0));
        report.kuiper_uniform = Some(kuiper_uniform(delta_gamma_deg, 0.0, 90.0));
        let mut observed = delta_gamma_deg.to_vec();
        observed.sort_by(|a, b| a.total_cmp(b));
        let sigmas = &params.errors.sigmas_deg;
        let (seed, bins) = (params.mc.seed, params.mc.bins);
        for (i, (label, model)) in params.models.iter().enumerate() {
            let cfg = McConfig {
                model: model.clone(),
                bins,
                ..McConfig::geometry(model.clone(), params.mc.pairs.min(MODEL_PAIRS), seed)
            };
            let (mut sim, out) = simulate_samples(&cfg)?;
            let prediction = predict(&observed, &mut sim, t);
            let with_errors = predict_convolved(&observed, &sim, sigmas, convolution_seed(seed, i as u64), t, bins);
            report.models.push(ModelComparison {
                label: label.clone(),
                model: model.spec(),
                mc: out,
                prediction,
                with_errors,
            });
        }
        // A Monte Carlo with (q, u) noise already carries measurement errors.
        let ism_sigmas: &[f64] = if params.mc.noise_percent.is_some() { &[] } else { sigmas };
        if let Some(pb) = &params.per_binary {
            let pairs = pairs_per_binary(params.mc.pairs, pb.noise_percent.len());
            for (i, &level) in params.ism_levels_percent.iter().enumerate() {
                let fg = ForegroundQu::fixed(Ism {
                    p_percent: level,
                    angle_deg: params.ism_angle_deg,
                });
                let sims = simulate_per_binary(&params.mc, &pb.setups(|_| fg), pairs, 1000 + i as u64)?;
                report
                    .ism
                    .push(per_binary_comparison(level, delta_gamma_deg, &observed, &sims, t, bins));
            }
            if pb.n_own_foreground() > 0 {
                let rest = pb.fallback.map_or(ForegroundQu::NONE, ForegroundQu::fixed);
                let sims =
                    simulate_per_binary(&params.mc, &pb.setups(|i| pb.foreground[i].unwrap_or(rest)), pairs, 999)?;
                let mut c = per_binary_comparison(
                    pb.fallback.map_or(0.0, |f| f.p_percent),
                    delta_gamma_deg,
                    &observed,
                    &sims,
                    t,
                    bins,
                );
                c.foreground = Some(pb.describe_foreground());
                report.own_foreground = Some(c);
            }
        }
        for (i, &level) in params.ism_levels_percent.iter().enumerate() {
            if params.per_binary.is_some() {
                break;
            }
            let mut cfg = params.mc.clone();
            cfg.ism = Some(Ism {
                p_percent: level,
                angle_deg: params.ism_angle_deg,
            });
            let (mut sim, out) = simulate_samples(&cfg)?;
            let p = predict(&observed, &mut sim, t);
            let conv_seed = convolution_seed(seed, 1000 + i as u64);
            report.ism.push(IsmComparison {
                p_ism_percent: level,
                ks: p.ks,
                mc_fraction_below_threshold: if sim.is_empty() {
                    0.0
                } else {
                    p.fraction_below_threshold
                },
                mc_median_delta_gamma_deg: p.median_deg,
                with_errors: predict_convolved(&observed, &sim, ism_sigmas, conv_seed, t, bins),
                mc: out,
                per_binary: None,
                min_accepted_per_binary: None,
                foreground: None,
            });
        }
    }
    report.verdict = verdict(&report, delta_gamma_deg);
    if n >= MIN_N_FOR_TESTS {
        report.verdict += "\n";
        report.verdict += &broadening(&report, params.mc.noise_percent.is_some());
    }
    Ok(report)
}

/// The comparison of the sample (`delta_gamma_deg` in sample order, `observed` sorted)
/// with per-binary predictions `sims`: the per-binary test, and the summary and two-sample
/// KS of their equal-weight mixture.
fn per_binary_comparison(
    level: f64,
    delta_gamma_deg: &[f64],
    observed: &[f64],
    sims: &[super::mc::BinarySim],
    t: f64,
    bins: usize,
) -> IsmComparison {
    let mut mix = mixture_sample(sims);
    let (histogram, _) = Histogram::from_values(0.0, 90.0, bins, &mix);
    let mean = if mix.is_empty() {
        f64::NAN
    } else {
        mix.iter().sum::<f64>() / mix.len() as f64
    };
    let out = McOutput {
        histogram,
        simulated: sims.iter().map(|s| s.simulated).sum(),
        accepted: sims.iter().map(|s| s.values.len() as u64).sum(),
        mean_delta_gamma_deg: mean,
    };
    let p = predict(observed, &mut mix, t);
    IsmComparison {
        p_ism_percent: level,
        ks: p.ks,
        mc_fraction_below_threshold: if mix.is_empty() {
            0.0
        } else {
            p.fraction_below_threshold
        },
        mc_median_delta_gamma_deg: p.median_deg,
        mc: out,
        with_errors: None,
        per_binary: per_binary_test(delta_gamma_deg, sims),
        min_accepted_per_binary: sims.iter().map(|s| s.values.len() as u64).min(),
        foreground: None,
    }
}

/// How the measurement errors broaden the predictions, in words and figures.
fn broadening(r: &AlignmentReport, mc_has_noise: bool) -> String {
    let a = r.significance;
    let mut s = describe_errors(&r.errors, r.n);
    if !r.errors.any() {
        return s;
    }
    s += " Random orientation is unchanged by angle errors (a uniform Delta gamma stays uniform), so the KS and Kuiper p-values against it above hold with the errors.";
    let mut lines = Vec::new();
    let mut crossings = Vec::new();
    let mut note = |label: String, without: &super::predictions::Prediction, with: &Option<Convolved>| {
        if let Some(c) = with {
            lines.push(format!(
                "  {}",
                broadening_line(&label, without, &c.prediction, r.threshold_deg)
            ));
            let (p0, p1) = (without.ks.p_value, c.prediction.ks.p_value);
            if !(p0 >= a) && p1 >= a {
                crossings.push(format!("{label} becomes consistent with the sample (KS p >= {a})"));
            } else if p0 >= a && !(p1 >= a) {
                crossings.push(format!("{label} becomes inconsistent (KS p < {a})"));
            }
        }
    };
    for m in &r.models {
        note(m.label.clone(), &m.prediction, &m.with_errors);
    }
    for c in &r.ism {
        let without = super::predictions::Prediction {
            mean_deg: c.mc.mean_delta_gamma_deg,
            median_deg: c.mc_median_delta_gamma_deg,
            fraction_below_threshold: c.mc_fraction_below_threshold,
            ks: c.ks.clone(),
        };
        note(
            format!("random + P_ism = {} %", c.p_ism_percent),
            &without,
            &c.with_errors,
        );
    }
    if !lines.is_empty() {
        s += " Convolved with these errors (each simulated pair gets a sigma drawn from the sample's and a Gaussian angle error, folded into [0, 90] deg), the predictions change (without -> with errors):\n";
        s += &lines.join("\n");
    }
    if mc_has_noise && !r.ism.is_empty() {
        s += "\n  The random disks + ISM predictions already draw (q, u) measurement noise: they are not convolved again.";
    }
    if !crossings.is_empty() {
        s += &format!("\nWith the errors: {}.", crossings.join("; "));
    }
    s
}

fn describe_mc(cfg: &McConfig, per_binary: Option<&PerBinary>) -> String {
    let noise = match (per_binary, cfg.noise_percent) {
        (Some(pb), _) => {
            let all: Vec<f64> = pb.noise_percent.iter().flatten().cloned().collect();
            let lo = all.iter().cloned().fold(f64::INFINITY, f64::min);
            let hi = all.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            format!("each binary's own noise sigma(q, u) = its components' sigma_P ({lo:.3} ... {hi:.3} %)")
        }
        (None, Some(s)) => format!("noise sigma(q, u) = {s:.3} %"),
        (None, None) => "no measurement noise".into(),
    };
    let cut = match cfg.snr_cut {
        Some(k) => format!(", both components P/sigma > {k}"),
        None => String::new(),
    };
    let perp = match cfg.perpendicular_fraction {
        [0.0, 0.0] => String::new(),
        [a, b] if a == b => format!(", {} % of disks polarized perpendicular to their long axis", a * 100.0),
        [a, b] => format!(", perpendicular fractions A {a}, B {b}"),
    };
    let pairs = match per_binary {
        Some(pb) => format!(
            "{} pairs per binary and level",
            pairs_per_binary(cfg.pairs, pb.noise_percent.len())
        ),
        None => format!("{} pairs per level", cfg.pairs),
    };
    format!(
        "model {}, P_int {}{perp}, {noise}{cut}, {pairs}, seed {}",
        cfg.model.spec(),
        cfg.p_int.spec(),
        cfg.seed
    )
}

fn list(levels: &[f64]) -> String {
    levels.iter().map(|l| format!("{l}")).collect::<Vec<_>>().join(", ")
}

/// The verdict in plain words.
fn verdict(r: &AlignmentReport, dg: &[f64]) -> String {
    let a = r.significance;
    match r.n {
        0 => return "No binary has both components above the P/sigma cut: there is nothing to test.".into(),
        1 => {
            return format!(
                "Only one binary ({:.1} deg) has both components above the P/sigma cut: a single pair cannot test alignment; no test was run.",
                dg[0]
            )
        }
        _ => {}
    }
    let (ks, kp, bt) = match (&r.ks_uniform, &r.kuiper_uniform, &r.below_threshold) {
        (Some(a), Some(b), Some(c)) => (a, b, c),
        _ => return "Tests were not run.".into(),
    };
    let mean = r.mean_delta_gamma_deg.unwrap_or(f64::NAN);
    let mut s = format!(
        "{} binaries have both components above the cut. Mean Delta gamma = {:.1} deg (random orientation: 45 deg); {} of {} ({:.0} %) have Delta gamma < {} deg (random: {:.0} %).\n",
        r.n,
        mean,
        bt.k,
        bt.n,
        100.0 * bt.k as f64 / bt.n as f64,
        r.threshold_deg,
        100.0 * bt.p0
    );
    s += &format!(
        "Against a uniform Pi(Delta gamma) on [0, 90] deg (randomly oriented disks): KS D = {:.3}, p = {}; Kuiper V = {:.3}, p = {} ({}); binomial test of the fraction below {} deg: one-sided p = {} (two-sided {}).\n",
        ks.statistic,
        format_p(ks.p_value),
        kp.statistic,
        format_p(kp.p_value),
        kp.method.split(' ').next().unwrap_or(""),
        r.threshold_deg,
        format_p(bt.p_greater),
        format_p(bt.p_two_sided)
    );
    let rejected = ks.p_value < a;
    if rejected && mean < 45.0 {
        s += &format!(
            "Verdict: random disk orientation is rejected at the {a} level (KS p = {}). The excess is at small Delta gamma: the disks of a binary tend to be aligned (in projection on the sky).",
            format_p(ks.p_value)
        );
    } else if rejected {
        s += &format!(
            "Verdict: random disk orientation is rejected at the {a} level (KS p = {}), but the excess is at large Delta gamma: the disks tend to be misaligned, not aligned.",
            format_p(ks.p_value)
        );
    } else {
        s += &format!(
            "Verdict: random disk orientation is not rejected at the {a} level (KS p = {}). With {} binaries this does not show that the disks are randomly oriented, only that any alignment is not strong enough to be detected.",
            format_p(ks.p_value),
            r.n
        );
        let others: Vec<String> = [("Kuiper", kp.p_value), ("binomial (one-sided)", bt.p_greater)]
            .iter()
            .filter(|(_, p)| *p < a)
            .map(|(name, p)| format!("{name} p = {}", format_p(*p)))
            .collect();
        if !others.is_empty() {
            s += &format!(
                " Note: {} would reject on its own; treat the evidence as marginal.",
                others.join(", ")
            );
        }
    }
    if r.n < 10 {
        s += &format!(" (With only {} binaries every test has little power.)", r.n);
    }
    if !r.ism.is_empty() {
        let ok: Vec<f64> = r
            .ism
            .iter()
            .filter(|c| c.p_value() >= a)
            .map(|c| c.p_ism_percent)
            .collect();
        let bad: Vec<f64> = r
            .ism
            .iter()
            .filter(|c| !(c.p_value() >= a))
            .map(|c| c.p_ism_percent)
            .collect();
        let per_binary = r.ism.iter().any(|c| c.per_binary.is_some());
        let test = if per_binary { "per-binary KS" } else { "two-sample KS" };
        s += &format!(
            "\nRandom disks plus interstellar polarization (Monte Carlo: {}): ",
            r.mc_description
        );
        if ok.is_empty() {
            s += &format!(
                "none of the levels P_ism = {} % reproduces the observed Delta gamma ({test} p < {a} for all): interstellar polarization alone does not explain it.",
                list(&bad)
            );
        } else if bad.is_empty() {
            s += &format!(
                "every level P_ism = {} % is consistent with the observed Delta gamma ({test} p >= {a}).",
                list(&ok)
            );
        } else {
            s += &format!(
                "consistent ({test} p >= {a}) for P_ism = {} %, inconsistent for P_ism = {} %.",
                list(&ok),
                list(&bad)
            );
            if rejected && mean < 45.0 {
                let min_ok = ok.iter().cloned().fold(f64::INFINITY, f64::min);
                s += &format!(
                    " Interstellar polarization could mimic the alignment only if P_ism >= {min_ok} % towards these binaries; compare with the interstellar polarization expected along their lines of sight."
                );
            }
        }
        if per_binary {
            s += " Each binary is predicted with its own noise (sigma_P of A and B) and its own P/sigma cut, and tested against its own prediction (KS of u_i = F_i(Delta gamma_i)).";
        }
    }
    if let Some(c) = &r.own_foreground {
        s += &format!(
            "\nWith {}: random disks give {} p = {} ({}); without any foreground random disks give a uniform Delta gamma for any noise and cut (the KS p = {} above).",
            c.foreground.as_deref().unwrap_or("each binary's own foreground"),
            if c.per_binary.is_some() { "per-binary KS" } else { "two-sample KS" },
            format_p(c.p_value()),
            if c.p_value() >= a { "consistent with the sample" } else { "inconsistent with the sample" },
            format_p(ks.p_value),
        );
    }
    s
}
