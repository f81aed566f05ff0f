//! Hard cases stay numerically stable and honest: a lone star is not split into a fake
//! binary; a faint unpolarized companion gives finite values and fails the cut; a
//! saturated primary is flagged, never silently used.
use sofipol_calib::Profile;
use sofipol_pipeline::reduce::run::reduce_loaded;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{loaded_from_sim, Scene, Simulator};

fn reduce(text: &str) -> (sofipol_pipeline::catalog::Target, sofipol_pipeline::sim::Truth) {
    let profile = Profile::sofi();
    let sim = Simulator::new(Scene::from_toml(text, "t").unwrap(), profile.clone()).unwrap();
    let (frames, truth) = sim.run_in_memory();
    let (seq, orients) = loaded_from_sim(frames, &profile);
    (
        reduce_loaded(&seq, orients, &profile, &TargetParams::default(), None, None, false).target,
        truth,
    )
}

fn scene(flux_b: f64, p_b: f64, sep: f64) -> String {
    format!(
        r#"name = "hard"
seed = 8
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "cosmic_rays"]
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[[binary]]
name = "Hard"
separation_arcsec = {sep}
pa_deg = 77.0
flux_a = 150000.0
flux_b = {flux_b}
p_a = 0.03
gamma_a_deg = 30.0
p_b = {p_b}
gamma_b_deg = 0.0
"#
    )
}

#[test]
fn a_lone_star_is_not_split_into_a_binary() {
    let (t, truth) = reduce(&scene(0.0, 0.0, 2.0));
    assert_eq!(t.components.len(), 1, "{t:?}");
    let flags = t.flags.as_ref().unwrap();
    assert!(flags.iter().any(|f| f == "companion_not_found"), "{flags:?}");
    let a = &t.components[0];
    let ta = &truth.targets[0].components[0];
    assert!(
        ((a.q - ta.q) / a.sigma_q).abs() < 4.0 && ((a.u - ta.u) / a.sigma_u).abs() < 4.0,
        "{a:?}"
    );
    assert!(t.delta_gamma_deg.is_none());
}

#[test]
fn an_unpolarized_faint_companion_stays_finite_and_fails_the_cut() {
    let (t, _) = reduce(&scene(8000.0, 0.0, 3.0));
    assert_eq!(t.components.len(), 2, "{t:?}");
    let b = &t.components[1];
    for v in [
        b.q,
        b.u,
        b.sigma_q,
        b.sigma_u,
        b.p,
        b.sigma_p,
        b.p_debiased,
        b.gamma_deg,
        b.sigma_gamma_deg,
    ] {
        assert!(v.is_finite(), "{b:?}");
    }
    assert!(!b.passes_cut, "{b:?}");
    assert!((0.0..180.0).contains(&b.gamma_deg));
    assert!(t.delta_gamma_deg.is_none());
}

#[test]
fn a_saturated_primary_is_flagged_not_silently_used() {
    let text = scene(60000.0, 0.04, 3.0)
        .replace("effects = [\"psf\",", "effects = [\"saturation\", \"psf\",")
        .replace("flux_a = 150000.0", "flux_a = 3000000.0");
    let (t, _) = reduce(&text);
    let a = &t.components[0];
    assert!(a.flags.iter().any(|f| f == "saturated"), "{:?}", a.flags);
    for v in [a.q, a.u, a.sigma_q, a.sigma_u, a.p, a.sigma_p] {
        assert!(v.is_finite(), "{a:?}");
    }
    // The companion, 50x fainter beside a saturated core, is either measured unflagged or
    // reported as not found: never a crash, never a silent NaN.
    match t.components.get(1) {
        Some(b) => assert!(!b.flags.iter().any(|f| f == "saturated") && b.q.is_finite(), "{b:?}"),
        None => assert!(t.flags.as_ref().unwrap().iter().any(|f| f == "companion_not_found")),
    }
}

/// One dither per orientation: no sky can come from the data itself. Refused by name
/// (each orientation dropped with the reason, then the target failed), never a number.
#[test]
fn one_dither_per_orientation_is_refused_by_name() {
    let text = scene(60000.0, 0.04, 3.0).replace(
        "[psf]",
        "[observation]\norientations_deg = [0.0, 45.0]\ndithers = 1\n[psf]",
    );
    let (t, _) = reduce(&text);
    assert_eq!(t.status, sofipol_pipeline::catalog::Status::Failed, "{t:?}");
    assert!(t.components.is_empty(), "{t:?}");
    let err = t.error.clone().unwrap_or_default();
    assert!(err.contains("at least 2 analyzer angles"), "{err}");
    let flags = t.flags.as_ref().unwrap();
    for pa in ["0", "45"] {
        assert!(
            flags.iter().any(|f| {
                let f = f.as_str();
                f.contains(&format!("POSANG {pa} dropped")) && f.contains("1 readable dither(s), need 2")
            }),
            "{flags:?}"
        );
    }
}
