//! The night's HTML report opened in a real headless Chromium: a simulated night (Alpha ok,
//! Beta partial, Gamma failed) through `sofipol night --report` and `sofipol report`, then
//! the page loaded with `?selftest=1`: its self-test script (pipeline/src/report/selftest.js)
//! clicks the P/sigma header, ticks "hide failed targets", types in the filter and writes
//! what it saw into `<pre id="selftest">`, which this test reads from the dumped DOM and
//! checks against the catalog (in a 500 px window: the page must not scroll sideways, nor
//! the targets table, a card per row). Before that, the layout at 1400 px and on a 390 px
//! phone, measured by the test's own probe (report_browser/layout.rs, probe.js): no
//! sideways page, no cell cut off, every table whole at 1400 px, sequence ids broken only
//! at '@', every figure on the page (per target, frame quality, statistics) a link to its
//! own PNG file. A screenshot is kept in
//! target/test-artifacts/report.png.
//!
//! The browser: `$SOFIPOL_CHROMIUM` (scripts/test.sh sets it from scripts/browser-env.sh,
//! which installs Debian's chromium), else /usr/bin/chromium or chromium on the PATH; none:
//! SKIPPED (passes, saying so). `SOFIPOL_SKIP_BROWSER=1` skips it explicitly.
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;
use common::{json, run};

#[path = "report_browser/layout.rs"]
mod layout;

/// A binary with every dither at one position (jitter step 0): the night refuses it.
/// The night's standards (one unpolarized, one polarized), observed before the targets:
/// a calibrated night, whose binaries the statistics take.
const STANDARDS: &str = r#"name = "stds"
seed = 9
effects = ["psf", "sky", "strips", "photon_noise", "read_noise"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
start_ut = "00:10:00"
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[[standard]]
name = "HD 64299"
flux = 150000.0
[[standard]]
name = "HD 204827"
flux = 150000.0
p = 0.0088
gamma_deg = 58.7
"#;

const STILL: &str = r#"name = "still"
seed = 8
effects = ["psf", "sky", "strips", "photon_noise", "read_noise"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 3
jitter_step_px = 0.0
start_ut = "04:00:00"
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[[binary]]
name = "Gamma"
separation_arcsec = 2.5
pa_deg = 300.0
flux_a = 90000.0
flux_b = 50000.0
p_a = 0.04
gamma_a_deg = 170.0
p_b = 0.02
gamma_b_deg = 80.0
"#;

fn chromium() -> Option<PathBuf> {
    if std::env::var("SOFIPOL_SKIP_BROWSER").is_ok_and(|v| v == "1") {
        println!("SKIPPED (SOFIPOL_SKIP_BROWSER=1): the report's browser test");
        return None;
    }
    if let Some(p) = std::env::var_os("SOFIPOL_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let found = ["/usr/bin/chromium".into()]
        .into_iter()
        .chain(std::env::var_os("PATH").into_iter().flat_map(|p| {
            std::env::split_paths(&p)
                .flat_map(|d| [d.join("chromium"), d.join("chromium-browser")])
                .collect::<Vec<PathBuf>>()
        }))
        .find(|p: &PathBuf| p.is_file());
    if found.is_none() {
        println!("SKIPPED (no chromium; scripts/test.sh installs it)");
        eprintln!("SKIPPED (no chromium; scripts/test.sh installs it)");
    }
    found
}

/// Run headless Chromium on `url` with `extra` flags and a fresh profile; its stdout. Killed
/// after two minutes.
fn headless(chromium: &Path, work: &Path, extra: &[String], url: &str) -> String {
    let profile = tempfile::tempdir_in(work).unwrap();
    let (out, err) = (work.join("chromium.out"), work.join("chromium.err"));
    let mut child = Command::new(chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .args(extra)
        .arg(url)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap())
        .spawn()
        .unwrap_or_else(|e| panic!("{}: {e}", chromium.display()));
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("chromium still running after 120 s on {url}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let stderr = std::fs::read_to_string(&err).unwrap_or_default();
    assert!(status.success(), "chromium {status} on {url}\n{stderr}");
    std::fs::read_to_string(&out).unwrap()
}

/// The rows of the table as the page lists them, "object/component" ("object/" for a target
/// without components), with their P/sigma and status, in catalog order.
fn rows(cat: &Value) -> Vec<(String, Option<f64>, String)> {
    let mut v = Vec::new();
    for t in cat["targets"].as_array().unwrap() {
        let (object, status) = (t["object"].as_str().unwrap(), t["status"].as_str().unwrap().to_string());
        let comps = t["components"].as_array().unwrap();
        if comps.is_empty() {
            v.push((format!("{object}/"), None, status.clone()));
        }
        for c in comps {
            let snr = c["snr"]
                .as_f64()
                .or_else(|| Some(c["p"].as_f64()? / c["sigma_p"].as_f64()?))
                .filter(|x| x.is_finite());
            v.push((format!("{object}/{}", c["name"].as_str().unwrap()), snr, status.clone()));
        }
    }
    v
}

/// The rows sorted by P/sigma (stable; rows without a value last in both directions).
fn sorted(rows: &[(String, Option<f64>, String)], ascending: bool) -> Vec<String> {
    let mut r = rows.to_vec();
    r.sort_by(|a, b| match (a.1, b.1) {
        (Some(x), Some(y)) if ascending => x.total_cmp(&y),
        (Some(x), Some(y)) => y.total_cmp(&x),
        (a, b) => b.is_some().cmp(&a.is_some()),
    });
    r.into_iter().map(|x| x.0).collect()
}

fn strings(v: &Value) -> Vec<String> {
    v.as_array()
        .unwrap_or_else(|| panic!("not a list: {v}"))
        .iter()
        .map(|s| s.as_str().unwrap().to_string())
        .collect()
}

#[test]
fn the_night_report_loads_sorts_filters_and_shows_every_image_in_chromium() {
    let Some(chromium) = chromium() else { return };
    let dir = tempfile::tempdir().unwrap();
    let n = common::night(dir.path());
    // Beta loses a dither (partial); Gamma never moves between dithers (failed).
    std::fs::remove_file(common::frames_of(&n, "Beta")[2].clone()).unwrap();
    let scene = dir.path().join("still.toml");
    std::fs::write(&scene, STILL).unwrap();
    common::simulate_into(&scene, &n);
    let scene = dir.path().join("standards.toml");
    std::fs::write(&scene, STANDARDS).unwrap();
    common::simulate_into(&scene, &n);

    let cat_path = dir.path().join("cat.json");
    let night_html = dir.path().join("out/night.html");
    let (code, out, err) = run(&[
        "night",
        n.to_str().unwrap(),
        "-o",
        cat_path.to_str().unwrap(),
        "--report",
        night_html.to_str().unwrap(),
    ]);
    assert_eq!(code, 2, "a night with a failed target\n{out}\n{err}");
    assert!(night_html.is_file(), "night --report wrote no page\n{out}");
    let cat = json(&cat_path);
    let rows = rows(&cat);
    let status = |s: &str| rows.iter().filter(|r| r.2 == s).count();
    assert!(
        status("ok") >= 2 && status("partial") >= 1 && status("failed") >= 1,
        "{rows:?}"
    );

    let page = dir.path().join("report.html");
    let (code, out, err) = run(&[
        "report",
        cat_path.to_str().unwrap(),
        "-o",
        page.to_str().unwrap(),
        "--pairs",
        "20000",
    ]);
    assert_eq!(code, 0, "{out}\n{err}");
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(
        !html.contains("http://") && !html.contains("https://"),
        "the page refers to the network"
    );
    let figures = std::fs::read_dir(sofipol_pipeline::night::products_dir(&cat_path))
        .unwrap()
        .filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "png"))
        .count();
    assert_eq!(figures, cat["targets"].as_array().unwrap().len(), "a figure per target");

    // The layout at a desktop width and on a phone, measured by the test's own probe.
    let products = sofipol_pipeline::night::products_dir(&cat_path);
    let mut bad = Vec::new();
    for width in [1400, 390] {
        let m = layout::measure(&chromium, dir.path(), &page, width);
        println!("layout at {width} px: {m}");
        let own = sofipol_pipeline::report::report_figures_dir(&page);
        bad.extend(layout::problems(&m, width, &products, &own));
    }
    assert!(bad.is_empty(), "the page does not read well:\n{}", bad.join("\n"));

    let url = format!("file://{}?selftest=1&q=Beta", page.display());
    let dom = headless(
        &chromium,
        dir.path(),
        &[
            "--virtual-time-budget=5000".into(),
            "--window-size=500,900".into(),
            "--dump-dom".into(),
        ],
        &url,
    );
    let start = dom
        .rfind("<pre id=\"selftest\"")
        .expect("no selftest element in the DOM");
    let body = &dom[start + dom[start..].find('>').unwrap() + 1..];
    let text = &body[..body.find("</pre>").unwrap()];
    let st: Value = serde_json::from_str(text).unwrap_or_else(|e| panic!("self-test output {text:?}: {e}"));

    assert_eq!(st["errors"], Value::Array(vec![]), "errors in the page");
    let images = st["images"].as_array().unwrap();
    assert_eq!(images.len(), html.matches("<img ").count());
    assert!(
        images.len() > figures,
        "the night's figures and the statistics' figures: {images:?}"
    );
    for im in images {
        assert!(im["naturalWidth"].as_u64().unwrap() > 0, "image not decoded: {im}");
    }

    // In a narrow window (500 px: headless Chromium's smallest) the page does not scroll
    // sideways and the targets table needs no sideways scrolling either: a card per row.
    let w = |k: &str| {
        st["layout"][k]
            .as_u64()
            .unwrap_or_else(|| panic!("layout.{k}: {}", st["layout"]))
    };
    assert!(w("inner_width") <= 500, "{}", st["layout"]);
    assert!(
        w("page_width") <= w("inner_width"),
        "the page is wider than the window: {}",
        st["layout"]
    );
    assert!(
        w("table_width") <= w("table_box"),
        "the targets table needs sideways scrolling: {}",
        st["layout"]
    );

    let initial: Vec<String> = rows.iter().map(|r| r.0.clone()).collect();
    assert_eq!(strings(&st["initial"]), initial, "rows in catalog order");
    let up = sorted(&rows, true);
    assert_ne!(up, initial, "the test needs a catalog not already sorted by P/sigma");
    assert_eq!(strings(&st["sort_snr_first"]), up, "first click: P/sigma ascending");
    assert_eq!(st["sort_snr_first_dir"], "ascending");
    let down = sorted(&rows, false);
    assert_eq!(
        strings(&st["sort_snr_second"]),
        down,
        "second click: P/sigma descending"
    );

    let failed: Vec<&String> = rows.iter().filter(|r| r.2 == "failed").map(|r| &r.0).collect();
    let kept: Vec<String> = down.iter().filter(|r| !failed.contains(r)).cloned().collect();
    assert_eq!(strings(&st["hide_failed"]), kept, "hide failed targets");
    assert_eq!(st["text_filter"]["q"], "Beta");
    let beta: Vec<String> = down.iter().filter(|r| r.starts_with("Beta/")).cloned().collect();
    assert_eq!(strings(&st["text_filter"]["rows"]), beta, "text filter");
    assert_eq!(strings(&st["after_clear"]), down, "filter cleared");

    // The screenshot, kept as a test artifact.
    let artifacts = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .unwrap()
        .join("test-artifacts");
    std::fs::create_dir_all(&artifacts).unwrap();
    let shot = artifacts.join("report.png");
    let _ = std::fs::remove_file(&shot);
    headless(
        &chromium,
        dir.path(),
        &[
            "--window-size=1280,2000".into(),
            format!("--screenshot={}", shot.display()),
        ],
        &format!("file://{}", page.display()),
    );
    let png = std::fs::read(&shot).unwrap_or_else(|e| panic!("{}: {e}", shot.display()));
    assert!(
        png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 20_000,
        "{} bytes",
        png.len()
    );
    let width = u32::from_be_bytes(png[16..20].try_into().unwrap());
    assert_eq!(width, 1280, "screenshot width");
    println!("screenshot: {}", shot.display());
}
