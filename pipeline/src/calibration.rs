//! The instrumental calibration of a night: standards -> `calibration.json` -> every target.
//!
//! ```text
//! standard sequences (DPR TYPE 'STD'), reduced as single stars
//!   -> matched to the standards table (name ignoring case, spaces, '_'; filter)
//!   -> per filter: c and theta0 (and parity) fitted jointly over every orientation of
//!      every standard, table values as nuisances with their errors
//!      (stokes::calibration::joint); when the standards cannot separate c from theta0:
//!      c from the unpolarized ones only, the profile's angles, `incomplete` says why
//!   -> Calibration (written as calibration.json by `sofipol calib`, read with --calib)
//! every target component: per-orientation F (from the measurement)
//!   -> analyzer angles from the calibration's theta0, parity (else the profile's)
//!   -> Stokes solve (stokes::calibration::solve_with_fallback): ratio method on balanced
//!      angles, else F - c with sigma_c propagated, else free offset (3+ angles), else
//!      plain least squares flagged `uncalibrated`; a chosen method that cannot apply
//!      falls back to that choice (flag `stokes_method_failed: ...; fell back to ...`)
//!   -> flag `calibration_incomplete` when the filter's calibration is incomplete
//! ```
//! The telescope's own polarization (tertiary mirror, turning with the parallactic angle) is
//! fitted with c and theta0 when the standards separate it, and removed from every
//! component's F at its frames' parallactic angles before the solve (`telescope`); otherwise
//! the components are flagged `telescope_polarization_uncorrected`.
//!
//! The photometry is not redone: the solve works on the per-orientation F values each
//! component carries in its `orientations` field.
use std::path::Path;

use sofipol_calib::Profile;

use crate::catalog::flags::has;
pub use crate::catalog::polarimetric_calibration::{
    Calibration, FilterCalibration, TelescopeCalibration, CALIBRATION_FILE, CALIBRATION_SCHEMA,
};
use crate::catalog::{CalibrationState, Catalog, Component, Flag, FlagCode, StandardResult, Status, Target};
use crate::foreground::{set_target_foreground, EstimateParams, FieldStarQu};
pub use crate::reduce::params::CalibrationParams;
pub use crate::solve::{calibration_errors, orientation_values, resolve_component, SolveSettings};
use crate::standards::{StandardStar, StandardsTable};
use crate::stokes::calibration::{
    joint::{fit_joint_with, JointOptions},
    OrientationF, StandardObservation,
};
use crate::stokes::fresnel::TelescopePrior;
use crate::stokes::inversion::Debias;
use crate::stokes::propagation::{self, CAL_THETA0};

impl Calibration {
    /// Read `calibration.json` from a calibration directory (or a file path).
    pub fn read(path: &Path) -> crate::error::Result<Calibration> {
        use crate::error::Error;
        let file = if path.is_dir() {
            path.join(CALIBRATION_FILE)
        } else {
            path.to_path_buf()
        };
        let text = sofipol_calib::input::read_to_string(&file, sofipol_calib::input::MAX_OPTION_FILE_BYTES).map_err(
            |source| Error::Io {
                path: file.clone(),
                source,
            },
        )?;
        let c: Calibration = serde_json::from_str(&text).map_err(|e| Error::CalibrationFile {
            path: file.clone(),
            reason: e.to_string(),
        })?;
        if c.schema_version.split('.').next() != CALIBRATION_SCHEMA.split('.').next() {
            return Err(Error::CalibrationFile {
                path: file,
                reason: format!(
                    "schema_version = '{}' is not compatible with {CALIBRATION_SCHEMA}",
                    c.schema_version
                ),
            });
        }
        let mut c = c;
        validate::validate(&mut c).map_err(|source| Error::CalibrationValue { path: file, source })?;
        Ok(c)
    }

    /// Write `calibration.json` into a directory (atomically).
    pub fn write(&self, dir: &Path) -> std::io::Result<std::path::PathBuf> {
        std::fs::create_dir_all(dir)?;
        let p = dir.join(CALIBRATION_FILE);
        crate::io::write_json_atomic(&p, self).map_err(|e| std::io::Error::other(e.to_string()))?;
        Ok(p)
    }
}

fn table_entry_for(t: &Target, table: &StandardsTable) -> (Option<StandardStar>, Vec<Flag>) {
    let filter = t.filter.as_deref().unwrap_or("");
    match table.find(&t.object, filter) {
        Some(e) => (Some(e.clone()), vec![]),
        None if table.knows(&t.object) => (None, vec![Flag::with_detail(FlagCode::NoTableValuesForFilter, filter)]),
        None => (None, vec![Flag::new(FlagCode::NotInStandardsTable)]),
    }
}

fn sequence_of(t: &Target) -> String {
    t.sequence_id().to_string()
}

fn filter_of(t: &Target) -> String {
    t.filter.clone().unwrap_or_default()
}

/// Measure the calibration from reduced standard sequences (raw values: before any
/// calibration). Standards not in the table, without a measurement, or in a filter without
/// table values are skipped. With `fit_telescope`, the telescope's polarization is fitted
/// too when the standards separate it. `None` when no filter gets anything.
pub fn measure(
    standards: &[Target],
    table: &StandardsTable,
    profile: &Profile,
    fit_telescope: bool,
) -> Option<Calibration> {
    let mut by_filter: std::collections::BTreeMap<String, Vec<(String, StandardObservation)>> = Default::default();
    let mut frames = Vec::new();
    for t in standards {
        let (Some(entry), _) = table_entry_for(t, table) else {
            continue;
        };
        let Some(c) = t.components.first() else { continue };
        let rows = crate::solve::orientation_rows(c, profile);
        if rows.len() < 2 {
            continue;
        }
        let so = StandardObservation {
            name: entry.name.clone(),
            posang_deg: rows.iter().map(|r| r.posang_deg).collect(),
            f: rows
                .iter()
                .map(|r| OrientationF {
                    analyzer_deg: f64::NAN,
                    f: r.f,
                    sigma_f: r.sigma_f,
                })
                .collect(),
            parallactic_2eta: rows.iter().map(|r| r.parallactic_2eta).collect(),
            p: entry.p,
            sigma_p: entry.sigma_p,
            gamma_deg: entry.gamma_deg,
            sigma_gamma_deg: entry.sigma_gamma_deg,
        };
        frames.extend(t.input_files.iter().flatten().cloned());
        by_filter.entry(filter_of(t)).or_default().push((sequence_of(t), so));
    }
    let mut filters = Vec::new();
    for (filter, list) in by_filter {
        let obs: Vec<StandardObservation> = list.iter().map(|(_, o)| o.clone()).collect();
        let opts = JointOptions {
            default_parity: profile.angles.parity,
            profile_theta0_deg: profile.angles.zero_point_deg,
            fit_telescope,
            telescope_prior: TelescopePrior::of(&profile.telescope, &filter),
        };
        let Some(j) = fit_joint_with(&obs, &opts) else {
            continue;
        };
        let ids = |from: &[usize]| from.iter().map(|&i| list[i].0.clone()).collect::<Vec<String>>();
        let mut covariance = j.covariance;
        // No polarized standard (and c measured): theta0 is the profile's, its uncertainty
        // a systematic error of every angle of the filter.
        let zero_point_from_profile = (j.angles.is_none() && j.incomplete.is_none() && j.offset.is_some()).then(|| {
            covariance[CAL_THETA0][CAL_THETA0] = profile.angles.sigma_zero_point_deg.powi(2);
            format!(
                "no polarized standard in this filter: theta0 = {} +- {} deg is the profile's",
                profile.angles.zero_point_deg, profile.angles.sigma_zero_point_deg
            )
        });
        filters.push(FilterCalibration {
            filter,
            offset: j.offset,
            offset_standards: ids(&j.offset_from),
            angle_standards: ids(&j.angles_from),
            angles: j.angles,
            cov_c_theta0_deg: j.cov_c_theta0_deg,
            incomplete: j.incomplete,
            telescope: j.telescope.map(|t| TelescopeCalibration::from_fit(&t, &j.covariance)),
            telescope_uncorrected: if fit_telescope {
                j.telescope_problem
            } else if profile.telescope.polarizes {
                Some(TELESCOPE_NOT_FITTED.into())
            } else {
                None
            },
            telescope_from_prior: j.telescope_from_prior,
            covariance: Some(covariance),
            covariance_parameters: Some(propagation::CAL_PARAMETERS.iter().map(|s| s.to_string()).collect()),
            zero_point_from_profile,
        });
    }
    if filters.is_empty() {
        return None;
    }
    frames.sort();
    Some(Calibration {
        schema_version: CALIBRATION_SCHEMA.into(),
        filters,
        frames,
        flats: vec![],
        provenance: crate::catalog::Provenance {
            standards_table: Some(serde_json::json!(table.sources)),
            ..crate::catalog::Provenance::build()
        },
    })
}

/// Why the telescope's polarization is not corrected when the settings say so.
const TELESCOPE_NOT_FITTED: &str = "not fitted (calibration.no_telescope_correction)";

/// What [`calibrate_catalog`] did, for the run summary.
#[derive(Debug, Clone, Default)]
pub struct CalibrationSummary {
    /// Lines for stderr (why numbers may be biased, what was used).
    pub lines: Vec<String>,
    /// Components flagged `uncalibrated`.
    pub n_uncalibrated: usize,
    /// Of those, the components whose P/sigma passed but that were refused by the cut for
    /// it (without `--allow-uncalibrated`).
    pub n_refused_uncalibrated: usize,
    /// Components flagged `calibration_incomplete`.
    pub n_incomplete: usize,
    /// Components flagged `zero_point_from_profile`.
    pub n_zero_point_from_profile: usize,
    /// Components whose chosen Stokes method could not apply (`stokes_method_failed`).
    pub n_method_failed: usize,
    /// Components flagged `telescope_polarization_uncorrected`.
    pub n_telescope_uncorrected: usize,
    /// Components whose telescope term was removed at the value fitted with the mirror's
    /// prior (`telescope_polarization_from_prior`).
    pub n_telescope_from_prior: usize,
    /// Components whose telescope term was neither removed nor carried
    /// (`telescope_polarization_unaccounted`).
    pub n_telescope_unaccounted: usize,
    /// Of the components whose P/sigma passed, those the cut refused because a term that
    /// biases P is missing (the offset, the telescope's term), without `--allow-uncalibrated`.
    pub n_refused_incomplete: usize,
}

/// Whether component `c` is uncalibrated: a term that biases its P is neither removed nor
/// carried in its error (its calibration state says so; flagged [`FlagCode::Uncalibrated`]:
/// 2 orientations without the offset c, or [`FlagCode::TelescopeUnaccounted`]). Such
/// components fail the cut, leave the statistics and make a night exit 2, unless allowed.
pub fn is_uncalibrated(c: &Component) -> bool {
    has(&c.flags, FlagCode::Uncalibrated)
        || has(&c.flags, FlagCode::TelescopeUnaccounted)
        || c.calibration.is_some_and(|s| !s.complete_for_the_cut())
}

/// The components of `cat`'s targets that are uncalibrated ([`is_uncalibrated`]).
pub fn uncalibrated_components(cat: &Catalog) -> usize {
    cat.targets
        .iter()
        .flat_map(|t| &t.components)
        .filter(|c| is_uncalibrated(c))
        .count()
}

/// Flag `calibration_incomplete` when the filter's calibration is incomplete (its angles
/// are the profile's; `FilterCalibration::incomplete` says why). Returns whether flagged.
fn flag_incomplete(c: &mut Component, cal: Option<&FilterCalibration>) -> bool {
    c.flags.retain(|f| !f.is(FlagCode::CalibrationIncomplete));
    let incomplete = cal.is_some_and(|f| f.incomplete.is_some());
    if incomplete {
        c.flags.push(Flag::new(FlagCode::CalibrationIncomplete));
    }
    incomplete
}

/// After a target component is re-solved: flag an incomplete calibration and count it,
/// and count a Stokes method that could not apply, for the run summary.
fn note_calibration_state(c: &mut Component, cal: Option<&FilterCalibration>, summary: &mut CalibrationSummary) {
    summary.n_incomplete += usize::from(flag_incomplete(c, cal));
    c.flags.retain(|f| !f.is(FlagCode::ZeroPointFromProfile));
    if cal.is_some_and(|f| f.zero_point_from_profile.is_some()) && c.q.is_finite() {
        c.flags.push(Flag::new(FlagCode::ZeroPointFromProfile));
        summary.n_zero_point_from_profile += 1;
    }
    summary.n_method_failed += usize::from(has(&c.flags, FlagCode::StokesMethodFailed));
    summary.n_telescope_uncorrected += usize::from(has(&c.flags, FlagCode::TelescopeUncorrected));
    summary.n_telescope_from_prior += usize::from(has(&c.flags, FlagCode::TelescopeFromPrior));
    summary.n_telescope_unaccounted += usize::from(has(&c.flags, FlagCode::TelescopeUnaccounted));
}

/// Where a calibration came from.
#[derive(Debug, Clone)]
pub enum CalibrationSource {
    /// Measured from this night's standards.
    Night,
    /// Read from a calibration directory (`--calib`).
    File(std::path::PathBuf, Box<Calibration>),
    /// None wanted (`no_calibration`).
    Disabled,
}

/// What the calibration of a catalog works with besides the catalog and its standards.
#[derive(Clone, Copy)]
pub struct CalibrationContext<'a> {
    /// The standards table (built-in and `--standards`).
    pub table: &'a StandardsTable,
    /// The instrument profile (angles, keywords).
    pub profile: &'a Profile,
    /// The calibration settings (Stokes method, telescope correction, opt-ins).
    pub params: &'a CalibrationParams,
    /// How P is debiased (the reduction's measure settings).
    pub debias: Debias,
    /// The cut in P/sigma.
    pub cut_snr: f64,
}

/// Calibrate a reduced catalog: measure the calibration from the standard sequences (or
/// use the given one), re-solve every target component with it and the chosen Stokes
/// method (the cut refuses uncalibrated components unless allowed), report the standards
/// in their own section, and record what was used in `catalog.calibration`; then the
/// photometric zero-points of the standards with a magnitude and every component's magnitude
/// ([`photometric::apply`]). Returns the calibration used and the summary.
pub fn calibrate_catalog(
    cat: &mut Catalog,
    standards: Vec<Target>,
    source: CalibrationSource,
    ctx: &CalibrationContext,
) -> (Option<Calibration>, CalibrationSummary) {
    let chosen = calibration_from(source, &standards, ctx);
    calibrate_catalog_with(cat, standards, chosen, ctx)
}

/// [`calibrate_catalog`] with the calibration already chosen ([`calibration_from`]: the
/// calibration and where it came from), e.g. before the science targets were reduced so
/// that each target's figure could be drawn as soon as it was reduced ([`resolved_target`]).
pub fn calibrate_catalog_with(
    cat: &mut Catalog,
    standards: Vec<Target>,
    (cal, origin): (Option<Calibration>, String),
    ctx: &CalibrationContext,
) -> (Option<Calibration>, CalibrationSummary) {
    let mut summary = CalibrationSummary::default();
    let other_night = !matches!(origin.as_str(), "night" | "disabled");
    for t in cat.targets.iter_mut() {
        resolve_target(t, cal.as_ref(), ctx, other_night, &mut summary);
    }
    night_foregrounds(&mut cat.targets, cal.as_ref(), ctx);
    standards_section(cat, standards, cal.as_ref(), ctx, &mut summary);
    cat.calibration = Some(crate::catalog::AppliedCalibration::new(
        cal.clone(),
        origin.clone(),
        ctx.params.stokes_method.name(),
    ));
    summary_lines(&mut summary, cal.as_ref(), &origin, ctx);
    let photometry = photometric::apply(cat, &ctx.profile.photometry);
    summary.lines.extend(photometric::lines(&photometry));
    (cal, summary)
}

/// A target as [`calibrate_catalog_with`] leaves it in the catalog, for one target alone:
/// its components re-solved with `cal` (which came from `origin`), the cut and Delta-gamma
/// updated. The function the catalog's calibration runs per target, so a figure drawn
/// from it shows the catalog's numbers, except the foreground and the Delta-gamma after
/// subtracting it: here from the target's field alone (flat prior), in the catalog from
/// the night's fields together (`night_foregrounds`).
pub fn resolved_target(t: &Target, cal: Option<&Calibration>, origin: &str, ctx: &CalibrationContext) -> Target {
    let mut t = t.clone();
    let other_night = !matches!(origin, "night" | "disabled");
    resolve_target(&mut t, cal, ctx, other_night, &mut CalibrationSummary::default());
    t
}

/// The calibration to apply, and where it came from (`night`, the file, `disabled`):
/// measured from the night's standards, read, or none; without the telescope's term when
/// the settings say so.
pub fn calibration_from(
    source: CalibrationSource,
    standards: &[Target],
    ctx: &CalibrationContext,
) -> (Option<Calibration>, String) {
    let CalibrationContext {
        table, profile, params, ..
    } = *ctx;
    let fit_telescope = !params.no_telescope_correction && profile.telescope.polarizes;
    let (mut cal, origin) = match source {
        CalibrationSource::Disabled => (None, "disabled".to_string()),
        CalibrationSource::File(p, c) => (Some(*c), p.display().to_string()),
        CalibrationSource::Night => (measure(standards, table, profile, fit_telescope), "night".to_string()),
    };
    if !fit_telescope {
        // Another night's telescope term is not applied either (nor any, when the profile's
        // telescope does not polarize).
        for f in cal.iter_mut().flat_map(|c| c.filters.iter_mut()) {
            if f.telescope.take().is_some() {
                f.telescope_uncorrected = profile.telescope.polarizes.then(|| TELESCOPE_NOT_FITTED.into());
            }
        }
    }
    (cal, origin)
}

/// Re-solve every component of target `t` with the calibration ([`resolve_component`]);
/// without `allow_uncalibrated`, an uncalibrated component fails the cut.
fn resolve_target(
    t: &mut Target,
    cal: Option<&Calibration>,
    ctx: &CalibrationContext,
    other_night: bool,
    summary: &mut CalibrationSummary,
) {
    let CalibrationContext {
        profile,
        params,
        debias,
        cut_snr,
        ..
    } = *ctx;
    let filter = filter_of(t);
    let fc = cal.and_then(|c| c.for_filter(&filter));
    let settings = SolveSettings {
        profile,
        cal: fc,
        method: params.stokes_method,
        debias,
        cut_snr,
        telescope_prior: TelescopePrior::of(&profile.telescope, &filter),
        telescope_polarizes: profile.telescope.polarizes,
    };
    let mut n_unc = 0;
    for c in t.components.iter_mut() {
        n_unc += usize::from(resolve_component(c, &settings));
        note_origin(c, other_night);
        if !params.allow_uncalibrated {
            refuse_incomplete(c, summary);
        }
        note_calibration_state(c, fc, summary);
    }
    summary.n_uncalibrated += n_unc;
    // The field stars: the same re-solve and the same refusals; the night's counts (and its
    // exit code) are the binaries' alone.
    let mut field_summary = CalibrationSummary::default();
    for s in t.field_stars.iter_mut().flatten() {
        resolve_component(&mut s.star, &settings);
        note_origin(&mut s.star, other_night);
        if !params.allow_uncalibrated {
            refuse_incomplete(&mut s.star, &mut field_summary);
        }
        note_calibration_state(&mut s.star, fc, &mut field_summary);
        s.settle();
    }
    let (qu, errors) = foreground_inputs(t, cal, ctx);
    match qu {
        // Field stars found: the binary's foreground estimated from them (or flagged too
        // few), and both Delta-gammas computed. None found (or none searched for): no
        // foreground and no flag, the Delta-gamma as without field stars.
        Some(qu) => {
            set_target_foreground(t, &qu, &EstimateParams::default(), errors.as_ref());
        }
        None => t.update_delta_gamma(errors.as_ref()),
    }
}

/// What the foreground's estimate of target `t` takes: its field stars as calibrated (None
/// when it has none), and the calibration's covariance for its filter (None when no
/// calibration applies).
fn foreground_inputs(
    t: &Target,
    cal: Option<&Calibration>,
    ctx: &CalibrationContext,
) -> (
    Option<Vec<FieldStarQu>>,
    Option<crate::stokes::propagation::CalibrationCovariance>,
) {
    let filter = filter_of(t);
    let fc = cal.and_then(|c| c.for_filter(&filter));
    let prior = TelescopePrior::of(&ctx.profile.telescope, &filter);
    let errors = (fc.is_some() || prior.is_some()).then(|| calibration_errors(fc, prior.as_ref()));
    let qu = t.field_stars.as_deref().filter(|s| !s.is_empty()).map(|stars| {
        stars
            .iter()
            .map(|s| field_star_qu(s, ctx.params.allow_uncalibrated))
            .collect()
    });
    (qu, errors)
}

/// The night's foregrounds: every target with field stars and a sky position estimated
/// again with the night's other fields informing the prior of the foreground's variation
/// ([`crate::foreground::estimate_night`]), its catalog entries and Delta-gammas updated.
/// A target alone (the per-target pass, [`resolved_target`]) has the flat prior.
fn night_foregrounds(targets: &mut [Target], cal: Option<&Calibration>, ctx: &CalibrationContext) {
    let finite = |v: Option<f64>| v.filter(|v| v.is_finite());
    let inputs: Vec<(
        usize,
        String,
        Vec<FieldStarQu>,
        Option<crate::stokes::propagation::CalibrationCovariance>,
    )> = targets
        .iter()
        .enumerate()
        .filter(|(_, t)| finite(t.ra_deg).is_some() && finite(t.dec_deg).is_some())
        .filter_map(|(i, t)| {
            let (qu, errors) = foreground_inputs(t, cal, ctx);
            qu.map(|qu| (i, filter_of(t), qu, errors))
        })
        .collect();
    // Each filter's fields alone: the foreground's size differs between filters.
    let mut filters: Vec<&str> = inputs.iter().map(|(_, f, ..)| f.as_str()).collect();
    filters.sort_unstable();
    filters.dedup();
    let mut results = Vec::new();
    for filter in filters {
        let group: Vec<&(usize, String, Vec<FieldStarQu>, _)> = inputs.iter().filter(|x| x.1 == filter).collect();
        if group.len() < 2 {
            continue;
        }
        let fields: Vec<(f64, f64, &[FieldStarQu])> = group
            .iter()
            .map(|(i, _, qu, _)| {
                let t = &targets[*i];
                (
                    t.ra_deg.unwrap_or_default(),
                    t.dec_deg.unwrap_or_default(),
                    qu.as_slice(),
                )
            })
            .collect();
        let outcomes = crate::foreground::estimate_night(&fields, &EstimateParams::default());
        results.extend(group.iter().map(|(i, _, _, e)| (*i, *e)).zip(outcomes));
    }
    for ((i, errors), outcome) in results {
        crate::foreground::apply_outcome(&mut targets[i], outcome, errors.as_ref());
    }
}

/// A calibrated field star as the foreground's estimate takes it (its total errors: the
/// measurement's and the calibration's). A star whose calibration leaves a term that biases
/// q and u (no offset c: no standards, another night's calibration without its filter) is
/// not used, as its components would not pass the cut, unless `allow_uncalibrated`.
fn field_star_qu(s: &crate::catalog::field_stars::FieldStar, allow_uncalibrated: bool) -> FieldStarQu {
    let calibrated = allow_uncalibrated || s.star.calibration.is_some_and(|c| c.complete_for_the_cut());
    FieldStarQu {
        id: s.id.clone(),
        q: s.star.pol.q,
        u: s.star.pol.u,
        sigma_q: s.star.pol.sigma_q,
        sigma_u: s.star.pol.sigma_u,
        cov_qu: s.star.cov_qu.unwrap_or(0.0),
        ra_deg: s.ra_deg.unwrap_or(f64::NAN),
        dec_deg: s.dec_deg.unwrap_or(f64::NAN),
        usable: s.usable && calibrated,
    }
}

/// A calibration read from another night: the terms it measured are marked so.
fn note_origin(c: &mut Component, other_night: bool) {
    if other_night {
        c.calibration = c.calibration.map(CalibrationState::from_another_night);
    }
}

/// The cut refuses a component whose calibration leaves a term that biases P neither
/// removed nor carried in its error (the offset c of 2 orientations without standards; the
/// telescope's term without a prior for the filter).
fn refuse_incomplete(c: &mut Component, summary: &mut CalibrationSummary) {
    if c.calibration.is_some_and(|s| !s.complete_for_the_cut()) {
        if has(&c.flags, FlagCode::Uncalibrated) {
            summary.n_refused_uncalibrated += usize::from(c.passes_cut);
        } else {
            summary.n_refused_incomplete += usize::from(c.passes_cut);
        }
        c.passes_cut = false;
    }
}

/// The standards, reduced as single stars, calibrated like the targets: each with its
/// table values, its measurement, the residuals and what the calibration took from it.
fn standards_section(
    cat: &mut Catalog,
    standards: Vec<Target>,
    cal: Option<&Calibration>,
    ctx: &CalibrationContext,
    summary: &mut CalibrationSummary,
) {
    let CalibrationContext {
        table,
        profile,
        params,
        debias,
        cut_snr,
    } = *ctx;
    let method = params.stokes_method;
    let used_offset: Vec<String> = cal
        .iter()
        .flat_map(|c| c.filters.iter().flat_map(|f| f.offset_standards.clone()))
        .collect();
    let used_angles: Vec<String> = cal
        .iter()
        .flat_map(|c| c.filters.iter().flat_map(|f| f.angle_standards.clone()))
        .collect();
    for t in standards {
        let (entry, mut flags) = table_entry_for(&t, table);
        let seq = sequence_of(&t);
        let filter = filter_of(&t);
        let fc = cal.as_ref().and_then(|c| c.for_filter(&filter));
        let mut measured = t.components.first().cloned();
        if let Some(c) = measured.as_mut() {
            c.flags.retain(|f| !f.is(FlagCode::CompanionNotFound));
            resolve_component(
                c,
                &SolveSettings {
                    profile,
                    cal: fc,
                    method,
                    debias,
                    cut_snr,
                    telescope_prior: TelescopePrior::of(&profile.telescope, &filter),
                    telescope_polarizes: profile.telescope.polarizes,
                },
            );
            flag_incomplete(c, fc);
        }
        if let Some(e) = t.error.as_ref().filter(|_| t.status == Status::Failed) {
            flags.push(Flag::with_detail(FlagCode::Failed, e.as_str()));
        }
        let res = match (&entry, &measured) {
            (Some(e), Some(m)) if m.p.is_finite() => residuals::table_residuals(m, e, profile, fc),
            _ => Default::default(),
        };
        for f in &res.flags {
            summary.lines.push(format!(
                "standard {} ({seq}, {filter}): {f} (measurement error and table error only)",
                entry.as_ref().map_or(t.object.as_str(), |e| e.name.as_str())
            ));
        }
        flags.extend(res.flags);
        let mut used_for = Vec::new();
        if used_offset.contains(&seq) {
            used_for.push("offset".to_string());
        }
        if used_angles.contains(&seq) {
            used_for.push("angles".to_string());
        }
        cat.standards.push(StandardResult {
            name: entry
                .as_ref()
                .map(|e| e.name.clone())
                .unwrap_or_else(|| t.object.clone()),
            object: t.object.clone(),
            sequence: seq,
            filter,
            status: if measured.as_ref().is_some_and(|m| m.q.is_finite()) {
                Status::Ok
            } else {
                Status::Failed
            },
            table: entry,
            measured,
            residual_p_sigma: res.p_sigma,
            residual_gamma_deg: res.gamma_deg,
            residual_gamma_sigma: res.gamma_sigma,
            residual_qu_chi2: res.qu_chi2,
            used_for,
            flags,
            ra_deg: t.ra_deg,
            dec_deg: t.dec_deg,
            dit_s: t.dit_s,
            mjd_mean: t.mjd_mean,
            input_files: t.input_files.clone(),
            frame_quality: t.frame_quality.clone(),
        });
    }
}

/// The summary's lines: what was refused and why, and the calibration of each filter.
fn summary_lines(summary: &mut CalibrationSummary, cal: Option<&Calibration>, origin: &str, ctx: &CalibrationContext) {
    let params = ctx.params;
    let method = params.stokes_method;
    if summary.n_uncalibrated > 0 {
        summary.lines.push(format!(
            "{} component(s) flagged 'uncalibrated': with 2 orientations the beam throughput ratio and the \
             instrumental polarization add a constant to F = (o-e)/(o+e) that biases q and u \
             (c ~ (1-k)/(1+k) + p_inst, e.g. 1.5 % for k = 0.97), and the angle zero-point is the \
             profile's; the night has no usable standards ({}). {} Observe unpolarized and polarized \
             standards, use --calib CALDIR from another night, or observe 4 orientations.",
            summary.n_uncalibrated,
            if cal.is_none() {
                "no calibration"
            } else {
                "no offset for this filter"
            },
            if params.allow_uncalibrated {
                "They may pass the cut (--allow-uncalibrated), flagged."
            } else {
                "They never pass the cut (--allow-uncalibrated lets them, flagged)."
            }
        ));
    }
    if summary.n_method_failed > 0 {
        summary.lines.push(format!(
            "{} component(s) flagged 'stokes_method_failed': --stokes-method {method} cannot be applied to \
             their orientations; solved with the automatic choice instead (the flag names it; an \
             uncalibrated fallback never passes the cut)",
            summary.n_method_failed
        ));
    }
    if let Some(c) = &cal {
        for f in &c.filters {
            if let Some(why) = &f.incomplete {
                summary.lines.push(format!(
                    "calibration ({origin}) {} incomplete: {why}; angle zero-point from the profile, \
                     its components flagged '{}' ({} in all filters)",
                    f.filter,
                    FlagCode::CalibrationIncomplete.name(),
                    summary.n_incomplete
                ));
            }
            if let Some(why) = &f.zero_point_from_profile {
                summary.lines.push(format!(
                    "calibration ({origin}) {}: {why}, carried in every angle's error (not in Delta-gamma); \
                     its components flagged '{}'. A polarized standard in {} measures it",
                    f.filter,
                    FlagCode::ZeroPointFromProfile.name(),
                    f.filter
                ));
            }
        }
        for f in &c.filters {
            let off = f
                .offset
                .map(|o| {
                    format!(
                        "c = {:.5} +- {:.5} ({} standards)",
                        o.c,
                        o.sigma_c,
                        f.offset_standards.len()
                    )
                })
                .unwrap_or_else(|| "no offset".into());
            let ang = f
                .angles
                .map(|a| {
                    format!(
                        "theta0 = {:.2} +- {:.2} deg, parity {:+} ({})",
                        a.theta0_deg,
                        a.sigma_theta0_deg,
                        a.parity,
                        if a.parity_measured { "measured" } else { "profile" }
                    )
                })
                .unwrap_or_else(|| "angle zero-point from the profile".into());
            summary
                .lines
                .push(format!("calibration ({origin}) {}: {off}; {ang}", f.filter));
            let prior = TelescopePrior::of(&ctx.profile.telescope, &f.filter);
            match (&f.telescope, &f.telescope_uncorrected) {
                (Some(t), _) => summary.lines.push(format!(
                    "calibration ({origin}) {}: telescope polarization p_tel = {:.3} +- {:.3} %, \
                     psi_tel = {:.1} +- {:.1} deg{}, removed from every component at its frames' parallactic angles",
                    f.filter,
                    100.0 * t.p_tel,
                    100.0 * t.sigma_p_tel,
                    t.psi_tel_deg,
                    t.sigma_psi_tel_deg,
                    match (&f.telescope_from_prior, prior) {
                        (Some(why), Some(p)) => format!(
                            " FROM THE MIRROR'S PRIOR ({:.2} +- {:.2} %, {:.0} +- {:.0} deg; the standards alone: {why})",
                            100.0 * p.p_tel,
                            100.0 * p.sigma_p_tel,
                            p.psi_tel_deg,
                            p.sigma_psi_tel_deg
                        ),
                        (Some(why), None) => format!(" from the mirror's prior (the standards alone: {why})"),
                        _ => String::new(),
                    }
                )),
                (None, _) if !ctx.profile.telescope.polarizes => {}
                (None, why) => summary.lines.push(format!(
                    "calibration ({origin}) {}: telescope polarization not corrected: {}; {}",
                    f.filter,
                    why.as_deref().unwrap_or("the calibration has no telescope term"),
                    match prior {
                        Some(p) => format!(
                            "its expected size from the mirror ({:.2} +- {:.2} %) is carried in every error",
                            100.0 * p.p_tel,
                            100.0 * p.sigma_p_tel
                        ),
                        None => "the profile gives no mirror index for this filter: its components cannot pass the cut"
                            .to_string(),
                    }
                )),
            }
        }
    }
    if summary.n_telescope_uncorrected > 0 {
        summary.lines.push(format!(
            "{} component(s) flagged '{}': the telescope's own polarization \
             (tertiary mirror, of order 0.8 % in Ks, turning with the parallactic angle) is in their q and u, \
             its expected size carried in their errors and in Delta-gamma's; \
             it is the same vector for both stars of a binary and pulls their angles together. Observe \
             unpolarized standards at parallactic angles far apart, or use --calib CALDIR from a night that did.",
            summary.n_telescope_uncorrected,
            FlagCode::TelescopeUncorrected.name()
        ));
    }
    if summary.n_telescope_from_prior > 0 {
        summary.lines.push(format!(
            "{} component(s) flagged '{}': the standards did not separate the telescope's polarization; \
             it was removed at the value fitted with the mirror's prior, whose width is in their errors. \
             Unpolarized standards at parallactic angles far apart measure it.",
            summary.n_telescope_from_prior,
            FlagCode::TelescopeFromPrior.name()
        ));
    }
    if summary.n_telescope_unaccounted > 0 {
        summary.lines.push(format!(
            "{} component(s) flagged '{}': the telescope's polarization was neither removed nor carried \
             (the profile's [telescope.filters] has no index for their filter); {}",
            summary.n_telescope_unaccounted,
            FlagCode::TelescopeUnaccounted.name(),
            if ctx.params.allow_uncalibrated {
                "they may pass the cut (--allow-uncalibrated), flagged"
            } else {
                "they never pass the cut (--allow-uncalibrated lets them, flagged)"
            }
        ));
    }
}

/// Whether a sequence observes a standard star: `DPR TYPE` of its first readable frame is
/// 'STD' (docs/frame-format.md). Unreadable headers count as science (the reduction reports them).
pub fn is_standard_sequence(seq: &crate::sequence::Sequence, profile: &Profile) -> bool {
    let key = &profile.keywords.dpr_type;
    seq.orientations
        .iter()
        .flat_map(|o| &o.exposures)
        .find_map(|e| sofipol_calib::fits::read_header(&e.path).ok())
        .and_then(|h| h.get_str(key).ok())
        .is_some_and(|t| t.trim().eq_ignore_ascii_case("STD"))
}

/// Reduction settings for a standard: a single star, never a binary (no companion is
/// accepted, so none is searched for in the photometry), without field stars (the
/// standards section keeps the star alone).
pub fn standard_params(p: &crate::reduce::TargetParams) -> crate::reduce::TargetParams {
    let mut s = p.clone();
    s.measure.field_stars = false;
    s.measure.min_companion_snr = f64::INFINITY;
    s.measure.companion_hint = None;
    s
}

pub mod photometric;
pub mod setup;
pub use setup::CalibSetup;
pub mod residuals;
pub mod validate;

#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_telescope;
