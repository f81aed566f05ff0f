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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::catalog::Flag;
    use crate::stokes::inversion::Polarization;

    fn star(id: &str, q: f64) -> FieldStar {
        let mut c = Component::new(id, Polarization::UNDEFINED);
        c.pol.q = q;
        c.pol.u = 0.01;
        c.flags.push(Flag::with_detail(FlagCode::StripEdge, "2 of 10 dithers"));
        FieldStar {
            id: id.into(),
            usable: q.is_finite(),
            x_px: 100.5,
            y_px: 420.25,
            separation_arcsec: 15.0,
            pa_deg: 60.0,
            ra_deg: Some(81.3),
            dec_deg: Some(-35.1),
            n_detected: 2,
            detection_snr: 250.0,
            star: c,
        }
    }

    /// A field star written and read back is the same (its component's keys flattened in
    /// beside its own), and its flags keep their codes.
    #[test]
    fn a_field_star_round_trips_through_json() {
        let s = star("F1", 0.02);
        let text = serde_json::to_string(&s).unwrap();
        assert!(text.starts_with("{\"id\":\"F1\",\"usable\":true,"), "{text}");
        let back: FieldStar = serde_json::from_str(&text).unwrap();
        // (NaN errors: compared as written.)
        assert_eq!(serde_json::to_string(&back).unwrap(), text);
        assert_eq!((back.id.as_str(), back.star.q, back.x_px), ("F1", 0.02, 100.5));
        assert!(has(&back.star.flags, FlagCode::StripEdge));
        assert!(back.star.extra.is_empty(), "{:?}", back.star.extra);
    }

    /// Validation names the star, the key and the value; ids are unique; `usable` needs q.
    #[test]
    fn validation_refuses_what_a_reader_cannot_use() {
        assert!(validate(&[star("F1", 0.02), star("F2", 0.0)]).is_ok());
        let e = validate(&[star("F1", 0.02), star("F1", 0.0)]).unwrap_err();
        assert!(e.contains("\"F1\" appears twice"), "{e}");
        let mut s = star("F3", f64::NAN);
        s.usable = true;
        assert!(validate(&[s]).unwrap_err().contains("F3: usable = true with q = NaN"));
        let mut s = star("F4", 0.0);
        s.x_px = f64::NAN;
        assert!(validate(&[s]).unwrap_err().contains("F4: x_px = NaN"));
        let mut s = star("F5", 0.0);
        s.dec_deg = Some(91.0);
        assert!(validate(&[s]).unwrap_err().contains("dec_deg = 91"));
        // A blended star is never usable, whatever its numbers.
        let mut s = star("F6", 0.02);
        s.star.flags.push(Flag::new(FlagCode::Blended));
        s.star.passes_cut = true;
        s.settle();
        assert!(!s.usable && !s.star.passes_cut);
    }
}
