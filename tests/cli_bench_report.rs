//! Smoke test of `sofipol bench accuracy --report DIR --quick` (tiny sizes; no timing checks).
use std::process::Command;

#[test]
fn bench_accuracy_report_quick_writes_tables_plots_and_json() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("report");
    let o = Command::new(env!("CARGO_BIN_EXE_sofipol"))
        .args(["bench", "accuracy", "--quick", "--report"])
        .arg(&out)
        .output()
        .expect("run sofipol");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let md = std::fs::read_to_string(out.join("README.md")).expect("README.md");
    for needle in [
        "## reduction",
        "## exposure",
        "## half-wave plate",
        "## half-wave-plate cycles",
        "## Monte Carlo",
        "(default)",
        "| front |",
    ] {
        assert!(md.contains(needle), "README.md lacks {needle:?}:\n{md}");
    }
    for png in [
        "pareto_reduction.png",
        "pareto_exposure.png",
        "pareto_half-wave_plate.png",
        "pareto_half-wave-plate_cycles.png",
        "mc_cost.png",
    ] {
        let bytes = std::fs::read(out.join(png)).expect(png);
        assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 2000, "{png}");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).expect("json")).expect("parse");
    let variants = json["variants"].as_array().expect("variants");
    assert!(variants.len() >= 10);
    // Exactly one default per group, and every default measured something.
    for v in variants.iter().filter(|v| v["is_default"] == true) {
        assert!(v["bins"].as_array().is_some_and(|b| !b.is_empty()), "{v}");
    }
    let mc = json["mc"].as_array().expect("mc");
    assert_eq!(mc.len(), 2);
    // More pairs, smaller expected error.
    assert!(mc[1]["max_rel_err_expected"].as_f64() < mc[0]["max_rel_err_expected"].as_f64());
}
