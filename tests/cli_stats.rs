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
    assert_eq!(a["provenance"]["parameters"]["seed"], 5);
    assert_eq!(a["provenance"]["parameters"]["model"], "spread:30");
    let software = a["provenance"]["software"].as_str().unwrap();
    assert_eq!(software, format!("sofipol {}", env!("CARGO_PKG_VERSION")));
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

/// catalog_aligned.json with a Delta-gamma error on every binary: 6 deg, except SYN-05
/// (25 deg, interval [10, 70]) and SYN-07 (interval only, [0, 45]: wider than 40 deg).
fn catalog_with_errors(dir: &std::path::Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(testdata("catalog_aligned.json")).unwrap();
    let mut cat: serde_json::Value = serde_json::from_str(&text).unwrap();
    for t in cat["targets"].as_array_mut().unwrap() {
        let obj = t["object"].as_str().unwrap().to_string();
        let t = t.as_object_mut().unwrap();
        t.insert("sigma_delta_gamma_deg".into(), serde_json::json!(6.0));
        if obj == "SYN-05" {
            t.insert("sigma_delta_gamma_deg".into(), serde_json::json!(25.0));
            t.insert("delta_gamma_interval_deg".into(), serde_json::json!([10.0, 70.0]));
        }
        if obj == "SYN-07" {
            t.insert("delta_gamma_interval_deg".into(), serde_json::json!([0.0, 45.0]));
        }
    }
    let path = dir.join("catalog_errors.json");
    std::fs::write(&path, serde_json::to_string(&cat).unwrap()).unwrap();
    path
}

#[test]
fn stats_with_delta_gamma_errors_reports_the_broadening_and_both_p_values() {
    let dir = tempfile::tempdir().unwrap();
    let cat = catalog_with_errors(dir.path());
    let out = sofipol()
        .args([
            "stats",
            cat.to_str().unwrap(),
            "--pairs",
            "5e4",
            "--p-ism",
            "1",
            "--noise",
            "none",
            "-o",
        ])
        .arg(dir.path().join("out"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    for s in [
        "Measurement errors of Delta gamma: 34 of 34 binaries have one (34 from sigma_delta_gamma_deg)",
        "median sigma = 6.0 deg, max 25.0 deg",
        "Large errors",
        "SYN-05 (Delta gamma",
        "sigma 25.0, 68 % interval [10.0, 70.0]",
        "aligned (α = 0): mean 0.0 -> ",
        "random + P_ism = 1 %: mean",
        "KS p err",
    ] {
        assert!(stdout.contains(s), "missing '{s}' in:\n{stdout}");
    }
    assert!(
        stdout.contains("SYN-07 (Delta gamma") && stdout.contains("interval [0.0, 45.0]"),
        "{stdout}"
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("out/stats.json")).unwrap()).unwrap();
    let r = &json["report"];
    assert_eq!(r["errors"]["sigmas_deg"].as_array().unwrap().len(), 34);
    // Perfect alignment: without errors every simulated Delta gamma is 0 (KS p = 0); with
    // 6-deg errors the prediction has a mean of about 6 sqrt(2/pi) = 4.8 deg and a p > 0.
    let aligned = &r["models"][0];
    assert_eq!(aligned["prediction"]["mean_deg"].as_f64().unwrap(), 0.0);
    let with = &aligned["with_errors"];
    let mean = with["mean_deg"].as_f64().unwrap();
    assert!((4.0..7.0).contains(&mean), "convolved mean {mean}");
    assert!(with["ks"]["p_value"].as_f64().unwrap() > aligned["prediction"]["ks"]["p_value"].as_f64().unwrap());
    // The noise-free ISM prediction is convolved too, and each comparison has both p-values.
    let ism = &r["ism"][0];
    assert!(ism["ks"]["p_value"].is_number() && ism["with_errors"]["ks"]["p_value"].is_number());
    assert_eq!(json["sample"]["binaries"][0]["sigma_source"], "propagated");
    for f in ["observed.png", "models.png", "ism_levels.png"] {
        assert!(dir.path().join("out").join(f).is_file(), "{f} missing");
    }
}

/// `sofipol report` computes its statistics with `sofipol stats`' defaults (pairs, seed, ISM
/// levels, intrinsic P), so that the page shows the numbers `stats` prints: every ISM row of
/// the page carries the KS D and p of `stats.json`, as the page formats them.
#[test]
fn report_statistics_use_the_defaults_of_stats() {
    let dir = tempfile::tempdir().unwrap();
    let cat = testdata("catalog_aligned.json");
    let o = sofipol()
        .args(["stats", &cat, "-q", "-o"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let page = dir.path().join("page.html");
    let o = sofipol()
        .args(["report", &cat, "-q", "-o"])
        .arg(&page)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(&page).unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("stats.json")).unwrap()).unwrap();
    let p_text = |p: f64| {
        if p < 1e-4 {
            format!("{p:.1e}")
        } else {
            format!("{p:.4}")
        }
    };
    let ism = json["report"]["ism"].as_array().unwrap();
    assert_eq!(ism.len(), 10, "the paper's ISM levels");
    for row in ism {
        let (d, p) = (
            row["ks"]["statistic"].as_f64().unwrap(),
            row["ks"]["p_value"].as_f64().unwrap(),
        );
        let cells = format!("<td class=\"num\">{d:.3}</td><td class=\"num\">{}</td>", p_text(p));
        assert!(
            html.contains(&cells),
            "P_ism {}: {cells} not in the page",
            row["p_ism_percent"]
        );
    }
}
