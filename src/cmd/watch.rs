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
    pub outputs: super::common::OutputArgs,
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
    let state = state_path(&args.output);
    if let Ok(m) = std::fs::symlink_metadata(&state) {
        anyhow::ensure!(
            m.is_file(),
            "{}: the live state beside the catalog is not a regular file; move it away or choose another -o",
            state.display()
        );
    }
    let options = LiveOptions {
        template_timeout: seconds("--template-timeout", args.template_timeout)?,
        file_timeout: seconds("--file-timeout", args.file_timeout)?,
    };
    let idle_exit = args
        .exit_when_idle
        .map(|s| seconds("--exit-when-idle", s))
        .transpose()?;
    let pool = super::common::worker_pool("watch", args.jobs, args.quiet)?;
    let cut = setup.params.measure.cut_snr;
    let allow_uncalibrated = setup.calibration.params.allow_uncalibrated;
    let outputs = super::common::outputs(&args.output, args.outputs.choice(false), &setup)?;
    let mut live = LiveNight::new(setup, args.dirs.clone(), options);
    live.set_outputs(outputs);
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
            eprintln!("sofipol watch: stopping: reducing what has arrived (Ctrl-C or SIGTERM again to stop at once)");
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
    // A catalog not yet on disk (the disk full, the folder not writable): written again
    // until it is, warning once per distinct reason.
    let mut unwritten: Option<(Catalog, String)> = None;
    let mut last_try = Instant::now();
    // The watched folders that were gone, as last warned about.
    let mut missing_warned: Vec<(PathBuf, String)> = Vec::new();
    let mut missing_since: Option<Instant> = None;
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
            if let Some(mut u) = pool.install(|| live.update(finish)) {
                last_change = Instant::now();
                if finish {
                    not_reduced_at_stop(&mut u.catalog, live.waiting(), args.quiet);
                }
                let was = unwritten.take().map(|(_, why)| why);
                unwritten = write(&u.catalog, &live, &args.output, &state)
                    .err()
                    .map(|e| (u.catalog.clone(), super::error_text(&super::chain_text(&e))));
                if let Some((_, why)) = &unwritten {
                    warn_unwritten(why, was.as_deref().is_none_or(|w| !same_reason(w, why)));
                }
                last_try = Instant::now();
                print_update(&u, cut, &args, u.calibration_lines != calibration_lines);
                calibration_lines = u.calibration_lines.clone();
                last = Some(u.catalog);
            }
            report_missing(&live, &mut missing_warned, &mut missing_since, args.quiet);
            if args.verbose > 0 && !args.quiet {
                for (p, why) in live.waiting() {
                    if announced.insert(p.clone()) {
                        eprintln!("[{}] {} still being written ({why})", clock(), p.display());
                    }
                }
            }
        }
        if let Some((cat, why)) = unwritten.take() {
            if finish || last_try.elapsed() >= Duration::from_secs(2) {
                last_try = Instant::now();
                match write(&cat, &live, &args.output, &state) {
                    Ok(()) => {
                        if !args.quiet {
                            eprintln!("[{}] catalog written at last: {}", clock(), args.output.display());
                        }
                    }
                    Err(e) => {
                        let now = super::error_text(&super::chain_text(&e));
                        warn_unwritten(&now, !same_reason(&now, &why));
                        unwritten = Some((cat, now));
                    }
                }
            } else {
                unwritten = Some((cat, why));
            }
        }
        if finish {
            break;
        }
        if let (Some(d), Some(t)) = (idle_exit, missing_since) {
            if t.elapsed() >= d {
                eprintln!(
                    "sofipol watch: stopping: {} still missing after {:.0} s; the catalog is as last written",
                    missing_warned
                        .iter()
                        .map(|(p, _)| p.display().to_string())
                        .collect::<Vec<_>>()
                        .join(", "),
                    d.as_secs_f64()
                );
                return Ok(ExitCode::from(2));
            }
        }
        if idle_exit.is_some_and(|d| live.settled() && last_change.elapsed() >= d) {
            break;
        }
    }
    if let Some((_, why)) = &unwritten {
        anyhow::bail!("the catalog could not be written ({why}); the last one on disk is older");
    }
    if !live.missing_roots().is_empty() {
        eprintln!(
            "sofipol watch: {} missing when stopped; the catalog is as last written",
            live.missing_roots()
                .iter()
                .map(|(p, _)| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
        return Ok(ExitCode::from(2));
    }
    let Some(cat) = last.or_else(|| read_catalog(&args.output)) else {
        if !args.quiet {
            eprintln!("sofipol watch: no frame reduced; no catalog written");
        }
        return Ok(ExitCode::SUCCESS);
    };
    if !args.quiet {
        if let Some(l) = super::summary::uncalibrated_line(&cat) {
            println!("{l}");
        }
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
    // Targets reduced across the updates: nothing earlier is cleared from the folders.
    let incomplete = live
        .take_outputs()
        .is_some_and(|o| super::common::finish_outputs(o, false, args.quiet, "watch"));
    let bad = cat.targets.iter().any(|t| t.status != Status::Ok)
        || !cat.failures.is_empty()
        || super::summary::uncalibrated_exit(&cat, allow_uncalibrated);
    Ok(if bad || incomplete {
        ExitCode::from(2)
    } else {
        ExitCode::SUCCESS
    })
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
        Err(e) => eprintln!("sofipol watch: not resuming: {}", printable(&e.to_string())),
    }
}

/// The catalog at `path`, if it is one.
fn read_catalog(path: &Path) -> Option<Catalog> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// Write the catalog, then the state, each atomically.
fn write(catalog: &Catalog, live: &LiveNight, output: &Path, state: &Path) -> anyhow::Result<()> {
    // The errors name their file already: no context that would repeat it.
    sofipol_pipeline::io::write_json_atomic(output, catalog)?;
    sofipol_pipeline::night::write_night_log(output, catalog)?;
    Ok(live.cache().save(state)?)
}

/// Whether two write errors have the same cause (the last part of the message: the
/// temporary file's random name differs between tries, `No space left on device` not).
fn same_reason(a: &str, b: &str) -> bool {
    let cause = |s: &str| {
        let last = s.rsplit(": ").next().unwrap_or(s);
        last.split(" at path ").next().unwrap_or(last).to_string()
    };
    cause(a) == cause(b)
}

/// Say that the catalog could not be written (when `first`: once per distinct reason).
fn warn_unwritten(why: &str, first: bool) {
    if first {
        eprintln!(
            "[{}] sofipol watch: WARNING: the catalog could not be written ({}); still watching, trying again",
            clock(),
            printable(why)
        );
    }
}

/// Warn when a watched folder goes missing or comes back; `since`: when the first went.
fn report_missing(live: &LiveNight, warned: &mut Vec<(PathBuf, String)>, since: &mut Option<Instant>, quiet: bool) {
    let now = live.missing_roots().to_vec();
    if now == *warned {
        return;
    }
    for (p, why) in now.iter().filter(|m| !warned.contains(m)) {
        eprintln!(
            "[{}] sofipol watch: WARNING: the watched folder {} is {}; the catalog is kept as last written, \
             waiting for it to come back",
            clock(),
            printable(&p.display().to_string()),
            printable(why)
        );
    }
    for (p, _) in warned.iter().filter(|(p, _)| !now.iter().any(|(q, _)| q == p)) {
        if !quiet {
            eprintln!(
                "[{}] sofipol watch: {} is back",
                clock(),
                printable(&p.display().to_string())
            );
        }
    }
    *since = if now.is_empty() {
        None
    } else {
        since.or(Some(Instant::now()))
    };
    *warned = now;
}

/// Name the files still being written when watch stops: in the catalog's failures and on
/// stderr, never silently left out.
fn not_reduced_at_stop(catalog: &mut Catalog, waiting: &[(PathBuf, String)], quiet: bool) {
    for (p, why) in waiting {
        if !quiet {
            eprintln!(
                "sofipol watch: {} not reduced: still being written when stopped ({})",
                printable(&p.display().to_string()),
                printable(why)
            );
        }
        catalog.failures.push(sofipol_pipeline::catalog::Failure {
            file: p.display().to_string(),
            error: format!("still being written when watch stopped ({why}): not reduced"),
        });
    }
    catalog.failures.sort_by(|a, b| a.file.cmp(&b.file));
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
    // The new numbers of each earlier target that changed (a late standard recalibrates
    // them): the observer never keeps a superseded value on screen.
    for (seq, _) in &u.changed {
        if let Some(t) = u
            .catalog
            .targets
            .iter()
            .find(|t| t.sequence.as_deref() == Some(seq.as_str()))
        {
            println!("[{now}]   now {}", target_line(t, cut));
        }
    }
    // The calibration's state (what calibrates each filter, or that nothing does) whenever
    // it changes, with or without -v.
    for l in u.calibration_lines.iter().filter(|_| calibration_changed) {
        eprintln!("[{now}] {}", printable(l));
    }
    if args.verbose > 0 {
        for h in &u.held {
            eprintln!(
                "[{now}] waiting for {}: {}, last frame {:.0} s ago",
                printable(&h.id),
                printable(&h.why),
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
