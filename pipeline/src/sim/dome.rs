//! Dome-flat frames (the `dome_flats` effect): per rotator angle, lamp-on then lamp-off
//! frames through the same detector as the science frames.
use ndarray::Array2;
use sofipol_calib::profile::Beam;
use sofipol_calib::{Frame, Header};

use super::truth::FlatFrameTruth;
use super::{effects, EffectKind, Simulator};

/// A simulated dome-flat frame in memory.
#[derive(Debug, Clone)]
pub struct SimFlatFrame {
    /// File name (no directory).
    pub file_name: String,
    /// The frame.
    pub frame: Frame,
    /// Its truth.
    pub truth: FlatFrameTruth,
}

/// Key of the random streams of dome-flat frames (science targets use their index).
const FLAT_STREAM_KEY: u64 = 1 << 40;

impl Simulator {
    /// Number of dome-flat frames (0 unless `dome_flats` is listed): per rotator angle,
    /// `frames_on` lamp-on then `frames_off` lamp-off frames.
    pub fn n_dome_flat_frames(&self) -> usize {
        if !self.scene.has(EffectKind::DomeFlats) {
            return 0;
        }
        let c = self.scene.dome_flats.clone().unwrap_or_default();
        self.scene.observation.orientations_deg.len() * (c.frames_on + c.frames_off)
    }

    /// (orientation index, index within its template, truth) of dome-flat frame `i`.
    pub(super) fn dome_flat_plan(&self, i: usize) -> ((usize, usize), FlatFrameTruth) {
        let s = &self.scene;
        let c = s.dome_flats.clone().unwrap_or_default();
        let per = c.frames_on + c.frames_off;
        let (io, j) = (i / per, i % per);
        let posang = s.observation.orientations_deg[io];
        let lamp_on = j < c.frames_on;
        let phi = self.profile.angles.analyzer_angle_deg(posang);
        let f = c.lamp_p * (2.0 * (phi - c.lamp_angle_deg).to_radians()).cos();
        let (t_o, t_e) = if s.has(EffectKind::Throughput) {
            effects::throughput(&self.calls, &s.throughput.clone().unwrap_or_default())
        } else {
            (1.0, 1.0)
        };
        let lamp = if lamp_on { c.lamp_adu } else { 0.0 };
        let slug = super::file_slug(&s.name);
        let ext = if s.observation.compress { "fits.fz" } else { "fits" };
        let file = format!(
            "SOFI_{slug}_FLAT_pa{:03}_{}_{:02}.{ext}",
            posang.round() as i64,
            if lamp_on { "on" } else { "off" },
            j + 1
        );
        (
            (io, j),
            FlatFrameTruth {
                file,
                posang_deg: posang,
                lamp_on,
                level_o_adu: t_o * (c.off_adu + lamp * (1.0 + f)),
                level_e_adu: t_e * (c.off_adu + lamp * (1.0 - f)),
            },
        )
    }

    /// Simulate dome-flat frame `i` (0-based, see [`Simulator::n_dome_flat_frames`]): the
    /// lamp (polarized: o and e strips differ) plus the lamp-off light, through the beams
    /// (`throughput` when listed) and the same detector as the science frames.
    pub fn dome_flat_frame(&self, i: usize) -> SimFlatFrame {
        self.calls.hit(EffectKind::DomeFlats);
        let s = &self.scene;
        let c = s.dome_flats.clone().unwrap_or_default();
        let g = &self.profile.geometry;
        let ((io, j), truth) = self.dome_flat_plan(i);
        let is_o = |y: usize| g.beam_of_row(y) == Some(Beam::Ordinary);
        let is_e = |y: usize| g.beam_of_row(y) == Some(Beam::Extraordinary);
        let mean = 0.5 * (truth.level_o_adu + truth.level_e_adu);
        let mut img = Array2::<f32>::from_shape_fn((g.ny, g.nx), |(y, _)| {
            (if is_o(y) {
                truth.level_o_adu
            } else if is_e(y) {
                truth.level_e_adu
            } else {
                mean
            }) as f32
        });
        let cr = self.detector(&mut img, (FLAT_STREAM_KEY + io as u64, j as u64), c.ndit);
        let _ = cr;
        // Header: the contract's dome-flat template.
        let o = &s.observation;
        let kw = &self.profile.keywords;
        let per = c.frames_on + c.frames_off;
        let mjd0 = effects::mjd_from_date_time(&o.date, &o.start_ut).unwrap_or(51240.0) - 0.25;
        let tpl_mjd = mjd0 + io as f64 * (per as f64 * (c.dit_s * c.ndit as f64 + 5.0) + 60.0) / 86400.0;
        let mjd = tpl_mjd + (j as f64 * (c.dit_s * c.ndit as f64 + 5.0) + 10.0) / 86400.0;
        let mut h = Header::new(&truth.file);
        h.set(&kw.instrument, self.profile.matching.instrument.as_str());
        h.set(&kw.object, "DOME FLAT");
        h.set(&kw.date_obs, effects::iso_from_mjd(mjd, true));
        h.set(&kw.mjd_obs, mjd);
        h.set(&kw.exptime, c.dit_s);
        h.set(&kw.dpr_catg, "CALIB");
        h.set(&kw.dpr_type, "FLAT");
        h.set(&kw.dpr_tech, self.profile.matching.polarimetry_tech.as_str());
        h.set(&kw.tpl_id, sofipol_calib::flat::DOME_FLAT_TEMPLATE);
        h.set(&kw.tpl_start, effects::iso_from_mjd(tpl_mjd, false));
        h.set(&kw.tpl_nexp, per as i64);
        h.set(&kw.tpl_expno, (j + 1) as i64);
        h.set(&kw.filter, o.filter.as_str());
        h.set(&format!("{}1 ID", kw.opti_prefix), "MASK_POL");
        h.set(&format!("{}3 ID", kw.opti_prefix), "WOLLASTON");
        h.set(&kw.pixscale, self.scale());
        h.set(&kw.posang, truth.posang_deg);
        h.set(&kw.offset_x, 0.0);
        h.set(&kw.offset_y, 0.0);
        h.set(&kw.dit, c.dit_s);
        h.set(&kw.ndit, c.ndit as i64);
        h.set(sofipol_calib::flat::LAMP_KEYWORD, truth.lamp_on);
        let frame = Frame::new(img, h).with_history(
            "simulate",
            format!(
                "scene '{}' seed {} dome flat POSANG {} lamp {} exposure {}",
                s.name,
                s.seed,
                truth.posang_deg,
                if truth.lamp_on { "on" } else { "off" },
                j + 1
            ),
        );
        SimFlatFrame {
            file_name: truth.file.clone(),
            frame,
            truth,
        }
    }

    /// Every dome-flat frame in memory (empty unless `dome_flats` is listed).
    pub fn dome_flat_frames(&self) -> Vec<SimFlatFrame> {
        use rayon::prelude::*;
        (0..self.n_dome_flat_frames())
            .into_par_iter()
            .map(|i| self.dome_flat_frame(i))
            .collect()
    }
}
