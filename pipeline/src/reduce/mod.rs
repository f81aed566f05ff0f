//! Reduction of one target sequence, from calibrated (sky-subtracted) frames to a catalog
//! entry. The stages, in order, each in its own file:
//!
//! ```text
//! run.rs        raw files -> read -> bad-pixel mask -> sky subtraction -> measure -> entry
//!               (the calibration stages come from sofipol-calib)
//! measure_sequence (this file), on the calibrated frames of every orientation:
//!   sources.rs    1. the primary (blend centroid) in every frame: the source at the
//!                    pointing carried by the header offset + centroid (a brighter star of
//!                    the strip elsewhere is flagged `brighter_source_in_strip`)
//!   beams.rs      2. the e-o offset: cross-correlation of the o and e images of the target
//!   companion.rs  3. the companion: two-star PSF fit on the registered stack of the dithers;
//!                    the offsets found at all orientations give one separation and PA
//!   fluxes.rs     4. PSF model and method (median FWHM and Moffat beta of the stacks)
//!                 5. per frame and beam: two-star PSF fit (deblending), then
//!                      separation >= deblend limit: aperture photometry of each star on the
//!                                                   frame with the companion's model subtracted
//!                      closer:                      PSF-fit fluxes
//!                    F = (o - e)/(o + e) per dither; dithers with bad pixels / cosmics /
//!                    saturation in an aperture rejected
//!   (this file)   6. e-o offset and geometry refined from the per-frame fits
//!   identity.rs   7. A/B identity on the per-dither photometry: B at one sky position
//!                    angle from A at every orientation, A the brighter in o+e flux when
//!                    the ratio is significant (else `ab_identity_unverified`)
//!   field.rs      field stars: every other point source of the strips, detected on the
//!                 stacks of each orientation (o and e images paired by offset and flux),
//!                 measured in every dither by stage 5's photometry
//! entry.rs      per component: clipped weighted mean of F per orientation, q, u (least
//!               squares over orientations), P, gamma, errors, debiasing, cut; catalog entry
//! params.rs     the settings of all stages, validated once when read
//! ```
//!
//! A new stage (an instrumental-polarization correction, say) is a function in its own file
//! called from [`measure_sequence`] (on the measured F values) or from
//! [`entry::component_from_dithers`] (on q and u).
pub mod beams;
pub mod companion;
pub mod entry;
pub mod field;
pub mod fluxes;
pub mod identity;
pub mod params;
pub mod quality;
pub mod residual;
pub mod run;
pub mod sources;
#[cfg(test)]
mod tests_offset;

use serde::Serialize;
use sofipol_calib::{Frame, Profile};

pub use entry::{component_from_dithers, target_entry};
pub use params::{MeasureParams, TargetParams};

/// The dithers of one orientation with the detector's signature and the sky removed
/// (flat-fielded, bad pixels masked, sky subtracted), ready to measure.
#[derive(Debug, Clone)]
pub struct SkySubtractedOrientation {
    /// Rotator position angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle, deg.
    pub analyzer_deg: f64,
    /// Sky-subtracted frames with variance and mask.
    pub frames: Vec<Frame>,
    /// Header jitter offsets (dx, dy), px.
    pub offsets: Vec<[f64; 2]>,
}

/// One star in one beam of one frame.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct BeamFlux {
    /// Flux, ADU.
    pub flux: f64,
    /// Variance, ADU^2.
    pub var: f64,
    /// Position (x, y), px.
    pub xy: (f64, f64),
    /// Aperture-photometry flags of this measurement ([`crate::photometry::Flags`] bits;
    /// 0 for PSF-fit fluxes).
    pub phot_flags: u32,
    /// Fraction of the fitted PSF model's flux inside the aperture, pixel-integrated at the
    /// star's sub-pixel position (None: PSF-fit flux, or no converged fit).
    pub aperture_fraction: Option<f64>,
}

/// Per-dither measurement of one component.
#[derive(Debug, Clone, Serialize)]
pub struct DitherValue {
    /// F = (o - e)/(o + e).
    pub f: f64,
    /// sigma_F.
    pub sigma_f: f64,
    /// o beam.
    pub o: BeamFlux,
    /// e beam.
    pub e: BeamFlux,
    /// Why this dither is not used (None: used unless clipped).
    pub rejected: Option<String>,
}

/// The intermediate results of a measured sequence (for diagnostics and plots).
#[derive(Debug, Clone, Serialize)]
pub struct Measured {
    /// e-o offset found, px.
    pub eo_offset_px: (f64, f64),
    /// Median FWHM, px.
    pub fwhm_px: f64,
    /// Per orientation, per frame: the frame's seeing FWHM from the PSF fits of the
    /// primary, px ([`fluxes::Fluxes::frame_fwhm_px`]; NaN when no fit converged).
    pub frame_fwhm_px: Vec<Vec<f64>>,
    /// Separation (arcsec) and PA (deg) of B from A, when B was found.
    pub geometry: Option<(f64, f64)>,
    /// Photometry method: "aperture" or "psf_fit".
    pub photometry: String,
    /// Aperture radius used (median over frames), px.
    pub aperture_px: f64,
    /// Per component, per orientation, per dither.
    pub dithers: Vec<Vec<Vec<DitherValue>>>,
    /// Target flags.
    pub flags: Vec<crate::catalog::Flag>,
    /// The field stars (empty unless `measure.field_stars`), F per orientation and dither
    /// like `dithers`.
    pub field: Vec<field::FieldMeasured>,
}

/// An error that stops the measurement of a sequence (defined with the crate's other errors).
pub use crate::error::MeasureError;

impl BeamFlux {
    /// No measurement (NaN flux and variance).
    pub fn missing() -> Self {
        BeamFlux {
            flux: f64::NAN,
            var: f64::NAN,
            xy: (f64::NAN, f64::NAN),
            phot_flags: 0,
            aperture_fraction: None,
        }
    }
}

impl DitherValue {
    /// A dither that could not be measured, for `reason`.
    pub fn missing(reason: &str) -> Self {
        DitherValue {
            f: f64::NAN,
            sigma_f: f64::NAN,
            o: BeamFlux::missing(),
            e: BeamFlux::missing(),
            rejected: Some(reason.into()),
        }
    }
}

/// Measure both components of a calibrated sequence: the stages in order.
pub fn measure_sequence(
    orients: &[SkySubtractedOrientation],
    profile: &Profile,
    params: &MeasureParams,
) -> Result<Measured, MeasureError> {
    let scale = profile.geometry.pixscale_arcsec;
    let mut flags = Vec::new();
    let masks = sources::unusable_masks(orients);
    let primary = sources::locate_primary(orients, &masks, profile, params)?;
    flags.extend(primary.flags.iter().cloned());
    let eo = beams::measure_eo_offset(orients, &primary, &masks, profile, &mut flags)?;
    // Without a focal mask the companion is searched on the pair images too: B's e image,
    // as bright as B, may lie within the companion search radius of A.
    let companion = if profile.geometry.has_mask() {
        companion::find_companion(orients, &primary, &masks, profile, params, &mut flags)
    } else {
        let (pairs, pair_masks) = sources::pair_images(orients, &masks, eo);
        companion::find_companion(&pairs, &primary, &pair_masks, profile, params, &mut flags)
    };
    let choice = fluxes::choose_psf(&companion, primary.fwhm_guess, scale, params);
    let setup = fluxes::FluxSetup {
        choice: &choice,
        eo_px: eo,
        scale_arcsec_per_px: scale,
        params,
        seeing: true,
    };
    let mut fl = fluxes::measure_fluxes(orients, &primary, &companion, &setup, &mut flags);

    // 6. Refine the e-o offset and the geometry from the per-frame fits (the stack is
    // registered to whole pixels).
    fl.apertures.sort_by(|a, b| a.total_cmp(b));
    let eo = beams::median_offset(&fl.fitted_a_oe).unwrap_or(eo);
    // The field stars, with the components' photometry at the refined e-o offset.
    let field = if params.field_stars {
        let setup = fluxes::FluxSetup { eo_px: eo, ..setup };
        field::measure_field_stars(orients, &primary, &companion, &setup, profile)
    } else {
        Vec::new()
    };
    let geometry = match companion::combine_geometry(&fl.pair_offsets, scale) {
        Some((sep, pa, _)) if companion.geometry.is_some() => Some((sep, pa)),
        _ => companion.geometry,
    };
    let mut measured = Measured {
        eo_offset_px: eo,
        fwhm_px: choice.fwhm_px,
        frame_fwhm_px: std::mem::take(&mut fl.frame_fwhm_px),
        geometry,
        photometry: if choice.use_psf {
            "psf_fit".into()
        } else {
            "aperture".into()
        },
        aperture_px: fl.apertures.get(fl.apertures.len() / 2).copied().unwrap_or(f64::NAN),
        dithers: fl.dithers,
        flags,
        field,
    };
    identity::verify_pair(&mut measured, orients, scale);
    Ok(measured)
}
