//! A night whose standards and targets all see the telescope's polarization, made with the
//! forward model at the catalog level (per-orientation F with each orientation's parallactic
//! angle): the calibration measures it, removes it, and says when it cannot.
use super::*;
use crate::catalog::CombinedF;
use crate::catalog::TermSource;
use crate::stokes::model::{normalized_difference, Polarization, TelescopePolarization};

const TEL: TelescopePolarization = TelescopePolarization {
    p_tel: 0.006,
    psi_tel_deg: 25.0,
};
const THETA0: f64 = 3.0;
const C: f64 = 0.0152;

/// A component observed at rotator angles `posangs`, orientation i at parallactic angle
/// `etas[i]`: F = (star + telescope) through the analyzer, plus c.
fn component(name: &str, star: Polarization, posangs: &[f64], etas: &[f64], sigma: f64) -> Component {
    let orients = posangs
        .iter()
        .zip(etas)
        .map(|(&pa, &eta)| {
            let e = 2.0 * eta.to_radians();
            CombinedF {
                posang_deg: Some(pa),
                analyzer_deg: pa,
                f: normalized_difference(star.add(TEL.at(eta)), pa + THETA0) + C,
                sigma_f: sigma,
                chi2: f64::NAN,
                n_dithers: 5,
                n_dithers_total: 5,
                parallactic_2eta: Some([e.cos(), e.sin()]),
                parallactic_deg: Some(eta),
                sigma_f_propagated: sigma,
                sigma_f_scatter: f64::NAN,
            }
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

/// Six standards at parallactic angles spread over the night (`spread` = false: all
/// within 2 deg of -150).
fn standards(table: &StandardsTable, spread: bool) -> Vec<Target> {
    let pol = |name: &str| {
        let e = table.find(name, "Ks").unwrap();
        Polarization::from_p_gamma(e.p, e.gamma_deg)
    };
    [
        ("HD 64299", Polarization::default(), -150.0),
        ("HD 204827", pol("HD 204827"), -100.0),
        ("HD 98161", Polarization::default(), -40.0),
        ("HD 94851", Polarization::default(), 20.0),
        ("HD 154445", pol("HD 154445"), 75.0),
        ("BD+28 4211", Polarization::default(), 140.0),
    ]
    .iter()
    .enumerate()
    .map(|(i, &(name, star, eta))| {
        let eta = if spread { eta } else { -150.0 + 0.4 * i as f64 };
        target(name, vec![component("A", star, &[0.0, 45.0], &[eta, eta + 3.0], 3e-4)])
    })
    .collect()
}

const TRUTH_A: Polarization = Polarization { q: 0.012, u: -0.004 };
const TRUTH_B: Polarization = Polarization { q: -0.003, u: 0.009 };

fn science(posangs: &[f64], etas: &[f64]) -> Catalog {
    Catalog {
        targets: vec![target(
            "HK Tau",
            vec![
                component("A", TRUTH_A, posangs, etas, 1e-3),
                component("B", TRUTH_B, posangs, etas, 1e-3),
            ],
        )],
        ..Default::default()
    }
}

fn calibrate(
    cat: &mut Catalog,
    stds: Vec<Target>,
    source: CalibrationSource,
    params: &CalibrationParams,
) -> (Option<Calibration>, CalibrationSummary) {
    calibrate_catalog(
        cat,
        stds,
        source,
        &CalibrationContext {
            table: &StandardsTable::builtin(),
            profile: &Profile::sofi(),
            params,
            debias: Debias::WardleKronberg,
            cut_snr: 3.0,
        },
    )
}

fn assert_truth(cat: &Catalog, tol: f64) {
    for (c, truth) in cat.targets[0].components.iter().zip([TRUTH_A, TRUTH_B]) {
        assert!(
            (c.q - truth.q).abs() < tol && (c.u - truth.u).abs() < tol,
            "{}: ({}, {}) vs {truth:?}; flags {:?}",
            c.name,
            c.q,
            c.u,
            c.flags
        );
        assert!(
            !c.flags.iter().any(|f| f.is(FlagCode::TelescopeUncorrected)),
            "{:?}",
            c.flags
        );
    }
}

#[test]
fn the_telescope_is_measured_from_the_standards_and_removed_from_every_method() {
    let table = StandardsTable::builtin();
    // Two orientations (least squares with c), and four (the ratio method, which cancels c
    // but not the telescope), the parallactic angle changing within the sequence.
    // (The ratio method cancels a beam ratio exactly but the additive c of these data only
    // to first order: 3e-6 here, with or without the telescope.)
    for (posangs, etas, tol) in [
        (vec![0.0, 45.0], vec![-100.0, -97.0], 1e-9),
        (vec![0.0, 45.0, 90.0, 135.0], vec![-100.0, -97.0, -94.0, -91.0], 1e-5),
    ] {
        let mut cat = science(&posangs, &etas);
        let (cal, sum) = calibrate(
            &mut cat,
            standards(&table, true),
            CalibrationSource::Night,
            &CalibrationParams::default(),
        );
        let cal = cal.unwrap();
        let f = cal.for_filter("Ks").unwrap();
        let t = f.telescope.as_ref().expect("measured");
        assert!(
            (t.p_tel - TEL.p_tel).abs() < 1e-9 && (t.psi_tel_deg - TEL.psi_tel_deg).abs() < 1e-6,
            "{t:?}"
        );
        assert!(f.telescope_uncorrected.is_none());
        assert_truth(&cat, tol);
        assert_eq!(sum.n_telescope_uncorrected, 0);
        assert!(sum.lines.iter().any(|l| l.contains("p_tel = 0.600")), "{:?}", sum.lines);
        // Nothing flagged, so no line says something was.
        for flag in [
            FlagCode::TelescopeUncorrected,
            FlagCode::Uncalibrated,
            FlagCode::StokesMethodFailed,
        ]
        .map(FlagCode::name)
        {
            assert!(
                !sum.lines.iter().any(|l| l.contains(&format!("flagged '{flag}'"))),
                "{flag}: {:?}",
                sum.lines
            );
        }
        let a = &cat.targets[0].components[0];
        // The removed vector is the telescope's at the sequence's parallactic angles.
        let removed = a.telescope_qu.unwrap();
        let mid = TEL.at(etas.iter().sum::<f64>() / etas.len() as f64);
        assert!(
            (removed[0] - mid.q).abs() < 2e-4 && (removed[1] - mid.u).abs() < 2e-4,
            "{removed:?} vs {mid:?}"
        );
        // Its gradient: the least-squares fit of -dT/da over the orientations (equal
        // weights; the ratio method is the same to first order in F), computed here.
        let g = a.telescope_gradient.unwrap();
        let phis: Vec<f64> = posangs.iter().map(|p| p + THETA0).collect();
        let col = |phi: f64, eta: f64| {
            let (t, e) = (2.0 * phi.to_radians(), 2.0 * eta.to_radians());
            (t.cos(), t.sin(), -(e.cos() * t.cos() + e.sin() * t.sin()))
        };
        let (mut xx, mut xy, mut yy, mut xr, mut yr) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (&phi, &eta) in phis.iter().zip(&etas) {
            let (x, y, r) = col(phi, eta);
            (xx, xy, yy, xr, yr) = (xx + x * x, xy + x * y, yy + y * y, xr + x * r, yr + y * r);
        }
        let det = xx * yy - xy * xy;
        let want = [(yy * xr - xy * yr) / det, (xx * yr - xy * xr) / det];
        assert!(
            (g[0][0] - want[0]).abs() < 0.01 && (g[0][1] - want[1]).abs() < 0.01,
            "{g:?} vs {want:?}"
        );
        // The telescope's error enters Delta-gamma (it does not cancel like theta0).
        let t0 = &cat.targets[0];
        let with = t0.sigma_delta_gamma_deg.unwrap();
        let mut without = t0.clone();
        for c in &mut without.components {
            c.telescope_gradient = None;
        }
        without.update_delta_gamma(Some(&f.covariance_matrix()));
        assert!(
            with > without.sigma_delta_gamma_deg.unwrap(),
            "{with} vs {:?}",
            without.sigma_delta_gamma_deg
        );
        // calibration.json keeps it: another night's targets calibrated with it (--calib).
        let dir = tempfile::tempdir().unwrap();
        cal.write(dir.path()).unwrap();
        let back = Calibration::read(dir.path()).unwrap();
        assert_eq!(back.for_filter("Ks").unwrap().telescope, f.telescope);
        let mut other = science(&posangs, &[30.0, 33.0, 36.0, 39.0][..posangs.len()]);
        calibrate(
            &mut other,
            vec![],
            CalibrationSource::File(dir.path().into(), Box::new(back)),
            &CalibrationParams::default(),
        );
        assert_truth(&other, tol);
    }
}

#[test]
fn without_the_correction_the_components_are_flagged_and_biased() {
    let table = StandardsTable::builtin();
    let (posangs, etas) = ([0.0, 45.0], [-100.0, -97.0]);
    // Asked not to correct.
    let mut cat = science(&posangs, &etas);
    let params = CalibrationParams {
        no_telescope_correction: true,
        ..Default::default()
    };
    let (cal, sum) = calibrate(&mut cat, standards(&table, true), CalibrationSource::Night, &params);
    assert!(cal.unwrap().filters[0].telescope.is_none());
    assert_eq!(sum.n_telescope_uncorrected, 2);
    let a = &cat.targets[0].components[0];
    assert!(
        a.flags.iter().any(|f| f.is(FlagCode::TelescopeUncorrected)),
        "{:?}",
        a.flags
    );
    assert!((a.q - TRUTH_A.q).hypot(a.u - TRUTH_A.u) > 1e-3, "{a:?}");
    // Standards all at one parallactic angle: the term is fitted with the mirror's prior,
    // the reason the standards alone did not suffice in the calibration, every component
    // flagged and the summary saying so.
    let mut cat = science(&posangs, &etas);
    let (cal, sum) = calibrate(
        &mut cat,
        standards(&table, false),
        CalibrationSource::Night,
        &CalibrationParams::default(),
    );
    let f = cal.unwrap().filters[0].clone();
    assert!(f.telescope.is_some() && f.telescope_uncorrected.is_none(), "{f:?}");
    let why = f.telescope_from_prior.unwrap();
    assert!(why.contains("span"), "{why}");
    assert_eq!((sum.n_telescope_uncorrected, sum.n_telescope_from_prior), (0, 2));
    let said = format!("2 component(s) flagged '{}'", FlagCode::TelescopeFromPrior.name());
    assert!(sum.lines.iter().any(|l| l.starts_with(&said)), "{:?}", sum.lines);
    assert!(
        sum.lines.iter().any(|l| l.contains("FROM THE MIRROR'S PRIOR")),
        "{:?}",
        sum.lines
    );
    for c in &cat.targets[0].components {
        assert_eq!(c.calibration.unwrap().telescope, TermSource::Prior, "{c:?}");
    }
    // Asked not to correct: the term's expected size is carried in the errors (and in
    // Delta-gamma's), and said.
    let mut cat = science(&posangs, &etas);
    let (_, sum) = calibrate(&mut cat, standards(&table, true), CalibrationSource::Night, &params);
    let a = &cat.targets[0].components[0];
    assert_eq!(a.calibration.unwrap().telescope, TermSource::Carried);
    assert!(a.sigma_q > 0.005 && a.sigma_q_stat.unwrap() < 0.002, "{a:?}");
    assert!(
        sum.lines
            .iter()
            .any(|l| l.contains("telescope polarization not corrected") && l.contains("carried in every error")),
        "{:?}",
        sum.lines
    );
    // Targets without parallactic angles cannot be corrected even when the telescope is known.
    let mut cat = science(&posangs, &etas);
    for c in &mut cat.targets[0].components {
        for o in c.orientations.iter_mut().flatten() {
            o.parallactic_2eta = None;
        }
    }
    let (_, sum) = calibrate(
        &mut cat,
        standards(&table, true),
        CalibrationSource::Night,
        &CalibrationParams::default(),
    );
    assert_eq!(sum.n_telescope_uncorrected, 2);
}

#[test]
fn an_absurd_telescope_or_covariance_in_calibration_json_is_refused_by_key() {
    let table = StandardsTable::builtin();
    let mut cat = science(&[0.0, 45.0], &[-100.0, -97.0]);
    let (cal, _) = calibrate(
        &mut cat,
        standards(&table, true),
        CalibrationSource::Night,
        &CalibrationParams::default(),
    );
    let good = serde_json::to_value(cal.unwrap()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join(CALIBRATION_FILE);
    let read = |v: &serde_json::Value| {
        std::fs::write(&file, v.to_string()).unwrap();
        Calibration::read(&file).map(|_| ()).map_err(|e| e.to_string())
    };
    read(&good).unwrap();
    let cases: Vec<(&str, serde_json::Value, &str)> = vec![
        (
            "/filters/0/telescope/p_tel",
            5.0.into(),
            "filters[0].telescope.p_tel = 5",
        ),
        (
            "/filters/0/telescope/sigma_p_tel",
            (-1.0).into(),
            "filters[0].telescope.sigma_p_tel = -1",
        ),
        ("/filters/0/telescope/a", 0.1.into(), "disagrees with p_tel"),
        (
            "/filters/0/covariance/2/3",
            1.0.into(),
            "filters[0].covariance[2][3] = 1",
        ),
        (
            "/filters/0/covariance/0/0",
            (-1e-6).into(),
            "filters[0].covariance[0][0] = -0.000001",
        ),
        (
            "/filters/0/telescope/p_tel",
            serde_json::Value::Null,
            "filters[0].telescope.p_tel",
        ),
    ];
    for (path, value, want) in cases {
        let mut bad = good.clone();
        *bad.pointer_mut(path).unwrap() = value;
        let err = read(&bad).unwrap_err();
        assert!(
            err.contains(want) && err.contains(file.to_str().unwrap()),
            "{path}: {err}"
        );
    }
}
