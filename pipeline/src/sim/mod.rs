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
//! frame parameters: time and pointing (parallactic angle), header offset (+ pointing_error),
//!   transparency, sky level, seeing, telescope polarization
//! expectation: sky (telescope pol.) -> sources (psf | point; ISM, telescope pol.,
//!   throughput, instrumental pol.)
//!   -> strips (focal mask) -> flat_field -> nonlinearity
//! noise: photon_noise -> read_noise
//! detector: cosmic_rays -> bad_pixels -> saturation
//! ```
//!
//! Submodules: [`scene`] (the TOML scene), [`schedule`] (when each sequence starts, where it
//! points), [`pointing`] (sidereal time, hour angle, airmass, parallactic angle at La
//! Silla), [`effects`] (one function per effect), [`foreground`] (the interstellar
//! foreground as a field on the sky), [`population`] (field stars drawn from a K-band
//! luminosity function), [`psf`] (PSF rendering), [`truth`] (what
//! was simulated), `frame` (one science frame: parameters,
//! sources, detector, header), `dome` (dome-flat frames), `output` (whole scenes in
//! memory or written to a folder), `loaded` (one target's frames as the reduction's input),
//! [`hwp`] (half-wave-plate scenes for a half-wave-plate profile: [`HwpSimulator`];
//! their scene section in [`hwp_scene`]).
mod dome;
pub mod effects;
pub mod foreground;
mod frame;
pub mod hwp;
pub mod hwp_scene;
mod loaded;
mod output;
pub mod pointing;
pub mod population;
pub mod psf;
pub mod rng;
pub mod scene;
pub mod schedule;
pub mod truth;
mod validate;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};

use ndarray::Array2;
use rand::RngExt;
use rand_distr::{Distribution, StandardNormal};
use sofipol_calib::Profile;

pub use dome::SimFlatFrame;
pub use hwp::{HwpSimulator, HwpTruth};
pub use loaded::loaded_from_sim;
pub use scene::{Binary, EffectKind, Scene, StandardSource};
pub use truth::{
    ComponentTruth, FieldStarTruth, FlatFrameTruth, FramePointing, FrameTruth, SimFrame, SourceTruth, TargetForeground,
    TargetTruth, Truth,
};

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

/// A prepared simulation: fixed detector maps and the plan of frames.
pub struct Simulator {
    scene: Scene,
    profile: Profile,
    calls: EffectCalls,
    bad: Option<effects::BadPixelMap>,
    flat: Option<Array2<f32>>,
    /// Sequence `t`'s start and pointing.
    plan: Vec<schedule::SequencePlan>,
    /// Binaries, then the standards as single stars (flux_b = 0): sequence `t` observes
    /// `targets[t]` (a binary's field stars: the scene's, then those drawn by
    /// `field_population`).
    targets: Vec<Binary>,
    /// The foreground field's modes (effect `foreground_field`).
    foreground: Option<foreground::ForegroundField>,
    /// K magnitude of each binary's drawn field stars (after the scene's own), per target.
    drawn_k: Vec<Vec<f64>>,
}

impl Simulator {
    /// Prepare a scene (validates it and draws the fixed detector maps of listed effects).
    pub fn new(scene: Scene, profile: Profile) -> crate::error::Result<Simulator> {
        scene.validate()?;
        let hwp = profile.modulation_kind() == sofipol_calib::profile::ModulationKind::HalfWavePlate;
        if scene.half_wave_plate.is_some() || hwp {
            return Err(crate::error::Error::Scene {
                origin: scene.name.clone(),
                reason: format!(
                    "profile {} (modulation.kind = {}) with{} a [half_wave_plate] section: a half-wave-plate scene is simulated by HwpSimulator (`sofipol simulate` chooses by the profile)",
                    profile.name,
                    profile.modulation_kind().name(),
                    if scene.half_wave_plate.is_some() { "" } else { "out" }
                ),
            });
        }
        let calls = EffectCalls::default();
        let (ny, nx) = (profile.geometry.ny, profile.geometry.nx);
        let bad = scene.has(EffectKind::BadPixels).then(|| {
            effects::bad_pixel_map(
                &calls,
                scene.detector_seed.unwrap_or(scene.seed),
                &scene.bad_pixels.clone().unwrap_or_default(),
                ny,
                nx,
            )
        });
        let flat = scene.has(EffectKind::FlatField).then(|| {
            effects::flat_field_map(
                &calls,
                scene.detector_seed.unwrap_or(scene.seed),
                &scene.flat_field.clone().unwrap_or_default(),
                ny,
                nx,
            )
        });
        let mut targets: Vec<Binary> = scene
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
                ra_deg: st.ra_deg,
                dec_deg: st.dec_deg,
                hour_angle_h: st.hour_angle_h,
                start_ut: st.start_ut.clone(),
            }))
            .collect();
        // When each sequence starts and where it points (binaries, then standards).
        let plan = scene.plan()?;
        let foreground = scene.has(EffectKind::ForegroundField).then(|| {
            let c = scene.foreground_field.clone().unwrap_or_default();
            calls.hit(EffectKind::ForegroundField);
            foreground::ForegroundField::new(&c, c.seed.unwrap_or(scene.seed))
        });
        let mut drawn_k = vec![Vec::new(); targets.len()];
        if let (Some(c), Some(zp)) = (&scene.field_population, scene.observation.zero_point_mag) {
            let g = &profile.geometry;
            let posang = scene.observation.orientations_deg[0];
            for (t, b) in targets.iter_mut().enumerate().take(scene.binary.len()) {
                let (bx, by) = stokes_offset(b, posang, g.pixscale_arcsec);
                let at = population::Frame0 {
                    a_xy: primary_xy(b, g),
                    b_off: [bx, by],
                    posang_deg: posang,
                };
                for d in population::draw(c, zp, scene.observation.dit_s, g, &at, scene.seed, t as u64) {
                    b.field_star.push(d.star);
                    drawn_k[t].push(d.k_mag);
                }
            }
        }
        Ok(Simulator {
            scene,
            profile,
            calls,
            bad,
            flat,
            plan,
            targets,
            foreground,
            drawn_k,
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

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Sequence `t`'s start (TPL START) and pointing.
    pub fn sequence_plan(&self, t: usize) -> &schedule::SequencePlan {
        &self.plan[t]
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

    /// File name of frame `k` of target `t`: the scene and target names reduced to
    /// [`file_slug`]s (a name holding `/` or `..` stays inside the output folder).
    pub fn file_name(&self, t: usize, k: usize) -> String {
        let ext = if self.scene.observation.compress {
            "fits.fz"
        } else {
            "fits"
        };
        format!(
            "SOFI_{}_{}_{:02}.{ext}",
            file_slug(&self.scene.name),
            file_slug(&self.targets[t].name),
            k + 1
        )
    }

    fn scale(&self) -> f64 {
        self.profile.geometry.pixscale_arcsec
    }
}

/// A's ordinary image (x, y) at zero offset, px: the binary's `x_px`, `y_px`, else the
/// profile's pointing ([`sofipol_calib::profile::Geometry::pointing_px`]: the detector's
/// centre column and the middle of the o-target strip, or without a focal mask the point
/// that centres the pair of images).
pub(crate) fn primary_xy(b: &Binary, g: &sofipol_calib::profile::Geometry) -> [f64; 2] {
    let (x, y) = g.pointing_px();
    [b.x_px.unwrap_or(x), b.y_px.unwrap_or(y)]
}

/// B's offset from A on the detector at rotator angle `posang`, px.
fn stokes_offset(b: &Binary, posang: f64, scale: f64) -> (f64, f64) {
    crate::stokes::model::companion_offset_px(b.separation_arcsec, b.pa_deg, posang, scale)
}

/// A name as a part of a file name: ASCII letters and digits kept, everything else
/// (`/`, `.`, spaces, control characters...) `_`.
pub fn file_slug(name: &str) -> String {
    name.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}

/// Draw a standard normal (helper shared by effects).
pub(crate) fn normal<R: rand::Rng + ?Sized>(r: &mut R) -> f64 {
    StandardNormal.sample(r)
}

/// Draw a uniform in [0, 1).
pub(crate) fn uniform<R: rand::Rng + ?Sized>(r: &mut R) -> f64 {
    r.random::<f64>()
}
