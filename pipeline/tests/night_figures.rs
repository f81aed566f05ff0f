//! The per-target figures of a night show the catalog's final numbers: drawn after the
//! calibration has re-solved every component, never from the reduction's first solution.
use std::sync::Mutex;

use sofipol_calib::Profile;
use sofipol_pipeline::calibration::CalibSetup;
use sofipol_pipeline::catalog::FlagCode;
use sofipol_pipeline::night::{run_night, Hooks, NightSetup, RunOptions};
use sofipol_pipeline::plots::target::{FigureNumbers, TargetFigure};
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{Scene, Simulator};

/// The demo scene with two of its binaries (the faint companion near the cut and the easy
/// pair), its standards, dome flats and instrument (offset c ~ 1.8 %, zero-point 3 deg):
/// the calibration moves every q and u by many sigma.
fn small_night(dir: &std::path::Path) {
    let text = include_str!("../../testdata/scenes/demo.toml");
    let mut scene = Scene::from_toml(text, "demo").unwrap();
    scene.binary.retain(|b| b.name == "Demo Faint" || b.name == "Demo Easy");
    assert_eq!(scene.binary.len(), 2);
    let sim = Simulator::new(scene, Profile::sofi()).unwrap();
    sim.write_to_dir(dir, &|_| {}).unwrap();
}

#[test]
fn night_figures_show_the_calibrated_catalog() {
    let dir = tempfile::tempdir().unwrap();
    small_night(dir.path());
    let params = TargetParams::default();
    let setup = NightSetup {
        profile: Profile::sofi(),
        calibration: CalibSetup::new(params.calibration.clone()).unwrap(),
        params,
    };
    let plan = setup.plan(&[dir.path().to_path_buf()], None);
    let drawn: Mutex<Vec<(String, FigureNumbers)>> = Mutex::new(Vec::new());
    let on_figure = |fig: &TargetFigure| {
        // The figure renders (the numbers below are what it draws).
        let (w, h, rgb) = fig.rgb().unwrap();
        assert_eq!(rgb.len(), (w * h * 3) as usize);
        drawn
            .lock()
            .unwrap()
            .push((fig.target.sequence_id().to_string(), fig.numbers()));
    };
    let opts = RunOptions {
        night_mask: true,
        hooks: Hooks {
            on_done: None,
            on_figure: Some(&on_figure),
            on_reduced: None,
        },
        ..Default::default()
    };
    let out = run_night(&plan, &setup, &opts);
    let cat = &out.catalog;
    let cal = out.calibration.as_ref().expect("the night's standards calibrate it");
    let fc = cal.for_filter("Ks").unwrap();
    let angles = fc.angles.as_ref().unwrap();
    let tel = fc
        .telescope
        .as_ref()
        .expect("the demo's standards measure the telescope's term");
    let drawn = drawn.into_inner().unwrap();
    assert_eq!(drawn.len(), cat.targets.len());
    assert_eq!(cat.targets.len(), 2);
    // The uncalibrated solution, as the reduction first made it: the figure must not show it.
    let mut moved = 0;
    for t in &cat.targets {
        let (_, nums) = drawn
            .iter()
            .find(|d| d.0 == t.sequence_id())
            .unwrap_or_else(|| panic!("no figure for {}", t.object));
        assert_eq!(nums.status, t.status, "{}", t.object);
        assert_eq!(nums.delta_gamma_deg, t.delta_gamma_deg, "{}", t.object);
        assert_eq!(nums.sigma_delta_gamma_deg, t.sigma_delta_gamma_deg, "{}", t.object);
        assert_eq!(
            nums.delta_gamma_interval_deg, t.delta_gamma_interval_deg,
            "{}",
            t.object
        );
        assert_eq!(nums.components.len(), t.components.len(), "{}", t.object);
        for (n, c) in nums.components.iter().zip(&t.components) {
            let who = format!("{} {}", t.object, c.name);
            assert_eq!(n.name, c.name, "{who}");
            // Bit for bit: the figure reads the catalog entry.
            for (what, a, b) in [
                ("q", n.q, c.q),
                ("u", n.u, c.u),
                ("sigma_q", n.sigma_q, c.sigma_q),
                ("sigma_u", n.sigma_u, c.sigma_u),
                ("P", n.p, c.p),
                ("sigma_P", n.sigma_p, c.sigma_p),
                ("P_debiased", n.p_debiased, c.p_debiased),
                ("gamma", n.gamma_deg, c.gamma_deg),
                ("sigma_gamma", n.sigma_gamma_deg, c.sigma_gamma_deg),
            ] {
                assert!(a.to_bits() == b.to_bits(), "{who}: figure {what} = {a}, catalog {b}");
            }
            assert_eq!(n.passes_cut, c.passes_cut, "{who}: cut");
            assert_eq!(n.flags, c.flags, "{who}: flags");
            assert!(
                !c.flags.iter().any(|f| f.is(FlagCode::Uncalibrated)),
                "{who}: {:?}",
                c.flags
            );
            // The fitted F lines: the calibration's analyzer angles, offset and telescope's
            // term, evaluated independently here from the calibration record and the
            // catalog's orientations.
            let offset = c.instrumental_offset.as_ref().expect("offset subtracted").c;
            assert!((offset - fc.offset.as_ref().unwrap().c).abs() < 1e-12, "{who}");
            assert!(c.telescope_qu.is_some(), "{who}: the telescope's term was not removed");
            let posangs = t.orientations_deg.as_ref().unwrap();
            assert_eq!(n.model_f.len(), posangs.len(), "{who}");
            for (k, &pa) in posangs.iter().enumerate() {
                let phi = (angles.parity as f64 * pa + angles.theta0_deg).to_radians();
                let (c2, s2) = ((2.0 * phi).cos(), (2.0 * phi).sin());
                let of = &c.orientations.as_ref().unwrap()[k];
                let [cc, ss] = of.parallactic_2eta.expect("parallactic angle");
                let tel_f = tel.a * (cc * c2 + ss * s2) + tel.b * (cc * s2 - ss * c2);
                let want = c.q * c2 + c.u * s2 + offset + tel_f;
                assert!(
                    (n.model_f[k] - want).abs() < 1e-12,
                    "{who}: F line at {pa}: {} vs {want}",
                    n.model_f[k]
                );
                assert!((n.telescope_f[k].unwrap() - tel_f).abs() < 1e-15, "{who}");
                // The line goes through the catalog's combined F of that orientation: two
                // orientations, two unknowns, an exact fit of F - c - T (without T in the
                // line it would miss F by T).
                assert!(
                    (n.model_f[k] - of.f).abs() < 1e-9,
                    "{who}: F line {} vs combined F {} +- {} (T = {tel_f})",
                    n.model_f[k],
                    of.f,
                    of.sigma_f
                );
            }
            // The calibration moved this component by more than its error: a figure drawn
            // from the first solution would differ.
            let first = c.orientations.as_ref().unwrap();
            let (f0, f1) = (first[0].f, first[1].f);
            // Uncalibrated solution of two orientations 45 deg apart with the profile's angles
            // (0 and 45 deg) and no offset: q = F(0), u = F(45).
            if (f0 - c.q).abs() > c.sigma_q || (f1 - c.u).abs() > c.sigma_u {
                moved += 1;
            }
        }
    }
    assert_eq!(moved, 4, "the calibration must move every component");
    // The faint companion: its catalog cut decision is the figure's.
    let faint = cat.targets.iter().find(|t| t.object.contains("Faint")).unwrap();
    let nums = &drawn.iter().find(|d| d.0 == faint.sequence_id()).unwrap().1;
    assert_eq!(nums.components[1].passes_cut, faint.components[1].passes_cut);
}
