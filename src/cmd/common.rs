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

/// Check that `-o out` is absent or a regular file: its outputs are written by renaming a
/// complete temporary file over it, which would replace a symbolic link or a device node
/// (`/dev/stdout`) with a regular file. `hint` ends the message (what to do instead).
pub fn check_regular_output(out: &std::path::Path, hint: &str) -> anyhow::Result<()> {
    sofipol_calib::atomic::check_destination(out).map_err(|e| anyhow::anyhow!("-o {e}{hint}"))
}

/// Check, before any work, that `-o out` can be written and is not an input: not a
/// directory, not a symbolic link or device ([`check_regular_output`]), not one of
/// `inputs` (by canonical path: a symlink or `./x` alias counts), not an existing FITS
/// file, and in a directory (or under an existing ancestor) where a file can be created.
/// sofipol never overwrites an input.
pub fn check_output<P: AsRef<std::path::Path>>(out: &std::path::Path, inputs: &[P]) -> anyhow::Result<()> {
    use std::path::Path;
    anyhow::ensure!(
        !out.is_dir(),
        "-o {}: is a directory; give a file name, e.g. {}",
        out.display(),
        out.join("catalog.json").display()
    );
    let name = out
        .file_name()
        .ok_or_else(|| anyhow::anyhow!("-o {}: not a file name", out.display()))?;
    let parent = match out.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    // The nearest existing ancestor must be a directory we can create files in.
    let mut dir = parent;
    while !dir.exists() {
        dir = match dir.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
    }
    anyhow::ensure!(
        dir.is_dir(),
        "-o {}: {} is not a directory",
        out.display(),
        dir.display()
    );
    tempfile::tempfile_in(dir)
        .with_context(|| format!("-o {}: cannot create files in {}", out.display(), dir.display()))?;
    let canon = std::fs::canonicalize(out)
        .or_else(|_| std::fs::canonicalize(parent).map(|d| d.join(name)))
        .unwrap_or_else(|_| out.to_path_buf());
    for i in inputs {
        let i = i.as_ref();
        if std::fs::canonicalize(i).map(|c| c == canon).unwrap_or(i == out) {
            anyhow::bail!(
                "-o {}: is an input ({}); sofipol never overwrites its inputs",
                out.display(),
                i.display()
            );
        }
    }
    check_regular_output(out, "; give a regular file name")?;
    if out.is_file() {
        let mut head = [0u8; 9];
        let is_fits = std::fs::File::open(out)
            .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
            .map(|_| &head == b"SIMPLE  =")
            .unwrap_or(false);
        anyhow::ensure!(
            !is_fits,
            "-o {}: is a FITS file; sofipol writes JSON there and never overwrites a frame",
            out.display()
        );
    }
    Ok(())
}

/// Check, before any work, that a directory for products exists or can be created and
/// accepts new files (creates it).
pub fn check_output_dir(dir: &std::path::Path, what: &str) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("{what} {}: cannot create the directory", dir.display()))?;
    tempfile::tempfile_in(dir).with_context(|| format!("{what} {}: cannot create files there", dir.display()))?;
    Ok(())
}
