//! The `[half_wave_plate]` section of a scene ([`HwpConfig`], its stars [`HwpStar`]): what
//! [`super::Scene`] holds; [`super::hwp`] renders it. Apart from the renderer, so that the
//! scene does not import it.
use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// The `[half_wave_plate]` section of a scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HwpConfig {
    /// Plate positions of one cycle, deg, in observing order.
    pub plate_deg: Vec<f64>,
    /// Cycles per star.
    pub cycles: usize,
    /// Cycles of sky frames (one frame per plate position each), after the stars.
    pub sky_cycles: usize,
    /// Dark frames (shutter closed), last.
    pub darks: usize,
    /// Dark level (bias and dark current) of every frame, ADU (as written).
    pub dark_adu: f64,
    /// Polarization of the sky through the plate (effect `sky`): the o beam's sky is
    /// multiplied by `1 + sky_modulation cos 4 plate`, the e beam's by `1 - ...`; the sky
    /// frames see the same.
    pub sky_modulation: f64,
    /// The site's latitude, deg (default: Keck on Maunakea).
    pub site_lat_deg: f64,
    /// The site's longitude, deg east (default: Keck).
    pub site_lon_deg: f64,
    /// Constant header keywords of every frame (numbers), e.g. the rotator's `ROTPDEST`
    /// of a `[field_rotation]` term; the keywords the simulator computes win.
    pub header: BTreeMap<String, f64>,
    /// x of the o image (default: the pair of images centred on the detector).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub x_px: Option<f64>,
    /// y of the o image (default: the pair of images centred).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub y_px: Option<f64>,
    /// The stars, observed one after the other.
    pub star: Vec<HwpStar>,
}

impl Default for HwpConfig {
    fn default() -> Self {
        HwpConfig {
            plate_deg: vec![0.0, 45.0, 22.5, 67.5],
            cycles: 2,
            sky_cycles: 1,
            darks: 2,
            dark_adu: 100.0,
            sky_modulation: 0.0,
            site_lat_deg: 19.8264,
            site_lon_deg: -155.4747,
            header: BTreeMap::new(),
            x_px: None,
            y_px: None,
            star: Vec::new(),
        }
    }
}

/// One star of a half-wave-plate scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HwpStar {
    /// Name (the target-name keyword and OBJECT).
    pub name: String,
    /// Total flux (o + e), ADU per frame as written (summed over the coadds when the
    /// profile's `detector.coadds_summed`, else averaged).
    pub flux: f64,
    /// Degree of polarization on the sky (fraction).
    #[serde(default)]
    pub p: f64,
    /// Angle, deg east of north.
    #[serde(default)]
    pub gamma_deg: f64,
    /// Declination, deg.
    pub dec_deg: f64,
    /// Hour angle at the star's first exposure, hours.
    pub hour_angle_h: f64,
}
