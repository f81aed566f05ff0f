//! The one error type of the pipeline crate, and the errors of its modules that it wraps
//! (re-exported there under their own names: `reduce::MeasureError`,
//! `photometry::PsfFitError`, `plots::Error`, `stats::Error`), and the errors of the
//! per-target outputs (`products::ProductError`, `products::CombineError`,
//! `products::StokesMapsError`). Messages name the file, the key and the value. A leaf: it
//! imports nothing from the crate, so every module can use it.
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
    /// A value of a calibration file (`calibration.json`) is refused: the file and the
    /// value's key, as [`CalibrationValueError`] says them.
    #[error("{path}: {source}")]
    CalibrationValue {
        /// File concerned.
        path: PathBuf,
        /// The key, the value and why it is refused.
        source: CalibrationValueError,
    },
    /// A Stokes method cannot be used with these orientations; says why.
    #[error("{reason}")]
    StokesMethod {
        /// Why (names the method and the angles present).
        reason: String,
    },
    /// A catalog given as an input cannot be read as one (`input::read_catalog`).
    #[error("{path}: {reason}")]
    CatalogFile {
        /// File concerned.
        path: PathBuf,
        /// What is wrong.
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
    Measure(#[from] MeasureError),
    /// A PSF fit failed.
    #[error(transparent)]
    PsfFit(#[from] PsfFitError),
    /// A figure could not be drawn or written.
    #[error(transparent)]
    Plot(#[from] PlotError),
    /// A statistics parameter, table or file is bad.
    #[error(transparent)]
    Stats(#[from] StatsError),
    /// The half-wave-plate reduction of a single pointing (`single_pointing`) stopped:
    /// names the file (or the night) and why.
    #[error("{file}: {reason}")]
    SinglePointing {
        /// The file or folder concerned.
        file: String,
        /// What is wrong.
        reason: String,
    },
    /// A saved live state (`sofipol watch`) was read but cannot be resumed from.
    #[error("{path}: {source}")]
    SavedState {
        /// File concerned.
        path: PathBuf,
        /// Why it is not used.
        source: SavedStateError,
    },
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

/// A value of `calibration.json` refused when the file is read (`calibration::validate`):
/// the key path (`filters[0].offset.c`), the value as written and why. A caller can tell
/// a value outside what is accepted from two values that contradict each other.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationValueError {
    /// A value outside what is accepted.
    #[error("{key} = {value}: {reason}")]
    Refused {
        /// Key path of the value (`filters[0].offset.c`).
        key: String,
        /// The value, short (`1e300`, a quoted text of at most 40 characters).
        value: String,
        /// What is accepted, or what is wrong.
        reason: String,
    },
    /// A value that contradicts another of the file (an error written twice, a matrix
    /// that is not symmetric, a name given twice).
    #[error("{key} = {value} {conflict}")]
    Contradicts {
        /// Key path of the value.
        key: String,
        /// The value, short.
        value: String,
        /// What it contradicts and why they must agree, in words.
        conflict: String,
    },
    /// A list of names of the wrong length.
    #[error("{key} has {count} names: {expected}")]
    NameCount {
        /// Key path of the list.
        key: String,
        /// Names found.
        count: usize,
        /// The names expected, in words.
        expected: String,
    },
}

/// An error that stops the measurement of a sequence (`reduce::MeasureError`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct MeasureError(pub String);

impl MeasureError {
    /// An error with this message.
    pub fn new(msg: impl Into<String>) -> Self {
        MeasureError(msg.into())
    }
}

/// Errors of the PSF fit (`photometry::fit_psf`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PsfFitError {
    /// No initial position was given.
    #[error("PSF fit: no source position given")]
    NoSources,
    /// Too few usable pixels.
    #[error("PSF fit: {n_pixels} usable pixels for {n_params} parameters")]
    TooFewPixels {
        /// Usable pixels found.
        n_pixels: usize,
        /// Parameters to fit.
        n_params: usize,
    },
    /// A setting is out of range.
    #[error("PSF fit: invalid setting {name} = {value}")]
    InvalidParams {
        /// Setting name.
        name: &'static str,
        /// Its value.
        value: f64,
    },
    /// The normal matrix could not be inverted at the solution (degenerate model).
    #[error("PSF fit: singular normal matrix at the solution (degenerate sources?)")]
    Singular,
}

/// Errors of the plotting module (`plots::Error`).
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// Drawing failed inside plotters.
    #[error("drawing {what}: {reason}")]
    Draw {
        /// What was being drawn.
        what: String,
        /// The plotters error.
        reason: String,
    },
    /// The embedded font could not be registered.
    #[error("registering the embedded DejaVu Sans font failed")]
    Font,
    /// Bad input (e.g. mismatched lengths).
    #[error("invalid plot input: {0}")]
    Input(String),
    /// Writing the file failed.
    #[error("writing {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// PNG encoding failed.
    #[error("encoding PNG: {0}")]
    Encode(String),
}

/// Errors of the statistics module (`stats::Error`).
#[derive(Debug, thiserror::Error)]
pub enum StatsError {
    /// A parameter is out of range or malformed.
    #[error("invalid {name} = '{value}': {reason}")]
    InvalidParameter {
        /// Parameter name (with unit).
        name: String,
        /// The value given.
        value: String,
        /// What is wrong.
        reason: String,
    },
    /// A table file is malformed.
    #[error("table {table}: {reason}")]
    Table {
        /// File name.
        table: String,
        /// What is wrong.
        reason: String,
    },
    /// A file could not be read.
    #[error("reading {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A catalog could not be parsed.
    #[error("catalog {path}: {reason}")]
    Catalog {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A figure could not be drawn or written.
    #[error(transparent)]
    Plot(#[from] PlotError),
}

/// Why a saved live state (`night::NightCache::load`) is not resumed from; the cache is
/// then left as it was. A caller can tell a state saved with other settings (everything is
/// reduced again, as expected) from one that is not a state at all.
#[derive(Debug, thiserror::Error)]
pub enum SavedStateError {
    /// The file is not a saved live state (not JSON, or not its layout).
    #[error("not a saved live state: {0}")]
    NotAState(serde_json::Error),
    /// The file was saved by a build with another layout.
    #[error("saved by another version (layout {found}, this build reads {reads})")]
    OtherVersion {
        /// Layout of the file.
        found: u32,
        /// Layout this build reads.
        reads: u32,
    },
    /// The file was saved with other settings.
    #[error("saved with other settings: everything is reduced again")]
    OtherSettings,
}

/// Why a per-target output file (figure, region file, FITS product) was not written or not
/// made (`products::ProductError`): the text after the file's path in
/// `products::Written::failed` and in the `fits_product_not_written` flag of its target.
#[derive(Debug, thiserror::Error)]
pub enum ProductError {
    /// An orientation's o and e cut-outs could not be combined (no measurement to register
    /// them on).
    #[error("o and e not made: {0}")]
    NoCombinedBeams(CombineError),
    /// The Stokes maps could not be made from the orientations combined.
    #[error("not made: {0}")]
    NoStokesMaps(StokesMapsError),
    /// Writing the file failed (FITS writer or atomic write; the message names the file).
    #[error("{source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: sofipol_calib::Error,
    },
    /// Creating the file's folder failed.
    #[error("{source}")]
    Io {
        /// The folder.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Drawing or writing a figure failed.
    #[error("could not write the figure: {source}")]
    Figure {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

/// Why one orientation's o and e beams could not be combined into cut-outs
/// (`products::CombineError`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CombineError {
    /// No dither has both a measured target position and a usable background.
    #[error("POSANG {posang_deg}: no dither with a measured target position and a usable background")]
    NoMeasuredDither {
        /// Rotator angle of the orientation, deg.
        posang_deg: f64,
    },
    /// No e-beam pixel is usable at the measured e-o offset.
    #[error("POSANG {posang_deg}: no usable e-beam pixel at the measured e-o offset {eo_offset_px:?} px")]
    NoEBeamPixel {
        /// Rotator angle of the orientation, deg.
        posang_deg: f64,
        /// The measured e - o offset, px.
        eo_offset_px: (f64, f64),
    },
}

/// Why a target has no Stokes maps (`products::StokesMapsError`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StokesMapsError {
    /// Fewer than 2 orientations have both beams combined.
    #[error("{found} orientation(s) with both beams: Q and U need 2")]
    TooFewOrientations {
        /// Orientations with both beams.
        found: usize,
    },
    /// The analyzer angles of the orientations do not constrain Q and U anywhere.
    #[error("the orientations' analyzer angles do not constrain Q and U")]
    Unconstrained,
}
