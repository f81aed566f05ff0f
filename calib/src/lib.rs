//! # sofipol-calib: instrument-signature removal
//!
//! Everything that knows about the detector and the raw files, and nothing about
//! Stokes parameters. The stages of one target, in the order the reduction runs them
//! (`pipeline/src/reduce/run.rs`):
//!
//! ```text
//!  fits::read_header ──classify::classify──▶ Science(ScienceInfo{object, sequence, posang, offset...}) | Rejected{reason}
//!                                   │
//!  FITS file ──fits::read_frame_rows_with_summary──▶ Frame {data, variance, mask, header, history}
//!                                   │   (+ PixelSummary: non-finite count, extremes)
//!        profile::Profile (calib/profiles/sofi.toml, user overrides): every instrument number
//!                                   │
//!  badpix: detect_bad_pixels_at (all frames of the target) + load_mask ──▶ combine_masks
//!          ──apply_mask_in_place──▶ BAD bits in every frame
//!                                   │
//!  flat: FlatSet::for_frame (dome flat by rotator angle, else superflat) ──FlatSet::rows──▶ FlatRows
//!                                   │   per orientation
//!  sky::sky_subtract_flat (the dithers of one orientation, given away: Vec<Frame>)
//!      levels ─▶ leave-one-out medians ─▶ raw - sky, variance, mask bits, / flat
//!      (one last pass; additive scaling divides by the flat first) ─▶ cosmic rays flagged
//!                                   │
//!                                   ▼
//!  sky-subtracted, flat-fielded Frames, each with its history records
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
pub mod input;
pub mod profile;
pub mod sky;
pub mod stack;
pub mod text;
pub mod time;

pub use error::{Error, Result};
pub use frame::{Frame, HistoryRecord, PixelSummary};
pub use header::{Card, Header, HeaderValue};
pub use profile::Profile;
