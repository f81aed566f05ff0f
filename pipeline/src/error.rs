//! The one error type of the pipeline crate. Messages name the file, the key and the value.
use std::path::PathBuf;
/// Result alias of the pipeline crate.
pub type Result<T> = std::result::Result<T, Error>;

/// A setting outside its allowed range: names the key, the value and what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("setting {key} = {value}: must be {allowed}")]
pub struct SettingError {
    /// Key as written in the settings file (`section.name`).
    pub key: &'static str,
    /// The value found.
    pub value: String,
    /// The allowed range.
    pub allowed: &'static str,
}

/// Everything that can go wrong in the pipeline crate.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A setting is out of its allowed range.
    #[error(transparent)]
    Setting(#[from] SettingError),
    /// A simulator scene is malformed or out of range.
    #[error("{origin}: {reason}")]
    Scene {
        /// Where the scene came from (file name, "embedded demo scene"...), or "scene".
        origin: String,
        /// What is wrong (names the key and the value).
        reason: String,
    },
    /// Shard catalogs cannot be merged, or a shard is misspelled.
    #[error("{file}: {reason}")]
    Merge {
        /// The catalog (or shard spelling) concerned.
        file: String,
        /// What is wrong.
        reason: String,
    },
    /// A calibration stage or file failed; `context` says which.
    #[error("{context}: {source}")]
    Calib {
        /// What was being done ("calibration mask", "night bad-pixel mask"...).
        context: String,
        /// The calib crate's error (names file, keyword, value).
        source: sofipol_calib::Error,
    },
    /// A standards table (built-in, harness or user file) is malformed.
    #[error("{origin}: {reason}")]
    Standards {
        /// Where the table came from (file path, "builtin standards"...).
        origin: String,
        /// What is wrong (names the star, the key and the value).
        reason: String,
    },
    /// A calibration file (`calibration.json`) cannot be used.
    #[error("{path}: {reason}")]
    CalibrationFile {
        /// File concerned.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A Stokes method cannot be used with these orientations; says why.
    #[error("{reason}")]
    StokesMethod {
        /// Why (names the method and the angles present).
        reason: String,
    },
    /// Plain I/O error on a file.
    #[error("{path}: {source}")]
    Io {
        /// File concerned.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// A frame that cannot be used as a whole (foreign size, mostly non-finite, constant):
    /// dropped by name with this reason, the other dithers carry on.
    #[error("{0}")]
    UnusableFrame(String),
    /// The measurement of a sequence stopped.
    #[error(transparent)]
    Measure(#[from] crate::reduce::MeasureError),
    /// A PSF fit failed.
    #[error(transparent)]
    PsfFit(#[from] crate::photometry::PsfFitError),
    /// A figure could not be drawn or written.
    #[error(transparent)]
    Plot(#[from] crate::plots::Error),
    /// A statistics parameter, table or file is bad.
    #[error(transparent)]
    Stats(#[from] crate::stats::Error),
}

impl Error {
    /// A calib error met while doing `context`.
    pub fn calib(context: impl Into<String>, source: sofipol_calib::Error) -> Error {
        Error::Calib {
            context: context.into(),
            source,
        }
    }
}
