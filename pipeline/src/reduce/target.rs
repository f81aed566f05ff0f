//! One target sequence from raw files to a catalog entry: read -> bad pixels -> sky ->
//! measure ([`super::measure_sequence`]) -> Stokes ([`super::target_entry`]).
use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use sofipol_calib::badpix::{self, BadPixelOptions};
use sofipol_calib::sky::{self, SkyOptions};
use sofipol_calib::{fits, Frame, Profile};

use super::{measure_sequence, target_entry, CalibratedOrientation, MeasureParams};
use crate::catalog::{Failure, Status, Target};
use crate::sequence::Sequence;

/// Settings of a target reduction.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TargetParams {
    /// Measurement settings.
    pub measure: MeasureParams,
    /// Sky subtraction (default: multiplicative scaling, cosmic-ray flagging on).
    pub sky: SkyOptions,
    /// Bad-pixel detection.
    pub bad_pixels: BadPixelOptions,
    /// A calibration bad-pixel mask (nonzero = bad), combined with the detected one.
    pub calib_mask: Option<PathBuf>,
    /// Do not detect bad pixels from the data (use only the calibration mask).
    pub no_detect_bad_pixels: bool,
    /// Write sky-subtracted FITS frames (data, VARIANCE, MASK) into this directory.
    pub save_intermediate: Option<PathBuf>,
    /// Sky-subtract whole frames. By default only the target strips (o-target and
    /// e-target rows, all the measurement uses) are sky-subtracted, about a third of the
    /// detector; whole frames are always done when intermediates are saved.
    pub full_frame_sky: bool,
    /// A bad-pixel mask already detected (night mode detects the detector's defects once
    /// from frames of many sequences); used instead of per-target detection.
    #[serde(skip)]
    pub night_mask: Option<std::sync::Arc<ndarray::Array2<u8>>>,
}

impl Default for TargetParams {
    fn default() -> Self {
        TargetParams {
            measure: MeasureParams::default(),
            sky: SkyOptions::recommended(),
            bad_pixels: BadPixelOptions::default(),
            calib_mask: None,
            no_detect_bad_pixels: false,
            save_intermediate: None,
            full_frame_sky: false,
            night_mask: None,
        }
    }
}

/// Timings of the stages of one target, seconds.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct StageTimes {
    /// Reading FITS.
    pub read: f64,
    /// Bad-pixel detection.
    pub bad_pixels: f64,
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
    pub calibrated: Option<Vec<CalibratedOrientation>>,
    /// Intermediate measurements (for plots).
    pub measured: Option<super::Measured>,
}

fn failed(seq: &Sequence, msg: String, failures: Vec<Failure>, times: StageTimes) -> TargetOutcome {
    let mut extra = serde_json::Map::new();
    extra.insert("sequence".into(), serde_json::json!(seq.id));
    extra.insert("input_files".into(), serde_json::json!(seq.files()));
    TargetOutcome {
        target: Target {
            object: seq.object.clone(),
            status: Status::Failed,
            error: Some(msg),
            components: vec![],
            delta_gamma_deg: None,
            extra,
        },
        failures,
        times,
        calibrated: None,
        measured: None,
    }
}

/// Reduce one sequence. Never panics on bad input: problems become failures, flags or a
/// failed target.
pub fn reduce_sequence(seq: &Sequence, profile: &Profile, params: &TargetParams, keep_frames: bool) -> TargetOutcome {
    let mut times = StageTimes::default();
    let mut failures = Vec::new();
    let t = std::time::Instant::now();
    // Read every frame; a file that cannot be read is a failure, the rest goes on.
    let mut orients: Vec<(f64, f64, Vec<Frame>, Vec<[f64; 2]>)> = Vec::new();
    // The sequence as read: problems (missing dithers...) are judged on the usable frames.
    let mut readable = seq.clone();
    for (o, ro) in seq.orientations.iter().zip(readable.orientations.iter_mut()) {
        let mut frames = Vec::new();
        let mut offs = Vec::new();
        ro.exposures.clear();
        for e in &o.exposures {
            match fits::read_frame(&e.path) {
                Ok(f) => {
                    frames.push(f);
                    offs.push(e.offset_px);
                    ro.exposures.push(e.clone());
                }
                Err(err) => failures.push(Failure {
                    file: e.path.display().to_string(),
                    error: err.to_string(),
                }),
            }
        }
        orients.push((o.posang_deg, o.analyzer_deg, frames, offs));
    }
    times.read = t.elapsed().as_secs_f64();
    let mut out = reduce_loaded(&readable, orients, profile, params, keep_frames);
    out.target
        .extra
        .insert("input_files".into(), serde_json::json!(seq.files()));
    out.times.read = times.read;
    failures.extend(out.failures);
    out.failures = failures;
    out
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
    keep_frames: bool,
) -> TargetOutcome {
    // Everything the measurement needs lies in the o- and e-target strips: unless whole
    // frames are wanted (intermediates for DS9), work on those rows only (a third of the
    // detector), with the profile's geometry shifted to match.
    let g = &profile.geometry;
    let (r0, r1) = (g.o_target[0].min(g.e_target[0]), g.o_target[1].max(g.e_target[1]));
    let crop = !params.full_frame_sky && params.save_intermediate.is_none() && r1 > r0;
    let mut orients = orients;
    let cropped_profile: Profile;
    let params_c: TargetParams;
    let (profile, params) = if crop {
        orients = orients
            .into_iter()
            .map(|(pa, phi, frames, offs)| {
                let frames = frames
                    .iter()
                    .map(|f| {
                        if f.shape().0 >= r1 {
                            f.crop_rows(r0, r1)
                        } else {
                            f.clone()
                        }
                    })
                    .collect();
                (pa, phi, frames, offs)
            })
            .collect::<Vec<_>>();
        cropped_profile = profile.cropped_rows(r0, r1);
        let mut p = params.clone();
        p.night_mask = params.night_mask.as_ref().map(|m| {
            if m.dim().0 >= r1 {
                std::sync::Arc::new(m.slice(ndarray::s![r0..r1, ..]).to_owned())
            } else {
                m.clone()
            }
        });
        params_c = p;
        (&cropped_profile, &params_c)
    } else {
        (profile, params)
    };
    let mut times = StageTimes::default();
    let failures = Vec::new();
    let mut flags: Vec<String> = seq.problems();

    // Bad pixels: calibration mask and/or detection on all frames of the sequence.
    let t = std::time::Instant::now();
    let all: Vec<&Frame> = orients.iter().flat_map(|o| o.2.iter()).collect();
    if all.is_empty() {
        return failed(seq, "no readable frame".into(), failures, times);
    }
    let mut mask = None;
    if let Some(p) = &params.calib_mask {
        match badpix::load_mask(p) {
            Ok(m) => {
                mask = Some(if crop && m.dim().0 >= r1 {
                    m.slice(ndarray::s![r0..r1, ..]).to_owned()
                } else {
                    m
                })
            }
            Err(e) => return failed(seq, format!("calibration mask: {e}"), failures, times),
        }
    }
    if let Some(nm) = &params.night_mask {
        mask = Some(match mask {
            Some(c) => match badpix::combine_masks(&c, nm) {
                Ok(x) => x,
                Err(e) => return failed(seq, format!("night bad-pixel mask: {e}"), failures, times),
            },
            None => (**nm).clone(),
        });
    } else if !params.no_detect_bad_pixels && all.len() >= 3 {
        match badpix::detect_bad_pixels(&all, profile, &params.bad_pixels) {
            Ok((m, _report)) => {
                mask = Some(match mask {
                    Some(c) => match badpix::combine_masks(&c, &m) {
                        Ok(x) => x,
                        Err(e) => return failed(seq, format!("calibration mask: {e}"), failures, times),
                    },
                    None => m,
                })
            }
            Err(e) => flags.push(format!("bad-pixel detection failed: {e}")),
        }
    }
    times.bad_pixels = t.elapsed().as_secs_f64();

    // Sky, orientation by orientation.
    let t = std::time::Instant::now();
    let mut cal = Vec::new();
    for (posang, phi, frames, offs) in orients {
        if frames.len() < 2 {
            flags.push(format!(
                "orientation POSANG {posang} dropped: {} readable dither(s), need 2 for the sky",
                frames.len()
            ));
            continue;
        }
        let frames: Vec<Frame> = match &mask {
            Some(m) => match frames
                .iter()
                .map(|f| badpix::apply_mask(f, m))
                .collect::<Result<Vec<_>, _>>()
            {
                Ok(v) => v,
                Err(e) => {
                    flags.push(format!("orientation POSANG {posang} dropped: {e}"));
                    continue;
                }
            },
            None => frames,
        };
        match sky::sky_subtract(&frames, profile, &params.sky) {
            Ok(s) => cal.push(CalibratedOrientation {
                posang_deg: posang,
                analyzer_deg: phi,
                frames: s,
                offsets: offs,
            }),
            Err(e) => flags.push(format!("orientation POSANG {posang} dropped: {e}")),
        }
    }
    times.sky = t.elapsed().as_secs_f64();

    if let Some(dir) = &params.save_intermediate {
        let t = std::time::Instant::now();
        let opts = fits::WriteOptions {
            with_variance_and_mask: true,
            ..Default::default()
        };
        if let Err(e) = std::fs::create_dir_all(dir) {
            flags.push(format!("could not create {}: {e}", dir.display()));
        }
        for o in &cal {
            for f in &o.frames {
                let name = f.path().file_name().and_then(|n| n.to_str()).unwrap_or("frame.fits");
                let base = name
                    .trim_end_matches(".gz")
                    .trim_end_matches(".fz")
                    .trim_end_matches(".fits")
                    .trim_end_matches(".fit");
                let out = dir.join(format!("{base}_skysub.fits"));
                if let Err(e) = fits::write_frame(&out, f, &opts) {
                    flags.push(format!("could not write intermediate {}: {e}", out.display()));
                }
            }
        }
        times.write = t.elapsed().as_secs_f64();
    }

    let distinct = {
        let mut v: Vec<i64> = cal
            .iter()
            .map(|o| ((o.analyzer_deg.rem_euclid(180.0)) * 100.0).round() as i64)
            .collect();
        v.sort();
        v.dedup();
        v.len()
    };
    if distinct < 2 {
        return failed(
            seq,
            format!(
                "{} usable orientation(s): q and u need at least 2 analyzer angles",
                cal.len()
            ),
            failures,
            times,
        );
    }

    let t = std::time::Instant::now();
    let measured = match measure_sequence(&cal, profile, &params.measure) {
        Ok(m) => m,
        Err(e) => return failed(seq, e.0, failures, times),
    };
    let mut target = target_entry(&seq.object, &cal, &measured, &params.measure);
    times.measure = t.elapsed().as_secs_f64();
    flags.extend(measured.flags.iter().cloned());
    if !flags.is_empty() && target.status == Status::Ok && !seq.problems().is_empty() {
        target.status = Status::Partial;
        target.error = seq.problems().first().cloned();
    }
    target.extra.insert("sequence".into(), serde_json::json!(seq.id));
    target
        .extra
        .insert("tpl_start".into(), serde_json::json!(seq.tpl_start));
    target.extra.insert("filter".into(), serde_json::json!(seq.filter));
    target
        .extra
        .insert("input_files".into(), serde_json::json!(seq.files()));
    target.extra.insert("flags".into(), serde_json::json!(flags));
    if let Some(m) = &mask {
        target.extra.insert(
            "bad_pixels_masked".into(),
            serde_json::json!(m.iter().filter(|&&v| v != 0).count()),
        );
    }
    TargetOutcome {
        target,
        failures,
        times,
        calibrated: if keep_frames { Some(cal) } else { None },
        measured: Some(measured),
    }
}

/// Group simulated frames of one target (in exposure order) into the [`Sequence`] and the
/// loaded orientations [`reduce_loaded`] takes: what `night` would build from the files,
/// without writing them (tests, the accuracy harness).
pub fn loaded_from_sim(frames: Vec<crate::sim::SimFrame>, profile: &Profile) -> (Sequence, Vec<LoadedOrientation>) {
    use crate::sequence::Orientation;
    use sofipol_calib::classify::{classify, Classification};
    let mut orients: Vec<LoadedOrientation> = Vec::new();
    let mut seq_or: Vec<Orientation> = Vec::new();
    let (mut object, mut tpl_start, mut filter) = (String::new(), String::new(), String::new());
    for f in frames {
        let pa = f.truth.posang_deg;
        if orients.last().is_none_or(|o| o.0 != pa) {
            orients.push((pa, f.truth.analyzer_deg, vec![], vec![]));
            seq_or.push(Orientation {
                posang_deg: pa,
                analyzer_deg: f.truth.analyzer_deg,
                exposures: vec![],
            });
        }
        if let Classification::Science(info) = classify(&f.frame.header, profile) {
            object.clone_from(&info.object);
            tpl_start.clone_from(&info.tpl_start);
            filter.clone_from(&info.filter);
            seq_or.last_mut().expect("pushed").exposures.push(*info);
        }
        let o = orients.last_mut().expect("pushed");
        o.3.push(f.truth.header_offset_px);
        o.2.push(f.frame);
    }
    let seq = Sequence {
        id: format!("{object}@{tpl_start}"),
        object,
        tpl_start,
        filter,
        orientations: seq_or,
    };
    (seq, orients)
}
