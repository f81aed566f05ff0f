//! The numerical-stability suite, for the parts that do not need a reduction:
//! the Stokes inversion at P = 0, P << sigma and P = 0.05 % on a very bright star, the
//! angle wrap at 0/180 and the Delta-gamma fold at 0/90, property tests of the forward
//! model and inversion, and the Monte Carlo at alpha exactly 0 and 180 deg.
use proptest::prelude::*;
use sofipol_pipeline::catalog::fold_delta_gamma;
use sofipol_pipeline::stats::mc::{simulate, McConfig};
use sofipol_pipeline::stats::model::{AlignmentModel, AlphaMeasure, AlphaTable};
use sofipol_pipeline::stokes::inversion::{combine_dithers, fit_qu, Debias, LinearPolarization};
use sofipol_pipeline::stokes::model::{beam_fluxes, Polarization};
use sofipol_pipeline::stokes::propagation::UNIFORM_ANGLE_SIGMA_DEG;

fn all_finite(lp: &LinearPolarization) -> bool {
    [
        lp.q,
        lp.u,
        lp.sigma_q,
        lp.sigma_u,
        lp.p,
        lp.sigma_p,
        lp.p_debiased,
        lp.gamma_deg,
        lp.sigma_gamma_deg,
        lp.sigma_gamma_nkc_deg,
        lp.snr,
    ]
    .iter()
    .all(|v| v.is_finite())
}

/// 68.27 % half-width of a uniform angle on [-90, 90): 0.6827 x 90 deg.
const UNIFORM_68_DEG: f64 = 0.682_689_492_137_085_9 * 90.0;

#[test]
fn p_zero_is_finite_with_zero_debiased_p_and_a_uniform_angle_error() {
    for how in [Debias::WardleKronberg, Debias::Mas] {
        for sigma in [0.01, 1e-6, 0.0] {
            let lp = LinearPolarization::from_qu(0.0, 0.0, sigma, sigma, how);
            assert!(all_finite(&lp), "sigma {sigma}: {lp:?}");
            assert_eq!(lp.p, 0.0);
            assert_eq!(lp.p_debiased, 0.0);
            assert_eq!(lp.snr, 0.0, "P = 0 has S/N 0 (was infinite with zero errors)");
            assert!((0.0..180.0).contains(&lp.gamma_deg));
            assert!(!lp.passes_cut(3.0));
            assert!((lp.sigma_gamma_deg - UNIFORM_ANGLE_SIGMA_DEG).abs() < 1e-12);
            assert!((lp.sigma_gamma_nkc_deg - UNIFORM_68_DEG).abs() < 0.5, "{lp:?}");
        }
    }
}

#[test]
fn p_far_below_sigma_gives_zero_debiased_p_and_the_low_snr_angle_error() {
    // Regression: sigma_gamma = 28.65 sigma_P / P gave 2 x 10^5 deg here.
    let (q, u, s) = (1e-6, -1e-6, 0.01);
    let lp = LinearPolarization::from_qu(q, u, s, s, Debias::WardleKronberg);
    assert!(all_finite(&lp), "{lp:?}");
    assert_eq!(lp.p_debiased, 0.0);
    assert!(!lp.passes_cut(3.0));
    assert!(lp.sigma_gamma_deg <= UNIFORM_ANGLE_SIGMA_DEG, "{lp:?}");
    assert!((lp.sigma_gamma_nkc_deg - UNIFORM_68_DEG).abs() < 0.5, "{lp:?}");
    let mas = LinearPolarization::from_qu(q, u, s, s, Debias::Mas);
    assert!(mas.p_debiased >= 0.0 && mas.p_debiased <= mas.p, "{mas:?}");
    // The cap leaves well-measured angles untouched: P = 10 sigma -> 28.65/10 deg.
    let hi = LinearPolarization::from_qu(0.1, 0.0, 0.01, 0.01, Debias::WardleKronberg);
    assert!((hi.sigma_gamma_deg - 2.864_788_975_654_116).abs() < 1e-12, "{hi:?}");
}

#[test]
fn p_0_05_percent_on_a_very_bright_star_keeps_its_digits() {
    // o and e agree to 5e-4: F = (o - e)/(o + e) must not lose P to cancellation, neither
    // in f64 nor after the beams went through f32 images (24-bit mantissa: 6e-8 relative).
    let truth = Polarization::from_p_gamma(5e-4, 33.0);
    let phis = [0.0, 45.0, 90.0, 135.0];
    for i_tot in [1e6, 1e9, 1e12] {
        for f32_beams in [false, true] {
            let f: Vec<f64> = phis
                .iter()
                .map(|&phi| {
                    let (mut o, mut e) = beam_fluxes(i_tot, truth, phi, 1.0, 1.0);
                    if f32_beams {
                        (o, e) = (o as f32 as f64, e as f32 as f64);
                    }
                    (o - e) / (o + e)
                })
                .collect();
            let fit = fit_qu(&phis, &f, &[1e-6; 4]).unwrap();
            let tol = if f32_beams { 2e-7 } else { 1e-13 };
            assert!(
                (fit.q - truth.q).abs() < tol && (fit.u - truth.u).abs() < tol,
                "I {i_tot:e} f32 {f32_beams}: {fit:?} vs {truth:?}"
            );
            let lp = LinearPolarization::from_qu(fit.q, fit.u, 1e-6, 1e-6, Debias::WardleKronberg);
            assert!((lp.gamma_deg - 33.0).abs() < 0.05, "{lp:?}");
        }
    }
}

#[test]
fn gamma_at_the_0_180_wrap_stays_in_0_180_and_delta_gamma_folds_at_0_and_90() {
    for u in [-1e-300, -1e-17, -0.0, 0.0, 1e-300, 1e-17] {
        let lp = LinearPolarization::from_qu(0.05, u, 0.001, 0.001, Debias::WardleKronberg);
        assert!((0.0..180.0).contains(&lp.gamma_deg), "u {u:e}: {}", lp.gamma_deg);
        assert!(
            lp.gamma_deg < 1e-9 || lp.gamma_deg > 180.0 - 1e-9,
            "u {u:e}: {}",
            lp.gamma_deg
        );
        let lp = LinearPolarization::from_qu(-0.05, u, 0.001, 0.001, Debias::WardleKronberg);
        assert!((lp.gamma_deg - 90.0).abs() < 1e-9, "q < 0, u {u:e}: {}", lp.gamma_deg);
    }
    // Two angles either side of the wrap are 0.2 deg apart, not 179.8.
    assert!((fold_delta_gamma(179.9, 0.1) - 0.2).abs() < 1e-9);
    assert!(fold_delta_gamma(0.0, 180.0 - 1e-13) < 1e-9);
    for (a, b) in [(0.0, 90.0), (45.0, 135.0), (179.999_999, 89.999_999), (90.0, 0.0)] {
        let d = fold_delta_gamma(a, b);
        assert!((0.0..=90.0).contains(&d) && (d - 90.0).abs() < 1e-6, "{a} {b}: {d}");
    }
    for (a, b) in [(10.0, 10.0), (0.0, 0.0), (179.999_999_999, 0.0)] {
        let d = fold_delta_gamma(a, b);
        assert!((0.0..1e-6).contains(&d), "{a} {b}: {d}");
    }
}

fn mc(model: AlignmentModel, pairs: u64) -> sofipol_pipeline::stats::mc::McOutput {
    simulate(&McConfig::geometry(model, pairs, 5)).unwrap()
}

#[test]
fn mc_with_alpha_exactly_0_or_180_puts_every_pair_at_delta_gamma_0() {
    // alpha = 180 (anti-parallel axes) is the same line as alpha = 0: Delta gamma = 0.
    let pairs = 20_000;
    for alpha in [0.0, 180.0] {
        // A table that is nonzero only at alpha (a narrow triangle ending exactly there).
        let (a, d) = if alpha == 0.0 {
            (vec![0.0, 1e-9], vec![1.0, 0.0])
        } else {
            (vec![180.0 - 1e-9, 180.0], vec![0.0, 1.0])
        };
        let t = AlphaTable::new("test", a, d, AlphaMeasure::Alpha).unwrap();
        let out = mc(AlignmentModel::Table(t), pairs);
        assert_eq!(out.simulated, pairs);
        assert_eq!(out.accepted, pairs);
        assert_eq!(out.histogram.counts.iter().sum::<u64>(), pairs);
        assert_eq!(
            out.histogram.counts[0],
            pairs,
            "alpha {alpha}: {:?}",
            &out.histogram.counts[..3]
        );
    }
    let out = mc(AlignmentModel::Aligned, pairs);
    assert_eq!(out.histogram.counts[0], pairs);
    // A cone of half-angle exactly 180 deg is the isotropic model: mean Delta gamma 45 deg.
    let out = mc(AlignmentModel::Cone { alpha0_deg: 180.0 }, 200_000);
    assert_eq!(out.histogram.counts.iter().sum::<u64>(), 200_000);
    let mean: f64 = out
        .histogram
        .counts
        .iter()
        .enumerate()
        .map(|(i, &c)| (i as f64 + 0.5) * c as f64)
        .sum::<f64>()
        / 200_000.0;
    // The projected-angle distribution of random pairs is not uniform, but symmetric about
    // 45 deg (Delta gamma -> 90 - Delta gamma is a rotation of one axis by 90 deg on the sky).
    assert!((mean - 45.0).abs() < 0.3, "{mean}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, failure_persistence: None, ..ProptestConfig::default() })]

    /// Random q, u, fluxes and photon noise through the forward model, per-dither F with
    /// propagated errors, dither combination and the q, u fit: the result is finite and
    /// within 5.5 sigma of the truth (false-alarm rate ~ 400 x 4e-8).
    #[test]
    fn forward_model_and_inversion_agree_within_their_errors(
        q0 in -0.2f64..0.2,
        u0 in -0.2f64..0.2,
        log_i in 3.0f64..8.0,
        three_angles in any::<bool>(),
        unif in proptest::collection::vec((1e-12f64..1.0, 0.0f64..1.0), 4 * 3 * 2),
    ) {
        let truth = Polarization { q: q0, u: u0 };
        let i_tot = 10f64.powf(log_i);
        let phis: Vec<f64> = if three_angles { vec![0.0, 60.0, 120.0] } else { vec![0.0, 45.0, 90.0, 135.0] };
        let mut normals = unif.iter().map(|&(a, b)| (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos());
        let (mut f, mut sf) = (Vec::new(), Vec::new());
        for &phi in &phis {
            let (mut vals, mut sigs) = (Vec::new(), Vec::new());
            for _ in 0..3 {
                // Equal beam throughputs (what the pipeline calibrates to), photon noise.
                let (o, e) = beam_fluxes(i_tot, truth, phi, 1.0, 1.0);
                let (so, se) = (o.sqrt(), e.sqrt());
                let (o, e) = (o + so * normals.next().unwrap(), e + se * normals.next().unwrap());
                let t = o + e;
                vals.push((o - e) / t);
                sigs.push(2.0 * ((e * so).powi(2) + (o * se).powi(2)).sqrt() / (t * t));
            }
            let c = combine_dithers(&vals, &sigs).unwrap();
            f.push(c.value);
            sf.push(c.sigma);
        }
        let fit = fit_qu(&phis, &f, &sf).unwrap();
        let lp = LinearPolarization::from_qu(fit.q, fit.u, fit.var_q.sqrt(), fit.var_u.sqrt(), Debias::WardleKronberg);
        prop_assert!(all_finite(&lp), "{:?}", lp);
        prop_assert!(((fit.q - q0) / fit.var_q.sqrt()).abs() < 5.5, "q {} vs {} +- {}", fit.q, q0, fit.var_q.sqrt());
        prop_assert!(((fit.u - u0) / fit.var_u.sqrt()).abs() < 5.5, "u {} vs {} +- {}", fit.u, u0, fit.var_u.sqrt());
        prop_assert!((0.0..180.0).contains(&lp.gamma_deg));
        prop_assert!(lp.p_debiased >= 0.0 && lp.p_debiased <= lp.p);
    }
}
