//! One target sequence from raw files to a catalog entry: read -> bad pixels -> sky ->
//! measure ([`super::measure_sequence`]) -> Stokes ([`super::target_entry`]).
use std::path::{Path, PathBuf};

use ndarray::{s, Array2};
use serde::Serialize;
use sofipol_calib::flat::{self, FlatSet};
use sofipol_calib::{badpix, fits, sky, Frame, PixelSummary, Profile};

use super::{measure_sequence, target_entry, SkySubtractedOrientation, TargetParams};
use crate::catalog::{Failure, Flag, FlagCode, Status, Target};
use crate::error::Error;
use crate::sequence::Sequence;

/// Timings of the stages of one target, seconds.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct StageTimes {
    /// Reading FITS.
    pub read: f64,
    /// Bad-pixel detection.
    pub bad_pixels: f64,
    /// Flat fielding.
    pub flat: f64,
    /// Sky subtraction.
    pub sky: f64,
    /// Source finding, photometry and Stokes.
    pub measure: f64,
    /// Writing intermediates.
    pub write: f64,
}

/// Everything a target reduction produced.
pub struct TargetOutcome {
    /// The catalog entry.
    pub target: Target,
    /// Files that could not be used.
    pub failures: Vec<Failure>,
    /// Stage timings.
    pub times: StageTimes,
    /// Calibrated orientations (kept only when asked, for plots).
    pub calibrated: Option<Vec<SkySubtractedOrientation>>,
    /// Intermediate measurements (for plots).
    pub measured: Option<super::Measured>,
    /// The frame of every dither, per orientation in the order of `measured`'s dithers
    /// (empty when the target failed before its frames were calibrated).
    pub frame_files: Vec<Vec<PathBuf>>,
    /// The detector row of the measured positions' y = 0 (the positions are in the
    /// target strips' rows when only those were reduced): add it for detector pixels.
    pub row_offset: usize,
}

/// `target` with the sequence's mean pointing and time from the frames' headers
/// ([`Sequence::mean_ra_dec_deg`], [`Sequence::mean_mjd`]) and its frames' integration time
/// ([`Sequence::common_dit_s`]).
fn pointed(mut target: Target, seq: &Sequence) -> Target {
    let radec = seq.mean_ra_dec_deg();
    target.ra_deg = radec.map(|p| p.0);
    target.dec_deg = radec.map(|p| p.1);
    target.mjd_mean = seq.mean_mjd();
    target.dit_s = seq.common_dit_s();
    target
}

/// The field stars of `target` on the detector (their rows moved by `row0`, the reduced
/// rows' first) and on the sky: the target's pointing (A's position, as the export gives A)
/// offset by each star's separation and PA from A
/// ([`crate::export::offset_position`], the one B gets).
fn place_field_stars(target: &mut Target, row0: usize) {
    let pointing = target.ra_deg.zip(target.dec_deg);
    for s in target.field_stars.iter_mut().flatten() {
        s.y_px += row0 as f64;
        let sky = pointing.map(|(ra, dec)| crate::export::offset_position(ra, dec, s.separation_arcsec, s.pa_deg));
        s.ra_deg = sky.map(|p| p.0);
        s.dec_deg = sky.map(|p| p.1);
    }
}

/// A failed target, keeping the diagnostic flags gathered before the failure.
fn failed(seq: &Sequence, msg: String, flags: &[Flag], failures: Vec<Failure>, times: StageTimes) -> TargetOutcome {
    TargetOutcome {
        target: Target {
            error: Some(msg),
            sequence: Some(seq.id.clone()),
            input_files: Some(seq.files()),
            flags: Some(flags.to_vec()),
            ..pointed(Target::new(seq.object.clone(), Status::Failed), seq)
        },
        failures,
        times,
        calibrated: None,
        measured: None,
        frame_files: Vec::new(),
        row_offset: 0,
    }
}

/// Reduce one sequence. Never panics on bad input: problems become failures, flags or a
/// failed target. `night_mask`: the detector's defects already detected for the night
/// (used instead of per-target detection), full-frame. `flats`: the night's flats
/// (full-frame; the flat of each orientation is chosen by rotator angle and filter).
pub fn reduce_sequence(
    seq: &Sequence,
    profile: &Profile,
    params: &TargetParams,
    night_mask: Option<&Array2<u8>>,
    flats: Option<&FlatSet>,
    keep_frames: bool,
) -> TargetOutcome {
    let mut failures = Vec::new();
    let t = std::time::Instant::now();
    // Read every frame; a file that cannot be read is a failure, the rest goes on.
    let mut orients: Vec<LoadedOrientation> = Vec::new();
    // The sequence as read: problems (missing dithers...) are judged on the usable frames.
    let mut readable = seq.clone();
    // Only the rows the reduction keeps are read (reduce_loaded leaves such frames as they are).
    let rows = crop_of(profile, params);
    for (o, ro) in seq.orientations.iter().zip(readable.orientations.iter_mut()) {
        let mut frames = Vec::new();
        let mut offs = Vec::new();
        ro.exposures.clear();
        for e in &o.exposures {
            match fits::read_frame_rows_with_summary(&e.path, rows)
                .map_err(|err| crate::scan::unreadable_reason(&e.path, &err.to_string()))
                .and_then(|(f, s)| usable_frame(f, &s, profile, rows).map_err(|e| e.to_string()))
            {
                Ok(f) => {
                    frames.push(f);
                    offs.push(e.offset_px);
                    ro.exposures.push(e.clone());
                }
                Err(err) => failures.push(Failure {
                    file: e.path.display().to_string(),
                    error: err,
                }),
            }
        }
        orients.push((o.posang_deg, o.analyzer_deg, frames, offs));
    }
    let read = t.elapsed().as_secs_f64();
    let mut out = reduce_loaded(&readable, orients, profile, params, night_mask, flats, keep_frames);
    out.target.input_files = Some(seq.files());
    out.times.read = read;
    failures.extend(out.failures);
    out.failures = failures;
    out
}

/// A frame as read, checked before it enters the reduction: an image of another size than
/// the profile's detector, one whose pixels are mostly not finite, or one whose pixels are
/// all equal (all zero...) is unusable as a whole and dropped by name with the reason (the
/// other dithers carry on). A few non-finite pixels (NaN, Inf) are bad pixels: set to the
/// frame's median and masked BAD, so an aperture that holds one flags its dither.
pub fn usable_frame(
    mut f: Frame,
    summary: &PixelSummary,
    profile: &Profile,
    rows: Option<(usize, usize)>,
) -> crate::error::Result<Frame> {
    let g = &profile.geometry;
    let want = match rows {
        Some((r0, r1)) => (r1 - r0, g.nx),
        None => (g.ny, g.nx),
    };
    let got = f.shape();
    if got != want && got != (g.ny, g.nx) {
        // Only some rows may have been read: the message gives the whole image's size.
        let whole = match rows {
            Some(_) => fits::read_image_shape(f.path()).unwrap_or(got),
            None => got,
        };
        return Err(crate::error::Error::UnusableFrame(format!(
            "image is {} x {} px (NAXIS2 x NAXIS1), the instrument profile's detector is {} x {}: frame not used",
            whole.0, whole.1, g.ny, g.nx
        )));
    }
    let n = f.data.len();
    // The summary comes from the reading's conversion pass; a copy only when needed.
    let (n_bad, lo, hi) = (summary.non_finite, summary.min, summary.max);
    if 2 * n_bad > n {
        return Err(crate::error::Error::UnusableFrame(format!(
            "{n_bad} of {n} pixels are not finite (NaN or Inf): frame unusable"
        )));
    }
    if lo == hi {
        return Err(crate::error::Error::UnusableFrame(format!(
            "every pixel equals {lo}: frame unusable"
        )));
    }
    if n_bad > 0 {
        let mut tmp: Vec<f32> = f.data.iter().copied().filter(|v| v.is_finite()).collect();
        let mid = tmp.len() / 2;
        let (_, med, _) = tmp.select_nth_unstable_by(mid, f32::total_cmp);
        let med = *med;
        ndarray::Zip::from(&mut f.data).and(&mut f.mask).for_each(|v, m| {
            if !v.is_finite() {
                *v = med;
                *m |= sofipol_calib::frame::mask::BAD;
            }
        });
        f = f.with_history(
            "read",
            format!("{n_bad} non-finite pixels set to the median {med} and masked BAD"),
        );
    }
    Ok(f)
}

/// Frames of one orientation already in memory: (POSANG, analyzer angle, frames, header
/// jitter offsets).
pub type LoadedOrientation = (f64, f64, Vec<Frame>, Vec<[f64; 2]>);

/// [`reduce_sequence`] on frames already in memory (`seq` gives the names and files).
pub fn reduce_loaded(
    seq: &Sequence,
    orients: Vec<LoadedOrientation>,
    profile: &Profile,
    params: &TargetParams,
    night_mask: Option<&Array2<u8>>,
    flats: Option<&FlatSet>,
    keep_frames: bool,
) -> TargetOutcome {
    // Everything the measurement needs lies in the o- and e-target strips: unless whole
    // frames are wanted (intermediates for DS9), work on those rows only (a third of the
    // detector), with the profile's geometry shifted to match.
    let crop = crop_of(profile, params);
    let (orients, cropped_profile) = match crop {
        Some((r0, r1)) => (crop_rows(orients, r0, r1), Some(profile.cropped_rows(r0, r1))),
        None => (orients, None),
    };
    let profile = cropped_profile.as_ref().unwrap_or(profile);
    let mut times = StageTimes::default();
    let mut failures = Vec::new();
    let mut flags: Vec<Flag> = seq.problems();
    flags.extend(mixed_exposure(seq));
    // Dithers that do not move leave the star in its own sky median: the result would be
    // wrong without a sign of it (gamma off by 10 deg and more, passing the cut). Refused.
    let still = seq.stationary_orientations();
    if !still.is_empty() {
        return failed(
            seq,
            format!(
                "all dithers at one position at POSANG {still:?} deg (header offsets within {} px): \
                 the sky median would contain the star; refused (no sky frames besides the dithers)",
                crate::sequence::STATIONARY_PX
            ),
            &flags,
            failures,
            times,
        );
    }

    // A frame without a sky to scale by would break its orientation's sky (and the
    // bad-pixel stack): dropped by name before either, the other dithers carry on.
    let t = std::time::Instant::now();
    let mut orients = orients;
    let dropped = drop_frames_without_sky(&mut orients, profile, params.sky.scaling, &mut failures, &mut flags);
    times.sky = t.elapsed().as_secs_f64();

    // Bad pixels: calibration mask and/or detection on all frames of the sequence.
    let t = std::time::Instant::now();
    let all: Vec<&Frame> = orients.iter().flat_map(|o| o.2.iter()).collect();
    if all.is_empty() {
        return failed(seq, "no readable frame".into(), &flags, failures, times);
    }
    // Header offsets of every frame (the target's detector position), when each frame has one.
    let offsets: Vec<[f64; 2]> = orients.iter().flat_map(|o| o.3.iter().copied()).collect();
    let offsets = (offsets.len() == all.len()).then_some(offsets.as_slice());
    let mask = match bad_pixel_mask(&all, offsets, crop, night_mask, profile, params, &mut flags) {
        Ok(m) => m,
        Err(e) => return failed(seq, e.to_string(), &flags, failures, times),
    };
    times.bad_pixels = t.elapsed().as_secs_f64();

    let t = std::time::Instant::now();
    let (flat_rows, mut flats_used) = match flats {
        Some(set) if !set.is_empty() => choose_flats(&orients, set, &seq.filter, crop, profile, &mut flags),
        _ => (vec![None; orients.len()], Vec::new()),
    };
    times.flat = t.elapsed().as_secs_f64();

    // The flat is divided out in the sky stage's last pass (its time counts there).
    let t = std::time::Instant::now();
    let (cal, sky_levels) = subtract_sky(orients, &flat_rows, mask.as_ref(), profile, params, &mut flags);
    flats_used.retain(|u| cal.iter().any(|o| u.starts_with(&format!("POSANG {}:", o.posang_deg))));
    times.sky += t.elapsed().as_secs_f64();

    if let Some(dir) = &params.save_intermediate {
        let t = std::time::Instant::now();
        save_intermediates(&cal, dir, &mut flags);
        times.write = t.elapsed().as_secs_f64();
    }

    if distinct_analyzer_angles(&cal) < 2 {
        return failed(
            seq,
            format!(
                "{} usable orientation(s): q and u need at least 2 analyzer angles",
                cal.len()
            ),
            &flags,
            failures,
            times,
        );
    }

    let t = std::time::Instant::now();
    let measured = match measure_sequence(&cal, profile, &params.measure) {
        Ok(m) => m,
        Err(e) => return failed(seq, e.0, &flags, failures, times),
    };
    let mut target = target_entry(&seq.object, &cal, &measured, &params.measure, profile);
    failures.extend(primary_not_found(&cal, &measured, &params.measure));
    times.measure = t.elapsed().as_secs_f64();
    // The measurement's flags and the entry's own (a frame's parallactic angle not used).
    flags.extend(target.flags.take().unwrap_or_default());
    if !flags.is_empty() && target.status == Status::Ok && !seq.problems().is_empty() {
        target.status = Status::Partial;
        target.error = seq.problems().first().map(Flag::to_string);
    }
    if let (Some(first), Status::Ok) = (dropped.first(), target.status) {
        target.status = Status::Partial;
        target.error = Some(first.to_string());
    }
    let mut target = pointed(target, seq);
    place_field_stars(&mut target, crop.map_or(0, |(r0, _)| r0));
    target.sequence = Some(seq.id.clone());
    target.tpl_start = Some(seq.tpl_start.clone());
    target.filter = Some(seq.filter.clone());
    target.input_files = Some(seq.files());
    target.flags = Some(flags);
    // JSON null when no flat was applied.
    target.flat = Some((!flats_used.is_empty()).then_some(flats_used));
    target.frame_quality = Some(super::quality::frame_quality(&cal, &sky_levels, &measured, profile));
    if let Some(m) = &mask {
        target.bad_pixels_masked = Some(m.iter().filter(|&&v| v != 0).count());
    }
    TargetOutcome {
        target,
        failures,
        times,
        frame_files: cal
            .iter()
            .map(|o| o.frames.iter().map(|f| f.path().to_path_buf()).collect())
            .collect(),
        row_offset: crop.map_or(0, |(r0, _)| r0),
        calibrated: if keep_frames { Some(cal) } else { None },
        measured: Some(measured),
    }
}

/// The frames in which the primary star was not found (its dither dropped, flag
/// `primary_not_found`), as failures: an input the catalog did not use is listed by name.
fn primary_not_found(
    cal: &[SkySubtractedOrientation],
    m: &super::Measured,
    params: &super::MeasureParams,
) -> Vec<Failure> {
    let Some(first) = m.dithers.first() else {
        return Vec::new();
    };
    cal.iter()
        .zip(first)
        .flat_map(|(o, values)| o.frames.iter().zip(values))
        .filter(|(_, v)| v.rejected.as_deref() == Some(FlagCode::PrimaryNotFound.name()))
        .map(|(f, _)| Failure {
            file: f.path().display().to_string(),
            error: format!(
                "primary star not found within measure.primary_search_px = {} px of its expected position \
                 (header offsets): dither not used",
                params.primary_search_px
            ),
        })
        .collect()
}

/// The flat of every orientation (rotator angle and filter) and its row of the frames' row
/// 0 (frames holding only the rows `crop` use those rows of a full-height flat, no copy),
/// checked against every frame; the sky stage divides it out in its last pass
/// ([`sky::sky_subtract_flat`]). Returns one entry per orientation and one provenance line
/// per flat-fielded orientation; an orientation without a flat, or with a flat that does
/// not fit one of its frames, is flagged and reduced without (an orientation is
/// flat-fielded whole or not at all).
fn choose_flats<'a>(
    orients: &[LoadedOrientation],
    set: &'a FlatSet,
    filter: &str,
    crop: Option<(usize, usize)>,
    profile: &Profile,
    flags: &mut Vec<Flag>,
) -> (Vec<Option<flat::FlatRows<'a>>>, Vec<String>) {
    let mut used = Vec::new();
    let chosen = orients
        .iter()
        .map(|(pa, _, frames, _)| {
            let pa = *pa;
            let Some(flat) = set.for_frame(pa, filter) else {
                flags.push(Flag::with_detail(
                    FlagCode::NoFlat,
                    format!("{pa} filter {filter}: not flat-fielded"),
                ));
                return None;
            };
            let row0 = match crop {
                Some((r0, r1)) if flat.shape().0 >= r1 && frames.first().is_some_and(|f| f.shape().0 == r1 - r0) => r0,
                _ => 0,
            };
            if let Some(e) = frames
                .iter()
                .find_map(|f| flat::check_flat(f, flat, row0, profile).err())
            {
                flags.push(Flag::with_detail(
                    FlagCode::FlatDoesNotFit,
                    format!("{pa} not flat-fielded: {e}"),
                ));
                return None;
            }
            used.push(format!("POSANG {pa}: {}", flat.describe()));
            let ny = frames.first().map_or(0, |f| f.shape().0);
            Some(set.rows(flat, row0, ny))
        })
        .collect();
    (chosen, used)
}

/// The detector rows `[r0, r1)` the reduction works on (the o- and e-target strips), unless
/// whole frames are wanted.
pub(crate) fn crop_of(profile: &Profile, params: &TargetParams) -> Option<(usize, usize)> {
    let g = &profile.geometry;
    let [r0, r1] = g.measured_rows();
    (!params.full_frame_sky && params.save_intermediate.is_none() && r1 > r0).then_some((r0, r1))
}

/// Rows [r0, r1) of every frame at least r1 rows high.
fn crop_rows(orients: Vec<LoadedOrientation>, r0: usize, r1: usize) -> Vec<LoadedOrientation> {
    orients
        .into_iter()
        .map(|(pa, phi, frames, offs)| {
            // Frames read as the strips already (the usual case) are moved, not copied.
            let frames = frames
                .into_iter()
                .map(|f| if f.shape().0 >= r1 { f.crop_rows(r0, r1) } else { f })
                .collect();
            (pa, phi, frames, offs)
        })
        .collect()
}

/// A full-frame mask cut to the rows `crop` (when it has them).
fn crop_mask(m: &Array2<u8>, crop: Option<(usize, usize)>) -> Array2<u8> {
    match crop {
        Some((r0, r1)) if m.dim().0 >= r1 => m.slice(s![r0..r1, ..]).to_owned(),
        _ => m.clone(),
    }
}

/// Whether a full-frame mask has `nx` columns and at least `ny` rows.
fn nm_fits(m: Option<&Array2<u8>>, ny: usize, nx: usize) -> bool {
    m.is_some_and(|m| m.dim().1 == nx && m.dim().0 >= ny)
}

/// The bad-pixel mask of a sequence: the calibration mask (settings), combined with the
/// night's mask when given, else with defects detected on the sequence's own frames
/// (at least 3; stacked per dither position when one position holds half of them, see
/// [`badpix::detect_bad_pixels_at`]). An error fails the target; a failed detection is
/// only flagged.
fn bad_pixel_mask(
    all: &[&Frame],
    offsets: Option<&[[f64; 2]]>,
    crop: Option<(usize, usize)>,
    night_mask: Option<&Array2<u8>>,
    profile: &Profile,
    params: &TargetParams,
    flags: &mut Vec<Flag>,
) -> crate::error::Result<Option<Array2<u8>>> {
    let mut mask = None;
    if let Some(p) = &params.calib_mask {
        let m = badpix::load_mask(p).map_err(|e| Error::calib("calibration mask", e))?;
        mask = Some(crop_mask(&m, crop));
    }
    let g = &profile.geometry;
    let full = match crop {
        // The night mask is full-frame (`profile` is already cut to the rows `crop`): it
        // must have the frames' width and reach row r1. A mask of another geometry is
        // not used (flagged) rather than failing the target.
        Some((_, r1)) => nm_fits(night_mask, r1, g.nx),
        None => nm_fits(night_mask, g.ny, g.nx),
    };
    if let (Some(nm), false) = (night_mask, full) {
        flags.push(Flag::with_detail(
            FlagCode::NightMaskUnfit,
            format!(
                "{} x {} px, the frames {} px wide: not used, defects detected on this sequence",
                nm.dim().0,
                nm.dim().1,
                g.nx
            ),
        ));
    }
    let night_mask = night_mask.filter(|_| full);
    if let Some(nm) = night_mask {
        let nm = crop_mask(nm, crop);
        mask = Some(match mask {
            Some(c) => badpix::combine_masks(&c, &nm).map_err(|e| Error::calib("night bad-pixel mask", e))?,
            None => nm,
        });
    } else if !params.no_detect_bad_pixels && all.len() >= 3 {
        match badpix::detect_bad_pixels_at(all, offsets, profile, &params.bad_pixels) {
            Ok((m, _report)) => {
                mask = Some(match mask {
                    Some(c) => badpix::combine_masks(&c, &m).map_err(|e| Error::calib("calibration mask", e))?,
                    None => m,
                })
            }
            Err(e) => flags.push(Flag::with_detail(FlagCode::BadPixelDetectionFailed, e.to_string())),
        }
    }
    Ok(mask)
}

/// Leave out of `orients` every frame whose sky level the sky stage cannot use
/// ([`sky::usable_sky_level`] with `scaling`: saturated, negated, byte-swapped or
/// background-free data), each named under `failures` with the reason and flagged; the
/// other dithers of its orientation carry on. Returns the flags added.
fn drop_frames_without_sky(
    orients: &mut [LoadedOrientation],
    profile: &Profile,
    scaling: sky::SkyScaling,
    failures: &mut Vec<Failure>,
    flags: &mut Vec<Flag>,
) -> Vec<Flag> {
    let mut dropped = Vec::new();
    for (posang, _, frames, offs) in orients.iter_mut() {
        let verdicts: Vec<Option<String>> = frames
            .iter()
            .map(|f| sky::usable_sky_level(f, profile, scaling).err().map(|e| e.to_string()))
            .collect();
        if verdicts.iter().all(Option::is_none) {
            continue;
        }
        // Header offsets are used only when every frame has one.
        let old_offs = if offs.len() == frames.len() {
            std::mem::take(offs)
        } else {
            Vec::new()
        };
        offs.clear();
        for (i, (f, why)) in std::mem::take(frames).into_iter().zip(verdicts).enumerate() {
            let Some(why) = why else {
                frames.push(f);
                offs.extend(old_offs.get(i));
                continue;
            };
            let file = f.path().display().to_string();
            let flag = Flag::with_detail(FlagCode::DitherDropped, format!("{posang} dropped: {why}"));
            failures.push(Failure {
                file,
                error: format!("{why}: frame not used, the other dithers of POSANG {posang} carry on"),
            });
            flags.push(flag.clone());
            dropped.push(flag);
        }
    }
    dropped
}

/// Sky subtraction, orientation by orientation (the mask applied first). An orientation
/// with fewer than 2 readable dithers, or whose sky fails, is dropped and flagged. Returns
/// the sky-subtracted orientations and the sky level of each of their frames, ADU.
fn subtract_sky(
    orients: Vec<LoadedOrientation>,
    flats: &[Option<flat::FlatRows>],
    mask: Option<&Array2<u8>>,
    profile: &Profile,
    params: &TargetParams,
    flags: &mut Vec<Flag>,
) -> (Vec<SkySubtractedOrientation>, Vec<Vec<f64>>) {
    let mut cal = Vec::new();
    let mut levels = Vec::new();
    for ((posang, phi, frames, offs), fl) in orients.into_iter().zip(flats) {
        if frames.len() < 2 {
            flags.push(Flag::with_detail(
                FlagCode::OrientationDropped,
                format!(
                    "{posang} dropped: {} readable dither(s), need 2 for the sky",
                    frames.len()
                ),
            ));
            continue;
        }
        let mut frames = frames;
        if let Some(m) = mask {
            if let Err(e) = frames.iter_mut().try_for_each(|f| badpix::apply_mask_in_place(f, m)) {
                flags.push(Flag::with_detail(
                    FlagCode::OrientationDropped,
                    format!("{posang} dropped: {e}"),
                ));
                continue;
            }
        }
        match sky::sky_subtract_flat(frames, profile, &params.sky, fl.as_ref()) {
            Ok((s, report)) => {
                levels.push(report.levels_adu);
                cal.push(SkySubtractedOrientation {
                    posang_deg: posang,
                    analyzer_deg: phi,
                    frames: s,
                    offsets: offs,
                })
            }
            Err(e) => flags.push(Flag::with_detail(
                FlagCode::OrientationDropped,
                format!("{posang} dropped: {e}"),
            )),
        }
    }
    (cal, levels)
}

/// Write the sky-subtracted frames (data, UNCERT (variance), MASK) into `dir` as `<name>_skysub.fits`.
fn save_intermediates(cal: &[SkySubtractedOrientation], dir: &Path, flags: &mut Vec<Flag>) {
    let opts = fits::WriteOptions {
        with_variance_and_mask: true,
        ..Default::default()
    };
    if let Err(e) = std::fs::create_dir_all(dir) {
        flags.push(Flag::with_detail(
            FlagCode::IntermediateDirNotCreated,
            format!("{}: {e}", dir.display()),
        ));
    }
    for o in cal {
        for f in &o.frames {
            let name = f.path().file_name().and_then(|n| n.to_str()).unwrap_or("frame.fits");
            let base = name
                .trim_end_matches(".gz")
                .trim_end_matches(".fz")
                .trim_end_matches(".fits")
                .trim_end_matches(".fit");
            let out = dir.join(format!("{base}_skysub.fits"));
            if let Err(e) = fits::write_frame(&out, f, &opts) {
                flags.push(Flag::with_detail(
                    FlagCode::IntermediateNotWritten,
                    format!("{}: {e}", out.display()),
                ));
            }
        }
    }
}

/// Number of distinct analyzer angles (mod 180 deg, to 0.01 deg).
fn distinct_analyzer_angles(cal: &[SkySubtractedOrientation]) -> usize {
    let mut v: Vec<i64> = cal
        .iter()
        .map(|o| ((o.analyzer_deg.rem_euclid(180.0)) * 100.0).round() as i64)
        .collect();
    v.sort();
    v.dedup();
    v.len()
}

/// A flag when the exposures of a sequence differ in DIT (or EXPTIME) or NDIT: such
/// frames are normalised, not refused. The data are ADU per DIT averaged over NDIT reads,
/// so NDIT changes only the noise (each frame's variance uses its own NDIT); a longer DIT
/// scales sky and stars alike, so each frame's sky comes from the other dithers scaled to
/// its own sky level (multiplicative sky scaling: exact; additive: the sky pattern is not
/// rescaled) and F = (o - e)/(o + e) is a flux ratio within one frame.
pub fn mixed_exposure(seq: &Sequence) -> Option<Flag> {
    let mut dits: Vec<f64> = Vec::new();
    let mut ndits: Vec<u32> = Vec::new();
    for e in seq.orientations.iter().flat_map(|o| &o.exposures) {
        if !dits.iter().any(|d| (d - e.dit_s).abs() <= 1e-6 * d.abs().max(1e-9)) {
            dits.push(e.dit_s);
        }
        if !ndits.contains(&e.ndit) {
            ndits.push(e.ndit);
        }
    }
    (dits.len() > 1 || ndits.len() > 1).then(|| {
        Flag::with_detail(
            FlagCode::MixedExposure,
            format!(
                "DIT {dits:?} s, NDIT {ndits:?} within the sequence: normalised \
                 (each frame's sky scaled to its own level, F a flux ratio within a frame, variance from its own NDIT)"
            ),
        )
    })
}
