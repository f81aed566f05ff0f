//! Half-wave-plate scenes: raw frames for a profile whose analyzer is a rotating half-wave
//! plate in front of a Wollaston prism (`[modulation] kind = "half_wave_plate"`, e.g.
//! `--profile nirc2`), reduced by [`crate::single_pointing`].
//!
//! Each star of `[[half_wave_plate.star]]` is observed at one pointing (no dithers, no
//! focal mask) for `cycles` cycles of the plate positions `plate_deg`; then `sky_cycles`
//! cycles of sky frames through the plate and `darks` dark frames. Every frame's header
//! carries what the profile reads: the plate angle (`modulation.keyword`), the keyword
//! rules that put the plate in the beam and give the file its role (`[classify]`), the
//! parallactic angle and the other terms of the angle on the sky (`[field_rotation]`), the
//! gain and read noise keywords, the coadds.
//!
//! A star of polarization (q, u) on the sky puts `I/2 (1 +- F)` into its o and e images,
//! `F = q cos 2 phi + u sin 2 phi`, with the analyzer's angle on the sky `phi = 2 plate +
//! zero_point + sky offset`: the sky offset is the profile's ([`FieldRotation::sky_offset_deg`]
//! of the frame's header; under pupil tracking the parallactic angle of the frame's
//! mid-exposure at the scene's site, minus the terms' keywords).
//!
//! Only listed effects are simulated, each by the function the SOFI simulator uses
//! ([`super::effects`]), in this order: sky (per beam, times `1 +- sky_modulation cos
//! 4 plate`) -> sources (psf | point; interstellar polarization, transparency,
//! throughput) -> flat_field -> photon_noise -> dark level -> read_noise -> cosmic_rays
//! -> bad_pixels -> saturation. The SOFI-only effects (strips, pointing error, dome flats,
//! analyzer angle, telescope polarization, foreground field, non-linearity, instrumental
//! polarization) are refused by name.
use std::collections::BTreeMap;

use ndarray::Array2;
use serde::Serialize;
use sofipol_calib::fits::{write_frame, Bitpix, WriteOptions};
use sofipol_calib::profile::{FieldRotation, KeywordRule, Modulation, ModulationKind, Role};
use sofipol_calib::{Frame, Header, Profile};

use super::pointing::{self, Pointing, Site};
use super::psf::{self, Psf};
use super::scene::{EffectKind, Scene};
use super::truth::DetectorTruth;
use super::{effects, file_slug, EffectCalls};
use crate::error::Error;

pub use super::hwp_scene::{HwpConfig, HwpStar};

/// Most frames of a half-wave-plate scene.
const MAX_FRAMES: usize = 100_000;

/// The effects a half-wave-plate scene may list.
const HWP_EFFECTS: [EffectKind; 11] = [
    EffectKind::Psf,
    EffectKind::Sky,
    EffectKind::PhotonNoise,
    EffectKind::ReadNoise,
    EffectKind::BadPixels,
    EffectKind::FlatField,
    EffectKind::Throughput,
    EffectKind::InterstellarPolarization,
    EffectKind::Transparency,
    EffectKind::CosmicRays,
    EffectKind::Saturation,
];

/// What one frame of a half-wave-plate scene is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HwpRole {
    /// Star `t`'s exposure `k`.
    Science(usize, usize),
    /// Sky frame `k`.
    Sky(usize),
    /// Dark frame `k`.
    Dark(usize),
}

/// Realised parameters of one frame.
#[derive(Debug, Clone, Serialize)]
pub struct HwpFrameTruth {
    /// File name.
    pub file: String,
    /// Plate angle written, deg (0 for darks).
    pub plate_deg: f64,
    /// Pointing at mid-exposure (parallactic angle, altitude...).
    pub pointing: Pointing,
    /// The angle on the sky the profile adds (`[field_rotation]` of this header), deg.
    pub sky_offset_deg: f64,
    /// The analyzer's angle on the sky phi = 2 plate + zero point + sky offset, deg.
    pub phi_sky_deg: f64,
    /// Sky level of one beam (before the plate's modulation), ADU (0 without sky or in a
    /// dark); rows of neither beam see both beams' skies.
    pub sky_level_adu: f64,
    /// Seeing FWHM, px (0 without psf).
    pub fwhm_px: f64,
    /// Transparency factor (1 without the effect).
    pub transparency: f64,
    /// o image (x, y), px (science frames).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub o_xy: Option<[f64; 2]>,
    /// e image (x, y), px.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub e_xy: Option<[f64; 2]>,
    /// o flux, ADU (before flat and noise).
    pub flux_o: f64,
    /// e flux, ADU.
    pub flux_e: f64,
    /// Pixels hit by cosmic rays.
    pub cosmic_ray_pixels: usize,
}

/// One star's truth.
#[derive(Debug, Clone, Serialize)]
pub struct HwpStarTruth {
    /// Name.
    pub name: String,
    /// Total flux (o + e), ADU per frame.
    pub flux: f64,
    /// Right ascension, deg.
    pub ra_deg: f64,
    /// Declination, deg.
    pub dec_deg: f64,
    /// What a perfect reduction reports on the sky: intrinsic + interstellar q.
    pub q: f64,
    /// Sky u.
    pub u: f64,
    /// Degree of (q, u).
    pub p: f64,
    /// Angle of (q, u), deg east of north in [0, 180).
    pub gamma_deg: f64,
    /// The frames, in exposure order.
    pub frames: Vec<HwpFrameTruth>,
}

/// Truth of a half-wave-plate scene (written as truth.json).
#[derive(Debug, Clone, Serialize)]
pub struct HwpTruth {
    /// sofipol version.
    pub software: String,
    /// The scene as parsed.
    pub scene: Scene,
    /// Profile name.
    pub profile: String,
    /// Effects simulated.
    pub effects: Vec<&'static str>,
    /// Effect sections present but not listed (ignored).
    pub ignored_sections: Vec<&'static str>,
    /// The plate keyword and the analyzer zero point used.
    pub plate_keyword: String,
    /// Zero point of phi, deg.
    pub zero_point_deg: f64,
    /// Fixed detector realisations.
    pub detector: DetectorTruth,
    /// Stars.
    pub stars: Vec<HwpStarTruth>,
    /// Sky frames.
    pub skies: Vec<HwpFrameTruth>,
    /// Dark frames.
    pub darks: Vec<String>,
}

/// A prepared half-wave-plate simulation.
pub struct HwpSimulator {
    scene: Scene,
    cfg: HwpConfig,
    profile: Profile,
    modulation: Modulation,
    rotation: Option<FieldRotation>,
    calls: EffectCalls,
    bad: Option<effects::BadPixelMap>,
    flat: Option<Array2<f32>>,
    /// Each star's RA (deg) and first exposure's MJD.
    starts: Vec<(f64, f64)>,
    /// MJD of the first sky frame.
    sky_start: f64,
    site: Site,
}

fn invalid(reason: String) -> Error {
    Error::Scene {
        origin: "scene".into(),
        reason,
    }
}

/// Set `keyword` so that `rule` holds (its `equals` value, else its `contains` text).
fn satisfy(h: &mut Header, rule: &KeywordRule) {
    if let Some(v) = rule.equals.as_ref().or(rule.contains.as_ref()) {
        h.set(&rule.keyword, v.as_str());
    }
}

impl HwpSimulator {
    /// Prepare a half-wave-plate scene for a half-wave-plate profile: refused (naming the
    /// key) when the profile is not one, the scene has no `[half_wave_plate]` stars, lists
    /// an effect this simulation does not make, or has SOFI sources (`[[binary]]`...).
    pub fn new(scene: Scene, profile: Profile) -> crate::error::Result<HwpSimulator> {
        let modulation = profile
            .modulation
            .clone()
            .filter(|m| m.kind == ModulationKind::HalfWavePlate && m.keyword.is_some())
            .ok_or_else(|| {
                invalid(format!(
                    "profile {}: modulation.kind = {} (a half_wave_plate scene needs a half_wave_plate profile with modulation.keyword)",
                    profile.name,
                    profile.modulation_kind().name()
                ))
            })?;
        let cfg = scene.half_wave_plate.clone().ok_or_else(|| {
            invalid(format!(
                "profile {} (modulation.kind = half_wave_plate): the scene needs a [half_wave_plate] section with its stars",
                profile.name
            ))
        })?;
        if let Some(k) = scene.effects.iter().find(|k| !HWP_EFFECTS.contains(k)) {
            return Err(invalid(format!(
                "effects: '{}' is not simulated for a half-wave-plate profile (it may list: {})",
                k.name(),
                HWP_EFFECTS.map(|k| k.name()).join(", ")
            )));
        }
        if !scene.binary.is_empty() || !scene.standard.is_empty() || scene.field_population.is_some() {
            return Err(invalid(
                "binary, standard, field_population: a half-wave-plate scene lists its stars in [[half_wave_plate.star]]"
                    .into(),
            ));
        }
        if cfg.star.is_empty() {
            return Err(invalid("half_wave_plate.star: no star".into()));
        }
        if cfg.plate_deg.is_empty() || cfg.plate_deg.iter().any(|p| !p.is_finite()) {
            return Err(invalid(format!(
                "half_wave_plate.plate_deg = {:?}: give one finite angle or more",
                cfg.plate_deg
            )));
        }
        if cfg.cycles == 0 {
            return Err(invalid("half_wave_plate.cycles = 0 must be >= 1".into()));
        }
        let n = cfg
            .star
            .len()
            .checked_mul(cfg.cycles)
            .and_then(|v| v.checked_mul(cfg.plate_deg.len()))
            .and_then(|v| {
                cfg.sky_cycles
                    .checked_mul(cfg.plate_deg.len())
                    .and_then(|s| v.checked_add(s))
            })
            .and_then(|v| v.checked_add(cfg.darks))
            .unwrap_or(usize::MAX);
        if n > MAX_FRAMES {
            return Err(invalid(format!(
                "half_wave_plate: {n} frames (stars x cycles x plate positions + skies + darks) is more than {MAX_FRAMES}"
            )));
        }
        for (what, v) in [
            ("dark_adu", cfg.dark_adu),
            ("site_lat_deg", cfg.site_lat_deg),
            ("site_lon_deg", cfg.site_lon_deg),
            ("sky_modulation", cfg.sky_modulation),
        ] {
            if !v.is_finite() {
                return Err(invalid(format!("half_wave_plate.{what} = {v} must be finite")));
            }
        }
        if !(cfg.sky_modulation.abs() < 1.0) || !(cfg.site_lat_deg.abs() <= 90.0) {
            return Err(invalid(format!(
                "half_wave_plate: sky_modulation = {} must be in (-1, 1) and site_lat_deg = {} in [-90, 90]",
                cfg.sky_modulation, cfg.site_lat_deg
            )));
        }
        for st in &cfg.star {
            if !(st.flux >= 0.0) || !(0.0..1.0).contains(&st.p) || !st.gamma_deg.is_finite() {
                return Err(invalid(format!(
                    "half_wave_plate.star '{}': flux = {} must be >= 0, p = {} in [0, 1), gamma_deg = {} finite",
                    st.name, st.flux, st.p, st.gamma_deg
                )));
            }
            if !(st.dec_deg.abs() <= 90.0) || !(st.hour_angle_h.abs() <= 12.0) {
                return Err(invalid(format!(
                    "half_wave_plate.star '{}': dec_deg = {} must be in [-90, 90] and hour_angle_h = {} in [-12, 12]",
                    st.name, st.dec_deg, st.hour_angle_h
                )));
            }
        }
        let rotation = profile.field_rotation.clone();
        if let Some(r) = &rotation {
            for t in &r.terms {
                if t.keyword != profile.keywords.altitude && !cfg.header.contains_key(&t.keyword) {
                    return Err(invalid(format!(
                        "half_wave_plate.header: no value for {} (a term of profile {}'s [field_rotation])",
                        t.keyword, profile.name
                    )));
                }
            }
        }
        if profile.classify.is_none() {
            return Err(invalid(format!(
                "profile {}: no [classify] section (the simulator marks darks and skies by its rules)",
                profile.name
            )));
        }
        let (ny, nx) = (profile.geometry.ny, profile.geometry.nx);
        let calls = EffectCalls::default();
        let dseed = scene.detector_seed.unwrap_or(scene.seed);
        let bad = scene
            .has(EffectKind::BadPixels)
            .then(|| effects::bad_pixel_map(&calls, dseed, &scene.bad_pixels.clone().unwrap_or_default(), ny, nx));
        let flat = scene
            .has(EffectKind::FlatField)
            .then(|| effects::flat_field_map(&calls, dseed, &scene.flat_field.clone().unwrap_or_default(), ny, nx));
        let o = &scene.observation;
        let start = effects::mjd_from_date_time(&o.date, &o.start_ut).ok_or_else(|| {
            invalid(format!(
                "observation: date = '{}', start_ut = '{}' (expected YYYY-MM-DD and HH:MM:SS)",
                o.date, o.start_ut
            ))
        })?;
        let site = Site {
            lat_deg: cfg.site_lat_deg,
            lon_deg: cfg.site_lon_deg,
            height_m: 0.0,
        };
        let step_d = (o.dit_s * o.ndit as f64 + o.overhead_s) / 86400.0;
        let per_star = cfg.cycles * cfg.plate_deg.len();
        let mut starts = Vec::new();
        let mut t0 = start;
        for st in &cfg.star {
            let ra = pointing::wrap_360(pointing::lst_deg(t0, &site) - 15.0 * st.hour_angle_h);
            starts.push((ra, t0));
            t0 += per_star as f64 * step_d;
        }
        let sim = HwpSimulator {
            cfg,
            modulation,
            rotation,
            calls,
            bad,
            flat,
            starts,
            sky_start: t0,
            site,
            scene,
            profile,
        };
        // Both images on the detector, each in its beam's rows.
        let [xo, yo] = sim.o_xy();
        let (xe, ye) = sim.profile.geometry.e_image_of((xo, yo));
        let g = &sim.profile.geometry;
        let on = |x: f64, y: f64, rows: Option<[usize; 2]>| {
            let [r0, r1] = rows.unwrap_or([0, g.ny]);
            (0.0..g.nx as f64 - 1.0).contains(&x) && (r0 as f64..r1 as f64 - 1.0).contains(&y)
        };
        if !on(xo, yo, sim.profile.beams.as_ref().map(|b| b.o_rows))
            || !on(xe, ye, sim.profile.beams.as_ref().map(|b| b.e_rows))
        {
            return Err(invalid(format!(
                "half_wave_plate: x_px, y_px = ({xo}, {yo}) puts the o image at ({xo}, {yo}) and the e image at ({xe}, {ye}): each must lie on the {} x {} detector in its beam's rows (profile {}'s beams.o_rows, e_rows)",
                g.nx, g.ny, sim.profile.name
            )));
        }
        // Every file name distinct, every header given its role by the profile's rules.
        let names = sim.file_names();
        let mut seen = std::collections::HashSet::new();
        for n in &names {
            if !seen.insert(n) {
                return Err(invalid(format!(
                    "half_wave_plate.star: two files would be named {n} (star names that differ only in punctuation, or a star named 'sky' or 'dark')"
                )));
            }
        }
        for r in sim.roles() {
            let h = sim.header(r).0;
            let want = match r {
                HwpRole::Science(..) => Role::Science,
                HwpRole::Sky(_) => Role::Sky,
                HwpRole::Dark(_) => Role::Dark,
            };
            let got = sim.profile.classify.as_ref().map(|c| c.role(&h));
            if got.as_ref() != Some(&want) {
                return Err(invalid(format!(
                    "{}: profile {}'s [classify] reads it as {:?}, not {:?} (a star's name matching a sky or dark rule?)",
                    sim.file_name(r),
                    sim.profile.name,
                    got,
                    want
                )));
            }
        }
        Ok(sim)
    }

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Calls of each effect function so far.
    pub fn calls(&self) -> BTreeMap<&'static str, u64> {
        self.calls.snapshot()
    }

    /// The fixed bad-pixel map (1 = bad), when the effect is listed.
    pub fn bad_pixel_mask(&self) -> Option<Array2<u8>> {
        self.bad.as_ref().map(|b| b.mask.clone())
    }

    /// Exposures per star.
    pub fn frames_per_star(&self) -> usize {
        self.cfg.cycles * self.cfg.plate_deg.len()
    }

    /// Every frame in observing order: the stars' exposures, the sky frames, the darks.
    pub fn roles(&self) -> Vec<HwpRole> {
        let n = self.frames_per_star();
        (0..self.cfg.star.len())
            .flat_map(|t| (0..n).map(move |k| HwpRole::Science(t, k)))
            .chain((0..self.cfg.sky_cycles * self.cfg.plate_deg.len()).map(HwpRole::Sky))
            .chain((0..self.cfg.darks).map(HwpRole::Dark))
            .collect()
    }

    /// A frame's file name: `<PROFILE>_<scene>_<star>_NN.fits`, `..._sky_NN`, `..._dark_NN`.
    pub fn file_name(&self, r: HwpRole) -> String {
        let ext = if self.scene.observation.compress {
            "fits.fz"
        } else {
            "fits"
        };
        let (what, k) = match r {
            HwpRole::Science(t, k) => (file_slug(&self.cfg.star[t].name), k),
            HwpRole::Sky(k) => ("sky".to_string(), k),
            HwpRole::Dark(k) => ("dark".to_string(), k),
        };
        format!(
            "{}_{}_{what}_{:02}.{ext}",
            file_slug(&self.profile.name),
            file_slug(&self.scene.name),
            k + 1
        )
    }

    /// Every file [`HwpSimulator::write_to_dir`] writes (the frames, `truth.json`).
    pub fn file_names(&self) -> Vec<String> {
        let mut v: Vec<String> = self.roles().into_iter().map(|r| self.file_name(r)).collect();
        v.push("truth.json".into());
        v
    }

    /// Bytes written at most (every frame uncompressed with two header blocks).
    pub fn output_bytes(&self) -> u64 {
        let g = &self.profile.geometry;
        let px = if self.scene.observation.bitpix == 16 { 2 } else { 4 };
        let frame = (g.nx as u64 * g.ny as u64 * px).div_ceil(2880) * 2880 + 2 * 2880;
        (self.roles().len() as u64).saturating_mul(frame)
    }

    /// Plate angle of frame `r`.
    fn plate(&self, r: HwpRole) -> f64 {
        let p = &self.cfg.plate_deg;
        match r {
            HwpRole::Science(_, k) | HwpRole::Sky(k) => p[k % p.len()],
            HwpRole::Dark(_) => p[0],
        }
    }

    /// MJD of the start of frame `r`, and its pointing (RA, Dec).
    fn when(&self, r: HwpRole) -> (f64, f64, f64) {
        let o = &self.scene.observation;
        let step_d = (o.dit_s * o.ndit as f64 + o.overhead_s) / 86400.0;
        match r {
            HwpRole::Science(t, k) => {
                let (ra, t0) = self.starts[t];
                (t0 + k as f64 * step_d, ra, self.cfg.star[t].dec_deg)
            }
            // Sky frames and darks: near the last star, where it pointed.
            HwpRole::Sky(k) => {
                let (ra, _) = *self.starts.last().expect("a star");
                let dec = self.cfg.star.last().expect("a star").dec_deg;
                (self.sky_start + k as f64 * step_d, ra, dec)
            }
            HwpRole::Dark(k) => {
                let (ra, _) = *self.starts.last().expect("a star");
                let dec = self.cfg.star.last().expect("a star").dec_deg;
                let nsky = self.cfg.sky_cycles * self.cfg.plate_deg.len();
                (self.sky_start + (nsky + k) as f64 * step_d, ra, dec)
            }
        }
    }

    /// The header of frame `r`, its pointing at mid-exposure and the angle on the sky the
    /// profile reads from it (offset, phi).
    fn header(&self, r: HwpRole) -> (Header, Pointing, f64, f64) {
        let p = &self.profile;
        let kw = &p.keywords;
        let o = &self.scene.observation;
        let (mjd, ra, dec) = self.when(r);
        let mid = mjd + 0.5 * o.dit_s * o.ndit as f64 / 86400.0;
        let pt = pointing::pointing(&self.site, mid, ra, dec);
        let mut h = Header::new("");
        for (k, v) in &self.cfg.header {
            h.set(k, *v);
        }
        h.set(&kw.instrument, p.matching.instrument.as_str());
        let classify = p.classify.as_ref().expect("checked in new");
        for rule in &classify.science {
            satisfy(&mut h, rule);
        }
        if let Some(rule) = &self.modulation.in_beam {
            satisfy(&mut h, rule);
        }
        let plate = self.plate(r);
        h.set(self.modulation.keyword.as_deref().expect("checked in new"), plate);
        match r {
            HwpRole::Science(t, _) => {
                let name = self.cfg.star[t].name.as_str();
                h.set(&kw.object, name);
                h.set(&kw.targ_name, name);
            }
            HwpRole::Sky(_) => {
                h.set(&kw.object, "sky");
                if let Some(rule) = classify.sky.first() {
                    satisfy(&mut h, rule);
                }
            }
            HwpRole::Dark(_) => {
                h.set(&kw.object, "dark");
                if let Some(rule) = classify.dark.first() {
                    satisfy(&mut h, rule);
                }
            }
        }
        h.set(&kw.date_obs, effects::iso_from_mjd(mjd, true).as_str());
        h.set(&kw.mjd_obs, mjd);
        h.set(&kw.exptime, o.dit_s);
        h.set(&kw.dit, o.dit_s);
        h.set(&kw.ndit, o.ndit as i64);
        h.set(&kw.filter, o.filter.as_str());
        h.set(&kw.ra, ra);
        h.set(&kw.dec, dec);
        h.set(&kw.altitude, pt.alt_deg);
        h.set(&kw.airmass, pt.airmass);
        let parang_key = self
            .rotation
            .as_ref()
            .and_then(|f| f.parang_keyword.clone())
            .unwrap_or_else(|| kw.parang.clone());
        h.set(&parang_key, pt.parang_deg);
        let d = &p.detector;
        if let Some(k) = &d.gain_keyword {
            h.set(k, d.gain_e_per_adu);
        }
        if let Some(k) = &d.read_noise_keyword {
            h.set(k, d.read_noise_e);
        }
        let offset = self
            .rotation
            .as_ref()
            .map_or(Ok(0.0), |f| f.sky_offset_deg(&h))
            .expect("every keyword of [field_rotation] is written");
        let phi = 2.0 * plate + self.modulation.zero_point_deg + offset;
        (h, pt, offset, phi)
    }

    /// Star `t`'s polarization on the sky (intrinsic + interstellar).
    fn star_qu(&self, t: usize) -> (f64, f64) {
        let st = &self.cfg.star[t];
        let two_g = 2.0 * st.gamma_deg.to_radians();
        let (mut q, mut u) = (st.p * two_g.cos(), st.p * two_g.sin());
        if self.scene.has(EffectKind::InterstellarPolarization) {
            let c = self.scene.interstellar_polarization.clone().unwrap_or_default();
            let a = 2.0 * c.angle_deg.to_radians();
            q += c.p * a.cos();
            u += c.p * a.sin();
        }
        (q, u)
    }

    /// The o image position, px: the scene's `x_px`, `y_px`, else the point that centres
    /// the pair of images on the detector (the e image at the profile's `eo_offset_px`).
    pub fn o_xy(&self) -> [f64; 2] {
        let g = &self.profile.geometry;
        let (x, y) = (
            (g.nx as f64 - g.eo_offset_px[0]) / 2.0 - 0.5,
            (g.ny as f64 - g.eo_offset_px[1]) / 2.0 - 0.5,
        );
        [self.cfg.x_px.unwrap_or(x), self.cfg.y_px.unwrap_or(y)]
    }

    /// Render frame `r`.
    pub fn frame(&self, r: HwpRole) -> (String, Frame, HwpFrameTruth) {
        let s = &self.scene;
        let p = &self.profile;
        let g = &p.geometry;
        let d = &p.detector;
        let (h, pt, offset, phi) = self.header(r);
        let key = match r {
            HwpRole::Science(t, k) => (t as u64, k as u64),
            HwpRole::Sky(k) => (1 << 32, k as u64),
            HwpRole::Dark(k) => ((1 << 32) + 1, k as u64),
        };
        let plate = self.plate(r);
        let mut img = Array2::<f32>::zeros((g.ny, g.nx));
        let mut truth = HwpFrameTruth {
            file: self.file_name(r),
            plate_deg: plate,
            pointing: pt,
            sky_offset_deg: offset,
            phi_sky_deg: phi,
            sky_level_adu: 0.0,
            fwhm_px: 0.0,
            transparency: 1.0,
            o_xy: None,
            e_xy: None,
            flux_o: 0.0,
            flux_e: 0.0,
            cosmic_ray_pixels: 0,
        };
        let dark = matches!(r, HwpRole::Dark(_));
        if !dark && s.has(EffectKind::Sky) {
            let c = s.sky.clone().unwrap_or_default();
            let level = effects::sky_level(&self.calls, s.seed, &c, key);
            truth.sky_level_adu = level;
            let m = self.cfg.sky_modulation * (4.0 * plate).to_radians().cos();
            let beams = p.beams.as_ref();
            let in_rows = |rows: Option<[usize; 2]>, y: usize| rows.is_none_or(|b| (b[0]..b[1]).contains(&y));
            // Rows of neither beam see both beams' skies.
            let factor: Vec<f32> = (0..g.ny)
                .map(|y| {
                    let (o, e) = (in_rows(beams.map(|b| b.o_rows), y), in_rows(beams.map(|b| b.e_rows), y));
                    let both = !o && !e;
                    (f64::from(o || both) * (1.0 + m) + f64::from(e || both) * (1.0 - m)) as f32
                })
                .collect();
            let mut sky = Array2::<f32>::zeros((g.ny, g.nx));
            effects::sky(&self.calls, &mut sky, level, &c);
            for ((y, _), v) in sky.indexed_iter_mut() {
                *v *= factor[y];
            }
            img += &sky;
        }
        if let HwpRole::Science(t, _) = r {
            let st = &self.cfg.star[t];
            let (q, u) = self.star_qu(t);
            let a = 2.0 * phi.to_radians();
            let f = q * a.cos() + u * a.sin();
            let trans = if s.has(EffectKind::Transparency) {
                effects::transparency(&self.calls, s.seed, &s.transparency.clone().unwrap_or_default(), key)
            } else {
                1.0
            };
            let (t_o, t_e) = if s.has(EffectKind::Throughput) {
                effects::throughput(&self.calls, &s.throughput.clone().unwrap_or_default())
            } else {
                (1.0, 1.0)
            };
            let fo = 0.5 * st.flux * trans * t_o * (1.0 + f);
            let fe = 0.5 * st.flux * trans * t_e * (1.0 - f);
            let psf = if s.has(EffectKind::Psf) {
                effects::frame_psf(
                    &self.calls,
                    s.seed,
                    &s.psf.clone().unwrap_or_default(),
                    key,
                    g.pixscale_arcsec,
                )
            } else {
                Psf::Point
            };
            let [xo, yo] = self.o_xy();
            let (xe, ye) = g.e_image_of((xo, yo));
            psf::add_stamp(&mut img, &psf::render(psf, xo, yo), fo);
            psf::add_stamp(&mut img, &psf::render(psf, xe, ye), fe);
            truth.fwhm_px = if s.has(EffectKind::Psf) { psf.fwhm_px() } else { 0.0 };
            truth.transparency = trans;
            truth.o_xy = Some([xo, yo]);
            truth.e_xy = Some([xe, ye]);
            truth.flux_o = fo;
            truth.flux_e = fe;
        }
        // The detector. Summed coadds: the photo-electrons of the frame are value x gain,
        // each coadd's read adds its noise; averaged reads (NDIT): value x gain x NDIT.
        let n = s.observation.ndit.max(1) as f64;
        let (gain_eff, read_sigma) = if d.coadds_summed {
            (d.gain_e_per_adu, d.read_noise_e / d.gain_e_per_adu * n.sqrt())
        } else {
            (
                d.effective_gain(s.observation.ndit),
                d.read_variance_adu2(s.observation.ndit).sqrt(),
            )
        };
        if let Some(flat) = &self.flat {
            self.calls.hit(EffectKind::FlatField);
            ndarray::Zip::from(&mut img).and(flat).for_each(|v, &r| *v *= r);
        }
        if s.has(EffectKind::PhotonNoise) {
            effects::photon_noise(&self.calls, &mut img, s.seed, key, gain_eff);
        }
        img.mapv_inplace(|v| v + self.cfg.dark_adu as f32);
        if s.has(EffectKind::ReadNoise) {
            effects::read_noise(&self.calls, &mut img, s.seed, key, read_sigma);
        }
        if s.has(EffectKind::CosmicRays) {
            truth.cosmic_ray_pixels = effects::cosmic_rays(
                &self.calls,
                &mut img,
                s.seed,
                key,
                &s.cosmic_rays.clone().unwrap_or_default(),
            );
        }
        if let Some(bad) = &self.bad {
            effects::apply_bad_pixels(&self.calls, &mut img, bad);
        }
        if s.has(EffectKind::Saturation) {
            let per_read = s
                .saturation
                .clone()
                .unwrap_or_default()
                .level_adu
                .unwrap_or(d.saturation_adu);
            let level = if d.coadds_summed { per_read * n } else { per_read };
            effects::saturation(&self.calls, &mut img, level);
        }
        let frame = Frame::new(img, h).with_history(
            "simulate",
            format!(
                "scene '{}' seed {} {}; effects: [{}]",
                s.name,
                s.seed,
                match r {
                    HwpRole::Science(t, k) => format!("star '{}' exposure {}", self.cfg.star[t].name, k + 1),
                    HwpRole::Sky(k) => format!("sky frame {}", k + 1),
                    HwpRole::Dark(k) => format!("dark {}", k + 1),
                },
                s.effects.iter().map(|e| e.name()).collect::<Vec<_>>().join(", ")
            ),
        );
        (truth.file.clone(), frame, truth)
    }

    /// The truth from the frames' (in [`HwpSimulator::roles`] order).
    fn truth(&self, frames: Vec<(HwpRole, HwpFrameTruth)>) -> HwpTruth {
        let s = &self.scene;
        let mut detector = DetectorTruth::of_pixels(self.bad.as_ref(), self.flat.as_ref());
        if s.has(EffectKind::Throughput) {
            let c = s.throughput.clone().unwrap_or_default();
            detector.throughput = Some(super::truth::ThroughputTruth { t_e: c.t_e, t_o: c.t_o });
        }
        let mut stars: Vec<HwpStarTruth> = self
            .cfg
            .star
            .iter()
            .enumerate()
            .map(|(t, st)| {
                let (q, u) = self.star_qu(t);
                HwpStarTruth {
                    name: st.name.clone(),
                    flux: st.flux,
                    ra_deg: self.starts[t].0,
                    dec_deg: st.dec_deg,
                    q,
                    u,
                    p: q.hypot(u),
                    gamma_deg: (0.5 * u.atan2(q).to_degrees()).rem_euclid(180.0),
                    frames: Vec::new(),
                }
            })
            .collect();
        let (mut skies, mut darks) = (Vec::new(), Vec::new());
        for (r, f) in frames {
            match r {
                HwpRole::Science(t, _) => stars[t].frames.push(f),
                HwpRole::Sky(_) => skies.push(f),
                HwpRole::Dark(_) => darks.push(f.file),
            }
        }
        HwpTruth {
            software: format!("sofipol {}", env!("CARGO_PKG_VERSION")),
            scene: s.clone(),
            profile: self.profile.name.clone(),
            effects: s.effects.iter().map(|e| e.name()).collect(),
            ignored_sections: s.ignored_sections(),
            plate_keyword: self.modulation.keyword.clone().unwrap_or_default(),
            zero_point_deg: self.modulation.zero_point_deg,
            detector,
            stars,
            skies,
            darks,
        }
    }

    /// Every frame in memory with the truth (tests, small scenes).
    pub fn run_in_memory(&self) -> (Vec<(String, Frame)>, HwpTruth) {
        use rayon::prelude::*;
        let roles = self.roles();
        let out: Vec<(String, Frame, HwpFrameTruth)> = roles.par_iter().map(|&r| self.frame(r)).collect();
        let mut frames = Vec::new();
        let mut truths = Vec::new();
        for ((name, f, t), &r) in out.into_iter().zip(&roles) {
            frames.push((name, f));
            truths.push((r, t));
        }
        (frames, self.truth(truths))
    }

    /// Simulate every frame into `dir` (FITS, atomically; BITPIX and compression from the
    /// scene's `observation`) with `truth.json`; `on_frame` after each frame.
    pub fn write_to_dir(
        &self,
        dir: &std::path::Path,
        on_frame: &(dyn Fn(&str) + Sync),
    ) -> crate::error::Result<HwpTruth> {
        use rayon::prelude::*;
        std::fs::create_dir_all(dir).map_err(|source| Error::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let o = &self.scene.observation;
        let opts = WriteOptions {
            bitpix: if o.bitpix == 16 { Bitpix::I16 } else { Bitpix::F32 },
            compress: o.compress,
            with_variance_and_mask: false,
        };
        let roles = self.roles();
        let truths = roles
            .par_iter()
            .map(|&r| {
                let (name, frame, t) = self.frame(r);
                write_frame(&dir.join(&name), &frame, &opts).map_err(|e| Error::calib("simulated frame", e))?;
                on_frame(&name);
                Ok((r, t))
            })
            .collect::<crate::error::Result<Vec<_>>>()?;
        let truth = self.truth(truths);
        crate::io::write_json_atomic(&dir.join("truth.json"), &truth).map_err(|e| Error::calib("truth", e))?;
        Ok(truth)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(effects: &str, extra: &str) -> Scene {
        Scene::from_toml(
            &format!(
                r#"
name = "t"
seed = 3
effects = [{effects}]
[observation]
dit_s = 0.5
ndit = 10
filter = "Lp"
date = "2025-12-08"
start_ut = "08:00:00"
overhead_s = 5.0
[half_wave_plate]
header = {{ ROTPDEST = 12.5 }}
{extra}
[[half_wave_plate.star]]
name = "Star A"
flux = 1e6
p = 0.04
gamma_deg = 30.0
dec_deg = 0.0
hour_angle_h = -0.5
"#
            ),
            "test",
        )
        .unwrap()
    }

    fn nirc2_small() -> Profile {
        Profile::embedded("nirc2")
            .unwrap()
            .unwrap()
            .with_overrides(&[
                "geometry.nx=64".into(),
                "geometry.ny=120".into(),
                "geometry.o_sky2=[0, 10]".into(),
                "geometry.e_sky2=[10, 20]".into(),
                "geometry.o_target=[20, 30]".into(),
                "geometry.e_target=[30, 40]".into(),
                "geometry.o_sky1=[40, 50]".into(),
                "geometry.e_sky1=[50, 60]".into(),
                "geometry.eo_offset_px=[-3.0, -60.0]".into(),
                "beams.o_rows=[62, 120]".into(),
                "beams.e_rows=[0, 58]".into(),
            ])
            .unwrap()
    }

    /// Without noise, the o and e images hold I/2 (1 +- F) with F from the sky (q, u) at
    /// phi = 2 plate + 26 + PARANG - EL - ROTPDEST (NIRC2's relation, written out here),
    /// PARANG the parallactic angle of the header's own hour angle and declination.
    #[test]
    fn beams_follow_the_forward_model_of_each_header() {
        let sim = HwpSimulator::new(scene("", ""), nirc2_small()).unwrap();
        let (frames, truth) = sim.run_in_memory();
        assert_eq!(frames.len(), 8 + 4 + 2);
        let st = &truth.stars[0];
        let (q, u) = (0.04 * 60f64.to_radians().cos(), 0.04 * 60f64.to_radians().sin());
        assert!((st.q - q).abs() < 1e-12 && (st.u - u).abs() < 1e-12);
        for (name, f) in frames.iter().take(8) {
            let h = &f.header;
            let plate = h.get_f64("PCUPR").unwrap();
            let (parang, el) = (h.get_f64("PARANG").unwrap(), h.get_f64("EL").unwrap());
            assert_eq!(h.get_f64("ROTPDEST").unwrap(), 12.5);
            let phi = (2.0 * plate + 26.0 + parang - el - 12.5).to_radians();
            let ff = q * (2.0 * phi).cos() + u * (2.0 * phi).sin();
            let [xo, yo] = sim.o_xy();
            assert_eq!([xo, yo], [33.0, 89.5]);
            let at = |x: f64, y: f64| f.data[[y.floor() as usize, x.floor() as usize]] as f64;
            // A point source shares its flux between the four nearest pixels.
            let sum4 = |x: f64, y: f64| at(x, y) + at(x + 1.0, y) + at(x, y + 1.0) + at(x + 1.0, y + 1.0) - 4.0 * 100.0;
            let (o, e) = (sum4(xo, yo), sum4(xo - 3.0, yo - 60.0));
            assert!((o - 5e5 * (1.0 + ff)).abs() < 0.1, "{name}: o {o}");
            assert!((e - 5e5 * (1.0 - ff)).abs() < 0.1, "{name}: e {e}");
            // The parallactic angle of the header's hour angle at Keck.
            let lst = pointing::lst_deg(h.get_f64("MJD").unwrap() + 2.5 / 86400.0, &sim.site);
            let ha = pointing::wrap_180(lst - h.get_f64("RA").unwrap());
            let want = pointing::parallactic_angle_deg(ha, 0.0, 19.8264);
            assert!((parang - want).abs() < 1e-9, "{parang} vs {want}");
        }
        // The pupil turns: PARANG advances with the hour angle over the star's frames.
        let pa: Vec<f64> = frames[..8]
            .iter()
            .map(|(_, f)| f.header.get_f64("PARANG").unwrap())
            .collect();
        assert!(pa.windows(2).all(|w| w[1] > w[0]), "{pa:?}");
        // Roles by the profile's own rules.
        let c = sim.profile.classify.clone().unwrap();
        let roles: Vec<Role> = frames.iter().map(|(_, f)| c.role(&f.header)).collect();
        assert!(roles[..8].iter().all(|r| *r == Role::Science));
        assert!(roles[8..12].iter().all(|r| *r == Role::Sky));
        assert!(roles[12..].iter().all(|r| *r == Role::Dark));
        // Nothing listed, nothing called; darks hold the dark level only.
        assert!(sim.calls().is_empty(), "{:?}", sim.calls());
        assert!(frames[12].1.data.iter().all(|&v| v == 100.0));
    }

    /// Photon and read noise of summed coadds: a dark's variance is NDIT (RN/gain)^2, a sky
    /// frame's adds sky/gain.
    #[test]
    fn noise_of_summed_coadds() {
        let sim = HwpSimulator::new(
            scene("\"sky\", \"photon_noise\", \"read_noise\"", "").clone(),
            nirc2_small(),
        )
        .unwrap();
        let var = |f: &Frame| {
            let v: Vec<f64> = f.data.iter().map(|&x| x as f64).collect();
            let m = v.iter().sum::<f64>() / v.len() as f64;
            (m, v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64)
        };
        let (_, dark, _) = sim.frame(HwpRole::Dark(0));
        let (_, vd) = var(&dark);
        let want = 10.0 * (40.0f64 / 8.0).powi(2);
        // 7680 pixels: the variance's relative standard error is sqrt(2/7680) = 1.6 %.
        assert!((vd / want - 1.0).abs() < 0.065, "{vd} vs {want}");
        let mut s = scene("\"sky\", \"photon_noise\", \"read_noise\"", "");
        s.sky = Some(crate::sim::scene::SkyConfig {
            level_adu: 20000.0,
            gradient_x: 0.0,
            gradient_y: 0.0,
            frame_change_frac: 0.0,
        });
        let sim = HwpSimulator::new(s, nirc2_small()).unwrap();
        let (_, sky, t) = sim.frame(HwpRole::Sky(1));
        // Rows of the o beam only: the level of one beam's sky.
        let rows = sky.data.slice(ndarray::s![62..120, ..]).to_owned();
        let (m, v) = var(&Frame::new(rows, Header::new("")));
        assert!((m - 20100.0).abs() < 5.0, "{m}");
        let want = 20000.0 / 8.0 + 10.0 * 25.0;
        assert!((v / want - 1.0).abs() < 0.1, "{v} vs {want}");
        assert_eq!(t.sky_level_adu, 20000.0);
    }

    #[test]
    fn refusals_name_the_key() {
        let e = HwpSimulator::new(scene("", ""), Profile::sofi())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("modulation.kind"), "{e}");
        let e = HwpSimulator::new(scene("\"strips\"", ""), nirc2_small())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("'strips'"), "{e}");
        let mut s = scene("", "");
        s.half_wave_plate.as_mut().unwrap().header.clear();
        let e = HwpSimulator::new(s, nirc2_small()).err().unwrap().to_string();
        assert!(e.contains("ROTPDEST"), "{e}");
        let mut s = scene("", "");
        s.half_wave_plate.as_mut().unwrap().star[0].name = "sky survey star".into();
        let e = HwpSimulator::new(s, nirc2_small()).err().unwrap().to_string();
        assert!(e.contains("[classify]"), "{e}");
    }
}
