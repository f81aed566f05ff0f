use super::*;

#[test]
fn catalog_floats_round_trip_bit_exactly() {
    // Regression: serde_json's default float parser is not exact; `merge` and `stats`
    // re-read catalogs, so a merged catalog differed from a single run in the last digit.
    let values: [f64; 5] = [
        0.037803643548976563,
        0.00044009000027138596,
        -9.993711226758646e-24,
        150.23621383361115,
        1.0 / 3.0,
    ];
    for v in values {
        let text = serde_json::to_string(&v).unwrap();
        let back: f64 = serde_json::from_str(&text).unwrap();
        assert_eq!(back.to_bits(), v.to_bits(), "{v:e} -> {text} -> {back:e}");
    }
}

/// The keys of the objects at nesting `depth` (1: the top-level object's own keys), in
/// the order the text has them.
fn keys_at(text: &str, depth: usize) -> Vec<String> {
    let (mut keys, mut level, mut in_str, mut esc, mut cur) = (Vec::new(), 0usize, false, false, String::new());
    let mut chars = text.chars().peekable();
    while let Some(ch) = chars.next() {
        if in_str {
            match (esc, ch) {
                (true, _) => esc = false,
                (false, '\\') => esc = true,
                (false, '"') => {
                    in_str = false;
                    while chars.peek().is_some_and(|c| c.is_whitespace()) {
                        chars.next();
                    }
                    if level == depth && chars.peek() == Some(&':') {
                        keys.push(std::mem::take(&mut cur));
                    }
                    cur.clear();
                    continue;
                }
                _ => {}
            }
            cur.push(ch);
            continue;
        }
        match ch {
            '"' => in_str = true,
            '{' | '[' => level += 1,
            '}' | ']' => level -= 1,
            _ => {}
        }
    }
    keys
}

fn combined_f(analyzer_deg: f64) -> CombinedF {
    CombinedF {
        analyzer_deg,
        chi2: 2.5,
        f: 0.031,
        n_dithers: 4,
        n_dithers_total: 5,
        parallactic_2eta: None,
        parallactic_deg: None,
        posang_deg: None,
        sigma_f: 4e-4,
        sigma_f_propagated: 3e-4,
        sigma_f_scatter: 5e-4,
    }
}

/// A component with every typed field set (and one key this build does not know).
fn full_component() -> Component {
    use crate::stokes::inversion::{Debias, LinearPolarization};
    let lp = LinearPolarization::from_qu(0.03, -0.04, 0.004, 0.005, Debias::WardleKronberg);
    let mut extra = serde_json::Map::new();
    extra.insert("a_key_from_elsewhere".into(), serde_json::json!({"x": 1}));
    Component {
        passes_cut: true,
        flags: vec![Flag::new(FlagCode::LowSnr)],
        cov_qu: Some(-4.25e-6),
        cov_qu_stat: Some(-3.5e-6),
        dropped_dithers: Some(vec![DroppedDither {
            file: "raw/SOFI_0003.fits".into(),
            reason: "bad_pixels".into(),
        }]),
        flux_adu: Some(142096.5),
        instrumental_offset: Some(InstrumentalOffset {
            c: 0.0183,
            sigma_c: 2.2e-4,
            source: "calibration".into(),
        }),
        offset_gradient: Some([-1.0, 0.0]),
        orientations: Some(vec![combined_f(0.0), combined_f(45.0)]),
        sigma_gamma_nkc_deg: Some(0.198),
        sigma_gamma_stat_deg: Some(0.191),
        sigma_gamma_zero_point_deg: Some(2.24),
        sigma_q_stat: Some(0.0039),
        sigma_u_stat: Some(0.0048),
        snr: Some(lp.snr),
        stokes_method: Some("least_squares".into()),
        extra,
        ..Component::new("A", lp.pol)
    }
}

#[test]
fn component_keys_keep_the_documented_order_and_round_trip() {
    let c = full_component();
    let text = serde_json::to_string(&c).unwrap();
    let want = [
        "name",
        "q",
        "u",
        "sigma_q",
        "sigma_u",
        "p",
        "sigma_p",
        "p_debiased",
        "gamma_deg",
        "sigma_gamma_deg",
        "passes_cut",
        "flags",
        // The optional fields, alphabetical (as when they were a sorted map).
        "cov_qu",
        "cov_qu_stat",
        "dropped_dithers",
        "flux_adu",
        "instrumental_offset",
        "offset_gradient",
        "orientations",
        "sigma_gamma_nkc_deg",
        "sigma_gamma_stat_deg",
        "sigma_gamma_zero_point_deg",
        "sigma_q_stat",
        "sigma_u_stat",
        "snr",
        "stokes_method",
        // Unknown keys last.
        "a_key_from_elsewhere",
    ];
    assert_eq!(keys_at(&text, 1), want, "{text}");
    // An orientation entry: alphabetical, as the JSON map it replaced; posang_deg only
    // when present.
    let o = serde_json::to_string(&combined_f(0.0)).unwrap();
    let want_o = [
        "analyzer_deg",
        "chi2",
        "f",
        "n_dithers",
        "n_dithers_total",
        "sigma_f",
        "sigma_f_propagated",
        "sigma_f_scatter",
    ];
    assert_eq!(keys_at(&o, 1), want_o, "{o}");
    let o = serde_json::to_string(&CombinedF {
        posang_deg: Some(45.0),
        ..combined_f(0.0)
    })
    .unwrap();
    assert_eq!(keys_at(&o, 1)[5], "posang_deg", "{o}");
    assert_eq!(
        keys_at(&serde_json::to_string(&c.instrumental_offset).unwrap(), 1),
        ["c", "sigma_c", "source"]
    );
    let back: Component = serde_json::from_str(&text).unwrap();
    assert_eq!(back, c);
    assert_eq!(serde_json::to_string(&back).unwrap(), text);
    assert_eq!(
        back.extra.len(),
        1,
        "only the unknown key goes to extra: {:?}",
        back.extra
    );
    // Without the optional fields, none of their keys is written.
    let bare = Component::new("B", c.pol);
    let text = serde_json::to_string(&bare).unwrap();
    assert_eq!(keys_at(&text, 1), want[..12], "{text}");
    // LinearPolarization itself serializes as before: the shared fields, then the S/N measures.
    use crate::stokes::inversion::{Debias, LinearPolarization};
    let lp = LinearPolarization::from_qu(0.03, -0.04, 0.004, 0.005, Debias::WardleKronberg);
    let lp_text = serde_json::to_string(&lp).unwrap();
    assert!(
        lp_text.starts_with("{\"q\":") && lp_text.ends_with(&format!("\"snr\":{}}}", lp.snr)),
        "{lp_text}"
    );
}

/// A target with every typed field set (and one key this build does not know).
fn full_target() -> Target {
    let mut extra = serde_json::Map::new();
    extra.insert("a_key_from_elsewhere".into(), serde_json::json!("kept"));
    Target {
        error: Some("k of n exposures".into()),
        components: vec![full_component()],
        delta_gamma_deg: Some(12.5),
        sigma_delta_gamma_deg: Some(0.8),
        delta_gamma_interval_deg: Some([11.7, 13.3]),
        aperture_radius_px: Some(2.9),
        bad_pixels_masked: Some(316),
        eo_offset_px: Some([-0.002, 167.0]),
        filter: Some("Ks".into()),
        flags: Some(vec![Flag::with_detail(FlagCode::CompanionPositionScatter, "0.4 px")]),
        flat: Some(Some(vec!["POSANG 0: dome POSANG 0 filter Ks, 6 frames".into()])),
        foreground: Some(crate::catalog::Foreground {
            q: 0.004,
            u: -0.001,
            sigma_q: 0.0005,
            sigma_u: 0.0006,
            cov_qu: 1e-8,
            source: Some("field stars, n = 9".into()),
            n_used: Some(9),
            tau: Some([0.0003, 0.0]),
            method: Some("field stars".into()),
            rejected: vec![crate::catalog::RejectedFieldStar {
                id: "f3".into(),
                reason: "outlier".into(),
            }],
        }),
        delta_gamma_fg_corrected_deg: Some(40.1),
        delta_gamma_fg_corrected_interval_deg: Some([38.0, 42.2]),
        sigma_delta_gamma_fg_corrected_deg: Some(2.1),
        fwhm_px: Some(2.89),
        input_files: Some(vec!["raw/a.fits".into(), "raw/b.fits".into()]),
        orientations_deg: Some(vec![0.0, 45.0]),
        pa_deg: Some(119.99),
        photometry: Some("aperture".into()),
        separation_arcsec: Some(4.6),
        sequence: Some("Demo Easy@1999-03-03T01:10:00".into()),
        tpl_start: Some("1999-03-03T01:10:00".into()),
        extra,
        ..Target::new("Demo Easy", Status::Partial)
    }
}

#[test]
fn target_keys_keep_the_documented_order_and_round_trip() {
    let t = full_target();
    let text = serde_json::to_string(&t).unwrap();
    let want = [
        "object",
        "status",
        "error",
        "components",
        "delta_gamma_deg",
        // Its error and interval, when there is a Delta-gamma.
        "sigma_delta_gamma_deg",
        "delta_gamma_interval_deg",
        // The optional fields, alphabetical (as when they were a sorted map).
        "aperture_radius_px",
        "bad_pixels_masked",
        "delta_gamma_fg_corrected_deg",
        "delta_gamma_fg_corrected_interval_deg",
        "eo_offset_px",
        "filter",
        "flags",
        "flat",
        "foreground",
        "fwhm_px",
        "input_files",
        "orientations_deg",
        "pa_deg",
        "photometry",
        "separation_arcsec",
        "sequence",
        "sigma_delta_gamma_fg_corrected_deg",
        "tpl_start",
        // Unknown keys last.
        "a_key_from_elsewhere",
    ];
    assert_eq!(keys_at(&text, 1), want, "{text}");
    let back: Target = serde_json::from_str(&text).unwrap();
    assert_eq!(back, t);
    assert_eq!(serde_json::to_string(&back).unwrap(), text);
    assert_eq!(
        back.extra.len(),
        1,
        "only the unknown key goes to extra: {:?}",
        back.extra
    );
    assert_eq!(back.sequence_id(), "Demo Easy@1999-03-03T01:10:00");
    // No flat applied: a present null, read back as such.
    let t = Target {
        flat: Some(None),
        ..full_target()
    };
    let text = serde_json::to_string(&t).unwrap();
    assert!(text.contains(r#""flat":null,"#), "{text}");
    let back: Target = serde_json::from_str(&text).unwrap();
    assert_eq!(back.flat, Some(None));
    assert_eq!(serde_json::to_string(&back).unwrap(), text);
    // A failed target as the reduction writes it: no component, three optional keys.
    let failed = Target {
        error: Some("no readable frame".into()),
        sequence: Some("X@t".into()),
        input_files: Some(vec![]),
        flags: Some(vec![]),
        ..Target::new("X", Status::Failed)
    };
    let text = serde_json::to_string(&failed).unwrap();
    assert_eq!(
        text,
        r#"{"object":"X","status":"failed","error":"no readable frame","components":[],"delta_gamma_deg":null,"flags":[],"input_files":[],"sequence":"X@t"}"#
    );
    assert_eq!(serde_json::from_str::<Target>(&text).unwrap(), failed);
}

#[test]
fn non_finite_numbers_are_written_null_and_read_back_present() {
    // serde_json writes NaN as null; a typed f64 must read it back, and the key must
    // stay (a catalog read and written again is unchanged).
    let mut t = full_target();
    t.pa_deg = Some(f64::NAN);
    t.eo_offset_px = Some([f64::NAN, 167.0]);
    t.orientations_deg = Some(vec![0.0, f64::NAN]);
    let c = &mut t.components[0];
    c.flux_adu = Some(f64::NAN);
    c.snr = Some(f64::INFINITY);
    c.orientations.as_mut().unwrap()[0].sigma_f_scatter = f64::NAN;
    let text = serde_json::to_string(&t).unwrap();
    for k in [
        r#""pa_deg":null"#,
        r#""eo_offset_px":[null,167.0]"#,
        r#""orientations_deg":[0.0,null]"#,
        r#""flux_adu":null"#,
        r#""snr":null"#,
        r#""sigma_f_scatter":null"#,
    ] {
        assert!(text.contains(k), "{k} not in {text}");
    }
    let back: Target = serde_json::from_str(&text).unwrap();
    assert!(back.pa_deg.is_some_and(f64::is_nan));
    assert!(back.components[0].flux_adu.is_some_and(f64::is_nan));
    assert!(back.components[0].orientations.as_ref().unwrap()[0]
        .sigma_f_scatter
        .is_nan());
    assert_eq!(serde_json::to_string(&back).unwrap(), text);
}

#[test]
fn catalog_without_the_optional_fields_reads_and_writes_back_unchanged() {
    // An older or foreign catalog (testdata/stats: the fixed fields only): the optional
    // fields stay absent, nothing is added on writing.
    let text = include_str!("../../../testdata/stats/catalog_aligned.json");
    let cat: Catalog = serde_json::from_str(text).unwrap();
    assert!(cat
        .targets
        .iter()
        .all(|t| t.sequence.is_none() && t.flags.is_none() && t.extra.is_empty()));
    assert!(cat
        .targets
        .iter()
        .flat_map(|t| &t.components)
        .all(|c| c.orientations.is_none()));
    // The keys of each target and component beyond the fixed ones (which have defaults
    // of their own), as read and as written.
    let optional_keys = |v: &serde_json::Value| -> Vec<Vec<String>> {
        let fixed = ["object", "status", "error", "components", "delta_gamma_deg"];
        let keys = |o: &serde_json::Value, skip: &[&str]| -> Vec<String> {
            let o = o.as_object().unwrap();
            o.keys().filter(|k| !skip.contains(&k.as_str())).cloned().collect()
        };
        let mut out = Vec::new();
        for t in v["targets"].as_array().unwrap() {
            out.push(keys(t, &fixed));
            for c in t["components"].as_array().into_iter().flatten() {
                out.push(keys(c, &[]));
            }
        }
        out
    };
    let read: serde_json::Value = serde_json::from_str(text).unwrap();
    let written = serde_json::to_value(&cat).unwrap();
    assert_eq!(optional_keys(&written), optional_keys(&read));
    assert_eq!(written["targets"][0]["components"], read["targets"][0]["components"]);
    // Unknown keys are kept (after the known ones).
    let t: Target = serde_json::from_str(r#"{"object":"X","status":"ok","zeta":[1],"alpha":2}"#).unwrap();
    assert_eq!(t.extra.len(), 2);
    assert_eq!(
        serde_json::to_string(&t).unwrap(),
        r#"{"object":"X","status":"ok","components":[],"delta_gamma_deg":null,"alpha":2,"zeta":[1]}"#
    );
}

#[test]
fn a_target_written_by_the_previous_build_round_trips_byte_identically() {
    // testdata/catalog/demo_target.json: a target of `sofipol demo`'s catalog as the build
    // before the fields were typed wrote it (every key then in the untyped map).
    let text = include_str!("../../../testdata/catalog/demo_target.json");
    let t: Target = serde_json::from_str(text).unwrap();
    assert!(t.extra.is_empty(), "every key is typed: {:?}", t.extra);
    assert_eq!(t.sequence.as_deref(), Some("Demo Easy@1999-03-03T01:10:00"));
    assert_eq!(t.filter.as_deref(), Some("Ks"));
    assert_eq!(t.photometry.as_deref(), Some("aperture"));
    assert_eq!(t.input_files.as_ref().map(Vec::len), Some(10));
    assert_eq!(t.orientations_deg, Some(vec![0.0, 45.0]));
    assert_eq!(t.bad_pixels_masked, Some(316));
    assert!(t.pa_deg.is_some() && t.separation_arcsec.is_some() && t.fwhm_px.is_some());
    assert!(t
        .flat
        .as_ref()
        .is_some_and(|f| f.as_ref().is_some_and(|f| f.len() == 2)));
    for c in &t.components {
        assert!(c.extra.is_empty(), "every key is typed: {:?}", c.extra);
        let o = c.orientations.as_ref().unwrap();
        assert_eq!(o.len(), 2);
        assert!(o.iter().all(|o| o.f.is_finite() && o.sigma_f > 0.0 && o.n_dithers > 0));
        assert!(c.snr.is_some() && c.cov_qu.is_some() && c.flux_adu.is_some());
        assert!(c.sigma_gamma_nkc_deg.is_some() && c.sigma_gamma_zero_point_deg.is_some());
        assert_eq!(c.stokes_method.as_deref(), Some("least_squares"));
        assert_eq!(c.instrumental_offset.as_ref().unwrap().source, "calibration");
    }
    assert_eq!(serde_json::to_string_pretty(&t).unwrap(), text);
}

#[test]
fn fold_is_axial_and_symmetric() {
    assert_eq!(fold_delta_gamma(10.0, 170.0), 20.0);
    assert_eq!(fold_delta_gamma(170.0, 10.0), 20.0);
    assert_eq!(fold_delta_gamma(0.0, 90.0), 90.0);
    assert_eq!(fold_delta_gamma(45.0, 45.0), 0.0);
    assert!((fold_delta_gamma(179.9, 0.1) - 0.2).abs() < 1e-9);
}
