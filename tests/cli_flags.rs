//! One spelling, one meaning for the flags of every subcommand (docs/cli.md, "Flags"):
//! walks `sofipol --help` and every subcommand's `--help`, and checks the output flag, the
//! thread count, `-q`, `-v`, duplicates, and that options state their defaults and units;
//! `--version` names the git commit; a long `mc` prints its estimated time.
mod common;

use std::io::BufRead;
use std::process::Stdio;

use common::{run, sofipol};

/// One option line of `--help`: (short, long, takes a value, its help text).
#[derive(Debug)]
struct Opt {
    short: Option<char>,
    long: String,
    value: bool,
    help: String,
}

/// The subcommands listed under "Commands:" of `sofipol PATH --help`.
fn subcommands(help: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut inside = false;
    for l in help.lines() {
        if l.starts_with("Commands:") {
            inside = true;
            continue;
        }
        if inside {
            if !l.starts_with("  ") || l.trim().is_empty() {
                break;
            }
            if let Some(name) = l.split_whitespace().next() {
                if name != "help" && !l.starts_with("   ") {
                    out.push(name.to_string());
                }
            }
        }
    }
    out
}

/// The options of a `--help` text (the long form, `--help`, lists each with its full help).
fn options(help: &str) -> Vec<Opt> {
    let mut out: Vec<Opt> = Vec::new();
    for l in help.lines() {
        let t = l.trim_start();
        let indent = l.len() - t.len();
        if t.starts_with('-') && indent <= 6 {
            let (spec, rest) = t.split_once("  ").unwrap_or((t, ""));
            let mut short = None;
            let mut long = String::new();
            for part in spec.split([',', ' ']).filter(|p| !p.is_empty()) {
                if let Some(x) = part.strip_prefix("--") {
                    long = x.trim_end_matches("...").to_string();
                } else if let Some(x) = part.strip_prefix('-') {
                    short = x.chars().next();
                }
            }
            out.push(Opt {
                short,
                long,
                value: spec.contains('<'),
                help: rest.trim().to_string(),
            });
        } else if let Some(o) = out.last_mut() {
            // Help on the lines below the flag (clap's layout when some help is long).
            if !t.is_empty() && indent > 6 {
                if !o.help.is_empty() {
                    o.help.push(' ');
                }
                o.help.push_str(t);
            }
        }
    }
    out
}

/// Every command path and its `--help` (long help).
fn all_helps() -> Vec<(String, String)> {
    let mut todo = vec![Vec::<String>::new()];
    let mut out = Vec::new();
    while let Some(path) = todo.pop() {
        let mut args: Vec<&str> = path.iter().map(String::as_str).collect();
        args.push("--help");
        let (code, help, err) = run(&args);
        assert_eq!(code, 0, "sofipol {}: {err}", args.join(" "));
        for s in subcommands(&help) {
            let mut p = path.clone();
            p.push(s);
            todo.push(p);
        }
        out.push((path.join(" "), help));
    }
    out
}

#[test]
fn every_subcommand_spells_each_flag_one_way() {
    let helps = all_helps();
    assert!(
        helps.len() >= 12,
        "{:?}",
        helps.iter().map(|h| &h.0).collect::<Vec<_>>()
    );
    let mut problems = Vec::new();
    for (cmd, help) in &helps {
        let opts = options(help);
        let mut seen = std::collections::BTreeSet::new();
        for o in &opts {
            let name = format!("sofipol {cmd}: --{} (-{:?})", o.long, o.short);
            if !seen.insert(o.long.clone()) {
                problems.push(format!("{name}: listed twice"));
            }
            let writes = ["out", "outdir", "output-dir", "out-dir"].contains(&o.long.as_str());
            if writes || (o.short == Some('o')) != (o.long == "output") {
                problems.push(format!("{name}: the output is -o, --output"));
            }
            if o.long == "threads" || (o.short == Some('j') && o.long != "jobs") {
                problems.push(format!("{name}: threads are --jobs"));
            }
            if (o.short == Some('q')) != (o.long == "quiet") {
                problems.push(format!("{name}: -q is --quiet"));
            }
            if (o.short == Some('v')) != (o.long == "verbose") {
                problems.push(format!("{name}: -v is --verbose"));
            }
            if o.long == "quiet" && !cmd.starts_with("demo") && !o.help.starts_with("Print only errors") {
                problems.push(format!("{name}: --quiet prints only errors ({})", o.help));
            }
        }
        let has = |l: &str| opts.iter().any(|o| o.long == l);
        // Every command that writes a file names it with -o, --output.
        if [
            "night", "target", "calib", "merge", "export", "simulate", "stats", "mc", "demo", "report",
        ]
        .contains(&cmd.as_str())
            && !has("output")
        {
            problems.push(format!("sofipol {cmd}: no -o, --output"));
        }
        if [
            "night", "target", "calib", "merge", "export", "simulate", "stats", "mc", "report",
        ]
        .contains(&cmd.as_str())
            && !has("quiet")
        {
            problems.push(format!("sofipol {cmd}: no -q, --quiet"));
        }
        if [
            "night", "target", "calib", "watch", "merge", "export", "stats", "mc", "report",
        ]
        .contains(&cmd.as_str())
            && !has("verbose")
        {
            problems.push(format!("sofipol {cmd}: no -v, --verbose"));
        }
        if ["night", "stats", "mc", "report"].contains(&cmd.as_str()) && !has("jobs") {
            problems.push(format!("sofipol {cmd}: no --jobs"));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn old_spellings_still_work_as_hidden_aliases() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("mc");
    let (code, _, err) = run(&[
        "mc",
        "--pairs",
        "1000",
        "--threads",
        "1",
        "--out",
        out.to_str().unwrap(),
        "-q",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(out.join("pi_delta_gamma.json").is_file());
    for cmd in ["mc", "stats"] {
        let (_, help, _) = run(&[cmd, "--help"]);
        assert!(!help.contains("--threads") && !help.contains("--out "), "{help}");
    }
}

/// Options (with a value) whose help must name a default: those not required, not
/// repeatable and not positional.
const NO_DEFAULT: &[&str] = &["param", "set"];

#[test]
fn options_state_their_defaults_and_units() {
    let mut problems = Vec::new();
    for cmd in [
        "night", "target", "calib", "stats", "mc", "simulate", "export", "merge", "report",
    ] {
        let (_, help, _) = run(&[cmd, "--help"]);
        for o in options(&help) {
            let required = o.help.contains("required");
            if o.value && !required && !NO_DEFAULT.contains(&o.long.as_str()) && !o.help.contains("default") {
                problems.push(format!(
                    "sofipol {cmd} --{}: no default in its help: {}",
                    o.long, o.help
                ));
            }
        }
        // Units, in the help text or the value name.
        let units: &[(&str, &[&str])] = &[
            ("aperture-fwhm", &["FWHM"]),
            ("companion", &["arcsec", "deg"]),
            ("ism-angle", &["deg"]),
            ("p-ism", &["percent"]),
            ("noise", &["percent"]),
            ("jobs", &["all cores"]),
            ("method", &["exact"]),
            ("debias", &["wk"]),
            ("stokes-method", &["auto"]),
        ];
        let lines: Vec<&str> = help.lines().collect();
        for (flag, want) in units {
            let opts = options(&help);
            let Some(o) = opts.iter().find(|o| o.long == *flag) else {
                continue;
            };
            let spec = lines
                .iter()
                .find(|l| l.contains(&format!("--{flag} ")))
                .copied()
                .unwrap_or("");
            for w in *want {
                if !o.help.contains(w) && !spec.contains(w) {
                    problems.push(format!("sofipol {cmd} --{flag}: '{w}' missing: {spec} {}", o.help));
                }
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// The commit `git` reports for this checkout, if it is one.
fn git_head() -> Option<String> {
    let o = std::process::Command::new("git")
        .args(["rev-parse", "HEAD"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .ok()?;
    o.status
        .success()
        .then(|| String::from_utf8_lossy(&o.stdout).trim().to_string())
}

#[test]
fn version_names_the_git_commit_and_mc_records_it() {
    let (code, v, _) = run(&["--version"]);
    assert_eq!(code, 0);
    let v = v.trim();
    let commit = v
        .split("(commit ")
        .nth(1)
        .and_then(|s| s.strip_suffix(')'))
        .unwrap_or_else(|| panic!("no '(commit ...)' in --version: {v}"));
    assert!(v.starts_with(&format!("sofipol {}", env!("CARGO_PKG_VERSION"))), "{v}");
    if let Some(head) = git_head() {
        let hash = commit.trim_end_matches("-dirty");
        assert!(
            hash.len() >= 7 && hash.chars().all(|c| c.is_ascii_hexdigit()) && head.starts_with(hash),
            "--version commit {commit} is not HEAD {head}"
        );
    }
    // Products record the same string.
    let dir = tempfile::tempdir().unwrap();
    let (code, _, err) = run(&["mc", "--pairs", "1000", "-q", "-o", dir.path().to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let j = common::json(&dir.path().join("pi_delta_gamma.json"));
    assert_eq!(j["provenance"]["commit"], commit, "{}", j["provenance"]);
}

#[test]
fn a_long_mc_prints_its_estimated_time_and_quiet_silences_it() {
    // 1e10 pairs (the most mc accepts) take minutes to hours: the estimate comes after the first half second of work.
    let mut child = sofipol()
        .args(["mc", "--pairs", "1e10"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for l in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            if tx.send(l).is_err() {
                break;
            }
        }
    });
    let line = rx
        .recv_timeout(std::time::Duration::from_secs(120))
        .map_err(|e| format!("{e}"));
    let _ = child.kill();
    let _ = child.wait();
    let line = line.expect("an estimate on stderr within 120 s");
    assert!(line.contains("estimated time"), "{line}");
    // At least minutes (indicatif's HumanDuration): 10^10 pairs at under 10^8 pairs/s.
    assert!(["minutes", "hours", "days"].iter().any(|u| line.contains(u)), "{line}");
    // A short run prints no estimate; -q prints nothing at all.
    let (code, out, err) = run(&["mc", "--pairs", "1e5"]);
    assert_eq!(code, 0, "{err}");
    assert!(!err.contains("estimated") && out.contains("accepted"), "{err}");
    let mut child = sofipol()
        .args(["mc", "--pairs", "1e10", "-q"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_secs(3));
    let _ = child.kill();
    let o = child.wait_with_output().unwrap();
    assert_eq!(
        (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)),
        ("".into(), "".into())
    );
}

/// `-v` says more on stderr wherever it exists, and the normal output is unchanged.
#[test]
fn verbose_adds_detail_on_stderr_to_every_command_that_has_it() {
    let dir = tempfile::tempdir().unwrap();
    let n = common::night(dir.path());
    let cat = dir.path().join("n.json");
    let (code, _, err) = run(&[
        "night",
        n.to_str().unwrap(),
        "--allow-uncalibrated",
        "-o",
        cat.to_str().unwrap(),
        "--no-png",
        "-q",
    ]);
    assert!(code == 0 || code == 2, "{err}");
    let c = cat.to_str().unwrap();
    let out = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (vec!["export".into(), c.into(), "-o".into(), out("t.ecsv")], "columns ("),
        (
            vec!["merge".into(), c.into(), "-o".into(), out("m.json")],
            ": whole night, 2 targets",
        ),
        (
            vec![
                "stats".into(),
                c.into(),
                "--pairs".into(),
                "2000".into(),
                "--allow-uncalibrated".into(),
            ],
            "analysis (",
        ),
        (
            vec![
                "report".into(),
                c.into(),
                "-o".into(),
                out("r.html"),
                "--pairs".into(),
                "2000".into(),
            ],
            "figures found",
        ),
        (vec!["mc".into(), "--pairs".into(), "5000".into()], "pairs drawn"),
    ];
    for (args, want) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let (code, stdout, stderr) = run(&args);
        assert_eq!(code, 0, "{args:?}\n{stderr}");
        assert!(!stderr.contains(want), "{args:?} says {want:?} without -v:\n{stderr}");
        let mut v = args.clone();
        v.push("-v");
        let (code, stdout_v, stderr_v) = run(&v);
        assert_eq!(code, 0, "{v:?}\n{stderr_v}");
        assert!(stderr_v.contains(want), "{v:?}: {want:?} not in\n{stderr_v}");
        // The normal output is the same apart from times (stdout of stats/mc has timings).
        assert_eq!(stdout.lines().count(), stdout_v.lines().count(), "{v:?}");
    }
}
