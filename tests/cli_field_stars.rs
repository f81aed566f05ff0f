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

/// The first target's special stars: saturated (25" away: beyond the primary's search, a
/// brighter source of the strip), at the o strip's upper edge at POSANG 0 (82 px from A
/// along +y, the strip ending 84 px above A), and a blended pair 1.8" apart (2.2 FWHM at
/// 0.8").
const SATURATED: Star = (25.0, 90.0, 4.0e6, 0.0, 0.0);
const EDGE: Star = (23.5, 0.0, 50000.0, 0.0, 0.0);
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

/// A night of 3 binaries and 5 standards (three unpolarized, two polarized), with or without
/// field stars; the telescope polarizes (the profile's mirror).
fn scene(seed: u64, with_stars: bool, real: bool) -> String {
    let mut s = format!(
        r#"name = "field"
seed = {seed}
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "saturation"{}]
[observation]
dithers = 5
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
"#,
        if real { ", \"telescope_polarization\"" } else { "" }
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
    // The standards' true polarization drawn from their table values and errors, as the
    // calibration's priors state them (docs/calibration.md: standards exactly at their table
    // values make an error the covariance counts and the night never makes).
    let mut rng = Gauss(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    for (k, (name, p, sigma_p, gamma, sigma_gamma)) in STANDARDS.into_iter().enumerate() {
        let (p, gamma) = if !real {
            (p, gamma)
        } else if p > 0.0 {
            (p + sigma_p * rng.next(), gamma + sigma_gamma * rng.next())
        } else {
            let (q, u) = (sigma_p / 2f64.sqrt() * rng.next(), sigma_p / 2f64.sqrt() * rng.next());
            (q.hypot(u), 0.5 * u.atan2(q).to_degrees())
        };
        // Spread over the night (hour angles, hence parallactic angles, apart): the
        // telescope's term is then measured, not taken from the mirror's prior.
        s += &format!(
            "[[standard]]\nname = \"{name}\"\nflux = 300000.0\np = {p}\ngamma_deg = {gamma}\nstart_ut = \"{:02}:00:00\"\n",
            1 + 2 * k
        );
    }
    s
}

/// The night's standards: name and the built-in table's p, sigma_p, gamma, sigma_gamma.
const STANDARDS: [(&str, f64, f64, f64, f64); 5] = [
    ("HD 64299", 0.0, 0.0005, 0.0, 0.0),
    ("HD 98161", 0.0, 0.0005, 0.0, 0.0),
    ("HD 94851", 0.0, 0.0005, 0.0, 0.0),
    ("HD 204827", 0.0088, 0.0022, 58.7, 2.0),
    ("HD 154445", 0.0068, 0.0017, 88.8, 2.0),
];

/// Standard normal draws (xorshift64* and Box-Muller), reproducible from a seed.
struct Gauss(u64);

impl Gauss {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        ((self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn next(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

/// Simulate and reduce one night: (catalog, truth, catalog path).
fn night(
    dir: &std::path::Path,
    tag: &str,
    seed: u64,
    with_stars: bool,
    real: bool,
    extra: &[&str],
) -> (Value, Value, std::path::PathBuf) {
    let scene_path = dir.join(format!("{tag}.toml"));
    std::fs::write(&scene_path, scene(seed, with_stars, real)).unwrap();
    let raw = dir.join(format!("{tag}_raw"));
    if !raw.join("truth.json").exists() {
        let (code, _, err) = run(&[
            "simulate",
            scene_path.to_str().unwrap(),
            "-o",
            raw.to_str().unwrap(),
            "-q",
        ]);
        assert_eq!(code, 0, "simulate {tag}: {err}");
    }
    let out = dir.join(format!("{tag}.json"));
    let mut args = vec![
        "night",
        raw.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--jobs",
        "2",
    ];
    if !real {
        args.extend(["--set", "telescope.polarizes=false"]);
    }
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
fn matched(fs: &[Value], st: Star) -> Option<&Value> {
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

/// The pulls of 8 nights pooled (`real`: see [`scene`]): the usable field stars' with their
/// total errors and with the measurement's alone, the components' with their total errors;
/// and the number of usable field stars. On the way, every night's field stars are checked:
/// found, within 1 px of the truth on the detector and on the sky, the saturated, edge and
/// blended ones flagged with that reason and not usable, none on the binary; the first
/// night's exports carry them.
struct Pulls {
    total: Vec<f64>,
    stat: Vec<f64>,
    components: Vec<f64>,
    n_usable: usize,
}

fn nights(real: bool) -> Pulls {
    let dir = tempfile::tempdir().unwrap();
    let mut pulls: Vec<f64> = Vec::new();
    let mut stat_pulls: Vec<f64> = Vec::new();
    let mut comp_pulls: Vec<f64> = Vec::new();
    let mut n_usable = 0;
    for seed in 1..=8u64 {
        let (cat, truth, path) = night(dir.path(), &format!("s{seed}"), seed, true, real, &[]);
        assert!(
            cat["calibration"]["calibration"].is_object(),
            "seed {seed}: the night has no calibration"
        );
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
                assert!(
                    s > 2.0 && (s - sep_b).abs() > 0.5 || s > sep_b + 2.0,
                    "seed {seed} T{t}: field star on the binary: {f}"
                );
            }
            // The binary's components, for reference: the same calibration, the same errors.
            for c in tg["components"].as_array().unwrap() {
                let tc = truth_t["components"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .find(|x| x["name"] == c["name"])
                    .unwrap();
                if c["q"].is_number() {
                    comp_pulls.push((num(&c["q"]) - num(&tc["q"])) / num(&c["sigma_q"]));
                    comp_pulls.push((num(&c["u"]) - num(&tc["u"])) / num(&c["sigma_u"]));
                }
            }
            for (i, st) in stars_of(t).into_iter().enumerate() {
                let name = format!("field{}", i + 1);
                let f = matched(fs, st)
                    .unwrap_or_else(|| panic!("seed {seed} T{t}: {name} {st:?} not found among {fs:#?}"));
                // Detector position: the o image in the first frame, within 1 px.
                let src = truth_t["frames"][0]["sources"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .find(|s| s["name"] == name)
                    .unwrap();
                let (tx, ty) = (num(&src["o_xy"][0]), num(&src["o_xy"][1]));
                let d = (num(&f["x_px"]) - tx).hypot(num(&f["y_px"]) - ty);
                assert!(
                    d < 1.0,
                    "seed {seed} T{t} {name}: detector position {d:.2} px from the truth"
                );
                // Sky position: the truth's separation and PA from A, within 1 px.
                let (tra, tdec) = offset(ra0, dec0, st.0, st.1);
                let ds = sky_distance_arcsec(num(&f["ra_deg"]), num(&f["dec_deg"]), tra, tdec);
                assert!(
                    ds < SCALE,
                    "seed {seed} T{t} {name}: sky position {ds:.3}\" from the truth"
                );
                let flags = flag_names(f);
                let special = t == 0 && i >= COMMON.len();
                if special {
                    let want = match i - COMMON.len() {
                        0 => "saturated",
                        1 => "strip_edge",
                        _ => "blended",
                    };
                    assert!(
                        flags.iter().any(|x| x == want),
                        "seed {seed} {name}: flags {flags:?} lack {want}"
                    );
                    assert_eq!(f["usable"], false, "seed {seed} {name}: {want} yet usable: {f}");
                    continue;
                }
                if f["usable"] != true {
                    // A good star may be faint in a bad seed; it must say why.
                    assert!(!flags.is_empty(), "seed {seed} {name}: unusable without a flag");
                    continue;
                }
                n_usable += 1;
                let (tq, tu) = (
                    st.3 * (2.0 * st.4.to_radians()).cos(),
                    st.3 * (2.0 * st.4.to_radians()).sin(),
                );
                pulls.push((num(&f["q"]) - tq) / num(&f["sigma_q"]));
                pulls.push((num(&f["u"]) - tu) / num(&f["sigma_u"]));
                stat_pulls.push((num(&f["q"]) - tq) / num(&f["sigma_q_stat"]));
                stat_pulls.push((num(&f["u"]) - tu) / num(&f["sigma_u_stat"]));
            }
        }
        if seed == 1 {
            exports_carry_field_stars(dir.path(), &path, &cat);
        }
    }
    Pulls {
        total: pulls,
        stat: stat_pulls,
        components: comp_pulls,
        n_usable,
    }
}

/// Mean and rms.
fn mean_rms(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    (
        v.iter().sum::<f64>() / n,
        (v.iter().map(|p| p * p).sum::<f64>() / n).sqrt(),
    )
}

/// A realistic night (the telescope polarizes, the standards' truths drawn from their table
/// errors): the field stars' pulls with their total errors (measurement and calibration)
/// are centred and as wide as the binary's components' in the same nights: the same
/// calibration, the same error propagation.
#[test]
fn field_stars_are_calibrated_like_the_components() {
    let p = nights(true);
    let (m, r) = mean_rms(&p.total);
    let (cm, cr) = mean_rms(&p.components);
    let n = p.total.len() as f64;
    println!(
        "realistic nights: field-star pulls (total errors) {} usable stars, {} pulls over 8 nights: mean {m:.3}, rms {r:.3}; \
         components' pulls ({}): mean {cm:.3}, rms {cr:.3}",
        p.n_usable,
        p.total.len(),
        p.components.len()
    );
    assert!(
        p.n_usable >= 8 * 12,
        "only {} usable field stars of {}",
        p.n_usable,
        8 * 15
    );
    assert!(m.abs() < 4.0 / n.sqrt(), "pull mean {m:.3} (n = {n})");
    assert!(r <= 1.1, "pull rms {r:.3} (n = {n})");
    assert!((r - cr).abs() <= 0.1, "field-star pull rms {r:.3}, components' {cr:.3}");
}

/// Nights whose calibration is exact in the simulator's terms (no telescope polarization,
/// and the profile says so; standards at their table values): the field stars' q and u
/// pulls with the measurement's errors have mean ~0 and rms in [0.9, 1.1], pooled over 8
/// nights. (The total errors there hold the table's doubt about the standards, which such
/// nights never realise: every total pull, components' as field stars', is ~0.7.)
#[test]
fn field_star_measurement_errors_are_honest() {
    let p = nights(false);
    let (m, r) = mean_rms(&p.stat);
    let (tm, tr) = mean_rms(&p.total);
    let (cm, cr) = mean_rms(&p.components);
    let n = p.stat.len() as f64;
    println!(
        "exact-calibration nights: field-star pulls (measurement errors) {} usable stars, {} pulls: mean {m:.3}, rms {r:.3}; \
         with total errors mean {tm:.3}, rms {tr:.3}; components' (total) mean {cm:.3}, rms {cr:.3}",
        p.n_usable,
        p.stat.len()
    );
    assert!(
        p.n_usable >= 8 * 12,
        "only {} usable field stars of {}",
        p.n_usable,
        8 * 15
    );
    assert!(m.abs() < 4.0 / n.sqrt(), "pull mean {m:.3} (n = {n})");
    assert!((0.9..=1.1).contains(&r), "pull rms {r:.3} (n = {n})");
}

/// ECSV and CSV exports hold one `field_star` row per field star, with its sky position;
/// the FITS table as many rows as the CSV.
fn exports_carry_field_stars(dir: &std::path::Path, catalog: &std::path::Path, cat: &Value) {
    let stars: Vec<&Value> = cat["targets"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|t| t["field_stars"].as_array().into_iter().flatten())
        .collect();
    let n_field = stars.len();
    assert!(n_field > 0);
    let mut csv_rows = 0;
    for ext in ["csv", "ecsv", "fits"] {
        let out = dir.join(format!("export.{ext}"));
        let (code, _, err) = run(&["export", catalog.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        assert_eq!(code, 0, "export {ext}: {err}");
        if ext == "fits" {
            // The table's NAXIS2 (the second HDU's; the primary has none).
            let bytes = std::fs::read(&out).unwrap();
            let cards: Vec<String> = bytes
                .chunks(80)
                .map(|c| String::from_utf8_lossy(c).into_owned())
                .collect();
            let naxis2: usize = cards
                .iter()
                .rfind(|c| c.starts_with("NAXIS2  ="))
                .and_then(|c| c[10..30].trim().parse().ok())
                .expect("NAXIS2 of the table");
            assert_eq!(naxis2, csv_rows, "fits rows {naxis2}, csv rows {csv_rows}");
            continue;
        }
        let text = std::fs::read_to_string(&out).unwrap();
        let body: Vec<&str> = text.lines().filter(|l| !l.starts_with('#')).skip(1).collect();
        let sep = ',';
        let header: Vec<&str> = text.lines().find(|l| !l.starts_with('#')).unwrap().split(sep).collect();
        let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
        let (kind, comp, ra, dec) = (col("kind"), col("component"), col("ra"), col("dec"));
        let rows: Vec<Vec<&str>> = body
            .iter()
            .map(|l| l.split(sep).collect::<Vec<_>>())
            .filter(|r| r.get(kind) == Some(&"field_star"))
            .collect();
        assert_eq!(
            rows.len(),
            n_field,
            "{ext}: {} field-star rows, catalog has {n_field}",
            rows.len()
        );
        // Each row at its star's sky position (the first target's stars come first).
        for (r, s) in rows.iter().zip(&stars) {
            assert_eq!(r[comp], s["id"].as_str().unwrap(), "{ext}");
            let (rra, rdec): (f64, f64) = (r[ra].parse().unwrap(), r[dec].parse().unwrap());
            let d = sky_distance_arcsec(rra, rdec, num(&s["ra_deg"]), num(&s["dec_deg"]));
            assert!(d < 0.01, "{ext}: {} at {d}\" from the catalog's position", r[comp]);
        }
        if ext == "csv" {
            csv_rows = body.len();
        }
    }
}

/// Without field stars in the scene, the components' numbers do not change when field
/// stars are measured (default) or not (`measure.field_stars=false`, the old behaviour).
#[test]
fn a_night_without_field_stars_keeps_the_components_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let (with, _, _) = night(dir.path(), "n", 3, false, true, &[]);
    let (without, _, _) = night(
        dir.path(),
        "n",
        3,
        false,
        true,
        &["--param", "measure.field_stars=false"],
    );
    let strip = |c: &Value| {
        let mut c = c.clone();
        c.as_object_mut().unwrap().remove("provenance");
        for t in c["targets"].as_array_mut().unwrap() {
            let f = t.as_object_mut().unwrap().remove("field_stars");
            if let Some(f) = f {
                assert_eq!(
                    f.as_array().map(Vec::len),
                    Some(0),
                    "a night without field stars found some: {f}"
                );
            }
        }
        c
    };
    assert!(with["targets"][0].get("field_stars").is_some());
    assert!(without["targets"][0].get("field_stars").is_none());
    assert_eq!(strip(&with), strip(&without));
}
