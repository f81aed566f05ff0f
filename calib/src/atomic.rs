//! Output files are never half-written, and writing one never touches anything but that
//! file: every writer of the workspace (FITS frames, catalogs, PNG figures, JSON) writes a
//! temporary file in the destination's directory, flushes and syncs it, then renames it
//! over the destination.
//!
//! The temporary is created with a random name and `O_CREAT | O_EXCL` (the `tempfile`
//! crate), which never follows a symbolic link: in a shared directory (`/tmp`, sticky)
//! another user cannot plant a link at a predictable name and make the run overwrite a
//! file of theirs choosing. Writers that need a file *name* (cfitsio creates the file
//! itself) get one inside a fresh private directory (mode 0700, random name) instead.
//!
//! Many small files written together (a night's figures) may instead be synced together,
//! after the last ([`write_atomic_deferred`], then [`sync_files`]): a sync per file and per
//! directory, one after the other, cost some 8 ms each on a virtual disk (0.4 s for 49
//! figures, more than drawing them). Each file's write-back is started as it is written,
//! and the syncs at the end run side by side, so the journal commits them together (49
//! figures: 4-14 ms). Only the run's own files are synced: a `syncfs` of the whole
//! filesystem would also wait for every other program's unwritten data (0.03-1.2 s
//! measured on a machine where compilers were writing). Until that sync a crash may lose
//! such a file (or leave it empty), as any program's unsynced output; it never leaves a
//! file with part of its content or replaces a good file by a half-written one.
//!
//! The destination must be absent or a regular file ([`check_destination`]): the rename
//! would replace a symbolic link or a device node (`-o /dev/stdout` as root replaced the
//! system's link) with a regular file, so such a destination is refused by name.
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

fn io(p: &Path, e: std::io::Error) -> Error {
    Error::Io {
        path: p.to_path_buf(),
        source: e,
    }
}

/// The directory a destination lives in (`.` for a bare file name).
fn dir_of(dest: &Path) -> &Path {
    match dest.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// The destination's file name reduced to plain characters (`[A-Za-z0-9._-]`, others
/// `_`): temporary names go through cfitsio's file-name parser.
fn safe_name(dest: &Path) -> Result<String> {
    let name = dest.file_name().ok_or_else(|| {
        io(
            dest,
            std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file name"),
        )
    })?;
    Ok(name
        .to_string_lossy()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "._-".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect())
}

/// What a non-regular file is, for a message.
fn kind_of(meta: &std::fs::Metadata, dest: &Path) -> String {
    let ft = meta.file_type();
    if ft.is_symlink() {
        return match std::fs::read_link(dest) {
            Ok(t) => format!("a symbolic link (to {})", t.display()),
            Err(_) => "a symbolic link".into(),
        };
    }
    if ft.is_dir() {
        return "a directory".into();
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if ft.is_char_device() {
            return "a character device".into();
        }
        if ft.is_block_device() {
            return "a block device".into();
        }
        if ft.is_fifo() {
            return "a named pipe (FIFO)".into();
        }
        if ft.is_socket() {
            return "a socket".into();
        }
    }
    "not a regular file".into()
}

/// Refuse to replace anything but a regular file: `dest` must be absent or a regular file
/// (not followed when it is a symbolic link). The error names it and what it is.
pub fn check_destination(dest: &Path) -> Result<()> {
    match std::fs::symlink_metadata(dest) {
        Ok(m) if !m.file_type().is_file() => Err(io(
            dest,
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!(
                    "is {}, not a regular file: sofipol writes its outputs by replacing the file, \
                     which would replace it; not written",
                    kind_of(&m, dest)
                ),
            ),
        )),
        _ => Ok(()),
    }
}

/// Sync a file's data, rename it over `dest` (checked first with [`check_destination`]),
/// then sync the directory (best effort: makes the rename itself durable).
fn sync_and_rename(tmp: &Path, dest: &Path) -> Result<()> {
    std::fs::File::open(tmp)
        .and_then(|f| f.sync_all())
        .map_err(|e| io(tmp, e))?;
    check_destination(dest)?;
    std::fs::rename(tmp, dest).map_err(|e| io(dest, e))?;
    let _ = std::fs::File::open(dir_of(dest)).and_then(|d| d.sync_all());
    Ok(())
}

/// A temporary file name next to the destination for writers that create the file
/// themselves (cfitsio): `path` lies in a fresh private directory (mode 0700, random
/// name) in the destination's directory, so nobody else can have put anything there. The
/// directory is removed when the `TempFile` is committed or dropped (with the file, when
/// it was not committed).
pub struct TempFile {
    /// Where to write before [`TempFile::commit`].
    pub path: PathBuf,
    dir: tempfile::TempDir,
    /// The private directory held open, for [`TempFile::ascii_path`].
    dir_handle: Option<std::fs::File>,
}

impl TempFile {
    /// A fresh temporary name for `dest` (the file is not created).
    pub fn new(dest: &Path) -> Result<TempFile> {
        let safe = safe_name(dest)?;
        check_destination(dest)?;
        let prefix = format!(".{safe}.");
        let mut b = tempfile::Builder::new();
        b.prefix(&prefix).suffix(".tmp");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            b.permissions(std::fs::Permissions::from_mode(0o700));
        }
        let parent = dir_of(dest);
        let dir = b.tempdir_in(parent).map_err(|e| io(parent, e))?;
        let path = dir.path().join(safe);
        Ok(TempFile {
            path,
            dir,
            dir_handle: None,
        })
    }

    /// A name of [`TempFile::path`] made only of ASCII letters, digits, `/`, `.`, `_` and
    /// `-`, for a library that takes file names as text and parses them (cfitsio): the
    /// path itself when it is such a name, else (a folder named in another encoding, or
    /// with brackets) the file inside the private directory held open, reached through
    /// `/proc/self/fd` (Linux). `None` where neither exists.
    pub fn ascii_path(&mut self) -> Option<String> {
        let plain = |s: &str| s.bytes().all(|b| b.is_ascii_alphanumeric() || b"/._-".contains(&b));
        if let Some(s) = self.path.to_str().filter(|s| plain(s) && !s.starts_with('-')) {
            return Some(s.to_string());
        }
        let name = self.path.file_name()?.to_str()?.to_string();
        if self.dir_handle.is_none() {
            self.dir_handle = std::fs::File::open(self.dir.path()).ok();
        }
        #[cfg(target_os = "linux")]
        {
            use std::os::fd::AsRawFd;
            let fd = self.dir_handle.as_ref()?.as_raw_fd();
            let p = format!("/proc/self/fd/{fd}/{name}");
            return Path::new(&p).parent()?.is_dir().then_some(p);
        }
        #[allow(unreachable_code)]
        {
            let _ = name;
            None
        }
    }

    /// Sync the temporary file and rename it over `dest` (which must be absent or a
    /// regular file), then sync the directory (best effort).
    pub fn commit(self, dest: &Path) -> Result<()> {
        sync_and_rename(&self.path, dest)?;
        drop(self.dir);
        Ok(())
    }
}

/// Write `bytes` to `path` atomically (a temporary file of random name created
/// exclusively in the same directory, synced, renamed; the directory must exist and
/// `path` be absent or a regular file). The file's permissions follow the umask, like a
/// file created the usual way (0644 with the usual 022).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_renamed(path, bytes, true)
}

/// [`write_atomic`] without the syncs: the file is renamed into place whole, its write-back
/// started (Linux), and made durable by a later [`sync_files`] (with the others written
/// since).
pub fn write_atomic_deferred(path: &Path, bytes: &[u8]) -> Result<()> {
    write_renamed(path, bytes, false)
}

/// A temporary of random name created exclusively beside `path`, filled, synced with the
/// directory when `sync` (else its write-back started), and renamed over `path`.
fn write_renamed(path: &Path, bytes: &[u8], sync: bool) -> Result<()> {
    let safe = safe_name(path)?;
    check_destination(path)?;
    let prefix = format!(".{safe}.");
    let mut b = tempfile::Builder::new();
    b.prefix(&prefix).suffix(".tmp");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        b.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let dir = dir_of(path);
    let mut tmp = b.tempfile_in(dir).map_err(|e| io(dir, e))?;
    tmp.write_all(bytes)
        .and_then(|_| {
            if sync {
                tmp.as_file().sync_all()
            } else {
                start_writeback(tmp.as_file());
                Ok(())
            }
        })
        .map_err(|e| io(tmp.path(), e))?;
    check_destination(path)?;
    tmp.persist(path).map_err(|e| io(path, e.error))?;
    if sync {
        let _ = std::fs::File::open(dir).and_then(|d| d.sync_all());
    }
    Ok(())
}

/// Ask the kernel to start writing `f`'s data to disk now, without waiting (Linux
/// `sync_file_range(SYNC_FILE_RANGE_WRITE)`; nothing elsewhere): the later sync then finds
/// little left to write. A hint: its failure changes nothing.
fn start_writeback(f: &std::fs::File) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        // SAFETY: `f` is an open file descriptor for the whole call; the call only reads it.
        #[allow(unsafe_code)]
        let _ = unsafe { libc::sync_file_range(f.as_raw_fd(), 0, 0, libc::SYNC_FILE_RANGE_WRITE) };
    }
    #[cfg(not(target_os = "linux"))]
    let _ = f;
}

/// How many syncs [`sync_files`] runs side by side.
const SYNC_THREADS: usize = 16;

/// Make `files` (written with [`write_atomic_deferred`]) and the directories holding them
/// durable: the files' data synced side by side (up to 16 threads, so that the journal
/// commits them together), then each directory once. Only these files are waited for,
/// never other programs' data. The errors, one per file or directory that could not be
/// synced (an absent file is one).
pub fn sync_files(files: &[PathBuf]) -> Vec<Error> {
    let errors = std::sync::Mutex::new(Vec::new());
    let sync = |p: &Path, data_only: bool| {
        let r = std::fs::File::open(p).and_then(|f| if data_only { f.sync_data() } else { f.sync_all() });
        if let Err(e) = r {
            errors.lock().unwrap_or_else(|e| e.into_inner()).push(io(p, e));
        }
    };
    let chunk = files.len().div_ceil(SYNC_THREADS).max(1);
    std::thread::scope(|s| {
        for part in files.chunks(chunk) {
            s.spawn(|| part.iter().for_each(|p| sync(p, true)));
        }
    });
    let mut dirs: Vec<&Path> = files.iter().map(|p| dir_of(p)).collect();
    dirs.sort();
    dirs.dedup();
    for d in dirs {
        sync(d, false);
    }
    errors.into_inner().unwrap_or_else(|e| e.into_inner())
}

/// Serialize `value` as pretty JSON (with a final newline) and write it atomically,
/// creating the directory if needed.
pub fn write_json_atomic<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    }
    let mut text = serde_json::to_vec_pretty(value).map_err(|e| io(path, std::io::Error::other(e)))?;
    text.push(b'\n');
    write_atomic(path, &text)
}

#[cfg(test)]
mod tests;
