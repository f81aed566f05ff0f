//! Hostile inputs, fourth part: arguments and file names that are not UTF-8, thread
//! counts, parallactic angles that are not angles, frames without one, figure files that
//! are not files, calibration values that are in range but not physical, dates and frame
//! counts that contradict each other, and the messages about all of them. Each test checks
//! what the user sees (exit code, the message naming file, keyword and value) and that no
//! number changed silently.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_hostile5` runs these tests against
//! another build (how they were checked to fail before the fixes).
use std::ffi::OsStr;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{bin, json, run};
use serde_json::Value;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `sofipol ARGS` (any bytes) killed after `limit` (a hang fails the test):
/// (code, stdout, stderr). The pipes are read while it runs (a page on stdout fills them).
fn run_os(args: &[&OsStr], limit: Duration) -> (i32, String, String) {
    run_os_in(&std::env::current_dir().unwrap(), args, limit)
}

/// [`run_os`] in the working directory `cwd`.
fn run_os_in(cwd: &Path, args: &[&OsStr], limit: Duration) -> (i32, String, String) {
    use std::io::Read;
    let mut child = Command::new(bin())
        .current_dir(cwd)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let drain = |mut r: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            r.read_to_end(&mut v).ok();
            String::from_utf8_lossy(&v).into_owned()
        })
    };
    let out = drain(Box::new(child.stdout.take().unwrap()));
    let err = drain(Box::new(child.stderr.take().unwrap()));
    let t0 = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if t0.elapsed() > limit {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!(
                "sofipol {args:?} still running after {limit:?}: killed\n{}",
                err.join().unwrap()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    (status.code().unwrap_or(-1), out.join().unwrap(), err.join().unwrap())
}

fn run_limited(args: &[&str], limit: Duration) -> (i32, String, String) {
    let a: Vec<&OsStr> = args.iter().map(OsStr::new).collect();
    run_os(&a, limit)
}

/// The telescope-polarization night (testdata/scenes/telpol_night.toml: 4 binaries, 6
/// standards at parallactic angles spread over the night, dome flats) in `dir/tel`.
fn telpol_night(dir: &Path) -> PathBuf {
    let n = dir.join("tel");
    let (code, _, err) = run(&[
        "simulate",
        concat!(env!("CARGO_MANIFEST_DIR"), "/testdata/scenes/telpol_night.toml"),
        "-o",
        s(&n),
        "-q",
    ]);
    assert_eq!(code, 0, "{err}");
    std::fs::remove_file(n.join("truth.json")).unwrap();
    n
}

/// `sofipol night DIR -o OUT -q --no-png`: (exit code, catalog).
fn reduce(n: &Path, out: &Path) -> (i32, Value) {
    let (code, _, err) = run(&["night", s(n), "-o", s(out), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "exit {code}: {err}");
    (code, json(out))
}

/// Replace the value of the header card `key` (`HIERARCH ESO TEL PARANG START`...) of the
/// FITS file `p`; `None` removes the card (renamed to a keyword nobody reads).
fn set_card(p: &Path, key: &str, value: Option<&str>) {
    let mut b = std::fs::read(p).unwrap();
    let pat = format!("{key} = ");
    let i = b
        .windows(pat.len())
        .position(|w| w == pat.as_bytes())
        .unwrap_or_else(|| panic!("no card {key} in {}", p.display()));
    assert_eq!(i % 80, 0, "{key} is not at a card's start");
    let card = match value {
        Some(v) => format!("{key} = {v}"),
        None => "COMMENT card removed by the test".to_string(),
    };
    let mut c = card.into_bytes();
    c.resize(80, b' ');
    b[i..i + 80].copy_from_slice(&c);
    std::fs::write(p, b).unwrap();
}

/// The target of `catalog` whose object is `object`.
fn target<'a>(catalog: &'a Value, object: &str) -> &'a Value {
    catalog["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == object)
        .unwrap_or_else(|| panic!("no target {object}"))
}

fn strings(v: &Value) -> Vec<String> {
    v.as_array()
        .map(|a| a.iter().map(|x| x.as_str().unwrap_or_default().to_string()).collect())
        .unwrap_or_default()
}

#[test]
fn an_argument_that_is_not_utf8_is_kept_in_the_provenance_instead_of_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let bad = |name: &[u8]| dir.path().join(OsStr::from_bytes(name));
    let cat = bad(b"cat\xff.json");
    let limit = Duration::from_secs(120);
    let (code, _, err) = run_os(
        &[
            OsStr::new("night"),
            n.as_os_str(),
            OsStr::new("-o"),
            cat.as_os_str(),
            OsStr::new("-q"),
        ],
        limit,
    );
    assert!(code == 0 || code == 2, "night exit {code}: {err}");
    let c: Value = serde_json::from_slice(&std::fs::read(&cat).unwrap()).unwrap();
    let line = strings(&c["provenance"]["command_line"]).join(" ");
    assert!(line.contains("cat\u{fffd}.json"), "{line}");

    let calib = bad(b"cal\xfe");
    let (code, _, err) = run_os(
        &[
            OsStr::new("calib"),
            n.as_os_str(),
            OsStr::new("-o"),
            calib.as_os_str(),
            OsStr::new("-q"),
        ],
        limit,
    );
    assert!(code == 0 || code == 2, "calib exit {code}: {err}");
    let st = bad(b"stats\xfe");
    let (code, _, err) = run_os(
        &[
            OsStr::new("stats"),
            cat.as_os_str(),
            OsStr::new("-o"),
            st.as_os_str(),
            OsStr::new("--pairs"),
            OsStr::new("2000"),
            OsStr::new("-q"),
        ],
        limit,
    );
    assert!(code == 0 || code == 2, "stats exit {code}: {err}");
    assert!(st.join("stats.json").is_file(), "{err}");
    let page = bad(b"page\xfe.html");
    let (code, _, err) = run_os(
        &[
            OsStr::new("report"),
            cat.as_os_str(),
            OsStr::new("-o"),
            page.as_os_str(),
            OsStr::new("--pairs"),
            OsStr::new("2000"),
            OsStr::new("-q"),
        ],
        limit,
    );
    assert_eq!(code, 0, "report: {err}");
    assert!(page.is_file());
    let mc = bad(b"mc\xfe");
    let (code, _, err) = run_os(
        &[
            OsStr::new("mc"),
            OsStr::new("--pairs"),
            OsStr::new("2000"),
            OsStr::new("-o"),
            mc.as_os_str(),
            OsStr::new("-q"),
        ],
        limit,
    );
    assert_eq!(code, 0, "mc: {err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn jobs_are_checked_and_capped_on_every_command() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let cat = dir.path().join("c.json");
    reduce(&n, &cat);
    let limit = Duration::from_secs(120);
    // 0 threads is refused by every command that takes --jobs, naming the option.
    let (w0, n0, r0, st0) = (
        dir.path().join("w0.json"),
        dir.path().join("n0.json"),
        dir.path().join("r0.html"),
        dir.path().join("st0"),
    );
    for args in [
        vec!["watch", s(&n), "-o", s(&w0), "--jobs", "0", "--exit-when-idle", "0"],
        vec!["night", s(&n), "-o", s(&n0), "--jobs", "0"],
        vec!["report", s(&cat), "-o", s(&r0), "--jobs", "0"],
        vec!["stats", s(&cat), "-o", s(&st0), "--jobs", "0"],
        vec!["mc", "--pairs", "1000", "--jobs", "0"],
    ] {
        let (code, _, err) = run_limited(&args, limit);
        assert_ne!(code, 0, "{args:?} accepted --jobs 0");
        assert!(err.contains("--jobs 0"), "{args:?}: {err}");
    }
    // 2048 threads are capped with a note, and the command finishes.
    let w = dir.path().join("w.json");
    let r = dir.path().join("r.html");
    for args in [
        vec![
            "watch",
            s(&n),
            "-o",
            s(&w),
            "--jobs",
            "2048",
            "--exit-when-idle",
            "0",
            "--poll",
            "0.1",
        ],
        vec!["report", s(&cat), "-o", s(&r), "--jobs", "2048", "--pairs", "2000"],
        vec!["stats", s(&cat), "-o", s(&st0), "--jobs", "2048", "--pairs", "2000"],
        vec!["mc", "--pairs", "2000", "--jobs", "2048"],
    ] {
        let (code, _, err) = run_limited(&args, limit);
        assert!(code == 0 || code == 2, "{args:?}: exit {code}: {err}");
        assert!(err.contains("--jobs 2048 capped at"), "{args:?}: {err}");
    }
}

#[test]
fn a_parallactic_angle_out_of_range_is_refused_by_name_and_the_correction_kept() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let (_, before) = reduce(&n, &dir.path().join("before.json"));
    let frame = n.join("SOFI_telpol_Tel_Easy_01.fits");
    set_card(&frame, "HIERARCH ESO TEL PARANG START", Some("1e300"));
    let (code, after) = reduce(&n, &dir.path().join("after.json"));
    assert_eq!(code, 0);
    let t = target(&after, "Tel Easy");
    let flags = strings(&t["flags"]).join("\n");
    // The frame, the keyword and the value, the value short.
    assert!(
        flags.contains("SOFI_telpol_Tel_Easy_01.fits")
            && flags.contains("ESO TEL PARANG START")
            && flags.contains("1e300")
            && flags.contains("[-360, 360]"),
        "{flags}"
    );
    assert!(flags.len() < 400, "{flags}");
    let b = target(&before, "Tel Easy");
    for (x, y) in t["components"]
        .as_array()
        .unwrap()
        .iter()
        .zip(b["components"].as_array().unwrap())
    {
        let f = strings(&x["flags"]);
        // The dither is left out by name, the telescope's correction kept.
        assert!(f.iter().any(|f| f == "no_parallactic_angle"), "{f:?}");
        assert!(
            !f.iter().any(|f| f.starts_with("telescope_polarization_uncorrected")),
            "{f:?}"
        );
        let dropped = x["dropped_dithers"].as_array().unwrap();
        assert!(
            dropped
                .iter()
                .any(|d| d["file"].as_str().unwrap().ends_with("Tel_Easy_01.fits")
                    && d["reason"] == "no_parallactic_angle"),
            "{dropped:?}"
        );
        // One dither of ten fewer: P within its error of the intact night's.
        let (p, q, sp) = (
            x["p"].as_f64().unwrap(),
            y["p"].as_f64().unwrap(),
            y["sigma_p"].as_f64().unwrap(),
        );
        assert!((p - q).abs() < 1.5 * sp, "P {p} against {q} +- {sp}");
    }
    // An end far from the start is refused the same way.
    set_card(&frame, "HIERARCH ESO TEL PARANG START", Some("10.0"));
    set_card(&frame, "HIERARCH ESO TEL PARANG END", Some("150.0"));
    let (_, after) = reduce(&n, &dir.path().join("after2.json"));
    let flags = strings(&target(&after, "Tel Easy")["flags"]).join("\n");
    assert!(
        flags.contains("ESO TEL PARANG END") && flags.contains("140.0 deg"),
        "{flags}"
    );
}

#[test]
fn one_frame_without_a_parallactic_angle_is_left_out_and_the_nights_correction_kept() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let (_, before) = reduce(&n, &dir.path().join("before.json"));
    // One standard frame and one science frame lose the keyword.
    set_card(
        &n.join("SOFI_telpol_HD_154445_01.fits"),
        "HIERARCH ESO TEL PARANG START",
        None,
    );
    set_card(
        &n.join("SOFI_telpol_Tel_Mid_04.fits"),
        "HIERARCH ESO TEL PARANG START",
        None,
    );
    let (code, after) = reduce(&n, &dir.path().join("after.json"));
    assert_eq!(code, 0);
    // The night's telescope term is still measured.
    let tel = |c: &Value| c["calibration"]["calibration"]["filters"][0]["telescope"].clone();
    assert!(tel(&after).is_object(), "no telescope term: {}", after["calibration"]);
    let mid = target(&after, "Tel Mid");
    let flags = strings(&mid["flags"]).join("\n");
    assert!(
        flags.contains("Tel_Mid_04.fits") && flags.contains("no ESO TEL PARANG START"),
        "{flags}"
    );
    for (t, b) in after["targets"]
        .as_array()
        .unwrap()
        .iter()
        .zip(before["targets"].as_array().unwrap())
    {
        for (x, y) in t["components"]
            .as_array()
            .unwrap()
            .iter()
            .zip(b["components"].as_array().unwrap())
        {
            let f = strings(&x["flags"]);
            assert!(
                !f.iter().any(|f| f.starts_with("telescope_polarization_uncorrected")),
                "{}: {f:?}",
                t["object"]
            );
            let (g, h, sg) = (
                x["gamma_deg"].as_f64().unwrap(),
                y["gamma_deg"].as_f64().unwrap(),
                y["sigma_gamma_deg"].as_f64().unwrap(),
            );
            assert!((g - h).abs() < sg, "{}: gamma {g} against {h} +- {sg}", t["object"]);
        }
    }
    let dropped = mid["components"][0]["dropped_dithers"].as_array().unwrap();
    assert!(
        dropped
            .iter()
            .any(|d| d["file"].as_str().unwrap().ends_with("Tel_Mid_04.fits")),
        "{dropped:?}"
    );
}

#[test]
fn a_figure_that_is_a_named_pipe_or_huge_is_left_out_without_reading_it() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let cat = dir.path().join("c.json");
    let (code, _, err) = run(&["night", s(&n), "-o", s(&cat), "-q"]);
    assert!(code == 0 || code == 2, "{err}");
    let figs = dir.path().join("c_products");
    let pngs: Vec<PathBuf> = std::fs::read_dir(&figs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    assert!(pngs.len() >= 2, "{pngs:?}");
    // A named pipe nobody writes to: opening it would block for ever.
    std::fs::remove_file(&pngs[0]).unwrap();
    let status = Command::new("mkfifo").arg(&pngs[0]).status().unwrap();
    assert!(status.success());
    // A sparse file far larger than any figure, starting like a PNG.
    let f = std::fs::OpenOptions::new()
        .write(true)
        .truncate(true)
        .open(&pngs[1])
        .unwrap();
    use std::io::Write;
    (&f).write_all(b"\x89PNG\r\n\x1a\n").unwrap();
    f.set_len(3 << 30).unwrap();
    let page = dir.path().join("page.html");
    let t0 = Instant::now();
    let (code, _, err) = run_limited(
        &["report", s(&cat), "-o", s(&page), "--pairs", "2000", "-q"],
        Duration::from_secs(60),
    );
    assert_eq!(code, 0, "{err}");
    assert!(t0.elapsed() < Duration::from_secs(30), "{:?}", t0.elapsed());
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.len() < 50 << 20, "{} bytes", html.len());
}

#[test]
fn a_frame_whose_name_is_not_utf8_is_reduced_like_the_others() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let (_, before) = reduce(&n, &dir.path().join("before.json"));
    let from = n.join("SOFI_telpol_Tel_Easy_03.fits");
    let to = n.join(OsStr::from_bytes(b"SOFI_telpol_Tel_Easy_\xff03.fits"));
    std::fs::rename(&from, &to).unwrap();
    let (code, after) = reduce(&n, &dir.path().join("after.json"));
    assert_eq!(code, 0, "{}", after["failures"]);
    let t = target(&after, "Tel Easy");
    assert_eq!(t["status"], "ok");
    let files = strings(&t["input_files"]);
    assert_eq!(files.len(), 10, "{files:?}");
    assert!(
        files.iter().any(|f| f.ends_with("Tel_Easy_\u{fffd}03.fits")),
        "{files:?}"
    );
    assert_eq!(t["components"], target(&before, "Tel Easy")["components"]);
}

#[test]
fn calibration_values_in_range_but_not_physical_are_refused_by_key_and_the_matrix_read_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let caldir = dir.path().join("cal");
    let (code, _, err) = run(&["calib", s(&n), "-o", s(&caldir), "-q"]);
    assert_eq!(code, 0, "{err}");
    let file = caldir.join("calibration.json");
    let good = json(&file);
    assert!(good["filters"][0]["telescope"].is_object() && good["filters"][0]["covariance"].is_array());
    let with_cal = |cal: &Value, name: &str| {
        let d = dir.path().join(name);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join("calibration.json"), serde_json::to_string_pretty(cal).unwrap()).unwrap();
        let out = dir.path().join(format!("{name}.json"));
        let r = run(&["night", s(&n), "--calib", s(&d), "-o", s(&out), "-q", "--no-png"]);
        (r, out)
    };
    let ((code, _, err), out) = with_cal(&good, "same");
    assert!(code == 0 || code == 2, "{err}");
    let reference = json(&out);
    // Each case: an edit of the good file and what the refusal must name.
    type Edit = Box<dyn Fn(&mut Value)>;
    let edits: Vec<(&str, Edit, &str)> = vec![
        (
            "c",
            Box::new(|c: &mut Value| c["filters"][0]["offset"]["c"] = 0.99.into()),
            "filters[0].offset.c = 0.99",
        ),
        (
            "p_tel",
            Box::new(|c: &mut Value| {
                let t = &mut c["filters"][0]["telescope"];
                let psi = t["psi_tel_deg"].as_f64().unwrap().to_radians() * 2.0;
                t["p_tel"] = 0.19.into();
                t["a"] = (0.19 * psi.cos()).into();
                t["b"] = (0.19 * psi.sin()).into();
            }),
            "filters[0].telescope.p_tel = 0.19",
        ),
        (
            "sigma_c",
            Box::new(|c: &mut Value| {
                let s = c["filters"][0]["offset"]["sigma_c"].as_f64().unwrap();
                c["filters"][0]["offset"]["sigma_c"] = (10.0 * s).into();
            }),
            "filters[0].offset.sigma_c",
        ),
        (
            "duplicate",
            Box::new(|c: &mut Value| {
                let f = c["filters"][0].clone();
                c["filters"].as_array_mut().unwrap().push(f);
            }),
            "filters[1].filter = \"Ks\": the filter is also filters[0]",
        ),
        (
            "names",
            Box::new(|c: &mut Value| c["filters"][0]["covariance_parameters"][3] = "tel_x".into()),
            "covariance_parameters[3] = \"tel_x\"",
        ),
    ];
    for (name, edit, expect) in &edits {
        let mut cal = good.clone();
        edit(&mut cal);
        let ((code, _, err), _) = with_cal(&cal, name);
        assert_eq!(code, 1, "{name}: accepted: {err}");
        assert!(
            err.contains(expect) && err.contains("calibration.json"),
            "{name}: {err}"
        );
        assert!(err.len() < 1000, "{name}: {err}");
    }
    // The covariance written in another order, with its names: the same reduction.
    let mut cal = good.clone();
    let f = &mut cal["filters"][0];
    let order = [3usize, 0, 2, 1];
    let names = f["covariance_parameters"].clone();
    let m = f["covariance"].clone();
    for (a, &i) in order.iter().enumerate() {
        f["covariance_parameters"][a] = names[i].clone();
        for (b, &j) in order.iter().enumerate() {
            f["covariance"][a][b] = m[i][j].clone();
        }
    }
    let ((code, _, err), out) = with_cal(&cal, "permuted");
    assert!(code == 0 || code == 2, "{err}");
    assert_eq!(json(&out)["targets"], reference["targets"]);
}

#[test]
fn a_standards_table_in_per_cent_is_refused_naming_entry_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let table = dir.path().join("std.toml");
    std::fs::write(
        &table,
        "[[standard]]\nname = \"HD 204827\"\nfilter = \"Ks\"\np = 0.88\nsigma_p = 0.2\ngamma_deg = 58.7\n\
         sigma_gamma_deg = 2.0\nband = \"Ks\"\nreference = \"typed in per cent\"\n",
    )
    .unwrap();
    let out = dir.path().join("c.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--standards",
        s(&table),
        "-o",
        s(&out),
        "-q",
        "--no-png",
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("std.toml")
            && err.contains("HD 204827")
            && err.contains("p = 0.88")
            && err.contains("0.0088 for 0.88 %"),
        "{err}"
    );
    assert!(!out.exists());
}

#[test]
fn frames_of_one_template_dated_decades_apart_make_it_partial_naming_the_span() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    set_card(&n.join("SOFI_telpol_Tel_Easy_01.fits"), "MJD-OBS", Some("40587.0"));
    set_card(&n.join("SOFI_telpol_Tel_Easy_10.fits"), "MJD-OBS", Some("88069.0"));
    let (code, c) = reduce(&n, &dir.path().join("c.json"));
    assert_eq!(code, 2);
    let t = target(&c, "Tel Easy");
    assert_eq!(t["status"], "partial");
    let e = t["error"].as_str().unwrap();
    assert!(
        e.contains("MJD-OBS") && e.contains("days") && e.contains("40587"),
        "{e}"
    );
}

#[test]
fn report_to_standard_output_and_catalogs_without_a_schema_version() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let cat = dir.path().join("c.json");
    reduce(&n, &cat);
    let words = ["report", s(&cat), "-o", "-", "--pairs", "2000", "-q"];
    let args: Vec<&OsStr> = words.iter().map(OsStr::new).collect();
    let (code, out, err) = run_os_in(dir.path(), &args, Duration::from_secs(120));
    assert_eq!(code, 0, "{err}");
    assert!(
        out.starts_with("<!DOCTYPE html>") && out.contains("Tel Easy"),
        "{}",
        &out[..out.len().min(200)]
    );
    assert!(!dir.path().join("-").exists(), "a file named '-' was written");
    // The same catalog without its schema_version is not one sofipol wrote.
    let mut c = json(&cat);
    for v in [Value::String(String::new()), Value::Null] {
        match &v {
            Value::Null => {
                c.as_object_mut().unwrap().remove("schema_version");
            }
            _ => c["schema_version"] = v.clone(),
        }
        let bad = dir.path().join("noschema.json");
        std::fs::write(&bad, serde_json::to_string(&c).unwrap()).unwrap();
        let page = dir.path().join("p.html");
        let (code, _, err) = run(&["report", s(&bad), "-o", s(&page), "-q"]);
        assert_eq!(code, 1, "{err}");
        assert!(
            err.contains("noschema.json") && err.contains("no schema_version"),
            "{err}"
        );
        assert!(!page.exists());
    }
}

#[test]
fn messages_are_short_printable_and_a_param_with_a_line_break_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let out = dir.path().join("c.json");
    // A line break in a --param value used to drop the rest silently.
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "-o",
        s(&out),
        "--param",
        "measure.cut_snr=4\nmeasure.clip_sigma=1",
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("line break") && err.contains("\\n") && err.lines().count() == 1,
        "{err}"
    );
    // 1e300 is written short.
    let (code, _, err) = run(&["night", s(&n), "-o", s(&out), "--param", "measure.cut_snr=1e300"]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("1e300") && !err.contains("0000000000000000000000"),
        "{err}"
    );
    // A value of 100 kB is cut in the middle, both ends kept.
    let long = format!("measure.cut_snr={}", "y".repeat(100_000));
    let (code, _, err) = run(&["night", s(&n), "-o", s(&out), "--param", &long]);
    assert_eq!(code, 1, "{}", &err[..err.len().min(300)]);
    assert!(
        err.len() < 2000 && err.contains("characters left out"),
        "{}",
        &err[..err.len().min(300)]
    );
    assert!(!out.exists());
}

#[test]
fn a_fits_export_takes_an_object_with_a_nul_byte_or_70000_characters() {
    let dir = tempfile::tempdir().unwrap();
    let n = telpol_night(dir.path());
    let cat = dir.path().join("c.json");
    reduce(&n, &cat);
    let mut c = json(&cat);
    c["targets"][0]["object"] = "Tel\u{0}Easy".into();
    c["targets"][1]["object"] = "z".repeat(70_000).into();
    let edited = dir.path().join("edited.json");
    std::fs::write(&edited, serde_json::to_string(&c).unwrap()).unwrap();
    let fits = dir.path().join("t.fits");
    let (code, _, err) = run(&["export", s(&edited), "--format", "fits", "-o", s(&fits)]);
    assert_eq!(code, 0, "{err}");
    let mut f = fitsio::FitsFile::open(&fits).unwrap();
    let hdu = f.hdu("SOFIPOL").unwrap();
    let objects: Vec<String> = hdu.read_col(&mut f, "target").unwrap();
    assert!(objects.iter().any(|o| o == "Tel\\x00Easy"), "{:?}", &objects[..2]);
    let long = objects.iter().find(|o| o.starts_with("zzz")).unwrap();
    assert!(
        long.len() <= 1024 && long.ends_with("...(70000 characters)"),
        "{}",
        long.len()
    );
}
