//! The telescope's term of F against the forward model: the sky-frame polarization
//! `TelescopePolarization::at(eta)` seen through the analyzer.
use super::*;
use crate::stokes::model::normalized_difference;

fn two_eta(eta_deg: f64) -> [f64; 2] {
    let e = 2.0 * eta_deg.to_radians();
    [e.cos(), e.sin()]
}

#[test]
fn the_telescope_term_is_the_forward_model_seen_through_the_analyzer() {
    let t = TelescopePolarization {
        p_tel: 0.006,
        psi_tel_deg: 25.0,
    };
    for eta in [-157.0, -90.0, -12.5, 0.0, 44.0, 179.0] {
        for phi in [0.0, 3.0, 45.0, 93.0, 138.0, -42.0] {
            let want = normalized_difference(t.at(eta), phi);
            let got = telescope_f(t.ab(), phi, two_eta(eta));
            assert!((got - want).abs() < 1e-15, "eta {eta} phi {phi}: {got} vs {want}");
        }
    }
    // Frames at several parallactic angles, weighted: the mean of the model over the frames.
    let (etas, w) = ([-150.0, -120.0, -95.0], [1.0, 2.0, 0.5]);
    let sw: f64 = w.iter().sum();
    let mean2: [f64; 2] =
        std::array::from_fn(|i| etas.iter().zip(&w).map(|(&e, &wi)| wi * two_eta(e)[i]).sum::<f64>() / sw);
    for phi in [0.0, 45.0] {
        let want: f64 = etas
            .iter()
            .zip(&w)
            .map(|(&e, &wi)| wi * normalized_difference(t.at(e), phi))
            .sum::<f64>()
            / sw;
        assert!((telescope_f(t.ab(), phi, mean2) - want).abs() < 1e-15);
    }
}

#[test]
fn removing_the_term_leaves_the_star_and_the_mean_removed_is_the_sky_frame_vector() {
    let t = TelescopePolarization {
        p_tel: 0.008,
        psi_tel_deg: 140.0,
    };
    let star = Polarization::from_p_gamma(0.02, 70.0);
    let etas = [-40.0, -38.0, -36.0, -34.0];
    let obs: Vec<OrientationF> = [0.0, 45.0, 90.0, 135.0]
        .iter()
        .zip(&etas)
        .map(|(&phi, &eta)| OrientationF {
            analyzer_deg: phi,
            f: normalized_difference(star.add(t.at(eta)), phi),
            sigma_f: 1e-3,
        })
        .collect();
    let eta2: Vec<Option<[f64; 2]>> = etas.iter().map(|&e| Some(two_eta(e))).collect();
    let clean = remove(&obs, &eta2, t.ab()).unwrap();
    for (o, &phi) in clean.iter().zip(&[0.0, 45.0, 90.0, 135.0]) {
        assert!((o.f - normalized_difference(star, phi)).abs() < 1e-15);
    }
    // Equal weights: the removed vector is the telescope's at the mean of 2eta.
    let m = mean_removed(&obs, &eta2, t.ab()).unwrap();
    let mean2: [f64; 2] = std::array::from_fn(|i| eta2.iter().map(|v| v.unwrap()[i]).sum::<f64>() / 4.0);
    let want = Polarization {
        q: t.ab()[0] * mean2[0] - t.ab()[1] * mean2[1],
        u: t.ab()[0] * mean2[1] + t.ab()[1] * mean2[0],
    };
    assert!((m.q - want.q).abs() < 1e-15 && (m.u - want.u).abs() < 1e-15);
    // Close to the vector at the middle angle (-37 deg): the angles span only 6 deg.
    assert!((m.q - t.at(-37.0).q).abs() < 1e-4 && (m.u - t.at(-37.0).u).abs() < 1e-4);
    // An orientation without a parallactic angle is named.
    let mut missing = eta2.clone();
    missing[2] = None;
    let err = remove(&obs, &missing, t.ab()).unwrap_err();
    assert!(err.contains("90.0"), "{err}");
}

#[test]
fn p_tel_and_psi_tel_errors_follow_from_the_covariance_of_a_and_b() {
    let t = TelescopePolarization {
        p_tel: 0.006,
        psi_tel_deg: 30.0,
    };
    let mut cov = [[0.0; 4]; 4];
    let s = 4e-4;
    cov[CAL_TEL_A][CAL_TEL_A] = s * s;
    cov[CAL_TEL_B][CAL_TEL_B] = s * s;
    let c = TelescopeCalibration::from_fit(&t, &cov);
    // Isotropic errors: sigma_p = s, sigma_psi = s / (2 p) rad.
    assert!((c.sigma_p_tel - s).abs() < 1e-15);
    assert!((c.sigma_psi_tel_deg - (s / (2.0 * 0.006)).to_degrees()).abs() < 1e-12);
    assert_eq!(c.ab(), t.ab());
}
