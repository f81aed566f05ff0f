//! The half-wave-plate reduction on frames made from a known polarization (the NIRC2
//! profile, shrunk to a 128 x 200 detector): a star's o and e images from the forward
//! model F = q cos 2phi + u sin 2phi with phi on the sky = 2 PCUPR + theta0 + PARANG - EL -
//! ROTPDEST, a plate-dependent sky (also in the sky frames), a dark with a hot pixel, a
//! flat-field gradient, unequal beam transmissions. Noise-free: every step is exact, so
//! (q, u) must come back to 1e-6 in the instrument frame (each cycle) and on the sky (least
//! squares over the frames, each with its own rotation).
use std::path::Path;

use ndarray::Array2;
use sofipol_calib::fits::{write_frame, WriteOptions};
use sofipol_calib::{Frame, Header, Profile};
use sofipol_pipeline::single_pointing;

const NX: usize = 128;
const NY: usize = 200;
const O_POS: (f64, f64) = (60.3, 150.7);
const EO: (f64, f64) = (-3.0, -100.0);
const Q_SKY: f64 = 0.021;
const U_SKY: f64 = -0.013;
const THETA0: f64 = 26.0;
/// The sky turns by PARANG - 2 EL per frame: -1.1 deg.
const STEP_PARANG: f64 = 1.0;
const STEP_EL: f64 = 0.05;

fn profile() -> Profile {
    Profile::embedded("nirc2")
        .unwrap()
        .unwrap()
        .with_overrides(&[
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
        ])
        .unwrap()
}

/// A flat-field gradient along x only: both beams' rows then have the same median, so the
/// per-beam normalisation leaves no beam imbalance (c = 0) and F is exact.
fn flat(x: usize, _y: usize) -> f64 {
    1.0 + 0.1 * (x as f64 / NX as f64)
}

fn star(x: usize, y: usize, c: (f64, f64), flux: f64) -> f64 {
    let r2 = (x as f64 - c.0).powi(2) + (y as f64 - c.1).powi(2);
    flux / (2.0 * std::f64::consts::PI * 2.0 * 2.0) * (-0.5 * r2 / 4.0).exp()
}

struct Shot<'a> {
    object: &'a str,
    plate: f64,
    parang: f64,
    el: f64,
    shutter: &'a str,
    star: bool,
    mjd: f64,
}

fn write(dir: &Path, name: &str, s: &Shot<'_>) {
    let dark = 100.0;
    // Sky per beam, depending on the plate (a polarized sky), the same in sky frames.
    let sky_o = 5000.0 * (1.0 + 0.01 * (4.0 * s.plate).to_radians().cos());
    let sky_e = 5400.0 * (1.0 - 0.01 * (4.0 * s.plate).to_radians().cos());
    let rotpdest = s.el + 0.7;
    let phi = 2.0 * s.plate + THETA0 + s.parang - s.el - rotpdest;
    let f = Q_SKY * (2.0 * phi).to_radians().cos() + U_SKY * (2.0 * phi).to_radians().sin();
    let (t_o, t_e) = (1.0, 1.0);
    let total = 4e6;
    let (o, e) = (0.5 * total * t_o * (1.0 + f), 0.5 * total * t_e * (1.0 - f));
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
            if s.star {
                light += if in_o { star(x, y, O_POS, o) } else { 0.0 } + if in_e { star(x, y, ec, e) } else { 0.0 };
            }
            v += light * flat(x, y);
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
    h.set("TARGNAME", if s.star { "Sim Star" } else { "" });
    h.set("SHRNAME", s.shutter);
    h.set("PCUPR", s.plate);
    h.set("PARANG", s.parang);
    h.set("EL", s.el);
    h.set("ROTPDEST", rotpdest);
    h.set("MJD", s.mjd);
    h.set("ITIME", 0.45);
    h.set("COADDS", 45i64);
    h.set("DETGAIN", 8.0);
    h.set("DETRN", 40.0);
    write_frame(&dir.join(name), &Frame::new(data, h), &WriteOptions::default()).unwrap();
}

#[test]
fn known_polarization_comes_back() {
    let dir = tempfile::tempdir().unwrap();
    let plates = [0.0, 45.0, 22.5, 67.5];
    for (k, &p) in plates.iter().enumerate() {
        let shot = Shot {
            object: "sky_flat",
            plate: p,
            parang: 0.0,
            el: 60.0,
            shutter: "open",
            star: false,
            mjd: 1.0 + k as f64 * 1e-3,
        };
        write(dir.path(), &format!("sky{k}.fits"), &shot);
    }
    for k in 0..2 {
        let shot = Shot {
            object: "dark",
            plate: 0.0,
            parang: 0.0,
            el: 0.0,
            shutter: "closed",
            star: false,
            mjd: 3.0 + k as f64 * 1e-3,
        };
        write(dir.path(), &format!("dark{k}.fits"), &shot);
    }
    // Two cycles; the sky turns by 2 deg per frame (pupil tracking).
    for k in 0..8 {
        let shot = Shot {
            object: "Sim Star_hwp",
            plate: plates[k % 4],
            parang: 215.0 - STEP_PARANG * k as f64,
            el: 77.0 + STEP_EL * k as f64,
            shutter: "open",
            star: true,
            mjd: 2.0 + k as f64 * 1e-3,
        };
        write(dir.path(), &format!("sci{k}.fits"), &shot);
    }
    std::fs::write(dir.path().join("notes.fits"), b"not a FITS file").unwrap();
    let cat = single_pointing::reduce(&[dir.path().to_path_buf()], &profile()).expect("reduces");
    assert_eq!((cat.darks.len(), cat.skies.len(), cat.flat_from.len()), (2, 4, 4));
    assert_eq!(cat.not_used.len(), 1, "{:?}", cat.not_used);
    let t = &cat.targets[0];
    assert_eq!((t.name.as_str(), t.frames.len(), t.cycles.len()), ("Sim Star", 8, 2));
    for f in &t.frames {
        // Cubic convolution is not exact on a 2-px-sigma Gaussian: the symmetry centre is
        // biased by 0.005 px (measured), the same in both images (same sub-pixel phase).
        assert!(
            (f.o_centre[0] - O_POS.0).abs() < 0.01 && (f.o_centre[1] - O_POS.1).abs() < 0.01,
            "{:?}",
            f.o_centre
        );
        assert!((f.eo_offset[0] - EO.0).abs() < 1e-3 && (f.eo_offset[1] - EO.1).abs() < 1e-3);
        assert!((f.sky_o.scale - 1.0).abs() < 1e-6 && (f.sky_e.scale - 1.0).abs() < 1e-6);
    }
    // On the sky, the least squares with each frame's rotation: exact.
    let ls = t.least_squares_sky.as_ref().unwrap();
    assert!(
        (ls.pol.q - Q_SKY).abs() < 1e-6 && (ls.pol.u - U_SKY).abs() < 1e-6,
        "{:?}",
        ls.pol
    );
    assert!(ls.c.unwrap().abs() < 1e-6, "{:?}", ls.c);
    // Each cycle: the double difference pairs frames 1 and 2 turns apart, so its (q, u) are
    // the sky's turned by the cycle's mean turn theta0 + PARANG - EL - ROTPDEST within
    // 2 P x (the turn per frame, rad) to first order (the pairs' mean turns lie one step
    // either side of the cycle's mean), 25 % added for the second order (measured: 1.0 x).
    let step = (STEP_PARANG + 2.0 * STEP_EL).to_radians();
    let bound = 1.25 * 2.0 * Q_SKY.hypot(U_SKY) * step;
    for (k, c) in t.cycles.iter().enumerate() {
        let mean_turn: f64 = (0..4)
            .map(|j| {
                let i = 4 * k + j;
                let (parang, el) = (215.0 - STEP_PARANG * i as f64, 77.0 + STEP_EL * i as f64);
                THETA0 + parang - el - (el + 0.7)
            })
            .sum::<f64>()
            / 4.0;
        let a = (2.0 * mean_turn).to_radians();
        // Instrument (theta0 = 0, no turn) = sky turned back by the mean turn.
        let (qi, ui) = (Q_SKY * a.cos() + U_SKY * a.sin(), -Q_SKY * a.sin() + U_SKY * a.cos());
        assert!(
            (c.instrument.q - qi).abs() < bound && (c.instrument.u - ui).abs() < bound,
            "cycle {k}: {:?} vs {qi}, {ui} (bound {bound})",
            c.instrument
        );
        assert!(
            (c.sky.q - Q_SKY).abs() < bound && (c.sky.u - U_SKY).abs() < bound,
            "cycle {k}: {:?}",
            c.sky
        );
    }
    // The angle east of north: exact by the least squares, within the cycles' blur by the
    // combined double difference.
    let truth = (0.5 * U_SKY.atan2(Q_SKY).to_degrees()).rem_euclid(180.0);
    assert!(
        (ls.pol.angle_deg - truth).abs() < 1e-3,
        "{} vs {truth}",
        ls.pol.angle_deg
    );
    let sky = t.sky.unwrap();
    let blur_deg = (0.5 * bound / Q_SKY.hypot(U_SKY)).to_degrees();
    assert!((sky.angle_deg - truth).abs() < blur_deg, "{} vs {truth}", sky.angle_deg);
    // The sky from an annulus about each image instead of the sky frames: the same (the
    // simulated sky is flat within each beam), exact by the least squares.
    let annulus = profile()
        .with_overrides(&[
            "single_pointing.sky=\"annulus\"".into(),
            "single_pointing.sky_annulus_px=[12.0, 20.0]".into(),
        ])
        .unwrap();
    let cat2 = single_pointing::reduce(&[dir.path().to_path_buf()], &annulus).expect("reduces");
    let t2 = &cat2.targets[0];
    let ls2 = t2.least_squares_sky.as_ref().unwrap();
    assert!(
        (ls2.pol.q - Q_SKY).abs() < 1e-6 && (ls2.pol.u - U_SKY).abs() < 1e-6,
        "{:?}",
        ls2.pol
    );
    assert!(t2.frames.iter().all(|f| f.sky_o.pixels > 500 && f.sky_o.scale == 1.0));
    // A profile that pairs at the wrong offset stops, naming the frame.
    let wrong = profile()
        .with_overrides(&["geometry.eo_offset_px=[-3.0, -80.0]".into()])
        .unwrap();
    let e = single_pointing::reduce(&[dir.path().to_path_buf()], &wrong)
        .unwrap_err()
        .to_string();
    assert!(e.contains("sci") && e.contains("eo_offset_px"), "{e}");
}
