//! No import cycle between the source files of a crate.
//!
//! A cycle between two files (a.rs uses b.rs, b.rs uses a.rs) means neither can be read,
//! moved or tested without the other; the layout stops showing which is the lower level.
//! This test reads every crate of the workspace as text (no compiler, no new dependency)
//! and fails listing each cycle as a chain of files, with the line that makes each step.
//!
//! What counts, per crate:
//! - Files: every `.rs` file reached from the crate root through `mod name;` (with
//!   `#[path]`), each mapped to its module path (`foo.rs` and `foo/mod.rs` are `foo`,
//!   `foo/bar.rs` is `foo::bar`); inline `mod name { .. }` blocks belong to their file.
//! - Tests do not count: items under `#[cfg(test)]` (a `mod tests { .. }` body, a test
//!   helper) are skipped, and so are the files of test modules (declared under
//!   `#[cfg(test)]`, or named `tests.rs`, `*_tests.rs`, `tests_*.rs`) and their children,
//!   because tests may reach anywhere.
//! - References: the paths of `use` declarations (nested braces, several lines, `as`,
//!   globs), and paths in code that start with `crate::`, `super::`, `self::`, a child
//!   module or a name a `use` brought in. A path resolves to the longest prefix that is a
//!   module; the item after it is looked up there, through `use` and glob re-exports, to
//!   the file that defines it (`crate::a::b::f` is file `a/b.rs` if it exists, else `a.rs`
//!   or `a/mod.rs` when `b` is an item defined or re-exported there).
//!
//! The rule for parents and children: a module's own file (`foo.rs` or `foo/mod.rs`)
//! declares, re-exports and assembles its children, and the children use the items it
//! holds for them (`super::Shared`); references between a file and its own descendants are
//! that composition, not a cycle. Every other reference, from file `a` to file `b`, is an
//! edge between the two children of their nearest common module that hold them (each
//! child standing for its file and everything below it): `stats/mc/p_int.rs` using
//! `stats/sample.rs` is the edge `stats::mc -> stats::sample`, and `night/mod.rs` using
//! `products/mod.rs` is `night -> products`. The test fails on any cycle among the
//! children of a module, which includes every cycle between two files that are not parent
//! and descendant. A `pub use child::Item;` re-export is transparent: whoever names
//! `parent::Item` depends on the child's file, not on the parent's. A `use` that names a
//! module (`use super::mc;`) is not an edge by itself; the paths through it (`mc::run`) are.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::{Path, PathBuf};

/// The crates of the workspace: display name and root file, relative to the workspace.
const CRATES: &[(&str, &str)] = &[
    ("sofipol-calib", "calib/src/lib.rs"),
    ("sofipol-pipeline", "pipeline/src/lib.rs"),
    ("sofipol-bench", "bench/src/lib.rs"),
    ("sofipol (binary)", "src/main.rs"),
];

// ---------------------------------------------------------------------------------------
// Tokens: identifiers, string literals (for `#[path = ".."]`), `::` and single characters,
// with comments, characters, lifetimes and numbers' insides dropped.

#[derive(Clone, Debug, PartialEq)]
enum Tok {
    Ident(String),
    Str(String),
    PathSep,
    Punct(char),
}

#[derive(Clone, Debug)]
struct Token {
    tok: Tok,
    line: usize,
}

fn is_ident_start(c: char) -> bool {
    c == '_' || c.is_alphabetic()
}

fn is_ident_char(c: char) -> bool {
    c == '_' || c.is_alphanumeric()
}

/// Reads a quoted string starting at the opening quote `s[i] == '"'`, with `hashes` `#`
/// after the closing quote for a raw string (escapes only count when not raw). Returns
/// the content and the index after the literal.
fn read_string(s: &[char], mut i: usize, raw: bool, hashes: usize, line: &mut usize) -> (String, usize) {
    let mut out = String::new();
    i += 1;
    while i < s.len() {
        let c = s[i];
        if c == '\n' {
            *line += 1;
        }
        if !raw && c == '\\' {
            if s.get(i + 1) == Some(&'\n') {
                *line += 1;
            }
            i += 2;
            continue;
        }
        if c == '"' && s[i + 1..].iter().take(hashes).filter(|&&h| h == '#').count() == hashes {
            return (out, i + 1 + hashes);
        }
        out.push(c);
        i += 1;
    }
    (out, i)
}

fn tokenize(src: &str) -> Vec<Token> {
    let s: Vec<char> = src.chars().collect();
    let mut out = Vec::new();
    let mut line = 1;
    let mut i = 0;
    while i < s.len() {
        let c = s[i];
        let next = s.get(i + 1).copied();
        if c == '\n' {
            line += 1;
            i += 1;
        } else if c.is_whitespace() {
            i += 1;
        } else if c == '/' && next == Some('/') {
            while i < s.len() && s[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            let mut depth = 0;
            while i < s.len() {
                if s[i] == '/' && s.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if s[i] == '*' && s.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    if s[i] == '\n' {
                        line += 1;
                    }
                    i += 1;
                }
            }
        } else if c == '"' {
            let start = line;
            let (text, end) = read_string(&s, i, false, 0, &mut line);
            out.push(Token {
                tok: Tok::Str(text),
                line: start,
            });
            i = end;
        } else if c == '\'' {
            // A character literal ('a', '\n', '\u{1F}') or a lifetime / label ('a, 'static).
            if next == Some('\\') {
                i += 3;
                while i < s.len() && s[i] != '\'' {
                    i += 1;
                }
                i += 1;
            } else if s.get(i + 2) == Some(&'\'') {
                i += 3;
            } else {
                i += 1;
                while i < s.len() && is_ident_char(s[i]) {
                    i += 1;
                }
            }
        } else if is_ident_start(c) || c.is_ascii_digit() {
            let start = i;
            while i < s.len() && is_ident_char(s[i]) {
                i += 1;
            }
            let word: String = s[start..i].iter().collect();
            let prefix = matches!(word.as_str(), "r" | "b" | "br" | "c" | "cr");
            if prefix && s.get(i) == Some(&'"') {
                let raw = word.contains('r');
                let start_line = line;
                let (text, end) = read_string(&s, i, raw, 0, &mut line);
                out.push(Token {
                    tok: Tok::Str(text),
                    line: start_line,
                });
                i = end;
            } else if prefix && word.contains('r') && s.get(i) == Some(&'#') {
                let mut hashes = 0;
                while s.get(i + hashes) == Some(&'#') {
                    hashes += 1;
                }
                if s.get(i + hashes) == Some(&'"') {
                    let start_line = line;
                    let (text, end) = read_string(&s, i + hashes, true, hashes, &mut line);
                    out.push(Token {
                        tok: Tok::Str(text),
                        line: start_line,
                    });
                    i = end;
                } else {
                    // A raw identifier, r#type.
                    i += hashes;
                    let id_start = i;
                    while i < s.len() && is_ident_char(s[i]) {
                        i += 1;
                    }
                    let id: String = s[id_start..i].iter().collect();
                    out.push(Token {
                        tok: Tok::Ident(id),
                        line,
                    });
                }
            } else if prefix && word == "b" && s.get(i) == Some(&'\'') {
                // A byte literal, b'x' or b'\n'.
                i += if s.get(i + 1) == Some(&'\\') { 3 } else { 2 };
                while i < s.len() && s[i] != '\'' {
                    i += 1;
                }
                i += 1;
            } else if !c.is_ascii_digit() {
                out.push(Token {
                    tok: Tok::Ident(word),
                    line,
                });
            }
        } else if c == ':' && next == Some(':') {
            out.push(Token {
                tok: Tok::PathSep,
                line,
            });
            i += 2;
        } else {
            out.push(Token {
                tok: Tok::Punct(c),
                line,
            });
            i += 1;
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// One file read: its modules (the file's own and its inline ones), their imports and
// definitions, the module files it declares, and the paths its code names.

type ModPath = Vec<String>;

/// One binding of a `use` declaration: `use a::b::{c as d, e::*};` gives `a::b::c`
/// bound to `d` and the glob `a::b::e::*`.
#[derive(Clone, Debug)]
struct Import {
    path: Vec<String>,
    /// The name it binds (`None` for a glob).
    binding: Option<String>,
    public: bool,
    line: usize,
}

#[derive(Default, Debug)]
struct ModScan {
    defs: BTreeSet<String>,
    children: BTreeSet<String>,
    imports: Vec<Import>,
}

#[derive(Debug)]
struct ModDecl {
    /// The module in which `mod name;` stands (the file's, or one of its inline modules).
    parent: ModPath,
    name: String,
    path_attr: Option<String>,
    test: bool,
}

#[derive(Debug)]
struct CodePath {
    module: ModPath,
    path: Vec<String>,
    line: usize,
}

#[derive(Default, Debug)]
struct FileScan {
    modules: BTreeMap<ModPath, ModScan>,
    decls: Vec<ModDecl>,
    code_paths: Vec<CodePath>,
    /// Identifiers in code, outside `use` declarations: whether the file names an item it
    /// re-exports.
    code_idents: BTreeSet<String>,
    /// `#![cfg(test)]` at the top.
    test_only: bool,
}

fn ident(t: Option<&Token>) -> Option<&str> {
    match t.map(|t| &t.tok) {
        Some(Tok::Ident(s)) => Some(s),
        _ => None,
    }
}

fn punct(t: Option<&Token>, c: char) -> bool {
    t.is_some_and(|t| t.tok == Tok::Punct(c))
}

fn is_open(t: &Token) -> bool {
    matches!(t.tok, Tok::Punct('(' | '[' | '{'))
}

fn is_close(t: &Token) -> bool {
    matches!(t.tok, Tok::Punct(')' | ']' | '}'))
}

/// Index after the bracket group that opens at `toks[i]`.
fn skip_group(toks: &[Token], mut i: usize) -> usize {
    let mut depth = 0usize;
    while i < toks.len() {
        if is_open(&toks[i]) {
            depth += 1;
        } else if is_close(&toks[i]) {
            depth -= 1;
            if depth == 0 {
                return i + 1;
            }
        }
        i += 1;
    }
    i
}

/// Index after the item that starts at `toks[i]`: up to a `;` or the closing `}` of its
/// body at its own level, or before a bracket that closes the enclosing group.
fn skip_item(toks: &[Token], mut i: usize) -> usize {
    let mut depth = 0usize;
    while i < toks.len() {
        let t = &toks[i];
        if is_open(t) {
            depth += 1;
        } else if is_close(t) {
            if depth == 0 {
                return i;
            }
            depth -= 1;
            if depth == 0 && t.tok == Tok::Punct('}') {
                return i + 1;
            }
        } else if depth == 0 && t.tok == Tok::Punct(';') {
            return i + 1;
        }
        i += 1;
    }
    i
}

/// Whether the attribute tokens (between `[` and `]`) are `cfg(...)` true only in tests.
fn is_cfg_test(attr: &[Token]) -> bool {
    ident(attr.first()) == Some("cfg")
        && attr.iter().any(|t| t.tok == Tok::Ident("test".into()))
        && !attr.iter().any(|t| t.tok == Tok::Ident("not".into()))
}

/// Parses a use tree at `toks[*i]` into its bindings, each with the full path written.
fn parse_use_tree(toks: &[Token], i: &mut usize, prefix: Vec<String>, out: &mut Vec<(Vec<String>, Option<String>)>) {
    let mut path = prefix;
    loop {
        match toks.get(*i).map(|t| &t.tok) {
            Some(Tok::Ident(s)) => {
                path.push(s.clone());
                *i += 1;
                if toks.get(*i).map(|t| &t.tok) == Some(&Tok::PathSep) {
                    *i += 1;
                } else {
                    break;
                }
            }
            Some(Tok::PathSep) => *i += 1, // a leading `::`: an external crate, kept as written
            Some(Tok::Punct('*')) => {
                *i += 1;
                out.push((path, None));
                return;
            }
            Some(Tok::Punct('{')) => {
                *i += 1;
                while *i < toks.len() && !punct(toks.get(*i), '}') {
                    parse_use_tree(toks, i, path.clone(), out);
                    if punct(toks.get(*i), ',') {
                        *i += 1;
                    }
                }
                *i += 1;
                return;
            }
            _ => break,
        }
    }
    if path.last().map(String::as_str) == Some("self") {
        path.pop();
    }
    let mut binding = path.last().cloned();
    if ident(toks.get(*i)) == Some("as") {
        binding = ident(toks.get(*i + 1)).map(str::to_string);
        *i += 2;
    }
    if !path.is_empty() {
        out.push((path, binding));
    }
}

/// Whether the `use` at `toks[i]` has a `pub` or `pub(...)` visibility.
fn is_pub_before(toks: &[Token], i: usize) -> bool {
    if i == 0 {
        return false;
    }
    if ident(toks.get(i - 1)) == Some("pub") {
        return true;
    }
    if punct(toks.get(i - 1), ')') {
        let mut j = i - 1;
        while j > 0 && !punct(toks.get(j), '(') {
            j -= 1;
        }
        return j > 0 && ident(toks.get(j - 1)) == Some("pub");
    }
    false
}

const DEF_KEYWORDS: &[&str] = &["fn", "struct", "enum", "trait", "type", "const", "static", "union"];

fn scan_file(src: &str, module: &ModPath) -> FileScan {
    let toks = tokenize(src);
    let mut scan = FileScan::default();
    scan.modules.entry(module.clone()).or_default();
    // The current module: the file's own, plus the inline modules we are inside.
    let mut current = module.clone();
    // One entry per open bracket: whether it is the body of an inline module.
    let mut groups: Vec<bool> = Vec::new();
    let mut pending_attrs: Vec<Vec<Token>> = Vec::new();
    let mut i = 0;
    while i < toks.len() {
        let t = &toks[i];
        // Attributes: `#[..]` collected for the next item, `#![cfg(test)]` on the file.
        if t.tok == Tok::Punct('#') {
            let inner = punct(toks.get(i + 1), '!');
            let open = if inner { i + 2 } else { i + 1 };
            if punct(toks.get(open), '[') {
                let end = skip_group(&toks, open);
                let attr = toks[open + 1..end - 1].to_vec();
                if inner {
                    if is_cfg_test(&attr) && groups.is_empty() {
                        scan.test_only = true;
                    }
                } else {
                    pending_attrs.push(attr);
                }
                i = end;
                continue;
            }
        }
        // A visibility belongs to the item after it: keep its attributes for that item.
        if ident(Some(t)) == Some("pub") {
            i += 1;
            if punct(toks.get(i), '(') {
                i = skip_group(&toks, i);
            }
            continue;
        }
        let attrs = std::mem::take(&mut pending_attrs);
        let test_item = attrs.iter().any(|a| is_cfg_test(a));
        let name = ident(Some(t));
        if name == Some("mod") {
            if let Some(child) = ident(toks.get(i + 1)) {
                let child = child.to_string();
                let path_attr = attrs.iter().find(|a| ident(a.first()) == Some("path")).and_then(|a| {
                    a.iter().find_map(|t| match &t.tok {
                        Tok::Str(s) => Some(s.clone()),
                        _ => None,
                    })
                });
                if punct(toks.get(i + 2), ';') {
                    if !test_item {
                        scan.modules.get_mut(&current).unwrap().children.insert(child.clone());
                    }
                    scan.decls.push(ModDecl {
                        parent: current.clone(),
                        name: child,
                        path_attr,
                        test: test_item,
                    });
                    i += 3;
                    continue;
                }
                if punct(toks.get(i + 2), '{') && !test_item {
                    scan.modules.get_mut(&current).unwrap().children.insert(child.clone());
                    current.push(child);
                    scan.modules.entry(current.clone()).or_default();
                    groups.push(true);
                    i += 3;
                    continue;
                }
            }
        }
        if test_item {
            i = skip_item(&toks, i);
            continue;
        }
        if name == Some("use") {
            let public = is_pub_before(&toks, i);
            let line = t.line;
            let mut j = i + 1;
            let mut bindings = Vec::new();
            parse_use_tree(&toks, &mut j, Vec::new(), &mut bindings);
            let m = scan.modules.get_mut(&current).unwrap();
            for (path, binding) in bindings {
                m.imports.push(Import {
                    path,
                    binding,
                    public,
                    line,
                });
            }
            i = skip_item(&toks, i);
            continue;
        }
        if let Some(word) = name {
            if DEF_KEYWORDS.contains(&word) || word == "macro_rules" {
                let at = if word == "macro_rules" { i + 2 } else { i + 1 };
                if let Some(def) = ident(toks.get(at)) {
                    scan.modules.get_mut(&current).unwrap().defs.insert(def.to_string());
                }
            }
            scan.code_idents.insert(word.to_string());
            if toks.get(i + 1).map(|t| &t.tok) == Some(&Tok::PathSep) {
                let mut path = vec![word.to_string()];
                let mut j = i + 1;
                while toks.get(j).map(|t| &t.tok) == Some(&Tok::PathSep) {
                    match ident(toks.get(j + 1)) {
                        Some(seg) => {
                            path.push(seg.to_string());
                            scan.code_idents.insert(seg.to_string());
                            j += 2;
                        }
                        None => break,
                    }
                }
                scan.code_paths.push(CodePath {
                    module: current.clone(),
                    path,
                    line: t.line,
                });
                i = j;
                continue;
            }
        }
        if is_open(t) {
            groups.push(false);
        } else if is_close(t) && groups.pop() == Some(true) {
            current.pop();
        }
        i += 1;
    }
    scan
}

// ---------------------------------------------------------------------------------------
// A crate: its files from the root down, and the resolution of paths to files.

struct SourceFile {
    /// Relative to the workspace, for messages.
    path: PathBuf,
    /// Its module path in the crate (`stats::mc` for `stats/mc/mod.rs`).
    module: ModPath,
    scan: FileScan,
}

struct Crate {
    files: Vec<SourceFile>,
    /// Every module (files' and inline ones) -> index of its file.
    module_file: BTreeMap<ModPath, usize>,
    /// Test files reached (skipped).
    test_files: Vec<PathBuf>,
}

fn is_test_file_name(path: &Path) -> bool {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    stem == "tests" || stem.ends_with("_tests") || stem.starts_with("tests_")
}

/// The directory where `mod x;` in `file` (not inside an inline module) looks for `x`.
fn module_dir(file: &Path) -> PathBuf {
    let dir = file.parent().unwrap().to_path_buf();
    match file.file_name().and_then(|n| n.to_str()) {
        Some("mod.rs" | "lib.rs" | "main.rs") => dir,
        _ => dir.join(file.file_stem().unwrap()),
    }
}

fn load_crate(workspace: &Path, root: &Path) -> Crate {
    let mut krate = Crate {
        files: Vec::new(),
        module_file: BTreeMap::new(),
        test_files: Vec::new(),
    };
    // (file path, module path, is test)
    let mut queue: VecDeque<(PathBuf, ModPath, bool)> = VecDeque::from([(root.to_path_buf(), Vec::new(), false)]);
    while let Some((path, module, test)) = queue.pop_front() {
        let full = workspace.join(&path);
        let src = std::fs::read_to_string(&full).unwrap_or_else(|e| panic!("{}: {e}", full.display()));
        let scan = scan_file(&src, &module);
        let test = test || scan.test_only || is_test_file_name(&path);
        for decl in &scan.decls {
            let inline = &decl.parent[module.len()..];
            let candidates = match &decl.path_attr {
                Some(p) if inline.is_empty() => vec![path.parent().unwrap().join(p)],
                Some(p) => vec![inline.iter().fold(module_dir(&path), |d, m| d.join(m)).join(p)],
                None => {
                    let dir = inline.iter().fold(module_dir(&path), |d, m| d.join(m));
                    vec![
                        dir.join(format!("{}.rs", decl.name)),
                        dir.join(&decl.name).join("mod.rs"),
                    ]
                }
            };
            let found: Vec<_> = candidates.into_iter().filter(|c| workspace.join(c).is_file()).collect();
            assert_eq!(
                found.len(),
                1,
                "{}: `mod {};` has files {found:?}",
                path.display(),
                decl.name
            );
            let mut child = decl.parent.clone();
            child.push(decl.name.clone());
            queue.push_back((found[0].clone(), child, test || decl.test));
        }
        if test {
            krate.test_files.push(path);
            continue;
        }
        let index = krate.files.len();
        for m in scan.modules.keys() {
            krate.module_file.insert(m.clone(), index);
        }
        krate.files.push(SourceFile { path, module, scan });
    }
    krate
}

impl Crate {
    fn module(&self, m: &ModPath) -> Option<&ModScan> {
        self.module_file.get(m).and_then(|&f| self.files[f].scan.modules.get(m))
    }

    /// The absolute path (from the crate root) of `path` as written in module `m`, or
    /// `None` when it leaves the crate (std, another crate) or names a local item.
    fn absolute(&self, m: &ModPath, path: &[String], depth: usize) -> Option<Vec<String>> {
        let first = path.first()?.as_str();
        let mut base: Vec<String>;
        let mut rest = path;
        match first {
            "crate" => {
                base = Vec::new();
                rest = &path[1..];
            }
            "self" => {
                base = m.clone();
                rest = &path[1..];
            }
            "super" => {
                base = m.clone();
                while rest.first().map(String::as_str) == Some("super") {
                    base.pop()?;
                    rest = &rest[1..];
                }
                if rest.first().map(String::as_str) == Some("self") {
                    rest = &rest[1..];
                }
            }
            _ => {
                let scope = self.module(m)?;
                if scope.children.contains(first) {
                    base = m.clone();
                } else if depth < 8 {
                    let import = scope.imports.iter().find(|i| i.binding.as_deref() == Some(first))?;
                    base = self.absolute(m, &import.path, depth + 1)?;
                    rest = &path[1..];
                } else {
                    return None;
                }
            }
        }
        base.extend(rest.iter().cloned());
        Some(base)
    }

    /// The module whose file defines what the absolute `path` names (`None` outside the
    /// crate), following `use` bindings and glob imports of the module it goes through.
    fn resolve(&self, path: &[String], depth: usize) -> Option<ModPath> {
        let split = (0..=path.len())
            .rev()
            .find(|&k| self.module_file.contains_key(&path[..k]))?;
        let module = path[..split].to_vec();
        let Some(item) = path.get(split) else {
            return Some(module);
        };
        let scope = self.module(&module)?;
        if scope.defs.contains(item) || depth >= 8 {
            return Some(module);
        }
        if let Some(import) = scope.imports.iter().find(|i| i.binding.as_ref() == Some(item)) {
            let mut target = self.absolute(&module, &import.path, depth + 1)?;
            target.extend(path[split + 1..].iter().cloned());
            return self.resolve(&target, depth + 1);
        }
        for glob in scope.imports.iter().filter(|i| i.binding.is_none()) {
            let Some(mut target) = self.absolute(&module, &glob.path, depth + 1) else {
                continue;
            };
            target.extend(path[split..].iter().cloned());
            if let Some(found) = self.resolve(&target, depth + 1) {
                if self.module(&found).is_some_and(|s| s.defs.contains(item)) {
                    return Some(found);
                }
            }
        }
        Some(module)
    }

    /// File-to-file edges, each with the first reference that makes it (line, path).
    fn edges(&self) -> BTreeMap<(usize, usize), (usize, String)> {
        let mut edges = BTreeMap::new();
        for (from, file) in self.files.iter().enumerate() {
            let mut add = |m: &ModPath, path: &[String], line: usize, module_too: bool| {
                let Some(abs) = self.absolute(m, path, 0) else { return };
                let Some(target) = self.resolve(&abs, 0) else { return };
                // A path that names a module itself (`use super::mc;`) is not a use of it.
                if !module_too && target == abs {
                    return;
                }
                let to = self.module_file[&target];
                if to != from {
                    edges.entry((from, to)).or_insert((line, path.join("::")));
                }
            };
            for (m, scope) in &file.scan.modules {
                for import in &scope.imports {
                    let mut path = import.path.clone();
                    if import.binding.is_none() {
                        // A glob uses the module it opens.
                        if import.public {
                            continue;
                        }
                        add(m, &path, import.line, true);
                        continue;
                    }
                    // A re-export is a use only if the file's own code names the item.
                    if import.public && !file.scan.code_idents.contains(import.binding.as_ref().unwrap()) {
                        continue;
                    }
                    if path.last().map(String::as_str) == Some("self") {
                        path.pop();
                    }
                    add(m, &path, import.line, false);
                }
            }
            for code in &file.scan.code_paths {
                add(&code.module, &code.path, code.line, false);
            }
        }
        edges
    }
}

// ---------------------------------------------------------------------------------------
// Strongly connected components (Tarjan) and a shortest cycle through a file.

fn strongly_connected(n: usize, adj: &[Vec<usize>]) -> Vec<Vec<usize>> {
    struct State<'a> {
        adj: &'a [Vec<usize>],
        index: Vec<Option<usize>>,
        low: Vec<usize>,
        on_stack: Vec<bool>,
        stack: Vec<usize>,
        next: usize,
        out: Vec<Vec<usize>>,
    }
    fn visit(s: &mut State, v: usize) {
        s.index[v] = Some(s.next);
        s.low[v] = s.next;
        s.next += 1;
        s.stack.push(v);
        s.on_stack[v] = true;
        for k in 0..s.adj[v].len() {
            let w = s.adj[v][k];
            match s.index[w] {
                None => {
                    visit(s, w);
                    s.low[v] = s.low[v].min(s.low[w]);
                }
                Some(iw) if s.on_stack[w] => s.low[v] = s.low[v].min(iw),
                _ => {}
            }
        }
        if Some(s.low[v]) == s.index[v] {
            let mut component = Vec::new();
            loop {
                let w = s.stack.pop().unwrap();
                s.on_stack[w] = false;
                component.push(w);
                if w == v {
                    break;
                }
            }
            component.sort();
            s.out.push(component);
        }
    }
    let mut s = State {
        adj,
        index: vec![None; n],
        low: vec![0; n],
        on_stack: vec![false; n],
        stack: Vec::new(),
        next: 0,
        out: Vec::new(),
    };
    for v in 0..n {
        if s.index[v].is_none() {
            visit(&mut s, v);
        }
    }
    s.out
}

/// The shortest cycle through `start` inside `component` (breadth first).
fn shortest_cycle(start: usize, component: &[usize], adj: &[Vec<usize>]) -> Vec<usize> {
    let mut previous: BTreeMap<usize, usize> = BTreeMap::new();
    let mut queue = VecDeque::from([start]);
    while let Some(v) = queue.pop_front() {
        for &w in &adj[v] {
            if !component.contains(&w) {
                continue;
            }
            if w == start {
                let mut chain = vec![v];
                while let Some(&p) = previous.get(chain.last().unwrap()) {
                    chain.push(p);
                }
                chain.reverse();
                return chain;
            }
            if w != start && !previous.contains_key(&w) {
                previous.insert(w, v);
                queue.push_back(w);
            }
        }
    }
    vec![start]
}

/// Every cycle of a crate, as text; and how much was read (files, file-to-file edges,
/// edges between sibling modules, test files).
///
/// A reference from file `a` to file `b` that are not parent and descendant is an edge
/// between the two children of their nearest common module that hold them: `stats::mc::p_int`
/// using `stats::sample` is the edge `stats::mc -> stats::sample`. Cycles are looked for
/// among the children of each module.
fn crate_cycles(workspace: &Path, root: &Path) -> (Vec<String>, usize, usize, usize, usize) {
    let krate = load_crate(workspace, root);
    let edges = krate.edges();
    // parent module -> (child -> child) -> the first file-level reference that makes it
    let mut levels: BTreeMap<ModPath, BTreeMap<(ModPath, ModPath), String>> = BTreeMap::new();
    for (&(a, b), (line, path)) in &edges {
        let (ma, mb) = (&krate.files[a].module, &krate.files[b].module);
        let common = ma.iter().zip(mb.iter()).take_while(|(x, y)| x == y).count();
        if common == ma.len() || common == mb.len() {
            continue; // a parent and its own descendant
        }
        let evidence = format!("{}:{line} `{path}`", krate.files[a].path.display());
        levels
            .entry(ma[..common].to_vec())
            .or_default()
            .entry((ma[..=common].to_vec(), mb[..=common].to_vec()))
            .or_insert(evidence);
    }
    let sibling_edges = levels.values().map(BTreeMap::len).sum();
    // A child module's name in messages: its file, and "and below" when it has children.
    let describe = |m: &ModPath| {
        let file = &krate.files[krate.module_file[m]];
        let below = krate
            .files
            .iter()
            .any(|f| f.module.len() > m.len() && f.module.starts_with(m));
        format!("{}{}", file.path.display(), if below { " (and below)" } else { "" })
    };
    let mut cycles = Vec::new();
    for level in levels.values() {
        let nodes: Vec<&ModPath> = level
            .keys()
            .flat_map(|(x, y)| [x, y])
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        let index = |m: &ModPath| nodes.iter().position(|n| *n == m).unwrap();
        let mut adj = vec![Vec::new(); nodes.len()];
        for (x, y) in level.keys() {
            adj[index(x)].push(index(y));
        }
        for component in strongly_connected(nodes.len(), &adj)
            .into_iter()
            .filter(|c| c.len() > 1)
        {
            let names: Vec<_> = component.iter().map(|&v| describe(nodes[v])).collect();
            let mut text = format!("cycle among {}:", names.join(", "));
            let mut seen = BTreeSet::new();
            for &start in &component {
                let chain = shortest_cycle(start, &component, &adj);
                let mut key = chain.clone();
                key.sort();
                if !seen.insert(key) {
                    continue;
                }
                text.push_str("\n   ");
                for (k, &x) in chain.iter().enumerate() {
                    let y = chain[(k + 1) % chain.len()];
                    text.push_str(&format!(" {} ->", level[&(nodes[x].clone(), nodes[y].clone())]));
                }
                text.push_str(&format!(" {}", describe(nodes[chain[0]])));
            }
            cycles.push(text);
        }
    }
    (
        cycles,
        krate.files.len(),
        edges.len(),
        sibling_edges,
        krate.test_files.len(),
    )
}

/// Every `.rs` file under `dir`.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }
    out
}

#[test]
fn no_import_cycle_between_files() {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut failures = Vec::new();
    for &(name, root) in CRATES {
        let (cycles, files, edges, siblings, tests) = crate_cycles(workspace, Path::new(root));
        println!(
            "{name}: {files} files ({tests} test files skipped), {edges} edges between files, {siblings} between \
             sibling modules, {} cycles",
            cycles.len()
        );
        // Every file under src/ was read: a file the walk from the root missed would hide
        // its references.
        let krate = load_crate(workspace, Path::new(root));
        let reached: BTreeSet<PathBuf> = krate
            .files
            .iter()
            .map(|f| f.path.clone())
            .chain(krate.test_files.iter().cloned())
            .collect();
        let src_dir = Path::new(root).parent().unwrap();
        for file in rust_files(&workspace.join(src_dir)) {
            let relative = file.strip_prefix(workspace).unwrap().to_path_buf();
            assert!(
                reached.contains(&relative),
                "{} is not reached from {root}",
                relative.display()
            );
        }
        failures.extend(cycles.into_iter().map(|c| format!("{name}: {c}")));
    }
    assert!(
        failures.is_empty(),
        "import cycles between files:\n{}",
        failures.join("\n")
    );
}

// ---------------------------------------------------------------------------------------
// The finder itself, on small crates written to a temporary directory.

fn cycles_of(files: &[(&str, &str)]) -> Vec<String> {
    let dir = tempfile::tempdir().unwrap();
    for (path, text) in files {
        let full = dir.path().join(path);
        std::fs::create_dir_all(full.parent().unwrap()).unwrap();
        std::fs::write(full, text).unwrap();
    }
    crate_cycles(dir.path(), Path::new("src/lib.rs")).0
}

#[test]
fn tokens_skip_comments_strings_and_lifetimes() {
    let toks = tokenize("a /* crate::x /* nested */ */ 'b' 'c: r#\"crate::y\"# b'\\'' // crate::z\n d::e");
    let words: Vec<_> = toks.iter().filter_map(|t| ident(Some(t))).collect();
    assert_eq!(words, ["a", "d", "e"]);
    assert_eq!(toks.last().unwrap().line, 2);
}

#[test]
fn use_trees_expand_to_every_binding() {
    let toks = tokenize("crate::a::{b::{self, C as D}, e::*,\n f};");
    let mut out = Vec::new();
    parse_use_tree(&toks, &mut 0, Vec::new(), &mut out);
    let text: Vec<_> = out.iter().map(|(p, b)| format!("{}={b:?}", p.join("::"))).collect();
    assert_eq!(
        text,
        [
            "crate::a::b=Some(\"b\")",
            "crate::a::b::C=Some(\"D\")",
            "crate::a::e=None",
            "crate::a::f=Some(\"f\")"
        ]
    );
}

#[test]
fn a_cycle_between_siblings_is_found_through_a_reexport() {
    let cycles = cycles_of(&[
        ("src/lib.rs", "mod a; mod b; pub use b::Thing;"),
        ("src/a.rs", "pub fn f() -> crate::Thing { todo!() }"),
        ("src/b.rs", "pub struct Thing;\nfn g() {\n    crate::a::f();\n}"),
    ]);
    assert_eq!(cycles.len(), 1, "{cycles:?}");
    assert!(cycles[0].contains("src/b.rs:3 `crate::a::f`"), "{cycles:?}");
}

#[test]
fn a_parent_declaring_and_reexporting_its_child_is_no_cycle() {
    let cycles = cycles_of(&[
        ("src/lib.rs", "mod m;"),
        (
            "src/m/mod.rs",
            "mod child;\npub use child::run;\npub struct Shared;\n#[cfg(test)]\nmod tests;",
        ),
        ("src/m/child.rs", "use super::Shared;\npub fn run(_: Shared) {}"),
        ("src/m/tests.rs", "use super::child::run;"),
    ]);
    assert!(cycles.is_empty(), "{cycles:?}");
}

#[test]
fn a_parent_assembling_its_children_from_its_own_types_is_no_cycle() {
    let cycles = cycles_of(&[
        ("src/lib.rs", "mod m;"),
        (
            "src/m.rs",
            "mod child;\npub struct Shared;\nfn go() { child::run(Shared) }",
        ),
        ("src/m/child.rs", "pub fn run(_: super::Shared) {}"),
    ]);
    assert!(cycles.is_empty(), "{cycles:?}");
}

#[test]
fn a_cycle_through_a_child_of_a_sibling_is_found() {
    // errors -> mc (its mod.rs) and mc::p_int -> sample -> errors: the modules errors, mc
    // and sample of `stats` use each other in a ring.
    let cycles = cycles_of(&[
        ("src/lib.rs", "mod stats;"),
        ("src/stats/mod.rs", "mod errors;\nmod mc;\nmod sample;"),
        (
            "src/stats/errors.rs",
            "use super::mc::CHUNK;\npub fn is_large() -> bool { CHUNK > 1 }",
        ),
        ("src/stats/mc/mod.rs", "mod p_int;\npub const CHUNK: usize = 2;"),
        ("src/stats/mc/p_int.rs", "fn f() { super::super::sample::g() }"),
        ("src/stats/sample.rs", "pub fn g() { super::errors::is_large(); }"),
    ]);
    assert_eq!(cycles.len(), 1, "{cycles:?}");
    let text = &cycles[0];
    assert!(text.contains("src/stats/mc/mod.rs (and below)"), "{text}");
    assert!(
        text.contains("src/stats/mc/p_int.rs:1 `super::super::sample::g`"),
        "{text}"
    );
}

#[test]
fn test_code_does_not_count() {
    let cycles = cycles_of(&[
        ("src/lib.rs", "mod a; mod b;"),
        ("src/a.rs", "pub fn f() { crate::b::g() }"),
        (
            "src/b.rs",
            "pub fn g() {}\n#[cfg(test)]\nfn helper() { crate::a::f() }\n#[cfg(test)]\nmod tests { use crate::a::f; }",
        ),
    ]);
    assert!(cycles.is_empty(), "{cycles:?}");
}
