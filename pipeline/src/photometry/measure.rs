//! One photometric measurement: aperture sum, annulus background, flux, variance, flags.

use ndarray::{s, ArrayView2};
use serde::{Deserialize, Serialize};

use super::aperture::{aperture_sum, Aperture, ApertureSum, MaskFill};
use super::background::{annulus_background, Annulus, Background, BkgStat};
use super::flags::Flags;
use super::overlap::Method;

/// A rectangle of valid pixels, inclusive 0-based indices (e.g. one beam's strip of rows).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Region {
    /// First valid column.
    pub x_min: usize,
    /// Last valid column (inclusive).
    pub x_max: usize,
    /// First valid row.
    pub y_min: usize,
    /// Last valid row (inclusive).
    pub y_max: usize,
}

/// Default aperture radius, px (about 2 FWHM of 0.8" seeing at SOFI's 0.288"/px).
pub const DEFAULT_R_AP_PX: f64 = 6.0;
/// Default background annulus, px.
pub const DEFAULT_ANNULUS_PX: (f64, f64) = (10.0, 16.0);
/// Default clipping threshold, in standard deviations.
pub const DEFAULT_CLIP_SIGMA: f64 = 3.0;
/// Default maximum number of clipping iterations.
pub const DEFAULT_CLIP_ITERS: u32 = 5;
/// Default minimum number of annulus pixels for a trusted background.
pub const DEFAULT_MIN_SKY_PIXELS: usize = 20;
/// Default S/N under which `low_snr` is set.
pub const DEFAULT_MIN_SNR: f64 = 5.0;

/// Settings of [`measure`]. Lengths in px, levels in ADU.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PhotParams {
    /// Aperture radius, px.
    pub r_ap_px: f64,
    /// Background annulus `(r_in, r_out)`, px; None: no local background (the frame is
    /// already sky-subtracted); the per-pixel noise must then come from a variance map.
    pub annulus_px: Option<(f64, f64)>,
    /// Pixel weights of the aperture.
    pub method: Method,
    /// Treatment of bad pixels inside the aperture.
    pub mask_fill: MaskFill,
    /// Background statistic.
    pub bkg_stat: BkgStat,
    /// Clipping threshold, standard deviations.
    pub clip_sigma: f64,
    /// Maximum clipping iterations.
    pub clip_iters: u32,
    /// Fewer valid annulus pixels than this sets `annulus_contaminated`.
    pub min_sky_pixels: usize,
    /// A valid aperture pixel at or above this level sets `saturated`, ADU.
    pub saturation_adu: Option<f64>,
    /// Pixels outside this region count as off the image (aperture and annulus).
    pub valid_region: Option<Region>,
    /// Radius attributed to the other listed sources, px: `companion_overlap` is set when one
    /// lies closer than `r_ap_px + companion_radius_px`.
    pub companion_radius_px: f64,
    /// Annulus pixels within this distance of another listed source are left out of the
    /// background (0: none are, and a source whose disc of `companion_radius_px` meets the
    /// annulus sets `annulus_contaminated`).
    pub annulus_exclude_radius_px: f64,
    /// S/N threshold of `low_snr`.
    pub min_snr: f64,
    /// Gain, e/ADU; used only without a variance map, for the source shot noise `f/g` (ADU^2).
    /// None: the shot noise of the source is left out (sky-limited approximation).
    pub gain_e_per_adu: Option<f64>,
}

impl Default for PhotParams {
    fn default() -> Self {
        PhotParams {
            r_ap_px: DEFAULT_R_AP_PX,
            annulus_px: Some(DEFAULT_ANNULUS_PX),
            method: Method::Exact,
            mask_fill: MaskFill::Exclude,
            bkg_stat: BkgStat::ClippedMean,
            clip_sigma: DEFAULT_CLIP_SIGMA,
            clip_iters: DEFAULT_CLIP_ITERS,
            min_sky_pixels: DEFAULT_MIN_SKY_PIXELS,
            saturation_adu: None,
            valid_region: None,
            companion_radius_px: DEFAULT_R_AP_PX,
            annulus_exclude_radius_px: 2.0 * DEFAULT_R_AP_PX,
            min_snr: DEFAULT_MIN_SNR,
            gain_e_per_adu: None,
        }
    }
}

/// Result of [`measure`]. Flux in ADU, variance in ADU^2.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Photometry {
    /// Aperture centre x, px (full-image coordinates).
    pub x: f64,
    /// Aperture centre y, px.
    pub y: f64,
    /// Background-subtracted flux `S - A b`, ADU. NaN (with `truncated`) when no valid pixel
    /// of the aperture is on the image.
    pub flux: f64,
    /// Variance of `flux`, ADU^2 (see the module docs). NaN (with `low_snr`) when no noise
    /// estimate exists (no variance map and no annulus).
    pub variance: f64,
    /// `flux / sqrt(variance)`.
    pub snr: f64,
    /// The raw aperture sum.
    pub aperture: ApertureSum,
    /// The annulus background, when one was requested and could be measured.
    pub background: Option<Background>,
    /// Problems found.
    pub flags: Flags,
}

/// Measures the source at `(x, y)` (px, full-image coordinates) with the settings `params`.
///
/// `others`: positions of the other known sources (e.g. the binary's companion), for the
/// `companion_overlap` flag and the exclusion from the annulus. `var` (ADU^2) and `mask`
/// (nonzero = bad) are optional and have the image's shape.
///
/// ```
/// use ndarray::Array2;
/// use sofipol_pipeline::photometry::{measure, PhotParams};
/// let mut img = Array2::<f32>::from_elem((64, 64), 100.0);
/// img[[30, 31]] += 5000.0; // a one-pixel "star" on a flat sky of 100 ADU
/// let p = measure(img.view(), None, None, &PhotParams::default(), 31.0, 30.0, &[]);
/// assert!((p.flux - 5000.0).abs() < 1e-6);
/// assert!(p.flags.is_empty(), "{:?}", p.flags.names());
/// ```
pub fn measure(
    img: ArrayView2<f32>,
    var: Option<ArrayView2<f32>>,
    mask: Option<ArrayView2<u8>>,
    params: &PhotParams,
    x: f64,
    y: f64,
    others: &[(f64, f64)],
) -> Photometry {
    let (ny, nx) = img.dim();
    // Restrict everything to the valid region by slicing and shifting the coordinates.
    let (ox, oy, img, var, mask) = match params.valid_region {
        Some(reg) if nx > 0 && ny > 0 => {
            let (x0, x1) = (reg.x_min.min(nx - 1), reg.x_max.min(nx - 1).max(reg.x_min.min(nx - 1)));
            let (y0, y1) = (reg.y_min.min(ny - 1), reg.y_max.min(ny - 1).max(reg.y_min.min(ny - 1)));
            let sl = s![y0..=y1, x0..=x1];
            (
                x0 as f64,
                y0 as f64,
                img.slice_move(sl),
                var.map(|v| v.slice_move(sl)),
                mask.map(|m| m.slice_move(sl)),
            )
        }
        _ => (0.0, 0.0, img, var, mask),
    };
    let (lx, ly) = (x - ox, y - oy);
    let others_local: Vec<(f64, f64)> = others.iter().map(|&(a, b)| (a - ox, b - oy)).collect();
    let r_ap = params.r_ap_px;
    let ap = Aperture { x: lx, y: ly, r: r_ap };
    let sum = aperture_sum(img, var, mask, &ap, params.method, params.mask_fill);

    let mut flags = Flags::NONE;
    if sum.truncated() {
        flags |= Flags::TRUNCATED;
    }
    if sum.masked_area > 0.0 {
        flags |= Flags::BAD_PIXELS;
    }
    if let (Some(sat), Some(max)) = (params.saturation_adu, sum.max_value) {
        if max >= sat {
            flags |= Flags::SATURATED;
        }
    }
    let dist = |&(a, b): &(f64, f64)| ((a - lx).powi(2) + (b - ly).powi(2)).sqrt();
    if others_local.iter().any(|o| dist(o) < r_ap + params.companion_radius_px) {
        flags |= Flags::COMPANION_OVERLAP;
    }

    let background = params.annulus_px.and_then(|(r_in, r_out)| {
        let exclude: Vec<(f64, f64, f64)> = if params.annulus_exclude_radius_px > 0.0 {
            others_local
                .iter()
                .map(|&(a, b)| (a, b, params.annulus_exclude_radius_px))
                .collect()
        } else {
            Vec::new()
        };
        let ann = Annulus {
            x: lx,
            y: ly,
            r_in,
            r_out,
        };
        annulus_background(
            img,
            mask,
            &ann,
            &exclude,
            params.bkg_stat,
            params.clip_sigma,
            params.clip_iters,
        )
    });
    if let Some((r_in, r_out)) = params.annulus_px {
        match &background {
            None => flags |= Flags::ANNULUS_CONTAMINATED,
            Some(b) if b.n < params.min_sky_pixels => flags |= Flags::ANNULUS_CONTAMINATED,
            Some(_) => {}
        }
        if params.annulus_exclude_radius_px <= 0.0 {
            let rc = params.companion_radius_px;
            if others_local.iter().any(|o| {
                let d = dist(o);
                d + rc > r_in && d - rc < r_out
            }) {
                flags |= Flags::ANNULUS_CONTAMINATED;
            }
        }
    }

    let (level, level_var, sky_sigma) = match &background {
        Some(b) => (b.level, b.level_variance, Some(b.sigma)),
        None => (0.0, 0.0, None),
    };
    let (flux, variance) = if sum.area > 0.0 {
        let flux = sum.sum - sum.area * level;
        let pixel_var = match (sum.variance, sky_sigma) {
            (Some(v), _) => Some(v),
            (None, Some(s)) => {
                let shot = params.gain_e_per_adu.map_or(0.0, |g| flux.max(0.0) / g);
                Some(shot + s * s * sum.area_w2)
            }
            (None, None) => None,
        };
        (
            flux,
            pixel_var.map_or(f64::NAN, |v| v + sum.area * sum.area * level_var),
        )
    } else {
        flags |= Flags::TRUNCATED;
        (f64::NAN, f64::NAN)
    };
    let snr = flux / variance.sqrt();
    if snr.is_nan() || snr < params.min_snr {
        flags |= Flags::LOW_SNR;
    }
    Photometry {
        x,
        y,
        flux,
        variance,
        snr,
        aperture: sum,
        background,
        flags,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn star_image(n: usize, x: f64, y: f64, flux: f64, sky: f32) -> Array2<f32> {
        let mut img = Array2::<f32>::from_elem((n, n), sky);
        let mut v = img.view_mut();
        crate::photometry::model::add_gaussian(&mut v, flux, x, y, 1.3, 1.3);
        img
    }

    #[test]
    fn photometry_measure_flags() {
        let mut img = star_image(64, 30.2, 31.6, 1.0e5, 50.0);
        let mut p = PhotParams {
            saturation_adu: Some(5.0e3),
            ..PhotParams::default()
        };
        let m = measure(img.view(), None, None, &p, 30.2, 31.6, &[]);
        assert!((m.flux - 1.0e5).abs() < 1.0e5 * 1e-4, "{}", m.flux);
        assert_eq!(m.flags, Flags::SATURATED);
        p.saturation_adu = None;
        // Truncated by the image edge and by a valid region.
        let m = measure(img.view(), None, None, &p, 2.0, 31.6, &[]);
        assert!(m.flags.contains(Flags::TRUNCATED));
        let reg = Region {
            x_min: 0,
            x_max: 63,
            y_min: 0,
            y_max: 33,
        };
        let m = measure(
            img.view(),
            None,
            None,
            &PhotParams {
                valid_region: Some(reg),
                ..p
            },
            30.2,
            31.6,
            &[],
        );
        assert!(m.flags.contains(Flags::TRUNCATED));
        // The region cuts the 10-16 px annulus roughly in half: the background comes from
        // the pixels inside (~45 % of the full annulus), still more than the minimum, so
        // it is trusted and not flagged.
        let full = measure(img.view(), None, None, &p, 30.2, 31.6, &[])
            .background
            .unwrap()
            .n;
        let b = m
            .background
            .expect("background from the part of the annulus inside the region");
        let frac = b.n as f64 / full as f64;
        assert!((0.35..0.6).contains(&frac), "{} of {full}", b.n);
        assert!(!m.flags.contains(Flags::ANNULUS_CONTAMINATED), "{:?}", m.flags);
        // A region that leaves fewer than the minimum of sky pixels flags the annulus.
        let tiny = Region {
            x_min: 27,
            x_max: 33,
            y_min: 20,
            y_max: 33,
        };
        let m = measure(
            img.view(),
            None,
            None,
            &PhotParams {
                valid_region: Some(tiny),
                ..p
            },
            30.2,
            31.6,
            &[],
        );
        assert!(
            m.background.is_none_or(|b| b.n < p.min_sky_pixels),
            "{:?}",
            m.background
        );
        assert!(
            m.flags.contains(Flags::ANNULUS_CONTAMINATED | Flags::TRUNCATED),
            "{:?}",
            m.flags
        );
        // Companion: overlap, and annulus contamination only when not excluded.
        let m = measure(img.view(), None, None, &p, 30.2, 31.6, &[(38.0, 31.6)]);
        assert!(m.flags.contains(Flags::COMPANION_OVERLAP));
        assert!(!m.flags.contains(Flags::ANNULUS_CONTAMINATED));
        let q = PhotParams {
            annulus_exclude_radius_px: 0.0,
            ..p
        };
        let m = measure(img.view(), None, None, &q, 30.2, 31.6, &[(44.0, 31.6)]);
        assert!(m.flags.contains(Flags::ANNULUS_CONTAMINATED));
        assert!(!m.flags.contains(Flags::COMPANION_OVERLAP));
        // Bad pixel.
        let mut mask = Array2::<u8>::zeros((64, 64));
        mask[[31, 30]] = 1;
        let m = measure(img.view(), None, Some(mask.view()), &p, 30.2, 31.6, &[]);
        assert_eq!(m.flags, Flags::BAD_PIXELS);
        // Off the image entirely: NaN flux, flagged.
        let m = measure(img.view(), None, None, &p, -40.0, 31.6, &[]);
        assert!(m.flux.is_nan() && m.flags.contains(Flags::TRUNCATED | Flags::LOW_SNR));
        // Faint source: low S/N (the sky has no scatter, so give it some).
        for ((iy, ix), v) in img.indexed_iter_mut() {
            *v = 50.0 + if (ix + iy) % 2 == 0 { 5.0 } else { -5.0 };
        }
        let m = measure(img.view(), None, None, &p, 30.2, 31.6, &[]);
        assert!(m.flags.contains(Flags::LOW_SNR), "{:?}", m);
        // No variance map and no annulus: variance undefined, flagged.
        let m = measure(
            img.view(),
            None,
            None,
            &PhotParams { annulus_px: None, ..p },
            30.2,
            31.6,
            &[],
        );
        assert!(m.variance.is_nan() && m.flags == Flags::LOW_SNR);
    }

    /// An empty image (no rows or no columns) with a valid region: nothing to measure, so
    /// NaN flux flagged `truncated`, not a panic from slicing the region out of it.
    #[test]
    fn photometry_measure_empty_image_with_region() {
        let reg = Region {
            x_min: 0,
            x_max: 10,
            y_min: 0,
            y_max: 10,
        };
        let p = PhotParams {
            valid_region: Some(reg),
            ..PhotParams::default()
        };
        for shape in [(0, 12), (12, 0), (0, 0)] {
            let img = Array2::<f32>::zeros(shape);
            let m = measure(img.view(), None, None, &p, 5.0, 5.0, &[]);
            assert!(
                m.flux.is_nan() && m.flags.contains(Flags::TRUNCATED),
                "{shape:?}: {m:?}"
            );
        }
        // A region reaching past the image is clamped to it: the same measurement as
        // without a region.
        let img = star_image(40, 20.3, 19.6, 1.0e4, 30.0);
        let big = Region {
            x_min: 0,
            x_max: 100,
            y_min: 0,
            y_max: 70,
        };
        let plain = measure(img.view(), None, None, &PhotParams::default(), 20.3, 19.6, &[]);
        let clamped = measure(
            img.view(),
            None,
            None,
            &PhotParams {
                valid_region: Some(big),
                ..PhotParams::default()
            },
            20.3,
            19.6,
            &[],
        );
        assert_eq!(plain, clamped);
        // A region wholly beyond the image is clamped to its last row and column: the
        // aperture is cut off (truncated), nothing is read outside the image.
        let off = Region {
            x_min: 50,
            x_max: 60,
            y_min: 45,
            y_max: 60,
        };
        let m = measure(
            img.view(),
            None,
            None,
            &PhotParams {
                valid_region: Some(off),
                ..PhotParams::default()
            },
            20.3,
            19.6,
            &[],
        );
        assert!(m.flags.contains(Flags::TRUNCATED), "{m:?}");
        // A region with its origin away from (0, 0) that holds the aperture and the
        // annulus: the same measurement (positions in full-image coordinates).
        let inner = Region {
            x_min: 3,
            x_max: 38,
            y_min: 2,
            y_max: 37,
        };
        let m = measure(
            img.view(),
            None,
            None,
            &PhotParams {
                valid_region: Some(inner),
                ..PhotParams::default()
            },
            20.3,
            19.6,
            &[],
        );
        assert_eq!((m.x, m.y), (20.3, 19.6));
        assert!(
            (m.flux - plain.flux).abs() < 1e-9 * plain.flux,
            "{} vs {}",
            m.flux,
            plain.flux
        );
        assert_eq!(m.background.map(|b| b.n), plain.background.map(|b| b.n));
        assert_eq!(m.flags, plain.flags);
    }
    /// `companion_overlap` is set for another source closer than `r_ap + companion_radius`
    /// (strictly), in full-image coordinates also when the valid region's origin is not
    /// (0, 0): the other sources are shifted to the region like the star.
    #[test]
    fn companion_overlap_is_judged_in_the_region_at_the_strict_limit() {
        let img = star_image(60, 30.0, 28.0, 1.0e4, 30.0);
        let region = Region {
            x_min: 12,
            x_max: 55,
            y_min: 9,
            y_max: 50,
        };
        let p = PhotParams {
            valid_region: Some(region),
            companion_radius_px: 3.0,
            ..PhotParams::default()
        };
        let limit = p.r_ap_px + p.companion_radius_px;
        let flagged = |dx: f64| {
            measure(img.view(), None, None, &p, 30.0, 28.0, &[(30.0 + dx, 28.0)])
                .flags
                .contains(Flags::COMPANION_OVERLAP)
        };
        assert!(flagged(limit - 0.5), "inside r_ap + companion_radius");
        assert!(flagged(p.r_ap_px - p.companion_radius_px + 0.5), "well inside");
        assert!(!flagged(limit), "at exactly the limit: not closer than it");
        assert!(!flagged(limit + 0.5), "outside");
        // Along a diagonal, the distance is the Euclidean one (3-4-5 directions).
        let flagged_at = |f: f64| {
            let (dx, dy) = (-0.6 * limit * f, 0.8 * limit * f);
            measure(img.view(), None, None, &p, 30.0, 28.0, &[(30.0 + dx, 28.0 + dy)])
                .flags
                .contains(Flags::COMPANION_OVERLAP)
        };
        assert!(flagged_at(0.97) && !flagged_at(1.03));
    }

    /// Without exclusion, a listed source whose disc (radius `companion_radius_px`) meets
    /// the annulus sets `annulus_contaminated`, strictly inside its edges; so does an
    /// annulus with fewer than `min_sky_pixels` pixels (as many is enough).
    #[test]
    fn the_annulus_is_contaminated_by_a_disc_that_meets_it_or_too_few_pixels() {
        let img = star_image(80, 40.0, 40.0, 1.0e4, 40.0);
        let p = PhotParams {
            annulus_exclude_radius_px: 0.0,
            companion_radius_px: 2.0,
            ..PhotParams::default()
        };
        let (r_in, r_out) = p.annulus_px.unwrap();
        let contaminated = |others: &[(f64, f64)], p: &PhotParams| {
            measure(img.view(), None, None, p, 40.0, 40.0, others)
                .flags
                .contains(Flags::ANNULUS_CONTAMINATED)
        };
        assert!(!contaminated(&[], &p));
        // Along x: d + 2 against r_in = 10 and d - 2 against r_out = 16, strictly.
        for (d, want) in [
            (r_in - 2.1, false),
            (r_in - 2.0, false),
            (r_in - 1.9, true),
            (r_out + 1.9, true),
            (r_out + 2.0, false),
        ] {
            assert_eq!(contaminated(&[(40.0 + d, 40.0)], &p), want, "d = {d}");
        }
        // Along a diagonal (3-4-5): the Euclidean distance.
        for (d, want) in [
            (r_in - 2.2, false),
            (r_in - 1.8, true),
            (r_out + 1.8, true),
            (r_out + 2.2, false),
        ] {
            assert_eq!(
                contaminated(&[(40.0 - 0.6 * d, 40.0 + 0.8 * d)], &p),
                want,
                "diagonal d = {d}"
            );
        }
        let n = measure(img.view(), None, None, &p, 40.0, 40.0, &[])
            .background
            .unwrap()
            .n;
        let with_min = |m: usize| PhotParams { min_sky_pixels: m, ..p };
        assert!(!contaminated(&[], &with_min(n)) && contaminated(&[], &with_min(n + 1)));
    }

    /// Without a variance map, a gain adds the source's shot noise flux / g (ADU^2) to the
    /// variance.
    #[test]
    fn a_gain_adds_the_source_shot_noise() {
        let img = star_image(64, 30.0, 31.0, 2.0e4, 40.0);
        let p = PhotParams::default();
        let sky_only = measure(img.view(), None, None, &p, 30.0, 31.0, &[]);
        let g = 4.0;
        let with_gain = measure(
            img.view(),
            None,
            None,
            &PhotParams {
                gain_e_per_adu: Some(g),
                ..p
            },
            30.0,
            31.0,
            &[],
        );
        assert_eq!(with_gain.flux, sky_only.flux);
        let shot = with_gain.variance - sky_only.variance;
        assert!(
            (shot - sky_only.flux / g).abs() < 1e-6 * shot,
            "{shot} vs {}",
            sky_only.flux / g
        );
    }

    /// Annulus pixels near a listed source are left out of the background (the sample is
    /// smaller than without the source); a valid region reaching beyond the image is the
    /// image.
    #[test]
    fn the_annulus_leaves_out_the_other_sources_and_the_region_is_clamped() {
        let img = star_image(64, 30.0, 31.0, 1.0e4, 40.0);
        let p = PhotParams::default();
        let alone = measure(img.view(), None, None, &p, 30.0, 31.0, &[]);
        let with = measure(img.view(), None, None, &p, 30.0, 31.0, &[(30.0, 31.0 + 13.0)]);
        let (n_alone, n_with) = (alone.background.unwrap().n, with.background.unwrap().n);
        assert!(n_with + 20 < n_alone, "{n_with} vs {n_alone}");
        let wide = Region {
            x_min: 0,
            x_max: 1000,
            y_min: 0,
            y_max: 1000,
        };
        let in_wide = measure(
            img.view(),
            None,
            None,
            &PhotParams {
                valid_region: Some(wide),
                ..p
            },
            30.0,
            31.0,
            &[],
        );
        assert_eq!(in_wide, alone);
    }
}
