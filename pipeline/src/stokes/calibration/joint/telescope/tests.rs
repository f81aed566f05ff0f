//! The joint fit with the telescope's term against standards made with the forward model
//! (`TelescopePolarization::at` added to each star's sky-frame polarization), noiseless and
//! over noise draws.
use super::super::{fit_joint_with, inflation, JointOptions};
use crate::stokes::calibration::{OrientationF, StandardObservation};
use crate::stokes::model::{normalized_difference, Polarization, TelescopePolarization};
use crate::stokes::propagation::{CAL_C, CAL_TEL_A, CAL_TEL_B, CAL_THETA0};
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;

const TWO: [f64; 2] = [0.0, 45.0];

/// The night's instrument: offset, zero-point, parity, telescope.
#[derive(Clone, Copy)]
struct Instrument {
    c: f64,
    theta0: f64,
    parity: i32,
    tel: TelescopePolarization,
}

const NTT: Instrument = Instrument {
    c: 0.0182,
    theta0: 3.0,
    parity: 1,
    tel: TelescopePolarization {
        p_tel: 0.006,
        psi_tel_deg: 25.0,
    },
};

/// A standard observed at rotator angles `posangs`, orientation i at parallactic angle
/// `eta[i]`: F = (star + telescope at eta) at phi = s PA + theta0, plus c.
fn standard(star: Polarization, posangs: &[f64], eta: &[f64], ins: Instrument, sigma_f: f64) -> StandardObservation {
    let polarized = star.p() > 0.0;
    StandardObservation {
        name: "S".into(),
        posang_deg: posangs.to_vec(),
        f: posangs
            .iter()
            .zip(eta)
            .map(|(&pa, &e)| OrientationF {
                analyzer_deg: f64::NAN,
                f: normalized_difference(star.add(ins.tel.at(e)), ins.parity as f64 * pa + ins.theta0) + ins.c,
                sigma_f,
            })
            .collect(),
        p: star.p(),
        sigma_p: if polarized { 0.1 * star.p() } else { 0.0005 },
        gamma_deg: star.gamma_deg(),
        sigma_gamma_deg: 1.0,
        parallactic_2eta: eta
            .iter()
            .map(|e| Some([(2.0 * e.to_radians()).cos(), (2.0 * e.to_radians()).sin()]))
            .collect(),
    }
}

fn opts(ins: Instrument) -> JointOptions {
    JointOptions {
        default_parity: ins.parity,
        profile_theta0_deg: 0.0,
        fit_telescope: true,
        telescope_prior: None,
    }
}

/// Six standards over a night: four unpolarized, two polarized, parallactic angles spread
/// (each orientation a few degrees on from the previous one).
fn six_standards(ins: Instrument, sigma_f: f64) -> Vec<StandardObservation> {
    let unpol = Polarization::default();
    [
        (unpol, -150.0),
        (Polarization::from_p_gamma(0.025, 40.0), -100.0),
        (unpol, -40.0),
        (unpol, 20.0),
        (Polarization::from_p_gamma(0.02, 100.0), 75.0),
        (unpol, 140.0),
    ]
    .iter()
    .map(|&(star, eta)| standard(star, &TWO, &[eta, eta + 4.0], ins, sigma_f))
    .collect()
}

/// The mirror's prior in Ks as the SOFI profile gives it: 0.77 +- 0.15 %, 0 +- 5 deg.
fn ks_prior() -> crate::stokes::fresnel::TelescopePrior {
    crate::stokes::fresnel::TelescopePrior {
        p_tel: 0.0077,
        sigma_p_tel: 0.2 * 0.0077,
        psi_tel_deg: 0.0,
        sigma_psi_tel_deg: 5.0,
    }
}

fn axial_diff(a: f64, b: f64) -> f64 {
    (a - b + 90.0).rem_euclid(180.0) - 90.0
}

#[test]
fn noiseless_standards_at_spread_parallactic_angles_give_the_telescope_exactly() {
    for parity in [1, -1] {
        for (c, theta0, p_tel, psi) in [(0.0182, 3.0, 0.006, 25.0), (-0.011, 171.0, 0.009, 140.0)] {
            let ins = Instrument {
                c,
                theta0,
                parity,
                tel: TelescopePolarization {
                    p_tel,
                    psi_tel_deg: psi,
                },
            };
            let j = fit_joint_with(&six_standards(ins, 3e-4), &opts(ins)).unwrap();
            assert!(j.telescope_problem.is_none(), "{:?}", j.telescope_problem);
            let t = j.telescope.unwrap();
            assert!((t.p_tel - p_tel).abs() < 1e-10, "p_tel {} vs {p_tel}", t.p_tel);
            assert!(
                axial_diff(t.psi_tel_deg, psi).abs() < 1e-7,
                "psi {} vs {psi}",
                t.psi_tel_deg
            );
            assert!((j.offset.unwrap().c - c).abs() < 1e-10);
            assert!(axial_diff(j.angles.unwrap().theta0_deg, theta0).abs() < 1e-7);
            assert!(j.chi2 < 1e-12, "{}", j.chi2);
            for k in [CAL_C, CAL_THETA0, CAL_TEL_A, CAL_TEL_B] {
                assert!(j.covariance[k][k] > 0.0, "{k}: {:?}", j.covariance);
            }
        }
    }
}

#[test]
fn unpolarized_standards_alone_measure_the_telescope_in_the_profiles_frame() {
    // No polarized standard: theta0 is the profile's (here the truth, 3 deg), the
    // telescope's term is fitted at the profile's analyzer angles.
    let ins = NTT;
    let stds: Vec<StandardObservation> = [-150.0, -60.0, 10.0, 95.0]
        .iter()
        .map(|&e| standard(Polarization::default(), &TWO, &[e, e + 3.0], ins, 3e-4))
        .collect();
    let j = fit_joint_with(
        &stds,
        &JointOptions {
            profile_theta0_deg: ins.theta0,
            ..opts(ins)
        },
    )
    .unwrap();
    assert!(j.angles.is_none());
    let t = j.telescope.expect("telescope measured");
    assert!(
        (t.p_tel - 0.006).abs() < 1e-10 && axial_diff(t.psi_tel_deg, 25.0).abs() < 1e-7,
        "{t:?}"
    );
    assert!((j.offset.unwrap().c - ins.c).abs() < 1e-10);
}

#[test]
fn standards_at_one_parallactic_angle_cannot_separate_the_telescope_from_c() {
    // Every standard within 2 deg of eta = -150: the telescope's term is a constant per
    // orientation, which c and the stars' own polarization absorb.
    let ins = NTT;
    let mut stds = six_standards(ins, 3e-4);
    for (i, s) in stds.iter_mut().enumerate() {
        let e = -150.0 + 0.3 * i as f64;
        *s = standard(
            if s.polarized() {
                Polarization::from_p_gamma(s.p, s.gamma_deg)
            } else {
                Polarization::default()
            },
            &TWO,
            &[e, e + 0.5],
            ins,
            3e-4,
        );
    }
    let j = fit_joint_with(&stds, &opts(ins)).unwrap();
    assert!(j.telescope.is_none());
    let why = j.telescope_problem.expect("a reason");
    assert!(why.contains("span") && why.contains("deg"), "{why}");
    // The fit without the telescope's term is kept (c and theta0 as before, biased by it).
    assert!(j.offset.is_some() && j.angles.is_some());
    assert_eq!(j.covariance[CAL_TEL_A][CAL_TEL_A], 0.0);
    // Without parallactic angles the reason says so.
    for s in &mut stds {
        s.parallactic_2eta.clear();
    }
    let why = fit_joint_with(&stds, &opts(ins)).unwrap().telescope_problem.unwrap();
    assert!(why.contains("parallactic angle"), "{why}");
    // Too few: one unpolarized standard at two orientations (2 data, 3 unknowns).
    let one = [standard(Polarization::default(), &TWO, &[-20.0, 40.0], ins, 3e-4)];
    let j = fit_joint_with(&one, &opts(ins)).unwrap();
    assert!(j.telescope.is_none(), "{j:?}");
    assert!(j.telescope_problem.unwrap().contains("no more orientations"));
}

/// Over noise draws (F, the polarized standards' table values, the unpolarized ones'
/// residual polarization), the fitted (c, theta0, a, b) scatter as their reported
/// covariance says (inflation divided out), and are unbiased.
#[test]
fn the_covariance_with_the_telescope_matches_the_scatter_of_the_estimates() {
    let ins = NTT;
    let sigma_f = 3e-4;
    let mut rng = rand::rngs::StdRng::seed_from_u64(20261126);
    let mut gauss = || -> f64 { rng.sample(StandardNormal) };
    let n = 4000;
    let template = six_standards(ins, sigma_f);
    let mut est: Vec<[f64; 4]> = Vec::with_capacity(n);
    let mut reported = [[0.0; 4]; 4];
    for _ in 0..n {
        let stds: Vec<StandardObservation> = template
            .iter()
            .map(|t| {
                let eta: Vec<f64> = t
                    .parallactic_2eta
                    .iter()
                    .map(|v| 0.5 * v.unwrap()[1].atan2(v.unwrap()[0]).to_degrees())
                    .collect();
                let (star, mut s) = if t.polarized() {
                    let star = Polarization::from_p_gamma(t.p, t.gamma_deg);
                    let mut s = standard(star, &TWO, &eta, ins, sigma_f);
                    s.p = t.p + t.sigma_p * gauss();
                    s.gamma_deg = t.gamma_deg + t.sigma_gamma_deg * gauss();
                    (star, s)
                } else {
                    let k = t.sigma_p / 2f64.sqrt();
                    let star = Polarization {
                        q: k * gauss(),
                        u: k * gauss(),
                    };
                    // Observed with its residual polarization; the table says 0 +- sigma_p.
                    let s = StandardObservation {
                        p: 0.0,
                        sigma_p: t.sigma_p,
                        gamma_deg: 0.0,
                        ..standard(star, &TWO, &eta, ins, sigma_f)
                    };
                    (star, s)
                };
                let _ = star;
                for o in &mut s.f {
                    o.f += sigma_f * gauss();
                }
                s.p = s.p.max(0.0);
                s
            })
            .collect();
        let j = fit_joint_with(&stds, &opts(ins)).unwrap();
        let t = j.telescope.unwrap_or_else(|| panic!("{:?}", j.telescope_problem));
        let [a, b] = t.ab();
        est.push([
            j.offset.unwrap().c,
            ins.theta0 + axial_diff(j.angles.unwrap().theta0_deg, ins.theta0),
            a,
            b,
        ]);
        if reported[0][0] == 0.0 {
            let k = inflation(j.chi2, j.dof);
            reported = j.covariance.map(|row| row.map(|v| v / k));
        }
    }
    let truth = {
        let [a, b] = ins.tel.ab();
        [ins.c, ins.theta0, a, b]
    };
    let mean: [f64; 4] = std::array::from_fn(|k| est.iter().map(|e| e[k]).sum::<f64>() / n as f64);
    let cov =
        |i: usize, j: usize| est.iter().map(|e| (e[i] - mean[i]) * (e[j] - mean[j])).sum::<f64>() / (n - 1) as f64;
    let names = ["c", "theta0", "a", "b"];
    for k in 0..4 {
        let ratio = cov(k, k) / reported[k][k];
        eprintln!(
            "{}: mean - truth {:+.2e} (MC error {:.1e}); var scatter/fit {ratio:.3}",
            names[k],
            mean[k] - truth[k],
            (cov(k, k) / n as f64).sqrt()
        );
        assert!((ratio - 1.0).abs() < 0.07, "{}: scatter/fit = {ratio}", names[k]);
        assert!(
            (mean[k] - truth[k]).abs() < 4.0 * (cov(k, k) / n as f64).sqrt(),
            "{} biased: {} vs {}",
            names[k],
            mean[k],
            truth[k]
        );
    }
    for (i, j) in [
        (CAL_C, CAL_TEL_A),
        (CAL_C, CAL_TEL_B),
        (CAL_TEL_A, CAL_TEL_B),
        (CAL_C, CAL_THETA0),
    ] {
        let corr_mc = cov(i, j) / (cov(i, i) * cov(j, j)).sqrt();
        let corr_fit = reported[i][j] / (reported[i][i] * reported[j][j]).sqrt();
        eprintln!(
            "corr({}, {}): scatter {corr_mc:.3}, fit {corr_fit:.3}",
            names[i], names[j]
        );
        assert!(
            (corr_mc - corr_fit).abs() < 0.05,
            "corr {i}{j}: {corr_mc} vs {corr_fit}"
        );
    }
}

/// How well a night measures the telescope: N standards (one in three polarized) at
/// parallactic angles spread evenly over [-150, 150] deg, sigma_F = 3e-4 per orientation,
/// 0/45. The errors come from the fit's covariance (noiseless data: no inflation). Quoted in
/// docs/calibration.md.
#[test]
fn the_telescope_is_measured_better_with_more_standards() {
    let ins = NTT;
    let mut last = f64::INFINITY;
    for n in [3usize, 6, 10] {
        let stds: Vec<StandardObservation> = (0..n)
            .map(|i| {
                let eta = -150.0 + 300.0 * i as f64 / (n - 1) as f64;
                let star = if i % 3 == 1 {
                    Polarization::from_p_gamma(0.008, 40.0 + 30.0 * i as f64)
                } else {
                    Polarization::default()
                };
                standard(star, &TWO, &[eta, eta + 3.0], ins, 3e-4)
            })
            .collect();
        let j = fit_joint_with(&stds, &opts(ins)).unwrap();
        let t = j.telescope.unwrap_or_else(|| panic!("{n}: {:?}", j.telescope_problem));
        let tc = crate::calibration::TelescopeCalibration::from_fit(&t, &j.covariance);
        eprintln!(
            "{n} standards: p_tel = {:.3} +- {:.3} %, psi_tel = {:.1} +- {:.1} deg; sigma_c = {:.5}, sigma_theta0 = {:.2} deg",
            100.0 * tc.p_tel,
            100.0 * tc.sigma_p_tel,
            tc.psi_tel_deg,
            tc.sigma_psi_tel_deg,
            j.covariance[CAL_C][CAL_C].sqrt(),
            j.covariance[CAL_THETA0][CAL_THETA0].sqrt()
        );
        assert!(tc.sigma_p_tel < last, "{n}: {} not below {last}", tc.sigma_p_tel);
        last = tc.sigma_p_tel;
    }
}

/// Standards all within a few degrees of one parallactic angle do not separate the
/// telescope's term from c; with the mirror's prior the fit is kept, the reason recorded,
/// and over draws of the truth from the prior (what the prior claims), of the noise and of
/// the standards' table values, the estimates of c, theta0, a and b scatter about the truth
/// as the reported covariance says: pulls of rms 1, no bias.
#[test]
fn clustered_standards_with_the_mirrors_prior_give_honest_errors() {
    let prior = ks_prior();
    let sigma_f = 3e-4;
    let mut rng = rand::rngs::StdRng::seed_from_u64(20261129);
    let mut gauss = || -> f64 { rng.sample(StandardNormal) };
    let stars = [
        Polarization::default(),
        Polarization::from_p_gamma(0.025, 40.0),
        Polarization::default(),
        Polarization::default(),
        Polarization::from_p_gamma(0.02, 100.0),
        Polarization::default(),
    ];
    let n = 1500;
    let mut pulls: Vec<[f64; 4]> = Vec::with_capacity(n);
    for draw in 0..n {
        // The truth drawn from the prior: along and across its mean direction.
        let [a0, b0] = prior.mean();
        let (da, db) = (
            prior.sigma_p_tel * gauss(),
            prior.p_tel * 2.0 * 5f64.to_radians() * gauss(),
        );
        let (a, b) = (a0 + da, b0 + db);
        let ins = Instrument {
            tel: TelescopePolarization {
                p_tel: a.hypot(b),
                psi_tel_deg: 0.5 * b.atan2(a).to_degrees(),
            },
            ..NTT
        };
        let stds: Vec<StandardObservation> = stars
            .iter()
            .enumerate()
            .map(|(i, &star)| {
                let e = 35.0 + 2.5 * i as f64;
                let mut s = if star.p() > 0.0 {
                    let mut s = standard(star, &TWO, &[e, e + 1.0], ins, sigma_f);
                    s.p = star.p() + s.sigma_p * gauss();
                    s.gamma_deg = star.gamma_deg() + s.sigma_gamma_deg * gauss();
                    s
                } else {
                    let k = 0.0005 / 2f64.sqrt();
                    let own = Polarization {
                        q: k * gauss(),
                        u: k * gauss(),
                    };
                    StandardObservation {
                        p: 0.0,
                        sigma_p: 0.0005,
                        gamma_deg: 0.0,
                        ..standard(own, &TWO, &[e, e + 1.0], ins, sigma_f)
                    }
                };
                for o in &mut s.f {
                    o.f += sigma_f * gauss();
                }
                s
            })
            .collect();
        let alone = fit_joint_with(&stds, &opts(ins)).unwrap();
        assert!(
            alone.telescope.is_none(),
            "draw {draw}: the standards alone separate it"
        );
        let j = fit_joint_with(
            &stds,
            &JointOptions {
                telescope_prior: Some(prior),
                ..opts(ins)
            },
        )
        .unwrap();
        let why = j
            .telescope_from_prior
            .as_deref()
            .unwrap_or_else(|| panic!("draw {draw}: {:?}", j.telescope_problem));
        assert!(why.contains("span"), "{why}");
        let t = j.telescope.expect("fitted with the prior");
        let [fa, fb] = t.ab();
        let est = [
            j.offset.unwrap().c,
            ins.theta0 + axial_diff(j.angles.unwrap().theta0_deg, ins.theta0),
            fa,
            fb,
        ];
        let truth = [ins.c, ins.theta0, a, b];
        pulls.push(std::array::from_fn(|k| (est[k] - truth[k]) / j.covariance[k][k].sqrt()));
    }
    let names = ["c", "theta0", "a", "b"];
    for k in 0..4 {
        let mean = pulls.iter().map(|p| p[k]).sum::<f64>() / n as f64;
        let rms = (pulls.iter().map(|p| p[k] * p[k]).sum::<f64>() / n as f64).sqrt();
        eprintln!("{}: pull mean {mean:+.3}, rms {rms:.3}", names[k]);
        // 1.01-1.05 measured (0.96-0.99 while the errors were inflated by chi^2/dof
        // whenever it exceeded 1).
        assert!((0.88..1.06).contains(&rms), "{}: pull rms {rms}", names[k]);
        assert!(mean.abs() < 0.1, "{}: pull mean {mean}", names[k]);
    }
}

/// The polarized-only night of `sofipol bench calibration`: HD 204827, HD 154445 and HD
/// 161056 (built-in Ks table: p 0.88, 0.68, 0.75 % known to 25 %, angles to 2 deg) at
/// parallactic angles -46, 167 and 80 deg, no unpolarized standard. The standards alone
/// never measure the term (no unpolarized one); with the mirror's prior, over draws of the
/// truth from the prior, of the stars from their table errors and of the noise, the
/// estimates of c, theta0, a and b scatter about the truth as the reported covariance says.
/// The linearised fit gave theta0 pulls of median |x| 0.75 and 2 % beyond 4 sigma (and,
/// before the telescope's d/dtheta0 was kept in the polarized standards' rows, b pulls of
/// rms 4.6); the fit marginalised over theta0 gives median |x| 0.66 and rms 1.04 on 2000
/// draws.
#[test]
fn polarized_standards_only_with_the_mirrors_prior_give_honest_errors() {
    let prior = ks_prior();
    let sigma_f = 3e-4;
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let mut gauss = || -> f64 { rng.sample(StandardNormal) };
    // (table p, table gamma, parallactic angle), deg.
    let table = [(0.0088, 58.7, -46.0), (0.0068, 88.8, 167.0), (0.0075, 67.3, 80.0)];
    let n = 700;
    let mut pulls: Vec<[f64; 4]> = Vec::with_capacity(n);
    let mut incomplete = 0;
    for draw in 0..n {
        let [a0, b0] = prior.mean();
        let (a, b) = (
            a0 + prior.sigma_p_tel * gauss(),
            b0 + prior.p_tel * 2.0 * prior.sigma_psi_tel_deg.to_radians() * gauss(),
        );
        let ins = Instrument {
            tel: TelescopePolarization {
                p_tel: a.hypot(b),
                psi_tel_deg: 0.5 * b.atan2(a).to_degrees(),
            },
            ..NTT
        };
        let stds: Vec<StandardObservation> = table
            .iter()
            .map(|&(p, g, e)| {
                let star = Polarization::from_p_gamma(p + 0.25 * p * gauss(), g + 2.0 * gauss());
                let mut s = standard(star, &TWO, &[e, e + 3.0], ins, sigma_f);
                (s.p, s.sigma_p, s.gamma_deg, s.sigma_gamma_deg) = (p, 0.25 * p, g, 2.0);
                for o in &mut s.f {
                    o.f += sigma_f * gauss();
                }
                s
            })
            .collect();
        let j = fit_joint_with(
            &stds,
            &JointOptions {
                telescope_prior: Some(prior),
                ..opts(ins)
            },
        )
        .unwrap();
        let why = j.telescope_from_prior.as_deref().unwrap_or("");
        let (Some(t), Some(angles)) = (j.telescope, j.angles) else {
            // c and theta0 not separated even with the term marginalised: incomplete.
            assert!(j.incomplete.is_some(), "draw {draw}");
            incomplete += 1;
            continue;
        };
        assert!(why.contains("unpolarized standard"), "draw {draw}: {why}");
        let [fa, fb] = t.ab();
        let est = [
            j.offset.unwrap().c,
            ins.theta0 + axial_diff(angles.theta0_deg, ins.theta0),
            fa,
            fb,
        ];
        let truth = [ins.c, ins.theta0, a, b];
        // The errors without the inflation by chi^2/dof (4 degrees of freedom), which is
        // common to every such fit.
        let k = inflation(j.chi2, j.dof);
        pulls.push(std::array::from_fn(|i| {
            (est[i] - truth[i]) / (j.covariance[i][i] / k).sqrt()
        }));
    }
    assert!(incomplete < n / 20, "{incomplete} of {n} incomplete");
    let m = pulls.len() as f64;
    for (i, name) in ["c", "theta0", "a", "b"].iter().enumerate() {
        let mean = pulls.iter().map(|p| p[i]).sum::<f64>() / m;
        let rms = (pulls.iter().map(|p| p[i] * p[i]).sum::<f64>() / m).sqrt();
        let mut abs: Vec<f64> = pulls.iter().map(|p| p[i].abs()).collect();
        abs.sort_by(f64::total_cmp);
        let median = abs[abs.len() / 2];
        eprintln!(
            "{name}: pull mean {mean:+.3}, rms {rms:.3}, median |x| {median:.3} ({m} fits, {incomplete} incomplete)"
        );
        assert!((0.9..1.12).contains(&rms), "{name}: pull rms {rms}");
        assert!((0.6..0.74).contains(&median), "{name}: median |pull| {median}");
        assert!(mean.abs() < 0.12, "{name}: pull mean {mean}");
    }
}

/// Pulls of (c, theta0, a, b) against each fit's own reported covariance (its chi^2/dof
/// inflation included) over `n` nights of 5 standards at 0/45 (3 unpolarized at 0 +- 0.05 %,
/// HD 204827 and HD 154445 with their Ks table values and errors; parallactic angles spread
/// over the night), each night drawing its instrument (c, theta0, p_tel, psi_tel), the
/// standards' truth from their table errors, sigma_F (1.5e-4 to 4.5e-4) and the noise. The
/// noise is `noise_factor` times sigma_F (1: honest errors). Returns the pulls and how
/// many fits were inflated and how many refused (the telescope's term or theta0 not
/// determined on its own).
fn pulls_of_reported_covariance(n: usize, noise_factor: f64, seed: u64) -> (Vec<[f64; 4]>, usize, usize) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let table = [
        (0.0, 0.0005, 0.0),
        (0.0, 0.0005, 0.0),
        (0.0, 0.0005, 0.0),
        (0.0088, 0.0022, 58.7),
        (0.0068, 0.0017, 88.8),
    ];
    let mut pulls = Vec::with_capacity(n);
    let (mut inflated, mut refused) = (0, 0);
    for _ in 0..n {
        let mut g = || -> f64 { rng.sample(StandardNormal) };
        let ins = Instrument {
            c: 0.018 + 0.005 * g(),
            theta0: 1.0 + 3.0 * g(),
            parity: 1,
            tel: TelescopePolarization {
                p_tel: 0.007 + 0.0015 * g(),
                psi_tel_deg: 5.0 * g(),
            },
        };
        let sigma_f = 1.5e-4 * 3f64.powf(rng.random::<f64>());
        let mut g = || -> f64 { rng.sample(StandardNormal) };
        let stds: Vec<StandardObservation> = table
            .iter()
            .enumerate()
            .map(|(i, &(p, sigma_p, gamma))| {
                // The parallactic angles of the simulated nights of
                // tests/cli_calibration_pulls.rs (standards 2 h apart), give or take 5 deg.
                let e = [108.0, -134.0, 29.0, -36.0, 37.0][i] + 5.0 * g();
                let star = if p > 0.0 {
                    Polarization::from_p_gamma(p + sigma_p * g(), gamma + 2.0 * g())
                } else {
                    let k = sigma_p / 2f64.sqrt();
                    Polarization { q: k * g(), u: k * g() }
                };
                let mut s = standard(star, &TWO, &[e, e + 2.0], ins, sigma_f);
                (s.p, s.sigma_p, s.gamma_deg, s.sigma_gamma_deg) = (p, sigma_p, gamma, if p > 0.0 { 2.0 } else { 0.0 });
                for o in &mut s.f {
                    o.f += noise_factor * sigma_f * g();
                }
                s
            })
            .collect();
        let j = fit_joint_with(&stds, &opts(ins)).unwrap();
        let (Some(t), Some(angles)) = (j.telescope, j.angles) else {
            refused += 1;
            continue;
        };
        inflated += usize::from(inflation(j.chi2, j.dof) > 1.0);
        let [fa, fb] = t.ab();
        let [a, b] = ins.tel.ab();
        let est = [
            j.offset.unwrap().c,
            ins.theta0 + axial_diff(angles.theta0_deg, ins.theta0),
            fa,
            fb,
        ];
        let truth = [ins.c, ins.theta0, a, b];
        pulls.push(std::array::from_fn(|k| (est[k] - truth[k]) / j.covariance[k][k].sqrt()));
    }
    (pulls, inflated, refused)
}

/// Mean and rms of one column of pulls.
fn mean_rms(pulls: &[[f64; 4]], k: usize) -> (f64, f64) {
    let m = pulls.len() as f64;
    (
        pulls.iter().map(|p| p[k]).sum::<f64>() / m,
        (pulls.iter().map(|p| p[k] * p[k]).sum::<f64>() / m).sqrt(),
    )
}

/// The error budget of the calibration as reported, inflation included: over 3000 nights
/// whose errors are honest, each of c, theta0, a, b has pulls of rms within 5 % of 1
/// (standard error 1.3 %), and all four pooled within 3 %. A budget 15 % off in either
/// direction fails; so did the inflation by chi^2/dof whenever it exceeded 1 (6 dof here,
/// E[1/k] = 0.876: c's rms 0.945, 41 % of the nights inflated).
#[test]
fn the_reported_calibration_covariance_gives_unit_pulls() {
    let n = 3000;
    let (pulls, inflated, refused) = pulls_of_reported_covariance(n, 1.0, 20261130);
    assert!(
        refused <= n / 20,
        "{refused} of {n} nights refused the telescope's term or theta0"
    );
    let n = pulls.len();
    let names = ["c", "theta0", "a", "b"];
    let stats: Vec<(f64, f64)> = (0..4).map(|k| mean_rms(&pulls, k)).collect();
    for (name, (mean, rms)) in names.iter().zip(&stats) {
        eprintln!("{name}: pull mean {mean:+.3}, rms {rms:.3} ({n} nights, {inflated} inflated, {refused} refused)");
    }
    let pooled = (stats.iter().map(|s| s.1 * s.1).sum::<f64>() / 4.0).sqrt();
    eprintln!("pooled rms {pooled:.3}");
    for (name, &(mean, rms)) in names.iter().zip(&stats) {
        assert!(
            (0.95..=1.05).contains(&rms),
            "{name}: pull rms {rms:.3} over {n} nights"
        );
        assert!(mean.abs() < 0.08, "{name}: pull mean {mean:+.3}");
    }
    assert!((0.97..=1.03).contains(&pooled), "pooled pull rms {pooled:.3}");
    // About 1 % of honest nights are inflated (the tail beyond the 99th percentile).
    assert!(inflated <= n / 40, "{inflated} of {n} honest nights inflated");
}
