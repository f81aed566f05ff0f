//! `demo`, `target` and `bench` through the `sofipol` binary, as a user runs them.

mod common;
use common::{json, run};

/// The README's first command is itself a check: the demo compares every recovered q, u
/// with the simulated truth and exits 0 only when all are within 5 sigma.
#[test]
fn demo_simulates_reduces_checks_and_writes_figures() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let (code, stdout, err) = run(&["demo", "-o", out.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(
        stdout.contains("check: every component's q and u within 5 sigma"),
        "{stdout}"
    );
    let cat = json(&out.join("catalog.json"));
    let targets = cat["targets"].as_array().unwrap();
    assert_eq!(targets.len(), 5);
    // The science product in the table (one Delta-gamma line per binary, with the
    // catalog's value where both stars pass), and where to go next.
    assert_eq!(stdout.matches("Delta-gamma true").count(), 5, "{stdout}");
    for t in targets {
        if let Some(dg) = t["delta_gamma_deg"].as_f64() {
            assert!(stdout.contains(&format!("found {dg:.1} +- ")), "{dg}: {stdout}");
        }
    }
    assert!(stdout.contains("next: sofipol report"), "{stdout}");
    // The provenance names the commit `--version` prints (docs/cli.md).
    let (_, version, _) = run(&["--version"]);
    let commit = cat["provenance"]["commit"].as_str().unwrap_or("(none)");
    assert!(
        commit != "unknown" || !std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(".git").exists(),
        "{commit}"
    );
    assert!(version.contains(&format!("(commit {commit})")), "{version} vs {commit}");
    let truth = json(&out.join("raw/truth.json"));
    assert_eq!(truth["targets"].as_array().unwrap().len(), 5);
    // The night's dome flats and standards calibrate it: flat, offset c within 3 sigma of
    // the simulated (1-k)/(1+k) + p_inst, no component left uncalibrated, every standard
    // reported and within 3 sigma of its table values.
    assert!(stdout.contains("calibration derived from the night"), "{stdout}");
    assert_eq!(
        cat["provenance"]["flat"]["mode"], "dome",
        "{}",
        cat["provenance"]["flat"]
    );
    let f = &cat["calibration"]["calibration"]["filters"][0];
    let (c, sc) = (
        f["offset"]["c"].as_f64().unwrap(),
        f["offset"]["sigma_c"].as_f64().unwrap(),
    );
    let c_true = 0.03 / 1.97 + 0.003;
    assert!((c - c_true).abs() < 3.0 * sc, "c = {c} +- {sc}, simulated {c_true}");
    let th = (
        f["angles"]["theta0_deg"].as_f64().unwrap(),
        f["angles"]["sigma_theta0_deg"].as_f64().unwrap(),
    );
    assert!((th.0 - 3.0).abs() < 3.0 * th.1, "theta0 {th:?}");
    for t in targets {
        for comp in t["components"].as_array().unwrap() {
            assert!(!comp["flags"].to_string().contains("uncalibrated"), "{}", t["object"]);
        }
    }
    let stds = cat["standards"].as_array().unwrap();
    assert_eq!(stds.len(), 3);
    for s in stds {
        // Polarized: P against the table in sigma; unpolarized: (q, u) against 0, chi^2 (2 dof).
        match s["residual_p_sigma"].as_f64() {
            Some(rp) => assert!(rp.abs() < 3.0, "{s}"),
            None => assert!(s["residual_qu_chi2"].as_f64().unwrap() < 11.83, "{s}"),
        }
    }
    let pngs = std::fs::read_dir(out.join("catalog_products"))
        .unwrap()
        .filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "png"));
    assert_eq!(pngs.count(), 5);

    // One night, one way: `night` on the demo's frames gives the demo's catalog, the
    // provenance included (the same keys; the same flats, mask frames and calibration
    // settings), apart from the time, the command line and the inputs as given.
    let night_cat = dir.path().join("night.json");
    let raw = out.join("raw");
    let (code, _, err) = run(&[
        "night",
        raw.to_str().unwrap(),
        "-o",
        night_cat.to_str().unwrap(),
        "-q",
        "--no-png",
    ]);
    assert_eq!(code, 0, "{err}");
    let mut night = json(&night_cat);
    let mut demo = cat.clone();
    for key in ["created_utc", "command_line", "inputs"] {
        for c in [&mut night, &mut demo] {
            c["provenance"].as_object_mut().unwrap().remove(key);
        }
    }
    assert_eq!(
        night["provenance"].as_object().unwrap().keys().collect::<Vec<_>>(),
        demo["provenance"].as_object().unwrap().keys().collect::<Vec<_>>()
    );
    assert_eq!(
        night, demo,
        "the demo's catalog differs from the night's on the same frames"
    );
}

const ONE: &str = r#"
name = "one"
seed = 5
effects = ["psf", "sky", "strips", "photon_noise", "read_noise"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[[binary]]
name = "Solo"
separation_arcsec = 3.0
pa_deg = 70.0
flux_a = 100000.0
flux_b = 60000.0
p_a = 0.04
gamma_a_deg = 35.0
p_b = 0.03
gamma_b_deg = 125.0
"#;

#[test]
fn target_reduces_one_sequence_to_the_truth_and_names_a_missing_object() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("raw");
    let scene = dir.path().join("one.toml");
    std::fs::write(&scene, ONE).unwrap();
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", raw.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    let out = dir.path().join("solo.json");
    let (code, stdout, err) = run(&[
        "target",
        raw.to_str().unwrap(),
        "--allow-uncalibrated",
        "--object",
        "Solo",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    let cat = json(&out);
    let t = &cat["targets"][0];
    assert_eq!(t["object"], "Solo");
    assert_eq!(t["status"], "ok", "{t}");
    let truth = json(&raw.join("truth.json"));
    let tt = &truth["targets"][0]["components"];
    for i in 0..2 {
        let c = &t["components"][i];
        for k in ["q", "u"] {
            let (got, want) = (c[k].as_f64().unwrap(), tt[i][k].as_f64().unwrap());
            let sigma = c[format!("sigma_{k}")].as_f64().unwrap();
            assert!(sigma > 0.0 && sigma < 0.01, "{k}: sigma {sigma}");
            assert!(
                ((got - want) / sigma).abs() < 5.0,
                "component {i} {k}: {got} vs {want} +- {sigma}"
            );
        }
    }
    assert!(cat["provenance"].is_object(), "provenance missing");

    // An object that is not in the input: exit 1, nothing written, the name in the message.
    let none = dir.path().join("none.json");
    let (code, _, err) = run(&[
        "target",
        raw.to_str().unwrap(),
        "--allow-uncalibrated",
        "--object",
        "Nobody",
        "-o",
        none.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("Nobody"), "{err}");
    assert!(err.contains("objects found: 'Solo'"), "{err}");
    assert!(!err.contains("did you mean"), "nothing is close to Nobody: {err}");
    assert!(!none.exists());
    // A name that differs in case and blanks, or by one letter: the close match is named.
    for wrong in ["solo", "SO LO", "Sola"] {
        let (code, _, err) = run(&[
            "target",
            raw.to_str().unwrap(),
            "--allow-uncalibrated",
            "--object",
            wrong,
            "-o",
            none.to_str().unwrap(),
        ]);
        assert_eq!(code, 1, "{err}");
        assert!(
            err.contains(&format!("object '{wrong}'")) && err.contains("did you mean --object 'Solo'?"),
            "{wrong}: {err}"
        );
        assert!(!none.exists());
    }
}

#[test]
fn bench_commands_print_figures() {
    let (code, stdout, err) = run(&["bench", "sim", "--repeats", "3"]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("ms"), "{stdout}");
    let (code, stdout, err) = run(&["bench", "stages", "--repeats", "1"]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("ms"), "{stdout}");
    let (code, stdout, err) = run(&["bench", "night", "--targets", "2", "--repeats", "1"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(stdout.to_lowercase().contains("wall"), "{stdout}");
}

/// `simulate -o DIR` into a folder that holds another scene's night refuses before writing
/// (it used to add its frames and overwrite the other truth.json with exit 0); the same
/// scene again into its own folder is fine.
#[test]
fn simulate_refuses_a_folder_holding_another_night() {
    let dir = tempfile::tempdir().unwrap();
    let scene = |name: &str| {
        let p = dir.path().join(format!("{name}.toml"));
        std::fs::write(
            &p,
            format!(
                "name = \"{name}\"\nseed = 3\neffects = [\"psf\", \"sky\"]\n[observation]\n\
                 orientations_deg = [0.0, 45.0]\ndithers = 2\n{}",
                common::ALPHA_BETA
            ),
        )
        .unwrap();
        p
    };
    let (a, b) = (scene("first"), scene("second"));
    let night = dir.path().join("night");
    let sim =
        |scene: &std::path::Path| run(&["simulate", scene.to_str().unwrap(), "-o", night.to_str().unwrap(), "-q"]);
    let (code, _, err) = sim(&a);
    assert_eq!(code, 0, "{err}");
    let truth = std::fs::read(night.join("truth.json")).unwrap();
    let before: Vec<_> = std::fs::read_dir(&night)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    let (code, _, err) = sim(&b);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("is not a file of this scene") && err.contains("night"),
        "{err}"
    );
    let after: Vec<_> = std::fs::read_dir(&night)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(before.len(), after.len(), "nothing written");
    assert_eq!(
        std::fs::read(night.join("truth.json")).unwrap(),
        truth,
        "truth.json kept"
    );
    let (code, _, err) = sim(&a);
    assert_eq!(code, 0, "the same scene again: {err}");
}
