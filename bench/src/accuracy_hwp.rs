//! The accuracy harness of the half-wave-plate profile (NIRC2's, pupil tracking): simulated
//! nights of single stars through a rotating half-wave plate, each night written as FITS
//! into a temporary folder and reduced by [`sofipol_pipeline::single_pointing::reduce`] as
//! `sofipol night DIR --profile nirc2` does; each star's q, u on the sky scored against the
//! truth the simulator wrote. Used by the accuracy report's half-wave-plate groups
//! ([`crate::accuracy_report`]) and its acceptance test.
//!
//! The detector is NIRC2's shrunk to 128 x 200 pixels ([`SMALL_NIRC2`], as the end-to-end
//! test `cli_hwp_sim` has it) so that a night of 6 stars reduces in a fraction of a second;
//! the stars' images (Gaussian FWHM 0.047", 4.7 px), the sky, the noise and the coadds are
//! NIRC2's L' frames.
use std::time::Instant;

use rand::{RngExt, SeedableRng};
use sofipol_calib::Profile;
use sofipol_pipeline::sim::hwp::HwpTruth;
use sofipol_pipeline::sim::{HwpSimulator, Scene};
use sofipol_pipeline::single_pointing::{self, SinglePointingCatalog};

use crate::accuracy::BinReport;

/// The NIRC2 profile's values the harness overrides: a 128 x 200 detector, its beams' rows,
/// an aperture, centring and sky-fit radii for 4.7-px images (the focal-mask strips NIRC2
/// inherits from SOFI's profile are not read, but must fit).
pub const SMALL_NIRC2: [&str; 17] = [
    "geometry.nx=128",
    "geometry.ny=200",
    "geometry.o_sky2=[0, 10]",
    "geometry.e_sky2=[10, 20]",
    "geometry.o_target=[20, 30]",
    "geometry.e_target=[30, 40]",
    "geometry.o_sky1=[40, 50]",
    "geometry.e_sky1=[50, 60]",
    "geometry.eo_offset_px=[-3.0, -100.0]",
    "beams.o_rows=[105, 200]",
    "beams.e_rows=[0, 95]",
    "single_pointing.aperture_px=[0.0, 9.0]",
    "single_pointing.centre_annulus_px=[1.5, 9.0]",
    "single_pointing.sky_fit_min_radius_px=25.0",
    "single_pointing.search_radius_px=4.0",
    "detector.linear_limit_adu=1e9",
    "detector.saturation_adu=2e9",
];

/// Which of the reduction's results on the sky is scored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HwpEstimate {
    /// The catalog's component: the complete cycles' double differences on the sky (each
    /// cycle fitted at its frames' own angles when the field turns) combined by their
    /// weighted mean, with the adopted error (the larger of the propagated error and the
    /// cycle-to-cycle scatter, 2 cycles or more); the least squares when no cycle is
    /// complete, as the catalog does.
    Catalog,
    /// The least squares over every frame at its own angle on the sky
    /// (`half_wave_plate.least_squares_sky` of the catalog), with its adopted error.
    LeastSquares,
}

/// What to simulate and how to reduce it.
#[derive(Debug, Clone)]
pub struct HwpAccuracyConfig {
    /// Seed of the night (its stars' draws and its noise).
    pub seed: u64,
    /// Stars per night.
    pub stars: usize,
    /// Cycles of the four plate positions per star.
    pub cycles: usize,
    /// Effects (scene names).
    pub effects: Vec<String>,
    /// Cosmic-ray hits per frame (effect `cosmic_rays`), anywhere on the 128 x 200 detector
    /// (default 1: the simulator's default density, 40 per 1024 x 1024 frame).
    pub cosmic_rays_per_frame: f64,
    /// Profile overrides of the reduction only (`--set KEY=VALUE` of `sofipol night`), on
    /// top of [`SMALL_NIRC2`]; the simulation keeps the profile as it is.
    pub reduce_set: Vec<String>,
    /// The result scored.
    pub estimate: HwpEstimate,
}

impl Default for HwpAccuracyConfig {
    fn default() -> Self {
        HwpAccuracyConfig {
            seed: 1,
            stars: 6,
            cycles: 2,
            effects: [
                "psf",
                "sky",
                "photon_noise",
                "read_noise",
                "flat_field",
                "bad_pixels",
                "cosmic_rays",
            ]
            .iter()
            .map(|s| s.to_string())
            .collect(),
            cosmic_rays_per_frame: 1.0,
            reduce_set: Vec::new(),
            estimate: HwpEstimate::Catalog,
        }
    }
}

/// DIT x coadds of the harness's frames, s (NIRC2 L': 45 coadds of 0.45 s).
pub const FRAME_EXPOSURE_S: f64 = 0.45 * 45.0;

impl HwpAccuracyConfig {
    /// Exposure time per star, s (plate positions x cycles x DIT x coadds).
    pub fn exposure_s(&self) -> f64 {
        (4 * self.cycles) as f64 * FRAME_EXPOSURE_S
    }
}

/// The NIRC2 profile on the harness's small detector ([`SMALL_NIRC2`]) and `extra`.
pub fn profile(extra: &[String]) -> Profile {
    let sets: Vec<String> = SMALL_NIRC2
        .iter()
        .map(|s| s.to_string())
        .chain(extra.iter().cloned())
        .collect();
    Profile::embedded("nirc2")
        .expect("embedded profile")
        .expect("nirc2 is embedded")
        .with_overrides(&sets)
        .unwrap_or_else(|e| panic!("profile overrides {extra:?}: {e}"))
}

/// The scene of one night: `cfg.stars` stars of 4e6 ADU (o + e per frame) with (q, u)
/// drawn uniformly in [-3 %, 3 %]^2, 3-30 deg south of the zenith within 36 min of the
/// meridian (the sky turns by 0.1-3 deg per frame), each `cfg.cycles` cycles of the plate
/// positions 0 / 45 / 22.5 / 67.5 deg; two cycles of sky frames (sky polarized 1 % through
/// the plate), three darks; a 1 % pixel response with 5 % vignetting, hot pixels, the
/// seeing changing by 5 % rms from frame to frame.
pub fn scene(cfg: &HwpAccuracyConfig) -> Scene {
    let mut r = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(0x4857_5041 ^ cfg.seed);
    let mut s = format!(
        r#"name = "hwp_accuracy"
seed = {}
profile = "nirc2"
effects = [{}]
[observation]
dit_s = 0.45
ndit = 45
overhead_s = 10.0
filter = "Lp"
date = "2025-12-08"
start_ut = "09:00:00"
[psf]
kind = "gaussian"
fwhm_arcsec = 0.047
seeing_rms_frac = 0.05
[sky]
level_adu = 5000.0
gradient_x = 0.0
gradient_y = 0.0
frame_change_frac = 0.0
[flat_field]
pixel_rms = 0.01
vignetting = 0.05
[bad_pixels]
hot_fraction = 1e-4
dead_fraction = 0.0
clusters = 0
column_segments = 0
[cosmic_rays]
rate_per_frame = {}
[half_wave_plate]
cycles = {}
sky_cycles = 2
darks = 3
sky_modulation = 0.01
header = {{ ROTPDEST = 45.7 }}
"#,
        cfg.seed,
        cfg.effects
            .iter()
            .map(|e| format!("\"{e}\""))
            .collect::<Vec<_>>()
            .join(", "),
        cfg.cosmic_rays_per_frame,
        cfg.cycles
    );
    for i in 0..cfg.stars {
        let (q, u) = (r.random_range(-0.03..0.03), r.random_range(-0.03..0.03));
        let p: f64 = f64::hypot(q, u);
        let gamma = 0.5 * f64::atan2(u, q).to_degrees();
        let dec = 19.8 - r.random_range(3.0..30.0);
        let ha = r.random_range(-0.6..0.6);
        s += &format!(
            "[[half_wave_plate.star]]\nname = \"Star {i}\"\nflux = 4e6\np = {p}\ngamma_deg = {gamma}\ndec_deg = {dec}\nhour_angle_h = {ha}\n"
        );
    }
    Scene::from_toml(&s, "half-wave-plate accuracy scene").expect("valid generated scene")
}

/// One night: simulated into a temporary folder, reduced (timed), scored.
pub struct HwpNight {
    /// Pulls (q - q_true)/sigma_q, (u - u_true)/sigma_u of every star measured.
    pub pulls: Vec<f64>,
    /// True errors q - q_true, u - u_true.
    pub errors: Vec<f64>,
    /// sigma_q of every star measured.
    pub sigmas: Vec<f64>,
    /// Stars without a result (the night failed, or the star has neither estimate).
    pub missing: usize,
    /// Wall time of the reduction (reading the files included), s.
    pub reduce_s: f64,
    /// Pixels repaired as cosmic-ray hits over the night's frames (o + e).
    pub repaired_pixels: u64,
    /// Stars with a pull beyond 5, or the night's error, in words.
    pub outliers: Vec<String>,
}

/// Simulate one night into a temporary folder and reduce it: the simulator's truth, the
/// catalog and the reduction's wall time (reading the files included), s.
pub fn simulate_and_reduce(
    cfg: &HwpAccuracyConfig,
) -> (HwpTruth, sofipol_pipeline::error::Result<SinglePointingCatalog>, f64) {
    let sim_profile = profile(&[]);
    let sim = HwpSimulator::new(scene(cfg), sim_profile).expect("valid half-wave-plate night");
    let dir = tempfile::tempdir().expect("temporary folder");
    let truth = sim.write_to_dir(dir.path(), &|_| {}).expect("simulated night written");
    let red_profile = profile(&cfg.reduce_set);
    let t0 = Instant::now();
    let cat = single_pointing::reduce(&[dir.path().to_path_buf()], &red_profile);
    (truth, cat, t0.elapsed().as_secs_f64())
}

/// Simulate, reduce and score one night.
pub fn run_night(cfg: &HwpAccuracyConfig) -> HwpNight {
    let (truth, cat, reduce_s) = simulate_and_reduce(cfg);
    score(cfg, &truth, cat, reduce_s)
}

fn score(
    cfg: &HwpAccuracyConfig,
    truth: &HwpTruth,
    cat: sofipol_pipeline::error::Result<SinglePointingCatalog>,
    reduce_s: f64,
) -> HwpNight {
    let mut night = HwpNight {
        pulls: vec![],
        errors: vec![],
        sigmas: vec![],
        missing: 0,
        reduce_s,
        repaired_pixels: 0,
        outliers: vec![],
    };
    let cat = match cat {
        Ok(c) => c,
        Err(e) => {
            night.missing = truth.stars.len();
            night.outliers.push(format!("seed {}: the night failed: {e}", cfg.seed));
            return night;
        }
    };
    night.repaired_pixels = cat
        .targets
        .iter()
        .flat_map(|t| &t.frames)
        .map(|f| (f.cosmic_ray_pixels[0] + f.cosmic_ray_pixels[1]) as u64)
        .sum();
    for st in &truth.stars {
        let t = cat.targets.iter().find(|t| t.name == st.name);
        let pol = t.and_then(|t| match cfg.estimate {
            HwpEstimate::Catalog => t.sky.or(t.least_squares_sky.as_ref().map(|l| l.pol)),
            HwpEstimate::LeastSquares => t.least_squares_sky.as_ref().map(|l| l.pol),
        });
        match pol {
            Some(p) if p.q.is_finite() && p.u.is_finite() && p.sigma_q > 0.0 && p.sigma_u > 0.0 => {
                let (pq, pu) = ((p.q - st.q) / p.sigma_q, (p.u - st.u) / p.sigma_u);
                night.pulls.extend([pq, pu]);
                night.errors.extend([p.q - st.q, p.u - st.u]);
                night.sigmas.push(p.sigma_q);
                if pq.abs() > 5.0 || pu.abs() > 5.0 {
                    night.outliers.push(format!(
                        "seed {} {}: q {:.5}/{:.5} u {:.5}/{:.5} sigma {:.5}/{:.5}",
                        cfg.seed, st.name, p.q, st.q, p.u, st.u, p.sigma_q, p.sigma_u
                    ));
                }
            }
            _ => {
                night.missing += 1;
                night
                    .outliers
                    .push(format!("seed {} {}: no result on the sky", cfg.seed, st.name));
            }
        }
    }
    night
}

/// The nights of `seeds` (each `cfg` with its own seed), pooled into one [`BinReport`]
/// (no separation: `sep_arcsec` and `sep_fwhm` are NaN); its time is the median over the
/// nights of the reduction's wall time per star. Also returns each night.
pub fn run_seeds(cfg: &HwpAccuracyConfig, seeds: &[u64]) -> (BinReport, Vec<HwpNight>) {
    let nights: Vec<HwpNight> = seeds
        .iter()
        .map(|&seed| run_night(&HwpAccuracyConfig { seed, ..cfg.clone() }))
        .collect();
    (pooled(&nights, cfg.stars), nights)
}

/// The nights pooled (see [`run_seeds`]).
pub fn pooled(nights: &[HwpNight], stars: usize) -> BinReport {
    let pulls: Vec<f64> = nights.iter().flat_map(|n| n.pulls.iter().copied()).collect();
    let errs: Vec<f64> = nights.iter().flat_map(|n| n.errors.iter().copied()).collect();
    let mut sig: Vec<f64> = nights.iter().flat_map(|n| n.sigmas.iter().copied()).collect();
    sig.sort_by(|a, b| a.total_cmp(b));
    let mut ts: Vec<f64> = nights.iter().map(|n| n.reduce_s / stars.max(1) as f64).collect();
    ts.sort_by(|a, b| a.total_cmp(b));
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    BinReport {
        sep_arcsec: (f64::NAN, f64::NAN),
        sep_fwhm: (f64::NAN, f64::NAN),
        n_pulls: pulls.len(),
        rms_pull: rms(&pulls),
        mean_pull: mean(&pulls),
        median_sigma: sig.get(sig.len() / 2).copied().unwrap_or(f64::NAN),
        rms_error: rms(&errs),
        mean_error: mean(&errs),
        missing: nights.iter().map(|n| n.missing).sum(),
        median_reduce_s: ts.get(ts.len() / 2).copied().unwrap_or(f64::NAN),
        outliers: nights.iter().flat_map(|n| n.outliers.iter().cloned()).collect(),
        delta_gamma_pulls: vec![],
    }
}
