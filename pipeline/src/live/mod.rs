//! Live reduction: a night reduced while it is observed.
//!
//! Each [`LiveNight::update`] lists the night's folders, waits for frames still being
//! written ([`readiness()`]), holds back templates still being observed (fewer frames than
//! `TPL NEXP`, unless no frame has arrived for the time-out: an aborted template), and
//! reduces the night's complete templates as `sofipol night` does
//! ([`run_night`](crate::night::run_night)), with a [`NightCache`]: a target is reduced
//! again only when its frames, the night's bad-pixel mask or its flats changed. The
//! standards and the calibration are always redone (a few hundredths of a second), so a
//! standard arriving late re-calibrates every target. When every template is complete
//! the catalog is the one `sofipol night` writes on the same frames.
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant, SystemTime};

use sofipol_calib::Header;

use crate::catalog::{Catalog, Target};
use crate::night::{self, CacheCounts, NightCache, NightSetup, RunOptions};
use crate::scan::{self, Listing};
use crate::sequence::Sequence;

mod lines;
pub mod readiness;

pub use lines::{cycles_needed, target_line};
pub use readiness::{readiness, Readiness};

/// How long to wait before giving up on a template or a file.
#[derive(Debug, Clone, Copy)]
pub struct LiveOptions {
    /// A template with fewer frames than `TPL NEXP` (or without `TPL NEXP`) is reduced as it
    /// is once no frame of it has arrived for this long (aborted).
    pub template_timeout: Duration,
    /// A file that stays incomplete and unchanged for this long is handed to the scan,
    /// which reports it (truncated), instead of being waited for.
    pub file_timeout: Duration,
}

impl Default for LiveOptions {
    fn default() -> Self {
        LiveOptions {
            template_timeout: Duration::from_secs(600),
            file_timeout: Duration::from_secs(120),
        }
    }
}

/// A file seen in the folder.
struct FileState {
    len: u64,
    modified: Option<SystemTime>,
    /// When its size or time last changed.
    since: Instant,
    ready: bool,
}

/// A template seen, complete or not.
struct TemplateState {
    frames: usize,
    /// When its last frame arrived.
    since: Instant,
}

/// A template held back: still being observed.
#[derive(Debug, Clone, PartialEq)]
pub struct Held {
    /// `object@tpl_start`.
    pub id: String,
    /// Frames present.
    pub frames: usize,
    /// `TPL NEXP`, when the frames say.
    pub nexp: Option<u32>,
    /// Seconds since its last frame arrived.
    pub idle_s: f64,
}

/// What one update did.
pub struct Update {
    /// Reduced with the mask and flats of the update before, although new frames change
    /// them: the next update rebuilds them and reduces every target again
    /// ([`LiveNight::wants_update`]).
    pub provisional: bool,
    /// The catalog of the complete templates (provenance included).
    pub catalog: Catalog,
    /// Targets reduced for the first time, in catalog order.
    pub new_targets: Vec<Target>,
    /// Earlier targets whose numbers changed, and why (in words).
    pub changed: Vec<(String, String)>,
    /// Templates still being observed.
    pub held: Vec<Held>,
    /// Files still being written (path, why).
    pub waiting: Vec<(PathBuf, String)>,
    /// Templates reduced and taken from the cache.
    pub counts: CacheCounts,
    /// The calibration's lines for a terminal.
    pub calibration_lines: Vec<String>,
    /// Wall time of the update, s.
    pub seconds: f64,
}

/// What earlier updates saw: the inputs of the flats, mask and calibration, the targets.
#[derive(Default)]
struct Seen {
    catalog: Option<Catalog>,
    flats: Option<serde_json::Value>,
    mask_from: Option<serde_json::Value>,
    standards: Vec<String>,
}

/// A night followed while it is observed.
pub struct LiveNight {
    setup: NightSetup,
    roots: Vec<PathBuf>,
    options: LiveOptions,
    cache: NightCache,
    files: BTreeMap<PathBuf, FileState>,
    templates: HashMap<String, TemplateState>,
    held: Vec<Held>,
    seen: Seen,
    dirty: bool,
    /// The last update was provisional: this one rebuilds the mask and flats.
    rebuild: bool,
    /// Files still being written at the last look.
    waiting: Vec<(PathBuf, String)>,
    headers: HeaderCache,
}

/// Headers read, by path, with the size and time of the file they were read from.
#[derive(Default)]
struct HeaderCache(Mutex<HashMap<PathBuf, StampedHeader>>);

/// A header with the size and modification time of the file it was read from.
type StampedHeader = (u64, Option<SystemTime>, Header);

impl HeaderCache {
    /// The header of `p`: the one read before when the file is unchanged, else read now.
    fn read(&self, p: &Path) -> sofipol_calib::Result<Header> {
        let meta = std::fs::metadata(p).ok();
        let stamp = (
            meta.as_ref().map(|m| m.len()),
            meta.as_ref().and_then(|m| m.modified().ok()),
        );
        if let (Some(len), modified) = stamp {
            if let Some((l, m, h)) = self.0.lock().unwrap_or_else(|e| e.into_inner()).get(p) {
                if *l == len && *m == modified {
                    return Ok(h.clone());
                }
            }
        }
        let h = sofipol_calib::fits::read_header(p)?;
        if let (Some(len), modified) = stamp {
            self.0
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(p.to_path_buf(), (len, modified, h.clone()));
        }
        Ok(h)
    }
}

impl LiveNight {
    /// Follow the night in `roots` with these settings.
    pub fn new(setup: NightSetup, roots: Vec<PathBuf>, options: LiveOptions) -> Self {
        let cache = NightCache::new(&setup);
        LiveNight {
            setup,
            roots,
            options,
            cache,
            files: BTreeMap::new(),
            templates: HashMap::new(),
            held: Vec::new(),
            seen: Seen::default(),
            dirty: true,
            rebuild: false,
            waiting: Vec::new(),
            headers: HeaderCache::default(),
        }
    }

    /// The cache of reduced targets (to save it, or to load a saved one before the first
    /// update).
    pub fn cache(&self) -> &NightCache {
        &self.cache
    }

    /// Start from a catalog written earlier: its targets are not reported again as new.
    pub fn resume_from(&mut self, catalog: Catalog) {
        self.seen.standards = catalog
            .provenance
            .get("live_standards")
            .and_then(|v| serde_json::from_value(v.clone()).ok())
            .unwrap_or_default();
        self.seen.flats = catalog.provenance.get("flat").cloned();
        self.seen.mask_from = catalog.provenance.get("night_bad_pixel_mask_from").cloned();
        self.seen.catalog = Some(catalog);
    }

    /// Look at the folders; reduce when a template completed, timed out or a calibration
    /// frame arrived (`finish`: reduce every template now, complete or not, as at the end
    /// of the night). `None` when nothing changed.
    pub fn update(&mut self, finish: bool) -> Option<Update> {
        let t0 = Instant::now();
        let listing = scan::list(&self.roots);
        let waiting = self.look_at_files(&listing, t0);
        self.waiting = waiting.clone();
        let timed_out = self
            .held
            .iter()
            .any(|h| self.idle(&h.id, t0) >= self.options.template_timeout);
        let finishing = finish && !self.held.is_empty();
        if !(self.dirty || timed_out || finishing) {
            return None;
        }
        self.dirty = false;
        let ready: Vec<PathBuf> = listing
            .files
            .iter()
            .filter(|f| self.files.get(*f).is_some_and(|s| s.ready))
            .cloned()
            .collect();
        let ready_listing = Listing {
            files: ready,
            unreadable_dirs: listing.unreadable_dirs,
            duplicates: listing.duplicates,
        };
        let templates = std::cell::RefCell::new(std::mem::take(&mut self.templates));
        let held = std::cell::RefCell::new(Vec::new());
        let timeout = self.options.template_timeout;
        let keep = |q: &Sequence| {
            let frames: usize = q.orientations.iter().map(|o| o.exposures.len()).sum();
            let mut t = templates.borrow_mut();
            let st = t.entry(q.id.clone()).or_insert(TemplateState { frames, since: t0 });
            if st.frames != frames {
                *st = TemplateState { frames, since: t0 };
            }
            let nexp = q.orientations.iter().flat_map(|o| &o.exposures).find_map(|e| e.nexp);
            let idle = t0.saturating_duration_since(st.since);
            let complete = nexp.is_some_and(|n| frames >= n as usize);
            let keep = finish || complete || idle >= timeout;
            if !keep {
                held.borrow_mut().push(Held {
                    id: q.id.clone(),
                    frames,
                    nexp,
                    idle_s: idle.as_secs_f64(),
                });
            }
            keep
        };
        let setup = &self.setup;
        let headers = &self.headers;
        let read_header = |p: &Path| headers.read(p);
        let plan = night::plan_listing(
            ready_listing,
            &setup.profile,
            setup.params.flat_options.max_frames,
            None,
            |q| crate::calibration::is_standard_sequence(q, &setup.profile),
            keep,
            &read_header,
        );
        self.templates = templates.into_inner();
        self.held = held.into_inner();
        // New frames for the mask or the flats: first a provisional run with those held
        // (a new target's numbers at once), then, at the next update, the run that rebuilds
        // them and reduces every target again. A finishing update is never provisional.
        let provisional = !finish
            && !self.rebuild
            && self.cache.holds_any()
            && !self
                .cache
                .holds(&plan.mask_frames, &plan.dome_flats, &plan.superflat_frames);
        self.cache.hold(provisional);
        let opts = RunOptions {
            night_mask: true,
            inputs: self.roots.clone(),
            cache: Some(&self.cache),
            ..Default::default()
        };
        let out = night::run_night(&plan, setup, &opts);
        self.cache.hold(false);
        self.dirty = provisional;
        self.rebuild = provisional;
        self.cache.prune();
        let counts = self.cache.take_counts();
        let mut catalog = out.catalog;
        let standards: Vec<String> = plan.standards.iter().map(|q| q.id.clone()).collect();
        catalog.provenance["live_standards"] = serde_json::json!(standards);
        let (new_targets, changed) = self.compare(&catalog, &standards);
        self.seen = Seen {
            flats: catalog.provenance.get("flat").cloned(),
            mask_from: catalog.provenance.get("night_bad_pixel_mask_from").cloned(),
            standards,
            catalog: Some(catalog.clone()),
        };
        Some(Update {
            provisional,
            catalog,
            new_targets,
            changed,
            held: self.held.clone(),
            waiting,
            counts,
            calibration_lines: out.summary.lines,
            seconds: t0.elapsed().as_secs_f64(),
        })
    }

    /// Whether the next [`LiveNight::update`] has work whatever arrives (after a
    /// provisional update, or when files changed).
    pub fn wants_update(&self) -> bool {
        self.dirty
    }

    /// Whether every template seen is reduced and no file is being written.
    pub fn settled(&self) -> bool {
        self.held.is_empty() && !self.dirty && self.files.values().all(|f| f.ready)
    }

    /// Files still being written at the last look (path, why), whether or not that look
    /// led to a reduction.
    pub fn waiting(&self) -> &[(PathBuf, String)] {
        &self.waiting
    }

    /// Templates still being observed.
    pub fn held(&self) -> &[Held] {
        &self.held
    }

    /// Time since the last frame of template `id` arrived.
    fn idle(&self, id: &str, now: Instant) -> Duration {
        self.templates
            .get(id)
            .map(|t| now.saturating_duration_since(t.since))
            .unwrap_or_default()
    }

    /// Note new, changed and vanished files; check the readiness of those not yet
    /// complete. Sets `dirty` when the set of complete files changed. Returns the files
    /// still being written.
    fn look_at_files(&mut self, listing: &Listing, now: Instant) -> Vec<(PathBuf, String)> {
        let mut waiting = Vec::new();
        let before = self.files.len();
        self.files.retain(|p, _| listing.files.binary_search(p).is_ok());
        if self.files.len() != before {
            self.dirty = true;
        }
        for p in &listing.files {
            let meta = std::fs::metadata(p).ok();
            let len = meta.as_ref().map(|m| m.len()).unwrap_or(0);
            let modified = meta.as_ref().and_then(|m| m.modified().ok());
            let st = self.files.entry(p.clone()).or_insert(FileState {
                len: u64::MAX,
                modified: None,
                since: now,
                ready: false,
            });
            let changed = st.len != len || st.modified != modified;
            if changed {
                let was_ready = st.ready;
                *st = FileState {
                    len,
                    modified,
                    since: now,
                    ready: false,
                };
                if was_ready {
                    self.dirty = true;
                }
            }
            if st.ready {
                continue;
            }
            match readiness(p) {
                Readiness::Complete => {
                    st.ready = true;
                    self.dirty = true;
                }
                Readiness::Incomplete(why) => {
                    if now.saturating_duration_since(st.since) >= self.options.file_timeout {
                        // Given up on: the scan reports it as unreadable.
                        st.ready = true;
                        self.dirty = true;
                    } else {
                        waiting.push((p.clone(), why));
                    }
                }
            }
        }
        waiting
    }

    /// The targets new since the last update, and those whose numbers changed with why.
    fn compare(&self, catalog: &Catalog, standards: &[String]) -> (Vec<Target>, Vec<(String, String)>) {
        let before: HashMap<&str, &Target> = self
            .seen
            .catalog
            .iter()
            .flat_map(|c| &c.targets)
            .filter_map(|t| t.sequence.as_deref().map(|s| (s, t)))
            .collect();
        let mut reasons = Vec::new();
        if self.seen.flats.is_some() && self.seen.flats.as_ref() != catalog.provenance.get("flat") {
            let mode = catalog.provenance["flat"]["mode"]
                .as_str()
                .unwrap_or("none")
                .to_string();
            reasons.push(format!("the flats changed (now {mode})"));
        }
        if self.seen.mask_from.is_some()
            && self.seen.mask_from.as_ref() != catalog.provenance.get("night_bad_pixel_mask_from")
        {
            reasons.push("the bad-pixel mask was detected on more frames".into());
        }
        let added = standards.iter().filter(|s| !self.seen.standards.contains(s)).count();
        if added > 0 {
            reasons.push(format!(
                "{added} standard(s) arrived: {} now calibrate the night",
                standards.len()
            ));
        }
        let why = if reasons.is_empty() {
            "recalibrated".to_string()
        } else {
            reasons.join("; ")
        };
        let mut new_targets = Vec::new();
        let mut changed = Vec::new();
        for t in &catalog.targets {
            match t.sequence.as_deref().and_then(|s| before.get(s)) {
                None => new_targets.push(t.clone()),
                Some(old) if !same_numbers(old, t) => {
                    changed.push((t.sequence.clone().unwrap_or_default(), why.clone()));
                }
                Some(_) => {}
            }
        }
        (new_targets, changed)
    }
}

/// Whether two entries of a target carry the same status and polarimetry.
fn same_numbers(a: &Target, b: &Target) -> bool {
    a.status == b.status
        && a.components.len() == b.components.len()
        && a.components.iter().zip(&b.components).all(|(x, y)| {
            let same = |p: f64, q: f64| p == q || (p.is_nan() && q.is_nan());
            same(x.q, y.q) && same(x.u, y.u) && same(x.sigma_q, y.sigma_q) && same(x.sigma_u, y.sigma_u)
        })
}
