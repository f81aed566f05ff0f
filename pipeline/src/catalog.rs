//! The JSON catalog: what `sofipol target` / `sofipol night` write and other tools read.
//! Schema documented in docs/catalog-schema.md; keep the two in step.
use serde::{Deserialize, Serialize};

use crate::stokes::inversion::Polarization;

/// Version of the catalog schema written by this build.
pub const SCHEMA_VERSION: &str = "1.0";

/// Reduction outcome of a target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Every stage ran and both components were measured.
    Ok,
    /// Reduced with degradation (missing frames, one component lost...): see flags.
    Partial,
    /// Nothing usable: see `error`.
    Failed,
}

/// One binary component's polarimetry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Component {
    /// "A" (brighter) or "B".
    pub name: String,
    /// q, u, P, gamma and their errors (keys in the JSON as if written here; read through
    /// `Deref`: `c.q`, `c.p_debiased`).
    #[serde(flatten)]
    pub pol: Polarization,
    /// P / sigma_P > 3.
    pub passes_cut: bool,
    /// Per-source flags (e.g. "truncated", "bad_pixels", "saturated", "companion_overlap", "low_snr").
    #[serde(default)]
    pub flags: Vec<String>,
    /// Further per-component fields (fluxes, positions, scatter-based errors...).
    #[serde(flatten, default)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

impl std::ops::Deref for Component {
    type Target = Polarization;
    fn deref(&self) -> &Polarization {
        &self.pol
    }
}

impl std::ops::DerefMut for Component {
    fn deref_mut(&mut self) -> &mut Polarization {
        &mut self.pol
    }
}

/// One target sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Target {
    /// Object name.
    pub object: String,
    /// Outcome.
    pub status: Status,
    /// Error message when failed (or the main degradation when partial).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Components, A first.
    #[serde(default)]
    pub components: Vec<Component>,
    /// |gamma_A - gamma_B| folded into [0, 90] when both components pass the cut.
    #[serde(default)]
    pub delta_gamma_deg: Option<f64>,
    /// Further per-target fields (sequence id, input files, e-o offset, flags...).
    #[serde(flatten, default)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// An input that could not be used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Failure {
    /// File name.
    pub file: String,
    /// Reason.
    pub error: String,
}

/// A whole catalog.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct Catalog {
    /// Schema version.
    #[serde(default)]
    pub schema_version: String,
    /// Targets.
    pub targets: Vec<Target>,
    /// Unusable inputs.
    #[serde(default)]
    pub failures: Vec<Failure>,
    /// Provenance: software version, command line, profile, parameters...
    #[serde(default)]
    pub provenance: serde_json::Value,
    /// Standard stars of the night, reduced as single stars (docs/catalog-schema.md).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub standards: Vec<StandardResult>,
    /// The instrumental calibration applied to the targets (`calibration.json`'s content
    /// and where it came from); absent when none was available.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<serde_json::Value>,
}

/// A standard star's table values, its measurement and the residuals.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StandardResult {
    /// Name in the standards table (the OBJECT when not in the table).
    pub name: String,
    /// OBJECT (or OBS TARG NAME) of the sequence.
    pub object: String,
    /// Sequence id.
    pub sequence: String,
    /// Filter.
    pub filter: String,
    /// Outcome of the reduction.
    pub status: Status,
    /// Table values (absent when the star is not in the table).
    #[serde(default)]
    pub table: Option<crate::standards::StandardStar>,
    /// Measured polarization (sky frame, calibration applied), when measured.
    #[serde(default)]
    pub measured: Option<Component>,
    /// (P - p_table) / sqrt(sigma_P^2 + sigma_p_table^2).
    #[serde(default)]
    pub residual_p_sigma: Option<f64>,
    /// gamma - gamma_table folded into [-90, 90), deg (polarized standards only).
    #[serde(default)]
    pub residual_gamma_deg: Option<f64>,
    /// The angle residual in units of the combined error.
    #[serde(default)]
    pub residual_gamma_sigma: Option<f64>,
    /// What the calibration used it for: "offset", "angles".
    #[serde(default)]
    pub used_for: Vec<String>,
    /// Flags ("not_in_standards_table", "no_table_values_for_filter", ...).
    #[serde(default)]
    pub flags: Vec<String>,
}

/// Fold an angle difference of two axial angles (degrees) into [0, 90].
pub fn fold_delta_gamma(gamma_a_deg: f64, gamma_b_deg: f64) -> f64 {
    let d = (gamma_a_deg - gamma_b_deg).rem_euclid(180.0);
    if d > 90.0 {
        180.0 - d
    } else {
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn catalog_floats_round_trip_bit_exactly() {
        // Regression: serde_json's default float parser is not exact; `merge` and `stats`
        // re-read catalogs, so a merged catalog differed from a single run in the last digit.
        let values: [f64; 5] = [
            0.037803643548976563,
            0.00044009000027138596,
            -9.993711226758646e-24,
            150.23621383361115,
            1.0 / 3.0,
        ];
        for v in values {
            let text = serde_json::to_string(&v).unwrap();
            let back: f64 = serde_json::from_str(&text).unwrap();
            assert_eq!(back.to_bits(), v.to_bits(), "{v:e} -> {text} -> {back:e}");
        }
    }

    #[test]
    fn component_keys_keep_the_documented_order_and_round_trip() {
        use crate::stokes::inversion::{Debias, LinearPolarization};
        let lp = LinearPolarization::from_qu(0.03, -0.04, 0.004, 0.005, Debias::WardleKronberg);
        let mut extra = serde_json::Map::new();
        extra.insert("snr".into(), serde_json::json!(lp.snr));
        let c = Component {
            name: "A".into(),
            pol: lp.pol,
            passes_cut: true,
            flags: vec!["low_snr".into()],
            extra,
        };
        let text = serde_json::to_string(&c).unwrap();
        let keys: Vec<&str> = text.split('"').skip(1).step_by(2).filter(|k| !k.is_empty()).collect();
        let want = [
            "name",
            "A",
            "q",
            "u",
            "sigma_q",
            "sigma_u",
            "p",
            "sigma_p",
            "p_debiased",
            "gamma_deg",
            "sigma_gamma_deg",
            "passes_cut",
            "flags",
            "low_snr",
            "snr",
        ];
        assert_eq!(keys, want, "{text}");
        let back: Component = serde_json::from_str(&text).unwrap();
        assert_eq!(back, c);
        assert_eq!(back.extra.len(), 1, "the flattened fields must not leak into extra");
        // LinearPolarization itself serializes as before: the shared fields, then the S/N measures.
        let lp_text = serde_json::to_string(&lp).unwrap();
        assert!(
            lp_text.starts_with("{\"q\":") && lp_text.ends_with(&format!("\"snr\":{}}}", lp.snr)),
            "{lp_text}"
        );
    }

    #[test]
    fn fold_is_axial_and_symmetric() {
        assert_eq!(fold_delta_gamma(10.0, 170.0), 20.0);
        assert_eq!(fold_delta_gamma(170.0, 10.0), 20.0);
        assert_eq!(fold_delta_gamma(0.0, 90.0), 90.0);
        assert_eq!(fold_delta_gamma(45.0, 45.0), 0.0);
        assert!((fold_delta_gamma(179.9, 0.1) - 0.2).abs() < 1e-9);
    }
}
