//! The target is the binary at the pointing, not the brightest star of the strip: a night
//! whose targets each have a saturated field star, far brighter than the binary, in the
//! target's strip is reduced like the same night without those stars.
//!
//! Both nights are simulated from one scene (the same seed: the same noise in every pixel
//! the field stars do not touch) and reduced by `sofipol night`; each binary must come out
//! with the same status, the same dithers used and q, u within a small fraction of their
//! errors, and the night with the stars must name each brighter star (separation and PA
//! from the target) in the catalog and in the night log.

use serde_json::Value;

mod common;
use common::{json, run};

/// A binary of the scene and the saturated field star placed in its strip.
struct Case {
    name: &'static str,
    sep_arcsec: f64,
    pa_deg: f64,
    fluxes: (f64, f64),
    star_sep_arcsec: f64,
    star_pa_deg: f64,
}

/// The field star's flux, ADU: about 0.04 of it falls on the brightest pixel of each beam at
/// 0.8" seeing, 4-5 times the profile's 37 000 ADU saturation; 30-40 times the binaries'
/// primaries (3.7-4 mag brighter).
const STAR_FLUX: f64 = 4.0e6;

/// Every place of the bright star that misled the reduction before the pointing was used:
/// 127" away along the strip (out of the frame in some dithers), 30" and 20" away (just
/// beyond the 60 px = 17" primary search), and one jitter step (86.8 px = 25") along the
/// dithers, where each dither puts the star on the binary's position of the previous one.
const CASES: [Case; 4] = [
    Case {
        name: "Far",
        sep_arcsec: 3.0,
        pa_deg: 40.0,
        fluxes: (120000.0, 60000.0),
        star_sep_arcsec: 127.0,
        star_pa_deg: 90.0,
    },
    Case {
        name: "Near",
        sep_arcsec: 2.5,
        pa_deg: 200.0,
        fluxes: (100000.0, 70000.0),
        star_sep_arcsec: 30.0,
        star_pa_deg: 100.0,
    },
    Case {
        name: "Closer",
        sep_arcsec: 4.0,
        pa_deg: 300.0,
        fluxes: (90000.0, 50000.0),
        star_sep_arcsec: 20.0,
        star_pa_deg: 250.0,
    },
    Case {
        name: "Dither",
        sep_arcsec: 3.5,
        pa_deg: 120.0,
        fluxes: (110000.0, 80000.0),
        star_sep_arcsec: 86.8 * 0.288,
        star_pa_deg: 270.0,
    },
];

/// The scene, with or without the field stars. Saturation is listed: the simulator clips
/// every pixel at the profile's level, and the reduction masks pixels at or above it.
fn scene(with_stars: bool) -> String {
    let mut s = String::from(
        r#"name = "fs"
seed = 7
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "saturation", "pointing_error"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 5
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
"#,
    );
    for (i, c) in CASES.iter().enumerate() {
        s += &format!(
            "[[binary]]\nname = \"{}\"\nseparation_arcsec = {}\npa_deg = {}\nflux_a = {}\nflux_b = {}\n\
             p_a = {}\ngamma_a_deg = {}\np_b = {}\ngamma_b_deg = {}\n",
            c.name,
            c.sep_arcsec,
            c.pa_deg,
            c.fluxes.0,
            c.fluxes.1,
            0.03 + 0.01 * i as f64,
            20.0 + 40.0 * i as f64,
            0.05 - 0.01 * i as f64,
            110.0 + 25.0 * i as f64,
        );
        if with_stars {
            s += &format!(
                "[[binary.field_star]]\nseparation_arcsec = {}\npa_deg = {}\nflux = {STAR_FLUX}\n",
                c.star_sep_arcsec, c.star_pa_deg
            );
        }
    }
    s
}

/// Simulate and reduce one night: (exit code of `night`, catalog, night log).
fn reduce(dir: &std::path::Path, with_stars: bool) -> (i32, Value, String) {
    let tag = if with_stars { "with" } else { "without" };
    let scene_path = dir.join(format!("{tag}.toml"));
    std::fs::write(&scene_path, scene(with_stars)).unwrap();
    let night = dir.join(tag);
    let (code, _, err) = run(&[
        "simulate",
        scene_path.to_str().unwrap(),
        "-o",
        night.to_str().unwrap(),
        "-q",
    ]);
    assert_eq!(code, 0, "simulate {tag}: {err}");
    let out = dir.join(format!("{tag}.json"));
    let (code, stdout, err) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--jobs",
        "2",
    ]);
    let log = std::fs::read_to_string(out.with_extension("log")).unwrap_or_else(|e| panic!("night log: {e}\n{err}"));
    assert!(code == 0 || code == 2, "night {tag}: exit {code}\n{stdout}\n{err}");
    (code, json(&out), log)
}

fn target<'a>(c: &'a Value, name: &str) -> &'a Value {
    c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == name)
        .unwrap_or_else(|| panic!("no target {name}"))
}

fn flags(v: &Value) -> Vec<String> {
    v["flags"]
        .as_array()
        .map(|a| a.iter().map(|f| f.as_str().unwrap().to_string()).collect())
        .unwrap_or_default()
}

/// The frames a component left out, by file name (without the night's folder).
fn dropped(comp: &Value) -> Vec<String> {
    comp["dropped_dithers"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|d| {
                    let f = d["file"].as_str().unwrap();
                    format!("{} {}", f.rsplit('/').next().unwrap(), d["reason"])
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Separation (") and PA (deg) of the brighter source, read from its flag.
fn sep_pa(flag: &str) -> (f64, f64) {
    let rest = flag.strip_prefix("brighter_source_in_strip: ").unwrap();
    let sep: f64 = rest.split('"').next().unwrap().parse().unwrap();
    let pa: f64 = rest
        .split("at PA ")
        .nth(1)
        .unwrap()
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    (sep, pa)
}

#[test]
fn a_saturated_field_star_brighter_than_the_binary_does_not_take_its_place() {
    let dir = tempfile::tempdir().unwrap();
    let (code_with, with, log) = reduce(dir.path(), true);
    let (code_without, without, log_without) = reduce(dir.path(), false);
    assert_eq!(code_with, code_without, "exit codes");
    for c in &CASES {
        let (tw, t0) = (target(&with, c.name), target(&without, c.name));
        assert_eq!(t0["status"], "ok", "{}: the night without the star: {t0}", c.name);
        assert_eq!(tw["status"], "ok", "{}: {}", c.name, tw["error"]);
        // The same target flags, plus the one naming the brighter star.
        let (fw, f0) = (flags(tw), flags(t0));
        let brighter: Vec<&String> = fw
            .iter()
            .filter(|f| f.starts_with("brighter_source_in_strip"))
            .collect();
        assert_eq!(brighter.len(), 1, "{}: {fw:?}", c.name);
        // The foreground's flag counts the field stars, the bright one among them: apart.
        let fg = |f: &&String| f.starts_with("foreground_too_few_field_stars");
        let rest: Vec<&String> = fw
            .iter()
            .filter(|f| !f.starts_with("brighter_source_in_strip") && !fg(f))
            .collect();
        assert_eq!(
            rest,
            f0.iter().filter(|f| !fg(f)).collect::<Vec<_>>(),
            "{}: target flags",
            c.name
        );
        assert!(!f0.iter().any(|f| f.starts_with("brighter_source_in_strip")), "{f0:?}");
        // The star is where the scene put it, from the target (A or the blend of the pair:
        // within the pair's separation of A).
        let (sep, pa) = sep_pa(brighter[0]);
        let slack = c.sep_arcsec + 1.0;
        assert!(
            (sep - c.star_sep_arcsec).abs() <= slack,
            "{}: {sep}\" for {}\"",
            c.name,
            c.star_sep_arcsec
        );
        let dpa = ((pa - c.star_pa_deg + 180.0).rem_euclid(360.0) - 180.0).abs();
        assert!(
            dpa <= (slack / c.star_sep_arcsec).asin().to_degrees(),
            "{}: PA {pa} for {}",
            c.name,
            c.star_pa_deg
        );
        // Both components measured as without the star: the same dithers used, the same
        // flags, q and u within a small fraction of their errors.
        let (cw, c0) = (
            tw["components"].as_array().unwrap(),
            t0["components"].as_array().unwrap(),
        );
        assert_eq!(cw.len(), 2, "{}: {tw}", c.name);
        assert_eq!(c0.len(), 2, "{}: {t0}", c.name);
        for (a, b) in cw.iter().zip(c0) {
            let who = format!("{} {}", c.name, b["name"]);
            assert_eq!(a["name"], b["name"], "{who}");
            assert_eq!(dropped(a), dropped(b), "{who}: dithers left out");
            assert_eq!(flags(a), flags(b), "{who}: flags");
            for (k, s) in [("q", "sigma_q"), ("u", "sigma_u")] {
                let (x, y, sig) = (a[k].as_f64().unwrap(), b[k].as_f64().unwrap(), b[s].as_f64().unwrap());
                assert!(
                    (x - y).abs() <= 0.1 * sig,
                    "{who}: {k} = {x} with the star, {y} without (sigma {sig}): {:.2} sigma",
                    (x - y) / sig
                );
                let rel = a[s].as_f64().unwrap() / sig;
                assert!((rel - 1.0).abs() <= 0.05, "{who}: {s} {rel} times");
            }
        }
        // The night log says it, in words, under this target.
        let block: Vec<&str> = log
            .lines()
            .skip_while(|l| !(l.starts_with(&format!("{} [", c.name)) || l.starts_with(&format!("{}:", c.name))))
            .skip(1)
            .take_while(|l| l.starts_with("  "))
            .collect();
        let why = sofipol_pipeline::catalog::FlagCode::BrighterSourceInStrip.explanation();
        assert!(
            block.iter().any(|l| l.contains("brighter_source_in_strip --")
                && l.contains(why)
                && l.contains(&format!("{sep:.1}\""))),
            "{}: the night log's lines of the target:\n{}",
            c.name,
            block.join("\n")
        );
    }
    assert!(!log_without.contains("brighter_source_in_strip"), "{log_without}");
    // Nothing dropped, nothing failed: every frame of both nights used.
    for c in [&with, &without] {
        assert_eq!(c["failures"].as_array().map_or(0, |f| f.len()), 0, "{}", c["failures"]);
    }
}
