//! The calibration stages (bad pixels, sky, cosmic rays) on simulated SOFI sequences,
//! judged against the simulator's truth.
use ndarray::Array2;
use sofipol_calib::badpix::{apply_mask, detect_bad_pixels, BadPixelOptions};
use sofipol_calib::frame::mask;
use sofipol_calib::sky::{sky_subtract, sky_subtract_with_report, CosmicOptions, SkyOptions, SkyScaling};
use sofipol_calib::{Frame, Profile};
use sofipol_pipeline::sim::{Scene, SimFrame, Simulator};

/// One target, `orientations` x 5 dithers, exact 87 px jitter (integer star centres:
/// the most peaked, hardest case for the cosmic-ray sharpness test).
fn scene(effects: &str, orientations: &str, extra: &str, seed: u64) -> Scene {
    let text = format!(
        r#"
name = "calib"
seed = {seed}
effects = [{effects}]
[observation]
orientations_deg = [{orientations}]
dithers = 5
jitter_step_px = 87.0
[[binary]]
name = "Calib Tau"
separation_arcsec = 4.0
pa_deg = 130.0
flux_a = 60000.0
flux_b = 20000.0
p_a = 0.05
gamma_a_deg = 30.0
p_b = 0.03
gamma_b_deg = 100.0
[[binary.field_star]]
separation_arcsec = 9.3
pa_deg = 250.0
flux = 150000.0
[[binary.field_star]]
separation_arcsec = 7.1
pa_deg = 65.0
flux = 90000.0
{extra}
"#
    );
    Scene::from_toml(&text, "calib test scene").unwrap()
}

fn run(sc: Scene) -> (Simulator, Vec<SimFrame>) {
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let (frames, _) = sim.run_in_memory();
    (sim, frames)
}

/// Rows of the four strips without sources (sky2 and sky1 strips).
fn empty_rows(p: &Profile) -> Vec<usize> {
    let g = &p.geometry;
    (g.o_sky2[0]..g.e_sky2[1]).chain(g.o_sky1[0]..g.e_sky1[1]).collect()
}

/// Mean residual / rms, and measured variance / mean predicted variance, over the
/// source-free strips (unmasked pixels).
fn residual_stats(f: &Frame, p: &Profile) -> (f64, f64) {
    let var = f.variance.as_ref().unwrap();
    let (mut n, mut s, mut s2, mut pv) = (0f64, 0f64, 0f64, 0f64);
    for y in empty_rows(p) {
        for x in 0..f.shape().1 {
            if f.mask[[y, x]] != 0 {
                continue;
            }
            let d = f.data[[y, x]] as f64;
            n += 1.0;
            s += d;
            s2 += d * d;
            pv += var[[y, x]] as f64;
        }
    }
    let mean = s / n;
    let measured = s2 / n - mean * mean;
    (mean / measured.sqrt(), measured / (pv / n))
}

/// Sum in a circular aperture of radius `r` (pixel centres inside), with its variance.
fn aperture(img: &Array2<f32>, var: &Array2<f32>, xy: [f64; 2], r: f64) -> (f64, f64) {
    let (mut s, mut v) = (0.0, 0.0);
    for y in (xy[1] - r).floor() as usize..=(xy[1] + r).ceil() as usize {
        for x in (xy[0] - r).floor() as usize..=(xy[0] + r).ceil() as usize {
            if (x as f64 - xy[0]).powi(2) + (y as f64 - xy[1]).powi(2) <= r * r {
                s += img[[y, x]] as f64;
                v += var[[y, x]] as f64;
            }
        }
    }
    (s, v)
}

#[test]
fn sky_subtraction_is_unbiased_its_variance_map_is_right_and_fluxes_survive() {
    let p = Profile::sofi();
    let sc = scene(
        "\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\"",
        "0.0, 45.0",
        "[psf]\nkind = \"gaussian\"\nfwhm_arcsec = 0.8\n[sky]\nlevel_adu = 1500.0\ngradient_x = 0.05\ngradient_y = -0.03\nframe_change_frac = 0.03\n",
        5,
    );
    let (_, sim) = run(sc);
    for scaling in [SkyScaling::Multiplicative, SkyScaling::Additive] {
        for orient in sim.chunks(5) {
            let raw: Vec<Frame> = orient.iter().map(|s| s.frame.clone()).collect();
            let opts = SkyOptions {
                scaling,
                cosmic_rays: None,
                ..SkyOptions::default()
            };
            let (out, rep) = sky_subtract_with_report(&raw, &p, &opts).unwrap();
            assert_eq!(rep.median_of, 4);
            assert!((rep.median_variance_factor - 1.192798).abs() < 1e-6);
            for ((f, s), level) in out.iter().zip(orient).zip(&rep.levels_adu) {
                // The level is the median of the strip rows: close to the centre level.
                assert!(
                    (level / s.truth.sky_level_adu - 1.0).abs() < 0.01,
                    "{level} vs {}",
                    s.truth.sky_level_adu
                );
                let (bias, ratio) = residual_stats(f, &p);
                eprintln!(
                    "{scaling:?} {}: mean residual {bias:+.4} sigma, variance measured/predicted {ratio:.4}",
                    s.file_name
                );
                assert!(
                    bias.abs() < 0.05,
                    "{scaling:?} {}: mean residual {bias} sigma",
                    s.file_name
                );
                assert!(
                    (0.9..1.1).contains(&ratio),
                    "{scaling:?} {}: var measured/predicted {ratio}",
                    s.file_name
                );
                // Star fluxes: every source image (o and e) inside the target strips.
                let var = f.variance.as_ref().unwrap();
                for src in &s.truth.sources {
                    for (xy, flux) in [(src.o_xy, src.flux_o), (src.e_xy, src.flux_e)] {
                        let (sum, v) = aperture(&f.data, var, xy, 7.0);
                        let z = (sum - flux) / v.sqrt();
                        assert!(
                            z.abs() < 4.5,
                            "{} {} at {xy:?}: {sum:.0} vs truth {flux:.0} ({z:.2} sigma)",
                            s.file_name,
                            src.name
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn sky_stage_never_mutates_inputs_and_records_history() {
    let p = Profile::sofi();
    let sc = scene("\"sky\", \"strips\", \"photon_noise\"", "45.0", "", 2);
    let (_, sim) = run(sc);
    let raw: Vec<Frame> = sim.iter().map(|s| s.frame.clone()).collect();
    let before: Vec<(Array2<f32>, usize)> = raw.iter().map(|f| (f.data.clone(), f.history.len())).collect();
    let out = sky_subtract(&raw, &p, &SkyOptions::recommended()).unwrap();
    for ((f, (d, h)), o) in raw.iter().zip(&before).zip(&out) {
        assert_eq!(&f.data, d);
        assert_eq!(f.history.len(), *h);
        assert!(f.variance.is_none());
        let stages: Vec<&str> = o.history.iter().map(|r| r.stage.as_str()).collect();
        assert_eq!(stages, ["simulate", "sky", "cosmic"]);
        assert_eq!(o.mask[[3, 100]] & mask::OFF_STRIP, mask::OFF_STRIP);
    }
    let e = sky_subtract(&raw[..1], &p, &SkyOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("fewer than 2 dithers at POSANG 45"), "{e}");
}

#[test]
fn bad_pixels_are_recovered_from_the_dithers() {
    let p = Profile::sofi();
    let sc = scene(
        "\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\", \"bad_pixels\"",
        "0.0, 45.0",
        "",
        21,
    );
    let (simulator, sim) = run(sc);
    let truth = simulator.bad_pixel_mask().unwrap();
    let frames: Vec<&Frame> = sim.iter().map(|s| &s.frame).collect();
    let (found, rep) = detect_bad_pixels(&frames, &p, &BadPixelOptions::default()).unwrap();
    let (mut tp, mut fn_, mut fp, mut n) = (0usize, 0usize, 0usize, 0usize);
    for (((y, _), &t), &f) in truth.indexed_iter().zip(found.iter()) {
        if !p.geometry.row_in_strip(y) {
            assert_eq!(f, 0, "no detection outside the strips");
            continue;
        }
        n += 1;
        match (t != 0, f != 0) {
            (true, true) => tp += 1,
            (true, false) => fn_ += 1,
            (false, true) => fp += 1,
            _ => {}
        }
    }
    let recall = tp as f64 / (tp + fn_) as f64;
    let fp_rate = fp as f64 / n as f64;
    eprintln!("bad pixels in strips: {tp} found, {fn_} missed, {fp} false ({recall:.4} recall, {fp_rate:.2e} false rate); {rep:?}");
    assert!(
        tp + fn_ > 500,
        "the scene should have many bad pixels, got {}",
        tp + fn_
    );
    assert!(recall >= 0.99, "recall {recall}");
    assert!(fp_rate < 1e-4, "false-positive rate {fp_rate}");
    assert_eq!(rep.total, tp + fp);
    // Applying the mask marks BAD and keeps the data.
    let masked = apply_mask(frames[0], &found).unwrap();
    assert_eq!(masked.data, frames[0].data);
    assert_eq!(masked.mask.iter().filter(|&&b| b & mask::BAD != 0).count(), rep.total);
}

/// Flag cosmic rays in one orientation of a scene with the given PSF; compare with the
/// cosmic-ray pixels known from a twin simulation without them (independent random
/// streams: only the hit pixels differ).
fn cosmic_case(psf: &str) -> (usize, usize, usize, usize) {
    let p = Profile::sofi();
    let base = "\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\"";
    let extra = format!("{psf}\n[cosmic_rays]\nrate_per_frame = 60.0\n");
    let (_, with) = run(scene(&format!("{base}, \"cosmic_rays\""), "0.0", &extra, 9));
    let (_, without) = run(scene(base, "0.0", &extra, 9));
    let raw: Vec<Frame> = with.iter().map(|s| s.frame.clone()).collect();
    let opts = SkyOptions {
        scaling: SkyScaling::Multiplicative,
        cosmic_rays: Some(CosmicOptions::default()),
        ..SkyOptions::default()
    };
    let (out, rep) = sky_subtract_with_report(&raw, &p, &opts).unwrap();
    let (mut hit_strong, mut found_strong, mut false_flags, mut star_flags) = (0, 0, 0, 0);
    for (k, f) in out.iter().enumerate() {
        let cr = Array2::from_shape_fn(f.data.raw_dim(), |ix| {
            with[k].frame.data[ix] - without[k].frame.data[ix]
        });
        let var = f.variance.as_ref().unwrap();
        let near_star = |y: usize, x: usize| {
            with[k].truth.sources.iter().any(|s| {
                [s.o_xy, s.e_xy]
                    .iter()
                    .any(|c| (c[0] - x as f64).powi(2) + (c[1] - y as f64).powi(2) <= 16.0)
            })
        };
        for ((y, x), &b) in f.mask.indexed_iter() {
            let flagged = b & mask::COSMIC != 0;
            let is_cr = cr[[y, x]] > 0.0;
            if flagged && near_star(y, x) && !is_cr {
                star_flags += 1;
            }
            if flagged && !is_cr {
                false_flags += 1;
            }
            if is_cr && p.geometry.row_in_strip(y) && !near_star(y, x) && cr[[y, x]] > 10.0 * var[[y, x]].sqrt() {
                hit_strong += 1;
                found_strong += flagged as usize;
            }
        }
    }
    assert_eq!(rep.cosmic.len(), 5);
    // Margin: the largest sharpness ratio any star pixel reaches (value - 5 sigma)/mean4.
    let mut worst = 0f64;
    for (k, f) in out.iter().enumerate() {
        let var = f.variance.as_ref().unwrap();
        for s in &with[k].truth.sources {
            for c in [s.o_xy, s.e_xy] {
                let (y, x) = (c[1].round() as usize, c[0].round() as usize);
                let v = f.data[[y, x]] as f64;
                let m4 = [(y - 1, x), (y + 1, x), (y, x - 1), (y, x + 1)]
                    .iter()
                    .map(|&ix| f.data[ix] as f64)
                    .sum::<f64>()
                    / 4.0;
                worst = worst.max((v - 5.0 * (var[[y, x]] as f64).sqrt()) / m4);
            }
        }
    }
    eprintln!(
        "{psf:?}: largest star-peak sharpness (value - 5 sigma)/mean4 = {worst:.2} (threshold {})",
        CosmicOptions::default().sharpness_ratio
    );
    (hit_strong, found_strong, false_flags, star_flags)
}

#[test]
fn cosmic_rays_are_flagged_but_not_star_cores_at_fwhm_1_7_px() {
    // Gaussian of FWHM 1.7 px (0.4896 arcsec at 0.288 arcsec/px), no seeing jitter.
    let (hit, found, false_flags, star) =
        cosmic_case("[psf]\nkind = \"gaussian\"\nfwhm_arcsec = 0.4896\nseeing_rms_frac = 0.0\n");
    eprintln!("FWHM 1.7 px Gaussian: {found}/{hit} cosmic-ray pixels > 10 sigma flagged; {false_flags} false flags, {star} on stars");
    assert_eq!(star, 0, "star cores flagged as cosmic rays");
    assert!(found as f64 >= 0.97 * hit as f64, "{found} of {hit}");
    assert!(false_flags <= 25, "{false_flags} false flags in 5 frames");
}

#[test]
fn cosmic_rays_are_flagged_but_not_star_cores_moffat_2_8_px() {
    let (hit, found, false_flags, star) =
        cosmic_case("[psf]\nkind = \"moffat\"\nbeta = 2.5\nfwhm_arcsec = 0.8064\nseeing_rms_frac = 0.0\n");
    eprintln!("FWHM 2.8 px Moffat: {found}/{hit} cosmic-ray pixels > 10 sigma flagged; {false_flags} false flags, {star} on stars");
    assert_eq!(star, 0, "star cores flagged as cosmic rays");
    assert!(found as f64 >= 0.97 * hit as f64, "{found} of {hit}");
    assert!(false_flags <= 25, "{false_flags} false flags in 5 frames");
}
