//! `--profile nirc2`: an instrument chosen by its profile. `sofipol night` reduces a
//! half-wave-plate profile with the single-pointing reduction (docs/instruments.md); the
//! commands and options that reduce SOFI's turned instrument refuse it, naming why. On the
//! real Keck/NIRC2 frames of AB Aur (read from ../shared/real, never copied; skipped, saying
//! so, when absent) the folder and a set-of-frames file listing the same frames with their
//! roles give the same result. The night writes sofipol's catalog (one target per star,
//! its half-wave-plate results in `half_wave_plate`), its night log and set-of-frames file;
//! `report`, `stats`, `export` and `merge` read it, and the set-of-frames file repeats the
//! run: on the real frames and on simulated ones (`sofipol simulate` with a half-wave-plate
//! scene).
use std::path::{Path, PathBuf};

use sofipol_pipeline::catalog::Catalog;

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
    let ca = typed(&a);
    assert_eq!(ca.targets.len(), 1);
    let t = &ca.targets[0];
    assert_eq!((t.object.as_str(), t.filter.as_deref()), ("AB Aur", Some("Lp")));
    let hw = t.half_wave_plate.as_ref().expect("half_wave_plate");
    assert_eq!(hw.profile, "NIRC2");
    assert_eq!(
        (hw.frames.len(), hw.cycles.len(), hw.darks.len(), hw.skies.len()),
        (8, 2, 3, 4)
    );
    assert!(t.components[0].p > 0.0);
    // RA '04:55:45.91', DEC '+30:33:08.1' in every frame's header.
    let ra = 15.0 * (4.0 + 55.0 / 60.0 + 45.91 / 3600.0);
    assert!((t.ra_deg.unwrap() - ra).abs() < 1e-9, "{:?}", t.ra_deg);
    assert!((t.dec_deg.unwrap() - (30.0 + 33.0 / 60.0 + 8.1 / 3600.0)).abs() < 1e-9);
    assert_eq!(t.dit_s, Some(0.45));
    every_command(&d.path().join("commands"), &a);
    repeat_from_frames_file(d.path(), &a, &[]);
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
    let cb = typed(&b);
    let tb = &cb.targets[0];
    assert_eq!(tb.object, "AB_Aur_listed");
    let hb = tb.half_wave_plate.as_ref().unwrap();
    assert_eq!((hb.instrument, hb.sky), (hw.instrument, hw.sky));
    assert_eq!(tb.components, t.components);
    // Its own set-of-frames file keeps the name given (target=) and repeats the run.
    let listed = std::fs::read_to_string(d.path().join("b.frames")).unwrap();
    assert!(
        listed.contains("n0932.fits.gz science target=AB_Aur_listed"),
        "{listed}"
    );
    repeat_from_frames_file(d.path(), &b, &[]);
}

/// `path` read as sofipol's typed catalog.
fn typed(path: &Path) -> Catalog {
    let text = std::fs::read_to_string(path).unwrap();
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{} is not sofipol's catalog: {e}", path.display()))
}

/// `night` on the set-of-frames file written beside `catalog`: exit 0 and the same catalog
/// apart from its provenance. `set`: the profile's overrides of the first run.
fn repeat_from_frames_file(dir: &Path, catalog: &Path, set: &[String]) {
    let frames = catalog.with_extension("frames");
    let log = std::fs::read_to_string(catalog.with_extension("log")).expect("night log");
    let first = typed(catalog);
    for f in first.targets.iter().flat_map(|t| t.input_files.iter().flatten()) {
        let name = Path::new(f).file_name().unwrap().to_str().unwrap();
        assert!(log.contains(name), "{name} not in the night log:\n{log}");
    }
    let again = dir.join(format!("{}-again.json", catalog.file_stem().unwrap().to_str().unwrap()));
    let mut args = vec![
        "night".to_string(),
        frames.display().to_string(),
        "--profile".into(),
        "nirc2".into(),
        "-o".into(),
        again.display().to_string(),
    ];
    for s in set {
        args.extend(["--set".to_string(), s.clone()]);
    }
    let (code, _, err) = run(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(code, 0, "{err}");
    let without_provenance = |p: &Path| {
        let mut v = json(p);
        v.as_object_mut().unwrap().remove("provenance");
        v
    };
    assert_eq!(
        without_provenance(catalog),
        without_provenance(&again),
        "{} and the run on {}",
        catalog.display(),
        frames.display()
    );
}

/// `report`, `stats`, `export` (every format) and `merge` on a half-wave-plate catalog:
/// each exits 0 and shows its single-star targets for what they are.
fn every_command(dir: &Path, catalog: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let cat = typed(catalog);
    let c = catalog.to_str().unwrap();
    // The night's page: the component and the half-wave-plate section.
    let html = dir.join("night.html");
    let (code, _, err) = run(&["report", c, "-o", html.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let page = std::fs::read_to_string(&html).unwrap();
    assert!(
        page.contains("<section id=\"half-wave-plate\">"),
        "no half-wave-plate section"
    );
    for t in &cat.targets {
        assert!(page.contains(&t.object), "{} not on the page", t.object);
    }
    // Statistics: no binary, each single star said to have no Delta-gamma.
    let st = dir.join("stats");
    let (code, out, err) = run(&["stats", c, "-o", st.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("0 binaries"), "{out}");
    for t in &cat.targets {
        assert!(
            out.contains(&format!("excluded {}: a single star: no Delta-gamma", t.object)),
            "{out}"
        );
    }
    let stats = json(&st.join("stats.json"));
    assert!(stats.to_string().contains("a single star: no Delta-gamma"), "{stats}");
    // Export: one row per star, q and u as the catalog has them.
    let q: Vec<f64> = cat.targets.iter().map(|t| t.components[0].q).collect();
    let u: Vec<f64> = cat.targets.iter().map(|t| t.components[0].u).collect();
    for format in ["csv", "ecsv", "fits"] {
        let out = dir.join(format!("table.{format}"));
        let (code, _, err) = run(&["export", c, "-o", out.to_str().unwrap()]);
        assert_eq!(code, 0, "{format}: {err}");
        let (tq, tu) = match format {
            "fits" => {
                let mut f = fitsio::FitsFile::open(&out).unwrap();
                let hdu = f.hdu("SOFIPOL").unwrap();
                (
                    hdu.read_col::<f64>(&mut f, "q").unwrap(),
                    hdu.read_col::<f64>(&mut f, "u").unwrap(),
                )
            }
            _ => text_columns(&std::fs::read_to_string(&out).unwrap()),
        };
        assert_eq!((tq, tu), (q.clone(), u.clone()), "{format}");
    }
    // Merge: with itself refused (the same sequences twice), with another night's stars kept whole.
    let m = dir.join("merged.json");
    let (code, _, err) = run(&["merge", c, c, "-o", m.to_str().unwrap()]);
    assert_ne!(code, 0);
    assert!(err.contains("appears in both"), "{err}");
    let (code, _, err) = run(&["merge", c, "-o", m.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let merged = typed(&m);
    assert_eq!(merged.targets, cat.targets);
    assert_eq!(merged.failures, cat.failures);
}

/// The q and u columns of an exported CSV or ECSV table (both comma-separated).
fn text_columns(text: &str) -> (Vec<f64>, Vec<f64>) {
    let mut lines = text.lines().filter(|l| !l.starts_with('#'));
    let sep = ',';
    let header: Vec<&str> = lines.next().unwrap().split(sep).collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .unwrap_or_else(|| panic!("no {name}"))
    };
    let (iq, iu) = (col("q"), col("u"));
    let (mut q, mut u) = (Vec::new(), Vec::new());
    for l in lines {
        // The first columns (target, kind, sequence...) may hold the separator inside quotes:
        // q and u are found from the end, where only numbers, booleans and flags follow.
        let cells = split_quoted(l, sep);
        assert_eq!(cells.len(), header.len(), "{l}");
        q.push(cells[iq].parse().unwrap());
        u.push(cells[iu].parse().unwrap());
    }
    (q, u)
}

/// A line split at `sep` outside double quotes.
fn split_quoted(line: &str, sep: char) -> Vec<String> {
    let (mut out, mut cur, mut quoted) = (Vec::new(), String::new(), false);
    for ch in line.chars() {
        match ch {
            '"' => quoted = !quoted,
            c if c == sep && !quoted => out.push(std::mem::take(&mut cur)),
            c => cur.push(c),
        }
    }
    out.push(cur);
    out
}

/// The overrides of the simulated frames' profile as `--set` arguments.
fn set_args(set: &[String]) -> Vec<String> {
    set.iter().flat_map(|s| ["--set".to_string(), s.clone()]).collect()
}

/// The small detector of the simulated nights: the NIRC2 profile's values the scenes
/// override (`profile_set`) and the night is given by `--set`.
const SETS: [&str; 17] = [
    "geometry.nx=128",
    "geometry.ny=200",
    "geometry.o_sky2=[0, 10]",
    "geometry.e_sky2=[10, 20]",
    "geometry.o_target=[20, 30]",
    "geometry.e_target=[30, 40]",
    "geometry.o_sky1=[40, 50]",
    "geometry.e_sky1=[50, 60]",
    "geometry.eo_offset_px=[-3.0, -100.0]",
    "beams.o_rows=[105, 200]",
    "beams.e_rows=[0, 95]",
    "single_pointing.aperture_px=[0.0, 9.0]",
    "single_pointing.centre_annulus_px=[1.5, 9.0]",
    "single_pointing.sky_fit_min_radius_px=25.0",
    "single_pointing.search_radius_px=4.0",
    "detector.linear_limit_adu=1e9",
    "detector.saturation_adu=2e9",
];

fn sets() -> Vec<String> {
    SETS.iter().map(|s| s.to_string()).collect()
}

/// `sofipol simulate` into `dir`: a noise-free half-wave-plate night named `name` of one
/// star of 4e6 ADU and polarization (p, gamma) on the sky, 10 deg south of the zenith near
/// the meridian (pupil tracking: the sky turns by ~0.7 deg per frame), two cycles of the
/// plate positions 0, 45, 22.5, 67.5 deg, one cycle of sky frames, two darks, a Gaussian
/// PSF, a vignetting pixel response, hot pixels. Returns truth.json.
fn simulate(dir: &Path, name: &str, star: &str, p: f64, gamma_deg: f64) -> serde_json::Value {
    let set = SETS.iter().map(|s| format!("\"{s}\"")).collect::<Vec<_>>().join(", ");
    let scene = format!(
        r#"name = "{name}"
seed = 3
profile = "nirc2"
profile_set = [{set}]
effects = ["psf", "sky", "flat_field", "bad_pixels"]
[observation]
dit_s = 0.45
ndit = 45
overhead_s = 10.0
filter = "Lp"
date = "2025-12-08"
start_ut = "09:00:00"
[psf]
kind = "gaussian"
fwhm_arcsec = 0.047
seeing_rms_frac = 0.0
[sky]
level_adu = 5000.0
gradient_x = 0.0
gradient_y = 0.0
frame_change_frac = 0.0
[flat_field]
pixel_rms = 0.0
vignetting = 0.1
[bad_pixels]
hot_fraction = 1.2e-4
dead_fraction = 0.0
clusters = 0
column_segments = 0
[half_wave_plate]
cycles = 2
sky_cycles = 1
darks = 2
sky_modulation = 0.01
header = {{ ROTPDEST = 45.7 }}
[[half_wave_plate.star]]
name = "{star}"
flux = 4e6
p = {p}
gamma_deg = {gamma_deg}
dec_deg = 10.0
hour_angle_h = -0.05
"#
    );
    let path = dir.with_extension("toml");
    std::fs::write(&path, scene).unwrap();
    let (code, _, err) = run(&["simulate", path.to_str().unwrap(), "-o", dir.to_str().unwrap(), "-q"]);
    assert_eq!(code, 0, "{err}");
    json(&dir.join("truth.json"))
}

/// `night --profile nirc2` on `dir` with the simulated frames' profile: (exit code, stderr).
fn sim_night(dir: &Path, out: &Path) -> (i32, String) {
    let mut args = vec![
        "night".to_string(),
        dir.display().to_string(),
        "--profile".into(),
        "nirc2".into(),
        "-o".into(),
        out.display().to_string(),
    ];
    args.extend(set_args(&sets()));
    let (code, _, err) = run(&args.iter().map(String::as_str).collect::<Vec<_>>());
    (code, err)
}

/// Simulated frames of a known polarization (`sofipol simulate`, noise-free, two plate
/// cycles under pupil tracking): the catalog's component is the sky result within the
/// cycles' blur of the truth, its half-wave-plate section holds the rest; every command
/// reads it; a file that is not a frame is a failure (exit 2, named in the log); the
/// set-of-frames file repeats the run; two nights merge into one catalog with both stars.
#[test]
fn simulated_half_wave_plate_night_through_every_command() {
    let d = tempfile::tempdir().unwrap();
    let (n1, n2) = (d.path().join("n1"), d.path().join("n2"));
    let truth = simulate(&n1, "hwp_a", "Sim Star", 0.0247, 163.6);
    simulate(&n2, "hwp_b", "Other_Star", 0.0202, 61.4);
    let ts = &truth["stars"][0];
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"));
    let (q_true, u_true) = (num(&ts["q"]), num(&ts["u"]));
    let a = d.path().join("a.json");
    let (code, err) = sim_night(&n1, &a);
    assert_eq!(code, 0, "{err}");
    let ca = typed(&a);
    assert!(ca.failures.is_empty(), "{:?}", ca.failures);
    assert_eq!(ca.targets.len(), 1);
    let t = &ca.targets[0];
    assert_eq!(t.object, "Sim Star");
    assert_eq!(t.status, sofipol_pipeline::catalog::Status::Ok);
    assert_eq!(t.components.len(), 1);
    let c = &t.components[0];
    let hw = t.half_wave_plate.as_ref().expect("half_wave_plate");
    assert_eq!(hw.component_from, "cycles");
    // The component is the cycles combined on the sky, as the summary gives it.
    let sky = hw.sky.unwrap();
    assert_eq!(
        (c.q, c.u, c.sigma_q, c.sigma_u),
        (sky.q, sky.u, sky.sigma_q, sky.sigma_u)
    );
    assert_eq!((c.p, c.sigma_p, c.gamma_deg), (sky.p, sky.sigma_p, sky.angle_deg));
    assert!(
        err.contains(&format!("sky q {:+.3} +- {:.3} %", 100.0 * sky.q, 100.0 * sky.sigma_q)),
        "{err}"
    );
    // ... within the cycles' blur of the truth (pipeline/tests/single_pointing_sim.rs): the
    // largest turn of the sky between two frames, from the truth.
    let turns: Vec<f64> = ts["frames"]
        .as_array()
        .expect("frames")
        .iter()
        .map(|f| num(&f["sky_offset_deg"]))
        .collect();
    let step = turns.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
    assert!(step > 0.1 && step < 5.0, "{turns:?}");
    let bound = 1.25 * 2.0 * q_true.hypot(u_true) * step.to_radians();
    assert!(
        (c.q - q_true).abs() < bound && (c.u - u_true).abs() < bound,
        "{} {} vs {q_true} {u_true} (bound {bound})",
        c.q,
        c.u
    );
    // The zero point: in the angle's error, and stated with its source.
    assert_eq!(c.sigma_gamma_zero_point_deg, Some(hw.zero_point.sigma_deg));
    assert!((c.sigma_gamma_deg - sky.sigma_angle_deg.hypot(hw.zero_point.sigma_deg)).abs() < 1e-12);
    assert!(c.flags.iter().any(|f| f.to_string().contains(&hw.zero_point.source)));
    // Frames, times, setup.
    let files: Vec<String> = ts["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| n1.join(f["file"].as_str().unwrap()).display().to_string())
        .collect();
    assert_eq!(files.len(), 8);
    assert_eq!(t.input_files.as_ref(), Some(&files));
    let mjd = hw.frames.iter().map(|f| f.mjd).sum::<f64>() / 8.0;
    // 2025-12-08 is MJD 61017; the night starts at 09:00 UT and lasts 8 x 30 s.
    assert!((t.mjd_mean.unwrap() - mjd).abs() < 1e-9, "{:?} vs {mjd}", t.mjd_mean);
    assert!((61017.375..61017.38).contains(&mjd), "{mjd}");
    assert_eq!((t.filter.as_deref(), t.dit_s), (Some("Lp"), Some(0.45)));
    let (ra, dec) = (num(&ts["ra_deg"]), num(&ts["dec_deg"]));
    assert!(
        (t.ra_deg.unwrap() - ra).abs() < 1e-6 && (t.dec_deg.unwrap() - dec).abs() < 1e-6,
        "{:?} {:?} vs {ra} {dec}",
        t.ra_deg,
        t.dec_deg
    );
    assert_eq!(hw.darks.len(), 2);
    // The one sky cycle is the flat (listed in plate order, the skies in time order).
    let sorted = |v: &[String]| {
        let mut v = v.to_vec();
        v.sort();
        v
    };
    assert_eq!(hw.skies.len(), 4);
    assert_eq!(sorted(&hw.skies), sorted(&hw.flat_from));
    every_command(&d.path().join("commands_a"), &a);
    repeat_from_frames_file(d.path(), &a, &sets());
    // Two nights merged: both stars, each with its own section.
    let b = d.path().join("b.json");
    let (code, err) = sim_night(&n2, &b);
    assert_eq!(code, 0, "{err}");
    let m = d.path().join("m.json");
    let (code, _, err) = run(&[
        "merge",
        a.to_str().unwrap(),
        b.to_str().unwrap(),
        "-o",
        m.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let merged = typed(&m);
    let mut names: Vec<&str> = merged.targets.iter().map(|t| t.object.as_str()).collect();
    names.sort();
    assert_eq!(names, ["Other_Star", "Sim Star"]);
    assert!(merged.targets.iter().all(|t| t.half_wave_plate.is_some()));
    every_command(&d.path().join("commands_m"), &m);
    // `night --report`: the page beside the catalog, with the half-wave-plate section.
    let r = d.path().join("r.json");
    let page = d.path().join("r.html");
    let mut args = vec![
        "night".to_string(),
        n1.display().to_string(),
        "--profile".into(),
        "nirc2".into(),
        "-o".into(),
        r.display().to_string(),
        "--report".into(),
        page.display().to_string(),
    ];
    args.extend(set_args(&sets()));
    let (code, _, err) = run(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(code, 0, "{err}");
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains("<section id=\"half-wave-plate\">") && html.contains("Sim Star"));
    // A file that is not a frame: a failure, named, exit 2; the star as before.
    std::fs::write(n1.join("notes.fits"), b"not a FITS file").unwrap();
    let f = d.path().join("f.json");
    let (code, err) = sim_night(&n1, &f);
    assert_eq!(code, 2, "{err}");
    let cf = typed(&f);
    assert_eq!(cf.failures.len(), 1);
    assert_eq!(cf.failures[0].file, n1.join("notes.fits").display().to_string());
    assert_eq!(cf.targets, ca.targets);
    let log = std::fs::read_to_string(d.path().join("f.log")).unwrap();
    assert!(
        log.lines()
            .any(|l| l.starts_with("notes.fits") && l.contains("not used")),
        "{log}"
    );
    let listed = std::fs::read_to_string(d.path().join("f.frames")).unwrap();
    assert!(listed.contains("# not listed, not used by the run:"), "{listed}");
}
