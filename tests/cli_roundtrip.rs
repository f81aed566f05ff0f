//! Whatever `night` writes, every sofipol reader reads: a number that is not finite is
//! written `null` (serde_json), and `export`, `stats` and `merge` must read it back (as
//! NaN) instead of refusing the catalog.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_roundtrip` runs these tests against
//! another build (how they were checked to fail before the fix).
use std::path::Path;

use serde_json::Value;

mod common;
use common::{json, run, ALPHA_BETA};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Replace every floating-point number of `v` by `null` (what serde_json writes for NaN and
/// infinities); integers (counts, the parity) are left alone. Returns how many.
fn null_every_float(v: &mut Value) -> usize {
    match v {
        Value::Number(n) if n.is_f64() => {
            *v = Value::Null;
            1
        }
        Value::Array(a) => a.iter_mut().map(null_every_float).sum(),
        Value::Object(o) => o.values_mut().map(null_every_float).sum(),
        _ => 0,
    }
}

/// Every key path of `v` that holds a float.
fn float_paths(v: &Value, path: &str, out: &mut Vec<String>) {
    match v {
        Value::Number(n) if n.is_f64() => out.push(path.to_string()),
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                float_paths(x, &format!("{path}[{i}]"), out);
            }
        }
        Value::Object(o) => {
            for (k, x) in o {
                float_paths(x, &format!("{path}.{k}"), out);
            }
        }
        _ => {}
    }
}

/// A night with standards (so the catalog holds `standards`, their table entries and the
/// calibration) is reduced; then every float of its catalog is made `null`, as a night
/// whose numbers all came out non-finite would write it. `export` (every format), `stats`
/// and `merge` read it (before, each refused it: "invalid type: null, expected f64"), and
/// `merge` writes it back unchanged: every `null` still there, at the same key.
#[test]
fn a_catalog_with_null_for_every_number_is_read_by_export_stats_and_merge() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = d.join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            r#"name = "rt"
seed = 3
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "throughput", "analyzer_angle"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[throughput]
t_o = 1.0
t_e = 0.97
[[standard]]
name = "HD 64299"
flux = 200000.0
[[standard]]
name = "HD 204827"
flux = 200000.0
p = 0.0088
gamma_deg = 58.7
{ALPHA_BETA}"#
        ),
    )
    .unwrap();
    let n = d.join("night");
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    let cat = d.join("cat.json");
    let (code, _, err) = run(&["night", s(&n), "-o", s(&cat), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{err}");

    let mut v = json(&cat);
    assert!(v["standards"][0]["table"].is_object(), "no standards in {v}");
    assert!(v["targets"][0]["components"][0]["orientations"].is_array(), "{v}");
    let mut before = Vec::new();
    float_paths(&v, "", &mut before);
    let nulled = null_every_float(&mut v);
    assert!(nulled > 100, "{nulled}");
    let bad = d.join("nulls.json");
    std::fs::write(&bad, serde_json::to_string_pretty(&v).unwrap()).unwrap();

    for fmt in ["ecsv", "csv", "fits"] {
        let out = d.join(format!("t.{fmt}"));
        let (code, _, err) = run(&["export", s(&bad), "--format", fmt, "-o", s(&out)]);
        assert_eq!(code, 0, "export {fmt}: {err}");
    }
    let ecsv = std::fs::read_to_string(d.join("t.ecsv")).unwrap();
    assert!(ecsv.lines().filter(|l| l.starts_with("Alpha")).count() == 2, "{ecsv}");

    let (code, _, err) = run(&[
        "stats",
        s(&bad),
        "-o",
        s(&d.join("st")),
        "--pairs",
        "1000",
        "--no-model-figure",
    ]);
    assert!(code == 0, "stats: {err}");
    assert!(!err.contains("parsing catalog"), "{err}");

    let merged = d.join("m.json");
    let (code, _, err) = run(&["merge", s(&bad), "-o", s(&merged)]);
    assert_eq!(code, 0, "merge: {err}");
    let m = json(&merged);
    let mut after = Vec::new();
    float_paths(&m, "", &mut after);
    assert!(after.is_empty(), "numbers made up on reading: {after:?}");
    // Every key that held a number is still there, null.
    for t in ["targets", "standards"] {
        assert_eq!(m[t], v[t], "{t}");
    }
}
