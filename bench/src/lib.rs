//! # sofipol-bench: benchmarks and accuracy harnesses
//!
//! The measuring tools of sofipol, kept out of the product crates' API (not published).
//! The binary's `sofipol bench ...` parses the command line and calls:
//!
//! ```text
//!  commands         bench sim (simulator cost), bench stages (cost of each reduction stage),
//!                   bench accuracy (pull table of one configuration)
//!  accuracy_report  bench accuracy --report DIR: accuracy against time of every trade-off
//!  night            bench night: a 49-target night reduced by `sofipol night` in a child
//!                   process, against the `cat` floor
//!  python           bench night --python: the expert Python reduction (bench/python/), timed
//!                   and compared
//!  accuracy         the accuracy harness: simulated nights by separation bin, pulls, time
//!  accuracy_hwp     the same for the half-wave-plate profile (NIRC2's, pupil tracking):
//!                   simulated nights of single stars, reduced as `night --profile nirc2`
//!  calibration      bench calibration: the calibration's pooled accuracy over many nights in
//!                   two hard cases (standards at one parallactic angle, polarized standards
//!                   only), each night simulated and reduced by `sofipol` in child processes
//!  standards_truth  the true polarization of simulated standards, drawn from their table
//!  world            the world-sampling harness (drawn conditions, the file path of `night`;
//!                   run by examples/world.rs and tests/accuracy_world.rs)
//!  timing           median of repeated timings; the stack kernels timed on sky-like frames
//!  watch            bench watch: a night copied frame by frame into a folder followed by
//!                   `sofipol watch`: latency per template, final catalog against `night`'s
//! ```
#![deny(missing_docs)]

pub mod accuracy;
pub mod accuracy_hwp;
pub mod accuracy_report;
pub mod calibration;
pub mod commands;
pub mod night;
pub mod python;
pub mod standards_truth;
pub mod timing;
pub mod watch;
pub mod world;
