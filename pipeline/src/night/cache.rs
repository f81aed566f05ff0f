//! What earlier runs of a night computed, for the next run over the same night (live
//! reduction re-runs [`run_night`](super::run_night) each time a template completes).
//!
//! Every entry is keyed by what it was computed from: the settings, and each input file's
//! path, size and modification time. A target is reused only when its own frames, the
//! frames of the night's bad-pixel mask and those of the flats are all unchanged, so a run
//! with a cache gives the catalog a run without one gives, value for value; when a new
//! dome flat changes the flats, every target is reduced again.
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

use super::plan::stable_hash;
use super::{NightFlats, NightMask, NightSetup};
use crate::catalog::{Failure, Target};
use crate::error::{Error, SavedStateError};
use crate::sequence::Sequence;

/// Version of the saved state's layout ([`NightCache::save`]).
const STATE_VERSION: u32 = 1;

/// A reduced (not yet calibrated) target, as [`reduce_sequence`](crate::reduce::run::reduce_sequence)
/// left it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CachedTarget {
    /// The key it was computed under ([`NightCache::target_key`]).
    pub key: u64,
    /// The catalog entry before calibration.
    pub target: Target,
    /// Its files that could not be used.
    pub failures: Vec<Failure>,
}

/// The state saved beside a live catalog.
#[derive(Serialize, Deserialize)]
struct SavedState {
    version: u32,
    settings: u64,
    targets: Vec<CachedTarget>,
}

/// Results of earlier runs of a night with the same settings (thread-safe).
pub struct NightCache {
    /// Hash of the instrument profile and the reduction settings.
    settings: u64,
    mask: Mutex<Option<(u64, Option<NightMask>)>>,
    flats: Mutex<Option<(u64, NightFlats)>>,
    targets: Mutex<HashMap<u64, CachedTarget>>,
    /// Keys used since the last [`NightCache::prune`].
    used: Mutex<HashSet<u64>>,
    reduced: AtomicUsize,
    reused: AtomicUsize,
    /// Keep the mask and flats held even when their frames changed ([`NightCache::hold`]).
    hold: AtomicBool,
}

/// Targets reduced and reused since the last call of [`NightCache::take_counts`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CacheCounts {
    /// Sequences reduced.
    pub reduced: usize,
    /// Sequences taken from the cache.
    pub reused: usize,
}

/// What identifies one state of a file on disk: size, modification time, and (on Unix) the
/// inode and the status-change time, so that a file replaced by another of the same size
/// and modification time (`cp -p`, `touch -r`, a rename over it) is a new file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FileStamp {
    /// Size, bytes.
    pub len: u64,
    /// Modification time, ns since 1970 (0 when unknown).
    pub mtime_ns: u128,
    /// Inode number (0 off Unix).
    pub ino: u64,
    /// Status-change time, ns since 1970 (0 off Unix).
    pub ctime_ns: i128,
}

impl FileStamp {
    /// The stamp of `path` now (`None` when it cannot be read).
    pub fn of(path: &Path) -> Option<FileStamp> {
        let m = std::fs::metadata(path).ok()?;
        let mtime_ns = m
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        #[cfg(unix)]
        let (ino, ctime_ns) = {
            use std::os::unix::fs::MetadataExt;
            (m.ino(), m.ctime() as i128 * 1_000_000_000 + m.ctime_nsec() as i128)
        };
        #[cfg(not(unix))]
        let (ino, ctime_ns) = (0, 0);
        Some(FileStamp {
            len: m.len(),
            mtime_ns,
            ino,
            ctime_ns,
        })
    }
}

/// Hash of files by path and [`FileStamp`] (a file rewritten or replaced changes its key),
/// mixed with `salt`.
pub fn files_key<P: AsRef<Path>>(salt: u64, files: impl IntoIterator<Item = P>) -> u64 {
    let mut s = format!("{salt:016x}");
    for f in files {
        let f = f.as_ref();
        match FileStamp::of(f) {
            Some(st) => {
                s += &format!(
                    "\n{}\t{}\t{}\t{}\t{}",
                    f.display(),
                    st.len,
                    st.mtime_ns,
                    st.ino,
                    st.ctime_ns
                )
            }
            None => s += &format!("\n{}\t{}\t0", f.display(), u64::MAX),
        }
    }
    stable_hash(&s)
}

impl NightCache {
    /// An empty cache for runs with these settings.
    pub fn new(setup: &NightSetup) -> Self {
        let settings = serde_json::to_string(&(&setup.profile, &setup.params)).unwrap_or_default();
        NightCache {
            settings: stable_hash(&settings),
            mask: Mutex::new(None),
            flats: Mutex::new(None),
            targets: Mutex::new(HashMap::new()),
            used: Mutex::new(HashSet::new()),
            reduced: AtomicUsize::new(0),
            reused: AtomicUsize::new(0),
            hold: AtomicBool::new(false),
        }
    }

    /// While `on`, the mask and flats held are used even when their frames changed: a
    /// provisional run that gives a new target's numbers at once, before the run that
    /// rebuilds them and reduces every target again.
    pub fn hold(&self, on: bool) {
        self.hold.store(on, Ordering::Relaxed);
    }

    /// Whether a mask and flats are held, and they are those of these frames.
    pub fn holds(
        &self,
        mask_frames: &[PathBuf],
        dome_flats: &[PathBuf],
        superflat_frames: &BTreeMap<String, Vec<PathBuf>>,
    ) -> bool {
        let mask = self
            .mask
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .map(|m| m.0);
        let flats = self
            .flats
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .map(|f| f.0);
        mask == Some(self.mask_key(mask_frames)) && flats == Some(self.flats_key(dome_flats, superflat_frames))
    }

    /// Whether a mask and flats are held (whatever their frames).
    pub fn holds_any(&self) -> bool {
        self.mask.lock().unwrap_or_else(|e| e.into_inner()).is_some()
            && self.flats.lock().unwrap_or_else(|e| e.into_inner()).is_some()
    }

    fn mask_key(&self, frames: &[PathBuf]) -> u64 {
        files_key(self.settings ^ 0x6d61_736b, frames)
    }

    fn flats_key(&self, dome_flats: &[PathBuf], superflat_frames: &BTreeMap<String, Vec<PathBuf>>) -> u64 {
        let named = superflat_frames.iter().flat_map(|(filter, v)| {
            std::iter::once(PathBuf::from(format!("filter {filter}"))).chain(v.iter().cloned())
        });
        files_key(
            self.settings ^ 0x666c_6174,
            dome_flats
                .iter()
                .cloned()
                .chain(std::iter::once("superflat".into()))
                .chain(named),
        )
    }

    /// The night's bad-pixel mask from these frames: the cached one when the frames are
    /// unchanged (or while held), else `compute()` (kept). Returns the mask and its key.
    pub fn mask(&self, frames: &[PathBuf], compute: impl FnOnce() -> Option<NightMask>) -> (Option<NightMask>, u64) {
        let key = self.mask_key(frames);
        let mut slot = self.mask.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((k, m)) = slot.as_ref() {
            if *k == key || self.hold.load(Ordering::Relaxed) {
                return (m.clone(), *k);
            }
        }
        let m = compute();
        *slot = Some((key, m.clone()));
        (m, key)
    }

    /// The night's flats from these frames: cached when unchanged (or while held), else
    /// `compute()`. Returns the flats and their key.
    pub fn flats(
        &self,
        dome_flats: &[PathBuf],
        superflat_frames: &BTreeMap<String, Vec<PathBuf>>,
        compute: impl FnOnce() -> NightFlats,
    ) -> (NightFlats, u64) {
        let key = self.flats_key(dome_flats, superflat_frames);
        let mut slot = self.flats.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((k, f)) = slot.as_ref() {
            if *k == key || self.hold.load(Ordering::Relaxed) {
                return (f.clone(), *k);
            }
        }
        let f = compute();
        *slot = Some((key, f.clone()));
        (f, key)
    }

    /// The key of a sequence reduced with the mask and flats of these keys: its grouping
    /// (every frame's header values), its files, the settings.
    pub fn target_key(&self, seq: &Sequence, mask_key: u64, flats_key: u64) -> u64 {
        let grouping = serde_json::to_string(seq).unwrap_or_default();
        files_key(
            stable_hash(&format!("{:x} {mask_key:x} {flats_key:x} {grouping}", self.settings)),
            seq.files(),
        )
    }

    /// The target reduced under `key`, else `compute()` (kept).
    pub fn target(&self, key: u64, compute: impl FnOnce() -> (Target, Vec<Failure>)) -> (Target, Vec<Failure>, bool) {
        self.used.lock().unwrap_or_else(|e| e.into_inner()).insert(key);
        if let Some(c) = self.targets.lock().unwrap_or_else(|e| e.into_inner()).get(&key) {
            self.reused.fetch_add(1, Ordering::Relaxed);
            return (c.target.clone(), c.failures.clone(), true);
        }
        let (target, failures) = compute();
        self.reduced.fetch_add(1, Ordering::Relaxed);
        self.targets.lock().unwrap_or_else(|e| e.into_inner()).insert(
            key,
            CachedTarget {
                key,
                target: target.clone(),
                failures: failures.clone(),
            },
        );
        (target, failures, false)
    }

    /// Forget the targets not used since the last prune (their frames, mask or flats
    /// changed).
    pub fn prune(&self) {
        let used = std::mem::take(&mut *self.used.lock().unwrap_or_else(|e| e.into_inner()));
        self.targets
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .retain(|k, _| used.contains(k));
    }

    /// Sequences reduced and reused since the last call.
    pub fn take_counts(&self) -> CacheCounts {
        CacheCounts {
            reduced: self.reduced.swap(0, Ordering::Relaxed),
            reused: self.reused.swap(0, Ordering::Relaxed),
        }
    }

    /// Number of targets held.
    pub fn len(&self) -> usize {
        self.targets.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// Whether no target is held.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Save the reduced targets (JSON, atomically): a later run with the same settings
    /// resumes from them ([`NightCache::load`]) without reducing them again. The mask and
    /// flats are not saved (rebuilt in well under a second).
    pub fn save(&self, path: &Path) -> sofipol_calib::Result<()> {
        let mut targets: Vec<CachedTarget> = self
            .targets
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .values()
            .cloned()
            .collect();
        targets.sort_by_key(|t| t.key);
        crate::io::write_json_atomic(
            path,
            &SavedState {
                version: STATE_VERSION,
                settings: self.settings,
                targets,
            },
        )
    }

    /// Load targets saved by [`NightCache::save`]. Returns how many were loaded, or why
    /// none was (unreadable: [`Error::Io`]; another version, other settings, not a state:
    /// [`Error::SavedState`]): the cache is then left as it was.
    pub fn load(&self, path: &Path) -> crate::error::Result<usize> {
        let refused = |source| Error::SavedState {
            path: path.to_path_buf(),
            source,
        };
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let state: SavedState = serde_json::from_str(&text).map_err(|e| refused(SavedStateError::NotAState(e)))?;
        if state.version != STATE_VERSION {
            return Err(refused(SavedStateError::OtherVersion {
                found: state.version,
                reads: STATE_VERSION,
            }));
        }
        if state.settings != self.settings {
            return Err(refused(SavedStateError::OtherSettings));
        }
        let n = state.targets.len();
        let mut map = self.targets.lock().unwrap_or_else(|e| e.into_inner());
        for t in state.targets {
            map.insert(t.key, t);
        }
        Ok(n)
    }
}
