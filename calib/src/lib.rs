//! # sofipol-calib: instrument-signature removal
//!
//! Everything that knows about the detector and the raw files, and nothing about
//! Stokes parameters:
//!
//! ```text
//!  FITS file ──fits::read_frame──▶ Frame {data, variance, mask, header, history}
//!                                   │
//!        profile::Profile (calib/profiles/sofi.toml, user overrides)
//!                                   │
//!  classify::classify(header) ──▶ Science(ScienceInfo{object, sequence, posang, offset...}) | Rejected{reason}
//!                                   │
//!  flat ─▶ badpix ─▶ sky ─▶ sky-subtracted Frame (each stage: &Frame -> Result<Frame>, with history)
//! ```
//!
//! Conventions (docs/conventions.md): arrays are indexed `[y, x]`, pixel centres sit at
//! integer 0-based coordinates, FITS 1-based coordinates appear only at I/O.
#![deny(missing_docs)]

pub mod atomic;
pub mod badpix;
pub mod classify;
pub mod error;
pub mod fits;
pub mod flat;
pub mod frame;
pub mod header;
pub mod profile;
pub mod sky;
pub mod stack;

pub use error::{Error, Result};
pub use frame::{Frame, HistoryRecord, PixelSummary};
pub use header::{Card, Header, HeaderValue};
pub use profile::Profile;
