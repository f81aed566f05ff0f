//! Options shared by several subcommands: the instrument profile and progress display.
use std::io::IsTerminal;
use std::path::PathBuf;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use sofipol_calib::Profile;

/// Instrument-profile options.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ProfileArgs {
    /// TOML file merged over the embedded SOFI profile (any subset of its keys).
    #[arg(long, value_name = "FILE")]
    pub profile: Option<PathBuf>,
    /// Override one profile value, e.g. `--set detector.gain_e_per_adu=5.6` (repeatable).
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    pub sets: Vec<String>,
}

impl ProfileArgs {
    /// The validated profile.
    pub fn load(&self) -> anyhow::Result<Profile> {
        let base = match &self.profile {
            Some(p) => Profile::sofi_with_override(p)?,
            None => Profile::sofi(),
        };
        base.with_overrides(&self.sets).context("applying --set overrides")
    }
}

/// A progress bar on a terminal; hidden otherwise (callers print quiet lines instead).
pub fn progress(len: u64, what: &str, quiet: bool) -> ProgressBar {
    if quiet || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("{prefix:>10} [{bar:40}] {pos}/{len} {msg} ({elapsed}, eta {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    pb.set_prefix(what.to_string());
    pb
}
