//! The world harness's telescope options (off by default): the night's p_tel and psi_tel
//! drawn in their ranges and written into every scene, and the standards spread in time
//! and parallactic angle. Nothing of the default night changes.
use sofipol_bench::world::{calibration_scene, draw_instrument, draw_scene, WorldConfig};
use sofipol_calib::Profile;
use sofipol_pipeline::sim::{pointing, schedule, EffectKind, Scene, Simulator};

/// Mean parallactic angle of each standard of a scene (deg) and its TPL START.
fn standards_eta(scene: Scene) -> Vec<(String, f64)> {
    let sim = Simulator::new(scene, Profile::sofi()).unwrap();
    let nb = sim.scene().binary.len();
    (nb..sim.n_sequences())
        .map(|t| {
            let plan = sim.sequence_plan(t);
            let (mut c, mut s) = (0.0, 0.0);
            for k in 0..sim.frames_per_target() {
                let (a, b) = schedule::exposure_pointing(sim.scene(), plan, k);
                let eta = pointing::mean_angle_deg(a.parang_deg, b.parang_deg).to_radians();
                (c, s) = (c + eta.cos(), s + eta.sin());
            }
            (plan.tpl_start.clone(), f64::atan2(s, c).to_degrees())
        })
        .collect()
}

/// 360 deg minus the largest gap between the angles 2 eta on the circle.
fn two_eta_coverage_deg(etas: &[f64]) -> f64 {
    let mut a: Vec<f64> = etas.iter().map(|e| (2.0 * e).rem_euclid(360.0)).collect();
    a.sort_by(f64::total_cmp);
    360.0
        - a.windows(2)
            .map(|w| w[1] - w[0])
            .fold(a[0] + 360.0 - a[a.len() - 1], f64::max)
}

#[test]
fn telescope_polarization_is_drawn_in_its_ranges_only_when_asked() {
    let dir = std::env::temp_dir();
    let (mut p_min, mut p_max, mut psi_min, mut psi_max) = (1.0f64, 0.0f64, 180.0f64, 0.0f64);
    for seed in 0..200 {
        let mut cfg = WorldConfig::new(&dir);
        cfg.seed = seed;
        let off = draw_instrument(&cfg);
        assert!(off.telescope.is_none());
        let sc = calibration_scene(&cfg, &off);
        assert!(!sc.has(EffectKind::TelescopePolarization) && sc.telescope_polarization.is_none());
        cfg.telescope_polarization = true;
        let on = draw_instrument(&cfg);
        // The other draws of the night are unchanged.
        assert_eq!(
            (on.k, on.p_inst_angle_deg, on.zero_point_deg, on.parity),
            (off.k, off.p_inst_angle_deg, off.zero_point_deg, off.parity)
        );
        let t = on.telescope.expect("drawn");
        assert!(
            (0.0..0.01).contains(&t.p_tel) && (0.0..180.0).contains(&t.psi_tel_deg),
            "{t:?}"
        );
        (p_min, p_max) = (p_min.min(t.p_tel), p_max.max(t.p_tel));
        (psi_min, psi_max) = (psi_min.min(t.psi_tel_deg), psi_max.max(t.psi_tel_deg));
        if seed < 3 {
            // Every scene of the night carries it: the calibration and the targets.
            let (target, _, _) = draw_scene(&cfg, &on, 0, 1, 0.5, 0.8);
            for sc in [calibration_scene(&cfg, &on), target] {
                assert!(sc.has(EffectKind::TelescopePolarization));
                assert_eq!(sc.telescope_polarization.clone().unwrap().model(), t);
            }
        }
    }
    // Uniform over 200 nights: the extremes reach near the ends of the ranges.
    assert!(p_min < 0.0005 && p_max > 0.0095, "p_tel {p_min}..{p_max}");
    assert!(psi_min < 9.0 && psi_max > 171.0, "psi_tel {psi_min}..{psi_max}");
}

#[test]
fn spread_standards_cover_the_parallactic_angles_and_the_default_does_not_move_them() {
    let mut cfg = WorldConfig::new(&std::env::temp_dir());
    let inst = draw_instrument(&cfg);
    let plain = standards_eta(calibration_scene(&cfg, &inst));
    // Default: one after another from 01:00 (12 frames of 75 s + 120 s = 1020 s each).
    let starts: Vec<&str> = plain.iter().map(|x| x.0.as_str()).collect();
    assert_eq!(
        starts,
        [
            "1999-03-03T01:00:00",
            "1999-03-03T01:17:00",
            "1999-03-03T01:34:00",
            "1999-03-03T01:51:00"
        ]
    );
    cfg.spread_standards = true;
    let spread = standards_eta(calibration_scene(&cfg, &inst));
    let etas: Vec<f64> = spread.iter().map(|x| x.1).collect();
    assert_eq!(spread[3].0, "1999-03-03T07:00:00");
    assert!(two_eta_coverage_deg(&etas) > 150.0, "{spread:?}");
}
