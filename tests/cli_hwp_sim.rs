//! `sofipol simulate` for a half-wave-plate profile, then `sofipol night` with that profile:
//! the simulated night reduces, and the errors the night reports match the scatter of its
//! q, u about the truth the simulator wrote (pulls pooled over seeds). The scene names its
//! profile (NIRC2's, shrunk by `profile_set` to a 128 x 200 detector so the test runs in
//! seconds); the night gets the same values by `--set`. Control: the same frames reduced
//! with the sky's rotation ignored give pulls far from 1. The frames have no cosmic rays, and
//! at most 1 % of them have pixels repaired as one (the seeing changes from frame to frame). The example scene
//! testdata/scenes/hwp_pupil.toml (the full NIRC2 detector) simulates and reduces with
//! `--profile nirc2` alone, every star within 5 sigma of its truth.
use std::path::Path;

use serde_json::Value;

mod common;
use common::{json, run};

/// The small detector of the pull test: the NIRC2 profile's values this scene overrides
/// (the focal-mask strips NIRC2 inherits from SOFI's profile are not read, but must fit).
const SETS: [&str; 17] = [
    "geometry.nx=128",
    "geometry.ny=200",
    "geometry.o_sky2=[0, 10]",
    "geometry.e_sky2=[10, 20]",
    "geometry.o_target=[20, 30]",
    "geometry.e_target=[30, 40]",
    "geometry.o_sky1=[40, 50]",
    "geometry.e_sky1=[50, 60]",
    "geometry.eo_offset_px=[-3.0, -100.0]",
    "beams.o_rows=[105, 200]",
    "beams.e_rows=[0, 95]",
    "single_pointing.aperture_px=[0.0, 9.0]",
    "single_pointing.centre_annulus_px=[1.5, 9.0]",
    "single_pointing.sky_fit_min_radius_px=25.0",
    "single_pointing.search_radius_px=4.0",
    "detector.linear_limit_adu=1e9",
    "detector.saturation_adu=2e9",
];

const SEEDS: u64 = 8;

/// Six stars of 4e6 ADU south of the zenith near the meridian (the sky turns by 0.3-3 deg
/// per frame), polarized up to 4 %, each two cycles of four plate positions; two cycles of
/// sky frames, three darks; photon and read noise, a pixel response, hot pixels, the seeing
/// changing by 5 % rms from frame to frame. (Ten times brighter stars show the flat's own
/// noise, which the reduction does not count: docs/instruments.md.)
fn scene() -> String {
    let sets = SETS.iter().map(|s| format!("\"{s}\"")).collect::<Vec<_>>().join(", ");
    let mut s = format!(
        r#"name = "hwp_pulls"
seed = 1
profile = "nirc2"
profile_set = [{sets}]
effects = ["psf", "sky", "photon_noise", "read_noise", "flat_field", "bad_pixels"]
[observation]
dit_s = 0.45
ndit = 45
overhead_s = 10.0
filter = "Lp"
date = "2025-12-08"
start_ut = "09:00:00"
[psf]
kind = "gaussian"
fwhm_arcsec = 0.047
seeing_rms_frac = 0.05
[sky]
level_adu = 5000.0
gradient_x = 0.0
gradient_y = 0.0
frame_change_frac = 0.0
[flat_field]
pixel_rms = 0.01
vignetting = 0.05
[bad_pixels]
hot_fraction = 1e-4
dead_fraction = 0.0
clusters = 0
column_segments = 0
[half_wave_plate]
sky_cycles = 2
darks = 3
sky_modulation = 0.01
header = {{ ROTPDEST = 45.7 }}
"#
    );
    for (i, (p, g, dec, ha)) in [
        (0.03, 10.0, 5.0, -0.5),
        (0.01, 50.0, -5.0, -0.3),
        (0.04, 100.0, 12.0, -0.2),
        (0.0, 0.0, 0.0, 0.0),
        (0.02, 150.0, -10.0, 0.2),
        (0.025, 75.0, 15.0, 0.4),
    ]
    .iter()
    .enumerate()
    {
        s += &format!(
            "[[half_wave_plate.star]]\nname = \"Star {i}\"\nflux = 4e6\np = {p}\ngamma_deg = {g}\ndec_deg = {dec}\nhour_angle_h = {ha}\n"
        );
    }
    s
}

/// One star's result in the night's catalog: (q, u, sigma_q, sigma_u) on the sky from the
/// least squares over the frames with the photometric errors, by target name (each
/// target's `half_wave_plate` section; the one place this test reads the catalog's layout).
fn sky_results(cat: &Value) -> Vec<(String, [f64; 4])> {
    cat["targets"]
        .as_array()
        .expect("targets")
        .iter()
        .map(|t| {
            let p = &t["half_wave_plate"]["least_squares_sky"]["pol"];
            let f = |k: &str| p[k].as_f64().unwrap_or_else(|| panic!("{k} in {t}"));
            (
                t["object"].as_str().expect("object").to_string(),
                [f("q"), f("u"), f("sigma_q_photometric"), f("sigma_u_photometric")],
            )
        })
        .collect()
}

/// The length of the list `key` of every target's `half_wave_plate` section.
fn per_target(cat: &Value, key: &str) -> Vec<usize> {
    cat["targets"]
        .as_array()
        .expect("targets")
        .iter()
        .map(|t| {
            t["half_wave_plate"][key]
                .as_array()
                .unwrap_or_else(|| panic!("{key} in {t}"))
                .len()
        })
        .collect()
}

/// Pulls (estimate - truth) / sigma of q and u of every star of the truth.
fn pulls(cat: &Value, truth: &Value) -> Vec<f64> {
    let res = sky_results(cat);
    let mut v = Vec::new();
    for st in truth["stars"].as_array().expect("stars") {
        let name = st["name"].as_str().unwrap();
        let (_, [q, u, sq, su]) = res
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("{name} not in the catalog"));
        v.push((q - st["q"].as_f64().unwrap()) / sq);
        v.push((u - st["u"].as_f64().unwrap()) / su);
    }
    v
}

/// Every frame's pixels repaired as cosmic-ray hits (o + e), with the target and file:
/// these frames have no cosmic rays.
fn repaired(cat: &Value) -> Vec<(String, String, u64)> {
    let mut v = Vec::new();
    for t in cat["targets"].as_array().expect("targets") {
        for f in t["half_wave_plate"]["frames"]
            .as_array()
            .unwrap_or_else(|| panic!("frames in {t}"))
        {
            let c = f["cosmic_ray_pixels"]
                .as_array()
                .unwrap_or_else(|| panic!("cosmic_ray_pixels in {f}"));
            let n = c.iter().map(|x| x.as_u64().expect("a count")).sum();
            v.push((t["object"].to_string(), f["file"].to_string(), n));
        }
    }
    v
}

fn night(raw: &Path, out: &Path, extra: &[&str]) -> Value {
    let mut args = vec![
        "night",
        raw.to_str().unwrap(),
        "--profile",
        "nirc2",
        "-q",
        "-o",
        out.to_str().unwrap(),
    ];
    for s in SETS.iter().chain(extra) {
        args.push("--set");
        args.push(s);
    }
    let (code, _, err) = run(&args);
    assert_eq!(code, 0, "{err}");
    json(out)
}

fn rms_mean(p: &[f64]) -> (f64, f64) {
    let n = p.len() as f64;
    (
        (p.iter().map(|x| x * x).sum::<f64>() / n).sqrt(),
        p.iter().sum::<f64>() / n,
    )
}

#[test]
fn simulated_half_wave_plate_nights_give_honest_pulls() {
    let d = tempfile::tempdir().unwrap();
    let scene_path = d.path().join("scene.toml");
    std::fs::write(&scene_path, scene()).unwrap();
    let (mut all, mut control, mut repairs) = (Vec::new(), Vec::new(), Vec::new());
    for seed in 1..=SEEDS {
        let raw = d.path().join(format!("raw{seed}"));
        let (code, out, err) = run(&[
            "simulate",
            scene_path.to_str().unwrap(),
            "-o",
            raw.to_str().unwrap(),
            "--seed",
            &seed.to_string(),
        ]);
        assert_eq!(code, 0, "{err}");
        assert!(out.contains("6 star(s)") && out.contains("48 frames"), "{out}");
        let truth = json(&raw.join("truth.json"));
        let cat = night(&raw, &d.path().join(format!("cat{seed}.json")), &[]);
        assert_eq!(per_target(&cat, "darks"), [3; 6]);
        assert_eq!(per_target(&cat, "skies"), [8; 6]);
        all.extend(pulls(&cat, &truth));
        let rep = repaired(&cat);
        assert_eq!(rep.len(), 48, "seed {seed}: frames in the catalog");
        repairs.extend(rep.into_iter().filter(|r| r.2 > 0).map(|r| (seed, r)));
        let cat = night(
            &raw,
            &d.path().join(format!("fixed{seed}.json")),
            &["field_rotation.kind=\"sky_fixed\""],
        );
        control.extend(pulls(&cat, &truth));
    }
    let (rms, mean) = rms_mean(&all);
    let n = all.len() as f64;
    eprintln!(
        "pulls over {SEEDS} seeds: N = {n}, rms {rms:.3} +- {:.3}, mean {mean:+.3} +- {:.3}",
        1.0 / (2.0 * n).sqrt(),
        1.0 / n.sqrt()
    );
    let (crms, cmean) = rms_mean(&control);
    eprintln!("control, rotation ignored: rms {crms:.2}, mean {cmean:+.2}");
    eprintln!("frames with pixels repaired as cosmic-ray hits: {}", repairs.len());
    // No cosmic rays were simulated: the seeing's changes from frame to frame are not hits.
    // Measured: one isolated pixel at 7 sigma in one of the 384 frames (unexplained; before
    // the smooth fit, 19-29 pixels per beam in several frames). At most 1 % of the frames,
    // with at most 3 pixels each.
    let frames = 48 * SEEDS as usize;
    assert!(
        repairs.len() * 100 <= frames && repairs.iter().all(|r| r.1 .2 <= 3),
        "repaired (seed, (target, file, pixels)) in {} of {frames} frames: {repairs:?}",
        repairs.len()
    );
    assert!((0.9..=1.1).contains(&rms), "pull rms {rms}");
    assert!(mean.abs() < 3.0 / n.sqrt(), "pull mean {mean}");
    assert!(crms > 3.0, "rotation ignored: rms {crms}");
}

#[test]
fn the_example_scene_reduces_with_its_profile() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("hwp");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("testdata/scenes/hwp_pupil.toml");
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", raw.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    let truth = json(&raw.join("truth.json"));
    // The truth on the sky is the scene's p, gamma (no interstellar polarization listed).
    let st = &truth["stars"][0];
    let (p, g) = (0.02, 30f64.to_radians());
    assert!((st["q"].as_f64().unwrap() - p * (2.0 * g).cos()).abs() < 1e-12);
    assert!((st["u"].as_f64().unwrap() - p * (2.0 * g).sin()).abs() < 1e-12);
    let out = d.path().join("hwp.json");
    let (code, _, err) = run(&[
        "night",
        raw.to_str().unwrap(),
        "--profile",
        "nirc2",
        "-q",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let cat = json(&out);
    let p = pulls(&cat, &truth);
    assert_eq!(p.len(), 8);
    assert!(p.iter().all(|x| x.abs() < 5.0), "{p:?}");
    // The frames' roles are the profile's: every star's 8 frames, 4 skies, 3 darks used.
    assert_eq!(per_target(&cat, "darks"), [3; 4]);
    assert_eq!(per_target(&cat, "skies"), [4; 4]);
    assert_eq!(per_target(&cat, "frames"), [8; 4]);
}
