//! The simulated frames of one target as the reduction's input, without writing them.
use sofipol_calib::classify::{classify, Classification};
use sofipol_calib::Profile;

use super::SimFrame;
use crate::reduce::run::LoadedOrientation;
use crate::sequence::{Orientation, Sequence};

/// Group simulated frames of one target (in exposure order) into the [`Sequence`] and the
/// loaded orientations [`reduce_loaded`](crate::reduce::run::reduce_loaded) takes: what `night` would build from the files,
/// without writing them (tests, the accuracy harness).
pub fn loaded_from_sim(frames: Vec<SimFrame>, profile: &Profile) -> (Sequence, Vec<LoadedOrientation>) {
    let mut orients: Vec<LoadedOrientation> = Vec::new();
    let mut seq_or: Vec<Orientation> = Vec::new();
    let (mut object, mut tpl_start, mut filter) = (String::new(), String::new(), String::new());
    for f in frames {
        let pa = f.truth.posang_deg;
        // The pipeline knows the profile's analyzer angle, not the simulated instrument's
        // true one (they differ when the scene lists `analyzer_angle`).
        let phi = profile.angles.analyzer_angle_deg(pa);
        if orients.last().is_none_or(|o| o.0 != pa) {
            orients.push((pa, phi, vec![], vec![]));
            seq_or.push(Orientation {
                posang_deg: pa,
                analyzer_deg: phi,
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
