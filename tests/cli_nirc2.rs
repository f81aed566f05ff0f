//! `--profile nirc2`: an instrument chosen by its profile. `sofipol night` reduces a
//! half-wave-plate profile with the single-pointing reduction (docs/instruments.md); the
//! commands and options that reduce SOFI's turned instrument refuse it, naming why. On the
//! real Keck/NIRC2 frames of AB Aur (read from ../shared/real, never copied; skipped, saying
//! so, when absent) the folder and a set-of-frames file listing the same frames with their
//! roles give the same result.
use std::path::{Path, PathBuf};

mod common;
use common::{json, run};

fn real() -> Option<PathBuf> {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/real/nirc2-abaur-lprime");
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!("SKIPPED the real-frame part: {} is absent", d.display());
        None
    }
}

#[test]
fn a_half_wave_plate_profile_is_refused_where_it_cannot_be_reduced() {
    let d = tempfile::tempdir().unwrap();
    let dir = d.path().to_str().unwrap();
    let out = d.path().join("c.json");
    let (code, _, err) = run(&[
        "target",
        dir,
        "--profile",
        "nirc2",
        "--object",
        "x",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_ne!(code, 0);
    assert!(
        err.contains("NIRC2") && err.contains("half_wave_plate") && err.contains("sofipol night"),
        "{err}"
    );
    let (code, _, err) = run(&[
        "night",
        dir,
        "--profile",
        "nirc2",
        "--shard",
        "1/2",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_ne!(code, 0);
    assert!(err.contains("--shard") && err.contains("NIRC2"), "{err}");
    // Every SOFI-only option is refused, each named with why, all at once.
    let (code, _, err) = run(&[
        "night",
        dir,
        "--profile",
        "nirc2",
        "--regions",
        "--stokes-method",
        "ratio",
        "--aperture-fwhm",
        "2",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_ne!(code, 0);
    for flag in [
        "--regions: no DS9 region files",
        "--stokes-method: q and u come from",
        "--aperture-fwhm: the aperture is single_pointing.aperture_px",
    ] {
        assert!(err.contains(flag), "{flag}: {err}");
    }
    assert!(!out.exists());
    // A bad value of a new section is refused naming the key.
    let (code, _, err) = run(&[
        "night",
        dir,
        "--profile",
        "nirc2",
        "--set",
        "modulation.tolerance_deg=30",
    ]);
    assert_ne!(code, 0);
    assert!(err.contains("modulation.tolerance_deg = 30"), "{err}");
    // An empty folder: said, nothing written.
    let (code, _, err) = run(&["night", dir, "--profile", "nirc2", "-o", out.to_str().unwrap()]);
    assert_ne!(code, 0);
    assert!(err.contains("no FITS files"), "{err}");
    assert!(!out.exists());
}

#[test]
fn nirc2_night_from_a_folder_and_from_a_frames_file() {
    let Some(frames) = real() else {
        return;
    };
    let d = tempfile::tempdir().unwrap();
    let a = d.path().join("a.json");
    let (code, _, err) = run(&[
        "night",
        frames.to_str().unwrap(),
        "--profile",
        "nirc2",
        "-o",
        a.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("AB Aur Lp (8 frames, 2 cycles): sky q"), "{err}");
    assert!(err.contains("consecutive cycles differ by"), "{err}");
    let ca = json(&a);
    assert_eq!(ca["kind"], "sofipol half-wave-plate single-pointing catalog");
    assert_eq!(ca["profile"], "NIRC2");
    let t = &ca["targets"][0];
    assert_eq!(t["name"], "AB Aur");
    assert!(t["sky"]["p"].as_f64().unwrap() > 0.0);
    // The same frames through a set-of-frames file, roles given there, the science frames
    // named another target.
    let list = d.path().join("abaur.frames");
    let mut text = String::new();
    for (file, role) in [
        ("n0902", "sky"),
        ("n0903", "sky"),
        ("n0904", "sky"),
        ("n0905", "sky"),
        ("n0984", "dark"),
        ("n0985", "dark"),
        ("n0986", "dark"),
    ] {
        text += &format!("{}/{file}.fits.gz {role}\n", frames.display());
    }
    for k in 932..=939 {
        text += &format!("{}/n0{k}.fits.gz science target=AB_Aur_listed\n", frames.display());
    }
    std::fs::write(&list, text).unwrap();
    let b = d.path().join("b.json");
    let (code, _, err) = run(&[
        "night",
        list.to_str().unwrap(),
        "--profile",
        "nirc2",
        "-o",
        b.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let cb = json(&b);
    let tb = &cb["targets"][0];
    assert_eq!(tb["name"], "AB_Aur_listed");
    for frame in ["instrument", "sky"] {
        for k in ["q", "u", "sigma_q", "sigma_u"] {
            assert_eq!(t[frame][k], tb[frame][k], "{frame}.{k}");
        }
    }
}
