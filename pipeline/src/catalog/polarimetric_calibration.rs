//! The polarimetric calibration of a night as `calibration.json` holds it (and a catalog's
//! `calibration`): per filter the offset c, the angle zero-point and parity, the
//! telescope's polarization and their covariance. Only types, here beside the catalog
//! that embeds them: measuring them is the `calibration` module, applying them its
//! `resolve.rs`. (The detector's signature, dark and flat, is the `calib` crate.)
use serde::{Deserialize, Serialize};

use super::Provenance;
use crate::stokes::calibration::{AngleCalibration, Offset};
use crate::stokes::propagation::{CalibrationCovariance, CAL_C, CAL_THETA0};

/// The telescope's polarization of one filter, as measured from the night's standards.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TelescopeCalibration {
    /// p_tel, fraction.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub p_tel: f64,
    /// Its 1-sigma error.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_p_tel: f64,
    /// psi_tel, deg in [0, 180): the angle of the telescope's polarization from the vertical.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub psi_tel_deg: f64,
    /// Its 1-sigma error, deg.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_psi_tel_deg: f64,
    /// `a = p_tel cos 2psi_tel`: the fitted parameter (with `b`; their covariance is in the
    /// filter's `covariance`).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub a: f64,
    /// `b = p_tel sin 2psi_tel`.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub b: f64,
}

/// File name of the calibration product in a calibration directory.
pub const CALIBRATION_FILE: &str = "calibration.json";

/// Version of the `calibration.json` schema.
pub const CALIBRATION_SCHEMA: &str = "1.0";

/// The calibration of one filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FilterCalibration {
    /// Filter name.
    pub filter: String,
    /// Instrumental offset of F (c ~ (1 - k)/(1 + k) + p_inst along the analyzer).
    pub offset: Option<Offset>,
    /// Standards (sequence ids) the offset comes from.
    pub offset_standards: Vec<String>,
    /// Angle zero-point and parity.
    pub angles: Option<AngleCalibration>,
    /// Polarized standards (sequence ids) the angles come from.
    pub angle_standards: Vec<String>,
    /// Covariance of c and theta0 (units of c times deg), when both come from one fit.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub cov_c_theta0_deg: Option<f64>,
    /// Why the standards could not separate c from theta0 (the angles are then the
    /// profile's and every component of the filter is flagged `calibration_incomplete`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incomplete: Option<String>,
    /// The telescope's own polarization, measured from the standards and removed from every
    /// component of the filter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub telescope: Option<TelescopeCalibration>,
    /// Why the telescope's polarization was not measured (too few standards, or all at
    /// nearly the same parallactic angle...): the filter's components are flagged
    /// `telescope_polarization_uncorrected`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub telescope_uncorrected: Option<String>,
    /// Why the standards alone did not separate the telescope's polarization, when
    /// `telescope` was fitted with the profile's mirror prior (its errors then mostly the
    /// prior's); absent when the standards measured it alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub telescope_from_prior: Option<String>,
    /// Covariance of the calibration parameters in the order of `covariance_parameters`
    /// (c, theta0 in deg, the telescope's a and b); zero rows for what was not fitted.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::square"
    )]
    pub covariance: Option<CalibrationCovariance>,
    /// The names of `covariance`'s rows: `["c", "theta0_deg", "tel_a", "tel_b"]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub covariance_parameters: Option<Vec<String>>,
    /// Why theta0 is the profile's (no polarized standard in the filter): its uncertainty
    /// (`angles.sigma_zero_point_deg` of the profile) is then the theta0 variance of
    /// `covariance`, and every component of the filter is flagged
    /// `zero_point_from_profile`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub zero_point_from_profile: Option<String>,
}

impl FilterCalibration {
    /// The covariance of (c, theta0, a, b): `covariance` when written, else built from the
    /// offset's and zero-point's errors and their covariance (files without it).
    pub fn covariance_matrix(&self) -> CalibrationCovariance {
        if let Some(m) = self.covariance {
            return m;
        }
        let mut m = [[0.0; 4]; 4];
        m[CAL_C][CAL_C] = self.offset.map_or(0.0, |o| o.sigma_c.powi(2));
        m[CAL_THETA0][CAL_THETA0] = self.angles.map_or(0.0, |a| a.sigma_theta0_deg.powi(2));
        let cross = if self.offset.is_some() && self.angles.is_some() {
            self.cov_c_theta0_deg.unwrap_or(0.0)
        } else {
            0.0
        };
        m[CAL_C][CAL_THETA0] = cross;
        m[CAL_THETA0][CAL_C] = cross;
        m
    }
}

/// The calibration products of a night (`calibration.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Schema version of this file.
    pub schema_version: String,
    /// Per filter.
    pub filters: Vec<FilterCalibration>,
    /// Input frames of the standards used.
    pub frames: Vec<String>,
    /// Flat-field products (FITS per rotator angle, relative to the calibration
    /// directory). Empty until the flat-field stage is connected.
    #[serde(default)]
    pub flats: Vec<String>,
    /// Where it came from: software, night directory, standards table sources...
    #[serde(default)]
    pub provenance: Provenance,
}

impl Calibration {
    /// The calibration of a filter (case-insensitive).
    pub fn for_filter(&self, filter: &str) -> Option<&FilterCalibration> {
        self.filters
            .iter()
            .find(|f| f.filter.eq_ignore_ascii_case(filter.trim()))
    }
}
