//! The half-wave-plate frames of the simulated nights (the NIRC2 profile shrunk to a
//! 128 x 200 detector): a star's o and e images from the forward model F = q cos 2phi +
//! u sin 2phi with phi on the sky = 2 PCUPR + theta0 + PARANG - EL - ROTPDEST, a
//! plate-dependent sky (also in the sky frames), a dark with a hot pixel, a flat-field
//! gradient, optional photon and read noise. Shared by `pipeline/tests/single_pointing_sim.rs`
//! and the command-line tests (`tests/cli_nirc2.rs`, through `#[path]`).
// Each test file uses a subset of these.
#![allow(dead_code)]

use std::path::Path;

use ndarray::Array2;
use rand::rngs::Xoshiro256PlusPlus;
use rand_distr::{Distribution, StandardNormal};
use sofipol_calib::fits::{write_frame, WriteOptions};
use sofipol_calib::{Frame, Header, Profile};

/// Detector columns.
pub const NX: usize = 128;
/// Detector rows.
pub const NY: usize = 200;
pub const O_POS: (f64, f64) = (60.3, 150.7);
pub const EO: (f64, f64) = (-3.0, -100.0);
pub const Q_SKY: f64 = 0.021;
pub const U_SKY: f64 = -0.013;
pub const THETA0: f64 = 26.0;
/// The sky turns by PARANG - 2 EL per frame: -1.1 deg.
pub const STEP_PARANG: f64 = 1.0;
pub const STEP_EL: f64 = 0.05;

/// The NIRC2 profile shrunk to the simulated detector ([`overrides`]).
pub fn profile() -> Profile {
    Profile::embedded("nirc2")
        .unwrap()
        .unwrap()
        .with_overrides(&overrides())
        .unwrap()
}

/// A flat-field gradient along x only: both beams' rows then have the same median, so the
/// per-beam normalisation leaves no beam imbalance (c = 0) and F is exact.
pub fn flat(x: usize, _y: usize) -> f64 {
    1.0 + 0.1 * (x as f64 / NX as f64)
}

pub fn star(x: usize, y: usize, c: (f64, f64), flux: f64) -> f64 {
    let r2 = (x as f64 - c.0).powi(2) + (y as f64 - c.1).powi(2);
    flux / (2.0 * std::f64::consts::PI * 2.0 * 2.0) * (-0.5 * r2 / 4.0).exp()
}

/// A star: its name (TARGNAME), polarization on the sky and total flux over both beams (ADU
/// summed over the coadds).
pub struct Star {
    pub name: String,
    pub q: f64,
    pub u: f64,
    pub flux: f64,
}

pub struct Shot<'a> {
    pub object: &'a str,
    pub plate: f64,
    pub parang: f64,
    pub el: f64,
    pub shutter: &'a str,
    pub star: Option<&'a Star>,
    pub mjd: f64,
}

/// The detector's noise: photon noise of the light (sky and star, after the flat) with the
/// gain `GAIN_E` e-/ADU, the read noise `RN_E` e- of each of the `COADDS` summed reads,
/// Gaussian (every pixel holds >= 10^4 e-, where Poisson is Gaussian to 1 %). The dark
/// level is a bias: read noise only.
pub struct Noise {
    pub rng: Xoshiro256PlusPlus,
}

pub const GAIN_E: f64 = 8.0;
pub const RN_E: f64 = 40.0;
pub const COADDS: i64 = 45;

pub fn write(dir: &Path, name: &str, s: &Shot<'_>, mut noise: Option<&mut Noise>) {
    let dark = 100.0;
    // Sky per beam, depending on the plate (a polarized sky), the same in sky frames.
    let sky_o = 5000.0 * (1.0 + 0.01 * (4.0 * s.plate).to_radians().cos());
    let sky_e = 5400.0 * (1.0 - 0.01 * (4.0 * s.plate).to_radians().cos());
    let rotpdest = s.el + 0.7;
    let phi = 2.0 * s.plate + THETA0 + s.parang - s.el - rotpdest;
    let (q, u, total) = s.star.map_or((0.0, 0.0, 0.0), |st| (st.q, st.u, st.flux));
    let f = q * (2.0 * phi).to_radians().cos() + u * (2.0 * phi).to_radians().sin();
    let (t_o, t_e) = (1.0, 1.0);
    let (o, e) = (0.5 * total * t_o * (1.0 + f), 0.5 * total * t_e * (1.0 - f));
    let read_var = COADDS as f64 * (RN_E / GAIN_E).powi(2);
    let ec = (O_POS.0 + EO.0, O_POS.1 + EO.1);
    let closed = s.shutter == "closed";
    let data = Array2::from_shape_fn((NY, NX), |(y, x)| {
        let mut v = 0.0;
        if !closed {
            let in_o = y >= 105;
            let in_e = y < 95;
            let sky = if in_o {
                sky_o
            } else if in_e {
                sky_e
            } else {
                sky_o + sky_e
            };
            let mut light = sky;
            if s.star.is_some() {
                light += if in_o { star(x, y, O_POS, o) } else { 0.0 } + if in_e { star(x, y, ec, e) } else { 0.0 };
            }
            v += light * flat(x, y);
        }
        if let Some(n) = noise.as_deref_mut() {
            let z: f64 = StandardNormal.sample(&mut n.rng);
            v += z * (v / GAIN_E + read_var).sqrt();
        }
        let hot = if (x, y) == (20, 30) { 9000.0 } else { 0.0 };
        (v + dark + hot) as f32
    });
    let mut h = Header::new("");
    for (k, v) in [
        ("INSTRUME", "NIRC2"),
        ("FWONAME", "Wollaston"),
        ("FWINAME", "Lp"),
        ("PCUNAME", "hwp_center"),
    ] {
        h.set(k, v);
    }
    h.set("OBJECT", s.object);
    h.set("TARGNAME", s.star.map_or("", |st| st.name.as_str()));
    h.set("SHRNAME", s.shutter);
    h.set("PCUPR", s.plate);
    h.set("PARANG", s.parang);
    h.set("EL", s.el);
    h.set("ROTPDEST", rotpdest);
    h.set("MJD", s.mjd);
    h.set("ITIME", 0.45);
    h.set("COADDS", COADDS);
    h.set("DETGAIN", GAIN_E);
    // A wrong gain (2x) for a profile that reads it instead (the pull test's control).
    h.set("SIMGAIN2", 2.0 * GAIN_E);
    h.set("DETRN", RN_E);
    write_frame(&dir.join(name), &Frame::new(data, h), &WriteOptions::default()).unwrap();
}

/// The profile's overrides as `--set` takes them (`profile()` applies them).
pub fn overrides() -> Vec<String> {
    vec![
        format!("geometry.nx={NX}"),
        format!("geometry.ny={NY}"),
        "geometry.o_sky2=[0, 10]".into(),
        "geometry.e_sky2=[10, 20]".into(),
        "geometry.o_target=[20, 30]".into(),
        "geometry.e_target=[30, 40]".into(),
        "geometry.o_sky1=[40, 50]".into(),
        "geometry.e_sky1=[50, 60]".into(),
        format!("geometry.eo_offset_px=[{}, {}]", EO.0, EO.1),
        "beams.o_rows=[105, 200]".into(),
        "beams.e_rows=[0, 95]".into(),
        "single_pointing.aperture_px=[0.0, 9.0]".into(),
        "single_pointing.centre_annulus_px=[1.5, 9.0]".into(),
        "single_pointing.sky_fit_min_radius_px=25.0".into(),
        "single_pointing.search_radius_px=4.0".into(),
        "detector.linear_limit_adu=1e9".into(),
        "detector.saturation_adu=2e9".into(),
    ]
}

/// A noise-free night in `dir`: 4 sky frames (one per plate position), 2 darks and two
/// plate cycles of `star` (8 frames) under pupil tracking, the sky turning by
/// -(STEP_PARANG + 2 STEP_EL) per frame; the science frames named `{prefix}sci{k}.fits`.
pub fn write_night(dir: &Path, star: &Star, prefix: &str) {
    let plates = [0.0, 45.0, 22.5, 67.5];
    for (k, &p) in plates.iter().enumerate() {
        let shot = Shot {
            object: "sky_flat",
            plate: p,
            parang: 0.0,
            el: 60.0,
            shutter: "open",
            star: None,
            mjd: 1.0 + k as f64 * 1e-3,
        };
        write(dir, &format!("{prefix}sky{k}.fits"), &shot, None);
    }
    for k in 0..2 {
        let shot = Shot {
            object: "dark",
            plate: 0.0,
            parang: 0.0,
            el: 0.0,
            shutter: "closed",
            star: None,
            mjd: 3.0 + k as f64 * 1e-3,
        };
        write(dir, &format!("{prefix}dark{k}.fits"), &shot, None);
    }
    for k in 0..8 {
        let shot = Shot {
            object: "hwp",
            plate: plates[k % 4],
            parang: 215.0 - STEP_PARANG * k as f64,
            el: 77.0 + STEP_EL * k as f64,
            shutter: "open",
            star: Some(star),
            mjd: 2.0 + k as f64 * 1e-3,
        };
        write(dir, &format!("{prefix}sci{k}.fits"), &shot, None);
    }
}
