//! The field stars of a target (`Target::field_stars`): every other point source of its
//! strips, measured like the binary's components (docs/catalog-schema.md, "Field stars").
use serde::{Deserialize, Serialize};

use super::flags::has;
use super::{Component, FlagCode};

/// One field star: where it is, and its polarimetry as a [`Component`] (the same keys, the
/// same per-orientation F that the calibration re-solves q and u from).
///
/// Key order in the JSON: `id`, `usable`, the positions, then the component's keys.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldStar {
    /// `F1`, `F2`, ... in decreasing order of detection S/N (unique within the target).
    pub id: String,
    /// Whether the star's q and u can be used: measured (q finite), not `blended`, not
    /// `faint`, not from flagged dithers only (`used_flagged_dithers`, e.g. a saturated
    /// core or every dither at a strip edge), orientations constraining q and u.
    pub usable: bool,
    /// Its o image in the first frame where the primary was found, detector px (0-based,
    /// whole-detector rows).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub x_px: f64,
    /// See `x_px`.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub y_px: f64,
    /// Separation from the binary's A, arcsec (the companion's convention).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub separation_arcsec: f64,
    /// Position angle from A, deg east of north, [0, 360).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub pa_deg: f64,
    /// Right ascension, deg in [0, 360): A's (the pointing, `Target::ra_deg`) offset by
    /// the separation and PA (absent when the frames have no pointing).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub ra_deg: Option<f64>,
    /// Declination, deg (as `ra_deg`).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub dec_deg: Option<f64>,
    /// Orientations at which it was detected (it is measured at all).
    #[serde(default)]
    pub n_detected: usize,
    /// Best detection S/N (the stacked dithers' 3x3 box above its ring).
    #[serde(default = "crate::nullable::nan", deserialize_with = "crate::nullable::num")]
    pub detection_snr: f64,
    /// q, u, P, gamma, errors, flags, per-orientation F...: a component's keys, `name`
    /// equal to `id`.
    #[serde(flatten)]
    pub star: Component,
}

/// Flags that make a field star unusable (with a q that is not finite).
pub const UNUSABLE: [FlagCode; 4] = [
    FlagCode::Blended,
    FlagCode::Faint,
    FlagCode::UsedFlaggedDithers,
    FlagCode::UndefinedPolarization,
];

/// Smallest S/N of a field star's mean flux for it to be usable.
pub const MIN_FLUX_SNR: f64 = 10.0;

impl FieldStar {
    /// Whether its values can be used (see [`FieldStar::usable`]).
    pub fn judge_usable(&self) -> bool {
        self.star.q.is_finite() && self.star.u.is_finite() && !UNUSABLE.iter().any(|&c| has(&self.star.flags, c))
    }

    /// Set `usable` ([`FieldStar::judge_usable`]); an unusable star never passes the cut.
    pub fn settle(&mut self) {
        self.usable = self.judge_usable();
        if !self.usable {
            self.star.passes_cut = false;
        }
    }

    /// Check what a reader relies on; the error names the key and the value.
    pub fn validate(&self) -> Result<(), String> {
        if self.id.trim().is_empty() {
            return Err("field star with an empty `id`".into());
        }
        for (key, v) in [
            ("x_px", self.x_px),
            ("y_px", self.y_px),
            ("separation_arcsec", self.separation_arcsec),
            ("pa_deg", self.pa_deg),
        ] {
            if !v.is_finite() {
                return Err(format!("field star {}: {key} = {v} is not a number", self.id));
            }
        }
        if self.separation_arcsec < 0.0 {
            return Err(format!(
                "field star {}: separation_arcsec = {} is negative",
                self.id, self.separation_arcsec
            ));
        }
        if let Some(dec) = self.dec_deg.filter(|d| !(-90.0..=90.0).contains(d)) {
            return Err(format!("field star {}: dec_deg = {dec} is not in [-90, 90]", self.id));
        }
        if self.usable && !(self.star.q.is_finite() && self.star.u.is_finite()) {
            return Err(format!(
                "field star {}: usable = true with q = {}, u = {}",
                self.id, self.star.q, self.star.u
            ));
        }
        Ok(())
    }
}

/// Check a target's field stars: each valid ([`FieldStar::validate`]), ids unique.
pub fn validate(stars: &[FieldStar]) -> Result<(), String> {
    let mut ids = std::collections::HashSet::new();
    for s in stars {
        s.validate()?;
        if !ids.insert(s.id.as_str()) {
            return Err(format!("field star id {:?} appears twice", s.id));
        }
    }
    Ok(())
}
