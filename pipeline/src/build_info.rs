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

/// The command line of this process, for provenance: each argument as given, with bytes
/// that are not valid UTF-8 (a file name in another encoding) shown as U+FFFD, so that a
/// product is never lost to an argument it cannot spell.
pub fn command_line() -> Vec<String> {
    std::env::args_os().map(|a| a.to_string_lossy().into_owned()).collect()
}

/// [`command_line`] joined by spaces.
pub fn command_line_string() -> String {
    command_line().join(" ")
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_command_line_is_this_process_arguments() {
        let v = super::command_line();
        assert!(!v.is_empty());
        assert_eq!(super::command_line_string(), v.join(" "));
    }
}
