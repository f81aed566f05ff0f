//! Every point source of a target's field, measured like the binary's components.
//!
//! Simulated nights (the night's standards included, so the calibration runs) whose
//! targets have several field stars of known flux, p and gamma, among them a saturated one,
//! one at the o strip's edge at one orientation and a blended pair, are reduced by
//! `sofipol night`:
//! - the usable field stars' q and u pulls (measured - truth)/sigma, pooled over 8 seeds,
//!   have a mean within 4 standard errors of 0 and an rms in [0.9, 1.1];
//! - the saturated, edge and blended stars are flagged with that reason and not usable;
//!   no field star sits on the binary's components; every field star is within 1 px of
//!   its truth on the detector and on the sky; every export carries them;
//! - a night without field stars gives the same components' numbers as with field-star
//!   measurement switched off (`--param measure.field_stars=false`).

use serde_json::Value;

mod common;
use common::{json, run};

/// Pixel scale of the SOFI profile, arcsec per px.
const SCALE: f64 = 0.288;

/// A field star of the scene: separation ("), PA (deg), flux (ADU), p, gamma (deg).
type Star = (f64, f64, f64, f64, f64);

/// Stars every target has: polarized and unpolarized, bright and faint, within 20" of A
/// (inside the strip at both orientations).
const COMMON: [Star; 5] = [
    (15.0, 60.0, 60000.0, 0.03, 20.0),
    (12.0, 200.0, 25000.0, 0.0, 0.0),
    (18.0, 300.0, 12000.0, 0.05, 120.0),
    (10.0, 110.0, 40000.0, 0.02, 75.0),
    (16.0, 250.0, 30000.0, 0.04, 160.0),
];

/// The first target's special stars: saturated, at the o strip's upper edge at POSANG 0
/// (78 px from A along +y), and a blended pair 1.8" apart (2.2 FWHM at 0.8").
const SATURATED: Star = (11.0, 150.0, 4.0e6, 0.0, 0.0);
const EDGE: Star = (22.5, 0.0, 50000.0, 0.0, 0.0);
const BLEND_1: Star = (14.0, 330.0, 30000.0, 0.0, 0.0);
const BLEND_2: Star = (14.0, 337.37, 20000.0, 0.0, 0.0);

fn star_toml((sep, pa, flux, p, gamma): Star) -> String {
    format!(
        "[[binary.field_star]]\nseparation_arcsec = {sep}\npa_deg = {pa}\nflux = {flux}\np = {p}\ngamma_deg = {gamma}\n"
    )
}

/// The stars of target `t` (0-based) of the scene, in the simulator's order (field1...).
fn stars_of(t: usize) -> Vec<Star> {
    let mut v: Vec<Star> = COMMON.to_vec();
    if t == 0 {
        v.extend([SATURATED, EDGE, BLEND_1, BLEND_2]);
    }
    v
}

/// A night of 3 binaries and 3 standards (two unpolarized, one polarized), with or without
/// field stars.
fn scene(seed: u64, with_stars: bool) -> String {
    let mut s = format!(
        r#"name = "field"
seed = {seed}
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "saturation"]
[observation]
dithers = 5
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
"#
    );
    for t in 0..3 {
        s += &format!(
            "[[binary]]\nname = \"T{t}\"\nseparation_arcsec = {}\npa_deg = {}\nflux_a = 120000.0\nflux_b = 60000.0\n\
             p_a = 0.03\ngamma_a_deg = {}\np_b = 0.02\ngamma_b_deg = {}\n",
            3.0 + t as f64,
            40.0 + 100.0 * t as f64,
            20.0 + 50.0 * t as f64,
            100.0 + 20.0 * t as f64,
        );
        if with_stars {
            for st in stars_of(t) {
                s += &star_toml(st);
            }
        }
    }
    s += r#"
[[standard]]
name = "HD 64299"
flux = 300000.0
[[standard]]
name = "HD 98161"
flux = 300000.0
[[standard]]
name = "HD 204827"
flux = 300000.0
p = 0.0088
gamma_deg = 58.7
"#;
    s
}

/// Simulate and reduce one night: (catalog, truth, catalog path).
fn night(dir: &std::path::Path, tag: &str, seed: u64, with_stars: bool, extra: &[&str]) -> (Value, Value, std::path::PathBuf) {
    let scene_path = dir.join(format!("{tag}.toml"));
    std::fs::write(&scene_path, scene(seed, with_stars)).unwrap();
    let raw = dir.join(format!("{tag}_raw"));
    if !raw.join("truth.json").exists() {
        let (code, _, err) = run(&["simulate", scene_path.to_str().unwrap(), "-o", raw.to_str().unwrap(), "-q"]);
        assert_eq!(code, 0, "simulate {tag}: {err}");
    }
    let out = dir.join(format!("{tag}.json"));
    let mut args = vec!["night", raw.to_str().unwrap(), "-o", out.to_str().unwrap(), "--jobs", "2"];
    args.extend_from_slice(extra);
    let (code, stdout, err) = run(&args);
    assert!(code == 0 || code == 2, "night {tag}: exit {code}\n{stdout}\n{err}");
    (json(&out), json(&raw.join("truth.json")), out)
}

fn target<'a>(c: &'a Value, name: &str) -> &'a Value {
    c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == name)
        .unwrap_or_else(|| panic!("no target {name}"))
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

fn flag_names(v: &Value) -> Vec<String> {
    v["flags"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|f| f.as_str().unwrap().split(':').next().unwrap().to_string())
                .collect()
        })
        .unwrap_or_default()
}

/// East, north offsets (arcsec) of a separation and PA.
fn en(sep: f64, pa: f64) -> (f64, f64) {
    let r = pa.to_radians();
    (sep * r.sin(), sep * r.cos())
}

/// The catalog's field star nearest the truth's `st` on the sky (by separation and PA
/// from A), within 1.5".
fn matched<'a>(fs: &'a [Value], st: Star) -> Option<&'a Value> {
    let want = en(st.0, st.1);
    fs.iter()
        .map(|f| {
            let e = en(num(&f["separation_arcsec"]), num(&f["pa_deg"]));
            (f, (e.0 - want.0).hypot(e.1 - want.1))
        })
        .filter(|(_, d)| *d < 1.5)
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(f, _)| f)
}

/// Great-circle distance, arcsec.
fn sky_distance_arcsec(ra1: f64, dec1: f64, ra2: f64, dec2: f64) -> f64 {
    let (d1, d2) = (dec1.to_radians(), dec2.to_radians());
    let c = d1.sin() * d2.sin() + d1.cos() * d2.cos() * (ra1 - ra2).to_radians().cos();
    c.clamp(-1.0, 1.0).acos().to_degrees() * 3600.0
}

/// The sky position `sep` (") at `pa` (deg) from (ra, dec): the great circle's destination.
fn offset(ra: f64, dec: f64, sep: f64, pa: f64) -> (f64, f64) {
    let (d0, r, p) = (dec.to_radians(), (sep / 3600.0).to_radians(), pa.to_radians());
    let d1 = (d0.sin() * r.cos() + d0.cos() * r.sin() * p.cos()).asin();
    let dra = (p.sin() * r.sin() * d0.cos()).atan2(r.cos() - d0.sin() * d1.sin());
    ((ra + dra.to_degrees()).rem_euclid(360.0), d1.to_degrees())
}

/// Pulls of the usable field stars of 8 nights pooled; flags, positions and exports on
/// the first night.
#[test]
fn field_stars_are_measured_like_components_with_honest_errors_flags_and_positions() {
    let dir = tempfile::tempdir().unwrap();
    let mut pulls: Vec<f64> = Vec::new();
    let mut n_usable = 0;
    for seed in 1..=8u64 {
        let (cat, truth, path) = night(dir.path(), &format!("s{seed}"), seed, true, &[]);
        assert!(cat["calibration"]["calibration"].is_object(), "seed {seed}: the night has no calibration");
        for t in 0..3 {
            let tg = target(&cat, &format!("T{t}"));
            let fs = tg["field_stars"]
                .as_array()
                .unwrap_or_else(|| panic!("seed {seed} T{t}: no field_stars"));
            let truth_t = truth["targets"]
                .as_array()
                .unwrap()
                .iter()
                .find(|x| x["object"] == format!("T{t}"))
                .unwrap();
            let (ra0, dec0) = (num(&tg["ra_deg"]), num(&tg["dec_deg"]));
            // The binary's own images are never field stars.
            let sep_b = num(&tg["separation_arcsec"]);
            for f in fs {
                let s = num(&f["separation_arcsec"]);
                assert!(s > 2.0 && (s - sep_b).abs() > 0.5 || s > sep_b + 2.0, "seed {seed} T{t}: field star on the binary: {f}");
            }
            for (i, st) in stars_of(t).into_iter().enumerate() {
                let name = format!("field{}", i + 1);
                let f = matched(fs, st).unwrap_or_else(|| panic!("seed {seed} T{t}: {name} {st:?} not found among {fs:#?}"));
                // Detector position: the o image in the first frame, within 1 px.
                let src = truth_t["frames"][0]["sources"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .find(|s| s["name"] == name)
                    .unwrap();
                let (tx, ty) = (num(&src["o_xy"][0]), num(&src["o_xy"][1]));
                let d = (num(&f["x_px"]) - tx).hypot(num(&f["y_px"]) - ty);
                assert!(d < 1.0, "seed {seed} T{t} {name}: detector position {d:.2} px from the truth");
                // Sky position: the truth's separation and PA from A, within 1 px.
                let (tra, tdec) = offset(ra0, dec0, st.0, st.1);
                let ds = sky_distance_arcsec(num(&f["ra_deg"]), num(&f["dec_deg"]), tra, tdec);
                assert!(ds < SCALE, "seed {seed} T{t} {name}: sky position {ds:.3}\" from the truth");
                let flags = flag_names(f);
                let special = t == 0 && i >= COMMON.len();
                if special {
                    let want = match i - COMMON.len() {
                        0 => "saturated",
                        1 => "strip_edge",
                        _ => "blended",
                    };
                    assert!(flags.iter().any(|x| x == want), "seed {seed} {name}: flags {flags:?} lack {want}");
                    assert_eq!(f["usable"], false, "seed {seed} {name}: {want} yet usable: {f}");
                    continue;
                }
                if f["usable"] != true {
                    // A good star may be faint in a bad seed; it must say why.
                    assert!(!flags.is_empty(), "seed {seed} {name}: unusable without a flag");
                    continue;
                }
                n_usable += 1;
                let (tq, tu) = (st.3 * (2.0 * st.4.to_radians()).cos(), st.3 * (2.0 * st.4.to_radians()).sin());
                pulls.push((num(&f["q"]) - tq) / num(&f["sigma_q"]));
                pulls.push((num(&f["u"]) - tu) / num(&f["sigma_u"]));
            }
        }
        if seed == 1 {
            exports_carry_field_stars(dir.path(), &path, &cat);
        }
    }
    let n = pulls.len() as f64;
    let mean = pulls.iter().sum::<f64>() / n;
    let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / n).sqrt();
    println!("field-star pulls: {n_usable} usable stars, {} pulls over 8 nights: mean {mean:.3}, rms {rms:.3}", pulls.len());
    assert!(n_usable >= 8 * 12, "only {n_usable} usable field stars of {}", 8 * 15);
    assert!(mean.abs() < 4.0 / n.sqrt(), "pull mean {mean:.3} (n = {n})");
    assert!((0.9..=1.1).contains(&rms), "pull rms {rms:.3} (n = {n})");
}

/// ECSV, FITS and CSV exports hold one `field_star` row per field star, at its sky position.
fn exports_carry_field_stars(dir: &std::path::Path, catalog: &std::path::Path, cat: &Value) {
    let n_field: usize = cat["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["field_stars"].as_array().map_or(0, Vec::len))
        .sum();
    assert!(n_field > 0);
    for ext in ["csv", "ecsv", "fits"] {
        let out = dir.join(format!("export.{ext}"));
        let (code, _, err) = run(&["export", catalog.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        assert_eq!(code, 0, "export {ext}: {err}");
        if ext == "fits" {
            let bytes = std::fs::read(&out).unwrap();
            let text = String::from_utf8_lossy(&bytes);
            assert_eq!(text.matches("field_star").count(), n_field + usize::from(text.contains("field_star (")), "{ext}");
            continue;
        }
        let text = std::fs::read_to_string(&out).unwrap();
        let rows: Vec<&str> = text.lines().filter(|l| l.contains(",field_star,") || l.contains(" field_star ")).collect();
        assert_eq!(rows.len(), n_field, "{ext}: {} field-star rows, catalog has {n_field}", rows.len());
    }
}

/// Without field stars in the scene, the components' numbers do not change when field
/// stars are measured (default) or not (`measure.field_stars=false`, the old behaviour).
#[test]
fn a_night_without_field_stars_keeps_the_components_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let (with, _, _) = night(dir.path(), "n", 3, false, &[]);
    let (without, _, _) = night(dir.path(), "n", 3, false, &["--param", "measure.field_stars=false"]);
    let strip = |c: &Value| {
        let mut c = c.clone();
        c.as_object_mut().unwrap().remove("provenance");
        for t in c["targets"].as_array_mut().unwrap() {
            let f = t.as_object_mut().unwrap().remove("field_stars");
            if let Some(f) = f {
                assert_eq!(f.as_array().map(Vec::len), Some(0), "a night without field stars found some: {f}");
            }
        }
        c
    };
    assert!(with["targets"][0].get("field_stars").is_some());
    assert!(without["targets"][0].get("field_stars").is_none());
    assert_eq!(strip(&with), strip(&without));
}
