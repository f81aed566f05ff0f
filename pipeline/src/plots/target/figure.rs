//! What a target figure is drawn from, in two parts: the pixels (cut-out stacks, prepared
//! while the frames are in memory, during the reduction) and the numbers (taken from the
//! catalog entry once the calibration has re-solved it). [`FigureNumbers`] is every
//! catalog value the figure draws: the text, the polarization vectors and the fitted F
//! lines all read it, so a figure can be checked against the catalog it belongs to.
use super::*;
use crate::calibration::FilterCalibration;
use crate::catalog::{CombinedF, Component};
use crate::solve::telescope;

/// The pixel part of one orientation's cell.
#[derive(Clone)]
pub struct OrientationSketch {
    /// Rotator angle, deg (NaN when the orientation's frames are not known).
    pub posang_deg: f64,
    /// Analyzer angle the reduction used (the profile's relation), deg.
    pub analyzer_deg: f64,
    /// Frames of the orientation.
    pub n_frames: usize,
    /// Median of the registered dithers of the o and e beams.
    pub(super) tiles: [Option<Stack>; 2],
}

/// Everything a target figure needs from the reduction besides the catalog entry: the
/// cut-out stacks of every orientation and the per-dither measurements. Small (a few
/// cut-outs per orientation): the frames can be dropped once it is made.
#[derive(Clone, Default)]
pub struct FigureInputs {
    /// Per orientation (at most 16).
    pub orientations: Vec<OrientationSketch>,
    /// The per-dither measurements, when the target got that far.
    pub measured: Option<Measured>,
}

impl FigureInputs {
    /// Stack the cut-outs of the kept frames `cal` (when present) around the measured
    /// positions of `m`.
    pub fn new(cal: Option<&[SkySubtractedOrientation]>, m: Option<&Measured>) -> FigureInputs {
        let cal = cal.unwrap_or(&[]);
        let n_or = match m {
            Some(m) => cal.len().max(
                m.dithers
                    .first()
                    .filter(|c| c.iter().any(|o| !o.is_empty()))
                    .map(|c| c.len())
                    .unwrap_or(0),
            ),
            None => 0,
        }
        .min(16);
        let orientations = (0..n_or)
            .map(|k| {
                let o = cal.get(k);
                OrientationSketch {
                    posang_deg: o.map_or(f64::NAN, |o| o.posang_deg),
                    analyzer_deg: o.map_or(f64::NAN, |o| o.analyzer_deg),
                    n_frames: o.map_or(0, |o| o.frames.len()),
                    tiles: match (o, m) {
                        (Some(o), Some(m)) => [stack(o, m, k, false), stack(o, m, k, true)],
                        _ => [None, None],
                    },
                }
            })
            .collect();
        FigureInputs {
            orientations,
            measured: m.cloned(),
        }
    }

    /// [`FigureInputs::new`] of a reduction's outcome (its kept frames, if any).
    pub fn from_outcome(outcome: &TargetOutcome) -> FigureInputs {
        FigureInputs::new(outcome.calibrated.as_deref(), outcome.measured.as_ref())
    }
}

/// The catalog values of one component that the figure draws.
#[derive(Debug, Clone, PartialEq)]
pub struct ComponentNumbers {
    /// "A" or "B".
    pub name: String,
    /// q, sigma_q, u, sigma_u (sky frame).
    pub q: f64,
    /// Error of q.
    pub sigma_q: f64,
    /// u.
    pub u: f64,
    /// Error of u.
    pub sigma_u: f64,
    /// P and its error.
    pub p: f64,
    /// Error of P.
    pub sigma_p: f64,
    /// Debiased P.
    pub p_debiased: f64,
    /// gamma and its error, deg.
    pub gamma_deg: f64,
    /// Error of gamma, deg.
    pub sigma_gamma_deg: f64,
    /// Whether the component passes the cut.
    pub passes_cut: bool,
    /// Component flags.
    pub flags: Vec<crate::catalog::Flag>,
    /// The instrumental offset c in the component's solution (0 when none).
    pub offset_c: f64,
    /// The model of F drawn on each orientation's panel: q cos 2phi + u sin 2phi + c, plus
    /// the telescope's term of that orientation where [`ComponentNumbers::telescope_f`]
    /// has one.
    pub model_f: Vec<f64>,
    /// The telescope's term of each orientation's model, `T(phi) = a (C cos 2phi + S sin
    /// 2phi) + b (C sin 2phi - S cos 2phi)`: (a, b) the calibration's, (C, S) the
    /// orientation's `parallactic_2eta`. `None` where it is not in the model: the
    /// calibration has no telescope term, the solve did not remove it from this component
    /// (no `telescope_qu`), or the orientation has no combined F with a parallactic angle.
    pub telescope_f: Vec<Option<f64>>,
}

/// Every catalog number a target figure draws.
#[derive(Debug, Clone, PartialEq)]
pub struct FigureNumbers {
    /// Status of the target.
    pub status: Status,
    /// Per component, A first.
    pub components: Vec<ComponentNumbers>,
    /// Delta-gamma, deg (None when not both components pass the cut).
    pub delta_gamma_deg: Option<f64>,
    /// Its 1-sigma error (delta method), deg.
    pub sigma_delta_gamma_deg: Option<f64>,
    /// Its central 68.27 % interval [low, high], deg.
    pub delta_gamma_interval_deg: Option<[f64; 2]>,
    /// Analyzer angle of each orientation: the calibration's relation when it has one, else
    /// the one the reduction used, deg.
    pub analyzer_deg: Vec<f64>,
}

/// One target's figure: the catalog entry (after the calibration), the pixels prepared
/// during the reduction and the filter's calibration (its angle relation and offset are
/// what the fitted F lines are drawn with).
#[derive(Clone, Copy)]
pub struct TargetFigure<'a> {
    /// The catalog entry, as written.
    pub target: &'a Target,
    /// Cut-outs and per-dither values.
    pub inputs: &'a FigureInputs,
    /// The calibration of the target's filter, if any.
    pub calibration: Option<&'a FilterCalibration>,
}

impl TargetFigure<'_> {
    /// The numbers the figure draws.
    pub fn numbers(&self) -> FigureNumbers {
        let analyzer_deg: Vec<f64> = self
            .inputs
            .orientations
            .iter()
            .map(|o| match self.calibration.and_then(|c| c.angles.as_ref()) {
                Some(a) if o.posang_deg.is_finite() => a.analyzer_deg(o.posang_deg),
                _ => o.analyzer_deg,
            })
            .collect();
        let tel_ab = self.calibration.and_then(|f| f.telescope.as_ref()).map(|t| t.ab());
        let components = self
            .target
            .components
            .iter()
            .map(|c| {
                let offset_c = c.instrumental_offset.as_ref().map_or(0.0, |o| o.c);
                // T is in the model only where the solve removed it from this component.
                let telescope_f: Vec<Option<f64>> = analyzer_deg
                    .iter()
                    .enumerate()
                    .map(|(k, &phi)| {
                        let ab = tel_ab.filter(|_| c.telescope_qu.is_some())?;
                        let eta = combined_f_of(c, &self.inputs.orientations, k)?.parallactic_2eta?;
                        Some(telescope::telescope_f(ab, phi, eta))
                    })
                    .collect();
                let model_f = analyzer_deg
                    .iter()
                    .zip(&telescope_f)
                    .map(|(phi, t)| {
                        let t2 = 2.0 * phi.to_radians();
                        c.q * t2.cos() + c.u * t2.sin() + offset_c + t.unwrap_or(0.0)
                    })
                    .collect();
                ComponentNumbers {
                    name: c.name.clone(),
                    q: c.q,
                    sigma_q: c.sigma_q,
                    u: c.u,
                    sigma_u: c.sigma_u,
                    p: c.p,
                    sigma_p: c.sigma_p,
                    p_debiased: c.p_debiased,
                    gamma_deg: c.gamma_deg,
                    sigma_gamma_deg: c.sigma_gamma_deg,
                    passes_cut: c.passes_cut,
                    flags: c.flags.clone(),
                    offset_c,
                    model_f,
                    telescope_f,
                }
            })
            .collect();
        FigureNumbers {
            status: self.target.status,
            components,
            delta_gamma_deg: self.target.delta_gamma_deg,
            sigma_delta_gamma_deg: self.target.sigma_delta_gamma_deg,
            delta_gamma_interval_deg: self.target.delta_gamma_interval_deg,
            analyzer_deg,
        }
    }

    /// Render to an RGB8 buffer (width, height, pixels); a text-only figure when the full
    /// one cannot be drawn.
    pub fn rgb(&self) -> io::Result<(u32, u32, Vec<u8>)> {
        ensure_font().map_err(to_io)?;
        let numbers = self.numbers();
        let text_only = FigureInputs::default();
        let full = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            render(self.target, self.inputs, &numbers)
        }));
        match full {
            Ok(Ok(v)) => Ok(v),
            Ok(Err(e)) => render(self.target, &text_only, &numbers).map_err(|_| e),
            Err(_) => render(self.target, &text_only, &numbers),
        }
    }

    /// Write the figure to `path` as a PNG (atomically).
    pub fn png(&self, path: &Path) -> io::Result<()> {
        write_atomic(path, &self.png_bytes()?).map_err(to_io)
    }

    /// Write the figure to `path` as a PNG, renamed into place whole but not synced: the
    /// caller syncs the figures together after the last ([`sofipol_calib::atomic::sync_files`]).
    pub fn png_deferred(&self, path: &Path) -> io::Result<()> {
        sofipol_calib::atomic::write_atomic_deferred(path, &self.png_bytes()?).map_err(|e| match e {
            sofipol_calib::Error::Io { source, .. } => source,
            other => io::Error::other(other.to_string()),
        })
    }

    /// The figure as PNG bytes.
    fn png_bytes(&self) -> io::Result<Vec<u8>> {
        let (w, h, rgb) = self.rgb()?;
        crate::plots::png_rgb::encode_rgb8(w, h, &rgb)
    }
}

/// The catalog's combined F of the figure's orientation `k` of `sketches`: matched by the
/// rotator angle when the catalog records it, else by the analyzer angle the reduction used
/// (the profile's, as the sketch's); by position when the sketches do not know their angles
/// and the counts agree. `None` when the orientation has no combined F (no usable dither).
fn combined_f_of<'c>(c: &'c Component, sketches: &[OrientationSketch], k: usize) -> Option<&'c CombinedF> {
    let ors = c.orientations.as_deref()?;
    let o = sketches.get(k)?;
    let near = |a: f64, b: f64| (a - b).abs() < 1e-6;
    if o.analyzer_deg.is_finite() || o.posang_deg.is_finite() {
        ors.iter().find(|f| match f.posang_deg {
            Some(pa) if o.posang_deg.is_finite() => near(pa, o.posang_deg),
            _ => near(f.analyzer_deg, o.analyzer_deg),
        })
    } else if ors.len() == sketches.len() {
        ors.get(k)
    } else {
        None
    }
}
