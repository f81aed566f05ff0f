//! The one error type of the calib crate. Messages name the file, the keyword and the value.
use std::path::PathBuf;

/// Result alias of the calib crate.
pub type Result<T> = std::result::Result<T, Error>;

/// Everything that can go wrong while reading, classifying or calibrating frames.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// cfitsio (through the fitsio crate) reported a problem with a file.
    #[error("{path}: FITS error: {message}")]
    Fits {
        /// File concerned.
        path: PathBuf,
        /// What cfitsio said.
        message: String,
    },
    /// A required header keyword is absent.
    #[error("{path}: missing header keyword {keyword}")]
    MissingKeyword {
        /// File concerned (may be empty for in-memory headers).
        path: PathBuf,
        /// Keyword name, without the `HIERARCH` prefix.
        keyword: String,
    },
    /// A header keyword has a value of the wrong type or out of range.
    #[error("{path}: header keyword {keyword} = {value}: {reason}")]
    BadKeyword {
        /// File concerned.
        path: PathBuf,
        /// Keyword name.
        keyword: String,
        /// The value as found.
        value: String,
        /// Why it is not acceptable.
        reason: String,
    },
    /// The image is not what sofipol can reduce (wrong dimensionality, size...).
    #[error("{path}: {reason}")]
    BadImage {
        /// File concerned.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// An instrument profile could not be read or is inconsistent.
    #[error("instrument profile {source_name}: {reason}")]
    Profile {
        /// Where the profile came from (file path or "embedded sofi").
        source_name: String,
        /// What is wrong.
        reason: String,
    },
    /// A header is not that of a polarimetric science frame: the classification's rejection
    /// reason (names the keyword and its value; the caller knows the file).
    #[error("{reason}")]
    Rejected {
        /// Why the frame is not reduced as science.
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
    /// A calibration stage could not proceed (too few frames, shapes differ...).
    #[error("{stage}: {reason}")]
    Stage {
        /// Stage name (e.g. "sky").
        stage: &'static str,
        /// What is wrong.
        reason: String,
    },
}
