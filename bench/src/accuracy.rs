//! Accuracy of the reduction on simulated nights: pulls `(q - q_true)/sigma_q` by
//! separation bin, and what it costs in time. Used by `sofipol bench accuracy` and by the
//! acceptance tests.
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;
use serde::Serialize;
use sofipol_calib::Profile;

use sofipol_pipeline::reduce::run::{reduce_loaded, LoadedOrientation};
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sequence::Sequence;
use sofipol_pipeline::sim::loaded_from_sim;
use sofipol_pipeline::sim::{Scene, Simulator};

/// What to simulate.
#[derive(Debug, Clone)]
pub struct AccuracyConfig {
    /// Separation bin edges, arcsec.
    pub bins_arcsec: Vec<f64>,
    /// Targets per bin.
    pub targets_per_bin: usize,
    /// Seed.
    pub seed: u64,
    /// Seeing FWHM, arcsec.
    pub fwhm_arcsec: f64,
    /// Per-frame FWHM spread: each frame's FWHM is multiplied by U(1 - s, 1 + s) (on top
    /// of the 8 % log-normal seeing change).
    pub fwhm_spread_frac: f64,
    /// Per-frame Moffat beta range (uniform), drawn independently of the FWHM; None: 3.
    pub beta_range: Option<[f64; 2]>,
    /// Effects (scene names).
    pub effects: Vec<String>,
    /// Instrument orientations (POSANG), degrees.
    pub orientations_deg: Vec<f64>,
    /// Dithers per orientation.
    pub dithers: usize,
    /// Extra scene sections (TOML), e.g. `[flat_field]` settings.
    pub extra_scene: String,
    /// Flat field applied to the raw frames before the reduction.
    pub flat: FlatMode,
    /// Calibrate each bin's night as `night` does: its standards (scene
    /// `[[standard]]`s, after the binaries) reduced as single stars, the offset and angle
    /// zero-point measured against the built-in table, every component re-solved with the
    /// automatic Stokes method (the ratio method for balanced angles).
    pub calibrate: bool,
    /// Score each binary against its intrinsic polarization after subtracting its measured
    /// foreground (the scene then has a foreground field and field stars: see
    /// [`AccuracyConfig::with_foreground`]); a binary without a foreground estimate is scored
    /// with the foreground left in.
    pub foreground: bool,
}

impl AccuracyConfig {
    /// `cfg` with a pixel response non-uniformity of `rms` (the `flat_field` effect, no
    /// vignetting; none when 0) and the flat `mode` (Dome adds the `dome_flats` effect).
    pub fn with_flat_field(mut cfg: AccuracyConfig, rms: f64, mode: FlatMode) -> AccuracyConfig {
        if rms > 0.0 {
            cfg.effects.push("flat_field".into());
            cfg.extra_scene += &format!("[flat_field]\npixel_rms = {rms}\nvignetting = 0.0\n");
        }
        if mode == FlatMode::Dome {
            cfg.effects.push("dome_flats".into());
            cfg.extra_scene += "[dome_flats]\nframes_on = 5\nframes_off = 5\n";
        }
        cfg.flat = mode;
        cfg
    }

    /// `cfg` with the instrument (beam ratio k = T_e/T_o = 0.97, instrumental
    /// polarization 0.3 % along the analyzer, angle zero-point 3 deg) and calibration on; with
    /// `standards`, each bin's night also holds two unpolarized standards of the built-in
    /// table (HD 64299, HD 98161) and two polarized ones with K-band values known to 0.02 %
    /// and 0.1 deg ([`ACCURACY_STANDARDS`], as a `--standards` file of measured values gives
    /// them; the built-in polarized entries are Serkowski extrapolations with 2 deg errors,
    /// which would dominate sigma_q of strongly polarized stars).
    pub fn with_instrument(mut cfg: AccuracyConfig, standards: bool) -> AccuracyConfig {
        for e in ["throughput", "instrumental_polarization", "analyzer_angle"] {
            cfg.effects.push(e.into());
        }
        cfg.extra_scene += "[throughput]\nt_o = 1.0\nt_e = 0.97\n[instrumental_polarization]\np = 0.003\nangle_deg = 0.0\n[analyzer_angle]\nzero_point_deg = 3.0\nparity = 1\n";
        if standards {
            let table = standards_table();
            for name in ["HD 64299", "HD 98161", "Pol A", "Pol B"] {
                let e = table.find(name, "Ks").expect("standard in the table");
                cfg.extra_scene += &format!(
                    "[[standard]]\nname = \"{name}\"\nflux = 150000.0\np = {}\ngamma_deg = {}\n",
                    e.p, e.gamma_deg
                );
            }
        }
        cfg.calibrate = true;
        cfg
    }

    /// `cfg` calibrated as [`AccuracyConfig::with_instrument`] (with standards: field stars
    /// are used for the foreground only once calibrated) and seen through an interstellar
    /// foreground that varies across the sky (mean 2 % at 60 deg, rms 0.4 % in q and in u,
    /// coherence 90"), with the field stars of a K-band luminosity function (1 star per
    /// arcmin^2 brighter than K = 14, 0.3 dex per magnitude, K 8-18, 10 % of them polarized
    /// 2-10 % of their own); each binary is scored against its intrinsic polarization.
    pub fn with_foreground(cfg: AccuracyConfig) -> AccuracyConfig {
        let mut cfg = AccuracyConfig::with_instrument(cfg, true);
        cfg.effects.push("foreground_field".into());
        cfg.extra_scene += "[foreground_field]\np = 0.02\nangle_deg = 60.0\nrms = 0.004\ncoherence_arcsec = 90.0\n\
            [field_population]\ndensity_per_arcmin2 = 1.0\nk_ref_mag = 14.0\nslope_dex_per_mag = 0.3\nk_min_mag = 8.0\n\
            k_max_mag = 18.0\npolarized_fraction = 0.1\np_polarized = [0.02, 0.10]\nexclude_arcsec = 3.0\n";
        cfg.foreground = true;
        cfg
    }
}

/// Polarized standards of the harness's nights, with measured-quality K-band values (added
/// to the built-in table when a bin is calibrated).
pub const ACCURACY_STANDARDS: &str = r#"
[[standard]]
name = "Pol A"
filter = "Ks"
p = 0.025
sigma_p = 0.0002
gamma_deg = 40.0
sigma_gamma_deg = 0.1
band = "Ks (simulated)"
reference = "sofipol accuracy harness"
[[standard]]
name = "Pol B"
filter = "Ks"
p = 0.02
sigma_p = 0.0002
gamma_deg = 100.0
sigma_gamma_deg = 0.1
band = "Ks (simulated)"
reference = "sofipol accuracy harness"
"#;

/// The built-in standards table plus [`ACCURACY_STANDARDS`].
pub fn standards_table() -> sofipol_pipeline::standards::StandardsTable {
    let mut t = sofipol_pipeline::standards::StandardsTable::builtin();
    t.merge_toml(ACCURACY_STANDARDS, "accuracy harness")
        .expect("valid table");
    t
}

/// Which flat the harness divides the raw frames by (each separation bin is one night).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FlatMode {
    /// No flat.
    None,
    /// Superflat from the sky of (up to 40) science frames of the bin's night, picked
    /// cycling through the dither positions.
    Superflat,
    /// Dome flats of the night (the scene must list `dome_flats`), one per rotator angle.
    Dome,
}

impl Default for AccuracyConfig {
    fn default() -> Self {
        AccuracyConfig {
            bins_arcsec: vec![0.5, 0.8, 1.2, 1.6, 2.5, 4.0, 5.3],
            targets_per_bin: 12,
            seed: 7,
            fwhm_arcsec: 0.8,
            fwhm_spread_frac: 0.2,
            beta_range: Some([2.5, 4.0]),
            effects: [
                "psf",
                "sky",
                "strips",
                "photon_noise",
                "read_noise",
                "bad_pixels",
                "transparency",
                "pointing_error",
                "cosmic_rays",
            ]
            .iter()
            .map(|s| s.to_string())
            .collect(),
            extra_scene: String::new(),
            flat: FlatMode::None,
            calibrate: false,
            foreground: false,
            orientations_deg: vec![0.0, 45.0],
            dithers: 5,
        }
    }
}

/// Pull statistics of one separation bin.
#[derive(Debug, Clone, Serialize)]
pub struct BinReport {
    /// Bin edges, arcsec.
    pub sep_arcsec: (f64, f64),
    /// Bin edges in units of the FWHM.
    pub sep_fwhm: (f64, f64),
    /// Pulls used (q and u of both components).
    pub n_pulls: usize,
    /// rms of (q - q_true)/sigma_q and (u - u_true)/sigma_u together.
    pub rms_pull: f64,
    /// Mean pull.
    pub mean_pull: f64,
    /// Median sigma_q, fraction.
    pub median_sigma: f64,
    /// rms of the true errors q - q_true and u - u_true (both components), fraction.
    pub rms_error: f64,
    /// Mean of the true errors (the bias), fraction.
    pub mean_error: f64,
    /// Components not measured (companion not found, failed...).
    pub missing: usize,
    /// Median wall time per target (simulation excluded), s.
    pub median_reduce_s: f64,
    /// Targets with a pull beyond 5: what went wrong, in words.
    pub outliers: Vec<String>,
    /// Pulls of Delta-gamma, `wrap(dgamma - dgamma_true) / sigma_delta_gamma_deg`, with
    /// the unfolded signed differences `dgamma = wrap(gamma_A - gamma_B)` (what the error
    /// describes; folding would bias the pull near 0 and 90 deg): one per binary with a
    /// Delta-gamma.
    pub delta_gamma_pulls: Vec<f64>,
}

/// The scene of separation bin `bin` (edges `lo`, `hi` arcsec) and its (sep, flux A, flux B, 0) draws.
pub fn scene_for(cfg: &AccuracyConfig, lo: f64, hi: f64, bin: usize) -> (Scene, Vec<[f64; 4]>) {
    let mut r = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(cfg.seed ^ (bin as u64 * 0x9E37));
    let mut text = format!(
        "name = \"acc{bin}\"\nseed = {}\neffects = [{}]\n{}\n[observation]\n{}orientations_deg = [{}]\ndithers = {}\n[psf]\nkind = \"moffat\"\nfwhm_arcsec = {}\nbeta = 3.0\nseeing_rms_frac = 0.08\nfwhm_spread_frac = {}\n{}",
        cfg.seed + bin as u64,
        cfg.effects.iter().map(|e| format!("\"{e}\"")).collect::<Vec<_>>().join(","),
        cfg.extra_scene,
        // The field population turns K magnitudes into fluxes (K = 10 saturates at 0.8").
        if cfg.foreground { "zero_point_mag = 22.3\n" } else { "" },
        cfg.orientations_deg.iter().map(|a| format!("{a:?}")).collect::<Vec<_>>().join(","),
        cfg.dithers,
        cfg.fwhm_arcsec,
        cfg.fwhm_spread_frac,
        cfg.beta_range
            .map(|[lo, hi]| format!("beta_range = [{lo}, {hi}]\n"))
            .unwrap_or_default()
    );
    let mut truths = Vec::new();
    for t in 0..cfg.targets_per_bin {
        let sep = lo + (hi - lo) * r.random::<f64>();
        let fa = 60000.0 + 140000.0 * r.random::<f64>();
        let fb = fa * (0.25 + 0.75 * r.random::<f64>());
        let (pa_, pb) = (0.01 + 0.07 * r.random::<f64>(), 0.01 + 0.07 * r.random::<f64>());
        let (ga, gb) = (180.0 * r.random::<f64>(), 180.0 * r.random::<f64>());
        text += &format!(
            "[[binary]]\nname = \"S{bin}_{t}\"\nseparation_arcsec = {sep}\npa_deg = {}\nflux_a = {fa}\nflux_b = {fb}\np_a = {pa_}\ngamma_a_deg = {ga}\np_b = {pb}\ngamma_b_deg = {gb}\n",
            360.0 * r.random::<f64>()
        );
        truths.push([sep, fa, fb, 0.0]);
    }
    (
        Scene::from_toml(&text, "accuracy scene").expect("valid generated scene"),
        truths,
    )
}

/// One reduced target: pulls and time.
struct One {
    note: Option<String>,
    pulls: Vec<f64>,
    errors: Vec<f64>,
    sigmas: Vec<f64>,
    delta_gamma_pull: Option<f64>,
    missing: usize,
    reduce_s: f64,
}

/// Simulate and reduce, bin by bin.
pub fn run(cfg: &AccuracyConfig, params: &TargetParams) -> Vec<BinReport> {
    run_scored(cfg, params)
        .iter()
        .map(|(w, ones)| bin_report(w, cfg.fwhm_arcsec, ones))
        .collect()
}

/// [`run`] for the seeds `seeds` (each a night of its own: its own draws, and its own
/// calibration when `cfg.calibrate`): each seed's bins, and the bins pooled over the seeds
/// (every pull of every seed; the median time over all targets).
pub fn run_seeds(cfg: &AccuracyConfig, params: &TargetParams, seeds: &[u64]) -> (Vec<Vec<BinReport>>, Vec<BinReport>) {
    let fwhm = cfg.fwhm_arcsec;
    let mut per_seed = Vec::new();
    let mut pooled: Vec<(Vec<f64>, Vec<One>)> = Vec::new();
    for &seed in seeds {
        let c = AccuracyConfig { seed, ..cfg.clone() };
        let scored = run_scored(&c, params);
        per_seed.push(scored.iter().map(|(w, ones)| bin_report(w, fwhm, ones)).collect());
        for (i, (w, ones)) in scored.into_iter().enumerate() {
            match pooled.get_mut(i) {
                Some(p) => p.1.extend(ones),
                None => pooled.push((w, ones)),
            }
        }
    }
    let pooled = pooled.iter().map(|(w, ones)| bin_report(w, fwhm, ones)).collect();
    (per_seed, pooled)
}

/// Simulate, reduce and score, bin by bin: each bin's edges and its targets' scores.
fn run_scored(cfg: &AccuracyConfig, params: &TargetParams) -> Vec<(Vec<f64>, Vec<One>)> {
    // The instrument reduced is the one simulated: a telescope that polarizes only when the
    // scene simulates it (else its expected size would be carried in every error).
    let mut profile = Profile::sofi();
    profile.telescope.polarizes = cfg.effects.iter().any(|e| e == "telescope_polarization");
    cfg.bins_arcsec
        .windows(2)
        .enumerate()
        .map(|(bin, w)| {
            let (scene, _) = scene_for(cfg, w[0], w[1], bin);
            let sim = Simulator::new(scene, profile.clone()).expect("valid");
            let n = sim.frames_per_target();
            let flats = simulated_flats(cfg.flat, &sim, &profile);
            let load = |t: usize| {
                let mut frames: Vec<_> = (0..n).map(|k| sim.frame(t, k)).collect();
                if let Some(set) = &flats {
                    for f in &mut frames {
                        if let Some(flat) = set.for_frame(f.truth.posang_deg, &sim.scene().observation.filter) {
                            f.frame = sofipol_calib::flat::apply_flat(&f.frame, flat, &profile).expect("same shape");
                        }
                    }
                }
                loaded_from_sim(frames, &profile)
            };
            let mut reduced: Vec<(sofipol_pipeline::catalog::Target, f64)> = (0..cfg.targets_per_bin)
                .into_par_iter()
                .map(|t| {
                    let (seq, orients) = load(t);
                    let t0 = std::time::Instant::now();
                    let out = reduce_loaded(&seq, orients, &profile, params, None, None, false);
                    (out.target, t0.elapsed().as_secs_f64())
                })
                .collect();
            if cfg.calibrate {
                calibrate_bin(cfg, params, &profile, &sim, &load, &mut reduced);
            }
            let truth = sim.truth(&[]);
            let ones: Vec<One> = reduced
                .into_iter()
                .enumerate()
                .map(|(t, (target, reduce_s))| score_target(&target, &truth.targets[t], reduce_s, cfg.foreground))
                .collect();
            (w.to_vec(), ones)
        })
        .collect()
}

/// Reduce the bin's standards and calibrate its reduced targets in place (the `night` path).
fn calibrate_bin<L>(
    cfg: &AccuracyConfig,
    params: &TargetParams,
    profile: &Profile,
    sim: &Simulator,
    load: &L,
    reduced: &mut [(sofipol_pipeline::catalog::Target, f64)],
) where
    L: Fn(usize) -> (Sequence, Vec<LoadedOrientation>) + Sync,
{
    use sofipol_pipeline::calibration::{calibrate_catalog, standard_params, CalibrationContext, CalibrationSource};
    let sp = standard_params(params);
    let stds: Vec<sofipol_pipeline::catalog::Target> = (cfg.targets_per_bin..sim.n_sequences())
        .into_par_iter()
        .map(|t| {
            let (seq, orients) = load(t);
            reduce_loaded(&seq, orients, profile, &sp, None, None, false).target
        })
        .collect();
    let mut cat = sofipol_pipeline::catalog::Catalog {
        targets: reduced.iter().map(|r| r.0.clone()).collect(),
        ..Default::default()
    };
    calibrate_catalog(
        &mut cat,
        stds,
        CalibrationSource::Night,
        &CalibrationContext {
            table: &standards_table(),
            profile,
            params: &params.calibration,
            debias: params.measure.debias,
            cut_snr: params.measure.cut_snr,
        },
    );
    for (r, t) in reduced.iter_mut().zip(cat.targets) {
        r.0 = t;
    }
}

/// Compare one reduced target with its truth: pulls, errors, and a note when it is an outlier.
fn score_target(
    target: &sofipol_pipeline::catalog::Target,
    tt: &sofipol_pipeline::sim::TargetTruth,
    reduce_s: f64,
    foreground: bool,
) -> One {
    let mut one = One {
        note: None,
        pulls: vec![],
        errors: vec![],
        sigmas: vec![],
        delta_gamma_pull: None,
        missing: 0,
        reduce_s,
    };
    // The reduction calls the brighter star A as measured; near-equal pairs may
    // be labelled the other way round from the scene: match by position angle.
    let found_pa = target.pa_deg;
    let swapped = found_pa.is_some_and(|pa| {
        let d = (pa - tt.pa_deg).rem_euclid(360.0);
        d > 90.0 && d < 270.0
    });
    let mut truth_comps = tt.components.clone();
    if swapped {
        truth_comps.swap(0, 1);
    }
    // With `foreground`, what is scored is the star's own polarization: the measured
    // foreground (when estimated) subtracted, its variance added, against the intrinsic truth.
    // Field stars measured but too few usable: no estimate to score (the components count
    // as missing). Without field stars the foreground stays in, and is scored so.
    let fg = target.foreground.as_ref().filter(|_| foreground);
    if foreground && fg.is_none() && target.field_stars.is_some() {
        one.missing = truth_comps.len();
        return one;
    }
    let (fq, fu, fvq, fvu) = fg.map_or((0.0, 0.0, 0.0, 0.0), |f| {
        (f.q, f.u, f.sigma_q.powi(2), f.sigma_u.powi(2))
    });
    for (i, tc) in truth_comps.iter().enumerate() {
        let (tq, tu) = if foreground {
            (tc.intrinsic.q, tc.intrinsic.u)
        } else {
            (tc.q, tc.u)
        };
        match target.components.get(i) {
            Some(c) if c.q.is_finite() && c.sigma_q > 0.0 => {
                let (q, u) = (c.q - fq, c.u - fu);
                let (sq, su) = ((c.sigma_q.powi(2) + fvq).sqrt(), (c.sigma_u.powi(2) + fvu).sqrt());
                one.pulls.push((q - tq) / sq);
                one.pulls.push((u - tu) / su);
                one.errors.push(q - tq);
                one.errors.push(u - tu);
                one.sigmas.push(sq);
            }
            _ => one.missing += 1,
        }
    }
    let wrap = |d: f64| (d + 90.0).rem_euclid(180.0) - 90.0;
    let angle = |q: f64, u: f64| 0.5 * u.atan2(q).to_degrees();
    if let (false, Some(s), [a, b], [ta, tb]) = (
        foreground,
        target.sigma_delta_gamma_deg,
        target.components.as_slice(),
        truth_comps.as_slice(),
    ) {
        let d = wrap(a.gamma_deg - b.gamma_deg);
        let d_true = wrap(angle(ta.q, ta.u) - angle(tb.q, tb.u));
        one.delta_gamma_pull = Some(wrap(d - d_true) / s);
    }
    if let (true, Some(f), [a, b], [ta, tb]) = (foreground, fg, target.components.as_slice(), truth_comps.as_slice()) {
        // Delta-gamma of the intrinsic angles against its error with the foreground's
        // covariance (common to both stars) propagated: the catalog's corrected pair.
        if let Some(s) = target.sigma_delta_gamma_fg_corrected_deg {
            let d = wrap(angle(a.q - f.q, a.u - f.u) - angle(b.q - f.q, b.u - f.u));
            let d_true = wrap(angle(ta.intrinsic.q, ta.intrinsic.u) - angle(tb.intrinsic.q, tb.intrinsic.u));
            one.delta_gamma_pull = Some(wrap(d - d_true) / s);
        }
    }
    if one.pulls.iter().any(|p| p.abs() > 5.0) || one.missing > 0 {
        let comps: Vec<String> = target
            .components
            .iter()
            .zip(&truth_comps)
            .map(|(c, tc)| {
                format!(
                    "{}: q {:.4}/{:.4} u {:.4}/{:.4} sig {:.4} flux {:.0}/{:.0} [{}]",
                    c.name,
                    c.q,
                    tc.q,
                    c.u,
                    tc.u,
                    c.sigma_q,
                    c.flux_adu.unwrap_or(f64::NAN),
                    tc.flux,
                    sofipol_pipeline::catalog::flags::join(&c.flags, ",")
                )
            })
            .collect();
        one.note = Some(format!(
            "{} sep {:.2}\" pa {:.0} found {:?}/{:?} phot {:?}: {} | {:?}",
            tt.object,
            tt.separation_arcsec,
            tt.pa_deg,
            target.separation_arcsec,
            target.pa_deg,
            target.photometry,
            comps.join(" ; "),
            target.flags
        ));
    }
    one
}

/// Summary statistics of one separation bin.
fn bin_report(w: &[f64], fwhm: f64, ones: &[One]) -> BinReport {
    let pulls: Vec<f64> = ones.iter().flat_map(|o| o.pulls.iter().copied()).collect();
    let errs: Vec<f64> = ones.iter().flat_map(|o| o.errors.iter().copied()).collect();
    let ne = errs.len().max(1) as f64;
    let mut sig: Vec<f64> = ones.iter().flat_map(|o| o.sigmas.iter().copied()).collect();
    sig.sort_by(|a, b| a.total_cmp(b));
    let mut ts: Vec<f64> = ones.iter().map(|o| o.reduce_s).collect();
    ts.sort_by(|a, b| a.total_cmp(b));
    let np = pulls.len().max(1) as f64;
    BinReport {
        sep_arcsec: (w[0], w[1]),
        sep_fwhm: (w[0] / fwhm, w[1] / fwhm),
        n_pulls: pulls.len(),
        rms_pull: (pulls.iter().map(|p| p * p).sum::<f64>() / np).sqrt(),
        mean_pull: pulls.iter().sum::<f64>() / np,
        median_sigma: sig.get(sig.len() / 2).copied().unwrap_or(f64::NAN),
        rms_error: (errs.iter().map(|e| e * e).sum::<f64>() / ne).sqrt(),
        mean_error: errs.iter().sum::<f64>() / ne,
        missing: ones.iter().map(|o| o.missing).sum(),
        median_reduce_s: ts.get(ts.len() / 2).copied().unwrap_or(f64::NAN),
        outliers: ones.iter().filter_map(|o| o.note.clone()).collect(),
        delta_gamma_pulls: ones.iter().filter_map(|o| o.delta_gamma_pull).collect(),
    }
}

/// The flats of one simulated night (one separation bin), built from the simulated frames in
/// memory with the library's `dome_flat` / `superflat` (`night::night_flats` builds the same
/// kinds from files; this harness never writes any).
pub fn simulated_flats(mode: FlatMode, sim: &Simulator, profile: &Profile) -> Option<sofipol_calib::flat::FlatSet> {
    use sofipol_calib::flat::{dome_flat, superflat, FlatOptions, FlatSet};
    let opts = FlatOptions::default();
    match mode {
        FlatMode::None => None,
        FlatMode::Superflat => {
            let n = sim.frames_per_target();
            let nt = sim.scene().binary.len();
            let mut picks = Vec::new();
            'outer: for round in 0..n {
                for t in 0..nt {
                    if picks.len() >= opts.max_frames {
                        break 'outer;
                    }
                    picks.push((t, (t + round * 3) % n));
                }
            }
            let frames: Vec<_> = picks.par_iter().map(|&(t, k)| sim.frame(t, k).frame).collect();
            let f = superflat(&frames, profile, &opts).expect("superflat of a simulated night");
            Some(FlatSet::new(vec![f]))
        }
        FlatMode::Dome => {
            let all = sim.dome_flat_frames();
            let mut angles: Vec<f64> = all.iter().map(|f| f.truth.posang_deg).collect();
            angles.dedup();
            let flats = angles
                .iter()
                .map(|&pa| {
                    let (on, off): (Vec<_>, Vec<_>) = all
                        .iter()
                        .filter(|f| f.truth.posang_deg == pa)
                        .partition(|f| f.truth.lamp_on);
                    let on: Vec<_> = on.into_iter().map(|f| f.frame.clone()).collect();
                    let off: Vec<_> = off.into_iter().map(|f| f.frame.clone()).collect();
                    dome_flat(&on, &off, profile, &opts).expect("dome flat of a simulated night")
                })
                .collect();
            Some(FlatSet::new(flats))
        }
    }
}

/// A table of the reports.
pub fn table(r: &[BinReport]) -> String {
    let mut s = format!(
        "{:>13} {:>11} {:>7} {:>9} {:>9} {:>10} {:>8} {:>10}\n",
        "sep [\"]", "sep [FWHM]", "pulls", "rms pull", "mean", "med sig_q", "missing", "reduce s"
    );
    for b in r {
        s += &format!(
            "{:>6.2}-{:<6.2} {:>5.2}-{:<5.2} {:>7} {:>9.3} {:>9.3} {:>10.5} {:>8} {:>10.3}\n",
            b.sep_arcsec.0,
            b.sep_arcsec.1,
            b.sep_fwhm.0,
            b.sep_fwhm.1,
            b.n_pulls,
            b.rms_pull,
            b.mean_pull,
            b.median_sigma,
            b.missing,
            b.median_reduce_s
        );
        if std::env::var_os("SOFIPOL_SHOW_OUTLIERS").is_some() {
            for o in &b.outliers {
                s += &format!("      outlier: {o}\n");
            }
        }
    }
    s
}
