//! End-to-end checks of `sofipol mc` and `sofipol stats` on the synthetic catalogs of
//! testdata/stats/ (made by testdata/stats/make_catalogs.py).
mod common;
use common::{sofipol, testdata};

#[test]
fn stats_on_an_aligned_sample_rejects_random_orientation_and_writes_figures() {
    let dir = tempfile::tempdir().unwrap();
    let out = sofipol()
        .args([
            "stats",
            &testdata("catalog_aligned.json"),
            "--pairs",
            "2e4",
            "--p-ism",
            "0.5,5",
            "-o",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("34 binaries"), "{stdout}");
    assert!(stdout.contains("random disk orientation is rejected"), "{stdout}");
    assert!(
        out.stderr.is_empty(),
        "a successful run leaves stderr empty: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    for f in ["stats.json", "observed.png", "ism_levels.png", "models.png"] {
        assert!(dir.path().join(f).is_file(), "{f} missing");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("stats.json")).unwrap()).unwrap();
    assert_eq!(json["report"]["n"], 34);
    assert!(json["report"]["ks_uniform"]["p_value"].as_f64().unwrap() < 1e-4);
    assert_eq!(json["report"]["ism"].as_array().unwrap().len(), 2);
}

#[test]
fn stats_on_a_single_binary_explains_instead_of_failing() {
    let out = sofipol()
        .args(["stats", &testdata("catalog_one.json"), "--pairs", "1000"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    assert!(stdout.contains("Only one binary"), "{stdout}");
}

#[test]
fn stats_on_a_missing_catalog_fails_with_the_file_name() {
    let out = sofipol().args(["stats", "/nonexistent/catalog.json"]).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/catalog.json"));
}

#[test]
fn mc_writes_a_reproducible_histogram_with_provenance() {
    let dir = tempfile::tempdir().unwrap();
    let run = |threads: &str, sub: &str| {
        let out = sofipol()
            .args([
                "mc",
                "--model",
                "spread:30",
                "--pairs",
                "1e5",
                "--seed",
                "5",
                "--threads",
                threads,
                "-o",
            ])
            .arg(dir.path().join(sub))
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join(sub).join("pi_delta_gamma.json")).unwrap()).unwrap();
        assert!(dir.path().join(sub).join("pi_delta_gamma.png").is_file());
        v
    };
    let a = run("1", "a");
    let b = run("2", "b");
    assert_eq!(a["runs"], b["runs"], "identical for 1 and 2 threads");
    let counts: u64 = a["runs"][0]["counts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_u64().unwrap())
        .sum();
    assert_eq!(counts, 100_000);
    assert_eq!(a["parameters"]["seed"], 5);
    assert_eq!(a["parameters"]["model"], "spread:30");
    assert!(a["software"]["version"].is_string());
}

#[test]
fn mc_refuses_a_cut_without_noise() {
    let out = sofipol()
        .args(["mc", "--pairs", "10", "--snr-cut", "3"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("snr-cut"));
}
