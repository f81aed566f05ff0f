//! A night that could not be calibrated never looks fine: without standards, or with one
//! polarized standard (which cannot separate the instrument's offset c from the angle
//! zero-point), two-orientation components are flagged `uncalibrated`, none passes the
//! cut, `night`, `target` and `watch` exit 2 with the summary's first line saying so, and
//! `stats` and the report's statistics leave those binaries out and say why.
//! `--allow-uncalibrated` lets them through, flagged.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_uncalibrated` runs these tests
//! against another build.
mod common;

use std::path::{Path, PathBuf};

use common::*;
use serde_json::Value;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 2-binary night (Alpha, Beta; 2 orientations x 3 dithers) with the instrument's
/// offset and zero-point, and the standards named (`[[standard]]` tables), in `dir/night`.
fn night_with(dir: &Path, standards: &str) -> PathBuf {
    instrument_night(dir, "unc", 5, standards)
}

const ONE_POLARIZED: &str = "[[standard]]\nname = \"HD 204827\"\nflux = 150000.0\np = 0.0088\ngamma_deg = 58.7\n";

fn components(c: &Value) -> Vec<Value> {
    c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|t| t["components"].as_array().unwrap().clone())
        .collect()
}

fn flagged(c: &Value, flag: &str) -> bool {
    c["flags"].as_array().unwrap().iter().any(|f| f == flag)
}

/// `night` on `n`: exit 2, the summary's first line says UNCALIBRATED, no component
/// passes, every one flagged; then stats and the report leave the binaries out.
fn refused_everywhere(dir: &Path, n: &Path) {
    let out = dir.join("c.json");
    let (code, stdout, err) = run(&["night", s(n), "-o", s(&out), "--no-png"]);
    assert_eq!(code, 2, "{stdout}\n{err}");
    let first = stdout.lines().next().unwrap_or_default();
    assert!(first.starts_with("UNCALIBRATED: 4 component(s)"), "{stdout}");
    assert!(first.contains("none passes the cut"), "{first}");
    let c = json(&out);
    for x in components(&c) {
        assert!(flagged(&x, "uncalibrated"), "{x}");
        assert_eq!(x["passes_cut"], false, "{x}");
        // Bright enough to pass on its measurement error alone: refused for its calibration.
        let stat = x["sigma_q_stat"]
            .as_f64()
            .unwrap()
            .max(x["sigma_u_stat"].as_f64().unwrap());
        assert!(
            x["p"].as_f64().unwrap() / stat > 3.0,
            "bright enough to pass if calibrated: {x}"
        );
    }
    // No Delta-gamma offered for a binary whose components do not pass.
    for t in c["targets"].as_array().unwrap() {
        assert!(t["delta_gamma_deg"].is_null(), "{t}");
    }
    // stats: nothing to test, said so, exit 1.
    let (code, _, err) = run(&["stats", s(&out), "--pairs", "2000"]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("no binary to test: 2 of 2 target(s) have no instrumental calibration"),
        "{err}"
    );
    // The report says so at the top and in its statistics.
    let page = dir.join("p.html");
    let (code, _, err) = run(&["report", s(&out), "-o", s(&page), "--pairs", "2000", "-q"]);
    assert_eq!(code, 0, "{err}");
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(
        html.contains("<strong>UNCALIBRATED</strong>: 4 component(s)"),
        "no banner"
    );
    assert!(
        html.contains("uncalibrated: no instrumental calibration"),
        "no exclusion reason"
    );
}

#[test]
fn a_night_without_standards_is_refused_by_the_cut_the_exit_code_and_the_statistics() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with(d.path(), "");
    refused_everywhere(d.path(), &n);
    // target: the same rule.
    let out = d.path().join("alpha.json");
    let (code, stdout, err) = run(&["target", s(&n), "--object", "Alpha", "-o", s(&out)]);
    assert_eq!(code, 2, "{stdout}\n{err}");
    assert!(stdout.starts_with("UNCALIBRATED: 2 component(s)"), "{stdout}");
    // With the opt-in: they pass, flagged; exit 0; stats takes them when asked to. (This
    // scene simulates no telescope polarization: reduced as an instrument whose telescope
    // adds none, or B's 1.4 % would drown in SOFI's M3 term carried in its error.)
    let out = d.path().join("allowed.json");
    let (code, stdout, err) = run(&[
        "night",
        s(&n),
        "-o",
        s(&out),
        "--no-png",
        "--allow-uncalibrated",
        "--set",
        "telescope.polarizes=false",
    ]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(
        stdout
            .lines()
            .next()
            .unwrap()
            .contains("4 pass the cut only because of --allow-uncalibrated"),
        "{stdout}"
    );
    let c = json(&out);
    for x in components(&c) {
        assert!(flagged(&x, "uncalibrated") && x["passes_cut"] == true, "{x}");
    }
    let (code, _, err) = run(&["stats", s(&out), "--pairs", "2000"]);
    assert_eq!(code, 1, "{err}");
    let (code, stdout, err) = run(&["stats", s(&out), "--pairs", "2000", "--allow-uncalibrated"]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("sample: 2 binaries"), "{stdout}");
    assert!(
        err.contains("2 binary(ies) without an instrumental calibration taken in"),
        "{err}"
    );
}

#[test]
fn a_night_with_one_polarized_standard_is_refused_the_same_way() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with(d.path(), ONE_POLARIZED);
    refused_everywhere(d.path(), &n);
}

#[test]
fn watch_on_a_night_without_standards_exits_2_and_says_uncalibrated() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with(d.path(), "");
    let out = d.path().join("w.json");
    let (code, stdout, err) = run(&["watch", s(&n), "-o", s(&out), "--exit-when-idle", "1", "--poll", "0.2"]);
    assert_eq!(code, 2, "{stdout}\n{err}");
    assert!(stdout.contains("UNCALIBRATED: 4 component(s)"), "{stdout}");
    assert!(components(&json(&out)).iter().all(|x| x["passes_cut"] == false));
}

const TWO_UNPOLARIZED: &str = "[[standard]]\nname = \"HD 64299\"\nflux = 150000.0\n\
[[standard]]\nname = \"HD 98161\"\nflux = 150000.0\n";

/// Unpolarized standards only: c is measured, theta0 is not. The components are flagged
/// `zero_point_from_profile` and the profile's uncertainty (5 deg) is in their angle
/// errors, so the angles, 3 deg off the profile's zero-point, stay within their errors;
/// Delta-gamma does not carry it (common to both stars).
#[test]
fn a_filter_without_a_polarized_standard_carries_the_profiles_zero_point_error() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with(d.path(), TWO_UNPOLARIZED);
    let out = d.path().join("c.json");
    let (code, stdout, err) = run(&["night", s(&n), "-o", s(&out), "--no-png"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(err.contains("no polarized standard in this filter"), "{err}");
    let c = json(&out);
    let truth = [("Alpha", [20.0, 110.0]), ("Beta", [60.0, 150.0])];
    for (object, gammas) in truth {
        let t = c["targets"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["object"] == object)
            .unwrap();
        for (x, g) in t["components"].as_array().unwrap().iter().zip(gammas) {
            assert!(
                flagged(x, "zero_point_from_profile") && !flagged(x, "uncalibrated"),
                "{x}"
            );
            let (gamma, sigma) = (x["gamma_deg"].as_f64().unwrap(), x["sigma_gamma_deg"].as_f64().unwrap());
            // The zero-point's part is the profile's 5 deg (to the propagation's 2 %).
            let zp = x["sigma_gamma_zero_point_deg"].as_f64().unwrap();
            assert!((zp - 5.0).abs() < 0.1, "{object}: zero-point part {zp}");
            assert!(sigma > 4.9 && sigma < 5.5, "{object}: sigma_gamma {sigma}");
            let off = (gamma - g + 90.0).rem_euclid(180.0) - 90.0;
            assert!(
                off.abs() > 1.5 && off.abs() < sigma,
                "{object}: gamma {gamma} vs {g} +- {sigma}"
            );
            assert_eq!(x["passes_cut"], true);
        }
        // Delta-gamma's error is the stars' own, not the zero-point's.
        let sdg = t["sigma_delta_gamma_deg"].as_f64().unwrap();
        assert!(sdg < 2.0, "{object}: sigma_delta_gamma {sdg}");
    }
    let cal = &c["calibration"]["calibration"]["filters"][0];
    assert!(
        cal["zero_point_from_profile"]
            .as_str()
            .unwrap()
            .contains("theta0 = 0 +- 5 deg"),
        "{cal}"
    );
    assert_eq!(cal["covariance"][1][1], 25.0);
}
