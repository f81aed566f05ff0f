//! The half-wave-plate reduction on frames the simulator makes from a known polarization
//! ([`sofipol_pipeline::sim::HwpSimulator`], the NIRC2 profile shrunk to a 128 x 200
//! detector): a star's o and e images from the forward model F = q cos 2phi + u sin 2phi
//! with phi on the sky = 2 PCUPR + theta0 + PARANG - EL - ROTPDEST, PARANG following the
//! hour angle (pupil tracking), a plate-dependent sky (also in the sky frames), darks, hot
//! pixels, a vignetting pixel response. Noise-free (`known_polarization_comes_back`): every
//! step is exact, so (q, u) must come back to 1e-6 on the sky (least squares over the
//! frames, each with its own rotation). With photon and read noise
//! (`pulls_on_noisy_pupil_tracking_nights`): the errors the reduction reports must match
//! the scatter about the truth over many simulated nights.
use std::path::Path;

use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use sofipol_calib::fits::{write_frame, WriteOptions};
use sofipol_calib::Profile;
use sofipol_pipeline::sim::hwp::{HwpConfig, HwpStar, HwpTruth};
use sofipol_pipeline::sim::{HwpSimulator, Scene};
use sofipol_pipeline::single_pointing;

const NX: usize = 128;
const NY: usize = 200;
const O_POS: (f64, f64) = (60.3, 150.7);
const EO: (f64, f64) = (-3.0, -100.0);
const Q_SKY: f64 = 0.021;
const U_SKY: f64 = -0.013;
/// The profile's zero point of phi (NIRC2's), written out.
const THETA0: f64 = 26.0;
const ROTPDEST: f64 = 45.7;
const GAIN_E: f64 = 8.0;

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
            format!("detector.gain_e_per_adu={GAIN_E}"),
            "detector.read_noise_e=40.0".into(),
        ])
        .unwrap()
}

/// A scene of `stars` through the plate: 45 coadds of 0.45 s and 10 s overheads (30 s
/// per frame), a Gaussian PSF of sigma 2 px, a sky of 5000 ADU per beam modulated by the
/// plate (1 +- 0.01 cos 4 plate), three hot pixels, a vignetting pixel response symmetric
/// about the detector's middle row (both beams' rows then have the same median, so the
/// per-beam normalisation leaves no beam imbalance), a dark level of 100 ADU; `noise` adds
/// photon and read noise. A header keyword SIMGAIN2 holds twice the true gain (the pull
/// test's control).
fn scene(seed: u64, stars: Vec<HwpStar>, sky_cycles: usize, darks: usize, noise: bool) -> Scene {
    let effects = if noise {
        r#""psf", "sky", "flat_field", "bad_pixels", "photon_noise", "read_noise""#
    } else {
        r#""psf", "sky", "flat_field", "bad_pixels""#
    };
    let fwhm_arcsec = 2.0 * (8.0f64 * 2f64.ln()).sqrt() * profile().geometry.pixscale_arcsec;
    let mut s = Scene::from_toml(
        &format!(
            r#"
name = "hwp"
seed = {seed}
effects = [{effects}]
[observation]
dit_s = 0.45
ndit = 45
overhead_s = 10.0
filter = "Lp"
date = "2025-12-08"
start_ut = "09:00:00"
[psf]
kind = "gaussian"
fwhm_arcsec = {fwhm_arcsec}
seeing_rms_frac = 0.0
[sky]
level_adu = 5000.0
gradient_x = 0.0
gradient_y = 0.0
frame_change_frac = 0.0
[flat_field]
pixel_rms = 0.0
vignetting = 0.1
[bad_pixels]
hot_fraction = 1.2e-4
dead_fraction = 0.0
hot_level_adu = 9000.0
clusters = 0
column_segments = 0
"#
        ),
        "test scene",
    )
    .unwrap();
    let mut header = std::collections::BTreeMap::new();
    header.insert("ROTPDEST".to_string(), ROTPDEST);
    header.insert("SIMGAIN2".to_string(), 2.0 * GAIN_E);
    s.half_wave_plate = Some(HwpConfig {
        plate_deg: vec![0.0, 45.0, 22.5, 67.5],
        cycles: 2,
        sky_cycles,
        darks,
        dark_adu: 100.0,
        sky_modulation: 0.01,
        header,
        x_px: Some(O_POS.0),
        y_px: Some(O_POS.1),
        star: stars,
        ..HwpConfig::default()
    });
    s
}

/// A star of polarization (q, u) on the sky.
fn star(name: &str, q: f64, u: f64, flux: f64, dec_deg: f64, hour_angle_h: f64) -> HwpStar {
    HwpStar {
        name: name.into(),
        flux,
        p: q.hypot(u),
        gamma_deg: 0.5 * u.atan2(q).to_degrees(),
        dec_deg,
        hour_angle_h,
    }
}

/// Simulate a scene into `dir` (the frames and truth.json).
fn simulate(dir: &Path, s: Scene) -> HwpTruth {
    HwpSimulator::new(s, profile())
        .expect("valid scene")
        .write_to_dir(dir, &|_| {})
        .expect("written")
}

#[test]
fn known_polarization_comes_back() {
    let dir = tempfile::tempdir().unwrap();
    // Near the meridian 10 deg from the zenith: the sky turns by ~0.7 deg per frame.
    let truth = simulate(
        dir.path(),
        scene(1, vec![star("Sim Star", Q_SKY, U_SKY, 4e6, 10.0, -0.05)], 1, 2, false),
    );
    assert!((truth.stars[0].q - Q_SKY).abs() < 1e-12 && (truth.stars[0].u - U_SKY).abs() < 1e-12);
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
    // Each frame's turn theta0 + PARANG - EL - ROTPDEST from its header (written out here,
    // not the profile's), the same as the truth's.
    let turns: Vec<f64> = truth.stars[0]
        .frames
        .iter()
        .map(|f| {
            let h = sofipol_calib::fits::read_header(&dir.path().join(&f.file)).unwrap();
            let turn =
                THETA0 + h.get_f64("PARANG").unwrap() - h.get_f64("EL").unwrap() - h.get_f64("ROTPDEST").unwrap();
            assert!((f.phi_sky_deg - 2.0 * f.plate_deg - turn).abs() < 1e-9);
            turn
        })
        .collect();
    // The pupil turns on the sky: by 0.3-2 deg per frame.
    let step_max = turns.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
    let step_min = turns
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .fold(f64::INFINITY, f64::min);
    assert!(step_min > 0.3 && step_max < 2.0, "{turns:?}");
    // On the sky, the least squares with each frame's rotation: exact.
    let ls = t.least_squares_sky.as_ref().unwrap();
    assert!(
        (ls.pol.q - Q_SKY).abs() < 1e-6 && (ls.pol.u - U_SKY).abs() < 1e-6,
        "{:?}",
        ls.pol
    );
    // No beam imbalance is simulated: c = 0 up to the f32 frames' and flat's rounding
    // (measured 3.7e-6).
    assert!(ls.c.unwrap().abs() < 1e-5, "{:?}", ls.c);
    // Each cycle: the double difference pairs frames 1 and 2 turns apart, so its (q, u) are
    // the sky's turned by the cycle's mean turn within 2 P x (the largest turn per frame,
    // rad) to first order (the pairs' mean turns lie one step either side of the cycle's
    // mean), 25 % added for the second order.
    let step = step_max.to_radians();
    let bound = 1.25 * 2.0 * Q_SKY.hypot(U_SKY) * step;
    for (k, c) in t.cycles.iter().enumerate() {
        let mean_turn: f64 = turns[4 * k..4 * k + 4].iter().sum::<f64>() / 4.0;
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
    let angle = (0.5 * U_SKY.atan2(Q_SKY).to_degrees()).rem_euclid(180.0);
    assert!((truth.stars[0].gamma_deg - angle).abs() < 1e-9);
    assert!(
        (ls.pol.angle_deg - angle).abs() < 1e-3,
        "{} vs {angle}",
        ls.pol.angle_deg
    );
    let sky = t.sky.unwrap();
    let blur_deg = (0.5 * bound / Q_SKY.hypot(U_SKY)).to_degrees();
    assert!((sky.angle_deg - angle).abs() < blur_deg, "{} vs {angle}", sky.angle_deg);
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
    assert!(e.contains("Sim_Star") && e.contains("eo_offset_px"), "{e}");
    // A science frame that cannot be measured (the star is not in it: a frame of another
    // scene's star, far off, renamed to this one) is listed as not used with why; the night
    // goes on with the others.
    let other = tempfile::tempdir().unwrap();
    let far = simulate(
        other.path(),
        scene(1, vec![star("Sim Star", Q_SKY, U_SKY, 0.0, 10.0, -0.05)], 0, 0, false),
    );
    let empty = sofipol_calib::fits::read_frame(&other.path().join(&far.stars[0].frames[0].file)).unwrap();
    write_frame(&dir.path().join("sci8.fits"), &empty, &WriteOptions::default()).unwrap();
    let cat3 = single_pointing::reduce(&[dir.path().to_path_buf()], &profile()).expect("the night goes on");
    let n = cat3
        .not_used
        .iter()
        .find(|n| n.file == "sci8.fits")
        .expect("sci8 listed as not used");
    assert!(!n.reason.is_empty() && !n.reason.starts_with("sci8"), "{}", n.reason);
    assert_eq!(cat3.targets[0].frames.len(), 8);
    assert_eq!(cat3.targets[0].least_squares_sky, cat.targets[0].least_squares_sky);
}

/// rms and mean of pulls, with their standard errors for unit-normal pulls (1/sqrt(2N),
/// 1/sqrt(N)).
struct PullStats {
    n: usize,
    rms: f64,
    mean: f64,
}

impl PullStats {
    fn of(p: &[f64]) -> Self {
        let n = p.len();
        Self {
            n,
            rms: (p.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt(),
            mean: p.iter().sum::<f64>() / n as f64,
        }
    }
    fn se_rms(&self) -> f64 {
        1.0 / (2.0 * self.n as f64).sqrt()
    }
    fn se_mean(&self) -> f64 {
        1.0 / (self.n as f64).sqrt()
    }
}

impl std::fmt::Display for PullStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "N = {}: rms {:.3} +- {:.3}, mean {:+.3} +- {:.3}",
            self.n,
            self.rms,
            self.se_rms(),
            self.mean,
            self.se_mean()
        )
    }
}

/// Simulated nights of the pull test; `SOFIPOL_PULL_SEEDS` sets another number (the
/// figures in docs/instruments.md also quote a 256-night run).
const PULL_SEEDS: u64 = 64;
const PULL_TARGETS: usize = 3;
/// Sky frames per plate position (the mean of them is each position's matched sky).
const PULL_SKIES: usize = 4;

/// Pulls (estimate - truth) / error of q and u on the sky, pooled over `PULL_SEEDS`
/// simulated nights with photon and read noise, each with `PULL_TARGETS` stars of their own
/// (q, u) drawn uniformly in [-3 %, 3 %]^2, two cycles of four plate positions each, pupil
/// tracking with the sky turning with the hour angle (stars 3-30 deg south of the zenith
/// within 36 min of the meridian, 30 s per frame).
/// The least squares over the frames (each frame's own rotation) with the photometric error
/// must give pulls of rms 1 and mean 0 within 3 standard errors (and rms within 0.9-1.1),
/// and so must the adopted error (scaled by sqrt(chi2/dof) only when chi2 lies beyond its
/// 99th percentile; never below the photometric one). Controls:
/// the same frames reduced with the rotation ignored (`sky_fixed`) or a gain 2x the true
/// one must fail the same test.
#[test]
fn pulls_on_noisy_pupil_tracking_nights() {
    let reduce_with = |dir: &Path, extra: &[&str]| {
        let p = profile()
            .with_overrides(&extra.iter().map(|s| s.to_string()).collect::<Vec<_>>())
            .unwrap();
        single_pointing::reduce(&[dir.to_path_buf()], &p).expect("reduces")
    };
    #[derive(Default)]
    struct Pulls {
        ls_phot: Vec<f64>,
        ls_adopted: Vec<f64>,
        ls_chi2: Vec<f64>,
        dd_phot: Vec<f64>,
        dd_adopted: Vec<f64>,
        no_rotation: Vec<f64>,
        gain_2x: Vec<f64>,
    }
    let mut pulls = Pulls::default();
    let seeds =
        std::env::var("SOFIPOL_PULL_SEEDS").map_or(PULL_SEEDS, |s| s.parse().expect("SOFIPOL_PULL_SEEDS: a number"));
    for seed in 0..seeds {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(0x5350_4F4C ^ seed);
        let dir = tempfile::tempdir().unwrap();
        // Stars 3-30 deg south of the zenith within 36 min of the meridian (the parallactic
        // angle passes 0, not 180 where it wraps): the sky turns by 0.1-3 deg per frame.
        let stars: Vec<HwpStar> = (0..PULL_TARGETS)
            .map(|t| {
                let dec = 19.8 - rng.random_range(3.0..30.0);
                star(
                    &format!("Star {t}"),
                    rng.random_range(-0.03..0.03),
                    rng.random_range(-0.03..0.03),
                    4e7,
                    dec,
                    rng.random_range(-0.6..0.6),
                )
            })
            .collect();
        let truth = simulate(dir.path(), scene(seed, stars, PULL_SKIES, 3, true));
        let cat = reduce_with(dir.path(), &[]);
        let no_rot = reduce_with(dir.path(), &["field_rotation.kind=\"sky_fixed\""]);
        let gain2 = reduce_with(dir.path(), &["detector.gain_keyword=\"SIMGAIN2\""]);
        assert_eq!(cat.targets.len(), PULL_TARGETS);
        for star in &truth.stars {
            let find = |c: &single_pointing::SinglePointingCatalog| {
                let t = c.targets.iter().find(|t| t.name == star.name).expect("target");
                assert_eq!((t.frames.len(), t.cycles.len()), (8, 2));
                t.least_squares_sky.clone().expect("least squares")
            };
            let t = cat.targets.iter().find(|t| t.name == star.name).unwrap();
            let ls = find(&cat);
            let p = &ls.pol;
            pulls.ls_phot.push((p.q - star.q) / p.sigma_q_photometric);
            pulls.ls_phot.push((p.u - star.u) / p.sigma_u_photometric);
            pulls.ls_adopted.push((p.q - star.q) / p.sigma_q);
            pulls.ls_adopted.push((p.u - star.u) / p.sigma_u);
            pulls.ls_chi2.push(ls.chi2 / ls.dof as f64);
            let dd = t.sky.as_ref().unwrap();
            pulls.dd_phot.push((dd.q - star.q) / dd.sigma_q_photometric);
            pulls.dd_phot.push((dd.u - star.u) / dd.sigma_u_photometric);
            pulls.dd_adopted.push((dd.q - star.q) / dd.sigma_q);
            pulls.dd_adopted.push((dd.u - star.u) / dd.sigma_u);
            let p = find(&no_rot).pol;
            pulls.no_rotation.push((p.q - star.q) / p.sigma_q_photometric);
            pulls.no_rotation.push((p.u - star.u) / p.sigma_u_photometric);
            let p = find(&gain2).pol;
            pulls.gain_2x.push((p.q - star.q) / p.sigma_q_photometric);
            pulls.gain_2x.push((p.u - star.u) / p.sigma_u_photometric);
        }
    }
    let ok = |s: &PullStats| {
        (s.rms - 1.0).abs() < 3.0 * s.se_rms() && (0.9..=1.1).contains(&s.rms) && s.mean.abs() < 3.0 * s.se_mean()
    };
    let ls_phot = PullStats::of(&pulls.ls_phot);
    let ls_adopted = PullStats::of(&pulls.ls_adopted);
    let dd_phot = PullStats::of(&pulls.dd_phot);
    let dd_adopted = PullStats::of(&pulls.dd_adopted);
    let no_rotation = PullStats::of(&pulls.no_rotation);
    let gain_2x = PullStats::of(&pulls.gain_2x);
    let chi2 = pulls.ls_chi2.iter().sum::<f64>() / pulls.ls_chi2.len() as f64;
    eprintln!("least squares, photometric error: {ls_phot}");
    eprintln!("least squares, adopted error: {ls_adopted}");
    eprintln!("least squares, mean chi2/dof {chi2:.3} ({} fits)", pulls.ls_chi2.len());
    eprintln!("double difference, photometric error: {dd_phot}");
    eprintln!("double difference, adopted error: {dd_adopted}");
    eprintln!("control, rotation ignored: {no_rotation}");
    eprintln!("control, gain 2x: {gain_2x}");
    assert!(ok(&ls_phot), "least squares, photometric error: {ls_phot}");
    // The cycles on the sky (each frame at its own angle) combined: as honest.
    assert!(ok(&dd_phot), "cycles on the sky, photometric error: {dd_phot}");
    // The adopted error is never below the photometric one, and inflated only when chi2
    // lies beyond its 99th percentile: honest on nights whose errors are right.
    assert!(ls_adopted.rms <= ls_phot.rms, "{ls_adopted} vs {ls_phot}");
    assert!(ok(&ls_adopted), "least squares, adopted error: {ls_adopted}");
    assert!(!ok(&no_rotation), "rotation ignored: {no_rotation}");
    assert!(!ok(&gain_2x), "gain 2x: {gain_2x}");
}

/// A night in `dir` from the simulator: one star ("Sim Star", (q, u) = (Q_SKY, U_SKY),
/// `flux`) observed at `plates` repeated `cycles` times under pupil tracking (10 deg from
/// the zenith near the meridian: the sky turns by ~0.7 deg per frame), 4 sky frames (one per
/// plate position 0, 45, 22.5, 67.5 deg) and 2 darks, with photon and read noise when
/// `noise`. Returns the science files in observing order.
fn night(dir: &Path, plates: &[f64], cycles: usize, flux: f64, noise: bool) -> Vec<String> {
    let four = [0.0, 45.0, 22.5, 67.5];
    let mut s = scene(77, vec![star("Sim Star", Q_SKY, U_SKY, flux, 10.0, -0.05)], 1, 2, noise);
    let hw = s.half_wave_plate.as_mut().unwrap();
    hw.plate_deg = plates.to_vec();
    hw.cycles = cycles;
    if plates.len() == 4 {
        return simulate(dir, s).stars[0]
            .frames
            .iter()
            .map(|f| f.file.clone())
            .collect();
    }
    // Fewer plate positions than a cycle: the sky frames and darks of a four-position
    // night of the same scene (the flat and the sky need every position).
    let hw = s.half_wave_plate.as_mut().unwrap();
    (hw.sky_cycles, hw.darks) = (0, 0);
    let science = simulate(dir, s.clone()).stars[0]
        .frames
        .iter()
        .map(|f| f.file.clone())
        .collect();
    let skies = tempfile::tempdir().unwrap();
    let hw = s.half_wave_plate.as_mut().unwrap();
    (hw.plate_deg, hw.cycles, hw.sky_cycles, hw.darks) = (four.to_vec(), 1, 1, 2);
    let t = simulate(skies.path(), s);
    for f in t.skies.iter().map(|f| &f.file).chain(&t.darks) {
        std::fs::copy(skies.path().join(f), dir.join(f)).unwrap();
    }
    science
}

/// Add `adu` to pixels `(x, y)` of a written frame.
fn hit(path: &Path, pixels: &[(usize, usize)], adu: f64) {
    let mut fr = sofipol_calib::fits::read_frame(path).unwrap();
    for &(x, y) in pixels {
        fr.data[[y, x]] += adu as f32;
    }
    write_frame(path, &fr, &WriteOptions::default()).unwrap();
}

/// Cosmic-ray hits: 3 pixels inside the o aperture of one frame (enough to move its F by 6
/// sigma_F), hits in both beams' sky-fit regions of another and in the o image's sky
/// annulus of a third. The hit pixels are found against the other frames and repaired: every frame's F
/// within 1 sigma_F of the clean night's, q and u (least squares and cycles) within
/// 1 sigma; the clean night repairs nothing. The same with the sky from an annulus.
#[test]
fn cosmic_rays_are_repaired_or_clipped() {
    let dir = tempfile::tempdir().unwrap();
    let sci = night(dir.path(), &[0.0, 22.5, 45.0, 67.5], 2, 4e7, true);
    let annulus = profile()
        .with_overrides(&[
            "single_pointing.sky=\"annulus\"".into(),
            "single_pointing.sky_annulus_px=[12.0, 20.0]".into(),
        ])
        .unwrap();
    let clean = single_pointing::reduce(&[dir.path().to_path_buf()], &profile()).unwrap();
    let clean_a = single_pointing::reduce(&[dir.path().to_path_buf()], &annulus).unwrap();
    for c in [&clean, &clean_a] {
        let t = &c.targets[0];
        assert_eq!(
            t.frames.iter().map(|f| &f.file).collect::<Vec<_>>(),
            sci.iter().collect::<Vec<_>>()
        );
        assert!(
            t.frames.iter().all(|f| f.cosmic_ray_pixels == [0, 0]),
            "clean frames repaired: {:?}",
            t.frames.iter().map(|f| f.cosmic_ray_pixels).collect::<Vec<_>>()
        );
    }
    // A hit of 3 pixels 3-4 px from the o image's centre in the fourth frame: 6 sigma_F in
    // F (dF = dO 2e / (o + e)^2 ~ dO / (o + e)), after the flat (~1.05).
    let f3 = &clean.targets[0].frames[3];
    let adu = 6.0 * f3.sigma_f * (f3.o + f3.e) / 3.0 * 1.05;
    let (x, y) = (O_POS.0.round() as usize, O_POS.1.round() as usize);
    hit(
        &dir.path().join(&sci[3]),
        &[(x + 3, y + 1), (x + 4, y + 1), (x + 4, y + 2)],
        adu,
    );
    // Hits in the sky-fit regions (beyond 25 px of the star) of the sixth frame, both
    // beams, and in the sky annulus (12-20 px) of the seventh's o image.
    hit(
        &dir.path().join(&sci[5]),
        &[(100, 180), (101, 180), (20, 60), (21, 61)],
        50.0 * adu,
    );
    hit(
        &dir.path().join(&sci[6]),
        &[(x + 15, y), (x + 15, y + 1), (x - 3, y - 14)],
        50.0 * adu,
    );
    for (c0, p) in [(&clean, profile()), (&clean_a, annulus)] {
        let cat = single_pointing::reduce(&[dir.path().to_path_buf()], &p).unwrap();
        let (t, t0) = (&cat.targets[0], &c0.targets[0]);
        assert_eq!(t.frames.len(), 8, "{:?}", cat.not_used);
        for (f, g) in t.frames.iter().zip(&t0.frames) {
            let d = (f.f - g.f) / g.sigma_f;
            println!(
                "{}: F moves by {d:+.3} sigma_F; {:?} pixels repaired",
                f.file, f.cosmic_ray_pixels
            );
            assert!(d.abs() < 1.0, "{}: F moves by {d} sigma_F", f.file);
        }
        assert!(
            t.frames[3].cosmic_ray_pixels[0] >= 3,
            "{:?}",
            t.frames[3].cosmic_ray_pixels
        );
        let (a, b) = (
            t.least_squares_sky.as_ref().unwrap().pol,
            t0.least_squares_sky.as_ref().unwrap().pol,
        );
        assert!(
            (a.q - b.q).abs() < b.sigma_q && (a.u - b.u).abs() < b.sigma_u,
            "{a:?} vs {b:?}"
        );
        let (a, b) = (t.sky.unwrap(), t0.sky.unwrap());
        assert!(
            (a.q - b.q).abs() < b.sigma_q && (a.u - b.u).abs() < b.sigma_u,
            "{a:?} vs {b:?}"
        );
    }
}

/// An aperture that crosses its beam's rows is refused naming the file, the star's
/// position, the aperture and the rows (it summed NaN: the rows outside the beam hold no
/// value of it); no NaN reaches the catalog.
#[test]
fn an_aperture_across_the_beam_rows_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let sci = night(dir.path(), &[0.0, 22.5, 45.0, 67.5], 1, 4e6, false);
    // The o image at y = 150.7, its rows from 105: an outer radius of 47 px reaches 103.7
    // (and stays inside the frame).
    let wide = profile()
        .with_overrides(&[
            "single_pointing.aperture_px=[0.0, 47.0]".into(),
            "single_pointing.sky_fit_min_radius_px=55.0".into(),
        ])
        .unwrap();
    let e = single_pointing::reduce(&[dir.path().to_path_buf()], &wide)
        .unwrap_err()
        .to_string();
    assert!(
        sci.iter().any(|f| e.contains(f.as_str()))
            && e.contains("(60.3, 150.7)")
            && e.contains("47 px")
            && e.contains("rows 105..200"),
        "{e}"
    );
}

/// A header angle that is no angle (PARANG = 1e300) in one frame: that frame is not used,
/// named with the keyword and value; the night goes on with the others.
#[test]
fn an_absurd_header_angle_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let sci = night(dir.path(), &[0.0, 22.5, 45.0, 67.5], 2, 4e6, false);
    let p = dir.path().join(&sci[4]);
    let mut fr = sofipol_calib::fits::read_frame(&p).unwrap();
    fr.header.set("PARANG", 1e300);
    write_frame(&p, &fr, &WriteOptions::default()).unwrap();
    let cat = single_pointing::reduce(&[dir.path().to_path_buf()], &profile()).unwrap();
    let n = cat
        .not_used
        .iter()
        .find(|n| n.file == sci[4])
        .unwrap_or_else(|| panic!("{} not used: {:?}", sci[4], cat.not_used));
    assert!(
        n.reason.contains("PARANG") && n.reason.contains("1e300"),
        "{}",
        n.reason
    );
    assert_eq!(cat.targets[0].frames.len(), 7);
}

/// Two plate positions only (0 and 22.5) on a field that turns by ~0.7 deg per frame: the
/// analyzer angles on the sky are distinct, but c is not determined by them and is not
/// fitted; the catalog and the summary say so. (q, u) on the sky come back exactly
/// (noise-free, equal beams).
#[test]
fn two_plate_positions_do_not_fit_c() {
    let dir = tempfile::tempdir().unwrap();
    night(dir.path(), &[0.0, 22.5], 3, 4e6, false);
    let cat = single_pointing::reduce(&[dir.path().to_path_buf()], &profile()).unwrap();
    let t = &cat.targets[0];
    assert_eq!(t.frames.len(), 6, "{:?}", cat.not_used);
    let ls = t.least_squares_sky.as_ref().unwrap();
    assert!(ls.c.is_none(), "{:?}", ls.c);
    let why = ls.c_not_fitted.as_deref().expect("why c is not fitted");
    assert!(why.contains("not fitted") && why.contains("do not determine"), "{why}");
    assert!(
        (ls.pol.q - Q_SKY).abs() < 1e-6 && (ls.pol.u - U_SKY).abs() < 1e-6,
        "{:?}",
        ls.pol
    );
    let lines = single_pointing::summary_lines(&cat);
    assert!(
        lines.iter().any(|l| l.contains("c (beam imbalance) is not fitted")),
        "{lines:?}"
    );
}

/// The reduction as sofipol's catalog ([`single_pointing::output::to_catalog`]): one target
/// per star, its component the cycles combined on the sky, every half-wave-plate result in
/// the typed `half_wave_plate` section as the reduction gave it, the files not used as
/// `failures` with their paths; the JSON reads back to the same catalog, and a SOFI target
/// writes no `half_wave_plate` key.
#[test]
fn the_reduction_as_sofipols_catalog() {
    use sofipol_pipeline::catalog::{Catalog, Status, Target};
    let dir = tempfile::tempdir().unwrap();
    let truth = simulate(
        dir.path(),
        scene(1, vec![star("Sim Star", Q_SKY, U_SKY, 4e6, 10.0, -0.05)], 1, 2, false),
    );
    std::fs::write(dir.path().join("notes.fits"), b"not a FITS file").unwrap();
    let roots = [dir.path().to_path_buf()];
    let files = single_pointing::input_files(&roots).unwrap();
    let sp = single_pointing::reduce_inputs(&files, &roots, &profile()).expect("reduces");
    let cat = single_pointing::output::to_catalog(&sp, &files, &profile()).expect("a catalog");
    assert_eq!(cat.targets.len(), 1);
    let (t, r) = (&cat.targets[0], &sp.targets[0]);
    assert_eq!((t.object.as_str(), t.status), ("Sim Star", Status::Ok));
    let c = &t.components[0];
    let sky = r.sky.unwrap();
    assert_eq!(
        (c.q, c.u, c.sigma_q, c.sigma_u),
        (sky.q, sky.u, sky.sigma_q, sky.sigma_u)
    );
    assert_eq!((c.p, c.sigma_p, c.gamma_deg), (sky.p, sky.sigma_p, sky.angle_deg));
    assert_eq!(c.sigma_gamma_stat_deg, Some(sky.sigma_angle_deg));
    let hw = t.half_wave_plate.as_ref().unwrap();
    assert_eq!((hw.instrument, hw.sky), (r.instrument, r.sky));
    assert_eq!(hw.cycles, r.cycles);
    assert_eq!(hw.cycle_agreement, r.cycle_agreement);
    assert_eq!(
        (&hw.least_squares_instrument, &hw.least_squares_sky),
        (&r.least_squares_instrument, &r.least_squares_sky)
    );
    assert_eq!((&hw.frames, &hw.left_out), (&r.frames, &r.left_out));
    assert_eq!(hw.zero_point, sp.zero_point);
    assert_eq!(hw.zero_point.deg, THETA0);
    let path = |n: &str| dir.path().join(n).display().to_string();
    assert_eq!(hw.darks, truth.darks.iter().map(|d| path(d)).collect::<Vec<_>>());
    assert_eq!(cat.failures.len(), 1);
    assert_eq!(cat.failures[0].file, path("notes.fits"));
    assert_eq!(cat.failures[0].error, sp.not_used[0].reason);
    let json = serde_json::to_string(&cat).unwrap();
    let back: Catalog = serde_json::from_str(&json).unwrap();
    assert_eq!(back.targets, cat.targets);
    assert_eq!(serde_json::to_string(&back).unwrap(), json);
    // A target without the section (SOFI's) writes no key for it.
    let sofi = serde_json::to_value(Target::new("x", Status::Ok)).unwrap();
    assert!(sofi.get("half_wave_plate").is_none(), "{sofi}");
    // Two inputs of one file name cannot be told apart in the catalog: refused, naming both.
    let first = &truth.stars[0].frames[0].file;
    let other = tempfile::tempdir().unwrap();
    std::fs::copy(dir.path().join(first), other.path().join(first)).unwrap();
    let mut twice = files.clone();
    twice.extend(single_pointing::input_files(&[other.path().to_path_buf()]).unwrap());
    let e = single_pointing::output::to_catalog(&sp, &twice, &profile())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(first.as_str()) && e.contains(other.path().to_str().unwrap()),
        "{e}"
    );
}
