//! Field stars: every point source of the target's strips other than the binary, measured
//! with the components' own photometry (docs/photometry.md, "Field stars").
//!
//! 1. Detection, once per orientation, on the dithers stacked on the primary (each frame
//!    shifted by whole pixels by the primary's centre found in it): peaks of the 3x3 box
//!    sums of the stack whose S/N, and whose S/N above the median of a ring about them
//!    (a star's own peak, not a bump on another's wing), reach `measure.field_star_snr`.
//!    An o-strip peak is a star when an e-strip peak lies at the measured e-o offset
//!    (within [`PAIR_TOL_PX`]) with a similar flux (|o - e|/(o + e) <= [`PAIR_MAX_F`]):
//!    never the nearest peak alone. Peaks within [`COMPONENT_FWHM`] FWHM of A or B are
//!    the binary's own images and are never field stars (without a focal mask, where the
//!    "strips" are the whole detector, nor are peaks that close to A's or B's e image).
//! 2. The orientations' detections are put on the sky (separation and PA from A, as the
//!    companion's) and merged within [`GROUP_TOL_PX`]: one star, one sky position.
//! 3. Measurement, in every dither of every orientation, at the star's sky position carried
//!    to the frame by A's position in it: the components' per-frame photometry
//!    (`fluxes::measure_frame`, aperture photometry with the PSF fit's neighbours
//!    subtracted and the aperture correction) and F per dither
//!    (`fluxes::dither_value`); a dither whose star falls beyond the strips or the
//!    detector has no value (`outside_field`), one whose aperture crosses a strip or
//!    detector edge is rejected (`strip_edge`).
//! 4. Without a focal mask, the images of the other beam of every other source (field
//!    stars, A, B, fainter pairs down to [`BLEND_PEAK_SNR`]) and the stack's peaks that none
//!    explains are fitted with the star when within reach of one of its images, and make it
//!    `blended` within [`BLEND_FWHM`] FWHM (docs/photometry.md, "Field stars"); so are
//!    the sources on the star's o-e residual on the stack ([`super::residual`]), within
//!    the aperture radius plus 1 FWHM of one of its images.
use ndarray::{Array2, ArrayView2};
use sofipol_calib::frame::mask as mbits;
use sofipol_calib::profile::Beam;
use sofipol_calib::Profile;

use super::companion::Companion;
use super::fluxes::{dither_value, measure_frame, FluxSetup, PsfChoice};
use super::residual::{residual_sources, StackImage, RESIDUAL_SNR};
use super::sources::{refine, Primary};
use super::{DitherValue, SkySubtractedOrientation};
use crate::catalog::FlagCode;
use crate::stokes::model::{companion_offset_px, offset_to_sep_pa};

/// Largest distance of an e-strip peak from the o-strip peak moved by the e-o offset, px.
pub const PAIR_TOL_PX: f64 = 2.0;
/// Largest |o - e|/(o + e) of the 3x3 box sums of a star's two images (a polarization of
/// 60 %, or a peak of the other beam that is not its image).
pub const PAIR_MAX_F: f64 = 0.6;
/// A peak within this many FWHM of A or B is that component's image.
pub const COMPONENT_FWHM: f64 = 1.5;
/// Detections of two orientations within this distance on the sky (in pixels) are one star.
pub const GROUP_TOL_PX: f64 = 2.0;
/// A field star with another source (field star or component) within this many FWHM is
/// `blended`: the wings share apertures and annuli.
pub const BLEND_FWHM: f64 = 3.0;
/// Without a focal mask, the S/N (as [`MeasureParams::field_star_snr`]'s) down to which
/// every peak of a stack is a source that can fall on a field star's images, paired or not
/// (a star whose other image is off the detector, too faint or too polarized to pair).
///
/// [`MeasureParams::field_star_snr`]: super::MeasureParams::field_star_snr
pub const BLEND_PEAK_SNR: f64 = 5.0;

/// One field star as measured: where it is and F per dither.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FieldMeasured {
    /// Separation from A, arcsec.
    pub sep_arcsec: f64,
    /// Position angle from A, deg east of north, [0, 360).
    pub pa_deg: f64,
    /// Its o image in the first frame where the primary was found (px of the reduced rows).
    pub xy_px: (f64, f64),
    /// Orientations at which it was detected.
    pub n_detected: usize,
    /// Largest detection S/N (3x3 box of the stack above its ring).
    pub detection_snr: f64,
    /// The sources within [`BLEND_FWHM`] FWHM: `field star at 1.2"`, `A at 1.0"`.
    pub blended_with: Vec<String>,
    /// Per orientation, per dither.
    pub dithers: Vec<Vec<DitherValue>>,
    /// Dithers whose aperture crosses a strip or detector edge.
    pub n_edge: usize,
    /// Dithers where the star is beyond the strips or the detector.
    pub n_outside: usize,
}

/// A peak pair found on one orientation's stack, in the reference frame's pixels.
#[derive(Debug, Clone, Copy)]
struct Detection {
    /// East and north offsets from A on the sky, arcsec.
    en: (f64, f64),
    snr: f64,
}

/// The geometry of the strips in the reduced rows.
#[derive(Debug, Clone, Copy)]
struct Strips {
    o: [usize; 2],
    e: [usize; 2],
    nx: usize,
    /// No focal mask: both images of every source on the whole detector.
    unmasked: bool,
}

impl Strips {
    /// Whether (x, y) lies inside strip `rows` and the detector with a margin `m`, px.
    fn inside(&self, rows: [usize; 2], (x, y): (f64, f64), m: f64) -> bool {
        x - m >= 0.0 && x + m <= self.nx as f64 - 1.0 && y - m >= rows[0] as f64 && y + m <= rows[1] as f64 - 1.0
    }
}

/// Detect and measure every field star of a sequence (see the module documentation).
/// `setup` is the components' photometry; `eo` the measured e-o offset.
pub fn measure_field_stars(
    orients: &[SkySubtractedOrientation],
    primary: &Primary,
    companion: &Companion,
    setup: &FluxSetup,
    profile: &Profile,
) -> Vec<FieldMeasured> {
    let g = &profile.geometry;
    let scale = setup.scale_arcsec_per_px;
    let fwhm = setup.choice.fwhm_px;
    let Some(nx) = orients.first().and_then(|o| o.frames.first()).map(|f| f.shape().1) else {
        return Vec::new();
    };
    let strips = Strips {
        o: g.target_rows(Beam::Ordinary),
        e: g.target_rows(Beam::Extraordinary),
        nx,
        unmasked: !g.has_mask(),
    };
    // B's sky position from A (arcsec east, north), when found.
    let b_en = companion.geometry.map(|(sep, pa)| en_of(sep, pa));
    let mut detections: Vec<Detection> = Vec::new();
    // Without a focal mask: the fainter pairs, and per orientation every peak of its stack
    // (px from A).
    let mut faint: Vec<Detection> = Vec::new();
    let mut all_peaks: Vec<Vec<(f64, f64)>> = Vec::new();
    // Without a focal mask, each orientation's stack (for the o-e residuals).
    let mut stacks: Vec<Option<Stack>> = Vec::new();
    for (k, o) in orients.iter().enumerate() {
        let rel_a = companion.found[k].map(|p| p.a).unwrap_or((0.0, 0.0));
        let (found, fainter, peaks, st) = detect_orientation(o, &primary.centres[k], rel_a, b_en, &strips, setup);
        detections.extend(found);
        faint.extend(fainter);
        all_peaks.push(peaks);
        stacks.push(st.filter(|_| strips.unmasked));
    }
    let groups = group(&detections, GROUP_TOL_PX * scale);
    // The fainter sources that are not field stars (nor the binary's).
    let faint: Vec<(String, (f64, f64))> = group(&faint, GROUP_TOL_PX * scale)
        .into_iter()
        .filter(|f| {
            let own = (COMPONENT_FWHM * fwhm).max(3.0) * scale;
            !groups
                .iter()
                .map(|g| g.en)
                .chain(std::iter::once((0.0, 0.0)))
                .chain(b_en)
                .any(|e| (e.0 - f.en.0).hypot(e.1 - f.en.1) < own.max(GROUP_TOL_PX * scale))
        })
        .map(|f| ("faint source".to_string(), f.en))
        .collect();
    let mut stars: Vec<FieldMeasured> = groups
        .iter()
        .map(|gr| {
            let (sep, pa) = sep_pa_of(gr.en);
            FieldMeasured {
                sep_arcsec: sep,
                pa_deg: pa,
                xy_px: (f64::NAN, f64::NAN),
                n_detected: gr.n,
                detection_snr: gr.snr,
                blended_with: Vec::new(),
                dithers: Vec::new(),
                n_edge: 0,
                n_outside: 0,
            }
        })
        .collect();
    // Neighbours: the other field stars and the components, on the sky.
    let mut sources: Vec<(String, (f64, f64))> = vec![("A".into(), (0.0, 0.0))];
    if let Some(b) = b_en {
        sources.push(("B".into(), b));
    }
    let blend_arcsec = BLEND_FWHM * fwhm * scale;
    let reach_arcsec = (setup.params.annulus_px(fwhm).1 + fwhm) * scale;
    let ens: Vec<(f64, f64)> = groups.iter().map(|g| g.en).collect();
    for (i, s) in stars.iter_mut().enumerate() {
        let me = ens[i];
        let mut neighbours: Vec<(f64, f64)> = Vec::new();
        let others: Vec<(String, (f64, f64))> = sources
            .iter()
            .cloned()
            .chain(
                ens.iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, e)| ("field star".to_string(), *e)),
            )
            .chain(faint.iter().cloned())
            .collect();
        for (name, en) in &others {
            let d = (en.0 - me.0).hypot(en.1 - me.1);
            if d < blend_arcsec {
                s.blended_with.push(format!("{name} at {d:.1}\""));
            }
            if d < reach_arcsec {
                neighbours.push(*en);
            }
        }
        // Without a focal mask every other source's e image lies among the o images and its
        // o image among the e images: those fall on this star's images too.
        let cross = if strips.unmasked { others.as_slice() } else { &[] };
        measure_star(
            s,
            me,
            &neighbours,
            cross,
            &all_peaks,
            &stacks,
            orients,
            primary,
            companion,
            &strips,
            setup,
        );
    }
    stars
}

/// Where the other beam's image of another source falls near a star's images, in one
/// orientation: the place in the star's o beam (offset from A, px) of an image that falls
/// on the star's o image (another source's e image) or, moved back by the e-o offset `eo`,
/// on its e image (another source's o image). `d` is the star's o image and `dj` the other
/// source's, both offsets from A, px. Returns (the place, o-beam image) and (the place,
/// e-beam image); each image is `d`'s neighbour at the place's distance from `d`.
fn cross_images(dj: (f64, f64), eo: (f64, f64)) -> [((f64, f64), Beam); 2] {
    [
        ((dj.0 + eo.0, dj.1 + eo.1), Beam::Ordinary),
        ((dj.0 - eo.0, dj.1 - eo.1), Beam::Extraordinary),
    ]
}

/// Measure one field star at sky offset `me` from A (arcsec east, north) in every dither,
/// its `neighbours` (sky offsets) fitted and subtracted with it. `cross` (named sky
/// offsets; empty with a focal mask) are the other sources whose images of the other beam
/// may fall on this star's: at each orientation those within reach of one of its images
/// are fitted and subtracted too (a source of the fit placed so that its image in that
/// beam is the other source's, [`cross_images`]), and one within [`BLEND_FWHM`] FWHM
/// makes the star `blended` (the closest approach over the orientations is reported).
/// `peaks` (per orientation, px from A; empty with a focal mask) are every peak of the
/// orientation's stack: one near one of the star's images that none of those sources
/// explains (within a FWHM) is a source all the same, fitted and subtracted, and blending
/// within [`BLEND_FWHM`] FWHM.
#[allow(clippy::too_many_arguments)]
fn measure_star(
    s: &mut FieldMeasured,
    me: (f64, f64),
    neighbours: &[(f64, f64)],
    cross: &[(String, (f64, f64))],
    peaks: &[Vec<(f64, f64)>],
    stacks: &[Option<Stack>],
    orients: &[SkySubtractedOrientation],
    primary: &Primary,
    companion: &Companion,
    strips: &Strips,
    setup: &FluxSetup,
) {
    let scale = setup.scale_arcsec_per_px;
    let fwhm = setup.choice.fwhm_px;
    let eo = setup.eo_px;
    // The edge margin: the aperture at the median FWHM, and 2 px for a wider frame's.
    let margin = setup.params.aperture_radius_px(fwhm) + 2.0;
    let px = |en: (f64, f64), posang: f64| {
        let (sep, pa) = sep_pa_of(en);
        companion_offset_px(sep, pa, posang, scale)
    };
    let reach_px = setup.params.annulus_px(fwhm).1 + fwhm;
    // The closest approach of each other source's image of the other beam: (index in
    // `cross`, beam of the star's image it falls on) -> px.
    let mut closest: Vec<((usize, Beam), f64)> = Vec::new();
    // The same for the peaks no source explains, per beam of the star's image.
    let mut unexplained: [f64; 2] = [f64::INFINITY; 2];
    // The same for the sources of the o-e residual no source explains (px, S/N).
    let mut on_residual: [(f64, f64); 2] = [(f64::INFINITY, 0.0); 2];
    let residual_radius = setup.params.aperture_radius_px(fwhm) + fwhm;
    for (k, o) in orients.iter().enumerate() {
        let rel_a = companion.found[k].map(|p| p.a).unwrap_or((0.0, 0.0));
        let d = px(me, o.posang_deg);
        let mut dn: Vec<(f64, f64)> = neighbours.iter().map(|&n| px(n, o.posang_deg)).collect();
        for (j, (_, en)) in cross.iter().enumerate() {
            for (q, beam) in cross_images(px(*en, o.posang_deg), eo) {
                let r = (q.0 - d.0).hypot(q.1 - d.1);
                if r < BLEND_FWHM * fwhm {
                    match closest.iter_mut().find(|(key, _)| *key == (j, beam)) {
                        Some((_, best)) => *best = best.min(r),
                        None => closest.push(((j, beam), r)),
                    }
                }
                // Fitted with the star unless another source of the fit is already there
                // (two sources of the fit within a FWHM are one blend of light).
                let taken = std::iter::once(&d)
                    .chain(dn.iter())
                    .any(|p| (p.0 - q.0).hypot(p.1 - q.1) < fwhm);
                if r < reach_px && !taken {
                    dn.push(q);
                }
            }
        }
        for p in peaks.get(k).into_iter().flatten() {
            for (bi, shift) in [(0.0, 0.0), eo].into_iter().enumerate() {
                // Where a source of the fit must be for its image in this beam to be `p`.
                let q = (p.0 - shift.0, p.1 - shift.1);
                let r = (q.0 - d.0).hypot(q.1 - d.1);
                let explained = std::iter::once(&d)
                    .chain(dn.iter())
                    .any(|e| (e.0 - q.0).hypot(e.1 - q.1) < fwhm);
                if r >= reach_px || explained {
                    continue;
                }
                if r < BLEND_FWHM * fwhm {
                    unexplained[bi] = unexplained[bi].min(r);
                }
                dn.push(q);
            }
        }
        // Without a focal mask, the sources on the o-e residual of the star's images on
        // the stack that no source of the fit explains (within a FWHM): fitted with the
        // star (unless within a FWHM of it, where they cannot be told from it), and each
        // makes it `blended`, within reach of its aperture's light.
        if let Some(st) = stacks.get(k).and_then(Option::as_ref) {
            let a_st = (st.centre.0 + rel_a.0, st.centre.1 + rel_a.1);
            let img = StackImage {
                mean: st.mean.view(),
                var: st.var.view(),
                bad: st.bad.view(),
            };
            let xo = (a_st.0 + d.0, a_st.1 + d.1);
            for src in residual_sources(&img, xo, eo, fwhm, residual_radius, RESIDUAL_SNR) {
                let (bi, shift) = match src.beam {
                    Beam::Ordinary => (0, (0.0, 0.0)),
                    Beam::Extraordinary => (1, eo),
                };
                let q = (src.xy.0 - shift.0 - a_st.0, src.xy.1 - shift.1 - a_st.1);
                if dn.iter().any(|e| (e.0 - q.0).hypot(e.1 - q.1) < fwhm) {
                    continue;
                }
                if src.r_px < on_residual[bi].0 {
                    on_residual[bi] = (src.r_px, src.snr);
                }
                if (q.0 - d.0).hypot(q.1 - d.1) >= fwhm {
                    dn.push(q);
                }
            }
        }
        let far = dn.iter().map(|n| (n.0 - d.0).hypot(n.1 - d.1)).fold(0.0, f64::max);
        let choice = PsfChoice {
            use_psf: false,
            elliptical: false,
            sep_px: far,
            ..*setup.choice
        };
        let fs = FluxSetup {
            choice: &choice,
            seeing: false,
            ..*setup
        };
        let mut values = Vec::with_capacity(o.frames.len());
        for (f, c) in o.frames.iter().zip(&primary.centres[k]) {
            let Some(c) = c else {
                values.push(DitherValue::missing(FlagCode::PrimaryNotFound.name()));
                continue;
            };
            let a = (c.0 + rel_a.0, c.1 + rel_a.1);
            let xo = (a.0 + d.0, a.1 + d.1);
            let xe = (xo.0 + eo.0, xo.1 + eo.1);
            if s.xy_px.0.is_nan() {
                s.xy_px = xo;
            }
            if !(strips.inside(strips.o, xo, 0.0) && strips.inside(strips.e, xe, 0.0)) {
                s.n_outside += 1;
                values.push(DitherValue::missing(FlagCode::OutsideField.name()));
                continue;
            }
            let edge = !(strips.inside(strips.o, xo, margin) && strips.inside(strips.e, xe, margin));
            let mut stars = vec![xo];
            stars.extend(dn.iter().map(|n| (a.0 + n.0, a.1 + n.1)));
            let (results, cov) = measure_frame(f, &stars, &fs);
            let mut v = dither_value(results[0].stars[0], results[1].stars[0], cov[0]);
            if edge {
                s.n_edge += 1;
                let why = FlagCode::StripEdge.name();
                v.rejected = Some(match v.rejected.take() {
                    Some(r) => format!("{r},{why}"),
                    None => why.to_string(),
                });
            }
            values.push(v);
        }
        s.dithers.push(values);
    }
    for ((j, beam), r) in closest {
        let (theirs, mine) = match beam {
            Beam::Ordinary => ("e", "o"),
            Beam::Extraordinary => ("o", "e"),
        };
        s.blended_with.push(format!(
            "{}'s {theirs} image at {:.1}\" from the {mine} image",
            cross[j].0,
            r * scale
        ));
    }
    for (r, mine) in unexplained.into_iter().zip(["o", "e"]) {
        if r.is_finite() {
            s.blended_with.push(format!(
                "an unpaired source at {:.1}\" from the {mine} image",
                r * scale
            ));
        }
    }
    for ((r, snr), mine) in on_residual.into_iter().zip(["o", "e"]) {
        if r.is_finite() {
            s.blended_with.push(format!(
                "a source on the o-e residual at {:.1}\" from the {mine} image (S/N {snr:.1})",
                r * scale
            ));
        }
    }
}

/// East and north offsets (arcsec) of separation `sep` (arcsec) at PA `pa` (deg).
fn en_of(sep: f64, pa: f64) -> (f64, f64) {
    let r = pa.to_radians();
    (sep * r.sin(), sep * r.cos())
}

/// Separation (arcsec) and PA (deg, [0, 360)) of east and north offsets (arcsec).
fn sep_pa_of(en: (f64, f64)) -> (f64, f64) {
    (en.0.hypot(en.1), en.0.atan2(en.1).to_degrees().rem_euclid(360.0))
}

/// Detections of several orientations merged into one star.
#[derive(Debug, Clone, Copy)]
struct Group {
    en: (f64, f64),
    snr: f64,
    n: usize,
    w: f64,
}

/// Merge detections within `tol` arcsec of a group's S/N-weighted mean position; the
/// groups in decreasing order of their best S/N (the catalog's F1, F2, ...).
fn group(dets: &[Detection], tol: f64) -> Vec<Group> {
    let mut order: Vec<&Detection> = dets.iter().collect();
    order.sort_by(|a, b| b.snr.total_cmp(&a.snr));
    let mut groups: Vec<Group> = Vec::new();
    for d in order {
        match groups
            .iter_mut()
            .find(|g| (g.en.0 - d.en.0).hypot(g.en.1 - d.en.1) <= tol)
        {
            Some(g) => {
                let w = g.w + d.snr;
                g.en = ((g.en.0 * g.w + d.en.0 * d.snr) / w, (g.en.1 * g.w + d.en.1 * d.snr) / w);
                g.w = w;
                g.n += 1;
            }
            None => groups.push(Group {
                en: d.en,
                snr: d.snr,
                n: 1,
                w: d.snr,
            }),
        }
    }
    groups
}

/// The mask bits that leave a pixel out of the detection stack: defects, cosmic rays and
/// the focal mask, not saturation (a saturated core left out would leave a hole whose rim
/// peaks in several places; kept, it is one plateau, and the photometry rejects it).
const STACK_SKIP: u8 = mbits::BAD | mbits::COSMIC | mbits::OFF_STRIP;

/// The stack of one orientation's frames registered on the first frame where the primary
/// was found (whole-pixel shifts by the primary's centres).
struct Stack {
    /// Mean of the usable pixels ([`STACK_SKIP`]), 0 where there is none.
    mean: Array2<f32>,
    /// Frames that gave each pixel.
    n: Array2<u16>,
    /// 1 where no frame gave a usable pixel.
    bad: Array2<u8>,
    /// Without a focal mask, the variance of each pixel of the mean, ADU^2: the frames'
    /// variance planes (the sky's, `var_pixel` over `n`, when a frame has none); empty
    /// with a mask.
    var: Array2<f32>,
    /// The median variance of one frame's pixel (the sky's), ADU^2: a pixel of the stack
    /// has this over `n` (the detection threshold is the sky's noise, as SExtractor's).
    var_pixel: f32,
    /// The primary's centre in the reference frame, px.
    centre: (f64, f64),
}

/// [`Stack`] of orientation `o`, with its variance plane when `with_var`; None when the
/// primary was found in no frame. Row slices, no per-pixel index checks: it runs on every
/// orientation of every target.
fn stack(o: &SkySubtractedOrientation, centres: &[Option<(f64, f64)>], with_var: bool) -> Option<Stack> {
    let r = centres.iter().position(Option::is_some)?;
    let cr = centres[r]?;
    let (ny, nx) = o.frames[r].shape();
    let mut sum = vec![0f32; ny * nx];
    let mut n = vec![0u16; ny * nx];
    let mut variances: Vec<f32> = Vec::new();
    // The sum of the frames' variances, and whether every frame had a variance plane.
    let mut vsum = if with_var { vec![0f32; ny * nx] } else { Vec::new() };
    let mut all_var = with_var;
    for (f, c) in o.frames.iter().zip(centres) {
        let Some(c) = c else { continue };
        if f.shape() != (ny, nx) {
            continue;
        }
        let (dx, dy) = ((c.0 - cr.0).round() as i64, (c.1 - cr.1).round() as i64);
        let data = f.data.as_standard_layout();
        let mask = f.mask.as_standard_layout();
        let var = f.variance.as_ref().filter(|_| with_var).map(|v| v.as_standard_layout());
        all_var &= var.is_some();
        let var = var.as_ref().and_then(|v| v.as_slice());
        let (Some(d), Some(m)) = (data.as_slice(), mask.as_slice()) else {
            continue;
        };
        let (x0, x1) = ((-dx).max(0) as usize, (nx as i64 - dx).clamp(0, nx as i64) as usize);
        if x1 <= x0 {
            continue;
        }
        for y in 0..ny {
            let ys = y as i64 + dy;
            if ys < 0 || ys >= ny as i64 {
                continue;
            }
            let so = ys as usize * nx + (x0 as i64 + dx) as usize;
            let len = x1 - x0;
            let (src, msk) = (&d[so..so + len], &m[so..so + len]);
            let dst = &mut sum[y * nx + x0..y * nx + x1];
            let cnt = &mut n[y * nx + x0..y * nx + x1];
            for i in 0..len {
                let ok = msk[i] & STACK_SKIP == 0 && src[i].is_finite();
                dst[i] += if ok { src[i] } else { 0.0 };
                cnt[i] += u16::from(ok);
            }
            if let Some(v) = var {
                let vsrc = &v[so..so + len];
                let vdst = &mut vsum[y * nx + x0..y * nx + x1];
                for i in 0..len {
                    if msk[i] & STACK_SKIP == 0 && src[i].is_finite() {
                        vdst[i] += vsrc[i];
                    }
                }
            }
        }
        // The sky's variance: the median of a sparse sample of this frame's pixels.
        if let Some(v) = f.variance.as_ref() {
            let mut sample: Vec<f32> = v
                .iter()
                .step_by(97)
                .copied()
                .filter(|x| x.is_finite() && *x > 0.0)
                .collect();
            if !sample.is_empty() {
                let mid = sample.len() / 2;
                let (_, med, _) = sample.select_nth_unstable_by(mid, f32::total_cmp);
                variances.push(*med);
            }
        }
    }
    for (s, &k) in sum.iter_mut().zip(&n) {
        if k > 0 {
            *s /= k as f32;
        }
    }
    let var_pixel = if variances.is_empty() {
        // No variance plane: the scatter of the stack's pixels about their median (MAD).
        let mut v: Vec<f32> = sum.iter().step_by(13).copied().collect();
        let mid = v.len() / 2;
        let med = *v.select_nth_unstable_by(mid, f32::total_cmp).1;
        let mut dev: Vec<f32> = v.iter().map(|x| (x - med).abs()).collect();
        let mad = *dev.select_nth_unstable_by(mid, f32::total_cmp).1;
        let k = n.iter().copied().max().unwrap_or(1).max(1) as f32;
        (1.4826 * mad).powi(2) * k
    } else {
        variances.sort_by(f32::total_cmp);
        variances[variances.len() / 2]
    };
    let var = if !with_var {
        Array2::zeros((0, 0))
    } else if all_var {
        let v: Vec<f32> = vsum
            .iter()
            .zip(&n)
            .map(|(s, &k)| if k > 0 { s / (k as f32 * k as f32) } else { f32::NAN })
            .collect();
        Array2::from_shape_vec((ny, nx), v).ok()?
    } else {
        Array2::from_shape_vec((ny, nx), n.iter().map(|&k| var_pixel / k.max(1) as f32).collect()).ok()?
    };
    let n = Array2::from_shape_vec((ny, nx), n).ok()?;
    Some(Stack {
        mean: Array2::from_shape_vec((ny, nx), sum).ok()?,
        bad: n.mapv(|k| u8::from(k == 0)),
        n,
        var_pixel,
        centre: cr,
        var,
    })
}

/// A peak of one strip of the stack: position (refined), 3x3 box sum, S/N above its ring.
#[derive(Debug, Clone, Copy)]
struct Peak {
    xy: (f64, f64),
    sum: f64,
    snr: f64,
}

/// The peaks of the stack in rows `rows` and columns `cols` (see the module
/// documentation). The 3x3 box sums by two passes of running sums over the window and a
/// 2 px margin; the noise of a box the sky's (9 var_pixel / n).
fn peaks(st: &Stack, rows: [usize; 2], cols: [usize; 2], fwhm: f64, snr_min: f64) -> Vec<Peak> {
    let img = st.mean.view();
    let (ny, nx) = img.dim();
    // The window keeps 3 px from the image's edges (its margin's boxes stay inside).
    let (y0, y1) = (rows[0].max(3), rows[1].min(ny).saturating_sub(3));
    let (x0, x1) = (cols[0].max(3), cols[1].min(nx).saturating_sub(3));
    if y1 <= y0 || x1 <= x0 || !(st.var_pixel > 0.0) {
        return Vec::new();
    }
    // Box sums over the window and a 2 px margin: local coordinates (y - y0 + 2, x - x0 + 2).
    let (wy, wx) = (y1 - y0 + 4, x1 - x0 + 4);
    let mut row3 = Array2::<f32>::zeros((wy + 2, wx));
    for ly in 0..wy + 2 {
        let src = img.row(y0 + ly - 3);
        let src = src.as_slice().expect("standard layout");
        let dst = row3.row_mut(ly).into_slice().expect("standard layout");
        for (lx, d) in dst.iter_mut().enumerate() {
            let c = x0 - 2 + lx;
            *d = src[c - 1] + src[c] + src[c + 1];
        }
    }
    let mut bs = Array2::<f32>::zeros((wy, wx));
    for ly in 0..wy {
        let (a, b, c) = (row3.row(ly), row3.row(ly + 1), row3.row(ly + 2));
        let dst = bs.row_mut(ly).into_slice().expect("standard layout");
        for lx in 0..wx {
            dst[lx] = a[lx] + b[lx] + c[lx];
        }
    }
    let box_noise = |y: usize, x: usize| (9.0 * st.var_pixel / st.n[[y, x]].max(1) as f32).sqrt();
    let (r_in, r_out) = ((1.5 * fwhm).max(3.0), (2.5 * fwhm).max(5.0));
    let ro = r_out.ceil() as i64;
    let mut out = Vec::new();
    for ly in 2..wy - 2 {
        let y = y0 + ly - 2;
        let row = bs.row(ly);
        let row = row.as_slice().expect("standard layout");
        for (lx, &s) in row.iter().enumerate().take(wx - 2).skip(2) {
            if !(s > 0.0) {
                continue;
            }
            let x = x0 + lx - 2;
            if st.n[[y, x]] == 0 {
                continue;
            }
            let noise = box_noise(y, x);
            if s < snr_min as f32 * noise {
                continue;
            }
            // A local maximum of the 5x5 neighbourhood (ties: the first in row-major order).
            let mut is_max = true;
            'n: for j in ly - 2..=ly + 2 {
                for i in lx - 2..=lx + 2 {
                    let o = bs[[j, i]];
                    if (j, i) != (ly, lx) && (o > s || (o == s && (j, i) < (ly, lx))) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if !is_max {
                continue;
            }
            // Its S/N above the median of the ring about it: a star's own peak, not noise
            // on the wing of a brighter one.
            let mut ring = Vec::new();
            for j in (y as i64 - ro).max(0)..=(y as i64 + ro).min(ny as i64 - 1) {
                for i in (x as i64 - ro).max(0)..=(x as i64 + ro).min(nx as i64 - 1) {
                    let r = ((i - x as i64) as f64).hypot((j - y as i64) as f64);
                    let (ju, iu) = (j as usize, i as usize);
                    if r >= r_in && r <= r_out && st.bad[[ju, iu]] == 0 {
                        ring.push(img[[ju, iu]]);
                    }
                }
            }
            if ring.len() < 8 {
                continue;
            }
            let mid = ring.len() / 2;
            let (_, med, _) = ring.select_nth_unstable_by(mid, f32::total_cmp);
            let prominence = s as f64 - 9.0 * *med as f64;
            let snr = prominence / noise as f64;
            if snr < snr_min {
                continue;
            }
            let xy = refine(img, st.bad.view(), x as f64, y as f64, fwhm, 2.0).unwrap_or((x as f64, y as f64));
            out.push(Peak { xy, sum: s as f64, snr });
        }
    }
    merge_plateaus(out, bs.view(), (y0 - 2, x0 - 2), fwhm)
}

/// Peaks of one source: a fainter peak within [`BLEND_FWHM`] FWHM of a brighter one with no
/// dip between them (the box sums along the segment never fall below [`DIP`] of the fainter
/// peak's; masked boxes skipped; `bs` the box sums of the window whose (0, 0) is the
/// stack's `origin` (y, x)) is the same source (a saturated plateau, a noisy core) and
/// is dropped. Two stars at 2 FWHM or more have a dip far deeper than that.
fn merge_plateaus(mut peaks: Vec<Peak>, bs: ArrayView2<f32>, origin: (usize, usize), fwhm: f64) -> Vec<Peak> {
    /// Fraction of the fainter peak's box sum that the segment must fall below for two peaks
    /// to be two sources.
    const DIP: f64 = 0.6;
    peaks.sort_by(|a, b| b.sum.total_cmp(&a.sum));
    let (ny, nx) = bs.dim();
    let mut kept: Vec<Peak> = Vec::new();
    for q in peaks {
        let same = kept.iter().any(|p| {
            let d = (p.xy.0 - q.xy.0).hypot(p.xy.1 - q.xy.1);
            if d > BLEND_FWHM * fwhm {
                return false;
            }
            let n = (2.0 * d).ceil().max(1.0) as usize;
            (0..=n).all(|k| {
                let t = k as f64 / n as f64;
                let (x, y) = (q.xy.0 + t * (p.xy.0 - q.xy.0), q.xy.1 + t * (p.xy.1 - q.xy.1));
                let (xi, yi) = (x.round() as i64 - origin.1 as i64, y.round() as i64 - origin.0 as i64);
                if xi < 0 || yi < 0 || xi as usize >= nx || yi as usize >= ny {
                    return true;
                }
                let v = bs[[yi as usize, xi as usize]] as f64;
                !(v.is_finite() && v > f64::from(f32::MIN)) || v >= DIP * q.sum
            })
        });
        if !same {
            kept.push(q);
        }
    }
    kept
}

/// What one orientation's stack gives: the field stars, the fainter pairs, every peak (px
/// from A) and the stack ([`detect_orientation`]).
type OrientationSources = (Vec<Detection>, Vec<Detection>, Vec<(f64, f64)>, Option<Stack>);

/// The field stars of one orientation on its stack: o-strip peaks paired with their e-strip
/// images, the binary's own images left out; as sky offsets from A. Without a focal mask
/// (both empty with one), also the pairs down to [`BLEND_PEAK_SNR`] (sky offsets from A)
/// and every peak of the stack down to it, px from A; and the stack (None when the primary
/// was found in no frame).
fn detect_orientation(
    o: &SkySubtractedOrientation,
    centres: &[Option<(f64, f64)>],
    rel_a: (f64, f64),
    b_en: Option<(f64, f64)>,
    strips: &Strips,
    setup: &FluxSetup,
) -> OrientationSources {
    let Some(st) = stack(o, centres, strips.unmasked) else {
        return (Vec::new(), Vec::new(), Vec::new(), None);
    };
    let cr = st.centre;
    let scale = setup.scale_arcsec_per_px;
    let fwhm = setup.choice.fwhm_px;
    let snr_min = setup.params.field_star_snr;
    let op = peaks(&st, strips.o, [0, strips.nx], fwhm, snr_min);
    let a = (cr.0 + rel_a.0, cr.1 + rel_a.1);
    let all_peaks: Vec<(f64, f64)> = if strips.unmasked {
        let ny = st.mean.dim().0;
        peaks(&st, [0, ny], [0, strips.nx], fwhm, BLEND_PEAK_SNR.min(snr_min))
            .into_iter()
            .map(|p| (p.xy.0 - a.0, p.xy.1 - a.1))
            .collect()
    } else {
        Vec::new()
    };
    let mut components = vec![a];
    if let Some(b) = b_en {
        let (sep, pa) = sep_pa_of(b);
        let d = companion_offset_px(sep, pa, o.posang_deg, scale);
        components.push((a.0 + d.0, a.1 + d.1));
    }
    if strips.unmasked {
        // Without a focal mask the components' e images lie among the o peaks too: they
        // are the binary's own images, never field stars.
        let eo = setup.eo_px;
        components.extend(components.clone().iter().map(|c| (c.0 + eo.0, c.1 + eo.1)));
    }
    let paired = |op: &[Peak], snr_min: f64| pair_peaks(&st, op, &components, a, o.posang_deg, strips, setup, snr_min);
    let out = paired(&op, snr_min);
    // Without a focal mask, the fainter pairs too: sources whose images can fall on a
    // field star's (not field stars themselves).
    let faint = if strips.unmasked && BLEND_PEAK_SNR < snr_min {
        let ny = st.mean.dim().0;
        paired(
            &peaks(&st, [0, ny], [0, strips.nx], fwhm, BLEND_PEAK_SNR),
            BLEND_PEAK_SNR,
        )
    } else {
        Vec::new()
    };
    (out, faint, all_peaks, Some(st))
}

/// The o-strip peaks `op` of stack `st` paired with their e-strip images at S/N
/// `snr_min` (see the module documentation), those within [`COMPONENT_FWHM`] FWHM of
/// `components` (the binary's images) left out; as sky offsets from A at `a` (px) at
/// rotator angle `posang`, deg.
#[allow(clippy::too_many_arguments)]
fn pair_peaks(
    st: &Stack,
    op: &[Peak],
    components: &[(f64, f64)],
    a: (f64, f64),
    posang: f64,
    strips: &Strips,
    setup: &FluxSetup,
    snr_min: f64,
) -> Vec<Detection> {
    let scale = setup.scale_arcsec_per_px;
    let fwhm = setup.choice.fwhm_px;
    let own = (COMPONENT_FWHM * fwhm).max(3.0);
    let mut order: Vec<&Peak> = op.iter().collect();
    order.sort_by(|p, q| q.snr.total_cmp(&p.snr));
    let mut used: Vec<(f64, f64)> = Vec::new();
    let mut out = Vec::new();
    for p in order {
        if components.iter().any(|c| (c.0 - p.xy.0).hypot(c.1 - p.xy.1) < own) {
            continue;
        }
        let want = (p.xy.0 + setup.eo_px.0, p.xy.1 + setup.eo_px.1);
        // The e image: a peak of the e strip (searched about the expected place only) at
        // the e-o offset AND of a similar flux; the closest such, each used once.
        let reach = PAIR_TOL_PX.ceil() as usize + 3;
        let (wx, wy) = (want.0.round().max(0.0) as usize, want.1.round().max(0.0) as usize);
        let rows = [
            wy.saturating_sub(reach).max(strips.e[0]),
            (wy + reach + 1).min(strips.e[1]),
        ];
        let cols = [wx.saturating_sub(reach), wx + reach + 1];
        let best = peaks(st, rows, cols, fwhm, snr_min)
            .into_iter()
            .filter(|e| !used.iter().any(|u| (u.0 - e.xy.0).hypot(u.1 - e.xy.1) < 0.5))
            .map(|e| (e, (e.xy.0 - want.0).hypot(e.xy.1 - want.1)))
            .filter(|(e, d)| *d <= PAIR_TOL_PX && ((p.sum - e.sum) / (p.sum + e.sum)).abs() <= PAIR_MAX_F)
            .min_by(|x, y| x.1.total_cmp(&y.1));
        let Some((e, _)) = best else { continue };
        used.push(e.xy);
        let (sep, pa) = offset_to_sep_pa(p.xy.0 - a.0, p.xy.1 - a.1, posang, scale);
        out.push(Detection {
            en: en_of(sep, pa),
            snr: p.snr.min(e.snr),
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sky offsets of [`en_of`] and [`sep_pa_of`] invert each other, and agree with the
    /// companion's convention ([`offset_to_sep_pa`] of [`companion_offset_px`]).
    #[test]
    fn sky_offsets_round_trip_in_the_companions_convention() {
        for (sep, pa) in [(10.0, 0.0), (33.3, 91.0), (120.0, 250.5), (5.0, 359.0)] {
            let (s, p) = sep_pa_of(en_of(sep, pa));
            assert!((s - sep).abs() < 1e-9 && (p - pa).abs() < 1e-9, "{sep} {pa}: {s} {p}");
            for posang in [0.0, 45.0, 90.0, 135.0] {
                let d = companion_offset_px(sep, pa, posang, 0.288);
                let (s2, p2) = offset_to_sep_pa(d.0, d.1, posang, 0.288);
                assert!((s2 - sep).abs() < 1e-9 && ((p2 - pa + 540.0) % 360.0 - 180.0).abs() < 1e-9);
            }
        }
    }

    /// Detections of several orientations within the tolerance are one star, in order of
    /// S/N; farther ones are two.
    #[test]
    fn detections_group_by_sky_position() {
        let d = |e: f64, n: f64, snr: f64| Detection { en: (e, n), snr };
        let g = group(&[d(10.0, 5.0, 20.0), d(10.2, 5.1, 40.0), d(30.0, 5.0, 100.0)], 0.6);
        assert_eq!(g.len(), 2);
        assert_eq!(g[0].n, 1);
        assert!((g[0].en.0 - 30.0).abs() < 1e-12);
        assert_eq!(g[1].n, 2);
        assert!((g[1].en.0 - (10.2 * 40.0 + 10.0 * 20.0) / 60.0).abs() < 1e-12);
    }
}
