//! The night's calibration against the simulator's truth over many small nights.
//!
//! Each night (2 binaries with 2 field stars each, the 5 standards of
//! `tests/cli_field_stars.rs` at parallactic angles spread over the night, Moffat PSF with
//! per-frame seeing, photon and read noise, saturation) draws its own instrument: beam ratio
//! k, instrumental polarization, analyzer zero-point theta0 and the telescope's
//! polarization (p_tel, psi_tel); the standards' true polarization is drawn from their table
//! values and errors, as the calibration's priors state them. `sofipol night` reduces it;
//! then
//! - the calibration's own pulls: (fitted - true) / reported error of c, theta0 and the
//!   telescope's (a, b), one of each per night: every night is an independent draw;
//! - the binaries' components' and usable field stars' q, u pulls with their total errors
//!   (measurement + calibration) and with the measurement's alone. Stars of one night share
//!   its calibration error: their rms is given with a standard error from the scatter of
//!   the nights' mean squares (nights are the independent units).
//!
//! The long harness is ignored (about 3 s a night):
//! `SOFIPOL_CAL_NIGHTS=48 cargo test --release --test cli_calibration_pulls -- --ignored --nocapture`
//! (`SOFIPOL_BIN=...` runs it against another build). docs/accuracy.md quotes its figures.

use serde_json::Value;

mod common;
use common::{json, run};

/// Standard normal and uniform draws (xorshift64* and Box-Muller), reproducible from a seed.
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }

    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        ((self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn gauss(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }

    fn between(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
}

/// The night's standards: name and the built-in table's p, sigma_p, gamma, sigma_gamma.
const STANDARDS: [(&str, f64, f64, f64, f64); 5] = [
    ("HD 64299", 0.0, 0.0005, 0.0, 0.0),
    ("HD 98161", 0.0, 0.0005, 0.0, 0.0),
    ("HD 94851", 0.0, 0.0005, 0.0, 0.0),
    ("HD 204827", 0.0088, 0.0022, 58.7, 2.0),
    ("HD 154445", 0.0068, 0.0017, 88.8, 2.0),
];

/// A field star: separation ("), PA (deg), flux (ADU), p, gamma (deg).
type Star = (f64, f64, f64, f64, f64);

/// Field stars of every target (bright and faint, polarized and not, inside the strips).
const FIELD: [Star; 2] = [(15.0, 60.0, 60000.0, 0.03, 20.0), (12.0, 200.0, 25000.0, 0.0, 0.0)];

/// The instrument a night draws: k (T_e / T_o), p_inst, its angle, theta0, p_tel, psi_tel.
struct Instrument {
    t_e: f64,
    p_inst: f64,
    inst_angle_deg: f64,
    theta0_deg: f64,
    p_tel: f64,
    psi_tel_deg: f64,
}

/// The scene of night `seed` and its instrument.
fn scene(seed: u64) -> (String, Instrument) {
    let mut rng = Rng::new(seed);
    let inst = Instrument {
        t_e: rng.between(0.95, 0.99),
        p_inst: rng.between(0.0, 0.006),
        inst_angle_deg: rng.between(0.0, 180.0),
        theta0_deg: rng.between(-4.0, 6.0),
        p_tel: rng.between(0.004, 0.010),
        psi_tel_deg: rng.between(-10.0, 10.0),
    };
    let mut s = format!(
        r#"name = "calpulls"
seed = {seed}
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "saturation", "throughput", "instrumental_polarization", "analyzer_angle", "telescope_polarization"]
[observation]
dithers = 5
[psf]
kind = "moffat"
fwhm_arcsec = {fwhm}
[throughput]
t_o = 1.0
t_e = {t_e}
[instrumental_polarization]
p = {p_inst}
angle_deg = {ang}
[analyzer_angle]
zero_point_deg = {th}
parity = 1
[telescope_polarization]
p_tel = {p_tel}
psi_tel_deg = {psi}
"#,
        fwhm = rng.between(0.7, 1.0),
        t_e = inst.t_e,
        p_inst = inst.p_inst,
        ang = inst.inst_angle_deg,
        th = inst.theta0_deg,
        p_tel = inst.p_tel,
        psi = inst.psi_tel_deg,
    );
    for t in 0..2 {
        s += &format!(
            "[[binary]]\nname = \"T{t}\"\nseparation_arcsec = {}\npa_deg = {}\nflux_a = 120000.0\nflux_b = 60000.0\n\
             p_a = 0.03\ngamma_a_deg = {}\np_b = 0.02\ngamma_b_deg = {}\n",
            3.0 + t as f64,
            rng.between(0.0, 360.0),
            rng.between(0.0, 180.0),
            rng.between(0.0, 180.0),
        );
        for (sep, pa, flux, p, gamma) in FIELD {
            s += &format!(
                "[[binary.field_star]]\nseparation_arcsec = {sep}\npa_deg = {pa}\nflux = {flux}\np = {p}\ngamma_deg = {gamma}\n"
            );
        }
    }
    // The standards' true polarization drawn from their table values and errors (the
    // priors of the calibration); spread over the night so that the telescope's term is
    // measured.
    for (k, (name, p, sigma_p, gamma, sigma_gamma)) in STANDARDS.into_iter().enumerate() {
        let (p, gamma) = if p > 0.0 {
            (p + sigma_p * rng.gauss(), gamma + sigma_gamma * rng.gauss())
        } else {
            let (q, u) = (sigma_p / 2f64.sqrt() * rng.gauss(), sigma_p / 2f64.sqrt() * rng.gauss());
            (q.hypot(u), 0.5 * u.atan2(q).to_degrees())
        };
        s += &format!(
            "[[standard]]\nname = \"{name}\"\nflux = 300000.0\np = {p}\ngamma_deg = {gamma}\nstart_ut = \"{:02}:00:00\"\n",
            1 + 2 * k
        );
    }
    (s, inst)
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// One night's figures.
#[derive(Default)]
struct Night {
    /// Pulls of c, theta0, a, b (NaN when not fitted).
    cal: [f64; 4],
    /// q and u pulls of the components and usable field stars with their total errors.
    total: Vec<f64>,
    /// The same with the measurement's errors alone.
    stat: Vec<f64>,
}

/// The truth of (c, theta0, a, b) of a night.
fn truth_of(inst: &Instrument) -> [f64; 4] {
    let c = (1.0 - inst.t_e) / (1.0 + inst.t_e) + inst.p_inst * (2.0 * inst.inst_angle_deg.to_radians()).cos();
    let psi = 2.0 * inst.psi_tel_deg.to_radians();
    [c, inst.theta0_deg, inst.p_tel * psi.cos(), inst.p_tel * psi.sin()]
}

/// Simulate and reduce night `seed` in `dir`.
fn night(dir: &std::path::Path, seed: u64) -> Night {
    let (text, inst) = scene(seed);
    let scene_path = dir.join(format!("n{seed}.toml"));
    std::fs::write(&scene_path, text).unwrap();
    let raw = dir.join(format!("n{seed}_raw"));
    let (code, _, err) = run(&[
        "simulate",
        scene_path.to_str().unwrap(),
        "-o",
        raw.to_str().unwrap(),
        "-q",
    ]);
    assert_eq!(code, 0, "simulate night {seed}: {err}");
    let out = dir.join(format!("n{seed}.json"));
    let (code, stdout, err) = run(&[
        "night",
        raw.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--jobs",
        "2",
    ]);
    assert!(code == 0 || code == 2, "night {seed}: exit {code}\n{stdout}\n{err}");
    let cat = json(&out);
    let truth = json(&raw.join("truth.json"));
    let _ = std::fs::remove_dir_all(&raw);
    let f = &cat["calibration"]["calibration"]["filters"][0];
    let cov = &f["covariance"];
    let sd = |i: usize| num(&cov[i][i]).sqrt();
    let want = truth_of(&inst);
    let got = [
        num(&f["offset"]["c"]),
        num(&f["angles"]["theta0_deg"]),
        num(&f["telescope"]["a"]),
        num(&f["telescope"]["b"]),
    ];
    let mut n = Night::default();
    for i in 0..4 {
        let mut d = got[i] - want[i];
        if i == 1 {
            d = (d + 90.0).rem_euclid(180.0) - 90.0;
        }
        n.cal[i] = d / sd(i);
    }
    for t in cat["targets"].as_array().unwrap() {
        let truth_t = truth["targets"]
            .as_array()
            .unwrap()
            .iter()
            .find(|x| x["object"] == t["object"])
            .unwrap_or_else(|| panic!("night {seed}: target {} not in the truth", t["object"]));
        for c in t["components"].as_array().unwrap() {
            let tc = truth_t["components"]
                .as_array()
                .unwrap()
                .iter()
                .find(|x| x["name"] == c["name"])
                .unwrap();
            if c["q"].is_number() {
                for (k, sk) in [("q", "sigma_q"), ("u", "sigma_u")] {
                    let d = num(&c[k]) - num(&tc[k]);
                    n.total.push(d / num(&c[sk]));
                    n.stat.push(d / num(&c[format!("{sk}_stat").as_str()]));
                }
            }
        }
        for fs in t["field_stars"].as_array().into_iter().flatten() {
            if fs["usable"] != true {
                continue;
            }
            // The field star of the scene at this separation (they are 3" apart or more).
            let Some(&(_, _, _, p, gamma)) = FIELD
                .iter()
                .find(|st| (st.0 - num(&fs["separation_arcsec"])).abs() < 1.0)
            else {
                continue;
            };
            let (tq, tu) = (
                p * (2.0 * gamma.to_radians()).cos(),
                p * (2.0 * gamma.to_radians()).sin(),
            );
            for (k, sk, tv) in [("q", "sigma_q", tq), ("u", "sigma_u", tu)] {
                let d = num(&fs[k]) - tv;
                n.total.push(d / num(&fs[sk]));
                n.stat.push(d / num(&fs[format!("{sk}_stat").as_str()]));
            }
        }
    }
    n
}

/// rms of pulls grouped by night, and its standard error with the nights as the
/// independent units (delta method on the ratio of sums of squares to counts).
fn rms_by_night(groups: &[Vec<f64>]) -> (f64, f64, usize) {
    let groups: Vec<&Vec<f64>> = groups.iter().filter(|g| !g.is_empty()).collect();
    let n_nights = groups.len() as f64;
    let ss: Vec<f64> = groups.iter().map(|g| g.iter().map(|x| x * x).sum()).collect();
    let cnt: Vec<f64> = groups.iter().map(|g| g.len() as f64).collect();
    let (s, m) = (ss.iter().sum::<f64>(), cnt.iter().sum::<f64>());
    let ms = s / m;
    // Var(ms) ~ sum (ss_i - ms cnt_i)^2 / m^2 x n / (n - 1).
    let var =
        ss.iter().zip(&cnt).map(|(a, b)| (a - ms * b).powi(2)).sum::<f64>() / (m * m) * n_nights / (n_nights - 1.0);
    let rms = ms.sqrt();
    (rms, var.sqrt() / (2.0 * rms), m as usize)
}

#[test]
#[ignore = "long: about 3 s a night; run with --ignored (SOFIPOL_CAL_NIGHTS, default 48)"]
fn calibration_pulls_over_many_nights() {
    let nights: u64 = std::env::var("SOFIPOL_CAL_NIGHTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(48);
    let dir = tempfile::tempdir().unwrap();
    let mut all = Vec::new();
    for seed in 1..=nights {
        let n = night(dir.path(), seed);
        println!(
            "night {seed}: pulls c {:+.2} theta0 {:+.2} a {:+.2} b {:+.2}; {} star pulls",
            n.cal[0],
            n.cal[1],
            n.cal[2],
            n.cal[3],
            n.total.len()
        );
        all.push(n);
    }
    let mut worst: f64 = 0.0;
    for (i, name) in ["c", "theta0", "tel_a", "tel_b"].into_iter().enumerate() {
        let groups: Vec<Vec<f64>> = all
            .iter()
            .map(|n| vec![n.cal[i]])
            .filter(|g| g[0].is_finite())
            .collect();
        let (rms, se, m) = rms_by_night(&groups);
        let mean = groups.iter().map(|g| g[0]).sum::<f64>() / m as f64;
        println!("calibration {name}: {m} nights, pull mean {mean:+.3}, rms {rms:.3} +- {se:.3}");
        worst = worst.max((rms - 1.0).abs() / se);
        assert!(m as u64 == nights, "{name} fitted in {m} of {nights} nights");
    }
    let pooled: Vec<Vec<f64>> = all.iter().map(|n| n.cal.to_vec()).collect();
    let (rms, se, m) = rms_by_night(&pooled);
    println!("calibration pooled: {m} pulls over {nights} nights, rms {rms:.3} +- {se:.3}");
    let total: Vec<Vec<f64>> = all.iter().map(|n| n.total.clone()).collect();
    let stat: Vec<Vec<f64>> = all.iter().map(|n| n.stat.clone()).collect();
    let (tr, tse, tm) = rms_by_night(&total);
    let (sr, sse, _) = rms_by_night(&stat);
    println!(
        "stars (components and usable field stars): {tm} q, u pulls over {nights} nights: \
         total errors rms {tr:.3} +- {tse:.3}; measurement errors alone rms {sr:.3} +- {sse:.3}"
    );
    assert!(
        (rms - 1.0).abs() < 3.0 * se,
        "calibration pulls rms {rms:.3} +- {se:.3}"
    );
    assert!(
        (tr - 1.0).abs() < 3.0 * tse,
        "stars' total pulls rms {tr:.3} +- {tse:.3}"
    );
    println!("largest |rms - 1| / se of one parameter: {worst:.2}");
}
