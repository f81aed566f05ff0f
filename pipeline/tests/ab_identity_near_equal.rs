//! A/B identity of a near-equal pair (8.3 px apart, B/A 0.90) over many simulated nights
//! with realistic conditions (seeing 0.6-1.1" varying per frame, Moffat beta 2.5-4,
//! ellipticity, flat field, beam ratio, instrumental polarization, analyzer zero-point and
//! parity, non-linearity, saturation, cosmic rays, bad pixels, 2 or 4 orientations): the
//! catalog never calls the fainter star A without `ab_identity_unverified` or
//! `ab_near_equal_flux` (the flux cannot tell them apart), and a clearly
//! unequal pair (B/A 0.5) is never flagged.
use sofipol_calib::Profile;
use sofipol_pipeline::catalog::{Flag, FlagCode, Target};
use sofipol_pipeline::reduce::run::reduce_loaded;
use sofipol_pipeline::reduce::{identity, measure_sequence, target_entry, SkySubtractedOrientation, TargetParams};
use sofipol_pipeline::sim::{loaded_from_sim, Scene, Simulator};

/// A pair `sep_px` apart (at the SOFI pixel scale), B/A = `ratio`, drawn conditions from `seed`.
fn pair_scene(sep_px: f64, ratio: f64, seed: u64) -> (String, f64) {
    // Conditions drawn from the seed (a small LCG: reproducible, independent of the sim's streams).
    let mut s = seed;
    let mut u = || {
        // splitmix64
        s = s.wrapping_add(0x9e3779b97f4a7c15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58476d1ce4e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d049bb133111eb);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    };
    let fwhm = 0.6 + 0.5 * u();
    let pa = 360.0 * u();
    let flux_a = 2e3 * 100f64.powf(u());
    let (pa_deg, ga, gb) = (pa, 180.0 * u(), 180.0 * u());
    let (p_a, p_b) = (0.01 + 0.07 * u(), 0.01 + 0.07 * u());
    let sep = sep_px * 0.288;
    let x = 250.0 + 524.0 * u();
    let y = 345.0 + 30.0 + (167.0 - 60.0) * u();
    let orientations = if seed.is_multiple_of(2) {
        "[0.0, 45.0]"
    } else {
        "[0.0, 45.0, 90.0, 135.0]"
    };
    let bitpix = if (seed / 2).is_multiple_of(2) { -32 } else { 16 };
    let k = 0.96 + 0.03 * u();
    let zp = -5.0 + 10.0 * u();
    let parity = if u() < 0.5 { 1 } else { -1 };
    (
        format!(
            r#"name = "pair"
seed = {seed}
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "bad_pixels", "transparency", "pointing_error", "cosmic_rays", "flat_field", "throughput", "instrumental_polarization", "analyzer_angle", "saturation", "nonlinearity"]
[observation]
orientations_deg = {orientations}
dithers = 5
bitpix = {bitpix}
[flat_field]
pixel_rms = 0.01
vignetting = 0.05
[throughput]
t_o = 1.0
t_e = {k}
[instrumental_polarization]
p = 0.003
angle_deg = 30.0
[analyzer_angle]
zero_point_deg = {zp}
parity = {parity}
[transparency]
min = 0.9
[psf]
kind = "moffat"
fwhm_arcsec = {fwhm}
fwhm_spread_frac = 0.2
beta_range = [2.5, 4.0]
axis_ratio_range = [0.9, 1.0]
[[binary]]
name = "Pair"
separation_arcsec = {sep}
pa_deg = {pa_deg}
flux_a = {flux_a}
flux_b = {}
p_a = {p_a}
gamma_a_deg = {ga}
p_b = {p_b}
gamma_b_deg = {gb}
x_px = {x}
y_px = {y}
"#,
            flux_a * ratio
        ),
        pa_deg,
    )
}

fn reduce(text: &str) -> Target {
    let profile = Profile::sofi();
    let sim = Simulator::new(Scene::from_toml(text, "t").unwrap(), profile.clone()).unwrap();
    let (frames, _) = sim.run_in_memory();
    let (seq, orients) = loaded_from_sim(frames, &profile);
    reduce_loaded(&seq, orients, &profile, &TargetParams::default(), None, None, false).target
}

/// Seeds of the many-night tests (each a whole target reduced).
const SEEDS: u64 = 24;

/// Whether the catalog calls the scene's B "A": B's position angle from A is the truth's
/// turned by 180 deg.
fn swapped(t: &Target, true_pa: f64) -> Option<bool> {
    let d = (t.pa_deg? - true_pa).rem_euclid(360.0);
    Some(d > 90.0 && d < 270.0)
}

fn unverified(t: &Target) -> bool {
    t.flags.iter().flatten().any(|f| f.is(FlagCode::AbIdentityUnverified))
}

/// The flux could not tell the stars apart (the labels follow the geometry).
fn near_equal(t: &Target) -> bool {
    t.flags.iter().flatten().any(|f| f.is(FlagCode::AbNearEqualFlux))
}

/// Over many nights of the near-equal pair, A is always the brighter true star unless the
/// target is flagged, and a flagged target has every component flagged and failing the cut.
#[test]
fn near_equal_pair_is_never_silently_swapped_over_many_nights() {
    use rayon::prelude::*;
    let rows: Vec<(u64, Option<bool>, bool, Target)> = (0..SEEDS)
        .into_par_iter()
        .map(|seed| {
            let (text, pa) = pair_scene(8.3, 0.90, seed);
            let t = reduce(&text);
            (seed, swapped(&t, pa), unverified(&t), t)
        })
        .collect();
    let mut found = 0;
    for (seed, sw, unver, t) in &rows {
        if *sw == Some(true) {
            assert!(
                *unver || near_equal(t),
                "seed {seed}: fainter star called A without a flag: {:?}",
                t.flags
            );
        }
        if sw.is_some() {
            found += 1;
        }
        if *unver {
            assert!(
                t.components
                    .iter()
                    .all(|c| !c.passes_cut && c.flags.iter().any(|f| f.is(FlagCode::AbIdentityUnverified))),
                "seed {seed}: {:?}",
                t.components
            );
        }
    }
    // The pair is resolved in (nearly) every night: the test looks at real labels.
    assert!(
        found >= SEEDS as usize * 3 / 4,
        "companion found in {found} of {SEEDS} nights"
    );
}

/// A pair with B/A 0.5 is told apart by flux in every night: never flagged, never swapped.
#[test]
fn clearly_unequal_pair_is_never_flagged() {
    use rayon::prelude::*;
    let rows: Vec<(u64, Option<bool>, bool, Vec<Flag>)> = (0..SEEDS)
        .into_par_iter()
        .map(|seed| {
            let (text, pa) = pair_scene(8.3, 0.5, 1000 + seed);
            let t = reduce(&text);
            (
                seed,
                swapped(&t, pa),
                unverified(&t),
                t.flags.clone().unwrap_or_default(),
            )
        })
        .collect();
    for (seed, sw, unver, flags) in rows {
        assert!(!unver, "seed {seed}: flagged: {flags:?}");
        assert_ne!(sw, Some(true), "seed {seed}: swapped: {flags:?}");
        assert!(
            !flags.iter().any(|f| f.code.name().starts_with("ab_relabelled")),
            "seed {seed}: {flags:?}"
        );
        assert!(
            !flags.iter().any(|f| f.is(FlagCode::AbNearEqualFlux)),
            "seed {seed}: {flags:?}"
        );
    }
}

/// The failure the check exists for: the companion search calls the fainter star A at
/// every orientation, consistently (B's position angle turned by 180 deg with it). The
/// per-dither o+e fluxes say B/A = 1.11 with a ratio error of about 1 %: the labels are
/// exchanged back and the catalog entry is the correctly labelled one; kept as the search
/// left them (no check), A's q and u are B's, many sigma off.
#[test]
fn fainter_star_labelled_a_at_every_orientation_is_relabelled_by_flux() {
    let (text, pa) = pair_scene(8.3, 0.90, 7);
    let profile = Profile::sofi();
    let sim = Simulator::new(Scene::from_toml(&text, "t").unwrap(), profile.clone()).unwrap();
    let (frames, _) = sim.run_in_memory();
    let (_, loaded) = loaded_from_sim(frames, &profile);
    let params = TargetParams::default();
    let orients: Vec<SkySubtractedOrientation> = loaded
        .into_iter()
        .map(|(posang, phi, frames, offs)| SkySubtractedOrientation {
            posang_deg: posang,
            analyzer_deg: phi,
            frames: sofipol_calib::sky::sky_subtract(&frames, &profile, &params.sky).unwrap(),
            offsets: offs,
        })
        .collect();
    let mut m = measure_sequence(&orients, &profile, &params.measure).unwrap();
    assert_eq!(m.dithers.len(), 2);
    assert!(
        !m.flags.iter().any(|f| f.code.name().starts_with("ab_")),
        "{:?}",
        m.flags
    );
    let right = target_entry("t", &orients, &m, &params.measure, &profile);
    assert_eq!(
        swapped(&right, pa),
        Some(false),
        "the reduction's own labels are the truth's"
    );
    // The labels as the referee found them: the fainter star is A everywhere.
    m.dithers.swap(0, 1);
    let g = m.geometry.as_mut().unwrap();
    g.1 = (g.1 + 180.0).rem_euclid(360.0);
    let wrong = target_entry("t", &orients, &m, &params.measure, &profile);
    assert_eq!(swapped(&wrong, pa), Some(true));
    let r = identity::flux_ratio(&m.dithers[0], &m.dithers[1]).unwrap();
    assert!(
        r.significant() && (r.ratio() - 1.0 / 0.9).abs() < 5.0 * r.ratio() * r.sigma,
        "{r:?}"
    );
    identity::verify_pair(&mut m, &orients, profile.geometry.pixscale_arcsec);
    assert!(
        m.flags.iter().any(|f| f.is(FlagCode::AbRelabelledByFlux)),
        "{:?}",
        m.flags
    );
    let t = target_entry("t", &orients, &m, &params.measure, &profile);
    assert!((t.pa_deg.unwrap() - right.pa_deg.unwrap()).abs() < 1e-9);
    for (c, r) in t.components.iter().zip(&right.components) {
        assert_eq!((c.name.as_str(), c.q, c.u), (r.name.as_str(), r.q, r.u));
        assert!(c.passes_cut == r.passes_cut);
    }
    // Without the check, A's q and u are B's: many sigma off A's own.
    let (a, w) = (&right.components[0], &wrong.components[0]);
    assert!(
        ((w.q - a.q) / a.sigma_q).hypot((w.u - a.u) / a.sigma_u) > 5.0,
        "{a:?} {w:?}"
    );
}

#[test]
#[ignore]
fn survey() {
    let n: u64 = std::env::var("N").ok().and_then(|v| v.parse().ok()).unwrap_or(40);
    let ratio: f64 = std::env::var("RATIO").ok().and_then(|v| v.parse().ok()).unwrap_or(0.9);
    use rayon::prelude::*;
    let rows: Vec<String> = (0..n).into_par_iter().map(|seed| {
        let (text, pa) = pair_scene(8.3, ratio, seed);
        let t = reduce(&text);
        let flags = t.flags.clone().unwrap_or_default();
        let unver = flags.iter().any(|f| f.is(FlagCode::AbIdentityUnverified));
        let swapped = t.pa_deg.map(|p| { let d = (p - pa).rem_euclid(360.0); d > 90.0 && d < 270.0 });
        let fl: Vec<f64> = t.components.iter().map(|c| c.flux_adu.unwrap_or(f64::NAN)).collect();
        format!("seed {seed} fwhm {:.2} pa {pa:.1} found {:?} swapped {swapped:?} unverified {unver} fluxes {fl:?} flags {flags:?}", t.fwhm_px.unwrap_or(0.0), t.pa_deg)
    }).collect();
    for r in rows {
        println!("{r}");
    }
}
