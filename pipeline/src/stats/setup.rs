//! The analysis of a catalog's sample as `sofipol stats` runs it: the Monte-Carlo set-up
//! from the sample (intrinsic P, noise, cut), the models compared with, and the texts of
//! its figures. `sofipol stats` and the HTML night report (`crate::report`) both call
//! [`params`] and [`analyse_sample`], so that the two say the same.
use super::alignment::{
    analyse, AlignmentReport, AnalysisParams, PerBinary, DEFAULT_SIGNIFICANCE, DEFAULT_THRESHOLD_DEG,
};
use super::figures::paper_models;
use super::mc::{Ism, McConfig, PIntDist, DEFAULT_BINS, DEFAULT_P_INT, DEFAULT_SEED, PAPER_ISM_LEVELS_PERCENT};
use super::model::AlignmentModel;
use super::sample::BinarySample;
use super::{format_p, Error, Result};

/// Default P/sigma cut of the simulated pairs when the Monte Carlo has noise.
pub const DEFAULT_MC_SNR_CUT: f64 = 3.0;
/// Default Monte-Carlo pairs per ISM level of `sofipol stats`.
pub const DEFAULT_PAIRS: u64 = 1_000_000;

/// Measurement noise of the Monte Carlo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Noise {
    /// Each binary's own: the sigma_P of its two components (the default of `sofipol
    /// stats`): the random disks + ISM predictions are made and tested per binary.
    PerBinary,
    /// One level for every binary: the median sigma_P of the catalog's components ([`BinarySample::median_sigma_p_percent`]).
    Auto,
    /// No noise.
    None,
    /// This sigma of q and u, percent.
    Percent(f64),
}

/// The choices of a sample analysis (the options of `sofipol stats`).
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// Interstellar polarization levels, percent.
    pub ism_levels_percent: Vec<f64>,
    /// Angle of the interstellar polarization, deg east of north.
    pub ism_angle_deg: f64,
    /// Monte-Carlo pairs per ISM level.
    pub pairs: u64,
    /// Seed of the Monte Carlo.
    pub seed: u64,
    /// Intrinsic P distribution; `None`: the debiased P of the sample's components
    /// ([`DEFAULT_P_INT`] when the sample is empty).
    pub p_int: Option<PIntDist>,
    /// Fraction of disks polarized perpendicular to their projected long axis.
    pub perpendicular_fraction: f64,
    /// Measurement noise of the Monte Carlo.
    pub noise: Noise,
    /// P/sigma cut of the simulated pairs (applied only when there is noise).
    pub snr_cut: Option<f64>,
    /// In the own-foreground prediction, the foreground of the binaries whose catalog entry
    /// has none: this degree (percent) at `ism_angle_deg`; None: no foreground.
    pub ism_fallback_percent: Option<f64>,
    /// Significance level of the verdict.
    pub significance: f64,
}

impl Default for Options {
    /// The defaults of `sofipol stats`.
    fn default() -> Self {
        Options {
            ism_levels_percent: PAPER_ISM_LEVELS_PERCENT.to_vec(),
            ism_angle_deg: 0.0,
            pairs: DEFAULT_PAIRS,
            seed: DEFAULT_SEED,
            p_int: None,
            perpendicular_fraction: 0.0,
            noise: Noise::PerBinary,
            snr_cut: Some(DEFAULT_MC_SNR_CUT),
            ism_fallback_percent: None,
            significance: DEFAULT_SIGNIFICANCE,
        }
    }
}

/// The alignment models the sample is compared with: perfect alignment, then the reference
/// study's models (b)-(d). Model (a), random orientation, is the uniform law of the KS and
/// Kuiper tests, which the errors leave unchanged.
pub fn comparison_models() -> Vec<(String, AlignmentModel)> {
    let mut m = vec![("aligned (α = 0)".to_string(), AlignmentModel::Aligned)];
    m.extend(paper_models().into_iter().filter(|(_, m)| *m != AlignmentModel::Random));
    m
}

/// The validated parameters of the analysis of `sample` (`source` names the catalog in
/// the description of an intrinsic P taken from it).
pub fn params(sample: &BinarySample, opts: &Options, source: &str) -> Result<AnalysisParams> {
    let p_int = match &opts.p_int {
        Some(p) => p.clone(),
        None if sample.is_empty() => PIntDist::parse(DEFAULT_P_INT)?,
        None => PIntDist::empirical(&format!("{source} (sample components)"), sample.p_percent())?,
    };
    let noise_percent = match opts.noise {
        Noise::PerBinary => sample.median_sample_sigma_p_percent(),
        Noise::Auto => sample.median_sigma_p_percent(),
        Noise::None => None,
        Noise::Percent(s) => Some(s),
    };
    let mc = McConfig {
        model: AlignmentModel::Random,
        pairs: opts.pairs,
        seed: opts.seed,
        bins: DEFAULT_BINS,
        p_int,
        ism: None,
        noise_percent,
        snr_cut: opts.snr_cut.filter(|_| noise_percent.is_some()),
        perpendicular_fraction: [opts.perpendicular_fraction; 2],
    };
    mc.validate()?;
    for b in &sample.binaries {
        if let Some(f) = b.foreground_percent {
            f.validate(&format!("{source}: target '{}'", b.object))?;
        }
    }
    if let Some(p) = opts.ism_fallback_percent {
        if !(p >= 0.0 && p.is_finite()) {
            return Err(Error::InvalidParameter {
                name: "ism-fallback (%)".into(),
                value: p.to_string(),
                reason: "must be >= 0".into(),
            });
        }
    }
    let own_noise = opts.noise == Noise::PerBinary;
    let any_foreground = sample.binaries.iter().any(|b| b.foreground_percent.is_some());
    let per_binary = (!sample.is_empty() && (own_noise || any_foreground)).then(|| PerBinary {
        noise_percent: if own_noise {
            sample.noise_percent()
        } else {
            vec![[noise_percent.unwrap_or(0.0); 2]; sample.len()]
        },
        foreground: sample.foregrounds(),
        fallback: opts.ism_fallback_percent.map(|p| Ism {
            p_percent: p,
            angle_deg: opts.ism_angle_deg,
        }),
    });
    Ok(AnalysisParams {
        significance: opts.significance,
        threshold_deg: DEFAULT_THRESHOLD_DEG,
        ism_levels_percent: opts.ism_levels_percent.clone(),
        ism_angle_deg: opts.ism_angle_deg,
        mc,
        models: comparison_models(),
        errors: sample.errors(),
        per_binary,
    })
}

/// Every test of `sample`'s Delta gamma with `params` ([`analyse`], in the current rayon
/// pool).
pub fn analyse_sample(sample: &BinarySample, params: &AnalysisParams) -> Result<AlignmentReport> {
    let mut report = analyse(&sample.delta_gamma_deg(), params)?;
    report.fg_corrected = super::alignment::FgCorrected::from_pairs(&sample.fg_corrected_pairs());
    Ok(report)
}

/// The subtitle of the ISM figure: the Monte Carlo's intrinsic P, noise and cut.
pub fn mc_subtitle(params: &AnalysisParams) -> String {
    let mc = &params.mc;
    let noise = match (&params.per_binary, mc.noise_percent) {
        (Some(pb), _) if pb.noise_percent.iter().flatten().any(|&s| s > 0.0) => {
            "each binary's own σ, equal-weight mixture".to_string()
        }
        (_, s) => s.map_or("no noise".to_string(), |s| format!("σ = {s:.2} %")),
    };
    let cut = mc.snr_cut.map_or(String::new(), |k| format!(", P/σ > {k}"));
    let p_int = match &mc.p_int {
        PIntDist::Empirical { values, .. } => format!("= observed ({} values)", values.len()),
        other => other.spec(),
    };
    format!("Pᵢₙₜ {p_int}, {noise}{cut}")
}

/// The test results written in the observed figure's Delta-gamma panel (none below
/// [`super::alignment::MIN_N_FOR_TESTS`] binaries).
pub fn observed_notes(r: &AlignmentReport) -> Vec<String> {
    match (&r.ks_uniform, &r.kuiper_uniform, &r.below_threshold) {
        (Some(ks), Some(kp), Some(bt)) => vec![
            format!("KS vs uniform: p = {}", format_p(ks.p_value)),
            format!("Kuiper: p = {}", format_p(kp.p_value)),
            format!(
                "{}/{} below {}°: p = {}",
                bt.k,
                bt.n,
                r.threshold_deg,
                format_p(bt.p_greater)
            ),
        ],
        _ => Vec::new(),
    }
}
