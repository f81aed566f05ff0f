//! Finding and classifying input files.
use std::path::{Path, PathBuf};

use sofipol_calib::classify::{classify, Classification, ScienceInfo};
use sofipol_calib::Profile;

use crate::catalog::Failure;

/// File names sofipol reads: `.fits`, `.fit`, `.fits.gz`, `.fit.gz`, `.fz` (any case).
pub fn is_fits_name(p: &Path) -> bool {
    // Lossy: a name that is not UTF-8 (another encoding) still ends in `.fits`.
    let n = p
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default()
        .to_ascii_lowercase();
    !n.starts_with('.')
        && [".fits", ".fit", ".fits.gz", ".fit.gz", ".fz"]
            .iter()
            .any(|e| n.ends_with(e))
}

/// The FITS-named files under some roots, and the directories that could not be listed.
#[derive(Debug, Default)]
pub struct Listing {
    /// Files found (sorted, each file once: paths that resolve to the same file are kept
    /// once, the others are in `duplicates`).
    pub files: Vec<PathBuf>,
    /// Directories that could not be listed (permissions, I/O errors), by path.
    pub unreadable_dirs: Vec<Failure>,
    /// Second and later paths of a file already found (`./good` and `good`, an absolute
    /// and a relative path, a symlink alias), with the path kept.
    pub duplicates: Vec<Failure>,
}

/// Every FITS-named file under `root` (recursively; a file is taken as given), sorted.
/// A directory that cannot be listed is reported by path and skipped, never fatal; a
/// directory reached twice (a symlink loop or alias) is listed once.
pub fn find_files(root: &Path) -> std::io::Result<Vec<PathBuf>> {
    if !root.exists() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::NotFound,
            format!("{}: no such file or directory", root.display()),
        ));
    }
    Ok(list(&[root.to_path_buf()]).files)
}

/// [`find_files`] over several roots, with each file kept once (by canonical path) and
/// the unreadable directories and duplicate paths reported.
pub fn list(roots: &[PathBuf]) -> Listing {
    list_with(roots, &|d: &Path| {
        std::fs::read_dir(d)?
            .map(|e| e.map(|e| e.path()))
            .collect::<std::io::Result<Vec<PathBuf>>>()
    })
}

/// [`list`] with the directory reader given (tests inject failures with it).
pub fn list_with(roots: &[PathBuf], read_dir: &dyn Fn(&Path) -> std::io::Result<Vec<PathBuf>>) -> Listing {
    let mut out = Listing::default();
    let mut found = Vec::new();
    let mut seen_dirs = std::collections::HashSet::new();
    // A root given twice (`night n ./n /abs/n`) is scanned once, silently: nothing is lost.
    let mut seen_roots = std::collections::HashSet::new();
    for root in roots {
        if !seen_roots.insert(std::fs::canonicalize(root).unwrap_or_else(|_| root.clone())) {
            continue;
        }
        if !root.is_dir() {
            if root.exists() {
                found.push(root.clone());
            }
            continue;
        }
        let mut stack = vec![root.clone()];
        while let Some(d) = stack.pop() {
            // A loop (`night/loop -> ..`) or an alias resolves to a directory already seen.
            if !seen_dirs.insert(std::fs::canonicalize(&d).unwrap_or_else(|_| d.clone())) {
                continue;
            }
            match read_dir(&d) {
                Ok(entries) => {
                    for p in entries {
                        if p.is_dir() {
                            stack.push(p);
                        } else if is_fits_name(&p) {
                            found.push(p);
                        }
                    }
                }
                Err(e) => out.unreadable_dirs.push(Failure {
                    file: d.display().to_string(),
                    error: format!("directory not readable, skipped: {e}"),
                }),
            }
        }
    }
    found.sort();
    found.dedup();
    let mut by_canonical: std::collections::HashMap<PathBuf, PathBuf> = std::collections::HashMap::new();
    for f in found {
        let c = std::fs::canonicalize(&f).unwrap_or_else(|_| f.clone());
        match by_canonical.get(&c) {
            Some(kept) => out.duplicates.push(Failure {
                file: f.display().to_string(),
                error: format!(
                    "duplicate of {} (the same file by another path): not used twice",
                    kept.display()
                ),
            }),
            None => {
                by_canonical.insert(c, f.clone());
                out.files.push(f);
            }
        }
    }
    out.unreadable_dirs.sort_by(|a, b| a.file.cmp(&b.file));
    out
}

/// Frames that are the same exposure under two names (a backup copy, a copy in a
/// subfolder): equal identifying header values (object, template start, exposure number,
/// MJD-OBS, position angle, offsets, filter, DIT, NDIT) and equal pixels. The first in
/// path order is kept; the others are returned as failures naming it. Pixels are read only
/// for frames whose identifying values collide.
pub fn drop_duplicate_exposures(science: Vec<ScienceInfo>) -> (Vec<ScienceInfo>, Vec<Failure>) {
    use std::collections::BTreeMap;
    let key = |i: &ScienceInfo| {
        format!(
            "{}|{}|{:?}|{:?}|{}|{}|{}|{}|{}|{}",
            i.object,
            i.tpl_start,
            i.expno,
            i.mjd.map(f64::to_bits),
            i.posang_deg.to_bits(),
            i.offset_px[0].to_bits(),
            i.offset_px[1].to_bits(),
            i.filter,
            i.dit_s.to_bits(),
            i.ndit
        )
    };
    let mut groups: BTreeMap<String, Vec<ScienceInfo>> = BTreeMap::new();
    for i in science {
        groups.entry(key(&i)).or_default().push(i);
    }
    let mut keep = Vec::new();
    let mut dups = Vec::new();
    for (_, mut g) in groups {
        if g.len() == 1 {
            keep.append(&mut g);
            continue;
        }
        g.sort_by(|a, b| a.path.cmp(&b.path));
        let mut kept: Vec<(u64, PathBuf)> = Vec::new();
        for i in g {
            let h = pixel_hash(&i.path);
            match (h, kept.iter().find(|(k, _)| Some(*k) == h)) {
                (Some(_), Some((_, first))) => dups.push(Failure {
                    file: i.path.display().to_string(),
                    error: format!(
                        "duplicate of {} (same exposure: identical identifying keywords and pixels): not used twice",
                        first.display()
                    ),
                }),
                _ => {
                    if let Some(h) = h {
                        kept.push((h, i.path.clone()));
                    }
                    keep.push(i);
                }
            }
        }
    }
    (keep, dups)
}

/// FNV-1a hash of a frame's pixel values (None when unreadable: such a file is kept and
/// fails later, by name, in the reduction).
fn pixel_hash(p: &Path) -> Option<u64> {
    let f = sofipol_calib::fits::read_frame(p).ok()?;
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let (ny, nx) = f.shape();
    for b in (ny as u64).to_le_bytes().into_iter().chain((nx as u64).to_le_bytes()) {
        h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3);
    }
    for v in f.data.iter() {
        for b in v.to_bits().to_le_bytes() {
            h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    Some(h)
}

/// The outcome of classifying a set of files.
#[derive(Debug, Default)]
pub struct Scan {
    /// Polarimetric science frames.
    pub science: Vec<ScienceInfo>,
    /// Readable FITS files that are not polarimetric science (flats, darks, other
    /// instruments...), with the reason.
    pub other: Vec<Failure>,
    /// Files that could not be read.
    pub unreadable: Vec<Failure>,
    /// Inputs reached twice (same file by another path, or a copy of the same exposure),
    /// with the one kept.
    pub duplicates: Vec<Failure>,
    /// Dome-flat frames (DPR TYPE 'FLAT' with a valid lamp keyword): calibration for the
    /// flat builder, not failures.
    pub dome_flats: Vec<PathBuf>,
    /// Set when the process ran out of file handles (EMFILE, ENFILE) while reading headers:
    /// the files it could not open are not unusable, the scan is (a fatal error).
    pub out_of_file_handles: Option<String>,
}

/// Whether `e` is the system refusing to open one more file (EMFILE: this process's limit,
/// `ulimit -n`; ENFILE: the system's): not a fault of the file.
pub fn is_out_of_file_handles(e: &sofipol_calib::Error) -> bool {
    matches!(e, sofipol_calib::Error::Io { source, .. } if matches!(source.raw_os_error(), Some(23) | Some(24)))
}

/// List the FITS files under `roots` ([`list`]), classify them ([`classify_all`]) and keep
/// each exposure once ([`drop_duplicate_exposures`]). Returns the scan and the files found.
pub fn scan(roots: &[PathBuf], profile: &Profile) -> (Scan, Vec<PathBuf>) {
    scan_listing(list(roots), profile)
}

/// [`scan`] of files already listed ([`list`]; live reduction lists only the files that
/// are complete).
pub fn scan_listing(l: Listing, profile: &Profile) -> (Scan, Vec<PathBuf>) {
    scan_listing_with(l, profile, &sofipol_calib::fits::read_header)
}

/// [`scan_listing`] with the header reader given (live reduction keeps the headers it has
/// read).
pub fn scan_listing_with(l: Listing, profile: &Profile, read_header: &ReadHeader<'_>) -> (Scan, Vec<PathBuf>) {
    let mut s = classify_with(&l.files, profile, read_header);
    s.unreadable.extend(l.unreadable_dirs);
    let (science, dups) = drop_duplicate_exposures(std::mem::take(&mut s.science));
    s.science = science;
    s.duplicates = l.duplicates;
    s.duplicates.extend(dups);
    s.duplicates.sort_by(|a, b| a.file.cmp(&b.file));
    (s, l.files)
}

/// Why a file could not be read, in words, without repeating the path (the failure record
/// names it): a file that does not start like FITS (`SIMPLE  =`, or gzip) is "not a FITS
/// file" with its first bytes shown, instead of cfitsio's "is the file truncated?".
pub fn unreadable_reason(path: &Path, message: &str) -> String {
    let mut head = [0u8; 30];
    // Only a regular file is opened: opening a named pipe would wait for a writer (the
    // message already says what it is).
    let open_regular = || {
        if std::fs::metadata(path)?.is_file() {
            std::fs::File::open(path)
        } else {
            Err(std::io::Error::other("not a regular file"))
        }
    };
    let n = open_regular()
        .and_then(|mut f| {
            let mut n = 0;
            while n < head.len() {
                match std::io::Read::read(&mut f, &mut head[n..])? {
                    0 => break,
                    k => n += k,
                }
            }
            Ok(n)
        })
        .unwrap_or(usize::MAX);
    if n != usize::MAX && !head[..n].starts_with(b"SIMPLE  =") && !head[..n].starts_with(&[0x1f, 0x8b]) {
        if n == 0 {
            return "not a FITS file: empty".into();
        }
        let preview: String = head[..n]
            .iter()
            .map(|&b| match b {
                b'\n' | b'\r' | b'\t' => ' ',
                0x20..0x7f => b as char,
                _ => '.',
            })
            .collect();
        return format!("not a FITS file: starts with '{}', not 'SIMPLE  ='", preview.trim_end());
    }
    let shown = path.display().to_string();
    message
        .strip_prefix(&shown)
        .and_then(|m| m.strip_prefix(": "))
        .unwrap_or(message)
        .to_string()
}

/// Classify files by header (in parallel; the order of the result does not depend on it).
pub fn classify_all(files: &[PathBuf], profile: &Profile) -> Scan {
    classify_with(files, profile, &sofipol_calib::fits::read_header)
}

/// The header reader of [`classify_all`] (tests inject errors with it).
pub type ReadHeader<'a> = dyn Fn(&Path) -> sofipol_calib::Result<sofipol_calib::Header> + Sync + 'a;

/// [`classify_all`] with the header reader given.
pub fn classify_with(files: &[PathBuf], profile: &Profile, read_header: &ReadHeader<'_>) -> Scan {
    use rayon::prelude::*;
    let results: Vec<(PathBuf, sofipol_calib::Result<(Classification, bool)>)> = files
        .par_iter()
        .map(|f| {
            let r = read_header(f).map(|h| {
                let c = classify(&h, profile);
                // A rejected frame that is a dome flat goes to the flat builder; a flat with
                // a bad lamp keyword stays a failure with that reason.
                if let Classification::Rejected { .. } = &c {
                    match sofipol_calib::flat::dome_flat_info(&h, profile) {
                        Ok(Some(_)) => return (c, true),
                        Err(e) => return (Classification::Rejected { reason: e.to_string() }, false),
                        Ok(None) => {}
                    }
                }
                (c, false)
            });
            (f.clone(), r)
        })
        .collect();
    let mut s = Scan::default();
    for (f, r) in results {
        match r {
            Ok((_, true)) => s.dome_flats.push(f),
            Ok((Classification::Science(info), false)) => s.science.push(*info),
            Ok((Classification::Rejected { reason }, false)) => s.other.push(Failure {
                file: f.display().to_string(),
                error: reason,
            }),
            Err(e) if is_out_of_file_handles(&e) => {
                s.out_of_file_handles.get_or_insert_with(|| e.to_string());
            }
            Err(e) => s.unreadable.push(Failure {
                file: f.display().to_string(),
                error: unreadable_reason(&f, &e.to_string()),
            }),
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unreadable_subdirectory_is_named_and_skipped() {
        // Regression: one unreadable subdirectory aborted the night without naming it.
        // (Tests may run as root, for whom chmod 000 changes nothing: the error is injected.)
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(d.path().join("a")).unwrap();
        std::fs::create_dir_all(d.path().join("locked")).unwrap();
        std::fs::write(d.path().join("a/x.fits"), b"").unwrap();
        std::fs::write(d.path().join("locked/y.fits"), b"").unwrap();
        let l = list_with(&[d.path().to_path_buf()], &|p: &Path| {
            if p.ends_with("locked") {
                return Err(std::io::Error::from(std::io::ErrorKind::PermissionDenied));
            }
            std::fs::read_dir(p)?.map(|e| e.map(|e| e.path())).collect()
        });
        assert_eq!(l.files, vec![d.path().join("a/x.fits")]);
        assert_eq!(l.unreadable_dirs.len(), 1, "{:?}", l.unreadable_dirs);
        assert_eq!(l.unreadable_dirs[0].file, d.path().join("locked").display().to_string());
        assert!(l.unreadable_dirs[0].error.contains("not readable"));
    }

    #[test]
    fn a_text_file_is_not_a_fits_file_and_the_path_is_not_repeated() {
        // Regression: a text file was reported as "is the file truncated?", and every FITS
        // error repeated the path the failure record already names.
        let d = tempfile::tempdir().unwrap();
        let notes = d.path().join("notes.fits");
        std::fs::write(&notes, "observing log: clouds at 3 UT\n").unwrap();
        let empty = d.path().join("empty.fits");
        std::fs::write(&empty, "").unwrap();
        let mut cut = std::fs::read(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../testdata/fits/sofi_pol_64x64_i16.fits"
        ))
        .unwrap();
        cut.truncate(1000);
        let trunc = d.path().join("cut.fits");
        std::fs::write(&trunc, cut).unwrap();
        let s = classify_all(&[notes.clone(), empty.clone(), trunc.clone()], &Profile::sofi());
        let get = |p: &Path| {
            s.unreadable
                .iter()
                .find(|f| f.file == p.display().to_string())
                .map(|f| f.error.clone())
                .unwrap()
        };
        let e = get(&notes);
        assert_eq!(
            e,
            "not a FITS file: starts with 'observing log: clouds at 3 UT', not 'SIMPLE  ='"
        );
        assert_eq!(get(&empty), "not a FITS file: empty");
        let e = get(&trunc);
        assert!(!e.contains(&trunc.display().to_string()) && e.contains("FITS"), "{e}");
    }

    #[test]
    fn running_out_of_file_handles_is_not_a_fault_of_the_files() {
        // Regression: with too low a `ulimit -n` every file of the night was listed as
        // unusable ("cfitsio status 104"), 85 of them, and the night went on without them.
        let d = tempfile::tempdir().unwrap();
        let files: Vec<PathBuf> = (0..4).map(|i| d.path().join(format!("f{i}.fits"))).collect();
        let read = |p: &Path| -> sofipol_calib::Result<sofipol_calib::Header> {
            if p.ends_with("f0.fits") {
                Err(sofipol_calib::Error::Io {
                    path: p.into(),
                    source: std::io::Error::other("disk on fire"),
                })
            } else {
                Err(sofipol_calib::Error::Io {
                    path: p.into(),
                    source: std::io::Error::from_raw_os_error(24),
                })
            }
        };
        let s = classify_with(&files, &Profile::sofi(), &read);
        // The file that failed for its own reason is named; the others are not blamed.
        assert_eq!(s.unreadable.len(), 1, "{:?}", s.unreadable);
        assert!(s.unreadable[0].file.ends_with("f0.fits"));
        let e = s.out_of_file_handles.expect("out of file handles noticed");
        assert!(e.contains("os error 24"), "{e}");
        let ok = classify_with(&files[..1], &Profile::sofi(), &read);
        assert!(ok.out_of_file_handles.is_none());
    }

    #[cfg(unix)]
    #[test]
    fn a_directory_symlink_loop_is_followed_once() {
        // Regression: `night/loop -> ..` made every frame count 41 times.
        let d = tempfile::tempdir().unwrap();
        let n = d.path().join("n");
        std::fs::create_dir_all(n.join("sub")).unwrap();
        std::fs::write(n.join("a.fits"), b"").unwrap();
        std::fs::write(n.join("sub/b.fits"), b"").unwrap();
        std::os::unix::fs::symlink("..", n.join("sub/loop")).unwrap();
        std::os::unix::fs::symlink(&n, n.join("self")).unwrap();
        std::os::unix::fs::symlink(n.join("a.fits"), n.join("alias.fits")).unwrap();
        let l = list(&[n.clone(), d.path().join("n/."), n.join("sub")]);
        assert_eq!(l.files, vec![n.join("a.fits"), n.join("sub/b.fits")], "{l:?}");
        assert_eq!(l.duplicates.len(), 1, "{:?}", l.duplicates);
        assert!(l.duplicates[0].file.ends_with("alias.fits"));
        assert!(l.unreadable_dirs.is_empty());
    }
}
