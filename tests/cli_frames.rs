//! One broken exposure among good ones: the frame is dropped by name, the other dithers
//! of its orientation carry on, and the target is reduced (`partial`, exit 2).
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_frames` runs these tests against
//! another build (how they were checked to fail before the fix).
use std::path::{Path, PathBuf};

use serde_json::Value;
use sofipol_calib::fits;

mod common;
use common::{json as catalog, run, ALPHA_BETA};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A simulated 2-target night (Alpha, Beta; 2 orientations x 4 dithers, 1500 ADU of sky)
/// in `dir/night`.
fn night(dir: &Path) -> PathBuf {
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            r#"
name = "fr"
seed = 11
effects = ["psf", "sky", "strips", "photon_noise", "read_noise"]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 4
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
{ALPHA_BETA}"#
        ),
    )
    .unwrap();
    let n = dir.join("night");
    let (code, _, err) = run(&["simulate", s(&scene), "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    std::fs::rename(n.join("truth.json"), dir.join("truth.json")).unwrap();
    n
}

/// Every component of `object` in catalog `c` within 5 sigma of the simulated truth in
/// q and u (the night is uncalibrated and the scene has no instrumental effects).
fn agrees_with_truth(c: &Value, truth: &Value, object: &str, what: &str) {
    let t = target(c, object);
    let tt = truth["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == object)
        .unwrap();
    let comps = t["components"].as_array().unwrap();
    assert_eq!(comps.len(), 2, "{what}: {t}");
    for (i, comp) in comps.iter().enumerate() {
        for k in ["q", "u"] {
            let got = comp[k].as_f64().unwrap_or(f64::NAN);
            let sigma = comp[format!("sigma_{k}")].as_f64().unwrap_or(f64::NAN);
            let want = tt["components"][i][k].as_f64().unwrap();
            assert!(
                sigma > 0.0 && ((got - want) / sigma).abs() < 5.0,
                "{what}: {object} component {i} {k} = {got} +- {sigma}, truth {want}"
            );
        }
    }
}

fn target<'a>(c: &'a Value, name: &str) -> &'a Value {
    c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["object"] == name)
        .unwrap_or_else(|| panic!("no target {name} in {c}"))
}

/// The byte offset of the data of a FITS file's primary HDU (the header's 2880-byte
/// blocks up to the END card).
fn data_start(bytes: &[u8]) -> usize {
    let end = bytes
        .chunks(80)
        .position(|c| c.starts_with(b"END") && c[3..].iter().all(|&b| b == b' '))
        .expect("END card");
    ((end + 1) * 80).div_ceil(2880) * 2880
}

/// Replace the header card of `key` (8 characters, padded) by `key = value`.
fn set_card(bytes: &mut [u8], key: &str, value: &str) {
    let k = format!("{key:<8}= ");
    let i = bytes[..data_start(bytes)]
        .chunks(80)
        .position(|c| c.starts_with(k.as_bytes()))
        .unwrap_or_else(|| panic!("no card {key}"));
    let card = format!("{k}{value:>20}");
    let card = format!("{card:<80}");
    bytes[i * 80..(i + 1) * 80].copy_from_slice(card.as_bytes());
}

/// The four ways of breaking one exposure, each of which leaves no sky to measure.
#[derive(Debug, Clone, Copy)]
enum Damage {
    /// min(data x 30, 37000) with a dead column: every sky pixel saturated.
    Saturated,
    /// An int16 copy whose BSCALE is -1: the data read back negated.
    NegativeBscale,
    /// The float32 data byte-swapped (a copy tool that got the endianness wrong).
    ByteSwapped,
    /// The background removed: data - its median, a sky level of about 0.
    ZeroBackground,
}

fn damage(path: &Path, how: Damage) {
    let mut f = fits::read_frame(path).unwrap();
    match how {
        Damage::Saturated => {
            f.data.mapv_inplace(|v| (v * 30.0).min(37000.0));
            // A dead column: the frame is not all one value.
            f.data.column_mut(5).fill(0.0);
            fits::write_frame(path, &f, &Default::default()).unwrap();
        }
        Damage::NegativeBscale => {
            // Stored as unsigned 16-bit (BZERO 32768) raw + 32768, then BZERO 0 and
            // BSCALE -1: physical = -stored_signed = -raw.
            f.data.mapv_inplace(|v| v.round() + 32768.0);
            let opts = fits::WriteOptions {
                bitpix: fits::Bitpix::I16,
                ..Default::default()
            };
            fits::write_frame(path, &f, &opts).unwrap();
            let mut b = std::fs::read(path).unwrap();
            set_card(&mut b, "BZERO", "0");
            set_card(&mut b, "BSCALE", "-1");
            std::fs::write(path, b).unwrap();
        }
        Damage::ByteSwapped => {
            fits::write_frame(path, &f, &Default::default()).unwrap();
            let mut b = std::fs::read(path).unwrap();
            let (ny, nx) = f.shape();
            let d0 = data_start(&b);
            for px in b[d0..d0 + 4 * ny * nx].chunks_mut(4) {
                px.reverse();
            }
            std::fs::write(path, b).unwrap();
        }
        Damage::ZeroBackground => {
            let mut v: Vec<f32> = f.data.iter().copied().collect();
            let mid = v.len() / 2;
            let med = *v.select_nth_unstable_by(mid, f32::total_cmp).1;
            f.data.mapv_inplace(|x| x - med);
            fits::write_frame(path, &f, &Default::default()).unwrap();
        }
    }
}

/// One exposure of Alpha (dither 2, orientation POSANG 0) broken four ways in turn: each
/// time the frame is named under `failures` with the reason (and nothing else is), the
/// orientation keeps its 3 other dithers, Alpha is `partial` with q and u of both
/// components within 5 sigma of the truth, Beta is `ok` and within 5 sigma too, and the
/// exit code is 2. Before, the whole orientation was dropped and Alpha failed ("need at
/// least 2 analyzer angles").
#[test]
fn one_frame_without_a_measurable_sky_is_dropped_by_name_and_the_target_is_reduced() {
    let dir = tempfile::tempdir().unwrap();
    let n = night(dir.path());
    let truth = catalog(&dir.path().join("truth.json"));
    let clean_out = dir.path().join("clean.json");
    let (code, _, err) = run(&[
        "night",
        s(&n),
        "--allow-uncalibrated",
        "-o",
        s(&clean_out),
        "-q",
        "--no-png",
    ]);
    assert_eq!(code, 0, "{err}");
    let clean = catalog(&clean_out);
    for object in ["Alpha", "Beta"] {
        agrees_with_truth(&clean, &truth, object, "clean");
    }
    let frame = n.join("SOFI_fr_Alpha_02.fits");
    let original = std::fs::read(&frame).unwrap();
    for how in [
        Damage::Saturated,
        Damage::NegativeBscale,
        Damage::ByteSwapped,
        Damage::ZeroBackground,
    ] {
        std::fs::write(&frame, &original).unwrap();
        damage(&frame, how);
        let out = dir.path().join(format!("{how:?}.json"));
        let (code, _, err) = run(&["night", s(&n), "--allow-uncalibrated", "-o", s(&out), "-q", "--no-png"]);
        assert_eq!(code, 2, "{how:?}: {err}");
        let c = catalog(&out);
        let what = format!("{how:?}");
        let alpha = target(&c, "Alpha");
        assert_eq!(alpha["status"], "partial", "{how:?}: {alpha}");
        assert!(alpha["error"].as_str().unwrap().contains("dropped"), "{how:?}: {alpha}");
        agrees_with_truth(&c, &truth, "Alpha", &what);
        assert_eq!(target(&c, "Beta")["status"], "ok", "{how:?}");
        agrees_with_truth(&c, &truth, "Beta", &what);
        let fl = c["failures"].as_array().unwrap();
        assert_eq!(fl.len(), 1, "{how:?}: {fl:?}");
        let (file, error) = (fl[0]["file"].as_str().unwrap(), fl[0]["error"].as_str().unwrap());
        assert!(file.ends_with("SOFI_fr_Alpha_02.fits"), "{how:?}: {file}");
        assert!(
            error.contains("sky level") && error.contains("frame not used"),
            "{how:?}: {error}"
        );
        // The flag names the frame too.
        assert!(
            alpha["flags"]
                .as_array()
                .unwrap()
                .iter()
                .any(|f| f.as_str().unwrap().contains("SOFI_fr_Alpha_02.fits")),
            "{how:?}: {alpha}"
        );
    }
}
