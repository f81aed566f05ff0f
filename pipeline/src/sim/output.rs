//! Whole scenes: the truth, every frame in memory, or every frame written to a folder.
use super::truth::{
    DetectorTruth, FieldPopulationTruth, FrameTruth, InstrumentalPolarizationTruth, SimFrame, ThroughputTruth, Truth,
};
use super::{effects, EffectKind, Simulator};

impl Simulator {
    /// Truth of the whole scene (frames are re-derived cheaply: no images are rendered).
    pub fn truth(&self, frames: &[Vec<FrameTruth>]) -> Truth {
        let s = &self.scene;
        let mut detector = DetectorTruth::of_pixels(self.bad.as_ref(), self.flat.as_ref());
        if s.has(EffectKind::Throughput) {
            let (t_o, t_e) = effects::throughput(&self.calls, &s.throughput.clone().unwrap_or_default());
            detector.throughput = Some(ThroughputTruth { t_e, t_o });
        }
        if s.has(EffectKind::InstrumentalPolarization) {
            let c = s.instrumental_polarization.clone().unwrap_or_default();
            detector.instrumental_polarization = Some(InstrumentalPolarizationTruth {
                angle_deg: c.angle_deg,
                p: c.p,
                q_inst_added_to_f: c.p * (2.0 * c.angle_deg.to_radians()).cos(),
            });
        }
        Truth {
            software: format!("sofipol {}", env!("CARGO_PKG_VERSION")),
            scene: s.clone(),
            profile: self.profile.name.clone(),
            effects: s.effects.iter().map(|e| e.name()).collect(),
            ignored_sections: s.ignored_sections(),
            telescope_polarization: s
                .has(EffectKind::TelescopePolarization)
                .then(|| s.telescope_polarization.clone().unwrap_or_default().model()),
            foreground_field: s.has(EffectKind::ForegroundField).then(|| {
                let c = s.foreground_field.clone().unwrap_or_default();
                super::foreground::ForegroundFieldTruth::of(&c, c.seed.unwrap_or(s.seed))
            }),
            field_population: s.field_population.as_ref().map(|c| FieldPopulationTruth {
                area_arcmin2: super::population::area_arcmin2(&self.profile.geometry),
                expected_per_binary: super::population::expected_count(c, &self.profile.geometry),
                zero_point_mag: s.observation.zero_point_mag.unwrap_or(f64::NAN),
            }),
            detector,
            targets: (0..s.binary.len()).map(|t| self.target_truth(t, frames)).collect(),
            standards: (s.binary.len()..self.targets.len())
                .map(|t| {
                    let mut tt = self.target_truth(t, frames);
                    tt.components.truncate(1);
                    tt
                })
                .collect(),
            dome_flats: (0..self.n_dome_flat_frames())
                .map(|i| self.dome_flat_plan(i).1)
                .collect(),
        }
    }

    /// Simulate every frame in memory (small scenes and tests; a night should stream
    /// with [`Simulator::frame`]).
    pub fn run_in_memory(&self) -> (Vec<SimFrame>, Truth) {
        use rayon::prelude::*;
        let n = self.frames_per_target();
        let jobs: Vec<(usize, usize)> = (0..self.targets.len())
            .flat_map(|t| (0..n).map(move |k| (t, k)))
            .collect();
        let frames: Vec<SimFrame> = jobs.par_iter().map(|&(t, k)| self.frame(t, k)).collect();
        let mut per_t: Vec<Vec<FrameTruth>> = vec![Vec::new(); self.targets.len()];
        for (f, &(t, _)) in frames.iter().zip(&jobs) {
            per_t[t].push(f.truth.clone());
        }
        let truth = self.truth(&per_t);
        (frames, truth)
    }
}

impl Simulator {
    /// The names of every file [`Simulator::write_to_dir`] writes: the frames of every
    /// sequence, the dome flats, `truth.json`.
    pub fn file_names(&self) -> Vec<String> {
        let mut names: Vec<String> = (0..self.targets.len())
            .flat_map(|t| (0..self.frames_per_target()).map(move |k| (t, k)))
            .map(|(t, k)| self.file_name(t, k))
            .collect();
        names.extend((0..self.n_dome_flat_frames()).map(|i| self.dome_flat_plan(i).1.file));
        names.push("truth.json".into());
        names
    }

    /// Bytes [`Simulator::write_to_dir`] writes at most: every frame uncompressed (its
    /// pixels and a header of two 2880-byte blocks; tile compression only makes less).
    pub fn output_bytes(&self) -> u64 {
        let g = &self.profile.geometry;
        let px = if self.scene.observation.bitpix == 16 { 2 } else { 4 };
        let frame = (g.nx as u64 * g.ny as u64 * px).div_ceil(2880) * 2880 + 2 * 2880;
        let frames = (self.targets.len() * self.frames_per_target() + self.n_dome_flat_frames()) as u64;
        frames.saturating_mul(frame)
    }

    /// Simulate every frame and write it to `dir` (FITS, atomically) together with
    /// `truth.json`. Frames stream: at most one frame per worker thread is in memory.
    /// `on_frame` is called after each frame is written (progress reporting).
    pub fn write_to_dir(&self, dir: &std::path::Path, on_frame: &(dyn Fn(&str) + Sync)) -> crate::error::Result<Truth> {
        use rayon::prelude::*;
        use sofipol_calib::fits::{write_frame, Bitpix, WriteOptions};
        std::fs::create_dir_all(dir).map_err(|source| crate::error::Error::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let o = &self.scene.observation;
        let opts = WriteOptions {
            bitpix: if o.bitpix == 16 { Bitpix::I16 } else { Bitpix::F32 },
            compress: o.compress,
            with_variance_and_mask: false,
        };
        let n = self.frames_per_target();
        let jobs: Vec<(usize, usize)> = (0..self.targets.len())
            .flat_map(|t| (0..n).map(move |k| (t, k)))
            .collect();
        let truths: Vec<crate::error::Result<FrameTruth>> = jobs
            .par_iter()
            .map(|&(t, k)| {
                let f = self.frame(t, k);
                let path = dir.join(&f.file_name);
                write_frame(&path, &f.frame, &opts).map_err(|e| crate::error::Error::calib("simulated frame", e))?;
                on_frame(&f.file_name);
                Ok(f.truth)
            })
            .collect();
        let mut per_t: Vec<Vec<FrameTruth>> = vec![Vec::new(); self.targets.len()];
        for (r, &(t, _)) in truths.into_iter().zip(&jobs) {
            per_t[t].push(r?);
        }
        (0..self.n_dome_flat_frames())
            .into_par_iter()
            .map(|i| {
                let f = self.dome_flat_frame(i);
                write_frame(&dir.join(&f.file_name), &f.frame, &opts)
                    .map_err(|e| crate::error::Error::calib("simulated dome flat", e))?;
                on_frame(&f.file_name);
                Ok(())
            })
            .collect::<crate::error::Result<Vec<()>>>()?;
        let truth = self.truth(&per_t);
        crate::io::write_json_atomic(&dir.join("truth.json"), &truth)
            .map_err(|e| crate::error::Error::calib("truth", e))?;
        Ok(truth)
    }
}
