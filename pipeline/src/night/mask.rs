//! The night's bad-pixel mask: detector defects stay put while the stars move between
//! dithers and sequences, so one median stack of frames from many sequences finds them.
use std::path::PathBuf;

use rayon::prelude::*;
use sofipol_calib::sky::SkyScaling;
use sofipol_calib::Profile;

use super::NightPlan;
use crate::products::badpix::NightMask;
use crate::reduce::TargetParams;

/// The detector's bad pixels for the whole night: detector defects stay put while stars
/// move between dithers and between sequences, so one median stack of frames taken from
/// many sequences ([`NightPlan::mask_frames`]) finds them once. Returns the
/// mask and the files used, or None when fewer than 3 frames can be read.
pub fn night_bad_pixel_mask(
    plan: &NightPlan,
    profile: &Profile,
    params: &TargetParams,
    max_frames: usize,
) -> Option<NightMask> {
    let opts = &params.bad_pixels;
    let picks: Vec<PathBuf> = plan.mask_frames.iter().take(max_frames).cloned().collect();
    // A reduction of the target strips only needs the mask there: detected on those rows
    // (a third of the work; the same mask there, see `detect_bad_pixels_in_rows`).
    let rows = crate::reduce::run::crop_of(profile, params);
    // Only frames of the profile's detector size (a sequence of another size, observed
    // first, used to give the mask its size, and every valid target then failed on it;
    // such frames are refused by name when their sequence is reduced). With `rows`, each
    // frame is kept as those rows and the sky level of the whole frame (measured as it is
    // read): two thirds less memory held.
    let shape = (profile.geometry.ny, profile.geometry.nx);
    // A frame without a usable sky level (saturated, negated, byte-swapped data: dropped by
    // name when its sequence is reduced) is left out: the stack scales every frame by it.
    let read: Vec<(sofipol_calib::Frame, f64)> = picks
        .par_iter()
        .filter_map(|p| sofipol_calib::fits::read_frame(p).ok())
        .filter(|f| f.shape() == shape)
        .filter_map(|f| {
            let level = sofipol_calib::sky::usable_sky_level(&f, profile, SkyScaling::Multiplicative).ok()?;
            Some(match rows {
                Some((r0, r1)) => (f.crop_rows(r0, r1), level),
                None => (f, level),
            })
        })
        .collect();
    let frames: Vec<&sofipol_calib::Frame> = read.iter().map(|(f, _)| f).collect();
    if frames.len() < 3 {
        return None;
    }
    // Where each frame put its target (header offset): with 2 dithers per sequence half
    // of the picks hold a star on the same pixels, and the stack must be built per position.
    let offsets: Option<Vec<[f64; 2]>> = frames
        .iter()
        .map(|f| match sofipol_calib::classify::classify(&f.header, profile) {
            sofipol_calib::classify::Classification::Science(info) => Some(info.offset_px),
            _ => None,
        })
        .collect();
    let mask = match rows {
        Some((r0, r1)) => {
            let levels: Vec<f64> = read.iter().map(|(_, l)| *l).collect();
            let (part, _report) = sofipol_calib::badpix::detect_bad_pixels_from_rows(
                &frames,
                &levels,
                offsets.as_deref(),
                profile,
                opts,
                (r0, r1),
            )
            .ok()?;
            let mut m = ndarray::Array2::<u8>::zeros(shape);
            m.slice_mut(ndarray::s![r0..r1, ..]).assign(&part);
            m
        }
        None => {
            sofipol_calib::badpix::detect_bad_pixels_at(&frames, offsets.as_deref(), profile, opts)
                .ok()?
                .0
        }
    };
    Some(NightMask {
        mask,
        files: frames.iter().map(|f| f.path().display().to_string()).collect(),
        rows,
    })
}
