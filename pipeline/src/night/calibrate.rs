//! The night's standards, reduced as single stars, and the calibration of the targets with
//! them (or with another night's calibration).
use ndarray::Array2;
use sofipol_calib::flat::FlatSet;
use sofipol_calib::Profile;

use super::{reduce_sequences, Hooks};
use crate::calibration::{self, CalibSetup, Calibration, CalibrationSummary};
use crate::catalog::{Catalog, Target};
use crate::reduce::TargetParams;
use crate::sequence::Sequence;

/// Reduce standard sequences as single stars (in the current rayon pool): their targets and
/// the files that could not be used.
pub fn reduce_standards(
    standards: &[Sequence],
    profile: &Profile,
    params: &TargetParams,
    night_mask: Option<&Array2<u8>>,
    flats: Option<&FlatSet>,
) -> Catalog {
    let single_star = calibration::standard_params(params);
    reduce_sequences(standards, profile, &single_star, night_mask, flats, &Hooks::default()).catalog
}

/// Calibrate a reduced catalog of targets: reduce the standards, measure the calibration
/// from them (unless another night's is given or none is wanted), re-solve every target
/// component. The standards' unusable files join the catalog's failures. Returns the
/// calibration used and the summary lines.
pub fn calibrate(
    cat: &mut Catalog,
    standards: &[Sequence],
    profile: &Profile,
    params: &TargetParams,
    setup: &CalibSetup,
    night_mask: Option<&Array2<u8>>,
    flats: Option<&FlatSet>,
) -> (Option<Calibration>, CalibrationSummary) {
    let std_cat = if standards.is_empty() {
        Catalog::default()
    } else {
        reduce_standards(standards, profile, params, night_mask, flats)
    };
    cat.failures.extend(std_cat.failures);
    cat.failures.sort_by(|a, b| a.file.cmp(&b.file));
    let std_targets: Vec<Target> = std_cat.targets;
    calibration::calibrate_catalog(
        cat,
        std_targets,
        &setup.table,
        profile,
        setup.source(),
        &setup.params,
        params.measure.debias,
        params.measure.cut_snr,
    )
}
