use super::*;
use crate::stokes::calibration::OrientationF;
use crate::stokes::model::{normalized_difference, Polarization};
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;

/// A standard whose F follows the model exactly: table values = truth.
fn standard(pol: Polarization, posangs: &[f64], theta0: f64, parity: i32, c: f64, sigma_f: f64) -> StandardObservation {
    let polarized = pol.p() > 0.0;
    StandardObservation {
        name: "S".into(),
        posang_deg: posangs.to_vec(),
        f: posangs
            .iter()
            .map(|&pa| OrientationF {
                analyzer_deg: f64::NAN,
                f: normalized_difference(pol, parity as f64 * pa + theta0) + c,
                sigma_f,
            })
            .collect(),
        p: pol.p(),
        sigma_p: if polarized { 0.1 * pol.p() } else { 0.0005 },
        gamma_deg: pol.gamma_deg(),
        sigma_gamma_deg: 1.0,
        parallactic_2eta: vec![],
    }
}

const TWO: [f64; 2] = [0.0, 45.0];
const FOUR: [f64; 4] = [0.0, 45.0, 90.0, 135.0];

fn axial_diff(a: f64, b: f64) -> f64 {
    (a - b + 90.0).rem_euclid(180.0) - 90.0
}

#[test]
fn noiseless_standards_give_c_and_theta0_exactly_in_every_separable_geometry() {
    let p1 = Polarization::from_p_gamma(0.025, 40.0);
    let p2 = Polarization::from_p_gamma(0.02, 100.0);
    for parity in [1, -1] {
        for (theta0, c) in [(3.0, 0.0167), (171.5, -0.021)] {
            let sets: Vec<(&str, Vec<StandardObservation>)> = vec![
                (
                    "unpolarized + two polarized, 0/45",
                    vec![
                        standard(Polarization::default(), &TWO, theta0, parity, c, 3e-4),
                        standard(p1, &TWO, theta0, parity, c, 3e-4),
                        standard(p2, &TWO, theta0, parity, c, 3e-4),
                    ],
                ),
                (
                    "two polarized, 0/45",
                    vec![
                        standard(p1, &TWO, theta0, parity, c, 3e-4),
                        standard(p2, &TWO, theta0, parity, c, 3e-4),
                    ],
                ),
                (
                    "one polarized, 4 orientations",
                    vec![standard(p1, &FOUR, theta0, parity, c, 3e-4)],
                ),
            ];
            for (what, stds) in sets {
                // The profile's parity is the truth where it cannot be measured.
                let j = fit_joint(&stds, parity).unwrap();
                assert!(j.incomplete.is_none(), "{what}: {:?}", j.incomplete);
                let (o, a) = (j.offset.unwrap(), j.angles.unwrap());
                assert!((o.c - c).abs() < 1e-12, "{what} parity {parity}: c {} vs {c}", o.c);
                assert!(
                    axial_diff(a.theta0_deg, theta0).abs() < 1e-9,
                    "{what} parity {parity}: theta0 {} vs {theta0}",
                    a.theta0_deg
                );
                assert_eq!(a.parity, parity, "{what}");
                assert!(j.chi2 < 1e-18, "{what}: chi2 {}", j.chi2);
                assert!(j.cov_c_theta0_deg.is_some() && o.sigma_c > 0.0 && a.sigma_theta0_deg > 0.0);
            }
        }
    }
}

#[test]
fn one_polarized_standard_at_two_orientations_cannot_separate_c_from_theta0() {
    let (theta0, c) = (3.0, 0.0167);
    let pol = Polarization::from_p_gamma(0.02, 40.0);
    let j = fit_joint(&[standard(pol, &TWO, theta0, 1, c, 3e-4)], 1).unwrap();
    let why = j.incomplete.as_deref().expect("incomplete");
    assert!(why.contains("cannot separate"), "{why}");
    assert!(j.angles.is_none() && j.offset.is_none() && j.cov_c_theta0_deg.is_none());
    // The same with an unpolarized standard added: c from it, theta0 from the polarized one.
    let j = fit_joint(
        &[
            standard(pol, &TWO, theta0, 1, c, 3e-4),
            standard(Polarization::default(), &TWO, theta0, 1, c, 3e-4),
        ],
        1,
    )
    .unwrap();
    assert!(j.incomplete.is_none(), "{:?}", j.incomplete);
    assert!((j.angles.unwrap().theta0_deg - theta0).abs() < 1e-9);
    // Unpolarized standards only: c, no angles, nothing incomplete.
    let j = fit_joint(&[standard(Polarization::default(), &TWO, theta0, 1, c, 3e-4)], 1).unwrap();
    assert!(j.incomplete.is_none() && j.angles.is_none());
    assert!((j.offset.unwrap().c - c).abs() < 1e-12);
}

/// Two polarized standards at the same angle and degree at 0/45 are one standard twice:
/// the data cannot separate c from theta0 (near-singular or two equal solutions).
#[test]
fn two_copies_of_one_polarized_standard_are_reported_incomplete() {
    let pol = Polarization::from_p_gamma(0.02, 40.0);
    let stds = vec![
        standard(pol, &TWO, 3.0, 1, 0.0167, 3e-4),
        standard(pol, &TWO, 3.0, 1, 0.0167, 3e-4),
    ];
    let j = fit_joint(&stds, 1).unwrap();
    assert!(j.incomplete.is_some(), "{j:?}");
    assert!(j.angles.is_none());
}

/// The covariance of (c, theta0) against the scatter of the estimates over noise draws:
/// the F of every orientation, the table values of the polarized standards (drawn about the
/// truth with their table errors) and the residual polarization of the unpolarized ones
/// (q, u ~ N(0, sigma_p^2/2)) all drawn anew. The reported covariance (inflation by
/// chi^2/dof divided out) must match within 5 % in each variance and 0.03 in the correlation.
#[test]
fn joint_covariance_matches_the_scatter_of_the_estimates() {
    let (theta0, c, parity) = (3.0, 0.0182, 1);
    let truth = [
        Polarization::default(),
        Polarization::default(),
        Polarization::from_p_gamma(0.025, 40.0),
        Polarization::from_p_gamma(0.02, 100.0),
    ];
    let sigma_f = 3e-4;
    let mut rng = rand::rngs::StdRng::seed_from_u64(20240611);
    let mut gauss = || -> f64 { rng.sample(StandardNormal) };
    let n = 6000;
    let (mut cs, mut ts) = (Vec::new(), Vec::new());
    let mut reported = None;
    for _ in 0..n {
        let stds: Vec<StandardObservation> = truth
            .iter()
            .map(|&t| {
                let mut s = standard(t, &TWO, theta0, parity, c, sigma_f);
                let actual = if t.p() > 0.0 {
                    // The table is off by its error; the star is the truth.
                    s.p = t.p() + s.sigma_p * gauss();
                    s.gamma_deg = t.gamma_deg() + s.sigma_gamma_deg * gauss();
                    t
                } else {
                    let k = s.sigma_p / 2f64.sqrt();
                    Polarization {
                        q: k * gauss(),
                        u: k * gauss(),
                    }
                };
                for (o, &pa) in s.f.iter_mut().zip(&s.posang_deg) {
                    o.f = normalized_difference(actual, parity as f64 * pa + theta0) + c + sigma_f * gauss();
                }
                s
            })
            .collect();
        let j = fit_joint(&stds, 1).unwrap();
        assert!(j.incomplete.is_none(), "{:?}", j.incomplete);
        let (o, a) = (j.offset.unwrap(), j.angles.unwrap());
        assert_eq!(a.parity, parity);
        cs.push(o.c);
        ts.push(theta0 + axial_diff(a.theta0_deg, theta0));
        if reported.is_none() {
            let k = inflation(j.chi2, j.dof);
            reported = Some((
                o.sigma_c.powi(2) / k,
                a.sigma_theta0_deg.powi(2) / k,
                j.cov_c_theta0_deg.unwrap() / k,
            ));
        }
    }
    let (vc, vt, cov) = reported.unwrap();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (mc, mt) = (mean(&cs), mean(&ts));
    let var = |v: &[f64], m: f64| v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64;
    let (sc, st) = (var(&cs, mc), var(&ts, mt));
    let sct = cs.iter().zip(&ts).map(|(a, b)| (a - mc) * (b - mt)).sum::<f64>() / (n - 1) as f64;
    let (corr_fit, corr_mc) = (cov / (vc * vt).sqrt(), sct / (sc * st).sqrt());
    eprintln!(
        "joint fit MC ({n} draws): var c {sc:.3e} vs {vc:.3e} ({:.3}); var theta0 {st:.4} vs {vt:.4} ({:.3}); \
         corr {corr_mc:.3} vs {corr_fit:.3}; mean c - truth {:.2e}, theta0 - truth {:.3} deg",
        sc / vc,
        st / vt,
        mc - c,
        mt - theta0
    );
    assert!((sc / vc - 1.0).abs() < 0.05, "var c: scatter {sc:e}, fit {vc:e}");
    assert!((st / vt - 1.0).abs() < 0.05, "var theta0: scatter {st}, fit {vt}");
    assert!(
        (corr_mc - corr_fit).abs() < 0.03,
        "corr: scatter {corr_mc}, fit {corr_fit}"
    );
    // Unbiased within the MC error.
    assert!((mc - c).abs() < 4.0 * (sc / n as f64).sqrt());
    assert!((mt - theta0).abs() < 4.0 * (st / n as f64).sqrt());
}

/// E[1/k] over chi^2 ~ chi^2_nu (what a pull's mean square is when the errors are honest
/// and k multiplies the variance): 1 - integral of pdf (1 - 1/k) by Simpson's rule (the
/// integrand vanishes where k = 1, so the infinite density of 1 dof at 0 does no harm).
fn mean_inverse_inflation(nu: usize) -> f64 {
    use statrs::distribution::{ChiSquared, Continuous};
    let d = ChiSquared::new(nu as f64).unwrap();
    let (hi, m) = (nu as f64 + 40.0 * (2.0 * nu as f64).sqrt() + 40.0, 200_000);
    let h = hi / m as f64;
    let f = |x: f64| {
        if x <= 0.0 {
            0.0
        } else {
            d.pdf(x) * (1.0 - 1.0 / inflation(x, nu))
        }
    };
    1.0 - (0..=m)
        .map(|i| {
            let w = if i == 0 || i == m {
                1.0
            } else if i % 2 == 1 {
                4.0
            } else {
                2.0
            };
            w * f(i as f64 * h)
        })
        .sum::<f64>()
        * h
        / 3.0
}

/// The inflation leaves a chi^2 its errors explain alone and scales an improbable one:
/// with honest errors the pulls' mean square E[1/k] is within 1 % of 1 for every dof,
/// and equals the closed form F_nu(a) + nu/(nu - 2) (1 - F_{nu-2}(a)) (a: the 99th
/// percentile). The former rule, k = max(1, chi^2/dof), gave E[1/k] = 0.85-0.91 for 2-20
/// dof (0.876 at the 6 dof of 5 standards at 0/45 with the telescope's term).
#[test]
fn the_inflation_leaves_honest_nights_alone() {
    use statrs::distribution::{ChiSquared, ContinuousCDF};
    for nu in 1..=30usize {
        let d = ChiSquared::new(nu as f64).unwrap();
        let a = d.inverse_cdf(1.0 - INFLATION_P);
        assert_eq!(inflation(nu as f64, nu), 1.0, "{nu} dof at chi^2 = dof");
        assert_eq!(inflation(0.999 * a, nu), 1.0, "{nu} dof just below the 99th percentile");
        let beyond = d.inverse_cdf(0.995);
        assert!(
            (inflation(beyond, nu) - beyond / nu as f64).abs() < 1e-12,
            "{nu} dof at the 99.5th percentile: {}",
            inflation(beyond, nu)
        );
        let e = mean_inverse_inflation(nu);
        assert!((0.99..=1.0 + 1e-6).contains(&e), "{nu} dof: E[1/k] = {e:.4}");
        if nu >= 3 {
            let lower = ChiSquared::new(nu as f64 - 2.0).unwrap();
            let closed = d.cdf(a) + nu as f64 / (nu as f64 - 2.0) * (1.0 - lower.cdf(a));
            assert!(
                (e - closed).abs() < 1e-4,
                "{nu} dof: quadrature {e:.6}, closed form {closed:.6}"
            );
        }
    }
    assert_eq!(inflation(5.0, 0), 1.0);
    assert_eq!(inflation(f64::NAN, 4), 1.0);
}
