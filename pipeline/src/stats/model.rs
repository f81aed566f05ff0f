//! The ingredients of the Monte Carlo: how the second disk's spin axis is drawn relative to
//! the first (Pi(alpha)), and how intrinsic polarization degrees are drawn (P_int).
//!
//! Convention for Pi(alpha): a density **per unit solid angle** around the first axis,
//! written relative to isotropy (isotropic = 1). This is the reading under which the
//! reference study's "Pi(alpha) = const" is random orientation and "Pi(alpha) = 0 for
//! alpha > alpha_0" is its model (d). The density of alpha itself (what a histogram of
//! alpha shows) is Pi(alpha) sin(alpha). Tables may be given either way (see
//! [`AlphaTable`]). Spin axes are treated as axes: alpha and 180 - alpha give the same
//! projected geometry, so plots fold alpha into [0, 90].
use std::f64::consts::PI;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::rng::Xoshiro256pp;
use super::{read_text, Error, Result};

/// Number of quantiles kept for tabulated distributions (inverse-CDF lookup, linear inside).
const QUANTILES: usize = 8192;
/// Fine grid used to integrate a tabulated density before inverting it.
const FINE_GRID: usize = 1 << 16;

/// Distribution of the angle alpha between the two spin axes of a binary.
#[derive(Debug, Clone, PartialEq)]
pub enum AlignmentModel {
    /// Independent, isotropic spin axes (Pi(alpha) = const per solid angle).
    Random,
    /// Perfectly aligned: alpha = 0.
    Aligned,
    /// Von Mises-Fisher spread around the first axis with concentration
    /// kappa = 1 / sigma^2 (sigma in radians): for small sigma, alpha is Rayleigh-distributed
    /// with mode sigma, i.e. each of the two tilt components has standard deviation sigma.
    Spread {
        /// Angular spread sigma, degrees.
        sigma_deg: f64,
    },
    /// Uniform per solid angle inside the cone alpha <= alpha_0, zero outside (the reference
    /// study's model (d): strong but imperfect alignment). alpha_0 = 90 is random orientation.
    Cone {
        /// Cone half-angle alpha_0, degrees (0 < alpha_0 <= 180).
        alpha0_deg: f64,
    },
    /// A tabulated density.
    Table(AlphaTable),
}

/// Whether a tabulated Pi(alpha) is a density per unit solid angle or per unit alpha.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AlphaMeasure {
    /// Per unit solid angle (the reference study's Pi(alpha); isotropic = constant).
    SolidAngle,
    /// Per unit alpha (a histogram of alpha; isotropic = sin alpha).
    Alpha,
}

/// A tabulated Pi(alpha): points (alpha_deg, density), linear between points, zero outside.
///
/// Text file format: one `alpha_deg density` pair per line, `#` starts a comment, and a line
/// `# measure: alpha` or `# measure: solid_angle` (the default) says how to read the density.
/// Alpha runs over [0, 180] (a table that stops at 90 means no anti-parallel pairs, which
/// projects identically because axes are axial).
#[derive(Debug, Clone, PartialEq)]
pub struct AlphaTable {
    /// Where it came from (file name), for provenance.
    pub source: String,
    /// Alpha, degrees, strictly increasing.
    pub alpha_deg: Vec<f64>,
    /// Density (any normalisation) at each alpha.
    pub density: Vec<f64>,
    /// How the density is measured.
    pub measure: AlphaMeasure,
    /// Inverse CDF of alpha (radians) at QUANTILES + 1 equally spaced probabilities.
    quantiles: Vec<f64>,
}

impl AlphaTable {
    /// Build from points; checks monotonicity, finiteness and a positive total.
    pub fn new(source: &str, alpha_deg: Vec<f64>, density: Vec<f64>, measure: AlphaMeasure) -> Result<Self> {
        let bad = |reason: String| Error::Table {
            table: source.to_string(),
            reason,
        };
        if alpha_deg.len() < 2 || alpha_deg.len() != density.len() {
            return Err(bad(format!(
                "needs at least two (alpha, density) points, got {}",
                alpha_deg.len()
            )));
        }
        for w in alpha_deg.windows(2) {
            if !(w[1] > w[0]) {
                return Err(bad(format!(
                    "alpha must increase strictly ({} then {} deg)",
                    w[0], w[1]
                )));
            }
        }
        if alpha_deg[0] < 0.0 || *alpha_deg.last().unwrap() > 180.0 {
            return Err(bad(format!(
                "alpha must lie in [0, 180] deg, got [{}, {}]",
                alpha_deg[0],
                alpha_deg.last().unwrap()
            )));
        }
        if let Some(d) = density.iter().find(|d| !(d.is_finite() && **d >= 0.0)) {
            return Err(bad(format!("densities must be finite and >= 0, got {d}")));
        }
        // Density of alpha (per radian of alpha) on a fine grid, integrated as piecewise
        // constant at cell midpoints, then inverted.
        let (a0, a1) = (alpha_deg[0].to_radians(), alpha_deg.last().unwrap().to_radians());
        let h = (a1 - a0) / FINE_GRID as f64;
        let mut cdf = Vec::with_capacity(FINE_GRID + 1);
        cdf.push(0.0);
        let mut acc = 0.0;
        for i in 0..FINE_GRID {
            let a = a0 + h * (i as f64 + 0.5);
            let mut d = interp(&alpha_deg, &density, a.to_degrees());
            if measure == AlphaMeasure::SolidAngle {
                d *= a.sin();
            }
            acc += d * h;
            cdf.push(acc);
        }
        if !(acc > 0.0) {
            return Err(bad("the density integrates to zero".into()));
        }
        let mut quantiles = Vec::with_capacity(QUANTILES + 1);
        let mut cell = 0;
        for j in 0..=QUANTILES {
            let target = acc * j as f64 / QUANTILES as f64;
            while cell < FINE_GRID - 1 && cdf[cell + 1] < target {
                cell += 1;
            }
            let (c0, c1) = (cdf[cell], cdf[cell + 1]);
            let frac = if c1 > c0 {
                ((target - c0) / (c1 - c0)).clamp(0.0, 1.0)
            } else {
                0.0
            };
            quantiles.push(a0 + h * (cell as f64 + frac));
        }
        Ok(Self {
            source: source.to_string(),
            alpha_deg,
            density,
            measure,
            quantiles,
        })
    }

    /// Read the text format described on the type.
    pub fn from_file(path: &Path) -> Result<Self> {
        Self::parse(&path.display().to_string(), &read_text(path)?)
    }

    /// Parse the text format described on the type.
    pub fn parse(source: &str, text: &str) -> Result<Self> {
        let mut measure = AlphaMeasure::SolidAngle;
        let (mut a, mut d) = (Vec::new(), Vec::new());
        for (lineno, line) in text.lines().enumerate() {
            let line = line.trim();
            if let Some(comment) = line.strip_prefix('#') {
                if let Some(m) = comment.trim().strip_prefix("measure:") {
                    measure = match m.trim() {
                        "alpha" => AlphaMeasure::Alpha,
                        "solid_angle" => AlphaMeasure::SolidAngle,
                        other => {
                            return Err(Error::Table {
                                table: source.to_string(),
                                reason: format!(
                                    "line {}: unknown measure '{other}' (alpha or solid_angle)",
                                    lineno + 1
                                ),
                            })
                        }
                    };
                }
                continue;
            }
            if line.is_empty() {
                continue;
            }
            let nums = parse_numbers(line, source, lineno + 1)?;
            if nums.len() != 2 {
                return Err(Error::Table {
                    table: source.to_string(),
                    reason: format!(
                        "line {}: expected 'alpha_deg density', got {} numbers",
                        lineno + 1,
                        nums.len()
                    ),
                });
            }
            a.push(nums[0]);
            d.push(nums[1]);
        }
        Self::new(source, a, d, measure)
    }

    /// Draw alpha (radians).
    #[inline]
    fn sample(&self, rng: &mut Xoshiro256pp) -> f64 {
        let x = rng.uniform() * QUANTILES as f64;
        let j = (x as usize).min(QUANTILES - 1);
        let f = x - j as f64;
        self.quantiles[j] + f * (self.quantiles[j + 1] - self.quantiles[j])
    }
}

/// Linear interpolation in a table (zero outside).
fn interp(x: &[f64], y: &[f64], at: f64) -> f64 {
    if at < x[0] || at > x[x.len() - 1] {
        return 0.0;
    }
    let i = x.partition_point(|&v| v <= at).clamp(1, x.len() - 1);
    let (x0, x1, y0, y1) = (x[i - 1], x[i], y[i - 1], y[i]);
    y0 + (y1 - y0) * (at - x0) / (x1 - x0)
}

/// Whitespace- or comma-separated numbers of line `lineno` of table `source`.
fn parse_numbers(s: &str, source: &str, lineno: usize) -> Result<Vec<f64>> {
    s.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<f64>().map_err(|_| Error::Table {
                table: source.to_string(),
                reason: format!("line {lineno}: '{t}' is not a number"),
            })
        })
        .collect()
}

fn invalid(name: &str, value: impl std::fmt::Display, reason: &str) -> Error {
    Error::InvalidParameter {
        name: name.to_string(),
        value: value.to_string(),
        reason: reason.to_string(),
    }
}

fn one_number(name: &str, arg: &str) -> Result<f64> {
    arg.trim()
        .parse::<f64>()
        .map_err(|_| invalid(name, arg, "expected a number"))
}

impl AlignmentModel {
    /// Parse `random`, `aligned`, `spread:SIGMA_DEG`, `uniform:ALPHA0_DEG` (alias `cone:`),
    /// `table:FILE`.
    pub fn parse(spec: &str) -> Result<Self> {
        let (kind, arg) = match spec.split_once(':') {
            Some((k, a)) => (k.trim(), Some(a)),
            None => (spec.trim(), None),
        };
        let model = match (kind, arg) {
            ("random" | "isotropic", None) => Self::Random,
            ("aligned", None) => Self::Aligned,
            ("spread" | "vmf", Some(a)) => Self::Spread {
                sigma_deg: one_number("model spread sigma (deg)", a)?,
            },
            ("uniform" | "cone", Some(a)) => Self::Cone {
                alpha0_deg: one_number("model alpha_0 (deg)", a)?,
            },
            ("table", Some(a)) => Self::Table(AlphaTable::from_file(Path::new(a.trim()))?),
            _ => {
                return Err(invalid(
                    "model",
                    spec,
                    "expected random, aligned, spread:SIGMA_DEG, uniform:ALPHA0_DEG or table:FILE",
                ))
            }
        };
        model.validate()?;
        Ok(model)
    }

    /// Check the parameters.
    pub fn validate(&self) -> Result<()> {
        match *self {
            Self::Spread { sigma_deg } if !(sigma_deg > 0.0 && sigma_deg.is_finite()) => {
                Err(invalid("spread sigma (deg)", sigma_deg, "must be > 0"))
            }
            Self::Cone { alpha0_deg } if !(alpha0_deg > 0.0 && alpha0_deg <= 180.0) => {
                Err(invalid("alpha_0 (deg)", alpha0_deg, "must be in (0, 180]"))
            }
            _ => Ok(()),
        }
    }

    /// The spec string this model parses from (tables: `table:SOURCE`).
    pub fn spec(&self) -> String {
        match self {
            Self::Random => "random".into(),
            Self::Aligned => "aligned".into(),
            Self::Spread { sigma_deg } => format!("spread:{sigma_deg}"),
            Self::Cone { alpha0_deg } => format!("uniform:{alpha0_deg}"),
            Self::Table(t) => format!("table:{}", t.source),
        }
    }

    /// Von Mises-Fisher concentration kappa = 1/sigma^2 (sigma in radians).
    fn kappa(sigma_deg: f64) -> f64 {
        let s = sigma_deg.to_radians();
        1.0 / (s * s)
    }

    /// Pi(alpha) per unit solid angle relative to isotropy, folded for axes (alpha in
    /// [0, 90] deg: the mean of the values at alpha and 180 - alpha). `None` for the
    /// perfectly aligned model (a delta at 0). Used for the figures and the sampler tests.
    pub fn pi_alpha_relative(&self, alpha_deg: f64) -> Option<f64> {
        let a = alpha_deg.to_radians();
        let vec_density = |a: f64| -> f64 {
            match self {
                Self::Random => 1.0,
                Self::Aligned => unreachable!(),
                Self::Spread { sigma_deg } => {
                    // kappa e^{kappa cos a} / sinh kappa, written to avoid overflow.
                    let k = Self::kappa(*sigma_deg);
                    2.0 * k * (k * (a.cos() - 1.0)).exp() / (-(-2.0 * k).exp_m1())
                }
                Self::Cone { alpha0_deg } => {
                    let c0 = alpha0_deg.to_radians().cos();
                    if a <= alpha0_deg.to_radians() {
                        2.0 / (1.0 - c0)
                    } else {
                        0.0
                    }
                }
                Self::Table(t) => {
                    let d = interp(&t.alpha_deg, &t.density, a.to_degrees());
                    let d = if t.measure == AlphaMeasure::Alpha {
                        if a.sin() > 1e-12 {
                            d / a.sin()
                        } else {
                            0.0
                        }
                    } else {
                        d
                    };
                    // Normalise: total probability = integral of d sin a da (per solid angle
                    // up to 2 pi), isotropic = 1 means density/(1/(4 pi)).
                    d * 2.0 / t.norm_per_solid_angle()
                }
            }
        };
        match self {
            Self::Aligned => None,
            _ => Some(0.5 * (vec_density(a) + vec_density(PI - a))),
        }
    }

    /// Draw (cos alpha, sin alpha) of the tilt between the axes; `None` for the models that
    /// do not tilt a first axis (random: independent draw; aligned: no tilt).
    #[inline]
    fn draw_tilt(&self, rng: &mut Xoshiro256pp, constant: f64) -> Option<(f64, f64)> {
        match self {
            Self::Random | Self::Aligned => None,
            Self::Spread { .. } => {
                // Exact von Mises-Fisher sampling on S^2 (Wood 1994):
                // w = 1 + ln(1 - v (1 - e^{-2 kappa})) / kappa, v uniform in (0, 1].
                let k = constant;
                let v = 1.0 - rng.uniform();
                let w = (1.0 + (-v * -(-2.0 * k).exp_m1()).ln_1p() / k).clamp(-1.0, 1.0);
                Some((w, ((1.0 - w) * (1.0 + w)).sqrt()))
            }
            Self::Cone { .. } => {
                // Uniform per solid angle in the cap: cos alpha uniform in [cos alpha_0, 1].
                let w = 1.0 - rng.uniform() * (1.0 - constant);
                Some((w, ((1.0 - w) * (1.0 + w)).max(0.0).sqrt()))
            }
            Self::Table(t) => {
                let (s, c) = t.sample(rng).sin_cos();
                Some((c, s))
            }
        }
    }

    /// Draw the second axis for a first axis `n1` (unit vector) and return its sky-projected
    /// components (x, y): the line of sight is z. `constant` is [`Self::sampler_constant`].
    #[inline]
    pub(crate) fn second_axis(&self, rng: &mut Xoshiro256pp, n1: [f64; 3], constant: f64) -> (f64, f64) {
        let (w, s) = match self {
            Self::Random => {
                let v = rng.unit_vector();
                return (v[0], v[1]);
            }
            Self::Aligned => return (n1[0], n1[1]),
            _ => self.draw_tilt(rng, constant).expect("tilting models draw a tilt"),
        };
        // Orthonormal basis perpendicular to n1, branch-free and stable for every n1
        // (Duff et al. 2017, "Building an orthonormal basis, revisited", JCGT 6(1)); only
        // the x, y components are needed for the projection.
        let [x, y, z] = n1;
        let sign = 1f64.copysign(z);
        let a = -1.0 / (sign + z);
        let b = x * y * a;
        let e1 = [1.0 + sign * x * x * a, sign * b];
        let e2 = [b, sign + y * y * a];
        let (cb, sb) = rng.unit_circle();
        (
            w * x + s * (cb * e1[0] + sb * e2[0]),
            w * y + s * (cb * e1[1] + sb * e2[1]),
        )
    }

    /// The per-model constant used by the samplers (kappa, or cos alpha_0).
    pub(crate) fn sampler_constant(&self) -> f64 {
        match *self {
            Self::Spread { sigma_deg } => Self::kappa(sigma_deg),
            Self::Cone { alpha0_deg } => alpha0_deg.to_radians().cos(),
            _ => 0.0,
        }
    }

    /// Draw alpha (degrees, in [0, 180]) with the same sampler the Monte Carlo uses, for
    /// tests and figures.
    pub fn sample_alpha_deg(&self, rng: &mut Xoshiro256pp) -> f64 {
        match self {
            Self::Random => rng.uniform_pm1().acos().to_degrees(),
            Self::Aligned => 0.0,
            _ => {
                let (w, s) = self
                    .draw_tilt(rng, self.sampler_constant())
                    .expect("tilting models draw a tilt");
                s.atan2(w).to_degrees()
            }
        }
    }
}

impl AlphaTable {
    /// Integral over the sphere of the density per solid angle, / (2 pi): int d_sa(a) sin a da.
    fn norm_per_solid_angle(&self) -> f64 {
        let n = 4096;
        let (a0, a1) = (
            self.alpha_deg[0].to_radians(),
            self.alpha_deg.last().unwrap().to_radians(),
        );
        let h = (a1 - a0) / n as f64;
        (0..n)
            .map(|i| {
                let a = a0 + h * (i as f64 + 0.5);
                let d = interp(&self.alpha_deg, &self.density, a.to_degrees());
                let d = if self.measure == AlphaMeasure::Alpha {
                    d
                } else {
                    d * a.sin()
                };
                d * h
            })
            .sum()
    }
}
