//! No uncorrected q, u passes the cut unnoticed: a chosen Stokes method that cannot apply
//! to two orientations, an absurd or unreadable `calibration.json`, a `--calib` without an
//! offset for the night's filter.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_uncorrected` runs these tests against
//! another build (how they were checked to fail before the fix).
use std::path::{Path, PathBuf};

use serde_json::Value;

mod common;
use common::{json as catalog, run, ALPHA_BETA};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The effects of a night whose instrument needs calibrating: beam ratio 0.97, 0.3 % of
/// instrumental polarization, an angle zero-point of 3 deg (offset c ~ 1.8 %).
const INSTRUMENT: &str = r#"effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "throughput",
           "instrumental_polarization", "analyzer_angle"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[throughput]
t_o = 1.0
t_e = 0.97
[instrumental_polarization]
p = 0.003
angle_deg = 0.0
[analyzer_angle]
zero_point_deg = 3.0
parity = 1
"#;

/// The standards of the built-in table the demo night observes.
const STANDARDS: &str = r#"[[standard]]
name = "HD 64299"
flux = 200000.0
[[standard]]
name = "HD 98161"
flux = 200000.0
[[standard]]
name = "HD 204827"
flux = 200000.0
p = 0.0088
gamma_deg = 58.7
"#;

/// Alpha and Beta on 2 orientations x 3 dithers, with the standards or without, in
/// `dir/name`.
fn night(dir: &Path, name: &str, standards: bool) -> PathBuf {
    let scene = dir.join(format!("{name}.toml"));
    let std = if standards { STANDARDS } else { "" };
    std::fs::write(
        &scene,
        format!("name = \"{name}\"\nseed = 5\n{INSTRUMENT}{std}{ALPHA_BETA}"),
    )
    .unwrap();
    let n = dir.join(name);
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    n
}

fn components(c: &Value) -> Vec<&Value> {
    c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|t| t["components"].as_array().unwrap())
        .collect()
}

fn flags(comp: &Value) -> Vec<&str> {
    comp["flags"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect()
}

/// `--stokes-method ratio | difference | free_offset` on two orientations cannot apply.
/// Without standards the fallback corrects nothing: flagged `... (uncalibrated)`, no
/// component passes the cut. With the night's standards the fallback subtracts their
/// offset: the numbers are those of `--stokes-method auto`, bit for bit, flagged.
#[test]
fn a_stokes_method_that_cannot_apply_never_lets_an_uncorrected_value_pass() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let bare = night(d, "bare", false);
    let with_std = night(d, "std", true);
    let reduce = |n: &Path, method: &str| {
        let out = d.join(format!("{}_{method}.json", n.file_name().unwrap().to_str().unwrap()));
        let (code, _, err) = run(&[
            "night",
            s(n),
            "-o",
            s(&out),
            "-q",
            "--no-png",
            "--stokes-method",
            method,
        ]);
        assert!(code == 0 || code == 2, "{method}: {err}");
        catalog(&out)
    };
    let auto = reduce(&with_std, "auto");
    let auto_comps = components(&auto);
    assert_eq!(auto_comps.len(), 4);
    assert!(auto_comps.iter().all(|c| c["passes_cut"] == true), "{auto}");
    for method in ["ratio", "difference", "free_offset"] {
        let c = reduce(&bare, method);
        let comps = components(&c);
        assert_eq!(comps.len(), 4, "{method}");
        for comp in &comps {
            let f = flags(comp);
            assert_eq!(comp["passes_cut"], false, "{method}: {comp}");
            assert!(
                f.iter()
                    .any(|f| f.starts_with("stokes_method_failed") && f.ends_with("(uncalibrated)")),
                "{method}: {f:?}"
            );
        }
        let c = reduce(&with_std, method);
        for (comp, a) in components(&c).iter().zip(&auto_comps) {
            assert_eq!((&comp["q"], &comp["u"]), (&a["q"], &a["u"]), "{method}");
            assert_eq!(comp["passes_cut"], a["passes_cut"], "{method}");
            assert!(
                flags(comp)
                    .iter()
                    .any(|f| f.starts_with("stokes_method_failed") && f.ends_with("fell back to least_squares")),
                "{method}: {comp}"
            );
        }
    }
}

/// A `calibration.json` (from `sofipol calib` on the night with standards) damaged one
/// way at a time: each is refused before any reduction (exit 1, no catalog), naming the
/// file and the key or the parse error. One without an offset for the night's filter
/// (another filter, no filters, offset and angles null) corrects nothing: the file is
/// named under `failures` (exit 2), every component is flagged `uncalibrated` and
/// `calibration_lacks_filter: ...`, and none passes the cut (they used to pass, exit 0).
#[test]
fn an_absurd_or_foreign_calibration_file_never_lets_an_uncorrected_value_pass() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let with_std = night(d, "std", true);
    let bare = night(d, "bare", false);
    let caldir = d.join("cal");
    let (code, _, err) = run(&["calib", s(&with_std), "-o", s(&caldir), "-q"]);
    assert_eq!(code, 0, "{err}");
    let text = std::fs::read_to_string(caldir.join("calibration.json")).unwrap();
    let good: Value = serde_json::from_str(&text).unwrap();
    let theta0 = good["filters"][0]["angles"]["theta0_deg"].to_string();
    let edit = |f: &dyn Fn(&mut Value)| {
        let mut v = good.clone();
        f(&mut v);
        serde_json::to_string_pretty(&v).unwrap()
    };
    let absurd: Vec<(&str, String, &str)> = vec![
        (
            "c5",
            edit(&|v| v["filters"][0]["offset"]["c"] = 5.0.into()),
            "filters[0].offset.c = 5",
        ),
        (
            "theta0_nan",
            text.replace(&format!("\"theta0_deg\": {theta0}"), "\"theta0_deg\": NaN"),
            "line",
        ),
        (
            "theta0_null",
            edit(&|v| v["filters"][0]["angles"]["theta0_deg"] = Value::Null),
            "filters[0].angles.theta0_deg = NaN",
        ),
        (
            "sigma_c_negative",
            edit(&|v| v["filters"][0]["offset"]["sigma_c"] = (-0.001).into()),
            "filters[0].offset.sigma_c = -0.001",
        ),
        (
            "sigma_theta0_negative",
            edit(&|v| v["filters"][0]["angles"]["sigma_theta0_deg"] = (-2.0).into()),
            "filters[0].angles.sigma_theta0_deg = -2",
        ),
        (
            "c_string",
            edit(&|v| v["filters"][0]["offset"]["c"] = "0.0186".into()),
            "invalid type: string",
        ),
        (
            "parity_0",
            edit(&|v| v["filters"][0]["angles"]["parity"] = 0.into()),
            "parity = 0",
        ),
        (
            "filters_object",
            edit(&|v| v["filters"] = serde_json::json!({})),
            "invalid type: map",
        ),
        ("empty", String::new(), "EOF"),
    ];
    for (name, body, want) in absurd {
        let cd = d.join(name);
        std::fs::create_dir(&cd).unwrap();
        std::fs::write(cd.join("calibration.json"), body).unwrap();
        let out = d.join(format!("{name}.json"));
        let (code, _, err) = run(&["night", s(&bare), "-o", s(&out), "-q", "--no-png", "--calib", s(&cd)]);
        assert_eq!(code, 1, "{name}: {err}");
        assert!(
            err.contains(&format!("{name}/calibration.json")) && err.contains(want),
            "{name}: {err}"
        );
        assert!(!out.exists(), "{name}");
    }

    let foreign: Vec<(&str, String)> = vec![
        ("filter_j", edit(&|v| v["filters"][0]["filter"] = "J".into())),
        ("no_filters", edit(&|v| v["filters"] = serde_json::json!([]))),
        (
            "nothing_measured",
            edit(&|v| {
                let f = v["filters"][0].as_object_mut().unwrap();
                f.insert("offset".into(), Value::Null);
                f.insert("angles".into(), Value::Null);
                f.remove("cov_c_theta0_deg");
            }),
        ),
    ];
    for (name, body) in foreign {
        let cd = d.join(name);
        std::fs::create_dir(&cd).unwrap();
        std::fs::write(cd.join("calibration.json"), body).unwrap();
        let out = d.join(format!("{name}.json"));
        let (code, _, err) = run(&["night", s(&bare), "-o", s(&out), "-q", "--no-png", "--calib", s(&cd)]);
        assert_eq!(code, 2, "{name}: {err}");
        let c = catalog(&out);
        let comps = components(&c);
        assert_eq!(comps.len(), 4, "{name}");
        for comp in comps {
            let f = flags(comp);
            assert_eq!(comp["passes_cut"], false, "{name}: {comp}");
            assert!(f.contains(&"uncalibrated"), "{name}: {f:?}");
            assert!(
                f.iter()
                    .any(|f| f.starts_with("calibration_lacks_filter: ") && f.contains("Ks")),
                "{name}: {f:?}"
            );
        }
        for t in c["targets"].as_array().unwrap() {
            assert!(t["delta_gamma_deg"].is_null(), "{name}: {t}");
        }
        let fl = c["failures"].as_array().unwrap();
        assert!(
            fl.iter().any(|f| f["file"]
                .as_str()
                .unwrap()
                .ends_with(&format!("{name}/calibration.json"))
                && f["error"].as_str().unwrap().contains("no offset")),
            "{name}: {fl:?}"
        );
    }
}
