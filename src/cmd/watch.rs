//! `sofipol watch DIR -o catalog.json`: reduce the night while it is observed.
//!
//! The folder is followed with the operating system's file notifications (the `notify`
//! crate), or by polling (`--poll`, for network file systems). Each time a template
//! completes, times out or a calibration frame arrives, the night's complete templates are
//! reduced as `sofipol night` reduces them ([`LiveNight`]: only what changed is reduced
//! again), the catalog is rewritten atomically, and one line per new target says P/sigma
//! of each component and how many more cycles would reach the cut.
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use anyhow::Context;
use notify::Watcher;
use sofipol_calib::text::printable;
use sofipol_pipeline::catalog::{Catalog, Status};
use sofipol_pipeline::live::{target_line, LiveNight, LiveOptions, Update};

use super::setup::SetupArgs;

/// Arguments of `sofipol watch`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Night directories to follow (searched recursively, as `night` does).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Output catalog (JSON, rewritten atomically after every update). Its live state is
    /// kept beside it (`<output>.state.json`): a restart resumes without reducing again.
    #[arg(short, long, value_name = "FILE", default_value = "catalog.json")]
    pub output: PathBuf,
    /// Worker threads [default: all cores].
    #[arg(short, long, value_name = "N")]
    pub jobs: Option<usize>,
    /// Poll the directories every SECONDS instead of using the operating system's file
    /// notifications (network file systems do not deliver them) [default: notifications].
    #[arg(long, value_name = "SECONDS")]
    pub poll: Option<f64>,
    /// Reduce a template with fewer frames than TPL NEXP (or without TPL NEXP) once no
    /// frame of it has arrived for this long (an aborted template), seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 600.0)]
    pub template_timeout: f64,
    /// Hand a file that stays incomplete and unchanged this long to the reduction, which
    /// reports it as unreadable, seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 120.0)]
    pub file_timeout: f64,
    /// Stop once every template is reduced and nothing has arrived for this long, seconds
    /// [default: run until Ctrl-C].
    #[arg(long, value_name = "SECONDS")]
    pub exit_when_idle: Option<f64>,
    /// Start over: ignore the catalog and state of an earlier run.
    #[arg(long)]
    pub fresh: bool,
    #[command(flatten)]
    pub setup: SetupArgs,
    /// Print only errors.
    #[arg(short, long)]
    pub quiet: bool,
    /// More detail: templates waited for, files being written, each update's time.
    #[arg(short, long, action = clap::ArgAction::Count)]
    pub verbose: u8,
}

/// Where the live state of catalog `output` is kept.
pub fn state_path(output: &Path) -> PathBuf {
    let mut s = output.as_os_str().to_owned();
    s.push(".state.json");
    PathBuf::from(s)
}

/// Seconds given on the command line, checked.
fn seconds(what: &str, s: f64) -> anyhow::Result<Duration> {
    anyhow::ensure!((0.0..1e9).contains(&s), "{what} {s}: need a number of seconds >= 0");
    Ok(Duration::from_secs_f64(s))
}

/// Run: resume or start, follow the folders, reduce on every change, stop on Ctrl-C (a
/// final update reduces every template as it is) or when idle.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let setup = args.setup.load()?;
    if args.setup.reduce.dump_params {
        print!("{}", super::setup::dump_params(&setup.params)?);
        return Ok(ExitCode::SUCCESS);
    }
    super::setup::check_input_frames(&setup.params)?;
    for d in &args.dirs {
        anyhow::ensure!(d.is_dir(), "{}: not a directory to watch", d.display());
    }
    super::common::check_output(&args.output, &args.setup.input_files())?;
    let options = LiveOptions {
        template_timeout: seconds("--template-timeout", args.template_timeout)?,
        file_timeout: seconds("--file-timeout", args.file_timeout)?,
    };
    let idle_exit = args
        .exit_when_idle
        .map(|s| seconds("--exit-when-idle", s))
        .transpose()?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.jobs.unwrap_or(0))
        .build()
        .context("starting worker threads")?;
    let cut = setup.params.measure.cut_snr;
    let mut live = LiveNight::new(setup, args.dirs.clone(), options);
    let state = state_path(&args.output);
    if !args.fresh {
        resume(&mut live, &args.output, &state, args.quiet);
    }
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || {
            if stop.swap(true, Ordering::SeqCst) {
                eprintln!("sofipol watch: stopped at once (the catalog on disk is complete as last written)");
                std::process::exit(130);
            }
            eprintln!("sofipol watch: stopping: reducing what has arrived (Ctrl-C again to stop at once)");
        })
        .context("installing the Ctrl-C handler")?;
    }
    let (tx, rx) = mpsc::channel();
    let (_watcher, rescan) = start_watcher(&args, tx)?;
    if !args.quiet {
        eprintln!(
            "sofipol watch: following {} ({}); catalog {}; Ctrl-C to stop",
            args.dirs
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            match args.poll {
                Some(s) => format!("polling every {s} s"),
                None => "file notifications".into(),
            },
            args.output.display()
        );
    }
    let mut last_change = Instant::now();
    let mut last_scan = Instant::now() - rescan;
    let mut last: Option<Catalog> = None;
    let mut calibration_lines = Vec::new();
    // Files announced as being written (once each).
    let mut announced = std::collections::HashSet::new();
    loop {
        let wait = if live.wants_update() {
            Duration::ZERO
        } else {
            Duration::from_millis(250)
        };
        let woke = wait_for_events(&rx, wait);
        let finish = stop.load(Ordering::SeqCst);
        if woke {
            last_change = Instant::now();
        }
        if woke || finish || live.wants_update() || last_scan.elapsed() >= rescan {
            last_scan = Instant::now();
            if let Some(u) = pool.install(|| live.update(finish)) {
                last_change = Instant::now();
                write(&u, &live, &args.output, &state)?;
                print_update(&u, cut, &args, u.calibration_lines != calibration_lines);
                calibration_lines = u.calibration_lines.clone();
                last = Some(u.catalog);
            }
            if args.verbose > 0 && !args.quiet {
                for (p, why) in live.waiting() {
                    if announced.insert(p.clone()) {
                        eprintln!("[{}] {} still being written ({why})", clock(), p.display());
                    }
                }
            }
        }
        if finish {
            break;
        }
        if idle_exit.is_some_and(|d| live.settled() && last_change.elapsed() >= d) {
            break;
        }
    }
    let Some(cat) = last.or_else(|| read_catalog(&args.output)) else {
        if !args.quiet {
            eprintln!("sofipol watch: no frame reduced; no catalog written");
        }
        return Ok(ExitCode::SUCCESS);
    };
    if !args.quiet {
        let count = |s: Status| cat.targets.iter().filter(|t| t.status == s).count();
        println!(
            "{} targets: {} ok, {} partial, {} failed; {} inputs not used; {} template(s) not complete -> {}",
            cat.targets.len(),
            count(Status::Ok),
            count(Status::Partial),
            count(Status::Failed),
            cat.failures.len(),
            live.held().len(),
            args.output.display()
        );
    }
    let bad = cat.targets.iter().any(|t| t.status != Status::Ok) || !cat.failures.is_empty();
    Ok(if bad { ExitCode::from(2) } else { ExitCode::SUCCESS })
}

/// Start the folder watcher: OS notifications (falling back to polling every second when
/// they cannot be set up) or, with `--poll`, polling. Returns it (events stop when it is
/// dropped) and how often to look at the folders without an event.
fn start_watcher(
    args: &Args,
    tx: mpsc::Sender<notify::Result<notify::Event>>,
) -> anyhow::Result<(Box<dyn Watcher>, Duration)> {
    let poll_watcher = |every: Duration, tx| -> anyhow::Result<Box<dyn Watcher>> {
        let config = notify::Config::default().with_poll_interval(every);
        Ok(Box::new(
            notify::PollWatcher::new(tx, config).context("starting the polling watcher")?,
        ))
    };
    let (mut watcher, rescan): (Box<dyn Watcher>, Duration) = match args.poll {
        Some(s) => {
            let every = seconds("--poll", s)?.max(Duration::from_millis(50));
            (poll_watcher(every, tx)?, every)
        }
        None => match notify::recommended_watcher(tx.clone()) {
            Ok(w) => (Box::new(w), Duration::from_secs(5)),
            Err(e) => {
                eprintln!("sofipol watch: file notifications unavailable ({e}): polling every second");
                (poll_watcher(Duration::from_secs(1), tx)?, Duration::from_secs(1))
            }
        },
    };
    for d in &args.dirs {
        watcher
            .watch(d, notify::RecursiveMode::Recursive)
            .with_context(|| format!("watching {}", d.display()))?;
    }
    Ok((watcher, rescan))
}

/// Whether a file event may mean new or changed frames: created, written, renamed or
/// removed. Reading (ours included: the reduction opens the frames) is not.
fn is_change(ev: &notify::Result<notify::Event>) -> bool {
    use notify::event::{AccessKind, AccessMode, EventKind, ModifyKind};
    match ev {
        Ok(e) => matches!(
            e.kind,
            EventKind::Create(_)
                | EventKind::Remove(_)
                | EventKind::Modify(ModifyKind::Data(_) | ModifyKind::Name(_) | ModifyKind::Any | ModifyKind::Other)
                | EventKind::Access(AccessKind::Close(AccessMode::Write))
                | EventKind::Any
                | EventKind::Other
        ),
        // A watcher error (e.g. a lost inotify queue): look again.
        Err(_) => true,
    }
}

/// Wait up to `timeout` for file events that mean a change ([`is_change`]), then take the
/// others already queued (a frame being copied sends several). Whether any arrived.
fn wait_for_events(rx: &mpsc::Receiver<notify::Result<notify::Event>>, timeout: Duration) -> bool {
    let until = Instant::now() + timeout;
    loop {
        match rx.recv_timeout(until.saturating_duration_since(Instant::now())) {
            Ok(ev) if is_change(&ev) => break,
            Ok(_) => continue,
            Err(_) => return false,
        }
    }
    std::thread::sleep(Duration::from_millis(20));
    while rx.try_recv().is_ok() {}
    true
}

/// Load the saved state and the catalog of an earlier run (a restart).
fn resume(live: &mut LiveNight, output: &Path, state: &Path, quiet: bool) {
    if !state.exists() {
        return;
    }
    match live.cache().load(state) {
        Ok(n) => {
            if let Some(cat) = read_catalog(output) {
                live.resume_from(cat);
            }
            if !quiet {
                eprintln!(
                    "sofipol watch: resuming from {}: {n} reduced template(s)",
                    state.display()
                );
            }
        }
        Err(e) => eprintln!("sofipol watch: not resuming: {}", printable(&e)),
    }
}

/// The catalog at `path`, if it is one.
fn read_catalog(path: &Path) -> Option<Catalog> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// Write the catalog, then the state, each atomically.
fn write(u: &Update, live: &LiveNight, output: &Path, state: &Path) -> anyhow::Result<()> {
    sofipol_pipeline::io::write_json_atomic(output, &u.catalog)
        .with_context(|| format!("writing {}", output.display()))?;
    sofipol_pipeline::night::write_night_log(output, &u.catalog)
        .with_context(|| format!("writing {}", sofipol_pipeline::night::log_path(output).display()))?;
    live.cache()
        .save(state)
        .with_context(|| format!("writing {}", state.display()))
}

/// The observer's lines: one per new target, one per reason earlier targets changed, and
/// with `-v` the calibration's lines (when `calibration_changed`), the templates still
/// arriving and the update's time (the files being written are announced by the loop).
fn print_update(u: &Update, cut: f64, args: &Args, calibration_changed: bool) {
    if args.quiet {
        return;
    }
    let now = clock();
    for t in &u.new_targets {
        println!("[{now}] {}", target_line(t, cut));
    }
    let mut why: std::collections::BTreeMap<&str, usize> = Default::default();
    for (_, w) in &u.changed {
        *why.entry(w.as_str()).or_default() += 1;
    }
    for (w, n) in why {
        println!("[{now}] {n} earlier target(s) updated: {}", printable(w));
    }
    if args.verbose > 0 {
        for l in u.calibration_lines.iter().filter(|_| calibration_changed) {
            eprintln!("[{now}] {}", printable(l));
        }
        for h in &u.held {
            eprintln!(
                "[{now}] waiting for {}: {} of {} frame(s), last {:.0} s ago",
                printable(&h.id),
                h.frames,
                h.nexp.map(|n| n.to_string()).unwrap_or_else(|| "?".into()),
                h.idle_s
            );
        }
        eprintln!(
            "[{now}] update {:.2} s: {} template(s) reduced, {} reused",
            u.seconds, u.counts.reduced, u.counts.reused
        );
    }
}

/// The time of day, UTC, `hh:mm:ss`.
fn clock() -> String {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    format!("{:02}:{:02}:{:02}", now / 3600 % 24, now / 60 % 60, now % 60)
}
