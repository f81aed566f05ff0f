//! `sofipol bench calibration`: the pooled accuracy of the polarimetric calibration over
//! many simulated nights, in two cases where the standards alone cannot measure everything
//! (docs/accuracy.md, "Calibration in hard cases").
//!
//! ```text
//!  clustered        6 standards (3 unpolarized, 3 polarized) at Dec -50 and hour angles
//!                   0.75-1.25 h: their parallactic angles span ~15 deg, so the telescope's
//!                   polarization cannot be told apart from the offset c
//!  polarized-only   HD 204827, HD 154445, HD 161056 only, hours apart at parallactic
//!                   angles spread over the circle; no unpolarized standard
//! ```
//!
//! Per night (seed) the instrument and the telescope are drawn over a realistic range
//! (t_e, the instrumental polarization, the analyzer's zero-point; the telescope's term from
//! the profile's mirror prior in Ks, [`ks_prior`]), each standard's true p and gamma are drawn
//! from its table value and error ([`crate::standards_truth`]), and ~10 binaries with drawn
//! separations, fluxes and polarizations fill the night. Each night is a scene file written
//! beside its results, simulated by `sofipol simulate` and reduced by `sofipol night` in
//! child processes (the current executable): the harness scores the very catalog.json a
//! user gets against the simulator's truth.json. Per-binary and per-component pulls go to
//! a JSON file for re-analysis.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};
use sofipol_pipeline::catalog::{fold_delta_gamma, Catalog, Target};
use sofipol_pipeline::sim::truth::DetectorTruth;
use sofipol_pipeline::sim::Scene;
use sofipol_pipeline::standards::StandardsTable;
use sofipol_pipeline::stokes::fresnel::TelescopePrior;
use sofipol_pipeline::stokes::model::TelescopePolarization;

/// The mirror's prior of the telescope's term in Ks from the built-in SOFI profile
/// (docs/calibration.md, "The mirror's prior"): each night's true term is drawn from it, so
/// the nights vary the term over the whole range the prior claims (0.77 +- 0.15 %, 0 +- 5
/// deg), no narrower (the errors would then be conservative) and no wider.
pub fn ks_prior() -> TelescopePrior {
    TelescopePrior::of(&sofipol_calib::profile::Profile::sofi().telescope, "Ks")
        .expect("the built-in SOFI profile gives the mirror's index in Ks")
}

/// A true telescope term drawn from `prior`: Gaussian along the prior's mean direction in
/// the (a, b) plane with width sigma_p, and across it with width p 2 sigma_psi, as the joint
/// fit's prior rows state it. Returns (p_tel, psi_tel in deg, within [-90, 90)).
pub fn draw_telescope(prior: &TelescopePrior, rng: &mut impl rand::Rng) -> (f64, f64) {
    let mut z = || -> f64 { rand_distr::Distribution::sample(&rand_distr::StandardNormal, rng) };
    let along = prior.p_tel + prior.sigma_p_tel * z();
    let across = prior.p_tel * 2.0 * prior.sigma_psi_tel_deg.to_radians() * z();
    let t = 2.0 * prior.psi_tel_deg.to_radians();
    let (a, b) = (along * t.cos() - across * t.sin(), along * t.sin() + across * t.cos());
    (a.hypot(b), wrap_deg(0.5 * b.atan2(a).to_degrees()))
}

/// The two hard cases.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Case {
    /// Six standards (3 unpolarized, 3 polarized) at nearly one parallactic angle (span
    /// ~15 deg): the telescope's polarization cannot be separated from c by them.
    Clustered,
    /// Three polarized standards (HD 204827, HD 154445, HD 161056) at parallactic angles
    /// spread over the circle, no unpolarized one.
    PolarizedOnly,
}

impl Case {
    /// Its name on the command line and in the files.
    pub fn name(self) -> &'static str {
        match self {
            Case::Clustered => "clustered",
            Case::PolarizedOnly => "polarized-only",
        }
    }

    /// A salt that keeps the two cases' draws apart for the same seed.
    fn salt(self) -> u64 {
        match self {
            Case::Clustered => 0xC1_057E_4ED0,
            Case::PolarizedOnly => 0x9014_0411_0000,
        }
    }
}

/// Arguments of `sofipol bench calibration`.
#[derive(clap::Args, Debug, Clone)]
pub struct CalibrationArgs {
    /// Case to run (repeat for both) [default: clustered and polarized-only].
    #[arg(long, value_enum)]
    case: Vec<Case>,
    /// Nights (seeds) per case: --first-seed, --first-seed + 1, ...
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=1000))]
    seeds: u64,
    /// The first seed.
    #[arg(long, default_value_t = 1)]
    first_seed: u64,
    /// Binaries per night.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=40))]
    binaries: u64,
    /// Output directory (created): per case and seed the scene, truth.json, catalog.json
    /// and the night's stderr; calibration_bench.json with every pull (required).
    #[arg(short, long, alias = "out", value_name = "DIR")]
    output: PathBuf,
    /// Worker threads of each `sofipol night` (default: all cores).
    #[arg(long)]
    jobs: Option<usize>,
    /// Keep each night's simulated frames (~0.7 GB a night) instead of deleting them once
    /// the night is reduced.
    #[arg(long)]
    keep_frames: bool,
}

/// What was drawn for one night (written into the JSON beside its results).
#[derive(Debug, Clone, Serialize)]
pub struct NightDraws {
    /// Extraordinary beam's throughput (t_o = 1).
    pub t_e: f64,
    /// Instrumental polarization added to F (angle 0).
    pub p_inst: f64,
    /// Analyzer zero-point, deg (parity +1).
    pub zero_point_deg: f64,
    /// The telescope's p_tel.
    pub p_tel: f64,
    /// Its angle from the vertical, deg.
    pub psi_tel_deg: f64,
    /// The standards observed.
    pub standards: Vec<StandardDraw>,
}

/// One standard of a night: its table values and the truth drawn from them.
#[derive(Debug, Clone, Serialize)]
pub struct StandardDraw {
    /// Name in the built-in table.
    pub name: String,
    /// Table p and gamma (Ks).
    pub table_p: f64,
    /// Table angle, deg.
    pub table_gamma_deg: f64,
    /// The simulated truth.
    pub p: f64,
    /// Simulated angle, deg.
    pub gamma_deg: f64,
    /// Pointing: declination, deg.
    pub dec_deg: f64,
    /// Hour angle at the start, h.
    pub hour_angle_h: f64,
    /// Start of the sequence (UT).
    pub start_ut: String,
}

/// The effects and fixed sections of every night: those of
/// testdata/scenes/telpol_night_same_eta.toml.
const SCENE_SECTIONS: &str = r#"effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "bad_pixels",
           "transparency", "pointing_error", "cosmic_rays", "saturation",
           "flat_field", "dome_flats", "throughput", "instrumental_polarization", "analyzer_angle",
           "telescope_polarization"]

[observation]
orientations_deg = [0.0, 45.0]
dithers = 5
dit_s = 10.0
ndit = 6
filter = "Ks"
bitpix = -32
date = "1999-03-03"
start_ut = "00:30:00"
overhead_s = 15.0

[psf]
kind = "moffat"
fwhm_arcsec = 0.8
beta = 3.0
seeing_rms_frac = 0.08

[sky]
level_adu = 1500.0
gradient_x = 0.05
gradient_y = -0.03
frame_change_frac = 0.03

[bad_pixels]
hot_fraction = 3e-4
dead_fraction = 3e-4

[transparency]
min = 0.92

[pointing_error]
rms_px = 0.7

[cosmic_rays]
rate_per_frame = 30.0

[flat_field]
pixel_rms = 0.01
vignetting = 0.05

[dome_flats]
frames_on = 3
frames_off = 3
"#;

/// A uniform draw in [a, b).
fn uniform(rng: &mut impl rand::Rng, a: f64, b: f64) -> f64 {
    a + (b - a) * rng.random::<f64>()
}

/// The scene of night `seed` of `case` with `binaries` binaries, and what was drawn.
pub fn scene_text(case: Case, seed: u64, binaries: usize) -> anyhow::Result<(String, NightDraws)> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(case.salt() ^ seed.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let t_e = uniform(&mut rng, 0.95, 0.99);
    let p_inst = uniform(&mut rng, 0.001, 0.004);
    let zero_point_deg = uniform(&mut rng, 0.0, 6.0);
    let (p_tel, psi_tel_deg) = draw_telescope(&ks_prior(), &mut rng);
    // (name, start UT, dec range, hour-angle range at the start).
    let plan: Vec<(&str, &str, [f64; 2], [f64; 2])> = match case {
        Case::Clustered => [
            ("HD 64299", "00:30:00"),
            ("HD 204827", "02:00:00"),
            ("HD 98161", "03:30:00"),
            ("HD 154445", "05:00:00"),
            ("HD 94851", "06:30:00"),
            ("HD 161056", "08:00:00"),
        ]
        .into_iter()
        .map(|(n, t)| (n, t, [-50.0, -50.0], [0.75, 1.25]))
        .collect(),
        // Parallactic angles about -36..-56, +-155..180 and 66..94 deg: 2 eta spread over
        // the circle.
        Case::PolarizedOnly => vec![
            ("HD 204827", "00:30:00", [-60.0, -45.0], [-2.5, -1.5]),
            ("HD 154445", "02:45:00", [-15.0, -5.0], [-0.5, 0.5]),
            ("HD 161056", "05:00:00", [-45.0, -35.0], [2.0, 3.0]),
        ],
    };
    let table = StandardsTable::builtin();
    let entries = plan
        .iter()
        .map(|(name, ..)| {
            table
                .find(name, "Ks")
                .with_context(|| format!("{name} is not in the built-in standards table for Ks"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let truths = crate::standards_truth::draw_night(&entries, case.salt() ^ seed);
    let mut standards = Vec::new();
    for ((name, ut, dec, ha), (e, (p, g))) in plan.iter().zip(entries.iter().zip(truths)) {
        standards.push(StandardDraw {
            name: name.to_string(),
            table_p: e.p,
            table_gamma_deg: e.gamma_deg,
            p,
            gamma_deg: g,
            dec_deg: uniform(&mut rng, dec[0], dec[1]),
            hour_angle_h: uniform(&mut rng, ha[0], ha[1]),
            start_ut: ut.to_string(),
        });
    }
    let mut s = format!(
        "# sofipol bench calibration: case {case}, seed {seed} (drawn: t_e, p_inst, zero-point, p_tel, psi_tel,\n\
         # each standard's truth from its table value and error, the binaries)\n\
         name = \"cal_{tag}_{seed}\"\nseed = {seed}\n{SCENE_SECTIONS}\n\
         [throughput]\nt_o = 1.0\nt_e = {t_e}\n\n\
         [instrumental_polarization]\np = {p_inst}\nangle_deg = 0.0\n\n\
         [analyzer_angle]\nzero_point_deg = {zero_point_deg}\nparity = 1\n\n\
         [telescope_polarization]\np_tel = {p_tel}\npsi_tel_deg = {psi_tel_deg}\n",
        case = case.name(),
        tag = match case {
            Case::Clustered => "clu",
            Case::PolarizedOnly => "pol",
        },
    );
    for d in &standards {
        s += &format!(
            "\n[[standard]]\nname = \"{}\"\nflux = 200000.0\np = {}\ngamma_deg = {}\nstart_ut = \"{}\"\ndec_deg = {}\nhour_angle_h = {}\n",
            d.name, d.p, d.gamma_deg, d.start_ut, d.dec_deg, d.hour_angle_h
        );
    }
    for i in 0..binaries {
        let flux_a = uniform(&mut rng, 40_000.0, 150_000.0);
        s += &format!(
            "\n[[binary]]\nname = \"B{i:02}\"\ndec_deg = {}\nhour_angle_h = {}\nseparation_arcsec = {}\npa_deg = {}\n\
             flux_a = {flux_a}\nflux_b = {}\np_a = {}\ngamma_a_deg = {}\np_b = {}\ngamma_b_deg = {}\n",
            uniform(&mut rng, -65.0, -5.0),
            uniform(&mut rng, -3.0, 3.0),
            uniform(&mut rng, 1.0, 5.0),
            uniform(&mut rng, 0.0, 360.0),
            flux_a * uniform(&mut rng, 0.25, 0.75),
            uniform(&mut rng, 0.005, 0.06),
            uniform(&mut rng, 0.0, 180.0),
            uniform(&mut rng, 0.005, 0.06),
            uniform(&mut rng, 0.0, 180.0),
        );
    }
    // Refused here, naming the key, rather than by the child process.
    Scene::from_toml(&s, "bench calibration scene").map_err(anyhow::Error::msg)?;
    let draws = NightDraws {
        t_e,
        p_inst,
        zero_point_deg,
        p_tel,
        psi_tel_deg,
        standards,
    };
    Ok((s, draws))
}

/// An angle difference, deg, wrapped into [-90, 90) (axial angles: 180 deg is no
/// difference).
pub fn wrap_deg(d: f64) -> f64 {
    (d + 90.0).rem_euclid(180.0) - 90.0
}

/// Whether `truth` lies inside the closed interval `[lo, hi]` (`None` or NaN ends: not
/// counted, `None` returned).
pub fn covers(interval: Option<[f64; 2]>, truth: f64) -> Option<bool> {
    let [lo, hi] = interval?;
    (lo.is_finite() && hi.is_finite() && truth.is_finite()).then_some(lo <= truth && truth <= hi)
}

/// (covered, counted) over values that have an interval.
pub fn coverage(values: impl IntoIterator<Item = Option<bool>>) -> (usize, usize) {
    values
        .into_iter()
        .flatten()
        .fold((0, 0), |(k, n), c| (k + usize::from(c), n + 1))
}

/// n, rms, mean and median absolute value of the finite values (of pulls: a unit Gaussian
/// has rms 1 and median |x| 0.674; an rms far above with the median near 0.67 means a few
/// outliers).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Moments {
    /// Values counted.
    pub n: usize,
    /// Root mean square.
    pub rms: f64,
    /// Mean.
    pub mean: f64,
    /// Median of |x|.
    pub median_abs: f64,
}

impl Moments {
    /// Of the finite values of `v`.
    pub fn of(v: impl IntoIterator<Item = f64>) -> Moments {
        let v: Vec<f64> = v.into_iter().filter(|x| x.is_finite()).collect();
        let n = v.len();
        let nf = n as f64;
        Moments {
            n,
            rms: (v.iter().map(|x| x * x).sum::<f64>() / nf).sqrt(),
            mean: v.iter().sum::<f64>() / nf,
            median_abs: median(v.iter().map(|x| x.abs()).collect()),
        }
    }
}

/// What the harness reads of truth.json (pipeline/src/sim/truth.rs writes it).
#[derive(Deserialize)]
struct TruthFile {
    scene: Scene,
    #[serde(default)]
    telescope_polarization: Option<TelescopePolarization>,
    #[serde(default)]
    detector: DetectorTruth,
    targets: Vec<TruthTarget>,
    #[serde(default)]
    standards: Vec<TruthTarget>,
}

#[derive(Deserialize)]
struct TruthTarget {
    object: String,
    separation_arcsec: f64,
    pa_deg: f64,
    components: Vec<TruthComponent>,
    frames: Vec<TruthFrame>,
}

#[derive(Deserialize, Clone)]
struct TruthComponent {
    flux: f64,
    q: f64,
    u: f64,
    p: f64,
    gamma_deg: f64,
}

#[derive(Deserialize)]
struct TruthFrame {
    pointing: TruthPointing,
}

#[derive(Deserialize)]
struct TruthPointing {
    parallactic_angle_deg: f64,
}

/// One binary's Delta-gamma against the truth.
#[derive(Debug, Clone, Serialize)]
pub struct BinaryScore {
    /// Case.
    pub case: Case,
    /// Night.
    pub seed: u64,
    /// OBJECT.
    pub object: String,
    /// The target's status in the catalog.
    pub status: String,
    /// True separation, arcsec.
    pub separation_arcsec: f64,
    /// True flux ratio B/A.
    pub flux_ratio: f64,
    /// True P of A and B.
    pub p_true: [f64; 2],
    /// The catalog's A and B were the truth's B and A (by the position angle).
    pub swapped: bool,
    /// passes_cut of A and B.
    pub passes_cut: [bool; 2],
    /// Both components have finite q, u and errors.
    pub both_measured: bool,
    /// True Delta-gamma, folded into [0, 90] as the catalog's.
    pub true_dgamma_deg: f64,
    /// Measured Delta-gamma: the catalog's when both pass the cut, else computed from the
    /// catalog's components by the catalog's own function (`Target::update_delta_gamma`,
    /// the cut lifted) with the catalog's calibration covariance.
    pub dgamma_deg: Option<f64>,
    /// Its 1-sigma error, deg.
    pub sigma_dgamma_deg: Option<f64>,
    /// Its 68.27 % interval, deg.
    pub dgamma_interval_deg: Option<[f64; 2]>,
    /// `catalog` or `recomputed` (the cut lifted).
    pub dgamma_source: &'static str,
    /// (measured - true) wrapped into [-90, 90), over sigma.
    pub pull: Option<f64>,
    /// The true Delta-gamma inside the interval.
    pub covered: Option<bool>,
    /// For a binary whose Delta-gamma the catalog gives: whether the recomputation (the
    /// path of `recomputed`) gives the same three numbers bit for bit.
    pub recompute_agrees: Option<bool>,
}

/// One component's q, u against the truth.
#[derive(Debug, Clone, Serialize)]
pub struct ComponentScore {
    /// Case.
    pub case: Case,
    /// Night.
    pub seed: u64,
    /// OBJECT.
    pub object: String,
    /// "A" or "B" (the catalog's).
    pub name: String,
    /// Catalog q, u, their errors.
    pub q: f64,
    /// Catalog u.
    pub u: f64,
    /// sigma_q.
    pub sigma_q: f64,
    /// sigma_u.
    pub sigma_u: f64,
    /// The truth's sky-frame q, u.
    pub q_true: f64,
    /// True u.
    pub u_true: f64,
    /// (q - q_true)/sigma_q.
    pub pull_q: f64,
    /// (u - u_true)/sigma_u.
    pub pull_u: f64,
    /// P/sigma_P as catalogued.
    pub snr: f64,
    /// passes_cut.
    pub passes_cut: bool,
    /// Flags (labels).
    pub flags: Vec<String>,
}

/// One night's calibration against its truth.
#[derive(Debug, Clone, Serialize)]
pub struct NightScore {
    /// Case.
    pub case: Case,
    /// Seed.
    pub seed: u64,
    /// Exit code of `sofipol simulate` and of `sofipol night` (None: killed).
    pub simulate_exit: Option<i32>,
    /// `sofipol night`'s exit code.
    pub night_exit: Option<i32>,
    /// Wall times, s.
    pub simulate_s: f64,
    /// `sofipol night`, s.
    pub night_s: f64,
    /// What was drawn.
    pub draws: NightDraws,
    /// The standards' frame parallactic angles: their span (mod 180, deg) and each
    /// standard's mean.
    pub standards_eta_span_deg: f64,
    /// Each standard's parallactic angles, first and last frame, deg.
    pub standards_eta_deg: Vec<[f64; 2]>,
    /// True offset c of F.
    pub c_true: Option<f64>,
    /// Fitted c and its error.
    pub c: Option<[f64; 2]>,
    /// (c - c_true)/sigma_c.
    pub c_pull: Option<f64>,
    /// Fitted theta0 and its error, deg.
    pub theta0_deg: Option<[f64; 2]>,
    /// (theta0 - zero_point) wrapped, over sigma.
    pub theta0_pull: Option<f64>,
    /// Parity fitted and whether measured.
    pub parity: Option<(i32, bool)>,
    /// Fitted p_tel and its error.
    pub p_tel: Option<[f64; 2]>,
    /// (p_tel - p_tel,true)/sigma.
    pub p_tel_pull: Option<f64>,
    /// Fitted psi_tel and its error, deg.
    pub psi_tel_deg: Option<[f64; 2]>,
    /// (psi_tel - psi_tel,true) wrapped, over sigma.
    pub psi_tel_pull: Option<f64>,
    /// Why the telescope was not corrected (the calibration's `telescope_uncorrected`).
    pub telescope_uncorrected: Option<String>,
    /// Why c and theta0 could not be separated (`incomplete`).
    pub incomplete: Option<String>,
    /// Why theta0 is the profile's.
    pub zero_point_from_profile: Option<String>,
    /// Standards' flags (label: count).
    pub standard_flags: BTreeMap<String, usize>,
    /// What went wrong with this night (simulation or reduction failed, a file unreadable).
    pub error: Option<String>,
}

/// Everything one night gave.
struct NightResult {
    night: NightScore,
    binaries: Vec<BinaryScore>,
    components: Vec<ComponentScore>,
}

/// Runs `exe args`, returning (exit code, wall s, stderr).
fn child(exe: &Path, args: &[&std::ffi::OsStr]) -> anyhow::Result<(Option<i32>, f64, String)> {
    let t = Instant::now();
    let o = std::process::Command::new(exe)
        .args(args)
        .stdin(std::process::Stdio::null())
        .output()
        .with_context(|| format!("running {}", exe.display()))?;
    Ok((
        o.status.code(),
        t.elapsed().as_secs_f64(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    ))
}

/// Simulate, reduce and score one night in `dir`.
fn run_night(exe: &Path, case: Case, seed: u64, args: &CalibrationArgs, dir: &Path) -> anyhow::Result<NightResult> {
    use std::ffi::OsStr;
    let (text, draws) = scene_text(case, seed, args.binaries as usize)?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let scene = dir.join("scene.toml");
    sofipol_pipeline::io::write_atomic(&scene, text.as_bytes())?;
    let raw = dir.join("raw");
    if raw.exists() {
        std::fs::remove_dir_all(&raw).with_context(|| format!("removing {}", raw.display()))?;
    }
    let mut night = NightScore {
        case,
        seed,
        simulate_exit: None,
        night_exit: None,
        simulate_s: f64::NAN,
        night_s: f64::NAN,
        draws,
        standards_eta_span_deg: f64::NAN,
        standards_eta_deg: Vec::new(),
        c_true: None,
        c: None,
        c_pull: None,
        theta0_deg: None,
        theta0_pull: None,
        parity: None,
        p_tel: None,
        p_tel_pull: None,
        psi_tel_deg: None,
        psi_tel_pull: None,
        telescope_uncorrected: None,
        incomplete: None,
        zero_point_from_profile: None,
        standard_flags: BTreeMap::new(),
        error: None,
    };
    let empty = |night| NightResult {
        night,
        binaries: Vec::new(),
        components: Vec::new(),
    };
    let (code, secs, err) = child(
        exe,
        &[
            OsStr::new("simulate"),
            scene.as_os_str(),
            OsStr::new("-o"),
            raw.as_os_str(),
            OsStr::new("-q"),
        ],
    )?;
    (night.simulate_exit, night.simulate_s) = (code, secs);
    if code != Some(0) {
        night.error = Some(format!("sofipol simulate exited {code:?}: {}", err.trim()));
        return Ok(empty(night));
    }
    // truth.json beside the night, not among its frames.
    let truth_path = dir.join("truth.json");
    std::fs::rename(raw.join("truth.json"), &truth_path).context("moving truth.json out of the frames")?;
    let catalog_path = dir.join("catalog.json");
    let jobs = args.jobs.map(|j| j.to_string());
    let mut night_args: Vec<&OsStr> = vec![
        OsStr::new("night"),
        raw.as_os_str(),
        OsStr::new("-o"),
        catalog_path.as_os_str(),
        OsStr::new("--no-png"),
    ];
    if let Some(j) = &jobs {
        night_args.extend([OsStr::new("--jobs"), OsStr::new(j.as_str())]);
    }
    let (code, secs, err) = child(exe, &night_args)?;
    (night.night_exit, night.night_s) = (code, secs);
    sofipol_pipeline::io::write_atomic(&dir.join("night.stderr"), err.as_bytes())?;
    if !args.keep_frames {
        std::fs::remove_dir_all(&raw).with_context(|| format!("removing {}", raw.display()))?;
    }
    if !matches!(code, Some(0) | Some(2)) {
        night.error = Some(format!(
            "sofipol night exited {code:?}: {}",
            err.lines().last().unwrap_or("").trim()
        ));
        return Ok(empty(night));
    }
    let read = || -> anyhow::Result<(Catalog, TruthFile)> {
        let catalog = sofipol_pipeline::input::read_catalog(&catalog_path)?;
        let text = std::fs::read_to_string(&truth_path).with_context(|| format!("reading {}", truth_path.display()))?;
        let truth = serde_json::from_str(&text).with_context(|| format!("reading {}", truth_path.display()))?;
        Ok((catalog, truth))
    };
    let (catalog, truth) = match read() {
        Ok(r) => r,
        Err(e) => {
            night.error = Some(format!("{e:#}"));
            return Ok(empty(night));
        }
    };
    score_calibration(&mut night, &catalog, &truth);
    let (binaries, components) = score_binaries(case, seed, &catalog, &truth);
    Ok(NightResult {
        night,
        binaries,
        components,
    })
}

/// The calibration of the catalog's Ks filter against the truth.
fn score_calibration(night: &mut NightScore, catalog: &Catalog, truth: &TruthFile) {
    let etas: Vec<[f64; 2]> = truth
        .standards
        .iter()
        .filter_map(|s| {
            let first = s.frames.first()?.pointing.parallactic_angle_deg;
            let last = s.frames.last()?.pointing.parallactic_angle_deg;
            Some([first, last])
        })
        .collect();
    night.standards_eta_span_deg = axial_span_deg(etas.iter().flatten().copied());
    night.standards_eta_deg = etas;
    for s in &catalog.standards {
        for f in &s.flags {
            *night.standard_flags.entry(f.label()).or_default() += 1;
        }
    }
    night.c_true = truth.detector.offset_c();
    let zero_point = truth.scene.analyzer_angle.as_ref().map_or(0.0, |a| a.zero_point_deg);
    let Some(f) = catalog
        .calibration
        .as_ref()
        .and_then(|a| a.calibration())
        .and_then(|c| c.for_filter("Ks"))
    else {
        night.error = Some("the catalog has no calibration for Ks".into());
        return;
    };
    night.incomplete = f.incomplete.clone();
    night.telescope_uncorrected = f.telescope_uncorrected.clone();
    night.zero_point_from_profile = f.zero_point_from_profile.clone();
    if let Some(o) = f.offset {
        night.c = Some([o.c, o.sigma_c]);
        night.c_pull = night.c_true.map(|c| (o.c - c) / o.sigma_c);
    }
    if let Some(a) = f.angles {
        night.theta0_deg = Some([a.theta0_deg, a.sigma_theta0_deg]);
        night.theta0_pull = Some(wrap_deg(a.theta0_deg - zero_point) / a.sigma_theta0_deg);
        night.parity = Some((a.parity, a.parity_measured));
    }
    if let (Some(t), Some(tt)) = (&f.telescope, &truth.telescope_polarization) {
        night.p_tel = Some([t.p_tel, t.sigma_p_tel]);
        night.p_tel_pull = Some((t.p_tel - tt.p_tel) / t.sigma_p_tel);
        night.psi_tel_deg = Some([t.psi_tel_deg, t.sigma_psi_tel_deg]);
        night.psi_tel_pull = Some(wrap_deg(t.psi_tel_deg - tt.psi_tel_deg) / t.sigma_psi_tel_deg);
    }
}

/// The span of axial angles (deg, mod 180): 180 minus the largest gap between them.
fn axial_span_deg(angles: impl IntoIterator<Item = f64>) -> f64 {
    let mut a: Vec<f64> = angles
        .into_iter()
        .filter(|x| x.is_finite())
        .map(|x| x.rem_euclid(180.0))
        .collect();
    if a.is_empty() {
        return f64::NAN;
    }
    a.sort_by(f64::total_cmp);
    let wrap_gap = a[0] + 180.0 - a[a.len() - 1];
    let gap = a.windows(2).map(|w| w[1] - w[0]).fold(wrap_gap, f64::max);
    180.0 - gap
}

/// Each catalog target with its truth, the truth's components in the catalog's order: the
/// catalog's B is placed by its position angle from A, so one opposite to the truth's
/// means the labels were exchanged.
fn matched<'a>(catalog: &'a Catalog, truth: &'a TruthFile) -> Vec<(&'a Target, &'a TruthTarget, bool)> {
    truth
        .targets
        .iter()
        .filter_map(|tt| {
            let t = catalog.targets.iter().find(|t| t.object == tt.object)?;
            let swapped = t
                .pa_deg
                .is_some_and(|pa| (90.0..270.0).contains(&(pa - tt.pa_deg).rem_euclid(360.0)));
            Some((t, tt, swapped))
        })
        .collect()
}

/// Every binary's Delta-gamma and every component's q, u against the truth.
fn score_binaries(
    case: Case,
    seed: u64,
    catalog: &Catalog,
    truth: &TruthFile,
) -> (Vec<BinaryScore>, Vec<ComponentScore>) {
    let fc = catalog
        .calibration
        .as_ref()
        .and_then(|a| a.calibration())
        .and_then(|c| c.for_filter("Ks"));
    let cov = fc.map(|f| f.covariance_matrix());
    let (mut binaries, mut components) = (Vec::new(), Vec::new());
    for (t, tt, swapped) in matched(catalog, truth) {
        let mut comps: Vec<TruthComponent> = tt.components.clone();
        if swapped {
            comps.swap(0, 1);
        }
        let measured = |c: &sofipol_pipeline::catalog::Component| {
            c.q.is_finite() && c.u.is_finite() && c.sigma_q > 0.0 && c.sigma_u > 0.0
        };
        for (c, ct) in t.components.iter().zip(&comps) {
            if !measured(c) {
                continue;
            }
            components.push(ComponentScore {
                case,
                seed,
                object: t.object.clone(),
                name: c.name.clone(),
                q: c.q,
                u: c.u,
                sigma_q: c.sigma_q,
                sigma_u: c.sigma_u,
                q_true: ct.q,
                u_true: ct.u,
                pull_q: (c.q - ct.q) / c.sigma_q,
                pull_u: (c.u - ct.u) / c.sigma_u,
                snr: c.snr.unwrap_or(f64::NAN),
                passes_cut: c.passes_cut,
                flags: c.flags.iter().map(|f| f.label()).collect(),
            });
        }
        let [ta, tb] = [&tt.components[0], &tt.components[1]];
        let true_dg = fold_delta_gamma(ta.gamma_deg, tb.gamma_deg);
        let both = t.components.len() == 2 && t.components.iter().all(measured);
        let passes = [0, 1].map(|i| t.components.get(i).is_some_and(|c| c.passes_cut));
        // The catalog's own Delta-gamma with its cut lifted: for binaries that do not both
        // pass, and, as a check of that path, for those that do.
        let lifted = both.then(|| {
            let mut lifted = t.clone();
            lifted.components.iter_mut().for_each(|c| c.passes_cut = true);
            lifted.update_delta_gamma(cov.as_ref());
            lifted
        });
        let recompute_agrees = match (&lifted, t.delta_gamma_deg) {
            (Some(l), Some(_)) => Some(
                l.delta_gamma_deg == t.delta_gamma_deg
                    && l.sigma_delta_gamma_deg == t.sigma_delta_gamma_deg
                    && l.delta_gamma_interval_deg == t.delta_gamma_interval_deg,
            ),
            _ => None,
        };
        let (dg, sigma, interval, source) = if t.delta_gamma_deg.is_some() {
            (
                t.delta_gamma_deg,
                t.sigma_delta_gamma_deg,
                t.delta_gamma_interval_deg,
                "catalog",
            )
        } else if let Some(l) = &lifted {
            (
                l.delta_gamma_deg,
                l.sigma_delta_gamma_deg,
                l.delta_gamma_interval_deg,
                "recomputed",
            )
        } else {
            (None, None, None, "none")
        };
        let pull = match (dg, sigma) {
            (Some(d), Some(s)) if s > 0.0 => Some(wrap_deg(d - true_dg) / s),
            _ => None,
        };
        binaries.push(BinaryScore {
            case,
            seed,
            object: t.object.clone(),
            status: format!("{:?}", t.status).to_lowercase(),
            separation_arcsec: tt.separation_arcsec,
            flux_ratio: tb.flux / ta.flux,
            p_true: [ta.p, tb.p],
            swapped,
            passes_cut: passes,
            both_measured: both,
            true_dgamma_deg: true_dg,
            dgamma_deg: dg,
            sigma_dgamma_deg: sigma,
            dgamma_interval_deg: interval,
            dgamma_source: source,
            pull,
            covered: covers(interval, true_dg),
            recompute_agrees,
        });
    }
    (binaries, components)
}

/// Pooled figures of one case.
#[derive(Debug, Clone, Serialize)]
pub struct CaseSummary {
    /// Case.
    pub case: Case,
    /// Nights run, and those whose catalog was scored.
    pub nights: usize,
    /// Nights scored.
    pub nights_scored: usize,
    /// `sofipol night` exit codes (code: nights).
    pub exit_codes: BTreeMap<String, usize>,
    /// Binaries in the truth, found in the catalogs, with both components measured, with
    /// both passing the cut.
    pub binaries: usize,
    /// Both components with finite q, u and errors.
    pub binaries_measured: usize,
    /// Both passing the cut.
    pub binaries_both_pass: usize,
    /// Binaries whose catalog Delta-gamma the recomputation reproduces: (agree, checked).
    pub recompute_check: (usize, usize),
    /// Delta-gamma pulls, both passing the cut.
    pub dgamma_pass: Moments,
    /// Coverage of the 68 % interval, both passing: (covered, counted).
    pub coverage_pass: (usize, usize),
    /// Delta-gamma pulls, every binary with finite values.
    pub dgamma_all: Moments,
    /// Coverage, every binary.
    pub coverage_all: (usize, usize),
    /// The spread of the pooled figures from night to night: the 16th and 84th percentiles
    /// of the Delta-gamma pulls' rms and of the coverage (both passing) over resamplings of
    /// the nights with replacement ([`night_bootstrap`]). A night's calibration is common to
    /// its binaries, so the nights, not the binaries, are the independent draws.
    pub dgamma_pass_rms_68: [f64; 2],
    /// Coverage's, as fractions.
    pub coverage_pass_68: [f64; 2],
    /// Delta-gamma pulls of binaries passing with a true Delta-gamma of 10-80 deg (away from
    /// the fold).
    pub dgamma_pass_unfolded: Moments,
    /// Delta-gamma pulls of binaries passing whose two stars both have a true P >= 2 %.
    pub dgamma_pass_bright: Moments,
    /// q pulls (every measured component).
    pub pull_q_all: Moments,
    /// u pulls.
    pub pull_u_all: Moments,
    /// q pulls of components passing the cut.
    pub pull_q_pass: Moments,
    /// u pulls of components passing the cut.
    pub pull_u_pass: Moments,
    /// Components measured, passing the cut.
    pub components_measured: usize,
    /// Passing the cut.
    pub components_pass: usize,
    /// Components with at least one flag.
    pub components_flagged: usize,
    /// Components per flag label.
    pub flags: BTreeMap<String, usize>,
    /// theta0 pulls over the nights with fitted angles.
    pub theta0_pull: Moments,
    /// c pulls.
    pub c_pull: Moments,
    /// p_tel pulls over the nights that measured the telescope.
    pub p_tel_pull: Moments,
    /// psi_tel pulls.
    pub psi_tel_pull: Moments,
    /// Nights whose telescope was left uncorrected.
    pub nights_telescope_uncorrected: usize,
    /// Nights flagged incomplete (c and theta0 not separated).
    pub nights_incomplete: usize,
    /// Median wall times per night, s.
    pub median_simulate_s: f64,
    /// `sofipol night`.
    pub median_night_s: f64,
}

/// Resamplings of the nights in [`night_bootstrap`].
const BOOTSTRAP_RESAMPLINGS: usize = 2000;

/// The 16th and 84th percentiles of the rms of the Delta-gamma pulls and of the coverage of
/// `pass` (binaries whose two components pass) over resamplings of its nights with
/// replacement (a fixed seed: the same figures for the same nights). NaN without binaries.
pub fn night_bootstrap(pass: &[&BinaryScore]) -> ([f64; 2], [f64; 2]) {
    let mut by_night: BTreeMap<u64, Vec<&BinaryScore>> = BTreeMap::new();
    for b in pass {
        by_night.entry(b.seed).or_default().push(b);
    }
    let nights: Vec<Vec<&BinaryScore>> = by_night.into_values().collect();
    if nights.is_empty() {
        return ([f64::NAN; 2], [f64::NAN; 2]);
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(0xB0075);
    let (mut rms, mut cov) = (Vec::new(), Vec::new());
    for _ in 0..BOOTSTRAP_RESAMPLINGS {
        let (mut sum2, mut n, mut covered, mut counted) = (0.0, 0usize, 0usize, 0usize);
        for _ in 0..nights.len() {
            for b in &nights[rng.random_range(0..nights.len())] {
                if let Some(p) = b.pull.filter(|p| p.is_finite()) {
                    sum2 += p * p;
                    n += 1;
                }
                if let Some(c) = b.covered {
                    covered += usize::from(c);
                    counted += 1;
                }
            }
        }
        if n > 0 {
            rms.push((sum2 / n as f64).sqrt());
        }
        if counted > 0 {
            cov.push(covered as f64 / counted as f64);
        }
    }
    let band = |mut v: Vec<f64>| -> [f64; 2] {
        if v.is_empty() {
            return [f64::NAN; 2];
        }
        v.sort_by(f64::total_cmp);
        let at = |q: f64| v[((q * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)];
        [at(0.16), at(0.84)]
    };
    (band(rms), band(cov))
}

/// Median of the finite values (NaN for none).
fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

fn summarize(case: Case, nights: &[NightScore], bins: &[BinaryScore], comps: &[ComponentScore]) -> CaseSummary {
    let mut exit_codes = BTreeMap::new();
    for n in nights {
        let k = n.night_exit.map_or("none".to_string(), |c| c.to_string());
        *exit_codes.entry(k).or_insert(0) += 1;
    }
    let mut flags = BTreeMap::new();
    for c in comps {
        for f in &c.flags {
            // The name before any detail ("bad_pixels: 1 of 10 ..." counts as bad_pixels).
            let name = f.split(':').next().unwrap_or(f).trim().to_string();
            *flags.entry(name).or_insert(0) += 1;
        }
    }
    let pass: Vec<&BinaryScore> = bins.iter().filter(|b| b.passes_cut == [true, true]).collect();
    let all: Vec<&BinaryScore> = bins.iter().filter(|b| b.pull.is_some()).collect();
    let pulls = |v: &[&BinaryScore]| Moments::of(v.iter().filter_map(|b| b.pull));
    let cp: Vec<&ComponentScore> = comps.iter().filter(|c| c.passes_cut).collect();
    let (dgamma_pass_rms_68, coverage_pass_68) = night_bootstrap(&pass);
    CaseSummary {
        case,
        nights: nights.len(),
        nights_scored: nights.iter().filter(|n| n.error.is_none()).count(),
        exit_codes,
        binaries: bins.len(),
        binaries_measured: bins.iter().filter(|b| b.both_measured).count(),
        binaries_both_pass: pass.len(),
        recompute_check: coverage(bins.iter().map(|b| b.recompute_agrees)),
        dgamma_pass: pulls(&pass),
        coverage_pass: coverage(pass.iter().map(|b| b.covered)),
        dgamma_all: pulls(&all),
        coverage_all: coverage(all.iter().map(|b| b.covered)),
        dgamma_pass_rms_68,
        coverage_pass_68,
        dgamma_pass_unfolded: Moments::of(
            pass.iter()
                .filter(|b| (10.0..=80.0).contains(&b.true_dgamma_deg))
                .filter_map(|b| b.pull),
        ),
        dgamma_pass_bright: Moments::of(
            pass.iter()
                .filter(|b| b.p_true.iter().all(|&p| p >= 0.02))
                .filter_map(|b| b.pull),
        ),
        pull_q_all: Moments::of(comps.iter().map(|c| c.pull_q)),
        pull_u_all: Moments::of(comps.iter().map(|c| c.pull_u)),
        pull_q_pass: Moments::of(cp.iter().map(|c| c.pull_q)),
        pull_u_pass: Moments::of(cp.iter().map(|c| c.pull_u)),
        components_measured: comps.len(),
        components_pass: cp.len(),
        components_flagged: comps.iter().filter(|c| !c.flags.is_empty()).count(),
        flags,
        theta0_pull: Moments::of(nights.iter().filter_map(|n| n.theta0_pull)),
        c_pull: Moments::of(nights.iter().filter_map(|n| n.c_pull)),
        p_tel_pull: Moments::of(nights.iter().filter_map(|n| n.p_tel_pull)),
        psi_tel_pull: Moments::of(nights.iter().filter_map(|n| n.psi_tel_pull)),
        nights_telescope_uncorrected: nights.iter().filter(|n| n.telescope_uncorrected.is_some()).count(),
        nights_incomplete: nights.iter().filter(|n| n.incomplete.is_some()).count(),
        median_simulate_s: median(nights.iter().map(|n| n.simulate_s).collect()),
        median_night_s: median(nights.iter().map(|n| n.night_s).collect()),
    }
}

/// `a/b` with the percentage.
fn frac((k, n): (usize, usize)) -> String {
    if n == 0 {
        "-".into()
    } else {
        format!("{k}/{n} = {:.0} %", 100.0 * k as f64 / n as f64)
    }
}

fn moments(m: &Moments) -> String {
    if m.n == 0 {
        "-".into()
    } else {
        format!(
            "rms {:.3}  mean {:+.3}  median |x| {:.3}  (n {})",
            m.rms, m.mean, m.median_abs, m.n
        )
    }
}

fn opt(v: Option<[f64; 2]>, digits: usize) -> String {
    v.map_or("-".into(), |[x, s]| format!("{x:.digits$} +- {s:.digits$}"))
}

fn pull(v: Option<f64>) -> String {
    v.map_or("-".into(), |p| format!("{p:+.2}"))
}

/// The table of one case: per night the calibration, then the pooled figures.
fn print_case(s: &CaseSummary, nights: &[NightScore]) {
    println!("\n== case {} ({} nights) ==", s.case.name(), s.nights);
    println!(
        "  {:>4} {:>4} {:>6} {:>6}  {:>17} {:>6}  {:>16} {:>6}  {:>17} {:>6} {:>6}  {:>14} {:>6}  standards / telescope",
        "seed",
        "exit",
        "sim s",
        "night",
        "c (true)",
        "pull",
        "theta0 deg",
        "pull",
        "p_tel %",
        "pull",
        "true",
        "psi_tel deg",
        "pull"
    );
    for n in nights {
        let note = n
            .error
            .clone()
            .or_else(|| n.telescope_uncorrected.as_ref().map(|w| format!("uncorrected: {w}")))
            .or_else(|| n.incomplete.as_ref().map(|w| format!("incomplete: {w}")))
            .unwrap_or_default();
        let note: String = note.chars().take(90).collect();
        println!(
            "  {:>4} {:>4} {:>6.1} {:>6.1}  {:>17} {:>6}  {:>16} {:>6}  {:>17} {:>6} {:>6.3}  {:>14} {:>6}  eta span {:.1} deg; {}",
            n.seed,
            n.night_exit.map_or("-".into(), |c| c.to_string()),
            n.simulate_s,
            n.night_s,
            format!(
                "{} ({:.5})",
                opt(n.c, 5).split(" +-").next().unwrap_or("-"),
                n.c_true.unwrap_or(f64::NAN)
            ),
            pull(n.c_pull),
            opt(n.theta0_deg, 2),
            pull(n.theta0_pull),
            opt(n.p_tel.map(|[p, s]| [100.0 * p, 100.0 * s]), 3),
            pull(n.p_tel_pull),
            100.0 * n.draws.p_tel,
            opt(n.psi_tel_deg, 1),
            pull(n.psi_tel_pull),
            n.standards_eta_span_deg,
            note
        );
    }
    println!(
        "  exit codes {:?}; binaries {} (both measured {}, both passing the cut {})",
        s.exit_codes, s.binaries, s.binaries_measured, s.binaries_both_pass
    );
    println!("  Delta-gamma pulls, both pass the cut:    {}", moments(&s.dgamma_pass));
    println!(
        "    night to night (nights resampled, 68 %): rms {:.2}-{:.2}, coverage {:.0}-{:.0} %",
        s.dgamma_pass_rms_68[0],
        s.dgamma_pass_rms_68[1],
        100.0 * s.coverage_pass_68[0],
        100.0 * s.coverage_pass_68[1]
    );
    println!(
        "    of which true Delta-gamma 10-80 deg:   {}",
        moments(&s.dgamma_pass_unfolded)
    );
    println!(
        "    of which both true P >= 2 %:           {}",
        moments(&s.dgamma_pass_bright)
    );
    println!(
        "  Delta-gamma pulls, all finite:           {}  (the catalog's cut lifted; check: \
         the recomputation reproduces {} catalog values)",
        moments(&s.dgamma_all),
        frac(s.recompute_check)
    );
    println!(
        "  68 % interval coverage: both pass {}; all finite {}",
        frac(s.coverage_pass),
        frac(s.coverage_all)
    );
    println!(
        "  q pulls: all measured {}; passing {}",
        moments(&s.pull_q_all),
        moments(&s.pull_q_pass)
    );
    println!(
        "  u pulls: all measured {}; passing {}",
        moments(&s.pull_u_all),
        moments(&s.pull_u_pass)
    );
    println!(
        "  theta0 pulls {}; c pulls {}",
        moments(&s.theta0_pull),
        moments(&s.c_pull)
    );
    println!(
        "  p_tel pulls {}; psi_tel pulls {} (telescope uncorrected on {} of {} nights, incomplete on {})",
        moments(&s.p_tel_pull),
        moments(&s.psi_tel_pull),
        s.nights_telescope_uncorrected,
        s.nights,
        s.nights_incomplete
    );
    println!(
        "  components: {} measured, {} pass the cut, {} flagged; flags: {}",
        s.components_measured,
        s.components_pass,
        s.components_flagged,
        s.flags
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    println!(
        "  median time per night: simulate {:.1} s, night {:.1} s",
        s.median_simulate_s, s.median_night_s
    );
}

/// The JSON file of a run.
#[derive(Serialize)]
struct Report<'a> {
    command: String,
    software: String,
    seeds: Vec<u64>,
    binaries_per_night: u64,
    summaries: Vec<CaseSummary>,
    nights: &'a [NightScore],
    binaries: &'a [BinaryScore],
    components: &'a [ComponentScore],
}

/// Run `sofipol bench calibration` (from the `sofipol` binary: its children are
/// [`std::env::current_exe`]).
pub fn run(args: CalibrationArgs) -> anyhow::Result<()> {
    let exe = std::env::current_exe().context("locating the sofipol executable")?;
    let cases = if args.case.is_empty() {
        vec![Case::Clustered, Case::PolarizedOnly]
    } else {
        let mut c: Vec<Case> = Vec::new();
        for &k in &args.case {
            if !c.contains(&k) {
                c.push(k);
            }
        }
        c
    };
    let seeds: Vec<u64> = (args.first_seed..args.first_seed + args.seeds).collect();
    std::fs::create_dir_all(&args.output).with_context(|| format!("creating {}", args.output.display()))?;
    println!(
        "sofipol bench calibration: cases [{}], seeds {}-{}, {} binaries a night, into {}",
        cases.iter().map(|c| c.name()).collect::<Vec<_>>().join(", "),
        seeds[0],
        seeds[seeds.len() - 1],
        args.binaries,
        args.output.display()
    );
    let t0 = Instant::now();
    let (mut nights, mut bins, mut comps, mut summaries) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for &case in &cases {
        let start = nights.len();
        for &seed in &seeds {
            let dir = args.output.join(case.name()).join(format!("seed{seed}"));
            let r = run_night(&exe, case, seed, &args, &dir)?;
            eprintln!(
                "  {} seed {seed}: simulate {:.1} s, night {:.1} s (exit {:?}), {} binaries scored{}",
                case.name(),
                r.night.simulate_s,
                r.night.night_s,
                r.night.night_exit,
                r.binaries.len(),
                r.night.error.as_ref().map(|e| format!(": {e}")).unwrap_or_default()
            );
            nights.push(r.night);
            bins.extend(r.binaries);
            comps.extend(r.components);
        }
        let ns = &nights[start..];
        let bs: Vec<BinaryScore> = bins.iter().filter(|b: &&BinaryScore| b.case == case).cloned().collect();
        let cs: Vec<ComponentScore> = comps
            .iter()
            .filter(|c: &&ComponentScore| c.case == case)
            .cloned()
            .collect();
        let s = summarize(case, ns, &bs, &cs);
        print_case(&s, ns);
        summaries.push(s);
    }
    let report = Report {
        command: sofipol_pipeline::build_info::command_line_string(),
        software: format!(
            "sofipol {} ({})",
            env!("CARGO_PKG_VERSION"),
            sofipol_pipeline::build_info::commit()
        ),
        seeds,
        binaries_per_night: args.binaries,
        summaries,
        nights: &nights,
        binaries: &bins,
        components: &comps,
    };
    let path = args.output.join("calibration_bench.json");
    sofipol_pipeline::io::write_atomic(&path, serde_json::to_string_pretty(&report)?.as_bytes())?;
    println!(
        "\nevery pull: {}; total {:.0} s",
        path.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angle_differences_wrap_into_minus_90_to_90() {
        for (d, w) in [
            (0.0, 0.0),
            (89.0, 89.0),
            (90.0, -90.0),
            (-90.0, -90.0),
            (91.0, -89.0),
            (179.0, -1.0),
            (-179.0, 1.0),
            (270.0, -90.0),
            (-300.0, 60.0),
        ] {
            assert!((wrap_deg(d) - w).abs() < 1e-12, "{d} -> {} (want {w})", wrap_deg(d));
        }
        // Folded Delta-gammas near the two ends of [0, 90].
        assert!((wrap_deg(fold_delta_gamma(10.0, 100.0) - 88.0) - 2.0).abs() < 1e-12);
        assert!((wrap_deg(fold_delta_gamma(170.0, 5.0) - 3.0) - 12.0).abs() < 1e-12);
    }

    #[test]
    fn coverage_counts_truths_inside_the_closed_interval() {
        assert_eq!(covers(Some([10.0, 20.0]), 10.0), Some(true));
        assert_eq!(covers(Some([10.0, 20.0]), 20.0), Some(true));
        assert_eq!(covers(Some([10.0, 20.0]), 20.5), Some(false));
        assert_eq!(covers(Some([10.0, 20.0]), 9.9), Some(false));
        assert_eq!(covers(None, 15.0), None);
        assert_eq!(covers(Some([f64::NAN, 20.0]), 15.0), None);
        let c = coverage([Some(true), Some(false), None, Some(true), Some(true)]);
        assert_eq!(c, (3, 4));
        assert_eq!(coverage(Vec::<Option<bool>>::new()), (0, 0));
    }

    #[test]
    fn axial_span_takes_the_shorter_way_round() {
        assert!((axial_span_deg([26.0, 41.0, 30.0]) - 15.0).abs() < 1e-12);
        // -170 and 175 are 15 deg apart mod 180 (10 and 175).
        assert!((axial_span_deg([-170.0, 175.0]) - 15.0).abs() < 1e-12);
        assert!(axial_span_deg(std::iter::empty()).is_nan());
    }

    impl BinaryScore {
        fn for_test(seed: u64) -> BinaryScore {
            BinaryScore {
                case: Case::Clustered,
                seed,
                object: String::new(),
                status: "ok".into(),
                separation_arcsec: 2.0,
                flux_ratio: 0.5,
                p_true: [0.02; 2],
                swapped: false,
                passes_cut: [true; 2],
                both_measured: true,
                true_dgamma_deg: 30.0,
                dgamma_deg: None,
                sigma_dgamma_deg: None,
                dgamma_interval_deg: None,
                dgamma_source: "catalog",
                pull: None,
                covered: None,
                recompute_agrees: None,
            }
        }
    }

    /// The night-resampled band holds the pooled value, and narrows as nights are added.
    #[test]
    fn night_bootstrap_brackets_the_pooled_figures() {
        let make = |nights: u64| -> Vec<BinaryScore> {
            let mut rng = rand::rngs::StdRng::seed_from_u64(nights);
            (0..nights)
                .flat_map(|seed| {
                    // A night-common error: every binary of a night shares a shift.
                    let shift: f64 = rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng);
                    (0..10)
                        .map(|_| {
                            let z: f64 = rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng);
                            let pull = 0.6 * z + 0.8 * shift;
                            let mut b = BinaryScore::for_test(seed);
                            b.pull = Some(pull);
                            b.covered = Some(pull.abs() <= 1.0);
                            b
                        })
                        .collect::<Vec<_>>()
                })
                .collect()
        };
        let width = |n: u64| {
            let bins = make(n);
            let refs: Vec<&BinaryScore> = bins.iter().collect();
            let (rms, cov) = night_bootstrap(&refs);
            let pooled = Moments::of(refs.iter().filter_map(|b| b.pull)).rms;
            assert!(rms[0] <= pooled && pooled <= rms[1], "{rms:?} {pooled}");
            assert!(cov[0] < cov[1]);
            rms[1] - rms[0]
        };
        let (w16, w256) = (width(16), width(256));
        assert!(w256 < 0.5 * w16, "{w16} {w256}");
    }

    #[test]
    fn moments_leave_out_non_finite_values() {
        let m = Moments::of([3.0, -3.0, f64::NAN, f64::INFINITY]);
        assert_eq!(m.n, 2);
        assert!((m.rms - 3.0).abs() < 1e-12 && m.mean.abs() < 1e-12 && m.median_abs == 3.0);
        assert_eq!(median(vec![4.0, 1.0, f64::NAN, 2.0, 3.0]), 2.5);
    }

    /// The drawn term follows the prior: over many draws the mean and spread along and across
    /// the prior's direction are its mean and widths.
    #[test]
    fn the_telescope_is_drawn_from_the_prior() {
        let prior = ks_prior();
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let n = 20000;
        let draws: Vec<(f64, f64)> = (0..n).map(|_| draw_telescope(&prior, &mut rng)).collect();
        let along: Vec<f64> = draws.iter().map(|(p, s)| p * (2.0 * s.to_radians()).cos()).collect();
        let across: Vec<f64> = draws.iter().map(|(p, s)| p * (2.0 * s.to_radians()).sin()).collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let sd = |v: &[f64]| {
            let m = mean(v);
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
        };
        let width_across = prior.p_tel * 2.0 * prior.sigma_psi_tel_deg.to_radians();
        assert!((mean(&along) - prior.p_tel).abs() < 4.0 * prior.sigma_p_tel / (n as f64).sqrt());
        assert!(mean(&across).abs() < 4.0 * width_across / (n as f64).sqrt());
        assert!((sd(&along) / prior.sigma_p_tel - 1.0).abs() < 0.03);
        assert!((sd(&across) / width_across - 1.0).abs() < 0.03);
    }

    #[test]
    fn every_night_scene_is_valid_and_reproducible() {
        for case in [Case::Clustered, Case::PolarizedOnly] {
            for seed in 1..4 {
                let (a, da) = scene_text(case, seed, 10).unwrap();
                let (b, _) = scene_text(case, seed, 10).unwrap();
                assert_eq!(a, b);
                let prior = ks_prior();
                assert!((da.p_tel - prior.p_tel).abs() < 5.0 * prior.sigma_p_tel, "{}", da.p_tel);
                assert!(
                    da.psi_tel_deg.abs() < 5.0 * prior.sigma_psi_tel_deg,
                    "{}",
                    da.psi_tel_deg
                );
                // Each standard's truth is drawn, not the table's.
                for s in &da.standards {
                    if s.table_p > 0.005 {
                        assert!(s.p != s.table_p && s.gamma_deg != s.table_gamma_deg, "{s:?}");
                    }
                }
            }
        }
    }
}
