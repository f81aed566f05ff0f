use super::*;

/// A flag of `code` as the pipeline writes it (no wildcard: a new code must bring its
/// example here).
fn example(code: FlagCode) -> &'static str {
    use FlagCode::*;
    match code {
        Uncalibrated => "uncalibrated",
        CalibrationIncomplete => "calibration_incomplete",
        ZeroPointFromProfile => "zero_point_from_profile",
        CalibrationLacksFilter => {
            "calibration_lacks_filter: cal/calibration.json has no offset c for filter H: q and u uncorrected"
        }
        TelescopeUncorrected => "telescope_polarization_uncorrected",
        TelescopeFromPrior => "telescope_polarization_from_prior",
        TelescopeUnaccounted => "telescope_polarization_unaccounted",
        StokesMethodFailed => "stokes_method_failed: needs 4 orientations; fell back to least_squares (uncalibrated)",
        BadPixels => "bad_pixels: 1 of 12 dithers dropped (a masked pixel within the aperture)",
        CosmicRay => "cosmic_ray",
        Saturated => "saturated",
        Truncated => "truncated",
        Nonlinear => "nonlinear",
        NoParallacticAngle => "no_parallactic_angle",
        PrimaryNotFound => "primary_not_found",
        PhotometryFailed => "photometry failed",
        CompanionOverlap => "companion_overlap",
        AnnulusContaminated => "annulus_contaminated",
        UsedFlaggedDithers => "used_flagged_dithers",
        AbIdentityUnverified => "ab_identity_unverified: B's position from A not measured at any orientation",
        DitherClipped => "dither_clipped",
        ExcessDitherScatter => "excess_dither_scatter",
        PAboveOne => "p_above_one",
        LowSnr => "low_snr",
        UndefinedPolarization => "undefined_polarization: orientations do not constrain q and u",
        OutsideField => "outside_field: 3 of 10 dithers",
        StripEdge => "strip_edge: 5 of 10 dithers",
        Blended => "blended: A at 2.1\", field star at 1.8\"",
        Faint => "faint: flux S/N 7.3",
        CompanionNotFound => "companion_not_found",
        CompanionRejected => "companion_rejected: significant at 1 of 4 orientations",
        CompanionPositionScatter => "companion_position_scatter: 0.73 px between orientations",
        CompanionCandidates => {
            "companion_candidates: another source at 4.91\" PA 104.0 deg from A, 1.29 times B's flux within the 6.0\" search radius: B at 1.79\" PA 189.0 deg is the less likely chance alignment"
        }
        AbIdentityFromFlux => {
            "ab_identity_from_flux: at POSANG 45.0 the star found is B (companion not found there); A placed by the geometry"
        }
        AbIdentityFromGeometry => "ab_identity_from_geometry: at POSANG 90.0 the star found is B",
        AbNearEqualFlux => "ab_near_equal_flux: B/A = 0.990 +- 0.020 in o+e flux over 16 dithers, within 3 sigma of 1",
        AbRelabelledByFlux => "ab_relabelled_by_flux: B/A = 1.300 +- 0.020 in o+e flux over 16 dithers: A is the brighter",
        EoOffsetDiffersFromProfile => "eo_offset_differs_from_profile: (0.12, 340.50) px",
        BrighterSourceInStrip => {
            "brighter_source_in_strip: 127.0\" at PA 90.0 deg from the target (441 px at POSANG 0), its peak 8.3 times the target's"
        }
        PrimaryNotFoundIn => "primary not found in /data/raw/SOFI.2026-11-26T01:00:00.fits",
        ForegroundTooFewFieldStars => "foreground_too_few_field_stars: 4 usable field star(s) after 2 rejection(s), need 5",
        MixedExposure => "mixed_exposure: DIT [10.0, 20.0] s, NDIT [1] within the sequence: normalised",
        DitherDropped => "dither of POSANG 45 dropped: sky: a.fits: no background",
        OrientationDropped => "orientation POSANG 90 dropped: 1 readable dither(s), need 2 for the sky",
        NoFlat => "no flat for POSANG 45 filter Ks: not flat-fielded",
        FlatDoesNotFit => "POSANG 45 not flat-fielded: flat is 1024 x 1024 px, the frame 1024 x 512",
        NightMaskUnfit => {
            "night bad-pixel mask is 512 x 512 px, the frames 1024 px wide: not used, defects detected on this sequence"
        }
        BadPixelDetectionFailed => "bad-pixel detection failed: too few frames",
        ParallacticAngleNotUsed => "parallactic angle not used: a.fits: no HIERARCH ESO TEL PARANG START",
        IntermediateDirNotCreated => "could not create /out/inter: permission denied",
        IntermediateNotWritten => "could not write intermediate /out/inter/a_skysub.fits: disk full",
        FitsProductNotWritten => "fits_product_not_written: /out/pa45_e.fits: disk full",
        StationaryDithers => {
            "all dithers at POSANG 45 deg at one position (SEQ CUMOFFSET equal): the sky median contains the star"
        }
        OneDither => "only 1 dither at POSANG 45 deg: cannot sky-subtract from the data itself",
        UnequalDithers => "unequal dithers per orientation: [4, 4, 3, 4]",
        MissingExposures => "15 of 16 exposures of the template present (TPL NEXP)",
        MjdSpread => "MJD-OBS of the frames spans 3.0 days (61000 to 61003): some frames' dates are wrong",
        MixedFilters => "mixed filters {\"H\", \"Ks\"}",
        NotInStandardsTable => "not_in_standards_table",
        NoTableValuesForFilter => "no_table_values_for_filter: Ks",
        Failed => "failed: no star found",
        PDisagreesWithTable => "p_disagrees_with_table: 4.2 sigma",
        QuDisagreesWithTable => "qu_disagrees_with_table: chi2 = 14.1 (2 dof)",
        Unknown => "a_flag_from_the_future: x",
    }
}

#[test]
fn every_code_has_a_sentence_a_unique_name_and_reads_back_as_itself() {
    let mut names = std::collections::BTreeSet::new();
    for &code in FlagCode::ALL {
        let why = code.explanation();
        assert!(!why.is_empty() && why.ends_with('.'), "{code:?}: {why}");
        assert!(names.insert(code.name()), "{code:?}: name {} twice", code.name());
        // The name alone is the flag, except where it is too common to tell (`POSANG`).
        if !matches!(code.form(), LeadingWith(_)) {
            assert_eq!(Flag::parse(code.name()).code, code, "{code:?}");
        }
        assert_eq!(Flag::new(code).to_string(), code.name());
        let text = example(code);
        let flag = Flag::parse(text);
        assert_eq!(flag.code, code, "{text}");
        assert_eq!(flag.to_string(), text);
    }
    assert!(!FlagCode::ALL.contains(&FlagCode::Unknown));
    assert_eq!(Flag::parse(example(FlagCode::Unknown)).code, FlagCode::Unknown);
}

#[test]
fn any_string_reads_and_writes_back_unchanged() {
    let odd = [
        "",
        "failed",
        "failed:",
        "failed: ",
        "failed:x",
        "low_snr ",
        " low_snr",
        "POSANG 45 dropped",
        "only the primary",
        "exposures of the template present (TPL NEXP)",
        "sky too bright",
        "mystery_flag: x",
        "stokes_method_failed: x; fell back to y",
        "ab_identity",
        "ünïcödé: ✓",
    ];
    let examples = FlagCode::ALL.iter().map(|&c| example(c));
    for text in odd.into_iter().chain(examples) {
        let flag: Flag = text.parse().unwrap();
        assert_eq!(flag.to_string(), text, "{flag:?}");
        let json = serde_json::to_string(&flag).unwrap();
        assert_eq!(json, serde_json::to_string(text).unwrap());
        assert_eq!(serde_json::from_str::<Flag>(&json).unwrap(), flag);
    }
    assert_eq!(Flag::parse("POSANG 45 dropped").code, FlagCode::Unknown);
    assert_eq!(Flag::parse("only the primary").code, FlagCode::Unknown);
    assert_eq!(Flag::parse("failed:x").code, FlagCode::Unknown);
}

#[test]
fn flags_read_as_sentences_with_a_named_flags_detail() {
    assert_eq!(
        Flag::new(FlagCode::CompanionNotFound).explain().as_deref(),
        Some("The companion was not found: only the primary was measured.")
    );
    let p = Flag::parse("p_disagrees_with_table: 4.2 sigma");
    assert_eq!(
        (p.label().as_str(), p.detail.as_deref()),
        ("p_disagrees_with_table", Some("4.2 sigma"))
    );
    let s = p.explain().unwrap();
    assert!(
        s.starts_with("The measured P disagrees") && s.ends_with("(4.2 sigma)"),
        "{s}"
    );
    let sentence = Flag::parse(example(FlagCode::NoFlat));
    assert_eq!(sentence.label(), example(FlagCode::NoFlat));
    assert_eq!(sentence.explain().as_deref(), Some(FlagCode::NoFlat.explanation()));
    assert_eq!(Flag::parse("some_future_flag").explain(), None);
    assert_eq!(Flag::parse("some_future_flag").label(), "some_future_flag");
}

/// docs/catalog-schema.md lists every flag once under "Flags", and nothing else there.
#[test]
fn the_schema_lists_every_flag_and_no_other() {
    let doc = include_str!("../../../../docs/catalog-schema.md");
    let section = doc.split("\n## Flags\n").nth(1).expect("a Flags section");
    let section = section.split("\n## ").next().unwrap();
    let listed: Vec<FlagCode> = section
        .lines()
        .filter_map(|l| l.strip_prefix("| `"))
        .map(|l| Flag::parse(l.split('`').next().unwrap()).code)
        .collect();
    assert!(!listed.contains(&FlagCode::Unknown), "{listed:?}");
    for &code in FlagCode::ALL {
        assert_eq!(listed.iter().filter(|&&c| c == code).count(), 1, "{code:?}");
    }
    assert_eq!(listed.len(), FlagCode::ALL.len());
}
