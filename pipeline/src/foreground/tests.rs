//! The foreground estimate against analytic values, a slow Monte Carlo of its covariance,
//! the pulls of its prediction at the binary over many simulated fields, the too-few
//! outcome, and the science: Delta-gamma of unaligned binaries behind a foreground, with
//! and without the subtraction.
use super::*;
use crate::catalog::{fold_delta_gamma, Component, Status};
use crate::stats::ks_uniform;
use crate::stokes::inversion::Polarization;
use crate::stokes::propagation::{
    delta_gamma_interval_with_foreground_deg, sigma_delta_gamma_deg, sigma_delta_gamma_with_foreground_deg, StarQu,
};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

type Rng64 = rand::rngs::Xoshiro256PlusPlus;

fn gauss(rng: &mut Rng64) -> f64 {
    StandardNormal.sample(rng)
}

/// The binary's place in every simulated field.
const RA: f64 = 83.8;
const DEC: f64 = -5.4;

fn star(id: usize, q: f64, u: f64, sigma: f64) -> FieldStarQu {
    FieldStarQu {
        id: format!("f{id}"),
        q,
        u,
        sigma_q: sigma,
        sigma_u: sigma,
        cov_qu: 0.0,
        ra_deg: RA + 0.01 * (id as f64 % 7.0 - 3.0),
        dec_deg: DEC + 0.01 * (id as f64 % 5.0 - 2.0),
        usable: true,
    }
}

fn estimated(o: Outcome) -> ForegroundEstimate {
    match o {
        Outcome::Estimated(e) => *e,
        other => panic!("no estimate: {other:?}"),
    }
}

/// Equal errors and no dispersion (assumed: [`Dispersion::None`]): the plain mean and
/// sigma^2/n for both the mean's and the prediction's variance.
#[test]
fn equal_errors_and_no_dispersion_give_the_plain_mean_and_sigma_over_sqrt_n() {
    let sigma = 0.005;
    let offsets = [0.1, -0.2, 0.05, 0.3, -0.15, 0.0, 0.2, -0.25, -0.05];
    let stars: Vec<FieldStarQu> = offsets
        .iter()
        .enumerate()
        .map(|(i, d)| star(i, 0.012 + d * sigma, -0.004 - 0.5 * d * sigma, sigma))
        .collect();
    let fixed = EstimateParams {
        dispersion: Dispersion::None,
        ..EstimateParams::default()
    };
    let e = estimated(estimate(RA, DEC, &stars, &fixed));
    let n = stars.len() as f64;
    let mean_q = stars.iter().map(|s| s.q).sum::<f64>() / n;
    let mean_u = stars.iter().map(|s| s.u).sum::<f64>() / n;
    assert!((e.q - mean_q).abs() < 1e-15 && (e.u - mean_u).abs() < 1e-15, "{e:?}");
    assert_eq!(e.tau, [0.0, 0.0]);
    for v in [e.cov.var_q, e.cov.var_u, e.cov_mean.var_q] {
        assert!((v / (sigma * sigma / n) - 1.0).abs() < 1e-12, "{v}");
    }
    assert_eq!(e.cov.cov_qu, 0.0);
    assert_eq!((e.used.len(), e.rejected.len()), (9, 0));
    let f = e.to_catalog();
    assert!((f.sigma_q - sigma / 3.0).abs() < 1e-15);
    assert_eq!(f.n_used, Some(9));
    f.validate().unwrap();
    // Dispersion estimated: the random-effects prediction is still the plain mean (equal
    // weights whatever tau), with the variance E[sigma^2/n + tau^2 (1 + 1/n)] >= sigma^2/n;
    // the kriging's (weights by place) is within its error of it and never more precise
    // than the stars' own noise allows.
    let e = estimated(estimate(RA, DEC, &stars, &EstimateParams::default()));
    let ([rq, ru], rc) = e.random_effects;
    assert!((rq - mean_q).abs() < 1e-15 && (ru - mean_u).abs() < 1e-15, "{e:?}");
    let t2 = e.tau[0].powi(2);
    assert!(t2 > 0.0);
    assert!((rc.var_q - (sigma * sigma / n + t2 * (1.0 + 1.0 / n))).abs() < 1e-9 * rc.var_q);
    assert!((e.q - mean_q).abs() < 2.0 * e.cov.var_q.sqrt(), "{} vs {mean_q}", e.q);
    assert!(
        e.cov.var_q >= sigma * sigma / n && e.cov.var_u >= sigma * sigma / n,
        "{:?}",
        e.cov
    );
}

/// The posterior of tau against a slow reference for equal errors, where the restricted
/// likelihood is `(sigma^2 + t)^-(n-1)/2 exp(-(n-1) s^2 / 2(sigma^2 + t))` (s^2 the
/// sample variance), integrated on a fine uniform grid of tau far into its tail.
#[test]
fn the_posterior_of_tau_matches_a_slow_integration() {
    let sigma2: f64 = 1e-5;
    for y in [
        vec![0.010, 0.018, 0.004, 0.022, 0.013, 0.007, 0.016],
        vec![0.010, 0.011, 0.009, 0.0105, 0.0095],
        vec![0.0, 0.03, -0.02, 0.01, 0.05, -0.04, 0.02, 0.0, 0.01, 0.015],
    ] {
        let n = y.len() as f64;
        let m = y.iter().sum::<f64>() / n;
        let s2 = y.iter().map(|y| (y - m).powi(2)).sum::<f64>() / (n - 1.0);
        let logl = |t: f64| -0.5 * (n - 1.0) * (sigma2 + t).ln() - 0.5 * (n - 1.0) * s2 / (sigma2 + t);
        let (mut z, mut et2) = (0.0, 0.0);
        let (steps, top) = (2_000_000, 3.0);
        let h = top / steps as f64;
        for i in 0..=steps {
            let tau = i as f64 * h;
            let w = if i == 0 || i == steps { 0.5 } else { 1.0 };
            let p = w * (logl(tau * tau) - logl(0.0)).exp();
            z += p;
            et2 += p * tau * tau;
        }
        let want = et2 / z;
        let v = vec![sigma2; y.len()];
        let got = tau_posterior(&y, &v, f64::INFINITY);
        eprintln!("n = {n}: E[tau^2] {got:?} slow {want:.4e}");
        assert!((got.tau2 / want - 1.0).abs() < 0.01, "{} vs {want}", got.tau2);
        assert!((got.var_mean / ((sigma2 + want) / n) - 1.0).abs() < 0.01);
        // The same likelihood in its general form, up to a constant.
        let (t1, t2) = (1e-5, 4e-4);
        let d = reml_log_likelihood(&y, &v, t1) - reml_log_likelihood(&y, &v, t2);
        assert!((d - (logl(t1) - logl(t2))).abs() < 1e-9, "{d}");
    }
}

/// A field of given stars (unequal, correlated errors) drawn again and again, with the
/// covariances the estimate reports (means over the draws) against the scatter of the
/// draws, within 8 % (12 % for the error of the field's mean when tau is estimated): (1) no dispersion, assumed and true: the scatter of the estimated
/// mean is `(sum W_j)^-1`; (2) the dispersion estimated, the true tau of q and u drawn for
/// each field uniformly within the prior's range: the scatter of the prediction error at
/// the binary is the random-effects prediction covariance, and that of the field's mean the
/// reported error of the mean.
#[test]
fn the_covariance_matches_a_slow_monte_carlo() {
    let mut rng = Rng64::seed_from_u64(11);
    let n = 16;
    let sig: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            let s = 0.001 * (1.0 + 19.0 * (i as f64 / (n - 1) as f64).powi(2));
            let (sq, su) = (s, 1.3 * s);
            [sq, su, 0.4 * sq * su * if i % 3 == 0 { -1.0 } else { 1.0 }]
        })
        .collect();
    let f = [0.015, -0.007];
    let draws = 6000;
    for (dispersion, tau_max) in [
        (Dispersion::None, 0.0),
        (Dispersion::Estimated { tau_max: TAU_PRIOR_MAX }, TAU_PRIOR_MAX),
    ] {
        let params = EstimateParams {
            dispersion,
            ..EstimateParams::default()
        };
        let (mut err_mean, mut err_pred) = (Vec::new(), Vec::new());
        let (mut rep_mean, mut rep_pred) = ([0.0; 3], [0.0; 3]);
        for _ in 0..draws {
            let tau = [tau_max * rng.random::<f64>(), tau_max * rng.random::<f64>()];
            let stars: Vec<FieldStarQu> = (0..n)
                .map(|i| {
                    let [sq, su, c] = sig[i];
                    // Correlated noise: Cholesky of [[sq^2, c], [c, su^2]].
                    let (z1, z2) = (gauss(&mut rng), gauss(&mut rng));
                    let l21 = c / sq;
                    let l22 = (su * su - l21 * l21).sqrt();
                    let mut s = star(i, 0.0, 0.0, sq);
                    s.sigma_u = su;
                    s.cov_qu = c;
                    s.q = f[0] + tau[0] * gauss(&mut rng) + sq * z1;
                    s.u = f[1] + tau[1] * gauss(&mut rng) + l21 * z1 + l22 * z2;
                    s
                })
                .collect();
            let e = estimated(estimate(RA, DEC, &stars, &params));
            let fb = [f[0] + tau[0] * gauss(&mut rng), f[1] + tau[1] * gauss(&mut rng)];
            let m = e.random_effects.0;
            err_mean.push([m[0] - f[0], m[1] - f[1]]);
            err_pred.push([fb[0] - m[0], fb[1] - m[1]]);
            for (acc, c) in [(&mut rep_mean, e.cov_mean), (&mut rep_pred, e.random_effects.1)] {
                acc[0] += c.var_q / draws as f64;
                acc[1] += c.cov_qu / draws as f64;
                acc[2] += c.var_u / draws as f64;
            }
        }
        let cov = |e: &[[f64; 2]]| {
            let m = e.len() as f64;
            let mq = e.iter().map(|x| x[0]).sum::<f64>() / m;
            let mu = e.iter().map(|x| x[1]).sum::<f64>() / m;
            [
                e.iter().map(|x| (x[0] - mq).powi(2)).sum::<f64>() / (m - 1.0),
                e.iter().map(|x| (x[0] - mq) * (x[1] - mu)).sum::<f64>() / (m - 1.0),
                e.iter().map(|x| (x[1] - mu).powi(2)).sum::<f64>() / (m - 1.0),
            ]
        };
        let (mc_mean, mc_pred) = (cov(&err_mean), cov(&err_pred));
        eprintln!("{dispersion:?}: mean: monte carlo {mc_mean:?}, reported {rep_mean:?}");
        eprintln!("{dispersion:?}: prediction: monte carlo {mc_pred:?}, reported {rep_pred:?}");
        // The error of the field's mean alone is looser when tau is estimated (measured:
        // 9 % low for q); the prediction at the binary, what is used, is within 8 %.
        let tol_mean = if tau_max > 0.0 { 0.12 } else { 0.08 };
        for (mc, rep, tol) in [(mc_mean, rep_mean, tol_mean), (mc_pred, rep_pred, 0.08)] {
            assert!((rep[0] / mc[0] - 1.0).abs() < tol, "var q: {} vs {}", rep[0], mc[0]);
            assert!((rep[2] / mc[2] - 1.0).abs() < tol, "var u: {} vs {}", rep[2], mc[2]);
            // The correlation is small: compare on the scale of the variances.
            assert!(
                (rep[1] - mc[1]).abs() < 0.08 * (mc[0] * mc[2]).sqrt(),
                "cov: {} vs {}",
                rep[1],
                mc[1]
            );
        }
    }
}

/// How the foreground varies over a simulated field.
#[derive(Clone, Copy, Debug)]
enum Variation {
    /// Each place an independent draw of N(0, tau^2) per q and u.
    Random,
    /// A linear gradient across the field (amplitude up to tau at 2.5 arcmin), the binary at
    /// the centre.
    Gradient,
}

/// One simulated field: (stars, the true foreground at the binary, the outliers' ids).
/// The mean foreground's degree is uniform in `p_range`, tau of q and u each uniform in
/// [0, `tau_max`].
fn simulate_field(
    rng: &mut Rng64,
    variation: Variation,
    p_range: [f64; 2],
    tau_max: f64,
) -> (Vec<FieldStarQu>, [f64; 2], Vec<String>) {
    simulate_field_with(rng, variation, p_range, tau_max, [0.10, 0.20])
}

fn simulate_field_with(
    rng: &mut Rng64,
    variation: Variation,
    p_range: [f64; 2],
    tau_max: f64,
    outlier_range: [f64; 2],
) -> (Vec<FieldStarQu>, [f64; 2], Vec<String>) {
    let n = rng.random_range(8..=30usize);
    let p_fg = p_range[0] + (p_range[1] - p_range[0]) * rng.random::<f64>();
    let ang = std::f64::consts::PI * rng.random::<f64>();
    let mean = [p_fg * (2.0 * ang).cos(), p_fg * (2.0 * ang).sin()];
    let tau = [tau_max * rng.random::<f64>(), tau_max * rng.random::<f64>()];
    let outlier_fraction = outlier_range[0] + (outlier_range[1] - outlier_range[0]) * rng.random::<f64>();
    let grad: [[f64; 2]; 2] = std::array::from_fn(|_| std::array::from_fn(|_| gauss(rng)));
    let fg_at = |rng: &mut Rng64, x: [f64; 2]| -> [f64; 2] {
        match variation {
            Variation::Random => [mean[0] + tau[0] * gauss(rng), mean[1] + tau[1] * gauss(rng)],
            // x in units of 2.5 arcmin; the gradient's rms over the field about tau.
            Variation::Gradient => std::array::from_fn(|k| mean[k] + tau[k] * (grad[k][0] * x[0] + grad[k][1] * x[1])),
        }
    };
    let mut outliers = Vec::new();
    let stars = (0..n)
        .map(|i| {
            let x = [rng.random::<f64>() * 2.0 - 1.0, rng.random::<f64>() * 2.0 - 1.0];
            let f = fg_at(rng, x);
            let sigma = 0.001 * 20f64.powf(rng.random::<f64>());
            let mut y = [f[0] + sigma * gauss(rng), f[1] + sigma * gauss(rng)];
            let id = format!("f{i}");
            if rng.random::<f64>() < outlier_fraction {
                let p = 0.01 + 0.05 * rng.random::<f64>();
                let a = std::f64::consts::PI * rng.random::<f64>();
                y[0] += p * (2.0 * a).cos();
                y[1] += p * (2.0 * a).sin();
                outliers.push(id.clone());
            }
            let dec = DEC + x[1] * 2.5 / 60.0;
            FieldStarQu {
                id,
                q: y[0],
                u: y[1],
                sigma_q: sigma,
                sigma_u: sigma,
                cov_qu: 0.0,
                ra_deg: RA + x[0] * 2.5 / 60.0 / DEC.to_radians().cos(),
                dec_deg: dec,
                usable: true,
            }
        })
        .collect();
    (stars, fg_at(rng, [0.0, 0.0]), outliers)
}

/// Pull statistics of the prediction at the binary over simulated fields: (rms of the
/// pulls of q and u pooled, count, fraction of outliers rejected, fraction of good stars
/// rejected, fields with too few).
fn pulls(seed: u64, fields: usize, variation: Variation) -> (f64, usize, f64, f64, usize) {
    let mut rng = Rng64::seed_from_u64(seed);
    let (mut ss, mut n) = (0.0, 0usize);
    let (mut out_total, mut out_rej, mut good_total, mut good_rej, mut too_few) = (0, 0, 0, 0, 0);
    for _ in 0..fields {
        let (stars, fb, outliers) = simulate_field(&mut rng, variation, [0.0, 0.03], 0.005);
        match estimate(RA, DEC, &stars, &EstimateParams::default()) {
            Outcome::Estimated(e) => {
                ss += (fb[0] - e.q).powi(2) / e.cov.var_q + (fb[1] - e.u).powi(2) / e.cov.var_u;
                n += 2;
                for s in &stars {
                    let rejected = e.rejected.iter().any(|(id, _)| id == &s.id);
                    if outliers.contains(&s.id) {
                        out_total += 1;
                        out_rej += usize::from(rejected);
                    } else {
                        good_total += 1;
                        good_rej += usize::from(rejected);
                    }
                }
            }
            Outcome::TooFew { .. } => too_few += 1,
        }
    }
    (
        (ss / n as f64).sqrt(),
        n,
        out_rej as f64 / out_total as f64,
        good_rej as f64 / good_total as f64,
        too_few,
    )
}

/// Fields of 8-30 stars, noise 0.1-2 %, a foreground of 0-3 % varying by tau 0-0.5 % from
/// place to place, 10-20 % intrinsically polarized stars (1-6 %): the pulls of the
/// foreground predicted at the binary, pooled over q and u and 3000 fields, have an rms in
/// [0.9, 1.1]; with a smooth gradient instead of random variation (binary at the centre)
/// the covariance is conservative (rms < 1).
#[test]
fn pulls_of_the_foreground_at_the_binary_have_unit_rms_over_random_fields() {
    let (rms, n, out_rej, good_rej, too_few) = pulls(2026, 3000, Variation::Random);
    eprintln!(
        "random variation: pull rms {rms:.3} over {n} pulls; outliers rejected {:.1} %, good stars rejected {:.2} %, too few {too_few}",
        100.0 * out_rej,
        100.0 * good_rej
    );
    assert!((0.9..=1.1).contains(&rms), "pull rms {rms}");
    assert!(out_rej > 0.5, "{out_rej}");
    assert!(good_rej < 0.02, "{good_rej}");
    let (rms_g, n_g, ..) = pulls(7, 2000, Variation::Gradient);
    eprintln!("gradient: pull rms {rms_g:.3} over {n_g} pulls");
    assert!(rms_g < 1.0, "gradient pull rms {rms_g}");
}

/// Fewer than 5 usable stars: no estimate, each rejection with its reason; 2 of 6 stars
/// far off (intrinsically polarized) leave 4: too few as well.
#[test]
fn too_few_field_stars_give_no_estimate_with_the_reasons() {
    let mut stars: Vec<FieldStarQu> = (0..4).map(|i| star(i, 0.01, 0.0, 0.002)).collect();
    let mut flagged = star(4, 0.01, 0.0, 0.002);
    flagged.usable = false;
    let mut broken = star(5, 0.01, 0.0, 0.0);
    broken.sigma_u = f64::NAN;
    stars.extend([flagged, broken]);
    match estimate(RA, DEC, &stars, &EstimateParams::default()) {
        Outcome::TooFew {
            n_left,
            minimum,
            rejected,
        } => {
            assert_eq!((n_left, minimum), (4, MIN_FIELD_STARS));
            assert_eq!(
                rejected,
                vec![
                    ("f4".to_string(), Rejection::NotUsable),
                    ("f5".to_string(), Rejection::InvalidMeasurement)
                ]
            );
        }
        other => panic!("{other:?}"),
    }
    let mut six: Vec<FieldStarQu> = [0.0, 0.001, -0.001, 0.0005]
        .iter()
        .enumerate()
        .map(|(i, d)| star(i, 0.01 + d, 0.0, 0.002))
        .collect();
    six.push(star(4, 0.08, 0.03, 0.002));
    six.push(star(5, -0.05, 0.06, 0.002));
    match estimate(RA, DEC, &six, &EstimateParams::default()) {
        Outcome::TooFew { n_left, rejected, .. } => {
            assert_eq!(n_left, 4);
            assert_eq!(rejected.len(), 2);
            assert!(rejected
                .iter()
                .all(|(_, r)| matches!(r, Rejection::Outlier { chi2, .. } if *chi2 > 100.0)));
        }
        other => panic!("{other:?}"),
    }
    // A seventh good star makes 5: an estimate, the two outliers named.
    six.push(star(6, 0.0102, 0.0, 0.002));
    let e = estimated(estimate(RA, DEC, &six, &EstimateParams::default()));
    assert_eq!(e.used.len(), 5);
    let ids: Vec<&str> = e.rejected.iter().map(|(id, _)| id.as_str()).collect();
    assert_eq!(ids, ["f4", "f5"]);
    assert!(
        e.rejected[0].1.to_string().starts_with("outlier: chi2 = "),
        "{}",
        e.rejected[0].1
    );
    // The distance limit.
    let far = EstimateParams {
        max_separation_arcmin: Some(0.5),
        ..EstimateParams::default()
    };
    match estimate(RA + 1.0, DEC, &six, &far) {
        Outcome::TooFew {
            n_left: 0, rejected, ..
        } => {
            assert!(rejected.iter().all(|(_, r)| matches!(r, Rejection::TooFar { .. })));
        }
        other => panic!("{other:?}"),
    }
}

fn component(name: &str, q: f64, u: f64, sigma: f64) -> Component {
    let p = q.hypot(u);
    let mut c = Component::new(
        name,
        Polarization {
            q,
            u,
            sigma_q: sigma,
            sigma_u: sigma,
            p,
            sigma_p: sigma,
            p_debiased: p,
            gamma_deg: (0.5 * u.atan2(q).to_degrees()).rem_euclid(180.0),
            sigma_gamma_deg: 28.65 * sigma / p,
        },
    );
    c.passes_cut = true;
    c
}

/// The one call: the target's foreground set from its stars, the subtracted Delta-gamma
/// computed; too few stars: foreground cleared, flag set (and removed again once there
/// are enough); no position: nothing done.
#[test]
fn set_target_foreground_fills_the_catalog_and_the_corrected_delta_gamma() {
    let fg = [0.02, 0.0];
    let mut t = Target::new("B1", Status::Ok);
    t.components = vec![
        component("A", fg[0] + 0.01, fg[1] + 0.0, 0.0005),
        component("B", fg[0] + 0.0, fg[1] + 0.01, 0.0005),
    ];
    t.update_delta_gamma(None);
    assert!(t.delta_gamma_fg_corrected_deg.is_none());
    let before = t.delta_gamma_deg.unwrap();
    let offsets = [0.1, -0.2, 0.05, 0.3, -0.15, 0.0, 0.2, -0.25];
    let stars: Vec<FieldStarQu> = offsets
        .iter()
        .enumerate()
        .map(|(i, d)| star(i, fg[0] + d * 0.001, fg[1] - d * 0.001, 0.001))
        .collect();
    assert_eq!(
        set_target_foreground(&mut t, &stars, &EstimateParams::default(), None),
        Applied::NoPosition
    );
    (t.ra_deg, t.dec_deg) = (Some(RA), Some(DEC));
    let Applied::Set(e) = set_target_foreground(&mut t, &stars, &EstimateParams::default(), None) else {
        panic!()
    };
    let f = t.foreground.clone().unwrap();
    assert_eq!((f.q, f.u, f.n_used), (e.q, e.u, Some(8)));
    // Intrinsic angles 0 and 45 deg: Delta-gamma 45 after the subtraction, 13.3 before.
    let dg = t.delta_gamma_fg_corrected_deg.unwrap();
    assert!((dg - 45.0).abs() < 0.5, "{dg}");
    assert!((before - 13.28).abs() < 0.01, "{before}");
    let s = t.sigma_delta_gamma_fg_corrected_deg.unwrap();
    assert!(s > t.sigma_delta_gamma_deg.unwrap(), "{s}");
    let [lo, hi] = t.delta_gamma_fg_corrected_interval_deg.unwrap();
    assert!(lo < dg && dg < hi);
    // A round trip through the JSON keeps everything.
    let back: Target = serde_json::from_str(&serde_json::to_string(&t).unwrap()).unwrap();
    assert_eq!(back, t);

    let few = &stars[..3];
    let Applied::TooFew { n_left: 3, .. } = set_target_foreground(&mut t, few, &EstimateParams::default(), None) else {
        panic!()
    };
    assert!(t.foreground.is_none() && t.delta_gamma_fg_corrected_deg.is_none());
    assert!(t
        .target_flags()
        .iter()
        .any(|f| f.is(FlagCode::ForegroundTooFewFieldStars)));
    set_target_foreground(&mut t, &stars, &EstimateParams::default(), None);
    assert!(t.flags.is_none() && t.foreground.is_some());
}

/// sigma of the subtracted Delta-gamma: the delta method against the scatter of draws in
/// which one foreground error moves both stars; the same covariance counted as two
/// independent errors (one per star) gives a different sigma; a zero foreground gives
/// exactly the uncorrected formula's value.
#[test]
fn the_foreground_error_is_common_to_both_stars_in_sigma_delta_gamma() {
    let stat = QuCovariance {
        var_q: 1e-8,
        var_u: 1e-8,
        cov_qu: 0.0,
    };
    let a = StarQu::with_offset_gradient(0.03, 0.01, stat, [0.0, 0.0]);
    let b = StarQu::with_offset_gradient(0.01, 0.025, stat, [0.0, 0.0]);
    let cal = [[0.0; 4]; 4];
    let fg = QuCovariance {
        var_q: 4e-6,
        var_u: 2.25e-6,
        cov_qu: 1e-6,
    };
    let want = sigma_delta_gamma_with_foreground_deg(&a, &b, &cal, &fg);
    assert_eq!(
        sigma_delta_gamma_with_foreground_deg(&a, &b, &cal, &QuCovariance::ZERO),
        sigma_delta_gamma_deg(&a, &b, &cal)
    );
    // Slow Monte Carlo: signed Delta-gamma (no fold near 30 deg) over draws.
    let mut rng = Rng64::seed_from_u64(5);
    let l11 = fg.var_q.sqrt();
    let l21 = fg.cov_qu / l11;
    let l22 = (fg.var_u - l21 * l21).sqrt();
    let g = |q: f64, u: f64| 0.5 * u.atan2(q).to_degrees();
    let draws: Vec<f64> = (0..200_000)
        .map(|_| {
            let (z1, z2) = (gauss(&mut rng), gauss(&mut rng));
            let (fq, fu) = (l11 * z1, l21 * z1 + l22 * z2);
            let n: [f64; 4] = std::array::from_fn(|_| 1e-4 * gauss(&mut rng));
            g(a.q + n[0] - fq, a.u + n[1] - fu) - g(b.q + n[2] - fq, b.u + n[3] - fu)
        })
        .collect();
    let m = draws.iter().sum::<f64>() / draws.len() as f64;
    let sd = (draws.iter().map(|d| (d - m).powi(2)).sum::<f64>() / (draws.len() - 1) as f64).sqrt();
    eprintln!("delta method {want:.3} deg, monte carlo {sd:.3} deg");
    assert!((want / sd - 1.0).abs() < 0.03, "{want} vs {sd}");
    // Independent per star: gA^T C gA + gB^T C gB, which is not the common value.
    let ga = crate::stokes::propagation::gamma_gradient_rad(a.q, a.u);
    let gb = crate::stokes::propagation::gamma_gradient_rad(b.q, b.u);
    let independent =
        (sigma_delta_gamma_deg(&a, &b, &cal).to_radians().powi(2) + fg.quadratic_form(ga) + fg.quadratic_form(gb))
            .sqrt()
            .to_degrees();
    assert!((independent / sd - 1.0).abs() > 0.1, "{independent} vs {sd}");
    let iv = delta_gamma_interval_with_foreground_deg(&a, &b, &cal, &fg);
    let dg = fold_delta_gamma(a.gamma_deg(), b.gamma_deg());
    assert!(((iv[1] - iv[0]) / (2.0 * want) - 1.0).abs() < 0.05, "{iv:?} {want}");
    assert!(iv[0] < dg && dg < iv[1]);
}

/// The science. 4000 unaligned binaries (random intrinsic angles, P_int 1-8 %), each
/// behind a foreground of 1-3 % (its own angle, varying by up to 0.3 % from place to
/// place), components measured with noise 0.1-2 %, and 8-30 field stars with the same
/// noise and 10-20 % intrinsically polarized ones. Without the subtraction the mean folded
/// Delta-gamma is far below 45 deg (alignment faked); after it, the mean signed error
/// against the true Delta-gamma is consistent with 0 and the mean |Delta-gamma| with 45
/// deg (uniform: KS p > 0.01).
#[test]
fn subtracting_the_estimated_foreground_removes_the_fake_alignment() {
    let mut rng = Rng64::seed_from_u64(314);
    let (mut raw, mut corrected, mut err_raw, mut err_corr) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut pulls = Vec::new();
    while corrected.len() < 4000 {
        let (stars, fb, _) = simulate_field(&mut rng, Variation::Random, [0.01, 0.03], 0.003);
        let Outcome::Estimated(e) = estimate(RA, DEC, &stars, &EstimateParams::default()) else {
            continue;
        };
        let mut gamma_true = [0.0; 2];
        let mut t = Target::new("sim", Status::Ok);
        (t.ra_deg, t.dec_deg) = (Some(RA), Some(DEC));
        for (k, name) in ["A", "B"].iter().enumerate() {
            let p = 0.01 * 8f64.powf(rng.random::<f64>());
            let a = std::f64::consts::PI * rng.random::<f64>();
            gamma_true[k] = a.to_degrees();
            let sigma = 0.001 * 20f64.powf(rng.random::<f64>());
            let q = p * (2.0 * a).cos() + fb[0] + sigma * gauss(&mut rng);
            let u = p * (2.0 * a).sin() + fb[1] + sigma * gauss(&mut rng);
            t.components.push(component(name, q, u, sigma));
        }
        t.foreground = Some(e.to_catalog());
        t.update_delta_gamma(None);
        let truth = fold_delta_gamma(gamma_true[0], gamma_true[1]);
        let (d_raw, d_corr) = (t.delta_gamma_deg.unwrap(), t.delta_gamma_fg_corrected_deg.unwrap());
        raw.push(d_raw);
        corrected.push(d_corr);
        err_raw.push(d_raw - truth);
        err_corr.push(d_corr - truth);
        pulls.push((d_corr - truth) / t.sigma_delta_gamma_fg_corrected_deg.unwrap());
    }
    let stats = |v: &[f64]| {
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        (m, sd / n.sqrt())
    };
    let (m_raw, se_raw) = stats(&raw);
    let (m_corr, se_corr) = stats(&corrected);
    let (e_raw, se_e_raw) = stats(&err_raw);
    let (e_corr, se_e_corr) = stats(&err_corr);
    let ks_raw = ks_uniform(&raw, 0.0, 90.0).p_value;
    let ks_corr = ks_uniform(&corrected, 0.0, 90.0).p_value;
    eprintln!(
        "without subtraction: mean |dg| {m_raw:.2} +- {se_raw:.2} deg, mean signed error {e_raw:.2} +- {se_e_raw:.2} deg, KS p {ks_raw:.1e}"
    );
    eprintln!(
        "after subtraction:   mean |dg| {m_corr:.2} +- {se_corr:.2} deg, mean signed error {e_corr:.2} +- {se_e_corr:.2} deg, KS p {ks_corr:.3}"
    );
    assert!(45.0 - m_raw > 10.0 * se_raw, "{m_raw} +- {se_raw}");
    assert!(ks_raw < 1e-6);
    assert!((m_corr - 45.0).abs() < 3.0 * se_corr, "{m_corr} +- {se_corr}");
    assert!(e_corr.abs() < 3.0 * se_e_corr, "{e_corr} +- {se_e_corr}");
    assert!(ks_corr > 0.01, "{ks_corr}");
    let within = pulls.iter().filter(|p| p.abs() < 1.0).count() as f64 / pulls.len() as f64;
    eprintln!(
        "corrected Delta-gamma within 1 sigma of the truth: {:.1} %",
        100.0 * within
    );
}

/// A target without a sky position still gets its Delta-gamma recomputed (no foreground):
/// a component that no longer passes the cut clears a Delta-gamma left from before, and a
/// stale foreground goes.
#[test]
fn without_a_position_the_delta_gamma_is_still_recomputed() {
    let mut t = Target::new("B2", Status::Ok);
    t.components = vec![component("A", 0.03, 0.0, 0.0005), component("B", 0.0, 0.03, 0.0005)];
    t.update_delta_gamma(None);
    assert!(t.delta_gamma_deg.is_some());
    t.foreground = Some(crate::catalog::Foreground::new(0.01, 0.0, 0.001, 0.001, 0.0));
    // The calibration refused B since.
    t.components[1].passes_cut = false;
    let stars: Vec<FieldStarQu> = (0..6).map(|i| star(i, 0.01, 0.0, 0.001)).collect();
    assert_eq!(
        set_target_foreground(&mut t, &stars, &EstimateParams::default(), None),
        Applied::NoPosition
    );
    assert!(
        t.delta_gamma_deg.is_none(),
        "a Delta-gamma of a component refused by the cut"
    );
    assert!(t.foreground.is_none() && t.delta_gamma_fg_corrected_deg.is_none());
}

/// The SOFI target strip on the sky about the binary: 1024 x 167 px of 0.288" (295" east-west
/// by 48" north-south), the binary at its centre, as the field stars of a reduced target
/// are found.
const STRIP_ARCSEC: [f64; 2] = [1024.0 * 0.288, 167.0 * 0.288];

/// One field seen through the simulator's foreground field (`sim::foreground`, a Gaussian
/// random field of the given rms and coherence scale drawn from `field_seed`), the binary at
/// (`ra`, `dec`): 6-24 stars uniform over the strip (none within 3" of the binary), noise
/// 0.1-1 % (log-uniform), 10 % intrinsically polarized (2-10 %). Returns the stars and the
/// field's value at the binary.
fn field_through_the_sky(
    rng: &mut Rng64,
    field: &crate::sim::foreground::ForegroundField,
    ra: f64,
    dec: f64,
) -> (Vec<FieldStarQu>, [f64; 2]) {
    use crate::sim::foreground::offset_position;
    let n = rng.random_range(6..=24usize);
    let mut stars = Vec::with_capacity(n);
    while stars.len() < n {
        let (e, nn) = (
            (rng.random::<f64>() - 0.5) * STRIP_ARCSEC[0],
            (rng.random::<f64>() - 0.5) * STRIP_ARCSEC[1],
        );
        if e.hypot(nn) < 3.0 {
            continue;
        }
        let (sra, sdec) = offset_position(ra, dec, e.hypot(nn), e.atan2(nn).to_degrees());
        let f = field.at(sra, sdec);
        let sigma = 0.001 * 10f64.powf(rng.random::<f64>());
        let mut y = [f.q + sigma * gauss(rng), f.u + sigma * gauss(rng)];
        if rng.random::<f64>() < 0.1 {
            let (p, a) = (
                0.02 + 0.08 * rng.random::<f64>(),
                std::f64::consts::PI * rng.random::<f64>(),
            );
            y[0] += p * (2.0 * a).cos();
            y[1] += p * (2.0 * a).sin();
        }
        stars.push(FieldStarQu {
            id: format!("f{}", stars.len()),
            q: y[0],
            u: y[1],
            sigma_q: sigma,
            sigma_u: sigma,
            cov_qu: 0.0,
            ra_deg: sra,
            dec_deg: sdec,
            usable: true,
        });
    }
    let fb = field.at(ra, dec);
    (stars, [fb.q, fb.u])
}

fn sky_field(rms: f64, coherence_arcsec: f64, seed: u64) -> crate::sim::foreground::ForegroundField {
    sky_field_with(rms, coherence_arcsec, None, seed)
}

/// [`sky_field`] with a power-law structure function of exponent `exponent` (outer scale
/// `coherence_arcsec`) when given.
fn sky_field_with(
    rms: f64,
    coherence_arcsec: f64,
    exponent: Option<f64>,
    seed: u64,
) -> crate::sim::foreground::ForegroundField {
    crate::sim::foreground::ForegroundField::new(
        &crate::sim::scene::ForegroundFieldConfig {
            p: 0.02,
            angle_deg: 60.0,
            rms,
            coherence_arcsec,
            structure_exponent: exponent,
            modes: 64,
            seed: None,
        },
        seed,
    )
}

fn rms_of(v: &[f64]) -> f64 {
    (v.iter().map(|p| p * p).sum::<f64>() / v.len() as f64).sqrt()
}

/// Nights of `size` fields through the simulator's random field (rms `rms_field`,
/// `coherence` arcsec; each field its own draw, the binary at its centre), every night's
/// fields estimated together ([`estimate_night`]): the pulls with the reported covariance
/// and with the random-effects one (the binary as one more independent place).
fn night_pulls(coherence: f64, size: usize, fields: usize, rms_field: f64) -> (Vec<f64>, Vec<f64>) {
    night_pulls_with(coherence, None, size, fields, rms_field)
}

/// [`night_pulls`] through a field of the given structure-function exponent (None:
/// Gaussian correlation).
fn night_pulls_with(
    coherence: f64,
    exponent: Option<f64>,
    size: usize,
    fields: usize,
    rms_field: f64,
) -> (Vec<f64>, Vec<f64>) {
    let mut rng = Rng64::seed_from_u64(11);
    let (mut pulls, mut re) = (Vec::new(), Vec::new());
    for night in 0..fields / size {
        // The binaries 1 deg apart in RA: separate fields.
        let at = |i: usize| (RA + i as f64, DEC);
        let drawn: Vec<_> = (0..size)
            .map(|i| {
                let field = sky_field_with(rms_field, coherence, exponent, 1000 + (night * size + i) as u64);
                field_through_the_sky(&mut rng, &field, at(i).0, at(i).1)
            })
            .collect();
        let input: Vec<(f64, f64, &[FieldStarQu])> = drawn
            .iter()
            .enumerate()
            .map(|(i, (s, _))| (at(i).0, at(i).1, s.as_slice()))
            .collect();
        for (o, (_, fb)) in estimate_night(&input, &EstimateParams::default()).iter().zip(&drawn) {
            if let Outcome::Estimated(e) = o {
                pulls.extend([(e.q - fb[0]) / e.cov.var_q.sqrt(), (e.u - fb[1]) / e.cov.var_u.sqrt()]);
                let (m, c) = e.random_effects;
                re.extend([(m[0] - fb[0]) / c.var_q.sqrt(), (m[1] - fb[1]) / c.var_u.sqrt()]);
            }
        }
    }
    (pulls, re)
}

/// The prediction at the binary against the simulator's own foreground field (a Gaussian
/// random field of rms 0.3 % in q and u; the stars in the SOFI target strip about the
/// binary; 300 fields per coherence scale), by nights of 6 fields (module doc, "The
/// night's fields"): the pulls have an rms in [0.85, 1.15] at a coherence scale of 20"
/// (nearly independent places, measured 1.06) and in [0.9, 1.15] at 90" (0.97); never wider
/// than 1.15 at 600" (nearly a gradient across the strip: conservative, 0.86), nor for a
/// field alone (the flat prior).
#[test]
fn pulls_at_the_binary_through_the_simulators_random_field() {
    let mut failures = Vec::new();
    for coherence in [20.0, 90.0, 600.0] {
        for size in [1, 6] {
            let (p, re) = night_pulls(coherence, size, 300, 0.003);
            let (r, rr) = (rms_of(&p), rms_of(&re));
            eprintln!(
                "coherence {coherence}\", nights of {size}: {} pulls, rms {r:.3} (random effects: {rr:.3})",
                p.len()
            );
            if p.len() < 500 {
                failures.push(format!("coherence {coherence}\": too few estimates: {}", p.len()));
            }
            if r > 1.15 {
                failures.push(format!(
                    "coherence {coherence}\", nights of {size}: pull rms {r:.3} (optimistic)"
                ));
            }
            if size == 6 && coherence == 20.0 && r < 0.85 {
                failures.push(format!(
                    "coherence 20\", nights of 6: pull rms {r:.3} (too conservative)"
                ));
            }
            // Measured: 0.97 against the random effects' 0.67 (0.95 with the plain sum's
            // best share, 0.86 with the flat prior's share fixed at 1/(n + 1); 0.77 with a
            // linear semivariogram alone).
            if size == 6 && coherence == 90.0 && !(r >= 0.9 && r >= rr + 0.05) {
                failures.push(format!(
                    "coherence 90\", nights of 6: pull rms {r:.3}, random effects {rr:.3}"
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// The prediction at the binary through turbulent fields (a power-law structure function,
/// as the dispersion of polarization angles in molecular clouds shows: a rough field of
/// exponent 0.7, Brownian 1.0, Kolmogorov's 5/3; outer scale 600", rms 0.3 %), by nights
/// of 6 fields: never optimistic (at most 1.15); within [0.9, 1.15] for the rough fields
/// (measured 1.11 and 1.07); at least 0.85 for Kolmogorov's (smooth below the stars'
/// spacing: conservative, measured 0.92; 0.78 with the flat prior's share fixed at
/// 1/(n + 1)).
#[test]
fn pulls_at_the_binary_through_turbulent_fields() {
    let mut failures = Vec::new();
    for (exponent, lowest) in [(0.7, 0.9), (1.0, 0.9), (5.0 / 3.0, 0.85)] {
        let (p, re) = night_pulls_with(600.0, Some(exponent), 6, 300, 0.003);
        let (r, rr) = (rms_of(&p), rms_of(&re));
        eprintln!(
            "structure exponent {exponent:.2}, nights of 6: {} pulls, rms {r:.3} (random effects: {rr:.3})",
            p.len()
        );
        if p.len() < 500 || !(lowest..=1.15).contains(&r) {
            failures.push(format!("exponent {exponent:.2}: {} pulls, rms {r:.3}", p.len()));
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// One binary's usable field stars as measured on simulated frames (q, u and total sigma,
/// rounded; the field at the binary q = -0.0070, u = 0.0209): one precise star showing the
/// foreground (f0), one precise young star polarized by its own 3 % (f1), and 9 stars of
/// 2-6 % errors, one of them polarized by 10 % (f5). The plain median of q sits among the
/// noisy stars, 2 % from f0; started there, the clip threw out f0 (chi2 79) and f1 and
/// the estimate was the noisy stars' mean, 3 sigma off in q. Started from the mixture's
/// best centre, f0 is kept, f1 clipped, and the estimate is within 2 sigma in q and u.
#[test]
fn a_precise_star_among_noisy_ones_is_not_clipped_for_their_median() {
    let values: [(f64, f64, f64); 11] = [
        (-0.0072, 0.0192, 0.0016),
        (-0.0180, 0.0520, 0.0040),
        (-0.0252, 0.0227, 0.0177),
        (-0.0533, -0.0185, 0.0207),
        (0.0325, 0.0131, 0.0273),
        (-0.1153, 0.0061, 0.0289),
        (-0.0436, 0.0098, 0.0331),
        (-0.0460, 0.0672, 0.0363),
        (-0.0275, -0.0035, 0.0372),
        (-0.0068, 0.0281, 0.0412),
        (-0.0461, 0.0214, 0.0634),
    ];
    let stars: Vec<FieldStarQu> = values
        .iter()
        .enumerate()
        .map(|(i, &(q, u, s))| star(i, q, u, s))
        .collect();
    let e = estimated(estimate(RA, DEC, &stars, &EstimateParams::default()));
    eprintln!(
        "q {:.4} +- {:.4}, u {:.4} +- {:.4}, used {:?}",
        e.q,
        e.cov.var_q.sqrt(),
        e.u,
        e.cov.var_u.sqrt(),
        e.used
    );
    assert!(
        e.used.contains(&"f0".to_string()),
        "the precise star was clipped: {:?}",
        e.rejected
    );
    assert!(
        !e.used.contains(&"f1".to_string()),
        "the polarized precise star was kept"
    );
    let (tq, tu) = (-0.0070, 0.0209);
    assert!((e.q - tq).abs() < 2.0 * e.cov.var_q.sqrt(), "q {} vs {tq}", e.q);
    assert!((e.u - tu).abs() < 2.0 * e.cov.var_u.sqrt(), "u {} vs {tu}", e.u);
}

/// One binary's usable field stars as measured on simulated frames (an end-to-end night
/// of `tests/cli_foreground.rs`, seed 17, T4: separation from A in arcsec, PA in deg, q,
/// u, sigma_q, sigma_u, rounded; the field at the binary q = -0.0189, u = 0.0239): one
/// precise star (F1, 0.15 %) that is a young star polarized by its own disk, its (q, u)
/// 3.5 % off the foreground in u, and 8 stars of 1-7 % errors about the foreground. The
/// clip keeps F1 (the noisy stars cannot contradict it alone), and the kriging leaned on it
/// with a weight near 1: the estimate was 16 sigma off in u. With F1 weighed as possibly
/// polarized (its residual against the others' prediction at its place), the prediction
/// without it is mixed in and the estimate is within 2 sigma.
#[test]
fn a_precise_polarized_star_among_noisy_ones_is_weighed_as_possibly_polarized() {
    use crate::sim::foreground::offset_position;
    let values: [(f64, f64, f64, f64, f64, f64); 9] = [
        (38.8, 102.0, -0.0233, -0.0106, 0.0014, 0.0018),
        (20.4, 192.0, 0.0025, 0.0261, 0.0122, 0.0138),
        (39.7, 116.0, -0.0220, 0.0437, 0.0280, 0.0308),
        (20.5, 208.0, -0.0124, -0.0009, 0.0285, 0.0329),
        (42.8, 290.0, 0.0070, 0.0049, 0.0334, 0.0408),
        (21.7, 93.0, 0.0234, 0.0074, 0.0473, 0.0475),
        (19.9, 217.0, -0.0206, -0.0539, 0.0464, 0.0562),
        (41.8, 120.0, -0.0126, 0.0096, 0.0542, 0.0577),
        (5.1, 120.0, -0.0114, -0.0519, 0.0667, 0.0649),
    ];
    let stars: Vec<FieldStarQu> = values
        .iter()
        .enumerate()
        .map(|(i, &(sep, pa, q, u, sq, su))| {
            let (ra, dec) = offset_position(RA, DEC, sep, pa);
            FieldStarQu {
                id: format!("F{i}"),
                q,
                u,
                sigma_q: sq,
                sigma_u: su,
                cov_qu: 0.0,
                ra_deg: ra,
                dec_deg: dec,
                usable: true,
            }
        })
        .collect();
    let e = estimated(estimate(RA, DEC, &stars, &EstimateParams::default()));
    let (tq, tu) = (-0.0189, 0.0239);
    let pulls = [(e.q - tq) / e.cov.var_q.sqrt(), (e.u - tu) / e.cov.var_u.sqrt()];
    eprintln!("q {:.4} u {:.4}, pulls {pulls:?}, dominant {:?}", e.q, e.u, e.dominant);
    assert!(
        e.used.contains(&"F0".to_string()),
        "the clip now rejects F0: {:?}",
        e.rejected
    );
    let d = e.dominant.as_ref().expect("F0 carries most of the weight");
    assert_eq!(d.id, "F0");
    assert!(d.weight >= DOMINANT_WEIGHT && d.probability_polarized > 0.1, "{d:?}");
    assert!(pulls.iter().all(|p| p.abs() < 2.0), "pulls {pulls:?}");
    assert!(e.method.contains("polarized itself with probability"), "{}", e.method);
}

/// A precise star that shows the foreground, among noisy ones that agree with it, keeps
/// nearly all its weight: the chance that it is polarized is small and the estimate is
/// the one with it.
#[test]
fn a_precise_star_that_shows_the_foreground_keeps_its_weight() {
    let mut stars = vec![star(0, 0.010, 0.020, 0.001)];
    let mut rng = Rng64::seed_from_u64(11);
    for i in 1..9 {
        stars.push(star(
            i,
            0.010 + 0.02 * gauss(&mut rng),
            0.020 + 0.02 * gauss(&mut rng),
            0.02,
        ));
    }
    let e = estimated(estimate(RA, DEC, &stars, &EstimateParams::default()));
    let d = e
        .dominant
        .as_ref()
        .expect("the precise star carries most of the weight");
    assert!(d.probability_polarized < 0.05, "{d:?}");
    assert!(
        (e.q - 0.010).abs() < 0.002 && (e.u - 0.020).abs() < 0.002,
        "{} {}",
        e.q,
        e.u
    );
}

/// Two targets at the same place with the same field stars (the binary observed twice, or
/// in two filters) do not inform each other's prior: with only such a twin besides, each
/// keeps the flat prior, and the estimate is the one of the field alone.
#[test]
fn the_same_field_twice_does_not_inform_its_own_prior() {
    let mut rng = Rng64::seed_from_u64(5);
    let field = sky_field(0.003, 90.0, 77);
    let (stars, _) = field_through_the_sky(&mut rng, &field, RA, DEC);
    let alone = estimated(estimate(RA, DEC, &stars, &EstimateParams::default()));
    let out = estimate_night(
        &[(RA, DEC, stars.as_slice()), (RA, DEC + 1.0 / 3600.0, stars.as_slice())],
        &EstimateParams::default(),
    );
    for (k, o) in out.into_iter().enumerate() {
        let e = estimated(o);
        assert_eq!(e.spatial.map(|s| s.night_prior), Some(None), "{}", e.method);
        assert!(
            e.method.contains("prior of the foreground's variation: flat"),
            "{}",
            e.method
        );
        if k == 0 {
            assert!((e.q - alone.q).abs() < 1e-12 && (e.cov.var_q - alone.cov.var_q).abs() < 1e-15);
        }
    }
}
