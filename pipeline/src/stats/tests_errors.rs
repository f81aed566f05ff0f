//! Tests of the Delta-gamma errors and of the predictions convolved with them, against
//! independent references: the uniform law (invariant under any angle error), the
//! half-normal (a point mass at 0), a brute-force quadrature of the folded normal, and the
//! catalog fields each error is taken from.
use statrs::function::erf::erf;

use super::alignment::{analyse, AnalysisParams};
use super::errors::{convolve_with_errors, fold_deg, folded_normal_cdf, ErrorSource, SampleErrors};
use super::ks::ks_uniform;
use super::mc::{McConfig, PIntDist};
use super::model::AlignmentModel;
use super::rng::Xoshiro256pp;
use super::sample::BinarySample;
use crate::catalog::{Catalog, Component, Status, Target};

/// Empirical CDF of `v` at `x`.
fn ecdf(v: &[f64], x: f64) -> f64 {
    v.iter().filter(|&&d| d <= x).count() as f64 / v.len() as f64
}

#[test]
fn convolving_a_uniform_delta_gamma_leaves_it_uniform() {
    // Random orientation: Delta gamma uniform on [0, 90]. Any Gaussian angle error, folded,
    // keeps it uniform (the angle difference is uniform modulo 180 and stays so).
    let mut rng = Xoshiro256pp::from_seed(11);
    let n = 300_000;
    let uniform: Vec<f64> = (0..n).map(|_| 90.0 * rng.uniform()).collect();
    let se = (0.25 / n as f64).sqrt();
    for sigmas in [vec![3.0], vec![10.0], vec![30.0], vec![2.0, 25.0, 70.0], vec![150.0]] {
        let conv = convolve_with_errors(&uniform, &sigmas, 5);
        assert!(
            conv.iter().all(|&d| (0.0..=90.0).contains(&d)),
            "not folded into [0, 90]"
        );
        let ks = ks_uniform(&conv, 0.0, 90.0);
        assert!(ks.p_value > 1e-3, "sigmas {sigmas:?}: KS p = {}", ks.p_value);
        for x in [1.0, 5.0, 20.0, 45.0, 70.0, 85.0, 89.0] {
            let f = ecdf(&conv, x);
            assert!((f - x / 90.0).abs() < 5.0 * se, "sigmas {sigmas:?}: F({x}) = {f}");
        }
    }
}

#[test]
fn a_point_mass_at_zero_becomes_the_half_normal() {
    // Perfectly aligned pairs measured with error sigma: |N(0, sigma)| for sigma << 90,
    // mean sigma sqrt(2/pi), CDF erf(x / (sigma sqrt 2)).
    let n = 400_000;
    let zeros = vec![0.0; n];
    for sigma in [2.0, 5.0, 10.0] {
        let conv = convolve_with_errors(&zeros, &[sigma], 17);
        let mean = conv.iter().sum::<f64>() / n as f64;
        let want = sigma * (2.0 / std::f64::consts::PI).sqrt();
        let se = sigma * (1.0 - 2.0 / std::f64::consts::PI).sqrt() / (n as f64).sqrt();
        assert!((mean - want).abs() < 4.0 * se, "sigma {sigma}: mean {mean} vs {want}");
        for k in [0.25, 0.5, 1.0, 2.0, 3.0] {
            let x = k * sigma;
            let f = erf(x / (sigma * std::f64::consts::SQRT_2));
            let got = ecdf(&conv, x);
            let se = (f * (1.0 - f) / n as f64).sqrt().max(1e-6);
            assert!((got - f).abs() < 4.0 * se, "sigma {sigma}: F({x}) = {got} vs {f}");
        }
    }
    // A mixture of errors: each pair draws its sigma uniformly from the list, so the CDF is
    // the mean of the half-normal CDFs.
    let sigmas = [2.0, 8.0];
    let conv = convolve_with_errors(&zeros, &sigmas, 3);
    for x in [1.0, 3.0, 6.0, 12.0] {
        let f: f64 = sigmas
            .iter()
            .map(|s| erf(x / (s * std::f64::consts::SQRT_2)))
            .sum::<f64>()
            / 2.0;
        let got = ecdf(&conv, x);
        let se = (f * (1.0 - f) / n as f64).sqrt();
        assert!((got - f).abs() < 4.0 * se, "mixture: F({x}) = {got} vs {f}");
    }
}

/// P(fold(mu + sigma z) <= x) by brute force: midpoint quadrature of the normal density over
/// z in [-12, 12], counting the z whose folded angle is at most x.
fn folded_cdf_by_quadrature(x: f64, mu: f64, sigma: f64) -> f64 {
    let m = 400_000;
    let h = 24.0 / m as f64;
    (0..m)
        .map(|i| {
            let z = -12.0 + (i as f64 + 0.5) * h;
            if fold_deg(mu + sigma * z) <= x {
                (-0.5 * z * z).exp() * h / (2.0 * std::f64::consts::PI).sqrt()
            } else {
                0.0
            }
        })
        .sum()
}

#[test]
fn convolution_near_the_fold_matches_the_folded_normal() {
    // Pairs with a true Delta gamma near 90 (and near 0) fold back at both ends: the image
    // sum of `folded_normal_cdf` against a brute-force quadrature, and the Monte Carlo
    // against both.
    let n = 200_000;
    for (mu, sigma) in [(80.0, 15.0), (5.0, 12.0), (45.0, 40.0), (88.0, 100.0)] {
        let conv = convolve_with_errors(&vec![mu; n], &[sigma], 23);
        for x in [2.0, 10.0, 30.0, 60.0, 75.0, 85.0, 89.5] {
            let exact = folded_normal_cdf(x, mu, sigma);
            let slow = folded_cdf_by_quadrature(x, mu, sigma);
            assert!(
                (exact - slow).abs() < 1e-4,
                "mu {mu} sigma {sigma} x {x}: {exact} vs {slow}"
            );
            let got = ecdf(&conv, x);
            let se = (exact * (1.0 - exact) / n as f64).sqrt().max(1e-6);
            assert!(
                (got - exact).abs() < 4.5 * se,
                "mu {mu} sigma {sigma}: F({x}) = {got} vs {exact}"
            );
        }
    }
}

#[test]
fn convolution_is_seeded_and_identical_for_any_thread_count() {
    let mut rng = Xoshiro256pp::from_seed(1);
    let v: Vec<f64> = (0..150_001).map(|_| 90.0 * rng.uniform()).collect();
    let run = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| convolve_with_errors(&v, &[1.0, 4.0, 9.0], seed))
    };
    let one = run(1, 7);
    assert_eq!(one, run(2, 7));
    assert_ne!(one, run(1, 8));
    assert_eq!(convolve_with_errors(&v, &[], 7), v, "no errors: unchanged");
}

fn component(name: &str, gamma: f64, sigma_gamma: f64, stat: Option<f64>) -> Component {
    Component {
        pol: crate::stokes::inversion::Polarization {
            q: 0.05,
            u: 0.0,
            sigma_q: 0.005,
            sigma_u: 0.005,
            p: 0.05,
            sigma_p: 0.005,
            p_debiased: 0.05,
            gamma_deg: gamma,
            sigma_gamma_deg: sigma_gamma,
        },
        passes_cut: true,
        sigma_gamma_stat_deg: stat,
        ..Component::new(name, crate::stokes::inversion::Polarization::UNDEFINED)
    }
}

fn target(object: &str, comps: Vec<Component>, sigma_dg: Option<f64>, interval: Option<[f64; 2]>) -> Target {
    Target {
        components: comps,
        sigma_delta_gamma_deg: sigma_dg,
        delta_gamma_interval_deg: interval,
        ..Target::new(object, Status::Ok)
    }
}

#[test]
fn each_binary_takes_its_error_from_the_best_available_field() {
    let cat = Catalog {
        targets: vec![
            // Propagated error wins over the components' errors.
            target(
                "prop",
                vec![
                    component("A", 10.0, 3.0, Some(2.0)),
                    component("B", 20.0, 4.0, Some(1.5)),
                ],
                Some(2.2),
                Some([8.0, 12.5]),
            ),
            // Statistical component errors in quadrature: hypot(2, 1.5) = 2.5.
            target(
                "stat",
                vec![
                    component("A", 10.0, 3.0, Some(2.0)),
                    component("B", 40.0, 4.0, Some(1.5)),
                ],
                None,
                None,
            ),
            // Total component errors in quadrature: hypot(12, 16) = 20 ... large only above 20.
            target(
                "total",
                vec![component("A", 10.0, 15.0, None), component("B", 70.0, 20.0, Some(1.0))],
                None,
                None,
            ),
            // No error at all; a wide interval alone makes it "large".
            target(
                "none",
                vec![component("A", 0.0, f64::NAN, None), component("B", 5.0, f64::NAN, None)],
                None,
                Some([0.0, 50.0]),
            ),
        ],
        ..Default::default()
    };
    let s = BinarySample::from_catalog(&cat, None);
    let e: Vec<_> = s
        .binaries
        .iter()
        .map(|b| (b.sigma_delta_gamma_deg, b.sigma_source))
        .collect();
    assert_eq!(e[0], (Some(2.2), Some(ErrorSource::Propagated)));
    assert_eq!(e[1], (Some(2.5), Some(ErrorSource::ComponentStat)));
    assert_eq!(e[2], (Some(25.0), Some(ErrorSource::ComponentTotal)));
    assert_eq!(e[3], (None, None));
    let errs = s.errors();
    assert_eq!(errs.sigmas_deg, vec![2.2, 2.5, 25.0]);
    assert_eq!(
        (
            errs.n_propagated,
            errs.n_component_stat,
            errs.n_component_total,
            errs.n_without_error
        ),
        (1, 1, 1, 1)
    );
    assert_eq!(errs.median_deg(), Some(2.5));
    assert_eq!(errs.max_deg(), Some(25.0));
    let large: Vec<&str> = errs.large.iter().map(|l| l.object.as_str()).collect();
    assert_eq!(large, vec!["total", "none"]);
}

fn params(noise: Option<f64>, sigmas: Vec<f64>) -> AnalysisParams {
    AnalysisParams {
        significance: 0.05,
        threshold_deg: 30.0,
        ism_levels_percent: vec![1.0],
        ism_angle_deg: 0.0,
        mc: McConfig {
            p_int: PIntDist::Fixed { p_percent: 4.0 },
            noise_percent: noise,
            ..McConfig::geometry(AlignmentModel::Random, 100_000, 4)
        },
        models: vec![
            ("aligned".into(), AlignmentModel::Aligned),
            ("random".into(), AlignmentModel::Random),
        ],
        errors: SampleErrors {
            n_propagated: sigmas.len(),
            sigmas_deg: sigmas,
            ..Default::default()
        },
        per_binary: None,
    }
}

#[test]
fn analyse_reports_each_prediction_with_and_without_the_errors() {
    // Aligned disks measured with sigma = 8 deg: the observed sample is a half-normal.
    let sigma = 8.0;
    let mut rng = Xoshiro256pp::from_seed(99);
    let dg: Vec<f64> = (0..40).map(|_| fold_deg(sigma * rng.normal_pair().0)).collect();
    let r = analyse(&dg, &params(None, vec![sigma; 40])).unwrap();
    let aligned = &r.models[0];
    let with = &aligned.with_errors.as_ref().unwrap().prediction;
    assert_eq!(aligned.prediction.mean_deg, 0.0);
    let want = sigma * (2.0 / std::f64::consts::PI).sqrt();
    assert!((with.mean_deg - want).abs() < 0.05, "{} vs {want}", with.mean_deg);
    // Without the errors, perfect alignment is rejected outright; with them it fits.
    assert!(aligned.prediction.ks.p_value < 1e-10);
    assert!(with.ks.p_value > 0.01, "{}", with.ks.p_value);
    // Random orientation: the convolved prediction stays at mean 45, f(<30) = 1/3.
    let random = r.models[1].with_errors.as_ref().unwrap();
    assert!((random.prediction.mean_deg - 45.0).abs() < 0.3);
    assert!((random.prediction.fraction_below_threshold - 1.0 / 3.0).abs() < 0.006);
    // Noise-free ISM Monte Carlo: convolved too.
    assert!(r.ism[0].with_errors.is_some());
    for s in [
        "median sigma = 8.0 deg",
        "aligned: mean 0.0 -> ",
        "uniform Delta gamma stays uniform",
    ] {
        assert!(r.verdict.contains(s), "missing '{s}' in {}", r.verdict);
    }
    assert!(r.verdict.contains("aligned becomes consistent"), "{}", r.verdict);
    // A Monte Carlo that draws (q, u) noise is not convolved a second time.
    let r = analyse(&dg, &params(Some(0.3), vec![sigma; 40])).unwrap();
    assert!(r.ism[0].with_errors.is_none() && r.models[0].with_errors.is_some());
    assert!(r.verdict.contains("not convolved again"), "{}", r.verdict);
    // No errors: nothing is convolved and the verdict says so.
    let r = analyse(&dg, &params(None, vec![])).unwrap();
    assert!(r.models.iter().all(|m| m.with_errors.is_none()) && r.ism[0].with_errors.is_none());
    assert!(r.verdict.contains("none of the 40 binaries has one"), "{}", r.verdict);
}

#[test]
fn ks_against_a_large_unsorted_sample_equals_the_sorted_merge() {
    // The counting form against the merge of two sorted samples (ks_two_sample), with ties
    // inside and across the samples (values rounded to 0.5 deg), and the median/mean/fraction
    // of `predict` against a sort.
    use super::ks::{ks_two_sample, ks_two_sample_against_large};
    use super::predictions::predict;
    let mut rng = Xoshiro256pp::from_seed(5);
    // x skewed to small values (F_x ahead of F_y: D at a value of x) and to large values
    // (F_y ahead: D just below a value of x).
    for (n1, n2, round, skew) in [
        (34, 100_001, true, 1.5),
        (34, 100_000, false, 0.4),
        (7, 5000, true, 0.5),
        (40, 200_000, false, 1.5),
        (1, 10, false, 1.0),
        (3, 4, true, 0.7),
    ] {
        let mut draw = |n: usize, skew: f64| -> Vec<f64> {
            (0..n)
                .map(|_| {
                    let v = 90.0 * rng.uniform().powf(skew);
                    if round {
                        (2.0 * v).round() / 2.0
                    } else {
                        v
                    }
                })
                .collect()
        };
        let mut x = draw(n1, skew);
        let y = draw(n2, 1.0);
        x.sort_by(|a, b| a.total_cmp(b));
        let fast = ks_two_sample_against_large(&x, &y);
        let slow = ks_two_sample(&x, &y);
        assert_eq!(fast.statistic, slow.statistic, "n1 {n1} n2 {n2}");
        assert_eq!(fast.p_value, slow.p_value);
        let mut sorted = y.clone();
        sorted.sort_by(|a, b| a.total_cmp(b));
        let median = if n2 % 2 == 1 {
            sorted[n2 / 2]
        } else {
            0.5 * (sorted[n2 / 2 - 1] + sorted[n2 / 2])
        };
        let mut y2 = y.clone();
        let p = predict(&x, &mut y2, 30.0);
        assert_eq!(p.median_deg, median, "n2 {n2}");
        assert_eq!(
            p.fraction_below_threshold,
            sorted.partition_point(|&d| d < 30.0) as f64 / n2 as f64
        );
        assert_eq!(p.ks.statistic, slow.statistic);
    }
}
