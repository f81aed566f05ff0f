//! Helpers shared by the `tests/cli_*.rs` integration tests: run the `sofipol` binary,
//! read its JSON outputs, find test data.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_...` runs the tests against another
//! build (how tests are checked to fail before a fix).
// Each test file uses a subset of these helpers.
#![allow(dead_code)]

use std::path::Path;
use std::process::Command;

use serde_json::Value;

/// The binary under test: `$SOFIPOL_BIN`, else the one cargo built.
pub fn bin() -> String {
    std::env::var("SOFIPOL_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_sofipol").to_string())
}

/// A command running the binary under test.
pub fn sofipol() -> Command {
    Command::new(bin())
}

/// Run `sofipol ARGS`: (exit code, stdout, stderr).
pub fn run(args: &[&str]) -> (i32, String, String) {
    let o = sofipol().args(args).output().expect("run sofipol");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

/// A JSON file (catalog, truth, report); panics naming the file.
pub fn json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())))
        .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// A file of testdata/stats/.
pub fn testdata(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("testdata/stats")
        .join(name)
        .display()
        .to_string()
}
