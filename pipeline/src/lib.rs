//! # sofipol-pipeline: the science
//!
//! A night is reduced one way, by [`night::run_night`] (plan, night-wide bad-pixel mask
//! and flats, every sequence in parallel, standards, calibration, provenance); the
//! commands and the harnesses call it. One sequence:
//!
//! ```text
//!  raw frames ─ calib (read, bad pixels, flat, sky) ─▶ sequence {orientation -> dithers}
//!      │
//!      ├─ beams: o/e target strips, e-o offset measured from the data
//!      ├─ sources: both binary components at each orientation (rotation moves B)
//!      ├─ photometry: exact-overlap apertures, annulus background, variance, flags
//!      ├─ stokes: F = (o-e)/(o+e) per dither -> q, u (N-orientation least squares),
//!      │          P, gamma, Wardle-Kronberg errors, debiasing, P/sigma > 3 cut
//!      ├─ catalog entry: JSON (docs/catalog-schema.md)
//!      └─ calibration: the night's standards -> offset c, zero-point theta0, parity
//!                      -> every component re-solved from its per-orientation F
//!
//!  sim:   scene simulator (the same forward model the inversion tests invert)
//!  stats: projection / ISM Monte Carlo, KS and Kuiper tests, histograms
//!  plots: PNG figures
//!  products: FITS products (combined o/e cut-outs, Stokes I, Q, U, bad-pixel mask)
//!  report: the night's HTML page (summary, table, figures, calibration, statistics)
//! ```
#![deny(missing_docs)]

pub mod build_info;
pub mod calibration;
pub mod catalog;
pub mod error;
pub mod export;
pub mod foreground;
pub mod frame_list;
pub mod input;
pub mod io;
pub mod live;
pub mod night;
pub(crate) mod nullable;
pub mod numeric;
pub mod photometry;
pub mod plots;
pub mod products;
pub mod reduce;
pub mod report;
pub mod scan;
pub mod sequence;
pub mod sim;
pub mod single_pointing;
pub mod solve;
pub mod standards;
pub mod stats;
pub mod stokes;
