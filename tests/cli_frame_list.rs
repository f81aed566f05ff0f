//! The set-of-frames file (pipeline/src/frame_list.rs): `sofipol night FILE` and `sofipol
//! target FILE` reduce the frames it lists, with their roles; the night writes the file of
//! the frames it used beside its catalog, and running the night on that file repeats the
//! run (the same catalog apart from provenance).
use std::path::Path;

mod common;
use common::{json, night, run};
use serde_json::Value;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The catalog without what differs between two runs of the same frames by design: the
/// provenance (command line, inputs, times) and the run's wall times.
fn science_of(mut v: Value) -> Value {
    let o = v.as_object_mut().unwrap();
    o.remove("provenance");
    o.remove("timing");
    o.remove("stage_times");
    v
}

#[test]
fn night_on_its_own_frames_file_repeats_the_run() {
    let d = tempfile::tempdir().unwrap();
    let n = night(d.path());
    // A file the night does not use (not a polarimetric frame): not in the frames file.
    let cat1 = d.path().join("first.json");
    let (code, _, err) = run(&["night", s(&n), "-o", s(&cat1), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    let frames = d.path().join("first.frames");
    let text = std::fs::read_to_string(&frames).expect("night writes its set-of-frames file");
    let listed: Vec<&str> = text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .collect();
    let n_fits = std::fs::read_dir(&n)
        .unwrap()
        .filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "fits"))
        .count();
    assert_eq!(listed.len(), n_fits, "{text}");
    assert!(listed.iter().all(|l| l.ends_with(" science")), "{text}");
    let cat2 = d.path().join("second.json");
    let (code, _, err) = run(&["night", s(&frames), "-o", s(&cat2), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    let (a, b) = (json(&cat1), json(&cat2));
    assert!(!a["targets"].as_array().unwrap().is_empty());
    assert_eq!(science_of(a), science_of(b));
    // The second run's own frames file lists the same frames.
    let again = std::fs::read_to_string(d.path().join("second.frames")).unwrap();
    let strip = |t: &str| {
        t.lines()
            .filter(|l| !l.starts_with('#'))
            .map(str::to_string)
            .collect::<Vec<_>>()
    };
    assert_eq!(strip(&text), strip(&again));
    // A run whose catalog's frames file would be its input list leaves the list alone.
    let mine = d.path().join("mine.frames");
    let hand = format!("# by hand\n{}\n", strip(&text).join("\n"));
    std::fs::write(&mine, &hand).unwrap();
    let (code, _, err) = run(&[
        "night",
        s(&mine),
        "-o",
        s(&d.path().join("mine.json")),
        "-q",
        "--no-png",
    ]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    assert_eq!(
        std::fs::read_to_string(&mine).unwrap(),
        hand,
        "the input list was overwritten"
    );
}

#[test]
fn target_reads_a_frames_file_and_the_roles_and_target_names_given() {
    let d = tempfile::tempdir().unwrap();
    let n = night(d.path());
    // Alpha's frames only, renamed; Beta's frames listed as darks (not used).
    let mut lines = vec!["# Alpha under another name".to_string()];
    let mut n_beta = 0;
    for e in std::fs::read_dir(&n).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        if name.contains("Alpha") {
            lines.push(format!("night/{name} science target=AlphaRenamed"));
        } else if name.contains("Beta") {
            lines.push(format!("night/{name} dark"));
            n_beta += 1;
        }
    }
    assert!(n_beta > 0, "{lines:?}");
    let list = d.path().join("alpha.txt");
    std::fs::write(&list, lines.join("\n")).unwrap();
    let out = d.path().join("alpha.json");
    let (code, _, err) = run(&["target", s(&list), "-o", s(&out), "-q"]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    let c = json(&out);
    let objects: Vec<&str> = c["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["object"].as_str().unwrap())
        .collect();
    assert_eq!(objects, vec!["AlphaRenamed"]);
    // The same through `night`: Beta's frames are named as listed darks, not reduced.
    let out = d.path().join("n.json");
    let (code, _, err) = run(&["night", s(&list), "-o", s(&out), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    let c = json(&out);
    let text = c.to_string();
    assert!(!text.contains("\"Beta\""), "Beta reduced");
    assert!(text.contains("listed as dark"), "{text}");
}

/// The demo night (5 binaries, dome flats, 3 standards): its frames file lists the
/// standards and the dome flats with their roles, the night on it gives the same catalog
/// (calibration included), and listing the standards' frames as `science` turns them into
/// targets.
#[test]
fn standards_and_dome_flats_keep_their_roles_through_the_frames_file() {
    let d = tempfile::tempdir().unwrap();
    let n = d.path().join("night");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("testdata/scenes/demo.toml")
        .display()
        .to_string();
    let (code, _, err) = run(&["simulate", &scene, "-o", s(&n), "-q"]);
    assert_eq!(code, 0, "{err}");
    let cat1 = d.path().join("first.json");
    let (code, _, err) = run(&["night", s(&n), "-o", s(&cat1), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    let frames = d.path().join("first.frames");
    let text = std::fs::read_to_string(&frames).unwrap();
    let count = |role: &str| {
        text.lines()
            .filter(|l| !l.starts_with('#') && l.ends_with(&format!(" {role}")))
            .count()
    };
    let a = json(&cat1);
    let n_std_files: usize = a["standards"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["input_files"].as_array().map_or(0, Vec::len))
        .sum();
    assert!(n_std_files > 0 && count("standard") == n_std_files, "{text}");
    assert!(count("flat") > 0, "{text}");
    assert!(a["provenance"]["flat"]["mode"] == "dome", "{}", a["provenance"]["flat"]);
    let cat2 = d.path().join("second.json");
    let (code, _, err) = run(&["night", s(&frames), "-o", s(&cat2), "-q", "--no-png"]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    let b = json(&cat2);
    assert_eq!(b["provenance"]["flat"]["mode"], "dome");
    assert_eq!(science_of(a.clone()), science_of(b));
    // The standards' frames listed as science: reduced as targets, no standard left.
    let as_science = text.replace(" standard\n", " science\n");
    let list = d.path().join("as_science.frames");
    std::fs::write(&list, as_science).unwrap();
    let cat3 = d.path().join("third.json");
    let (code, _, err) = run(&[
        "night",
        s(&list),
        "-o",
        s(&cat3),
        "-q",
        "--no-png",
        "--allow-uncalibrated",
    ]);
    assert!(code == 0 || code == 2, "{code}: {err}");
    let c = json(&cat3);
    assert!(
        c["standards"].as_array().is_none_or(|v| v.is_empty()),
        "{}",
        c["standards"]
    );
    let n_targets = |v: &Value| v["targets"].as_array().unwrap().len();
    assert_eq!(n_targets(&c), n_targets(&a) + a["standards"].as_array().unwrap().len());
}
