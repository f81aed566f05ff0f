//! The set-of-frames file: a plain-text list of the frames of a run, one per line, with
//! each frame's role, instead of a directory to search (docs/frame-format.md, "A set of
//! frames as a file").
//!
//! ```text
//! # comment (a whole line, or the rest of a line after whitespace)
//! raw/SOFI.2003-01-17T01:02:03.fits   science
//! raw/SOFI.2003-01-17T01:20:00.fits   science   angle=45   target=HK_Tau
//! "dir with space/std1.fits"          standard
//! flats/dome_on_1.fits                flat
//! darks/dark_1.fits                   dark
//! ```
//!
//! A line is a path (double-quoted when it holds whitespace or starts with `#` or `"`), a
//! role ([`FrameRole`]) and optional `key=value` settings: `angle` (the modulation angle in
//! degrees: SOFI's POSANG, used in place of the header's) and `target` (the target name,
//! in place of the header's OBJECT). Relative paths are relative to the file's directory.
//! Every problem is an error naming the file, the line, the key and the value: a missing
//! file, a path listed twice (also by another spelling of the same file), an unknown role
//! or key, an angle that is not a finite number within one turn ([`MAX_ANGLE_DEG`]), a
//! line that is not UTF-8 or is longer than [`MAX_LINE_BYTES`], a file longer than
//! [`MAX_FILE_BYTES`] (refused before it is held in memory).
use std::path::{Path, PathBuf};

/// The longest line read, bytes.
pub const MAX_LINE_BYTES: usize = 4096;

/// The longest set-of-frames file read, bytes (some 200 000 lines of frames): a larger
/// file (or a device that never ends) is refused before it is held in memory.
pub const MAX_FILE_BYTES: u64 = 64 << 20;

/// The largest modulation angle a line may give, deg (in either sign): an instrument
/// angle, a plate angle or an analyzer angle lies within one turn.
pub const MAX_ANGLE_DEG: f64 = 360.0;

/// The extension of the set-of-frames file the night writes beside its catalog.
pub const EXTENSION: &str = "frames";

/// What a listed frame is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameRole {
    /// A polarimetric science frame (its header must still describe one: POSANG, offsets,
    /// the Wollaston...); its sequence is reduced as a target even when the header says
    /// standard (DPR TYPE 'STD').
    Science,
    /// A polarimetric standard star's frame: its sequence goes to the calibration.
    Standard,
    /// A dome flat (lamp on or off, read from the header's lamp keyword).
    Flat,
    /// A dark: listed, not used (the SOFI reduction subtracts the sky, not a dark).
    Dark,
    /// A sky frame: listed, not used (the SOFI reduction measures the sky around each star).
    Sky,
}

/// The roles' spellings.
pub const ROLE_SPELLINGS: &str = "science, standard, flat, dark or sky";

impl FrameRole {
    /// The spelling in the file.
    pub fn name(self) -> &'static str {
        match self {
            FrameRole::Science => "science",
            FrameRole::Standard => "standard",
            FrameRole::Flat => "flat",
            FrameRole::Dark => "dark",
            FrameRole::Sky => "sky",
        }
    }

    fn parse(s: &str) -> Option<FrameRole> {
        use FrameRole::*;
        [Science, Standard, Flat, Dark, Sky].into_iter().find(|r| r.name() == s)
    }
}

/// One listed frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ListedFrame {
    /// The path, resolved against the file's directory.
    pub path: PathBuf,
    /// 1-based line number in the file.
    pub line: usize,
    /// Its role.
    pub role: FrameRole,
    /// `angle=`: the modulation angle, deg, in place of the header's.
    pub angle_deg: Option<f64>,
    /// `target=`: the target name, in place of the header's.
    pub target: Option<String>,
}

/// A parsed set-of-frames file.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameList {
    /// The file read.
    pub file: PathBuf,
    /// Its frames, in file order.
    pub frames: Vec<ListedFrame>,
}

/// A problem in a set-of-frames file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}{}: {key} = {value}: {reason}", file.display(), line.map(|l| format!(":{l}")).unwrap_or_default())]
pub struct FrameListError {
    /// The file.
    pub file: PathBuf,
    /// 1-based line, when the problem is on one.
    pub line: Option<usize>,
    /// What is wrong: `path`, `role`, `angle`, `target`, the key given, or `line`.
    pub key: String,
    /// The value found (quoted, control characters escaped, cut at 80 characters).
    pub value: String,
    /// Why.
    pub reason: String,
}

fn shown(v: &str) -> String {
    let cut: String = v.chars().take(80).collect();
    let more = if v.chars().count() > 80 { "..." } else { "" };
    format!("{cut:?}{more}")
}

/// Whether `path` is to be read as a set-of-frames file: an existing regular file whose
/// name is not a FITS name ([`crate::scan::is_fits_name`]).
pub fn is_frame_list(path: &Path) -> bool {
    path.is_file() && !crate::scan::is_fits_name(path)
}

/// Read and check a set-of-frames file.
pub fn read(file: &Path) -> Result<FrameList, FrameListError> {
    read_limited(file, MAX_FILE_BYTES)
}

/// [`read`] refusing a file longer than `max_bytes`.
fn read_limited(file: &Path, max_bytes: u64) -> Result<FrameList, FrameListError> {
    let err = |line: Option<usize>, key: &str, value: String, reason: String| FrameListError {
        file: file.to_path_buf(),
        line,
        key: key.into(),
        value,
        reason,
    };
    let shown_file = || shown(&file.display().to_string());
    let mut bytes = Vec::new();
    {
        use std::io::Read;
        let f = std::fs::File::open(file).map_err(|e| err(None, "file", shown_file(), e.to_string()))?;
        f.take(max_bytes + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| err(None, "file", shown_file(), e.to_string()))?;
    }
    if bytes.len() as u64 > max_bytes {
        return Err(err(
            None,
            "file",
            shown_file(),
            format!("longer than the {max_bytes} bytes a set-of-frames file may have"),
        ));
    }
    let base = file.parent().map(Path::to_path_buf).unwrap_or_default();
    parse(&bytes, file, &base)
}

/// Parse the bytes of a set-of-frames file `file` (named in errors), relative paths
/// resolved against `base`. Checks that every listed file exists and is listed once.
pub fn parse(bytes: &[u8], file: &Path, base: &Path) -> Result<FrameList, FrameListError> {
    let err = |line: usize, key: &str, value: &str, reason: String| FrameListError {
        file: file.to_path_buf(),
        line: Some(line),
        key: key.into(),
        value: shown(value),
        reason,
    };
    let mut frames: Vec<ListedFrame> = Vec::new();
    let mut seen: std::collections::HashMap<PathBuf, usize> = std::collections::HashMap::new();
    for (i, raw) in bytes.split(|&b| b == b'\n').enumerate() {
        let n = i + 1;
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        if raw.len() > MAX_LINE_BYTES {
            let start = String::from_utf8_lossy(&raw[..raw.len().min(40)]).into_owned();
            return Err(err(
                n,
                "line",
                &start,
                format!(
                    "{} bytes, longer than the {MAX_LINE_BYTES} bytes a line may have",
                    raw.len()
                ),
            ));
        }
        let text = std::str::from_utf8(raw).map_err(|e| {
            err(
                n,
                "line",
                &String::from_utf8_lossy(raw),
                format!("not UTF-8 (invalid byte at column {})", e.valid_up_to() + 1),
            )
        })?;
        let tokens = tokenize(text).map_err(|(v, why)| err(n, "path", &v, why))?;
        let Some((path_text, rest)) = tokens.split_first() else {
            continue;
        };
        let Some((role_text, settings)) = rest.split_first() else {
            return Err(err(
                n,
                "role",
                "",
                format!("missing after the path {}: one of {ROLE_SPELLINGS}", shown(path_text)),
            ));
        };
        let role = FrameRole::parse(role_text)
            .ok_or_else(|| err(n, "role", role_text, format!("unknown role: must be {ROLE_SPELLINGS}")))?;
        let (mut angle_deg, mut target) = (None, None);
        for s in settings {
            let Some((k, v)) = s.split_once('=') else {
                return Err(err(n, s, "", "not key=value (keys: angle, target)".into()));
            };
            match k {
                "angle" => {
                    if angle_deg.is_some() {
                        return Err(err(n, k, v, "given twice on the line".into()));
                    }
                    let a: f64 = v
                        .parse()
                        .map_err(|_| err(n, k, v, "not a number (the modulation angle in degrees)".into()))?;
                    if !a.is_finite() {
                        return Err(err(n, k, v, "not a finite angle".into()));
                    }
                    if a.abs() > MAX_ANGLE_DEG {
                        return Err(err(
                            n,
                            k,
                            v,
                            format!("outside -{MAX_ANGLE_DEG}..{MAX_ANGLE_DEG} deg (one turn)"),
                        ));
                    }
                    angle_deg = Some(a);
                }
                "target" => {
                    if target.is_some() {
                        return Err(err(n, k, v, "given twice on the line".into()));
                    }
                    if v.is_empty() || v.chars().any(char::is_control) {
                        return Err(err(n, k, v, "empty or holds control characters".into()));
                    }
                    target = Some(v.to_string());
                }
                _ => return Err(err(n, k, v, "unknown key (keys: angle, target)".into())),
            }
        }
        if path_text.is_empty() || path_text.contains('\0') {
            return Err(err(n, "path", path_text, "empty or holds a NUL byte".into()));
        }
        let p = Path::new(path_text.as_str());
        let path = if p.is_absolute() { p.to_path_buf() } else { base.join(p) };
        let meta =
            std::fs::metadata(&path).map_err(|e| err(n, "path", path_text, format!("{}: {e}", path.display())))?;
        if !meta.is_file() {
            return Err(err(
                n,
                "path",
                path_text,
                format!("{}: not a regular file", path.display()),
            ));
        }
        let canonical = std::fs::canonicalize(&path).unwrap_or_else(|_| path.clone());
        if let Some(first) = seen.insert(canonical, n) {
            return Err(err(
                n,
                "path",
                path_text,
                format!("the same file as line {first}: each frame is listed once"),
            ));
        }
        frames.push(ListedFrame {
            path,
            line: n,
            role,
            angle_deg,
            target,
        });
    }
    Ok(FrameList {
        file: file.to_path_buf(),
        frames,
    })
}

/// Whitespace-separated tokens up to a `#` that starts a token; the first may be a
/// double-quoted path (no escapes).
fn tokenize(line: &str) -> Result<Vec<String>, (String, String)> {
    let mut out = Vec::new();
    let mut rest = line.trim_start();
    if let Some(q) = rest.strip_prefix('"') {
        let end = q
            .find('"')
            .ok_or_else(|| (rest.to_string(), "a quoted path without its closing quote".to_string()))?;
        out.push(q[..end].to_string());
        rest = &q[end + 1..];
        if !(rest.is_empty() || rest.starts_with(char::is_whitespace)) {
            return Err((line.to_string(), "text right after the closing quote".into()));
        }
    }
    for t in rest.split_whitespace() {
        if t.starts_with('#') {
            break;
        }
        out.push(t.to_string());
    }
    Ok(out)
}

/// The text of a set-of-frames file listing `frames` (path, role), with `header` as comment
/// lines. Paths are written as given (absolute paths stay valid wherever the file goes),
/// quoted when they hold whitespace or start with `#` or `"`; a path that cannot be written
/// (a quote and whitespace, a newline, not UTF-8) becomes a comment saying so.
pub fn write(header: &[String], frames: &[(PathBuf, FrameRole)]) -> String {
    let frames: Vec<(PathBuf, FrameRole, Option<&str>)> = frames.iter().map(|(p, r)| (p.clone(), *r, None)).collect();
    write_with_targets(header, &frames)
}

/// [`write()`], each frame with its `target=` when given: a name that a line can carry
/// (no whitespace, no control character) is written, another is left out (the frame's
/// header then names the target).
pub fn write_with_targets(header: &[String], frames: &[(PathBuf, FrameRole, Option<&str>)]) -> String {
    let mut s = String::new();
    for h in header {
        for l in h.lines() {
            s.push_str(&format!("# {l}\n"));
        }
    }
    for (p, role, target) in frames {
        let setting = target
            .filter(|t| !t.is_empty() && !t.chars().any(|c| c.is_whitespace() || c.is_control()))
            .map(|t| format!(" target={t}"))
            .unwrap_or_default();
        let Some(t) = p.to_str() else {
            s.push_str(&format!("# not listed (path not UTF-8): {}\n", p.display()));
            continue;
        };
        let needs_quotes = t.contains(char::is_whitespace) || t.starts_with('#') || t.starts_with('"');
        if t.contains(['\n', '\r']) || t.len() > MAX_LINE_BYTES - 16 || (needs_quotes && t.contains('"')) {
            s.push_str(&format!("# not listed (path not representable): {t:?}\n"));
        } else if needs_quotes {
            s.push_str(&format!("\"{t}\" {}{setting}\n", role.name()));
        } else {
            s.push_str(&format!("{t} {}{setting}\n", role.name()));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn setup() -> (tempfile::TempDir, PathBuf) {
        let d = tempfile::tempdir().unwrap();
        for f in ["a.fits", "b.fits", "sub dir/c.fits"] {
            let p = d.path().join(f);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(&p, b"SIMPLE  =").unwrap();
        }
        std::fs::create_dir_all(d.path().join("sub")).unwrap();
        let list = d.path().join("run.frames");
        (d, list)
    }

    fn parse_text(dir: &Path, list: &Path, text: &[u8]) -> Result<FrameList, FrameListError> {
        std::fs::write(list, text).unwrap();
        let _ = dir;
        read(list)
    }

    #[test]
    fn a_good_file_parses_with_roles_settings_comments_and_relative_paths() {
        let (d, list) = setup();
        let abs = d.path().join("b.fits");
        let text = format!(
            "# a run\n\n  a.fits science angle=45 target=HK_Tau # note\n{} standard\r\n\"sub dir/c.fits\" flat\n",
            abs.display()
        );
        let l = parse_text(d.path(), &list, text.as_bytes()).unwrap();
        assert_eq!(l.frames.len(), 3);
        assert_eq!(l.frames[0].path, d.path().join("a.fits"));
        assert_eq!((l.frames[0].line, l.frames[0].role), (3, FrameRole::Science));
        assert_eq!(l.frames[0].angle_deg, Some(45.0));
        assert_eq!(l.frames[0].target.as_deref(), Some("HK_Tau"));
        assert_eq!((l.frames[1].path.clone(), l.frames[1].role), (abs, FrameRole::Standard));
        assert_eq!(l.frames[2].path, d.path().join("sub dir/c.fits"));
        // What `write` writes reads back the same.
        let frames: Vec<(PathBuf, FrameRole)> = l.frames.iter().map(|f| (f.path.clone(), f.role)).collect();
        let again = parse_text(d.path(), &list, write(&["x".into()], &frames).as_bytes()).unwrap();
        let back: Vec<(PathBuf, FrameRole)> = again.frames.iter().map(|f| (f.path.clone(), f.role)).collect();
        assert_eq!(back, frames);
        // With targets: a name a line can carry is written and read back; one with
        // whitespace is left out (the header names the target again).
        let named = [
            (d.path().join("a.fits"), FrameRole::Science, Some("AB_Aur")),
            (d.path().join("b.fits"), FrameRole::Science, Some("AB Aur")),
            (d.path().join("sub dir/c.fits"), FrameRole::Dark, None),
        ];
        let text = write_with_targets(&[], &named);
        let again = parse_text(d.path(), &list, text.as_bytes()).unwrap();
        let back: Vec<_> = again.frames.iter().map(|f| (f.role, f.target.as_deref())).collect();
        assert_eq!(
            back,
            [
                (FrameRole::Science, Some("AB_Aur")),
                (FrameRole::Science, None),
                (FrameRole::Dark, None)
            ],
            "{text}"
        );
    }

    #[test]
    fn a_file_longer_than_the_limit_is_refused_before_it_is_read_whole() {
        let dir = tempfile::tempdir().unwrap();
        let mut text = String::new();
        for k in 0..10 {
            std::fs::write(dir.path().join(format!("a{k}.fits")), b"").unwrap();
            text += &format!("a{k}.fits science\n");
        }
        let list = dir.path().join("frames.txt");
        std::fs::write(&list, &text).unwrap();
        assert_eq!(text.len(), 160);
        assert_eq!(read_limited(&list, 160).unwrap().frames.len(), 10);
        let e = read_limited(&list, 159).unwrap_err().to_string();
        assert!(e.contains("frames.txt") && e.contains("159 bytes"), "{e}");
    }

    #[test]
    fn hostile_lines_are_errors_naming_file_line_key_and_value() {
        let (d, list) = setup();
        let long = format!("a.fits science target={}\n", "x".repeat(5000));
        let cases: Vec<(Vec<u8>, usize, &str, &str)> = vec![
            (
                b"a.fits science\nmissing.fits science\n".to_vec(),
                2,
                "path",
                "missing.fits",
            ),
            (b"a.fits science\n./a.fits flat\n".to_vec(), 2, "path", "line 1"),
            (b"a.fits bias\n".to_vec(), 1, "role", "unknown role"),
            (b"a.fits\n".to_vec(), 1, "role", "missing"),
            (b"a.fits science angle=nan\n".to_vec(), 1, "angle", "finite"),
            (b"a.fits science angle=inf\n".to_vec(), 1, "angle", "finite"),
            (b"a.fits science angle=1e300\n".to_vec(), 1, "angle", "one turn"),
            (b"a.fits science angle=-360.5\n".to_vec(), 1, "angle", "one turn"),
            (b"a.fits science angle=north\n".to_vec(), 1, "angle", "not a number"),
            (b"a.fits science angle=1 angle=2\n".to_vec(), 1, "angle", "twice"),
            (b"a.fits science colour=red\n".to_vec(), 1, "colour", "unknown key"),
            (b"a.fits science loose\n".to_vec(), 1, "loose", "key=value"),
            (b"# ok\na.fits sci\xffence\n".to_vec(), 2, "line", "not UTF-8"),
            (long.into_bytes(), 1, "line", "longer than"),
            (b"\"sub dir/c.fits science\n".to_vec(), 1, "path", "closing quote"),
            (b"sub science\n".to_vec(), 1, "path", "not a regular file"),
            (b"a.fits science target=\n".to_vec(), 1, "target", "empty"),
        ];
        for (text, line, key, why) in cases {
            let e = parse_text(d.path(), &list, &text).unwrap_err();
            let msg = e.to_string();
            assert_eq!(e.line, Some(line), "{msg}");
            assert_eq!(e.key, key, "{msg}");
            assert!(msg.contains(why), "{msg}");
            assert!(
                msg.starts_with(&format!("{}:{line}: {key} = ", list.display())),
                "{msg}"
            );
        }
        // An empty file and a file of comments list nothing (the caller refuses that).
        assert!(parse_text(d.path(), &list, b"").unwrap().frames.is_empty());
        assert!(parse_text(d.path(), &list, b"# only\n   \n").unwrap().frames.is_empty());
        // A file that cannot be read.
        let e = read(&d.path().join("nope.frames")).unwrap_err();
        assert!(e.line.is_none() && e.to_string().contains("nope.frames"), "{e}");
    }
}
