//! The per-target diagnostic PNG: simulated sequences reduced end to end, then plotted;
//! degenerate inputs (one component, NaN, failed target) must still give a PNG.
use std::path::Path;
use std::time::Instant;

use sofipol_calib::Profile;
use sofipol_pipeline::catalog::{Status, Target};
use sofipol_pipeline::plots::target::{outcome_png, target_png, target_png_opt, WIDTH};
use sofipol_pipeline::reduce::run::{reduce_loaded, LoadedOrientation, TargetOutcome};
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sequence::Sequence;
use sofipol_pipeline::sim::{Scene, Simulator};

fn scene(orientations: &str, binary: &str) -> String {
    format!(
        "name = \"plot\"\nseed = 11\neffects = [\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\", \"cosmic_rays\", \"bad_pixels\"]\n\
         [observation]\norientations_deg = [{orientations}]\ndithers = 5\n[psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.8\n\
         [[binary]]\n{binary}\n"
    )
}

/// Simulate one sequence and reduce it (frames kept for the plot).
fn reduce(orientations: &str, binary: &str) -> TargetOutcome {
    let sim = Simulator::new(
        Scene::from_toml(&scene(orientations, binary), "t").unwrap(),
        Profile::sofi(),
    )
    .unwrap();
    let (frames, truth) = sim.run_in_memory();
    let object = truth.targets[0].object.clone();
    let mut orients: Vec<LoadedOrientation> = Vec::new();
    for f in &frames {
        let pa = f.truth.posang_deg;
        if orients.last().is_none_or(|o| o.0 != pa) {
            orients.push((pa, f.truth.analyzer_deg, vec![], vec![]));
        }
        let o = orients.last_mut().unwrap();
        o.2.push(f.frame.clone());
        o.3.push(f.truth.header_offset_px);
    }
    let seq = Sequence {
        id: format!("{object}@sim"),
        object: object.clone(),
        tpl_start: "sim".into(),
        filter: "Ks".into(),
        orientations: vec![],
    };
    reduce_loaded(
        &seq,
        orients,
        &Profile::sofi(),
        &TargetParams::default(),
        None,
        None,
        true,
    )
}

/// Decode and check the PNG: width, and that it shows more than white and text.
fn check_png(path: &Path) -> (u32, u32) {
    let img = image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8();
    assert_eq!(img.width(), WIDTH);
    assert!(img.height() > 200);
    let px: Vec<&[u8]> = img.as_raw().chunks(3).collect();
    let dark = px.iter().filter(|p| p[0] < 80 && p[1] < 80 && p[2] < 80).count();
    let white = px.iter().filter(|p| p[0] > 250 && p[1] > 250 && p[2] > 250).count();
    assert!(dark > 2000, "{}: only {dark} dark pixels", path.display());
    assert!(white < px.len() * 97 / 100, "{}: blank", path.display());
    (img.width(), img.height())
}

fn keep_example(path: &Path) {
    if let Ok(dir) = std::env::var("SOFIPOL_PLOT_EXAMPLES") {
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::copy(path, Path::new(&dir).join(path.file_name().unwrap())).unwrap();
    }
}

const WIDE: &str =
    "name = \"Wide Tau\"\nseparation_arcsec = 2.2\npa_deg = 300.0\nflux_a = 120000.0\nflux_b = 40000.0\n\
                    p_a = 0.03\ngamma_a_deg = 150.0\np_b = 0.05\ngamma_b_deg = 95.0";

#[test]
fn plot_target_png_of_a_reduced_binary() {
    let dir = tempfile::tempdir().unwrap();
    for (name, orients, binary) in [
        ("wide_2or.png", "0.0, 45.0", WIDE),
        (
            "close_4or.png",
            "0.0, 45.0, 90.0, 135.0",
            "name = \"Close Lup\"\nseparation_arcsec = 0.9\npa_deg = 20.0\nflux_a = 60000.0\nflux_b = 30000.0\n\
             p_a = 0.04\ngamma_a_deg = 10.0\np_b = 0.01\ngamma_b_deg = 170.0",
        ),
        (
            "single.png",
            "0.0, 45.0",
            "name = \"Single Cha\"\nseparation_arcsec = 4.0\npa_deg = 100.0\nflux_a = 80000.0\nflux_b = 0.0\n\
             p_a = 0.02\ngamma_a_deg = 60.0\np_b = 0.0\ngamma_b_deg = 0.0",
        ),
    ] {
        let out = reduce(orients, binary);
        let (cal, m) = (out.calibrated.as_deref().unwrap(), out.measured.as_ref().unwrap());
        let path = dir.path().join(name);
        let t = Instant::now();
        target_png(&path, &out.target, cal, m).unwrap();
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let (w, h) = check_png(&path);
        eprintln!(
            "{name}: {w}x{h}, {ms:.1} ms, status {:?}, {} components",
            out.target.status,
            out.target.components.len()
        );
        keep_example(&path);
        // Same figure through the outcome wrapper.
        outcome_png(&dir.path().join(format!("o_{name}")), &out).unwrap();
    }
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with('.'))
        .collect();
    assert!(left.is_empty(), "temporary files left behind");
}

#[test]
fn plot_target_png_survives_degenerate_input() {
    let dir = tempfile::tempdir().unwrap();
    let out = reduce("0.0, 45.0", WIDE);
    let (cal, m) = (out.calibrated.clone().unwrap(), out.measured.clone().unwrap());

    // NaN everywhere it can be.
    let mut bad_m = m.clone();
    for c in bad_m.dithers.iter_mut() {
        for o in c.iter_mut() {
            for (i, d) in o.iter_mut().enumerate() {
                d.f = f64::NAN;
                if i % 2 == 0 {
                    d.o.xy = (f64::NAN, f64::NAN);
                    d.rejected = Some("photometry failed".into());
                }
            }
        }
    }
    bad_m.fwhm_px = f64::NAN;
    bad_m.aperture_px = f64::NAN;
    bad_m.geometry = Some((f64::NAN, f64::NAN));
    let mut bad_t = out.target.clone();
    for c in bad_t.components.iter_mut() {
        c.p = f64::NAN;
        c.gamma_deg = f64::NAN;
        c.sigma_gamma_deg = f64::INFINITY;
    }
    let p = dir.path().join("nan.png");
    target_png(&p, &bad_t, &cal, &bad_m).unwrap();
    check_png(&p);
    keep_example(&p);

    // One component only, no frames at the second orientation, huge P.
    let mut one_m = m.clone();
    one_m.dithers.truncate(1);
    one_m.geometry = None;
    let mut one_t = out.target.clone();
    one_t.components.truncate(1);
    one_t.components[0].p = 0.9;
    one_t.status = Status::Partial;
    one_t.error = Some("companion_not_found".into());
    let mut one_cal = cal.clone();
    one_cal[1].frames.clear();
    let p = dir.path().join("one.png");
    target_png(&p, &one_t, &one_cal, &one_m).unwrap();
    check_png(&p);
    keep_example(&p);

    // Measurements but empty dither lists; and frames but no measurement.
    let mut empty_m = m.clone();
    for c in empty_m.dithers.iter_mut() {
        for o in c.iter_mut() {
            o.clear();
        }
    }
    let p = dir.path().join("empty_dithers.png");
    target_png(&p, &out.target, &cal, &empty_m).unwrap();
    check_png(&p);
    target_png_opt(&dir.path().join("no_m.png"), &out.target, Some(&cal), None).unwrap();
    check_png(&dir.path().join("no_m.png"));

    // A failed target: text only.
    let failed = Target {
        error: Some("no readable frame: every file of the sequence failed to open (a long message that has to wrap over several lines of the text band)".into()),
        ..Target::new("Broken Ori", Status::Failed)
    };
    let p = dir.path().join("failed.png");
    let t = Instant::now();
    target_png(&p, &failed, &[], &empty_m).unwrap();
    eprintln!("failed: {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    check_png(&p);
    keep_example(&p);
    target_png_opt(&dir.path().join("failed2.png"), &failed, None, None).unwrap();
    check_png(&dir.path().join("failed2.png"));

    // Unwritable destination: an error, not a panic.
    assert!(target_png(&dir.path().join("no/such/dir/x.png"), &failed, &[], &empty_m).is_err());
}
