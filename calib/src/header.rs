//! An ordered FITS header held in memory.
//!
//! Keys are stored as cfitsio reports them, upper case, **without** the `HIERARCH `
//! prefix (`ESO ADA POSANG`). Look-ups ignore case and accept the name with or without
//! that prefix, like cfitsio itself.
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// The largest |value| a header angle may have, deg ([`Header::get_angle_deg`]): two turns.
pub const MAX_HEADER_ANGLE_DEG: f64 = 720.0;

/// A header value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum HeaderValue {
    /// Logical `T`/`F`.
    Bool(bool),
    /// Integer.
    Int(i64),
    /// Floating point.
    Float(f64),
    /// Character string (quotes removed, trailing blanks trimmed).
    Str(String),
}

impl std::fmt::Display for HeaderValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HeaderValue::Bool(b) => write!(f, "{}", if *b { "T" } else { "F" }),
            HeaderValue::Int(i) => write!(f, "{i}"),
            HeaderValue::Float(x) => write!(f, "{x}"),
            HeaderValue::Str(s) => write!(f, "'{s}'"),
        }
    }
}

/// One keyword card.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Card {
    /// Keyword, upper case, without `HIERARCH `.
    pub key: String,
    /// Value.
    pub value: HeaderValue,
    /// Comment, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub comment: Option<String>,
}

/// An ordered list of keyword cards plus the file it came from (for error messages).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Cards in file order. Structural keywords (SIMPLE, BITPIX, NAXISn, BZERO, BSCALE,
    /// EXTEND, compression keywords) are not kept: they describe the file, not the data.
    pub cards: Vec<Card>,
    /// File the header was read from (empty for headers built in memory).
    #[serde(default)]
    pub path: PathBuf,
    /// HDU of the file the image and these cards come from (0: the primary; 1 and more: an
    /// image extension, e.g. of a tile-compressed file).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub image_hdu: usize,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Normalise a keyword for comparison: trim, upper case, drop a leading `HIERARCH `.
pub fn normalize_key(key: &str) -> String {
    let k = key.trim().to_ascii_uppercase();
    match k.strip_prefix("HIERARCH ") {
        Some(rest) => rest.trim().to_string(),
        None => k,
    }
}

impl Header {
    /// Empty header attached to `path`.
    pub fn new(path: impl AsRef<Path>) -> Self {
        Header {
            cards: Vec::new(),
            path: path.as_ref().to_path_buf(),
            image_hdu: 0,
        }
    }

    /// Set (replace or append) a keyword.
    pub fn set(&mut self, key: &str, value: impl Into<HeaderValue>) {
        let k = normalize_key(key);
        let value = value.into();
        if let Some(c) = self.cards.iter_mut().find(|c| c.key == k) {
            c.value = value;
        } else {
            self.cards.push(Card {
                key: k,
                value,
                comment: None,
            });
        }
    }

    /// Set a keyword with a comment.
    pub fn set_with_comment(&mut self, key: &str, value: impl Into<HeaderValue>, comment: &str) {
        self.set(key, value);
        let k = normalize_key(key);
        if let Some(c) = self.cards.iter_mut().find(|c| c.key == k) {
            c.comment = Some(comment.to_string());
        }
    }

    /// Raw value of a keyword, if present.
    pub fn get(&self, key: &str) -> Option<&HeaderValue> {
        let k = normalize_key(key);
        self.cards.iter().find(|c| c.key == k).map(|c| &c.value)
    }

    /// Whether the keyword is present.
    pub fn contains(&self, key: &str) -> bool {
        self.get(key).is_some()
    }

    fn missing(&self, key: &str) -> Error {
        Error::MissingKeyword {
            path: self.path.clone(),
            keyword: normalize_key(key),
        }
    }

    fn bad(&self, key: &str, value: &HeaderValue, reason: &str) -> Error {
        Error::BadKeyword {
            path: self.path.clone(),
            keyword: normalize_key(key),
            value: value.to_string(),
            reason: reason.to_string(),
        }
    }

    /// A string keyword (numbers are rendered as text).
    pub fn get_str(&self, key: &str) -> Result<String> {
        match self.get(key) {
            None => Err(self.missing(key)),
            Some(HeaderValue::Str(s)) => Ok(s.clone()),
            Some(v) => Ok(v.to_string()),
        }
    }

    /// A floating-point keyword; integers are accepted, as are numeric strings.
    pub fn get_f64(&self, key: &str) -> Result<f64> {
        let v = self.get(key).ok_or_else(|| self.missing(key))?;
        let x = match v {
            HeaderValue::Float(x) => *x,
            HeaderValue::Int(i) => *i as f64,
            HeaderValue::Str(s) => s
                .trim()
                .parse::<f64>()
                .map_err(|_| self.bad(key, v, "expected a number"))?,
            HeaderValue::Bool(_) => return Err(self.bad(key, v, "expected a number")),
        };
        if !x.is_finite() {
            return Err(self.bad(key, v, "not a finite number"));
        }
        Ok(x)
    }

    /// An angle keyword, deg: a finite number within +-[`MAX_HEADER_ANGLE_DEG`] (a plate
    /// angle, a parallactic angle, a rotator position). A value beyond two turns is not an
    /// angle any instrument writes (a corrupt card, a wrong keyword) and is refused, named.
    pub fn get_angle_deg(&self, key: &str) -> Result<f64> {
        let x = self.get_f64(key)?;
        if x.abs() > MAX_HEADER_ANGLE_DEG {
            // 1e300 written as such, not as its 301 digits.
            let shown = match self.get(key) {
                Some(HeaderValue::Float(v)) if v.abs() >= 1e6 => format!("{v:e}"),
                Some(v) => v.to_string(),
                None => x.to_string(),
            };
            return Err(Error::BadKeyword {
                path: self.path.clone(),
                keyword: normalize_key(key),
                value: shown,
                reason: format!("not an angle in degrees (beyond +-{MAX_HEADER_ANGLE_DEG})"),
            });
        }
        Ok(x)
    }

    /// An integer keyword; floats with an integral value are accepted.
    pub fn get_i64(&self, key: &str) -> Result<i64> {
        let v = self.get(key).ok_or_else(|| self.missing(key))?;
        match v {
            HeaderValue::Int(i) => Ok(*i),
            HeaderValue::Float(x) if x.fract() == 0.0 && x.abs() < 9e15 => Ok(*x as i64),
            HeaderValue::Str(s) => s
                .trim()
                .parse::<i64>()
                .map_err(|_| self.bad(key, v, "expected an integer")),
            _ => Err(self.bad(key, v, "expected an integer")),
        }
    }

    /// Optional float: `Ok(None)` when absent, an error when present but malformed.
    pub fn opt_f64(&self, key: &str) -> Result<Option<f64>> {
        if self.contains(key) {
            self.get_f64(key).map(Some)
        } else {
            Ok(None)
        }
    }

    /// Optional string.
    pub fn opt_str(&self, key: &str) -> Option<String> {
        self.get_str(key).ok()
    }
}

impl From<bool> for HeaderValue {
    fn from(v: bool) -> Self {
        HeaderValue::Bool(v)
    }
}
impl From<i64> for HeaderValue {
    fn from(v: i64) -> Self {
        HeaderValue::Int(v)
    }
}
impl From<i32> for HeaderValue {
    fn from(v: i32) -> Self {
        HeaderValue::Int(v as i64)
    }
}
impl From<usize> for HeaderValue {
    fn from(v: usize) -> Self {
        HeaderValue::Int(v as i64)
    }
}
impl From<f64> for HeaderValue {
    fn from(v: f64) -> Self {
        HeaderValue::Float(v)
    }
}
impl From<&str> for HeaderValue {
    fn from(v: &str) -> Self {
        HeaderValue::Str(v.to_string())
    }
}
impl From<String> for HeaderValue {
    fn from(v: String) -> Self {
        HeaderValue::Str(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hierarch_prefix_and_case_are_ignored() {
        let mut h = Header::new("x.fits");
        h.set("HIERARCH ESO ADA POSANG", 45.0);
        assert_eq!(h.get_f64("ESO ADA POSANG").unwrap(), 45.0);
        assert_eq!(h.get_f64("hierarch eso ada posang").unwrap(), 45.0);
    }

    #[test]
    fn errors_name_file_keyword_and_value() {
        let mut h = Header::new("night/frame_007.fits");
        h.set("ESO ADA POSANG", "forty-five");
        let msg = h.get_f64("ESO ADA POSANG").unwrap_err().to_string();
        assert!(msg.contains("frame_007.fits"), "{msg}");
        assert!(msg.contains("ESO ADA POSANG"), "{msg}");
        assert!(msg.contains("forty-five"), "{msg}");
        let msg = h.get_f64("ESO DET NDIT").unwrap_err().to_string();
        assert!(msg.contains("missing") && msg.contains("ESO DET NDIT"), "{msg}");
    }
}
