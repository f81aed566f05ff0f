//! The catalog's record of a night's photometric calibration (`calibration.photometry`):
//! the zero-point per filter and the standards it came from, or why there is none. Filled
//! by the calibration's photometric stage (`crate::calibration::photometric`).
use serde::{Deserialize, Serialize};

/// The photometric calibration of a night (the catalog's `calibration.photometry`).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PhotometricCalibration {
    /// One zero-point per filter with a usable photometric standard.
    #[serde(default)]
    pub filters: Vec<ZeroPoint>,
    /// Why some or all components have no magnitude (one line each).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

/// The zero-point of one filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ZeroPoint {
    /// The filter.
    pub filter: String,
    /// Magnitude of a source of 1 ADU per second above the atmosphere (airmass 0).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub zero_point_mag: f64,
    /// Its 1-sigma error, mag (the weighted mean's, scaled by the Birge ratio when the
    /// standards' chi^2 lies beyond its 99th percentile).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_zero_point_mag: f64,
    /// Standard deviation of the standards' zero-points (two or more standards), mag.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub scatter_mag: Option<f64>,
    /// The extinction k used, mag per airmass (the profile's).
    #[serde(deserialize_with = "crate::nullable::num")]
    pub extinction_mag_per_airmass: f64,
    /// The standards it was measured from.
    pub standards: Vec<PhotometricStandard>,
}

/// One standard's zero-point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhotometricStandard {
    /// Name in the standards table.
    pub name: String,
    /// Its sequence id.
    pub sequence: String,
    /// The table's magnitude and its error.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub mag: f64,
    /// 1-sigma error of `mag`.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_mag: f64,
    /// The table's band of `mag`, as given.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub mag_band: String,
    /// Measured o+e count rate, ADU per second, and its error.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub rate_adu_per_s: f64,
    /// 1-sigma error of `rate_adu_per_s`.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_rate_adu_per_s: f64,
    /// Mean airmass of its frames (absent when they do not say).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub airmass: Option<f64>,
    /// Its zero-point and error, mag.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub zero_point_mag: f64,
    /// 1-sigma error of `zero_point_mag`.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_zero_point_mag: f64,
}

/// The photometry in one line per filter (and the notes), for the night log and the
/// summary.
pub fn lines(p: &PhotometricCalibration) -> Vec<String> {
    let mut v: Vec<String> = p
        .filters
        .iter()
        .map(|z| {
            let names: Vec<&str> = z.standards.iter().map(|s| s.name.as_str()).collect();
            format!(
                "photometric zero-point {}: ZP = {:.3} +- {:.3} mag (1 ADU/s above the atmosphere; k = {} mag/airmass) from {} standard(s): {}{}",
                z.filter,
                z.zero_point_mag,
                z.sigma_zero_point_mag,
                z.extinction_mag_per_airmass,
                z.standards.len(),
                names.join(", "),
                z.scatter_mag.map_or(String::new(), |s| format!("; scatter {s:.3} mag"))
            )
        })
        .collect();
    v.extend(p.notes.iter().cloned());
    v
}
