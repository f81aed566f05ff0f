//! One target's FITS products from its reduction (frames still in memory): per orientation
//! the combined o and e cut-outs, then the Stokes I, Q, U maps.
use std::path::{Path, PathBuf};

use sofipol_calib::fits::{write_images, ImageHdu, ImagePixels};
use sofipol_calib::{Frame, Header, HistoryRecord, Profile};

use super::combine::{combine_beam, combine_following, cutout_half_size, BeamStack};
use super::headers::{self, ProductKind};
use super::stokes_maps::{
    aperture_fluxes, e_to_o_shift, match_psfs, stokes_maps, transparency_scales, OrientationBeams, StokesMaps,
};
use super::{CombineError, ProductError, StokesMapsError};
use crate::catalog::polarimetric_calibration::FilterCalibration;
use crate::catalog::Target;
use crate::reduce::run::TargetOutcome;
use crate::reduce::{Measured, SkySubtractedOrientation, TargetParams};
use crate::solve::OrientationCorrection;

/// One orientation's combined beams.
pub struct OrientationProduct {
    /// Index of the orientation in the reduction (and in its measurements).
    pub index: usize,
    /// Rotator angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle the reduction used (the profile's relation), deg.
    pub analyzer_deg: f64,
    /// The o beam's dithers combined.
    pub o: BeamStack,
    /// The e beam's dithers combined.
    pub e: BeamStack,
    /// The orientation's frames (files), in dither order.
    pub files: Vec<PathBuf>,
    /// The detector row of the frames' row 0 (the reduction reads the target strips only).
    pub row0: usize,
    /// The stages each frame went through (those of the first frame combined).
    pub history: Vec<HistoryRecord>,
}

/// How one orientation went into the Stokes maps.
#[derive(Debug, Clone)]
pub struct OrientationStokes {
    /// Rotator angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle, deg: the calibration's when the maps are calibrated, else the
    /// profile's.
    pub analyzer_deg: f64,
    /// The calibration's offset c taken from F (0: instrumental).
    pub offset: f64,
    /// The telescope's term taken from F (0: instrumental or none removed).
    pub telescope: f64,
    /// The o stack resampled at (x, y) + this, px (its target onto the centre pixel).
    pub o_shift: (f64, f64),
    /// The e stack's target from the o stack's, px: e resampled at (x, y) + o_shift + this.
    pub eo_shift: (f64, f64),
    /// Transparency normalisation a_k.
    pub scale: f64,
    /// Sigma of the Gaussian its o and e were convolved with to match the broadest
    /// orientation's PSF, px (0: none).
    pub psf_sigma: f64,
}

/// The Stokes maps and how they were made.
pub struct StokesProduct {
    /// I, Q, U and their variances.
    pub maps: StokesMaps,
    /// The orientations used.
    pub orientations: Vec<OrientationStokes>,
    /// Why the transparency scales are all 1, if they are.
    pub unscaled: Option<String>,
    /// Whether the night's calibration was applied (`POLCALIB`); why not, when it was not.
    pub calibrated: Result<(), String>,
}

/// What the Stokes maps are made from, kept from the reduction (the frames gone) until the
/// night's calibration is known: every orientation's o and e beams on the sky grid.
pub struct StokesInputs {
    /// The beams, instrumental (the profile's analyzer angles, nothing taken from F).
    pub beams: Vec<OrientationBeams>,
    /// How each went in (same order).
    pub orientations: Vec<OrientationStokes>,
    /// Transparency normalisation a_k (same order).
    pub scales: Vec<f64>,
    /// Why the scales are all 1, if they are.
    pub unscaled: Option<String>,
}

impl StokesInputs {
    /// The maps under the calibration `corrections` (the component A's orientations,
    /// [`crate::solve::orientation_corrections`]; `None`: instrumental, `why` not): each
    /// orientation with its calibrated analyzer angle and the offset and telescope term
    /// taken from F, as the catalog's solve does. An orientation the catalog did not use
    /// (no correction at its rotator angle) is left out of calibrated maps.
    pub fn maps(
        &self,
        corrections: Result<&[OrientationCorrection], String>,
    ) -> Result<StokesProduct, StokesMapsError> {
        let mut beams = Vec::new();
        let mut info = Vec::new();
        let mut scales = Vec::new();
        for ((b, o), &a) in self.beams.iter().zip(&self.orientations).zip(&self.scales) {
            let (mut b, mut o) = (b.clone(), o.clone());
            if let Ok(cs) = &corrections {
                let Some(c) = cs.iter().find(|c| (c.posang_deg - o.posang_deg).abs() < 1e-6) else {
                    continue;
                };
                b.calibrate(c.analyzer_deg, c.offset + c.telescope);
                o.analyzer_deg = c.analyzer_deg;
                o.offset = c.offset;
                o.telescope = c.telescope;
            }
            beams.push(b);
            info.push(o);
            scales.push(a);
        }
        if beams.len() < 2 {
            return Err(StokesMapsError::TooFewOrientations { found: beams.len() });
        }
        let maps = stokes_maps(&beams, &scales);
        if maps.mask.iter().all(|&v| v != 0) {
            return Err(StokesMapsError::Unconstrained);
        }
        Ok(StokesProduct {
            maps,
            orientations: info,
            unscaled: self.unscaled.clone(),
            calibrated: corrections.map(|_| ()),
        })
    }
}

/// Everything one target's products hold.
pub struct TargetProducts {
    /// Half-size of the cut-outs, px.
    pub half: usize,
    /// The pixel scale the reduction used (the profile's), arcsec/px: the cut-outs' WCS.
    pub pixscale_arcsec: f64,
    /// The orientations whose two beams could be combined.
    pub orientations: Vec<OrientationProduct>,
    /// The orientations that could not (POSANG, why).
    pub missing: Vec<(f64, CombineError)>,
    /// What the Stokes maps are made from, or why there are none.
    pub stokes: Result<StokesInputs, StokesMapsError>,
}

/// The products of a reduced target, or `None` when it has no frames or no measurements (a
/// failed target). The cut-out size follows the pair and its photometry
/// ([`cutout_half_size`]: the separation, `measure.annulus_fwhm` outer radius x the FWHM).
pub fn build(outcome: &TargetOutcome, profile: &Profile, params: &TargetParams) -> Option<TargetProducts> {
    let cal = outcome.calibrated.as_deref()?;
    let m = outcome.measured.as_ref()?;
    let a = m.dithers.first()?;
    // The reduction keeps the target strips only: the detector row of the frames' row 0.
    let row0 = crate::reduce::run::crop_of(profile, params).map_or(0, |(r0, _)| r0);
    let sep_px = m
        .geometry
        .map_or(0.0, |(sep, _)| sep / profile.geometry.pixscale_arcsec);
    let half = cutout_half_size(m.fwhm_px, params.measure.annulus_fwhm.1, sep_px);
    let mut orientations = Vec::new();
    let mut missing = Vec::new();
    for (index, (o, dithers)) in cal.iter().zip(a).enumerate() {
        match orientation_product(index, o, dithers, (half, row0), m.eo_offset_px) {
            Ok(p) => orientations.push(p),
            Err(why) => missing.push((o.posang_deg, why)),
        }
    }
    let stokes = stokes_inputs(&orientations, m);
    Some(TargetProducts {
        half,
        pixscale_arcsec: profile.geometry.pixscale_arcsec,
        orientations,
        missing,
        stokes,
    })
}

fn orientation_product(
    index: usize,
    o: &SkySubtractedOrientation,
    dithers: &[crate::reduce::DitherValue],
    (half, row0): (usize, usize),
    eo_offset_px: (f64, f64),
) -> Result<OrientationProduct, CombineError> {
    let frames: Vec<&Frame> = o.frames.iter().collect();
    let positions: Vec<Option<(f64, f64)>> = (0..frames.len()).map(|i| dithers.get(i).map(|d| d.o.xy)).collect();
    let ob = combine_beam(&frames, &positions, half).ok_or(CombineError::NoMeasuredDither {
        posang_deg: o.posang_deg,
    })?;
    let eb = combine_following(&ob, &frames, eo_offset_px).ok_or(CombineError::NoEBeamPixel {
        posang_deg: o.posang_deg,
        eo_offset_px,
    })?;
    let first = frames[ob.anchors[0].index];
    Ok(OrientationProduct {
        index,
        posang_deg: o.posang_deg,
        analyzer_deg: o.analyzer_deg,
        row0,
        history: first.history.clone(),
        files: frames.iter().map(|f| f.path().to_path_buf()).collect(),
        o: ob,
        e: eb,
    })
}

/// Every orientation's beams onto the sky grid centred on the target (north up, east
/// left), with the transparency normalisation from the target's fluxes, or why there can be
/// no Stokes maps.
fn stokes_inputs(orients: &[OrientationProduct], m: &Measured) -> Result<StokesInputs, StokesMapsError> {
    let mut beams = Vec::new();
    let mut info = Vec::new();
    for o in orients {
        let Some(shift) = e_to_o_shift(&o.o, &o.e, m.eo_offset_px) else {
            continue;
        };
        beams.push(OrientationBeams::on_sky(
            o.analyzer_deg,
            o.posang_deg,
            &o.o,
            &o.e,
            shift,
        ));
        let t = o.o.target_xy();
        let c = o.o.half as f64;
        info.push(OrientationStokes {
            posang_deg: o.posang_deg,
            analyzer_deg: o.analyzer_deg,
            offset: 0.0,
            telescope: 0.0,
            o_shift: (t.0 - c, t.1 - c),
            eo_shift: shift,
            scale: 1.0,
            psf_sigma: 0.0,
        });
    }
    if beams.len() < 2 {
        return Err(StokesMapsError::TooFewOrientations { found: beams.len() });
    }
    let (inner, outer) = match_radii(orients[0].o.half, m.aperture_px);
    let c = orients[0].o.half as f64;
    for (i, sigma) in info.iter_mut().zip(match_psfs(&mut beams, c, (inner, outer))) {
        i.psf_sigma = sigma;
    }
    let (scales, unscaled) = match transparency_scales(&aperture_fluxes(&beams, c, outer)) {
        Ok(s) => (s, None),
        Err(why) => (vec![1.0; beams.len()], Some(why)),
    };
    for (i, a) in info.iter_mut().zip(&scales) {
        i.scale = *a;
    }
    Ok(StokesInputs {
        beams,
        orientations: info,
        scales,
        unscaled,
    })
}

/// The radii of the PSF matching and the transparency normalisation, px: the catalog's
/// aperture radius (a third of the grid's half-size when it has none), and three times it
/// within the grid less the resampling's and the smoothing's masked border.
fn match_radii(half: usize, aperture_px: f64) -> (f64, f64) {
    let edge = (half as f64 - 8.0).max(2.0);
    let inner = if aperture_px.is_finite() && aperture_px > 0.0 {
        aperture_px
    } else {
        half as f64 / 3.0
    };
    (inner.min(edge / 2.0), (3.0 * inner).min(edge))
}

/// File name of a product of the target `slug`: `<slug>_pa<angle>_o.fits`, `_e.fits`,
/// `<slug>_stokes.fits`.
pub fn file_name(slug: &str, posang_deg: Option<f64>, what: &str) -> String {
    match posang_deg {
        Some(pa) => format!("{slug}_pa{}_{what}.fits", angle_tag(pa)),
        None => format!("{slug}_{what}.fits"),
    }
}

/// An angle in a file name: `45`, `22p5`, `m45` (to 0.1 deg).
pub fn angle_tag(deg: f64) -> String {
    let s = format!("{:.1}", deg);
    let s = s.strip_suffix(".0").unwrap_or(&s);
    s.replace('-', "m").replace('.', "p")
}

/// A file written, or why not.
pub type FileResult = (PathBuf, Result<(), ProductError>);

/// The Stokes maps of one target, waiting for the night's calibration
/// ([`PendingStokes::write`]).
pub struct PendingStokes {
    /// Where they go.
    pub path: PathBuf,
    /// The target's sequence id (its entry in the catalog).
    pub sequence: String,
    /// The cards known at the reduction (target, measurement, frames).
    header: Header,
    /// The stages of the first orientation's frames.
    history: Vec<HistoryRecord>,
    /// Half-size of the grid, px.
    half: usize,
    /// The pixel scale, arcsec/px.
    pixscale_arcsec: f64,
    /// What the maps are made from.
    inputs: StokesInputs,
}

impl PendingStokes {
    /// Make and write the maps for `target` as the catalog has it after the calibration,
    /// `cal` the calibration of its filter (`None`: the night has none, the maps are
    /// instrumental as the catalog's values are) and `profile` the profile the catalog's
    /// solve used.
    pub fn write(
        &self,
        target: &Target,
        cal: Option<&FilterCalibration>,
        profile: &Profile,
    ) -> Result<(), ProductError> {
        let corrections = match (cal, target.components.first()) {
            (Some(cal), Some(a)) => Ok(crate::solve::orientation_corrections(a, profile, Some(cal))),
            (None, _) => Err("the night has no calibration for this filter".to_string()),
            (Some(_), None) => Err("the target has no measured component".to_string()),
        };
        let s = self
            .inputs
            .maps(corrections.as_deref().map_err(String::clone))
            .map_err(ProductError::NoStokesMaps)?;
        write_stokes(&self.path, self, target, &s).map_err(|source| ProductError::Write {
            path: self.path.clone(),
            source,
        })
    }
}

/// Write the products of `p` for `target` into `dir` (names from `slug`): the result of
/// each file, in order; a product that could not be made (an orientation without a
/// combined beam, the Stokes maps) is an error too. The Stokes maps wait for the night's
/// calibration: returned to be written with it ([`PendingStokes::write`]).
pub fn write(
    dir: &Path,
    slug: &str,
    target: &Target,
    m: &Measured,
    p: TargetProducts,
) -> (Vec<FileResult>, Option<PendingStokes>) {
    let mut out = Vec::new();
    for o in &p.orientations {
        for (kind, beam, stack) in [(headers::COMBINED_O, "o", &o.o), (headers::COMBINED_E, "e", &o.e)] {
            let path = dir.join(file_name(slug, Some(o.posang_deg), beam));
            let r = write_beam(&path, kind, (target, m), o, stack, p.pixscale_arcsec).map_err(|source| {
                ProductError::Write {
                    path: path.clone(),
                    source,
                }
            });
            out.push((path, r));
        }
    }
    for (pa, why) in &p.missing {
        out.push((
            dir.join(file_name(slug, Some(*pa), "o")),
            Err(ProductError::NoCombinedBeams(why.clone())),
        ));
    }
    let path = dir.join(file_name(slug, None, "stokes"));
    let header = stokes_header(target, m, &p);
    let history = p.orientations.first().map(|o| o.history.clone()).unwrap_or_default();
    let pending = match p.stokes {
        Ok(inputs) => Some(PendingStokes {
            path,
            sequence: target.sequence_id().to_string(),
            header,
            history,
            half: p.half,
            pixscale_arcsec: p.pixscale_arcsec,
            inputs,
        }),
        Err(why) => {
            out.push((path, Err(ProductError::NoStokesMaps(why))));
            None
        }
    };
    (out, pending)
}

/// The cards a target's products share: product kind, target, the catalog's measurement.
fn target_header(kind: ProductKind, target: &Target, m: &Measured, half: usize) -> Header {
    let mut h = headers::product_header(kind);
    headers::target_cards(&mut h, target);
    headers::qc(&mut h, "FWHM", m.fwhm_px, "px, median FWHM of the target's frames");
    headers::qc(
        &mut h,
        "EO OFFSET X",
        m.eo_offset_px.0,
        "px, measured e - o offset on the detector",
    );
    headers::qc(
        &mut h,
        "EO OFFSET Y",
        m.eo_offset_px.1,
        "px, measured e - o offset on the detector",
    );
    headers::qc(
        &mut h,
        "APERTURE RADIUS",
        m.aperture_px,
        "px, the catalog's aperture radius",
    );
    headers::qc(
        &mut h,
        "CUTOUT HALF",
        half as i64,
        "px, the cut-out is 2 x HALF + 1 px wide",
    );
    if let Some((sep, pa)) = m.geometry {
        headers::qc(&mut h, "PAIR SEP", sep, "arcsec, separation of B from A");
        headers::qc(&mut h, "PAIR PA", pa, "deg, position angle of B from A");
    }
    h
}

fn write_beam(
    path: &Path,
    kind: ProductKind,
    (target, m): (&Target, &Measured),
    o: &OrientationProduct,
    stack: &BeamStack,
    pixscale_arcsec: f64,
) -> sofipol_calib::Result<()> {
    let mut h = target_header(kind, target, m, stack.half);
    headers::set(&mut h, "POSANG", o.posang_deg, "deg, rotator position angle");
    headers::set(
        &mut h,
        "ANALYZER",
        o.analyzer_deg,
        "deg, analyzer angle (the profile's)",
    );
    h.set_with_comment("BUNIT", "adu", headers::unit_comment("adu"));
    let used: Vec<&Path> = stack.anchors.iter().map(|a| o.files[a.index].as_path()).collect();
    headers::raw_cards(&mut h, &used, "POL_SCIENCE");
    headers::qc(&mut h, "NDITHER", stack.anchors.len() as i64, "dithers combined");
    let (tx, ty) = stack.target_xy();
    headers::qc(&mut h, "TARGET X", tx + 1.0, "FITS px, target's mean position here");
    headers::qc(&mut h, "TARGET Y", ty + 1.0, "FITS px, target's mean position here");
    if let (Some(ra), Some(dec)) = (target.ra_deg, target.dec_deg) {
        headers::wcs_cards(&mut h, (ra, dec), (tx + 1.0, ty + 1.0), o.posang_deg, pixscale_arcsec);
    }
    let mut history = o.history.clone();
    history.push(register_record(o, stack, kind == headers::COMBINED_E, m.eo_offset_px));
    history.push(combine_record(stack));
    write_images(
        path,
        &[
            ImageHdu {
                extname: "",
                header: &h,
                history: &history,
                pixels: ImagePixels::F32(&stack.data),
            },
            ImageHdu {
                extname: sofipol_calib::fits::VARIANCE_EXTNAME,
                header: &headers::variance_header("variance of the combined image"),
                history: &[],
                pixels: ImagePixels::F32(&stack.variance),
            },
            ImageHdu {
                extname: "MASK",
                header: &headers::extension_header(None, "1 = no dither usable at this pixel (value NaN)"),
                history: &[],
                pixels: ImagePixels::U8(&stack.mask),
            },
            ImageHdu {
                extname: "NCOMBINE",
                header: &headers::extension_header(None, "number of dithers combined at this pixel"),
                history: &[],
                pixels: ImagePixels::U8(&stack.n_combined),
            },
        ],
    )
}

fn register_record(o: &OrientationProduct, stack: &BeamStack, e_beam: bool, eo: (f64, f64)) -> HistoryRecord {
    let h = stack.half as i64;
    let anchors: Vec<String> = stack
        .anchors
        .iter()
        .map(|a| {
            let name = o.files[a.index]
                .file_name()
                .map(|n| n.to_string_lossy())
                .unwrap_or_default();
            format!(
                "{name}: target at detector ({:.2}, {:.2}), pixel ({}, {}) here ({}, {})",
                a.position.0 + 1.0,
                a.position.1 + 1.0 + o.row0 as f64,
                a.origin.0 + h + 1,
                a.origin.1 + h + 1 + o.row0 as i64,
                h + 1,
                h + 1
            )
        })
        .collect();
    let how = if e_beam {
        format!(
            "each dither shifted by whole pixels (no interpolation: the pixels' noise stays independent) \
             as its o beam was, plus the whole-pixel part of the measured e-o offset ({:.3}, {:.3}) px, \
             i.e. ({}, {}): o and e carry the same registration, the e target at the o target's position \
             + ({:.3}, {:.3}) px",
            eo.0,
            eo.1,
            eo.0.round(),
            eo.1.round(),
            eo.0 - eo.0.round(),
            eo.1 - eo.1.round()
        )
    } else {
        "each dither shifted by whole pixels (no interpolation: the pixels' noise stays independent) so \
         that the pixel holding the target (component A, its position fitted by the reduction in this \
         dither) is the cut-out's centre pixel"
            .to_string()
    };
    HistoryRecord::new("register", format!("{how}; FITS coordinates: {}", anchors.join("; ")))
}

fn combine_record(stack: &BeamStack) -> HistoryRecord {
    HistoryRecord::new(
        "combine",
        format!(
            "{} dithers: weighted mean over the usable dithers of each pixel (BAD, COSMIC, SATURATED, \
             OFF_STRIP and non-finite pixels left out), one weight per dither, w = 1/b, b its background \
             variance (the median of its variance over the cut-out; a pixel's own variance holds the \
             star's photon noise and would bias the star's flux): value = sum(w v)/sum(w); UNCERT (variance) = \
             sum(w^2 var)/sum(w)^2 (1/sum(w) on the sky); MASK = 1 where no dither is usable; NCOMBINE = \
             the dithers at each pixel",
            stack.anchors.len()
        ),
    )
}

fn write_stokes(path: &Path, p: &PendingStokes, target: &Target, s: &StokesProduct) -> sofipol_calib::Result<()> {
    let h = stokes_calibration_cards(p, target, s);
    let history = stokes_history(p, s);
    let mp = &s.maps;
    let kind = if s.calibrated.is_ok() {
        "calibrated"
    } else {
        "instrumental"
    };
    let ext = |unit: Option<&str>, what: &str| headers::extension_header(unit, what);
    let hdus = [
        (
            "Q",
            ext(Some("adu"), &format!("Stokes Q ({kind}), north up, east left")),
            ImagePixels::F32(&mp.q),
        ),
        (
            "U",
            ext(Some("adu"), &format!("Stokes U ({kind}), north up, east left")),
            ImagePixels::F32(&mp.u),
        ),
        (
            sofipol_calib::fits::VARIANCE_EXTNAME,
            headers::variance_header("variance of I"),
            ImagePixels::F32(&mp.var_i),
        ),
        ("VAR_Q", ext(Some("adu2"), "variance of Q"), ImagePixels::F32(&mp.var_q)),
        ("VAR_U", ext(Some("adu2"), "variance of U"), ImagePixels::F32(&mp.var_u)),
        (
            "COV_QU",
            ext(Some("adu2"), "covariance of Q and U"),
            ImagePixels::F32(&mp.cov_qu),
        ),
        (
            "MASK",
            ext(None, "1 = Q and U not constrained here (values NaN)"),
            ImagePixels::U8(&mp.mask),
        ),
    ];
    let mut all = vec![ImageHdu {
        extname: "",
        header: &h,
        history: &history,
        pixels: ImagePixels::F32(&mp.i),
    }];
    all.extend(hdus.iter().map(|(name, header, pixels)| ImageHdu {
        extname: name,
        header,
        history: &[],
        pixels: *pixels,
    }));
    write_images(path, &all)
}

/// The primary header of the Stokes maps known at the reduction: the target's cards and the
/// frames they come from.
fn stokes_header(target: &Target, m: &Measured, p: &TargetProducts) -> Header {
    let mut h = target_header(headers::STOKES, target, m, p.half);
    h.set_with_comment("BUNIT", "adu", headers::unit_comment("adu"));
    let files: Vec<&Path> = p
        .orientations
        .iter()
        .flat_map(|o| o.o.anchors.iter().map(|a| o.files[a.index].as_path()))
        .collect();
    headers::raw_cards(&mut h, &files, "POL_SCIENCE");
    h
}

/// The primary header with what the calibration decided: whether it was applied, each
/// orientation's angles, shifts, scale and what was taken from F, the catalog's values of A
/// (calibrated as the maps are) and the sky grid's WCS (north up, east left, the target star
/// at the centre pixel and at the pointing).
fn stokes_calibration_cards(p: &PendingStokes, target: &Target, s: &StokesProduct) -> Header {
    let mut h = p.header.clone();
    let comment = match &s.calibrated {
        Ok(()) => "night calibration applied, as to the catalog (HISTORY)",
        Err(_) => "instrumental: no night calibration (HISTORY)",
    };
    h.set_with_comment("POLCALIB", s.calibrated.is_ok(), comment);
    headers::qc(&mut h, "NORIENT", s.orientations.len() as i64, "orientations combined");
    orientation_cards(&mut h, s);
    if let Some(c) = target.components.first() {
        let when = if s.calibrated.is_ok() {
            "calibrated, as the maps"
        } else {
            "instrumental, as the maps"
        };
        headers::qc(&mut h, "A Q", c.q, &format!("catalog q of A, {when}"));
        headers::qc(&mut h, "A U", c.u, &format!("catalog u of A, {when}"));
        headers::qc(&mut h, "A SIGQ", c.sigma_q, "its error");
        headers::qc(&mut h, "A SIGU", c.sigma_u, "its error");
    }
    let c = (p.half + 1) as f64;
    headers::qc(&mut h, "TARGET X", c, "FITS px, target's position (the centre pixel)");
    headers::qc(&mut h, "TARGET Y", c, "FITS px, target's position (the centre pixel)");
    if let (Some(ra), Some(dec)) = (target.ra_deg, target.dec_deg) {
        headers::wcs_cards(&mut h, (ra, dec), (c, c), 0.0, p.pixscale_arcsec);
    }
    h
}

/// QC cards of each orientation combined: angles, the o and e shifts, the scale.
fn orientation_cards(h: &mut Header, s: &StokesProduct) {
    for (k, o) in s.orientations.iter().enumerate() {
        let k = k + 1;
        headers::qc(
            h,
            &format!("ORI{k} POSANG"),
            o.posang_deg,
            "deg, rotator position angle",
        );
        headers::qc(
            h,
            &format!("ORI{k} PHI"),
            o.analyzer_deg,
            if s.calibrated.is_ok() {
                "deg, analyzer angle (the calibration's)"
            } else {
                "deg, analyzer angle (the profile's)"
            },
        );
        headers::qc(h, &format!("ORI{k} OFFSET"), o.offset, "offset c taken from F");
        headers::qc(
            h,
            &format!("ORI{k} TELPOL"),
            o.telescope,
            "telescope's term taken from F",
        );
        headers::qc(
            h,
            &format!("ORI{k} OSHIFT X"),
            o.o_shift.0,
            "px, o cut-out resampled at x + this",
        );
        headers::qc(
            h,
            &format!("ORI{k} OSHIFT Y"),
            o.o_shift.1,
            "px, o cut-out resampled at y + this",
        );
        headers::qc(
            h,
            &format!("ORI{k} EOSHIFT X"),
            o.eo_shift.0,
            "px, e target - o target in the cut-outs",
        );
        headers::qc(
            h,
            &format!("ORI{k} EOSHIFT Y"),
            o.eo_shift.1,
            "px, e target - o target in the cut-outs",
        );
        headers::qc(h, &format!("ORI{k} SCALE"), o.scale, "transparency normalisation a_k");
        headers::qc(
            h,
            &format!("ORI{k} PSFMATCH"),
            o.psf_sigma,
            "px, sigma of the Gaussian matching the PSFs",
        );
    }
}

/// The HISTORY of the Stokes maps: each step from the combined cut-outs to I, Q, U.
fn stokes_history(p: &PendingStokes, s: &StokesProduct) -> Vec<HistoryRecord> {
    let mut history = p.history.clone();
    history.push(HistoryRecord::new(
        "register",
        "the o and e cut-outs of every orientation as in the SOFIPOL_COMBINED_O/E products: \
         whole-pixel shifts on the target's measured position in each dither (e: the o shift + the \
         whole-pixel part of the e-o offset), weighted mean (one weight per dither)",
    ));
    history.push(HistoryRecord::new(
        "resample",
        "every orientation's o and e cut-outs onto one sky grid, north up and east left, the target \
         at its centre pixel c: o'(p) = o(t + R(-POSANG) (p - c)), e'(p) = e(t + EOSHIFT + R(-POSANG) \
         (p - c)), t the o target's position in the cut-out (c + OSHIFT, QC ORIi), EOSHIFT the \
         measured e-o offset less the mean whole-pixel registration difference of the dithers; \
         Lanczos-3 interpolation (6 x 6 taps at each point, normalised per axis: flux and a \
         well-sampled star's shape kept); variance sum(w var), what an aperture sum carries \
         (neighbouring pixels are correlated); a pixel with a masked tap is masked",
    ));
    history.push(HistoryRecord::new(
        "psf-match",
        "the orientations' PSFs matched: o' and e' of each orientation whose star is more concentrated \
         than the broadest orientation's (its o' + e' flux within the catalog's aperture radius r as a \
         share of that within 3 r) convolved with the Gaussian (QC ORIi PSFMATCH, sigma in px) that \
         brings the share to the broadest's; the same kernel for o' and e' keeps a star's F; the \
         orientations' I then agree in an aperture of any size",
    ));
    history.push(HistoryRecord::new(
        "normalise",
        match &s.unscaled {
            None => "o' and e' of orientation k times a_k = mean(T)/T_k (QC ORIi SCALE), T_k the target's \
                     o' + e' flux within 3 r of the centre (pixels usable in every orientation): transparency \
                     changes between orientations cancel as in F = (o-e)/(o+e)"
                .to_string(),
            Some(why) => format!("not normalised (a_k = 1): {why}"),
        },
    ));
    history.push(HistoryRecord::new(
        "stokes",
        "per pixel, D_k = a_k ((o' - e') - f_k (o' + e')) = Q cos 2phi_k + U sin 2phi_k over the usable \
         orientations, f_k = OFFSET + TELPOL (QC ORIi), by the catalog's weighted least squares \
         (stokes::inversion::fit_qu) with one weight per orientation, 1/B_k, B_k the median of V_k = \
         a_k^2 ((1 - f_k)^2 var_o' + (1 + f_k)^2 var_e') (a pixel's own variance would bias the star); \
         Q = sum c_k D_k, VAR_Q = sum c_k^2 V_k (U, VAR_U, COV_QU alike); I = sum(a_k (o' + e')/B_k) / \
         sum(1/B_k), UNCERT (variance of I) = sum(a_k^2 (var_o' + var_e')/B_k^2)/sum(1/B_k)^2; MASK = 1 \
         where the usable orientations do not constrain Q and U. Over an aperture, sum(Q)/sum(I) is the \
         least-squares q of the aperture's F_k - f_k at the angles phi_k: the star's q as the catalog \
         solves it",
    ));
    history.push(HistoryRecord::new(
        "calibration",
        match &s.calibrated {
            Ok(()) => "applied as to the catalog: the analyzer angles phi_k = parity POSANG + theta0 of the \
                       night's calibration (QC ORIi PHI), its offset c (QC ORIi OFFSET) and, where the \
                       calibration measured it, the telescope's polarization at each orientation's \
                       parallactic angles (QC ORIi TELPOL) taken from F; Q and U are on the sky, angles from \
                       north through east. Their errors (VAR_Q, VAR_U) are the photometry's; the catalog's \
                       also carry the calibration's"
                .to_string(),
            Err(why) => format!(
                "NOT applied ({why}): the profile's analyzer angles (QC ORIi PHI), nothing taken from F \
                 (instrumental offset c, telescope's polarization left in), as the catalog's values of this \
                 target"
            ),
        },
    ));
    history
}
