//! An accuracy harness that samples the world instead of our defaults.
//!
//! Every target of every separation bin draws its own observing conditions from the ranges
//! real SOFI nights show, is written to FITS (float or 16-bit) and is reduced through the
//! same file path as `sofipol night` (its folder planned and reduced by
//! [`night::reduce_sequences`]; the night's flats and calibration measured by
//! [`night::run_night`] on the calibration frames, as `sofipol calib` does):
//!
//! | condition | drawn from |
//! |---|---|
//! | seeing FWHM | 0.6-1.1" per target; per frame 10 % rms and x U(0.8, 1.2) |
//! | Moffat beta | 2.5-4 per frame |
//! | PSF ellipticity | axis ratio 0.9-1 per frame, random angle |
//! | e-o beam offset | x -1..+1 px (tilt), y 165.5-168.5 px (the reducer starts from the profile's 0, 167) |
//! | primary position | x 250-774 px, y anywhere in the o-target strip with room for the pair |
//! | flux of A | 2e3-2e5 ADU, log-uniform; B 25-100 % of A; every 6th target 2e6-4e6 (saturated) |
//! | polarization | P 1-8 % each, angles uniform |
//! | orientations | 2 (0/45) or 4 (0/45/90/135), alternating |
//! | file format | BITPIX -32 or 16 (BZERO 32768), alternating |
//! | effects | psf, sky (gradient, 3 % level changes), strips, photon and read noise, bad pixels, transparency, pointing error, cosmic rays |
//! | instrument (one per night) | 1 % pixel response + 5 % vignetting (one detector: `detector_seed`), k = T_e/T_o 0.96-0.99, instrumental polarization 0.3 %, analyzer zero-point -5..5 deg and parity +-1, non-linearity, saturation |
//! | calibration | dome flats and 2 unpolarized + 2 polarized standards of the same night and detector (their true polarization drawn from the table's values and errors), reduced and applied as `sofipol night` does |
//! | telescope (off by default) | with `telescope_polarization`: p_tel 0-1 %, psi_tel 0-180 deg for the night; with `spread_standards`: the standards hours apart at spread parallactic angles |
//! | foreground (off by default) | with `foreground_field`: one field on the sky for the night (every target's scene shares its seed): mean P 0-3 % at an angle 0-180 deg, rms of q and u 0.1-0.8 %, coherence 20-600" (log-uniform); each component gets the field at its own position |
//!
//! Pulls are `(q - q_true)/sigma_q` and `(u - u_true)/sigma_u` of both components; the A/B
//! labels of the catalog are matched to the truth by position angle, and a swap of a pair
//! whose flux ratio is below [`RELABEL_RATIO`] is counted as a relabelling error.
//! P and gamma are scored too: `(P_debiased - P_true)/sigma_P` where the true S/N
//! P_true/sigma_P exceeds [`P_PULL_MIN_SNR`] and `wrap(gamma - gamma_true)/sigma_gamma` where it
//! exceeds [`GAMMA_PULL_MIN_SNR`] (see [`WorldTarget::p_pulls`] and [`WorldTarget::gamma_pulls`]).
//! Components flagged `saturated` or `ab_identity_unverified` are refused: counted, not scored.
use std::path::{Path, PathBuf};

use rand::{RngExt, SeedableRng};
use rayon::prelude::*;
use serde::Serialize;
use sofipol_calib::Profile;

use sofipol_pipeline::calibration::{
    calibrate_catalog, CalibSetup, Calibration, CalibrationContext, CalibrationParams, CalibrationSource,
};
use sofipol_pipeline::catalog::{Catalog, Target};
use sofipol_pipeline::night::{self, Hooks, NightSetup, RunOptions};
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::scene::ForegroundFieldConfig;
use sofipol_pipeline::sim::{Scene, Simulator, TargetTruth};
use sofipol_pipeline::standards::StandardsTable;
use sofipol_pipeline::stokes::model::TelescopePolarization;

mod score;

use score::{bin_of, scored};
pub use score::{pool_nights, rms_and_mean, table, wrap_angle_deg};

/// A/B swaps of pairs fainter than this flux ratio B/A are labelling errors (closer to
/// equal, noise may legitimately reorder them).
pub const RELABEL_RATIO: f64 = 0.8;

/// P pulls are scored where P_true/sigma_P exceeds this: there Wardle & Kronberg's
/// debiased P is nearly unbiased (mean pull -0.016, rms 1.05 at exactly 3 for equal
/// uncorrelated errors; -0.004, 1.013 at 5).
pub const P_PULL_MIN_SNR: f64 = 3.0;

/// Angle pulls are scored where P_true/sigma_P exceeds this: there the angle's
/// distribution is near Gaussian (its pull rms 1.02 at exactly 5, 1.06 at 3).
pub const GAMMA_PULL_MIN_SNR: f64 = 5.0;

/// What to draw.
#[derive(Debug, Clone)]
pub struct WorldConfig {
    /// Separation bin edges, arcsec.
    pub bins_arcsec: Vec<f64>,
    /// Targets per bin.
    pub targets_per_bin: usize,
    /// Seed.
    pub seed: u64,
    /// Scratch directory for the FITS frames (one sub-folder per target, removed after).
    pub work_dir: PathBuf,
    /// Lowest flux of A, ADU.
    pub min_flux_adu: f64,
    /// Every instrument effect (pixel response, beam ratio, instrumental polarization,
    /// analyzer zero-point and parity, non-linearity, saturation) in every scene.
    pub instrument: bool,
    /// Use the calibration the night provides (dome flats, standards). Off: the reduction
    /// ignores them (to show what they are worth).
    pub calibrate: bool,
    /// PSF axis ratio 0.9-1 per frame (with `instrument`).
    pub ellipticity: bool,
    /// Detector non-linearity (with `instrument`).
    pub nonlinearity: bool,
    /// Every this many targets of a bin has a saturated primary (2e6-4e6 ADU; 0: none).
    pub saturated_every: usize,
    /// The telescope's polarization (effect `telescope_polarization`) in every scene, drawn
    /// once for the night: p_tel uniform in [0, 1 %), psi_tel uniform in [0, 180) deg.
    pub telescope_polarization: bool,
    /// The night's standards observed hours apart at hour angles and declinations
    /// ([`SPREAD_STANDARDS`]) that spread their parallactic angles, instead of one after
    /// another at pointings drawn from their names.
    pub spread_standards: bool,
    /// The interstellar foreground as a field on the sky (effect `foreground_field`) in
    /// every target's scene, drawn once for the night ([`draw_foreground`]).
    pub foreground_field: bool,
}

/// (start UT, Dec, hour angle at the start in h) of the four standards of the world night
/// with `spread_standards`: mean parallactic angles -56, 57, 114 and -149 deg (2 eta covers
/// 187 deg of the circle).
pub const SPREAD_STANDARDS: [(&str, f64, f64); 4] = [
    ("01:00:00", -50.0, -2.0),
    ("03:00:00", -40.0, 1.0),
    ("05:00:00", -20.0, 2.0),
    ("07:00:00", -10.0, -1.0),
];

impl WorldConfig {
    /// The default draw, frames under `work_dir`.
    pub fn new(work_dir: &Path) -> Self {
        WorldConfig {
            bins_arcsec: vec![0.5, 0.8, 1.2, 1.6, 2.5, 4.0, 5.3],
            targets_per_bin: 12,
            seed: 13,
            work_dir: work_dir.to_path_buf(),
            min_flux_adu: 2e3,
            instrument: true,
            calibrate: true,
            ellipticity: true,
            nonlinearity: true,
            saturated_every: 6,
            telescope_polarization: false,
            spread_standards: false,
            foreground_field: false,
        }
    }
}

/// The conditions one target drew.
#[derive(Debug, Clone, Serialize)]
pub struct Conditions {
    /// Seeing FWHM, arcsec (median over frames; each frame +-20 % and 10 % rms).
    pub fwhm_arcsec: f64,
    /// e-o offset (x, y), px.
    pub eo_offset_px: [f64; 2],
    /// Primary position (x, y) at zero offset, px.
    pub primary_xy_px: [f64; 2],
    /// Rotator angles.
    pub orientations_deg: Vec<f64>,
    /// BITPIX of the files.
    pub bitpix: i32,
}

/// One reduced target.
#[derive(Debug, Clone, Serialize)]
pub struct WorldTarget {
    /// Object name.
    pub object: String,
    /// True separation, arcsec.
    pub separation_arcsec: f64,
    /// Flux ratio B/A.
    pub flux_ratio: f64,
    /// Flux of A, ADU.
    pub flux_a_adu: f64,
    /// The conditions.
    pub conditions: Conditions,
    /// Pulls (q, u of A then B; only measured components).
    pub pulls: Vec<f64>,
    /// sigma_q of the measured components.
    pub sigmas: Vec<f64>,
    /// True errors (q - q_true, u - u_true of A then B; only measured components).
    pub errors: Vec<f64>,
    /// Pulls of P, `(P_debiased - P_true)/sigma_P`, of the scored components whose true S/N
    /// P_true/sigma_P exceeds [`P_PULL_MIN_SNR`], where Wardle-Kronberg debiasing is
    /// nearly unbiased. Selected on the true S/N, not on the measured one (the catalog's
    /// cut): a cut on the measured P keeps the upward fluctuations of stars near the
    /// threshold, which biases the mean pull upwards (+0.15 in a Monte Carlo of equal,
    /// uncorrelated errors with the true S/N log-uniform in 0.5-50; +0.03 on the nights of
    /// `bench/tests/accuracy_p_gamma.rs`, whose S/N is mostly high).
    pub p_pulls: Vec<f64>,
    /// Pulls of the angle, `(gamma - gamma_true)/sigma_gamma` with the difference wrapped
    /// to [-90, 90) deg, of the scored components whose true S/N exceeds
    /// [`GAMMA_PULL_MIN_SNR`], where the angle's distribution is near Gaussian.
    pub gamma_pulls: Vec<f64>,
    /// Components not measured.
    pub missing: usize,
    /// Components refused (flagged `saturated` or `ab_identity_unverified`, not scored).
    pub refused: usize,
    /// A was made bright enough to saturate (flux above [`SATURATED_FLUX_ADU`]).
    pub saturated: bool,
    /// Catalog labels swapped against the truth for a pair of flux ratio below [`RELABEL_RATIO`].
    pub relabelled: bool,
    /// Catalog status and flags, for the report.
    pub note: String,
    /// Photometry method of the sequence (`psf` or `aperture`, the catalog's `photometry`).
    pub photometry: String,
    /// Per scored component and orientation: (chi2 of the dither values about their
    /// weighted mean, number of dithers combined), from the catalog's `orientations`.
    pub dither_chi2: Vec<(f64, usize)>,
    /// Per scored component (catalog order) and orientation: (analyzer angle, F, sigma_F).
    pub orientation_f: Vec<Vec<(f64, f64, f64)>>,
}

/// Pull statistics of one bin.
#[derive(Debug, Clone, Serialize)]
pub struct WorldBin {
    /// Bin edges, arcsec.
    pub sep_arcsec: (f64, f64),
    /// Pulls.
    pub n_pulls: usize,
    /// rms pull.
    pub rms_pull: f64,
    /// Mean pull.
    pub mean_pull: f64,
    /// Median sigma_q.
    pub median_sigma: f64,
    /// P pulls ([`WorldTarget::p_pulls`]).
    pub n_p_pulls: usize,
    /// rms P pull.
    pub rms_p_pull: f64,
    /// Mean P pull.
    pub mean_p_pull: f64,
    /// Angle pulls ([`WorldTarget::gamma_pulls`]).
    pub n_gamma_pulls: usize,
    /// rms angle pull.
    pub rms_gamma_pull: f64,
    /// Mean angle pull.
    pub mean_gamma_pull: f64,
    /// rms of the true errors of q and u.
    pub rms_error: f64,
    /// Components not measured.
    pub missing: usize,
    /// Components refused (saturated, or A/B identity unverified).
    pub refused: usize,
    /// Pairs relabelled.
    pub relabelled: usize,
    /// The targets.
    pub targets: Vec<WorldTarget>,
}

/// The instrument of the world night, drawn once: every target and standard sees it.
#[derive(Debug, Clone, Serialize)]
pub struct Instrument {
    /// Beam transmission ratio k = T_e/T_o.
    pub k: f64,
    /// Instrumental polarization (instrument frame) and its angle, deg.
    pub p_inst: f64,
    /// Angle of the instrumental polarization, deg.
    pub p_inst_angle_deg: f64,
    /// True analyzer zero-point, deg (the profile says 0).
    pub zero_point_deg: f64,
    /// True analyzer parity (the profile says +1).
    pub parity: i32,
    /// The telescope's polarization (with `telescope_polarization`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub telescope: Option<TelescopePolarization>,
    /// The foreground field on the sky (with `foreground_field`; not instrumental, but drawn
    /// once per night like the instrument).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub foreground: Option<ForegroundFieldConfig>,
}

/// The night's foreground field, from its own stream of the seed: mean P uniform in
/// [0, 3 %) at an angle uniform in [0, 180) deg (K-band foregrounds of nearby star-forming
/// clouds are 0-3 %), rms of q and of u uniform in [0.1, 0.8) %, coherence log-uniform in
/// [20, 600) arcsec, the modes drawn from the night's seed (every target's scene sees the
/// same field, each at its own place on the sky).
pub fn draw_foreground(seed: u64) -> ForegroundFieldConfig {
    let mut r = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(seed ^ 0xF0E6_0F1E);
    ForegroundFieldConfig {
        p: 0.03 * r.random::<f64>(),
        angle_deg: 180.0 * r.random::<f64>(),
        rms: 0.001 + 0.007 * r.random::<f64>(),
        coherence_arcsec: 20.0 * 30f64.powf(r.random::<f64>()),
        structure_exponent: None,
        modes: 64,
        seed: Some(seed),
    }
}

/// Draw the night's instrument from the seed.
pub fn draw_instrument(cfg: &WorldConfig) -> Instrument {
    let mut r = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(cfg.seed ^ 0x1A57_2B00);
    Instrument {
        k: 0.96 + 0.03 * r.random::<f64>(),
        p_inst: 0.003,
        p_inst_angle_deg: 180.0 * r.random::<f64>(),
        zero_point_deg: -5.0 + 10.0 * r.random::<f64>(),
        parity: if r.random::<f64>() < 0.5 { 1 } else { -1 },
        // Its own stream: the draws above do not depend on it.
        telescope: cfg.telescope_polarization.then(|| {
            let mut r = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(cfg.seed ^ 0x7E1E_5C0E);
            TelescopePolarization {
                p_tel: 0.01 * r.random::<f64>(),
                psi_tel_deg: 180.0 * r.random::<f64>(),
            }
        }),
        foreground: cfg.foreground_field.then(|| draw_foreground(cfg.seed)),
    }
}

/// The effects and sections every scene of the night shares: the detector (same seed of
/// the fixed maps) and, with `cfg.instrument`, the instrument.
fn night_sections(cfg: &WorldConfig, inst: &Instrument) -> (String, String) {
    let mut effects = String::from(
        r#""psf", "sky", "strips", "photon_noise", "read_noise", "bad_pixels", "transparency", "pointing_error", "cosmic_rays""#,
    );
    let mut sections = format!(
        "[psf]\nkind = \"moffat\"\nfwhm_arcsec = {{fwhm}}\nseeing_rms_frac = 0.1\nfwhm_spread_frac = 0.2\nbeta_range = [2.5, 4.0]\n{}[transparency]\nmin = 0.9\n",
        if cfg.instrument && cfg.ellipticity {
            "axis_ratio_range = [0.9, 1.0]\n"
        } else {
            ""
        }
    );
    if cfg.instrument {
        effects += r#", "flat_field", "throughput", "instrumental_polarization", "analyzer_angle", "saturation""#;
        if cfg.nonlinearity {
            effects += r#", "nonlinearity""#;
        }
        sections += &format!(
            "[flat_field]\npixel_rms = 0.01\nvignetting = 0.05\n[throughput]\nt_o = 1.0\nt_e = {}\n[instrumental_polarization]\np = {}\nangle_deg = {}\n[analyzer_angle]\nzero_point_deg = {}\nparity = {}\n",
            inst.k, inst.p_inst, inst.p_inst_angle_deg, inst.zero_point_deg, inst.parity
        );
    }
    if let Some(t) = &inst.telescope {
        effects += r#", "telescope_polarization""#;
        sections += &format!(
            "[telescope_polarization]\np_tel = {}\npsi_tel_deg = {}\n",
            t.p_tel, t.psi_tel_deg
        );
    }
    if let Some(f) = &inst.foreground {
        // (The standards of the calibration scene see none: the simulator adds it to
        // binaries only.)
        effects += r#", "foreground_field""#;
        sections += &format!(
            "[foreground_field]\np = {}\nangle_deg = {}\nrms = {}\ncoherence_arcsec = {}\nmodes = {}\nseed = {}\n",
            f.p,
            f.angle_deg,
            f.rms,
            f.coherence_arcsec,
            f.modes,
            f.seed.unwrap_or(cfg.seed)
        );
    }
    (effects, sections)
}

/// Draw the scene of target `t` of bin `bin` (separations `lo`..`hi`): the scene, its
/// conditions and the flux ratio B/A.
pub fn draw_scene(
    cfg: &WorldConfig,
    inst: &Instrument,
    bin: usize,
    t: usize,
    lo: f64,
    hi: f64,
) -> (Scene, Conditions, f64) {
    let mut r =
        rand::rngs::Xoshiro256PlusPlus::seed_from_u64(cfg.seed ^ ((bin as u64) << 32) ^ (t as u64 * 0x9E37_79B9));
    let sep = lo + (hi - lo) * r.random::<f64>();
    let fwhm = 0.6 + 0.5 * r.random::<f64>();
    // (Beta was drawn here per target; it is now drawn per frame by the simulator: the
    // draw is kept so that every other condition stays what it was.)
    let _ = r.random::<f64>();
    let eo = [-1.0 + 2.0 * r.random::<f64>(), 165.5 + 3.0 * r.random::<f64>()];
    let o_rows = Profile::sofi()
        .geometry
        .target_rows(sofipol_calib::profile::Beam::Ordinary);
    let margin = 30.0;
    let xy = [
        250.0 + 524.0 * r.random::<f64>(),
        o_rows[0] as f64 + margin + {
            let span = (o_rows[1] - o_rows[0]) as f64 - 2.0 * margin;
            span * r.random::<f64>()
        },
    ];
    let mut fa = cfg.min_flux_adu * (2e5 / cfg.min_flux_adu).powf(r.random::<f64>());
    if cfg.instrument && cfg.saturated_every > 0 && t % cfg.saturated_every == cfg.saturated_every - 1 {
        fa = 2e6 * (1.0 + r.random::<f64>());
    }
    let ratio = 0.15 + 0.85 * r.random::<f64>();
    let (pa_, pb) = (0.01 + 0.07 * r.random::<f64>(), 0.01 + 0.07 * r.random::<f64>());
    let (ga, gb) = (180.0 * r.random::<f64>(), 180.0 * r.random::<f64>());
    let pa = 360.0 * r.random::<f64>();
    let orientations: Vec<f64> = if t.is_multiple_of(2) {
        vec![0.0, 45.0]
    } else {
        vec![0.0, 45.0, 90.0, 135.0]
    };
    let bitpix = if (t / 2).is_multiple_of(2) { -32 } else { 16 };
    let (effects, sections) = night_sections(cfg, inst);
    let text = format!(
        r#"name = "world{bin}_{t}"
seed = {seed}
detector_seed = {dseed}
effects = [{effects}]
[observation]
orientations_deg = {orientations:?}
dithers = 5
bitpix = {bitpix}
{sections}
[[binary]]
name = "W{bin}_{t}"
separation_arcsec = {sep}
pa_deg = {pa}
flux_a = {fa}
flux_b = {fb}
p_a = {pa_}
gamma_a_deg = {ga}
p_b = {pb}
gamma_b_deg = {gb}
x_px = {x}
y_px = {y}
"#,
        seed = cfg.seed.wrapping_mul(1000).wrapping_add((bin * 100 + t) as u64),
        dseed = cfg.seed,
        sections = sections.replace("{fwhm}", &fwhm.to_string()),
        fb = fa * ratio,
        x = xy[0],
        y = xy[1],
    );
    let scene = Scene::from_toml(&text, "world scene").expect("valid generated scene");
    let cond = Conditions {
        fwhm_arcsec: fwhm,
        eo_offset_px: eo,
        primary_xy_px: xy,
        orientations_deg: orientations,
        bitpix,
    };
    (scene, cond, ratio)
}

/// Table values of the world night's polarized standards (a user `--standards` file).
pub const WORLD_STANDARDS: &str = r#"
[[standard]]
name = "World Pol A"
filter = "Ks"
p = 0.025
sigma_p = 0.0002
gamma_deg = 40.0
sigma_gamma_deg = 0.1
[[standard]]
name = "World Pol B"
filter = "Ks"
p = 0.02
sigma_p = 0.0002
gamma_deg = 115.0
sigma_gamma_deg = 0.1
"#;

/// The calibration scene of the world night: two unpolarized standards of the built-in
/// table and two polarized ones ([`WORLD_STANDARDS`]), observed at 0/45/90/135, and dome
/// flats at those angles, through the same detector and instrument as the targets (with
/// `spread_standards`, at the times and pointings of [`SPREAD_STANDARDS`]). Each standard's
/// true polarization is drawn from its table value and error
/// ([`crate::standards_truth::draw_night`]), as the calibration's covariance assumes.
pub fn calibration_scene(cfg: &WorldConfig, inst: &Instrument) -> Scene {
    let (effects, sections) = night_sections(cfg, inst);
    let table = world_standards_table();
    let entries: Vec<_> = WORLD_NIGHT_STANDARDS
        .iter()
        .map(|n| table.find(n, "Ks").expect("a world standard in the table"))
        .collect();
    let truth = crate::standards_truth::draw_night(&entries, cfg.seed);
    let pol = |i: usize| format!("p = {}\ngamma_deg = {}\n", truth[i].0, truth[i].1);
    let at = |i: usize| match SPREAD_STANDARDS[i] {
        (ut, dec, h) if cfg.spread_standards => {
            format!("start_ut = \"{ut}\"\ndec_deg = {dec}\nhour_angle_h = {h}\n")
        }
        _ => String::new(),
    };
    let text = format!(
        r#"name = "worldcal"
seed = {seed}
detector_seed = {dseed}
effects = [{effects}, "dome_flats"]
[observation]
orientations_deg = [0.0, 45.0, 90.0, 135.0]
dithers = 3
{sections}
[[standard]]
name = "HD 64299"
flux = 150000.0
{pol0}{at0}[[standard]]
name = "HD_98161"
flux = 150000.0
{pol1}{at1}[[standard]]
name = "World Pol A"
flux = 150000.0
{pol2}{at2}[[standard]]
name = "World Pol B"
flux = 150000.0
{pol3}{at3}"#,
        pol0 = pol(0),
        pol1 = pol(1),
        pol2 = pol(2),
        pol3 = pol(3),
        at0 = at(0),
        at1 = at(1),
        at2 = at(2),
        at3 = at(3),
        seed = cfg.seed.wrapping_mul(1000).wrapping_add(99_999),
        dseed = cfg.seed,
        sections = sections.replace("{fwhm}", "0.8"),
    );
    Scene::from_toml(&text, "world calibration scene").expect("valid generated scene")
}

/// What the night provides for the calibration, measured as `sofipol calib` measures it
/// ([`night::run_night`] on the night's calibration frames): the flats (dome flats) and the
/// calibration from the standards, reduced as single stars.
pub struct NightCalibration {
    /// Flats.
    pub flats: Option<sofipol_calib::flat::FlatSet>,
    /// The calibration measured from the standards (None: no usable standard).
    pub calibration: Option<Calibration>,
}

/// The setup of the world's reductions: the SOFI profile, `params`, the built-in standards
/// table with [`WORLD_STANDARDS`] added.
fn world_setup(params: &TargetParams) -> NightSetup {
    NightSetup {
        profile: Profile::sofi(),
        params: params.clone(),
        calibration: CalibSetup {
            params: CalibrationParams::default(),
            table: world_standards_table(),
            external: None,
        },
    }
}

/// The standards of the world night, in the calibration scene's order.
pub const WORLD_NIGHT_STANDARDS: [&str; 4] = ["HD 64299", "HD_98161", "World Pol A", "World Pol B"];

/// The standards table of the world night: the built-in table with [`WORLD_STANDARDS`].
pub fn world_standards_table() -> StandardsTable {
    let mut table = StandardsTable::builtin();
    table
        .merge_toml(WORLD_STANDARDS, "world standards")
        .expect("valid standards table");
    table
}

/// Simulate the night's calibration frames into a scratch folder and measure the flats and
/// the calibration from them.
pub fn night_calibration(cfg: &WorldConfig, inst: &Instrument, params: &TargetParams) -> NightCalibration {
    let dir = cfg.work_dir.join("calibration");
    let sim = Simulator::new(calibration_scene(cfg, inst), Profile::sofi()).expect("valid scene");
    sim.write_to_dir(&dir, &|_| {}).expect("calibration frames written");
    let setup = world_setup(params);
    let plan = setup.plan(std::slice::from_ref(&dir), None);
    let out = night::run_night(&plan, &setup, &RunOptions::default());
    let _ = std::fs::remove_dir_all(&dir);
    NightCalibration {
        flats: out.flats.set,
        calibration: out.calibration,
    }
}

/// Draw target `t` of bin `bin` (separations `lo`..`hi`) and write its frames and
/// truth.json into `dir` (e.g. to look at one case with `sofipol target`).
pub fn write_target(
    cfg: &WorldConfig,
    bin: usize,
    t: usize,
    lo: f64,
    hi: f64,
    dir: &Path,
) -> (TargetTruth, Conditions, f64) {
    let inst = draw_instrument(cfg);
    let (scene, cond, ratio) = draw_scene(cfg, &inst, bin, t, lo, hi);
    let mut sim_profile = Profile::sofi();
    sim_profile.geometry.eo_offset_px = cond.eo_offset_px;
    let sim = Simulator::new(scene, sim_profile).expect("valid scene");
    let truth = sim.write_to_dir(dir, &|_| {}).expect("frames written");
    (truth.targets[0].clone(), cond, ratio)
}

/// One target drawn, reduced and calibrated, before scoring.
struct Reduced {
    bin: usize,
    target: Target,
    truth: TargetTruth,
    cond: Conditions,
    ratio: f64,
}

fn one_target(
    cfg: &WorldConfig,
    params: &TargetParams,
    flats: Option<&sofipol_calib::flat::FlatSet>,
    (bin, t, lo, hi): (usize, usize, f64, f64),
) -> Reduced {
    let dir = cfg.work_dir.join(format!("w{bin}_{t}"));
    let (truth, cond, ratio) = write_target(cfg, bin, t, lo, hi, &dir);
    // Reduce as `sofipol night` would: plan the folder, reduce its sequence from the files
    // with the night's flats, the instrument profile's defaults (not the drawn e-o offset).
    let setup = world_setup(params);
    let plan = setup.plan(std::slice::from_ref(&dir), None);
    let mut reduced = night::reduce_sequences(&plan.sequences, &setup.profile, params, None, flats, &Hooks::default());
    let target = reduced.catalog.targets.swap_remove(0);
    let _ = std::fs::remove_dir_all(&dir);
    Reduced {
        bin,
        target,
        truth,
        cond,
        ratio,
    }
}

/// Flux of A above which a world target is saturated by design, ADU.
pub const SATURATED_FLUX_ADU: f64 = 5e5;

/// Draw, write, reduce, calibrate and score every target (targets in parallel); with
/// `cfg.instrument` the night's calibration (dome flats, standards) is simulated and
/// reduced first and, with `cfg.calibrate`, used.
pub fn run(cfg: &WorldConfig, params: &TargetParams) -> Vec<WorldBin> {
    let inst = draw_instrument(cfg);
    let cal = (cfg.instrument && cfg.calibrate).then(|| night_calibration(cfg, &inst, params));
    let jobs: Vec<(usize, usize, f64, f64)> = cfg
        .bins_arcsec
        .windows(2)
        .enumerate()
        .flat_map(|(bin, w)| (0..cfg.targets_per_bin).map(move |t| (bin, t, w[0], w[1])))
        .collect();
    let flats = cal.as_ref().and_then(|c| c.flats.as_ref());
    let reduced: Vec<Reduced> = jobs.par_iter().map(|&j| one_target(cfg, params, flats, j)).collect();
    let mut cat = Catalog::default();
    let meta: Vec<(usize, TargetTruth, Conditions, f64)> = reduced
        .into_iter()
        .map(|r| {
            cat.targets.push(r.target);
            (r.bin, r.truth, r.cond, r.ratio)
        })
        .collect();
    if cfg.instrument {
        // The night's calibration, as `sofipol night` applies it (without it, every
        // 2-orientation component is flagged `uncalibrated` and left as measured).
        // The calibration measured from the night's standards, applied to every target.
        let source = match cal.and_then(|c| c.calibration) {
            Some(c) => CalibrationSource::File("the night's standards".into(), Box::new(c)),
            None => CalibrationSource::Night,
        };
        calibrate_catalog(
            &mut cat,
            vec![],
            source,
            &CalibrationContext {
                table: &StandardsTable::builtin(),
                profile: &Profile::sofi(),
                params: &CalibrationParams::default(),
                debias: params.measure.debias,
                cut_snr: params.measure.cut_snr,
            },
        );
    }
    let mut targets: Vec<Vec<WorldTarget>> = vec![Vec::new(); cfg.bins_arcsec.len().saturating_sub(1)];
    for (target, (bin, truth, cond, ratio)) in cat.targets.into_iter().zip(meta) {
        let sat = truth.components[0].flux > SATURATED_FLUX_ADU;
        targets[bin].push(scored(
            Reduced {
                bin,
                target,
                truth,
                cond,
                ratio,
            },
            sat,
        ));
    }
    cfg.bins_arcsec
        .windows(2)
        .zip(targets)
        .map(|(w, targets)| bin_of((w[0], w[1]), targets))
        .collect()
}
