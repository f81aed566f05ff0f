//! The documentation stands alone: a user has the repository, nothing else. No page of
//! docs/ (nor the README) points outside it, speaks of our work tracker's issues, or links
//! a file the repository does not have.

use std::path::{Path, PathBuf};

fn pages() -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut pages = vec![root.join("README.md")];
    let mut dirs = vec![root.join("docs")];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "md") {
                pages.push(path);
            }
        }
    }
    pages.sort();
    assert!(pages.len() > 10, "docs/ has {} pages", pages.len());
    pages
}

/// Whether `word` occurs in `line` as a whole word (ASCII letters around it do not count).
fn has_word(line: &str, word: &str) -> bool {
    let lower = line.to_ascii_lowercase();
    lower.match_indices(word).any(|(i, _)| {
        let before = lower[..i].chars().next_back();
        let after = lower[i + word.len()..].chars().next();
        !before.is_some_and(|c| c.is_ascii_alphabetic()) && !after.is_some_and(|c| c.is_ascii_alphabetic())
    })
}

#[test]
fn word_detection() {
    assert!(has_word("as in issue 10", "issue"));
    assert!(has_word("the issue-10 night", "issue"));
    assert!(has_word("Issue: x", "issue"));
    assert!(!has_word("disk tissue", "issue"));
    assert!(!has_word("reissued", "issue"));
}

#[test]
fn no_page_points_outside_the_repository_or_at_our_issues() {
    let mut bad = Vec::new();
    for page in pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        for (n, line) in text.lines().enumerate() {
            let why = if line.contains("../shared") {
                Some("points at ../shared")
            } else if has_word(line, "issue") || has_word(line, "issues") {
                Some("speaks of an issue")
            } else {
                None
            };
            if let Some(why) = why {
                bad.push(format!("{}:{}: {why}: {line}", page.display(), n + 1));
            }
        }
    }
    assert!(bad.is_empty(), "pages a user cannot follow:\n{}", bad.join("\n"));
}

#[test]
fn every_relative_link_resolves() {
    let mut bad = Vec::new();
    let mut links = 0;
    for page in pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        let dir = page.parent().unwrap();
        for (i, _) in text.match_indices("](") {
            let rest = &text[i + 2..];
            let Some(end) = rest.find(')') else { continue };
            let target = &rest[..end];
            if target.contains("://") || target.starts_with('#') || target.starts_with("mailto:") {
                continue;
            }
            let file = target.split('#').next().unwrap();
            links += 1;
            if !dir.join(file).exists() {
                bad.push(format!("{}: ({target})", page.display()));
            }
        }
    }
    assert!(
        links > 20,
        "only {links} relative links found: is the link parser broken?"
    );
    assert!(
        bad.is_empty(),
        "links to files the repository does not have:\n{}",
        bad.join("\n")
    );
}
