//! The catalog is read through its types: no product code indexes a JSON value by key
//! (`v["key"]`, `.pointer("/a/b")`) or pushes a flag as a string literal. Test modules and
//! test files may (they check what is written). A text scan of every crate's sources;
//! it prints what it checked.
use std::path::{Path, PathBuf};

/// The `.rs` files under `dir`, test files left out (`tests.rs`, `*_tests.rs`, `tests_*.rs`,
/// and anything in a `tests` folder).
fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if p.is_dir() {
            if name != "tests" {
                sources(&p, out);
            }
        } else if name.ends_with(".rs")
            && !(name == "tests.rs" || name.ends_with("_tests.rs") || name.starts_with("tests_"))
        {
            out.push(p);
        }
    }
}

/// The file's text before its first `#[cfg(test)]` (test modules sit at the end).
fn product_code(text: &str) -> &str {
    text.find("#[cfg(test)]").map_or(text, |i| &text[..i])
}

/// `v["key"]`: an index by a string literal.
fn json_index(line: &str) -> bool {
    let b = line.as_bytes();
    line.match_indices("[\"").any(|(i, _)| {
        let rest = &line[i + 2..];
        let Some(end) = rest.find('"') else { return false };
        let key = &rest[..end];
        i > 0
            && (b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_' || b[i - 1] == b']' || b[i - 1] == b')')
            && !key.is_empty()
            && key
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
            && rest[end + 1..].starts_with(']')
    })
}

#[test]
fn no_json_key_reads_and_no_string_flags_in_product_code() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for krate in ["src", "calib/src", "pipeline/src", "bench/src"] {
        sources(&root.join(krate), &mut files);
    }
    let mut found = Vec::new();
    let mut lines = 0;
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        for (n, line) in product_code(&text).lines().enumerate() {
            lines += 1;
            let code = line.split("//").next().unwrap_or("");
            if json_index(code) || code.contains(".pointer(") || code.contains("flags.push(\"") {
                found.push(format!(
                    "{}:{}: {}",
                    f.strip_prefix(root).unwrap().display(),
                    n + 1,
                    line.trim()
                ));
            }
        }
    }
    eprintln!("{} files, {lines} lines of product code scanned", files.len());
    assert!(
        files.len() > 100,
        "{} files: the scan found too few sources",
        files.len()
    );
    assert!(
        found.is_empty(),
        "JSON read by key or a flag pushed as a string:\n{}",
        found.join("\n")
    );
}

#[test]
fn the_scan_sees_what_it_forbids() {
    assert!(json_index(r#"let x = v["targets"].as_array();"#));
    assert!(json_index(r#"prov["flat"]["mode"]"#));
    assert!(!json_index(r#"let a = ["a", "b"];"#));
    assert!(!json_index(r#"assert_eq!(x, ["sofipol 1"]);"#));
}
