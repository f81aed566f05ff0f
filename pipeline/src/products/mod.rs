//! FITS products an astronomer opens in DS9 or astropy to check a reduction
//! (docs/products.md), written when asked (`night --fits-products`) into
//! `<catalog stem>_products/fits/`:
//!
//! ```text
//! per target, per orientation   <slug>_pa<angle>_o.fits, _e.fits   combine.rs
//!     the dithers of one beam registered on the target by whole pixels and combined
//!     (inverse-variance weighted mean; UNCERT (variance), MASK, NCOMBINE extensions)
//! per target                    <slug>_stokes.fits                 stokes_maps.rs
//!     o and e of every orientation onto one sky grid (north up, Lanczos-3, at the measured
//!     e-o offset), Stokes I, Q, U by the catalog's least squares per pixel with the night's
//!     calibration applied as to the catalog (written once the calibration is known)
//! per night                     night_badpix.fits                  badpix.rs
//!     the night's bad-pixel mask, readable by --badpix
//! every product                 SOFIPROD, HIERARCH ESO PRO ..., QC, HISTORY   headers.rs
//! per frame (night --regions)    regions/<frame>.reg (DS9 regions)  regions.rs
//! ```
//!
//! Every per-target output (figures, regions, FITS products) is written through
//! [`Outputs`] (outputs.rs: the folders and the names). The per-target products are made
//! while the target's frames are in memory, during the reduction
//! ([`FitsProducts::write_target`], called by `night::run_night` through [`Outputs`]). Every file is
//! written atomically; a file that cannot be written is a flag on its target
//! (`fits_product_not_written: ...`) and a line in [`Written::failed`], never a
//! failed night.
pub mod badpix;
pub mod combine;
pub mod headers;
pub mod outputs;
mod paths;
pub mod regions;
pub mod stokes_maps;
pub mod target;

use std::path::{Path, PathBuf};

use sofipol_calib::Profile;

use crate::catalog::{Flag, FlagCode};
pub use crate::error::{CombineError, ProductError, StokesMapsError};
use crate::reduce::run::TargetOutcome;
use crate::reduce::TargetParams;
pub use outputs::{OutputChoice, Outputs, OutputsSummary, Written};
pub use paths::{products_dir, slug};

/// Where the FITS products of a catalog go: `<dir>/<stem>_products/fits/`.
pub fn fits_dir(catalog: &Path) -> PathBuf {
    products_dir(catalog).join(outputs::FITS_DIR)
}

/// The FITS products of one run, written into one folder (which exists) from the reduction's
/// threads; [`FitsProducts::finish`] says what was written.
pub struct FitsProducts {
    files: outputs::Files,
    /// The Stokes maps of the targets reduced, waiting for the night's calibration.
    pending: std::sync::Mutex<Vec<target::PendingStokes>>,
}

impl FitsProducts {
    /// Products written into `dir` (which must exist).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        FitsProducts {
            files: outputs::Files::new(dir.into()),
            pending: std::sync::Mutex::new(Vec::new()),
        }
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        self.files.dir()
    }

    /// Record a file's outcome; the target flag ([`FlagCode::FitsProductNotWritten`]) when
    /// it was not written.
    fn record(&self, path: &Path, result: Result<(), ProductError>) -> Option<Flag> {
        self.files
            .record(path, result)
            .map(|line| Flag::with_detail(FlagCode::FitsProductNotWritten, line))
    }

    /// Write the products of one reduced target (its frames kept: `outcome.calibrated`),
    /// named after its sequence id: the combined o and e cut-outs of every orientation; its
    /// Stokes maps wait for the night's calibration ([`FitsProducts::write_stokes_maps`]).
    /// Returns one flag per file not written (for the target's flags). A target that was
    /// not measured (failed) has no products.
    pub fn write_target(&self, outcome: &TargetOutcome, profile: &Profile, params: &TargetParams) -> Vec<Flag> {
        let Some(m) = outcome.measured.as_ref() else {
            return Vec::new();
        };
        let Some(p) = target::build(outcome, profile, params) else {
            return Vec::new();
        };
        let slug = slug(outcome.target.sequence_id());
        let (results, pending) = target::write(self.dir(), &slug, &outcome.target, m, p);
        if let Some(p) = pending {
            self.pending.lock().unwrap_or_else(|e| e.into_inner()).push(p);
        }
        results
            .into_iter()
            .filter_map(|(path, r)| self.record(&path, r))
            .collect()
    }

    /// Write the Stokes maps of every target reduced since the last call, with the night's
    /// calibration `cal` applied as to the catalog's `targets` (calibrated; matched by
    /// sequence id): a map not written is a flag on its target. `profile`: the one the
    /// catalog's solve used.
    pub fn write_stokes_maps(
        &self,
        targets: &mut [crate::catalog::Target],
        cal: Option<&crate::catalog::polarimetric_calibration::Calibration>,
        profile: &Profile,
    ) {
        use rayon::prelude::*;
        let pending = std::mem::take(&mut *self.pending.lock().unwrap_or_else(|e| e.into_inner()));
        let flags: Vec<(String, Flag)> = pending
            .par_iter()
            .filter_map(|p| {
                let t = targets.iter().find(|t| t.sequence_id() == p.sequence)?;
                let fc = cal.and_then(|c| c.for_filter(t.filter.as_deref().unwrap_or("")));
                let flag = self.record(&p.path, p.write(t, fc, profile))?;
                Some((p.sequence.clone(), flag))
            })
            .collect();
        for (seq, flag) in flags {
            if let Some(t) = targets.iter_mut().find(|t| t.sequence_id() == seq) {
                t.flags.get_or_insert_with(Vec::new).push(flag);
            }
        }
    }

    /// Write the night's bad-pixel mask as `night_badpix.fits` ([`badpix::write`]); a
    /// failure is recorded (and returned).
    pub fn write_bad_pixel_mask(&self, mask: &badpix::NightMask, params: &TargetParams) -> Option<Flag> {
        let path = self.dir().join(badpix::FILE_NAME);
        let r = badpix::write(&path, mask, params).map_err(|source| ProductError::Write {
            path: path.clone(),
            source,
        });
        self.record(&path, r)
    }

    /// What was written and what failed. With `clean` (a whole night), the folder is
    /// cleared of what earlier runs left there and this one did not write: sofipol FITS
    /// products (files with `SOFIPROD`) of targets no longer reduced, and the temporary
    /// directories of interrupted writes.
    pub fn finish(self, clean: bool) -> outputs::Written {
        self.files.finish(clean, is_product)
    }
}

/// Whether `path` is a sofipol FITS product (its header has `SOFIPROD`).
fn is_product(path: &Path) -> bool {
    sofipol_calib::fits::read_header(path).is_ok_and(|h| h.contains(sofipol_calib::classify::PRODUCT_KEYWORD))
}
