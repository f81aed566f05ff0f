//! The locating stages of the reduction (reduce/sources.rs, reduce/beams.rs,
//! reduce/companion.rs) on images whose answer is known by construction.
use ndarray::Array2;
use sofipol_pipeline::photometry::model::add_gaussian;
use sofipol_pipeline::reduce::beams::{eo_offset_by_correlation, median_offset};
use sofipol_pipeline::reduce::companion::combine_geometry;
use sofipol_pipeline::reduce::sources::{brightest_peak, brightest_peak_scan};
use sofipol_pipeline::stokes::model::companion_offset_px;

fn image(ny: usize, nx: usize, stars: &[(f64, f64, f64)], sky: f32) -> Array2<f32> {
    let mut img = Array2::from_elem((ny, nx), sky);
    let mut v = img.view_mut();
    for &(flux, x, y) in stars {
        add_gaussian(&mut v, flux, x, y, 1.2, 1.2);
    }
    img
}

#[test]
fn brightest_peak_finds_the_brighter_star_within_radius_rows_and_mask() {
    let img = image(
        100,
        120,
        &[(5e4, 40.3, 50.6), (9e4, 80.2, 50.1), (2e5, 60.0, 90.0)],
        10.0,
    );
    let mut mask = Array2::<u8>::zeros(img.raw_dim());
    // Around (60, 50) with radius 30 both of the first two stars are in reach; the third
    // is outside the rows [20, 80).
    let (x, y, _) = brightest_peak(img.view(), mask.view(), 60.0, 50.0, 30.0, [20, 80]).unwrap();
    assert_eq!((x, y), (80.0, 50.0));
    // Radius 15 around (45, 50): only the fainter star.
    let (x, y, _) = brightest_peak(img.view(), mask.view(), 45.0, 50.0, 15.0, [20, 80]).unwrap();
    assert_eq!((x, y), (40.0, 51.0));
    // Without the row limit the brightest star of all wins.
    let (x, y, _) = brightest_peak(img.view(), mask.view(), 60.0, 70.0, 40.0, [0, 100]).unwrap();
    assert_eq!((x, y), (60.0, 90.0));
    // The bright star masked out: its 3x3 boxes have too few good pixels or lower values.
    for j in 85..96 {
        for i in 55..66 {
            mask[[j, i]] = 1;
        }
    }
    let (x, y, _) = brightest_peak(img.view(), mask.view(), 60.0, 70.0, 40.0, [0, 100]).unwrap();
    assert_eq!((x, y), (80.0, 50.0));
    // Everything masked: nothing found.
    mask.fill(1);
    assert!(brightest_peak(img.view(), mask.view(), 60.0, 50.0, 30.0, [0, 100]).is_none());
}

/// The pruned search returns what the plain row-major scan returns, bit for bit: on noise
/// with stars, cosmic-like spikes, masked hot pixels, ties (values on a coarse grid) and a
/// NaN, over whole strips and small radii.
#[test]
fn brightest_peak_pruned_search_equals_the_plain_scan() {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(17);
    for case in 0..60 {
        let (ny, nx) = (40 + case % 7 * 9, 50 + case % 5 * 13);
        let coarse = case % 3 == 0; // values on a grid of 1: many ties
        let mut img = Array2::from_shape_fn((ny, nx), |_| {
            let v: f32 = rng.random_range(-5.0..5.0);
            if coarse {
                v.round()
            } else {
                v
            }
        });
        for _ in 0..case % 4 {
            let (x, y) = (rng.random_range(0.0..nx as f64), rng.random_range(0.0..ny as f64));
            add_gaussian(&mut img.view_mut(), rng.random_range(10.0..500.0), x, y, 1.3, 1.3);
        }
        let mut mask = Array2::<u8>::zeros((ny, nx));
        for _ in 0..case % 6 * 5 {
            let (i, j) = (rng.random_range(0..nx), rng.random_range(0..ny));
            img[[j, i]] += 1e4; // a spike: masked or not
            mask[[j, i]] = u8::from(rng.random_bool(0.7));
        }
        if case % 10 == 9 {
            img[[ny / 2, nx / 2]] = f32::NAN;
        }
        for _ in 0..5 {
            let (x0, y0) = (rng.random_range(0.0..nx as f64), rng.random_range(0.0..ny as f64));
            let radius = if rng.random_bool(0.3) {
                nx as f64
            } else {
                rng.random_range(0.5..15.0)
            };
            let lo = rng.random_range(0..ny / 3);
            let rows = [lo, rng.random_range(lo + 1..=ny)];
            let a = brightest_peak(img.view(), mask.view(), x0, y0, radius, rows);
            let b = brightest_peak_scan(img.view(), mask.view(), x0, y0, radius, rows);
            assert_eq!(
                a.map(|p| (p.0, p.1, p.2.to_bits())),
                b.map(|p| (p.0, p.1, p.2.to_bits())),
                "case {case}"
            );
        }
    }
}

#[test]
fn median_offset_of_odd_and_even_counts_and_empty() {
    assert_eq!(median_offset(&[]), None);
    let p = |dx: f64, dy: f64| ((10.0, 20.0), (10.0 + dx, 20.0 + dy));
    assert_eq!(
        median_offset(&[p(1.0, 5.0), p(3.0, -1.0), p(100.0, 2.0)]),
        Some((3.0, 2.0))
    );
    assert_eq!(median_offset(&[p(1.0, 5.0), p(3.0, -1.0)]), Some((2.0, 2.0)));
}

/// The e-o offset off the whole pixel and slightly tilted, with the fluxes of the pair
/// swapped in rank between the beams (a brightest-peak match would jump to the other star).
/// The correlation is the starting point of the per-frame fits, which find each beam's
/// position on their own: it must land within half a pixel (the right whole-pixel peak,
/// refined towards the truth by the parabola).
#[test]
fn eo_offset_by_correlation_recovers_a_fractional_tilted_offset() {
    for &(dx, dy) in &[(0.4, 166.6), (-0.7, 167.3), (1.2, 165.5), (0.0, 167.0)] {
        let (xo, yo) = (60.3, 40.7);
        let sep = (3.1, 2.4);
        let img = image(
            260,
            130,
            &[
                (6e4, xo, yo),
                (4e4, xo + sep.0, yo + sep.1),
                // e beam: A fainter than B here.
                (3.5e4, xo + dx, yo + dy),
                (5e4, xo + sep.0 + dx, yo + sep.1 + dy),
            ],
            0.0,
        );
        let mask = Array2::<u8>::zeros(img.raw_dim());
        let got = eo_offset_by_correlation(&[(&img, &mask)], &[(xo, yo)], (0.0, 167.0), 9, 5).unwrap();
        assert!(
            (got.0 - dx).abs() < 0.5 && (got.1 - dy).abs() < 0.5,
            "true ({dx}, {dy}), found {got:?}"
        );
    }
}

#[test]
fn eo_offset_is_none_when_the_target_is_too_close_to_the_edge() {
    let img = image(200, 100, &[(6e4, 3.0, 20.0)], 0.0);
    let mask = Array2::<u8>::zeros(img.raw_dim());
    assert!(eo_offset_by_correlation(&[(&img, &mask)], &[(3.0, 20.0)], (0.0, 167.0), 9, 5).is_none());
}

#[test]
fn combine_geometry_inverts_the_rotation_convention_and_wraps_the_pa() {
    let scale = 0.288;
    for &(sep, pa) in &[(2.2, 130.0), (0.6, 359.5), (4.6, 0.4), (1.1, 181.0)] {
        let found: Vec<_> = [0.0, 45.0, 90.0, 135.0]
            .iter()
            .map(|&posang| (posang, companion_offset_px(sep, pa, posang, scale), 1.0))
            .collect();
        let (s, p, worst) = combine_geometry(&found, scale).unwrap();
        let dpa = (p - pa + 180.0).rem_euclid(360.0) - 180.0;
        assert!(
            (s - sep).abs() < 1e-9 && dpa.abs() < 1e-9 && worst < 1e-9,
            "{sep} {pa}: {s} {p} {worst}"
        );
    }
    // PAs of 359 and 1 deg average to 0, not 180; the disagreement is reported in px.
    let off = |pa: f64| (0.0, companion_offset_px(3.0, pa, 0.0, scale), 1.0);
    let (_, p, worst) = combine_geometry(&[off(359.0), off(1.0)], scale).unwrap();
    assert!(!(1e-9..=360.0 - 1e-9).contains(&p), "{p}");
    let chord = 3.0 / scale * (2.0 * (1f64).to_radians().sin() / 2.0) * 2.0 / 2.0;
    assert!((worst - chord).abs() < 0.01, "{worst} vs {chord}");
    assert!(combine_geometry(&[], scale).is_none());
}

/// A near-equal pair 12.4 px apart, 80 px from the detector centre (beyond
/// `primary_search_px` of it), no position given: the brightest source of the first
/// orientation's frames is A in two frames and B in three (fluxes within 6 %), and the true
/// pointing misses the header offsets by up to 1.4 px. The frames agree on the pair: the
/// primary is found, on one and the same star, in every frame (a nominal position taken as
/// the median of both stars' positions sits on the edge of B's, agrees with only two of the
/// five frames within 3 px, and the search falls back to the strip centre, out of reach).
#[test]
fn primary_of_a_near_equal_pair_off_centre_is_found_when_the_brightest_alternates() {
    use sofipol_calib::{Frame, Header, Profile};
    use sofipol_pipeline::reduce::sources::{locate_primary, unusable_masks};
    use sofipol_pipeline::reduce::{MeasureParams, SkySubtractedOrientation};

    let profile = Profile::sofi();
    let (nx, ny) = (profile.geometry.nx, profile.geometry.ny);
    let a = (433.6, 452.0);
    let b = (431.8, 439.6);
    let header_dx = [-173.6, -86.8, 0.0, 86.8, 173.6];
    let pointing = [(-0.3, -0.9), (-0.4, -1.4), (-0.1, 1.3), (0.8, -0.6), (1.2, 0.8)];
    // (A, B) fluxes: A brighter in the first and last frame, B in the other three.
    let fluxes = [
        (9300.0, 8800.0),
        (8800.0, 9300.0),
        (8800.0, 9300.0),
        (8800.0, 9300.0),
        (9300.0, 8800.0),
    ];
    let sigma = 2.2 / (8f64.ln() * 2.0).sqrt();
    let truth: Vec<[(f64, f64); 2]> = header_dx
        .iter()
        .zip(&pointing)
        .map(|(&hx, &(ex, ey))| [(a.0 + hx + ex, a.1 + ey), (b.0 + hx + ex, b.1 + ey)])
        .collect();
    let frames = truth
        .iter()
        .zip(&fluxes)
        .map(|(stars, &(fa, fb))| {
            let mut img = Array2::<f32>::zeros((ny, nx));
            let mut v = img.view_mut();
            add_gaussian(&mut v, fa, stars[0].0, stars[0].1, sigma, sigma);
            add_gaussian(&mut v, fb, stars[1].0, stars[1].1, sigma, sigma);
            Frame::new(img, Header::default())
        })
        .collect();
    let orients = [SkySubtractedOrientation {
        posang_deg: 0.0,
        analyzer_deg: 0.0,
        frames,
        offsets: header_dx.iter().map(|&dx| [dx, 0.0]).collect(),
    }];
    let masks = unusable_masks(&orients);
    let primary = locate_primary(&orients, &masks, &profile, &MeasureParams::default()).unwrap();
    // Every frame's centre is on the same star (A or B), to the centroid's accuracy.
    let on = |star: usize| {
        primary.centres[0]
            .iter()
            .zip(&truth)
            .all(|(c, t)| c.is_some_and(|(x, y)| (x - t[star].0).hypot(y - t[star].1) < 0.05))
    };
    assert!(on(0) || on(1), "centres {:?}, truth {truth:?}", primary.centres[0]);
}

/// Frames of one orientation (POSANG 0, five dithers of 86.8 px along x, the true pointing
/// off the header offsets by up to 1.4 px) holding Gaussian stars (flux, x, y at zero
/// offset); pixels at or above `saturation` masked SATURATED as the sky stage masks them;
/// a variance of 100 ADU^2 per pixel.
fn dithered(stars: &[(f64, f64, f64)], saturation: f32) -> Vec<sofipol_pipeline::reduce::SkySubtractedOrientation> {
    use sofipol_calib::frame::mask::SATURATED;
    use sofipol_calib::{Frame, Header, Profile};
    let g = Profile::sofi().geometry;
    let header_dx = [-173.6, -86.8, 0.0, 86.8, 173.6];
    let pointing = [(-0.3, -0.9), (-0.4, -1.4), (-0.1, 1.3), (0.8, -0.6), (1.2, 0.8)];
    let sigma = 2.8 / (8f64.ln() * 2.0).sqrt();
    let frames = header_dx
        .iter()
        .zip(&pointing)
        .map(|(&hx, &(ex, ey))| {
            let mut img = Array2::<f32>::zeros((g.ny, g.nx));
            let mut v = img.view_mut();
            for &(f, x, y) in stars {
                add_gaussian(&mut v, f, x + hx + ex, y + ey, sigma, sigma);
            }
            let mask = img.mapv(|p| if p >= saturation { SATURATED } else { 0 });
            let img = img.mapv(|p| p.min(saturation));
            let mut frame = Frame::new(img, Header::default());
            frame.mask = mask;
            frame.variance = Some(Array2::from_elem((g.ny, g.nx), 100.0));
            frame
        })
        .collect();
    vec![sofipol_pipeline::reduce::SkySubtractedOrientation {
        posang_deg: 0.0,
        analyzer_deg: 0.0,
        frames,
        offsets: header_dx.iter().map(|&dx| [dx, 0.0]).collect(),
    }]
}

/// The target is the binary at the pointing (detector centre in x, middle of the o-target
/// strip in y: (512, 428) at zero offset), not the brightest source of the strip: a
/// saturated star 40 times brighter 69-441 px away along the strip (where a dither may put
/// it on the binary's place in another frame, or off the detector) leaves every frame's
/// centre on the binary and is named in `brighter_source_in_strip` (also when the binary is
/// 20 px off the pointing and the star 55 px from it); a fainter star there
/// changes nothing and is not named; with nothing at the pointing the brightest source of
/// the strip is still the target (a target placed elsewhere), without the flag.
#[test]
fn the_target_is_the_binary_at_the_pointing_not_the_brightest_star_of_the_strip() {
    use sofipol_calib::Profile;
    use sofipol_pipeline::catalog::FlagCode;
    use sofipol_pipeline::reduce::sources::{locate_primary, unusable_masks};
    use sofipol_pipeline::reduce::MeasureParams;

    let profile = Profile::sofi();
    let sat = profile.detector.saturation_adu as f32;
    let pair = [(1.2e5, 512.0, 428.0), (6e4, 519.0, 437.0)];
    let header_dx = [-173.6, -86.8, 0.0, 86.8, 173.6];
    let on_a = |centres: &[Option<(f64, f64)>], a: (f64, f64)| {
        centres
            .iter()
            .zip(&header_dx)
            .all(|(c, hx)| c.is_some_and(|(x, y)| (x - (a.0 + hx)).hypot(y - a.1) < 2.0))
    };
    let brighter = |flags: &[sofipol_pipeline::catalog::Flag]| {
        flags.iter().filter(|f| f.is(FlagCode::BrighterSourceInStrip)).count()
    };
    for (dx, dy) in [(-441.0, 0.0), (-102.6, -18.1), (65.2, -23.7), (86.8, 0.0), (0.0, 75.0)] {
        for (flux, named) in [(4.8e6, 1), (2e4, 0)] {
            let mut stars = pair.to_vec();
            stars.push((flux, 512.0 + dx, 428.0 + dy));
            let orients = dithered(&stars, sat);
            let masks = unusable_masks(&orients);
            let p = locate_primary(&orients, &masks, &profile, &MeasureParams::default()).unwrap();
            assert!(
                on_a(&p.centres[0], (512.0, 428.0)),
                "star {flux} at ({dx}, {dy}): centres {:?}",
                p.centres[0]
            );
            assert_eq!(brighter(&p.flags), named, "star {flux} at ({dx}, {dy}): {:?}", p.flags);
        }
    }
    // The binary 20 px from the pointing, the saturated star 75 px from the pointing on the
    // same side: 55 px from the binary, within `primary_search_px` of it.
    let mut stars = vec![(1.2e5, 532.0, 428.0), (6e4, 539.0, 437.0)];
    stars.push((4.8e6, 587.0, 428.0));
    let orients = dithered(&stars, sat);
    let masks = unusable_masks(&orients);
    let p = locate_primary(&orients, &masks, &profile, &MeasureParams::default()).unwrap();
    assert!(on_a(&p.centres[0], (532.0, 428.0)), "centres {:?}", p.centres[0]);
    assert_eq!(brighter(&p.flags), 1, "{:?}", p.flags);
    // The binary 200 px from the pointing, nothing at the pointing: the brightest source.
    let away = [(1.2e5, 312.0, 440.0), (6e4, 319.0, 449.0)];
    let orients = dithered(&away, sat);
    let masks = unusable_masks(&orients);
    let p = locate_primary(&orients, &masks, &profile, &MeasureParams::default()).unwrap();
    assert!(on_a(&p.centres[0], (312.0, 440.0)), "centres {:?}", p.centres[0]);
    assert!(p.flags.is_empty(), "{:?}", p.flags);
}
