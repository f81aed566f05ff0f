//! The Delta-gamma sample of a catalog: binaries whose two components both pass the cut.
use serde::{Deserialize, Serialize};

use super::errors::{is_large, ErrorSource, LargeError, SampleErrors};
use super::foreground::ForegroundQu;
use crate::catalog::{fold_delta_gamma, Catalog, Component, Foreground, Status, Target};

/// One binary of the sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SampleBinary {
    /// Object name.
    pub object: String,
    /// |gamma_A - gamma_B| folded into [0, 90], degrees.
    pub delta_gamma_deg: f64,
    /// Debiased P of the two components, percent.
    pub p_percent: [f64; 2],
    /// sigma_P of the two components, percent.
    pub sigma_p_percent: [f64; 2],
    /// 1-sigma error of Delta gamma, deg (see `sigma_source`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_delta_gamma_deg: Option<f64>,
    /// Where `sigma_delta_gamma_deg` comes from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_source: Option<ErrorSource>,
    /// The catalog's central 68.27 % interval of Delta gamma, deg.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub delta_gamma_interval_deg: Option<[f64; 2]>,
    /// Delta gamma after subtracting the binary's own foreground (the catalog's
    /// `delta_gamma_fg_corrected_deg`), deg.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub delta_gamma_fg_corrected_deg: Option<f64>,
    /// The binary's own interstellar foreground (the catalog's `foreground`), percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub foreground_percent: Option<ForegroundQu>,
}

/// The Delta-gamma error of a binary: the catalog's `sigma_delta_gamma_deg`, else the
/// components' `sigma_gamma_stat_deg` in quadrature, else their `sigma_gamma_deg` in
/// quadrature (an overestimate: it includes the common zero-point), else none.
pub fn delta_gamma_error(t: &Target, a: &Component, b: &Component) -> Option<(f64, ErrorSource)> {
    let ok = |s: f64| s.is_finite() && s >= 0.0;
    if let Some(s) = t.sigma_delta_gamma_deg.filter(|&s| ok(s)) {
        return Some((s, ErrorSource::Propagated));
    }
    if let (Some(sa), Some(sb)) = (a.sigma_gamma_stat_deg, b.sigma_gamma_stat_deg) {
        if ok(sa) && ok(sb) {
            return Some((sa.hypot(sb), ErrorSource::ComponentStat));
        }
    }
    let (sa, sb) = (a.sigma_gamma_deg, b.sigma_gamma_deg);
    (ok(sa) && ok(sb)).then(|| (sa.hypot(sb), ErrorSource::ComponentTotal))
}

/// The catalog's foreground (fractions, errors) in percent with its covariance.
pub fn foreground_percent(f: &Foreground) -> ForegroundQu {
    ForegroundQu {
        q_percent: 100.0 * f.q,
        u_percent: 100.0 * f.u,
        cov_percent2: [1e4 * f.sigma_q * f.sigma_q, 1e4 * f.cov_qu, 1e4 * f.sigma_u * f.sigma_u],
    }
}

/// A target left out of the sample, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Excluded {
    /// Object name.
    pub object: String,
    /// Reason in words.
    pub reason: String,
}

/// The sample of binaries with both components above the cut.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct BinarySample {
    /// Binaries in the sample.
    pub binaries: Vec<SampleBinary>,
    /// Targets left out.
    pub excluded: Vec<Excluded>,
    /// Warnings (e.g. a stored delta_gamma_deg that disagrees with the components).
    pub warnings: Vec<String>,
    /// sigma_P (percent) of every measured component of every two-component target, passing
    /// the cut or not: what the noise model of the Monte Carlo is taken from.
    pub all_sigma_p_percent: Vec<f64>,
}

impl BinarySample {
    /// Build the sample. A component passes when `passes_cut` is set, or, when `cut` is
    /// given, when P / sigma_P > cut (recomputed from `p` and `sigma_p`). Catalog P values
    /// are fractions; the sample stores percent.
    ///
    /// A binary with a component flagged `uncalibrated` is left out (its q, u carry the
    /// instrument's offset, its angle the profile's zero-point: a fake alignment), with a
    /// warning counting them; [`BinarySample::from_catalog_allowing_uncalibrated`] takes them.
    pub fn from_catalog(cat: &Catalog, cut: Option<f64>) -> Self {
        Self::build(cat, cut, false)
    }

    /// [`BinarySample::from_catalog`] that also takes binaries flagged `uncalibrated`
    /// (`stats --allow-uncalibrated`), with a warning counting them.
    pub fn from_catalog_allowing_uncalibrated(cat: &Catalog, cut: Option<f64>) -> Self {
        Self::build(cat, cut, true)
    }

    fn build(cat: &Catalog, cut: Option<f64>, allow_uncalibrated: bool) -> Self {
        let mut s = Self::default();
        let mut n_uncalibrated = 0;
        let passes = |c: &Component| match cut {
            Some(k) => c.sigma_p > 0.0 && c.p / c.sigma_p > k,
            None => c.passes_cut,
        };
        for t in &cat.targets {
            let mut exclude = |reason: String| {
                s.excluded.push(Excluded {
                    object: t.object.clone(),
                    reason,
                })
            };
            if t.status == Status::Failed {
                exclude("reduction failed".into());
                continue;
            }
            // A half-wave-plate target is one star by design (a SOFI target with one
            // component lost its companion).
            if t.half_wave_plate.is_some() && t.components.len() == 1 {
                exclude("a single star: no Delta-gamma (it needs two components)".into());
                continue;
            }
            if t.components.len() != 2 {
                exclude(format!("{} component(s), need 2", t.components.len()));
                continue;
            }
            let (a, b) = (&t.components[0], &t.components[1]);
            for c in [a, b] {
                if c.sigma_p.is_finite() && c.sigma_p > 0.0 {
                    s.all_sigma_p_percent.push(100.0 * c.sigma_p);
                }
            }
            let finite = |c: &Component| c.gamma_deg.is_finite() && c.p.is_finite() && c.sigma_p.is_finite();
            if !finite(a) || !finite(b) {
                exclude("non-finite P, sigma_P or gamma".into());
                continue;
            }
            let uncalibrated = [a, b].iter().any(|c| crate::calibration::is_uncalibrated(c));
            n_uncalibrated += usize::from(uncalibrated);
            if uncalibrated && !allow_uncalibrated {
                exclude("uncalibrated: no instrumental calibration (q, u carry the instrument's offset)".into());
                continue;
            }
            let failing: Vec<&str> = [a, b].iter().filter(|c| !passes(c)).map(|c| c.name.as_str()).collect();
            if !failing.is_empty() {
                exclude(format!("component(s) {} below the P/sigma cut", failing.join(", ")));
                continue;
            }
            let dg = fold_delta_gamma(a.gamma_deg, b.gamma_deg);
            if let Some(stored) = t.delta_gamma_deg {
                if (stored - dg).abs() > 1e-6 {
                    s.warnings.push(format!(
                        "{}: stored delta_gamma_deg {stored} differs from |gamma_A - gamma_B| folded = {dg}; using {dg}",
                        t.object
                    ));
                }
            }
            // The foreground-subtracted Delta-gamma recomputed from the components' q, u
            // and the foreground (which a user may have filled or edited), as the raw one.
            let dg_fg = t.fg_corrected_delta_gamma();
            match (t.delta_gamma_fg_corrected_deg, dg_fg) {
                (Some(stored), Some(d)) if (stored - d).abs() > 1e-6 => s.warnings.push(format!(
                    "{}: stored delta_gamma_fg_corrected_deg {stored} differs from the one the components and the \
                     foreground give, {d}; using {d}",
                    t.object
                )),
                (Some(stored), None) if stored.is_finite() => s.warnings.push(format!(
                    "{}: stored delta_gamma_fg_corrected_deg {stored} without a valid foreground; not used",
                    t.object
                )),
                _ => {}
            }
            let error = delta_gamma_error(t, a, b);
            s.binaries.push(SampleBinary {
                object: t.object.clone(),
                delta_gamma_deg: dg,
                p_percent: [100.0 * a.p_debiased, 100.0 * b.p_debiased],
                sigma_p_percent: [100.0 * a.sigma_p, 100.0 * b.sigma_p],
                sigma_delta_gamma_deg: error.map(|e| e.0),
                sigma_source: error.map(|e| e.1),
                delta_gamma_interval_deg: t
                    .delta_gamma_interval_deg
                    .filter(|[lo, hi]| lo.is_finite() && hi.is_finite()),
                delta_gamma_fg_corrected_deg: dg_fg,
                foreground_percent: t.foreground.as_ref().map(foreground_percent),
            });
        }
        if n_uncalibrated > 0 {
            s.warnings.push(if allow_uncalibrated {
                format!(
                    "{n_uncalibrated} binary(ies) without an instrumental calibration taken in \
                     (--allow-uncalibrated): their Delta-gamma is biased"
                )
            } else {
                format!(
                    "{n_uncalibrated} binary(ies) left out: no instrumental calibration (flagged 'uncalibrated'; \
                     their q, u carry the instrument's offset and fake an alignment); --allow-uncalibrated takes them"
                )
            });
        }
        s
    }

    /// Number of binaries.
    pub fn len(&self) -> usize {
        self.binaries.len()
    }

    /// True when no binary qualifies.
    pub fn is_empty(&self) -> bool {
        self.binaries.is_empty()
    }

    /// The Delta-gamma values, degrees.
    pub fn delta_gamma_deg(&self) -> Vec<f64> {
        self.binaries.iter().map(|b| b.delta_gamma_deg).collect()
    }

    /// (Delta gamma, Delta gamma after subtracting the binary's own foreground) of the
    /// binaries that have the latter, deg.
    pub fn fg_corrected_pairs(&self) -> Vec<(f64, f64)> {
        self.binaries
            .iter()
            .filter_map(|b| b.delta_gamma_fg_corrected_deg.map(|a| (b.delta_gamma_deg, a)))
            .collect()
    }

    /// Debiased P of every component in the sample (2 per binary), percent.
    pub fn p_percent(&self) -> Vec<f64> {
        self.binaries.iter().flat_map(|b| b.p_percent).collect()
    }

    /// The Delta-gamma errors of the sample: the sigmas, their sources, the large ones.
    pub fn errors(&self) -> SampleErrors {
        let mut e = SampleErrors::default();
        for b in &self.binaries {
            match b.sigma_source {
                Some(ErrorSource::Propagated) => e.n_propagated += 1,
                Some(ErrorSource::ComponentStat) => e.n_component_stat += 1,
                Some(ErrorSource::ComponentTotal) => e.n_component_total += 1,
                None => e.n_without_error += 1,
            }
            e.sigmas_deg.extend(b.sigma_delta_gamma_deg);
            if is_large(b.sigma_delta_gamma_deg, b.delta_gamma_interval_deg) {
                e.large.push(LargeError {
                    object: b.object.clone(),
                    delta_gamma_deg: b.delta_gamma_deg,
                    sigma_deg: b.sigma_delta_gamma_deg,
                    interval_deg: b.delta_gamma_interval_deg,
                });
            }
        }
        e
    }

    /// Each binary's noise: the sigma_P of A and B, percent (sample order).
    pub fn noise_percent(&self) -> Vec<[f64; 2]> {
        self.binaries.iter().map(|b| b.sigma_p_percent).collect()
    }

    /// Median sigma_P of the sample's components (2 per binary), percent.
    pub fn median_sample_sigma_p_percent(&self) -> Option<f64> {
        median(&self.binaries.iter().flat_map(|b| b.sigma_p_percent).collect::<Vec<_>>())
    }

    /// Each binary's own foreground, percent (None where the catalog has none).
    pub fn foregrounds(&self) -> Vec<Option<ForegroundQu>> {
        self.binaries.iter().map(|b| b.foreground_percent).collect()
    }

    /// Median sigma_P over all measured components of two-component targets, percent.
    pub fn median_sigma_p_percent(&self) -> Option<f64> {
        median(&self.all_sigma_p_percent)
    }
}

pub use crate::numeric::median_finite as median;
