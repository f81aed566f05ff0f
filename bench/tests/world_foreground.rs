//! The world harness's foreground option (off by default): the night's field drawn in its
//! ranges and shared by every target's scene, the truth of each component including the
//! field at its position, and two such targets reduced with pulls of the usual width.
use sofipol_bench::world::{self, draw_foreground, draw_instrument, draw_scene, WorldConfig};
use sofipol_calib::Profile;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{EffectKind, Simulator};

#[test]
fn foreground_is_drawn_in_its_ranges_shared_by_the_night_and_off_by_default() {
    let dir = std::env::temp_dir();
    let (mut p_max, mut rms_min, mut rms_max, mut l_min, mut l_max) = (0.0f64, 1.0f64, 0.0f64, 1e9f64, 0.0f64);
    for seed in 0..200 {
        let mut cfg = WorldConfig::new(&dir);
        cfg.seed = seed;
        let off = draw_instrument(&cfg);
        assert!(off.foreground.is_none());
        let (plain, _, _) = draw_scene(&cfg, &off, 1, 2, 0.8, 1.2);
        assert!(!plain.has(EffectKind::ForegroundField) && plain.foreground_field.is_none());
        cfg.foreground_field = true;
        let on = draw_instrument(&cfg);
        // The instrument's draws are unchanged.
        assert_eq!(
            (on.k, on.p_inst_angle_deg, on.zero_point_deg, on.parity),
            (off.k, off.p_inst_angle_deg, off.zero_point_deg, off.parity)
        );
        let f = on.foreground.clone().expect("drawn");
        assert_eq!(f, draw_foreground(seed));
        assert!(
            (0.0..0.03).contains(&f.p) && (0.0..180.0).contains(&f.angle_deg),
            "{f:?}"
        );
        assert!(
            (0.001..0.008).contains(&f.rms) && (20.0..600.0).contains(&f.coherence_arcsec),
            "{f:?}"
        );
        (p_max, rms_min, rms_max) = (p_max.max(f.p), rms_min.min(f.rms), rms_max.max(f.rms));
        (l_min, l_max) = (l_min.min(f.coherence_arcsec), l_max.max(f.coherence_arcsec));
        if seed < 3 {
            // Every target's scene of the night: the same field (same seed), otherwise the
            // same scene as without it.
            for (bin, t) in [(0, 0), (3, 5)] {
                let (a, _, _) = draw_scene(&cfg, &on, bin, t, 0.5, 0.8);
                assert!(a.has(EffectKind::ForegroundField));
                assert_eq!(a.foreground_field.as_ref(), Some(&f));
                let mut b = a.clone();
                b.effects.retain(|e| *e != EffectKind::ForegroundField);
                b.foreground_field = None;
                cfg.foreground_field = false;
                let (c, _, _) = draw_scene(&cfg, &off, bin, t, 0.5, 0.8);
                cfg.foreground_field = true;
                assert_eq!(b, c);
            }
        }
    }
    assert!(
        p_max > 0.028 && rms_min < 0.0012 && rms_max > 0.0078,
        "{p_max} {rms_min} {rms_max}"
    );
    assert!(l_min < 25.0 && l_max > 500.0, "coherence {l_min}..{l_max}");
}

#[test]
fn world_targets_behind_the_field_reduce_to_their_truth() {
    let dir = std::env::temp_dir().join(format!("sofipol-world-fg-{}", std::process::id()));
    let mut cfg = WorldConfig::new(&dir);
    cfg.instrument = false;
    cfg.foreground_field = true;
    cfg.bins_arcsec = vec![2.5, 4.0];
    cfg.targets_per_bin = 2;
    // A night whose foreground is strong (P 2.6 %) and varies on the scale of the pairs.
    cfg.seed = (0..200)
        .find(|&s| {
            let f = draw_foreground(s);
            f.p > 0.02 && f.coherence_arcsec < 60.0 && f.rms > 0.004
        })
        .expect("such a night among 200");
    let inst = draw_instrument(&cfg);
    let f = inst.foreground.clone().unwrap();
    // The truth: each component's q, u = intrinsic + the field at that component.
    let (scene, _, _) = draw_scene(&cfg, &inst, 0, 0, 2.5, 4.0);
    let sim = Simulator::new(scene, Profile::sofi()).unwrap();
    let truth = sim.truth(&[]);
    let tt = &truth.targets[0];
    let fg = tt.foreground.as_ref().unwrap();
    for (c, s) in tt.components.iter().zip(&fg.stars) {
        assert!((c.q - c.intrinsic.q - s.q).abs() < 1e-15 && (c.u - c.intrinsic.u - s.u).abs() < 1e-15);
    }
    assert!(fg.q.hypot(fg.u) > 0.005, "{f:?}: foreground at A {:?}", (fg.q, fg.u));
    let bins = world::run(&cfg, &TargetParams::default());
    let _ = std::fs::remove_dir_all(&dir);
    let b = &bins[0];
    // 2 targets x 2 components x (q, u): up to 8 pulls of a unit normal.
    assert!(b.n_pulls >= 6, "{}", world::table(&bins, true));
    assert!(
        b.rms_pull < 2.0 && b.mean_pull.abs() < 1.5,
        "{}",
        world::table(&bins, true)
    );
}
