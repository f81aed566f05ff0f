//! Stokes parameters: the instrument's forward model and its inversion.
pub mod calibration;
pub mod fresnel;
pub mod hwp;
pub mod inversion;
pub mod model;
pub mod propagation;

pub use model::{beam_fluxes, companion_offset_px, normalized_difference, Polarization};
