use super::*;
use crate::stokes::model::{beam_fluxes, Polarization};

/// Noiseless F of the forward model with throughput ratio k and an additive
/// instrumental term.
fn f_of(pol: Polarization, phi: f64, k: f64, inst: f64) -> f64 {
    let (o, e) = beam_fluxes(1000.0, pol, phi, 1.0, k);
    (o - e) / (o + e) + inst
}

fn obs(pol: Polarization, phis: &[f64], k: f64, inst: f64) -> Vec<OrientationF> {
    phis.iter()
        .map(|&p| OrientationF {
            analyzer_deg: p,
            f: f_of(pol, p, k, inst),
            sigma_f: 0.001,
        })
        .collect()
}

#[test]
fn ratio_method_cancels_any_beam_ratio_exactly() {
    let pol = Polarization { q: 0.043, u: -0.021 };
    for k in [0.5, 0.9, 0.97, 1.0, 1.1, 2.0] {
        for phis in [
            vec![0.0, 45.0, 90.0, 135.0],
            vec![10.0, 55.0, 100.0, 145.0],
            vec![0.0, 22.5, 45.0, 67.5, 90.0, 112.5, 135.0, 157.5],
        ] {
            let s = solve(&obs(pol, &phis, k, 0.0), StokesMethod::Auto, None).unwrap();
            assert_eq!(s.method, StokesMethod::Ratio);
            assert!(!s.uncalibrated);
            assert!((s.fit.q - pol.q).abs() < 1e-14, "k {k}: q {}", s.fit.q);
            assert!((s.fit.u - pol.u).abs() < 1e-14, "k {k}: u {}", s.fit.u);
        }
    }
    // The textbook form: R_q^2 = (o0/e0)/(o90/e90), q = (R_q - 1)/(R_q + 1).
    let k = 0.93;
    let (o0, e0) = beam_fluxes(1.0, pol, 0.0, 1.0, k);
    let (o9, e9) = beam_fluxes(1.0, pol, 90.0, 1.0, k);
    let r = ((o0 / e0) / (o9 / e9)).sqrt();
    let a = OrientationF {
        analyzer_deg: 0.0,
        f: (o0 - e0) / (o0 + e0),
        sigma_f: 0.01,
    };
    let b = OrientationF {
        analyzer_deg: 90.0,
        f: (o9 - e9) / (o9 + e9),
        sigma_f: 0.01,
    };
    assert!((ratio_pair(&a, &b).0 - (r - 1.0) / (r + 1.0)).abs() < 1e-15);
}

#[test]
fn ratio_error_matches_a_numerical_derivative() {
    let a = OrientationF {
        analyzer_deg: 0.0,
        f: 0.12,
        sigma_f: 0.01,
    };
    let b = OrientationF {
        analyzer_deg: 90.0,
        f: -0.05,
        sigma_f: 0.02,
    };
    let h = 1e-6;
    let d = |da: f64, db: f64| ratio_pair(&OrientationF { f: a.f + da, ..a }, &OrientationF { f: b.f + db, ..b }).0;
    let ga = (d(h, 0.0) - d(-h, 0.0)) / (2.0 * h);
    let gb = (d(0.0, h) - d(0.0, -h)) / (2.0 * h);
    let s = ((ga * a.sigma_f).powi(2) + (gb * b.sigma_f).powi(2)).sqrt();
    assert!((ratio_pair(&a, &b).1 - s).abs() < 1e-9);
}

#[test]
fn difference_and_free_offset_cancel_a_constant_offset() {
    let pol = Polarization { q: -0.012, u: 0.034 };
    let phis = [0.0, 45.0, 90.0, 135.0];
    let o = obs(pol, &phis, 1.0, 0.0123);
    let d = solve(&o, StokesMethod::Difference, None).unwrap();
    assert!((d.fit.q - pol.q).abs() < 1e-15 && (d.fit.u - pol.u).abs() < 1e-15);
    // sigma_q = 1/2 sqrt(s0^2 + s90^2).
    assert!((d.fit.var_q.sqrt() - 0.5 * 2f64.sqrt() * 0.001).abs() < 1e-15);
    let f = solve(&o, StokesMethod::FreeOffset, None).unwrap();
    assert!((f.fit.q - pol.q).abs() < 1e-14 && (f.fit.u - pol.u).abs() < 1e-14);
    assert!((f.offset.unwrap().c - 0.0123).abs() < 1e-14);
    // Three unbalanced angles: the free offset still recovers everything exactly.
    let o3 = obs(pol, &[0.0, 60.0, 120.0], 1.0, -0.007);
    let (fit, off) = fit_qu_offset(&o3).unwrap();
    assert!((fit.q - pol.q).abs() < 1e-14 && (fit.u - pol.u).abs() < 1e-14 && (off.c + 0.007).abs() < 1e-14);
    // Two angles cannot hold three unknowns.
    assert!(fit_qu_offset(&obs(pol, &[0.0, 45.0], 1.0, 0.0)).is_none());
    assert!(solve(&obs(pol, &[0.0, 45.0], 1.0, 0.0), StokesMethod::Ratio, None).is_err());
}

#[test]
fn calibrated_least_squares_subtracts_the_offset_and_propagates_its_error() {
    let pol = Polarization { q: 0.02, u: 0.01 };
    let o = obs(pol, &[0.0, 45.0], 1.0, 0.005);
    let plain = solve(&o, StokesMethod::Auto, None).unwrap();
    assert!(plain.uncalibrated);
    assert!((plain.fit.q - 0.025).abs() < 1e-15);
    let off = Offset {
        c: 0.005,
        sigma_c: 0.0003,
    };
    let s = solve(&o, StokesMethod::Auto, Some(off)).unwrap();
    assert!(!s.uncalibrated && s.method == StokesMethod::LeastSquares);
    assert!((s.fit.q - pol.q).abs() < 1e-15 && (s.fit.u - pol.u).abs() < 1e-15);
    // Two orientations: q = F0 - c, u = F45 - c, so d(q, u)/dc = (-1, -1), the fit keeps the
    // measurement's Var q = s0^2, and with the offset's error Var q = s0^2 + sc^2, Cov = sc^2.
    let g = s.offset_gradient.unwrap();
    assert!((g[0] + 1.0).abs() < 1e-12 && (g[1] + 1.0).abs() < 1e-12, "{g:?}");
    assert!((s.fit.var_q - 1e-6).abs() < 1e-18 && s.fit.cov_qu.abs() < 1e-20);
    let total = s.fit_with_offset_error();
    assert!((total.var_q - (1e-6 + 9e-8)).abs() < 1e-18);
    assert!((total.cov_qu - 9e-8).abs() < 1e-18);
    // Balanced angles: the offset cancels in the least squares, its error too.
    let o4 = obs(pol, &[0.0, 45.0, 90.0, 135.0], 1.0, 0.005);
    let s4 = solve(&o4, StokesMethod::LeastSquares, Some(off)).unwrap();
    assert!((s4.fit.var_q - 0.5e-6).abs() < 1e-18);
    let g = s4.offset_gradient.unwrap();
    assert!(g[0].abs() < 1e-15 && g[1].abs() < 1e-15, "{g:?}");
}

/// Every method's name parses back to it (from `&str` and from `String`, as TOML and JSON
/// give it); other spellings are refused with the setting's key.
#[test]
fn method_names_round_trip_and_other_spellings_are_refused() {
    use StokesMethod::*;
    for m in [Auto, LeastSquares, FreeOffset, Difference, Ratio] {
        assert_eq!(m.name().parse::<StokesMethod>().unwrap(), m);
        let s = String::from(m);
        assert_eq!(s, m.name());
        assert_eq!(StokesMethod::try_from(s).unwrap(), m);
        assert_eq!(m.to_string(), m.name());
    }
    for bad in ["Ratio", "least-squares", "", "xyzzy"] {
        let e = bad.parse::<StokesMethod>().unwrap_err();
        assert_eq!(e.key, "calibration.stokes_method");
        assert!(e.value.contains(bad), "{e:?}");
        assert!(StokesMethod::try_from(bad.to_string()).is_err());
    }
}

/// Merging orientations by angle leaves out an F or an error that is not a number, an
/// infinite error, and a zero one, and averages the rest with inverse-variance weights.
#[test]
fn merging_orientations_skips_unusable_values() {
    let o = |phi: f64, f: f64, s: f64| OrientationF {
        analyzer_deg: phi,
        f,
        sigma_f: s,
    };
    let m = merged(&[
        o(0.0, 0.010, 1e-3),
        o(180.0, 0.013, 2e-3),
        o(0.0, f64::NAN, 1e-3),
        o(45.0, 0.02, f64::INFINITY),
        o(90.0, 0.03, f64::NAN),
        o(135.0, 0.04, 0.0),
    ]);
    assert_eq!(m.len(), 1, "{m:?}");
    let (w1, w2) = (1e6, 0.25e6);
    assert!((m[0].f - (0.010 * w1 + 0.013 * w2) / (w1 + w2)).abs() < 1e-15, "{m:?}");
    assert!((m[0].sigma_f - (w1 + w2).recip().sqrt()).abs() < 1e-15, "{m:?}");
}

/// Pairs for the difference and ratio methods need at least two pairs (four angles, 90 deg
/// apart two by two): one pair alone, an odd count or an angle without a partner gives none.
#[test]
fn balanced_pairs_need_two_full_pairs() {
    let pol = Polarization::from_p_gamma(0.03, 40.0);
    assert!(balanced_pairs(&obs(pol, &[0.0, 90.0], 1.0, 0.0)).is_none());
    assert!(balanced_pairs(&obs(pol, &[0.0, 45.0, 90.0], 1.0, 0.0)).is_none());
    assert!(balanced_pairs(&obs(pol, &[0.0, 45.0, 90.0, 135.0, 30.0], 1.0, 0.0)).is_none());
    assert!(balanced_pairs(&obs(pol, &[0.0, 45.0, 90.0, 120.0], 1.0, 0.0)).is_none());
    let pairs = balanced_pairs(&obs(pol, &[0.0, 45.0, 90.0, 135.0], 1.0, 0.0)).unwrap();
    let keys: Vec<(f64, f64)> = pairs.iter().map(|(a, b)| (a.analyzer_deg, b.analyzer_deg)).collect();
    assert_eq!(keys, vec![(0.0, 90.0), (45.0, 135.0)]);
}

/// The automatic choice without a calibration offset: three distinct angles without
/// balanced pairs fit the offset freely; two cannot and stay least squares (uncalibrated).
/// A method that needs pairs says how many distinct angles there are.
#[test]
fn auto_without_an_offset_fits_it_from_three_angles() {
    let pol = Polarization::from_p_gamma(0.03, 40.0);
    let three = obs(pol, &[0.0, 30.0, 60.0], 0.97, 0.002);
    let s = solve(&three, StokesMethod::Auto, None).unwrap();
    assert_eq!(s.method, StokesMethod::FreeOffset);
    assert!(!s.uncalibrated);
    let two = obs(pol, &[0.0, 45.0], 0.97, 0.002);
    let s = solve(&two, StokesMethod::Auto, None).unwrap();
    assert_eq!(s.method, StokesMethod::LeastSquares);
    assert!(s.uncalibrated);
    let e = solve(&three, StokesMethod::Ratio, None).unwrap_err().to_string();
    assert!(e.contains("3 distinct analyzer angle(s)"), "{e}");
}

/// The free-offset fit: q, u and c are linear in the F values, so their (co)variances
/// are sum_i g_i g_i' s_i^2 with g the response to a unit change of F_i, measured through
/// the fit itself. Four angles without pairs and unequal errors (weights matter).
#[test]
fn free_offset_covariance_is_the_propagated_one() {
    let phis = [0.0, 30.0, 70.0, 120.0];
    let fs = [0.031, 0.012, -0.02, 0.007];
    let ss = [0.002, 0.004, 0.001, 0.003];
    let o = |f: &[f64]| -> Vec<OrientationF> {
        phis.iter()
            .zip(f)
            .zip(&ss)
            .map(|((&p, &f), &s)| OrientationF {
                analyzer_deg: p,
                f,
                sigma_f: s,
            })
            .collect()
    };
    let (fit, off) = fit_qu_offset(&o(&fs)).unwrap();
    let (mut vq, mut vu, mut cqu, mut vc) = (0.0, 0.0, 0.0, 0.0);
    for i in 0..4 {
        let mut g = fs;
        g[i] += 1.0;
        let (m, mo) = fit_qu_offset(&o(&g)).unwrap();
        let (gq, gu, gc) = (m.q - fit.q, m.u - fit.u, mo.c - off.c);
        let v = ss[i] * ss[i];
        (vq, vu, cqu, vc) = (vq + gq * gq * v, vu + gu * gu * v, cqu + gq * gu * v, vc + gc * gc * v);
    }
    let close = |a: f64, b: f64| (a - b).abs() < 1e-8 * b.abs();
    assert!(close(fit.var_q, vq), "{} vs {vq}", fit.var_q);
    assert!(close(fit.var_u, vu), "{} vs {vu}", fit.var_u);
    assert!(close(fit.cov_qu, cqu), "{} vs {cqu}", fit.cov_qu);
    assert!(close(off.sigma_c, vc.sqrt()), "{} vs {}", off.sigma_c, vc.sqrt());
    // chi^2: the weighted residual sum, one degree of freedom here.
    let chi2: f64 = (0..4)
        .map(|i| {
            let t = 2.0 * phis[i].to_radians();
            ((fs[i] - fit.q * t.cos() - fit.u * t.sin() - off.c) / ss[i]).powi(2)
        })
        .sum();
    assert!(chi2 > 0.1 && close(fit.chi2, chi2), "{} vs {chi2}", fit.chi2);
}

/// The 3x3 inverse: times the matrix it is the identity (a general, non-symmetric
/// matrix, so that every cofactor counts); singular or all-zero matrices, and one whose
/// determinant is below 1e-10 of its scale cubed, have none.
#[test]
fn invert3_inverts_and_refuses_singular_matrices() {
    let a = [[4.0, -2.0, 1.0], [3.0, 6.0, -4.0], [2.0, 1.0, 8.0]];
    let inv = invert3(&a).unwrap();
    for (i, row) in inv.iter().enumerate() {
        for j in 0..3 {
            let prod: f64 = row.iter().zip(&a).map(|(x, arow)| x * arow[j]).sum();
            let want = if i == j { 1.0 } else { 0.0 };
            assert!((prod - want).abs() < 1e-14, "({i}, {j}): {prod}");
        }
    }
    assert!(invert3(&[[0.0; 3]; 3]).is_none());
    assert!(invert3(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [1.0, 0.0, 1.0]]).is_none());
    // det 0.01 at scale 1e3: relative 1e-11, refused; det 10 accepted.
    let diag = |d: f64| [[1e3, 0.0, 0.0], [0.0, 1e3, 0.0], [0.0, 0.0, d]];
    assert!(invert3(&diag(1e-8)).is_none());
    assert!(invert3(&diag(1e-5)).is_some());
}

/// The error of a subtracted offset c moves q and u along d(q, u)/dc: the fit with the
/// offset's error adds (dq/dc)^2 sigma_c^2 to var q, and so on, with the gradient measured
/// here by solving again with c + 1 (q, u are linear in c). Three angles without pairs, so
/// that the gradient is not (-1, -1).
#[test]
fn the_offset_error_adds_along_the_measured_gradient() {
    let pol = Polarization::from_p_gamma(0.03, 40.0);
    let o = obs(pol, &[0.0, 30.0, 70.0], 1.0, 0.01);
    let offset = Offset {
        c: 0.01,
        sigma_c: 0.003,
    };
    let s = solve(&o, StokesMethod::LeastSquares, Some(offset)).unwrap();
    let moved = solve(&o, StokesMethod::LeastSquares, Some(Offset { c: 1.01, ..offset })).unwrap();
    let (gq, gu) = (moved.fit.q - s.fit.q, moved.fit.u - s.fit.u);
    assert!((gq + 1.0).abs() > 0.05 && (gu + 1.0).abs() > 0.05, "({gq}, {gu})");
    let v = offset.sigma_c.powi(2);
    let full = s.fit_with_offset_error();
    let close = |a: f64, b: f64| (a - b).abs() < 1e-9 * b.abs();
    assert!(close(full.var_q, s.fit.var_q + gq * gq * v), "{full:?}");
    assert!(close(full.var_u, s.fit.var_u + gu * gu * v), "{full:?}");
    assert!(close(full.cov_qu, s.fit.cov_qu + gq * gu * v), "{full:?}");
}

/// A table star counts as polarized when p > 3 sigma_p strictly (as the cut): exactly 3
/// sigma is not; p = sigma is not.
#[test]
fn polarized_standards_are_more_than_three_sigma() {
    let star = |p: f64, sigma_p: f64| StandardObservation {
        name: "S".into(),
        posang_deg: vec![],
        f: vec![],
        p,
        sigma_p,
        gamma_deg: 0.0,
        sigma_gamma_deg: 1.0,
        parallactic_2eta: vec![],
    };
    assert!(star(3.5, 1.0).polarized());
    assert!(!star(3.0, 1.0).polarized());
    assert!(!star(0.01, 0.01).polarized());
    assert!(!star(0.0, 0.0).polarized());
}
