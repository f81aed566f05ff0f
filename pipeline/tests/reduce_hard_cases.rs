//! Hard cases stay numerically stable and honest: a lone star is not split into a fake
//! binary; a faint unpolarized companion gives an undefined angle without NaN; the
//! pipeline survives an all-masked dither.
use sofipol_calib::Profile;
use sofipol_pipeline::reduce::target::{reduce_loaded, LoadedOrientation, TargetParams};
use sofipol_pipeline::sequence::{Orientation, Sequence};
use sofipol_pipeline::sim::{Scene, Simulator};

fn reduce(text: &str) -> (sofipol_pipeline::catalog::Target, sofipol_pipeline::sim::Truth) {
    let profile = Profile::sofi();
    let sim = Simulator::new(Scene::from_toml(text, "t").unwrap(), profile.clone()).unwrap();
    let (frames, truth) = sim.run_in_memory();
    let mut orients: Vec<LoadedOrientation> = Vec::new();
    let mut so: Vec<Orientation> = Vec::new();
    for f in frames {
        let pa = f.truth.posang_deg;
        if orients.last().is_none_or(|o| o.0 != pa) {
            orients.push((pa, f.truth.analyzer_deg, vec![], vec![]));
            so.push(Orientation { posang_deg: pa, analyzer_deg: f.truth.analyzer_deg, exposures: vec![] });
        }
        let o = orients.last_mut().unwrap();
        o.3.push(f.truth.header_offset_px);
        o.2.push(f.frame);
    }
    let t = &truth.targets[0];
    let seq = Sequence { id: t.object.clone(), object: t.object.clone(), tpl_start: t.tpl_start.clone(), filter: "Ks".into(), orientations: so };
    (reduce_loaded(&seq, orients, &profile, &TargetParams::default(), false).target, truth)
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
    let flags = t.extra["flags"].as_array().unwrap();
    assert!(flags.iter().any(|f| f == "companion_not_found"), "{flags:?}");
    let a = &t.components[0];
    let ta = &truth.targets[0].components[0];
    assert!(((a.q - ta.q) / a.sigma_q).abs() < 4.0 && ((a.u - ta.u) / a.sigma_u).abs() < 4.0, "{a:?}");
    assert!(t.delta_gamma_deg.is_none());
}

#[test]
fn an_unpolarized_faint_companion_stays_finite_and_fails_the_cut() {
    let (t, _) = reduce(&scene(8000.0, 0.0, 3.0));
    assert_eq!(t.components.len(), 2, "{t:?}");
    let b = &t.components[1];
    for v in [b.q, b.u, b.sigma_q, b.sigma_u, b.p, b.sigma_p, b.p_debiased, b.gamma_deg, b.sigma_gamma_deg] {
        assert!(v.is_finite(), "{b:?}");
    }
    assert!(!b.passes_cut, "{b:?}");
    assert!((0.0..180.0).contains(&b.gamma_deg));
    assert!(t.delta_gamma_deg.is_none());
}
