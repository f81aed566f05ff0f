//! `sofipol watch`: a night reduced while its frames arrive. Frames are copied into a
//! followed folder one by one (a file half-written for a while, an aborted template, the
//! standards after the targets, a restart, Ctrl-C), and the final catalog is compared with
//! the one `sofipol night` writes on the same frames.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_watch` runs these tests against
//! another build.
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
/// unpolarized and a polarized standard and the instrumental effects they calibrate, in
/// `dir/night`.
fn night_with_standards(dir: &Path) -> PathBuf {
    instrument_night(dir, "live", 11, TWO_STANDARDS)
}

/// The frames of the night whose name holds `part`, sorted.
fn frames(n: &Path, part: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(n)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().to_str().unwrap().contains(part))
        .collect();
    v.sort();
    assert!(!v.is_empty(), "no frames with '{part}' in {}", n.display());
    v
}

/// Start `sofipol watch DIR -o OUT ARGS` (stdout and stderr captured).
fn start_watch(dir: &Path, out: &Path, args: &[&str]) -> Child {
    sofipol()
        .args(["watch", s(dir), "-o", s(out)])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start sofipol watch")
}

/// Wait for the child (at most `limit`), then (exit code, stdout, stderr).
fn finish(child: Child, limit: Duration) -> (i32, String, String) {
    finish_child(child, limit)
}

/// Copy `files` into `dir`, one every `every`.
fn copy_slowly(files: &[PathBuf], dir: &Path, every: Duration) {
    for f in files {
        std::fs::copy(f, dir.join(f.file_name().unwrap())).unwrap();
        std::thread::sleep(every);
    }
}

/// `sofipol night` on `dir`: the catalog.
fn night_catalog(dir: &Path, out: &Path) -> Value {
    let (code, _, err) = run(&["night", s(dir), "-o", s(out), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{err}");
    json(out)
}

/// Targets and failures equal (the provenance differs by command line and times).
fn assert_same_reduction(live: &Value, night: &Value) {
    assert_eq!(live["failures"], night["failures"], "failures differ");
    let (a, b) = (
        live["targets"].as_array().unwrap(),
        night["targets"].as_array().unwrap(),
    );
    assert_eq!(a.len(), b.len(), "targets: {} live, {} night", a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert_eq!(x, y, "target {} differs from night's", x["object"]);
    }
}

#[test]
fn frames_arriving_one_by_one_give_the_nights_catalog_and_late_standards_recalibrate() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let live = d.path().join("live");
    std::fs::create_dir(&live).unwrap();
    let out = d.path().join("watch.json");
    let child = start_watch(&live, &out, &["--exit-when-idle", "2", "-v"]);
    std::thread::sleep(Duration::from_millis(300));
    let alpha = frames(&n, "_Alpha_");
    let beta = frames(&n, "_Beta_");
    let standards = frames(&n, "_HD_");
    // Alpha, then Beta's first frame half-written for 1.5 s (a frame being written by
    // the instrument must be waited for, not failed), then the rest, then the standards.
    copy_slowly(&alpha, &live, Duration::from_millis(100));
    let first = &beta[0];
    let bytes = std::fs::read(first).unwrap();
    let target = live.join(first.file_name().unwrap());
    std::fs::write(&target, &bytes[..bytes.len() / 2]).unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new().append(true).open(&target).unwrap();
        f.write_all(&bytes[bytes.len() / 2..]).unwrap();
    }
    copy_slowly(&beta[1..], &live, Duration::from_millis(100));
    std::thread::sleep(Duration::from_millis(1500));
    copy_slowly(&standards, &live, Duration::from_millis(100));
    let (code, stdout, stderr) = finish(child, Duration::from_secs(120));
    assert!(code == 0 || code == 2, "exit {code}: {stderr}");
    // One line per target when it completes, naming P/sigma of each component.
    for obj in ["Alpha ok", "Beta ok"] {
        assert_eq!(
            stdout
                .lines()
                .filter(|l| l.contains(obj) && !l.contains("   now "))
                .count(),
            1,
            "{obj}:\n{stdout}\n{stderr}"
        );
        // After the standards recalibrated them, their new numbers are shown too.
        assert!(
            stdout.lines().any(|l| l.contains("   now ") && l.contains(obj)),
            "{obj} not shown again after the recalibration:\n{stdout}"
        );
    }
    assert!(stdout.contains("P/sig"), "{stdout}");
    // The standards arrived after both targets: the line says they re-calibrated them.
    assert!(
        stdout
            .lines()
            .any(|l| l.contains("earlier target(s) updated") && l.contains("standard(s) arrived")),
        "no re-calibration line:\n{stdout}\n{stderr}"
    );
    assert!(
        stderr.contains("still being written"),
        "the half-written frame was not waited for:\n{stderr}"
    );
    let w = json(&out);
    let night = night_catalog(&live, &d.path().join("night.json"));
    assert_same_reduction(&w, &night);
    assert!(w["failures"].as_array().unwrap().is_empty(), "{}", w["failures"]);
    // Calibrated by the standards: no component flagged uncalibrated.
    for t in w["targets"].as_array().unwrap() {
        for c in t["components"].as_array().unwrap() {
            assert!(
                !c["flags"].as_array().unwrap().iter().any(|f| f == "uncalibrated"),
                "{}",
                t["object"]
            );
        }
    }
}

/// Settings that keep the night's bad pixels and flats fixed (none detected, no flat): no
/// update is provisional, so a target's numbers change only when the calibration does.
const FIXED_MASK_AND_FLATS: [&str; 3] = ["--param", "no_detect_bad_pixels=true", "--no-flat"];

/// Component `name`'s P, sigma_P (%) and P/sigma as a watch line `line` shows them
/// (`A P 5.01+-0.07 % gamma 17 deg P/sig 68.9 ok`).
fn shown(line: &str, name: &str) -> (f64, f64, f64) {
    let part = line
        .split(" | ")
        .find(|p| p.starts_with(&format!("{name} P ")))
        .unwrap_or_else(|| panic!("no component {name} on: {line}"));
    let words: Vec<&str> = part.split_whitespace().collect();
    let (p, s) = words[2].split_once("+-").unwrap();
    let at = words.iter().position(|w| *w == "P/sig").unwrap();
    let snr = words[at + 1].trim_end_matches(':');
    (p.parse().unwrap(), s.parse().unwrap(), snr.parse().unwrap())
}

/// The line `line` shows the P, sigma_P and P/sigma of every component of `target` (a
/// catalog entry), to the digits it prints.
fn assert_line_shows(line: &str, target: &Value, what: &str) {
    for c in target["components"].as_array().unwrap() {
        let name = c["name"].as_str().unwrap();
        let (p, s) = (c["p"].as_f64().unwrap(), c["sigma_p"].as_f64().unwrap());
        let (lp, ls, lsnr) = shown(line, name);
        assert!(
            (lp - 100.0 * p).abs() <= 0.005 + 1e-9
                && (ls - 100.0 * s).abs() <= 0.005 + 1e-9
                && (lsnr - p / s).abs() <= 0.05 + 1e-9,
            "{what}, {}: the line shows P {lp} +- {ls} %, P/sig {lsnr}; the catalog holds {:.4} +- {:.4} %, \
             P/sig {:.2}\n{line}",
            name,
            100.0 * p,
            100.0 * s,
            p / s
        );
    }
}

/// The target `object` of a catalog.
fn target_of<'a>(cat: &'a Value, object: &str) -> &'a Value {
    cat["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == object)
        .unwrap_or_else(|| panic!("no {object} in the catalog"))
}

/// The line printed when a target is reduced holds the numbers the catalog then holds:
/// calibrated by the standards reduced before it, the calibration's error in sigma_P (not the
/// provisional solve of the reduction, nor the measurement's error alone; "P/sig 232.9 on
/// the line, 118.8 in the catalog" must not happen). Alpha arrives after one standard: its
/// first line is `sofipol night` on the frames there then. The second standard recalibrates
/// it: the `now` line shows the final catalog, as Beta's first line does.
#[test]
fn each_watch_line_shows_the_calibrated_numbers_the_catalog_holds_at_its_update() {
    let d = tempfile::tempdir().unwrap();
    let n = night_with_standards(d.path());
    let (unpolarized, polarized) = (frames(&n, "_HD_64299_"), frames(&n, "_HD_204827_"));
    let (alpha, beta) = (frames(&n, "_Alpha_"), frames(&n, "_Beta_"));
    let live = d.path().join("live");
    std::fs::create_dir(&live).unwrap();
    let out = d.path().join("watch.json");
    let mut args = vec!["--exit-when-idle", "3"];
    args.extend(FIXED_MASK_AND_FLATS);
    let child = start_watch(&live, &out, &args);
    std::thread::sleep(Duration::from_millis(300));
    copy_slowly(&unpolarized, &live, Duration::from_millis(50));
    copy_slowly(&alpha, &live, Duration::from_millis(50));
    // Alpha reduced (with HD 64299 alone) before the polarized standard arrives.
    let t = Instant::now();
    let has_alpha = || {
        std::fs::read_to_string(&out)
            .ok()
            .and_then(|s| serde_json::from_str::<Value>(&s).ok())
            .is_some_and(|c| {
                c["targets"]
                    .as_array()
                    .is_some_and(|v| v.iter().any(|t| t["object"] == "Alpha"))
            })
    };
    while !has_alpha() {
        assert!(t.elapsed() < Duration::from_secs(60), "Alpha never reduced");
        std::thread::sleep(Duration::from_millis(50));
    }
    copy_slowly(&polarized, &live, Duration::from_millis(50));
    std::thread::sleep(Duration::from_millis(1000));
    copy_slowly(&beta, &live, Duration::from_millis(50));
    let (code, stdout, stderr) = finish(child, Duration::from_secs(120));
    assert!(code == 0 || code == 2, "exit {code}: {stderr}");
    let lines_of = |obj: &str| -> (Vec<&str>, Vec<&str>) {
        let all = stdout
            .lines()
            .filter(|l| l.contains(&format!("] {obj} ok")) || l.contains(&format!("now {obj} ok")));
        all.partition(|l| !l.contains("   now "))
    };
    let w = json(&out);

    // Alpha's first line: the night of the frames there when it was reduced.
    let upto = d.path().join("upto_alpha");
    std::fs::create_dir(&upto).unwrap();
    copy_slowly(&[unpolarized.clone(), alpha.clone()].concat(), &upto, Duration::ZERO);
    let night_fixed = |dir: &Path, out: &Path| {
        let mut a = vec!["night", s(dir), "-o", s(out), "-q", "--no-png"];
        a.extend(FIXED_MASK_AND_FLATS);
        let (code, _, err) = run(&a);
        assert!(code == 0 || code == 2, "{err}");
        json(out)
    };
    let then = night_fixed(&upto, &d.path().join("upto_alpha.json"));
    let (first, now) = lines_of("Alpha");
    assert_eq!(first.len(), 1, "{stdout}");
    assert_line_shows(first[0], target_of(&then, "Alpha"), "Alpha when reduced after HD 64299");
    // HD 204827 recalibrated Alpha: the last `now` line is the final catalog.
    let last = now
        .last()
        .unwrap_or_else(|| panic!("Alpha not shown again after HD 204827:\n{stdout}"));
    assert_line_shows(last, target_of(&w, "Alpha"), "Alpha recalibrated");
    // Beta, reduced after both standards: nothing changes it later.
    let (first, now) = lines_of("Beta");
    assert_eq!((first.len(), now.len()), (1, 0), "{stdout}");
    assert_line_shows(first[0], target_of(&w, "Beta"), "Beta");
    // The final catalog is `night`'s on the same frames.
    assert_same_reduction(&w, &night_fixed(&live, &d.path().join("night.json")));

    // Those lines could tell a calibrated P/sigma from the others: every component is
    // calibrated, and its P/sigma from the measurement's error alone (the reduction's
    // provisional error) differs from the catalog's by more than the line's last digit.
    for t in w["targets"].as_array().unwrap() {
        for c in t["components"].as_array().unwrap() {
            let who = format!("{} {}", t["object"], c["name"]);
            assert!(!c["flags"].to_string().contains("\"uncalibrated\""), "{who}");
            let f = |k: &str| c[k].as_f64().unwrap_or_else(|| panic!("{who}: no {k}"));
            let (q, u, p) = (f("q"), f("u"), f("p"));
            let (vq, vu, cqu) = (f("sigma_q_stat").powi(2), f("sigma_u_stat").powi(2), f("cov_qu_stat"));
            let sigma_stat = (q * q * vq + u * u * vu + 2.0 * q * u * cqu).sqrt() / p;
            let (snr, snr_stat) = (p / f("sigma_p"), p / sigma_stat);
            assert!(
                snr_stat - snr > 0.15,
                "{who}: P/sig {snr:.2} with the calibration's error, {snr_stat:.2} without"
            );
        }
    }
}

#[test]
fn an_aborted_template_is_reduced_after_the_time_out_and_ctrl_c_leaves_a_complete_catalog() {
    let d = tempfile::tempdir().unwrap();
    let n = night(d.path());
    let live = d.path().join("live");
    std::fs::create_dir(&live).unwrap();
    let out = d.path().join("watch.json");
    let alpha = frames_of(&n, "Alpha");
    let beta = frames_of(&n, "Beta");
    // Alpha aborted after 4 of its 6 frames; Beta complete.
    copy_slowly(&alpha[..4], &live, Duration::ZERO);
    copy_slowly(&beta, &live, Duration::ZERO);
    let t0 = Instant::now();
    let child = start_watch(&live, &out, &["--template-timeout", "3", "--exit-when-idle", "1", "-v"]);
    let (code, stdout, stderr) = finish(child, Duration::from_secs(120));
    assert!(t0.elapsed() >= Duration::from_secs(3), "did not wait for the time-out");
    assert!(code == 0 || code == 2, "exit {code}: {stderr}");
    let beta_line = stdout.find("Beta ok").unwrap_or_else(|| panic!("{stdout}"));
    let alpha_line = stdout.find("Alpha").unwrap_or_else(|| panic!("{stdout}"));
    assert!(beta_line < alpha_line, "Alpha reduced before its time-out:\n{stdout}");
    assert!(stderr.contains("waiting for Alpha"), "{stderr}");
    let w = json(&out);
    let a = w["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == "Alpha")
        .unwrap();
    assert!(a["flags"].to_string().contains("4 of 6 exposures"), "{}", a["flags"]);
    assert_same_reduction(&w, &night_catalog(&live, &d.path().join("night.json")));

    // Ctrl-C: a template still arriving is reduced as it is, the catalog is whole.
    let live2 = d.path().join("live2");
    std::fs::create_dir(&live2).unwrap();
    let out2 = d.path().join("watch2.json");
    copy_slowly(&beta, &live2, Duration::ZERO);
    copy_slowly(&alpha[..2], &live2, Duration::ZERO);
    let child = start_watch(&live2, &out2, &["--template-timeout", "1000"]);
    let t = Instant::now();
    while !out2.exists() && t.elapsed() < Duration::from_secs(60) {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        json(&out2)["targets"].as_array().unwrap().len(),
        1,
        "only Beta is complete"
    );
    let st = std::process::Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(st.success());
    let (code, _, stderr) = finish(child, Duration::from_secs(60));
    assert!(code == 0 || code == 2, "exit {code}: {stderr}");
    let w2 = json(&out2);
    assert_eq!(w2["targets"].as_array().unwrap().len(), 2, "{stderr}");
    assert_same_reduction(&w2, &night_catalog(&live2, &d.path().join("night2.json")));
}

#[test]
fn a_restart_resumes_from_the_catalog_without_reducing_again() {
    let d = tempfile::tempdir().unwrap();
    let n = night(d.path());
    let live = d.path().join("live");
    std::fs::create_dir(&live).unwrap();
    let out = d.path().join("watch.json");
    copy_slowly(&frames_of(&n, "Alpha"), &live, Duration::ZERO);
    let (code, stdout, stderr) = finish(
        start_watch(&live, &out, &["--exit-when-idle", "1"]),
        Duration::from_secs(60),
    );
    assert!(code == 0 || code == 2, "{stderr}");
    assert!(stdout.contains("Alpha ok"), "{stdout}");
    let before = json(&out);

    // Restarted with nothing new: nothing reduced, nothing reported again.
    let (code, stdout, stderr) = finish(
        start_watch(&live, &out, &["--exit-when-idle", "1", "-v"]),
        Duration::from_secs(60),
    );
    assert!(code == 0 || code == 2, "{stderr}");
    assert!(stderr.contains("resuming from"), "{stderr}");
    assert!(stderr.contains("0 template(s) reduced, 1 reused"), "{stderr}");
    assert!(!stdout.contains("Alpha ok"), "reported again:\n{stdout}");
    assert_eq!(json(&out)["targets"], before["targets"]);

    // Restarted while Beta arrives: Beta is reduced and reported; the catalog ends equal
    // to night's.
    let child = start_watch(&live, &out, &["--exit-when-idle", "2"]);
    std::thread::sleep(Duration::from_millis(500));
    copy_slowly(&frames_of(&n, "Beta"), &live, Duration::from_millis(100));
    let (code, stdout, stderr) = finish(child, Duration::from_secs(60));
    assert!(code == 0 || code == 2, "{stderr}");
    // Alpha is not reported as new again (its line may come back as `now ...` when Beta's
    // frames change the night's flats).
    let new_alpha = stdout.lines().any(|l| l.contains("Alpha ok") && !l.contains("   now "));
    assert!(stdout.contains("Beta ok") && !new_alpha, "{stdout}");
    assert_same_reduction(&json(&out), &night_catalog(&live, &d.path().join("night.json")));
}

#[test]
fn polling_finds_frames_too() {
    let d = tempfile::tempdir().unwrap();
    let n = night(d.path());
    let live = d.path().join("live");
    std::fs::create_dir(&live).unwrap();
    let out = d.path().join("watch.json");
    let child = start_watch(&live, &out, &["--poll", "0.2", "--exit-when-idle", "2"]);
    std::thread::sleep(Duration::from_millis(300));
    copy_slowly(&frames_of(&n, "Beta"), &live, Duration::from_millis(50));
    let (code, stdout, stderr) = finish(child, Duration::from_secs(60));
    assert!(code == 0 || code == 2, "{stderr}");
    assert!(stdout.contains("Beta ok"), "{stdout}\n{stderr}");
    assert!(stderr.contains("polling every 0.2 s"), "{stderr}");
}
