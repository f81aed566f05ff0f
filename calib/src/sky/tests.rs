use super::*;
use crate::frame::mask;
use crate::header::Header;
use ndarray::Array2;

fn frame_from(data: Array2<f32>, ndit: i64, posang: f64) -> Frame {
    let p = Profile::sofi();
    let mut h = Header::new("");
    h.set(&p.keywords.ndit, ndit);
    h.set(&p.keywords.posang, posang);
    Frame::new(data, h)
}

/// xorshift + Box-Muller (tests only).
struct Gauss(u64);
impl Gauss {
    fn u(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn n(&mut self) -> f64 {
        (-2.0 * self.u().ln()).sqrt() * (2.0 * std::f64::consts::PI * self.u()).cos()
    }
}

#[test]
fn median_variance_factor_matches_monte_carlo() {
    let mut g = Gauss(99);
    for m in 2..=9usize {
        let trials = 200_000;
        let mut s2 = 0.0;
        for _ in 0..trials {
            let v: Vec<f32> = (0..m).map(|_| g.n() as f32).collect();
            let med = stack::reference_median(&v) as f64;
            s2 += med * med;
        }
        let c = m as f64 * s2 / trials as f64;
        let want = median_variance_factor(m);
        assert!((c / want - 1.0).abs() < 0.015, "m {m}: Monte Carlo {c} vs table {want}");
    }
    assert_eq!(median_variance_factor(2), 1.0);
    assert!((median_variance_factor(1000) - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
}

#[test]
fn too_few_dithers_is_an_error_naming_posang_and_count() {
    let f = frame_from(Array2::from_elem((1024, 1024), 1000.0), 6, 45.0);
    let e = sky_subtract(&[f], &Profile::sofi(), &SkyOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("fewer than 2 dithers at POSANG 45") && e.contains("(1 given)"),
        "{e}"
    );
}

#[test]
fn flat_sky_subtracts_to_zero_with_flags_and_history() {
    let p = Profile::sofi();
    let mut frames = Vec::new();
    for (j, level) in [1000.0f32, 1100.0, 1050.0].into_iter().enumerate() {
        let mut d = Array2::from_elem((1024, 1024), level);
        for y in 0..1024 {
            if !p.geometry.row_in_strip(y) {
                d.row_mut(y).fill(0.0);
            }
        }
        d[[400, 100 + 50 * j]] = 40000.0; // a "star" that moves
        d[[600, 700]] = 12000.0 * (j + 1) as f32; // non-linear, saturating in none
        frames.push(frame_from(d, 6, 0.0));
    }
    let inputs = frames.clone();
    let no_cr = SkyOptions {
        cosmic_rays: None,
        ..SkyOptions::default()
    };
    let out = sky_subtract(&frames, &p, &no_cr).unwrap();
    // Inputs untouched.
    for (a, b) in inputs.iter().zip(&frames) {
        assert_eq!(a.data, b.data);
        assert_eq!(a.history, b.history);
    }
    for (j, f) in out.iter().enumerate() {
        assert!((f.data[[500, 500]]).abs() < 1e-3, "{}", f.data[[500, 500]]);
        assert_eq!(f.mask[[400, 100 + 50 * j]] & mask::SATURATED, mask::SATURATED);
        assert!(f.data[[400, 100 + 50 * j]] > 38000.0);
        assert_eq!(f.mask[[600, 700]] & mask::NONLINEAR, mask::NONLINEAR);
        assert_eq!(f.mask[[5, 5]] & mask::OFF_STRIP, mask::OFF_STRIP);
        assert_eq!(f.mask[[500, 5]], 0);
        let h = f.history.last().unwrap();
        assert_eq!(h.stage, "sky");
        assert!(
            h.detail.contains("multiplicative") && h.detail.contains("c(2) = 1.000000"),
            "{}",
            h.detail
        );
        // Variance: Poisson + read + c(2)/2 x (same): 1.5 x (L/32.4 + (11.3/5.4)^2/6).
        let l = [1000.0, 1100.0, 1050.0][j];
        let want = 1.5 * (l / 32.4 + (11.3f64 / 5.4).powi(2) / 6.0);
        let got = f.variance.as_ref().unwrap()[[500, 500]] as f64;
        assert!((got / want - 1.0).abs() < 1e-4, "{got} vs {want}");
    }
}

#[test]
fn additive_scaling_removes_additive_level_changes_exactly() {
    let base = Array2::from_shape_fn((1024, 64), |(y, x)| {
        (y as f32 * 0.01 + x as f32 * 0.5).sin() * 50.0 + 500.0
    });
    let frames: Vec<Frame> = [0.0f32, 30.0, -20.0, 12.0]
        .iter()
        .map(|&c| frame_from(base.mapv(|v| v + c), 1, 0.0))
        .collect();
    let opts = SkyOptions {
        scaling: SkyScaling::Additive,
        cosmic_rays: None,
        ..SkyOptions::default()
    };
    let p = Profile::sofi();
    let out = sky_subtract(&frames, &p, &opts).unwrap();
    for f in &out {
        for y in (11..1013).step_by(7) {
            for x in 0..64 {
                assert!(f.data[[y, x]].abs() < 0.01, "{}", f.data[[y, x]]);
            }
        }
    }
}

#[test]
fn cosmic_flags_single_pixel_and_track_but_not_a_broad_bump() {
    let (ny, nx) = (64, 64);
    let mut d = Array2::<f32>::zeros((ny, nx));
    d[[10, 10]] = 1000.0;
    // Track of 4 along +x: 2000, 1000, 667, 500.
    for i in 0..4 {
        d[[30, 20 + i]] += 2000.0 / (1.0 + i as f32);
    }
    // Gaussian bump, sigma 1.2 px (FWHM 2.8 px), peak 5000.
    for y in 40..60 {
        for x in 40..60 {
            let r2 = ((y as f32 - 50.0).powi(2) + (x as f32 - 50.0).powi(2)) / (2.0 * 1.2 * 1.2);
            d[[y, x]] += 5000.0 * (-r2).exp();
        }
    }
    let var = d.mapv(|v| 50.0 + v.max(0.0) / 32.4);
    let mut f = Frame::new(d, Header::new(""));
    f.variance = Some(var);
    let (out, rep) = flag_cosmic_rays(&f, &CosmicOptions::default()).unwrap();
    assert_eq!(out.mask[[10, 10]], mask::COSMIC);
    for i in 0..4 {
        assert_eq!(out.mask[[30, 20 + i]], mask::COSMIC, "track pixel {i}");
    }
    assert_eq!(
        out.mask
            .slice(ndarray::s![40..60, 40..60])
            .iter()
            .filter(|&&b| b != 0)
            .count(),
        0
    );
    assert_eq!(rep.total, 5);
    assert_eq!(out.data, f.data);
    assert_eq!(out.history.last().unwrap().stage, "cosmic");
    let e = flag_cosmic_rays(
        &Frame::new(Array2::zeros((4, 4)), Header::new("a.fits")),
        &CosmicOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("a.fits") && e.contains("variance"), "{e}");
}

/// The seeds of the cosmic-ray test, pixel by pixel as documented (the slow reference of
/// the chunked candidate scan): value > k sigma and value - ratio x max(mean of the
/// unmasked 4-neighbours, 0) > k sigma, skipping BAD / OFF_STRIP / SATURATED pixels.
fn reference_seeds(d: &Array2<f32>, var: &Array2<f32>, m: &Array2<u8>, o: &CosmicOptions) -> Vec<(usize, usize)> {
    let skip = mask::BAD | mask::OFF_STRIP | mask::SATURATED;
    let (ny, nx) = d.dim();
    let (k, r) = (o.sigma_clip as f32, o.sharpness_ratio as f32);
    let mut out = Vec::new();
    for y in 0..ny {
        for x in 0..nx {
            let (v, s) = (d[[y, x]], var[[y, x]].max(0.0).sqrt());
            if m[[y, x]] & skip != 0 || !(v > 0.0 && v * v > k * k * var[[y, x]]) {
                continue;
            }
            let nb: Vec<f32> = [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)]
                .iter()
                .map(|(dy, dx)| (y as i64 + dy, x as i64 + dx))
                .filter(|&(yy, xx)| yy >= 0 && xx >= 0 && (yy as usize) < ny && (xx as usize) < nx)
                .map(|(yy, xx)| (yy as usize, xx as usize))
                .filter(|&p| m[p] & skip == 0)
                .map(|p| d[p])
                .collect();
            if nb.is_empty() {
                continue;
            }
            let mean4 = (nb.iter().sum::<f32>() / nb.len() as f32).max(0.0);
            if v - r * mean4 > k * s {
                out.push((y, x));
            }
        }
    }
    out
}

#[test]
fn cosmic_seeds_match_a_pixel_by_pixel_reference() {
    // Noise with many candidates (a low threshold), masked pixels, widths around the
    // 64-pixel chunks of the candidate scan.
    let mut g = Gauss(0x00c0_ffee);
    for (ny, nx) in [(5, 1), (7, 63), (9, 64), (6, 65), (11, 200), (3, 1024)] {
        let d = Array2::from_shape_fn((ny, nx), |_| (g.n() * 3.0) as f32);
        let var = Array2::from_shape_fn((ny, nx), |_| (1.0 + g.u() * 2.0) as f32);
        let m = Array2::from_shape_fn((ny, nx), |_| {
            let u = g.u();
            if u < 0.05 {
                mask::BAD
            } else if u < 0.08 {
                mask::SATURATED
            } else if u < 0.1 {
                mask::NONLINEAR
            } else {
                0
            }
        });
        let o = CosmicOptions {
            sigma_clip: 1.5,
            sharpness_ratio: 0.5,
            grow_iterations: 0,
            ..CosmicOptions::default()
        };
        let mut got = m.clone();
        let rep = cosmic_flags(&d, &var.view(), &mut got, &o);
        let want = reference_seeds(&d, &var, &m, &o);
        assert!(
            want.len() > ny * nx / 50,
            "{ny}x{nx}: too few seeds to test ({})",
            want.len()
        );
        assert_eq!(rep.seeds, want.len(), "{ny}x{nx}");
        let mut want_mask = m.clone();
        for &p in &want {
            want_mask[p] |= mask::COSMIC;
        }
        assert_eq!(got, want_mask, "{ny}x{nx}");
    }
}

/// Frames of 1024 x 64 px: level `l` in the strips plus Gaussian noise (sigma `s`), 0 off-strip.
fn noisy_frames(levels: &[f32], s: f64, seed: u64) -> Vec<Frame> {
    let p = Profile::sofi();
    let mut g = Gauss(seed);
    levels
        .iter()
        .map(|&l| {
            let d = Array2::from_shape_fn((1024, 64), |(y, _)| {
                if p.geometry.row_in_strip(y) {
                    l + (s * g.n()) as f32
                } else {
                    0.0
                }
            });
            frame_from(d, 1, 0.0)
        })
        .collect()
}

#[test]
fn clipped_mean_matches_a_slow_reference_and_drops_outliers() {
    let p = Profile::sofi();
    let mut frames = noisy_frames(&[1000.0, 1040.0, 980.0, 1010.0, 1020.0], 6.0, 5);
    // A bright outlier in frame 1 (a star) must not enter the other frames' skies.
    frames[1].data[[450, 20]] += 3000.0;
    let opts = SkyOptions {
        estimator: SkyEstimator::ClippedMean,
        cosmic_rays: None,
        ..SkyOptions::default()
    };
    let (out, rep) = sky_subtract_with_report(&frames, &p, &opts).unwrap();
    assert_eq!(rep.median_variance_factor, 1.0);
    let inv_g = (1.0 / p.detector.effective_gain(1)) as f32;
    let rv = p.detector.read_variance_adu2(1) as f32;
    let n = frames.len();
    for i in 0..n {
        for (y, x) in [(450, 20), (451, 3), (700, 63), (350, 40)] {
            // Reference: median of the other level-normalized values, drop those more than
            // 3 sigma away, mean of the rest.
            let mut v = Vec::new();
            for j in (0..n).filter(|&j| j != i) {
                let sc = (1.0 / rep.levels_adu[j]) as f32;
                let r = frames[j].data[[y, x]];
                v.push((r * sc, (r.max(0.0) * inv_g + rv).sqrt() * sc));
            }
            let mut s: Vec<f32> = v.iter().map(|a| a.0).collect();
            s.sort_by(f32::total_cmp);
            let med = (s[1] + s[2]) * 0.5;
            let kept: Vec<f64> = v
                .iter()
                .filter(|a| (a.0 - med).abs() <= 3.0 * a.1)
                .map(|a| a.0 as f64)
                .collect();
            let est = kept.iter().sum::<f64>() / kept.len() as f64;
            let want = frames[i].data[[y, x]] as f64 - rep.levels_adu[i] * est;
            let got = out[i].data[[y, x]] as f64;
            assert!((got - want).abs() < 0.01, "frame {i} ({y}, {x}): {got} vs {want}");
            if i != 1 && (y, x) == (450, 20) {
                assert!(got.abs() < 30.0, "outlier leaked into the sky of frame {i}: {got}");
            }
        }
    }
    let h = &out[0].history.last().unwrap().detail;
    assert!(
        h.contains("3-sigma clipped mean") && h.contains("c(4) = 1.000000"),
        "{h}"
    );
}

#[test]
fn masking_sources_removes_the_bias_of_a_star_in_the_other_dithers() {
    let p = Profile::sofi();
    // 3 dithers: each sky is the median of 2 values, their mean: a star in one of the other
    // dithers enters at half its brightness.
    let mut frames = noisy_frames(&[1000.0, 1000.0, 1000.0], 0.0, 1);
    for (j, f) in frames.iter_mut().enumerate() {
        let cx = 10.0 + 20.0 * j as f32;
        for y in 440..460 {
            for x in 0..64 {
                let r2 = (y as f32 - 450.0).powi(2) + (x as f32 - cx).powi(2);
                f.data[[y, x]] += 5000.0 * (-r2 / (2.0 * 1.5f32.powi(2))).exp();
            }
        }
    }
    let plain = SkyOptions {
        cosmic_rays: None,
        ..SkyOptions::default()
    };
    let masked = SkyOptions {
        mask_sources: true,
        ..plain.clone()
    };
    let a = sky_subtract(&frames, &p, &plain).unwrap();
    let b = sky_subtract(&frames, &p, &masked).unwrap();
    // Frame 0 at the star of frame 1 (x = 30): -2500 without masking, ~0 with.
    assert!(a[0].data[[450, 30]] < -2000.0, "{}", a[0].data[[450, 30]]);
    assert!(b[0].data[[450, 30]].abs() < 1.0, "{}", b[0].data[[450, 30]]);
    // The star of frame 0 itself is kept whole by both.
    assert!((a[0].data[[450, 10]] - 5000.0).abs() < 1.0);
    assert!((b[0].data[[450, 10]] - 5000.0).abs() < 1.0);
    // Away from the stars nothing changes; where one dither was left out the sky variance
    // is that of one value (c(1)/1 = 1 instead of c(2)/2 = 1/2).
    assert_eq!(a[0].data[[700, 40]], b[0].data[[700, 40]]);
    let va = a[0].variance.as_ref().unwrap();
    let vb = b[0].variance.as_ref().unwrap();
    assert_eq!(va[[700, 40]], vb[[700, 40]]);
    let one = 1000.0 / p.detector.effective_gain(1) + p.detector.read_variance_adu2(1);
    assert!((va[[700, 40]] as f64 / (1.5 * one) - 1.0).abs() < 1e-3);
    assert!(
        (vb[[450, 30]] as f64 / (2.0 * one) - 1.0).abs() < 1e-3,
        "{} vs {}",
        vb[[450, 30]],
        2.0 * one
    );
    assert!(b[0].history.last().unwrap().detail.contains("second pass"));
}

#[test]
fn sky_options_are_checked_and_defaults_are_not_written() {
    let p = Profile::sofi();
    let frames = noisy_frames(&[1000.0, 1000.0], 5.0, 2);
    let bad = SkyOptions {
        clip_sigma: 0.0,
        ..SkyOptions::default()
    };
    let e = sky_subtract(&frames, &p, &bad).unwrap_err().to_string();
    assert!(e.contains("sky.clip_sigma = 0"), "{e}");
    let v = serde_json::to_value(SkyOptions::recommended()).unwrap();
    assert!(v.get("estimator").is_none() && v.get("mask_sources").is_none(), "{v}");
    let o: SkyOptions = serde_json::from_str(r#"{"estimator": "clipped_mean", "mask_sources": true}"#).unwrap();
    assert_eq!(o.estimator, SkyEstimator::ClippedMean);
    assert!(o.mask_sources && o.cosmic_rays.is_some());
}

/// The default sky stage computes the leave-one-out medians inside its last pass, row
/// block by row block, and takes the cosmic-ray candidates from the rows it has just
/// written. Both must give what the two-pass stage gives (medians over whole frames first;
/// cosmic rays flagged afterwards by a scan of every pixel), bit for bit: for 2 to 6
/// dithers (odd and even medians), both scalings, with and without a flat (with an unusable
/// pixel), with an input variance map in one frame, bad pixels, a star, cosmic-ray hits and
/// thresholds low enough to flag noise peaks near them.
#[test]
fn the_fused_sky_pass_matches_the_two_pass_stage() {
    use crate::flat::FlatRows;
    let p = Profile::sofi();
    let (ny, nx) = (1024, 64);
    let mut g = Gauss(4242);
    let mut flat = crate::flat::tests::superflat_of(&Array2::from_shape_fn((ny, nx), |(y, x)| {
        1.0 + 0.02 * (((y * 31 + x * 17) % 13) as f32 / 6.0 - 1.0)
    }));
    flat.bad[[400, 10]] = 1;
    let fr = FlatRows::new(&flat, 0, ny);
    let mut compared = 0;
    for n in 2..=6usize {
        let levels: Vec<f32> = (0..n).map(|i| 900.0 + 40.0 * i as f32).collect();
        let mut frames = noisy_frames(&levels, 6.0, 77 + n as u64);
        for (i, f) in frames.iter_mut().enumerate() {
            let sx = 8.0 + 10.0 * i as f32;
            for y in 380..420 {
                for x in 0..nx {
                    let r2 = (x as f32 - sx).powi(2) + (y as f32 - 400.0).powi(2);
                    f.data[[y, x]] += 4000.0 * (-r2 / 4.5).exp();
                }
            }
            // Cosmic-ray hits: a single pixel and a two-pixel track.
            let (cy, cx) = (350 + 37 * i, 5 + 9 * i % 50);
            f.data[[cy, cx]] += 3000.0;
            f.data[[cy + 200, cx + 3]] += 2500.0;
            f.data[[cy + 200, cx + 4]] += 2000.0;
            for _ in 0..20 {
                let (y, x) = ((g.u() * ny as f64) as usize, (g.u() * nx as f64) as usize);
                f.mask[[y, x]] |= mask::BAD;
            }
        }
        frames[n - 1].variance = Some(Array2::from_shape_fn((ny, nx), |_| (4.0 + g.u()) as f32));
        for scaling in [SkyScaling::Multiplicative, SkyScaling::Additive] {
            for with_flat in [false, true] {
                // Thresholds low enough that noise peaks near them are flagged too.
                let opts = SkyOptions {
                    scaling,
                    cosmic_rays: Some(CosmicOptions {
                        sigma_clip: 2.5,
                        sharpness_ratio: 0.5,
                        ..CosmicOptions::default()
                    }),
                    ..SkyOptions::default()
                };
                let run = |opts: &SkyOptions, unfused: bool| {
                    let route = Route {
                        fuse_medians: !unfused,
                        ..Route::FAST
                    };
                    sky_subtract_by(frames.clone(), &p, opts, with_flat.then_some(&fr), route).unwrap()
                };
                let (fused, rep) = run(&opts, false);
                let (two_pass, rep2) = run(&opts, true);
                // Cosmic rays flagged afterwards by the whole-frame scan.
                let plain = SkyOptions {
                    cosmic_rays: None,
                    ..opts.clone()
                };
                let (unflagged, _) = run(&plain, false);
                let what = format!("{n} dithers, {scaling:?}, flat {with_flat}");
                let mut flagged = 0;
                for ((a, b), c) in fused.iter().zip(&two_pass).zip(&unflagged) {
                    let bits = |v: &Array2<f32>| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert!(bits(&a.data) == bits(&b.data), "{what}: data differ");
                    assert!(
                        bits(a.variance.as_ref().unwrap()) == bits(b.variance.as_ref().unwrap()),
                        "{what}: variance differs"
                    );
                    assert_eq!(a.mask, b.mask, "{what}");
                    let (scanned, _) = flag_cosmic_rays(c, opts.cosmic().unwrap()).unwrap();
                    assert_eq!(a.mask, scanned.mask, "{what}: cosmic-ray flags differ from the scan's");
                    flagged += a.mask.iter().filter(|&&m| m & mask::COSMIC != 0).count();
                    compared += 1;
                }
                assert_eq!(rep.cosmic, rep2.cosmic, "{what}");
                // The hits and noise peaks are found (not two empty masks compared).
                assert!(flagged >= 50 * n, "{what}: {flagged} cosmic-ray pixels");
            }
        }
    }
    assert_eq!(compared, 4 * (2..=6).sum::<usize>());
}
