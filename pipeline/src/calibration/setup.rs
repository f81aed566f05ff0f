//! What the calibration options of a reduction resolve to: the settings, the standards
//! table and, when another night's products are used, their calibration.
use std::path::PathBuf;

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
    /// Set up from the settings: the standards table (the built-in one, with the user
    /// table of `params.standards` added) and the calibration of another night
    /// (`params.calib_dir`), both read now. Errors name the file and what is wrong.
    pub fn new(params: CalibrationParams) -> crate::error::Result<Self> {
        let table = match &params.standards {
            Some(f) => StandardsTable::with_file(f)?,
            None => StandardsTable::builtin(),
        };
        let external = match &params.calib_dir {
            Some(p) => Some((p.clone(), Calibration::read(p)?)),
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
    pub fn provenance(&self) -> crate::catalog::provenance::CalibrationInputs {
        crate::catalog::provenance::CalibrationInputs {
            calib_dir: self.external.as_ref().map(|e| e.0.display().to_string()),
            params: serde_json::json!(self.params),
            standards_table: serde_json::json!(self.table.sources),
        }
    }
}
