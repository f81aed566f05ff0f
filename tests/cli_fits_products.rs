//! `night --fits-products`: the FITS products of a simulated night checked against
//! independent references: the simulated fluxes and PSFs (truth.json), the pixel scatter of
//! blank sky, centroids measured here on the pixels, the catalog's q and u; their headers;
//! a second night over a folder holding them; the bad-pixel mask read back by `--badpix`;
//! astropy opening them.
mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use common::{aperture, centroid, json, run};
use serde_json::Value;
use sofipol_calib::fits::read_frame;
use sofipol_calib::Frame;

/// The e image 0.4 px right of and 0.4 px below the whole-pixel offset of the profile: the
/// e beam's sub-pixel shift onto the o grid is then 0.4 px in each axis.
const EO: &str = "geometry.eo_offset_px=[0.4,166.6]";

/// Solo: one polarized star (its companion, 30 ADU, is not found); Pair: a 3" binary. Four
/// orientations of 3 dithers, a Moffat PSF whose FWHM changes from frame to frame, a
/// pointing error (the dithers' sub-pixel positions differ), the detector's bad pixels.
const SCENE: &str = r#"name = "fp"
seed = 11
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "pointing_error", "bad_pixels"]
[observation]
orientations_deg = [0.0, 45.0, 90.0, 135.0]
dithers = 3
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[pointing_error]
rms_px = 0.7
[[binary]]
name = "Solo"
separation_arcsec = 5.0
pa_deg = 30.0
flux_a = 150000.0
flux_b = 30.0
p_a = 0.04
gamma_a_deg = 30.0
p_b = 0.0
gamma_b_deg = 0.0
[[binary]]
name = "Pair"
separation_arcsec = 3.0
pa_deg = 200.0
flux_a = 100000.0
flux_b = 70000.0
p_a = 0.03
gamma_a_deg = 60.0
p_b = 0.06
gamma_b_deg = 150.0
"#;

/// The night, reduced once with `--fits-products` (the catalog and its products inside the
/// night folder, as an observer may leave them): (night folder, catalog, products folder).
fn reduced() -> &'static (PathBuf, PathBuf, PathBuf) {
    static NIGHT: OnceLock<(PathBuf, PathBuf, PathBuf)> = OnceLock::new();
    NIGHT.get_or_init(|| {
        let root = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cli_fits_products");
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        let scene = root.join("scene.toml");
        std::fs::write(&scene, SCENE).unwrap();
        let night = root.join("night");
        let (code, _, err) = run(&[
            "simulate",
            scene.to_str().unwrap(),
            "-o",
            night.to_str().unwrap(),
            "--set",
            EO,
            "-q",
        ]);
        assert_eq!(code, 0, "{err}");
        std::fs::rename(night.join("truth.json"), root.join("truth.json")).unwrap();
        let cat = night.join("out").join("cat.json");
        let (code, out, err) = run(&[
            "night",
            night.to_str().unwrap(),
            "-o",
            cat.to_str().unwrap(),
            "--fits-products",
            "--no-png",
            "--set",
            EO,
        ]);
        // Solo's companion is not found: partial, exit 2.
        assert_eq!(code, 2, "{out}\n{err}");
        assert!(out.contains("fits products: "), "{out}");
        let products = night.join("out").join("cat_products").join("fits");
        (night, cat, products)
    })
}

fn truth() -> Value {
    json(
        &Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join("cli_fits_products")
            .join("truth.json"),
    )
}

fn target<'a>(cat: &'a Value, object: &str) -> &'a Value {
    cat["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == object)
        .unwrap_or_else(|| panic!("no {object} in the catalog"))
}

/// The product of `object` (`what`: `pa0_o`, `stokes`...): `<object>_<TPL START>_<what>.fits`.
fn product(dir: &Path, object: &str, what: &str) -> PathBuf {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| {
            let n = p.file_name().unwrap().to_string_lossy();
            n.starts_with(&format!("{object}_1999-03-03T")) && n.ends_with(&format!("_{what}.fits"))
        })
        .unwrap_or_else(|| panic!("no {what} product of {object} in {}", dir.display()))
}

fn hf(f: &Frame, key: &str) -> f64 {
    f.header
        .get_f64(key)
        .unwrap_or_else(|e| panic!("{}: {key}: {e}", f.path().display()))
}

fn hs(f: &Frame, key: &str) -> String {
    f.header
        .get_str(key)
        .unwrap_or_else(|e| panic!("{}: {key}: {e}", f.path().display()))
}

/// The fraction of a Moffat star (FWHM `fwhm` px, `beta`) within `r`:
/// 1 - (1 + (r/alpha)^2)^(1 - beta), alpha = FWHM / (2 sqrt(2^(1/beta) - 1)).
fn moffat_fraction(fwhm: f64, beta: f64, r: f64) -> f64 {
    let alpha = fwhm / (2.0 * (2f64.powf(1.0 / beta) - 1.0).sqrt());
    1.0 - (1.0 + (r / alpha).powi(2)).powf(1.0 - beta)
}

const POSANGS: [f64; 4] = [0.0, 45.0, 90.0, 135.0];

/// The combined o image's flux within 5 FWHM equals the simulated o flux of the star (times
/// the Moffat fraction inside) within 4 sigma of the UNCERT (variance) summed there; its target
/// sits where its header says; the e image's star is where the o one is plus the shift the
/// Stokes maps bring it back by.
#[test]
fn combined_images_keep_the_flux_and_register_o_and_e() {
    let (_, _, dir) = reduced();
    let truth = truth();
    let frames = truth["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == "Solo")
        .unwrap()["frames"]
        .as_array()
        .unwrap()
        .clone();
    let stokes = read_frame(&product(dir, "Solo", "stokes")).unwrap();
    for (k, pa) in POSANGS.iter().enumerate() {
        let o = read_frame(&product(dir, "Solo", &format!("pa{pa}_o"))).unwrap();
        let e = read_frame(&product(dir, "Solo", &format!("pa{pa}_e"))).unwrap();
        // The header's target position against the pixels' centroid.
        let (tx, ty) = (hf(&o, "ESO QC TARGET X") - 1.0, hf(&o, "ESO QC TARGET Y") - 1.0);
        let (cx, cy) = centroid(&o.data, tx, ty, 6.0);
        assert!(
            (cx - tx).abs() < 0.05 && (cy - ty).abs() < 0.05,
            "POSANG {pa}: o star at ({cx}, {cy}), header ({tx}, {ty})"
        );
        // e: the star at the o star + EOSHIFT (the Stokes maps resample e back by it).
        let n = k + 1;
        let (sx, sy) = (
            hf(&stokes, &format!("ESO QC ORI{n} EOSHIFT X")),
            hf(&stokes, &format!("ESO QC ORI{n} EOSHIFT Y")),
        );
        assert_eq!(hf(&stokes, &format!("ESO QC ORI{n} POSANG")), *pa);
        assert!(
            sx.abs() > 0.3 && sy.abs() > 0.3,
            "POSANG {pa}: shift ({sx}, {sy}) too small to test"
        );
        let (ex, ey) = centroid(&e.data, cx + sx, cy + sy, 6.0);
        assert!(
            (ex - sx - cx).abs() < 0.05 && (ey - sy - cy).abs() < 0.05,
            "POSANG {pa}: e star at ({ex}, {ey}) - shift ({sx}, {sy}) is not the o star ({cx}, {cy})"
        );
        // Flux against the simulation.
        let dithers: Vec<&Value> = frames.iter().filter(|f| f["posang_deg"] == *pa).collect();
        assert_eq!(dithers.len(), 3);
        assert_eq!(hf(&o, "ESO QC NDITHER"), 3.0);
        let fwhm = dithers.iter().map(|f| f["fwhm_px"].as_f64().unwrap()).sum::<f64>() / 3.0;
        let r = 5.0 * fwhm;
        let want: f64 = dithers
            .iter()
            .map(|f| {
                let a = &f["sources"][0];
                assert_eq!(a["name"], "A");
                a["flux_o"].as_f64().unwrap()
                    * moffat_fraction(f["fwhm_px"].as_f64().unwrap(), f["beta"].as_f64().unwrap(), r)
            })
            .sum::<f64>()
            / 3.0;
        let got = aperture(&o.data, cx, cy, r);
        let sigma = aperture(o.variance.as_ref().unwrap(), cx, cy, r).sqrt();
        assert!(
            (got - want).abs() < 4.0 * sigma,
            "POSANG {pa}: o flux {got} within {r:.1} px, simulated {want} (sigma {sigma})"
        );
    }
}

/// The UNCERT extension (a variance) is the variance of the pixels: on blank sky (the cut-outs'
/// corners, far from the star) the mean of value^2 / variance is 1.
#[test]
fn the_variance_extension_matches_the_scatter_of_blank_sky() {
    let (_, _, dir) = reduced();
    let (mut chi2, mut n) = (0.0, 0usize);
    for pa in POSANGS {
        for beam in ["o", "e"] {
            let f = read_frame(&product(dir, "Solo", &format!("pa{pa}_{beam}"))).unwrap();
            let var = f.variance.as_ref().unwrap();
            let side = f.shape().0;
            assert!(side >= 41, "{side}");
            for ((j, i), &v) in f.data.indexed_iter() {
                let corner = (i < 10 || i >= side - 10) && (j < 10 || j >= side - 10);
                if corner && f.mask[[j, i]] == 0 {
                    chi2 += (v as f64).powi(2) / var[[j, i]] as f64;
                    n += 1;
                }
            }
        }
    }
    assert!(n > 2500, "{n} blank pixels");
    let ratio = chi2 / n as f64;
    // sqrt(2/n) = 0.03 of scatter: 0.85..1.15 is 5 sigma.
    assert!(
        (ratio - 1.0).abs() < 0.15,
        "scatter^2 / UNCERT = {ratio} over {n} pixels"
    );
}

/// The Stokes maps summed over an aperture of twice the catalog's radius give the catalog's
/// q and u of the star (within 3 sigma of the maps' own propagated error), and I is centred
/// on the grid's centre pixel.
#[test]
fn stokes_maps_summed_in_an_aperture_give_the_catalogs_q_and_u() {
    let (_, cat, dir) = reduced();
    let cat = json(cat);
    let solo = target(&cat, "Solo");
    let a = &solo["components"][0];
    let path = product(dir, "Solo", "stokes");
    let i = read_frame(&path).unwrap();
    assert_eq!(hs(&i, "SOFIPROD"), "STOKES");
    assert_eq!(hs(&i, "ESO PRO CATG"), "SOFIPOL_STOKES_IQU");
    assert_eq!(i.header.get("POLCALIB"), Some(&sofipol_calib::HeaderValue::Bool(false)));
    let c = hf(&i, "ESO QC TARGET X") - 1.0;
    assert_eq!(c, (i.shape().0 / 2) as f64);
    let mut f = fitsio::FitsFile::open(&path).unwrap();
    let mut ext = |name: &str| -> ndarray::Array2<f32> {
        let hdu = f.hdu(name).unwrap();
        let v: Vec<f32> = hdu.read_image(&mut f).unwrap();
        ndarray::Array2::from_shape_vec(i.shape(), v).unwrap()
    };
    let (q, u, vq, vu) = (ext("Q"), ext("U"), ext("VAR_Q"), ext("VAR_U"));
    let r = 2.0 * solo["aperture_radius_px"].as_f64().unwrap();
    let si = aperture(&i.data, c, c, r);
    let (mq, mu) = (aperture(&q, c, c, r) / si, aperture(&u, c, c, r) / si);
    let (sq, su) = (aperture(&vq, c, c, r).sqrt() / si, aperture(&vu, c, c, r).sqrt() / si);
    let (cq, cu) = (a["q"].as_f64().unwrap(), a["u"].as_f64().unwrap());
    assert!((mq - cq).abs() < 3.0 * sq, "q: maps {mq} +- {sq}, catalog {cq}");
    assert!((mu - cu).abs() < 3.0 * su, "u: maps {mu} +- {su}, catalog {cu}");
    let (cx, cy) = centroid(&i.data, c, c, 6.0);
    assert!(
        (cx - c).abs() < 0.05 && (cy - c).abs() < 0.05,
        "I centred at ({cx}, {cy}), not {c}"
    );
    // The maps' errors are those of the star's photometry, not far from the catalog's
    // measurement error (the catalog's sigma_q also carries the calibration's, e.g. the
    // telescope's term where it was not removed).
    let cs = a["sigma_q_stat"].as_f64().unwrap();
    assert!(
        sq > 0.7 * cs && sq < 3.0 * cs,
        "maps' sigma_q {sq}, catalog's measurement error {cs}"
    );
}

/// Every product says what it is and where it comes from.
#[test]
fn every_product_carries_its_category_provenance_and_history() {
    let (night, _, dir) = reduced();
    let (_, version, _) = run(&["--version"]);
    let commit = version
        .split("commit ")
        .nth(1)
        .unwrap()
        .trim_end_matches([')', '\n'])
        .to_string();
    let mut n = 0;
    for object in ["Solo", "Pair"] {
        for pa in POSANGS {
            for (beam, catg) in [("o", "SOFIPOL_COMBINED_O"), ("e", "SOFIPOL_COMBINED_E")] {
                let f = read_frame(&product(dir, object, &format!("pa{pa}_{beam}"))).unwrap();
                let who = f.path().display().to_string();
                assert_eq!(hs(&f, "SOFIPROD"), "COMBINED", "{who}");
                assert_eq!(hs(&f, "ESO PRO CATG"), catg, "{who}");
                assert_eq!(hs(&f, "ESO PRO REC1 ID"), "sofipol", "{who}");
                assert_eq!(
                    hs(&f, "ESO PRO REC1 DRS ID"),
                    format!("sofipol-{}", env!("CARGO_PKG_VERSION")),
                    "{who}"
                );
                assert!(hs(&f, "PROCSOFT").contains(&commit), "{who}: {commit}");
                assert_eq!(hs(&f, "OBJECT"), object, "{who}");
                assert_eq!(hs(&f, "FILTER"), "Ks", "{who}");
                assert_eq!(hs(&f, "BUNIT"), "adu", "{who}");
                assert_eq!(hf(&f, "POSANG"), pa, "{who}");
                for k in [
                    "ESO QC FWHM",
                    "ESO QC EO OFFSET X",
                    "ESO QC EO OFFSET Y",
                    "ESO QC NDITHER",
                ] {
                    assert!(hf(&f, k).is_finite(), "{who}: {k}");
                }
                // The input frames by name, and only this orientation's.
                for d in 1..=3 {
                    let raw = hs(&f, &format!("ESO PRO REC1 RAW{d} NAME"));
                    assert!(night.join(&raw).is_file() && raw.contains(object), "{who}: {raw}");
                }
                let stages: Vec<&str> = f.history.iter().map(|h| h.stage.as_str()).collect();
                for s in ["badpix", "flat", "sky", "register", "combine"] {
                    assert!(stages.contains(&s), "{who}: no HISTORY of {s}: {stages:?}");
                }
                assert!(f.history.iter().any(|h| h.detail.contains("no interpolation")), "{who}");
                assert!(f.variance.is_some(), "{who}");
                n += 1;
            }
        }
        let s = read_frame(&product(dir, object, "stokes")).unwrap();
        let stages: Vec<&str> = s.history.iter().map(|h| h.stage.as_str()).collect();
        for st in ["sky", "register", "resample", "stokes", "calibration"] {
            assert!(stages.contains(&st), "{object} stokes: no HISTORY of {st}: {stages:?}");
        }
        assert_eq!(hf(&s, "ESO PRO DATANCOM"), 12.0);
    }
    // The pair and its photometry fit in the cut-out: separation + the sky annulus (6 FWHM).
    let cat = json(&reduced().1);
    let pair = target(&cat, "Pair");
    let f = read_frame(&product(dir, "Pair", "pa0_o")).unwrap();
    let half = hf(&f, "ESO QC CUTOUT HALF");
    let sep_px = pair["separation_arcsec"].as_f64().unwrap() / 0.288;
    assert!(
        half >= sep_px + 6.0 * hf(&f, "ESO QC FWHM"),
        "half {half}, separation {sep_px} px"
    );
    assert_eq!(f.shape(), (2 * half as usize + 1, 2 * half as usize + 1));
    assert_eq!(n, 16);
}

/// A second night over the folder holding the products skips every one of them by its
/// SOFIPROD and reduces the same targets to the same numbers.
#[test]
fn a_second_night_skips_the_products() {
    let (night, cat, dir) = reduced();
    let first = json(cat);
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cli_fits_products_second");
    let _ = std::fs::remove_dir_all(&out);
    let second = out.join("cat.json");
    let (code, _, err) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        second.to_str().unwrap(),
        "--no-png",
        "--set",
        EO,
        "-q",
    ]);
    assert_eq!(code, 2, "{err}");
    let second = json(&second);
    let products: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(products.len(), 2 * (8 + 1) + 1, "{products:?}");
    for p in &products {
        let f = second["failures"]
            .as_array()
            .unwrap()
            .iter()
            .find(|f| Path::new(f["file"].as_str().unwrap()) == p)
            .unwrap_or_else(|| panic!("{} not listed under failures", p.display()));
        let why = f["error"].as_str().unwrap();
        assert!(
            why.contains("a sofipol product (SOFIPROD = '"),
            "{}: {why}",
            p.display()
        );
    }
    assert_eq!(second["targets"].as_array().unwrap().len(), 2);
    for object in ["Solo", "Pair"] {
        let (a, b) = (
            &target(&first, object)["components"][0],
            &target(&second, object)["components"][0],
        );
        assert_eq!(a["q"], b["q"], "{object}");
        assert_eq!(a["u"], b["u"], "{object}");
    }
}

/// The night's bad-pixel mask is a product `--badpix` reads back: every pixel it marks is
/// masked in the target reduced with it.
#[test]
fn the_night_mask_is_read_back_by_badpix() {
    let (night, _, dir) = reduced();
    let path = dir.join("night_badpix.fits");
    let m = read_frame(&path).unwrap();
    assert_eq!(hs(&m, "SOFIPROD"), "BADPIX");
    assert_eq!(hs(&m, "ESO PRO CATG"), "SOFIPOL_BADPIX");
    let nbad = hf(&m, "ESO QC BADPIX NBAD") as usize;
    let mask = sofipol_calib::badpix::load_mask(&path).unwrap();
    assert_eq!(mask.iter().filter(|&&v| v != 0).count(), nbad);
    // The simulated detector's defects (3e-4 hot, 3e-4 dead, clusters, columns) in the
    // target strips (334 rows): a few hundred.
    assert!(nbad > 50, "{nbad} bad pixels");
    let (row0, row1) = (
        hf(&m, "ESO QC BADPIX ROW0") as usize,
        hf(&m, "ESO QC BADPIX ROW1") as usize,
    );
    assert!(mask
        .indexed_iter()
        .all(|((j, _), &v)| v == 0 || (j + 1 >= row0 && j < row1)));
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cli_fits_products_badpix");
    let _ = std::fs::remove_dir_all(&out);
    let cat = out.join("solo.json");
    let (code, _, err) = run(&[
        "target",
        night.to_str().unwrap(),
        "--object",
        "Solo",
        "--badpix",
        path.to_str().unwrap(),
        "--fits-products",
        "-o",
        cat.to_str().unwrap(),
        "--set",
        EO,
        "-q",
    ]);
    assert!(code == 0 || code == 2, "{err}");
    assert!(!err.contains("badpix"), "{err}");
    let t = &json(&cat)["targets"][0];
    assert_ne!(t["status"], "failed", "{t}");
    let masked = t["bad_pixels_masked"].as_u64().unwrap() as usize;
    assert!(masked >= nbad, "{masked} pixels masked with --badpix marking {nbad}");
    // `target --fits-products` writes its own products beside its catalog.
    let own = out.join("solo_products").join("fits");
    assert_eq!(std::fs::read_dir(&own).unwrap().count(), 9, "{}", own.display());
}

/// astropy opens the products: extension names, data types and shapes, the HIERARCH cards
/// and HISTORY; `CCDData.read` with its defaults gets the data, the variance (as a
/// `VarianceUncertainty`), the mask and the unit of a cut-out and of the Stokes maps; every
/// cut-out's WCS puts the target star on its pixel, +y at PA POSANG and -x to the east.
#[test]
fn astropy_opens_the_products() {
    let Some(python) = common::python_with("astropy", "astropy_opens_the_products") else {
        return;
    };
    let (_, _, dir) = reduced();
    let script = r#"
import sys
import numpy as np
from astropy.io import fits
from astropy.nddata import CCDData, VarianceUncertainty
import astropy.units as u
with fits.open(sys.argv[1]) as h:
    assert [x.name for x in h] == ["PRIMARY", "UNCERT", "MASK", "NCOMBINE"], [x.name for x in h]
    p = h[0].header
    assert p["ESO PRO CATG"] == "SOFIPOL_COMBINED_O", p["ESO PRO CATG"]
    assert p["SOFIPROD"] == "COMBINED" and p["BUNIT"] == "adu" and p["OBJECT"] == "Solo"
    assert p["HIERARCH ESO QC NDITHER"] == 3
    assert any("register" in str(c) for c in p["HISTORY"])
    assert h[0].data.shape == h["UNCERT"].data.shape == h["MASK"].data.shape
    assert h["MASK"].data.dtype.name == "uint8" and h[0].data.dtype.name.startswith("float")
    assert h["UNCERT"].header["BUNIT"] == "adu2"
    assert h["UNCERT"].header["UTYPE"] == "VarianceUncertainty"
    var, mask, data = h["UNCERT"].data, h["MASK"].data, h[0].data
# CCDData with astropy's defaults: data, its variance, the mask and the unit.
for path in sys.argv[1:3]:
    c = CCDData.read(path)
    assert c.unit == u.adu, (path, c.unit)
    assert isinstance(c.uncertainty, VarianceUncertainty), (path, type(c.uncertainty))
    assert c.mask is not None and c.mask.shape == c.data.shape, path
c = CCDData.read(sys.argv[1])
assert np.array_equal(c.uncertainty.array, var, equal_nan=True)
# The cut-outs' WCS: the target star (at the pointing) on its pixel, +y towards PA POSANG,
# the pixel scale the profile's, in the o and the e cut-out of every orientation.
from astropy.wcs import WCS
from astropy.coordinates import SkyCoord
for path in sys.argv[4:]:
    with fits.open(path) as h:
        p = h[0].header
    w = WCS(p)
    star = SkyCoord(p["RA"] * u.deg, p["DEC"] * u.deg)
    x, y = w.world_to_pixel(star)
    tx, ty = p["HIERARCH ESO QC TARGET X"] - 1, p["HIERARCH ESO QC TARGET Y"] - 1
    assert abs(x - tx) < 1e-6 and abs(y - ty) < 1e-6, (path, x, y, tx, ty)
    up = w.pixel_to_world(tx, ty + 10)
    d = (star.position_angle(up).deg - p["POSANG"] + 180) % 360 - 180
    assert abs(d) < 1e-4, (path, star.position_angle(up).deg, p["POSANG"])
    assert abs(star.separation(up).arcsec - 10 * 0.288) < 1e-6, star.separation(up).arcsec
    left = w.pixel_to_world(tx - 10, ty)
    d = (star.position_angle(left).deg - (p["POSANG"] + 90) + 180) % 360 - 180
    assert abs(d) < 1e-4, (path, "-x is east of +y")
assert np.array_equal(c.mask, mask != 0) and np.array_equal(c.data, data, equal_nan=True)
with fits.open(sys.argv[2]) as h:
    names = [x.name for x in h]
    assert names == ["PRIMARY", "Q", "U", "UNCERT", "VAR_Q", "VAR_U", "COV_QU", "MASK"], names
    assert h[0].header["ESO PRO CATG"] == "SOFIPOL_STOKES_IQU"
    assert h[0].header["POLCALIB"] is False
with fits.open(sys.argv[3]) as h:
    assert h[0].header["ESO PRO CATG"] == "SOFIPOL_BADPIX" and h[0].data.dtype.name == "uint8"
    assert h[0].data.shape == (1024, 1024)
print("ok")
"#;
    let o = Command::new(&python)
        .args(["-c", script])
        .arg(product(dir, "Solo", "pa45_o"))
        .arg(product(dir, "Solo", "stokes"))
        .arg(dir.join("night_badpix.fits"))
        .args(
            POSANGS
                .iter()
                .flat_map(|pa| ["o", "e"].map(|b| product(dir, "Solo", &format!("pa{pa}_{b}")))),
        )
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "astropy: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// A product that cannot be written (a directory stands where its file goes) is a flag on
/// its target and a line on stderr, the run exits 2 and writes everything else.
#[test]
fn a_product_not_written_flags_its_target_and_the_night_goes_on() {
    let root = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cli_fits_products_blocked");
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();
    let night = common::night(&root);
    let cat = root.join("out").join("cat.json");
    let fits = root.join("out").join("cat_products").join("fits");
    let blocked = fits.join("Alpha_1999-03-03T01_00_00_pa45_e.fits");
    std::fs::create_dir_all(&blocked).unwrap();
    let (code, out, err) = run(&[
        "night",
        night.to_str().unwrap(),
        "-o",
        cat.to_str().unwrap(),
        "--fits-products",
        "--no-png",
    ]);
    assert_eq!(code, 2, "{out}\n{err}");
    assert!(
        err.contains("FITS product not written") && err.contains("pa45_e.fits"),
        "{err}"
    );
    assert!(err.contains("the products are incomplete"), "{err}");
    let cat = json(&cat);
    let alpha = target(&cat, "Alpha");
    let flags: Vec<&str> = alpha["flags"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert!(
        flags
            .iter()
            .any(|f| f.starts_with("fits_product_not_written: ") && f.contains("pa45_e.fits")),
        "{flags:?}"
    );
    // Everything else was written: Alpha's other files, Beta's, the mask.
    for what in ["pa0_o", "pa0_e", "pa45_o", "stokes"] {
        assert!(
            fits.join(format!("Alpha_1999-03-03T01_00_00_{what}.fits")).is_file(),
            "{what}"
        );
    }
    assert!(fits.join("night_badpix.fits").is_file());
    assert!(blocked.is_dir());
    let beta = target(&cat, "Beta");
    assert!(!beta["flags"]
        .as_array()
        .unwrap()
        .iter()
        .any(|f| f.as_str().unwrap().starts_with("fits_product")));
}
