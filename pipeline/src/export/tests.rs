//! The table of a catalog with targets and standards: one row per target component and
//! per measured standard, with the pointing, time, geometry and provenance of each.
use super::*;
use crate::catalog::{Flag, StandardResult, Target};
use crate::stokes::inversion::{Debias, LinearPolarization};

fn component(name: &str, q: f64, u: f64) -> Component {
    let lp = LinearPolarization::from_qu(q, u, 0.002, 0.003, Debias::WardleKronberg);
    Component {
        passes_cut: true,
        flags: vec![Flag::parse(&format!("flag_{name}"))],
        ..Component::new(name, lp.pol)
    }
}

fn standard(name: &str, measured: Option<Component>) -> StandardResult {
    StandardResult {
        name: name.into(),
        object: format!("{name} obj"),
        sequence: format!("{name} obj@1999-03-03T05:00:00"),
        filter: "Ks".into(),
        status: if measured.is_some() { Status::Ok } else { Status::Failed },
        table: None,
        measured,
        residual_p_sigma: None,
        residual_gamma_deg: None,
        residual_gamma_sigma: None,
        residual_qu_chi2: None,
        used_for: vec!["offset".into()],
        flags: vec![Flag::parse(&format!("std_flag_{name}"))],
        ra_deg: Some(101.5),
        dec_deg: Some(-33.25),
        dit_s: Some(2.0),
        mjd_mean: Some(51240.21),
        input_files: None,
        frame_quality: None,
    }
}

/// A merged catalog (software only in its inputs' provenance) of one binary and two
/// standards, one of them not measured.
fn catalog() -> Catalog {
    let target = Target {
        components: vec![component("A", 0.03, -0.01), component("B", -0.02, 0.04)],
        ra_deg: Some(67.625),
        dec_deg: Some(18.125),
        mjd_mean: Some(51240.0625),
        separation_arcsec: Some(4.0),
        pa_deg: Some(30.0),
        filter: Some("Ks".into()),
        sequence: Some("Alpha@1999-03-03T01:00:00".into()),
        delta_gamma_deg: Some(48.0),
        foreground: Some(crate::catalog::Foreground::new(0.004, -0.002, 0.0005, 0.0007, 0.0)),
        delta_gamma_fg_corrected_deg: Some(51.5),
        sigma_delta_gamma_fg_corrected_deg: Some(1.25),
        ..Target::new("Alpha", Status::Ok)
    };
    Catalog {
        schema_version: "1.0".into(),
        targets: vec![target, Target::new("Lost", Status::Failed)],
        standards: vec![
            standard("HD 64299", Some(component("A", 0.0005, -0.0002))),
            standard("HD 98161", None),
        ],
        provenance: serde_json::from_value(serde_json::json!({"merged_from": [
            {"file": "s1.json", "provenance": {"software": "sofipol 9.9.9", "commit": "abc"}},
            {"file": "s2.json", "provenance": {"software": "sofipol 9.9.9", "commit": "abc"}},
        ]}))
        .unwrap(),
        ..Default::default()
    }
}

fn column<'a>(t: &'a Table, name: &str) -> &'a Column {
    t.columns
        .iter()
        .find(|c| c.name == name)
        .unwrap_or_else(|| panic!("no column {name}"))
}

fn strs<'a>(t: &'a Table, name: &str) -> &'a [String] {
    match &column(t, name).data {
        Data::Str(v) => v,
        d => panic!("{name}: {d:?}"),
    }
}

fn nums<'a>(t: &'a Table, name: &str) -> &'a [f64] {
    match &column(t, name).data {
        Data::F64(v) => v,
        d => panic!("{name}: {d:?}"),
    }
}

#[test]
fn standards_are_rows_of_kind_standard_with_pointing_time_and_units() {
    let cat = catalog();
    let t = table(&cat, "m.json");
    assert_eq!(t.rows(), 3, "two components and one measured standard");
    assert_eq!((t.targets_without_components, t.standards_without_measurement), (1, 1));
    assert_eq!(strs(&t, "kind"), ["target", "target", "standard"]);
    assert_eq!(strs(&t, "target"), ["Alpha", "Alpha", "HD 64299"]);
    assert_eq!(strs(&t, "component"), ["A", "B", ""]);
    assert_eq!(
        strs(&t, "sequence"),
        [
            "Alpha@1999-03-03T01:00:00",
            "Alpha@1999-03-03T01:00:00",
            "HD 64299 obj@1999-03-03T05:00:00"
        ]
    );
    assert_eq!(strs(&t, "filter"), ["Ks", "Ks", "Ks"]);
    assert_eq!(strs(&t, "status"), ["ok", "ok", "ok"]);
    assert_eq!(strs(&t, "flags"), ["flag_A", "flag_B", "flag_A"]);
    assert_eq!(strs(&t, "target_flags"), ["", "", "std_flag_HD 64299"]);
    // The values are the catalog's, row by row.
    let std = cat.standards[0].measured.as_ref().unwrap();
    let comps = [&cat.targets[0].components[0], &cat.targets[0].components[1], std];
    for (i, c) in comps.iter().enumerate() {
        assert_eq!(nums(&t, "q")[i], c.q);
        assert_eq!(nums(&t, "u")[i], c.u);
        assert_eq!(nums(&t, "gamma")[i], c.gamma_deg);
        assert_eq!(nums(&t, "p_debiased")[i], c.p_debiased);
    }
    // A and the standard at their pointings; B where the separation and PA put it (see
    // `b_lies_at_the_measured_separation_and_position_angle_from_a`).
    let (ra, dec) = (nums(&t, "ra"), nums(&t, "dec"));
    assert_eq!((ra[0], dec[0], ra[2], dec[2]), (67.625, 18.125, 101.5, -33.25));
    assert!(ra[1] != ra[0] && dec[1] != dec[0], "B has its own position");
    assert_eq!(nums(&t, "mjd"), [51240.0625, 51240.0625, 51240.21]);
    let (sep, pa, dg) = (nums(&t, "separation"), nums(&t, "pa"), nums(&t, "delta_gamma"));
    assert_eq!((sep[0], sep[1], pa[0], pa[1], dg[0]), (4.0, 4.0, 30.0, 30.0, 48.0));
    assert!(
        sep[2].is_nan() && pa[2].is_nan() && dg[2].is_nan(),
        "a standard has no pair"
    );
    // The foreground and the Delta-gamma after subtracting it, on both of the target's rows.
    for (col, want) in [
        ("fg_q", 0.004),
        ("fg_u", -0.002),
        ("sigma_fg_q", 0.0005),
        ("sigma_fg_u", 0.0007),
        ("delta_gamma_fg_corrected", 51.5),
        ("sigma_delta_gamma_fg_corrected", 1.25),
    ] {
        let v = nums(&t, col);
        assert_eq!((v[0], v[1]), (want, want), "{col}");
        assert!(v[2].is_nan(), "{col}: a standard has no foreground");
    }
    for (name, unit) in [
        ("ra", "deg"),
        ("dec", "deg"),
        ("mjd", "d"),
        ("separation", "arcsec"),
        ("pa", "deg"),
        ("gamma", "deg"),
        ("q", ""),
    ] {
        assert_eq!(column(&t, name).unit, unit, "{name}");
    }
    // The software of a merged catalog is its inputs'.
    assert_eq!(strs(&t, "software"), ["sofipol 9.9.9"; 3]);
    assert!(t.meta.contains(&("software", "sofipol 9.9.9".into())), "{:?}", t.meta);
    assert!(t.meta.contains(&("commit", "abc".into())), "{:?}", t.meta);
    let ecsv = to_ecsv(&t);
    assert!(ecsv.contains("# - {name: mjd, unit: d, datatype: float64,"), "{ecsv}");
    assert!(
        ecsv.contains("# - {name: separation, unit: arcsec, datatype: float64,"),
        "{ecsv}"
    );
}

/// Inputs of different software versions: every version, not one of them nor `unknown`.
#[test]
fn a_merge_of_different_versions_exports_every_version() {
    let mut cat = catalog();
    let merged = cat.provenance.merged_from.as_mut().unwrap();
    merged[1].provenance.software = Some(crate::catalog::provenance::OneOrMany::One("sofipol 9.9.10".into()));
    let t = table(&cat, "m.json");
    assert_eq!(strs(&t, "software")[0], "sofipol 9.9.9; sofipol 9.9.10");
    cat.provenance =
        serde_json::from_value(serde_json::json!({"software": ["sofipol 1", "sofipol 2"], "merged_from": []})).unwrap();
    assert_eq!(strs(&table(&cat, "m.json"), "software")[0], "sofipol 1; sofipol 2");
    cat.provenance = Default::default();
    assert_eq!(strs(&table(&cat, "m.json"), "software")[0], "unknown");
}

/// Separation (arcsec) and position angle (deg, east of north, [0, 360)) of (ra1, dec1) from
/// (ra0, dec0) by the haversine and the initial bearing: the inverse of `offset_position`,
/// written independently of it.
fn separation_and_pa(ra0: f64, dec0: f64, ra1: f64, dec1: f64) -> (f64, f64) {
    let (a0, d0, a1, d1) = (ra0.to_radians(), dec0.to_radians(), ra1.to_radians(), dec1.to_radians());
    let h = ((d1 - d0) / 2.0).sin().powi(2) + d0.cos() * d1.cos() * ((a1 - a0) / 2.0).sin().powi(2);
    let sep = 2.0 * h.sqrt().asin();
    let pa = ((a1 - a0).sin() * d1.cos()).atan2(d0.cos() * d1.sin() - d0.sin() * d1.cos() * (a1 - a0).cos());
    (sep.to_degrees() * 3600.0, pa.to_degrees().rem_euclid(360.0))
}

/// The exported B lies at the catalog's separation and position angle from A (the cross-match
/// with 2MASS or Gaia needs each star's own position); checked against the haversine and the
/// bearing, also across RA 0, near the pole and for wide and close pairs.
#[test]
fn b_lies_at_the_measured_separation_and_position_angle_from_a() {
    let t = table(&catalog(), "cat.json");
    let (ra, dec) = (nums(&t, "ra"), nums(&t, "dec"));
    let (sep, pa) = separation_and_pa(ra[0], dec[0], ra[1], dec[1]);
    assert!((sep - 4.0).abs() < 1e-7, "{sep}");
    assert!((pa - 30.0).abs() < 1e-6, "{pa}");
    for (ra0, dec0, s, p) in [
        (0.0001, 10.0, 5.3, 250.0),
        (359.9999, -45.0, 0.5, 95.0),
        (120.0, 89.99, 3.0, 180.0),
        (200.0, -89.5, 40.0, 10.0),
        (67.6, 18.1, 1.0, 0.0),
    ] {
        let (ra1, dec1) = offset_position(ra0, dec0, s, p);
        assert!((0.0..360.0).contains(&ra1), "{ra1}");
        let (s1, p1) = separation_and_pa(ra0, dec0, ra1, dec1);
        assert!(
            (s1 - s).abs() < 1e-6 * s.max(1.0),
            "{ra0} {dec0}: separation {s1} for {s}"
        );
        let dp = (p1 - p + 180.0).rem_euclid(360.0) - 180.0;
        assert!(dp.abs() < 1e-5, "{ra0} {dec0}: PA {p1} for {p}");
    }
    // Flat-sky check at small separation: dDec = s cos PA, dRA cos Dec = s sin PA.
    let (ra1, dec1) = offset_position(67.625, 18.125, 4.0, 30.0);
    let ddec = (dec1 - 18.125) * 3600.0;
    let dra = (ra1 - 67.625) * 3600.0 * 18.125f64.to_radians().cos();
    assert!((ddec - 4.0 * 30f64.to_radians().cos()).abs() < 1e-4, "{ddec}");
    assert!((dra - 4.0 * 30f64.to_radians().sin()).abs() < 1e-4, "{dra}");
}
