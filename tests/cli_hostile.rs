//! Hostile but realistic use of the `sofipol` binary (issue 9): each test simulates a
//! 2-target night, damages it or the command line in one way, and checks that nothing is
//! lost and nothing is silently wrong: the undamaged target is reduced exactly as in a
//! clean run, and every unused input is named under `failures`.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_hostile` runs these tests against
//! another build (how they were checked to fail before the fixes).
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use serde_json::Value;

fn bin() -> String {
    std::env::var("SOFIPOL_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_sofipol").to_string())
}

const SCENE: &str = r#"
name = "hx"
seed = 7
effects = ["psf", "sky", "strips", "photon_noise", "read_noise"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[[binary]]
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

fn run(args: &[&str]) -> (i32, String, String) {
    let o = Command::new(bin()).args(args).output().expect("run sofipol");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

/// A simulated 2-target night (Alpha, Beta; 2 orientations x 3 dithers) in `dir/night`.
fn night(dir: &Path) -> PathBuf {
    let n = dir.join("night");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, SCENE).unwrap();
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    n
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn catalog(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

fn target<'a>(c: &'a Value, name: &str) -> &'a Value {
    c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == name)
        .unwrap_or_else(|| panic!("no target {name} in {c}"))
}

fn failures(c: &Value) -> Vec<(String, String)> {
    c["failures"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            (
                f["file"].as_str().unwrap().to_string(),
                f["error"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

/// The reference catalog of the undamaged night.
fn clean_catalog(dir: &Path, n: &Path) -> Value {
    let out = dir.join("clean.json");
    let (code, _, err) = run(&["night", s(n), "-o", s(&out), "-q", "--no-png"]);
    assert_eq!(code, 0, "{err}");
    catalog(&out)
}

#[test]
fn closed_stdout_and_stderr_do_not_panic_and_the_catalog_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let out = dir.path().join("cat.json");
    // Both ends closed before sofipol writes anything: every write fails with EPIPE.
    let (r1, w1) = std::io::pipe().unwrap();
    let (r2, w2) = std::io::pipe().unwrap();
    drop(r1);
    drop(r2);
    let st = Command::new(bin())
        .args(["night", s(&n), "-o", s(&out), "--no-png", "-v"])
        .stdout(Stdio::from(w1))
        .stderr(Stdio::from(w2))
        .status()
        .unwrap();
    assert_eq!(st.code(), Some(0), "{st:?}");
    let c = catalog(&out);
    assert_eq!(c["targets"].as_array().unwrap().len(), 2, "{c}");
    // The same for `target`, and for an error path (message to a closed stderr).
    let (r, w) = std::io::pipe().unwrap();
    drop(r);
    let st = Command::new(bin())
        .args(["night", "/nonexistent/night", "-o", s(&out)])
        .stderr(Stdio::from(w))
        .status()
        .unwrap();
    assert_eq!(st.code(), Some(1), "{st:?}");
    let out2 = dir.path().join("t.json");
    let (r, w) = std::io::pipe().unwrap();
    drop(r);
    let st = Command::new(bin())
        .args(["target", s(&n), "--object", "Beta", "-o", s(&out2)])
        .stdout(Stdio::from(w))
        .status()
        .unwrap();
    assert_eq!(st.code(), Some(0), "{st:?}");
    assert_eq!(catalog(&out2)["targets"].as_array().unwrap().len(), 1);
}
