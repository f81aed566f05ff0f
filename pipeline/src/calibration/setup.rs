//! What the calibration options of a reduction resolve to: the settings, the standards
//! table and, when another night's products are used, their calibration.
use std::path::{Path, PathBuf};

use super::{Calibration, CalibrationParams, CalibrationSource};
use crate::standards::StandardsTable;

/// The calibration of a reduction, set up and checked before any frame is read.
#[derive(Debug, Clone)]
pub struct CalibSetup {
    /// Settings (`[calibration]`, command-line flags applied).
    pub params: CalibrationParams,
    /// The standards table (built-in, plus a user table when given).
    pub table: StandardsTable,
    /// Another night's calibration (its directory or file, and what it holds), used
    /// instead of this night's standards.
    pub external: Option<(PathBuf, Calibration)>,
}

impl CalibSetup {
    /// Set up from the settings, an optional user standards table (TOML, adding to or
    /// overriding the built-in one by name and filter) and an optional calibration directory
    /// or `calibration.json` of another night. Errors name the file and what is wrong.
    pub fn new(
        params: CalibrationParams,
        standards: Option<&Path>,
        calib: Option<&Path>,
    ) -> crate::error::Result<Self> {
        let table = match standards {
            Some(f) => StandardsTable::with_file(f)?,
            None => StandardsTable::builtin(),
        };
        let external = match calib {
            Some(p) => Some((p.to_path_buf(), Calibration::read(p)?)),
            None => None,
        };
        Ok(CalibSetup {
            params,
            table,
            external,
        })
    }

    /// Where the calibration of the targets comes from.
    pub fn source(&self) -> CalibrationSource {
        if self.params.no_calibration {
            CalibrationSource::Disabled
        } else if let Some((p, c)) = &self.external {
            CalibrationSource::File(p.clone(), Box::new(c.clone()))
        } else {
            CalibrationSource::Night
        }
    }

    /// The catalog's `provenance.calibration`: settings, standards tables, calibration
    /// directory.
    pub fn provenance(&self) -> serde_json::Value {
        serde_json::json!({"params": self.params, "standards_table": self.table.sources,
            "calib_dir": self.external.as_ref().map(|e| e.0.display().to_string())})
    }
}
