//! End-to-end: a simulated night with bad inputs mixed in, through the `sofipol` binary.

use serde_json::Value;
use sofipol_calib::fits;

mod common;
use common::{json as catalog, run, ALPHA_BETA};

/// The simulated night's scene (Alpha and Beta from [`common::ALPHA_BETA`]).
fn scene_toml() -> String {
    format!(
        r#"
name = "it"
seed = 99
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "bad_pixels", "pointing_error"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 4
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
{ALPHA_BETA}[[binary]]
name = "Gamma"
separation_arcsec = 2.5
pa_deg = 300.0
flux_a = 90000.0
flux_b = 50000.0
p_a = 0.04
gamma_a_deg = 170.0
p_b = 0.02
gamma_b_deg = 80.0
"#
    )
}

fn without_time(mut v: Value) -> Value {
    v["provenance"]["created_utc"] = Value::Null;
    v["provenance"]["command_line"] = Value::Null;
    v
}

#[test]
fn a_night_with_bad_inputs_reduces_every_good_target_and_names_every_bad_file() {
    let dir = tempfile::tempdir().unwrap();
    let night = dir.path().join("night");
    let scene = dir.path().join("scene.toml");
    std::fs::write(&scene, scene_toml()).unwrap();
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", night.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(night.join("truth.json")).unwrap();
    // Damage: a truncated copy, a text file, a flat from another template, a frame missing
    // POSANG, and one dither of Beta removed.
    let good = night.join("SOFI_it_Alpha_01.fits");
    let bytes = std::fs::read(&good).unwrap();
    std::fs::create_dir(night.join("sub")).unwrap();
    std::fs::write(night.join("sub/truncated.fits"), &bytes[..bytes.len() / 3]).unwrap();
    std::fs::write(night.join("notes.fits"), "observing log: clouds at 3 UT\n").unwrap();
    let mut flat = fits::read_frame(&good).unwrap();
    flat.header.set("ESO TPL ID", "SOFI_img_cal_SkyFlats");
    flat.header.set("ESO DPR TYPE", "FLAT");
    flat.header.set("ESO DPR TECH", "IMAGE");
    fits::write_frame(&night.join("flat_0001.fits"), &flat, &Default::default()).unwrap();
    let mut nokey = fits::read_frame(&good).unwrap();
    nokey.header.cards.retain(|c| c.key != "ESO ADA POSANG");
    nokey.header.set("ESO TPL START", "1999-03-03T05:00:00");
    fits::write_frame(&night.join("nokey.fits"), &nokey, &Default::default()).unwrap();
    std::fs::remove_file(night.join("SOFI_it_Beta_07.fits")).unwrap();

    let out1 = dir.path().join("cat1.json");
    let (code, stdout, err) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        out1.to_str().unwrap(),
        "--jobs",
        "2",
    ]);
    assert_eq!(code, 2, "exit code for a night with failures\n{stdout}\n{err}");
    let c = catalog(&out1);
    let targets = c["targets"].as_array().unwrap();
    let names: Vec<&str> = targets.iter().map(|t| t["object"].as_str().unwrap()).collect();
    assert_eq!(names.len(), 3, "{names:?}");
    for t in targets {
        let obj = t["object"].as_str().unwrap();
        let status = t["status"].as_str().unwrap();
        if obj == "Beta" {
            assert_eq!(status, "partial", "{t}");
            assert!(
                t["error"].as_str().unwrap().contains("unequal") || t["error"].as_str().unwrap().contains("of 8"),
                "{t}"
            );
        } else {
            assert_eq!(status, "ok", "{obj}: {t}");
        }
        assert_eq!(t["components"].as_array().unwrap().len(), 2, "{obj}");
        for comp in t["components"].as_array().unwrap() {
            assert!(comp["q"].as_f64().unwrap().is_finite());
        }
    }
    let fails = c["failures"].as_array().unwrap();
    let find = |name: &str| {
        fails
            .iter()
            .find(|f| f["file"].as_str().unwrap().ends_with(name))
            .map(|f| f["error"].as_str().unwrap().to_string())
    };
    assert!(find("truncated.fits").is_some(), "{fails:?}");
    assert!(find("notes.fits").is_some(), "{fails:?}");
    assert!(
        find("flat_0001.fits").unwrap().contains("SOFI_img_cal_SkyFlats")
            || find("flat_0001.fits").unwrap().contains("FLAT"),
        "{fails:?}"
    );
    assert!(find("nokey.fits").unwrap().contains("ESO ADA POSANG"), "{fails:?}");
    assert_eq!(fails.len(), 4, "{fails:?}");
    assert!(
        stdout.contains("Alpha") && stdout.contains("truncated.fits"),
        "{stdout}"
    );
    // The summary says which P is which: P not debiased, Pdb debiased (as `demo`).
    let head = stdout.lines().find(|l| l.starts_with("object")).unwrap();
    assert!(head.contains(" P [%]") && head.contains("Pdb [%]"), "{head}");
    let alpha = &targets.iter().find(|t| t["object"] == "Alpha").unwrap()["components"][0];
    let row = stdout.lines().find(|l| l.starts_with("Alpha ")).unwrap();
    for key in ["p", "p_debiased"] {
        let v = format!("{:.3}", 100.0 * alpha[key].as_f64().unwrap());
        assert!(row.split_whitespace().any(|w| w == v), "{key} {v} not in {row}");
    }

    // The night log beside the catalog: one line per file of the folder, used or not,
    // with its outcome and what it was used for or why not.
    assert!(
        stdout.contains(&format!("night log: {}", dir.path().join("cat1.log").display())),
        "{stdout}"
    );
    let log = std::fs::read_to_string(dir.path().join("cat1.log")).unwrap();
    // The frames' table (the frame-quality table after it names the science frames again).
    let frames_table = log.split("\n## ").find(|s| s.starts_with("Frames:")).unwrap();
    let files: Vec<String> = walk(&night);
    assert_eq!(files.len(), 27, "{files:?}");
    for f in &files {
        let rel = f.strip_prefix(&format!("{}/", night.display())).unwrap();
        let lines: Vec<&str> = frames_table
            .lines()
            .filter(|l| l.split_whitespace().next() == Some(rel))
            .collect();
        assert_eq!(lines.len(), 1, "{rel}: {lines:?}\n{log}");
        let l = lines[0];
        let (outcome, why) = match rel {
            // Its header groups it with Alpha's frames; its data cannot be read.
            "sub/truncated.fits" => ("dropped", find(rel).unwrap()),
            "notes.fits" | "nokey.fits" => ("not used", find(rel).unwrap()),
            "flat_0001.fits" => ("not used", find(rel).unwrap()),
            _ => ("used", String::new()),
        };
        assert!(l.contains(&format!("  {outcome} ")), "{l}");
        assert!(l.contains(why.split_whitespace().next().unwrap_or("")), "{l} / {why}");
        if rel.starts_with("SOFI_it_Alpha") || rel == "sub/truncated.fits" {
            assert!(l.contains("target Alpha"), "{l}");
        }
        if rel.starts_with("SOFI_it_Beta") {
            assert!(l.contains("target Beta"), "{l}");
        }
    }
    assert!(log.contains("## Targets: 3"), "{log}");

    // Same inputs, one thread: identical catalog (timestamps aside).
    let out2 = dir.path().join("cat2.json");
    let (code, _, _) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        out2.to_str().unwrap(),
        "--jobs",
        "1",
        "-q",
        "--no-png",
    ]);
    assert_eq!(code, 2);
    assert_eq!(without_time(catalog(&out1)), without_time(catalog(&out2)));

    // Shards 1/2 and 2/2 merged hold the same targets and failures as the whole night.
    let s1 = dir.path().join("s1.json");
    let s2 = dir.path().join("s2.json");
    let (code1, _, err1) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        s1.to_str().unwrap(),
        "--shard",
        "1/2",
        "-q",
        "--no-png",
    ]);
    let (code2, _, err2) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        s2.to_str().unwrap(),
        "--shard",
        "2/2",
        "-q",
        "--no-png",
    ]);
    // Each shard reports what it saw: the damaged files and the partial Beta fall into
    // some shard, so at least one exits 2, and neither fails outright.
    assert!([0, 2].contains(&code1) && [0, 2].contains(&code2), "{err1}\n{err2}");
    assert!(code1 == 2 || code2 == 2, "{err1}\n{err2}");
    let merged = dir.path().join("merged.json");
    let (code, _, err) = run(&[
        "merge",
        s1.to_str().unwrap(),
        s2.to_str().unwrap(),
        "-o",
        merged.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let m = catalog(&merged);
    assert_eq!(m["targets"], c["targets"]);
    assert_eq!(m["failures"], c["failures"]);
}

/// Every file under `dir`, recursively, as paths.
fn walk(dir: &std::path::Path) -> Vec<String> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p.display().to_string());
        }
    }
    out
}

#[test]
fn usage_errors_exit_1_and_name_the_problem() {
    let (code, _, err) = run(&["night", "/nonexistent/night", "-o", "/tmp/x.json"]);
    assert_eq!(code, 1);
    assert!(err.contains("/nonexistent/night"), "{err}");
    let (code, _, err) = run(&["night", "/tmp", "--shard", "3/2"]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("3/2"), "{err}");
}
