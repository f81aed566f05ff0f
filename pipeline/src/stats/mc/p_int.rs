//! Distributions of the intrinsic polarization degree of one disk ([`PIntDist`]).
use std::path::Path;

use super::super::rng::Xoshiro256pp;
use super::super::{read_text, Error, Result};
use super::PofITable;
use crate::catalog::Catalog;

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
                let cat: Catalog = crate::input::read_catalog(path).map_err(|e| Error::Catalog {
                    path: path.into(),
                    reason: e.to_string(),
                })?;
                let sample = super::super::sample::BinarySample::from_catalog(&cat, None);
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
        let text = read_text(path)?;
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
    pub(super) fn draw(&self, rng: &mut Xoshiro256pp, r2: f64) -> f64 {
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
