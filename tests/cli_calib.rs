//! End-to-end: `sofipol calib` on a night with standards, `night --calib` on a night
//! without, and the `uncalibrated` flag and its explanation when nothing calibrates.

use serde_json::Value;

mod common;
use common::run;

fn scene(standards: bool) -> String {
    let mut s = r#"
name = "cc"
seed = 31
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "throughput", "instrumental_polarization", "analyzer_angle"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
fwhm_arcsec = 0.8
[throughput]
t_e = 0.97
[instrumental_polarization]
p = 0.003
angle_deg = 0.0
[analyzer_angle]
zero_point_deg = 3.0
[[binary]]
name = "Alpha"
separation_arcsec = 4.0
pa_deg = 30.0
flux_a = 100000.0
flux_b = 60000.0
p_a = 0.05
gamma_a_deg = 20.0
p_b = 0.03
gamma_b_deg = 110.0
"#
    .to_string();
    if standards {
        s += r#"
[[standard]]
name = "HD 64299"
flux = 150000.0
[[standard]]
name = "HD_98161"
flux = 150000.0
[[standard]]
name = "My Pol"
flux = 150000.0
p = 0.02
gamma_deg = 45.0
"#;
    }
    s
}

const STANDARDS: &str = r#"
[[standard]]
name = "my pol"
filter = "Ks"
p = 0.02
sigma_p = 0.0002
gamma_deg = 45.0
sigma_gamma_deg = 0.2
"#;

fn simulate(dir: &std::path::Path, name: &str, standards: bool) -> String {
    let sc = dir.join(format!("{name}.toml"));
    std::fs::write(&sc, scene(standards)).unwrap();
    let out = dir.join(name);
    let (code, _, err) = run(&["simulate", sc.to_str().unwrap(), "-o", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    out.to_str().unwrap().to_string()
}

#[test]
fn calib_products_serve_another_night_and_uncalibrated_is_flagged_and_explained() {
    let tmp = tempfile::tempdir().unwrap();
    let with = simulate(tmp.path(), "with", true);
    let without = simulate(tmp.path(), "without", false);
    let stds = tmp.path().join("stds.toml");
    std::fs::write(&stds, STANDARDS).unwrap();
    let caldir = tmp.path().join("cal");

    let (code, out, err) = run(&[
        "calib",
        &with,
        "-o",
        caldir.to_str().unwrap(),
        "--standards",
        stds.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{out}\n{err}");
    let cal: Value = serde_json::from_str(&std::fs::read_to_string(caldir.join("calibration.json")).unwrap()).unwrap();
    let f = &cal["filters"][0];
    let c = f["offset"]["c"].as_f64().unwrap();
    let c_true = 0.03 / 1.97 + 0.003;
    assert!(
        (c - c_true).abs() < 5.0 * f["offset"]["sigma_c"].as_f64().unwrap(),
        "{f}"
    );
    let th = f["angles"]["theta0_deg"].as_f64().unwrap();
    assert!(
        (th - 3.0).abs() < 5.0 * f["angles"]["sigma_theta0_deg"].as_f64().unwrap(),
        "{f}"
    );
    assert_eq!(f["offset_standards"].as_array().unwrap().len(), 3);
    assert!(cal["frames"].as_array().unwrap().len() == 18);
    // The terminal line: numbers with their names and units, standards by name (no
    // `["...", "..."]` of a Rust debug print).
    let line = out
        .lines()
        .find(|l| l.starts_with("Ks: "))
        .unwrap_or_else(|| panic!("{out}"));
    let sigma_th = f["angles"]["sigma_theta0_deg"].as_f64().unwrap();
    for part in [
        format!(
            "instrumental offset c = {c:.5} +- {:.5}",
            f["offset"]["sigma_c"].as_f64().unwrap()
        ),
        // c comes from every standard of the joint fit; the polarized one is not called
        // unpolarized.
        "from 3 standards (2 unpolarized, 1 polarized): ".to_string(),
        format!("angle zero-point theta0 = {th:.2} +- {sigma_th:.2} deg"),
        "telescope polarization".to_string(),
    ] {
        assert!(line.contains(&part), "{part} not in {line}");
    }
    assert!(!line.contains('[') && !line.contains('"'), "{line}");

    // The night without standards, calibrated from the other night's products.
    let cat_path = tmp.path().join("c1.json");
    let (code, out, err) = run(&[
        "night",
        &without,
        "-o",
        cat_path.to_str().unwrap(),
        "--no-png",
        "--calib",
        caldir.to_str().unwrap(),
    ]);
    assert!(code == 0 || code == 2, "{out}\n{err}");
    let cat: Value = serde_json::from_str(&std::fs::read_to_string(&cat_path).unwrap()).unwrap();
    assert_eq!(cat["calibration"]["source"], caldir.to_str().unwrap());
    assert_eq!(cat["provenance"]["calibration"]["calib_dir"], caldir.to_str().unwrap());
    for c in cat["targets"][0]["components"].as_array().unwrap() {
        assert!(
            !c["flags"].as_array().unwrap().iter().any(|f| f == "uncalibrated"),
            "{c}"
        );
        assert_eq!(c["stokes_method"], "least_squares");
    }

    // Nothing to calibrate with: flagged, and stderr says why.
    let cat_path = tmp.path().join("c2.json");
    let (_, _, err) = run(&["night", &without, "-o", cat_path.to_str().unwrap(), "--no-png"]);
    assert!(err.contains("uncalibrated") && err.contains("biases q and u"), "{err}");
    let cat: Value = serde_json::from_str(&std::fs::read_to_string(&cat_path).unwrap()).unwrap();
    for c in cat["targets"][0]["components"].as_array().unwrap() {
        assert!(
            c["flags"].as_array().unwrap().iter().any(|f| f == "uncalibrated"),
            "{c}"
        );
    }

    // The night with standards calibrates itself; standards are their own section.
    let cat_path = tmp.path().join("c3.json");
    let (_, _, err) = run(&[
        "night",
        &with,
        "-o",
        cat_path.to_str().unwrap(),
        "--no-png",
        "--standards",
        stds.to_str().unwrap(),
    ]);
    assert!(err.contains("1 sequences + 3 standard(s)"), "{err}");
    let cat: Value = serde_json::from_str(&std::fs::read_to_string(&cat_path).unwrap()).unwrap();
    assert_eq!(cat["targets"].as_array().unwrap().len(), 1);
    assert_eq!(cat["standards"].as_array().unwrap().len(), 3);
    assert_eq!(cat["calibration"]["source"], "night");

    // A night without standards cannot make calibration products: exit 1 with the reason.
    let (code, _, err) = run(&["calib", &without, "-o", tmp.path().join("cal2").to_str().unwrap()]);
    assert_eq!(code, 1);
    assert!(err.contains("no usable standard"), "{err}");
}

/// An absurd calibration.json (c = 5, parity 7, theta0 1e300) is refused before anything is
/// reduced: exit 1, the message naming the file, the key path and the value.
#[test]
fn night_with_an_absurd_calibration_file_exits_1_naming_file_key_and_value() {
    let tmp = tempfile::tempdir().unwrap();
    let night = tmp.path().join("night");
    std::fs::create_dir(&night).unwrap();
    let caldir = tmp.path().join("cal");
    std::fs::create_dir(&caldir).unwrap();
    let write = |c: f64, parity: i32, theta0: f64| {
        let doc = serde_json::json!({
            "schema_version": "1.0",
            "filters": [{"filter": "Ks", "offset": {"c": c, "sigma_c": 0.0002}, "offset_standards": [],
                         "angles": {"theta0_deg": theta0, "sigma_theta0_deg": 0.5, "parity": parity,
                                    "parity_measured": false, "n_standards": 1},
                         "angle_standards": []}],
            "frames": [], "provenance": {}
        });
        std::fs::write(caldir.join("calibration.json"), doc.to_string()).unwrap();
    };
    let file = caldir.join("calibration.json");
    for (c, parity, theta0, expect) in [
        (5.0, 7, 1e300, "filters[0].offset.c = 5"),
        (0.018, 7, 3.0, "filters[0].angles.parity = 7"),
        (0.018, 1, 1e300, "filters[0].angles.theta0_deg = 1e300"),
    ] {
        write(c, parity, theta0);
        let out = tmp.path().join("c.json");
        let (code, _, err) = run(&[
            "night",
            night.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--no-png",
            "--calib",
            caldir.to_str().unwrap(),
        ]);
        assert_eq!(code, 1, "{err}");
        assert!(
            err.contains(file.to_str().unwrap()) && err.contains(expect),
            "{expect}: {err}"
        );
        assert!(!out.exists());
    }
}

/// `calib` on a night with dome flats at both rotator angles writes one flat per angle;
/// another night (no dome flats) reduced with `--calib CALDIR` uses them, each orientation
/// the flat of its angle, as it does with the two files given as `--flat A --flat B`.
#[test]
fn the_flats_of_a_calibration_directory_serve_another_night_one_per_rotator_angle() {
    let tmp = tempfile::tempdir().unwrap();
    let sc = tmp.path().join("domes.toml");
    let scene = scene(true).replace(
        "\"analyzer_angle\"]",
        "\"analyzer_angle\", \"dome_flats\"]\n[dome_flats]\nframes_on = 3\nframes_off = 3",
    );
    std::fs::write(&sc, scene).unwrap();
    let domes = tmp.path().join("domes");
    let (code, _, err) = run(&["simulate", sc.to_str().unwrap(), "-o", domes.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    let without = simulate(tmp.path(), "without", false);
    let stds = tmp.path().join("stds.toml");
    std::fs::write(&stds, STANDARDS).unwrap();
    let caldir = tmp.path().join("cal");
    let (code, out, err) = run(&[
        "calib",
        domes.to_str().unwrap(),
        "-o",
        caldir.to_str().unwrap(),
        "--standards",
        stds.to_str().unwrap(),
        "-q",
    ]);
    assert_eq!(code, 0, "{out}\n{err}");
    let cal: Value = serde_json::from_str(&std::fs::read_to_string(caldir.join("calibration.json")).unwrap()).unwrap();
    let mut flats: Vec<&str> = cal["flats"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    flats.sort();
    assert_eq!(flats, ["flat_dome_Ks_pa000.fits", "flat_dome_Ks_pa045.fits"], "{cal}");

    let reduce = |name: &str, extra: &[&str]| -> Value {
        let cat = tmp.path().join(name);
        let mut args = vec!["night", without.as_str(), "-o", cat.to_str().unwrap(), "--no-png", "-q"];
        args.extend_from_slice(extra);
        let (code, out, err) = run(&args);
        assert!(code == 0 || code == 2, "{out}\n{err}");
        serde_json::from_str(&std::fs::read_to_string(&cat).unwrap()).unwrap()
    };
    let by_calib = reduce("c1.json", &["--calib", caldir.to_str().unwrap()]);
    let prov = &by_calib["provenance"]["flat"];
    assert_eq!(prov["mode"], "file", "{prov}");
    assert_eq!(prov["from"], "calib_dir", "{prov}");
    assert_eq!(prov["flats"].as_array().unwrap().len(), 2, "{prov}");
    // Each orientation divided by the flat of its rotator angle.
    let used = by_calib["targets"][0]["flat"].as_array().unwrap();
    let text: Vec<&str> = used.iter().map(|u| u.as_str().unwrap()).collect();
    assert_eq!(text.len(), 2, "{text:?}");
    assert!(
        text.iter().any(|u| u.starts_with("POSANG 0:") && u.contains("pa000")),
        "{text:?}"
    );
    assert!(
        text.iter().any(|u| u.starts_with("POSANG 45:") && u.contains("pa045")),
        "{text:?}"
    );

    // The same two files given one by one: the same flats, the same numbers.
    let (a, b) = (caldir.join(flats[0]), caldir.join(flats[1]));
    let by_files = reduce(
        "c2.json",
        &["--flat", a.to_str().unwrap(), "--flat", b.to_str().unwrap()],
    );
    assert_eq!(by_files["provenance"]["flat"]["from"], "flat");
    assert_eq!(by_files["targets"][0]["flat"], by_calib["targets"][0]["flat"]);
    let q = |c: &Value| c["targets"][0]["components"][0]["q"].as_f64().unwrap();
    let uncal = reduce(
        "c3.json",
        &[
            "--flat",
            a.to_str().unwrap(),
            "--flat",
            b.to_str().unwrap(),
            "--calib",
            caldir.to_str().unwrap(),
        ],
    );
    assert_eq!(q(&uncal), q(&by_calib));
    // Without them the night builds a superflat of its own.
    let own = reduce("c4.json", &[]);
    assert_eq!(own["provenance"]["flat"]["mode"], "superflat");
}
