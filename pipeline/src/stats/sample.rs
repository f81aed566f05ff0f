//! The Delta-gamma sample of a catalog: binaries whose two components both pass the cut.
use serde::{Deserialize, Serialize};

use crate::catalog::{fold_delta_gamma, Catalog, Component, Status};

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
    pub fn from_catalog(cat: &Catalog, cut: Option<f64>) -> Self {
        let mut s = Self::default();
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
            s.binaries.push(SampleBinary {
                object: t.object.clone(),
                delta_gamma_deg: dg,
                p_percent: [100.0 * a.p_debiased, 100.0 * b.p_debiased],
                sigma_p_percent: [100.0 * a.sigma_p, 100.0 * b.sigma_p],
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

    /// Debiased P of every component in the sample (2 per binary), percent.
    pub fn p_percent(&self) -> Vec<f64> {
        self.binaries.iter().flat_map(|b| b.p_percent).collect()
    }

    /// Median sigma_P over all measured components of two-component targets, percent.
    pub fn median_sigma_p_percent(&self) -> Option<f64> {
        median(&self.all_sigma_p_percent)
    }
}

pub use crate::numeric::median_finite as median;
