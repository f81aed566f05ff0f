//! `sofipol watch` against a hostile night: a frame that vanishes or is refused after its
//! template was reduced, a frame refused from the start, the watched folder taken away, a
//! frame replaced by another of the same size and time, SIGTERM with a file half-written,
//! a full disk, and a TPL NEXP below the frame count. A target once in the catalog never
//! leaves it, nothing waits for the template time-out when every frame is there, and
//! nothing is lost silently. Every test uses a template time-out of 600 s, so a test that
//! waited for it would fail on its own time limit.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_watch_hostile` runs these tests
//! against another build.
mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use common::*;
use serde_json::Value;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 2-binary night (Alpha, Beta: 2 orientations x 3 dithers, TPL NEXP 6) with an
/// unpolarized and a polarized standard, in `dir/night`.
fn night_with_standards(dir: &Path) -> PathBuf {
    instrument_night(dir, "live", 11, TWO_STANDARDS)
}

/// Every frame of the night copied into `dir/live` at once.
fn live_copy(dir: &Path, n: &Path) -> PathBuf {
    let live = dir.join("live");
    std::fs::create_dir(&live).unwrap();
    for e in std::fs::read_dir(n).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, live.join(p.file_name().unwrap())).unwrap();
    }
    live
}

/// `sofipol watch DIR -o OUT --template-timeout 600 --poll 0.2 ARGS`.
fn start_watch(dir: &Path, out: &Path, args: &[&str]) -> Child {
    sofipol()
        .args([
            "watch",
            s(dir),
            "-o",
            s(out),
            "--template-timeout",
            "600",
            "--poll",
            "0.2",
        ])
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start sofipol watch")
}

/// Wait for the child (at most `limit`), then (exit code, stdout, stderr).
fn finish(child: Child, limit: Duration) -> (i32, String, String) {
    finish_child(child, limit)
}

/// SIGTERM to the child.
fn terminate(child: &Child) {
    let ok = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(ok.success());
}

/// The catalog at `out` once `cond` holds for it (at most `limit`; the child is killed and
/// the test fails otherwise).
fn catalog_when(child: &mut Child, out: &Path, limit: Duration, what: &str, cond: impl Fn(&Value) -> bool) -> Value {
    let t = Instant::now();
    loop {
        if let Some(c) = std::fs::read_to_string(out)
            .ok()
            .and_then(|s| serde_json::from_str::<Value>(&s).ok())
        {
            if cond(&c) {
                return c;
            }
        }
        if t.elapsed() > limit || child.try_wait().unwrap().is_some() {
            child.kill().ok();
            let c = std::fs::read_to_string(out).unwrap_or_default();
            panic!(
                "{what}: not seen in {:?}; catalog:\n{}",
                t.elapsed(),
                &c[..c.len().min(3000)]
            );
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn objects(c: &Value) -> Vec<(String, String)> {
    c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            (
                t["object"].as_str().unwrap().to_string(),
                t["status"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

fn has_both(c: &Value) -> bool {
    let o = objects(c);
    o.iter().any(|(n, _)| n == "Alpha") && o.iter().any(|(n, _)| n == "Beta")
}

fn calibrated(c: &Value) -> bool {
    c["targets"].as_array().unwrap().iter().all(|t| {
        t["components"]
            .as_array()
            .unwrap()
            .iter()
            .all(|x| !x["flags"].as_array().unwrap().iter().any(|f| f == "uncalibrated"))
    })
}

fn failure_of(c: &Value, name: &str) -> Option<String> {
    c["failures"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["file"].as_str().unwrap().ends_with(name))
        .map(|f| f["error"].as_str().unwrap().to_string())
}

fn frame_named(live: &Path, part: &str, k: usize) -> PathBuf {
    let mut v: Vec<PathBuf> = std::fs::read_dir(live)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().to_str().unwrap().contains(part))
        .collect();
    v.sort();
    v[k].clone()
}

/// Replace the value of header card `key` of the FITS file `p`.
fn set_card(p: &Path, key: &str, value: &str) {
    let mut b = std::fs::read(p).unwrap();
    let pat = if key.len() > 8 {
        format!("{key} =")
    } else {
        format!("{key:<8}=")
    };
    let i = (0..2880 * 4)
        .step_by(80)
        .find(|&i| b[i..].starts_with(pat.as_bytes()))
        .unwrap_or_else(|| panic!("no card {key}"));
    let mut c = format!("{pat} {value}").into_bytes();
    c.resize(80, b' ');
    b[i..i + 80].copy_from_slice(&c);
    std::fs::write(p, b).unwrap();
}

#[test]
fn a_frame_that_vanishes_after_its_template_was_reduced_never_takes_the_target_out() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let live = live_copy(d.path(), &n);
    let out = d.path().join("w.json");
    let mut child = start_watch(&live, &out, &["-v"]);
    let limit = Duration::from_secs(60);
    catalog_when(&mut child, &out, limit, "both targets calibrated", |c| {
        has_both(c) && calibrated(c)
    });
    // A science frame deleted, a standard's frame moved out of the folder.
    let alpha1 = frame_named(&live, "_Alpha_", 0);
    std::fs::remove_file(&alpha1).unwrap();
    let std1 = frame_named(&live, "_HD_204827_", 0);
    std::fs::rename(&std1, d.path().join("moved.fits")).unwrap();
    let alpha_name = alpha1.file_name().unwrap().to_str().unwrap().to_string();
    let c = catalog_when(&mut child, &out, limit, "Alpha partial naming the frame", |c| {
        failure_of(c, &alpha_name).is_some()
    });
    assert!(has_both(&c), "{:?}", objects(&c));
    assert!(calibrated(&c), "the calibration left with the standard's frame");
    assert!(
        objects(&c).contains(&("Alpha".into(), "partial".into())),
        "{:?}",
        objects(&c)
    );
    assert!(failure_of(&c, &alpha_name).unwrap().contains("vanished"));
    // A frame replaced by an incomplete one (a copy started over it): Beta stays in the
    // catalog, reduced without it at once.
    let beta3 = frame_named(&live, "_Beta_", 2);
    let bytes = std::fs::read(&beta3).unwrap();
    std::fs::write(&beta3, &bytes[..bytes.len() / 3]).unwrap();
    let c = catalog_when(&mut child, &out, limit, "Beta partial without its third frame", |c| {
        objects(c).contains(&("Beta".into(), "partial".into()))
    });
    assert!(has_both(&c) && calibrated(&c), "{:?}", objects(&c));
    std::fs::write(&beta3, &bytes).unwrap();
    catalog_when(&mut child, &out, limit, "Beta ok again", |c| {
        objects(c).contains(&("Beta".into(), "ok".into()))
    });
    // A frame renamed within the folder is found again, not lost.
    let beta1 = frame_named(&live, "_Beta_", 0);
    std::fs::rename(&beta1, live.join("renamed_beta.fits")).unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    terminate(&child);
    let (code, _, stderr) = finish(child, limit);
    assert_eq!(code, 2, "{stderr}");
    let c = json(&out);
    assert!(has_both(&c) && calibrated(&c), "{:?}", objects(&c));
    assert!(
        objects(&c).contains(&("Beta".into(), "ok".into())),
        "{:?}\n{stderr}",
        objects(&c)
    );
    assert!(failure_of(&c, beta1.file_name().unwrap().to_str().unwrap()).is_none());
}

/// All frames present from the start, Beta's fifth damaged by `damage`: watch (template
/// time-out 600 s) must reduce Beta at once as `partial` and stop when idle within a
/// minute. Returns why the damaged frame is under `failures`.
fn beta_reduced_at_once_with_a_damaged_frame(damage: impl Fn(&Path)) -> String {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let live = live_copy(d.path(), &n);
    let bad = frame_named(&live, "_Beta_", 4);
    damage(&bad);
    let out = d.path().join("w.json");
    let t0 = Instant::now();
    let child = start_watch(&live, &out, &["--exit-when-idle", "1"]);
    let (code, stdout, stderr) = finish(child, Duration::from_secs(90));
    assert_eq!(code, 2, "{stdout}\n{stderr}");
    assert!(t0.elapsed() < Duration::from_secs(60), "{:?}", t0.elapsed());
    let c = json(&out);
    assert!(
        objects(&c).contains(&("Beta".into(), "partial".into())),
        "{:?}",
        objects(&c)
    );
    failure_of(&c, bad.file_name().unwrap().to_str().unwrap()).expect("the damaged frame is named")
}

#[test]
fn a_frame_refused_from_the_start_completes_its_template_at_once() {
    let why = beta_reduced_at_once_with_a_damaged_frame(|f| set_card(f, "MJD-OBS", "'x'"));
    assert!(why.contains("MJD-OBS"), "{why}");
}

#[test]
fn a_frame_whose_header_cannot_be_read_counts_for_the_template_being_observed() {
    // Garbage (a transfer gone wrong): no header names its template.
    beta_reduced_at_once_with_a_damaged_frame(|f| std::fs::write(f, vec![b'x'; 8640]).unwrap());
}

#[test]
fn the_watched_folder_taken_away_keeps_the_catalog_and_never_exits_0() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let live = live_copy(d.path(), &n);
    let out = d.path().join("w.json");
    let mut child = start_watch(&live, &out, &["--exit-when-idle", "3"]);
    let before = catalog_when(&mut child, &out, Duration::from_secs(60), "both targets", has_both);
    std::fs::rename(&live, d.path().join("elsewhere")).unwrap();
    let (code, _, stderr) = finish(child, Duration::from_secs(60));
    assert_eq!(code, 2, "{stderr}");
    assert!(
        stderr.contains("WARNING: the watched folder") && stderr.contains("gone"),
        "{stderr}"
    );
    let after = json(&out);
    assert_eq!(after["targets"], before["targets"]);
}

#[test]
fn a_frame_replaced_by_another_of_the_same_size_and_time_is_reduced_again() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let live = live_copy(d.path(), &n);
    let out = d.path().join("w.json");
    let mut child = start_watch(&live, &out, &[]);
    catalog_when(&mut child, &out, Duration::from_secs(60), "both targets", has_both);
    // Alpha's first frame becomes a copy of its second, with the first's modification time.
    let (a1, a2) = (frame_named(&live, "_Alpha_", 0), frame_named(&live, "_Alpha_", 1));
    let tmp = d.path().join("a1.fits");
    std::fs::copy(&a2, &tmp).unwrap();
    let st = std::process::Command::new("touch")
        .arg("-r")
        .arg(&a1)
        .arg(&tmp)
        .status()
        .unwrap();
    assert!(st.success());
    assert_eq!(
        std::fs::metadata(&tmp).unwrap().len(),
        std::fs::metadata(&a1).unwrap().len()
    );
    std::fs::rename(&tmp, &a1).unwrap();
    let names = [a1, a2].map(|p| p.file_name().unwrap().to_str().unwrap().to_string());
    // The copy is the same exposure as the second frame: one of the two is named as a
    // duplicate of the other.
    catalog_when(
        &mut child,
        &out,
        Duration::from_secs(60),
        "the replaced frame named",
        |c| {
            names
                .iter()
                .any(|n| failure_of(c, n).is_some_and(|e| e.contains("duplicate")))
        },
    );
    terminate(&child);
    finish(child, Duration::from_secs(60));
}

#[test]
fn sigterm_makes_the_final_update_and_names_the_file_still_being_written() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let live = live_copy(d.path(), &n);
    // Alpha still being observed: its sixth frame half-written.
    let a5 = frame_named(&live, "_Alpha_", 5);
    let bytes = std::fs::read(&a5).unwrap();
    std::fs::write(&a5, &bytes[..bytes.len() / 2]).unwrap();
    let out = d.path().join("w.json");
    let mut child = start_watch(&live, &out, &["--file-timeout", "600"]);
    catalog_when(&mut child, &out, Duration::from_secs(60), "Beta", |c| {
        objects(c).iter().any(|(o, _)| o == "Beta")
    });
    std::thread::sleep(Duration::from_millis(500));
    terminate(&child);
    let (code, _, stderr) = finish(child, Duration::from_secs(60));
    assert_eq!(code, 2, "{stderr}");
    let c = json(&out);
    // The final update reduced the template still being observed.
    assert!(
        objects(&c).contains(&("Alpha".into(), "partial".into())),
        "{:?}\n{stderr}",
        objects(&c)
    );
    let name = a5.file_name().unwrap().to_str().unwrap();
    let why = failure_of(&c, name).unwrap_or_else(|| panic!("{name} not named: {}", c["failures"]));
    assert!(why.contains("still being written"), "{why}");
    assert!(
        stderr.contains(name) && stderr.contains("still being written"),
        "{stderr}"
    );
}

#[test]
fn a_full_disk_is_warned_about_and_the_catalog_written_once_there_is_room() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let live = live_copy(d.path(), &n);
    let disk = d.path().join("disk");
    std::fs::create_dir(&disk).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=2m", "tmpfs", s(&disk)])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("SKIPPED: a small file system cannot be mounted here (needs root and mount rights)");
        return;
    }
    struct Unmount(PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(&self.0).status();
        }
    }
    let _unmount = Unmount(disk.clone());
    // Fill the disk but for a few kB.
    let filler = disk.join("filler");
    let _ = std::fs::write(&filler, vec![0u8; 2 << 20]);
    let len = std::fs::metadata(&filler).unwrap().len();
    std::fs::write(&filler, vec![0u8; len as usize - 4096]).unwrap();
    let out = disk.join("w.json");
    let mut child = start_watch(&live, &out, &[]);
    std::thread::sleep(Duration::from_secs(3));
    assert!(child.try_wait().unwrap().is_none(), "watch ended on a full disk");
    std::fs::remove_file(&filler).unwrap();
    catalog_when(
        &mut child,
        &out,
        Duration::from_secs(60),
        "the catalog once there is room",
        has_both,
    );
    terminate(&child);
    let (code, _, stderr) = finish(child, Duration::from_secs(60));
    assert!(code == 0 || code == 2, "{stderr}");
    // Warned once, the reason said once (not repeated by the error's chain).
    assert_eq!(stderr.matches("could not be written").count(), 1, "{stderr}");
    assert_eq!(stderr.matches("No space left on device").count(), 1, "{stderr}");
    assert!(stderr.contains("catalog written at last"), "{stderr}");
}

#[test]
fn a_tpl_nexp_below_the_frame_count_is_not_trusted_and_gives_no_false_failure() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    for p in std::fs::read_dir(&n).unwrap().map(|e| e.unwrap().path()) {
        if p.to_str().unwrap().contains("_Alpha_") {
            set_card(&p, "HIERARCH ESO TPL NEXP", "2");
        }
    }
    let live = d.path().join("live");
    std::fs::create_dir(&live).unwrap();
    let out = d.path().join("w.json");
    let mut child = start_watch(&live, &out, &["-v"]);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&n).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort_by_key(|p| !p.to_str().unwrap().contains("_Alpha_"));
    for f in &files {
        std::fs::copy(f, live.join(f.file_name().unwrap())).unwrap();
        std::thread::sleep(Duration::from_millis(150));
    }
    catalog_when(&mut child, &out, Duration::from_secs(60), "Beta", |c| {
        objects(c).iter().any(|(o, _)| o == "Beta")
    });
    terminate(&child);
    let (code, stdout, stderr) = finish(child, Duration::from_secs(60));
    assert!(code == 0 || code == 2, "{stderr}");
    assert!(!stdout.contains("FAILED"), "{stdout}");
    assert!(
        stderr.contains("TPL NEXP = 2") && stderr.contains("the count is not trusted"),
        "{stderr}"
    );
    let w = json(&out);
    let night = d.path().join("night.json");
    let (code, _, err) = run(&["night", s(&live), "-o", s(&night), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{err}");
    let nt = json(&night);
    assert_eq!(w["targets"], nt["targets"]);
}

#[test]
fn a_state_path_that_is_a_folder_is_refused_before_anything_is_reduced() {
    let d = tempfile::tempdir().unwrap();
    let live = d.path().join("live");
    std::fs::create_dir(&live).unwrap();
    let out = d.path().join("w.json");
    std::fs::create_dir(d.path().join("w.json.state.json")).unwrap();
    let t0 = Instant::now();
    let child = start_watch(&live, &out, &["--exit-when-idle", "30"]);
    let (code, _, stderr) = finish(child, Duration::from_secs(20));
    assert_eq!(code, 1, "{stderr}");
    assert!(
        stderr.contains("w.json.state.json") && stderr.contains("not a regular file"),
        "{stderr}"
    );
    assert!(t0.elapsed() < Duration::from_secs(10));
    assert!(!out.exists());
}
