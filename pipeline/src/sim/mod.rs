//! The scene simulator: SOFI-like raw frames with known truth.
//!
//! A [`Scene`] lists the observing setup, the binaries and the effects to simulate.
//! **Only listed effects are simulated** and an unlisted effect is never called (the
//! [`Simulator`] counts the calls of every effect function; tests check the counts).
//! A scene with no effects gives the exact noiseless expectation of the forward model
//! ([`crate::stokes::model`]), which is the same model the inversion tests invert.
//!
//! Per frame, in this order (each step its own function in [`effects`]):
//! ```text
//! frame parameters: header offset (+ pointing_error), transparency, sky level, seeing
//! expectation: sky -> sources (psf | point; throughput, ISM, instrumental pol.)
//!   -> strips (focal mask) -> flat_field -> nonlinearity
//! noise: photon_noise -> read_noise
//! detector: cosmic_rays -> bad_pixels -> saturation
//! ```
pub mod effects;
pub mod psf;
pub mod rng;
pub mod scene;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};

use ndarray::Array2;
use rand::RngExt;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;
use sofipol_calib::{Frame, Header, Profile};

use crate::stokes::model::{beam_fluxes, companion_offset_px, Polarization};
pub use scene::{Binary, EffectKind, Scene, StandardSource};

/// Per-effect call counters.
#[derive(Debug, Default)]
pub struct EffectCalls([AtomicU64; EffectKind::ALL.len()]);

impl EffectCalls {
    /// Count one call of an effect function.
    pub fn hit(&self, k: EffectKind) {
        self.0[k.index()].fetch_add(1, Ordering::Relaxed);
    }
    /// Calls so far of each effect that was called at least once.
    pub fn snapshot(&self) -> BTreeMap<&'static str, u64> {
        EffectKind::ALL
            .iter()
            .filter_map(|&k| {
                let n = self.0[k.index()].load(Ordering::Relaxed);
                (n > 0).then_some((k.name(), n))
            })
            .collect()
    }
}

/// Where a source landed in one frame and with what fluxes (ADU, before noise).
#[derive(Debug, Clone, Serialize)]
pub struct SourceTruth {
    /// "A", "B", or "field1"...
    pub name: String,
    /// Ordinary image position (x, y), px, true (pointing error included).
    pub o_xy: [f64; 2],
    /// Extraordinary image position.
    pub e_xy: [f64; 2],
    /// Ordinary-beam flux, ADU (transparency, throughput, polarization included; before
    /// flat field and non-linearity).
    pub flux_o: f64,
    /// Extraordinary-beam flux, ADU.
    pub flux_e: f64,
}

/// Realised parameters of one frame.
#[derive(Debug, Clone, Serialize)]
pub struct FrameTruth {
    /// File name (no directory).
    pub file: String,
    /// Rotator position angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle phi = s POSANG + theta0, deg.
    pub analyzer_deg: f64,
    /// Jitter offset written to the header, px.
    pub header_offset_px: [f64; 2],
    /// True jitter offset, px.
    pub true_offset_px: [f64; 2],
    /// Transparency factor applied to the sources.
    pub transparency: f64,
    /// Sky level at the detector centre, ADU (0 without sky).
    pub sky_level_adu: f64,
    /// Seeing FWHM of this frame, px (0 without psf).
    pub fwhm_px: f64,
    /// Moffat beta of this frame (0 for other profiles).
    pub beta: f64,
    /// Sources.
    pub sources: Vec<SourceTruth>,
    /// Cosmic-ray pixels hit.
    pub cosmic_ray_pixels: usize,
}

/// A binary component's truth.
#[derive(Debug, Clone, Serialize)]
pub struct ComponentTruth {
    /// "A" or "B".
    pub name: String,
    /// Total flux (o + e) with unit transmission, ADU.
    pub flux: f64,
    /// Intrinsic polarization.
    pub intrinsic: Polarization,
    /// What a perfect reduction should report in the sky frame: intrinsic + ISM.
    pub q: f64,
    /// Sky-frame u (intrinsic + ISM).
    pub u: f64,
    /// Degree of polarization of (q, u).
    pub p: f64,
    /// Angle of (q, u), deg [0, 180).
    pub gamma_deg: f64,
}

/// One target's truth.
#[derive(Debug, Clone, Serialize)]
pub struct TargetTruth {
    /// Object name.
    pub object: String,
    /// TPL START of the sequence.
    pub tpl_start: String,
    /// Separation, arcsec.
    pub separation_arcsec: f64,
    /// PA of B from A, deg.
    pub pa_deg: f64,
    /// Components A, B.
    pub components: Vec<ComponentTruth>,
    /// Frames in exposure order.
    pub frames: Vec<FrameTruth>,
}

/// Truth of a whole simulation (written as truth.json).
#[derive(Debug, Clone, Serialize)]
pub struct Truth {
    /// sofipol version.
    pub software: String,
    /// The scene as parsed (defaults filled in).
    pub scene: Scene,
    /// Instrument profile name.
    pub profile: String,
    /// Effects simulated.
    pub effects: Vec<&'static str>,
    /// Effect sections present but not listed (ignored).
    pub ignored_sections: Vec<&'static str>,
    /// Fixed detector realisations (bad-pixel counts, flat statistics...).
    pub detector: serde_json::Value,
    /// Targets.
    pub targets: Vec<TargetTruth>,
    /// Dome-flat frames (the `dome_flats` effect), in exposure order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub dome_flats: Vec<FlatFrameTruth>,
    /// Standard stars (one component "A", separation 0), in observing order after the
    /// targets.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub standards: Vec<TargetTruth>,
}

/// Realised parameters of one dome-flat frame.
#[derive(Debug, Clone, Serialize)]
pub struct FlatFrameTruth {
    /// File name (no directory).
    pub file: String,
    /// Rotator position angle, deg.
    pub posang_deg: f64,
    /// Lamp on (`INS LAMP1 ST` = T).
    pub lamp_on: bool,
    /// Light per pixel in the o strips and the e strips before the pixel response, ADU.
    pub level_o_adu: f64,
    /// Same for the e strips.
    pub level_e_adu: f64,
}

/// A simulated frame in memory.
#[derive(Debug, Clone)]
pub struct SimFrame {
    /// File name (no directory).
    pub file_name: String,
    /// The frame (data in ADU, header, history).
    pub frame: Frame,
    /// Its truth.
    pub truth: FrameTruth,
}

/// A prepared simulation: fixed detector maps and the plan of frames.
pub struct Simulator {
    scene: Scene,
    profile: Profile,
    calls: EffectCalls,
    bad: Option<effects::BadPixelMap>,
    flat: Option<Array2<f32>>,
    tpl_starts: Vec<(f64, String)>,
    /// Binaries, then the standards as single stars (flux_b = 0): sequence `t` observes
    /// `targets[t]`.
    targets: Vec<Binary>,
}

/// Per-frame parameters drawn before rendering.
struct FrameParams {
    posang: f64,
    phi: f64,
    header_off: [f64; 2],
    true_off: [f64; 2],
    transparency: f64,
    sky_level: f64,
    psf: psf::Psf,
    mjd: f64,
}

impl Simulator {
    /// Prepare a scene (validates it and draws the fixed detector maps of listed effects).
    pub fn new(scene: Scene, profile: Profile) -> crate::error::Result<Simulator> {
        scene.validate()?;
        let calls = EffectCalls::default();
        let (ny, nx) = (profile.geometry.ny, profile.geometry.nx);
        let bad = scene.has(EffectKind::BadPixels).then(|| {
            effects::bad_pixel_map(
                &calls,
                scene.seed,
                &scene.bad_pixels.clone().unwrap_or_default(),
                ny,
                nx,
            )
        });
        let flat = scene.has(EffectKind::FlatField).then(|| {
            effects::flat_field_map(
                &calls,
                scene.seed,
                &scene.flat_field.clone().unwrap_or_default(),
                ny,
                nx,
            )
        });
        // Sequence start times: targets one after another through the night.
        let o = &scene.observation;
        let mjd0 = effects::mjd_from_date_time(&o.date, &o.start_ut).ok_or_else(|| crate::error::Error::Scene {
            origin: "scene".into(),
            reason: format!("observation.date/start_ut '{} {}' not understood", o.date, o.start_ut),
        })?;
        let nframes = o.orientations_deg.len() * o.dithers;
        let per_seq_s = nframes as f64 * (o.dit_s * o.ndit as f64 + o.overhead_s) + 120.0;
        let targets: Vec<Binary> = scene
            .binary
            .iter()
            .cloned()
            .chain(scene.standard.iter().map(|st| Binary {
                name: st.name.clone(),
                separation_arcsec: 0.0,
                pa_deg: 0.0,
                flux_a: st.flux,
                flux_b: 0.0,
                p_a: st.p,
                gamma_a_deg: st.gamma_deg,
                p_b: 0.0,
                gamma_b_deg: 0.0,
                x_px: None,
                y_px: None,
                field_star: vec![],
            }))
            .collect();
        let tpl_starts = (0..targets.len())
            .map(|t| {
                let mjd = mjd0 + t as f64 * per_seq_s / 86400.0;
                (mjd, effects::iso_from_mjd(mjd, false))
            })
            .collect();
        Ok(Simulator {
            scene,
            profile,
            calls,
            bad,
            flat,
            tpl_starts,
            targets,
        })
    }

    /// Whether sequence `t` observes a standard star (after the binaries).
    pub fn is_standard(&self, t: usize) -> bool {
        t >= self.scene.binary.len()
    }

    /// Number of sequences: binaries, then standards.
    pub fn n_sequences(&self) -> usize {
        self.targets.len()
    }

    fn target_truth(&self, t: usize, frames: &[Vec<FrameTruth>]) -> TargetTruth {
        let b = &self.targets[t];
        TargetTruth {
            object: b.name.clone(),
            tpl_start: self.tpl_starts[t].1.clone(),
            separation_arcsec: b.separation_arcsec,
            pa_deg: b.pa_deg,
            components: self.component_truth(t),
            frames: frames.get(t).cloned().unwrap_or_default(),
        }
    }

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Frames per target.
    pub fn frames_per_target(&self) -> usize {
        self.scene.observation.orientations_deg.len() * self.scene.observation.dithers
    }

    /// Calls of each effect function so far.
    pub fn calls(&self) -> BTreeMap<&'static str, u64> {
        self.calls.snapshot()
    }

    /// The fixed bad-pixel map (1 = bad), when the effect is listed.
    pub fn bad_pixel_mask(&self) -> Option<Array2<u8>> {
        self.bad.as_ref().map(|b| b.mask.clone())
    }

    /// The fixed pixel response (the `flat_field` effect), when listed.
    pub fn pixel_response(&self) -> Option<&Array2<f32>> {
        self.flat.as_ref()
    }

    /// File name of frame `k` of target `t`.
    pub fn file_name(&self, t: usize, k: usize) -> String {
        let slug: String = self.targets[t]
            .name
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
            .collect();
        let ext = if self.scene.observation.compress {
            "fits.fz"
        } else {
            "fits"
        };
        format!("SOFI_{}_{slug}_{:02}.{ext}", self.scene.name, k + 1)
    }

    fn scale(&self) -> f64 {
        self.profile.geometry.pixscale_arcsec
    }

    fn frame_params(&self, t: usize, k: usize) -> FrameParams {
        let s = &self.scene;
        let o = &s.observation;
        let nd = o.dithers;
        let (io, d) = (k / nd, k % nd);
        let posang = o.orientations_deg[io];
        let step = o.jitter_step_px.unwrap_or(self.profile.geometry.jitter_step_px);
        let header_off = [(d as f64 - (nd as f64 - 1.0) / 2.0) * step, 0.0];
        let key = (t as u64, k as u64);
        let true_off = if s.has(EffectKind::PointingError) {
            effects::pointing_error(
                &self.calls,
                s.seed,
                &s.pointing_error.clone().unwrap_or_default(),
                key,
                header_off,
            )
        } else {
            header_off
        };
        let transparency = if s.has(EffectKind::Transparency) {
            effects::transparency(&self.calls, s.seed, &s.transparency.clone().unwrap_or_default(), key)
        } else {
            1.0
        };
        let sky_level = if s.has(EffectKind::Sky) {
            effects::sky_level(&self.calls, s.seed, &s.sky.clone().unwrap_or_default(), key)
        } else {
            0.0
        };
        let psf = if s.has(EffectKind::Psf) {
            effects::frame_psf(
                &self.calls,
                s.seed,
                &s.psf.clone().unwrap_or_default(),
                key,
                self.scale(),
            )
        } else {
            psf::Psf::Point
        };
        let mjd = self.tpl_starts[t].0 + (k as f64 * (o.dit_s * o.ndit as f64 + o.overhead_s) + 20.0) / 86400.0;
        FrameParams {
            posang,
            phi: if s.has(EffectKind::AnalyzerAngle) {
                effects::analyzer_angle(&self.calls, &s.analyzer_angle.clone().unwrap_or_default(), posang)
            } else {
                self.profile.angles.analyzer_angle_deg(posang)
            },
            header_off,
            true_off,
            transparency,
            sky_level,
            psf,
            mjd,
        }
    }

    /// Truth of target `t`'s components.
    fn component_truth(&self, t: usize) -> Vec<ComponentTruth> {
        let b = &self.targets[t];
        let ism = if self.is_standard(t) {
            Polarization::default()
        } else {
            self.ism()
        };
        [
            ("A", b.flux_a, b.p_a, b.gamma_a_deg),
            ("B", b.flux_b, b.p_b, b.gamma_b_deg),
        ]
        .into_iter()
        .map(|(name, flux, p, g)| {
            let intrinsic = Polarization::from_p_gamma(p, g);
            let sky = intrinsic.add(ism);
            ComponentTruth {
                name: name.into(),
                flux,
                intrinsic,
                q: sky.q,
                u: sky.u,
                p: sky.p(),
                gamma_deg: sky.gamma_deg(),
            }
        })
        .collect()
    }

    fn ism(&self) -> Polarization {
        if self.scene.has(EffectKind::InterstellarPolarization) {
            self.calls.hit(EffectKind::InterstellarPolarization);
            let c = self.scene.interstellar_polarization.clone().unwrap_or_default();
            Polarization::from_p_gamma(c.p, c.angle_deg)
        } else {
            Polarization::default()
        }
    }

    /// Simulate frame `k` (0-based exposure index) of target `t`.
    pub fn frame(&self, t: usize, k: usize) -> SimFrame {
        let s = &self.scene;
        let g = &self.profile.geometry;
        let (ny, nx) = (g.ny, g.nx);
        let b = &self.targets[t];
        let fp = self.frame_params(t, k);
        let mut img = Array2::<f32>::zeros((ny, nx));

        if s.has(EffectKind::Sky) {
            effects::sky(&self.calls, &mut img, fp.sky_level, &s.sky.clone().unwrap_or_default());
        }

        // Sources: A, B and field stars, each as (name, offset from A in px, flux, pol).
        let x_a = b.x_px.unwrap_or(nx as f64 / 2.0);
        let y_a = b.y_px.unwrap_or((g.o_target[0] + g.o_target[1]) as f64 / 2.0 - 0.5);
        let ism = if self.is_standard(t) {
            Polarization::default()
        } else {
            self.ism()
        };
        let (t_o, t_e) = if s.has(EffectKind::Throughput) {
            effects::throughput(&self.calls, &s.throughput.clone().unwrap_or_default())
        } else {
            (1.0, 1.0)
        };
        let inst = if s.has(EffectKind::InstrumentalPolarization) {
            effects::instrumental_polarization(&self.calls, &s.instrumental_polarization.clone().unwrap_or_default())
        } else {
            0.0
        };
        let mut srcs: Vec<(String, (f64, f64), f64, Polarization)> = vec![
            (
                "A".into(),
                (0.0, 0.0),
                b.flux_a,
                Polarization::from_p_gamma(b.p_a, b.gamma_a_deg),
            ),
            (
                "B".into(),
                companion_offset_px(b.separation_arcsec, b.pa_deg, fp.posang, self.scale()),
                b.flux_b,
                Polarization::from_p_gamma(b.p_b, b.gamma_b_deg),
            ),
        ];
        if self.is_standard(t) {
            srcs.truncate(1);
        }
        for (i, f) in b.field_star.iter().enumerate() {
            srcs.push((
                format!("field{}", i + 1),
                companion_offset_px(f.separation_arcsec, f.pa_deg, fp.posang, self.scale()),
                f.flux,
                Polarization::from_p_gamma(f.p, f.gamma_deg),
            ));
        }
        let mut sources = Vec::with_capacity(srcs.len());
        for (name, (dx, dy), flux, pol) in srcs {
            let pol = pol.add(ism);
            let (mut fo, mut fe) = beam_fluxes(flux * fp.transparency, pol, fp.phi, t_o, t_e);
            let tot = fo + fe;
            if inst != 0.0 && tot > 0.0 {
                // Instrumental polarization q_inst (instrument frame) adds to F at every
                // orientation: f_o,e = (f_o + f_e)/2 (1 +- (F + q_inst)). (A zero-flux
                // component stays zero, not 0/0.)
                let f = (fo - fe) / tot + inst;
                fo = 0.5 * tot * (1.0 + f);
                fe = 0.5 * tot * (1.0 - f);
            }
            let xo = x_a + fp.true_off[0] + dx;
            let yo = y_a + fp.true_off[1] + dy;
            let xe = xo + g.eo_offset_px[0];
            let ye = yo + g.eo_offset_px[1];
            let stamp_o = self.render(fp.psf, xo, yo);
            psf::add_stamp(&mut img, &stamp_o, fo);
            // The e image has the o image's sub-pixel phase when the beam offset is a
            // whole number of pixels (SOFI: 167 px): reuse the stamp.
            let (ox, oy) = (g.eo_offset_px[0], g.eo_offset_px[1]);
            let stamp_e = if ox.fract() == 0.0 && oy.fract() == 0.0 && (xe - ox == xo) && (ye - oy == yo) {
                stamp_o.shifted(ox as i64, oy as i64)
            } else {
                self.render(fp.psf, xe, ye)
            };
            psf::add_stamp(&mut img, &stamp_e, fe);
            sources.push(SourceTruth {
                name,
                o_xy: [xo, yo],
                e_xy: [xe, ye],
                flux_o: fo,
                flux_e: fe,
            });
        }

        let cr_pixels = self.detector(&mut img, (t as u64, k as u64), s.observation.ndit);

        let file_name = self.file_name(t, k);
        let header = self.header(t, k, &fp, &file_name);
        let frame = Frame::new(img, header).with_history(
            "simulate",
            format!(
                "scene '{}' seed {} target '{}' exposure {}; effects: [{}]",
                s.name,
                s.seed,
                b.name,
                k + 1,
                s.effects.iter().map(|e| e.name()).collect::<Vec<_>>().join(", ")
            ),
        );
        let truth = FrameTruth {
            file: file_name.clone(),
            posang_deg: fp.posang,
            analyzer_deg: fp.phi,
            header_offset_px: fp.header_off,
            true_offset_px: fp.true_off,
            transparency: fp.transparency,
            sky_level_adu: fp.sky_level,
            fwhm_px: fp.psf.fwhm_px(),
            beta: match fp.psf {
                psf::Psf::Moffat { beta, .. } => beta,
                _ => 0.0,
            },
            sources,
            cosmic_ray_pixels: cr_pixels,
        };
        SimFrame {
            file_name,
            frame,
            truth,
        }
    }

    /// What the detector does to the light of any frame (science or calibration), in
    /// order: strips -> flat_field -> nonlinearity -> photon_noise -> read_noise ->
    /// cosmic_rays -> bad_pixels -> saturation (listed effects only). Returns the pixels
    /// hit by cosmic rays.
    fn detector(&self, img: &mut Array2<f32>, fkey: (u64, u64), ndit: u32) -> usize {
        let s = &self.scene;
        let g = &self.profile.geometry;
        if s.has(EffectKind::Strips) {
            effects::strips(&self.calls, img, g);
        }
        if let Some(flat) = &self.flat {
            self.calls.hit(EffectKind::FlatField);
            ndarray::Zip::from(&mut *img).and(flat).for_each(|v, &r| *v *= r);
        }
        if s.has(EffectKind::Nonlinearity) {
            let c = s
                .nonlinearity
                .clone()
                .unwrap_or_default()
                .coeff_per_adu
                .unwrap_or(self.profile.detector.nonlin_coeff_per_adu);
            effects::nonlinearity(&self.calls, img, c);
        }
        if s.has(EffectKind::PhotonNoise) {
            effects::photon_noise(
                &self.calls,
                img,
                s.seed,
                fkey,
                self.profile.detector.effective_gain(ndit),
            );
        }
        if s.has(EffectKind::ReadNoise) {
            effects::read_noise(
                &self.calls,
                img,
                s.seed,
                fkey,
                self.profile.detector.read_variance_adu2(ndit).sqrt(),
            );
        }
        let mut cr_pixels = 0;
        if s.has(EffectKind::CosmicRays) {
            cr_pixels = effects::cosmic_rays(
                &self.calls,
                img,
                s.seed,
                fkey,
                &s.cosmic_rays.clone().unwrap_or_default(),
            );
        }
        if let Some(bad) = &self.bad {
            effects::apply_bad_pixels(&self.calls, img, bad);
        }
        if s.has(EffectKind::Saturation) {
            let level = s
                .saturation
                .clone()
                .unwrap_or_default()
                .level_adu
                .unwrap_or(self.profile.detector.saturation_adu);
            effects::saturation(&self.calls, img, level);
        }
        cr_pixels
    }

    fn render(&self, p: psf::Psf, x: f64, y: f64) -> psf::Stamp {
        if !matches!(p, psf::Psf::Point) {
            self.calls.hit(EffectKind::Psf);
        }
        psf::render(p, x, y)
    }

    fn header(&self, t: usize, k: usize, fp: &FrameParams, file_name: &str) -> Header {
        let s = &self.scene;
        let o = &s.observation;
        let kw = &self.profile.keywords;
        let b = &self.targets[t];
        let mut h = Header::new(file_name);
        h.set(&kw.instrument, self.profile.matching.instrument.as_str());
        h.set(&kw.object, b.name.as_str());
        h.set(&kw.date_obs, effects::iso_from_mjd(fp.mjd, true));
        h.set(&kw.mjd_obs, fp.mjd);
        h.set(&kw.exptime, o.dit_s);
        // A fixed fake pointing per target, from its name.
        let hash = rng::splitmix64(
            b.name
                .bytes()
                .fold(7u64, |a, c| a.wrapping_mul(31).wrapping_add(c as u64)),
        );
        h.set("RA", (hash % 36000) as f64 / 100.0);
        h.set("DEC", -60.0 + ((hash >> 20) % 9000) as f64 / 100.0);
        if self.is_standard(t) {
            h.set(&kw.dpr_catg, "CALIB");
            h.set(&kw.dpr_type, "STD");
        } else {
            h.set(&kw.dpr_catg, "SCIENCE");
            h.set(&kw.dpr_type, "OBJECT");
        }
        h.set(&kw.dpr_tech, self.profile.matching.polarimetry_tech.as_str());
        h.set(&kw.tpl_id, self.profile.matching.polarimetry_template.as_str());
        h.set(&kw.tpl_start, self.tpl_starts[t].1.as_str());
        h.set(&kw.tpl_nexp, self.frames_per_target() as i64);
        h.set(&kw.tpl_expno, (k + 1) as i64);
        h.set(&kw.targ_name, b.name.replace(' ', "_"));
        h.set(&kw.filter, o.filter.as_str());
        h.set(&format!("{}1 ID", kw.opti_prefix), "MASK_POL");
        h.set(&format!("{}3 ID", kw.opti_prefix), "WOLLASTON");
        h.set(&kw.pixscale, self.scale());
        h.set(&kw.posang, fp.posang);
        h.set(&kw.offset_x, fp.header_off[0]);
        h.set(&kw.offset_y, fp.header_off[1]);
        h.set(&kw.dit, o.dit_s);
        h.set(&kw.ndit, o.ndit as i64);
        h.set(&kw.parang, -150.0 + 2.0 * k as f64);
        h.set(&kw.airmass, 1.05 + 0.002 * k as f64);
        h
    }

    /// Truth of the whole scene (frames are re-derived cheaply: no images are rendered).
    pub fn truth(&self, frames: &[Vec<FrameTruth>]) -> Truth {
        let s = &self.scene;
        let mut detector = serde_json::Map::new();
        if let Some(b) = &self.bad {
            detector.insert(
                "bad_pixels".into(),
                serde_json::to_value(&b.summary).unwrap_or_default(),
            );
        }
        if let Some(f) = &self.flat {
            let n = f.len() as f64;
            let mean = f.iter().map(|&v| v as f64).sum::<f64>() / n;
            let rms = (f.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n).sqrt();
            detector.insert("flat_field".into(), serde_json::json!({"mean": mean, "rms": rms}));
        }
        if s.has(EffectKind::Throughput) {
            let (t_o, t_e) = effects::throughput(&self.calls, &s.throughput.clone().unwrap_or_default());
            detector.insert("throughput".into(), serde_json::json!({"t_o": t_o, "t_e": t_e}));
        }
        if s.has(EffectKind::InstrumentalPolarization) {
            let c = s.instrumental_polarization.clone().unwrap_or_default();
            detector.insert(
                "instrumental_polarization".into(),
                serde_json::json!({"p": c.p, "angle_deg": c.angle_deg, "q_inst_added_to_F": c.p * (2.0 * c.angle_deg.to_radians()).cos()}),
            );
        }
        Truth {
            software: format!("sofipol {}", env!("CARGO_PKG_VERSION")),
            scene: s.clone(),
            profile: self.profile.name.clone(),
            effects: s.effects.iter().map(|e| e.name()).collect(),
            ignored_sections: s.ignored_sections(),
            detector: serde_json::Value::Object(detector),
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
    fn dome_flat_plan(&self, i: usize) -> ((usize, usize), FlatFrameTruth) {
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
        let slug: String = s
            .name
            .chars()
            .map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '_' })
            .collect();
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
        let is_o = |y: usize| [g.o_sky2, g.o_target, g.o_sky1].iter().any(|r| y >= r[0] && y < r[1]);
        let is_e = |y: usize| [g.e_sky2, g.e_target, g.e_sky1].iter().any(|r| y >= r[0] && y < r[1]);
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

/// Draw a standard normal (helper shared by effects).
pub(crate) fn normal<R: rand::Rng + ?Sized>(r: &mut R) -> f64 {
    StandardNormal.sample(r)
}

/// Draw a uniform in [0, 1).
pub(crate) fn uniform<R: rand::Rng + ?Sized>(r: &mut R) -> f64 {
    r.random::<f64>()
}

impl Simulator {
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
