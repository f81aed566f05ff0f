//! Build script: the git commit this binary is built from, for `sofipol --version` and the
//! provenance of every catalog (`SOFIPOL_GIT_COMMIT`): `git rev-parse --short=12 HEAD`,
//! with `-dirty` when tracked files differ from it, or "unknown" without git or outside a
//! git checkout of this repository (a source tarball still builds).
use std::path::{Path, PathBuf};
use std::process::Command;

fn git(dir: &Path, args: &[&str]) -> Option<String> {
    // --no-optional-locks: `git status` must not rewrite the index, which would make this
    // script run again on the next build.
    let out = Command::new("git")
        .arg("--no-optional-locks")
        .args(args)
        .current_dir(dir)
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

fn main() {
    let dir = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    for p in [
        "build.rs",
        "Cargo.toml",
        "Cargo.lock",
        "src",
        "calib",
        "pipeline",
        "bench",
        "testdata",
    ] {
        println!("cargo:rerun-if-changed={p}");
    }
    // Only this repository's own checkout counts (not a parent directory's repository).
    let toplevel = git(&dir, &["rev-parse", "--show-toplevel"]).map(PathBuf::from);
    let ours = toplevel
        .and_then(|t| t.canonicalize().ok())
        .is_some_and(|t| dir.canonicalize().is_ok_and(|d| d == t));
    let commit = ours
        .then(|| git(&dir, &["rev-parse", "--short=12", "HEAD"]))
        .flatten()
        .filter(|c| !c.is_empty());
    let commit = match commit {
        Some(c) => {
            let dirty = git(&dir, &["status", "--porcelain", "--untracked-files=no"]).is_some_and(|s| !s.is_empty());
            // Run again when HEAD moves (commit, checkout) or the index changes (add).
            let mut paths = vec!["HEAD".to_string(), "index".to_string(), "packed-refs".to_string()];
            paths.extend(git(&dir, &["symbolic-ref", "-q", "HEAD"]));
            for p in paths {
                let f = git(&dir, &["rev-parse", "--path-format=absolute", "--git-path", &p]);
                // A missing file would make cargo run this script on every build.
                if let Some(f) = f.filter(|f| Path::new(f).exists()) {
                    println!("cargo:rerun-if-changed={f}");
                }
            }
            if dirty {
                format!("{c}-dirty")
            } else {
                c
            }
        }
        None => "unknown".to_string(),
    };
    println!("cargo:rustc-env=SOFIPOL_GIT_COMMIT={commit}");
}
