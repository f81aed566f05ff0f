//! Per-frame quality (seeing, sky, airmass, transparency) of a simulated night through the
//! `sofipol` binary, against the simulator's truth: every science frame of the targets and
//! standards in the catalog, its numbers within tolerances of what was simulated, and the
//! night log, the report and its figure showing them.
//!
//! Seen to fail with the build before the catalog kept `frame_quality` (`SOFIPOL_BIN=...`:
//! no `frame_quality` on the first target).
use serde_json::Value;
use sofipol_calib::fits;

mod common;
use common::{json, run, ALPHA_BETA, TWO_STANDARDS};

/// Pixel scale of the SOFI profile, arcsec/px.
const SCALE: f64 = 0.288;

/// A night of two binaries and two standards whose seeing (20 % rms), sky (8 % rms) and
/// transparency (0.6-1) change from frame to frame.
fn scene_toml() -> String {
    format!(
        "name = \"qc\"\nseed = 31\neffects = [\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\", \"transparency\"]\n\
         [observation]\norientations_deg = [0.0, 45.0]\ndithers = 4\n\
         [psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.9\nseeing_rms_frac = 0.2\n\
         [sky]\nlevel_adu = 1500.0\nframe_change_frac = 0.08\n\
         [transparency]\nmin = 0.6\n{TWO_STANDARDS}{ALPHA_BETA}"
    )
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The catalog's quality entries of every target and standard, by file name.
fn entries(cat: &Value) -> std::collections::BTreeMap<String, Value> {
    let mut out = std::collections::BTreeMap::new();
    for list in [&cat["targets"], &cat["standards"]] {
        for t in list.as_array().unwrap() {
            let fq = t["frame_quality"]
                .as_array()
                .unwrap_or_else(|| panic!("no frame_quality on {}", t["object"]));
            for q in fq {
                let name = q["file"].as_str().unwrap().rsplit('/').next().unwrap().to_string();
                out.insert(name, q.clone());
            }
        }
    }
    out
}

#[test]
fn every_science_frame_has_its_simulated_seeing_sky_airmass_and_transparency() {
    let dir = tempfile::tempdir().unwrap();
    let night = dir.path().join("night");
    let scene = dir.path().join("scene.toml");
    std::fs::write(&scene, scene_toml()).unwrap();
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", night.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    let truth = json(&night.join("truth.json"));
    std::fs::rename(night.join("truth.json"), dir.path().join("truth.json")).unwrap();
    let out = dir.path().join("out");
    let cat_path = out.join("catalog.json");
    let page = out.join("night.html");
    let (code, _, err) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        cat_path.to_str().unwrap(),
        "--report",
        page.to_str().unwrap(),
        "-q",
    ]);
    assert_eq!(code, 0, "{err}");
    let cat = json(&cat_path);
    let got = entries(&cat);

    let mut n_frames = 0;
    let (mut worst_fwhm, mut worst_sky, mut worst_t) = (0.0f64, 0.0f64, 0.0f64);
    for seq in truth["targets"]
        .as_array()
        .unwrap()
        .iter()
        .chain(truth["standards"].as_array().unwrap())
    {
        let frames = seq["frames"].as_array().unwrap();
        // The truth's transparency relative to its sequence's median: what the catalog's is.
        let t_median = median(frames.iter().map(|f| f["transparency"].as_f64().unwrap()).collect());
        for f in frames {
            let file = f["file"].as_str().unwrap();
            let q = got.get(file).unwrap_or_else(|| panic!("{file} has no quality entry"));
            n_frames += 1;
            let fwhm = f["fwhm_px"].as_f64().unwrap() * SCALE;
            let rel = q["fwhm_arcsec"].as_f64().unwrap() / fwhm - 1.0;
            worst_fwhm = worst_fwhm.max(rel.abs());
            assert!(rel.abs() < 0.02, "{file}: seeing {q} against {fwhm:.3}\" simulated");
            let sky = f["sky_level_adu"].as_f64().unwrap();
            let rel = q["sky_adu"].as_f64().unwrap() / sky - 1.0;
            worst_sky = worst_sky.max(rel.abs());
            assert!(rel.abs() < 0.002, "{file}: sky {q} against {sky:.1} ADU simulated");
            let t = f["transparency"].as_f64().unwrap() / t_median;
            let d = q["transparency"].as_f64().unwrap() - t;
            worst_t = worst_t.max(d.abs());
            assert!(d.abs() < 0.025, "{file}: transparency {q} against {t:.4} simulated");
            // The airmass is the header's (mean of start and end), the simulated pointing's.
            let p = &f["pointing"];
            let airmass = 0.5 * (p["start"]["airmass"].as_f64().unwrap() + p["end"]["airmass"].as_f64().unwrap());
            assert!(
                (q["airmass"].as_f64().unwrap() - airmass).abs() < 1e-9,
                "{file}: {q} airmass {airmass}"
            );
            let h = fits::read_header(&night.join(file)).unwrap();
            let header = 0.5 * (h.get_f64("ESO TEL AIRM START").unwrap() + h.get_f64("ESO TEL AIRM END").unwrap());
            assert_eq!(q["airmass"].as_f64().unwrap(), header, "{file}");
            assert_eq!(q["mjd"].as_f64().unwrap(), h.get_f64("MJD-OBS").unwrap(), "{file}");
        }
    }
    // 2 binaries and 2 standards, 2 orientations x 4 dithers each.
    assert_eq!(n_frames, 32);
    assert_eq!(got.len(), n_frames, "frames in the catalog that were not simulated");
    eprintln!(
        "worst of {n_frames} frames: seeing {:.1} %, sky {:.2} %, transparency {:.4}",
        100.0 * worst_fwhm,
        100.0 * worst_sky,
        worst_t
    );

    // The night log: the table with every frame, the medians.
    let log = std::fs::read_to_string(out.join("catalog.log")).unwrap();
    let table = log
        .split("## Frame quality")
        .nth(1)
        .expect("no frame-quality table in the log");
    assert!(table.starts_with(": 32 frames"), "{table}");
    assert!(table.contains("night medians: airmass"), "{table}");
    for name in got.keys() {
        let line = table
            .lines()
            .find(|l| l.contains(name.as_str()))
            .unwrap_or_else(|| panic!("{name} not in the table"));
        let q = &got[name];
        assert!(
            line.contains(&format!("{:.2}", q["fwhm_arcsec"].as_f64().unwrap())),
            "{line}"
        );
        assert!(
            line.contains(&format!("{:.3}", q["transparency"].as_f64().unwrap())),
            "{line}"
        );
    }

    // The report: the section with one row per frame, the figure embedded and beside it.
    let html = std::fs::read_to_string(&page).unwrap();
    let section = html
        .split("<section id=\"quality\">")
        .nth(1)
        .expect("no quality section");
    let section = section.split("</section>").next().unwrap();
    assert_eq!(section.matches("<tr><td title=").count(), 32, "{section}");
    assert!(
        section.contains("<img alt=\"Seeing, sky level and transparency"),
        "figure not embedded"
    );
    let png = std::fs::read(out.join("night_figures/quality.png")).expect("the quality figure beside the report");
    assert!(
        section.contains("<a href=\"night_figures/quality.png\""),
        "the figure is not a link to its file"
    );
    assert!(
        png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 10_000,
        "{} bytes",
        png.len()
    );
}
