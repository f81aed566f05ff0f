//! Tests of the statistics module: independent references (testdata/stats/reference.json,
//! made by scipy/astropy/mpmath, see its "origin"), invariants of the Monte Carlo, and
//! slow-but-obvious reimplementations of the fast paths.
use serde_json::Value;

use super::alignment::{analyse, AnalysisParams};
use super::binomial::binomial_test;
use super::hist::Histogram;
use super::ks::{kolmogorov_sf, ks_statistics, ks_two_sample, ks_uniform, smirnov_sf, EXACT_MAX_N};
use super::kuiper::{
    kuiper_cdf_dual_for_tests, kuiper_cdf_exact, kuiper_p, kuiper_q, kuiper_q_series_for_tests, kuiper_sf,
    kuiper_uniform, EXACT_MAX_N as KUIPER_EXACT_MAX_N, METHOD_EXACT,
};
use super::mc::{self, simulate, simulate_samples, Ism, McConfig, PIntDist, CHUNK_PAIRS};
use super::model::{AlignmentModel, AlphaMeasure, AlphaTable};
use super::rng::Xoshiro256pp;
use super::sample::BinarySample;
use crate::catalog::{fold_delta_gamma, Catalog, Component, Status, Target};

fn reference() -> Value {
    serde_json::from_str(include_str!("../../../testdata/stats/reference.json")).unwrap()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(f).collect()
}

fn rel_close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * b.abs().max(1e-300)
}

// ---------------------------------------------------------------- references

#[test]
fn ks_one_sample_matches_scipy() {
    let r = reference();
    for e in r["one_sample"].as_array().unwrap() {
        let name = e["name"].as_str().unwrap();
        let data = floats(&e["data"]);
        let t = ks_uniform(&data, 0.0, 90.0);
        assert!(
            (t.statistic - f(&e["ks_d"])).abs() < 1e-12,
            "{name}: D {} vs {}",
            t.statistic,
            e["ks_d"]
        );
        let exact = f(&e["ks_p_exact"]);
        if data.len() <= EXACT_MAX_N {
            assert!(
                rel_close(t.p_value, exact, 1e-7),
                "{name}: p {} vs scipy exact {exact}",
                t.p_value
            );
        } else {
            // Asymptotic with Stephens' correction: within 1 % of the exact value here.
            assert!(
                rel_close(t.p_value, exact, 0.01),
                "{name}: p {} vs scipy exact {exact}",
                t.p_value
            );
        }
    }
}

#[test]
fn kolmogorov_sf_matches_kstwo_including_far_tail() {
    let r = reference();
    for e in r["kolmogorov_sf"].as_array().unwrap() {
        let (d, n, sf) = (f(&e["d"]), e["n"].as_u64().unwrap() as usize, f(&e["sf"]));
        let (p, method) = kolmogorov_sf(d, n);
        assert!(
            rel_close(p, sf, 1e-7),
            "d = {d}, n = {n}: {p} ({method}) vs scipy kstwo {sf}"
        );
    }
    for e in r["asymptotic_kolmogorov"].as_array().unwrap() {
        let (d, n, sf) = (f(&e["d"]), e["n"].as_u64().unwrap() as usize, f(&e["sf_scipy_kstwo"]));
        let (p, _) = kolmogorov_sf(d, n);
        assert!(rel_close(p, sf, 0.01), "asymptotic d = {d}, n = {n}: {p} vs {sf}");
    }
}

#[test]
fn kuiper_matches_astropy_mpmath_and_monte_carlo() {
    let r = reference();
    for e in r["one_sample"].as_array().unwrap() {
        let name = e["name"].as_str().unwrap();
        let data = floats(&e["data"]);
        let t = kuiper_uniform(&data, 0.0, 90.0);
        assert!(
            (t.statistic - f(&e["kuiper_v"])).abs() < 1e-12,
            "{name}: V {} vs astropy {}",
            t.statistic,
            e["kuiper_v"]
        );
        let n = data.len();
        let stephens = f(&e["kuiper_p_stephens_mpmath"]);
        assert!(
            rel_close(kuiper_sf(t.statistic, n), stephens, 1e-9),
            "{name}: Stephens p {} vs mpmath {stephens}",
            kuiper_sf(t.statistic, n)
        );
        assert_eq!(
            t.method,
            if n <= KUIPER_EXACT_MAX_N {
                METHOD_EXACT
            } else {
                super::kuiper::METHOD_STEPHENS
            }
        );
        // astropy's Paltani (2004) formulas may be up to 1.5x high; they agree within that.
        let paltani = f(&e["kuiper_p_astropy_paltani"]);
        assert!(
            t.p_value / paltani < 1.5 && paltani / t.p_value < 1.5,
            "{name}: {} vs astropy {paltani}",
            t.p_value
        );
        // Against brute force: exact within 4 standard errors, Stephens (n > 200) within 5 % + 4 SE.
        if let Some(mcp) = e.get("kuiper_p_monte_carlo") {
            let (mcp, se) = (f(mcp), f(&e["kuiper_p_monte_carlo_se"]));
            let slack = if n <= KUIPER_EXACT_MAX_N { 0.0 } else { 0.05 * mcp };
            assert!(
                (t.p_value - mcp).abs() < slack + 4.0 * se,
                "{name}: {} vs Monte Carlo {mcp} +- {se}",
                t.p_value
            );
        }
    }
}

/// testdata/stats/kuiper_exact.json (make_kuiper_exact.py): Stephens' (1965) exact upper
/// tail in 50-digit mpmath where it applies, else a 10^7-sample numpy Monte Carlo.
#[test]
fn kuiper_exact_small_n_matches_independent_references_within_one_percent() {
    let r: Value = serde_json::from_str(include_str!("../../../testdata/stats/kuiper_exact.json")).unwrap();
    let mut ns = std::collections::BTreeSet::new();
    for e in r["cases"].as_array().unwrap() {
        let (n, v) = (e["n"].as_u64().unwrap() as usize, f(&e["v"]));
        ns.insert(n);
        let (p, method) = kuiper_p(v, n);
        assert_eq!(method, METHOD_EXACT);
        let (mc, se) = (f(&e["monte_carlo"]), f(&e["monte_carlo_se"]));
        println!(
            "n {n:2} V {v:.2}: exact {p:.6e}, Monte Carlo {mc:.6e} +- {se:.1e} ({:+.1} SE)",
            (p - mc) / se
        );
        if let Some(ex) = e.get("stephens1965_exact") {
            let ex = f(ex);
            assert!(rel_close(p, ex, 1e-9), "n {n} V {v}: {p} vs Stephens 1965 exact {ex}");
        } else {
            assert!(se < 0.0025 * mc, "n {n} V {v}: reference too imprecise");
            assert!(rel_close(p, mc, 0.01), "n {n} V {v}: {p} vs Monte Carlo {mc} +- {se}");
        }
        assert!(
            (p - mc).abs() < 4.5 * se.max(1e-6),
            "n {n} V {v}: {p} vs Monte Carlo {mc} +- {se}"
        );
    }
    assert_eq!(ns.into_iter().collect::<Vec<_>>(), vec![5, 9, 12, 20]);
    // Analytic cases: n = 1, V = 1 always; n = 2, V = max(g, 1 - g) with g uniform.
    assert_eq!(kuiper_cdf_exact(0.999, 1), 0.0);
    assert_eq!(kuiper_cdf_exact(1.0, 1), 1.0);
    for v in [0.5, 0.6, 0.75, 0.9, 0.99] {
        assert!((kuiper_cdf_exact(v, 2) - 2.0 * (v - 0.5)).abs() < 1e-14, "n 2 V {v}");
    }
    // V_n >= 1/n; monotone CDF; continuous and close to Stephens at n = 200.
    for n in [3, 7, 30, 200] {
        assert_eq!(kuiper_cdf_exact(0.999 / n as f64, n), 0.0);
        let mut prev = 0.0;
        for i in 0..=100 {
            let c = kuiper_cdf_exact(i as f64 / 100.0, n);
            assert!(
                c >= prev - 1e-14 && c <= 1.0,
                "n {n}: not monotone at {}",
                i as f64 / 100.0
            );
            prev = c;
        }
    }
    let (pe, ps) = (1.0 - kuiper_cdf_exact(0.13, 200), kuiper_sf(0.13, 200));
    assert!(rel_close(pe, ps, 0.02), "n 200: exact {pe} vs Stephens {ps}");
}

#[test]
fn kuiper_q_matches_mpmath_and_is_continuous_at_the_switch() {
    let r = reference();
    for e in r["kuiper_q"].as_array().unwrap() {
        let (lam, q) = (f(&e["lambda"]), f(&e["q"]));
        let ours = kuiper_q(lam);
        assert!(
            (ours - q).abs() <= 1e-13 + 1e-11 * q,
            "Q_KP({lam}) = {ours} vs mpmath {q}"
        );
    }
    // The two representations agree where both converge.
    for i in 0..=40 {
        let lam = 0.7 + 0.015 * i as f64;
        let a = kuiper_q_series_for_tests(lam);
        let b = 1.0 - kuiper_cdf_dual_for_tests(lam);
        assert!((a - b).abs() < 1e-14, "lambda {lam}: series {a} vs dual {b}");
    }
    // Limits and monotonicity.
    assert_eq!(kuiper_q(0.0), 1.0);
    assert!(kuiper_q(0.2) > 1.0 - 1e-15 && kuiper_q(0.2) <= 1.0);
    let mut prev = 1.0;
    for i in 1..200 {
        let q = kuiper_q(0.05 * i as f64);
        assert!(q <= prev && q >= 0.0, "Q_KP not monotone at {}", 0.05 * i as f64);
        prev = q;
    }
    // Far tail: the leading term 2 (4 lambda^2 - 1) exp(-2 lambda^2) alone, to full precision.
    let lead = 2.0 * (4.0 * 36.0 - 1.0) * (-72f64).exp();
    assert!(rel_close(kuiper_q(6.0), lead, 1e-12), "{} vs {lead}", kuiper_q(6.0));
}

#[test]
fn ks_two_sample_matches_scipy_asymp() {
    let r = reference();
    for e in r["two_sample"].as_array().unwrap() {
        let name = e["name"].as_str().unwrap();
        let t = ks_two_sample(&floats(&e["a"]), &floats(&e["b"]));
        assert!(
            (t.statistic - f(&e["d"])).abs() < 1e-12,
            "{name}: D {} vs {}",
            t.statistic,
            e["d"]
        );
        assert!(
            rel_close(t.p_value, f(&e["p_asymp"]), 1e-7),
            "{name}: p {} vs {}",
            t.p_value,
            e["p_asymp"]
        );
    }
}

#[test]
fn binomial_matches_scipy_binomtest() {
    let r = reference();
    for e in r["binomial"].as_array().unwrap() {
        let (k, n) = (e["k"].as_u64().unwrap(), e["n"].as_u64().unwrap());
        let b = binomial_test(k, n, f(&e["p0"]));
        assert!(
            rel_close(b.p_greater, f(&e["p_greater"]), 1e-9),
            "{k}/{n}: {} vs {}",
            b.p_greater,
            e["p_greater"]
        );
        assert!(
            rel_close(b.p_two_sided, f(&e["p_two_sided"]), 1e-9),
            "{k}/{n}: {} vs {}",
            b.p_two_sided,
            e["p_two_sided"]
        );
    }
}

// ------------------------------------------------------- fast vs slow, invariants

#[test]
fn ks_statistics_match_brute_force_and_statrs() {
    let mut rng = Xoshiro256pp::from_seed(99);
    let cdf = |x: f64| (x / 90.0).clamp(0.0, 1.0);
    for case in 0..200 {
        let n = 1 + (case % 40);
        let data: Vec<f64> = (0..n)
            .map(|_| 90.0 * rng.uniform().powf(1.0 + (case % 3) as f64 * 0.5))
            .collect();
        let (d, dp, dm) = ks_statistics(&data, &cdf);
        // Brute force: sup over x of ECDF(x) - F(x) and F(x) - ECDF(x-), at every data point.
        let ecdf = |x: f64, strict: bool| {
            data.iter().filter(|&&v| if strict { v < x } else { v <= x }).count() as f64 / n as f64
        };
        let bp = data.iter().map(|&x| ecdf(x, false) - cdf(x)).fold(0.0f64, f64::max);
        let bm = data.iter().map(|&x| cdf(x) - ecdf(x, true)).fold(0.0f64, f64::max);
        assert!((dp - bp).abs() < 1e-14 && (dm - bm).abs() < 1e-14, "case {case}");
        assert_eq!(d, dp.max(dm));
        if n >= 2 {
            // statrs computes D independently (no exact p for us: it needs nalgebra).
            let (sd, _) = statrs::stats_tests::ks_test::ks_onesample(
                data.clone(),
                &statrs::distribution::Uniform::new(0.0, 90.0).unwrap(),
                statrs::stats_tests::ks_test::KSOneSampleAlternativeMethod::TwoSidedAsymptotic,
                statrs::stats_tests::NaNPolicy::Error,
            )
            .unwrap();
            assert!((sd - d).abs() < 1e-12, "case {case}: statrs D {sd} vs {d}");
        }
    }
}

/// Q_KS(lambda) against scipy's `special.kolmogorov` (testdata/stats/kolmogorov.json) to
/// 1e-11 relative: on both sides of the switch between the two series at lambda = 1, in the
/// far tail (Q = 3e-8 to 1e-31, where 1 - sum would keep no digit) and near 0 (where the
/// alternating series would need hundreds of terms).
#[test]
fn kolmogorov_q_matches_scipy_on_both_series_and_in_the_far_tail() {
    let r: Value = serde_json::from_str(include_str!("../../../testdata/stats/kolmogorov.json")).unwrap();
    for e in r["q"].as_array().unwrap() {
        let (lambda, want) = (f(&e["lambda"]), f(&e["q"]));
        let got = super::ks::kolmogorov_q(lambda);
        assert!(
            rel_close(got, want, 1e-11),
            "lambda {lambda}: {got:e} vs scipy {want:e}"
        );
    }
    assert_eq!(super::ks::kolmogorov_q(0.0), 1.0);
    assert_eq!(super::ks::kolmogorov_q(-1.0), 1.0);
}

/// The exact P(D_n >= d) at odd n near the exact method's limit (999, 997): the matrix
/// power's entries pass 1e140 and are rescaled, and its odd steps then add the exponents of
/// A and A^(2k) (n = 1000, in `kolmogorov_sf_matches_kstwo_including_far_tail`, has no odd
/// step after the rescaling begins); at n = 513 the power carries the exponent 140, which
/// the final loop over n!/n^n must take back once. Against the same matrix formula in 50-digit mpmath
/// (testdata/stats/kolmogorov.json) to 1e-10, and scipy's `kstwo`, an approximation here,
/// to 1e-6 (it is off by up to 3.4e-7).
#[test]
fn kolmogorov_sf_at_odd_n_matches_the_50_digit_formula() {
    let r: Value = serde_json::from_str(include_str!("../../../testdata/stats/kolmogorov.json")).unwrap();
    for e in r["sf"].as_array().unwrap() {
        let (d, n) = (f(&e["d"]), e["n"].as_u64().unwrap() as usize);
        let (want, scipy) = (f(&e["sf"]), f(&e["sf_scipy"]));
        let (p, method) = kolmogorov_sf(d, n);
        assert!(
            rel_close(p, want, 1e-10),
            "d {d} n {n}: {p} ({method}) vs 50 digits {want}"
        );
        assert!(rel_close(p, scipy, 1e-6), "d {d} n {n}: {p} vs scipy {scipy}");
    }
}

/// The trivial cases of P(D_n >= d): no data or d <= 0 give 1, d >= 1 gives 0 (D <= 1).
#[test]
fn kolmogorov_sf_trivial_cases() {
    for (d, n) in [(0.5, 0), (0.0, 10), (-0.2, 10), (-0.2, 5000)] {
        assert_eq!(kolmogorov_sf(d, n), (1.0, "trivial"), "d {d} n {n}");
    }
    for (d, n) in [(1.0, 10), (1.5, 5000)] {
        assert_eq!(kolmogorov_sf(d, n), (0.0, "trivial"), "d {d} n {n}");
    }
}

/// Kuiper's V on an interval that does not start at 0, by hand: u = 0.1, 0.35, 0.4, 0.9 of
/// the interval give D+ = 0.75 - 0.4 = 0.35 and D- = 0.9 - 0.75 = 0.15, V = 0.5, on [10, 100]
/// and on [-90, 0] alike; the p-value is the exact one of V = 0.5, n = 4.
#[test]
fn kuiper_uniform_scales_any_interval_to_the_unit_one() {
    let u = [0.4, 0.1, 0.9, 0.35];
    for (lo, hi) in [(10.0, 100.0), (-90.0, 0.0), (0.0, 1.0)] {
        let data: Vec<f64> = u.iter().map(|x| lo + (hi - lo) * x).collect();
        let t = kuiper_uniform(&data, lo, hi);
        assert!((t.statistic - 0.5).abs() < 1e-12, "[{lo}, {hi}]: V {}", t.statistic);
        assert_eq!(t.n, 4);
        assert!((t.p_value - kuiper_p(0.5, 4).0).abs() < 1e-12, "[{lo}, {hi}]: {t:?}");
    }
}

/// The trivial cases of the asymptotic P(V_n >= v): no data or v <= 0 give 1.
#[test]
fn kuiper_sf_trivial_cases() {
    for (v, n) in [(0.5, 0), (0.0, 300), (-0.1, 300)] {
        assert_eq!(kuiper_sf(v, n), 1.0, "v {v} n {n}");
    }
    assert!(kuiper_sf(0.5, 300) < 1e-20);
}

#[test]
fn kolmogorov_tail_formula_agrees_with_exact_where_they_overlap() {
    // Around the switch both are valid: 2 P(D+ >= d) and 1 - K(d) agree to ~p^2.
    for (d, n) in [(0.42, 34usize), (0.40, 34), (0.2, 120)] {
        let tail = 2.0 * smirnov_sf(d, n);
        let sn = (n as f64).sqrt();
        let (p, _) = kolmogorov_sf(d, n);
        assert!(rel_close(p, tail, 1e-4), "d {d} n {n}: {p} vs {tail}");
        // and the asymptotic law is in the right neighbourhood
        let asym = super::ks::kolmogorov_q((sn + 0.12 + 0.11 / sn) * d);
        assert!(rel_close(asym, p, 0.2), "asymptotic {asym} vs exact {p}");
    }
}

#[test]
fn fast_angle_formulas_match_trigonometry() {
    let mut rng = Xoshiro256pp::from_seed(5);
    for _ in 0..20_000 {
        let (x1, y1, x2, y2) = (
            rng.uniform_pm1(),
            rng.uniform_pm1(),
            rng.uniform_pm1(),
            rng.uniform_pm1(),
        );
        let pa = |x: f64, y: f64| y.atan2(x).to_degrees();
        let slow = fold_delta_gamma(pa(x1, y1), pa(x2, y2));
        let fast = mc::delta_gamma_axes(x1, y1, x2, y2);
        assert!((slow - fast).abs() < 1e-9, "axes: {slow} vs {fast}");
        let g = |q: f64, u: f64| 0.5 * u.atan2(q).to_degrees();
        let slow = fold_delta_gamma(g(x1, y1), g(x2, y2));
        let fast = mc::delta_gamma_qu(x1, y1, x2, y2);
        assert!((slow - fast).abs() < 1e-9, "qu: {slow} vs {fast}");
        // Intrinsic polarization is along the long axis: 90 deg from the projected spin axis.
        let (q, u) = mc::intrinsic_qu(3.0, x1, y1);
        assert!(((q * q + u * u).sqrt() - 3.0).abs() < 1e-12);
        assert!((fold_delta_gamma(g(q, u), pa(x1, y1)) - 90.0).abs() < 1e-9);
    }
    // The convention spelled out: an axis pointing north gives gamma = 90 deg (east-west E vector).
    let (q, u) = mc::intrinsic_qu(1.0, 1.0, 0.0);
    assert_eq!((q, u), (-1.0, 0.0));
}

fn geometry(model: AlignmentModel, pairs: u64, seed: u64) -> McConfig {
    McConfig::geometry(model, pairs, seed)
}

#[test]
fn isotropic_alignment_gives_flat_pi_delta_gamma_across_seeds() {
    for seed in [1u64, 2, 3, 20010101] {
        let (s, out) = simulate_samples(&geometry(AlignmentModel::Random, 1_000_000, seed)).unwrap();
        assert_eq!(out.accepted, 1_000_000);
        let ks = ks_uniform(&s, 0.0, 90.0);
        let kp = kuiper_uniform(&s, 0.0, 90.0);
        assert!(
            ks.p_value > 1e-3,
            "seed {seed}: KS D = {} p = {}",
            ks.statistic,
            ks.p_value
        );
        assert!(
            kp.p_value > 1e-3,
            "seed {seed}: Kuiper V = {} p = {}",
            kp.statistic,
            kp.p_value
        );
        // And the 90-bin histogram is flat by a chi-square test.
        let e = 1_000_000.0 / 90.0;
        let chi2: f64 = out.histogram.counts.iter().map(|&c| (c as f64 - e).powi(2) / e).sum();
        let p =
            1.0 - statrs::distribution::ContinuousCDF::cdf(&statrs::distribution::ChiSquared::new(89.0).unwrap(), chi2);
        assert!(p > 1e-3, "seed {seed}: chi2 = {chi2}, p = {p}");
    }
}

#[test]
fn equivalent_descriptions_of_random_orientation_are_flat_too() {
    // A 90-deg cone is isotropic for axes; so is a table flat per solid angle, or sin(alpha) per alpha.
    let flat_sa = AlphaTable::new("flat", vec![0.0, 180.0], vec![1.0, 1.0], AlphaMeasure::SolidAngle).unwrap();
    let xs: Vec<f64> = (0..=180).map(|i| i as f64).collect();
    let sin_alpha = AlphaTable::new(
        "sin",
        xs.clone(),
        xs.iter().map(|a| a.to_radians().sin()).collect(),
        AlphaMeasure::Alpha,
    )
    .unwrap();
    for model in [
        AlignmentModel::Cone { alpha0_deg: 90.0 },
        AlignmentModel::Table(flat_sa),
        AlignmentModel::Table(sin_alpha),
    ] {
        let (s, _) = simulate_samples(&geometry(model.clone(), 1_000_000, 7)).unwrap();
        let ks = ks_uniform(&s, 0.0, 90.0);
        assert!(ks.p_value > 1e-3, "{}: KS p = {}", model.spec(), ks.p_value);
    }
}

#[test]
fn the_flatness_test_has_power_against_alignment() {
    // Pi(alpha) flat per unit alpha is NOT isotropic (too many small alpha): must be rejected.
    let flat_alpha = AlphaTable::new("flat-per-alpha", vec![0.0, 90.0], vec![1.0, 1.0], AlphaMeasure::Alpha).unwrap();
    for model in [
        AlignmentModel::Table(flat_alpha),
        AlignmentModel::Spread { sigma_deg: 60.0 },
        AlignmentModel::Cone { alpha0_deg: 60.0 },
    ] {
        let (s, _) = simulate_samples(&geometry(model.clone(), 200_000, 3)).unwrap();
        let ks = ks_uniform(&s, 0.0, 90.0);
        assert!(
            ks.p_value < 1e-10,
            "{}: KS p = {} should reject",
            model.spec(),
            ks.p_value
        );
        let mean = s.iter().sum::<f64>() / s.len() as f64;
        assert!(mean < 44.0, "{}: mean {mean} should be below 45", model.spec());
    }
}

#[test]
fn perfect_alignment_gives_zero_delta_gamma() {
    let n = 3 * CHUNK_PAIRS + 17;
    let (s, out) = simulate_samples(&geometry(AlignmentModel::Aligned, n, 11)).unwrap();
    assert!(s.iter().all(|&d| d == 0.0));
    assert_eq!(out.histogram.counts[0], n);
    assert_eq!(out.histogram.total(), n);
    // Still exactly zero with a common ISM and a fixed intrinsic P (same angle, same P).
    let mut cfg = geometry(AlignmentModel::Aligned, 100_000, 12);
    cfg.p_int = PIntDist::Fixed { p_percent: 4.0 };
    cfg.ism = Some(Ism {
        p_percent: 2.0,
        angle_deg: 33.0,
    });
    let (s, _) = simulate_samples(&cfg).unwrap();
    assert!(
        s.iter().all(|&d| d < 1e-9),
        "max {}",
        s.iter().cloned().fold(0.0, f64::max)
    );
}

#[test]
fn measurement_noise_has_the_wardle_kronberg_width() {
    // Aligned disks, P = 10 %, sigma = 0.5 %: sigma_gamma = 28.65 deg * sigma/P per component,
    // the difference has sigma sqrt(2) sigma_gamma and |difference| has mean sigma sqrt(2/pi).
    let mut cfg = geometry(AlignmentModel::Aligned, 400_000, 21);
    cfg.p_int = PIntDist::Fixed { p_percent: 10.0 };
    cfg.noise_percent = Some(0.5);
    let (s, _) = simulate_samples(&cfg).unwrap();
    let mean = s.iter().sum::<f64>() / s.len() as f64;
    let sigma_gamma = (0.5 * 0.5f64 / 10.0).to_degrees(); // sigma_P / (2P) rad = 28.65 deg * 0.05
    let expected = 2f64.sqrt() * sigma_gamma * (2.0 / std::f64::consts::PI).sqrt();
    assert!(
        (mean / expected - 1.0).abs() < 0.01,
        "mean |dgamma| {mean} vs {expected}"
    );
}

#[test]
fn rising_ism_makes_pi_delta_gamma_fall_more_steeply() {
    let levels = [0.0, 0.5, 1.0, 2.0, 4.0];
    let mut fractions = Vec::new();
    let mut ratios = Vec::new();
    for &p in &levels {
        let mut cfg = geometry(AlignmentModel::Random, 400_000, 31);
        cfg.ism = Some(Ism {
            p_percent: p,
            angle_deg: 0.0,
        });
        let out = simulate(&cfg).unwrap();
        let h = &out.histogram;
        let below30 = h.counts[..30].iter().sum::<u64>() as f64 / h.total() as f64;
        let first = h.counts[..10].iter().sum::<u64>() as f64;
        let last = h.counts[80..].iter().sum::<u64>() as f64;
        fractions.push(below30);
        ratios.push(first / last);
        if p == 0.0 {
            // No ISM: the polarization path reproduces the flat geometry.
            assert!(
                (below30 - 1.0 / 3.0).abs() < 4.0 * (2.0 / 9.0 / 400_000f64).sqrt(),
                "P_ism = 0: {below30}"
            );
        }
    }
    let se = (0.25 / 400_000f64).sqrt();
    for i in 1..levels.len() {
        assert!(
            fractions[i] > fractions[i - 1] + 3.0 * se,
            "fraction < 30 deg not rising: {fractions:?}"
        );
        assert!(
            ratios[i] > ratios[i - 1],
            "first/last decile ratio not rising: {ratios:?}"
        );
    }
    // Monotone decrease of Pi(Delta gamma) at a strong ISM (5-deg bins).
    let mut cfg = geometry(AlignmentModel::Random, 400_000, 32);
    cfg.ism = Some(Ism {
        p_percent: 4.0,
        angle_deg: 0.0,
    });
    let h = simulate(&cfg).unwrap().histogram.rebin(5).unwrap();
    for w in h.counts.windows(2) {
        assert!(w[1] < w[0], "not decreasing: {:?}", h.counts);
    }
}

#[test]
fn ism_angle_does_not_matter_for_isotropic_disks() {
    let run = |angle: f64, seed: u64| {
        let mut cfg = geometry(AlignmentModel::Random, 300_000, seed);
        cfg.ism = Some(Ism {
            p_percent: 2.0,
            angle_deg: angle,
        });
        cfg.p_int = PIntDist::LogNormal {
            median_percent: 3.0,
            sigma_ln: 0.5,
        };
        simulate_samples(&cfg).unwrap().0
    };
    let t = ks_two_sample(&run(0.0, 41), &run(37.0, 42));
    assert!(
        t.p_value > 1e-3,
        "ISM angle changed Pi(dgamma): D = {} p = {}",
        t.statistic,
        t.p_value
    );
}

#[test]
fn results_are_identical_for_any_thread_count() {
    let mut pol = geometry(AlignmentModel::Spread { sigma_deg: 30.0 }, 5 * CHUNK_PAIRS + 123, 77);
    pol.ism = Some(Ism {
        p_percent: 1.0,
        angle_deg: 10.0,
    });
    pol.noise_percent = Some(0.3);
    pol.snr_cut = Some(3.0);
    pol.p_int = PIntDist::LogNormal {
        median_percent: 2.0,
        sigma_ln: 0.7,
    };
    for cfg in [geometry(AlignmentModel::Random, 7 * CHUNK_PAIRS + 5, 5), pol] {
        let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let two = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        let h1 = one.install(|| simulate(&cfg)).unwrap();
        let h2 = two.install(|| simulate(&cfg)).unwrap();
        assert_eq!(h1, h2);
        let s1 = one.install(|| simulate_samples(&cfg)).unwrap();
        let s2 = two.install(|| simulate_samples(&cfg)).unwrap();
        assert_eq!(s1.0, s2.0);
        // Both entry points bin identically.
        assert_eq!(s1.1.histogram, h1.histogram);
        assert_eq!(h1.accepted, s1.0.len() as u64);
        let mut other = cfg.clone();
        other.seed += 1;
        assert_ne!(simulate(&other).unwrap().histogram, h1.histogram);
    }
}

/// P(|(nu, 0) + N(0, 1)^2| > k), the Rice tail (Marcum Q_1), by quadrature.
fn rice_tail(nu: f64, k: f64) -> f64 {
    let i0 = |x: f64| {
        let (mut s, mut t) = (1.0, 1.0);
        for j in 1..200 {
            t *= (x / 2.0) * (x / 2.0) / (j * j) as f64;
            s += t;
            if t < 1e-17 * s {
                break;
            }
        }
        s
    };
    let (h, mut s) = (1e-3, 0.0);
    let mut x = k + h / 2.0;
    while x < nu + 12.0 {
        s += x * (-(x * x + nu * nu) / 2.0).exp() * i0(nu * x) * h;
        x += h;
    }
    s
}

#[test]
fn snr_cut_keeps_the_expected_fraction() {
    // Fixed P = 1 %, noise 0.5 %: each component passes P/sigma > 3 with the Rice tail
    // probability at nu = 2, k = 3; both are independent.
    let mut cfg = geometry(AlignmentModel::Random, 300_000, 51);
    cfg.p_int = PIntDist::Fixed { p_percent: 1.0 };
    cfg.noise_percent = Some(0.5);
    cfg.snr_cut = Some(3.0);
    let out = simulate(&cfg).unwrap();
    let p = rice_tail(2.0, 3.0).powi(2);
    let frac = out.accepted as f64 / out.simulated as f64;
    let se = (p * (1.0 - p) / out.simulated as f64).sqrt();
    assert!((frac - p).abs() < 4.0 * se, "accepted {frac} vs {p} +- {se}");
    assert_eq!(out.histogram.total(), out.accepted);
}

fn folded_alpha_cdf(model: &AlignmentModel) -> impl Fn(f64) -> f64 {
    // CDF of alpha folded into [0, 90] from the analytic Pi(alpha): density sin(a) Pi_rel(a).
    let n = 20_000;
    let h = 90.0 / n as f64;
    let mut cdf = vec![0.0; n + 1];
    for i in 0..n {
        let a = h * (i as f64 + 0.5);
        cdf[i + 1] = cdf[i] + a.to_radians().sin() * model.pi_alpha_relative(a).unwrap() * h.to_radians();
    }
    move |x: f64| {
        let pos = (x / h).clamp(0.0, n as f64);
        let i = (pos as usize).min(n - 1);
        cdf[i] + (cdf[i + 1] - cdf[i]) * (pos - i as f64)
    }
}

#[test]
fn alpha_samplers_follow_their_analytic_pi_alpha() {
    let tab = AlphaTable::parse("inline", "# measure: solid_angle\n0 3\n40 1\n90 0.5\n180 0.5\n").unwrap();
    for model in [
        AlignmentModel::Random,
        AlignmentModel::Spread { sigma_deg: 25.0 },
        AlignmentModel::Spread { sigma_deg: 60.0 },
        AlignmentModel::Spread { sigma_deg: 2.0 },
        AlignmentModel::Cone { alpha0_deg: 30.0 },
        AlignmentModel::Table(tab),
    ] {
        let cdf = folded_alpha_cdf(&model);
        assert!(
            (cdf(90.0) - 1.0).abs() < 1e-4,
            "{}: Pi(alpha) integrates to {}",
            model.spec(),
            cdf(90.0)
        );
        let mut rng = Xoshiro256pp::from_seed(61);
        let a: Vec<f64> = (0..200_000)
            .map(|_| {
                let x = model.sample_alpha_deg(&mut rng);
                if x > 90.0 {
                    180.0 - x
                } else {
                    x
                }
            })
            .collect();
        let t = super::ks::ks_one_sample(&a, &cdf);
        assert!(
            t.p_value > 1e-3,
            "{}: sampled alpha vs analytic, D = {} p = {}",
            model.spec(),
            t.statistic,
            t.p_value
        );
        if let AlignmentModel::Cone { alpha0_deg } = model {
            assert!(a.iter().all(|&x| x <= alpha0_deg + 1e-9));
        }
    }
    // von Mises-Fisher: E cos(alpha) = coth(kappa) - 1/kappa.
    let mut rng = Xoshiro256pp::from_seed(62);
    let m = AlignmentModel::Spread { sigma_deg: 40.0 };
    let k = 1.0 / 40f64.to_radians().powi(2);
    let mean = (0..200_000)
        .map(|_| m.sample_alpha_deg(&mut rng).to_radians().cos())
        .sum::<f64>()
        / 200_000.0;
    assert!(
        (mean - (1.0 / k.tanh() - 1.0 / k)).abs() < 0.003,
        "E cos alpha = {mean}"
    );
}

#[test]
fn strong_but_imperfect_alignment_still_gives_large_delta_gamma() {
    // The reference study's remark on model (d): Delta gamma > alpha_0 is still possible.
    let out = simulate(&geometry(AlignmentModel::Cone { alpha0_deg: 20.0 }, 200_000, 71)).unwrap();
    let beyond = out.histogram.counts[20..].iter().sum::<u64>() as f64 / out.histogram.total() as f64;
    assert!(beyond > 0.05, "fraction beyond alpha_0: {beyond}");
}

#[test]
fn specs_parse_and_bad_input_is_refused() {
    assert_eq!(AlignmentModel::parse("random").unwrap(), AlignmentModel::Random);
    assert_eq!(
        AlignmentModel::parse("spread:15").unwrap(),
        AlignmentModel::Spread { sigma_deg: 15.0 }
    );
    assert_eq!(
        AlignmentModel::parse("uniform:30").unwrap(),
        AlignmentModel::Cone { alpha0_deg: 30.0 }
    );
    for bad in [
        "",
        "spread",
        "spread:-1",
        "uniform:0",
        "uniform:200",
        "table:/nonexistent/x",
        "nonsense:3",
    ] {
        assert!(AlignmentModel::parse(bad).is_err(), "{bad} accepted");
    }
    assert_eq!(
        PIntDist::parse("lognormal:3,0.5").unwrap(),
        PIntDist::LogNormal {
            median_percent: 3.0,
            sigma_ln: 0.5
        }
    );
    assert_eq!(
        PIntDist::parse("sin2i:6").unwrap(),
        PIntDist::Sin2i { p_max_percent: 6.0 }
    );
    for bad in [
        "fixed",
        "fixed:-1",
        "uniform:3,1",
        "lognormal:0,1",
        "sin2i:a",
        "table:/nonexistent",
    ] {
        assert!(PIntDist::parse(bad).is_err(), "{bad} accepted");
    }
    assert!(AlphaTable::parse("t", "0 1\n0 2\n").is_err());
    assert!(AlphaTable::parse("t", "0 1\n10 -2\n").is_err());
    assert!(AlphaTable::parse("t", "0 0\n10 0\n").is_err());
    assert!(AlphaTable::parse("t", "# measure: volume\n0 1\n10 1\n").is_err());
    let mut cfg = geometry(AlignmentModel::Random, 10, 1);
    cfg.snr_cut = Some(3.0);
    assert!(simulate(&cfg).is_err(), "a cut without noise must be refused");
    cfg.snr_cut = None;
    cfg.pairs = 0;
    assert!(simulate(&cfg).is_err());
}

#[test]
fn histogram_tables_and_catalog_p_are_drawn_from() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("p.txt");
    std::fs::write(&p, "# lo hi weight\n1 2 1\n2 3 0\n3 5 3\n").unwrap();
    let d = PIntDist::parse(&format!("table:{}", p.display())).unwrap();
    let mut cfg = geometry(AlignmentModel::Random, 20_000, 3);
    cfg.p_int = d;
    cfg.ism = Some(Ism {
        p_percent: 0.5,
        angle_deg: 0.0,
    });
    assert_eq!(simulate(&cfg).unwrap().accepted, 20_000);
    let cat = test_catalog();
    let path = dir.path().join("cat.json");
    std::fs::write(&path, serde_json::to_string(&cat).unwrap()).unwrap();
    match PIntDist::parse(&format!("catalog:{}", path.display())).unwrap() {
        PIntDist::Empirical { values, .. } => assert_eq!(values, vec![5.0, 3.0, 2.0, 4.0]),
        other => panic!("{other:?}"),
    }
}

// ------------------------------------------------------------ sample and verdict

fn component(name: &str, p: f64, sigma_p: f64, gamma: f64) -> Component {
    let two_g = 2.0 * gamma.to_radians();
    Component {
        pol: crate::stokes::inversion::Polarization {
            q: p * two_g.cos(),
            u: p * two_g.sin(),
            sigma_q: sigma_p,
            sigma_u: sigma_p,
            p,
            sigma_p,
            p_debiased: p,
            gamma_deg: gamma,
            sigma_gamma_deg: 28.65 * sigma_p / p,
        },
        passes_cut: p / sigma_p > 3.0,
        ..Component::new(name, crate::stokes::inversion::Polarization::UNDEFINED)
    }
}

fn target(name: &str, status: Status, comps: Vec<Component>, stored: Option<f64>) -> Target {
    Target {
        components: comps,
        delta_gamma_deg: stored,
        ..Target::new(name, status)
    }
}

fn test_catalog() -> Catalog {
    Catalog {
        schema_version: "1.0".into(),
        targets: vec![
            target(
                "both",
                Status::Ok,
                vec![component("A", 0.05, 0.005, 10.0), component("B", 0.03, 0.005, 170.0)],
                Some(20.0),
            ),
            target(
                "weakB",
                Status::Ok,
                vec![component("A", 0.05, 0.005, 10.0), component("B", 0.01, 0.005, 80.0)],
                None,
            ),
            target("failed", Status::Failed, vec![], None),
            target("single", Status::Partial, vec![component("A", 0.05, 0.005, 10.0)], None),
            target(
                "stale",
                Status::Ok,
                vec![component("A", 0.02, 0.002, 0.0), component("B", 0.04, 0.004, 100.0)],
                Some(12.0),
            ),
        ],
        failures: vec![],
        provenance: Default::default(),
        ..Default::default()
    }
}

#[test]
fn sample_takes_binaries_with_both_components_above_the_cut() {
    let s = BinarySample::from_catalog(&test_catalog(), None);
    assert_eq!(s.len(), 2);
    assert_eq!(s.delta_gamma_deg(), vec![20.0, 80.0]);
    assert_eq!(s.excluded.len(), 3);
    assert!(s.excluded.iter().any(|e| e.object == "weakB" && e.reason.contains('B')));
    assert_eq!(
        s.warnings.len(),
        1,
        "the stale stored delta_gamma is reported: {:?}",
        s.warnings
    );
    assert_eq!(s.p_percent(), vec![5.0, 3.0, 2.0, 4.0]);
    // sigma_P of every component of two-component targets (passing or not), percent.
    assert_eq!(s.all_sigma_p_percent.len(), 6);
    assert!((s.median_sigma_p_percent().unwrap() - 0.5).abs() < 1e-12);
    // A stricter recomputed cut drops the weaker pair.
    let strict = BinarySample::from_catalog(&test_catalog(), Some(7.0));
    assert_eq!(strict.delta_gamma_deg(), vec![80.0]);
}

fn params(pairs: u64) -> AnalysisParams {
    AnalysisParams {
        significance: 0.05,
        threshold_deg: 30.0,
        ism_levels_percent: vec![0.5, 5.0],
        ism_angle_deg: 0.0,
        mc: McConfig {
            p_int: PIntDist::LogNormal {
                median_percent: 3.0,
                sigma_ln: 0.5,
            },
            ..geometry(AlignmentModel::Random, pairs, 9)
        },
        models: Vec::new(),
        errors: Default::default(),
        per_binary: None,
    }
}

#[test]
fn tiny_samples_get_a_message_not_a_crash() {
    for (dg, says) in [
        (vec![], "No binary has both components above the P/sigma cut"),
        (vec![12.0], "Only one binary (12.0 deg)"),
    ] {
        let r = analyse(&dg, &params(1000)).unwrap();
        assert!(r.ks_uniform.is_none() && r.kuiper_uniform.is_none() && r.ism.is_empty());
        assert!(r.verdict.starts_with(says), "{}", r.verdict);
        assert!(r.verdict.contains("nothing to test") || r.verdict.contains("no test was run"));
    }
}

#[test]
fn verdict_on_a_strongly_aligned_sample_and_on_a_flat_one() {
    let r = reference();
    let skewed = floats(&r["one_sample"][0]["data"]);
    let rep = analyse(&skewed, &params(50_000)).unwrap();
    assert_eq!(rep.n, 34);
    assert!(rep.ks_uniform.as_ref().unwrap().p_value < 1e-5);
    assert!(
        rep.verdict.contains("rejected") && rep.verdict.contains("aligned"),
        "{}",
        rep.verdict
    );
    assert_eq!(rep.ism.len(), 2);
    // 5 % ISM produces a much steeper Pi than 0.5 %: closer to the aligned sample.
    assert!(rep.ism[1].ks.statistic < rep.ism[0].ks.statistic);
    assert!(rep.ism[1].mc_fraction_below_threshold > rep.ism[0].mc_fraction_below_threshold);
    let flat: Vec<f64> = (0..40).map(|i| 90.0 * (i as f64 + 0.5) / 40.0).collect();
    let rep = analyse(&flat, &params(20_000)).unwrap();
    assert!(rep.verdict.contains("not rejected"), "{}", rep.verdict);
}

#[test]
fn histogram_cdf_is_consistent_with_counts() {
    let (h, _) = Histogram::from_values(0.0, 90.0, 18, &[1.0, 2.0, 6.0, 44.0, 89.0]);
    assert_eq!(h.total(), 5);
    assert!((h.cdf(5.0) - 0.4).abs() < 1e-12);
    assert!((h.cdf(90.0) - 1.0).abs() < 1e-12);
}

#[test]
fn figure_counts_use_superscripts_and_mc_mean_comes_from_the_pairs() {
    use super::figures::format_count;
    assert_eq!(format_count(10_000_000), "10⁷");
    assert_eq!(format_count(2_000_000), "2×10⁶");
    assert_eq!(format_count(123_456), "123456");
    assert_eq!(format_count(900), "900");
    // Aligned pairs: every Delta gamma is exactly 0, so the mean is 0, not half a bin.
    let out = simulate(&McConfig::geometry(AlignmentModel::Aligned, 100_000, 3)).unwrap();
    assert_eq!(out.mean_delta_gamma_deg, 0.0);
    // Random pairs: the mean of the samples, and 45 deg within 4 standard errors.
    let cfg = McConfig::geometry(AlignmentModel::Random, 200_000, 4);
    let (s, o) = simulate_samples(&cfg).unwrap();
    let m = s.iter().sum::<f64>() / s.len() as f64;
    assert!((o.mean_delta_gamma_deg - m).abs() < 1e-9);
    let h = simulate(&cfg).unwrap();
    assert!((h.mean_delta_gamma_deg - m).abs() < 1e-9);
    assert!(
        (m - 45.0).abs() < 4.0 * 90.0 / 12f64.sqrt() / (s.len() as f64).sqrt(),
        "{m}"
    );
}

// ---- perpendicular polarization and P(i) tables ----

fn with_perp(cfg: McConfig, f: [f64; 2]) -> McConfig {
    McConfig {
        perpendicular_fraction: f,
        ..cfg
    }
}

fn pol(model: AlignmentModel, pairs: u64, seed: u64, p_int: PIntDist, ism: Option<f64>, angle: f64) -> McConfig {
    McConfig {
        p_int,
        ism: ism.map(|p| Ism {
            p_percent: p,
            angle_deg: angle,
        }),
        noise_percent: Some(0.0),
        ..geometry(model, pairs, seed)
    }
}

/// Sum of |a_k - b_(n-1-k)|: zero when b is a mirrored (Delta gamma -> 90 - Delta gamma).
fn mirror_mismatch(a: &[u64], b: &[u64]) -> u64 {
    a.iter().zip(b.iter().rev()).map(|(x, y)| x.abs_diff(*y)).sum()
}

#[test]
fn perpendicular_on_both_components_leaves_pi_delta_gamma_unchanged() {
    // Geometry path: rotating both polarization angles by 90 deg changes no difference.
    for model in [AlignmentModel::Random, AlignmentModel::Cone { alpha0_deg: 30.0 }] {
        let base = geometry(model.clone(), 200_000, 5);
        let a = simulate(&base).unwrap();
        let b = simulate(&with_perp(base, [1.0, 1.0])).unwrap();
        assert_eq!(a.histogram.counts, b.histogram.counts, "{model:?}");
    }
    // With ISM: both (q, u) negated is the ISM vector negated (gamma_ism + 90 deg), pair by
    // pair, up to the last bit of sin(2 (gamma_ism + 90 deg)).
    let p = PIntDist::Sin2i { p_max_percent: 6.0 };
    let cone = AlignmentModel::Cone { alpha0_deg: 30.0 };
    let flipped = simulate(&with_perp(
        pol(cone.clone(), 200_000, 6, p.clone(), Some(2.0), 0.0),
        [1.0, 1.0],
    ))
    .unwrap();
    let rotated_ism = simulate(&pol(cone.clone(), 200_000, 6, p.clone(), Some(2.0), 90.0)).unwrap();
    assert!(
        mirror_mismatch(
            &flipped.histogram.counts,
            &rotated_ism.histogram.counts.iter().rev().copied().collect::<Vec<_>>()
        ) <= 4
    );
    // ... and for isotropic disks the ISM angle does not matter, so the fraction below 30 deg
    // is unchanged within its statistical error.
    let unflipped = simulate(&pol(AlignmentModel::Random, 400_000, 7, p.clone(), Some(2.0), 0.0)).unwrap();
    let flipped = simulate(&with_perp(
        pol(AlignmentModel::Random, 400_000, 8, p, Some(2.0), 0.0),
        [1.0, 1.0],
    ))
    .unwrap();
    let (f0, f1) = (unflipped.histogram.cdf(30.0), flipped.histogram.cdf(30.0));
    let se = (2.0 * f0 * (1.0 - f0) / 400_000.0).sqrt();
    assert!((f0 - f1).abs() < 4.0 * se, "{f0} vs {f1}");
}

#[test]
fn perpendicular_on_one_component_mirrors_delta_gamma() {
    let cone = AlignmentModel::Cone { alpha0_deg: 30.0 };
    // Geometry path and the polarization path (fixed P, no ISM, zero noise).
    let configs = [
        geometry(cone.clone(), 200_000, 11),
        pol(cone.clone(), 200_000, 12, PIntDist::Fixed { p_percent: 3.0 }, None, 0.0),
        pol(cone, 200_000, 13, PIntDist::Sin2i { p_max_percent: 6.0 }, None, 0.0),
    ];
    for cfg in configs {
        let a = simulate(&cfg).unwrap();
        let b = simulate(&with_perp(cfg.clone(), [1.0, 0.0])).unwrap();
        let c = simulate(&with_perp(cfg, [0.0, 1.0])).unwrap();
        // Values within rounding of a bin edge may move by one bin: allow a handful.
        assert!(mirror_mismatch(&a.histogram.counts, &b.histogram.counts) <= 4);
        assert!(mirror_mismatch(&a.histogram.counts, &c.histogram.counts) <= 4);
        assert!((a.mean_delta_gamma_deg - (90.0 - b.mean_delta_gamma_deg)).abs() < 1e-9);
        // The aligned cone really is asymmetric, so the mirror is not trivially satisfied.
        assert!(a.histogram.cdf(30.0) > 0.8 && b.histogram.cdf(30.0) < 0.2);
    }
    // A fraction in between draws per component: 50 % gives half the pairs one flip.
    let cfg = with_perp(geometry(AlignmentModel::Aligned, 100_000, 14), [0.5, 0.5]);
    let out = simulate(&cfg).unwrap();
    let at_90 = *out.histogram.counts.last().unwrap() as f64 / 100_000.0;
    assert!((at_90 - 0.5).abs() < 4.0 * (0.25f64 / 100_000.0).sqrt(), "{at_90}");
}

#[test]
fn perpendicular_fraction_is_validated() {
    for f in [-0.1, 1.1, f64::NAN] {
        let err = simulate(&with_perp(geometry(AlignmentModel::Random, 10, 1), [f, 0.0])).unwrap_err();
        assert!(err.to_string().contains("perpendicular-fraction"), "{err}");
    }
}

#[test]
fn constant_p_of_i_table_equals_the_fixed_model_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("flat.csv");
    std::fs::write(&path, "inclination_deg,p\n0,0.02\n45,0.02\n90,0.02\n").unwrap();
    let table = PIntDist::parse(&format!("pofi:{}", path.display())).unwrap();
    for model in [AlignmentModel::Random, AlignmentModel::Spread { sigma_deg: 20.0 }] {
        let mk = |p: PIntDist| McConfig {
            p_int: p,
            ism: Some(Ism {
                p_percent: 1.0,
                angle_deg: 10.0,
            }),
            noise_percent: Some(0.3),
            snr_cut: Some(3.0),
            ..geometry(model.clone(), 150_000, 21)
        };
        let a = simulate(&mk(table.clone())).unwrap();
        let b = simulate(&mk(PIntDist::Fixed { p_percent: 2.0 })).unwrap();
        assert_eq!(a, b);
    }
}

#[test]
fn p_of_i_table_interpolates_linearly_and_exactly_at_its_points() {
    let inc = vec![0.0, 10.0, 35.5, 60.0, 90.0];
    let p = vec![0.1, 0.7, 2.3, 4.9, 8.3];
    let t = mc::PofITable::new("test", inc.clone(), p.clone()).unwrap();
    for (i, v) in inc.iter().zip(&p) {
        assert_eq!(t.p_percent_at(*i), *v, "at {i}");
    }
    assert!((t.p_percent_at(5.0) - 0.4).abs() < 1e-12);
    assert!((t.p_percent_at(47.75) - 3.6).abs() < 1e-12);
    assert!((t.p_percent_at(80.0) - (4.9 + 3.4 * 20.0 / 30.0)).abs() < 1e-12);
    // Ends: the end values outside the table.
    let short = mc::PofITable::new("short", vec![20.0, 70.0], vec![1.0, 5.0]).unwrap();
    assert_eq!(short.p_percent_at(0.0), 1.0);
    assert_eq!(short.p_percent_at(90.0), 5.0);
    // A fine table of 6 % sin^2 i reproduces the analytic sin2i model (independent code path).
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sin2.csv");
    let text: String = (0..=180)
        .map(|k| {
            let i = k as f64 * 0.5;
            format!("{i},{:.10}\n", 0.06 * i.to_radians().sin().powi(2))
        })
        .collect();
    std::fs::write(&path, text).unwrap();
    let tab = PIntDist::parse(&format!("pofi:{}", path.display())).unwrap();
    let mk = |p: PIntDist| pol(AlignmentModel::Random, 200_000, 31, p, Some(2.0), 0.0);
    let a = simulate(&mk(tab)).unwrap();
    let b = simulate(&mk(PIntDist::Sin2i { p_max_percent: 6.0 })).unwrap();
    // Same seed, same geometry: P differs by the interpolation error only (< 1e-4 %).
    assert!((a.histogram.cdf(30.0) - b.histogram.cdf(30.0)).abs() < 1e-3);
    assert!((a.mean_delta_gamma_deg - b.mean_delta_gamma_deg).abs() < 1e-2);
    // The example file in testdata parses.
    let ex = PIntDist::parse("pofi:../testdata/stats/p_of_i_illustrative.csv").unwrap();
    assert!(matches!(ex, PIntDist::Inclination(ref t) if t.inclination_deg.len() == 10 && t.p_percent[9] == 8.5));
}

#[test]
fn bad_p_of_i_files_are_refused_naming_file_line_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        ("decreasing.csv", "0,0.01\n40,0.03\n30,0.04\n", "line 3", "30"),
        ("equal.csv", "0,0.01\n40,0.03\n40,0.04\n", "line 3", "40"),
        ("p_too_big.csv", "# comment\n0,0.01\n90,1.2\n", "line 3", "1.2"),
        ("p_negative.csv", "0,-0.01\n90,0.05\n", "line 1", "-0.01"),
        ("inc_too_big.csv", "0,0.01\n95,0.05\n", "line 2", "95"),
        ("inc_negative.csv", "-5,0.01\n90,0.05\n", "line 1", "-5"),
        ("nan.csv", "0,0.01\n45,abc\n", "line 2", "abc"),
        ("three.csv", "inclination_deg,p\n0,0.01,7\n", "line 2", "0,0.01,7"),
        ("empty.csv", "# nothing\n", "no (inclination_deg, p) points", ""),
        (
            "header_late.csv",
            "0,0.01\ninclination_deg,p\n",
            "line 2",
            "inclination_deg",
        ),
    ];
    for (name, text, where_, value) in cases {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        let err = PIntDist::parse(&format!("pofi:{}", path.display()))
            .unwrap_err()
            .to_string();
        assert!(err.contains(name), "{name}: {err}");
        assert!(err.contains(where_), "{name}: {err}");
        assert!(err.contains(value), "{name}: {err}");
    }
    let missing = dir.path().join("missing.csv");
    let err = PIntDist::parse(&format!("pofi:{}", missing.display()))
        .unwrap_err()
        .to_string();
    assert!(err.contains("missing.csv"), "{err}");
}

/// A p-value of exactly 0 (the Kolmogorov tail below the smallest double: a sample that
/// rejects the model beyond any doubt the double can hold) reads as a bound, not "0.0e0";
/// the others as before.
#[test]
fn a_p_value_of_zero_is_printed_as_a_bound() {
    let (p, _) = kolmogorov_sf(1.0, 2000);
    assert_eq!(p, 0.0, "the series underflows at D = 1, n = 2000");
    assert_eq!(super::format_p(p), "< 1e-300");
    assert_eq!(super::format_p(0.5), "0.5000");
    assert_eq!(super::format_p(2.5e-7), "2.5e-7");
}

/// A catalog of `n` binaries with Delta gamma spread over [0, 90), sigma_P of A and B
/// from 0.2 % to 1 %, P 4 % and 3 %; the first `with_fg` carry a foreground of 3 %.
fn per_binary_catalog(n: usize, with_fg: usize) -> Catalog {
    let targets = (0..n)
        .map(|i| {
            let s = 0.002 + 0.008 * i as f64 / n as f64;
            let mut t = target(
                &format!("T{i}"),
                Status::Ok,
                vec![
                    component("A", 0.04, s, 10.0),
                    component("B", 0.03, s, 10.0 + 90.0 * i as f64 / n as f64),
                ],
                None,
            );
            if i < with_fg {
                t.foreground = Some(crate::catalog::Foreground::new(0.03, 0.0, 0.001, 0.001, 0.0));
            }
            t
        })
        .collect();
    Catalog {
        schema_version: "1.0".into(),
        targets,
        ..Default::default()
    }
}

/// `stats`' default analysis predicts random disks + ISM per binary (each level has the
/// per-binary test, and the mixture's accepted pairs), adds the own-foreground prediction
/// only when a target has a foreground, states it, and a strong own foreground pulls the
/// prediction towards small Delta gamma (fraction below 30 deg above the level-0.1 row's).
/// A bad foreground is refused naming the target and the key.
#[test]
fn stats_predicts_per_binary_and_with_each_binarys_own_foreground() {
    use super::setup::{analyse_sample, params, Noise, Options};
    let opts = Options {
        pairs: 40_000,
        ism_levels_percent: vec![0.1],
        ..Default::default()
    };
    assert_eq!(opts.noise, Noise::PerBinary);
    let none = BinarySample::from_catalog(&per_binary_catalog(12, 0), None);
    let r = analyse_sample(&none, &params(&none, &opts, "cat.json").unwrap()).unwrap();
    assert!(r.own_foreground.is_none());
    assert!(r.ism[0].per_binary.is_some() && r.ism[0].min_accepted_per_binary.unwrap() >= 2000);
    assert!(
        r.mc_description.contains("each binary's own noise"),
        "{}",
        r.mc_description
    );

    let some = BinarySample::from_catalog(&per_binary_catalog(12, 12), None);
    let r = analyse_sample(&some, &params(&some, &opts, "cat.json").unwrap()).unwrap();
    let own = r.own_foreground.as_ref().expect("own-foreground prediction");
    assert!(own.foreground.as_deref().unwrap().contains("12 of 12"));
    assert!(
        own.mc_fraction_below_threshold > r.ism[0].mc_fraction_below_threshold + 0.1,
        "own {} vs 0.1 % {}",
        own.mc_fraction_below_threshold,
        r.ism[0].mc_fraction_below_threshold
    );
    assert!(r.verdict.contains("own foreground"), "{}", r.verdict);

    let mut bad = per_binary_catalog(3, 1);
    bad.targets[0].foreground.as_mut().unwrap().cov_qu = 0.01;
    let s = BinarySample::from_catalog(&bad, None);
    let e = params(&s, &opts, "cat.json").unwrap_err().to_string();
    assert!(
        e.contains("cat.json") && e.contains("T0") && e.contains("cov_qu"),
        "{e}"
    );
}

/// The sample recomputes each binary's foreground-subtracted Delta-gamma from its
/// components' q, u and its foreground, and tests it against uniform: binaries whose
/// intrinsic angles differ evenly over [0, 90] deg, seen through a 5 % foreground that
/// squeezes their raw Delta-gamma below ~25 deg, give a KS p < 1e-6 before and > 0.5 after.
/// A stored value that disagrees is replaced (with a warning), as the raw Delta-gamma is.
#[test]
fn stats_tests_the_delta_gamma_after_subtracting_each_foreground() {
    let n = 40;
    let (fq, fu) = (0.05, 0.0);
    let seen = |name: &str, p: f64, g: f64| {
        let t = 2.0 * g.to_radians();
        let (q, u) = (p * t.cos() + fq, p * t.sin() + fu);
        component(name, q.hypot(u), 0.001, 0.5 * u.atan2(q).to_degrees())
    };
    let targets: Vec<Target> = (0..n)
        .map(|i| {
            let d = 90.0 * (i as f64 + 0.5) / n as f64;
            let mut t = target(
                &format!("B{i}"),
                Status::Ok,
                vec![seen("A", 0.02, 10.0), seen("B", 0.02, 10.0 + d)],
                None,
            );
            if i % 4 != 3 {
                t.foreground = Some(crate::catalog::Foreground::new(fq, fu, 0.001, 0.001, 0.0));
                // A stale stored value on one binary: replaced by the recomputed one.
                t.delta_gamma_fg_corrected_deg = Some(if i == 0 { 77.0 } else { d });
            }
            t
        })
        .collect();
    let cat = Catalog {
        targets,
        ..Catalog::default()
    };
    let s = BinarySample::from_catalog(&cat, None);
    let pairs = s.fg_corrected_pairs();
    assert_eq!(pairs.len(), 30);
    for (k, (_, after)) in pairs.iter().enumerate() {
        let i = k + k / 3; // every fourth binary has no foreground
        let d = 90.0 * (i as f64 + 0.5) / n as f64;
        assert!((after - d).abs() < 1e-9, "binary {i}: {after} vs {d}");
    }
    let stale: Vec<&String> = s
        .warnings
        .iter()
        .filter(|w| w.contains("delta_gamma_fg_corrected_deg"))
        .collect();
    assert!(
        stale.len() == 1 && stale[0].starts_with("B0:") && stale[0].contains("77"),
        "{:?}",
        s.warnings
    );
    let f = crate::stats::alignment::FgCorrected::from_pairs(&pairs).unwrap();
    assert_eq!(f.n, 30);
    assert!(f.ks_before.p_value < 1e-6, "{:?}", f.ks_before);
    assert!(f.ks_after.p_value > 0.5, "{:?}", f.ks_after);
    assert!(
        (f.mean_after_deg - 45.0).abs() < 3.5 && f.mean_before_deg < 25.0,
        "{f:?}"
    );
    assert!(crate::stats::alignment::FgCorrected::from_pairs(&[]).is_none());
}
