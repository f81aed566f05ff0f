//! Aperture photometry with exact pixel-overlap geometry.
//!
//! ```text
//!  image (ADU) + variance (ADU^2) + mask ─┬─ centroid():   windowed first moment near a guess
//!                                         ├─ fit_psf():    1..n pixel-integrated Gaussians or
//!                                         │                Moffats by Levenberg-Marquardt;
//!                                         │                subtract_star() deblends a companion
//!                                         └─ measure():    aperture_sum()  exact/center/subpixel
//!                                                          annulus_background()  sigma-clipped
//!                                                          flux, variance, Flags
//! ```
//!
//! Conventions (as photutils): arrays are indexed `[y, x]`; pixel `(ix, iy)` covers
//! `[ix-0.5, ix+0.5] x [iy-0.5, iy+0.5]`, so pixel centres are at integer 0-based coordinates.
//! Images are f32, every sum accumulates in f64.
//!
//! Units: this module works in the image's units, ADU, and variances in ADU^2; areas are in
//! px^2. Converting to electrons (multiply fluxes by the gain in e/ADU, variances by its square)
//! is the caller's job. The only place a gain enters is the source shot-noise term when no
//! variance map is given ([`PhotParams::gain_e_per_adu`]).
//!
//! Error of a background-subtracted flux (docs/polarimetry.md, "Errors", here in ADU):
//!
//! ```text
//!   f        = S - A b                       S = sum w_i v_i, A = sum w_i, b = annulus level
//!   sigma_f^2 = sum w_i^2 var_i              (variance map given; it holds all the noise)
//!             | f/g + sum(w_i^2) sigma_sky^2  (no map: shot noise with gain g, sky scatter)
//!             + A^2 var(b)                   var(b) = sigma_sky^2 / n_sky (clipped mean),
//!                                                     (pi/2) sigma_sky^2 / n_sky (median)
//! ```
//!
//! For the `Center` method `sum w_i^2 = A`, recovering `A sigma_sky^2` of the formula.
//!
//! Per-source problems are [`Flags`] bits, never panics or silent NaNs; see docs/photometry.md.
//!
//! Main entry points:
//! * [`overlap_circle_pixel`], [`overlap_circle_rect`], [`pixel_weight`], [`for_each_weight`]
//! * [`aperture_sum`] -> [`ApertureSum`]
//! * [`annulus_background`] -> [`Background`], [`sigma_clip`]
//! * [`measure`] with [`PhotParams`] -> [`Photometry`]
//! * [`centroid`] with [`CentroidParams`] -> [`Centroid`]
//! * [`fit_psf`], [`fit_two_psf`] with [`PsfFitParams`] ([`PsfModel`]) -> [`PsfFit`];
//!   [`subtract_star`], [`PsfFit::render_star`], [`PsfFit::model_value`]
//! * [`model`]: pixel-integrated Gaussian (erf differences) used by the fit and by simulators.
//! * [`moffat`]: pixel-integrated circular Moffat (Gauss-Legendre quadrature per pixel).

mod aperture;
mod background;
mod centroid;
mod flags;
mod measure;
pub mod model;
pub mod moffat;
mod overlap;
mod psf;
mod psf_fit;

#[cfg(test)]
mod psf_moffat_tests;
#[cfg(test)]
mod tests;

pub use aperture::{aperture_sum, Aperture, ApertureSum, MaskFill};
pub use background::{annulus_background, sigma_clip, Annulus, Background, BkgStat, Clipped};
pub use centroid::{centroid, Centroid, CentroidParams};
pub use flags::{flag_names, Flags};
pub use measure::{measure, PhotParams, Photometry, Region};
pub use overlap::{for_each_weight, overlap_circle_pixel, overlap_circle_rect, pixel_weight, Method};
pub use psf::{
    subtract_star, subtract_star_near, subtract_star_near_in_place, subtract_star_near_where, PsfFit, PsfFitError,
    PsfFitParams, PsfModel, PsfStar, MOFFAT_ALPHA_RANGE, MOFFAT_BETA_RANGE, MOFFAT_BETA_START, MOFFAT_ELLIPTICITY_MAX,
};
pub use psf_fit::{fit_psf, fit_psf_from, fit_psf_joint, fit_two_psf, FitImage, JointFit, PsfStart};
