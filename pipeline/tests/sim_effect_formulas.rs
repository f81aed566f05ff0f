//! The simulator's pixel response, non-linearity and instrumental polarization against the
//! formulas docs/simulator.md states for them (each effect alone, noiseless).
use ndarray::{s, Array2};
use sofipol_calib::Profile;
use sofipol_pipeline::sim::{Scene, Simulator};
use sofipol_pipeline::stokes::model::{normalized_difference, Polarization};

fn scene(effects: &str, orientations: &str, extra: &str, p_a: f64, flux_a: f64) -> Scene {
    let text = format!(
        r#"
name = "formulas"
seed = 17
effects = [{effects}]
[observation]
orientations_deg = [{orientations}]
dithers = 2
[[binary]]
name = "single"
separation_arcsec = 3.0
pa_deg = 0.0
flux_a = {flux_a}
flux_b = 0.0
p_a = {p_a}
gamma_a_deg = 71.0
p_b = 0.0
gamma_b_deg = 0.0
{extra}
"#
    );
    Scene::from_toml(&text, "formula scene").unwrap()
}

const FLAT_SKY: &str = "[sky]\nlevel_adu = 1000.0\ngradient_x = 0.0\ngradient_y = 0.0\nframe_change_frac = 0.0\n";

fn frames(sc: Scene) -> Vec<Array2<f32>> {
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    sim.run_in_memory().0.into_iter().map(|f| f.frame.data).collect()
}

/// flat_field: response (1 - v r^2/r_corner^2)(1 + rms N(0,1)), fixed on the detector.
#[test]
fn pixel_response_follows_vignetting_times_gaussian_pixel_noise_and_is_fixed() {
    let (rms, v) = (0.01, 0.05);
    let extra = format!("{FLAT_SKY}[flat_field]\npixel_rms = {rms}\nvignetting = {v}\n");
    let imgs = frames(scene("\"sky\", \"flat_field\"", "0.0, 45.0", &extra, 0.0, 0.0));
    // The same response in every frame, whatever the orientation or dither.
    for f in &imgs[1..] {
        assert_eq!(f, &imgs[0]);
    }
    let resp = imgs[0].mapv(|x| x as f64 / 1000.0);
    let (ny, nx) = resp.dim();
    let (cy, cx) = ((ny as f64 - 1.0) / 2.0, (nx as f64 - 1.0) / 2.0);
    let rc2 = cx * cx + cy * cy;
    // Divide out the stated vignetting: what is left is 1 + rms N(0,1), pixel by pixel.
    let mut resid = Vec::with_capacity(ny * nx);
    for ((y, x), &r) in resp.indexed_iter() {
        let vig = 1.0 - v * ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)) / rc2;
        resid.push(r / vig - 1.0);
    }
    let n = resid.len() as f64;
    let mean = resid.iter().sum::<f64>() / n;
    let sd = (resid.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    // 1M pixels: the mean is known to rms/1000, the rms to 0.07 %.
    assert!(mean.abs() < 5.0 * rms / n.sqrt(), "mean {mean}");
    assert!((sd / rms - 1.0).abs() < 0.005, "rms {sd}");
    // Gaussian: 4.55 % of the pixels beyond 2 sigma (binomial error 0.02 %).
    let beyond = resid.iter().filter(|d| d.abs() > 2.0 * rms).count() as f64 / n;
    assert!((beyond - 0.0455).abs() < 0.001, "{beyond}");
    // Neighbouring pixels are independent.
    let lag1: f64 = (0..ny)
        .flat_map(|y| (0..nx - 1).map(move |x| (y, x)))
        .map(|(y, x)| resid[y * nx + x] * resid[y * nx + x + 1])
        .sum::<f64>()
        / (n * sd * sd);
    assert!(lag1.abs() < 0.005, "lag-1 correlation {lag1}");
    // The corner is 5 % darker than the centre, on average.
    let corner = resp.slice(s![..16, ..16]).mean().unwrap();
    let centre = resp.slice(s![504..520, 504..520]).mean().unwrap();
    assert!(
        (corner / centre - (1.0 - v * 0.97)).abs() < 0.003,
        "{corner} / {centre}"
    );
}

/// nonlinearity: measured = true (1 - c true) for positive values.
#[test]
fn nonlinearity_is_the_stated_quadratic() {
    let c = 2e-6;
    let extra = format!("{FLAT_SKY}[nonlinearity]\ncoeff_per_adu = {c}\n");
    let imgs = frames(scene("\"sky\", \"nonlinearity\"", "0.0", &extra, 0.0, 0.0));
    let want = 1000.0 * (1.0 - c * 1000.0);
    for f in &imgs {
        for &x in f.iter() {
            assert!((x as f64 - want).abs() < 1e-3, "{x} vs {want}");
        }
    }
    // The profile's coefficient when the scene gives none: SOFI ~1 % at 13.5 kADU.
    let extra = "[sky]\nlevel_adu = 13500.0\ngradient_x = 0.0\ngradient_y = 0.0\nframe_change_frac = 0.0\n";
    let imgs = frames(scene("\"sky\", \"nonlinearity\"", "0.0", extra, 0.0, 0.0));
    let c_prof = Profile::sofi().detector.nonlin_coeff_per_adu;
    let got = imgs[0][[500, 500]] as f64;
    assert!((got - 13500.0 * (1.0 - c_prof * 13500.0)).abs() < 0.01, "{got}");
    let loss = 1.0 - got / 13500.0;
    assert!(
        (0.005..0.02).contains(&loss),
        "profile non-linearity at 13.5 kADU: {loss}"
    );
}

/// instrumental_polarization: p cos 2(angle) adds to F = (o - e)/(o + e) at every rotator
/// angle (fixed in the instrument frame), o + e unchanged.
#[test]
fn instrumental_polarization_adds_a_constant_to_f_at_every_angle() {
    let p = Profile::sofi();
    let (p_inst, ang) = (0.004, 20.0);
    let c = p_inst * (2.0 * f64::to_radians(ang)).cos();
    for p_star in [0.0, 0.12] {
        let extra = format!(
            "[instrumental_polarization]\np = {p_inst}\nangle_deg = {ang}\n[psf]\nkind = \"gaussian\"\nfwhm_arcsec = 1.0\n"
        );
        let sc = scene(
            "\"psf\", \"instrumental_polarization\"",
            "0.0, 45.0, 90.0, 135.0, 161.0",
            &extra,
            p_star,
            40000.0,
        );
        let sim = Simulator::new(sc, p.clone()).unwrap();
        let (frames, _) = sim.run_in_memory();
        let pol = Polarization::from_p_gamma(p_star, 71.0);
        for f in &frames {
            let o: f64 = f
                .frame
                .data
                .slice(s![p.geometry.o_target[0]..p.geometry.o_target[1], ..])
                .iter()
                .map(|&v| v as f64)
                .sum();
            let e: f64 = f
                .frame
                .data
                .slice(s![p.geometry.e_target[0]..p.geometry.e_target[1], ..])
                .iter()
                .map(|&v| v as f64)
                .sum();
            let phi = f.truth.analyzer_deg;
            assert!(f.frame.data.iter().all(|v| v.is_finite()));
            assert!(((o + e) / 40000.0 - 1.0).abs() < 2e-6, "o + e = {}", o + e);
            let want = normalized_difference(pol, phi) + c;
            assert!(
                ((o - e) / (o + e) - want).abs() < 2e-6,
                "p {p_star}, phi {phi}: F {} vs {want}",
                (o - e) / (o + e)
            );
        }
    }
}

/// psf with `axis_ratio_range`: each frame draws its own axis ratio in the range and a
/// major-axis angle, recorded in the truth; the star's second moments show them. Without
/// the key the PSF is circular and the truth has no ellipse. A Gaussian cannot be asked
/// for it (it would be silently circular).
#[test]
fn psf_ellipticity_is_drawn_per_frame_in_its_range_and_seen_in_the_image() {
    let psf = "[psf]\nkind = \"moffat\"\nfwhm_arcsec = 1.0\nseeing_rms_frac = 0.0\n";
    let extra = format!("{psf}axis_ratio_range = [0.7, 0.9]\n");
    let sim = Simulator::new(scene("\"psf\"", "0.0, 45.0", &extra, 0.0, 1e5), Profile::sofi()).unwrap();
    let (frames, _) = sim.run_in_memory();
    let mut ratios = Vec::new();
    for f in &frames {
        let [ratio, pa] = f.truth.ellipse.expect("ellipse in the truth");
        assert!(
            (0.7..=0.9).contains(&ratio) && (0.0..180.0).contains(&pa),
            "{ratio} {pa}"
        );
        ratios.push(ratio);
        // Second moments of the o image of A around its true position.
        let [x, y] = f.truth.sources[0].o_xy;
        let (xi, yi) = (x.round() as usize, y.round() as usize);
        let (mut t, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0);
        for j in yi - 25..=yi + 25 {
            for i in xi - 25..=xi + 25 {
                let v = f.frame.data[[j, i]] as f64;
                let (dx, dy) = (i as f64 - x, j as f64 - y);
                t += v;
                xx += v * dx * dx;
                yy += v * dy * dy;
                xy += v * dx * dy;
            }
        }
        let (xx, yy, xy) = (xx / t - 1.0 / 12.0, yy / t - 1.0 / 12.0, xy / t);
        let angle = 0.5 * (2.0 * xy).atan2(xx - yy).to_degrees();
        let d = (angle - pa).rem_euclid(180.0);
        assert!(d.min(180.0 - d) < 1.0, "moments angle {angle} vs {pa}");
        let disc = (0.25 * (xx - yy).powi(2) + xy * xy).sqrt();
        let (l1, l2) = (0.5 * (xx + yy) + disc, 0.5 * (xx + yy) - disc);
        assert!(
            (l2 / l1 - ratio * ratio).abs() < 0.03,
            "{} vs {}",
            l2 / l1,
            ratio * ratio
        );
    }
    ratios.dedup();
    assert!(ratios.len() > 1, "one ratio for every frame");
    // Not asked for: circular, no ellipse in the truth.
    let sim = Simulator::new(scene("\"psf\"", "0.0", psf, 0.0, 1e5), Profile::sofi()).unwrap();
    assert!(sim.run_in_memory().0.iter().all(|f| f.truth.ellipse.is_none()));
    let gauss = "[psf]\nkind = \"gaussian\"\naxis_ratio_range = [0.9, 1.0]\n";
    let text = format!("name = \"g\"\neffects = [\"psf\"]\n{gauss}");
    let e = Scene::from_toml(&text, "g").and_then(|s| s.validate().map(|_| s));
    assert!(e.is_err_and(|e| e.to_string().contains("axis_ratio_range")));
}

/// telescope_polarization: in the sky frame every source gains
/// `(q_tel, u_tel) = p_tel (cos 2(eta + psi_tel), sin 2(eta + psi_tel))`, eta the frame's
/// parallactic angle as the reduction reads it from the header (mean of PARANG START and
/// END), before the analyzer: an unpolarized star shows F = q_tel cos 2phi + u_tel sin 2phi.
/// The sky's o and e strips differ by the same F. The star's truth stays its own.
#[test]
fn telescope_polarization_adds_p_tel_at_each_frames_parallactic_angle() {
    let prof = Profile::sofi();
    let kw = &prof.keywords;
    let (p_tel, psi) = (0.006, 25.0);
    // The star transits 0.26 deg from the zenith during its sequence: eta sweeps ~180 deg.
    let pointing = "dec_deg = -29.0\nhour_angle_h = -0.1\n";
    let tel = format!("[telescope_polarization]\np_tel = {p_tel}\npsi_tel_deg = {psi}\n");
    let orients = "0.0, 45.0, 90.0, 135.0";
    let g = &prof.geometry;
    for p_star in [0.0, 0.05] {
        let sc = scene(
            "\"telescope_polarization\"",
            orients,
            &format!("{pointing}{tel}"),
            p_star,
            40000.0,
        );
        let sim = Simulator::new(sc, prof.clone()).unwrap();
        let (frames, truth) = sim.run_in_memory();
        assert_eq!(sim.calls().get("telescope_polarization"), Some(&(frames.len() as u64)));
        let t = truth.telescope_polarization.expect("p_tel, psi_tel in the truth");
        assert_eq!((t.p_tel, t.psi_tel_deg), (p_tel, psi));
        // The star's truth is its own polarization, without the telescope's.
        let a = &truth.targets[0].components[0];
        let own = Polarization::from_p_gamma(p_star, 71.0);
        assert!((a.q - own.q).abs() < 1e-15 && (a.u - own.u).abs() < 1e-15);
        let mut etas = Vec::new();
        for f in &frames {
            let eta = kw.parallactic_angle_deg(&f.frame.header).unwrap().expect("PARANG");
            etas.push(eta);
            let two = 2.0 * f64::to_radians(eta + psi);
            let (q_tel, u_tel) = (p_tel * two.cos(), p_tel * two.sin());
            let rec = f.truth.telescope.expect("telescope (q, u) in the frame truth");
            assert!((rec.q - q_tel).abs() < 1e-12 && (rec.u - u_tel).abs() < 1e-12);
            let o = f
                .frame
                .data
                .slice(s![g.o_target[0]..g.o_target[1], ..])
                .iter()
                .map(|&v| v as f64)
                .sum::<f64>();
            let e = f
                .frame
                .data
                .slice(s![g.e_target[0]..g.e_target[1], ..])
                .iter()
                .map(|&v| v as f64)
                .sum::<f64>();
            let phi = 2.0 * f.truth.analyzer_deg.to_radians();
            let want = (own.q + q_tel) * phi.cos() + (own.u + u_tel) * phi.sin();
            assert!(((o + e) / 40000.0 - 1.0).abs() < 2e-6, "o + e = {}", o + e);
            assert!(
                ((o - e) / (o + e) - want).abs() < 2e-6,
                "p {p_star}, eta {eta}, phi {}: F {} vs {want}",
                f.truth.analyzer_deg,
                (o - e) / (o + e)
            );
        }
        let swing: f64 = etas
            .windows(2)
            .map(|w| (w[1] - w[0] + 540.0).rem_euclid(360.0) - 180.0)
            .sum();
        assert!(swing.abs() > 90.0, "eta covers {swing} deg: {etas:?}");
    }
    // The sky passes the telescope too: o strips 1000 (1 + F_tel), e strips 1000 (1 - F_tel).
    let sc = scene(
        "\"sky\", \"telescope_polarization\"",
        orients,
        &format!("{pointing}{FLAT_SKY}{tel}"),
        0.0,
        0.0,
    );
    let sim = Simulator::new(sc, prof.clone()).unwrap();
    for f in sim.run_in_memory().0 {
        let eta = kw.parallactic_angle_deg(&f.frame.header).unwrap().unwrap();
        let two = 2.0 * f64::to_radians(eta + psi);
        let phi = 2.0 * f.truth.analyzer_deg.to_radians();
        let f_tel = p_tel * (two.cos() * phi.cos() + two.sin() * phi.sin());
        for (name, rows) in g.strips() {
            let v = f.frame.data[[(rows[0] + rows[1]) / 2, 300]] as f64;
            let want = 1000.0
                * if name.starts_with("o_") {
                    1.0 + f_tel
                } else {
                    1.0 - f_tel
                };
            assert!((v - want).abs() < 1e-3, "{name}: {v} vs {want}");
        }
        assert_eq!(f.frame.data[[3, 300]], 1000.0, "outside the strips: unchanged");
    }
}
