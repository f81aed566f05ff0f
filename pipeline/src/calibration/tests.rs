use super::*;
use crate::catalog::CombinedF;
use crate::stokes::calibration::{AngleCalibration, Offset, StokesMethod};
use crate::stokes::model::{normalized_difference, Polarization};
use crate::stokes::propagation::CAL_C;

fn component(name: &str, pol: Polarization, posangs: &[f64], theta0: f64, c: f64, sigma: f64) -> Component {
    let orients: Vec<CombinedF> = posangs
        .iter()
        .map(|&pa| CombinedF {
            posang_deg: Some(pa),
            analyzer_deg: pa,
            f: normalized_difference(pol, pa + theta0) + c,
            sigma_f: sigma,
            chi2: f64::NAN,
            n_dithers: 0,
            n_dithers_total: 0,
            parallactic_2eta: None,
            parallactic_deg: None,
            sigma_f_propagated: f64::NAN,
            sigma_f_scatter: f64::NAN,
        })
        .collect();
    Component {
        orientations: Some(orients),
        ..Component::new(name, crate::stokes::inversion::Polarization::UNDEFINED)
    }
}

fn target(object: &str, comps: Vec<Component>) -> Target {
    Target {
        components: comps,
        filter: Some("Ks".into()),
        sequence: Some(format!("{object}@t")),
        ..Target::new(object, Status::Ok)
    }
}

#[test]
fn night_calibration_recovers_truth_and_flags_uncalibrated_without_it() {
    let pa = [0.0, 45.0];
    let (theta0, c) = (3.0, 0.0152);
    let table = StandardsTable::builtin();
    let hd = table.find("HD 204827", "Ks").unwrap().clone();
    let stds = vec![
        target(
            "HD 64299",
            vec![component("A", Polarization::default(), &pa, theta0, c, 3e-4)],
        ),
        target(
            "HD_98161",
            vec![component("A", Polarization::default(), &pa, theta0, c, 3e-4)],
        ),
        target(
            "HD 204827",
            vec![component(
                "A",
                Polarization::from_p_gamma(hd.p, hd.gamma_deg),
                &pa,
                theta0,
                c,
                3e-4,
            )],
        ),
        target(
            "Mystery",
            vec![component("A", Polarization::default(), &pa, theta0, c, 3e-4)],
        ),
    ];
    let truth_a = Polarization::from_p_gamma(0.05, 20.0);
    let truth_b = Polarization::from_p_gamma(0.03, 110.0);
    let science = || Catalog {
        targets: vec![target(
            "HK Tau",
            vec![
                component("A", truth_a, &pa, theta0, c, 1e-3),
                component("B", truth_b, &pa, theta0, c, 1e-3),
            ],
        )],
        ..Default::default()
    };
    // A telescope that adds no polarization (these synthetic stars carry none): the errors
    // below are sigma_F, c's and theta0's alone.
    let mut profile = Profile::sofi();
    profile.telescope.polarizes = false;
    let mut cat = science();
    let (cal, sum) = calibrate_catalog(
        &mut cat,
        stds.clone(),
        CalibrationSource::Night,
        &CalibrationContext {
            table: &table,
            profile: &profile,
            params: &CalibrationParams::default(),
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
        },
    );
    let cal = cal.unwrap();
    let f = cal.for_filter("ks").unwrap();
    assert!((f.offset.unwrap().c - c).abs() < 1e-12, "{f:?}");
    assert!((f.angles.unwrap().theta0_deg - theta0).abs() < 1e-9);
    assert_eq!(sum.n_uncalibrated, 0);
    let a = &cat.targets[0].components[0];
    assert!(
        (a.q - truth_a.q).abs() < 1e-12 && (a.u - truth_a.u).abs() < 1e-12,
        "{a:?}"
    );
    assert!(!a.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)));
    // sigma_q holds sigma_F and sigma_c: at phi = 3 and 48 deg, q = F_a cos 6 - F_b sin 6.
    let t = 6f64.to_radians();
    // ... and the zero-point error, which rotates (q, u): dq = -2u dtheta0.
    let st = f.angles.unwrap().sigma_theta0_deg.to_radians();
    // c and theta0 come from one fit: their covariance adds 2 (dq/dc)(dq/dtheta0) cov, with
    // dq/dc = -(cos 6 - sin 6) and dq/dtheta0 = -2u per rad.
    let cov = f.cov_c_theta0_deg.unwrap().to_radians();
    let expect = 1e-6
        + (t.cos() - t.sin()).powi(2) * f.offset.unwrap().sigma_c.powi(2)
        + (2.0 * truth_a.u * st).powi(2)
        + 2.0 * (t.cos() - t.sin()) * (2.0 * truth_a.u) * cov;
    assert!(f.offset.unwrap().sigma_c > 0.0);
    assert!(
        (a.sigma_q.powi(2) - expect).abs() < 1e-9 * expect,
        "{} vs {expect}",
        a.sigma_q.powi(2)
    );
    assert!((cat.targets[0].delta_gamma_deg.unwrap() - 90.0).abs() < 1e-6);
    // Standards section: four entries, the unknown one flagged and unused.
    assert_eq!(cat.standards.len(), 4);
    let hd_res = cat.standards.iter().find(|s| s.name == "HD 204827").unwrap();
    assert_eq!(hd_res.used_for, vec!["offset".to_string(), "angles".to_string()]);
    assert!(hd_res.residual_p_sigma.unwrap().abs() < 1e-6);
    let m = cat.standards.iter().find(|s| s.object == "Mystery").unwrap();
    assert!(m.flags.iter().any(|f| f.is(FlagCode::NotInStandardsTable)) && m.used_for.is_empty());
    assert_eq!(
        cat.standards.iter().find(|s| s.object == "HD_98161").unwrap().name,
        "HD 98161"
    );

    // Without calibration: biased by c, flagged, and the summary says why.
    let mut raw = science();
    let (none, sum) = calibrate_catalog(
        &mut raw,
        vec![],
        CalibrationSource::Night,
        &CalibrationContext {
            table: &table,
            profile: &profile,
            params: &CalibrationParams::default(),
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
        },
    );
    assert!(none.is_none());
    assert_eq!(sum.n_uncalibrated, 2);
    assert!(sum.lines[0].contains("uncalibrated") && sum.lines[0].contains("4 orientations"));
    let a = &raw.targets[0].components[0];
    assert!(a.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)));
    assert!((a.q - truth_a.q).abs() > 0.01);

    // The calibration file round-trips and serves another night.
    let dir = tempfile::tempdir().unwrap();
    cal.write(dir.path()).unwrap();
    let back = Calibration::read(dir.path()).unwrap();
    assert_eq!(back, cal);
    let mut other = science();
    calibrate_catalog(
        &mut other,
        vec![],
        CalibrationSource::File(dir.path().into(), Box::new(back)),
        &CalibrationContext {
            table: &table,
            profile: &profile,
            params: &CalibrationParams::default(),
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
        },
    );
    assert!((other.targets[0].components[0].q - truth_a.q).abs() < 1e-12);
    assert_eq!(
        other.calibration.as_ref().unwrap().source.as_deref(),
        Some(dir.path().display().to_string().as_str())
    );
}

#[test]
fn four_orientations_need_no_calibration() {
    let pa = [0.0, 45.0, 90.0, 135.0];
    let truth = Polarization::from_p_gamma(0.04, 150.0);
    let mut c = component("A", truth, &pa, 0.0, 0.0, 1e-3);
    // A pure beam ratio k: F_obs = (F + ck)/(1 + ck F).
    let ck = (1.0 - 0.97) / 1.97;
    for o in c.orientations.as_mut().unwrap() {
        o.f = (o.f + ck) / (1.0 + ck * o.f);
    }
    let unc = resolve_component(
        &mut c,
        &SolveSettings {
            profile: &Profile::sofi(),
            cal: None,
            method: StokesMethod::Auto,
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
            telescope_prior: None,
            telescope_polarizes: true,
        },
    );
    assert!(!unc);
    assert_eq!(c.stokes_method.as_deref(), Some("ratio"));
    assert!((c.q - truth.q).abs() < 1e-14 && (c.u - truth.u).abs() < 1e-14);
}

/// A degree of polarization above 1 (F values no light gives) is flagged `p_above_one`
/// and never passes the cut, however large P/sigma; 0.99 passes.
#[test]
fn a_degree_of_polarization_above_one_is_flagged_and_refused() {
    let pa = [0.0, 45.0, 90.0, 135.0];
    let resolved = |p: f64| {
        let mut c = component("A", Polarization::from_p_gamma(p, 30.0), &pa, 0.0, 0.0, 1e-3);
        resolve_component(
            &mut c,
            &SolveSettings {
                profile: &Profile::sofi(),
                cal: None,
                method: StokesMethod::LeastSquares,
                debias: Debias::WardleKronberg,
                cut_snr: 3.0,
                telescope_prior: None,
                telescope_polarizes: true,
            },
        );
        c
    };
    let c = resolved(1.32);
    assert!((c.p - 1.32).abs() < 1e-9, "{}", c.p);
    assert!(c.flags.iter().any(|f| f.is(FlagCode::PAboveOne)), "{:?}", c.flags);
    assert!(!c.passes_cut && c.snr.unwrap() > 100.0);
    let c = resolved(0.99);
    assert!(
        c.passes_cut && !c.flags.iter().any(|f| f.is(FlagCode::PAboveOne)),
        "{:?}",
        c.flags
    );
}

fn target_in(object: &str, filter: &str, comps: Vec<Component>) -> Target {
    let mut t = target(object, comps);
    t.filter = Some(filter.into());
    t.sequence = Some(format!("{object}@{filter}"));
    t
}

/// The offset is per filter: a night in J and Ks with different offsets gets one
/// entry per filter in calibration.json, and each target is corrected with its own
/// filter's entry (also when the calibration is read back from the file, as `--calib`
/// does); a filter without standards is flagged `uncalibrated`.
#[test]
fn two_filter_night_gets_one_offset_per_filter_and_targets_use_their_own() {
    let pa = [0.0, 45.0];
    let table = StandardsTable::builtin();
    let hd = table.find("HD 204827", "Ks").unwrap().clone();
    // Ks: k and p_inst give c = 0.0152, zero-point 3 deg (from HD 204827). J: c = -0.008
    // and, with no polarized standard in J, the profile's zero-point (0).
    let (c_ks, th_ks, c_j) = (0.0152, 3.0, -0.008);
    let unpol = |name: &str, filter: &str, th: f64, c: f64| {
        target_in(
            name,
            filter,
            vec![component("A", Polarization::default(), &pa, th, c, 3e-4)],
        )
    };
    let stds = vec![
        unpol("HD 64299", "Ks", th_ks, c_ks),
        unpol("HD 98161", "Ks", th_ks, c_ks),
        target_in(
            "HD 204827",
            "Ks",
            vec![component(
                "A",
                Polarization::from_p_gamma(hd.p, hd.gamma_deg),
                &pa,
                th_ks,
                c_ks,
                3e-4,
            )],
        ),
        unpol("HD 64299", "J", 0.0, c_j),
        unpol("HD 94851", "J", 0.0, c_j),
    ];
    let truth = Polarization::from_p_gamma(0.04, 35.0);
    let science = || Catalog {
        targets: vec![
            target_in("T Ks", "Ks", vec![component("A", truth, &pa, th_ks, c_ks, 1e-3)]),
            target_in("T J", "J", vec![component("A", truth, &pa, 0.0, c_j, 1e-3)]),
            target_in("T H", "H", vec![component("A", truth, &pa, 0.0, 0.01, 1e-3)]),
        ],
        ..Default::default()
    };
    let profile = Profile::sofi();
    let run = |source: CalibrationSource| {
        let mut cat = science();
        let (cal, sum) = calibrate_catalog(
            &mut cat,
            stds.clone(),
            source,
            &CalibrationContext {
                table: &table,
                profile: &profile,
                params: &CalibrationParams::default(),
                debias: Debias::WardleKronberg,
                cut_snr: 3.0,
            },
        );
        (cat, cal, sum)
    };
    let (cat, cal, sum) = run(CalibrationSource::Night);
    let cal = cal.unwrap();
    let names: Vec<&str> = cal.filters.iter().map(|f| f.filter.as_str()).collect();
    assert_eq!(names.len(), 2, "{names:?}");
    let (ks, j) = (cal.for_filter("Ks").unwrap(), cal.for_filter("J").unwrap());
    assert!((ks.offset.unwrap().c - c_ks).abs() < 1e-12, "{ks:?}");
    assert!((j.offset.unwrap().c - c_j).abs() < 1e-12, "{j:?}");
    assert!((ks.angles.unwrap().theta0_deg - th_ks).abs() < 1e-9);
    assert!(j.angles.is_none(), "no polarized standard in J: {j:?}");
    assert_eq!(j.offset_standards.len(), 2);
    assert!(cal.for_filter("H").is_none());

    let check = |cat: &Catalog, what: &str| {
        for object in ["T Ks", "T J"] {
            let a = &cat.targets.iter().find(|t| t.object == object).unwrap().components[0];
            assert!(
                (a.q - truth.q).abs() < 1e-9 && (a.u - truth.u).abs() < 1e-9,
                "{what} {object}: q {} u {} vs {} {}",
                a.q,
                a.u,
                truth.q,
                truth.u
            );
            assert!(!a.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)), "{what} {object}");
        }
        let h = &cat.targets.iter().find(|t| t.object == "T H").unwrap().components[0];
        assert!(
            h.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)),
            "{what}: {:?}",
            h.flags
        );
    };
    check(&cat, "night");
    assert_eq!(sum.n_uncalibrated, 1);
    assert!(
        sum.lines.iter().any(|l| l.contains("no offset for this filter")),
        "{:?}",
        sum.lines
    );

    // Written and read back (calibration.json), then applied as --calib does.
    let dir = tempfile::tempdir().unwrap();
    let path = cal.write(dir.path()).unwrap();
    let back = Calibration::read(dir.path()).unwrap();
    assert_eq!(back.filters.len(), 2);
    let (cat2, _, _) = run(CalibrationSource::File(path, Box::new(back)));
    check(&cat2, "--calib");
}

/// The zero-point's error turns (q, u) about the origin: it must add to the tangential
/// variance only, (2 sigma_theta0)^2 P^2, and leave the radial one (what sigma_P is made of)
/// as it was. The sign of its q-u covariance term decides that (with the opposite sign the
/// radial variance grows by 4 q^2 u^2 (2 sigma_theta0)^2 / P^2).
#[test]
fn the_zero_point_error_adds_tangential_variance_only() {
    let pa = [0.0, 45.0, 90.0, 135.0];
    let truth = Polarization::from_p_gamma(0.04, 30.0);
    let parity = Profile::sofi().angles.parity;
    let resolved = |sigma_theta0_deg: f64| {
        let mut c = component("A", truth, &pa, 0.0, 0.0, 1e-3);
        let fc = FilterCalibration {
            filter: "Ks".into(),
            offset: None,
            offset_standards: vec![],
            angles: Some(AngleCalibration {
                theta0_deg: 0.0,
                sigma_theta0_deg,
                parity,
                parity_measured: false,
                n_standards: 1,
            }),
            angle_standards: vec![],
            cov_c_theta0_deg: None,
            incomplete: None,
            telescope: None,
            telescope_uncorrected: None,
            telescope_from_prior: None,
            covariance: None,
            covariance_parameters: None,
            zero_point_from_profile: None,
        };
        resolve_component(
            &mut c,
            &SolveSettings {
                profile: &Profile::sofi(),
                cal: Some(&fc),
                method: StokesMethod::Auto,
                debias: Debias::WardleKronberg,
                cut_snr: 3.0,
                telescope_prior: None,
                telescope_polarizes: true,
            },
        );
        c
    };
    let split = |c: &Component| {
        let (q, u, vq, vu, cqu) = (c.q, c.u, c.sigma_q.powi(2), c.sigma_u.powi(2), c.cov_qu.unwrap());
        let p2 = q * q + u * u;
        let radial = (q * q * vq + u * u * vu + 2.0 * q * u * cqu) / p2;
        let tangential = (u * u * vq + q * q * vu - 2.0 * q * u * cqu) / p2;
        (radial, tangential, p2)
    };
    let (r0, t0, p2) = split(&resolved(0.0));
    let sigma = 5.0_f64;
    let (r1, t1, _) = split(&resolved(sigma));
    let added = (2.0 * sigma.to_radians()).powi(2) * p2;
    assert!((r1 - r0).abs() <= 1e-9 * r0, "radial variance {r0:e} -> {r1:e}");
    assert!(
        ((t1 - t0) - added).abs() <= 1e-9 * added,
        "tangential variance grows by {:e}, expected {added:e}",
        t1 - t0
    );
}

/// Through `calibrate_catalog`: a binary at 2 orientations calibrated with an offset and a
/// zero-point. sigma_gamma is the measurement's and the calibration's parts in quadrature;
/// the zero-point's error (here 6 deg, ten times the stars' own) must not enter
/// sigma_delta_gamma, the offset's must (it moves the two angles differently), and the
/// catalog's value equals the delta method computed here from the F errors by hand.
#[test]
fn delta_gamma_error_has_the_offset_and_not_the_zero_point() {
    let pa = [0.0, 45.0];
    let (a_pol, b_pol) = (
        Polarization::from_p_gamma(0.03, 20.0),
        Polarization::from_p_gamma(0.02, 70.0),
    );
    let (sf, sc) = (4e-4, 6e-4);
    let parity = Profile::sofi().angles.parity;
    let run = |sigma_theta0_deg: f64| {
        let mut cat = Catalog {
            targets: vec![target(
                "Pair",
                vec![
                    component("A", a_pol, &pa, 0.0, 0.01, sf),
                    component("B", b_pol, &pa, 0.0, 0.01, sf),
                ],
            )],
            ..Default::default()
        };
        let fc = FilterCalibration {
            filter: "Ks".into(),
            offset: Some(Offset { c: 0.01, sigma_c: sc }),
            offset_standards: vec![],
            angles: Some(AngleCalibration {
                theta0_deg: 0.0,
                sigma_theta0_deg,
                parity,
                parity_measured: false,
                n_standards: 1,
            }),
            angle_standards: vec![],
            cov_c_theta0_deg: Some(-0.5 * sc * sigma_theta0_deg),
            incomplete: None,
            telescope: None,
            telescope_uncorrected: None,
            telescope_from_prior: None,
            covariance: None,
            covariance_parameters: None,
            zero_point_from_profile: None,
        };
        let cal = Calibration {
            schema_version: CALIBRATION_SCHEMA.into(),
            filters: vec![fc],
            frames: vec![],
            flats: vec![],
            provenance: Default::default(),
        };
        calibrate_catalog(
            &mut cat,
            vec![],
            CalibrationSource::File("cal".into(), Box::new(cal)),
            &CalibrationContext {
                table: &StandardsTable::builtin(),
                profile: &Profile::sofi(),
                params: &CalibrationParams::default(),
                debias: Debias::WardleKronberg,
                cut_snr: 3.0,
            },
        );
        cat.targets.remove(0)
    };
    let (t0, t6) = (run(0.0), run(6.0));
    let (s0, s6) = (t0.sigma_delta_gamma_deg.unwrap(), t6.sigma_delta_gamma_deg.unwrap());
    assert!(
        (s0 - s6).abs() < 1e-12,
        "theta0's error entered sigma_delta_gamma: {s0} -> {s6}"
    );
    // By hand: with 2 orientations q = F(0) - c, u = F(45) - c (analyzer = posang here:
    // theta0 = 0 and the parity's sign only mirrors u), so each star has Var q = Var u = sf^2,
    // no covariance, and d(q, u)/dc = (-1, -1) up to the parity's sign on u.
    let grad = |c: &Component| {
        let p2 = c.q * c.q + c.u * c.u;
        [-c.u / (2.0 * p2), c.q / (2.0 * p2)]
    };
    let (a, b) = (&t6.components[0], &t6.components[1]);
    let (ga, gb) = (grad(a), grad(b));
    let (da, db) = (a.offset_gradient.unwrap(), b.offset_gradient.unwrap());
    assert!(
        (da[0] + 1.0).abs() < 1e-12 && (da[1].abs() - 1.0).abs() < 1e-12,
        "{da:?}"
    );
    let own = (ga[0] * ga[0] + ga[1] * ga[1] + gb[0] * gb[0] + gb[1] * gb[1]) * sf * sf;
    let common = ga[0] * da[0] + ga[1] * da[1] - gb[0] * db[0] - gb[1] * db[1];
    let want = (own + common * common * sc * sc).sqrt().to_degrees();
    assert!((s6 / want - 1.0).abs() < 1e-9, "{s6} vs by hand {want}");
    assert!(
        common.abs() * sc > 0.3 * own.sqrt(),
        "the offset's term matters in this test"
    );
    // Per star: the total angle error is the two parts in quadrature, and the zero-point part
    // holds the 6 deg.
    for c in [a, b] {
        let (st, zp) = (c.sigma_gamma_stat_deg.unwrap(), c.sigma_gamma_zero_point_deg.unwrap());
        assert!((c.sigma_gamma_deg - st.hypot(zp)).abs() < 1e-9 * c.sigma_gamma_deg);
        assert!(zp > 4.5 && st < 1.0, "stat {st}, zero-point {zp}");
    }
    let iv = t6.delta_gamma_interval_deg.unwrap();
    let dg = t6.delta_gamma_deg.unwrap();
    assert!(
        iv[0] < dg && dg < iv[1] && (iv[1] - iv[0] - 2.0 * s6).abs() < 0.1 * s6,
        "{iv:?} {dg} {s6}"
    );
}

fn written_calibration(filter: serde_json::Value) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let doc = serde_json::json!({
        "schema_version": CALIBRATION_SCHEMA, "filters": [filter], "frames": [], "provenance": {}
    });
    let p = dir.path().join(CALIBRATION_FILE);
    std::fs::write(&p, serde_json::to_string(&doc).unwrap()).unwrap();
    (dir, p)
}

/// `calibration.json` is checked on reading: an absurd number is refused with the file, the
/// key path and the value; sane ones pass, theta0 normalised into [0, 180).
#[test]
fn calibration_file_with_absurd_numbers_is_refused_naming_file_key_and_value() {
    let good = serde_json::json!({
        "filter": "Ks", "offset": {"c": 0.018, "sigma_c": 0.0002}, "offset_standards": [],
        "angles": {"theta0_deg": -177.0, "sigma_theta0_deg": 0.5, "parity": -1,
                   "parity_measured": true, "n_standards": 2},
        "angle_standards": [], "cov_c_theta0_deg": -7e-5
    });
    let (dir, _) = written_calibration(good.clone());
    let c = Calibration::read(dir.path()).unwrap();
    assert!((c.filters[0].angles.unwrap().theta0_deg - 3.0).abs() < 1e-12);
    let cases: [(&str, serde_json::Value, &str); 8] = [
        ("/offset/c", 5.0.into(), "filters[0].offset.c = 5"),
        ("/offset/sigma_c", (-1e-3).into(), "filters[0].offset.sigma_c = -0.001"),
        ("/angles/parity", 7.into(), "filters[0].angles.parity = 7"),
        (
            "/angles/theta0_deg",
            1e300.into(),
            "filters[0].angles.theta0_deg = 1e300",
        ),
        (
            "/angles/sigma_theta0_deg",
            91.0.into(),
            "filters[0].angles.sigma_theta0_deg = 91",
        ),
        (
            "/angles/sigma_theta0_deg",
            (-0.1).into(),
            "filters[0].angles.sigma_theta0_deg = -0.1",
        ),
        ("/cov_c_theta0_deg", 2e-4.into(), "filters[0].cov_c_theta0_deg = 0.0002"),
        ("/cov_c_theta0_deg", 1e300.into(), "filters[0].cov_c_theta0_deg = 1e300"),
    ];
    for (ptr, v, expect) in cases {
        let mut f = good.clone();
        *f.pointer_mut(ptr).unwrap() = v;
        let (_dir, p) = written_calibration(f);
        let e = Calibration::read(&p).unwrap_err().to_string();
        assert!(e.contains(&p.display().to_string()) && e.contains(expect), "{ptr}: {e}");
    }
    // The refusal is a value a caller can match: the file, the key and the value apart.
    let mut f = good.clone();
    f["offset"]["c"] = 5.0.into();
    let (_dir, p) = written_calibration(f);
    match Calibration::read(&p).unwrap_err() {
        crate::error::Error::CalibrationValue {
            path,
            source: crate::error::CalibrationValueError::Refused { key, value, .. },
        } => assert_eq!((path, key.as_str(), value.as_str()), (p, "filters[0].offset.c", "5")),
        e => panic!("not a refused value: {e:?}"),
    }
    // A covariance without the angles it belongs to.
    let mut f = good;
    f["angles"] = serde_json::Value::Null;
    let (_dir, p) = written_calibration(f);
    let e = Calibration::read(&p).unwrap_err().to_string();
    assert!(e.contains("filters[0].cov_c_theta0_deg"), "{e}");
}

fn run_night(
    stds: Vec<Target>,
    cat: &mut Catalog,
    table: &StandardsTable,
    params: &CalibrationParams,
) -> (Option<Calibration>, CalibrationSummary) {
    calibrate_catalog(
        cat,
        stds,
        CalibrationSource::Night,
        &CalibrationContext {
            table,
            profile: &Profile::sofi(),
            params,
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
        },
    )
}

const PRECISE_POL: &str = r#"
[[standard]]
name = "Pol A"
filter = "Ks"
p = 0.025
sigma_p = 0.0002
gamma_deg = 40.0
sigma_gamma_deg = 0.1
[[standard]]
name = "Pol B"
filter = "Ks"
p = 0.02
sigma_p = 0.0002
gamma_deg = 100.0
sigma_gamma_deg = 0.1
"#;

/// One polarized standard at 0/45 and no unpolarized one: the data cannot separate c from
/// theta0 (the sequential estimate took c = 0 and turned every angle by the offset's
/// share). The calibration says so, keeps the profile's angles, and every component of the
/// filter is flagged `calibration_incomplete` (and `uncalibrated`: no offset either).
#[test]
fn one_polarized_standard_at_two_orientations_gives_an_incomplete_flagged_calibration() {
    let pa = [0.0, 45.0];
    let (theta0, c) = (3.0, 0.0152);
    let mut table = StandardsTable::builtin();
    table.merge_toml(PRECISE_POL, "test").unwrap();
    let pol = Polarization::from_p_gamma(0.025, 40.0);
    let stds = vec![target("Pol A", vec![component("A", pol, &pa, theta0, c, 3e-4)])];
    let truth = Polarization::from_p_gamma(0.04, 35.0);
    let mut cat = Catalog {
        targets: vec![target(
            "T",
            vec![
                component("A", truth, &pa, theta0, c, 1e-3),
                component("B", truth, &pa, theta0, c, 1e-3),
            ],
        )],
        ..Default::default()
    };
    let (cal, sum) = run_night(stds, &mut cat, &table, &CalibrationParams::default());
    let f = cal.unwrap().for_filter("Ks").unwrap().clone();
    assert!(
        f.angles.is_none(),
        "no theta0 from a standard that cannot give it: {f:?}"
    );
    assert!(f.offset.is_none() && f.cov_c_theta0_deg.is_none());
    assert!(f.incomplete.as_deref().unwrap().contains("cannot separate"), "{f:?}");
    for comp in &cat.targets[0].components {
        assert!(
            comp.flags.iter().any(|f| f.is(FlagCode::CalibrationIncomplete)),
            "{:?}",
            comp.flags
        );
        assert!(comp.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)));
    }
    assert_eq!(sum.n_incomplete, 2);
    assert!(
        sum.lines
            .iter()
            .any(|l| l.contains("incomplete") && l.contains("cannot separate")),
        "{:?}",
        sum.lines
    );
    // The file keeps the reason and serves another night with the same flags.
    let dir = tempfile::tempdir().unwrap();
    let cal = measure(
        &[target("Pol A", vec![component("A", pol, &pa, theta0, c, 3e-4)])],
        &table,
        &Profile::sofi(),
        true,
    )
    .unwrap();
    cal.write(dir.path()).unwrap();
    assert_eq!(
        Calibration::read(dir.path()).unwrap().filters[0].incomplete,
        f.incomplete
    );

    // Two polarized standards at different angles separate them: c and theta0 exact, and
    // nothing flagged.
    let stds = vec![
        target("Pol A", vec![component("A", pol, &pa, theta0, c, 3e-4)]),
        target(
            "Pol B",
            vec![component(
                "A",
                Polarization::from_p_gamma(0.02, 100.0),
                &pa,
                theta0,
                c,
                3e-4,
            )],
        ),
    ];
    let mut cat2 = Catalog {
        targets: vec![target("T", vec![component("A", truth, &pa, theta0, c, 1e-3)])],
        ..Default::default()
    };
    let (cal, sum) = run_night(stds, &mut cat2, &table, &CalibrationParams::default());
    let f = cal.unwrap().for_filter("Ks").unwrap().clone();
    assert!(f.incomplete.is_none(), "{f:?}");
    assert!((f.angles.unwrap().theta0_deg - theta0).abs() < 1e-9 && (f.offset.unwrap().c - c).abs() < 1e-12);
    let cov = f.cov_c_theta0_deg.unwrap();
    let corr = cov / (f.offset.unwrap().sigma_c * f.angles.unwrap().sigma_theta0_deg);
    eprintln!("two polarized standards, 0/45: corr(c, theta0) = {corr:.3}");
    assert!(corr.abs() < 1.0);
    let a = &cat2.targets[0].components[0];
    assert!((a.q - truth.q).abs() < 1e-9 && (a.u - truth.u).abs() < 1e-9, "{a:?}");
    // Only the telescope's polarization is not corrected (these components carry no
    // parallactic angles).
    assert_eq!(a.flags, [Flag::new(FlagCode::TelescopeUncorrected)], "{:?}", a.flags);
    assert_eq!(sum.n_incomplete, 0);
}

/// A polarized standard whose P is off its table value by many sigma is flagged, with the
/// residual in units of the measurement's statistical error and the table error (not the
/// calibration's); an unpolarized standard is tested in (q, u) against 0 with 2 dof.
#[test]
fn standards_disagreeing_with_their_table_are_flagged_with_statistical_residuals() {
    let pa = [0.0, 45.0];
    let (theta0, c, sf) = (0.0, 0.0152, 3e-4);
    let mut table = StandardsTable::builtin();
    table.merge_toml(PRECISE_POL, "test").unwrap();
    // Pol A is in truth 3 % (table 2.5 +- 0.02 %); HD 94851 carries 0.4 % (table 0 +- 0.05 %).
    let stds = vec![
        target(
            "HD 64299",
            vec![component("A", Polarization::default(), &pa, theta0, c, sf)],
        ),
        target(
            "HD 98161",
            vec![component("A", Polarization::default(), &pa, theta0, c, sf)],
        ),
        target(
            "HD 94851",
            vec![component(
                "A",
                Polarization::from_p_gamma(0.004, 10.0),
                &pa,
                theta0,
                c,
                sf,
            )],
        ),
        target(
            "Pol A",
            vec![component(
                "A",
                Polarization::from_p_gamma(0.03, 40.0),
                &pa,
                theta0,
                c,
                sf,
            )],
        ),
        target(
            "Pol B",
            vec![component(
                "A",
                Polarization::from_p_gamma(0.02, 100.0),
                &pa,
                theta0,
                c,
                sf,
            )],
        ),
    ];
    let mut cat = Catalog::default();
    let (cal, sum) = run_night(stds, &mut cat, &table, &CalibrationParams::default());
    let f = cal.unwrap().for_filter("Ks").unwrap().clone();
    let by = |n: &str| cat.standards.iter().find(|s| s.name == n).unwrap().clone();
    let a = by("Pol A");
    let m = a.measured.as_ref().unwrap();
    // 0/45: sigma_P,stat = sigma_F (q = F0 - c, u = F45 - c up to the theta0 rotation).
    let expect = (m.p - 0.025) / sf.hypot(0.0002);
    assert!(
        (a.residual_p_sigma.unwrap() - expect).abs() < 1e-6 * expect.abs(),
        "{:?} vs {expect}",
        a.residual_p_sigma
    );
    assert!(expect > 3.0, "{expect}");
    assert!(
        a.flags
            .iter()
            .any(|x| x.to_string() == format!("p_disagrees_with_table: {:.1} sigma", expect)),
        "{:?}",
        a.flags
    );
    assert!(
        sum.lines
            .iter()
            .any(|l| l.contains("Pol A") && l.contains("p_disagrees_with_table")),
        "{:?}",
        sum.lines
    );
    // Unpolarized: chi^2 of (q, u) with Var = sigma_F^2 + sigma_p^2/2 each (0/45: no covariance
    // once theta0 is the profile's... here theta0 comes from Pol A and B, a rotation, which
    // leaves the isotropic covariance isotropic).
    assert!(f.angles.is_some());
    let hd = by("HD 94851");
    let mh = hd.measured.as_ref().unwrap();
    let chi2 = (mh.q * mh.q + mh.u * mh.u) / (sf * sf + 0.0005f64.powi(2) / 2.0);
    assert!(
        (hd.residual_qu_chi2.unwrap() - chi2).abs() < 1e-6 * chi2,
        "{:?} vs {chi2}",
        hd.residual_qu_chi2
    );
    assert!(hd.residual_p_sigma.is_none());
    assert!(
        hd.flags.iter().any(|x| x.is(FlagCode::QuDisagreesWithTable)),
        "{:?}",
        hd.flags
    );

    // Every standard at its table values: nothing flagged, residuals 0.
    let stds = vec![
        target(
            "HD 64299",
            vec![component("A", Polarization::default(), &pa, theta0, c, sf)],
        ),
        target(
            "Pol A",
            vec![component(
                "A",
                Polarization::from_p_gamma(0.025, 40.0),
                &pa,
                theta0,
                c,
                sf,
            )],
        ),
        target(
            "Pol B",
            vec![component(
                "A",
                Polarization::from_p_gamma(0.02, 100.0),
                &pa,
                theta0,
                c,
                sf,
            )],
        ),
    ];
    let mut cat = Catalog::default();
    let (_, sum) = run_night(stds, &mut cat, &table, &CalibrationParams::default());
    for s in &cat.standards {
        assert!(s.flags.is_empty(), "{s:?}");
        let r = s.residual_p_sigma.or(s.residual_qu_chi2).unwrap();
        assert!(r.abs() < 1e-6, "{}: {r}", s.name);
    }
    assert!(!sum.lines.iter().any(|l| l.contains("disagrees")), "{:?}", sum.lines);
}

/// A Stokes method that cannot apply (ratio on 0/45) falls back to the automatic choice:
/// with a calibration offset the least squares of F - c (flag names both, the value may
/// pass the cut); without, the plain fit, flagged `uncalibrated`, and it never passes the cut.
#[test]
fn an_impossible_stokes_method_falls_back_to_auto_and_never_passes_silently() {
    let pa = [0.0, 45.0];
    let (theta0, c) = (0.0, 0.0152);
    let table = StandardsTable::builtin();
    let truth = Polarization::from_p_gamma(0.05, 30.0);
    let science = || Catalog {
        targets: vec![target("T", vec![component("A", truth, &pa, theta0, c, 1e-3)])],
        ..Default::default()
    };
    let params = CalibrationParams {
        stokes_method: StokesMethod::Ratio,
        ..Default::default()
    };
    let stds = || {
        vec![
            target(
                "HD 64299",
                vec![component("A", Polarization::default(), &pa, theta0, c, 3e-4)],
            ),
            target(
                "HD 98161",
                vec![component("A", Polarization::default(), &pa, theta0, c, 3e-4)],
            ),
        ]
    };
    let mut cat = science();
    let (_, sum) = run_night(stds(), &mut cat, &table, &params);
    let a = &cat.targets[0].components[0];
    assert_eq!(a.stokes_method.as_deref(), Some("least_squares"));
    assert!((a.q - truth.q).abs() < 1e-9 && (a.u - truth.u).abs() < 1e-9, "{a:?}");
    let flag = a
        .flags
        .iter()
        .find(|f| f.is(FlagCode::StokesMethodFailed))
        .expect("flagged");
    let detail = flag.detail.as_deref().unwrap_or_default();
    assert!(
        detail.contains("ratio") && detail.ends_with("; fell back to least_squares"),
        "{flag}"
    );
    assert!(a.passes_cut && !a.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)));
    assert_eq!(sum.n_method_failed, 1);
    assert!(
        sum.lines.iter().any(|l| l.contains("stokes_method_failed")),
        "{:?}",
        sum.lines
    );

    // No calibration: the fallback is uncalibrated; flagged, and refused by the cut.
    let mut cat = science();
    run_night(vec![], &mut cat, &table, &params);
    let a = &cat.targets[0].components[0];
    assert!(a.q.is_finite() && (a.q - (truth.q + c)).abs() < 1e-9, "{a:?}");
    assert!(a
        .flags
        .iter()
        .any(|f| f.is(FlagCode::StokesMethodFailed) && f.to_string().contains("fell back to least_squares")));
    assert!(a.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)), "{:?}", a.flags);
    assert!(!a.passes_cut, "an uncalibrated fallback passed the cut: {:?}", a.flags);
}

/// A calibration file without the full covariance (older files): the matrix is built from
/// the offset's and zero-point's errors, with their covariance only when both were
/// measured (a cross term next to a missing parameter would be a stray number).
#[test]
fn the_covariance_of_a_file_without_one_is_built_from_what_it_has() {
    let parity = Profile::sofi().angles.parity;
    let fc = |offset: bool, angles: bool| FilterCalibration {
        filter: "Ks".into(),
        offset: offset.then_some(crate::stokes::calibration::Offset {
            c: 0.015,
            sigma_c: 2e-4,
        }),
        offset_standards: vec![],
        angles: angles.then_some(AngleCalibration {
            theta0_deg: 3.0,
            sigma_theta0_deg: 0.5,
            parity,
            parity_measured: true,
            n_standards: 1,
        }),
        angle_standards: vec![],
        cov_c_theta0_deg: Some(-4e-5),
        incomplete: None,
        telescope: None,
        telescope_uncorrected: None,
        telescope_from_prior: None,
        covariance: None,
        covariance_parameters: None,
        zero_point_from_profile: None,
    };
    let both = fc(true, true).covariance_matrix();
    assert_eq!(both[CAL_C][CAL_C], 4e-8);
    assert_eq!(both[CAL_THETA0][CAL_THETA0], 0.25);
    assert_eq!(both[CAL_C][CAL_THETA0], -4e-5);
    assert_eq!(both[CAL_THETA0][CAL_C], -4e-5);
    for (o, a) in [(true, false), (false, true), (false, false)] {
        let m = fc(o, a).covariance_matrix();
        assert_eq!(m[CAL_C][CAL_THETA0], 0.0, "offset {o}, angles {a}");
        assert_eq!(m[CAL_THETA0][CAL_C], 0.0, "offset {o}, angles {a}");
        assert_eq!(m[CAL_C][CAL_C], if o { 4e-8 } else { 0.0 });
    }
    // A written covariance is taken as it is.
    let mut written = fc(true, true);
    written.covariance = Some([[1.0, 2.0, 0.0, 0.0], [2.0, 5.0, 0.0, 0.0], [0.0; 4], [0.0; 4]]);
    assert_eq!(written.covariance_matrix()[CAL_C][CAL_THETA0], 2.0);
}

/// A standard the table knows but not in the filter observed is named for what is missing
/// (its values in that filter), not as a star the table lacks.
#[test]
fn a_known_standard_in_a_filter_without_values_is_flagged_for_the_filter() {
    let table = crate::standards::StandardsTable::builtin();
    let mut t = Target::new("HD 204827", Status::Ok);
    t.filter = Some("Ks".into());
    let (entry, flags) = table_entry_for(&t, &table);
    assert!(entry.is_some() && flags.is_empty(), "{flags:?}");
    t.filter = Some("J".into());
    let (entry, flags) = table_entry_for(&t, &table);
    assert!(entry.is_none());
    assert_eq!(flags, [Flag::with_detail(FlagCode::NoTableValuesForFilter, "J")]);
    assert_eq!(flags[0].to_string(), "no_table_values_for_filter: J");
    let unknown = Target::new("Not A Standard", Status::Ok);
    assert_eq!(
        table_entry_for(&unknown, &table).1,
        [Flag::new(FlagCode::NotInStandardsTable)]
    );
}

/// A standard observed at four orientations is used (more orientations only help); one seen
/// at a single orientation cannot give both q and u and is left out, even when its F is
/// far off.
#[test]
fn standards_at_four_orientations_are_used_and_at_one_are_not() {
    let (theta0, c) = (3.0, 0.0152);
    let table = StandardsTable::builtin();
    let hd = table.find("HD 204827", "Ks").unwrap().clone();
    let four = [0.0, 22.5, 45.0, 67.5];
    let polarized = Polarization::from_p_gamma(hd.p, hd.gamma_deg);
    let stds = vec![
        target(
            "HD 64299",
            vec![component("A", Polarization::default(), &four, theta0, c, 3e-4)],
        ),
        target("HD 204827", vec![component("A", polarized, &four, theta0, c, 3e-4)]),
        // At one orientation, with an offset ten times the true one.
        target(
            "HD_98161",
            vec![component("A", Polarization::default(), &[0.0], theta0, 0.15, 3e-4)],
        ),
    ];
    let cal = measure(&stds, &table, &Profile::sofi(), false).expect("two usable standards");
    let f = cal.for_filter("ks").unwrap();
    assert!((f.offset.unwrap().c - c).abs() < 1e-9, "{f:?}");
    assert!((f.angles.unwrap().theta0_deg - theta0).abs() < 1e-6, "{f:?}");
    assert_eq!(f.offset_standards.len(), 2, "{:?}", f.offset_standards);
    assert!(
        f.offset_standards.iter().all(|s| !s.contains("98161")),
        "{:?}",
        f.offset_standards
    );
}

/// What the standards section keeps of a standard's reduction: its own flags but not
/// `companion_not_found` (a standard is a single star); `failed: ...` for a failed
/// reduction only; residuals against the table only for a measured P.
#[test]
fn the_standards_section_keeps_flags_failures_and_residuals_only_where_they_apply() {
    let pa = [0.0, 45.0];
    let (theta0, c) = (3.0, 0.0152);
    let table = StandardsTable::builtin();
    let hd = table.find("HD 204827", "Ks").unwrap().clone();
    let polarized = Polarization::from_p_gamma(hd.p, hd.gamma_deg);
    let mut measured = target(
        "HD 64299",
        vec![component("A", Polarization::default(), &pa, theta0, c, 3e-4)],
    );
    measured.components[0].flags = vec![Flag::new(FlagCode::CompanionNotFound), Flag::new(FlagCode::BadPixels)];
    // A note that is not a failure: the reduction succeeded.
    measured.error = Some("one dither dropped".into());
    let mut failed = target(
        "HD_98161",
        vec![component("A", Polarization::default(), &[], theta0, c, 3e-4)],
    );
    failed.status = Status::Failed;
    failed.error = Some("no star found".into());
    let stds = vec![
        measured,
        failed,
        target("HD 204827", vec![component("A", polarized, &pa, theta0, c, 3e-4)]),
    ];
    let mut cat = Catalog::default();
    let (cal, _) = run_night(stds, &mut cat, &table, &CalibrationParams::default());
    assert!(cal.is_some());
    let by = |object: &str| cat.standards.iter().find(|s| s.object == object).unwrap();
    let m = by("HD 64299");
    let flags = &m.measured.as_ref().unwrap().flags;
    assert!(flags.iter().any(|f| f.is(FlagCode::BadPixels)), "{flags:?}");
    assert!(!flags.iter().any(|f| f.is(FlagCode::CompanionNotFound)), "{flags:?}");
    assert!(!m.flags.iter().any(|f| f.is(FlagCode::Failed)), "{:?}", m.flags);
    assert!(m.residual_qu_chi2.is_some_and(f64::is_finite), "{m:?}");
    let f = by("HD_98161");
    assert!(
        f.flags.iter().any(|x| x.to_string() == "failed: no star found"),
        "{:?}",
        f.flags
    );
    assert_eq!(f.status, Status::Failed);
    assert!(
        f.residual_qu_chi2.is_none() && f.residual_p_sigma.is_none() && f.residual_gamma_deg.is_none(),
        "{f:?}"
    );
}

/// A standard is reduced as a single star: no companion accepted or hinted, no field
/// stars; every other setting is the targets'.
#[test]
fn standards_are_reduced_as_single_stars_with_the_targets_settings() {
    let mut p = crate::reduce::TargetParams::default();
    p.measure.companion_hint = Some((3.0, 120.0));
    p.measure.min_companion_snr = 7.0;
    p.measure.clip_sigma = 4.5;
    let s = standard_params(&p);
    assert_eq!(s.measure.min_companion_snr, f64::INFINITY);
    assert!(s.measure.companion_hint.is_none());
    assert_eq!(s.measure.clip_sigma, 4.5);
    assert!(!s.measure.field_stars);
    let mut back = s.clone();
    back.measure.field_stars = p.measure.field_stars;
    back.measure.companion_hint = p.measure.companion_hint;
    back.measure.min_companion_snr = p.measure.min_companion_snr;
    assert_eq!(serde_json::to_value(&back).unwrap(), serde_json::to_value(&p).unwrap());
}

/// A sequence is a standard's when `DPR TYPE` of its first readable frame is STD (any case,
/// padded); frames that cannot be read are passed over; a sequence with no readable frame,
/// or whose first readable frame says OBJECT, is science.
#[test]
fn a_standard_sequence_is_told_by_the_first_readable_dpr_type() {
    use sofipol_calib::classify::ScienceInfo;
    let dir = tempfile::tempdir().unwrap();
    let profile = Profile::sofi();
    let write = |name: &str, dpr: &str| {
        let path = dir.path().join(name);
        let mut h = sofipol_calib::header::Header::new(&path);
        h.set(&profile.keywords.dpr_type, dpr);
        let frame = sofipol_calib::frame::Frame::new(ndarray::Array2::zeros((4, 4)), h);
        sofipol_calib::fits::write_frame(&path, &frame, &Default::default()).unwrap();
        path
    };
    let info = |path: std::path::PathBuf| ScienceInfo {
        path,
        object: "S".into(),
        tpl_start: "t".into(),
        sequence: "S@t".into(),
        posang_deg: 0.0,
        offset_px: [0.0, 0.0],
        filter: "Ks".into(),
        wollaston: "WOLLASTON".into(),
        dit_s: 10.0,
        ndit: 6,
        expno: Some(1),
        nexp: Some(2),
        mjd: None,
        ra_deg: None,
        dec_deg: None,
        pixscale_arcsec: 0.288,
    };
    let seq = |paths: Vec<std::path::PathBuf>| crate::sequence::Sequence {
        id: "S@t".into(),
        object: "S".into(),
        tpl_start: "t".into(),
        filter: "Ks".into(),
        orientations: vec![crate::sequence::Orientation {
            posang_deg: 0.0,
            analyzer_deg: 0.0,
            exposures: paths.into_iter().map(info).collect(),
        }],
    };
    let (std, obj, missing) = (
        write("std.fits", " std "),
        write("obj.fits", "OBJECT"),
        dir.path().join("gone.fits"),
    );
    assert!(is_standard_sequence(&seq(vec![std.clone(), obj.clone()]), &profile));
    assert!(is_standard_sequence(&seq(vec![missing.clone(), std.clone()]), &profile));
    assert!(!is_standard_sequence(&seq(vec![obj, std]), &profile));
    assert!(!is_standard_sequence(&seq(vec![missing]), &profile));
}
