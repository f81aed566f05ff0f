//! The night's standards, reduced as single stars, and the calibration of the targets with
//! them (or with another night's calibration).
use ndarray::Array2;
use sofipol_calib::flat::FlatSet;
use sofipol_calib::Profile;

use super::{reduce_sequences, Hooks};
use crate::calibration::{self, CalibSetup, Calibration, CalibrationContext, CalibrationSummary};
use crate::catalog::flags::has;
use crate::catalog::{Catalog, Failure, Flag, FlagCode, Target};
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
    let (cal, mut summary) = calibration::calibrate_catalog(
        cat,
        std_targets,
        setup.source(),
        &CalibrationContext {
            table: &setup.table,
            profile,
            params: &setup.params,
            debias: params.measure.debias,
            cut_snr: params.measure.cut_snr,
        },
    );
    if let (Some((dir, _)), false) = (&setup.external, setup.params.no_calibration) {
        refuse_uncorrected(cat, dir, &mut summary);
    }
    (cal, summary)
}

/// With another night's calibration (`--calib`), a component left `uncalibrated` is one
/// whose filter that calibration has no offset c for: asked to be corrected and not
/// corrected, it never passes the cut (flag `calibration_lacks_filter: ...`), and the
/// calibration file is named under `failures` once per filter.
fn refuse_uncorrected(cat: &mut Catalog, dir: &std::path::Path, summary: &mut CalibrationSummary) {
    let file = if dir.is_dir() {
        dir.join(calibration::CALIBRATION_FILE)
    } else {
        dir.to_path_buf()
    };
    let mut per_filter: std::collections::BTreeMap<String, usize> = Default::default();
    for t in cat.targets.iter_mut() {
        let filter = t.filter.clone().unwrap_or_default();
        let mut changed = false;
        for c in t
            .components
            .iter_mut()
            .filter(|c| has(&c.flags, FlagCode::Uncalibrated))
        {
            c.passes_cut = false;
            c.flags.push(Flag::with_detail(
                FlagCode::CalibrationLacksFilter,
                format!(
                    "{} has no offset c for filter {filter}: q and u uncorrected",
                    file.display()
                ),
            ));
            *per_filter.entry(filter.clone()).or_default() += 1;
            changed = true;
        }
        if changed {
            t.update_delta_gamma(None);
        }
    }
    for (filter, n) in per_filter {
        let error = format!(
            "no offset c for filter {filter}: {n} component(s) of filter {filter} left uncorrected \
             (flags uncalibrated, {}), never passing the cut",
            FlagCode::CalibrationLacksFilter.name()
        );
        summary.lines.push(format!("{}: {error}", file.display()));
        cat.failures.push(Failure {
            file: file.display().to_string(),
            error,
        });
    }
    cat.failures.sort_by(|a, b| a.file.cmp(&b.file));
}
