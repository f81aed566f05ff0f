//! `merge` of shards reduced with another calibration: refused like shards with other
//! reduction parameters, naming the key and the file; shards calibrated alike merge.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_merge` runs these tests against
//! another build (how they were checked to fail before the fix).
use std::path::{Path, PathBuf};

mod common;
use common::{json as catalog, run, ALPHA_BETA};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 2-target night with the three standards of the built-in table that the demo night
/// observes, a beam ratio of 0.97, 0.3 % of instrumental polarization and an angle
/// zero-point of 3 deg (2 orientations x 3 dithers), in `dir/night`.
fn night(dir: &Path) -> PathBuf {
    night_of(dir, ALPHA_BETA)
}

/// [`night`] with other `[[binary]]` tables.
fn night_of(dir: &Path, binaries: &str) -> PathBuf {
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            r#"
name = "mg"
seed = 5
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "throughput",
           "instrumental_polarization", "analyzer_angle"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[throughput]
t_o = 1.0
t_e = 0.97
[instrumental_polarization]
p = 0.003
angle_deg = 0.0
[analyzer_angle]
zero_point_deg = 3.0
parity = 1
[[standard]]
name = "HD 64299"
flux = 200000.0
[[standard]]
name = "HD 98161"
flux = 200000.0
[[standard]]
name = "HD 204827"
flux = 200000.0
p = 0.0088
gamma_deg = 58.7
{binaries}"#
        ),
    )
    .unwrap();
    let n = dir.join("night");
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    n
}

/// A user standards table that moves HD 204827's angle by 91 deg.
const TURNED: &str = r#"[[standard]]
name = "HD 204827"
filter = "Ks"
p = 0.0088
sigma_p = 0.0022
gamma_deg = 149.7
sigma_gamma_deg = 2.0
"#;

/// Shard 2/2 reduced with `--no-calibration`, `--stokes-method least_squares`,
/// `--standards` (HD 204827 turned by 91 deg), `--calib` (this night's own calibration
/// directory) or with the same `--standards` path whose content changed between the
/// shards: each merge with shard 1/2 is refused (exit 1, nothing written), naming the
/// shard and what differs. Shards reduced alike (with another `--jobs`) merge (exit 0) and
/// the merged catalog's calibration is theirs. (The edited table used to merge, exit 0,
/// with shard 1's calibration on top.)
#[test]
fn merge_refuses_shards_reduced_with_another_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let n = night(d);
    let shard = |k: &str, name: &str, extra: &[&str]| {
        let out = d.join(format!("{name}.json"));
        let mut a = vec!["night", s(&n), "-o", s(&out), "-q", "--no-png", "--shard", k];
        a.extend_from_slice(extra);
        let (code, _, err) = run(&a);
        assert!(code == 0 || code == 2, "{name}: {err}");
        out
    };
    let s1 = shard("1/2", "s1", &[]);
    // Another thread count: the same calibration, bit for bit.
    let s2 = shard("2/2", "s2", &["--jobs", "1"]);
    let m = d.join("m.json");
    let (code, _, err) = run(&["merge", s(&s1), s(&s2), "-o", s(&m)]);
    assert_eq!(code, 0, "{err}");
    let merged = catalog(&m);
    let cal1 = catalog(&s1)["calibration"].clone();
    assert_eq!(cal1["source"], "night", "{cal1}");
    assert!(cal1["calibration"]["filters"][0]["angles"].is_object(), "{cal1}");
    assert_eq!(merged["calibration"], cal1);
    std::fs::remove_file(&m).unwrap();

    let turned = d.join("turned.toml");
    std::fs::write(&turned, TURNED).unwrap();
    let caldir = d.join("cal");
    let (code, _, err) = run(&["calib", s(&n), "-o", s(&caldir), "-q"]);
    assert_eq!(code, 0, "{err}");
    let variants: Vec<(&str, Vec<&str>, &str)> = vec![
        ("nocal", vec!["--no-calibration"], "no_calibration"),
        ("ls", vec!["--stokes-method", "least_squares"], "stokes_method"),
        ("turned", vec!["--standards", s(&turned)], "standards"),
        ("caldir", vec!["--calib", s(&caldir)], "calib_dir"),
    ];
    for (name, extra, key) in variants {
        let s2b = shard("2/2", name, &extra);
        for pair in [[&s1, &s2b], [&s2b, &s1]] {
            let (code, _, err) = run(&["merge", s(pair[0]), s(pair[1]), "-o", s(&m)]);
            assert_eq!(code, 1, "{name}: {err}");
            assert!(
                err.contains("calibration") && err.contains(key) && err.contains(s(&s2b)),
                "{name}: {err}"
            );
            assert!(!m.exists(), "{name}: written");
        }
    }

    // The same --standards path in both shards, its content changed in between: the
    // settings agree, the calibrations applied do not.
    let table = d.join("table.toml");
    std::fs::write(&table, TURNED.replace("149.7", "58.7")).unwrap();
    let a = shard("1/2", "ta", &["--standards", s(&table)]);
    std::fs::write(&table, TURNED).unwrap();
    let b = shard("2/2", "tb", &["--standards", s(&table)]);
    let (code, _, err) = run(&["merge", s(&a), s(&b), "-o", s(&m)]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("calibration") && err.contains("theta0_deg") && err.contains(s(&b)),
        "{err}"
    );
    assert!(!m.exists());
}

/// `object` of every target, in catalog order.
fn objects(cat: &serde_json::Value) -> Vec<String> {
    cat["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["object"].as_str().unwrap().to_string())
        .collect()
}

/// The mean of `keyword` over the headers of the frames of the sequence `sequence`
/// (`object@TPL START`), read by the project's header reader.
fn header_mean(n: &Path, sequence: &str, keyword: &str) -> f64 {
    let tpl = sequence.rsplit_once('@').unwrap().1;
    let values: Vec<f64> = std::fs::read_dir(n)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "fits"))
        .map(|p| sofipol_calib::fits::read_header(&p).unwrap())
        .filter(|h| h.get_str("ESO TPL START").is_ok_and(|t| t == tpl))
        .map(|h| h.get_f64(keyword).unwrap())
        .collect();
    assert!(values.len() >= 6, "{sequence}: {} frames", values.len());
    values.iter().sum::<f64>() / values.len() as f64
}

/// The shards of a night merged: the targets in the unsharded night's order (by TPL
/// START: Zulu was observed before Beta, so not alphabetical), the software and commit of
/// the shards in the provenance and in the exported table (it said `unknown`), the
/// standards once. The catalog's `ra_deg`, `dec_deg` and `mjd_mean` of every target and
/// standard are the means of its frames' `RA`, `DEC` and `MJD-OBS`.
#[test]
fn merged_shards_keep_the_nights_order_and_software() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let n = night_of(d, &ALPHA_BETA.replace("Alpha", "Zulu"));
    let reduce = |name: &str, extra: &[&str]| {
        let out = d.join(format!("{name}.json"));
        let mut a = vec!["night", s(&n), "-o", s(&out), "-q", "--no-png"];
        a.extend_from_slice(extra);
        let (code, _, err) = run(&a);
        assert!(code == 0 || code == 2, "{name}: {err}");
        out
    };
    let whole = catalog(&reduce("whole", &[]));
    let (s1, s2) = (reduce("s1", &["--shard", "1/2"]), reduce("s2", &["--shard", "2/2"]));
    let m = d.join("m.json");
    let (code, _, err) = run(&["merge", s(&s1), s(&s2), "-o", s(&m)]);
    assert_eq!(code, 0, "{err}");
    let merged = catalog(&m);
    assert_eq!(objects(&whole), ["Zulu", "Beta"], "the night's order is by TPL START");
    assert_eq!(objects(&merged), objects(&whole));
    let software = whole["provenance"]["software"].as_str().unwrap();
    assert!(software.starts_with("sofipol "), "{software}");
    assert_eq!(merged["provenance"]["software"], software);
    assert_eq!(merged["provenance"]["commit"], whole["provenance"]["commit"]);
    let n_std = whole["standards"].as_array().unwrap().len();
    assert_eq!(n_std, 3);
    assert_eq!(merged["standards"].as_array().unwrap().len(), n_std);

    // The export of the merged catalog names the software.
    let csv = d.join("m.csv");
    let (code, _, err) = run(&["export", s(&m), "--format", "csv", "-o", s(&csv)]);
    assert_eq!(code, 0, "{err}");
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert!(rows.iter().all(|r| r[col("software")] == software), "{text}");
    let kinds: Vec<&str> = rows.iter().map(|r| r[col("kind")]).collect();
    assert_eq!(kinds.iter().filter(|k| **k == "standard").count(), n_std, "{text}");
    let targets: Vec<&str> = rows
        .iter()
        .filter(|r| r[col("kind")] == "target")
        .map(|r| r[col("target")])
        .collect();
    assert_eq!(targets, ["Zulu", "Zulu", "Beta", "Beta"], "{text}");

    // Pointing and time: the means of the frames' headers.
    let entries = whole["targets"]
        .as_array()
        .unwrap()
        .iter()
        .chain(whole["standards"].as_array().unwrap());
    for t in entries {
        let seq = t["sequence"].as_str().unwrap();
        for (key, keyword) in [("ra_deg", "RA"), ("dec_deg", "DEC"), ("mjd_mean", "MJD-OBS")] {
            let want = header_mean(&n, seq, keyword);
            let got = t[key].as_f64().unwrap_or_else(|| panic!("{seq}: no {key} in {t}"));
            assert!((got - want).abs() < 1e-9, "{seq} {key}: {got} vs {want}");
        }
    }
}
