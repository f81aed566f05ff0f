//! Output files are never half-written: every writer of the workspace (FITS frames,
//! catalogs, PNG figures, JSON) writes a temporary file in the destination's directory,
//! flushes and syncs it, then renames it over the destination.
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::error::{Error, Result};

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A temporary file next to the destination, removed unless committed.
pub struct TempFile {
    /// Where to write before [`TempFile::commit`].
    pub path: PathBuf,
    committed: bool,
}

impl TempFile {
    /// A fresh temporary name next to `dest` (a stale file of that name is removed).
    pub fn new(dest: &Path) -> Result<TempFile> {
        let name = dest.file_name().ok_or_else(|| Error::Io {
            path: dest.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file name"),
        })?;
        // Only plain characters: the name goes through cfitsio's file-name parser.
        let safe: String = name
            .to_string_lossy()
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || "._-".contains(c) {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
        let tmp_name = format!(".{safe}.tmp-{}-{n}", std::process::id());
        let path = match dest.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.join(tmp_name),
            _ => PathBuf::from(tmp_name),
        };
        // A stale file of this name (from a crashed process with a recycled pid) would
        // make cfitsio refuse to create: it is ours to remove.
        let _ = std::fs::remove_file(&path);
        Ok(TempFile { path, committed: false })
    }

    /// Sync the temporary file and rename it over `dest` (then sync the directory, best
    /// effort).
    pub fn commit(mut self, dest: &Path) -> Result<()> {
        let io = |p: &Path, e| Error::Io {
            path: p.to_path_buf(),
            source: e,
        };
        // Data on disk before the rename makes it visible.
        std::fs::File::open(&self.path)
            .and_then(|f| f.sync_all())
            .map_err(|e| io(&self.path, e))?;
        std::fs::rename(&self.path, dest).map_err(|e| io(dest, e))?;
        self.committed = true;
        if let Some(dir) = dest.parent().filter(|p| !p.as_os_str().is_empty()) {
            // Best effort: make the rename itself durable.
            let _ = std::fs::File::open(dir).and_then(|d| d.sync_all());
        }
        Ok(())
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// Write `bytes` to `path` atomically (temporary file + rename in the same directory; the
/// directory must exist).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let io = |p: &Path, e| Error::Io {
        path: p.to_path_buf(),
        source: e,
    };
    let tmp = TempFile::new(path)?;
    std::fs::File::create(&tmp.path)
        .and_then(|mut f| f.write_all(bytes))
        .map_err(|e| io(&tmp.path, e))?;
    tmp.commit(path)
}

/// Serialize `value` as pretty JSON (with a final newline) and write it atomically,
/// creating the directory if needed.
pub fn write_json_atomic<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Error::Io {
            path: dir.to_path_buf(),
            source: e,
        })?;
    }
    let mut text = serde_json::to_vec_pretty(value).map_err(|e| Error::Io {
        path: path.to_path_buf(),
        source: std::io::Error::other(e),
    })?;
    text.push(b'\n');
    write_atomic(path, &text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_and_leaves_no_temporaries() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("sub").join("cat.json");
        assert!(write_atomic(&p, b"first").is_err(), "the directory must exist");
        write_json_atomic(&p, &1).unwrap();
        write_atomic(&p, b"second").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"second");
        let names: Vec<_> = std::fs::read_dir(p.parent().unwrap())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 1, "{names:?}");
    }

    #[test]
    fn dropped_temporary_leaves_destination_untouched() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("cat.json");
        write_atomic(&p, b"old").unwrap();
        let tmp = TempFile::new(&p).unwrap();
        std::fs::write(&tmp.path, b"partial").unwrap();
        drop(tmp);
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
    }
}
