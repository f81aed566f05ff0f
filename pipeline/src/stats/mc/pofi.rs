//! P as a function of the disk's inclination, read from a table ([`PofITable`]).
use std::path::Path;

use super::super::{read_text, Error, Result};

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
        Self::parse(&path.display().to_string(), &read_text(path)?)
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
