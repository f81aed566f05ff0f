use super::*;
use crate::reduce::{BeamFlux, DitherValue};

fn beam(x: f64, y: f64) -> BeamFlux {
    BeamFlux {
        flux: 1e4,
        var: 1e4,
        xy: (x, y),
        phot_flags: 0,
        aperture_fraction: None,
    }
}

fn dither(o: (f64, f64), e: (f64, f64), rejected: Option<&str>) -> DitherValue {
    DitherValue {
        f: 0.01,
        sigma_f: 0.001,
        o: beam(o.0, o.1),
        e: beam(e.0, e.1),
        rejected: rejected.map(String::from),
    }
}

/// Two orientations of two dithers; B's second dither at the second orientation left out.
fn outcome() -> TargetOutcome {
    let a = vec![
        vec![
            dither((10.0, 20.0), (10.5, 187.0), None),
            dither((35.0, 20.0), (35.5, 187.0), None),
        ],
        vec![
            dither((11.0, 21.0), (11.5, 188.0), None),
            dither((36.0, 21.0), (36.5, 188.0), None),
        ],
    ];
    let b = vec![
        vec![
            dither((14.0, 22.0), (14.5, 189.0), None),
            dither((39.0, 22.0), (39.5, 189.0), None),
        ],
        vec![
            dither((15.0, 23.0), (15.5, 190.0), None),
            dither((40.0, 23.0), (f64::NAN, f64::NAN), Some("cosmic_ray")),
        ],
    ];
    let measured = Measured {
        eo_offset_px: (0.5, 167.0),
        fwhm_px: 3.0,
        frame_fwhm_px: Vec::new(),
        geometry: Some((1.0, 60.0)),
        photometry: "aperture".into(),
        aperture_px: 4.5,
        dithers: vec![a, b],
        flags: Vec::new(),
        field: Vec::new(),
    };
    let files = |k: usize| {
        (1..=2)
            .map(|d| PathBuf::from(format!("/n/raw/SOFI_{k}{d}.fits.gz")))
            .collect()
    };
    TargetOutcome {
        target: crate::catalog::Target::new("HK Tau", crate::catalog::Status::Ok),
        failures: Vec::new(),
        times: Default::default(),
        calibrated: None,
        measured: Some(measured),
        frame_files: vec![files(1), files(2)],
        row_offset: 345,
    }
}

#[test]
fn one_file_per_frame_in_ds9_image_coordinates() {
    let params = MeasureParams::default();
    let files = target_regions(&outcome(), &params, "sofipol 9.9 (abc)");
    let names: Vec<&str> = files.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["SOFI_11.reg", "SOFI_12.reg", "SOFI_21.reg", "SOFI_22.reg"]);
    let t = &files[1].text;
    assert!(t.starts_with("# Region file format: DS9 version 4.1\n"), "{t}");
    assert!(t.contains("HK Tau on /n/raw/SOFI_12.fits.gz"), "{t}");
    assert!(t.contains("\nimage\n"), "{t}");
    // 0-based (35, 20) in the strip starting at row 345 -> DS9 (36, 366).
    let r_in = params.annulus_fwhm.0 * 3.0;
    let r_out = params.annulus_fwhm.1 * 3.0;
    assert!(
        t.contains("circle(36.000,366.000,4.500) # color=green text={A o}"),
        "{t}"
    );
    assert!(
        t.contains("circle(36.500,533.000,4.500) # color=green text={A e}"),
        "{t}"
    );
    assert!(
        t.contains(&format!(
            "annulus(40.000,368.000,{r_in:.3},{r_out:.3}) # color=cyan dash=1"
        )),
        "{t}"
    );
    // Each frame holds its own dither: 2 components x 2 beams.
    assert_eq!(t.matches("circle(").count(), 4, "{t}");
}

#[test]
fn a_left_out_dither_is_red_with_its_reason_and_missing_positions_are_skipped() {
    let files = target_regions(&outcome(), &MeasureParams::default(), "sofipol");
    let t = &files[3].text;
    assert!(
        t.contains("circle(41.000,369.000,4.500) # color=red text={B o left out: cosmic_ray}"),
        "{t}"
    );
    // B's e position is unknown in that dither: no region for it.
    assert_eq!(t.matches("text={B e").count(), 0, "{t}");
    assert_eq!(t.matches("circle(").count(), 3, "{t}");
}

#[test]
fn a_failed_target_has_no_regions_and_headers_cannot_break_lines() {
    let mut out = outcome();
    out.target.object = "X\n# injected\x1b".into();
    let f = target_regions(&out, &MeasureParams::default(), "s");
    assert!(
        !f[0].text.contains("\n# injected") && !f[0].text.contains('\x1b'),
        "{}",
        f[0].text
    );
    out.measured = None;
    assert!(target_regions(&out, &MeasureParams::default(), "s").is_empty());
}

#[test]
fn written_atomically_into_a_new_folder() {
    let dir = tempfile::tempdir().unwrap();
    let sub = dir.path().join("regions");
    let files = target_regions(&outcome(), &MeasureParams::default(), "s");
    assert!(write_regions(&sub, &files).iter().all(|(_, r)| r.is_ok()));
    let mut listed: Vec<String> = std::fs::read_dir(&sub)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    listed.sort();
    assert_eq!(listed, ["SOFI_11.reg", "SOFI_12.reg", "SOFI_21.reg", "SOFI_22.reg"]);
    assert_eq!(std::fs::read_to_string(sub.join("SOFI_21.reg")).unwrap(), files[2].text);
}
