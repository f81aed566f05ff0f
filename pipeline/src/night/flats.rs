//! The night's flats: a calibration flat file, else dome flats, else a superflat from the
//! night's own sky, built once for the whole night.
use std::collections::BTreeMap;
use std::path::PathBuf;

use rayon::prelude::*;
use sofipol_calib::Profile;

use crate::catalog::provenance::{FlatFileError, FlatProvenance};
use crate::catalog::Failure;
use crate::reduce::TargetParams;

/// The flats a night uses, and what was done.
#[derive(Debug, Clone, Default)]
pub struct NightFlats {
    /// The flats (None: no flat-fielding).
    pub set: Option<sofipol_calib::flat::FlatSet>,
    /// Provenance: which flats, from which frames (catalog provenance `flat`).
    pub provenance: FlatProvenance,
    /// Flat frames that could not be used, with the reason.
    pub failures: Vec<Failure>,
}

/// The flats that `calibration.json` of `calibration.calib_dir` (`--calib CALDIR`, a
/// directory written by `sofipol calib` or its calibration.json) lists, as paths in that
/// directory; none when it lists none or cannot be read (the calibration's own reading
/// reports that).
pub fn calib_dir_flat_files(params: &TargetParams) -> Vec<PathBuf> {
    let Some(dir) = params.calibration.calib_dir.as_ref() else {
        return Vec::new();
    };
    let dir = if dir.is_dir() {
        dir.clone()
    } else {
        dir.parent().map(PathBuf::from).unwrap_or_default()
    };
    crate::calibration::Calibration::read(&dir)
        .map(|c| c.flats.iter().map(|f| dir.join(f)).collect())
        .unwrap_or_default()
}

/// The night's flats from calibration flat files (`origin`: "flat" for `--flat`,
/// "calib_dir" for `--calib`): each read and checked against the detector's size; a file
/// that cannot be used is a failure, the others are used.
fn flats_from_files(files: &[PathBuf], origin: &str, profile: &Profile) -> NightFlats {
    use sofipol_calib::flat::{read_flat, FlatSet};
    let mut out = NightFlats::default();
    let want = (profile.geometry.ny, profile.geometry.nx);
    let mut flats = Vec::new();
    let mut errors = Vec::new();
    for p in files {
        match read_flat(p).and_then(|f| {
            // A flat of another geometry would leave every orientation un-flat-fielded
            // (flagged per target): refused once, by name, instead.
            if f.shape() == want {
                Ok(f)
            } else {
                Err(sofipol_calib::Error::Stage {
                    stage: "flat",
                    reason: format!(
                        "image is {} x {} px (NAXIS2 x NAXIS1), the instrument profile's detector is {} x {}: not used",
                        f.shape().0,
                        f.shape().1,
                        want.0,
                        want.1
                    ),
                })
            }
        }) {
            Ok(f) => flats.push(f),
            Err(e) => {
                errors.push(FlatFileError {
                    file: p.display().to_string(),
                    error: e.to_string(),
                });
                out.failures.push(Failure {
                    file: p.display().to_string(),
                    error: format!("calibration flat: {e}"),
                });
            }
        }
    }
    out.provenance = FlatProvenance {
        errors: Some(errors),
        flats: (!flats.is_empty()).then(|| flats.iter().map(|f| f.provenance()).collect()),
        from: Some(origin.to_string()),
        ..FlatProvenance::mode(if flats.is_empty() { "none" } else { "file" })
    };
    if !flats.is_empty() {
        out.set = Some(FlatSet::new(flats));
    }
    out
}

/// Build the night's flats, the first of: the calibration flat files of the settings
/// (`--flat`); the night's dome flats (lamp on - off per rotator angle); the flats of the
/// other night's calibration directory (`--calib CALDIR`); a superflat per filter from
/// `superflat_frames` (at least `flat_options.min_values` frames). `params.no_flat`: none.
pub fn night_flats(
    dome_flats: &[PathBuf],
    superflat_frames: &BTreeMap<String, Vec<PathBuf>>,
    profile: &Profile,
    params: &TargetParams,
) -> NightFlats {
    use sofipol_calib::flat::{build_flats, superflat, FlatSet};
    let mut out = NightFlats::default();
    if params.no_flat {
        out.provenance = FlatProvenance::mode("none (no_flat)");
        return out;
    }
    if !params.flat.is_empty() {
        return flats_from_files(&params.flat, "flat", profile);
    }
    if !dome_flats.is_empty() {
        let (set, problems) = build_flats(dome_flats, profile, &params.flat_options);
        out.failures.extend(problems.into_iter().map(|(p, e)| Failure {
            file: p.display().to_string(),
            error: e,
        }));
        if !set.is_empty() {
            out.provenance = FlatProvenance {
                flats: Some(set.flats.iter().map(|f| f.provenance()).collect()),
                ..FlatProvenance::mode("dome")
            };
            out.set = Some(set);
            return out;
        }
    }
    let caldir = calib_dir_flat_files(params);
    if !caldir.is_empty() {
        return flats_from_files(&caldir, "calib_dir", profile);
    }
    let mut flats = Vec::new();
    let mut notes = Vec::new();
    // Only the target strips are reduced unless whole frames are wanted: build the
    // superflat on those rows (a third of the detector) and leave 1 elsewhere.
    let g = &profile.geometry;
    let [r0, r1] = g.measured_rows();
    let crop = !params.full_frame_sky && params.save_intermediate.is_none() && r1 > r0;
    let cropped_profile = profile.cropped_rows(r0, r1);
    for (filter, paths) in superflat_frames {
        // Only the rows used are read (cfitsio reads a row range).
        let rows = crop.then_some((r0, r1));
        let frames: Vec<sofipol_calib::Frame> = paths
            .par_iter()
            .filter_map(|p| sofipol_calib::fits::read_frame_rows(p, rows).ok())
            .map(|f| {
                if crop && f.shape().0 >= r1 {
                    f.crop_rows(r0, r1)
                } else {
                    f
                }
            })
            .collect();
        let cropped = crop && frames.first().is_some_and(|f| f.shape().0 == r1 - r0);
        let built = if cropped {
            superflat(&frames, &cropped_profile, &params.flat_options).map(|f| {
                let ny = paths
                    .first()
                    .and_then(|p| sofipol_calib::fits::read_header(p).ok())
                    .and_then(|h| h.get_i64("NAXIS2").ok())
                    .map(|n| n as usize)
                    .unwrap_or(g.ny)
                    .max(r1);
                f.embed_rows(r0, ny)
            })
        } else {
            superflat(&frames, profile, &params.flat_options)
        };
        match built {
            Ok(f) => flats.push(f),
            Err(e) => notes.push(format!("filter {filter}: no superflat: {e}")),
        }
    }
    out.provenance = FlatProvenance {
        flats: Some(flats.iter().map(|f| f.provenance()).collect()),
        notes: Some(notes),
        ..FlatProvenance::mode(if flats.is_empty() { "none" } else { "superflat" })
    };
    if !flats.is_empty() {
        out.set = Some(FlatSet::new(flats));
    }
    out
}
