//! The one error type of the pipeline crate. Messages name the file, the key and the value.
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
}
