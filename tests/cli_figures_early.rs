//! The per-target figures are drawn while the night's last targets are still reduced, from
//! the night's calibration chosen before the science targets (the standards reduced first).
//! They must be the figures of the calibrated catalog: a night with standards and
//! instrumental polarization is reduced twice, as is (figures drawn during the reduction)
//! and with `--fits-products` (which draws every figure after the calibration, as all
//! figures were drawn before), and every figure must be the same file, byte for byte.

mod common;
use common::{json, run, ALPHA_BETA};

fn scene() -> String {
    format!(
        r#"name = "early"
seed = 7
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "instrumental_polarization", "throughput"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 4
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[instrumental_polarization]
p = 0.02
angle_deg = 30.0
{ALPHA_BETA}
[[standard]]
name = "HD 64299"
flux = 300000.0
[[standard]]
name = "HD 98161"
flux = 300000.0
[[standard]]
name = "HD 204827"
flux = 300000.0
p = 0.0088
gamma_deg = 58.7
"#
    )
}

#[test]
fn figures_drawn_during_the_reduction_are_those_of_the_calibrated_catalog() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("scene.toml");
    std::fs::write(&scene_path, scene()).unwrap();
    let raw = dir.path().join("raw");
    let (code, _, err) = run(&[
        "simulate",
        scene_path.to_str().unwrap(),
        "-o",
        raw.to_str().unwrap(),
        "-q",
    ]);
    assert_eq!(code, 0, "simulate: {err}");
    let mut figures = Vec::new();
    for (tag, extra) in [("early", None), ("after", Some("--fits-products"))] {
        let out = dir.path().join(tag).join("cat.json");
        let mut args = vec![
            "night",
            raw.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "-q",
            "--jobs",
            "2",
        ];
        args.extend(extra);
        let (code, stdout, err) = run(&args);
        assert!(code == 0 || code == 2, "night {tag}: exit {code}\n{stdout}\n{err}");
        let cat = json(&out);
        // The calibration was measured and moved the numbers: the figures have something
        // to get wrong.
        let offset = &cat["calibration"]["calibration"]["filters"];
        assert!(
            offset.is_array() || offset.is_object(),
            "{tag}: no calibration in {cat:#}"
        );
        let products = dir.path().join(tag).join("cat_products");
        let mut pngs: Vec<(String, Vec<u8>)> = std::fs::read_dir(&products)
            .unwrap()
            .flatten()
            .filter(|e| e.path().extension().is_some_and(|x| x == "png"))
            .map(|e| {
                (
                    e.file_name().to_string_lossy().into_owned(),
                    std::fs::read(e.path()).unwrap(),
                )
            })
            .collect();
        pngs.sort();
        assert_eq!(
            pngs.len(),
            2,
            "{tag}: one figure per binary, got {:?}",
            pngs.iter().map(|p| &p.0).collect::<Vec<_>>()
        );
        figures.push(pngs);
    }
    for ((name, early), (name_after, after)) in figures[0].iter().zip(&figures[1]) {
        assert_eq!(name, name_after);
        assert!(
            early == after,
            "{name}: the figure drawn during the reduction differs from the one drawn after the calibration"
        );
    }
}
