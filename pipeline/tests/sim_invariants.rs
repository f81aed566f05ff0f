//! Invariants of the scene simulator against the analytic forward model.
use ndarray::{s, Array2};
use sofipol_calib::Profile;
use sofipol_pipeline::sim::{EffectKind, Scene, Simulator};
use sofipol_pipeline::stokes::model::{companion_offset_px, normalized_difference, Polarization};

fn scene(effects: &str, extra: &str, orientations: &str) -> Scene {
    let text = format!(
        r#"
name = "t"
seed = 11
effects = [{effects}]
[observation]
orientations_deg = [{orientations}]
dithers = 2
[[binary]]
name = "Test Star"
separation_arcsec = 4.0
pa_deg = 130.0
flux_a = 50000.0
flux_b = 20000.0
p_a = 0.08
gamma_a_deg = 35.0
p_b = 0.05
gamma_b_deg = 160.0
{extra}
"#
    );
    Scene::from_toml(&text, "test scene").unwrap()
}

fn single_star(effects: &str, orientations: &str, extra: &str) -> Scene {
    let text = format!(
        r#"
name = "t"
seed = 3
effects = [{effects}]
[observation]
orientations_deg = [{orientations}]
dithers = 1
[[binary]]
name = "single"
separation_arcsec = 3.0
pa_deg = 0.0
flux_a = 40000.0
flux_b = 0.0
p_a = 0.12
gamma_a_deg = 71.0
p_b = 0.0
gamma_b_deg = 0.0
{extra}
"#
    );
    Scene::from_toml(&text, "single-star scene").unwrap()
}

fn strip_sum(img: &Array2<f32>, rows: [usize; 2]) -> f64 {
    img.slice(s![rows[0]..rows[1], ..]).iter().map(|&v| v as f64).sum()
}

fn sum(img: &Array2<f32>) -> f64 {
    img.iter().map(|&v| v as f64).sum()
}

#[test]
fn psf_flux_sums_to_requested_flux() {
    for psf in ["kind = \"gaussian\"", "kind = \"moffat\"\nbeta = 2.5"] {
        let sc = scene("\"psf\"", &format!("[psf]\n{psf}\nfwhm_arcsec = 0.9\n"), "0.0, 45.0");
        let sim = Simulator::new(sc, Profile::sofi()).unwrap();
        let (frames, _) = sim.run_in_memory();
        for f in &frames {
            let total = sum(&f.frame.data);
            assert!((total / 70000.0 - 1.0).abs() < 2e-6, "{psf}: {total}");
        }
    }
}

#[test]
fn o_plus_e_is_i_times_transmission_and_f_follows_the_model() {
    let p = Profile::sofi();
    let sc = single_star(
        "\"psf\", \"throughput\"",
        "0.0, 22.5, 45.0, 67.5, 90.0, 135.0, 161.0",
        "[throughput]\nt_o = 0.9\nt_e = 0.9\n[psf]\nkind = \"gaussian\"\nfwhm_arcsec = 1.0\n",
    );
    let sim = Simulator::new(sc, p.clone()).unwrap();
    let (frames, truth) = sim.run_in_memory();
    let pol = Polarization::from_p_gamma(0.12, 71.0);
    assert_eq!(frames.len(), 7);
    for f in &frames {
        let o = strip_sum(&f.frame.data, p.geometry.o_target);
        let e = strip_sum(&f.frame.data, p.geometry.e_target);
        assert!(((o + e) / (0.9 * 40000.0) - 1.0).abs() < 2e-6, "o+e = {}", o + e);
        let phi = f.truth.analyzer_deg;
        let model = normalized_difference(pol, phi);
        assert!(
            ((o - e) / (o + e) - model).abs() < 2e-6,
            "phi {phi}: F {} vs {model}",
            (o - e) / (o + e)
        );
    }
    assert!((truth.targets[0].components[0].gamma_deg - 71.0).abs() < 1e-9);
}

#[test]
fn unequal_throughput_scales_each_beam() {
    let p = Profile::sofi();
    let sc = single_star("\"throughput\"", "0.0, 45.0", "[throughput]\nt_o = 1.0\nt_e = 0.8\n");
    let sim = Simulator::new(sc, p.clone()).unwrap();
    let (frames, _) = sim.run_in_memory();
    // phi = 0, q = 0.12 cos(142 deg): f_o = 1.0/2 I (1 + q), f_e = 0.8/2 I (1 - q).
    let q = 0.12 * (142f64).to_radians().cos();
    let o = strip_sum(&frames[0].frame.data, p.geometry.o_target);
    let e = strip_sum(&frames[0].frame.data, p.geometry.e_target);
    assert!((o - 20000.0 * (1.0 + q)).abs() < 1e-2, "{o}");
    assert!((e - 16000.0 * (1.0 - q)).abs() < 1e-2, "{e}");
}

/// Flux-weighted centroid in a (2h+1)^2 window around (x, y).
fn centroid(img: &Array2<f32>, x: f64, y: f64, h: i64) -> (f64, f64) {
    let (mut t, mut mx, mut my) = (0.0, 0.0, 0.0);
    for j in (y.round() as i64 - h)..=(y.round() as i64 + h) {
        for i in (x.round() as i64 - h)..=(x.round() as i64 + h) {
            let v = img[[j as usize, i as usize]] as f64;
            t += v;
            mx += v * i as f64;
            my += v * j as f64;
        }
    }
    (mx / t, my / t)
}

#[test]
fn companion_lands_where_the_rotation_convention_says() {
    // No PSF: each star is a cloud-in-cell point, so window centroids are exact.
    let sc = scene("", "", "0.0, 45.0, 90.0, 200.0");
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let (frames, _) = sim.run_in_memory();
    for f in &frames {
        let posang = f.truth.posang_deg;
        let a = f.truth.sources[0].o_xy;
        // Independent statement of the convention: at POSANG theta the detector +y axis
        // points to PA theta and -x to PA theta + 90.
        let psi = (130.0 - posang).to_radians();
        let (dx, dy) = (-4.0 / 0.288 * psi.sin(), 4.0 / 0.288 * psi.cos());
        let (bx, by) = (a[0] + dx, a[1] + dy);
        let (cx, cy) = centroid(&f.frame.data, bx, by, 3);
        assert!(
            (cx - bx).abs() < 1e-4 && (cy - by).abs() < 1e-4,
            "posang {posang}: B at ({cx},{cy}) expected ({bx},{by})"
        );
        // The extraordinary image 167 px above.
        let (ex, ey) = centroid(&f.frame.data, bx, by + 167.0, 3);
        assert!((ex - bx).abs() < 1e-4 && (ey - by - 167.0).abs() < 1e-4);
        // A moves with the header dither offset.
        let (ax, ay) = centroid(&f.frame.data, a[0], a[1], 3);
        let off = f.truth.header_offset_px;
        assert!(
            (ax - (512.0 + off[0])).abs() < 1e-4 && (ay - 428.0).abs() < 1e-4,
            "A at ({ax},{ay})"
        );
        let (mx, my) = companion_offset_px(4.0, 130.0, posang, 0.288);
        assert!((mx - dx).abs() < 1e-9 && (my - dy).abs() < 1e-9);
    }
}

#[test]
fn no_effects_is_the_exact_noiseless_expectation() {
    let sc = scene("", "", "0.0, 45.0");
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let (frames, truth) = sim.run_in_memory();
    assert!(sim.calls().is_empty(), "effects called: {:?}", sim.calls());
    for f in &frames {
        // Everything is in the 4 pixels of each of 4 point images; the rest is exactly 0.
        let nonzero = f.frame.data.iter().filter(|&&v| v != 0.0).count();
        assert!(nonzero <= 16, "{nonzero}");
        let total = sum(&f.frame.data);
        assert!((total - 70000.0).abs() < 0.05, "{total}");
        for s in &f.truth.sources {
            let (ox, oy) = centroid(&f.frame.data, s.o_xy[0], s.o_xy[1], 2);
            assert!((ox - s.o_xy[0]).abs() < 1e-4 && (oy - s.o_xy[1]).abs() < 1e-4);
        }
    }
    assert_eq!(truth.detector, Default::default());
}

const ALL_SECTIONS: &str = r#"
[psf]
fwhm_arcsec = 0.7
[sky]
level_adu = 900.0
[bad_pixels]
hot_fraction = 0.001
[flat_field]
pixel_rms = 0.02
[throughput]
t_e = 0.9
[instrumental_polarization]
p = 0.01
[interstellar_polarization]
p = 0.02
[transparency]
min = 0.5
[pointing_error]
rms_px = 2.0
[cosmic_rays]
rate_per_frame = 100.0
[nonlinearity]
coeff_per_adu = 1e-6
[saturation]
level_adu = 100.0
[dome_flats]
frames_on = 2
frames_off = 1
[analyzer_angle]
zero_point_deg = 7.0
parity = -1
[telescope_polarization]
p_tel = 0.02
psi_tel_deg = 10.0
"#;

#[test]
fn unlisted_effects_leave_frames_bit_identical_and_are_never_called() {
    // Every section of ALL_SECTIONS configures an effect that is not listed here.
    let listed = "\"photon_noise\", \"read_noise\", \"strips\"";
    let plain = Simulator::new(scene(listed, "", "0.0, 45.0"), Profile::sofi()).unwrap();
    let configured = Simulator::new(scene(listed, ALL_SECTIONS, "0.0, 45.0"), Profile::sofi()).unwrap();
    let (a, _) = plain.run_in_memory();
    let (b, tb) = configured.run_in_memory();
    for (fa, fb) in a.iter().zip(&b) {
        assert!(fa
            .frame
            .data
            .iter()
            .zip(fb.frame.data.iter())
            .all(|(x, y)| x.to_bits() == y.to_bits()));
    }
    let calls = configured.calls();
    let names: Vec<&str> = calls.keys().copied().collect();
    assert_eq!(names, vec!["photon_noise", "read_noise", "strips"]);
    assert_eq!(tb.ignored_sections.len(), 15, "{:?}", tb.ignored_sections);
    assert_eq!(configured.n_dome_flat_frames(), 0);
    assert!(tb.dome_flats.is_empty());
}

#[test]
fn each_effect_is_called_only_when_listed_and_changes_the_frames() {
    let base_list = ["psf", "sky", "photon_noise"];
    let quoted = |l: &[&str]| l.iter().map(|e| format!("\"{e}\"")).collect::<Vec<_>>().join(",");
    let base = Simulator::new(scene(&quoted(&base_list), ALL_SECTIONS, "0.0, 45.0"), Profile::sofi()).unwrap();
    let (base_frames, _) = base.run_in_memory();
    for k in EffectKind::ALL {
        if base_list.contains(&k.name()) {
            continue;
        }
        let mut list = base_list.to_vec();
        list.push(k.name());
        let sim = Simulator::new(scene(&quoted(&list), ALL_SECTIONS, "0.0, 45.0"), Profile::sofi()).unwrap();
        let (frames, _) = sim.run_in_memory();
        if k == EffectKind::DomeFlats {
            // Dome flats add frames and leave the science frames bit-identical.
            assert!(sim.calls().is_empty() || !sim.calls().contains_key("dome_flats"));
            assert!(frames.iter().zip(&base_frames).all(|(f, g)| f
                .frame
                .data
                .iter()
                .zip(g.frame.data.iter())
                .all(|(x, y)| x.to_bits() == y.to_bits())));
            let flats = sim.dome_flat_frames();
            assert_eq!(flats.len(), 2 * 3);
            let calls = sim.calls();
            assert_eq!(calls.get("dome_flats"), Some(&6), "{calls:?}");
            assert_eq!(calls.len(), 4, "{calls:?}");
            continue;
        }
        let calls = sim.calls();
        assert!(calls.contains_key(k.name()), "{} listed but not called", k.name());
        assert_eq!(calls.len(), 4, "{}: {:?}", k.name(), calls);
        let changed = frames
            .iter()
            .zip(&base_frames)
            .map(|(f, g)| {
                f.frame
                    .data
                    .iter()
                    .zip(g.frame.data.iter())
                    .filter(|(x, y)| x != y)
                    .count()
            })
            .sum::<usize>();
        assert!(changed > 0, "{} changed nothing", k.name());
        if k == EffectKind::CosmicRays {
            // Independent streams: only the pixels hit by cosmic rays differ.
            let hit: usize = frames.iter().map(|f| f.truth.cosmic_ray_pixels).sum();
            assert!(changed <= hit, "cosmic rays changed {changed} pixels but hit {hit}");
        }
    }
}

#[test]
fn seeded_deterministic_and_thread_count_independent() {
    let all = EffectKind::ALL
        .iter()
        .map(|e| format!("\"{}\"", e.name()))
        .collect::<Vec<_>>()
        .join(",");
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let sim = Simulator::new(scene(&all, "", "0.0, 45.0"), Profile::sofi()).unwrap();
            sim.run_in_memory().0
        })
    };
    let a = run(1);
    let b = run(2);
    for (x, y) in a.iter().zip(&b) {
        assert!(x
            .frame
            .data
            .iter()
            .zip(y.frame.data.iter())
            .all(|(p, q)| p.to_bits() == q.to_bits()));
    }
    // A different seed gives a different realisation.
    let mut sc = scene(&all, "", "0.0, 45.0");
    sc.seed = 12;
    let c = Simulator::new(sc, Profile::sofi()).unwrap().run_in_memory().0;
    assert!(a[0].frame.data.iter().zip(c[0].frame.data.iter()).any(|(p, q)| p != q));
}

#[test]
fn ism_adds_to_the_truth_in_the_sky_frame() {
    let sc = scene(
        "\"interstellar_polarization\"",
        "[interstellar_polarization]\np = 0.02\nangle_deg = 10.0\n",
        "0.0, 45.0",
    );
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let (_, truth) = sim.run_in_memory();
    let a = &truth.targets[0].components[0];
    let expect = Polarization::from_p_gamma(0.08, 35.0).add(Polarization::from_p_gamma(0.02, 10.0));
    assert!((a.q - expect.q).abs() < 1e-15 && (a.u - expect.u).abs() < 1e-15);
}

#[test]
fn dome_flats_follow_the_contract_and_see_the_science_pixel_response() {
    use sofipol_calib::flat::{dome_flat_info, LAMP_KEYWORD};
    let sc = scene(
        "\"strips\", \"flat_field\", \"dome_flats\", \"throughput\"",
        "[flat_field]\npixel_rms = 0.01\nvignetting = 0.0\n[throughput]\nt_e = 0.9\n[dome_flats]\nframes_on = 2\nframes_off = 1\nlamp_p = 0.04\n",
        "0.0, 45.0",
    );
    let p = Profile::sofi();
    let sim = Simulator::new(sc, p.clone()).unwrap();
    let flats = sim.dome_flat_frames();
    assert_eq!(flats.len(), 6);
    let g = &p.geometry;
    for f in &flats {
        let h = &f.frame.header;
        assert_eq!(h.get_str("ESO DPR CATG").unwrap(), "CALIB");
        assert_eq!(h.get_str("ESO DPR TYPE").unwrap(), "FLAT");
        assert_eq!(h.get_str("ESO DPR TECH").unwrap(), "POLARIMETRY");
        assert_eq!(h.get_str("ESO TPL ID").unwrap(), "SOFI_img_cal_DomeFlat");
        assert!(h.contains(LAMP_KEYWORD));
        let info = dome_flat_info(h, &p).unwrap().unwrap();
        assert_eq!(info.lamp_on, f.truth.lamp_on);
        assert_eq!(info.posang_deg, f.truth.posang_deg);
        // Noiseless: pixel = level x response, the same response as the science frames'.
        let row_o = (g.o_target[0] + g.o_target[1]) / 2;
        let row_e = (g.e_target[0] + g.e_target[1]) / 2;
        let (o, e) = (f.frame.data[[row_o, 300]] as f64, f.frame.data[[row_e, 300]] as f64);
        assert!(o != e);
        if f.truth.lamp_on {
            // o and e strips differ by the lamp's polarization and the throughput.
            assert!((f.truth.level_o_adu / f.truth.level_e_adu - 1.0).abs() > 0.05);
        }
        assert_eq!(f.frame.data[[3, 300]], 0.0, "off-strip row blocked by the focal mask");
    }
    // The science frames see the same pixel response: ratio of two flats' pixels equals the
    // ratio of the science sky... here with no sky, compare the flat of two orientations.
    let on0 = &flats[0].frame.data;
    let on1 = &flats[3].frame.data;
    let row = (g.o_target[0] + g.o_target[1]) / 2;
    let r0: Vec<f64> = (100..110)
        .map(|x| on0[[row, x]] as f64 / on0[[row, 100]] as f64)
        .collect();
    let r1: Vec<f64> = (100..110)
        .map(|x| on1[[row, x]] as f64 / on1[[row, 100]] as f64)
        .collect();
    for (a, b) in r0.iter().zip(&r1) {
        assert!((a - b).abs() < 1e-6);
    }
    assert!(r0.iter().any(|r| (r - 1.0).abs() > 1e-3), "pixel response not applied");
}

#[test]
fn psf_fwhm_and_beta_vary_independently_frame_to_frame() {
    let sc = scene(
        "\"psf\"",
        "[psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.8\nseeing_rms_frac = 0.0\nfwhm_spread_frac = 0.2\nbeta_range = [2.5, 4.0]\n",
        "0.0, 45.0, 90.0, 135.0",
    );
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let (frames, _) = sim.run_in_memory();
    let f0 = 0.8 / 0.288;
    let fw: Vec<f64> = frames.iter().map(|f| f.truth.fwhm_px / f0).collect();
    let be: Vec<f64> = frames.iter().map(|f| f.truth.beta).collect();
    assert!(fw.iter().all(|&r| (0.8..=1.2).contains(&r)), "{fw:?}");
    assert!(be.iter().all(|&b| (2.5..=4.0).contains(&b)), "{be:?}");
    let spread = |v: &[f64]| v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min);
    assert!(spread(&fw) > 0.2 && spread(&be) > 0.7, "{fw:?} {be:?}");
    // Independent: correlation of the two draws is small over the frames.
    let n = fw.len() as f64;
    let (mf, mb) = (fw.iter().sum::<f64>() / n, be.iter().sum::<f64>() / n);
    let cov: f64 = fw.iter().zip(&be).map(|(a, b)| (a - mf) * (b - mb)).sum::<f64>() / n;
    let sd = |v: &[f64], m: f64| (v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / n).sqrt();
    let corr = cov / (sd(&fw, mf) * sd(&be, mb));
    assert!(corr.abs() < 0.6, "corr {corr}");
}

#[test]
fn standards_are_single_calib_std_sequences_and_follow_k_inst_zero_point_and_parity() {
    // Noiseless: a standard's beams follow the forward model with the true analyzer angle
    // phi = s POSANG + theta0, the beam ratio k and the instrumental term; nothing else.
    let extra = r#"
[throughput]
t_o = 1.0
t_e = 0.97
[instrumental_polarization]
p = 0.003
angle_deg = 0.0
[analyzer_angle]
zero_point_deg = 3.0
parity = -1
[[standard]]
name = "HD 204827"
flux = 30000.0
p = 0.02
gamma_deg = 58.7
[[standard]]
name = "HD 64299"
flux = 20000.0
"#;
    let effects = "\"throughput\", \"instrumental_polarization\", \"analyzer_angle\"";
    let sim = Simulator::new(scene(effects, extra, "0.0, 45.0, 90.0, 135.0"), Profile::sofi()).unwrap();
    assert_eq!(sim.n_sequences(), 3);
    assert!(!sim.is_standard(0) && sim.is_standard(1) && sim.is_standard(2));
    let (frames, truth) = sim.run_in_memory();
    assert_eq!(truth.targets.len(), 1);
    assert_eq!(truth.standards.len(), 2);
    assert_eq!(truth.standards[0].components.len(), 1);
    assert!((truth.standards[0].components[0].p - 0.02).abs() < 1e-15);
    let k = 0.97;
    let c_k = (1.0 - k) / (1.0 + k);
    let per = sim.frames_per_target();
    for (i, f) in frames.iter().enumerate() {
        let t = i / per;
        let h = &f.frame.header;
        let catg = h.get_str("HIERARCH ESO DPR CATG").unwrap();
        let typ = h.get_str("HIERARCH ESO DPR TYPE").unwrap();
        if t == 0 {
            assert_eq!((catg.as_str(), typ.as_str()), ("SCIENCE", "OBJECT"));
            continue;
        }
        assert_eq!((catg.as_str(), typ.as_str()), ("CALIB", "STD"));
        assert_eq!(f.truth.sources.len(), 1, "a standard is a single star");
        let phi = -f.truth.posang_deg + 3.0;
        assert!((f.truth.analyzer_deg - phi).abs() < 1e-12);
        let st = &truth.standards[t - 1].components[0];
        let ft = normalized_difference(Polarization { q: st.q, u: st.u }, phi);
        let expect = (ft + c_k) / (1.0 + c_k * ft) + 0.003;
        let s0 = &f.truth.sources[0];
        let fm = (s0.flux_o - s0.flux_e) / (s0.flux_o + s0.flux_e);
        assert!((fm - expect).abs() < 1e-12, "{fm} vs {expect}");
        // And the image holds exactly those beam fluxes (no PSF: point images).
        let g = Profile::sofi().geometry;
        let (so, se) = (
            strip_sum(&f.frame.data, g.o_target),
            strip_sum(&f.frame.data, g.e_target),
        );
        assert!(
            (so - s0.flux_o).abs() < 0.05 && (se - s0.flux_e).abs() < 0.05,
            "{so} {se}"
        );
    }
    let calls = sim.calls();
    assert!(calls.contains_key("analyzer_angle") && calls.contains_key("throughput"));
    assert!(!calls.contains_key("interstellar_polarization"));
}

/// Telescope polarization is simulated only when listed: unlisted (section or not) or
/// listed with p_tel = 0, the frames are bit-identical and the headers equal; listed with
/// p_tel > 0 only the pixels change, the headers (pointing included) stay the same.
#[test]
fn telescope_polarization_changes_only_the_pixels_and_only_when_asked() {
    let base = "\"psf\", \"sky\", \"photon_noise\"";
    let with = format!("{base}, \"telescope_polarization\"");
    let tel = |p: f64| format!("[psf]\nfwhm_arcsec = 0.9\n[telescope_polarization]\np_tel = {p}\npsi_tel_deg = 30.0\n");
    let run = |effects: &str, extra: &str| {
        let sim = Simulator::new(scene(effects, extra, "0.0, 45.0"), Profile::sofi()).unwrap();
        let (frames, truth) = sim.run_in_memory();
        (frames, truth, sim.calls())
    };
    let (plain, tp, calls) = run(base, "[psf]\nfwhm_arcsec = 0.9\n");
    assert!(!calls.contains_key("telescope_polarization") && tp.telescope_polarization.is_none());
    let (ignored, _, calls) = run(base, &tel(0.01));
    assert!(!calls.contains_key("telescope_polarization"));
    let (zero, tz, calls) = run(&with, &tel(0.0));
    assert_eq!(
        calls.get("telescope_polarization"),
        Some(&(2 * 4)),
        "per frame: sources and sky"
    );
    assert!(tz.telescope_polarization.is_some());
    let (on, _, _) = run(&with, &tel(0.01));
    let same = |a: &[sofipol_pipeline::sim::SimFrame], b: &[sofipol_pipeline::sim::SimFrame]| {
        a.iter().zip(b).all(|(x, y)| {
            x.frame
                .data
                .iter()
                .zip(y.frame.data.iter())
                .all(|(p, q)| p.to_bits() == q.to_bits())
        })
    };
    let headers = |a: &[sofipol_pipeline::sim::SimFrame], b: &[sofipol_pipeline::sim::SimFrame]| {
        a.iter()
            .zip(b)
            .all(|(x, y)| x.frame.header.cards == y.frame.header.cards)
    };
    assert!(same(&plain, &ignored) && same(&plain, &zero));
    assert!(headers(&plain, &ignored) && headers(&plain, &zero) && headers(&plain, &on));
    assert!(!same(&plain, &on), "p_tel = 1 % changed nothing");
    assert!(plain.iter().all(|f| f.truth.telescope.is_none()));
    assert!(on.iter().all(|f| f.truth.telescope.is_some()));
}
