//! Hostile inputs, third part: compressed frames that expand past any detector, option
//! files and catalogs that never end or are not files, inputs and outputs checked only
//! after the work, messages that did not say what is wrong, products left incomplete or
//! stale. Each test checks what the user sees (the error naming the file or key and the
//! exit code of docs/cli.md) and that nothing was lost or overwritten.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_hostile4` runs these tests against
//! another build (how they were checked to fail before the fixes).
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{bin, frames_of, json, night, run};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// An 80-character header card `KEY = value`.
fn card(key: &str, value: &str) -> Vec<u8> {
    format!("{key:<8}= {value:>20}").into_bytes()
}

/// Header cards padded to whole 2880-byte blocks, END included.
fn header(cards: &[Vec<u8>]) -> Vec<u8> {
    let mut h = Vec::new();
    for c in cards.iter().chain([&b"END".to_vec()]) {
        let mut c = c.clone();
        c.resize(80, b' ');
        h.extend(c);
    }
    h.resize(h.len().div_ceil(2880) * 2880, b' ');
    h
}

/// Where the data of the primary HDU of the FITS bytes `b` start (after its END block).
fn data_start(b: &[u8]) -> usize {
    let end = (0..b.len())
        .step_by(80)
        .find(|&i| b[i..].starts_with(b"END     "))
        .unwrap();
    end / 2880 * 2880 + 2880
}

/// The 80-character card of the first header of `b` that starts with `key`, replaced.
fn set_card(b: &mut [u8], key: &str, value: &str) {
    let i = (0..2880 * 4)
        .step_by(80)
        .find(|&i| b[i..].starts_with(format!("{key:<8}=").as_bytes()))
        .unwrap_or_else(|| panic!("no card {key}"));
    let mut c = card(key, value);
    c.resize(80, b' ');
    b[i..i + 80].copy_from_slice(&c);
}

fn failures(c: &serde_json::Value) -> Vec<(String, String)> {
    c["failures"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| (f["file"].as_str().unwrap().into(), f["error"].as_str().unwrap().into()))
        .collect()
}

/// The failure of the file named `name` (by its last path component).
fn failure_of(c: &serde_json::Value, name: &str) -> String {
    failures(c)
        .into_iter()
        .find(|(f, _)| f.ends_with(name))
        .unwrap_or_else(|| panic!("{name} not under failures: {}", c["failures"]))
        .1
}

/// `sofipol ARGS` killed after `limit` (a hang fails the test): (code, stdout, stderr).
fn run_limited(args: &[&str], limit: Duration) -> (i32, String, String) {
    let mut child = Command::new(bin())
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
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
fn a_gzip_frame_that_expands_past_any_detector_is_refused_before_it_is_inflated() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    // 8192 x 8192 float pixels (268 MB) in a 2 MB gzip file: 140 times, within the
    // 1000 x cap on compression, far beyond a 4096 x 4096 detector.
    let big = n.join("big.fits.gz");
    let mut gz = flate2::write::GzEncoder::new(std::fs::File::create(&big).unwrap(), flate2::Compression::fast());
    gz.write_all(&header(&[
        card("SIMPLE", "T"),
        card("BITPIX", "-32"),
        card("NAXIS", "2"),
        card("NAXIS1", "8192"),
        card("NAXIS2", "8192"),
    ]))
    .unwrap();
    let mut row = vec![0u8; 8192 * 4];
    for (i, b) in row.iter_mut().enumerate().step_by(1000) {
        *b = (i * 7919 % 251) as u8;
    }
    for _ in 0..8192 {
        gz.write_all(&row).unwrap();
    }
    gz.finish().unwrap();
    assert!(std::fs::metadata(&big).unwrap().len() > 268_435_456 / 1000);
    let out = dir.path().join("cat.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&out),
        "--no-png",
        "-q",
        "-v",
    ]);
    assert_eq!(code, 2, "{err}");
    let c = json(&out);
    let e = failure_of(&c, "big.fits.gz");
    assert!(
        e.contains("gzip file inflates to more than") && e.contains("refused before reading"),
        "{e}"
    );
    assert_eq!(c["targets"].as_array().unwrap().len(), 2);
    // Peak memory of the whole night stays far below the inflated file (268 MB).
    let mb: f64 = err
        .split("peak RSS ")
        .nth(1)
        .and_then(|t| t.split(" MB").next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no peak RSS in {err}"));
    assert!(mb < 200.0, "peak RSS {mb} MB");
}

#[cfg(unix)]
#[test]
fn option_files_and_catalogs_must_be_regular_files_of_bounded_size() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let out = dir.path().join("cat.json");
    let fifo = dir.path().join("pipe.toml");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let big = dir.path().join("big.toml");
    std::fs::write(&big, "# padding\n".repeat(600_000)).unwrap();
    let limit = Duration::from_secs(60);
    for (args, want) in [
        (
            vec!["mc", "--p-int", "pofi:/dev/zero", "--pairs", "1000"],
            "a character device",
        ),
        (vec!["mc", "--config", s(&fifo)], "a named pipe"),
        (
            vec![
                "night",
                s(&n),
                "--allow-uncalibrated",
                "-o",
                s(&out),
                "--params",
                "/dev/zero",
            ],
            "a character device",
        ),
        (
            vec![
                "night",
                s(&n),
                "--allow-uncalibrated",
                "-o",
                s(&out),
                "--standards",
                s(&fifo),
            ],
            "a named pipe",
        ),
        (
            vec![
                "night",
                s(&n),
                "--allow-uncalibrated",
                "-o",
                s(&out),
                "--profile",
                s(&big),
            ],
            "more than the 4194304 bytes",
        ),
        (
            vec![
                "night",
                s(&n),
                "--allow-uncalibrated",
                "-o",
                s(&out),
                "--calib",
                s(&fifo),
            ],
            "a named pipe",
        ),
        (
            vec!["export", "/dev/zero", "-o", s(&dir.path().join("t.ecsv"))],
            "a character device",
        ),
        (vec!["stats", s(&fifo)], "a named pipe"),
        (
            vec!["merge", s(&fifo), "/dev/zero", "-o", s(&dir.path().join("m.json"))],
            "a named pipe",
        ),
        (
            vec!["simulate", s(&fifo), "-o", s(&dir.path().join("sim"))],
            "a named pipe",
        ),
    ] {
        let (code, _, err) = run_limited(&args, limit);
        assert_eq!(code, 1, "{args:?}: {err}");
        assert!(err.contains(want), "{args:?}: {err}");
    }
    assert!(!out.exists());
    // 10^15 pairs aborted (SIGABRT) allocating 244 GB: refused by name.
    let (code, _, err) = run_limited(&["mc", "--pairs", "1e15"], limit);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("pairs") && err.contains("1000000000000000"), "{err}");
}

#[test]
fn calibration_frames_and_outputs_are_checked_before_the_reduction() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let out = dir.path().join("cat.json");
    let text = dir.path().join("flat.fits");
    std::fs::write(&text, "not a flat\n").unwrap();
    let long = dir.path().join(format!("{}.json", "c".repeat(250)));
    let file = dir.path().join("file");
    std::fs::write(&file, "x").unwrap();
    let blocked = file.join("sub"); // under a regular file: no directory can be made
    for (args, want) in [
        (
            vec![
                "night",
                s(&n),
                "--allow-uncalibrated",
                "-o",
                s(&out),
                "--badpix",
                "/no/such/mask.fits",
            ],
            "--badpix",
        ),
        (
            vec![
                "night",
                s(&n),
                "--allow-uncalibrated",
                "-o",
                s(&out),
                "--flat",
                s(&text),
            ],
            "--flat",
        ),
        (
            vec!["night", s(&n), "--allow-uncalibrated", "-o", s(&long)],
            "bytes long",
        ),
        (vec!["calib", s(&n), "-o", s(&blocked)], "cannot create"),
        (
            vec!["stats", &common::testdata("catalog_aligned.json"), "-o", s(&blocked)],
            "cannot create",
        ),
        (vec!["mc", "--pairs", "1000", "-o", s(&blocked)], "cannot create"),
    ] {
        let (code, stdout, err) = run(&args);
        assert_eq!(code, 1, "{args:?}: {err}");
        assert!(err.contains(want), "{args:?}: {err}");
        // Before the work: nothing reduced, analysed or simulated.
        assert!(stdout.is_empty(), "{args:?}: {stdout}");
    }
    assert!(!out.exists() && !long.exists());
}

#[test]
fn unreadable_frames_are_reported_with_what_is_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let good = std::fs::read(&frames_of(&n, "Alpha")[0]).unwrap();
    let bad = n.join("bad");
    std::fs::create_dir(&bad).unwrap();
    let mut b = good.clone();
    set_card(&mut b, "BITPIX", "17");
    std::fs::write(bad.join("bitpix.fits"), &b).unwrap();
    let mut b = good.clone();
    set_card(&mut b, "NAXIS2", "-5");
    std::fs::write(bad.join("naxis2.fits"), &b).unwrap();
    let mut b = good.clone();
    b.extend(b"appended by mistake\n".repeat(100));
    std::fs::write(bad.join("junk.fits"), &b).unwrap();
    // The keywords in a primary HDU without image, the image in extension 1.
    let start = data_start(&good);
    let mut primary: Vec<Vec<u8>> = good[..start]
        .chunks(80)
        .take_while(|c| !c.starts_with(b"END     "))
        .filter(|c| !c.starts_with(b"NAXIS1") && !c.starts_with(b"NAXIS2"))
        .map(|c| c.to_vec())
        .collect();
    let naxis = primary.iter().position(|c| c.starts_with(b"NAXIS ")).unwrap();
    primary[naxis] = card("NAXIS", "0");
    let mut ext = header(&primary);
    ext.extend(header(&[
        b"XTENSION= 'IMAGE   '".to_vec(),
        card("BITPIX", "-32"),
        card("NAXIS", "2"),
        card("NAXIS1", "1024"),
        card("NAXIS2", "1024"),
        card("PCOUNT", "0"),
        card("GCOUNT", "1"),
    ]));
    ext.extend(&good[start..]);
    std::fs::write(bad.join("ext.fits"), &ext).unwrap();
    // A 4096 x 4096 dither of Alpha (16-bit).
    let alpha2 = &frames_of(&n, "Alpha")[1];
    let b = std::fs::read(alpha2).unwrap();
    let mut b = b[..data_start(&b)].to_vec();
    set_card(&mut b, "BITPIX", "16");
    set_card(&mut b, "NAXIS1", "4096");
    set_card(&mut b, "NAXIS2", "4096");
    b.extend((0..4096 * 4096).flat_map(|i: u32| ((i % 1000) as i16).to_be_bytes()));
    std::fs::write(alpha2, &b).unwrap();

    let out = dir.path().join("cat.json");
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "--no-png", "-q"]);
    assert_eq!(code, 2, "{err}");
    let c = json(&out);
    for (name, want) in [
        ("bitpix.fits", "BITPIX = 17 is not a FITS pixel type"),
        ("naxis2.fits", "NAXIS2 = -5 is negative"),
        (
            "ext.fits",
            "missing keyword INSTRUME in the header of HDU 1, the image extension",
        ),
        ("junk.fits", "junk appended to the file"),
        ("SOFI_hx_Alpha_02.fits", "image is 4096 x 4096 px"),
    ] {
        let e = failure_of(&c, name);
        assert!(e.contains(want), "{name}: {e}");
        assert!(!e.contains("not a FITS file?") && !e.contains(name), "{name}: {e}");
    }
}

#[cfg(unix)]
#[test]
fn a_frame_that_cannot_be_opened_is_reported_with_the_systems_reason() {
    // Root opens any file: the run is made as user nobody (setpriv, util-linux) when the
    // tests run as root; as another user, chmod 000 is enough.
    use std::os::unix::fs::PermissionsExt;
    let root = Command::new("id").arg("-u").output().unwrap().stdout == b"0\n";
    if root && Command::new("setpriv").arg("--version").output().is_err() {
        panic!("tests run as root and setpriv is missing: cannot test permissions");
    }
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let locked = &frames_of(&n, "Beta")[0];
    for p in [dir.path(), &n] {
        std::fs::set_permissions(p, std::fs::Permissions::from_mode(0o777)).unwrap();
    }
    for f in std::fs::read_dir(&n).unwrap() {
        std::fs::set_permissions(f.unwrap().path(), std::fs::Permissions::from_mode(0o644)).unwrap();
    }
    std::fs::set_permissions(locked, std::fs::Permissions::from_mode(0o000)).unwrap();
    // The binary may sit under a private directory: a copy nobody can run.
    let exe = dir.path().join("sofipol");
    std::fs::copy(bin(), &exe).unwrap();
    std::fs::set_permissions(&exe, std::fs::Permissions::from_mode(0o755)).unwrap();
    let out = dir.path().join("cat.json");
    let mut cmd = if root {
        let mut c = Command::new("setpriv");
        c.args(["--reuid=65534", "--regid=65534", "--clear-groups"]).arg(&exe);
        c
    } else {
        Command::new(&exe)
    };
    let o = cmd
        .args(["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "--no-png", "-q"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    let e = failure_of(&json(&out), locked.file_name().unwrap().to_str().unwrap());
    assert!(e.contains("cannot be opened: Permission denied"), "{e}");
}

#[test]
fn figures_that_cannot_be_written_make_exit_2_and_stale_products_are_removed() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let out = dir.path().join("cat.json");
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q"]);
    assert_eq!(code, 0, "{err}");
    let products = dir.path().join("cat_products");
    let mut pngs: Vec<PathBuf> = std::fs::read_dir(&products)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    pngs.sort();
    assert_eq!(pngs.len(), 2, "{pngs:?}");
    // A figure of a target no longer in the night, the temporary file of an interrupted
    // write, and Beta's figure that cannot be written (a directory in its place).
    std::fs::write(products.join("Gone_1999.png"), b"old").unwrap();
    std::fs::write(products.join(".Alpha.png.tmp-999999-0"), b"half").unwrap();
    let beta = pngs.iter().find(|p| p.to_str().unwrap().contains("Beta")).unwrap();
    std::fs::remove_file(beta).unwrap();
    std::fs::create_dir(beta).unwrap();
    std::fs::write(beta.join("keep"), b"").unwrap();
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("could not write the figure") && err.contains("products are incomplete"),
        "{err}"
    );
    // The catalog is complete; Alpha's figure is there; what earlier runs left is gone.
    let c = json(&out);
    assert!(c["failures"].as_array().unwrap().is_empty(), "{c}");
    let mut left: Vec<String> = std::fs::read_dir(&products)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left.len(), 2, "{left:?}");
    assert!(
        left.iter().any(|f| f.starts_with("Alpha") && f.ends_with(".png")),
        "{left:?}"
    );
    assert!(beta.is_dir(), "a directory is not removed");
}

#[test]
fn catalogs_of_an_unknown_schema_version_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(common::testdata("catalog_aligned.json")).unwrap();
    let mut c: serde_json::Value = serde_json::from_str(&text).unwrap();
    c["schema_version"] = "9.0".into();
    let cat = dir.path().join("future.json");
    std::fs::write(&cat, c.to_string()).unwrap();
    for args in [
        vec!["export", s(&cat), "-o", s(&dir.path().join("t.ecsv"))],
        vec!["stats", s(&cat), "--pairs", "1000", "--no-model-figure"],
        vec!["merge", s(&cat), "-o", s(&dir.path().join("m.json"))],
    ] {
        let (code, _, err) = run(&args);
        assert_eq!(code, 1, "{args:?}: {err}");
        assert!(
            err.contains("future.json") && err.contains("schema_version = '9.0'"),
            "{args:?}: {err}"
        );
    }
    assert!(!dir.path().join("t.ecsv").exists());
}

#[test]
fn a_dither_whose_primary_is_not_found_is_listed_under_failures() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    // The header offset of one dither sends the search 250 px away from the star.
    let f = &frames_of(&n, "Alpha")[1];
    let mut b = std::fs::read(f).unwrap();
    let i = (0..2880 * 2)
        .step_by(80)
        .find(|&i| b[i..].starts_with(b"HIERARCH ESO SEQ CUMOFFSETX"))
        .unwrap();
    let mut c = b"HIERARCH ESO SEQ CUMOFFSETX = 250.0".to_vec();
    c.resize(80, b' ');
    b[i..i + 80].copy_from_slice(&c);
    std::fs::write(f, b).unwrap();
    let out = dir.path().join("cat.json");
    let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "--no-png", "-q"]);
    assert_eq!(code, 2, "{err}");
    let e = failure_of(&json(&out), f.file_name().unwrap().to_str().unwrap());
    assert!(
        e.contains("primary star not found") && e.contains("primary_search_px"),
        "{e}"
    );
}

#[test]
fn calib_without_standards_says_none_were_found() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let cal = dir.path().join("cal");
    let (code, _, err) = run(&["calib", s(&n), "-o", s(&cal), "-q"]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("none found") && !err.contains(", )"), "{err}");
}
