//! The calibration applied to a catalog's targets (the catalog's `calibration`): the
//! `calibration.json` content itself, where it came from and the Stokes method; for a
//! catalog merged from nights calibrated apart, every input catalog's.
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use super::polarimetric_calibration::Calibration;

/// What a catalog records of its calibration (docs/catalog-schema.md).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AppliedCalibration {
    /// The calibration applied; JSON `null` when the night had none (absent in a catalog
    /// merged from several calibrations: see `catalogs`).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::present"
    )]
    pub calibration: Option<Option<Recorded>>,
    /// A catalog merged from catalogs calibrated apart: each one's calibration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub catalogs: Option<Vec<CatalogCalibration>>,
    /// The photometric zero-points of the night and the standards they came from, or why
    /// there are none (absent in older catalogs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photometry: Option<crate::catalog::photometry::PhotometricCalibration>,
    /// `night` (the night's standards), the calibration file given, `disabled`, or
    /// `per_catalog` (merged).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// The Stokes method the components were solved with.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stokes_method: Option<String>,
    /// Keys this build does not know: kept as read.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// One input catalog's calibration in a merged catalog.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CatalogCalibration {
    /// Its calibration (`null`: none).
    pub calibration: Option<Box<AppliedCalibration>>,
    /// The catalog's file.
    pub file: String,
}

/// A calibration as recorded: typed when this build reads it, else kept as it was written
/// (a catalog of another version), so it is written back unchanged.
#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
pub enum Recorded {
    /// Read as `calibration.json` is.
    Typed(Box<Calibration>),
    /// Not readable as one: kept as read.
    Raw(Value),
}

impl Serialize for Recorded {
    /// As a JSON object with its keys sorted at every level, as catalogs have always
    /// written it (calibration.json itself keeps the declaration order).
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Recorded::Typed(c) => serde_json::to_value(c).map_err(serde::ser::Error::custom)?.serialize(s),
            Recorded::Raw(v) => v.serialize(s),
        }
    }
}

impl AppliedCalibration {
    /// The calibration the night's targets were solved with (`calibration` none: no
    /// calibration was available), from `source`, with `stokes_method`.
    pub fn new(calibration: Option<Calibration>, source: String, stokes_method: &str) -> AppliedCalibration {
        AppliedCalibration {
            calibration: Some(calibration.map(|c| Recorded::Typed(Box::new(c)))),
            catalogs: None,
            photometry: None,
            source: Some(source),
            stokes_method: Some(stokes_method.to_string()),
            extra: Map::new(),
        }
    }

    /// A merged catalog's: every input catalog's calibration, by file.
    pub fn per_catalog(catalogs: Vec<(String, Option<AppliedCalibration>)>) -> AppliedCalibration {
        AppliedCalibration {
            calibration: None,
            catalogs: Some(
                catalogs
                    .into_iter()
                    .map(|(file, c)| CatalogCalibration {
                        calibration: c.map(Box::new),
                        file,
                    })
                    .collect(),
            ),
            photometry: None,
            source: Some(PER_CATALOG.into()),
            stokes_method: None,
            extra: Map::new(),
        }
    }

    /// The photometric calibration, or why there is none, in lines (the night log's and the
    /// report's): "fluxes in ADU only" when the catalog does not record any (older).
    pub fn photometry_lines(&self) -> Vec<String> {
        match &self.photometry {
            Some(p) => crate::catalog::photometry::lines(p),
            None => vec!["no magnitudes: the catalog records no photometric calibration (fluxes in ADU only)".into()],
        }
    }

    /// The calibration applied, when this build could read it.
    pub fn calibration(&self) -> Option<&Calibration> {
        match self.calibration.as_ref()?.as_ref()? {
            Recorded::Typed(c) => Some(c),
            Recorded::Raw(_) => None,
        }
    }

    /// Whether two records are the same as written (NaN equal to NaN: both `null`).
    pub fn same_as(&self, other: &AppliedCalibration) -> bool {
        serde_json::to_value(self).ok() == serde_json::to_value(other).ok()
    }
}

/// The `source` of a merged catalog's calibration.
pub const PER_CATALOG: &str = "per_catalog";

#[cfg(test)]
mod tests {
    use super::*;

    /// A catalog's calibration reads and writes back unchanged: typed, null, merged, and
    /// one this build cannot read as a calibration.
    #[test]
    fn a_recorded_calibration_writes_back_as_read() {
        for text in [
            r#"{"calibration":null,"source":"night","stokes_method":"auto"}"#,
            r#"{"calibration":{"filters":[],"flats":[],"frames":["a"],"provenance":{"commit":"x"},"schema_version":"1.0"},"source":"night","stokes_method":"auto"}"#,
            r#"{"calibration":{"filters":[{"c":0.018}]},"source":"night"}"#,
            r#"{"catalogs":[{"calibration":null,"file":"a.json"},{"calibration":{"calibration":null,"source":"night"},"file":"b.json"}],"source":"per_catalog"}"#,
        ] {
            let c: AppliedCalibration = serde_json::from_str(text).unwrap();
            assert_eq!(serde_json::to_string(&c).unwrap(), text);
        }
        let typed: AppliedCalibration = serde_json::from_str(
            r#"{"calibration":{"filters":[],"flats":[],"frames":["a"],"provenance":{},"schema_version":"1.0"}}"#,
        )
        .unwrap();
        assert_eq!(typed.calibration().unwrap().frames, ["a"]);
    }
}
