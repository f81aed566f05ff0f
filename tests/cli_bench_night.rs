//! `sofipol bench night`: the night's pixel-type mix, the re-simulation of a cached night
//! made with another mix, and the expert Python reduction (numpy, scipy, astropy,
//! photutils: `$SOFIPOL_PYTHON`, set by scripts/test.sh; fails without it unless
//! SOFIPOL_SKIP_PYTHON=1) against sofipol and against the simulated truth.
//! No timing is checked here.
use std::path::Path;
use std::process::Command;

use serde_json::Value;

mod common;

const BIN: &str = env!("CARGO_BIN_EXE_sofipol");

fn bench_night(dir: &Path, extra: &[&str]) -> String {
    let o = Command::new(BIN)
        .args(["bench", "night", "--targets", "4", "--repeats", "1", "--dir"])
        .arg(dir)
        .args(extra)
        .env_remove("SOFIPOL_PYTHON")
        .output()
        .expect("run sofipol");
    let stdout = String::from_utf8_lossy(&o.stdout).to_string();
    assert_eq!(
        o.status.code(),
        Some(0),
        "{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    stdout
}

/// BITPIX (and BZERO) of a FITS file's primary header.
fn bitpix(path: &Path) -> (i64, Option<f64>) {
    let bytes = std::fs::read(path).unwrap();
    let cards: Vec<String> = bytes[..2880 * 2]
        .chunks(80)
        .map(|c| String::from_utf8_lossy(c).to_string())
        .collect();
    let value = |k: &str| {
        cards
            .iter()
            .find(|c| c.starts_with(&format!("{k:<8}=")))
            .map(|c| c[10..].split('/').next().unwrap().trim().to_string())
    };
    (
        value("BITPIX").unwrap().parse().unwrap(),
        value("BZERO").map(|v| v.parse().unwrap()),
    )
}

#[test]
fn bench_night_is_half_float_half_16_bit_and_resimulates_another_mix() {
    let dir = tempfile::tempdir().unwrap();
    let out = bench_night(dir.path(), &[]);
    assert!(out.contains("20 float BITPIX -32, 20 16-bit BITPIX 16"), "{out}");
    let raw = dir.path().join("raw");
    for t in 0..4 {
        for k in [1, 10] {
            let (b, z) = bitpix(&raw.join(format!("SOFI_bench_Bench_{t:02}_{k:02}.fits")));
            if t % 2 == 0 {
                assert_eq!((b, z), (-32, None), "target {t}");
            } else {
                assert_eq!((b, z), (16, Some(32768.0)), "target {t}");
            }
        }
    }
    assert!(out.contains("Python reference: not run"), "{out}");
    // Same options: reused. A cache made by an older bench (all float, its tag): re-simulated.
    let again = bench_night(dir.path(), &[]);
    assert!(again.contains("reusing"), "{again}");
    std::fs::write(raw.join(".bench-night-complete"), "4\n").unwrap();
    let stale = bench_night(dir.path(), &[]);
    assert!(stale.contains("simulated 4 targets"), "{stale}");
}

/// The bench night's truth, from the formulas of `night_scene` (bench/src/night.rs):
/// (flux, q, u) of components a and b of target i of n.
fn truth(i: usize, n: usize) -> [(f64, f64, f64); 2] {
    let _ = n;
    let qu = |p: f64, g: f64| (p * (2.0 * g.to_radians()).cos(), p * (2.0 * g.to_radians()).sin());
    let fa = 60000.0 + 90000.0 * ((i * 7 % 10) as f64 / 10.0);
    let fb = 30000.0 + 50000.0 * ((i * 3 % 10) as f64 / 10.0);
    let (qa, ua) = qu(0.01 + 0.06 * ((i * 5 % 11) as f64 / 11.0), (i * 37 % 180) as f64);
    let (qb, ub) = qu(0.01 + 0.06 * ((i * 9 % 11) as f64 / 11.0), (i * 71 % 180) as f64);
    [(fa, qa, ua), (fb, qb, ub)]
}

#[test]
fn python_reduction_agrees_with_sofipol_and_with_the_truth() {
    let Some(py) = common::python_with(
        "numpy, scipy, astropy, photutils",
        "python_reduction_agrees_with_sofipol_and_with_the_truth",
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = bench_night(dir.path(), &["--python", py.to_str().unwrap()]);
    assert!(out.contains("ratio Python / sofipol: wall"), "{out}");
    // "Python - sofipol, q and u in units of sofipol's sigma (all, sofipol status ok): 16 values, rms 0.52, ..."
    let line = out
        .lines()
        .find(|l| l.contains("sofipol's sigma (all, sofipol status ok)"))
        .unwrap_or_else(|| panic!("{out}"));
    assert!(line.contains("16 values"), "{line}");
    let rms: f64 = line
        .split("rms ")
        .nth(1)
        .unwrap()
        .split(',')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let max: f64 = line
        .split("max |d| ")
        .nth(1)
        .unwrap()
        .split(',')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(rms < 1.0 && max < 3.0, "{line}");
    assert!(out.contains("Python  against the simulated truth"), "{out}");

    // The Python catalog on its own against the truth (A = the brighter component).
    let cat: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("catalog_python.json")).unwrap()).unwrap();
    let targets = cat["targets"].as_array().unwrap();
    assert_eq!(targets.len(), 4);
    let mut pulls = Vec::new();
    for (i, t) in targets.iter().enumerate() {
        assert_eq!(t["object"], format!("Bench {i:02}"));
        let mut tr = truth(i, 4);
        tr.sort_by(|a, b| b.0.total_cmp(&a.0));
        let comps = t["components"].as_array().unwrap();
        assert_eq!(comps.len(), 2, "{t}");
        for (c, (_, q, u)) in comps.iter().zip(tr) {
            pulls.push((c["q"].as_f64().unwrap() - q) / c["sigma_q"].as_f64().unwrap());
            pulls.push((c["u"].as_f64().unwrap() - u) / c["sigma_u"].as_f64().unwrap());
        }
    }
    let rms = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    assert!(
        pulls.iter().all(|p| p.abs() < 4.0) && rms < 2.0,
        "Python q, u against the truth, in sigma: {pulls:?}"
    );
}
