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

/// The night's calibration chosen before its science targets are reduced: the standards
/// reduced (when the night measures its own), the calibration to apply and where it came
/// from. What [`finish`] applies to the catalog, and what a target's figure is drawn with as
/// soon as the target is reduced ([`Prepared::resolved`]).
pub struct Prepared {
    /// The standards as reduced.
    pub standards: Catalog,
    /// The calibration and where it came from ([`calibration::calibration_from`]).
    pub chosen: (Option<Calibration>, String),
}

/// Reduce the standards (in the current rayon pool) and choose the calibration: measured
/// from them, another night's (`--calib`) or none.
pub fn prepare(
    standards: &[Sequence],
    profile: &Profile,
    params: &TargetParams,
    setup: &CalibSetup,
    night_mask: Option<&Array2<u8>>,
    flats: Option<&FlatSet>,
) -> Prepared {
    let std_cat = if standards.is_empty() {
        Catalog::default()
    } else {
        reduce_standards(standards, profile, params, night_mask, flats)
    };
    let chosen = calibration::calibration_from(setup.source(), &std_cat.targets, &context(profile, params, setup));
    Prepared {
        standards: std_cat,
        chosen,
    }
}

/// What the calibration works with besides the catalog and its standards.
fn context<'a>(profile: &'a Profile, params: &TargetParams, setup: &'a CalibSetup) -> CalibrationContext<'a> {
    CalibrationContext {
        table: &setup.table,
        profile,
        params: &setup.params,
        debias: params.measure.debias,
        cut_snr: params.measure.cut_snr,
    }
}

impl Prepared {
    /// Target `t` as [`finish`] leaves it in the catalog (re-solved with the calibration,
    /// refused where another night's calibration lacks its filter), for one target alone:
    /// its foreground from its own field (flat prior), where the catalog's comes from the
    /// night's fields together.
    pub fn resolved(&self, t: &Target, profile: &Profile, params: &TargetParams, setup: &CalibSetup) -> Target {
        let (cal, origin) = &self.chosen;
        let mut t = calibration::resolved_target(t, cal.as_ref(), origin, &context(profile, params, setup));
        if let (Some((dir, _)), false) = (&setup.external, setup.params.no_calibration) {
            refuse_uncorrected_target(&mut t, &calibration_file(dir));
        }
        t
    }
}

/// Apply a [`prepare`]d calibration to a reduced catalog: every target component re-solved,
/// the standards' unusable files joined to the catalog's failures. Returns the calibration
/// used and the summary lines.
pub fn finish(
    cat: &mut Catalog,
    prepared: Prepared,
    profile: &Profile,
    params: &TargetParams,
    setup: &CalibSetup,
) -> (Option<Calibration>, CalibrationSummary) {
    let Prepared { standards, chosen } = prepared;
    cat.failures.extend(standards.failures);
    cat.failures.sort_by(|a, b| a.file.cmp(&b.file));
    let (cal, mut summary) =
        calibration::calibrate_catalog_with(cat, standards.targets, chosen, &context(profile, params, setup));
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
    let file = calibration_file(dir);
    let mut per_filter: std::collections::BTreeMap<String, usize> = Default::default();
    for t in cat.targets.iter_mut() {
        let n = refuse_uncorrected_target(t, &file);
        if n > 0 {
            *per_filter.entry(t.filter.clone().unwrap_or_default()).or_default() += n;
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

/// The calibration file of a `--calib` directory (or the file itself).
fn calibration_file(dir: &std::path::Path) -> std::path::PathBuf {
    if dir.is_dir() {
        dir.join(calibration::CALIBRATION_FILE)
    } else {
        dir.to_path_buf()
    }
}

/// [`refuse_uncorrected`] for one target: each component left `uncalibrated` fails the cut
/// with the flag `calibration_lacks_filter` naming `file`. The number of such components.
fn refuse_uncorrected_target(t: &mut Target, file: &std::path::Path) -> usize {
    let filter = t.filter.clone().unwrap_or_default();
    let mut n = 0;
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
        n += 1;
    }
    if n > 0 {
        t.update_delta_gamma(None);
    }
    n
}
