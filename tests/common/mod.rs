//! Helpers shared by the `tests/cli_*.rs` integration tests: run the `sofipol` binary,
//! read its JSON outputs, find test data.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_...` runs the tests against another
//! build (how tests are checked to fail before a fix).
// Each test file uses a subset of these helpers.
#![allow(dead_code)]

use std::path::Path;
use std::process::Command;

use serde_json::Value;

/// The binary under test: `$SOFIPOL_BIN`, else the one cargo built.
pub fn bin() -> String {
    std::env::var("SOFIPOL_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_sofipol").to_string())
}

/// A command running the binary under test.
pub fn sofipol() -> Command {
    Command::new(bin())
}

/// Run `sofipol ARGS`: (exit code, stdout, stderr).
pub fn run(args: &[&str]) -> (i32, String, String) {
    let o = sofipol().args(args).output().expect("run sofipol");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

/// A JSON file (catalog, truth, report); panics naming the file.
pub fn json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())))
        .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// A file of testdata/stats/.
pub fn testdata(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("testdata/stats")
        .join(name)
        .display()
        .to_string()
}

/// Two binaries, Alpha (4.0 arcsec, PA 30) and Beta (3.0 arcsec, PA 200), as `[[binary]]`
/// tables of a simulator scene: the targets of the simulated nights of `cli_hostile` and
/// `cli_night`.
pub const ALPHA_BETA: &str = r#"[[binary]]
name = "Alpha"
separation_arcsec = 4.0
pa_deg = 30.0
flux_a = 120000.0
flux_b = 60000.0
p_a = 0.05
gamma_a_deg = 20.0
p_b = 0.04
gamma_b_deg = 110.0
[[binary]]
name = "Beta"
separation_arcsec = 3.0
pa_deg = 200.0
flux_a = 100000.0
flux_b = 70000.0
p_a = 0.03
gamma_a_deg = 60.0
p_b = 0.06
gamma_b_deg = 150.0
"#;

/// The Python interpreter of the Python-dependent tests: `$SOFIPOL_PYTHON` (set by
/// scripts/test.sh, the project's test command, to the venv of scripts/python-env.sh),
/// checked to import `modules`. A missing variable or a missing package fails the test;
/// only `SOFIPOL_SKIP_PYTHON=1` skips it (None, after printing `SKIPPED` and why).
pub fn python_with(modules: &str, test: &str) -> Option<std::path::PathBuf> {
    if std::env::var("SOFIPOL_SKIP_PYTHON").is_ok_and(|v| v == "1") {
        println!("SKIPPED (SOFIPOL_SKIP_PYTHON=1): {test} needs Python with {modules}");
        eprintln!("SKIPPED (SOFIPOL_SKIP_PYTHON=1): {test} needs Python with {modules}");
        return None;
    }
    let Some(py) = std::env::var_os("SOFIPOL_PYTHON") else {
        panic!(
            "{test} needs Python with {modules}: run the tests with scripts/test.sh (it sets \
             SOFIPOL_PYTHON to the venv of scripts/python-env.sh), set SOFIPOL_PYTHON to such an \
             interpreter, or skip these tests explicitly with SOFIPOL_SKIP_PYTHON=1"
        )
    };
    let py = std::path::PathBuf::from(py);
    let o = Command::new(&py)
        .args(["-c", &format!("import {modules}")])
        .output()
        .unwrap_or_else(|e| panic!("{test}: SOFIPOL_PYTHON={}: {e}", py.display()));
    assert!(
        o.status.success(),
        "{test}: SOFIPOL_PYTHON={} cannot import {modules} (scripts/python-env.sh installs them): {}",
        py.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    Some(py)
}

/// A simulated 2-target night (Alpha, Beta; 2 orientations x 3 dithers) in `dir/night`.
pub fn night(dir: &Path) -> std::path::PathBuf {
    let n = dir.join("night");
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            "name = \"hx\"\nseed = 7\neffects = [\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\"]\n\
             [observation]\norientations_deg = [0.0, 45.0]\ndithers = 3\n[psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.8\n{ALPHA_BETA}"
        ),
    )
    .unwrap();
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", n.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    n
}

/// Simulate `scene` beside the night folder `n` (simulate refuses a folder holding another
/// scene's frames) and move its frames into `n`, leaving its truth.json out.
pub fn simulate_into(scene: &Path, n: &Path) {
    let apart = n.with_file_name(format!("{}_apart", scene.file_stem().unwrap().to_string_lossy()));
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", apart.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    for f in std::fs::read_dir(&apart).unwrap() {
        let p = f.unwrap().path();
        if p.extension().is_some_and(|e| e == "fits") {
            std::fs::rename(&p, n.join(p.file_name().unwrap())).unwrap();
        }
    }
}

/// The frames of `object` in the night folder `n`.
pub fn frames_of(n: &Path, object: &str) -> Vec<std::path::PathBuf> {
    let mut v: Vec<std::path::PathBuf> = std::fs::read_dir(n)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .unwrap()
                .to_str()
                .unwrap()
                .contains(&format!("_{object}_"))
        })
        .collect();
    v.sort();
    assert!(!v.is_empty(), "no frames of {object} in {}", n.display());
    v
}

/// The instrument of the calibration tests: beam ratio 0.97, instrumental polarization
/// 0.3 %, analyzer zero-point 3 deg (the effects standards calibrate).
pub const INSTRUMENT: &str = "[throughput]\nt_e = 0.97\n[instrumental_polarization]\np = 0.003\nangle_deg = 0.0\n\
[analyzer_angle]\nzero_point_deg = 3.0\n";

/// An unpolarized and a polarized standard, as `[[standard]]` tables of a scene.
pub const TWO_STANDARDS: &str = "[[standard]]\nname = \"HD 64299\"\nflux = 150000.0\n\
[[standard]]\nname = \"HD 204827\"\nflux = 150000.0\np = 0.0088\ngamma_deg = 58.7\n";

/// A 2-binary night (Alpha, Beta: 2 orientations x 3 dithers, TPL NEXP 6) with the
/// [`INSTRUMENT`]'s effects and the `standards` given (`[[standard]]` tables), simulated
/// with `name` and `seed` into `dir/night` (its truth.json removed).
pub fn instrument_night(dir: &Path, name: &str, seed: u64, standards: &str) -> std::path::PathBuf {
    let n = dir.join("night");
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            "name = \"{name}\"\nseed = {seed}\neffects = [\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\", \
             \"throughput\", \"instrumental_polarization\", \"analyzer_angle\"]\n\
             [observation]\norientations_deg = [0.0, 45.0]\ndithers = 3\n[psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.8\n\
             {INSTRUMENT}{standards}{ALPHA_BETA}"
        ),
    )
    .unwrap();
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", n.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    n
}

/// Wait for `child` (at most `limit`; past it the child is killed and the test fails with
/// its output), then (exit code, stdout, stderr).
pub fn finish_child(mut child: std::process::Child, limit: std::time::Duration) -> (i32, String, String) {
    let t = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t.elapsed() > limit {
            child.kill().ok();
            let o = child.wait_with_output().unwrap();
            panic!(
                "sofipol still running after {limit:?}: {}\n{}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            );
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

/// Flux-weighted centroid within `r` px of (x, y), iterated (0-based pixel coordinates).
pub fn centroid(img: &ndarray::Array2<f32>, mut x: f64, mut y: f64, r: f64) -> (f64, f64) {
    for _ in 0..20 {
        let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for ((j, i), &v) in img.indexed_iter() {
            if v.is_finite() && (i as f64 - x).hypot(j as f64 - y) <= r {
                s += v as f64;
                sx += v as f64 * i as f64;
                sy += v as f64 * j as f64;
            }
        }
        (x, y) = (sx / s, sy / s);
    }
    (x, y)
}

/// Sum of the pixels whose centre lies within `r` of (x, y), NaN pixels left out.
pub fn aperture(img: &ndarray::Array2<f32>, x: f64, y: f64, r: f64) -> f64 {
    img.indexed_iter()
        .filter(|((j, i), v)| v.is_finite() && (*i as f64 - x).hypot(*j as f64 - y) <= r)
        .map(|(_, &v)| v as f64)
        .sum()
}
