//! The interstellar foreground field (effect `foreground_field`) and the field-star
//! population (`field_population`) of the simulator, against independent references:
//! positions on the sky computed here by rotating unit vectors, the frames' beam fluxes
//! against the forward model, a slow aperture sum on noisy frames, and the analytic
//! luminosity function (KS test).
use sofipol_calib::Profile;
use sofipol_pipeline::sim::foreground::ForegroundField;
use sofipol_pipeline::sim::population::k_cdf;
use sofipol_pipeline::sim::scene::{FieldPopulationConfig, ForegroundFieldConfig};
use sofipol_pipeline::sim::{Scene, Simulator};
use sofipol_pipeline::stokes::model::{normalized_difference, Polarization};

/// The unit vector `sep` arcsec from (ra, dec) at position angle `pa` (east of north):
/// cos(sep) n + sin(sep) (sin(pa) east + cos(pa) north), by vectors (the simulator uses
/// spherical trigonometry on RA and Dec).
fn star_unit(ra: f64, dec: f64, sep_arcsec: f64, pa: f64) -> [f64; 3] {
    let (a, d) = (ra.to_radians(), dec.to_radians());
    let n = [d.cos() * a.cos(), d.cos() * a.sin(), d.sin()];
    let east = [-a.sin(), a.cos(), 0.0];
    let north = [-d.sin() * a.cos(), -d.sin() * a.sin(), d.cos()];
    let th = (sep_arcsec / 3600.0).to_radians();
    let (s, c) = (pa.to_radians().sin(), pa.to_radians().cos());
    std::array::from_fn(|i| th.cos() * n[i] + th.sin() * (s * east[i] + c * north[i]))
}

const FIELD: &str = r#"
[foreground_field]
p = 0.02
angle_deg = 40.0
rms = 0.008
coherence_arcsec = 8.0
modes = 64
seed = 5
"#;

fn parse(text: &str) -> Scene {
    Scene::from_toml(text, "test scene").unwrap()
}

#[test]
fn truth_records_the_field_at_every_star_and_the_frames_carry_it() {
    let text = format!(
        r#"
name = "fg"
seed = 3
effects = ["foreground_field", "interstellar_polarization"]
[observation]
orientations_deg = [0.0, 45.0, 90.0, 135.0]
dithers = 2
zero_point_mag = 22.0
{FIELD}
[interstellar_polarization]
p = 0.005
angle_deg = 100.0
[field_population]
density_per_arcmin2 = 0.2
k_max_mag = 16.0
[[binary]]
name = "One"
separation_arcsec = 2.5
pa_deg = 70.0
flux_a = 1e5
flux_b = 4e4
p_a = 0.03
gamma_a_deg = 20.0
p_b = 0.01
gamma_b_deg = 150.0
ra_deg = 68.9
dec_deg = -24.5
[[binary.field_star]]
separation_arcsec = 15.0
pa_deg = 250.0
flux = 3e5
p = 0.05
gamma_deg = 10.0
[[binary]]
name = "Two"
separation_arcsec = 1.0
pa_deg = 300.0
flux_a = 5e4
flux_b = 5e4
p_a = 0.0
gamma_a_deg = 0.0
p_b = 0.0
gamma_b_deg = 0.0
hour_angle_h = 1.0
dec_deg = -60.0
[[standard]]
name = "HD 64299"
flux = 1e5
"#
    );
    let sc = parse(&text);
    let cfg: ForegroundFieldConfig = sc.foreground_field.clone().unwrap();
    let field = ForegroundField::new(&cfg, 5);
    let ism = Polarization::from_p_gamma(0.005, 100.0);
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let (frames, truth) = sim.run_in_memory();
    let f = truth.foreground_field.as_ref().expect("field parameters in the truth");
    let mean = Polarization::from_p_gamma(0.02, 40.0);
    assert_eq!(
        (f.q_mean, f.u_mean, f.rms, f.coherence_arcsec, f.seed),
        (mean.q, mean.u, 0.008, 8.0, 5)
    );
    let mut checked = 0;
    for tt in &truth.targets {
        let fg = tt.foreground.as_ref().expect("foreground at every binary");
        // A, B, then every field star (the scene's and the drawn ones).
        assert_eq!(fg.stars.len(), 2 + tt.field_stars.len());
        assert!(tt.field_stars.len() > 1, "{}: the population drew no star", tt.object);
        assert_eq!(
            tt.field_stars.iter().filter(|s| s.k_mag.is_none()).count(),
            usize::from(tt.object == "One")
        );
        let geometry = std::iter::once((0.0, 0.0))
            .chain(std::iter::once((tt.separation_arcsec, tt.pa_deg)))
            .chain(tt.field_stars.iter().map(|s| (s.separation_arcsec, s.pa_deg)));
        for (star, (sep, pa)) in fg.stars.iter().zip(geometry) {
            let want = field.at_unit(star_unit(tt.ra_deg, tt.dec_deg, sep, pa));
            assert!(
                (star.q - want.q).abs() < 1e-9 && (star.u - want.u).abs() < 1e-9,
                "{} {}: truth ({}, {}) vs field ({}, {})",
                tt.object,
                star.name,
                star.q,
                star.u,
                want.q,
                want.u
            );
            checked += 1;
        }
        assert_eq!(
            (fg.q, fg.u),
            (fg.stars[0].q, fg.stars[0].u),
            "the binary's value is A's"
        );
        // The stars' totals: intrinsic + uniform ISM + the field at the star.
        for (c, s) in tt.components.iter().zip(&fg.stars) {
            assert!(
                (c.q - (c.intrinsic.q + ism.q + s.q)).abs() < 1e-15,
                "{} {}",
                tt.object,
                c.name
            );
            assert!(
                (c.u - (c.intrinsic.u + ism.u + s.u)).abs() < 1e-15,
                "{} {}",
                tt.object,
                c.name
            );
        }
        for (c, s) in tt.field_stars.iter().zip(&fg.stars[2..]) {
            assert_eq!(c.name, s.name);
            assert!((c.q - (c.intrinsic.q + ism.q + s.q)).abs() < 1e-15);
            assert!((c.u - (c.intrinsic.u + ism.u + s.u)).abs() < 1e-15);
        }
        // Every frame: each source's F = (o - e)/(o + e) is that total along the analyzer.
        let totals: Vec<(String, Polarization)> = tt
            .components
            .iter()
            .map(|c| (c.name.clone(), Polarization { q: c.q, u: c.u }))
            .chain(
                tt.field_stars
                    .iter()
                    .map(|c| (c.name.clone(), Polarization { q: c.q, u: c.u })),
            )
            .collect();
        let own: Vec<_> = frames
            .iter()
            .filter(|fr| tt.frames.iter().any(|t| t.file == fr.file_name))
            .collect();
        assert_eq!(own.len(), 8);
        for fr in own {
            assert_eq!(fr.truth.sources.len(), totals.len());
            for (src, (name, pol)) in fr.truth.sources.iter().zip(&totals) {
                assert_eq!(&src.name, name);
                let tot = src.flux_o + src.flux_e;
                if tot > 0.0 {
                    let f = (src.flux_o - src.flux_e) / tot;
                    let want = normalized_difference(*pol, fr.truth.analyzer_deg);
                    assert!((f - want).abs() < 1e-12, "{} {name}: F {f} vs {want}", tt.object);
                }
            }
        }
    }
    assert!(checked > 6);
    // Standards see no foreground: their p and gamma are their totals.
    let st = &truth.standards[0];
    assert!(st.foreground.is_none() && st.field_stars.is_empty());
    assert_eq!((st.components[0].q, st.components[0].u), (0.0, 0.0));
}

/// A bright field star without intrinsic polarization, measured from noisy frames by a
/// slow aperture sum, shows the foreground at its own position (not at the binary's).
#[test]
fn unpolarized_bright_star_measured_in_the_frames_shows_the_foreground_at_its_position() {
    let text = format!(
        r#"
name = "fgstar"
seed = 11
effects = ["foreground_field", "photon_noise"]
[observation]
orientations_deg = [0.0, 45.0, 90.0, 135.0]
dithers = 3
{FIELD}
[[binary]]
name = "Target"
separation_arcsec = 2.0
pa_deg = 30.0
flux_a = 2e4
flux_b = 0.0
p_a = 0.0
gamma_a_deg = 0.0
p_b = 0.0
gamma_b_deg = 0.0
ra_deg = 68.9
dec_deg = -24.5
[[binary.field_star]]
separation_arcsec = 20.0
pa_deg = 60.0
flux = 2e6
"#
    );
    let profile = Profile::sofi();
    let gain = profile.detector.effective_gain(6);
    let sim = Simulator::new(parse(&text), profile).unwrap();
    let (frames, truth) = sim.run_in_memory();
    let tt = &truth.targets[0];
    let fg = tt.foreground.as_ref().unwrap();
    let (star, at_a) = (&fg.stars[2], &fg.stars[0]);
    assert_eq!(star.name, "field1");
    // Aperture sums (7 x 7 px around the true image; no sky, no PSF: a point shared among
    // four pixels) and F per frame, then q, u by least squares on cos 2phi, sin 2phi.
    let box_sum = |img: &ndarray::Array2<f32>, xy: [f64; 2]| {
        let (x0, y0) = (xy[0].round() as usize, xy[1].round() as usize);
        let mut s = 0.0;
        for y in y0 - 3..=y0 + 3 {
            for x in x0 - 3..=x0 + 3 {
                s += img[[y, x]] as f64;
            }
        }
        s
    };
    let (mut a11, mut a12, mut a22, mut b1, mut b2, mut var_f) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for fr in &frames {
        let src = fr.truth.sources.iter().find(|s| s.name == "field1").unwrap();
        let (o, e) = (box_sum(&fr.frame.data, src.o_xy), box_sum(&fr.frame.data, src.e_xy));
        let f = (o - e) / (o + e);
        let t = 2.0 * fr.truth.analyzer_deg.to_radians();
        let (c, s) = (t.cos(), t.sin());
        a11 += c * c;
        a12 += c * s;
        a22 += s * s;
        b1 += c * f;
        b2 += s * f;
        // Poisson: var F = (1 - F^2)/N_e with N_e the electrons of o + e.
        var_f += (1.0 - f * f) / ((o + e) * gain);
    }
    let n = frames.len() as f64;
    let det = a11 * a22 - a12 * a12;
    let (q, u) = ((a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det);
    // The angles are evenly spread: sigma_q = sigma_u = sigma_F sqrt(2/n).
    let sigma = (var_f / n).sqrt() * (2.0 / n).sqrt();
    assert!(sigma < 1e-4, "sigma {sigma}");
    let (dq, du) = (q - star.q, u - star.u);
    assert!(
        dq.abs() < 4.0 * sigma && du.abs() < 4.0 * sigma,
        "measured ({q:.5}, {u:.5}) vs the field at the star ({:.5}, {:.5}), sigma {sigma:.1e}",
        star.q,
        star.u
    );
    // The measurement tells the star's foreground from the binary's (8" coherence, 20"
    // away) and from no foreground at all.
    assert!(
        (star.q - at_a.q).hypot(star.u - at_a.u) > 20.0 * sigma,
        "field at A and at the star alike"
    );
    assert!(q.hypot(u) > 50.0 * sigma);
}

/// The drawn magnitudes follow the configured luminosity function (KS test against the
/// analytic CDF), their number the expected Poisson mean, and the rest of the population
/// its configuration.
#[test]
fn field_population_follows_the_luminosity_function() {
    let mut text = String::from(
        r#"
name = "lf"
seed = 21
[observation]
orientations_deg = [30.0]
dithers = 1
dit_s = 10.0
zero_point_mag = 22.5
[field_population]
density_per_arcmin2 = 0.5
k_ref_mag = 14.0
slope_dex_per_mag = 0.3
k_min_mag = 8.0
k_max_mag = 18.0
polarized_fraction = 0.1
p_polarized = [0.02, 0.10]
exclude_arcsec = 3.0
"#,
    );
    let n_bin = 40;
    for i in 0..n_bin {
        text += &format!(
            "[[binary]]\nname = \"T{i}\"\nseparation_arcsec = 1.5\npa_deg = 10.0\nflux_a = 1e5\nflux_b = 1e5\np_a = 0.0\ngamma_a_deg = 0.0\np_b = 0.0\ngamma_b_deg = 0.0\n"
        );
    }
    let sc = parse(&text);
    let cfg: FieldPopulationConfig = sc.field_population.clone().unwrap();
    let profile = Profile::sofi();
    let g = profile.geometry.clone();
    let sim = Simulator::new(sc, profile).unwrap();
    let truth = sim.truth(&[]);
    let pop = truth.field_population.as_ref().unwrap();
    // SOFI: three o strips of 167 rows x 1024 px at 0.288"/px.
    let area = 1024.0 * 3.0 * 167.0 * 0.288f64.powi(2) / 3600.0;
    assert!((pop.area_arcmin2 - area).abs() < 1e-9, "{}", pop.area_arcmin2);
    let lambda = 0.5 * area * (10f64.powf(0.3 * 4.0) - 10f64.powf(0.3 * -6.0));
    assert!((pop.expected_per_binary - lambda).abs() < 1e-9);

    let stars: Vec<_> = truth.targets.iter().flat_map(|t| t.field_stars.iter()).collect();
    let total = n_bin as f64 * lambda;
    let n = stars.len() as f64;
    // Poisson total (less the 2 x pi 3"^2 excluded around A and B: 0.14 % of the area).
    assert!(
        (n - total * 0.9986).abs() < 4.0 * total.sqrt(),
        "{n} stars, expected {total}"
    );

    let mut k: Vec<f64> = stars.iter().map(|s| s.k_mag.unwrap()).collect();
    k.sort_by(f64::total_cmp);
    let d = k
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let f = k_cdf(&cfg, x);
            (f - i as f64 / n).abs().max(((i + 1) as f64 / n - f).abs())
        })
        .fold(0.0, f64::max);
    // KS at the 1 % level: D < 1.63 / sqrt(n).
    assert!(d < 1.63 / n.sqrt(), "KS D = {d} over {n} stars");
    // The analytic law in two numbers: a quarter of the stars fainter than 17.58 (F = 0.75
    // at K = 8 + log10(1 + 0.75 (10^3 - 1))/0.3) and a tenth brighter than 14.68.
    let frac = |lo: f64| k.iter().filter(|&&x| x > lo).count() as f64 / n;
    let k75 = 8.0 + (1.0 + 0.75 * (10f64.powf(3.0) - 1.0)).log10() / 0.3;
    assert!((frac(k75) - 0.25).abs() < 4.0 * (0.25f64 * 0.75 / n).sqrt());

    let zp_flux = |m: f64| 10.0 * 10f64.powf(-0.4 * (m - 22.5));
    let mut polarized = 0;
    let scale = g.pixscale_arcsec;
    let (xa, ya) = (g.nx as f64 / 2.0, (g.o_target[0] + g.o_target[1]) as f64 / 2.0 - 0.5);
    for s in &stars {
        let m = s.k_mag.unwrap();
        assert!((8.0..18.0).contains(&m));
        assert!((s.flux / zp_flux(m) - 1.0).abs() < 1e-12);
        if s.intrinsic.p() > 0.0 {
            polarized += 1;
            assert!((0.02..=0.10).contains(&s.intrinsic.p()), "{}", s.intrinsic.p());
        }
        // Inside an o strip at the first rotator angle (30 deg) and zero offset, on the
        // detector, and not within 3" of A.
        assert!(s.separation_arcsec >= 3.0);
        let d = (s.pa_deg - 30.0).to_radians();
        let x = xa - s.separation_arcsec * d.sin() / scale;
        let y = ya + s.separation_arcsec * d.cos() / scale;
        assert!((-0.5..g.nx as f64 - 0.5).contains(&x), "x {x}");
        let row = (y + 0.5).floor() as usize;
        assert!(
            g.strips()
                .iter()
                .any(|(name, r)| name.starts_with("o_") && (r[0]..r[1]).contains(&row)),
            "y {y} in no o strip"
        );
    }
    let pf = polarized as f64 / n;
    assert!((pf - 0.1).abs() < 4.0 * (0.09 / n).sqrt(), "polarized fraction {pf}");
    // Some saturated (peak above 37000 ADU needs ~1e6 ADU at 0.8" seeing), most faint.
    assert!(stars.iter().any(|s| s.flux > 1e6));
    assert!(stars.iter().filter(|s| s.flux < 1e4).count() as f64 > 0.5 * n);
}

/// Not listed, the section changes nothing; listed with zero amplitude, the frames are
/// bit-identical too (the effect draws from no other effect's stream).
#[test]
fn without_the_effect_or_at_zero_amplitude_the_frames_are_unchanged() {
    let base = r#"
name = "same"
seed = 4
effects = [EFFECTS]
[observation]
orientations_deg = [0.0, 45.0]
dithers = 2
[psf]
fwhm_arcsec = 0.8
[[binary]]
name = "Pair"
separation_arcsec = 2.0
pa_deg = 30.0
flux_a = 1e5
flux_b = 5e4
p_a = 0.03
gamma_a_deg = 20.0
p_b = 0.02
gamma_b_deg = 100.0
[[binary.field_star]]
separation_arcsec = 12.0
pa_deg = 200.0
flux = 3e4
"#;
    let run = |effects: &str, extra: &str| {
        let sc = parse(&(base.replace("EFFECTS", effects) + extra));
        let sim = Simulator::new(sc, Profile::sofi()).unwrap();
        let (frames, truth) = sim.run_in_memory();
        (frames, serde_json::to_value(&truth).unwrap(), sim.calls())
    };
    let common = r#""psf", "sky", "photon_noise", "read_noise""#;
    let (plain, plain_truth, _) = run(common, "");
    let (ignored, ignored_truth, calls) = run(common, FIELD);
    assert!(!calls.contains_key("foreground_field"));
    let zero = "[foreground_field]\np = 0.0\nrms = 0.0\n";
    let (zeroed, zeroed_truth, zcalls) = run(&format!("{common}, \"foreground_field\""), zero);
    assert!(zcalls.contains_key("foreground_field"));
    let bits = |fs: &[sofipol_pipeline::sim::SimFrame]| {
        fs.iter()
            .flat_map(|f| f.frame.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&plain), bits(&ignored));
    assert_eq!(bits(&plain), bits(&zeroed));
    // The truth: the same but for the scene's section and the ignored list.
    let strip = |mut v: serde_json::Value| {
        v["scene"].as_object_mut().unwrap().remove("foreground_field");
        v["ignored_sections"] = serde_json::Value::Null;
        v
    };
    assert_eq!(strip(plain_truth.clone()), strip(ignored_truth));
    assert!(plain_truth["targets"][0].get("foreground").is_none());
    assert!(plain_truth["targets"][0].get("field_stars").is_none());
    assert!(plain_truth.get("foreground_field").is_none());
    assert!(zeroed_truth["targets"][0]["foreground"]["stars"][2]["q"] == 0.0);
}

#[test]
fn refused_values_name_the_key() {
    let base = "name = \"bad\"\neffects = [\"foreground_field\"]\n[[binary]]\nname = \"P\"\nseparation_arcsec = 2.0\npa_deg = 0.0\nflux_a = 1.0\nflux_b = 1.0\np_a = 0.0\ngamma_a_deg = 0.0\np_b = 0.0\ngamma_b_deg = 0.0\n";
    for (extra, key) in [
        (
            "[foreground_field]\ncoherence_arcsec = 0.0\n",
            "foreground_field.coherence_arcsec = 0",
        ),
        ("[foreground_field]\nrms = -0.01\n", "foreground_field.rms = -0.01"),
        ("[foreground_field]\nmodes = 0\n", "foreground_field.modes = 0"),
        ("[field_population]\n", "observation.zero_point_mag"),
        (
            "[observation]\nzero_point_mag = 22.0\n[field_population]\nslope_dex_per_mag = 0.0\n",
            "field_population.slope_dex_per_mag = 0",
        ),
        (
            "[observation]\nzero_point_mag = 22.0\n[field_population]\nk_max_mag = 30.0\n",
            "field_population.density_per_arcmin2",
        ),
    ] {
        let err = Scene::from_toml(&format!("{base}{extra}"), "bad.toml")
            .unwrap_err()
            .to_string();
        assert!(err.contains(key) && err.contains("bad.toml"), "{extra}: {err}");
    }
}

/// The example of docs/simulator.md parses and gives what the page says of it.
#[test]
fn documented_example_scene_gives_the_stated_population() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../testdata/scenes/foreground_field.toml");
    let sc = Scene::from_toml(&std::fs::read_to_string(path).unwrap(), path).unwrap();
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let truth = sim.truth(&[]);
    let pop = truth.field_population.as_ref().unwrap();
    // "0.5 x 11.8 x (10^1.2 - 10^-1.8) = 94" stars on "11.8 arcmin^2".
    assert!((pop.area_arcmin2 - 11.8).abs() < 0.05 && (pop.expected_per_binary - 94.0).abs() < 0.5);
    for tt in &truth.targets {
        let n = tt.field_stars.len() as f64;
        assert!((n - 94.0).abs() < 4.0 * 94f64.sqrt(), "{}: {n} field stars", tt.object);
        let fg = tt.foreground.as_ref().unwrap();
        let mean = Polarization::from_p_gamma(0.02, 60.0);
        assert!((fg.q - mean.q).abs() < 5.0 * 0.004 && (fg.u - mean.u).abs() < 5.0 * 0.004);
    }
}
