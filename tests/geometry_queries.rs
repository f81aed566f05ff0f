//! The detector geometry is asked, not read: no source file but the profile's own
//! (`calib/src/profile.rs`) names the focal mask's strip fields (`o_target`, `e_target`,
//! `o_sky1`, `o_sky2`, `e_sky1`, `e_sky2`).
//!
//! Every stage that needs to know which rows hold the target, which beam a row receives,
//! how many rows a frame must have or where the e image of an o position lies asks
//! `Geometry` (`measured_rows`, `target_rows`, `beam_of_row`, `lit_rows_end`,
//! `e_image_of`, `strips`, `row_in_strip`). An instrument whose beams and mask are laid out
//! otherwise then changes the profile's answers, not the stages. Tests may build profiles
//! by hand, so test files (`tests.rs`, `tests_*.rs`, `*_tests.rs`, `tests/` folders) do not
//! count. This test reads the sources as text and fails naming each file and line.

use std::path::{Path, PathBuf};

/// The source folders of the workspace's crates, relative to the workspace.
const SOURCES: &[&str] = &["src", "calib/src", "pipeline/src", "bench/src"];

/// The one file that may name the strip fields.
const OWNER: &str = "calib/src/profile.rs";

/// The strip fields of `Geometry`.
const FIELDS: &[&str] = &["o_target", "e_target", "o_sky1", "o_sky2", "e_sky1", "e_sky2"];

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if p.is_dir() {
            if name != "tests" {
                rust_files(&p, out);
            }
        } else if name.ends_with(".rs") && !is_test_file(name) {
            out.push(p);
        }
    }
}

fn is_test_file(name: &str) -> bool {
    name == "tests.rs" || name.starts_with("tests_") || name.ends_with("_tests.rs")
}

/// Whether `line` names `field` as a field (`.field` or `field:` in a struct literal or
/// pattern), not as part of a longer identifier nor inside a string literal.
fn names_field(line: &str, field: &str) -> bool {
    let bytes = line.as_bytes();
    let ident = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
    let mut from = 0;
    while let Some(i) = line[from..].find(field).map(|i| i + from) {
        let before = i.checked_sub(1).map(|j| bytes[j]);
        let after = bytes.get(i + field.len()).copied();
        let whole = !before.is_some_and(ident) && !after.is_some_and(ident);
        let as_field = before == Some(b'.') || line[i + field.len()..].trim_start().starts_with(':');
        // Inside a string literal (an odd number of quotes before it): text, not code.
        let in_string = line[..i].bytes().filter(|&b| b == b'"').count() % 2 == 1;
        if whole && as_field && !in_string && !line[i + field.len()..].trim_start().starts_with("::") {
            return true;
        }
        from = i + field.len();
    }
    false
}

#[test]
fn only_the_profile_names_the_strip_fields() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for s in SOURCES {
        rust_files(&root.join(s), &mut files);
    }
    assert!(
        files.len() > 50,
        "found only {} source files under {SOURCES:?}",
        files.len()
    );
    let mut offenders = Vec::new();
    for f in &files {
        let rel = f.strip_prefix(root).unwrap_or(f).to_string_lossy().replace('\\', "/");
        if rel == OWNER {
            continue;
        }
        let text = std::fs::read_to_string(f).unwrap_or_default();
        // Test modules inside a source file start at `#[cfg(test)]`: not counted.
        let code = text.split("#[cfg(test)]").next().unwrap_or("");
        for (k, line) in code.lines().enumerate() {
            let l = line.trim_start();
            if l.starts_with("//") {
                continue;
            }
            for field in FIELDS {
                if names_field(line, field) {
                    offenders.push(format!("{rel}:{}: {field}: {}", k + 1, line.trim()));
                }
            }
        }
    }
    assert!(
        offenders.is_empty(),
        "these lines read the focal mask's strips directly; ask the profile's Geometry instead \
         (measured_rows, target_rows, beam_of_row, lit_rows_end, strips):\n{}",
        offenders.join("\n")
    );
}

#[test]
fn the_field_matcher_finds_field_uses_only() {
    assert!(names_field("let r = g.o_target;", "o_target"));
    assert!(names_field("Geometry { o_target: [1, 2], ..g }", "o_target"));
    assert!(names_field("let x = (g.o_target[0] + 1);", "o_target"));
    assert!(!names_field("fn detection_on_the_o_target_rows() {", "o_target"));
    assert!(!names_field("let o_target_rows = 3;", "o_target"));
    assert!(!names_field("write_target(out)", "e_target"));
    assert!(!names_field("let s = \"geometry.e_sky1\";", "e_sky1"));
}
