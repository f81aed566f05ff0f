//! Hostile but realistic use of the `sofipol` binary: each test simulates a
//! 2-target night, damages it or the command line in one way, and checks that nothing is
//! lost and nothing is silently wrong: the undamaged target is reduced exactly as in a
//! clean run, and every unused input is named under `failures`.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_hostile` runs these tests against
//! another build (how they were checked to fail before the fixes).
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use serde_json::Value;

mod common;
use common::{bin, json as catalog, run, ALPHA_BETA};

/// The simulated night's scene (Alpha and Beta from [`common::ALPHA_BETA`]).
fn scene_toml() -> String {
    format!(
        r#"
name = "hx"
seed = 7
effects = ["psf", "sky", "strips", "photon_noise", "read_noise"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
{ALPHA_BETA}"#
    )
}

/// A simulated 2-target night (Alpha, Beta; 2 orientations x 3 dithers) in `dir/night`.
fn night(dir: &Path) -> PathBuf {
    let n = dir.join("night");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, scene_toml()).unwrap();
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    n
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
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
    let (code, _, err) = run(&["night", s(n), "--allow-uncalibrated", "-o", s(&out), "-q", "--no-png"]);
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
        .args(["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "--no-png", "-v"])
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
        .args([
            "target",
            s(&n),
            "--allow-uncalibrated",
            "--object",
            "Beta",
            "-o",
            s(&out2),
        ])
        .stdout(Stdio::from(w))
        .status()
        .unwrap();
    assert_eq!(st.code(), Some(0), "{st:?}");
    assert_eq!(catalog(&out2)["targets"].as_array().unwrap().len(), 1);
}

fn components(t: &Value) -> &Value {
    &t["components"]
}

#[cfg(unix)]
#[test]
fn the_same_frame_reached_twice_is_used_once_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let clean = clean_catalog(dir.path(), &n);
    // A backup copy in a subfolder, a symlink alias, and the night given three times
    // (relative, ./relative, absolute).
    std::fs::create_dir(n.join("backup")).unwrap();
    std::fs::copy(n.join("SOFI_hx_Beta_02.fits"), n.join("backup/SOFI_hx_Beta_02.fits")).unwrap();
    std::os::unix::fs::symlink(n.join("SOFI_hx_Beta_05.fits"), n.join("alias.fits")).unwrap();
    let out = dir.path().join("cat.json");
    let o = Command::new(bin())
        .current_dir(dir.path())
        .args([
            "night",
            "night",
            "./night",
            s(&n),
            "--allow-uncalibrated",
            "-o",
            s(&out),
            "-q",
            "--no-png",
        ])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    let c = catalog(&out);
    for name in ["Alpha", "Beta"] {
        assert_eq!(target(&c, name)["status"], "ok", "{name}");
        // Bit-identical to the clean night: no frame used twice (sigma would shrink).
        assert_eq!(components(target(&c, name)), components(target(&clean, name)), "{name}");
    }
    let f = failures(&c);
    assert_eq!(f.len(), 2, "{f:?}");
    assert!(
        f.iter()
            .any(|(file, e)| file.ends_with("alias.fits") && e.contains("duplicate of")),
        "{f:?}"
    );
    assert!(
        f.iter()
            .any(|(file, e)| file.ends_with("backup/SOFI_hx_Beta_02.fits") && e.contains("SOFI_hx_Beta_02.fits")),
        "{f:?}"
    );
}

#[test]
fn output_onto_an_input_or_a_directory_or_an_unwritable_place_is_refused_before_the_reduction() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let frame = n.join("SOFI_hx_Alpha_01.fits");
    let before = std::fs::read(&frame).unwrap();
    for (o, want) in [
        (frame.clone(), "input"),
        (n.join("./SOFI_hx_Beta_01.fits"), "input"),
        (n.clone(), "directory"),
        (PathBuf::from("/proc/sofipol-cat.json"), "cannot create"),
    ] {
        let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&o), "--no-png"]);
        assert_eq!(code, 1, "-o {}: {err}", o.display());
        assert!(err.contains(want) && err.contains(s(&o)), "-o {}: {err}", o.display());
        // Refused before any target was reduced.
        assert!(!err.contains("[1/2]"), "{err}");
        let (code, _, err) = run(&[
            "target",
            s(&n),
            "--allow-uncalibrated",
            "--object",
            "Alpha",
            "-o",
            s(&o),
        ]);
        assert_eq!(code, 1, "target -o {}: {err}", o.display());
    }
    assert_eq!(std::fs::read(&frame).unwrap(), before, "an input frame was overwritten");
    // merge onto one of its own inputs.
    let c = dir.path().join("c.json");
    let (code, _, _) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&c), "-q", "--no-png"]);
    assert_eq!(code, 0);
    let c_before = std::fs::read(&c).unwrap();
    let (code, _, err) = run(&["merge", s(&c), "-o", s(&c), "--allow-partial"]);
    assert_eq!(code, 1, "{err}");
    assert_eq!(std::fs::read(&c).unwrap(), c_before);
}

#[test]
fn merge_refuses_missing_shards_and_shards_with_different_parameters() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let sh = |k: &str, extra: &[&str]| {
        let out = dir
            .path()
            .join(format!("s{}{}.json", k.replace('/', "of"), extra.len()));
        let mut a = vec![
            "night",
            s(&n),
            "--allow-uncalibrated",
            "-o",
            s(&out),
            "-q",
            "--no-png",
            "--shard",
            k,
        ];
        a.extend_from_slice(extra);
        let (code, _, err) = run(&a);
        assert!(code == 0 || code == 2, "{err}");
        out
    };
    let (s1, s2, s3) = (sh("1/3", &[]), sh("2/3", &[]), sh("3/3", &[]));
    let s2b = sh("2/3", &["--aperture-fwhm", "2.5"]);
    let m = dir.path().join("m.json");
    // Complete and consistent: merged.
    let (code, _, err) = run(&["merge", s(&s1), s(&s2), s(&s3), "-o", s(&m)]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(catalog(&m)["targets"].as_array().unwrap().len(), 2);
    // A shard missing: refused, naming it; --allow-partial merges, says so, exits 2.
    std::fs::remove_file(&m).unwrap();
    let (code, _, err) = run(&["merge", s(&s1), s(&s3), "-o", s(&m)]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("2/3") && err.contains("--allow-partial"), "{err}");
    assert!(!m.exists());
    let (code, _, err) = run(&["merge", s(&s1), s(&s3), "-o", s(&m), "--allow-partial"]);
    assert_eq!(code, 2, "{err}");
    let ms = catalog(&m)["provenance"]["missing_shards"].clone();
    assert!(
        ms.as_array().unwrap().len() == 1 && ms[0].as_str().unwrap().starts_with("2/3 of"),
        "{ms}"
    );
    // A shard given twice, or run with other parameters: refused.
    let (code, _, err) = run(&["merge", s(&s1), s(&s2), s(&s2b), s(&s3), "-o", s(&m)]);
    assert_eq!(code, 1, "{err}");
    let (code, _, err) = run(&["merge", s(&s1), s(&s2b), s(&s3), "-o", s(&m)]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("aperture_fwhm") && err.contains(s(&s2b)), "{err}");
}

#[test]
fn an_empty_or_fits_less_night_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    std::fs::write(dir.path().join("notes.txt"), "no frames").unwrap();
    let out = dir.path().join("c.json");
    for d in [empty.clone(), dir.path().to_path_buf()] {
        let (code, _, err) = run(&["night", s(&d), "-o", s(&out), "--no-png"]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains("no FITS files") && err.contains(s(&d)), "{err}");
    }
    assert!(!out.exists());
}

#[test]
fn jobs_2048_is_capped_and_finishes_and_unused_input_counts_agree() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    std::fs::write(n.join("notes.fits"), "observing log\n").unwrap();
    let out = dir.path().join("c.json");
    let mut child = Command::new(bin())
        .args([
            "night",
            s(&n),
            "--allow-uncalibrated",
            "-o",
            s(&out),
            "--no-png",
            "--jobs",
            "2048",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed().as_secs() > 120 {
            child.kill().unwrap();
            panic!("--jobs 2048 did not finish in 120 s");
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let o = child.wait_with_output().unwrap();
    let (stdout, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--jobs 2048 capped at"), "{err}");
    // The start line and the end line count the same unused inputs.
    assert!(err.contains("1 inputs not used (found while scanning)"), "{err}");
    assert!(
        stdout.contains("1 inputs not used (1 found while scanning, 0 during the reduction)"),
        "{stdout}"
    );
    assert_eq!(catalog(&out)["targets"].as_array().unwrap().len(), 2);
}

#[test]
fn save_intermediate_inside_the_night_folder_is_skipped_by_the_next_run() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let clean = clean_catalog(dir.path(), &n);
    let products = n.join("products");
    let first = dir.path().join("first.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&first),
        "-q",
        "--no-png",
        "--save-intermediate",
        s(&products),
    ]);
    assert_eq!(code, 0, "{err}");
    let saved: Vec<_> = std::fs::read_dir(&products).unwrap().collect();
    assert_eq!(saved.len(), 12, "one sky-subtracted product per frame");
    // The next run over the same folder finds the products, skips them by name, and
    // reduces the raw frames exactly as before.
    let second = dir.path().join("second.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&second),
        "-q",
        "--no-png",
    ]);
    assert_eq!(code, 2, "{err}");
    let c = catalog(&second);
    for name in ["Alpha", "Beta"] {
        assert_eq!(target(&c, name)["status"], "ok", "{name}: {}", target(&c, name));
        assert_eq!(components(target(&c, name)), components(target(&clean, name)), "{name}");
    }
    let f = failures(&c);
    assert_eq!(f.len(), 12, "{f:?}");
    assert!(
        f.iter().all(|(file, e)| file.contains("products")
            && file.ends_with("_skysub.fits")
            && e.contains("sofipol product")),
        "{f:?}"
    );
}

/// Alpha (dithered as usual) and, simulated separately, Beta with every dither at one
/// position (jitter step 0), in one night folder.
fn night_with_a_stationary_target(dir: &Path) -> PathBuf {
    let n = night(dir);
    for f in std::fs::read_dir(&n).unwrap() {
        let p = f.unwrap().path();
        if p.to_str().unwrap().contains("Beta") {
            std::fs::remove_file(p).unwrap();
        }
    }
    let still = scene_toml()
        .replace("name = \"hx\"", "name = \"still\"")
        .replace("dithers = 3", "dithers = 3\njitter_step_px = 0.0");
    let still = still[..still.find("[[binary]]\nname = \"Alpha\"").unwrap()].to_string()
        + &still[still.find("[[binary]]\nname = \"Beta\"").unwrap()..];
    let scene = dir.join("still.toml");
    std::fs::write(&scene, still).unwrap();
    // Simulated apart (simulate refuses a folder holding another scene's frames), then
    // moved into the night's folder.
    let apart = dir.join("still_night");
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&apart), "-q"]);
    assert_eq!(code, 0, "{err}");
    for f in std::fs::read_dir(&apart).unwrap() {
        let p = f.unwrap().path();
        if p.extension().is_some_and(|e| e == "fits") {
            std::fs::rename(&p, n.join(p.file_name().unwrap())).unwrap();
        }
    }
    n
}

#[test]
fn all_dithers_at_one_position_are_refused_by_name_and_kept_out_of_the_night_mask() {
    let dir = tempfile::tempdir().unwrap();
    let n = night_with_a_stationary_target(dir.path());
    let out = dir.path().join("c.json");
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q", "--no-png"]);
    assert_eq!(code, 2, "{err}");
    let c = catalog(&out);
    let beta = target(&c, "Beta");
    // Refused clearly (it was `partial` with gamma off and `passes_cut: true`).
    assert_eq!(beta["status"], "failed", "{beta}");
    assert!(beta["error"].as_str().unwrap().contains("one position"), "{beta}");
    assert!(beta["components"].as_array().unwrap().is_empty(), "{beta}");
    // A failed target keeps its diagnostic flags.
    let flags = beta["flags"].as_array().unwrap();
    assert!(
        flags.iter().any(|f| f.as_str().unwrap().contains("one position")),
        "{beta}"
    );
    assert_eq!(target(&c, "Alpha")["status"], "ok");
    // The stationary star must not be taken for a detector defect.
    let from = c["provenance"]["night_bad_pixel_mask_from"].as_array().unwrap();
    assert!(from.iter().all(|f| !f.as_str().unwrap().contains("still")), "{from:?}");
}

#[test]
fn a_corrupt_naxis_of_100000_is_named_and_the_night_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let clean = clean_catalog(dir.path(), &n);
    let f = n.join("SOFI_hx_Alpha_01.fits");
    let mut b = std::fs::read(&f).unwrap();
    for key in [&b"NAXIS1  ="[..], &b"NAXIS2  ="[..]] {
        let at = (0..b.len() / 80)
            .map(|i| i * 80)
            .find(|&i| b[i..].starts_with(key))
            .unwrap();
        let card = format!("{:<8}= {:>20}", std::str::from_utf8(&key[..8]).unwrap().trim(), 100000);
        b[at..at + 30].copy_from_slice(card.as_bytes());
    }
    std::fs::write(&f, &b).unwrap();
    let out = dir.path().join("c.json");
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q", "--no-png"]);
    assert_eq!(code, 2, "{err}");
    let c = catalog(&out);
    // The night's superflat is built from frames of every target, so the damaged frame
    // changes Beta's flat slightly: Beta must agree with the clean night far within its
    // errors.
    let (now, before) = (components(target(&c, "Beta")), components(target(&clean, "Beta")));
    assert_eq!(now.as_array().unwrap().len(), 2);
    for (a, b) in now.as_array().unwrap().iter().zip(before.as_array().unwrap()) {
        for k in ["q", "u"] {
            let (x, y) = (a[k].as_f64().unwrap(), b[k].as_f64().unwrap());
            let sx = b[format!("sigma_{k}").as_str()].as_f64().unwrap();
            assert!((x - y).abs() < 0.1 * sx, "Beta {k}: {x} vs {y} (sigma {sx})");
        }
    }
    assert_ne!(target(&c, "Alpha")["status"], "ok");
    let fl = failures(&c);
    assert!(
        fl.iter()
            .any(|(file, e)| file.ends_with("SOFI_hx_Alpha_01.fits") && e.contains("corrupt header")),
        "{fl:?}"
    );
}

#[test]
fn unknown_keys_and_out_of_range_values_are_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let out = dir.path().join("c.json");
    let params = dir.path().join("p.toml");
    let prof = dir.path().join("prof.toml");
    std::fs::write(&prof, "[detector]\ngain = 5.6\n").unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec!["--set".into(), "detector.gian_e_per_adu=5".into()],
            "gian_e_per_adu",
        ),
        (vec!["--profile".into(), s(&prof).into()], "gain"),
        (vec!["--params".into(), s(&params).into()], "bad_pixels.window_px"),
    ];
    std::fs::write(&params, "[bad_pixels]\nwindow_px = 0\n").unwrap();
    for (extra, key) in cases {
        let mut a = vec!["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "--no-png"];
        a.extend(extra.iter().map(|x| x.as_str()));
        let (code, _, err) = run(&a);
        assert_eq!(code, 1, "{a:?}: {err}");
        assert!(err.contains(key), "{a:?}: {err}");
    }
    for (text, key) in [
        ("[sky.cosmic_rays]\nsigma_clip = nan\n", "sky.cosmic_rays.sigma_clip"),
        ("[bad_pixels]\nsigma = -1.0\n", "bad_pixels.sigma"),
    ] {
        std::fs::write(&params, text).unwrap();
        let (code, _, err) = run(&[
            "night",
            s(&n),
            "--allow-uncalibrated",
            "-o",
            s(&out),
            "--no-png",
            "--params",
            s(&params),
        ]);
        assert_eq!(code, 1, "{text}: {err}");
        assert!(err.contains(key), "{text}: {err}");
    }
    assert!(!out.exists());
    // A [sky] table with only `scaling` keeps cosmic-ray flagging (it silently dropped it).
    std::fs::write(&params, "[sky]\nscaling = \"additive\"\n").unwrap();
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&out),
        "-q",
        "--no-png",
        "--params",
        s(&params),
    ]);
    assert_eq!(code, 0, "{err}");
    let sky = &catalog(&out)["provenance"]["parameters"]["sky"];
    assert_eq!(sky["cosmic_rays"]["enabled"], true, "{sky}");
    assert_eq!(sky["scaling"], "additive", "{sky}");
}

/// One NaN pixel used to fail the whole target and
/// an all-NaN or foreign-size frame was never named. A non-finite pixel is now a bad pixel;
/// a frame unusable as a whole is dropped by name and the other dithers carry on.
#[test]
fn a_nan_pixel_is_a_bad_pixel_and_unusable_frames_are_dropped_by_name() {
    use sofipol_calib::fits;
    let dir = tempfile::tempdir().unwrap();
    // 4 dithers, so that each orientation keeps 3 after the damage (2 dithers cannot
    // sky-subtract each other well: docs/accuracy.md).
    let n = dir.path().join("night");
    let scene = dir.path().join("scene4.toml");
    std::fs::write(&scene, scene_toml().replace("dithers = 3", "dithers = 4")).unwrap();
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    // The scene has no pixel response: runs without the night's superflat, which the dropped
    // frames would change for Beta too, so that Beta can be compared bit for bit.
    let clean_out = dir.path().join("clean.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&clean_out),
        "-q",
        "--no-png",
        "--no-flat",
    ]);
    assert_eq!(code, 0, "{err}");
    let clean = catalog(&clean_out);
    let frame = |k: u32| n.join(format!("SOFI_hx_Alpha_{k:02}.fits"));
    // One NaN and one Inf pixel in a target strip of dither 1, away from the stars.
    let mut f1 = fits::read_frame(&frame(1)).unwrap();
    f1.data[[400, 100]] = f32::NAN;
    f1.data[[600, 900]] = f32::INFINITY;
    fits::write_frame(&frame(1), &f1, &Default::default()).unwrap();
    // Dither 2 (orientation 1): every pixel NaN. Dither 6 (orientation 2): another size.
    let mut f2 = fits::read_frame(&frame(2)).unwrap();
    f2.data.fill(f32::NAN);
    fits::write_frame(&frame(2), &f2, &Default::default()).unwrap();
    let mut f6 = fits::read_frame(&frame(6)).unwrap();
    f6.data = f6.data.slice(ndarray::s![..512, ..512]).to_owned();
    f6.mask = f6.mask.slice(ndarray::s![..512, ..512]).to_owned();
    fits::write_frame(&frame(6), &f6, &Default::default()).unwrap();

    let out = dir.path().join("c.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&out),
        "-q",
        "--no-png",
        "--no-flat",
    ]);
    assert_eq!(code, 2, "{err}");
    let c = catalog(&out);
    let alpha = target(&c, "Alpha");
    assert_eq!(alpha["status"], "partial", "{alpha}");
    let comps = alpha["components"].as_array().unwrap();
    assert_eq!(comps.len(), 2, "{alpha}");
    for comp in comps {
        // Every number the schema promises (a NaN would be written as null).
        for k in [
            "q",
            "u",
            "sigma_q",
            "sigma_u",
            "p",
            "sigma_p",
            "p_debiased",
            "gamma_deg",
            "sigma_gamma_deg",
        ] {
            assert!(comp[k].as_f64().is_some_and(f64::is_finite), "{k}: {comp}");
        }
    }
    let fl = failures(&c);
    let named = |k: u32, why: &str| {
        fl.iter()
            .any(|(file, e)| file.ends_with(&format!("Alpha_{k:02}.fits")) && e.contains(why))
    };
    assert!(named(2, "not finite"), "{fl:?}");
    assert!(named(6, "detector is 1024 x 1024"), "{fl:?}");
    assert!(!fl.iter().any(|(file, _)| file.ends_with("Alpha_01.fits")), "{fl:?}");
    // Beta is untouched.
    assert_eq!(target(&c, "Beta")["components"], target(&clean, "Beta")["components"]);
    assert_eq!(target(&c, "Beta")["status"], "ok");
}

/// 2 dithers: every target of a night sits on the same pixels for a given dither
/// offset, so with 2 dithers per orientation half of the frames picked for the night's
/// bad-pixel mask held a star on the same pixels: the mask took the star cores for
/// defects and the primaries came out unmeasured ("photometry failed", q and u null, the
/// standards' F wrong alike). The night mask is now stacked per dither position: both
/// components of both targets are measured and agree with the simulated truth.
#[test]
fn a_night_of_two_dithers_per_orientation_measures_every_component() {
    let dir = tempfile::tempdir().unwrap();
    let n = dir.path().join("night");
    let scene = dir.path().join("scene2.toml");
    std::fs::write(&scene, scene_toml().replace("dithers = 3", "dithers = 2")).unwrap();
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    let truth = catalog(&n.join("truth.json"));
    std::fs::remove_file(n.join("truth.json")).unwrap();
    let out = dir.path().join("c.json");
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q", "--no-png"]);
    assert_eq!(code, 0, "{err}");
    let c = catalog(&out);
    assert!(
        c["provenance"]["night_bad_pixel_mask_from"]
            .as_array()
            .is_some_and(|a| a.len() >= 3),
        "the night mask was not built: {}",
        c["provenance"]
    );
    for name in ["Alpha", "Beta"] {
        let t = target(&c, name);
        assert_eq!(t["status"], "ok", "{t}");
        let tt = truth["targets"]
            .as_array()
            .unwrap()
            .iter()
            .find(|x| x["object"] == name)
            .unwrap();
        for (comp, tc) in components(t)
            .as_array()
            .unwrap()
            .iter()
            .zip(tt["components"].as_array().unwrap())
        {
            for (k, sk) in [("q", "sigma_q"), ("u", "sigma_u")] {
                let (v, sig, truth) = (
                    comp[k].as_f64().unwrap_or(f64::NAN),
                    comp[sk].as_f64().unwrap_or(f64::NAN),
                    tc[k].as_f64().unwrap(),
                );
                assert!(
                    ((v - truth) / sig).abs() < 4.0,
                    "{name} {}: {k} {v} +- {sig}, truth {truth}: {comp}",
                    comp["name"]
                );
            }
        }
    }
}

/// A sequence of another frame size (Gamma, 1024 rows x 512 columns,
/// observed first in the night) used to give the night's bad-pixel mask its size: every valid target then
/// failed on the mask. The night mask is built only from frames of the profile's detector
/// size; Gamma's frames are refused by name ("detector is 1024 x 1024") and Alpha and
/// Beta come out exactly as in a night without Gamma.
#[test]
fn a_sequence_of_another_frame_size_fails_no_valid_target_via_the_night_mask() {
    use sofipol_calib::fits;
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    // Without the night's superflat, which Gamma's frames would change (not the point here).
    let clean_out = dir.path().join("clean.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&clean_out),
        "-q",
        "--no-png",
        "--no-flat",
    ]);
    assert_eq!(code, 0, "{err}");
    let clean = catalog(&clean_out);
    let gamma = scene_toml()
        .replace("name = \"hx\"", "name = \"small\"")
        .replace("dithers = 3", "dithers = 3\nstart_ut = \"00:10:00\"")
        .replace("name = \"Alpha\"", "name = \"Gamma\"")
        .replace("name = \"Beta\"", "name = \"Delta\"");
    let gamma = gamma[..gamma.find("[[binary]]\nname = \"Delta\"").unwrap()].to_string();
    let scene = dir.path().join("gamma.toml");
    std::fs::write(&scene, gamma).unwrap();
    let g = dir.path().join("gamma");
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&g), "-q"]);
    assert_eq!(code, 0, "{err}");
    let mut n_small = 0;
    for e in std::fs::read_dir(&g).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "fits") {
            let mut f = fits::read_frame(&p).unwrap();
            f.data = f.data.slice(ndarray::s![.., ..512]).to_owned();
            f.mask = f.mask.slice(ndarray::s![.., ..512]).to_owned();
            fits::write_frame(&n.join(p.file_name().unwrap()), &f, &Default::default()).unwrap();
            n_small += 1;
        }
    }
    assert_eq!(n_small, 6);
    let out = dir.path().join("c.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&out),
        "-q",
        "--no-png",
        "--no-flat",
    ]);
    assert_eq!(code, 2, "{err}");
    let c = catalog(&out);
    for name in ["Alpha", "Beta"] {
        assert_eq!(target(&c, name)["status"], "ok", "{}", target(&c, name));
        assert_eq!(
            target(&c, name)["components"],
            target(&clean, name)["components"],
            "{name}"
        );
    }
    assert_eq!(target(&c, "Gamma")["status"], "failed");
    let fl = failures(&c);
    let small: Vec<_> = fl.iter().filter(|(f, _)| f.contains("Gamma")).collect();
    assert_eq!(small.len(), 6, "{fl:?}");
    assert!(
        small.iter().all(|(_, e)| e.contains("detector is 1024 x 1024")),
        "{fl:?}"
    );
    let from = c["provenance"]["night_bad_pixel_mask_from"].as_array().unwrap();
    assert!(
        from.len() >= 3 && from.iter().all(|f| !f.as_str().unwrap().contains("Gamma")),
        "{from:?}"
    );
}

/// `export -o` onto its input catalog (the same path, or an alias through `..` or a
/// symlink) is refused before anything is written, like `night`/`target -o`; the
/// catalog is left as it was.
#[test]
fn export_never_overwrites_its_input_catalog() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    clean_catalog(dir.path(), &n);
    let cat = dir.path().join("clean.json");
    let before = std::fs::read(&cat).unwrap();
    let alias = dir.path().join("night").join("..").join("clean.json");
    let link = dir.path().join("link.json");
    #[cfg(unix)]
    std::os::unix::fs::symlink(&cat, &link).unwrap();
    for (out, fmt) in [(&cat, "ecsv"), (&alias, "csv"), (&link, "fits")] {
        if !out.exists() {
            continue;
        }
        let (code, _, err) = run(&["export", s(&cat), "--format", fmt, "-o", s(out)]);
        assert_ne!(code, 0, "{}: {err}", out.display());
        assert!(err.contains("never overwrites its inputs"), "{err}");
        assert_eq!(
            std::fs::read(&cat).unwrap(),
            before,
            "{} overwrote the catalog",
            out.display()
        );
    }
    // A directory is refused too; a fresh file is written.
    let (code, _, err) = run(&["export", s(&cat), "-o", s(dir.path())]);
    assert_ne!(code, 0, "{err}");
    let ok = dir.path().join("t.ecsv");
    let (code, _, err) = run(&["export", s(&cat), "-o", s(&ok)]);
    assert_eq!(code, 0, "{err}");
    assert!(ok.is_file());
}

/// `--flat FILE` of the wrong size is refused once, by name (a failure "calibration flat:
/// ... detector is 1024 x 1024: not used", exit 2, provenance `flat.mode` "none"), and the
/// targets are reduced exactly as with `--no-flat`. A flat with NaN pixels: they are bad
/// pixels of the flat (counted in the provenance), so a dither whose aperture holds one
/// is flagged `bad_pixels`: never a NaN, and a component from such dithers only never
/// passes the cut.
#[test]
fn a_flat_file_of_the_wrong_size_or_with_nan_pixels_is_refused_or_flagged_by_name() {
    use sofipol_calib::fits;
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let noflat = dir.path().join("noflat.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&noflat),
        "-q",
        "--no-png",
        "--no-flat",
    ]);
    assert_eq!(code, 0, "{err}");
    let noflat = catalog(&noflat);
    let mut f = fits::read_frame(&n.join("SOFI_hx_Alpha_01.fits")).unwrap();
    let small = dir.path().join("small_flat.fits");
    let mut g = f.clone();
    g.data = ndarray::Array2::from_elem((512, 512), 1.0);
    g.mask = ndarray::Array2::zeros((512, 512));
    fits::write_frame(&small, &g, &Default::default()).unwrap();
    let out = dir.path().join("c.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&out),
        "-q",
        "--no-png",
        "--flat",
        s(&small),
    ]);
    assert_eq!(code, 2, "{err}");
    let c = catalog(&out);
    let fl = failures(&c);
    assert!(
        fl.iter()
            .any(|(file, e)| file.ends_with("small_flat.fits") && e.contains("detector is 1024 x 1024: not used")),
        "{fl:?}"
    );
    assert_eq!(c["provenance"]["flat"]["mode"], "none");
    for name in ["Alpha", "Beta"] {
        assert_eq!(
            target(&c, name)["components"],
            target(&noflat, name)["components"],
            "{name}"
        );
    }

    // NaN pixels on every 7th diagonal: in every aperture.
    f.data = ndarray::Array2::from_shape_fn((1024, 1024), |(y, x)| if (x + y) % 7 == 0 { f32::NAN } else { 1.0 });
    f.mask = ndarray::Array2::zeros((1024, 1024));
    let nan = dir.path().join("nan_flat.fits");
    fits::write_frame(&nan, &f, &Default::default()).unwrap();
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&out),
        "-q",
        "--no-png",
        "--flat",
        s(&nan),
    ]);
    assert!(code == 0 || code == 2, "{err}");
    let c = catalog(&out);
    let bad = c["provenance"]["flat"]["flats"][0]["bad_pixels"].as_u64().unwrap();
    assert!(bad > 140_000, "{}", c["provenance"]["flat"]);
    for name in ["Alpha", "Beta"] {
        for comp in components(target(&c, name)).as_array().unwrap() {
            assert!(comp["q"].as_f64().is_some_and(f64::is_finite), "{comp}");
            let flags: Vec<&str> = comp["flags"]
                .as_array()
                .unwrap()
                .iter()
                .map(|f| f.as_str().unwrap())
                .collect();
            assert!(flags.iter().any(|f| f.starts_with("bad_pixels: ")), "{name}: {flags:?}");
            assert!(
                !flags.contains(&"used_flagged_dithers") || comp["passes_cut"] == false,
                "{comp}"
            );
        }
    }
}

/// A named pipe among the night's files (`*.fits`: a copy tool's leftover, or a file being
/// streamed in) is named as "not a regular file" and the night goes on, the targets as in
/// a clean run. Reading it would wait for a writer forever: the run is killed after 120 s.
#[test]
fn a_named_pipe_among_the_files_is_named_and_the_night_does_not_wait_on_it() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let clean = clean_catalog(dir.path(), &n);
    let pipe = n.join("SOFI_hx_zz_pipe.fits");
    if !Command::new("mkfifo").arg(&pipe).status().is_ok_and(|s| s.success()) {
        eprintln!("no mkfifo here: nothing to check");
        return;
    }
    let out = dir.path().join("c.json");
    let mut child = common::sofipol()
        .args(["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q", "--no-png"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    let code = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st.code();
        }
        if t0.elapsed().as_secs() > 120 {
            let _ = child.kill();
            panic!("the night waited on the named pipe");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    assert_eq!(code, Some(2));
    let c = catalog(&out);
    let fl = failures(&c);
    assert!(
        fl.iter()
            .any(|(file, e)| file.ends_with("SOFI_hx_zz_pipe.fits") && e == "not a regular file"),
        "{fl:?}"
    );
    for name in ["Alpha", "Beta"] {
        assert_eq!(components(target(&c, name)), components(target(&clean, name)), "{name}");
    }
}
