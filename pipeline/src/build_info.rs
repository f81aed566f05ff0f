//! What built this sofipol, for `--version` and the provenance of every product: the
//! version and the git commit. The commit is known to the `sofipol` binary (its build
//! script runs `git`), which sets it once at start-up with [`set_commit`]; a library
//! caller that does not set it records "unknown".
use std::sync::OnceLock;

static COMMIT: OnceLock<String> = OnceLock::new();

/// This crate's version (the workspace's).
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Record the git commit of the build (`abcdef123456`, `abcdef123456-dirty` or
/// `unknown`); the first call wins.
pub fn set_commit(commit: &str) {
    let _ = COMMIT.set(commit.to_string());
}

/// The git commit recorded by [`set_commit`], else "unknown".
pub fn commit() -> &'static str {
    COMMIT.get().map(String::as_str).unwrap_or("unknown")
}
