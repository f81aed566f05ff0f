//! The profile sections of an instrument that is not modulated like SOFI: how the analyzer
//! angle is set (`[modulation]`), how the field turns on the detector (`[field_rotation]`),
//! which files are darks, skies and science when the headers are not ESO's (`[classify]`),
//! where the two beams fall (`[beams]`) and how a single pointing is measured
//! (`[single_pointing]`). Every section is optional: a profile without them (SOFI's) is
//! reduced exactly as before, and none of them is written into a SOFI catalog's provenance.
//! docs/instruments.md describes each key; [`super::Profile::validate`] checks them and
//! names the key of any bad value.
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::header::Header;

/// How the analyzer angle of a frame is set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ModulationKind {
    /// The whole instrument turns on the sky (SOFI: the rotator's position angle, POSANG,
    /// gives phi = s POSANG + theta0; orientations and dithers, the ESO template).
    #[default]
    RotateInstrument,
    /// A half-wave plate in front of a fixed Wollaston: phi = 2 theta + theta0 with theta the
    /// plate angle in the header (`keyword`), frames grouped into plate cycles.
    HalfWavePlate,
    /// The analyzer angle itself is in each file's header (`keyword`): phi = value + theta0.
    PerFile,
}

impl ModulationKind {
    /// The profile's spelling.
    pub fn name(self) -> &'static str {
        match self {
            ModulationKind::RotateInstrument => "rotate_instrument",
            ModulationKind::HalfWavePlate => "half_wave_plate",
            ModulationKind::PerFile => "per_file",
        }
    }
}

/// `[modulation]`: how the analyzer angle is set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Modulation {
    /// `rotate_instrument` (SOFI, the default), `half_wave_plate` or `per_file`.
    #[serde(default)]
    pub kind: ModulationKind,
    /// The header keyword of the plate angle (`half_wave_plate`) or of the analyzer angle
    /// (`per_file`), deg. Required by both.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keyword: Option<String>,
    /// A science frame is used only when this rule holds (e.g. the plate is in the beam:
    /// `{ keyword = "PCUNAME", equals = "hwp_center" }`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub in_beam: Option<KeywordRule>,
    /// theta0, deg: the analyzer's angle on the sky at plate angle 0 once the field rotation
    /// is removed (phi_sky = 2 theta + theta0 + field offset). The instrument-frame results
    /// are given with theta0 = 0.
    #[serde(default)]
    pub zero_point_deg: f64,
    /// Its 1-sigma uncertainty, deg (a systematic error of every angle on the sky).
    #[serde(default = "default_sigma_zero_point")]
    pub sigma_zero_point_deg: f64,
    /// Where `zero_point_deg` comes from, in words (written into the catalog).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub zero_point_source: String,
    /// Tolerance of a plate angle about its cycle position (0, 22.5, 45, 67.5 deg), deg.
    #[serde(default = "default_tolerance")]
    pub tolerance_deg: f64,
}

fn default_sigma_zero_point() -> f64 {
    5.0
}

fn default_tolerance() -> f64 {
    1.0
}

impl Modulation {
    /// The plate angle of a frame as [`crate::profile`]'s half-wave-plate model uses it, deg:
    /// the keyword's value (`half_wave_plate`) or half the analyzer angle (`per_file`, so
    /// that phi = 2 x this + theta0 is the header's angle). Errors name the file and key; a
    /// value beyond +-720 deg is refused ([`Header::get_angle_deg`]).
    pub fn plate_deg(&self, h: &Header) -> Result<f64> {
        let key = self.keyword.as_deref().unwrap_or_default();
        let v = h.get_angle_deg(key)?;
        Ok(match self.kind {
            ModulationKind::PerFile => 0.5 * v,
            _ => v,
        })
    }
}

/// How the field turns on the detector between frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum FieldRotationKind {
    /// The sky keeps its orientation on the detector (a derotator following the field, or
    /// SOFI's rotator set to a position angle on the sky).
    #[default]
    SkyFixed,
    /// The pupil is fixed on the detector and the sky turns with the parallactic angle
    /// (e.g. NIRC2's 'vertical angle' mode): the analyzer's angle on the sky is the
    /// instrument's plus the parallactic angle (and any further `terms`).
    PupilTracking,
}

/// One header angle added to the analyzer's angle on the sky: `factor x value`, deg.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AngleTerm {
    /// The keyword (deg).
    pub keyword: String,
    /// Its factor.
    pub factor: f64,
}

/// `[field_rotation]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct FieldRotation {
    /// `sky_fixed` (default) or `pupil_tracking`.
    #[serde(default)]
    pub kind: FieldRotationKind,
    /// The parallactic-angle keyword of `pupil_tracking` (deg; added with factor +1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parang_keyword: Option<String>,
    /// Further header angles of the optical train between the modulator and the sky (e.g.
    /// an image rotator after the plate), each `factor x value` added.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub terms: Vec<AngleTerm>,
}

impl FieldRotation {
    /// The offset of the analyzer's angle on the sky from its angle in the instrument, deg,
    /// for one frame: 0 for `sky_fixed`; `PARANG + sum(factor x keyword)` for
    /// `pupil_tracking`. Errors name the file and the keyword; each angle must be finite and
    /// within +-720 deg ([`Header::get_angle_deg`]).
    pub fn sky_offset_deg(&self, h: &Header) -> Result<f64> {
        match self.kind {
            FieldRotationKind::SkyFixed => Ok(0.0),
            FieldRotationKind::PupilTracking => {
                let key = self.parang_keyword.as_deref().unwrap_or_default();
                let mut a = h.get_angle_deg(key)?;
                for t in &self.terms {
                    a += t.factor * h.get_angle_deg(&t.keyword)?;
                }
                Ok(a)
            }
        }
    }
}

/// A test of one header keyword: its value (as text, blanks trimmed, case ignored) equals
/// `equals` or contains `contains` (exactly one of the two is given).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeywordRule {
    /// The keyword.
    pub keyword: String,
    /// The value it must equal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub equals: Option<String>,
    /// A text its value must contain.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contains: Option<String>,
}

impl KeywordRule {
    /// Whether the header passes the test (an absent keyword never does).
    pub fn matches(&self, h: &Header) -> bool {
        let Some(v) = h.opt_str(&self.keyword) else {
            return false;
        };
        let v = v.trim().to_lowercase();
        match (&self.equals, &self.contains) {
            (Some(e), _) => v == e.trim().to_lowercase(),
            (None, Some(c)) => v.contains(&c.trim().to_lowercase()),
            (None, None) => false,
        }
    }

    /// The rule in words, e.g. `SHRNAME = 'closed'`.
    pub fn describe(&self) -> String {
        match (&self.equals, &self.contains) {
            (Some(e), _) => format!("{} = '{e}'", self.keyword),
            (None, Some(c)) => format!("{} contains '{c}'", self.keyword),
            (None, None) => format!("{} (no test)", self.keyword),
        }
    }
}

/// `[classify]`: the roles of files whose headers are not ESO's. A file is a dark when any
/// `dark` rule holds, else a sky frame when any `sky` rule holds, else science when every
/// `science` rule holds; else it is not used (and the catalog says which rule failed).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Classify {
    /// Dark frames (any rule).
    #[serde(default)]
    pub dark: Vec<KeywordRule>,
    /// Sky frames (any rule): the sky of matching plate angle and, combined over whole
    /// plate cycles, the flat field.
    #[serde(default)]
    pub sky: Vec<KeywordRule>,
    /// Science frames (every rule).
    #[serde(default)]
    pub science: Vec<KeywordRule>,
}

/// The role [`Classify`] gives a file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Role {
    /// A dark frame.
    Dark,
    /// A sky frame.
    Sky,
    /// A science frame.
    Science,
    /// Not used, with the reason.
    NotUsed(String),
}

impl Classify {
    /// The role of a file.
    pub fn role(&self, h: &Header) -> Role {
        if self.dark.iter().any(|r| r.matches(h)) {
            Role::Dark
        } else if self.sky.iter().any(|r| r.matches(h)) {
            Role::Sky
        } else if let Some(r) = self.science.iter().find(|r| !r.matches(h)) {
            Role::NotUsed(format!(
                "not a dark, not a sky frame, and not science: {} fails (value {})",
                r.describe(),
                h.opt_str(&r.keyword)
                    .map_or("absent".to_string(), |v| format!("'{}'", v.trim()))
            ))
        } else {
            Role::Science
        }
    }
}

/// `[beams]`: the detector rows of each beam of a Wollaston without a focal mask (each beam
/// a full-width region), 0-based half-open. The e image of a star is at its o image plus
/// `geometry.eo_offset_px`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Beams {
    /// Rows of the ordinary beam.
    pub o_rows: [usize; 2],
    /// Rows of the extraordinary beam.
    pub e_rows: [usize; 2],
    /// How far the measured e - o offset may lie from `geometry.eo_offset_px`, px.
    #[serde(default = "default_offset_tolerance")]
    pub offset_tolerance_px: f64,
    /// How far the o/e flux ratio may lie from 1 for two images to be one star's.
    #[serde(default = "default_ratio_tolerance")]
    pub flux_ratio_tolerance: f64,
}

fn default_offset_tolerance() -> f64 {
    3.0
}

fn default_ratio_tolerance() -> f64 {
    0.2
}

/// Where the sky of a single pointing comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum SkySource {
    /// The sky frame at the same plate angle, scaled and offset per beam by a least-squares
    /// fit on the pixels beyond `sky_fit_min_radius_px` from the star.
    #[default]
    SkyFrames,
    /// The median of an annulus around each image (`sky_annulus_px`).
    Annulus,
}

/// `[single_pointing]`: one target per frame, no dithers (the star stays on the same
/// pixels): how its sky, centre and flux are measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SinglePointing {
    /// `sky_frames` (default) or `annulus`.
    #[serde(default)]
    pub sky: SkySource,
    /// `sky_frames`: fit the sky frame's scale and offset beyond this radius, px.
    #[serde(default = "default_sky_fit_radius")]
    pub sky_fit_min_radius_px: f64,
    /// `annulus`: inner and outer radius of the sky annulus, px.
    #[serde(default = "default_sky_annulus")]
    pub sky_annulus_px: [f64; 2],
    /// The photometric aperture: an annulus `[r_in, r_out]` px (r_in = 0: a circle), r_in
    /// outside a saturated core.
    pub aperture_px: [f64; 2],
    /// The annulus over which the centre of 180-degree symmetry is found, px (a saturated
    /// core has no usable peak or centroid).
    #[serde(default = "default_centre_annulus")]
    pub centre_annulus_px: [f64; 2],
    /// The symmetry centre is searched within this distance of the brightest smoothed
    /// pixel, px.
    #[serde(default = "default_search")]
    pub search_radius_px: f64,
    /// A pixel of the master dark further than this from its median is bad, ADU.
    #[serde(default = "default_hot")]
    pub hot_pixel_adu: f64,
}

fn default_sky_fit_radius() -> f64 {
    200.0
}
fn default_sky_annulus() -> [f64; 2] {
    [60.0, 80.0]
}
fn default_centre_annulus() -> [f64; 2] {
    [9.0, 40.0]
}
fn default_search() -> f64 {
    12.0
}
fn default_hot() -> f64 {
    300.0
}

/// Check the sections of a profile that has them; errors name the key.
pub(super) fn validate(p: &super::Profile) -> std::result::Result<(), String> {
    let kind = p.modulation_kind();
    let pupil = p
        .field_rotation
        .as_ref()
        .is_some_and(|f| f.kind == FieldRotationKind::PupilTracking);
    if let Some(m) = &p.modulation {
        if m.kind != ModulationKind::RotateInstrument && m.keyword.as_deref().is_none_or(|k| k.trim().is_empty()) {
            return Err(format!(
                "modulation.kind = {} needs modulation.keyword (the header keyword of the angle)",
                m.kind.name()
            ));
        }
        for (k, v) in [
            ("modulation.zero_point_deg", m.zero_point_deg),
            ("modulation.sigma_zero_point_deg", m.sigma_zero_point_deg),
            ("modulation.tolerance_deg", m.tolerance_deg),
        ] {
            if !v.is_finite() {
                return Err(format!("{k} = {v} must be a finite number"));
            }
        }
        if !(0.0..=90.0).contains(&m.sigma_zero_point_deg) {
            return Err(format!(
                "modulation.sigma_zero_point_deg = {} must be in [0, 90]",
                m.sigma_zero_point_deg
            ));
        }
        if !(m.tolerance_deg > 0.0 && m.tolerance_deg < 11.25) {
            return Err(format!(
                "modulation.tolerance_deg = {} must be in (0, 11.25) (half the 22.5-deg step of a plate cycle)",
                m.tolerance_deg
            ));
        }
        if let Some(r) = &m.in_beam {
            check_rule("modulation.in_beam", r)?;
        }
    }
    if let Some(f) = &p.field_rotation {
        if pupil && f.parang_keyword.as_deref().is_none_or(|k| k.trim().is_empty()) {
            return Err("field_rotation.kind = pupil_tracking needs field_rotation.parang_keyword".into());
        }
        for (i, t) in f.terms.iter().enumerate() {
            if !t.factor.is_finite() || t.keyword.trim().is_empty() {
                return Err(format!(
                    "field_rotation.terms[{i}]: keyword '{}', factor {} (a keyword and a finite factor)",
                    t.keyword, t.factor
                ));
            }
        }
    }
    if pupil && kind == ModulationKind::RotateInstrument {
        return Err(
            "field_rotation.kind = pupil_tracking needs modulation.kind = half_wave_plate or per_file \
                    (the rotate_instrument reduction assumes a sky-fixed field)"
                .into(),
        );
    }
    if let Some(c) = &p.classify {
        for (name, rules) in [("dark", &c.dark), ("sky", &c.sky), ("science", &c.science)] {
            for (i, r) in rules.iter().enumerate() {
                check_rule(&format!("classify.{name}[{i}]"), r)?;
            }
        }
    }
    let ny = p.geometry.ny;
    if let Some(b) = &p.beams {
        for (k, r) in [("beams.o_rows", b.o_rows), ("beams.e_rows", b.e_rows)] {
            if r[0] >= r[1] || r[1] > ny {
                return Err(format!("{k} = [{}, {}) is not inside 0..{ny}", r[0], r[1]));
            }
        }
        if b.o_rows[0] < b.e_rows[1] && b.e_rows[0] < b.o_rows[1] {
            return Err(format!(
                "beams.o_rows = [{}, {}) and beams.e_rows = [{}, {}) overlap",
                b.o_rows[0], b.o_rows[1], b.e_rows[0], b.e_rows[1]
            ));
        }
        if !(b.offset_tolerance_px > 0.0 && b.offset_tolerance_px <= 100.0) {
            return Err(format!(
                "beams.offset_tolerance_px = {} must be in (0, 100]",
                b.offset_tolerance_px
            ));
        }
        if !(b.flux_ratio_tolerance > 0.0 && b.flux_ratio_tolerance < 1.0) {
            return Err(format!(
                "beams.flux_ratio_tolerance = {} must be in (0, 1)",
                b.flux_ratio_tolerance
            ));
        }
    }
    if let Some(s) = &p.single_pointing {
        let pairs = [
            ("single_pointing.aperture_px", s.aperture_px),
            ("single_pointing.sky_annulus_px", s.sky_annulus_px),
            ("single_pointing.centre_annulus_px", s.centre_annulus_px),
        ];
        for (k, [a, b]) in pairs {
            if !(a.is_finite() && b.is_finite() && a >= 0.0 && b > a && b <= 1000.0) {
                return Err(format!("{k} = [{a}, {b}] must satisfy 0 <= r_in < r_out <= 1000 px"));
            }
        }
        for (k, v) in [
            ("single_pointing.sky_fit_min_radius_px", s.sky_fit_min_radius_px),
            ("single_pointing.search_radius_px", s.search_radius_px),
            ("single_pointing.hot_pixel_adu", s.hot_pixel_adu),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{k} = {v} must be a finite number > 0"));
            }
        }
    }
    if kind != ModulationKind::RotateInstrument {
        for (what, present) in [
            ("[beams]", p.beams.is_some()),
            ("[classify]", p.classify.is_some()),
            ("[single_pointing]", p.single_pointing.is_some()),
        ] {
            if !present {
                return Err(format!("modulation.kind = {} needs a {what} section", kind.name()));
            }
        }
    }
    let d = &p.detector;
    for (k, v) in [
        ("detector.gain_keyword", &d.gain_keyword),
        ("detector.read_noise_keyword", &d.read_noise_keyword),
    ] {
        if v.as_deref().is_some_and(|s| s.trim().is_empty()) {
            return Err(format!("{k} is empty (leave it out to use the number)"));
        }
    }
    Ok(())
}

fn check_rule(key: &str, r: &KeywordRule) -> std::result::Result<(), String> {
    if r.keyword.trim().is_empty() {
        return Err(format!("{key}.keyword is empty"));
    }
    if r.equals.is_some() == r.contains.is_some() {
        return Err(format!(
            "{key} (keyword {}): give exactly one of equals = ... or contains = ...",
            r.keyword
        ));
    }
    Ok(())
}

/// A detector number read from the header when the profile names a keyword, else the
/// profile's number; an error names the file, the keyword and the value when it is not a
/// positive finite number.
pub(super) fn number_or_keyword(h: &Header, keyword: Option<&str>, number: f64, what: &str) -> Result<f64> {
    let Some(k) = keyword else {
        return Ok(number);
    };
    let v = h.get_f64(k)?;
    if !(v > 0.0) {
        return Err(Error::BadKeyword {
            path: h.path.clone(),
            keyword: k.to_string(),
            value: crate::text::short_number(v),
            reason: format!("{what} must be > 0"),
        });
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::super::Profile;
    use super::*;

    fn nirc2() -> Profile {
        Profile::embedded("nirc2").expect("embedded").expect("valid")
    }

    fn header(cards: &[(&str, crate::header::HeaderValue)]) -> Header {
        let mut h = Header::new("n0932.fits.gz");
        for (k, v) in cards {
            h.set(k, v.clone());
        }
        h
    }

    /// The embedded NIRC2 profile: a half-wave plate read from PCUPR, pupil tracking with
    /// PARANG, EL and ROTPDEST, header gain and read noise, summed coadds; SOFI's has none of
    /// these sections and serializes exactly the keys it had before (its catalogs'
    /// provenance is unchanged).
    #[test]
    fn nirc2_profile_describes_a_half_wave_plate() {
        let p = nirc2();
        assert_eq!(p.name, "NIRC2");
        assert_eq!(p.modulation_kind(), ModulationKind::HalfWavePlate);
        assert_eq!(p.modulation.as_ref().unwrap().keyword.as_deref(), Some("PCUPR"));
        assert_eq!(
            p.field_rotation.as_ref().unwrap().kind,
            FieldRotationKind::PupilTracking
        );
        assert!(p.detector.coadds_summed);
        assert_eq!(p.keywords.ndit, "COADDS");
        assert_eq!(p.geometry.eo_offset_px, [-13.0, -505.0]);
        assert_eq!(
            Profile::embedded("NIRC2 ").map(|r| r.unwrap().name),
            Some("NIRC2".into())
        );
        assert!(Profile::embedded("nirc3").is_none());
        let sofi = Profile::sofi();
        assert_eq!(Profile::embedded("sofi").unwrap().unwrap(), sofi);
        assert_eq!(sofi.modulation_kind(), ModulationKind::RotateInstrument);
        let v = toml::Value::try_from(&sofi).unwrap();
        let keys: Vec<&String> = v.as_table().unwrap().keys().collect();
        assert_eq!(
            keys,
            [
                "angles",
                "detector",
                "geometry",
                "keywords",
                "match",
                "name",
                "photometry",
                "telescope"
            ]
        );
        let det: Vec<&String> = v["detector"].as_table().unwrap().keys().collect();
        assert_eq!(
            det,
            [
                "gain_e_per_adu",
                "linear_limit_adu",
                "nonlin_coeff_per_adu",
                "nonlinear_warn_adu",
                "read_noise_e",
                "saturation_adu"
            ]
        );
    }

    /// The analyzer's turn on the sky is PARANG - EL - ROTPDEST for NIRC2 (0 for a sky-fixed
    /// field); the gain and read noise come from the header; a missing or bad keyword is an
    /// error naming it.
    #[test]
    fn angles_and_detector_numbers_come_from_the_header() {
        use crate::header::HeaderValue as V;
        let p = nirc2();
        let h = header(&[
            ("PARANG", V::Float(215.07)),
            ("EL", V::Float(77.17)),
            ("ROTPDEST", V::Float(77.87)),
            ("PCUPR", V::Float(22.4975)),
            ("DETGAIN", V::Float(8.0)),
            ("DETRN", V::Float(40.0)),
        ]);
        let f = p.field_rotation.as_ref().unwrap();
        assert!((f.sky_offset_deg(&h).unwrap() - (215.07 - 77.17 - 77.87)).abs() < 1e-12);
        assert_eq!(FieldRotation::default().sky_offset_deg(&h).unwrap(), 0.0);
        assert_eq!(p.modulation.as_ref().unwrap().plate_deg(&h).unwrap(), 22.4975);
        // `per_file`: the header's angle is the analyzer's, i.e. twice a plate's.
        let per_file = p.with_overrides(&["modulation.kind=\"per_file\"".into()]).unwrap();
        assert_eq!(
            per_file.modulation.as_ref().unwrap().plate_deg(&h).unwrap(),
            0.5 * 22.4975
        );
        assert_eq!(
            (p.detector.gain_of(&h).unwrap(), p.detector.read_noise_of(&h).unwrap()),
            (8.0, 40.0)
        );
        let no_el = header(&[("PARANG", V::Float(215.07)), ("ROTPDEST", V::Float(77.87))]);
        let e = f.sky_offset_deg(&no_el).unwrap_err().to_string();
        assert!(e.contains("EL") && e.contains("n0932"), "{e}");
        let mut bad = h.clone();
        bad.set("DETGAIN", -8.0);
        let e = p.detector.gain_of(&bad).unwrap_err().to_string();
        assert!(e.contains("DETGAIN") && e.contains("-8"), "{e}");
        // SOFI's numbers stay the profile's.
        assert_eq!(Profile::sofi().detector.gain_of(&bad).unwrap(), 5.4);
    }

    /// A header angle that is no angle (1e300, beyond two turns, or not a number) is refused
    /// naming the file, the keyword and the value; two turns are still an angle.
    #[test]
    fn absurd_header_angles_are_refused_by_name() {
        use crate::header::HeaderValue as V;
        let p = nirc2();
        let (m, f) = (p.modulation.as_ref().unwrap(), p.field_rotation.as_ref().unwrap());
        let good = [
            ("PARANG", V::Float(215.07)),
            ("EL", V::Float(77.17)),
            ("ROTPDEST", V::Float(77.87)),
            ("PCUPR", V::Float(22.4975)),
        ];
        for (key, value, shown) in [
            ("PCUPR", V::Float(1e300), "1e300"),
            ("PARANG", V::Float(-1e300), "-1e300"),
            ("EL", V::Float(720.5), "720.5"),
            ("ROTPDEST", V::Str("nan".into()), "nan"),
        ] {
            let mut cards = good.to_vec();
            cards.retain(|c| c.0 != key);
            cards.push((key, value));
            let h = header(&cards);
            let e = if key == "PCUPR" {
                m.plate_deg(&h).unwrap_err()
            } else {
                f.sky_offset_deg(&h).unwrap_err()
            }
            .to_string();
            assert!(
                e.contains(key) && e.to_lowercase().contains(shown) && e.contains("n0932"),
                "{key}: {e}"
            );
        }
        let mut cards = good.to_vec();
        cards[0] = ("PARANG", V::Float(-720.0));
        assert!((f.sky_offset_deg(&header(&cards)).unwrap() - (-720.0 - 77.17 - 77.87)).abs() < 1e-9);
    }

    /// Roles from keyword tests: darks by the shutter, sky frames by OBJECT, science needs the
    /// Wollaston; anything else is not used, naming the test that failed.
    #[test]
    fn files_are_classified_by_keyword_tests() {
        use crate::header::HeaderValue as V;
        let c = nirc2().classify.unwrap();
        let s = |v: &str| V::Str(v.into());
        let base = [
            ("INSTRUME", s("NIRC2")),
            ("FWONAME", s("Wollaston")),
            ("SHRNAME", s("open")),
        ];
        let with = |extra: &[(&str, V)]| {
            let mut cards = base.to_vec();
            cards.extend_from_slice(extra);
            header(&cards)
        };
        assert_eq!(c.role(&with(&[("OBJECT", s("AB Aur_hwp_0.0"))])), Role::Science);
        assert_eq!(c.role(&with(&[("OBJECT", s("sky_flat_hwp_45.0"))])), Role::Sky);
        assert_eq!(
            c.role(&with(&[("OBJECT", s("dark")), ("SHRNAME", s(" Closed "))])),
            Role::Dark
        );
        let Role::NotUsed(why) = c.role(&with(&[("OBJECT", s("AB Aur")), ("FWONAME", s("clear"))])) else {
            panic!("a frame without the Wollaston is not science");
        };
        assert!(
            why.contains("FWONAME = 'Wollaston'") && why.contains("'clear'"),
            "{why}"
        );
    }

    /// Hostile values are refused naming the key.
    #[test]
    fn bad_sections_are_refused_by_key() {
        let p = nirc2();
        for (set, key) in [
            ("modulation.tolerance_deg=20", "modulation.tolerance_deg"),
            ("modulation.tolerance_deg=nan", "modulation.tolerance_deg"),
            ("modulation.sigma_zero_point_deg=100", "modulation.sigma_zero_point_deg"),
            ("modulation.zero_point_deg=inf", "modulation.zero_point_deg"),
            ("modulation.keyword=\"\"", "modulation.keyword"),
            ("modulation.kind=\"quarter_wave\"", "quarter_wave"),
            ("modulation.plate=1", "plate"),
            ("modulation.kind=\"rotate_instrument\"", "pupil_tracking"),
            ("field_rotation.parang_keyword=\"\"", "field_rotation.parang_keyword"),
            ("beams.o_rows=[0, 500]", "overlap"),
            ("beams.e_rows=[0, 2000]", "beams.e_rows"),
            ("beams.flux_ratio_tolerance=1.5", "beams.flux_ratio_tolerance"),
            (
                "single_pointing.aperture_px=[40.0, 18.0]",
                "single_pointing.aperture_px",
            ),
            ("single_pointing.hot_pixel_adu=-1", "single_pointing.hot_pixel_adu"),
            ("single_pointing.sky=\"moon\"", "moon"),
            ("detector.gain_keyword=\"\"", "detector.gain_keyword"),
        ] {
            let e = p.with_overrides(&[set.to_string()]).expect_err(set).to_string();
            assert!(e.contains(key), "{set}: {e}");
        }
        let e = p
            .with_overrides(&[
                "classify.dark=[{ keyword = \"SHRNAME\", equals = \"closed\", contains = \"c\" }]".into(),
            ])
            .unwrap_err()
            .to_string();
        assert!(e.contains("classify.dark[0]") && e.contains("exactly one"), "{e}");
        // A half-wave plate on SOFI's profile needs the sections it lacks.
        let e = Profile::sofi()
            .with_overrides(&[
                "modulation.kind=\"half_wave_plate\"".into(),
                "modulation.keyword=\"X\"".into(),
            ])
            .unwrap_err()
            .to_string();
        assert!(e.contains("[beams]"), "{e}");
        let e = Profile::sofi()
            .with_overrides(&[
                "field_rotation.kind=\"pupil_tracking\"".into(),
                "field_rotation.parang_keyword=\"P\"".into(),
            ])
            .unwrap_err()
            .to_string();
        assert!(e.contains("rotate_instrument"), "{e}");
    }
}
