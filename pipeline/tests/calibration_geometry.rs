//! End to end on simulated frames (beam ratio k = 0.97, instrumental polarization 0.3 %,
//! zero-point theta0 = 3 deg, 2 orientations 0/45, no unpolarized standard): whether the
//! night's standards can separate the offset c from theta0 decides what the calibration does.
//!
//! * Two polarized standards at different angles (40 and 100 deg): c and theta0 are fitted
//!   jointly; theta0 within 3 sigma of the simulated 3 deg, c within 3 sigma of
//!   (1 - k)/(1 + k) + p_inst, nothing flagged `calibration_incomplete`.
//! * One polarized standard only: the data cannot separate c from theta0; the calibration is
//!   incomplete (no theta0 taken from the standard, the profile's zero-point kept) and every
//!   component of the filter is flagged `calibration_incomplete`.
use sofipol_calib::Profile;
use sofipol_pipeline::calibration::{
    calibrate_catalog, standard_params, CalibrationContext, CalibrationParams, CalibrationSource,
};
use sofipol_pipeline::catalog::{Catalog, FlagCode, Target};
use sofipol_pipeline::reduce::run::reduce_loaded;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{loaded_from_sim, Scene, Simulator};
use sofipol_pipeline::standards::StandardsTable;
use sofipol_pipeline::stokes::inversion::Debias;

const SCENE: &str = r#"
name = "geom"
seed = 4242
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "throughput", "instrumental_polarization", "analyzer_angle"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
fwhm_arcsec = 0.8
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
[[binary]]
name = "T0"
separation_arcsec = 4.0
pa_deg = 30.0
flux_a = 60000.0
flux_b = 40000.0
p_a = 0.05
gamma_a_deg = 20.0
p_b = 0.03
gamma_b_deg = 110.0
[[standard]]
name = "Pol A"
flux = 300000.0
p = 0.025
gamma_deg = 40.0
[[standard]]
name = "Pol B"
flux = 300000.0
p = 0.02
gamma_deg = 100.0
"#;

const TABLE: &str = r#"
[[standard]]
name = "Pol A"
filter = "Ks"
p = 0.025
sigma_p = 0.0002
gamma_deg = 40.0
sigma_gamma_deg = 0.1
[[standard]]
name = "Pol B"
filter = "Ks"
p = 0.02
sigma_p = 0.0002
gamma_deg = 100.0
sigma_gamma_deg = 0.1
"#;

/// Reduce every sequence as `night` does (analyzer angles from the profile): (science
/// catalog, standards).
fn reduce_night() -> (Catalog, Vec<Target>) {
    let profile = Profile::sofi();
    let sim = Simulator::new(Scene::from_toml(SCENE, "geometry scene").unwrap(), profile.clone()).unwrap();
    let params = TargetParams {
        no_detect_bad_pixels: true,
        ..Default::default()
    };
    let mut cat = Catalog::default();
    let mut stds = Vec::new();
    for t in 0..sim.n_sequences() {
        let frames = (0..sim.frames_per_target()).map(|k| sim.frame(t, k)).collect();
        let (seq, orients) = loaded_from_sim(frames, &profile);
        let p = if sim.is_standard(t) {
            standard_params(&params)
        } else {
            params.clone()
        };
        let target = reduce_loaded(&seq, orients, &profile, &p, None, None, false).target;
        if sim.is_standard(t) {
            stds.push(target);
        } else {
            cat.targets.push(target);
        }
    }
    (cat, stds)
}

fn calibrate(cat: &mut Catalog, stds: Vec<Target>) -> (serde_json::Value, Vec<String>) {
    let mut table = StandardsTable::builtin();
    table.merge_toml(TABLE, "test standards").unwrap();
    let (_, sum) = calibrate_catalog(
        cat,
        stds,
        CalibrationSource::Night,
        &CalibrationContext {
            table: &table,
            profile: &Profile::sofi(),
            params: &CalibrationParams::default(),
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
        },
    );
    (
        serde_json::to_value(&cat.calibration.as_ref().unwrap().calibration().unwrap().filters[0]).unwrap(),
        sum.lines,
    )
}

#[test]
fn the_standards_geometry_decides_between_a_joint_fit_and_an_incomplete_flagged_calibration() {
    let (raw, stds) = reduce_night();
    assert_eq!(stds.len(), 2);
    let c_true = 0.03 / 1.97 + 0.003;

    // A: two polarized standards at different angles.
    let mut cat = raw.clone();
    let (f, _) = calibrate(&mut cat, stds.clone());
    assert!(f.get("incomplete").is_none(), "{f}");
    let (th, sth) = (
        f["angles"]["theta0_deg"].as_f64().unwrap(),
        f["angles"]["sigma_theta0_deg"].as_f64().unwrap(),
    );
    let (c, sc) = (
        f["offset"]["c"].as_f64().unwrap(),
        f["offset"]["sigma_c"].as_f64().unwrap(),
    );
    let cov = f["cov_c_theta0_deg"].as_f64().unwrap();
    eprintln!(
        "two polarized standards: theta0 = {th:.2} +- {sth:.2} deg (truth 3), c = {c:.5} +- {sc:.5} (truth {c_true:.5}), \
         corr(c, theta0) = {:.3}",
        cov / (sc * sth)
    );
    assert!((th - 3.0).abs() < 3.0 * sth, "theta0 {th} +- {sth}");
    assert!((c - c_true).abs() < 3.0 * sc, "c {c} +- {sc}");
    for t in &cat.targets {
        for comp in &t.components {
            assert!(
                !comp
                    .flags
                    .iter()
                    .any(|x| x.is(FlagCode::CalibrationIncomplete) || x.is(FlagCode::Uncalibrated)),
                "{:?}",
                comp.flags
            );
        }
    }

    // B: Pol A alone.
    let mut cat = raw;
    let only_a: Vec<Target> = stds.into_iter().filter(|t| t.object == "Pol A").collect();
    assert_eq!(only_a.len(), 1);
    let (f, lines) = calibrate(&mut cat, only_a);
    eprintln!("one polarized standard: {f}");
    assert!(f["incomplete"].as_str().is_some_and(|s| !s.is_empty()), "{f}");
    assert!(f["angles"].is_null(), "theta0 taken from the lone standard: {f}");
    assert!(f["angle_standards"].as_array().unwrap().is_empty());
    let mut n = 0;
    for t in &cat.targets {
        for comp in &t.components {
            assert!(
                comp.flags.iter().any(|x| x.is(FlagCode::CalibrationIncomplete)),
                "{:?}",
                comp.flags
            );
            n += 1;
        }
    }
    assert!(n >= 2);
    assert!(lines.iter().any(|l| l.contains("incomplete")), "{lines:?}");
}
