//! Magnitudes next to ADU fluxes: a simulated night whose standards have a magnitude (the
//! simulator's `zero_point_mag`, the standards table's `mag` given with `--standards`) is
//! reduced by `sofipol night`, and every target component's magnitude is compared with the
//! truth (`ZP - 2.5 log10(flux / DIT)` from the scene's fluxes and zero-point) in units of
//! its error; the zero-point and its standards are in the catalog, the log, the report and
//! the export. A night whose standards have no magnitude (the built-in table) gives none
//! and says why in one line.
use std::path::Path;

mod common;
use common::{json, run, ALPHA_BETA, INSTRUMENT};

/// The simulated night's zero-point (magnitude of 1 ADU/s, o+e) and DIT.
const ZP: f64 = 20.0;
const DIT_S: f64 = 10.0;
/// A field star of the last binary (Beta): separation from A, arcsec, and flux (o+e, ADU per
/// frame, unit transmission).
const FIELD_SEP: f64 = 40.0;
const FIELD_FLUX: f64 = 80000.0;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A night of Alpha and Beta with two standards given by their magnitudes.
fn night(dir: &Path) -> std::path::PathBuf {
    let n = dir.join("night");
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            "name = \"mags\"\nseed = 21\neffects = [\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\", \
             \"throughput\", \"instrumental_polarization\", \"analyzer_angle\"]\n\
             [observation]\norientations_deg = [0.0, 45.0]\ndithers = 3\ndit_s = {DIT_S}\nzero_point_mag = {ZP}\n\
             [psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.8\n{INSTRUMENT}\
             [[standard]]\nname = \"HD 64299\"\nmag = 9.5\n\
             [[standard]]\nname = \"HD 204827\"\nmag = 9.7\np = 0.0088\ngamma_deg = 58.7\n{ALPHA_BETA}             [[binary.field_star]]\nseparation_arcsec = {FIELD_SEP}\npa_deg = 270.0\nflux = {FIELD_FLUX}\np = 0.0\ngamma_deg = 0.0\n"
        ),
    )
    .unwrap();
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    n
}

/// The standards table with the two standards' magnitudes (in Ks).
const TABLE: &str = r#"[[standard]]
name = "HD 64299"
filter = "Ks"
p = 0.0
sigma_p = 0.0005
mag = 9.5
sigma_mag = 0.01
mag_band = "simulated Ks"
[[standard]]
name = "HD 204827"
filter = "Ks"
p = 0.0088
sigma_p = 0.0022
gamma_deg = 58.7
sigma_gamma_deg = 2.0
mag = 9.7
sigma_mag = 0.01
"#;

#[test]
fn a_night_with_photometric_standards_gives_magnitudes_that_agree_with_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let truth = json(&n.join("truth.json"));
    std::fs::remove_file(n.join("truth.json")).unwrap();
    // The standards' fluxes follow their magnitudes and the zero-point.
    for (i, mag) in [9.5, 9.7].into_iter().enumerate() {
        let f = truth["standards"][i]["components"][0]["flux"]
            .as_f64()
            .unwrap_or_else(|| panic!("standard {i} in truth.json: {}", truth["standards"]));
        let want = DIT_S * 10f64.powf(-0.4 * (mag - ZP));
        assert!((f - want).abs() < 1e-6 * want, "standard {i} flux {f} vs {want}");
    }
    let table = dir.path().join("table.toml");
    std::fs::write(&table, TABLE).unwrap();
    let cat_path = dir.path().join("cat.json");
    let page = dir.path().join("night.html");
    let (code, out, err) = run(&[
        "night",
        s(&n),
        "-o",
        s(&cat_path),
        "--standards",
        s(&table),
        "--report",
        s(&page),
    ]);
    assert!(code == 0 || code == 2, "{out}\n{err}");
    let cat = json(&cat_path);
    let ph = &cat["calibration"]["photometry"];
    let zp = &ph["filters"][0];
    assert_eq!(zp["filter"], "Ks", "{ph}");
    assert_eq!(zp["standards"].as_array().unwrap().len(), 2, "{ph}");
    let (zp_mag, zp_sigma) = (
        zp["zero_point_mag"].as_f64().unwrap(),
        zp["sigma_zero_point_mag"].as_f64().unwrap(),
    );
    println!("ZP = {zp_mag:.4} +- {zp_sigma:.4} (true {ZP}; the throughput and aperture losses are in it)");
    assert!(zp_sigma > 0.005 && zp_sigma < 0.05, "{ph}");

    // The truth: each component's o+e flux per frame (unit transmission), as simulated.
    let truth_flux = |object: &str, comp: &str| -> f64 {
        let t = truth["targets"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["object"] == object)
            .unwrap_or_else(|| panic!("{object} not in truth.json"));
        let c = t["components"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["name"] == comp)
            .unwrap();
        c["flux"].as_f64().unwrap()
    };
    let mut pulls = Vec::new();
    for t in cat["targets"].as_array().unwrap() {
        let object = t["object"].as_str().unwrap();
        assert_eq!(t["dit_s"].as_f64(), Some(DIT_S), "{object}");
        for c in t["components"].as_array().unwrap() {
            let name = c["name"].as_str().unwrap();
            let truth_mag = ZP - 2.5 * (truth_flux(object, name) / DIT_S).log10();
            let (m, sm) = (c["mag"].as_f64(), c["sigma_mag"].as_f64());
            let (m, sm) = (m.unwrap_or_else(|| panic!("{object} {name}: no mag: {c}")), sm.unwrap());
            let pull = (m - truth_mag) / sm;
            println!("{object} {name}: mag {m:.4} +- {sm:.4}, truth {truth_mag:.4}, pull {pull:+.2}");
            assert!(sm >= zp_sigma && sm < 0.1, "{object} {name}: sigma_mag {sm}");
            assert!((m - truth_mag).abs() < 0.05, "{object} {name}: {m} vs {truth_mag}");
            pulls.push(pull);
        }
    }
    assert_eq!(pulls.len(), 4);
    // Field stars are measured like the components and get magnitudes alike.
    let beta = cat["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == "Beta")
        .unwrap();
    let fs = beta["field_stars"]
        .as_array()
        .unwrap_or_else(|| panic!("Beta: no field_stars: {beta}"));
    let star = fs
        .iter()
        .find(|f| (f["separation_arcsec"].as_f64().unwrap() - FIELD_SEP).abs() < 1.0)
        .unwrap_or_else(|| panic!("the field star at {FIELD_SEP}\" not found: {fs:?}"));
    let truth_mag = ZP - 2.5 * (FIELD_FLUX / DIT_S).log10();
    let (m, sm) = (
        star["mag"]
            .as_f64()
            .unwrap_or_else(|| panic!("field star: no mag: {star}")),
        star["sigma_mag"].as_f64().unwrap(),
    );
    let pull = (m - truth_mag) / sm;
    println!("Beta field star: mag {m:.4} +- {sm:.4}, truth {truth_mag:.4}, pull {pull:+.2}");
    assert!(
        sm >= zp_sigma && (m - truth_mag).abs() < 0.05,
        "field star {m} +- {sm} vs {truth_mag}"
    );
    pulls.push(pull);
    for p in &pulls {
        assert!(p.abs() < 4.0, "pulls {pulls:?}");
    }

    // The night log, the report and the export say it.
    let log = std::fs::read_to_string(dir.path().join("cat.log")).unwrap();
    assert!(log.contains("photometry: photometric zero-point Ks: ZP = "), "{log}");
    assert!(log.contains(" mag\n") && log.contains(", Ks = "), "{log}");
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(
        html.contains("<table id=\"photometry\">") && html.contains("data-label=\"Mag\""),
        "report"
    );
    let csv = dir.path().join("cat.csv");
    let (code, _, err) = run(&["export", s(&cat_path), "-o", s(&csv)]);
    assert_eq!(code, 0, "{err}");
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines().filter(|l| !l.starts_with('#'));
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == "mag").expect("a mag column");
    let first: Vec<&str> = lines.next().unwrap().split(',').collect();
    let exported: f64 = first[col].parse().unwrap();
    let catalog_mag = cat["targets"][0]["components"][0]["mag"].as_f64().unwrap();
    assert!((exported - catalog_mag).abs() < 1e-9, "{exported} vs {catalog_mag}");
    let ecsv = dir.path().join("cat.ecsv");
    let (code, _, err) = run(&["export", s(&cat_path), "-o", s(&ecsv)]);
    assert_eq!(code, 0, "{err}");
    let text = std::fs::read_to_string(&ecsv).unwrap();
    for col in ["mag", "sigma_mag"] {
        assert!(
            text.lines()
                .any(|l| l.starts_with(&format!("# - {{name: {col}, unit: mag, datatype: float64"))),
            "{col} in the ECSV header"
        );
    }
}

#[test]
fn a_night_without_a_magnitude_standard_gives_no_magnitudes_and_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let n = common::instrument_night(dir.path(), "nomag", 5, common::TWO_STANDARDS);
    let cat_path = dir.path().join("cat.json");
    let page = dir.path().join("night.html");
    let (code, out, err) = run(&["night", s(&n), "-o", s(&cat_path), "--report", s(&page)]);
    assert!(code == 0 || code == 2, "{out}\n{err}");
    let cat = json(&cat_path);
    let comps: Vec<&serde_json::Value> = cat["targets"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|t| t["components"].as_array().unwrap())
        .collect();
    assert!(!comps.is_empty());
    assert!(comps
        .iter()
        .all(|c| c.get("mag").is_none() && c.get("sigma_mag").is_none()));
    assert!(comps.iter().all(|c| c["flux_adu"].as_f64().is_some_and(|f| f > 0.0)));
    let why = "no magnitudes: the night has no standard with a magnitude in its filter (fluxes in ADU only";
    let notes = &cat["calibration"]["photometry"]["notes"];
    assert!(notes[0].as_str().is_some_and(|l| l.starts_with(why)), "{notes}");
    let log = std::fs::read_to_string(dir.path().join("cat.log")).unwrap();
    assert_eq!(log.matches(why).count(), 1, "{log}");
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains(why), "report");

    // A scene magnitude without the night's zero-point is refused, naming the key.
    let scene = dir.path().join("bad.toml");
    std::fs::write(&scene, "name = \"bad\"\n[[standard]]\nname = \"S\"\nmag = 9.0\n").unwrap();
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&dir.path().join("bad")), "-q"]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("standard 'S': mag = 9 needs observation.zero_point_mag"),
        "{err}"
    );
}
