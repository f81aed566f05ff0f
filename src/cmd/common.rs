//! Options shared by several subcommands: the instrument profile and progress display.
use std::io::IsTerminal;
use std::path::PathBuf;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use sofipol_calib::Profile;
use sofipol_pipeline::night::NightSetup;
use sofipol_pipeline::products::{outputs, OutputChoice, Outputs};

/// Instrument-profile options.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ProfileArgs {
    /// An embedded profile by name (`sofi`, `nirc2`: Keck/NIRC2's half-wave plate,
    /// docs/instruments.md), or a TOML file merged over the embedded SOFI profile (any subset
    /// of its keys; write `./nirc2` for a file of an embedded profile's name) [default: none,
    /// the embedded SOFI profile].
    #[arg(long, value_name = "NAME|FILE")]
    pub profile: Option<PathBuf>,
    /// Override one profile value, e.g. `--set detector.gain_e_per_adu=5.6` (repeatable).
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    pub sets: Vec<String>,
}

impl ProfileArgs {
    /// The validated profile.
    pub fn load(&self) -> anyhow::Result<Profile> {
        let base = match &self.profile {
            Some(p) => match p.to_str().and_then(Profile::embedded) {
                Some(embedded) => embedded?,
                None => Profile::sofi_with_override(p)?,
            },
            None => Profile::sofi(),
        };
        base.with_overrides(&self.sets).context("applying --set overrides")
    }

    /// [`Self::load`] for a command that reduces only an instrument turned on the sky
    /// (SOFI's `rotate_instrument` modulation): a half-wave-plate profile is refused, naming
    /// the command that reduces it.
    pub fn load_rotating(&self, command: &str) -> anyhow::Result<Profile> {
        let p = self.load()?;
        let kind = p.modulation_kind();
        anyhow::ensure!(
            kind == sofipol_calib::profile::ModulationKind::RotateInstrument,
            "profile {}: modulation.kind = {} is reduced by `sofipol night DIR --profile ...` only; `sofipol {command}` \
             reduces an instrument turned on the sky (modulation.kind = rotate_instrument)",
            p.name,
            kind.name()
        );
        Ok(p)
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
    check_name_length(out, name)?;
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
            !is_fits || is_sofipol_table(out),
            "-o {}: is a FITS file; sofipol never overwrites a frame (only a table it exported itself)",
            out.display()
        );
    }
    Ok(())
}

/// Longest output file name, bytes: the file system's 255 less room for the temporary
/// file (`.NAME.tmp-...`) the atomic write renames.
pub const MAX_OUTPUT_NAME_BYTES: usize = 200;

/// Refuse, before any work, an output name the atomic write could not create next to it.
fn check_name_length(out: &std::path::Path, name: &std::ffi::OsStr) -> anyhow::Result<()> {
    let n = name.as_encoded_bytes().len();
    anyhow::ensure!(
        n <= MAX_OUTPUT_NAME_BYTES,
        "-o {}: the file name is {n} bytes long, more than the {MAX_OUTPUT_NAME_BYTES} sofipol accepts \
         (file systems allow 255, and the atomic write needs room for a temporary name)",
        out.display()
    );
    Ok(())
}

/// Whether `path` is a FITS table written by `sofipol export` (an empty primary HDU and a
/// binary table `EXTNAME = 'SOFIPOL'`): the one kind of FITS file an output may replace.
pub fn is_sofipol_table(path: &std::path::Path) -> bool {
    let mut head = vec![0u8; 16 * 2880];
    let n = std::fs::File::open(path)
        .and_then(|mut f| {
            let mut n = 0;
            while n < head.len() {
                match std::io::Read::read(&mut f, &mut head[n..])? {
                    0 => break,
                    k => n += k,
                }
            }
            Ok(n)
        })
        .unwrap_or(0);
    let cards: Vec<&[u8]> = head[..n].chunks_exact(80).collect();
    let value = |c: &&[u8], key: &[u8]| c.starts_with(key);
    let naxis0 = cards
        .iter()
        .take(36)
        .any(|c| value(c, b"NAXIS   =") && std::str::from_utf8(&c[10..30]).is_ok_and(|v| v.trim() == "0"));
    let table = cards.iter().any(|c| value(c, b"XTENSION= 'BINTABLE'"));
    let ours = cards.iter().any(|c| value(c, b"EXTNAME = 'SOFIPOL "));
    naxis0 && table && ours
}

/// Check, before any work, that the files `names` can be written into `dir` (created if
/// needed) without replacing an input (compared by canonical path) or a directory.
pub fn check_outputs_in_dir(
    dir: &std::path::Path,
    names: &[&str],
    inputs: &[&std::path::Path],
    what: &str,
) -> anyhow::Result<()> {
    check_output_dir(dir, what)?;
    for name in names {
        let out = dir.join(name);
        anyhow::ensure!(
            !out.is_dir(),
            "{what} {}: {} is a directory",
            dir.display(),
            out.display()
        );
        let Ok(canon) = std::fs::canonicalize(&out) else {
            continue;
        };
        for i in inputs {
            if std::fs::canonicalize(i).is_ok_and(|c| c == canon) {
                anyhow::bail!(
                    "{what} {}: would replace {} with {name}; sofipol never overwrites its inputs",
                    dir.display(),
                    i.display()
                );
            }
        }
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

/// Refuse to reduce a night whose scan ran out of file handles: its files are not
/// unusable, the process could not open them (exit 1, nothing written).
pub fn check_scan_complete(plan: &sofipol_pipeline::night::NightPlan) -> anyhow::Result<()> {
    if let Some(e) = &plan.out_of_file_handles {
        anyhow::bail!(
            "ran out of file handles while reading the headers ({e}): the inputs were not all \
             read; raise the limit (`ulimit -n`) or use fewer --jobs. Nothing was reduced"
        );
    }
    Ok(())
}

/// The per-target outputs wanted besides the catalog, wherever a night is reduced (night,
/// target, watch).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct OutputArgs {
    /// Also write DS9 region files, one per frame (both stars' apertures and sky annuli in
    /// the o and e beams, dithers left out in red), into `<catalog stem>_products/regions/`
    /// [default: none].
    #[arg(long)]
    pub regions: bool,
    /// Also write FITS products into `<catalog stem>_products/fits/`: per target and
    /// orientation the combined o and e cut-outs, per target Stokes I, Q, U, the night's
    /// bad-pixel mask (docs/products.md) [default: not written].
    #[arg(long)]
    pub fits_products: bool,
}

impl OutputArgs {
    /// The outputs asked for, with or without the figures.
    pub fn choice(&self, figures: bool) -> OutputChoice {
        OutputChoice {
            figures,
            regions: self.regions,
            fits: self.fits_products,
        }
    }
}

/// The per-target outputs of a run beside `catalog` ([`Outputs`]): each folder asked for is
/// created and checked writable first (a run never reduces a night to fail at its first
/// product), naming the option that wants it.
pub fn outputs(catalog: &std::path::Path, choice: OutputChoice, setup: &NightSetup) -> anyhow::Result<Outputs> {
    let root = sofipol_pipeline::products::products_dir(catalog);
    for (want, dir, what) in [
        (choice.figures, root.clone(), "the figures' folder"),
        (choice.regions, root.join(outputs::REGIONS_DIR), "--regions"),
        (choice.fits, root.join(outputs::FITS_DIR), "--fits-products"),
    ] {
        if want {
            check_output_dir(&dir, what)?;
        }
    }
    Outputs::create(catalog, choice, &setup.params.measure).with_context(|| format!("creating {}", root.display()))
}

/// The end of a run's outputs (`clean`: a whole night, see [`Outputs::finish`]): the FITS
/// products' files and size on stdout (unless `quiet`), every file not written on stderr.
/// Returns whether one was not written (the run then exits 2: its products are incomplete).
pub fn finish_outputs(o: Outputs, clean: bool, quiet: bool, cmd: &str) -> bool {
    let s = o.finish(clean);
    let kinds = [
        (&s.regions, "region file", "region file(s)"),
        (&s.figures, "figure", "figure(s)"),
        (&s.fits, "FITS product not written", "FITS product(s)"),
    ];
    if let (Some(f), false) = (&s.fits, quiet) {
        println!(
            "fits products: {} files, {:.1} MB -> {}",
            f.files.len(),
            f.bytes as f64 / 1e6,
            f.dir.display()
        );
    }
    for (written, what, many) in kinds {
        let Some(w) = written else { continue };
        for line in &w.failed {
            eprintln!("sofipol {cmd}: {what}: {}", sofipol_calib::text::printable(line));
        }
        if !w.failed.is_empty() {
            eprintln!(
                "sofipol {cmd}: {} {many} could not be written: the products are incomplete (exit 2)",
                w.failed.len()
            );
        }
    }
    s.incomplete()
}

/// `--jobs` is capped at this many threads per core.
pub const MAX_JOBS_PER_CORE: usize = 4;

/// The worker threads of command `cmd` for `--jobs` (`None`: one per core): at least 1,
/// and capped at [`MAX_JOBS_PER_CORE`] x the cores (with a note unless `quiet`), since
/// thousands of threads only thrash, and each may hold a frame set in memory.
pub fn worker_pool(cmd: &str, jobs: Option<usize>, quiet: bool) -> anyhow::Result<rayon::ThreadPool> {
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let threads = match jobs {
        None => cores,
        Some(0) => anyhow::bail!("--jobs 0: need at least 1 worker thread"),
        Some(j) => {
            let cap = MAX_JOBS_PER_CORE * cores;
            if j > cap && !quiet {
                eprintln!("sofipol {cmd}: --jobs {j} capped at {cap} ({MAX_JOBS_PER_CORE} x {cores} cores)");
            }
            j.min(cap)
        }
    };
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("starting worker threads")
}
