use super::*;
use crate::catalog::{Component, Failure, StandardResult, Target};

fn component(name: &str, flags: &[&str]) -> Component {
    let mut c: Component = serde_json::from_value(serde_json::json!({
        "name": name, "q": 0.03, "u": 0.04, "sigma_q": 0.005, "sigma_u": 0.005,
        "p": 0.05, "sigma_p": 0.005, "p_debiased": 0.0497, "gamma_deg": 26.57,
        "sigma_gamma_deg": 2.9, "passes_cut": true, "flags": []
    }))
    .unwrap();
    c.flags = flags.iter().map(|f| Flag::parse(f)).collect();
    c
}

/// A night: one target of 4 frames (one dropped), one standard of 2 frames, a superflat
/// of the target's frames, a mask from two of them, and a file that is not a frame.
fn night() -> Catalog {
    let mut target = Target::new("HK Tau", Status::Partial);
    target.error = Some("a dither was dropped".into());
    target.components = vec![
        component("A", &["bad_pixels: 1 of 4 dithers dropped (POSANG 0)"]),
        component("B", &[]),
    ];
    target.sequence = Some("HK Tau@2026-11-26T01:00:00".into());
    target.input_files = Some((1..=4).map(|i| format!("/data/night/raw/hk_{i}.fits")).collect());
    target.flags = Some(vec![Flag::parse("mystery_flag: x")]);
    target.components[0].dropped_dithers = Some(vec![crate::catalog::DroppedDither {
        file: "/data/night/raw/hk_2.fits".into(),
        reason: "bad_pixels".into(),
    }]);
    let standard: StandardResult = serde_json::from_value(serde_json::json!({
        "name": "HD 64299", "object": "HD64299", "sequence": "s", "filter": "Ks",
        "status": "ok", "used_for": ["offset"], "flags": [],
        "input_files": ["/data/night/raw/std_1.fits", "/data/night/raw/std_2.fits"]
    }))
    .unwrap();
    Catalog {
        targets: vec![target],
        standards: vec![standard],
        failures: vec![
            Failure {
                file: "/data/night/raw/hk_3.fits".into(),
                error: "primary star not found\nin its frame".into(),
            },
            Failure {
                file: "/data/night/notes.fits".into(),
                error: "not a FITS file: starts with 'junk'".into(),
            },
        ],
        provenance: serde_json::from_value(serde_json::json!({
            "software": "sofipol 9.9.9",
            "commit": "abc1234",
            "command_line": ["sofipol", "night", "raw", "-o", "night.json"],
            "flat": {"mode": "superflat", "flats": [{"kind": "superflat", "filter": "Ks", "posang_deg": null,
                "frames": ["/data/night/raw/hk_1.fits", "/data/night/raw/hk_2.fits"]}]},
            "night_bad_pixel_mask_from": ["/data/night/raw/hk_1.fits", "/data/night/raw/std_1.fits"],
        }))
        .unwrap(),
        ..Default::default()
    }
}

fn line_of<'a>(log: &'a str, file: &str) -> &'a str {
    log.lines()
        .find(|l| l.starts_with(file))
        .unwrap_or_else(|| panic!("no line for {file} in\n{log}"))
}

#[test]
fn every_file_gets_one_line_with_its_use_and_outcome() {
    let log = night_log(&night(), "night.json");
    // Paths are shown under the folder they share.
    assert!(log.contains("frames under: /data/night/\n"), "{log}");
    assert!(
        log.contains("7 in all, 4 used, 1 used in part, 1 dropped, 1 not used"),
        "{log}"
    );
    let l = line_of(&log, "raw/hk_1.fits");
    assert!(l.contains(" used ") && l.contains("target HK Tau"), "{l}");
    assert!(l.contains("superflat Ks") && l.contains("bad-pixel mask"), "{l}");
    let l = line_of(&log, "raw/hk_2.fits");
    assert!(
        l.contains(" in part ") && l.contains("HK Tau left out of A: bad_pixels"),
        "{l}"
    );
    let l = line_of(&log, "raw/hk_3.fits");
    assert!(
        l.contains(" dropped ") && l.contains("primary star not found in its frame"),
        "{l}"
    );
    let l = line_of(&log, "notes.fits");
    assert!(l.contains(" not used ") && l.contains("not a FITS file"), "{l}");
    let l = line_of(&log, "raw/std_2.fits");
    assert!(l.contains("standard HD 64299 (calibration: offset)"), "{l}");
    // One line per file: 7 files.
    let n = log
        .lines()
        .filter(|l| l.starts_with("raw/") || l.starts_with("notes"))
        .count();
    assert_eq!(n, 7, "{log}");
}

#[test]
fn targets_list_their_components_and_flags_in_words() {
    let log = night_log(&night(), "night.json");
    assert!(
        log.contains("HK Tau [HK Tau@2026-11-26T01:00:00]: partial (a dither was dropped)"),
        "{log}"
    );
    assert!(
        log.contains("A: P = 5.00 +- 0.50 %, gamma = 26.6 +- 2.9 deg, P/sigma = 9.9, passes the cut"),
        "{log}"
    );
    // A known flag with its sentence, an unknown one as it is.
    assert!(
        log.contains(
            "A: bad_pixels -- A dither was dropped: bad pixels in the aperture. (1 of 4 dithers dropped (POSANG 0))"
        ),
        "{log}"
    );
    assert!(log.contains("\n  mystery_flag: x\n"), "{log}");
    assert!(log.contains("software: sofipol 9.9.9 (commit abc1234)"), "{log}");
    assert!(log.contains("command: sofipol night raw -o night.json"), "{log}");
}

#[test]
fn the_common_folder_stops_at_a_path_separator() {
    assert_eq!(common_dir(["/a/raw1/x.fits", "/a/raw2/y.fits"].into_iter()), "/a/");
    assert_eq!(common_dir(["/a/b/x.fits", "/a/b/y.fits"].into_iter()), "/a/b/");
    assert_eq!(common_dir(["x.fits", "/a/y.fits"].into_iter()), "");
    assert_eq!(common_dir(std::iter::empty()), "");
}

#[test]
fn the_log_is_named_for_the_catalog_and_never_replaces_it() {
    assert_eq!(log_path(Path::new("out/night.json")), Path::new("out/night.log"));
    assert_eq!(log_path(Path::new("night")), Path::new("night.log"));
    assert_eq!(log_path(Path::new("a/night.log")), Path::new("a/night.log.log"));
}

#[test]
fn text_from_headers_cannot_forge_lines_or_escape_sequences() {
    let mut cat = night();
    cat.targets[0].object = "HK Tau\nFAKE.fits  used  target X\x1b[2J".into();
    let log = night_log(&cat, "night.json");
    assert!(!log.contains('\x1b'), "{log}");
    assert!(!log.lines().any(|l| l.starts_with("FAKE")), "{log}");
}

/// `night()` with a quality entry for each of HK Tau's frames (hk_4 under a cloud, hk_2 in
/// bad seeing) and the standard's.
fn night_with_quality() -> Catalog {
    let mut cat = night();
    let q = |i: usize, fwhm: f64, t: f64| crate::catalog::FrameQuality {
        file: format!("/data/night/raw/hk_{i}.fits"),
        posang_deg: 0.0,
        dither: i,
        mjd: Some(61005.25 + 0.001 * i as f64),
        airmass: Some(1.1 + 0.01 * i as f64),
        fwhm_arcsec: Some(fwhm),
        sky_adu: Some(1500.0 + i as f64),
        transparency: Some(t),
    };
    cat.targets[0].frame_quality = Some(vec![
        q(1, 0.80, 1.0),
        q(2, 1.40, 1.01),
        q(3, 0.82, 0.99),
        q(4, 0.81, 0.55),
    ]);
    let mut s = q(9, 0.79, 1.0);
    s.file = "/data/night/raw/std_1.fits".into();
    s.mjd = Some(61005.2);
    cat.standards[0].frame_quality = Some(vec![s]);
    cat
}

#[test]
fn the_quality_table_lists_every_frame_in_time_order_with_the_medians_and_marks_outliers() {
    let log = night_log(&night_with_quality(), "night.json");
    let table = log.split("## Frame quality").nth(1).expect(&log);
    assert!(table.starts_with(": 5 frames of the targets and standards"), "{table}");
    // Medians of the 5 frames: seeing 0.81, sky 1503 ADU, transparency 1.0.
    assert!(
        table.contains("night medians: airmass 1.130, seeing 0.81\", sky 1503.0 ADU, transparency 1.000"),
        "{table}"
    );
    let rows: Vec<&str> = table.lines().filter(|l| l.starts_with("raw/")).collect();
    assert_eq!(rows.len(), 5, "{table}");
    // The standard was observed first (MJD), then hk_1 ... hk_4.
    assert!(
        rows[0].starts_with("raw/std_1.fits") && rows[0].contains("HD 64299 (std)"),
        "{table}"
    );
    assert!(rows[1].contains("06:01:26") && rows[1].contains("1.110"), "{}", rows[1]);
    assert!(rows[2].contains("1.40") && rows[2].ends_with("* seeing"), "{}", rows[2]);
    assert!(
        rows[4].contains("0.550") && rows[4].ends_with("* transparency"),
        "{}",
        rows[4]
    );
    assert!(!rows[3].contains('*') && !rows[1].contains('*'), "{table}");
}

#[test]
fn a_catalog_without_quality_has_no_quality_table() {
    assert!(!night_log(&night(), "night.json").contains("Frame quality"));
}
