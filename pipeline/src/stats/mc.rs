//! The projection / interstellar-polarization Monte Carlo of Pi(Delta gamma).
//!
//! One pair: the first spin axis n1 is isotropic; the second is drawn from the alignment
//! model (Pi(alpha) about n1 with a uniform azimuth, or independently for random pairs);
//! both are projected on the sky (line of sight z, sky axes x = north, y = east).
//!
//! * Geometry only (no ISM, no noise): Delta gamma is the angle between the two projected
//!   axes as lines, atan2(|v1 x v2|, |v1 . v2|), in [0, 90] deg: one atan2, no other trig.
//! * With ISM and/or noise: each component gets an intrinsic (q, u) = P_int (cos 2g, sin 2g)
//!   with g = PA(projected spin axis) + 90 deg (polarization along the long axis of the
//!   projected disk, the reference study's convention), computed without trigonometry as
//!   cos 2g = -(x^2 - y^2)/r^2, sin 2g = -2xy/r^2; then (q_ism, u_ism) is added to both,
//!   then independent Gaussian noise of sigma to each q and u; optionally both components
//!   must pass P / sigma > cut; Delta gamma = half the angle between the (q, u) vectors.
//!
//! Only the effects the configuration asks for are simulated.
//!
//! Determinism: the pairs are split into chunks of [`CHUNK_PAIRS`]; chunk i draws from its
//! own generator `Xoshiro256pp::for_stream(seed, i)` and fills its own integer histogram;
//! chunk histograms are summed (integer sums do not depend on order), and samples are
//! concatenated in chunk order. The result is bit-identical for any number of threads.
use std::path::Path;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::hist::Histogram;
use super::model::AlignmentModel;
use super::rng::Xoshiro256pp;
use super::{Error, Result};
use crate::catalog::Catalog;

/// Pairs per chunk (one RNG stream each). Part of the definition of a seeded result:
/// changing it changes every seeded histogram.
pub const CHUNK_PAIRS: u64 = 1 << 16;
/// Default number of pairs (the reference study used 10^7).
pub const DEFAULT_PAIRS: u64 = 10_000_000;
/// Most pairs [`simulate_samples`] keeps in memory (800 MB).
pub const MAX_SAMPLE_PAIRS: u64 = 100_000_000;
/// Default seed.
pub const DEFAULT_SEED: u64 = 20010101;
/// Default number of Delta-gamma bins on [0, 90] deg (1 deg each).
pub const DEFAULT_BINS: usize = 90;
/// The interstellar polarization degrees of the reference study's figure, percent.
pub const PAPER_ISM_LEVELS_PERCENT: [f64; 10] = [0.1, 0.2, 0.4, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0];
/// Default intrinsic-polarization model of `sofipol mc`: P = 6 % sin^2 i.
pub const DEFAULT_P_INT: &str = "sin2i:6";

/// Distribution of the intrinsic polarization degree of one disk, in percent.
#[derive(Debug, Clone, PartialEq)]
pub enum PIntDist {
    /// Every disk has the same P.
    Fixed {
        /// P, percent.
        p_percent: f64,
    },
    /// Uniform in [lo, hi] percent.
    Uniform {
        /// Lower bound, percent.
        lo_percent: f64,
        /// Upper bound, percent.
        hi_percent: f64,
    },
    /// Log-normal with the given median (percent) and sigma of ln P.
    LogNormal {
        /// Median, percent.
        median_percent: f64,
        /// Standard deviation of ln P.
        sigma_ln: f64,
    },
    /// P = P_max sin^2 i with i the inclination of the disk drawn in the Monte Carlo
    /// (optically thin scattering, Brown, McLean & Emslie 1978): zero face-on, P_max
    /// edge-on, tied to the same geometry that sets the angle, like the reference study's
    /// radiative-transfer P(i).
    Sin2i {
        /// P_max, percent.
        p_max_percent: f64,
    },
    /// Resample a list of values (e.g. the P of a catalog's components).
    Empirical {
        /// Where the values came from.
        source: String,
        /// The values, percent.
        values: Vec<f64>,
    },
    /// P as a function of the inclination i of the drawn disk, from a table
    /// (`pofi:FILE`, [`PofITable`]): linear interpolation in i, no randomness.
    Inclination(PofITable),
    /// A tabulated histogram: a bin is drawn by weight, then P uniformly inside it.
    Histogram {
        /// Where it came from.
        source: String,
        /// Bin (lo, hi) edges, percent.
        bins: Vec<(f64, f64)>,
        /// Cumulative normalised weights (last = 1).
        cumulative: Vec<f64>,
    },
}

impl PIntDist {
    /// Parse `fixed:P`, `uniform:LO,HI`, `lognormal:MEDIAN,SIGMA_LN`, `sin2i:PMAX` (all in
    /// percent), `table:FILE` (lines `lo_percent hi_percent weight`) or `catalog:FILE` (the
    /// debiased P of the components of a catalog's Delta-gamma sample).
    pub fn parse(spec: &str) -> Result<Self> {
        let bad = |reason: &str| Error::InvalidParameter {
            name: "p-int".into(),
            value: spec.into(),
            reason: reason.into(),
        };
        let (kind, arg) = spec.split_once(':').ok_or_else(|| {
            bad("expected fixed:P, uniform:LO,HI, lognormal:MEDIAN,SIGMA_LN, sin2i:PMAX, pofi:FILE, table:FILE or catalog:FILE")
        })?;
        let nums = || -> Result<Vec<f64>> {
            arg.split(',')
                .map(|t| t.trim().parse::<f64>().map_err(|_| bad("expected numbers (percent)")))
                .collect()
        };
        let d = match kind.trim() {
            "fixed" => match nums()?[..] {
                [p] => Self::Fixed { p_percent: p },
                _ => return Err(bad("fixed takes one value")),
            },
            "uniform" => match nums()?[..] {
                [lo, hi] => Self::Uniform {
                    lo_percent: lo,
                    hi_percent: hi,
                },
                _ => return Err(bad("uniform takes LO,HI")),
            },
            "lognormal" => match nums()?[..] {
                [m, s] => Self::LogNormal {
                    median_percent: m,
                    sigma_ln: s,
                },
                _ => return Err(bad("lognormal takes MEDIAN,SIGMA_LN")),
            },
            "sin2i" => match nums()?[..] {
                [p] => Self::Sin2i { p_max_percent: p },
                _ => return Err(bad("sin2i takes PMAX")),
            },
            "table" => Self::histogram_from_file(Path::new(arg.trim()))?,
            "pofi" => Self::Inclination(PofITable::from_file(Path::new(arg.trim()))?),
            "catalog" => {
                let path = Path::new(arg.trim());
                let text = std::fs::read_to_string(path).map_err(|e| Error::Io {
                    path: path.into(),
                    source: e,
                })?;
                let cat: Catalog = serde_json::from_str(&text).map_err(|e| Error::Catalog {
                    path: path.into(),
                    reason: e.to_string(),
                })?;
                let sample = super::sample::BinarySample::from_catalog(&cat, None);
                Self::Empirical {
                    source: path.display().to_string(),
                    values: sample.p_percent(),
                }
            }
            _ => return Err(bad("unknown distribution")),
        };
        d.validate()?;
        Ok(d)
    }

    /// Check the parameters.
    pub fn validate(&self) -> Result<()> {
        let bad = |value: String, reason: &str| {
            Err(Error::InvalidParameter {
                name: "p-int".into(),
                value,
                reason: reason.into(),
            })
        };
        let ok = |v: f64| v.is_finite() && v >= 0.0;
        match self {
            Self::Fixed { p_percent } if !ok(*p_percent) => bad(p_percent.to_string(), "P must be >= 0"),
            Self::Uniform { lo_percent, hi_percent }
                if !(ok(*lo_percent) && ok(*hi_percent) && lo_percent <= hi_percent) =>
            {
                bad(format!("{lo_percent},{hi_percent}"), "need 0 <= LO <= HI")
            }
            Self::LogNormal {
                median_percent,
                sigma_ln,
            } if !(*median_percent > 0.0 && median_percent.is_finite() && ok(*sigma_ln)) => bad(
                format!("{median_percent},{sigma_ln}"),
                "need MEDIAN > 0 and SIGMA_LN >= 0",
            ),
            Self::Sin2i { p_max_percent } if !ok(*p_max_percent) => bad(p_max_percent.to_string(), "PMAX must be >= 0"),
            Self::Empirical { source, values } if values.is_empty() || !values.iter().all(|v| ok(*v)) => {
                bad(source.clone(), "needs at least one value, all finite and >= 0")
            }
            _ => Ok(()),
        }
    }

    /// Resample the given values (percent).
    pub fn empirical(source: &str, values: Vec<f64>) -> Result<Self> {
        let d = Self::Empirical {
            source: source.into(),
            values,
        };
        d.validate()?;
        Ok(d)
    }

    /// Read a histogram table: lines `lo_percent hi_percent weight`, `#` comments.
    pub fn histogram_from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::Io {
            path: path.into(),
            source: e,
        })?;
        let source = path.display().to_string();
        let bad = |reason: String| Error::Table {
            table: source.clone(),
            reason,
        };
        let mut bins = Vec::new();
        let mut weights = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let nums: Vec<f64> = line
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|t| !t.is_empty())
                .map(|t| t.parse::<f64>())
                .collect::<std::result::Result<_, _>>()
                .map_err(|_| bad(format!("line {}: not numbers", i + 1)))?;
            match nums[..] {
                [lo, hi, w] if lo >= 0.0 && hi >= lo && w >= 0.0 && w.is_finite() && hi.is_finite() => {
                    bins.push((lo, hi));
                    weights.push(w);
                }
                _ => {
                    return Err(bad(format!(
                        "line {}: expected 'lo hi weight' with 0 <= lo <= hi, weight >= 0",
                        i + 1
                    )))
                }
            }
        }
        let total: f64 = weights.iter().sum();
        if !(total > 0.0) {
            return Err(bad("the weights sum to zero".into()));
        }
        let mut acc = 0.0;
        let cumulative = weights
            .iter()
            .map(|w| {
                acc += w / total;
                acc
            })
            .collect();
        Ok(Self::Histogram {
            source,
            bins,
            cumulative,
        })
    }

    /// The spec string (files: their name).
    pub fn spec(&self) -> String {
        match self {
            Self::Fixed { p_percent } => format!("fixed:{p_percent}"),
            Self::Uniform { lo_percent, hi_percent } => format!("uniform:{lo_percent},{hi_percent}"),
            Self::LogNormal {
                median_percent,
                sigma_ln,
            } => format!("lognormal:{median_percent},{sigma_ln}"),
            Self::Sin2i { p_max_percent } => format!("sin2i:{p_max_percent}"),
            Self::Empirical { source, values } => format!("empirical:{source} ({} values)", values.len()),
            Self::Histogram { source, .. } => format!("table:{source}"),
            Self::Inclination(t) => format!("pofi:{}", t.source),
        }
    }

    /// Draw P (percent) for a disk whose projected axis has squared length r2 = sin^2 i.
    #[inline]
    fn draw(&self, rng: &mut Xoshiro256pp, r2: f64) -> f64 {
        match self {
            Self::Fixed { p_percent } => *p_percent,
            Self::Uniform { lo_percent, hi_percent } => lo_percent + (hi_percent - lo_percent) * rng.uniform(),
            Self::LogNormal {
                median_percent,
                sigma_ln,
            } => median_percent * (sigma_ln * rng.normal_pair().0).exp(),
            Self::Sin2i { p_max_percent } => p_max_percent * r2,
            Self::Inclination(t) => t.p_percent_at(r2.min(1.0).sqrt().asin().to_degrees()),
            Self::Empirical { values, .. } => values[rng.below(values.len() as u64) as usize],
            Self::Histogram { bins, cumulative, .. } => {
                let u = rng.uniform();
                let i = cumulative.partition_point(|&c| c <= u).min(bins.len() - 1);
                let (lo, hi) = bins[i];
                lo + (hi - lo) * rng.uniform()
            }
        }
    }
}

/// Intrinsic P against inclination, P(i), read from a two-column CSV file (the reference
/// study's radiative-transfer P_l(i) is of this form).
///
/// Format: one `inclination_deg,p` line per point (commas or whitespace), `#` comments,
/// an optional header line `inclination_deg,p`. Inclinations in degrees (0 = face-on,
/// 90 = edge-on), strictly increasing, within [0, 90]; p is a **fraction** in [0, 1) like the
/// catalog's P (0.06 = 6 %), converted to percent on reading. Between points P is linear
/// in i; below the first or above the last point it is the end value.
#[derive(Debug, Clone, PartialEq)]
pub struct PofITable {
    /// File name, for provenance and messages.
    pub source: String,
    /// Inclinations, degrees, strictly increasing in [0, 90].
    pub inclination_deg: Vec<f64>,
    /// P at each inclination, percent.
    pub p_percent: Vec<f64>,
}

impl PofITable {
    /// Build from points (P in **percent**), validated.
    pub fn new(source: &str, inclination_deg: Vec<f64>, p_percent: Vec<f64>) -> Result<Self> {
        let bad = |reason: String| Error::Table {
            table: source.to_string(),
            reason,
        };
        if inclination_deg.is_empty() || inclination_deg.len() != p_percent.len() {
            return Err(bad(format!(
                "needs at least one (inclination_deg, p) point, got {}",
                inclination_deg.len()
            )));
        }
        for (k, (&i, &p)) in inclination_deg.iter().zip(&p_percent).enumerate() {
            if !(0.0..=90.0).contains(&i) {
                return Err(bad(format!("point {}: inclination {i} deg outside [0, 90]", k + 1)));
            }
            if !(0.0..100.0).contains(&p) {
                return Err(bad(format!("point {}: p = {} outside [0, 1)", k + 1, p / 100.0)));
            }
        }
        for (k, w) in inclination_deg.windows(2).enumerate() {
            if !(w[1] > w[0]) {
                return Err(bad(format!(
                    "point {}: inclinations must increase strictly ({} then {} deg)",
                    k + 2,
                    w[0],
                    w[1]
                )));
            }
        }
        Ok(Self {
            source: source.to_string(),
            inclination_deg,
            p_percent,
        })
    }

    /// Read the CSV format described on the type; errors name the file, the line and the value.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::Io {
            path: path.to_path_buf(),
            source: e,
        })?;
        Self::parse(&path.display().to_string(), &text)
    }

    /// Parse the CSV format described on the type.
    pub fn parse(source: &str, text: &str) -> Result<Self> {
        let bad = |lineno: usize, reason: String| Error::Table {
            table: source.to_string(),
            reason: format!("line {lineno}: {reason}"),
        };
        let (mut inc, mut p) = (Vec::new(), Vec::new());
        let mut header_allowed = true;
        let mut last_line = 0;
        for (k, raw) in text.lines().enumerate() {
            let lineno = k + 1;
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let fields: Vec<&str> = line
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|t| !t.is_empty())
                .collect();
            if header_allowed && fields == ["inclination_deg", "p"] {
                header_allowed = false;
                continue;
            }
            header_allowed = false;
            if fields.len() != 2 {
                return Err(bad(
                    lineno,
                    format!("expected 'inclination_deg,p', got '{line}' ({} fields)", fields.len()),
                ));
            }
            let num = |t: &str| {
                t.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| bad(lineno, format!("'{t}' is not a finite number")))
            };
            let (i, pv) = (num(fields[0])?, num(fields[1])?);
            if !(0.0..=90.0).contains(&i) {
                return Err(bad(lineno, format!("inclination {i} deg outside [0, 90]")));
            }
            if !(0.0..1.0).contains(&pv) {
                return Err(bad(lineno, format!("p = {pv} outside [0, 1) (a fraction: 0.06 = 6 %)")));
            }
            if let Some(&prev) = inc.last() {
                if !(i > prev) {
                    return Err(bad(
                        lineno,
                        format!("inclination {i} deg does not exceed the previous {prev} deg (line {last_line})"),
                    ));
                }
            }
            inc.push(i);
            p.push(pv * 100.0);
            last_line = lineno;
        }
        if inc.is_empty() {
            return Err(Error::Table {
                table: source.to_string(),
                reason: "no (inclination_deg, p) points".into(),
            });
        }
        Self::new(source, inc, p)
    }

    /// P (percent) at inclination `i_deg`: linear between points, exact at the points, the
    /// end value outside the table.
    #[inline]
    pub fn p_percent_at(&self, i_deg: f64) -> f64 {
        let (x, y) = (&self.inclination_deg, &self.p_percent);
        let n = x.len();
        if i_deg <= x[0] {
            return y[0];
        }
        if i_deg >= x[n - 1] {
            return y[n - 1];
        }
        // x[j-1] <= i < x[j]
        let j = x.partition_point(|&v| v <= i_deg);
        let (x0, x1, y0, y1) = (x[j - 1], x[j], y[j - 1], y[j]);
        y0 + (y1 - y0) * ((i_deg - x0) / (x1 - x0))
    }
}

/// Interstellar polarization common to both components.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Ism {
    /// Degree P_ism, percent.
    pub p_percent: f64,
    /// Angle gamma_ism, degrees east of north.
    pub angle_deg: f64,
}

/// A validated Monte-Carlo configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct McConfig {
    /// Pi(alpha).
    pub model: AlignmentModel,
    /// Number of simulated pairs.
    pub pairs: u64,
    /// Seed.
    pub seed: u64,
    /// Number of Delta-gamma bins on [0, 90] deg.
    pub bins: usize,
    /// Intrinsic polarization degrees (used only with ISM or noise).
    pub p_int: PIntDist,
    /// Interstellar polarization, if any.
    pub ism: Option<Ism>,
    /// Gaussian measurement noise sigma of q and u of each component, percent, if any.
    pub noise_percent: Option<f64>,
    /// Keep a pair only when both measured P / sigma exceed this (needs noise).
    pub snr_cut: Option<f64>,
    /// Fraction of disks polarized **perpendicular** to the long axis of their projection
    /// (polarization angle rotated by 90 deg: edge-on, multiple-scattering disks), drawn
    /// independently for component A (`[0]`) and B (`[1]`); the CLI sets both to
    /// `--perpendicular-fraction`. 0 and 1 draw no random number.
    pub perpendicular_fraction: [f64; 2],
}

impl McConfig {
    /// Geometry-only configuration with the defaults.
    pub fn geometry(model: AlignmentModel, pairs: u64, seed: u64) -> Self {
        Self {
            model,
            pairs,
            seed,
            bins: DEFAULT_BINS,
            p_int: PIntDist::Sin2i { p_max_percent: 6.0 },
            ism: None,
            noise_percent: None,
            snr_cut: None,
            perpendicular_fraction: [0.0; 2],
        }
    }

    /// Check every parameter (the Monte Carlo refuses an invalid configuration).
    pub fn validate(&self) -> Result<()> {
        let bad = |name: &str, value: String, reason: &str| {
            Err(Error::InvalidParameter {
                name: name.into(),
                value,
                reason: reason.into(),
            })
        };
        self.model.validate()?;
        self.p_int.validate()?;
        if self.pairs == 0 {
            return bad("pairs", "0".into(), "must be >= 1");
        }
        if self.bins == 0 || self.bins > 1_000_000 {
            return bad("bins", self.bins.to_string(), "must be in 1..=1000000");
        }
        if let Some(ism) = self.ism {
            if !(ism.p_percent >= 0.0 && ism.p_percent.is_finite()) {
                return bad("p-ism (%)", ism.p_percent.to_string(), "must be >= 0");
            }
            if !ism.angle_deg.is_finite() {
                return bad("ism-angle (deg)", ism.angle_deg.to_string(), "must be finite");
            }
        }
        for f in self.perpendicular_fraction {
            if !(0.0..=1.0).contains(&f) {
                return bad("perpendicular-fraction", f.to_string(), "must be in [0, 1]");
            }
        }
        if let Some(s) = self.noise_percent {
            if !(s >= 0.0 && s.is_finite()) {
                return bad("noise (%)", s.to_string(), "must be >= 0");
            }
        }
        if let Some(k) = self.snr_cut {
            if !(k >= 0.0 && k.is_finite()) {
                return bad("snr-cut", k.to_string(), "must be >= 0");
            }
            if !matches!(self.noise_percent, Some(s) if s > 0.0) {
                return bad("snr-cut", k.to_string(), "a P/sigma cut needs --noise > 0");
            }
        }
        Ok(())
    }

    /// True when the polarization (not only the geometry) has to be simulated.
    pub fn simulates_polarization(&self) -> bool {
        self.ism.is_some() || self.noise_percent.is_some()
    }
}

/// Result of a Monte-Carlo run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct McOutput {
    /// Pi(Delta gamma) counts on [0, 90] deg.
    pub histogram: Histogram,
    /// Pairs simulated.
    pub simulated: u64,
    /// Pairs that passed the P/sigma cut (all of them without a cut).
    pub accepted: u64,
    /// Mean Delta gamma of the accepted pairs (deg), from the pairs themselves (not bin
    /// centres); per-chunk sums added in chunk order, so independent of the thread count.
    pub mean_delta_gamma_deg: f64,
}

/// Precomputed per-run constants of the kernel.
struct Kernel<'a> {
    cfg: &'a McConfig,
    model_constant: f64,
    ism_qu: (f64, f64),
    noise: f64,
    cut2: Option<f64>,
}

const RAD_TO_DEG: f64 = 180.0 / std::f64::consts::PI;

impl<'a> Kernel<'a> {
    fn new(cfg: &'a McConfig) -> Self {
        let ism_qu = cfg.ism.map_or((0.0, 0.0), |ism| {
            let (s, c) = (2.0 * ism.angle_deg.to_radians()).sin_cos();
            (ism.p_percent * c, ism.p_percent * s)
        });
        let noise = cfg.noise_percent.unwrap_or(0.0);
        let cut2 = cfg.snr_cut.map(|k| (k * noise) * (k * noise));
        Self {
            cfg,
            model_constant: cfg.model.sampler_constant(),
            ism_qu,
            noise,
            cut2,
        }
    }

    /// Intrinsic (q, u) of a disk with projected axis (x, y), percent.
    #[inline]
    fn intrinsic(&self, rng: &mut Xoshiro256pp, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        if let PIntDist::Sin2i { p_max_percent } = self.cfg.p_int {
            // P_max sin^2 i (cos 2g, sin 2g) = -P_max (x^2 - y^2, 2xy): no division.
            return (-p_max_percent * (x * x - y * y), -p_max_percent * 2.0 * x * y);
        }
        intrinsic_qu(self.cfg.p_int.draw(rng, r2), x, y)
    }

    /// Simulate `n` pairs of chunk `chunk`, calling `sink` with each accepted Delta gamma
    /// (degrees); returns the number accepted.
    #[inline]
    fn run_chunk(&self, chunk: u64, n: u64, sink: &mut impl FnMut(f64)) -> u64 {
        let mut rng = Xoshiro256pp::for_stream(self.cfg.seed, chunk);
        let model = &self.cfg.model;
        let pol = self.cfg.simulates_polarization();
        let mut accepted = 0;
        for _ in 0..n {
            let n1 = rng.unit_vector();
            let (x1, y1) = (n1[0], n1[1]);
            let (x2, y2) = model.second_axis(&mut rng, n1, self.model_constant);
            let flip1 = perpendicular(&mut rng, self.cfg.perpendicular_fraction[0]);
            let flip2 = perpendicular(&mut rng, self.cfg.perpendicular_fraction[1]);
            if !pol {
                let dg = delta_gamma_axes(x1, y1, x2, y2);
                // One polarization rotated by 90 deg: the folded difference becomes 90 - dg.
                sink(if flip1 != flip2 { 90.0 - dg } else { dg });
                accepted += 1;
                continue;
            }
            let (mut q1, mut u1) = self.intrinsic(&mut rng, x1, y1);
            let (mut q2, mut u2) = self.intrinsic(&mut rng, x2, y2);
            // A 90-deg rotation of the polarization angle is (q, u) -> (-q, -u).
            if flip1 {
                (q1, u1) = (-q1, -u1);
            }
            if flip2 {
                (q2, u2) = (-q2, -u2);
            }
            q1 += self.ism_qu.0;
            u1 += self.ism_qu.1;
            q2 += self.ism_qu.0;
            u2 += self.ism_qu.1;
            if self.noise > 0.0 {
                let (a, b) = rng.normal_pair();
                let (c, d) = rng.normal_pair();
                q1 += self.noise * a;
                u1 += self.noise * b;
                q2 += self.noise * c;
                u2 += self.noise * d;
            }
            if let Some(cut2) = self.cut2 {
                if !(q1 * q1 + u1 * u1 > cut2 && q2 * q2 + u2 * u2 > cut2) {
                    continue;
                }
            }
            sink(delta_gamma_qu(q1, u1, q2, u2));
            accepted += 1;
        }
        accepted
    }
}

/// Whether a disk is polarized perpendicular to its projected long axis (probability `f`);
/// draws a uniform only for 0 < f < 1, so f = 0 leaves every seeded result unchanged.
#[inline]
fn perpendicular(rng: &mut Xoshiro256pp, f: f64) -> bool {
    if f <= 0.0 {
        false
    } else if f >= 1.0 {
        true
    } else {
        rng.uniform() < f
    }
}

/// Folded angle between two projected axes (x, y) taken as lines, degrees in [0, 90].
#[inline]
pub(crate) fn delta_gamma_axes(x1: f64, y1: f64, x2: f64, y2: f64) -> f64 {
    let cross = x1 * y2 - y1 * x2;
    let dot = x1 * x2 + y1 * y2;
    cross.abs().atan2(dot.abs()) * RAD_TO_DEG
}

/// Folded difference of the polarization angles of two (q, u), degrees in [0, 90]:
/// 2 Delta gamma is the angle between the (q, u) vectors.
#[inline]
pub(crate) fn delta_gamma_qu(q1: f64, u1: f64, q2: f64, u2: f64) -> f64 {
    let cross = q1 * u2 - u1 * q2;
    let dot = q1 * q2 + u1 * u2;
    0.5 * cross.abs().atan2(dot) * RAD_TO_DEG
}

/// (q, u) of degree `p` polarized along the long axis of a disk whose projected spin axis
/// is (x, y): gamma = PA(axis) + 90 deg, so (cos 2g, sin 2g) = -(x^2 - y^2, 2xy) / r^2.
#[inline]
pub(crate) fn intrinsic_qu(p: f64, x: f64, y: f64) -> (f64, f64) {
    let r2 = x * x + y * y;
    if r2 > 0.0 {
        let f = -p / r2;
        (f * (x * x - y * y), f * 2.0 * x * y)
    } else {
        (p, 0.0) // exactly face-on: the angle is undefined; any choice has measure zero
    }
}

fn chunks(pairs: u64) -> Vec<(u64, u64)> {
    let n = pairs.div_ceil(CHUNK_PAIRS);
    (0..n).map(|i| (i, CHUNK_PAIRS.min(pairs - i * CHUNK_PAIRS))).collect()
}

/// Run the Monte Carlo and return the Pi(Delta gamma) histogram. Uses the current rayon
/// pool; the result does not depend on its size.
pub fn simulate(cfg: &McConfig) -> Result<McOutput> {
    cfg.validate()?;
    let kernel = Kernel::new(cfg);
    let bins = cfg.bins;
    let inv_width = bins as f64 / 90.0;
    let parts: Vec<(Vec<u64>, u64, f64)> = chunks(cfg.pairs)
        .into_par_iter()
        .map(|(chunk, n)| {
            let mut counts = vec![0u64; bins];
            let mut sum = 0.0;
            let accepted = kernel.run_chunk(chunk, n, &mut |dg| {
                counts[((dg * inv_width) as usize).min(bins - 1)] += 1;
                sum += dg;
            });
            (counts, accepted, sum)
        })
        .collect();
    let (mut counts, mut accepted, mut sum) = (vec![0u64; bins], 0u64, 0.0f64);
    for (c, a, s) in parts {
        for (x, y) in counts.iter_mut().zip(&c) {
            *x += *y;
        }
        accepted += a;
        sum += s;
    }
    Ok(McOutput {
        histogram: Histogram {
            lo: 0.0,
            hi: 90.0,
            counts,
        },
        simulated: cfg.pairs,
        accepted,
        mean_delta_gamma_deg: if accepted > 0 { sum / accepted as f64 } else { f64::NAN },
    })
}

/// Run the Monte Carlo and also return every accepted Delta gamma (degrees) in a fixed
/// order (chunk by chunk), for two-sample tests. Memory: 8 bytes per pair, so at most
/// [`MAX_SAMPLE_PAIRS`] pairs (refused above, before allocating; the histogram of
/// [`simulate`] has no such limit).
pub fn simulate_samples(cfg: &McConfig) -> Result<(Vec<f64>, McOutput)> {
    cfg.validate()?;
    if cfg.pairs > MAX_SAMPLE_PAIRS {
        return Err(Error::InvalidParameter {
            name: "pairs".into(),
            value: cfg.pairs.to_string(),
            reason: format!(
                "a two-sample test keeps every simulated Delta gamma (8 bytes each): at most {MAX_SAMPLE_PAIRS} pairs"
            ),
        });
    }
    let kernel = Kernel::new(cfg);
    let parts: Vec<Vec<f64>> = chunks(cfg.pairs)
        .into_par_iter()
        .map(|(chunk, n)| {
            let mut v = Vec::with_capacity(n as usize);
            kernel.run_chunk(chunk, n, &mut |dg| v.push(dg));
            v
        })
        .collect();
    let samples: Vec<f64> = parts.concat();
    let (histogram, _) = Histogram::from_values(0.0, 90.0, cfg.bins, &samples);
    let accepted = samples.len() as u64;
    let mean_delta_gamma_deg = parts_mean(&samples);
    Ok((
        samples,
        McOutput {
            histogram,
            simulated: cfg.pairs,
            accepted,
            mean_delta_gamma_deg,
        },
    ))
}

fn parts_mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

#[cfg(test)]
mod hard_case_tests {
    use super::*;

    #[test]
    fn a_billion_pairs_are_counted_exactly_and_samples_refused_before_allocating() {
        // 10^9 pairs: the chunking covers every pair once (u64 throughout), without
        // running 10^9 draws; `simulate_samples` (8 GB) refuses before allocating.
        let pairs = 1_000_000_000u64;
        let c = chunks(pairs);
        assert_eq!(c.len() as u64, pairs.div_ceil(CHUNK_PAIRS));
        assert_eq!(c.iter().map(|&(_, n)| n).sum::<u64>(), pairs);
        assert!(c
            .iter()
            .enumerate()
            .all(|(i, &(k, n))| k == i as u64 && n >= 1 && n <= CHUNK_PAIRS));
        assert_eq!(c.last().unwrap().1, pairs - (c.len() as u64 - 1) * CHUNK_PAIRS);
        let cfg = McConfig::geometry(AlignmentModel::Random, pairs, 1);
        let e = simulate_samples(&cfg).unwrap_err().to_string();
        assert!(e.contains("pairs") && e.contains("1000000000"), "{e}");
    }
}
