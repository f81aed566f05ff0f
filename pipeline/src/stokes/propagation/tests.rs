//! The delta-method errors against Monte Carlo draws of the same covariance (drawn here,
//! independently of the module's own sampler), in conditions where every term matters:
//! unequal and correlated errors, q u != 0, a common offset that does not cancel.
use super::*;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

fn rng(seed: u64) -> rand::rngs::Xoshiro256PlusPlus {
    rand::rngs::Xoshiro256PlusPlus::seed_from_u64(seed)
}

/// A correlated Gaussian draw of (dq, du) with covariance `c`.
fn draw(c: &QuCovariance, r: &mut rand::rngs::Xoshiro256PlusPlus) -> (f64, f64) {
    let (z1, z2): (f64, f64) = (StandardNormal.sample(r), StandardNormal.sample(r));
    let l11 = c.var_q.sqrt();
    let l21 = c.cov_qu / l11;
    let l22 = (c.var_u - l21 * l21).sqrt();
    (l11 * z1, l21 * z1 + l22 * z2)
}

fn normal(r: &mut rand::rngs::Xoshiro256PlusPlus) -> f64 {
    StandardNormal.sample(r)
}

fn sd(v: &[f64]) -> f64 {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

/// Axial difference wrapped into [-90, 90).
fn wrap(d: f64) -> f64 {
    (d + 90.0).rem_euclid(180.0) - 90.0
}

/// Strongly correlated, unequal errors at S/N ~ 40: dropping the covariance term, or
/// flipping its sign, changes sigma_gamma by 30-60 % and sigma_P by 20-40 %.
const CASES: [(f64, f64, QuCovariance); 3] = [
    (
        0.03,
        0.02,
        QuCovariance {
            var_q: 1.0e-6,
            var_u: 0.64e-6,
            cov_qu: 0.6e-6,
        },
    ),
    (
        -0.02,
        0.03,
        QuCovariance {
            var_q: 0.49e-6,
            var_u: 1.0e-6,
            cov_qu: -0.55e-6,
        },
    ),
    (
        0.025,
        -0.025,
        QuCovariance {
            var_q: 0.9e-6,
            var_u: 0.4e-6,
            cov_qu: 0.5e-6,
        },
    ),
];

#[test]
fn sigma_p_and_sigma_gamma_are_the_scatter_of_draws_from_the_covariance() {
    let mut r = rng(22);
    for (q, u, c) in CASES {
        let n = 200_000;
        let (mut ps, mut gs) = (Vec::with_capacity(n), Vec::with_capacity(n));
        let g0 = 0.5 * u.atan2(q).to_degrees();
        for _ in 0..n {
            let (dq, du) = draw(&c, &mut r);
            ps.push((q + dq).hypot(u + du));
            gs.push(wrap(0.5 * (u + du).atan2(q + dq).to_degrees() - g0));
        }
        let (sp, sg) = (sigma_p(q, u, &c), sigma_gamma_deg(q, u, &c));
        assert!(
            (sp / sd(&ps) - 1.0).abs() < 0.02,
            "q {q} u {u}: sigma_P {sp} vs MC {}",
            sd(&ps)
        );
        assert!(
            (sg / sd(&gs) - 1.0).abs() < 0.02,
            "q {q} u {u}: sigma_gamma {sg} vs MC {}",
            sd(&gs)
        );
        // The covariance matters here: without it the formulas are off by > 10 %.
        let diag = QuCovariance { cov_qu: 0.0, ..c };
        assert!((sigma_p(q, u, &diag) / sp - 1.0).abs() > 0.1);
        assert!((sigma_gamma_deg(q, u, &diag) / sg - 1.0).abs() > 0.1);
    }
}

#[test]
fn the_calibration_covariance_is_the_scatter_of_correlated_c_and_theta0() {
    // (q, u) moved by d * dc and rotated by 2 dtheta0, with corr(c, theta0) = -0.7.
    let (q, u, d) = (0.03, -0.01, [-1.0, 0.35]);
    let (sc, st) = (4e-4, 2.5); // sigma_c, sigma_theta0 [deg]
    let cal = CalibrationErrors {
        var_c: sc * sc,
        var_theta0_deg2: st * st,
        cov_c_theta0_deg: -0.7 * sc * st,
    };
    let want = calibration_covariance(q, u, Some(d), &cal);
    let joint = QuCovariance {
        var_q: cal.var_c,
        var_u: cal.var_theta0_deg2,
        cov_qu: cal.cov_c_theta0_deg,
    };
    let mut r = rng(7);
    let n = 200_000;
    let (mut xs, mut ys) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        let (dc, dt) = draw(&joint, &mut r);
        let t = 2.0 * dt.to_radians();
        let (q1, u1) = (q + d[0] * dc, u + d[1] * dc);
        xs.push(q1 * t.cos() - u1 * t.sin());
        ys.push(q1 * t.sin() + u1 * t.cos());
    }
    let (mx, my) = (xs.iter().sum::<f64>() / n as f64, ys.iter().sum::<f64>() / n as f64);
    let cov = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum::<f64>() / (n - 1) as f64;
    let (vq, vu) = (sd(&xs).powi(2), sd(&ys).powi(2));
    assert!((want.var_q / vq - 1.0).abs() < 0.03, "{} vs {vq}", want.var_q);
    assert!((want.var_u / vu - 1.0).abs() < 0.03, "{} vs {vu}", want.var_u);
    assert!(
        (want.cov_qu - cov).abs() < 0.03 * (vq * vu).sqrt(),
        "{} vs {cov}",
        want.cov_qu
    );
    // theta0 is tangential: it adds nothing to sigma_P.
    let rot = CalibrationErrors {
        var_theta0_deg2: 9.0,
        ..Default::default()
    };
    let only_theta0 = calibration_covariance(q, u, Some(d), &rot);
    assert!(only_theta0.quadratic_form(p_gradient(q, u)) < 1e-20);
    assert!((sigma_gamma_deg(q, u, &only_theta0) - 3.0).abs() < 1e-9);
}

/// Two stars at different angles with a common offset whose contribution does not cancel.
fn binary() -> (StarQu, StarQu, f64) {
    let a = StarQu::with_offset_gradient(
        0.030,
        0.012,
        QuCovariance {
            var_q: 0.64e-6,
            var_u: 1.0e-6,
            cov_qu: 0.3e-6,
        },
        [-1.0, 0.0],
    );
    let b = StarQu::with_offset_gradient(
        -0.008,
        0.021,
        QuCovariance {
            var_q: 1.2e-6,
            var_u: 0.8e-6,
            cov_qu: -0.4e-6,
        },
        [-0.9, 0.2],
    );
    (a, b, (1.5e-3f64).powi(2))
}

#[test]
fn sigma_delta_gamma_is_the_scatter_of_draws_and_theta0_cancels() {
    let (a, b, var_c) = binary();
    let cal = offset_covariance(var_c);
    let want = sigma_delta_gamma_deg(&a, &b, &cal);
    // With a 5-deg zero-point error (correlated with c) in the calibration: unchanged.
    let mut with_theta0 = cal;
    with_theta0[CAL_THETA0][CAL_THETA0] = 25.0;
    with_theta0[CAL_C][CAL_THETA0] = -0.5 * 5.0 * var_c.sqrt();
    with_theta0[CAL_THETA0][CAL_C] = with_theta0[CAL_C][CAL_THETA0];
    assert!((sigma_delta_gamma_deg(&a, &b, &with_theta0) / want - 1.0).abs() < 1e-9);
    let mut r = rng(3);
    let n = 200_000;
    let d0 = 0.5 * (a.u.atan2(a.q) - b.u.atan2(b.q)).to_degrees();
    let mut ds = Vec::with_capacity(n);
    let mut ds_theta0 = Vec::with_capacity(n);
    for _ in 0..n {
        let (dqa, dua) = draw(&a.stat, &mut r);
        let (dqb, dub) = draw(&b.stat, &mut r);
        let dc = var_c.sqrt() * normal(&mut r);
        let (qa, ua) = (
            a.q + dqa + a.jacobian[CAL_C][0] * dc,
            a.u + dua + a.jacobian[CAL_C][1] * dc,
        );
        let (qb, ub) = (
            b.q + dqb + b.jacobian[CAL_C][0] * dc,
            b.u + dub + b.jacobian[CAL_C][1] * dc,
        );
        let d = wrap(0.5 * (ua.atan2(qa) - ub.atan2(qb)).to_degrees() - d0);
        ds.push(d);
        // A common zero-point error of 5 deg rotates both stars: the difference is unchanged.
        let t = 2.0 * (5.0 * normal(&mut r)).to_radians();
        let rot = |q: f64, u: f64| (q * t.cos() - u * t.sin(), q * t.sin() + u * t.cos());
        let ((qa2, ua2), (qb2, ub2)) = (rot(qa, ua), rot(qb, ub));
        ds_theta0.push(wrap(0.5 * (ua2.atan2(qa2) - ub2.atan2(qb2)).to_degrees() - d0));
    }
    assert!(
        (want / sd(&ds) - 1.0).abs() < 0.02,
        "delta method {want} vs MC {}",
        sd(&ds)
    );
    assert!(
        (want / sd(&ds_theta0) - 1.0).abs() < 0.02,
        "theta0 must cancel: {want} vs {}",
        sd(&ds_theta0)
    );
    // The offset's term is there and does not cancel (leaving it out is off by > 10 %).
    assert!((sigma_delta_gamma_deg(&a, &b, &offset_covariance(0.0)) / want - 1.0).abs() > 0.1);
    // The folded interval at this S/N is Delta-gamma +- sigma (the fold is far away).
    let iv = delta_gamma_interval_deg(&a, &b, &cal);
    let dg = d0.abs();
    assert!(
        ((iv[1] - iv[0]) / (2.0 * want) - 1.0).abs() < 0.05,
        "{iv:?} vs {dg} +- {want}"
    );
    assert!(((iv[0] + iv[1]) / 2.0 - dg).abs() < 0.1 * want, "{iv:?} vs {dg}");
}

#[test]
fn the_interval_is_skewed_near_zero_and_reproducible() {
    // Two stars 1 deg apart, each with a 4 deg angle error: the folded difference cannot be
    // negative, so the interval lies above 0 and is wider above the value than below.
    let s = QuCovariance {
        var_q: 1e-5,
        var_u: 1e-5,
        cov_qu: 0.0,
    };
    let a = StarQu::with_offset_gradient(0.045, 0.0, s, [0.0; 2]);
    let g = 2.0f64.to_radians();
    let b = StarQu::with_offset_gradient(0.045 * g.cos(), 0.045 * g.sin(), s, [0.0; 2]);
    let none = offset_covariance(0.0);
    let iv = delta_gamma_interval_deg(&a, &b, &none);
    assert!(
        iv[0] >= 0.0 && iv[0] < 1.0 && iv[1] > 1.0 + sigma_delta_gamma_deg(&a, &b, &none) * 0.9,
        "{iv:?}"
    );
    assert_eq!(iv, delta_gamma_interval_deg(&a, &b, &none));
    // Against a folded normal: with true difference 1 deg and sigma ~ 5.9 deg, |N(1, s)|'s
    // 15.87 % and 84.13 % quantiles, computed here by bisection on its CDF.
    let sig = sigma_delta_gamma_deg(&a, &b, &none);
    let cdf = |x: f64| {
        let phi = |z: f64| 0.5 * statrs::function::erf::erfc(-z / std::f64::consts::SQRT_2);
        phi((x - 1.0) / sig) - phi((-x - 1.0) / sig)
    };
    let quantile = |p: f64| {
        let (mut lo, mut hi) = (0.0, 90.0);
        for _ in 0..60 {
            let m = 0.5 * (lo + hi);
            if cdf(m) < p {
                lo = m
            } else {
                hi = m
            }
        }
        lo
    };
    let (lo, hi) = (quantile(0.158_655), quantile(0.841_345));
    assert!(
        (iv[0] - lo).abs() < 0.3 && (iv[1] - hi).abs() < 0.3,
        "{iv:?} vs folded normal [{lo}, {hi}]"
    );
}

/// The telescope's (a, b) subtracted from both stars at the mean parallactic angle eta:
/// `d(q, u)/da = -(cos 2eta, sin 2eta)`, `d(q, u)/db = (sin 2eta, -cos 2eta)`.
fn with_telescope(mut s: StarQu, eta_deg: f64) -> StarQu {
    let e = 2.0 * eta_deg.to_radians();
    s.jacobian[CAL_TEL_A] = [-e.cos(), -e.sin()];
    s.jacobian[CAL_TEL_B] = [e.sin(), -e.cos()];
    s
}

#[test]
fn the_telescope_term_is_common_to_both_stars_and_does_not_cancel() {
    // Two stars 40 deg apart; the telescope's (a, b) known to 0.3 % (correlated with c):
    // the delta method against the scatter of Delta-gamma over draws of the whole
    // calibration, each moving both stars by their Jacobians.
    let (a, b, var_c) = binary();
    let (a, b) = (with_telescope(a, -140.0), with_telescope(b, -140.0));
    let mut cal = offset_covariance(var_c);
    let st = 3.0e-3;
    cal[CAL_TEL_A][CAL_TEL_A] = st * st;
    cal[CAL_TEL_B][CAL_TEL_B] = 0.7 * st * st;
    cal[CAL_TEL_A][CAL_TEL_B] = 0.2 * st * st;
    cal[CAL_TEL_B][CAL_TEL_A] = 0.2 * st * st;
    cal[CAL_C][CAL_TEL_A] = -0.6 * st * var_c.sqrt();
    cal[CAL_TEL_A][CAL_C] = cal[CAL_C][CAL_TEL_A];
    let want = sigma_delta_gamma_deg(&a, &b, &cal);
    let without = sigma_delta_gamma_deg(&a, &b, &offset_covariance(var_c));
    assert!(want > 1.1 * without, "{want} vs {without} without the telescope");
    let l = cholesky_psd(&cal);
    let mut r = rng(11);
    let d0 = 0.5 * (a.u.atan2(a.q) - b.u.atan2(b.q)).to_degrees();
    let ds: Vec<f64> = (0..200_000)
        .map(|_| {
            let (dqa, dua) = draw(&a.stat, &mut r);
            let (dqb, dub) = draw(&b.stat, &mut r);
            let z: [f64; 4] = std::array::from_fn(|_| normal(&mut r));
            let t: [f64; 4] = std::array::from_fn(|i| (0..=i).map(|k| l[i][k] * z[k]).sum());
            let mv = |s: &StarQu, i: usize| (0..4).map(|k| s.jacobian[k][i] * t[k]).sum::<f64>();
            let (qa, ua) = (a.q + dqa + mv(&a, 0), a.u + dua + mv(&a, 1));
            let (qb, ub) = (b.q + dqb + mv(&b, 0), b.u + dub + mv(&b, 1));
            wrap(0.5 * (ua.atan2(qa) - ub.atan2(qb)).to_degrees() - d0)
        })
        .collect();
    assert!(
        (want / sd(&ds) - 1.0).abs() < 0.02,
        "delta method {want} vs MC {}",
        sd(&ds)
    );
    // The interval carries the same term.
    let iv = delta_gamma_interval_deg(&a, &b, &cal);
    assert!(
        ((iv[1] - iv[0]) / (2.0 * want) - 1.0).abs() < 0.05,
        "{iv:?} vs +- {want}"
    );
}

#[test]
fn cholesky_of_a_calibration_without_some_parameters_reproduces_it() {
    let mut m = offset_covariance(4e-6);
    m[CAL_TEL_A][CAL_TEL_A] = 1e-6;
    m[CAL_TEL_B][CAL_TEL_B] = 2e-6;
    m[CAL_TEL_A][CAL_TEL_B] = 0.5e-6;
    m[CAL_TEL_B][CAL_TEL_A] = 0.5e-6;
    m[CAL_C][CAL_TEL_B] = -1e-6;
    m[CAL_TEL_B][CAL_C] = -1e-6;
    let l = cholesky_psd(&m);
    for i in 0..4 {
        for j in 0..4 {
            let llt: f64 = (0..4).map(|k| l[i][k] * l[j][k]).sum();
            assert!((llt - m[i][j]).abs() < 1e-18, "{i}{j}: {llt} vs {}", m[i][j]);
        }
    }
}
