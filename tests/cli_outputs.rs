//! `-o` onto something that is not a regular file: a symbolic link or a named pipe (a
//! device node is the same case; as root, `export ... -o /dev/stdout` replaced the
//! system's /dev/stdout link with a regular file). Refused by name, left as it was;
//! `export -o -` writes to standard output.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_outputs` runs these tests against
//! another build (how they were checked to fail before the fix).
#![cfg(unix)]
use std::path::Path;

mod common;
use common::{run, sofipol, testdata};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn is_symlink(p: &Path) -> bool {
    std::fs::symlink_metadata(p).is_ok_and(|m| m.file_type().is_symlink())
}

/// A symbolic link to another file and a named pipe as `-o` of `export` (each format),
/// `merge`, `night` (`target` shares its check) and as a file `stats` writes into its
/// directory: each is
/// refused (exit 1) naming the path and what it is; the link still points where it did,
/// its target is unchanged, the pipe is still a pipe.
#[test]
fn output_onto_a_symlink_or_a_named_pipe_is_refused_and_left_alone() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cat = testdata("catalog_aligned.json");
    let target = d.join("elsewhere.txt");
    std::fs::write(&target, b"someone's file").unwrap();
    let link = d.join("link.out");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let pipe = d.join("pipe.out");
    let have_fifo = std::process::Command::new("mkfifo")
        .arg(&pipe)
        .status()
        .is_ok_and(|st| st.success());
    let mut dests = vec![(link.clone(), "symbolic link")];
    if have_fifo {
        dests.push((pipe.clone(), "named pipe"));
    }
    // A night folder with one (unreadable) FITS file: enough to get to the output check.
    let night = d.join("night");
    std::fs::create_dir(&night).unwrap();
    std::fs::write(night.join("x.fits"), b"not a frame").unwrap();
    for (dest, what) in &dests {
        let mut runs: Vec<Vec<&str>> = ["ecsv", "csv", "fits"]
            .iter()
            .map(|f| vec!["export", cat.as_str(), "--format", f, "-o", s(dest)])
            .collect();
        runs.push(vec!["merge", cat.as_str(), "-o", s(dest)]);
        runs.push(vec!["night", s(&night), "-o", s(dest), "--no-png", "-q"]);
        for args in runs {
            let (code, _, err) = run(&args);
            assert_eq!(code, 1, "{args:?}: {err}");
            assert!(err.contains(s(dest)) && err.contains(what), "{args:?}: {err}");
            assert!(!err.contains("panicked"), "{err}");
        }
    }
    assert!(is_symlink(&link) && std::fs::read_link(&link).unwrap() == target);
    assert_eq!(std::fs::read(&target).unwrap(), b"someone's file");
    if have_fifo {
        use std::os::unix::fs::FileTypeExt;
        assert!(std::fs::symlink_metadata(&pipe).unwrap().file_type().is_fifo());
    }
    // stats writes stats.json into its directory: a link planted there is not replaced.
    let out = d.join("st");
    std::fs::create_dir(&out).unwrap();
    let planted = out.join("stats.json");
    std::os::unix::fs::symlink(&target, &planted).unwrap();
    let (code, _, err) = run(&[
        "stats",
        cat.as_str(),
        "-o",
        s(&out),
        "--pairs",
        "1000",
        "--no-model-figure",
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("stats.json") && err.contains("symbolic link"), "{err}");
    assert!(is_symlink(&planted));
    assert_eq!(std::fs::read(&target).unwrap(), b"someone's file");
}

/// `export -o -` writes the table to standard output: the same bytes as the file, for
/// every format, and nothing else on stdout.
#[test]
fn export_to_standard_output_with_a_dash() {
    let dir = tempfile::tempdir().unwrap();
    let cat = testdata("catalog_aligned.json");
    for fmt in ["ecsv", "csv", "fits"] {
        let file = dir.path().join(format!("t.{fmt}"));
        let (code, _, err) = run(&["export", cat.as_str(), "--format", fmt, "-o", s(&file)]);
        assert_eq!(code, 0, "{err}");
        let o = sofipol()
            .args(["export", cat.as_str(), "--format", fmt, "-o", "-"])
            .current_dir(dir.path())
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stderr));
        let want = std::fs::read(&file).unwrap();
        if fmt == "fits" {
            // The FITS header carries nothing time-dependent: byte-identical too.
            assert!(o.stdout.starts_with(b"SIMPLE  ="), "{fmt}");
        }
        assert_eq!(o.stdout, want, "{fmt}");
        assert!(!dir.path().join("-").exists(), "a file named '-' was written");
    }
}
