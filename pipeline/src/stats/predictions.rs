//! A model's predicted Delta-gamma distribution against the observed sample, without and
//! with the measurement errors (the prediction convolved with the sample's errors,
//! [`super::errors::convolve_with_errors`]), and the broadening in words.
use serde::{Deserialize, Serialize};

use super::errors::{convolve_with_errors, ErrorSource, SampleErrors};
use super::hist::Histogram;
use super::ks::ks_two_sample_against_large;
use super::ks::ks_uniform;
use super::mc::{BinarySim, McOutput};
use super::{format_p, TestOutcome};

/// Summary of a predicted Delta gamma and the two-sample KS test of the observed sample
/// against it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// Mean predicted Delta gamma, deg.
    pub mean_deg: f64,
    /// Median predicted Delta gamma, deg.
    pub median_deg: f64,
    /// Predicted fraction below the threshold of the binomial test.
    pub fraction_below_threshold: f64,
    /// Two-sample KS, observed vs predicted.
    pub ks: TestOutcome,
}

/// The prediction convolved with the sample's measurement errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Convolved {
    /// Summary and KS test of the convolved prediction.
    #[serde(flatten)]
    pub prediction: Prediction,
    /// Its histogram on [0, 90] deg (the bins of the Monte Carlo).
    pub histogram: Histogram,
}

/// Comparison of the observed Delta gamma with one alignment model (geometry only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelComparison {
    /// Label, e.g. "(c) spread σ = 25°".
    pub label: String,
    /// The model as a `--model` spec.
    pub model: String,
    /// The simulated Pi(Delta gamma) (no measurement error).
    pub mc: McOutput,
    /// The prediction without measurement errors.
    pub prediction: Prediction,
    /// The prediction convolved with the measured errors (None when no binary has one).
    pub with_errors: Option<Convolved>,
}

/// Summarize `sim` (reordered here: the median is selected in place) and test the sorted
/// `observed` against it. No sort of `sim`: O(len) plus the KS count.
pub fn predict(observed_sorted: &[f64], sim: &mut [f64], threshold_deg: f64) -> Prediction {
    let n = sim.len();
    if n == 0 {
        return Prediction {
            mean_deg: f64::NAN,
            median_deg: f64::NAN,
            fraction_below_threshold: f64::NAN,
            ks: TestOutcome {
                statistic: f64::NAN,
                p_value: f64::NAN,
                n: 0,
                method: "no simulated pair passed the cut".into(),
            },
        };
    }
    let mean_deg = sim.iter().sum::<f64>() / n as f64;
    let fraction_below_threshold = sim.iter().filter(|&&d| d < threshold_deg).count() as f64 / n as f64;
    let ks = ks_two_sample_against_large(observed_sorted, sim);
    let (_, &mut upper, _) = sim.select_nth_unstable_by(n / 2, |a, b| a.total_cmp(b));
    let median_deg = if n % 2 == 1 {
        upper
    } else {
        // The lower middle value is the largest of the elements before n/2.
        let lower = sim[..n / 2].iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (lower + upper)
    };
    Prediction {
        mean_deg,
        median_deg,
        fraction_below_threshold,
        ks,
    }
}

/// `sim` convolved with the errors `sigmas_deg` (seeded), summarized and tested; None when
/// there is no error to convolve with.
pub fn predict_convolved(
    observed_sorted: &[f64],
    sim: &[f64],
    sigmas_deg: &[f64],
    seed: u64,
    threshold_deg: f64,
    bins: usize,
) -> Option<Convolved> {
    if sigmas_deg.is_empty() {
        return None;
    }
    let mut conv = convolve_with_errors(sim, sigmas_deg, seed);
    let (histogram, _) = Histogram::from_values(0.0, 90.0, bins, &conv);
    Some(Convolved {
        prediction: predict(observed_sorted, &mut conv, threshold_deg),
        histogram,
    })
}

/// One line of the broadening: "label: mean a -> b deg, median c -> d deg, f(<t) e -> f,
/// KS p g -> h".
pub fn broadening_line(label: &str, without: &Prediction, with: &Prediction, threshold_deg: f64) -> String {
    format!(
        "{label}: mean {:.1} -> {:.1} deg, median {:.1} -> {:.1} deg, f(<{threshold_deg}) {:.3} -> {:.3}, KS p {} -> {}",
        without.mean_deg,
        with.mean_deg,
        without.median_deg,
        with.median_deg,
        without.fraction_below_threshold,
        with.fraction_below_threshold,
        format_p(without.ks.p_value),
        format_p(with.ks.p_value),
    )
}

/// The errors of the sample in words: how many binaries have one, from where, median and
/// maximum, and the large ones.
pub fn describe_errors(e: &SampleErrors, n: usize) -> String {
    let Some(median) = e.median_deg() else {
        return format!(
            "Measurement errors of Delta gamma: none of the {n} binaries has one (no sigma_delta_gamma_deg, sigma_gamma_stat_deg or sigma_gamma_deg): the predictions are compared without errors only."
        );
    };
    let mut sources = Vec::new();
    for (k, what) in [
        (e.n_propagated, "sigma_delta_gamma_deg"),
        (e.n_component_stat, "the components' sigma_gamma_stat_deg in quadrature"),
        (e.n_component_total, "the components' sigma_gamma_deg in quadrature"),
    ] {
        if k > 0 {
            sources.push(format!("{k} from {what}"));
        }
    }
    let mut s = format!(
        "Measurement errors of Delta gamma: {} of {n} binaries have one ({}); median sigma = {median:.1} deg, max {:.1} deg.",
        e.sigmas_deg.len(),
        sources.join(", "),
        e.max_deg().unwrap_or(f64::NAN),
    );
    if e.n_component_total > 0 {
        s += &format!(
            " Caution: {} of them include the calibration zero-point, which is common to both components and cancels in Delta gamma: those errors are overestimates, and so is the broadening below.",
            e.n_component_total
        );
    }
    if e.n_without_error > 0 {
        s += &format!(
            " {} binaries without an error are left out of the error draw.",
            e.n_without_error
        );
    }
    if e.large.is_empty() {
        s += &format!(
            " No binary has sigma > {} deg or a 68.27 % interval wider than {} deg.",
            super::errors::LARGE_SIGMA_DEG,
            super::errors::LARGE_INTERVAL_DEG
        );
    } else {
        let items: Vec<String> = e
            .large
            .iter()
            .map(|l| {
                let mut t = format!("{} (Delta gamma {:.1} deg", l.object, l.delta_gamma_deg);
                if let Some(sg) = l.sigma_deg {
                    t += &format!(", sigma {sg:.1}");
                }
                if let Some([lo, hi]) = l.interval_deg {
                    t += &format!(", 68 % interval [{lo:.1}, {hi:.1}]");
                }
                t + ")"
            })
            .collect();
        s += &format!(
            " Large errors (sigma > {} deg or 68.27 % interval wider than {} deg; a Gaussian error describes them poorly): {}.",
            super::errors::LARGE_SIGMA_DEG,
            super::errors::LARGE_INTERVAL_DEG,
            items.join("; ")
        );
    }
    s
}

/// Short name of an error source, for tables.
pub fn source_name(s: Option<ErrorSource>) -> &'static str {
    match s {
        Some(ErrorSource::Propagated) => "propagated",
        Some(ErrorSource::ComponentStat) => "stat (A, B)",
        Some(ErrorSource::ComponentTotal) => "total (A, B)",
        None => "none",
    }
}

/// The per-binary test of a sample against predictions made for each binary: with F_i the
/// simulated CDF of binary i (its own noise, cut and foreground; ties counted half), the
/// probability transforms u_i = F_i(Delta gamma_i) are iid uniform on [0, 1] under the
/// model whatever the F_i, and are tested with the one-sample KS. `observed` and `sims` are
/// in the same (sample) order; binaries whose simulation has no accepted pair are left out.
/// None below two usable binaries.
pub fn per_binary_test(observed: &[f64], sims: &[BinarySim]) -> Option<TestOutcome> {
    let u: Vec<f64> = observed
        .iter()
        .zip(sims)
        .map(|(&x, s)| s.cdf_mid(x))
        .filter(|u| u.is_finite())
        .collect();
    if u.len() < 2 {
        return None;
    }
    let mut t = ks_uniform(&u, 0.0, 1.0);
    t.method = format!(
        "one-sample KS of u_i = F_i(Delta gamma_i) vs uniform, F_i simulated per binary; {}",
        t.method
    );
    Some(t)
}

/// The equal-weight mixture (1/n) sum F_i of the binaries' predictions as one sample: the
/// first m accepted values of each binary (a random sample of it: chunk order does not
/// depend on the value), m the smallest accepted count among the binaries that have one.
pub fn mixture_sample(sims: &[BinarySim]) -> Vec<f64> {
    let m = sims
        .iter()
        .map(|s| s.values.len())
        .filter(|&l| l > 0)
        .min()
        .unwrap_or(0);
    sims.iter()
        .filter(|s| !s.values.is_empty())
        .flat_map(|s| s.values[..m].iter().cloned())
        .collect()
}
