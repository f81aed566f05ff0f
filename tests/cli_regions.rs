//! `night --regions`: one DS9 region file per frame, its circles on the simulated stars
//! (the simulator's truth, not the reduction's own numbers), read by astropy-regions.
mod common;
use common::*;
use serde_json::Value;
use std::path::Path;

/// A 1-target night (2 orientations x 3 dithers) with its truth.json kept.
fn night(dir: &Path) -> std::path::PathBuf {
    let n = dir.join("night");
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        "name = \"rg\"\nseed = 11\neffects = [\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\"]\n\
         [observation]\norientations_deg = [0.0, 45.0]\ndithers = 3\n[psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.8\n\
         [[binary]]\nname = \"Alpha\"\nseparation_arcsec = 4.0\npa_deg = 30.0\nflux_a = 120000.0\nflux_b = 60000.0\n\
         p_a = 0.05\ngamma_a_deg = 20.0\np_b = 0.04\ngamma_b_deg = 110.0\n",
    )
    .unwrap();
    let (code, _, err) = run(&["simulate", scene.to_str().unwrap(), "-o", n.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    n
}

/// The circles of a region file: (text label, x, y, r) in DS9 image coordinates.
fn circles(text: &str) -> Vec<(String, f64, f64, f64)> {
    text.lines()
        .filter_map(|l| {
            let args = l.strip_prefix("circle(")?.split(')').next()?;
            let v: Vec<f64> = args.split(',').map(|a| a.parse().unwrap()).collect();
            let label = l.split("text={").nth(1)?.split('}').next()?.to_string();
            Some((label, v[0], v[1], v[2]))
        })
        .collect()
}

#[test]
fn region_files_mark_both_stars_in_both_beams_where_the_simulation_put_them() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let truth: Value = serde_json::from_str(&std::fs::read_to_string(n.join("truth.json")).unwrap()).unwrap();
    let cat = dir.path().join("cat.json");
    let (code, out, err) = run(&[
        "night",
        n.to_str().unwrap(),
        "--allow-uncalibrated",
        "-o",
        cat.to_str().unwrap(),
        "--regions",
        "--no-png",
    ]);
    assert_eq!(code, 0, "{out}\n{err}");
    let regions = dir.path().join("cat_products/regions");
    assert!(out.contains(&format!("DS9 regions: {}", regions.display())), "{out}");
    let aperture = json(&cat)["targets"][0]["aperture_radius_px"].as_f64().unwrap();
    let frames = truth["targets"][0]["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 6);
    let mut worst: f64 = 0.0;
    for f in frames {
        let name = f["file"].as_str().unwrap().trim_end_matches(".fits");
        let text = std::fs::read_to_string(regions.join(format!("{name}.reg"))).unwrap();
        assert!(text.starts_with("# Region file format: DS9 version 4.1\n"), "{text}");
        let c = circles(&text);
        assert_eq!(c.len(), 4, "{text}");
        for s in f["sources"].as_array().unwrap() {
            let star = s["name"].as_str().unwrap();
            for beam in ["o", "e"] {
                let xy = &s[format!("{beam}_xy")];
                // The truth is 0-based on the detector; DS9 is 1-based.
                let (tx, ty) = (xy[0].as_f64().unwrap() + 1.0, xy[1].as_f64().unwrap() + 1.0);
                let (_, x, y, r) = c
                    .iter()
                    .find(|c| c.0 == format!("{star} {beam}"))
                    .unwrap_or_else(|| panic!("no {star} {beam} in {text}"));
                worst = worst.max((x - tx).hypot(y - ty));
                assert!(
                    (x - tx).hypot(y - ty) < 0.2,
                    "{name} {star} {beam}: ({x}, {y}) vs truth ({tx}, {ty})"
                );
                assert!((r - aperture).abs() < 1e-3, "{r} vs {aperture}");
            }
        }
    }
    println!("largest distance region - truth: {worst:.3} px");

    // astropy-regions reads every file: 4 circles and 4 annuli, the circles where they are.
    let Some(py) = python_with("regions, astropy", "region files read by astropy-regions") else {
        return;
    };
    let script = r#"
import sys, glob
from regions import Regions, CircleAnnulusPixelRegion, CirclePixelRegion
files = sorted(glob.glob(sys.argv[1] + "/*.reg"))
assert len(files) == 6, files
for f in files:
    r = Regions.read(f, format="ds9")
    circles = [x for x in r if isinstance(x, CirclePixelRegion)]
    annuli = [x for x in r if isinstance(x, CircleAnnulusPixelRegion)]
    assert len(circles) == 4 and len(annuli) == 4, (f, r)
    for c in circles:
        # astropy-regions is 0-based: DS9's (x, y) - 1.
        print(f.split("/")[-1], c.meta["text"], "%.3f %.3f %.3f" % (c.center.x, c.center.y, c.radius))
"#;
    let o = std::process::Command::new(py)
        .args(["-c", script, regions.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let printed = String::from_utf8_lossy(&o.stdout);
    assert_eq!(printed.lines().count(), 24, "{printed}");
    for f in frames {
        let name = f["file"].as_str().unwrap().trim_end_matches(".fits");
        let a_o = &f["sources"][0]["o_xy"];
        let line = printed
            .lines()
            .find(|l| l.starts_with(&format!("{name}.reg A o ")))
            .unwrap_or_else(|| panic!("{printed}"));
        let v: Vec<f64> = line
            .split_whitespace()
            .rev()
            .take(3)
            .map(|w| w.parse().unwrap())
            .collect();
        let (x, y) = (v[2], v[1]);
        let (tx, ty) = (a_o[0].as_f64().unwrap(), a_o[1].as_f64().unwrap());
        assert!((x - tx).hypot(y - ty) < 0.2, "{line} vs ({tx}, {ty})");
    }
}
