use super::*;

fn profile() -> Profile {
    Profile::sofi()
}

/// A response map: 1 + 0.02 * a deterministic pattern, in every strip.
fn response(ny: usize, nx: usize) -> Array2<f32> {
    Array2::from_shape_fn((ny, nx), |(y, x)| {
        let h = (y as u64 * 7919 + x as u64 * 104729) % 1000;
        1.0 + 0.02 * (h as f32 / 500.0 - 1.0)
    })
}

/// A superflat of response `resp` with variance 1e-4 everywhere, no unusable pixel.
pub(crate) fn superflat_of(resp: &Array2<f32>) -> Flat {
    Flat {
        data: resp.clone(),
        variance: Array2::from_elem(resp.dim(), 1e-4),
        bad: Array2::zeros(resp.dim()),
        kind: FlatKind::Superflat,
        posang_deg: None,
        filter: None,
        sources: vec![],
        detail: String::new(),
        path: None,
    }
}

fn header(posang: f64, lamp: Option<bool>) -> Header {
    let p = profile();
    let mut h = Header::new("");
    h.set(&p.keywords.dpr_type, "FLAT");
    h.set(&p.keywords.posang, posang);
    h.set(&p.keywords.ndit, 6i64);
    h.set(&p.keywords.filter, "Ks");
    if let Some(l) = lamp {
        h.set(LAMP_KEYWORD, l);
    }
    h
}

/// Noiseless lamp frames: the o strips see the lamp 3 % brighter than the e strips.
fn lamp_frames(resp: &Array2<f32>, posang: f64) -> (Vec<Frame>, Vec<Frame>) {
    let g = profile().geometry;
    let pol = |y: usize| {
        if [g.o_sky2, g.o_target, g.o_sky1].iter().any(|r| y >= r[0] && y < r[1]) {
            1.03
        } else {
            0.97
        }
    };
    let mk = |lamp: f32, on: bool| {
        let d = Array2::from_shape_fn(resp.dim(), |(y, x)| {
            if g.row_in_strip(y) {
                (lamp * pol(y) + 300.0) * resp[[y, x]]
            } else {
                0.0
            }
        });
        Frame::new(d, header(posang, Some(on)))
    };
    (vec![mk(5000.0, true), mk(5000.0, true)], vec![mk(0.0, false)])
}

#[test]
fn dome_flat_recovers_the_response_strip_by_strip() {
    let g = profile().geometry;
    let resp = response(g.ny, g.nx);
    let (on, off) = lamp_frames(&resp, 45.0);
    let f = dome_flat(&on, &off, &profile(), &FlatOptions::default()).unwrap();
    assert_eq!(f.kind, FlatKind::Dome);
    assert_eq!(f.posang_deg, Some(45.0));
    // Each strip: flat = resp / median(resp over the strip), whatever the lamp level.
    for (_, [a, b]) in g.strips() {
        let mut v: Vec<f32> = resp.slice(s![a..b, ..]).iter().copied().collect();
        let med = median_f32(&mut v).unwrap();
        for y in (a..b).step_by(37) {
            for x in (0..g.nx).step_by(41) {
                let want = resp[[y, x]] / med;
                assert!(
                    (f.data[[y, x]] - want).abs() < 2e-3,
                    "{y} {x}: {} vs {want}",
                    f.data[[y, x]]
                );
            }
        }
    }
    assert_eq!(f.data[[0, 5]], 1.0);
    assert!(f.variance[[400, 400]] > 0.0);
    // Variance: (on/g + rv)/n_on + (off/g + rv)/n_off over the level^2.
    let det = profile().detector;
    let (inv_g, rv) = (1.0 / det.effective_gain(6), det.read_variance_adu2(6));
    let raw_on = on[0].data[[400, 400]] as f64;
    let raw_off = off[0].data[[400, 400]] as f64;
    let want = ((raw_on * inv_g + rv) / 2.0 + (raw_off * inv_g + rv)) / (raw_on - raw_off).powi(2)
        * (f.data[[400, 400]] as f64).powi(2);
    assert!(((f.variance[[400, 400]] as f64) / want - 1.0).abs() < 0.02);
}

#[test]
fn superflat_recovers_the_response_with_stars_present() {
    let g = profile().geometry;
    let (ny, nx) = (g.ny, g.nx);
    let resp = response(ny, nx);
    let frames: Vec<Frame> = (0..9)
        .map(|i| {
            let level = 1000.0 + 50.0 * i as f32;
            let sx = 100.0 + 90.0 * i as f32;
            let d = Array2::from_shape_fn((ny, nx), |(y, x)| {
                if !g.row_in_strip(y) {
                    return 0.0;
                }
                let r2 = (x as f32 - sx).powi(2) + (y as f32 - 420.0).powi(2);
                (level + 20000.0 * (-r2 / 8.0).exp()) * resp[[y, x]]
            });
            let mut h = header(0.0, None);
            h.set(&profile().keywords.dpr_type, "OBJECT");
            Frame::new(d, h)
        })
        .collect();
    let f = superflat(&frames, &profile(), &FlatOptions::default()).unwrap();
    let (a, b) = (g.o_target[0], g.o_target[1]);
    let mut v: Vec<f32> = resp.slice(s![a..b, ..]).iter().copied().collect();
    let med = median_f32(&mut v).unwrap();
    let mut worst = 0f32;
    for y in a..b {
        for x in 0..nx {
            worst = worst.max((f.data[[y, x]] - resp[[y, x]] / med).abs());
        }
    }
    // Noiseless: exact up to the strip normalization (median over a 1-in-4 sample).
    assert!(worst < 2e-3, "worst {worst}");
    assert_eq!(f.bad.iter().filter(|&&b| b != 0).count(), 0);
}

#[test]
fn apply_divides_and_propagates_the_flat_noise() {
    let g = profile().geometry;
    let resp = response(g.ny, g.nx);
    let mut flat = superflat_of(&resp);
    flat.bad[[400, 10]] = 1;
    let mut data = Array2::from_shape_fn(resp.dim(), |(y, x)| 1000.0 * resp[[y, x]]);
    data[[400, 500]] += 3000.0 * resp[[400, 500]];
    let fr = Frame::new(data, header(0.0, None));
    let out = apply_flat(&fr, &flat, &profile()).unwrap();
    assert!((out.data[[400, 400]] - 1000.0).abs() < 1e-2);
    assert!((out.data[[400, 500]] - 4000.0).abs() < 1e-1);
    let det = profile().detector;
    let (inv_g, rv) = (1.0 / det.effective_gain(6), det.read_variance_adu2(6));
    let f = resp[[400, 500]] as f64;
    let raw = 4000.0 * f;
    let want = (raw * inv_g + rv + 3000.0f64.powi(2) * 1e-4) / (f * f);
    assert!(((out.variance.as_ref().unwrap()[[400, 500]] as f64) / want - 1.0).abs() < 1e-3);
    // Sky pixels: no flat-noise term (it cancels in the sky subtraction).
    let f = resp[[400, 400]] as f64;
    let want = (1000.0 * f * inv_g + rv) / (f * f);
    assert!(((out.variance.as_ref().unwrap()[[400, 400]] as f64) / want - 1.0).abs() < 1e-2);
    assert_eq!(out.mask[[400, 10]] & mask::BAD, mask::BAD);
    assert_eq!(out.history.last().unwrap().stage, "flat");
    // In place on the target strips, reading those rows of the full-height flat: the same
    // numbers bit for bit as the cropped frame divided by the cropped flat.
    let (r0, r1) = (g.o_target[0], g.e_target[1]);
    let cp = profile().cropped_rows(r0, r1);
    let crop = fr.crop_rows(r0, r1);
    let want = apply_flat(&crop, &flat.crop_rows(r0, r1), &cp).unwrap();
    let mut got = crop.clone();
    apply_flat_in_place(&mut got, &flat, r0, &cp).unwrap();
    assert_eq!(got.data, want.data);
    assert_eq!(got.variance, want.variance);
    assert_eq!(got.mask, want.mask);
    assert_eq!(got.mask[[400 - r0, 10]] & mask::BAD, mask::BAD);
    // A flat too short for the rows asked is refused, the frame left as it was.
    let mut same = crop.clone();
    let e = apply_flat_in_place(&mut same, &flat, g.ny - 10, &cp).unwrap_err();
    assert!(e.to_string().contains("differs from the flat's"), "{e}");
    assert_eq!(same.data, crop.data);
    assert!(same.variance.is_none());
}

#[test]
fn flat_file_round_trip_and_choice_by_angle() {
    let g = profile().geometry;
    let resp = response(g.ny, g.nx);
    let (on, off) = lamp_frames(&resp, 90.0);
    let f = dome_flat(&on, &off, &profile(), &FlatOptions::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join(flat_file_name(&f));
    assert!(p.ends_with("flat_dome_Ks_pa090.fits"));
    write_flat(&p, &f).unwrap();
    let back = read_flat(&p).unwrap();
    assert_eq!(back.data, f.data);
    assert_eq!(back.variance, f.variance);
    assert_eq!(back.bad, f.bad);
    assert_eq!(back.kind, FlatKind::Dome);
    assert_eq!(back.posang_deg, Some(90.0));
    assert_eq!(back.filter.as_deref(), Some("Ks"));
    assert_eq!(back.sources.len(), 3);
    // Found again in a night folder, the written flat is skipped as a sofipol product,
    // not reported as a foreign ("not SOFI") frame.
    let c = crate::classify::classify(&crate::fits::read_header(&p).unwrap(), &profile());
    let reason = c.reason().unwrap();
    assert!(reason.contains("a sofipol product (SOFIPROD = 'FLAT')"), "{reason}");
    let mut f0 = back.clone();
    f0.posang_deg = Some(0.0);
    let set = FlatSet::new(vec![f0, back]);
    assert_eq!(set.for_frame(90.2, "Ks").unwrap().posang_deg, Some(90.0));
    assert_eq!(set.for_frame(359.9, "ks").unwrap().posang_deg, Some(0.0));
    assert_eq!(set.for_frame(80.0, "Ks").unwrap().posang_deg, Some(90.0));
    assert!(set.for_frame(0.0, "J").is_none());
}

#[test]
fn lamp_keyword_is_required_and_checked() {
    let p = profile();
    // A flat of another template without the lamp keyword (a sky flat) is not a dome flat;
    // the dome-flat template without it is an error naming the keyword.
    assert!(dome_flat_info(&header(0.0, None), &p).unwrap().is_none());
    let mut dome = header(0.0, None);
    dome.set(&p.keywords.tpl_id, DOME_FLAT_TEMPLATE);
    assert!(dome_flat_info(&dome, &p).unwrap_err().to_string().contains("LAMP1"));
    let mut h = header(0.0, None);
    h.set(LAMP_KEYWORD, "maybe");
    let e = dome_flat_info(&h, &p).unwrap_err().to_string();
    assert!(e.contains("LAMP1") && e.contains("maybe"), "{e}");
    assert!(dome_flat_info(&header(30.0, Some(false)), &p)
        .unwrap()
        .is_some_and(|i| !i.lamp_on));
    let mut sci = header(0.0, Some(true));
    sci.set(&p.keywords.dpr_type, "OBJECT");
    assert!(dome_flat_info(&sci, &p).unwrap().is_none());
}

/// Five noiseless dithers of a sky that changes level from frame to frame, with a star
/// that moves, seen through `resp`.
fn dithers_through(resp: &Array2<f32>) -> Vec<Frame> {
    (0..5)
        .map(|i| {
            let (sky, sx) = (1000.0 * (1.0 + 0.03 * i as f32), 300.0 + 87.0 * i as f32);
            let data = Array2::from_shape_fn(resp.dim(), |(y, x)| {
                let r2 = (x as f32 - sx).powi(2) + (y as f32 - 400.0).powi(2);
                resp[[y, x]] * (sky + 5000.0 * (-r2 / 4.5).exp())
            });
            Frame::new(data, header(0.0, None))
        })
        .collect()
}

/// The sky-stage scene: the profile, its geometry, a response map, its superflat with one
/// unusable pixel at (400, 10), and dithered frames through the response.
fn sky_scene() -> (Profile, crate::profile::Geometry, Array2<f32>, Flat, Vec<Frame>) {
    let p = profile();
    let g = p.geometry.clone();
    let resp = response(g.ny, g.nx);
    let mut flat = superflat_of(&resp);
    flat.bad[[400, 10]] = 1;
    let frames = dithers_through(&resp);
    (p, g, resp, flat, frames)
}

#[test]
fn the_sky_stage_divides_by_the_flat_like_dividing_first() {
    use crate::sky::{sky_subtract, sky_subtract_flat, SkyOptions, SkyScaling};
    let (p, g, resp, flat, frames) = sky_scene();
    let opts = SkyOptions {
        cosmic_rays: None,
        ..Default::default()
    };
    // The reference: every frame divided by the flat first, then sky-subtracted.
    let first: Vec<Frame> = frames.iter().map(|f| apply_flat(f, &flat, &p).unwrap()).collect();
    let want = sky_subtract(&first, &p, &opts).unwrap();
    let fr = FlatRows::new(&flat, 0, g.ny);
    let (got, _) = sky_subtract_flat(frames.clone(), &p, &opts, Some(&fr)).unwrap();
    let mut worst = (0f32, 0f32);
    for (w, o) in want.iter().zip(&got) {
        for y in (0..g.ny).filter(|&y| g.row_in_strip(y)) {
            for x in 0..g.nx {
                if w.mask[[y, x]] & mask::BAD != 0 {
                    continue;
                }
                let (a, b) = (w.data[[y, x]], o.data[[y, x]]);
                worst.0 = worst.0.max((a - b).abs());
                let (va, vb) = (
                    w.variance.as_ref().unwrap()[[y, x]],
                    o.variance.as_ref().unwrap()[[y, x]],
                );
                worst.1 = worst.1.max((va / vb - 1.0).abs());
            }
        }
        assert_eq!(o.mask[[400, 10]] & mask::BAD, mask::BAD);
        // Unusable in the flat: raw - sky, not divided.
        assert_eq!(o.history.iter().filter(|h| h.stage == "flat").count(), 1);
    }
    // The star's 5000 ADU peak and a 1000-1120 ADU sky: the same to float rounding; the
    // variances differ only in how the sky estimate's noise meets the flat (sky / flat
    // against sky / flat^2: ~2 % for a 2 % response).
    assert!(worst.0 < 0.05, "data differ by {} ADU", worst.0);
    assert!(worst.1 < 0.03, "variances differ by {}", worst.1);
    // The star's signal above the sky carries the flat's noise: ~5000^2 x 1e-4 = 2500 ADU^2
    // on top of its Poisson variance.
    let star_var = got[0].variance.as_ref().unwrap()[[400, 300]];
    let no_flat_noise = {
        let mut f0 = flat.clone();
        f0.variance.fill(0.0);
        let (o, _) = sky_subtract_flat(frames.clone(), &p, &opts, Some(&FlatRows::new(&f0, 0, g.ny))).unwrap();
        o[0].variance.as_ref().unwrap()[[400, 300]]
    };
    let f = resp[[400, 300]];
    let sig = got[0].data[[400, 300]];
    assert!(((star_var - no_flat_noise) / (sig * sig * 1e-4 / (f * f)) - 1.0).abs() < 1e-3);
    // Additive scaling: the flat is divided out first (the sky does not scale with it).
    let add = SkyOptions {
        scaling: SkyScaling::Additive,
        ..opts.clone()
    };
    let want = sky_subtract(&first, &p, &add).unwrap();
    let (got, _) = sky_subtract_flat(frames.clone(), &p, &add, Some(&fr)).unwrap();
    for (w, o) in want.iter().zip(&got) {
        assert_eq!(w.data, o.data);
        assert_eq!(w.variance, o.variance);
    }
    // A flat whose rows do not cover the frames is refused by name.
    let short = flat.crop_rows(0, g.ny - 10);
    let e = sky_subtract_flat(frames, &p, &opts, Some(&FlatRows::new(&short, 0, g.ny))).unwrap_err();
    assert!(e.to_string().contains("does not fit the superflat"), "{e}");
}

/// The sky stage's last pass gives the same numbers, bit for bit, in its run-time chosen
/// vector build (AVX2) and in the portable build (SSE2), with and without the flat, with multiplicative and additive
/// scaling, with the source-masked second pass (per-pixel dither counts) and a NaN-free
/// frame set holding a flat pixel that is unusable.
#[test]
fn the_sky_pass_is_the_same_in_every_vector_build() {
    use crate::sky::{sky_subtract_by, Kernel, Route, SkyOptions, SkyScaling};
    let (p, g, _, mut flat, frames) = sky_scene();
    flat.variance[[401, 11]] = 0.3;
    let fr = FlatRows::new(&flat, 0, g.ny);
    let mut compared = 0;
    for scaling in [SkyScaling::Multiplicative, SkyScaling::Additive] {
        for mask_sources in [false, true] {
            for with_flat in [false, true] {
                let opts = SkyOptions {
                    scaling,
                    mask_sources,
                    ..Default::default()
                };
                let run = |kernel: Kernel| {
                    let route = Route { kernel, ..Route::FAST };
                    sky_subtract_by(frames.clone(), &p, &opts, with_flat.then_some(&fr), route)
                        .unwrap()
                        .0
                };
                let (a, b) = (run(Kernel::Fastest), run(Kernel::Portable));
                for (x, y) in a.iter().zip(&b) {
                    let bits = |f: &Frame| f.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    let vbits = |f: &Frame| {
                        f.variance
                            .as_ref()
                            .unwrap()
                            .iter()
                            .map(|v| v.to_bits())
                            .collect::<Vec<_>>()
                    };
                    assert!(
                        bits(x) == bits(y),
                        "{scaling:?} {mask_sources} {with_flat}: data differ"
                    );
                    assert!(
                        vbits(x) == vbits(y),
                        "{scaling:?} {mask_sources} {with_flat}: variance differs"
                    );
                    assert_eq!(x.mask, y.mask);
                    compared += 1;
                }
            }
        }
    }
    assert_eq!(compared, 8 * frames.len());
}
