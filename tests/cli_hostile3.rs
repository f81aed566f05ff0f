//! Hostile inputs and options, second part: header text that would drive the terminal or a
//! spreadsheet, parameters without an upper bound, outputs that would replace an input,
//! simulator scenes that escape their folder or fill the disk, compressed frames that
//! expand past any detector, option files that never end. Each test checks what the user
//! sees: a clear error naming the file or key (exit 1) before any work, or the catalog
//! and the exit code of docs/cli.md, and that nothing was lost or overwritten.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_hostile3` runs these tests against
//! another build (how they were checked to fail before the fixes).
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{bin, frames_of, json, night, run};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Replace the 80-character card starting with `key` in the first header of `file` by
/// `card` (raw bytes, padded with blanks): header values no FITS writer would write.
fn set_card(file: &Path, key: &[u8], card: &[u8]) {
    let mut b = std::fs::read(file).unwrap();
    let i = (0..2880 * 4)
        .step_by(80)
        .find(|&i| b[i..].starts_with(key))
        .unwrap_or_else(|| panic!("{}: no card {}", file.display(), String::from_utf8_lossy(key)));
    let mut c = card.to_vec();
    assert!(c.len() <= 80);
    c.resize(80, b' ');
    b[i..i + 80].copy_from_slice(&c);
    std::fs::write(file, b).unwrap();
}

/// Run `sofipol ARGS` for at most `limit`: (exit code, stdout, stderr); a run still going
/// after `limit` is killed and fails the test (what a hang looked like before the fixes).
fn run_limited(args: &[&str], limit: Duration) -> (i32, String, String) {
    let mut child = Command::new(bin())
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        if t0.elapsed() > limit {
            child.kill().unwrap();
            let _ = child.wait();
            panic!("sofipol {args:?} still running after {limit:?}: killed");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

#[test]
fn control_characters_in_object_never_reach_the_terminal_or_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    // An OBJECT that clears the screen, forges a progress line and retitles the terminal.
    let evil = "\u{1b}[2J\r\n[2/2] X ok\u{1b}]0;pwn\u{7}";
    let mut card = b"OBJECT  = '".to_vec();
    card.extend(evil.as_bytes());
    card.push(b'\'');
    for f in frames_of(&n, "Beta") {
        set_card(&f, b"OBJECT  =", &card);
    }
    let out = dir.path().join("cat.json");
    // stderr is a pipe: the per-target progress lines of a batch job's log.
    let (code, stdout, stderr) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "--no-png"]);
    assert_eq!(code, 0, "{stderr}");
    for (name, text) in [("stdout", &stdout), ("stderr", &stderr)] {
        assert!(
            !text.contains(['\u{1b}', '\r', '\u{7}']),
            "{name} holds raw control characters: {text:?}"
        );
        assert!(
            !text.lines().any(|l| l.starts_with("[2/2] X ok")),
            "{name} holds a forged log line: {text}"
        );
    }
    // The value is shown escaped, on the target's own line.
    assert!(
        stderr.contains("\\x1b[2J\\r\\n[2/2] X ok\\x1b]0;pwn\\x07 ok"),
        "{stderr}"
    );
    assert!(stdout.contains("\\x1b[2J\\r\\n[2/2] X ok"), "{stdout}");
    // The catalog keeps the value as it is (JSON escapes it).
    let c = json(&out);
    assert!(
        c["targets"].as_array().unwrap().iter().any(|t| t["object"] == evil),
        "{c}"
    );
}

#[test]
fn csv_export_neutralises_formulas_in_text_cells_and_keeps_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    for (object, value) in [("Alpha", "=1+2"), ("Beta", "-2+3")] {
        for f in frames_of(&n, object) {
            set_card(&f, b"OBJECT  =", format!("OBJECT  = '{value}'").as_bytes());
        }
    }
    let cat = dir.path().join("cat.json");
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&cat), "-q", "--no-png"]);
    assert_eq!(code, 0, "{err}");
    let csv = dir.path().join("t.csv");
    let (code, _, err) = run(&["export", s(&cat), "--format", "csv", "-o", s(&csv)]);
    assert_eq!(code, 0, "{err}");
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 4, "{text}");
    let mut targets: Vec<&str> = rows.iter().map(|r| r[col("target")]).collect();
    targets.sort();
    targets.dedup();
    // Text that a spreadsheet would evaluate starts with a quote (shown as text).
    assert_eq!(targets, ["'-2+3", "'=1+2"], "{text}");
    // Numbers stay numbers: every q parses, and some are negative.
    let q: Vec<f64> = rows.iter().map(|r| r[col("q")].parse().unwrap()).collect();
    assert!(q.iter().any(|&v| v < 0.0), "{q:?}");
    // ECSV keeps the value (astropy reads it as data).
    let ecsv = dir.path().join("t.ecsv");
    let (code, _, err) = run(&["export", s(&cat), "-o", s(&ecsv)]);
    assert_eq!(code, 0, "{err}");
    let e = std::fs::read_to_string(&ecsv).unwrap();
    assert!(e.lines().any(|l| l.starts_with("=1+2,")) && !e.contains("'=1+2"), "{e}");
}

#[test]
fn parameters_without_an_upper_bound_are_refused_by_key_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let out = dir.path().join("cat.json");
    let limit = Duration::from_secs(60);
    for (args, key) in [
        (&["--aperture-fwhm", "1e20"][..], "measure.aperture_fwhm"),
        (&["--method", "subpixel:100000000"][..], "measure.method"),
        (
            &["--param", "measure.annulus_fwhm=[4.0, 1e9]"][..],
            "measure.annulus_fwhm",
        ),
        (
            &["--param", "measure.primary_search_px=1e12"][..],
            "measure.primary_search_px",
        ),
        (
            &["--param", "flat_options.min_response=2"][..],
            "flat_options.min_response",
        ),
        (
            &["--param", "flat_options.max_response=1"][..],
            "flat_options.max_response",
        ),
        (&["--param", "flat_options.max_frames=0"][..], "flat_options.max_frames"),
        (
            &["--param", "flat_options.min_values=100"][..],
            "flat_options.min_values",
        ),
    ] {
        let mut a = vec!["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q", "--no-png"];
        a.extend(args);
        let (code, _, err) = run_limited(&a, limit);
        assert_eq!(code, 1, "{args:?}: {err}");
        assert!(err.contains(key) && err.contains("must be"), "{args:?}: {err}");
        assert!(!out.exists(), "{args:?}: a catalog was written");
    }
    // The bounds themselves are accepted (the night is reduced).
    let (code, _, err) = run_limited(
        &[
            "night",
            s(&n),
            "--allow-uncalibrated",
            "-o",
            s(&out),
            "-q",
            "--no-png",
            "--param",
            "flat_options.min_values=25",
        ],
        limit,
    );
    assert_eq!(code, 0, "{err}");
}

#[test]
fn stats_and_export_never_overwrite_their_input_or_a_frame() {
    let dir = tempfile::tempdir().unwrap();
    // `stats CAT -o DIR` where CAT is DIR/stats.json.
    let out = dir.path().join("st");
    std::fs::create_dir(&out).unwrap();
    let cat = out.join("stats.json");
    std::fs::copy(common::testdata("catalog_aligned.json"), &cat).unwrap();
    let before = std::fs::read(&cat).unwrap();
    let (code, _, err) = run(&["stats", s(&cat), "-o", s(&out), "--pairs", "1000", "--no-model-figure"]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("never overwrites its inputs") && err.contains("stats.json"),
        "{err}"
    );
    assert_eq!(std::fs::read(&cat).unwrap(), before, "stats overwrote its input");
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 1, "nothing else written");
    // `export -o FRAME.fits` onto a raw frame.
    let n = night(dir.path());
    let frame = frames_of(&n, "Alpha").remove(0);
    let raw = std::fs::read(&frame).unwrap();
    let good = dir.path().join("good.json");
    std::fs::copy(common::testdata("catalog_aligned.json"), &good).unwrap();
    let (code, _, err) = run(&["export", s(&good), "--format", "fits", "-o", s(&frame)]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("FITS file") && err.contains("never overwrites a frame"),
        "{err}"
    );
    assert_eq!(std::fs::read(&frame).unwrap(), raw, "export replaced a raw frame");
    // ... but a table it exported itself is replaced, as any output is.
    let t = dir.path().join("t.fits");
    for _ in 0..2 {
        let (code, _, err) = run(&["export", s(&good), "--format", "fits", "-o", s(&t)]);
        assert_eq!(code, 0, "{err}");
    }
}

#[test]
fn demo_refuses_a_folder_holding_foreign_frames_or_a_foreign_catalog() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    // Foreign frames in DIR/raw would be reduced with the demo's.
    let d1 = dir.path().join("d1");
    std::fs::create_dir_all(d1.join("raw")).unwrap();
    let foreign = d1.join("raw/SOFI_hx_Alpha_01.fits");
    std::fs::copy(frames_of(&n, "Alpha").remove(0), &foreign).unwrap();
    let (code, _, err) = run_limited(&["demo", "-o", s(&d1), "-q"], Duration::from_secs(120));
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("SOFI_hx_Alpha_01.fits") && err.contains("not a file of the demo"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_dir(d1.join("raw")).unwrap().count(),
        1,
        "the demo wrote frames"
    );
    assert!(!d1.join("catalog.json").exists());
    // A user's catalog.json in a folder that is not an earlier demo's.
    let d2 = dir.path().join("d2");
    std::fs::create_dir(&d2).unwrap();
    std::fs::write(d2.join("catalog.json"), "{\"mine\": true}").unwrap();
    let (code, _, err) = run_limited(&["demo", "-o", s(&d2), "-q"], Duration::from_secs(120));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("catalog.json") && err.contains("not overwritten"), "{err}");
    assert_eq!(
        std::fs::read_to_string(d2.join("catalog.json")).unwrap(),
        "{\"mine\": true}"
    );
    assert!(!d2.join("raw").exists());
}

/// A scene with `name`, `dithers` and `binaries` copies of one binary (distinct names).
fn scene(name: &str, dithers: usize, binaries: usize) -> String {
    let mut t = format!(
        "name = {name:?}\nseed = 1\neffects = [\"psf\", \"sky\"]\n[observation]\norientations_deg = [0.0, 45.0]\ndithers = {dithers}\n"
    );
    for i in 0..binaries {
        t += &format!(
            "[[binary]]\nname = \"T{i}\"\nseparation_arcsec = 3.0\npa_deg = 10.0\nflux_a = 1e5\nflux_b = 5e4\np_a = 0.02\ngamma_a_deg = 10.0\np_b = 0.02\ngamma_b_deg = 20.0\n"
        );
    }
    t
}

#[test]
fn simulate_writes_only_inside_its_folder_and_bounds_what_it_writes() {
    let dir = tempfile::tempdir().unwrap();
    let sc = dir.path().join("scene.toml");
    let out = dir.path().join("a/b");
    // A name with `../`: the frames stay inside -o.
    std::fs::write(&sc, scene("../../escaped", 2, 1)).unwrap();
    let (code, _, err) = run(&["simulate", s(&sc), "-o", s(&out), "-q"]);
    assert_eq!(code, 0, "{err}");
    let mut outside: Vec<String> = Vec::new();
    for d in [dir.path().to_path_buf(), dir.path().join("a")] {
        for e in std::fs::read_dir(&d).unwrap() {
            let name = e.unwrap().file_name().to_string_lossy().into_owned();
            if name.ends_with(".fits") {
                outside.push(format!("{}/{name}", d.display()));
            }
        }
    }
    assert!(outside.is_empty(), "frames written outside -o: {outside:?}");
    let inside = std::fs::read_dir(&out).unwrap().count();
    assert_eq!(inside, 2 * 2 + 1, "4 frames and truth.json");
    // Counts without bound, and a scene that would fill the disk, are refused before
    // anything is written.
    for (body, want) in [
        (scene("big", 100_000, 1), "observation.dithers = 100000"),
        // 7 targets x 200 frames of 4 MiB (short exposures: the night's schedule keeps
        // every target above the horizon).
        (
            scene("huge", 100, 7).replace(
                "dithers = 100\n",
                "dithers = 100\ndit_s = 1.0\nndit = 1\noverhead_s = 1.0\n",
            ),
            "--force",
        ),
    ] {
        std::fs::write(&sc, body).unwrap();
        let o = dir.path().join("big");
        let (code, _, err) = run_limited(&["simulate", s(&sc), "-o", s(&o), "-q"], Duration::from_secs(60));
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(want), "{err}");
        assert!(!o.exists(), "{err}");
    }
    // Two targets whose names give the same file names would overwrite each other.
    std::fs::write(
        &sc,
        scene("x", 2, 2)
            .replace("name = \"T0\"", "name = \"A/B\"")
            .replace("name = \"T1\"", "name = \"A_B\""),
    )
    .unwrap();
    let (code, _, err) = run(&["simulate", s(&sc), "-o", s(&dir.path().join("dup")), "-q"]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("same frame files"), "{err}");
}
