//! Acceptance of the instrumental calibration on simulated nights, fixed seeds:
//! beam ratio k = 0.97, instrumental polarization 0.3 %, angle zero-point 3 deg.
//!
//! * 2 orientations with 2 unpolarized + 2 polarized standards: q, u pulls of the pooled
//!   components have rms in 0.8-1.2 and mean within 0.3; standards agree with their table.
//! * The same night without calibration: every component flagged `uncalibrated` (and the
//!   pulls are far off: the test shows why the flag is needed).
//! * 4 orientations with k = 0.97 and no calibration data: the ratio method gives pulls
//!   with rms in 0.8-1.2.
//!
//! Frames are simulated and reduced one sequence at a time (streaming: a night of 1024^2
//! frames does not fit in memory), in parallel over sequences.
use rayon::prelude::*;
use sofipol_bench::accuracy::{simulated_flats, FlatMode};
use sofipol_calib::flat::FlatSet;
use sofipol_calib::Profile;
use sofipol_pipeline::calibration::{
    calibrate_catalog, standard_params, CalibrationContext, CalibrationParams, CalibrationSource,
};
use sofipol_pipeline::catalog::{Catalog, FlagCode, Target};
use sofipol_pipeline::reduce::run::reduce_loaded;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{loaded_from_sim, EffectKind, Scene, Simulator, Truth};
use sofipol_pipeline::standards::StandardsTable;
use sofipol_pipeline::stokes::inversion::Debias;

const N_BINARIES: usize = 16;

fn scene(orientations: &str, instrument: &str, standards: bool) -> Scene {
    let mut s = format!(
        r#"
name = "cal"
seed = 808
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", {instrument}]
[flat_field]
pixel_rms = 0.01
vignetting = 0.05
[dome_flats]
frames_on = 3
frames_off = 3
[observation]
orientations_deg = [{orientations}]
dithers = 3
[psf]
fwhm_arcsec = 0.8
seeing_rms_frac = 0.05
[sky]
level_adu = 1500.0
[throughput]
t_o = 1.0
t_e = 0.97
[instrumental_polarization]
p = 0.003
angle_deg = 0.0
[analyzer_angle]
zero_point_deg = 3.0
parity = 1
"#
    );
    for i in 0..N_BINARIES {
        // Wide pairs (4-5"), intrinsic P 1-6 %, angles spread over [0, 180).
        let f = i as f64;
        s += &format!(
            "[[binary]]\nname = \"T{i}\"\nseparation_arcsec = {}\npa_deg = {}\nflux_a = 20000.0\nflux_b = 12000.0\np_a = {}\ngamma_a_deg = {}\np_b = {}\ngamma_b_deg = {}\n",
            4.0 + 0.06 * f,
            (37.0 * f) % 360.0,
            0.01 + 0.05 * ((f * 0.37) % 1.0),
            (23.0 + 71.0 * f) % 180.0,
            0.01 + 0.05 * ((f * 0.61 + 0.3) % 1.0),
            (101.0 + 53.0 * f) % 180.0,
        );
    }
    if standards {
        s += r#"
[[standard]]
name = "HD 64299"
flux = 150000.0
[[standard]]
name = "HD_98161"
flux = 150000.0
[[standard]]
name = "Pol A"
flux = 150000.0
p = 0.025
gamma_deg = 40.0
[[standard]]
name = "Pol B"
flux = 150000.0
p = 0.02
gamma_deg = 100.0
"#;
    }
    Scene::from_toml(&s, "calibration scene").unwrap()
}

/// Table values of the scene's polarized standards (as a user --standards file would give).
const USER_STANDARDS: &str = r#"
[[standard]]
name = "Pol A"
filter = "Ks"
p = 0.025
sigma_p = 0.0002
gamma_deg = 40.0
sigma_gamma_deg = 0.1
[[standard]]
name = "POL_B"
filter = "Ks"
p = 0.02
sigma_p = 0.0002
gamma_deg = 100.0
sigma_gamma_deg = 0.1
"#;

/// Simulate and reduce sequence `t` the way `night` reads files: analyzer angles from the
/// profile (the pipeline does not know the instrument's true zero-point), the night's dome
/// flats applied when the scene has a pixel response.
fn reduce_one(sim: &Simulator, t: usize, profile: &Profile, params: &TargetParams, flats: Option<&FlatSet>) -> Target {
    let frames = (0..sim.frames_per_target()).map(|k| sim.frame(t, k)).collect();
    let (seq, orients) = loaded_from_sim(frames, profile);
    let p = if sim.is_standard(t) {
        standard_params(params)
    } else {
        params.clone()
    };
    reduce_loaded(&seq, orients, profile, &p, None, flats, false).target
}

/// Reduce every sequence: (science catalog, standard targets).
fn reduce_night(sc: Scene) -> (Catalog, Vec<Target>, Truth) {
    let profile = Profile::sofi();
    let sim = Simulator::new(sc, profile.clone()).unwrap();
    let params = TargetParams {
        no_detect_bad_pixels: true,
        ..Default::default()
    };
    let mode = if sim.scene().has(EffectKind::DomeFlats) {
        FlatMode::Dome
    } else {
        FlatMode::None
    };
    let flats = simulated_flats(mode, &sim, &profile);
    let targets: Vec<Target> = (0..sim.n_sequences())
        .into_par_iter()
        .map(|t| reduce_one(&sim, t, &profile, &params, flats.as_ref()))
        .collect();
    let truth = sim.truth(&[]);
    let nb = truth.targets.len();
    let mut cat = Catalog::default();
    let mut stds = Vec::new();
    for (t, target) in targets.into_iter().enumerate() {
        if t < nb {
            cat.targets.push(target);
        } else {
            stds.push(target);
        }
    }
    (cat, stds, truth)
}

/// Pooled q and u pulls of every component of status ok against the truth.
fn pulls(cat: &Catalog, truth: &Truth) -> Vec<f64> {
    let mut out = Vec::new();
    for (t, tt) in cat.targets.iter().zip(&truth.targets) {
        assert_eq!(t.object, tt.object);
        if t.components.len() != 2 {
            continue;
        }
        for (c, ct) in t.components.iter().zip(&tt.components) {
            out.push((c.q - ct.q) / c.sigma_q);
            out.push((c.u - ct.u) / c.sigma_u);
        }
    }
    out
}

fn mean_rms(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    (m, (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt())
}

fn calibrate(cat: &mut Catalog, stds: Vec<Target>, source: CalibrationSource) -> usize {
    let mut table = StandardsTable::builtin();
    table.merge_toml(USER_STANDARDS, "test standards").unwrap();
    // These scenes simulate no telescope polarization: the instrument reduced is one whose
    // telescope adds none (with SOFI's M3 its expected size would be carried in every error).
    let mut profile = Profile::sofi();
    profile.telescope.polarizes = false;
    let (_, s) = calibrate_catalog(
        cat,
        stds,
        source,
        &CalibrationContext {
            table: &table,
            profile: &profile,
            params: &CalibrationParams::default(),
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
        },
    );
    s.n_uncalibrated
}

#[test]
fn two_orientations_with_standards_give_unbiased_pulls_and_without_them_are_flagged() {
    // 1 % pixel response (and 5 % vignetting) with dome flats, k = 0.97, p_inst 0.3 %,
    // zero-point 3 deg, 2 unpolarized + 2 polarized standards.
    let (raw, stds, truth) = reduce_night(scene(
        "0.0, 45.0",
        "\"throughput\", \"instrumental_polarization\", \"analyzer_angle\", \"flat_field\", \"dome_flats\"",
        true,
    ));
    assert_eq!(stds.len(), 4);
    // Standards are single stars, never binaries.
    for s in &stds {
        assert_eq!(s.components.len(), 1, "{}: {:?}", s.object, s.components.len());
    }

    let mut cat = raw.clone();
    assert_eq!(calibrate(&mut cat, stds.clone(), CalibrationSource::Night), 0);
    let cal = &cat.calibration.as_ref().unwrap().calibration().unwrap().filters[0];
    let (offset, angles) = (cal.offset.unwrap(), cal.angles.unwrap());
    let (c, sc) = (offset.c, offset.sigma_c);
    let c_true = 0.03 / 1.97 + 0.003;
    let (th, sth) = (angles.theta0_deg, angles.sigma_theta0_deg);
    eprintln!("c = {c:.5} +- {sc:.5} (true {c_true:.5}); theta0 = {th:.3} +- {sth:.3} (true 3)");
    assert!((c - c_true).abs() < 3.0 * sc, "c {c} +- {sc} vs {c_true}");
    assert!((th - 3.0).abs() < 3.0 * sth, "theta0 {th} +- {sth}");
    assert_eq!(angles.parity, 1);
    assert!(angles.parity_measured);

    let p = pulls(&cat, &truth);
    let (m, rms) = mean_rms(&p);
    eprintln!(
        "calibrated, 2 orientations: n = {} q,u pulls, mean {m:.3}, rms {rms:.3}",
        p.len()
    );
    assert!(p.len() >= 60, "{}", p.len());
    assert!((0.8..=1.2).contains(&rms), "pull rms {rms}");
    assert!(m.abs() < 0.3, "pull mean {m}");
    // No bias beyond 0.3 sigma in q or in u (pulls alternate q, u).
    for (what, k) in [("q", 0), ("u", 1)] {
        let v: Vec<f64> = p.iter().skip(k).step_by(2).copied().collect();
        let (mk, rk) = mean_rms(&v);
        eprintln!("  {what}: n = {}, pull mean {mk:.3}, rms {rk:.3}", v.len());
        assert!(mk.abs() < 0.3, "{what} pull mean {mk}");
        assert!((0.8..=1.2).contains(&rk), "{what} pull rms {rk}");
    }
    for t in &cat.targets {
        for c in &t.components {
            assert!(!c.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)));
        }
    }
    // Every standard is reported, matched to the table, and agrees with it within errors.
    assert_eq!(cat.standards.len(), 4);
    for s in &cat.standards {
        eprintln!(
            "standard {}: P residual {:?} sigma, (q, u) chi2 {:?}, angle residual {:?} deg ({:?} sigma)",
            s.name, s.residual_p_sigma, s.residual_qu_chi2, s.residual_gamma_deg, s.residual_gamma_sigma
        );
        assert!(s.table.is_some(), "{}", s.object);
        // Polarized: P against the table; unpolarized: (q, u) against 0 (chi^2, 2 dof).
        match (s.residual_p_sigma, s.residual_qu_chi2) {
            (Some(rp), None) => assert!(rp.abs() < 3.0, "{}: P residual {rp} sigma", s.name),
            (None, Some(chi2)) => assert!(chi2 < 11.83, "{}: (q, u) chi2 {chi2}", s.name),
            other => panic!("{}: residuals {other:?}", s.name),
        }
        if let Some(rg) = s.residual_gamma_sigma {
            assert!(rg.abs() < 3.0, "{}: angle residual {rg} sigma", s.name);
        }
        assert!(s.used_for.contains(&"offset".to_string()));
    }

    // The same night without calibration: flagged, and biased.
    let mut unc = raw;
    let n = calibrate(&mut unc, vec![], CalibrationSource::Night);
    assert_eq!(n, 2 * N_BINARIES);
    for t in &unc.targets {
        for c in &t.components {
            assert!(c.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)), "{}", t.object);
        }
    }
    let (m0, rms0) = mean_rms(&pulls(&unc, &truth));
    eprintln!("uncalibrated, 2 orientations: pull mean {m0:.2}, rms {rms0:.2}");
    assert!(rms0 > 2.0 || m0.abs() > 2.0);
}

#[test]
fn four_orientations_with_a_beam_ratio_need_no_calibration() {
    let (mut cat, stds, truth) = reduce_night(scene("0.0, 45.0, 90.0, 135.0", "\"throughput\"", false));
    assert!(stds.is_empty());
    assert_eq!(calibrate(&mut cat, stds, CalibrationSource::Night), 0);
    for t in &cat.targets {
        for c in &t.components {
            assert_eq!(c.stokes_method.as_deref(), Some("ratio"));
            assert!(!c.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)));
        }
    }
    let p = pulls(&cat, &truth);
    let (m, rms) = mean_rms(&p);
    eprintln!(
        "ratio method, 4 orientations, k = 0.97: n = {} pulls, mean {m:.3}, rms {rms:.3}",
        p.len()
    );
    assert!(p.len() >= 60);
    assert!((0.8..=1.2).contains(&rms), "pull rms {rms}");
    assert!(m.abs() < 0.3, "pull mean {m}");
}
