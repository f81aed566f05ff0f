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
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use sofipol_calib::Header;

use crate::catalog::{Catalog, Failure, Target};
use crate::night::{self, CacheCounts, FileStamp, NightCache, NightSetup, RunOptions};
use crate::scan::{self, Listing};
use crate::sequence::Sequence;

mod lines;
pub mod readiness;

pub use lines::{cycles_needed, target_line};
pub use readiness::{readiness, HeaderProblem, Incomplete, Readiness};

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
    /// Size, times and inode when last looked at (`None`: could not be read).
    stamp: Option<FileStamp>,
    /// When its stamp last changed.
    since: Instant,
    /// When it was first seen.
    first_seen: Instant,
    ready: bool,
}

/// A template seen, complete or not.
struct TemplateState {
    frames: usize,
    /// When its last frame arrived.
    since: Instant,
}

/// Why a template is held back, in words for the observer (`None`: not held).
fn held_reason(frames: usize, nexp: Option<u32>, counts: &[usize]) -> Option<String> {
    match nexp {
        None => Some("no TPL NEXP: waiting for the template's time-out".into()),
        Some(n) if frames < n as usize => Some(format!("{frames} of {n} frames")),
        Some(n) if frames > n as usize => Some(format!(
            "{frames} frames but TPL NEXP = {n}: the count is not trusted; waiting for the template's time-out"
        )),
        Some(n) if counts.len() < 2 => Some(format!(
            "TPL NEXP = {n} reached at one orientation (q and u need two): the count is not trusted; \
             waiting for the template's time-out"
        )),
        Some(_) if counts.iter().any(|&c| c != counts[0]) => Some(format!(
            "TPL NEXP reached with unequal dithers per orientation {counts:?}: waiting for the template's time-out"
        )),
        Some(_) => None,
    }
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
    /// Why it is held, in words.
    pub why: String,
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
    /// Frames of reduced templates that vanished from the folder (they are under the
    /// catalog's failures too), and frames refused that made a template complete.
    pub lost_frames: Vec<Failure>,
    /// Wall time of the update, s.
    pub seconds: f64,
}

/// What earlier updates saw: the inputs of the flats, mask and calibration, the targets.
#[derive(Default)]
struct Seen {
    catalog: Option<Catalog>,
    flats: Option<crate::catalog::provenance::FlatProvenance>,
    mask_from: Option<Vec<String>>,
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
    /// Templates reduced once: never held back again (a frame lost later makes them
    /// partial, it never takes them out of the catalog).
    reduced: HashSet<String>,
    /// Ready frames that vanished from the folder, with the template their header named.
    vanished: BTreeMap<PathBuf, Option<String>>,
    /// Watched folders that are gone or cannot be listed, with why (no update meanwhile:
    /// the catalog stays as last written).
    missing_roots: Vec<(PathBuf, String)>,
    /// Per-target outputs (DS9 regions, FITS products) written for each target reduced.
    outputs: Option<crate::products::Outputs>,
}

/// Headers read, by path, with the stamp of the file they were read from.
#[derive(Default)]
struct HeaderCache(Mutex<HashMap<PathBuf, (FileStamp, Header)>>);

impl HeaderCache {
    /// The header of `p`: the one read before when the file is unchanged, else read now.
    fn read(&self, p: &Path) -> sofipol_calib::Result<Header> {
        let stamp = FileStamp::of(p);
        if let Some(st) = stamp {
            if let Some((s, h)) = self.0.lock().unwrap_or_else(|e| e.into_inner()).get(p) {
                if *s == st {
                    return Ok(h.clone());
                }
            }
        }
        let h = sofipol_calib::fits::read_header(p)?;
        if let Some(st) = stamp {
            self.0
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(p.to_path_buf(), (st, h.clone()));
        }
        Ok(h)
    }

    /// The header last read from `p`, whatever the file is now (a file that vanished).
    fn last(&self, p: &Path) -> Option<Header> {
        self.0
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(p)
            .map(|(_, h)| h.clone())
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
            reduced: HashSet::new(),
            vanished: BTreeMap::new(),
            missing_roots: Vec::new(),
            outputs: None,
        }
    }

    /// Write each target's outputs (DS9 regions, FITS products) as it is reduced; targets
    /// taken unchanged from the cache keep the files written when they were reduced.
    pub fn set_outputs(&mut self, outputs: crate::products::Outputs) {
        self.outputs = Some(outputs);
    }

    /// The outputs, to finish them when the night is over.
    pub fn take_outputs(&mut self) -> Option<crate::products::Outputs> {
        self.outputs.take()
    }

    /// The cache of reduced targets (to save it, or to load a saved one before the first
    /// update).
    pub fn cache(&self) -> &NightCache {
        &self.cache
    }

    /// Start from a catalog written earlier: its targets are not reported again as new.
    pub fn resume_from(&mut self, catalog: Catalog) {
        self.seen.standards = catalog.provenance.live_standards.clone().unwrap_or_default();
        self.seen.flats = catalog.provenance.flat.clone();
        self.seen.mask_from = catalog.provenance.night_bad_pixel_mask_from.clone();
        self.reduced
            .extend(catalog.targets.iter().filter_map(|t| t.sequence.clone()));
        self.seen.catalog = Some(catalog);
    }

    /// Look at the folders; reduce when a template completed, timed out or a calibration
    /// frame arrived (`finish`: reduce every template now, complete or not, as at the end
    /// of the night). `None` when nothing changed, or when a watched folder is gone or
    /// cannot be listed ([`LiveNight::missing_roots`]: the catalog is then kept as it is).
    pub fn update(&mut self, finish: bool) -> Option<Update> {
        let t0 = Instant::now();
        self.missing_roots = self
            .roots
            .iter()
            .filter_map(|r| root_problem(r).map(|why| (r.clone(), why)))
            .collect();
        if !self.missing_roots.is_empty() {
            // Looked at again when they are back.
            self.dirty = true;
            return None;
        }
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
        let ready_listing = |files: Vec<PathBuf>| Listing {
            files,
            unreadable_dirs: listing.unreadable_dirs.clone(),
            duplicates: listing.duplicates.clone(),
        };
        // First pass: which templates are complete. A held template whose missing frames
        // are present but refused (a bad keyword, a broken file) is complete too: a second
        // pass keeps it.
        let mut force: HashSet<String> = HashSet::new();
        let mut plan = self.plan(ready_listing(ready.clone()), finish, &force, t0);
        if !self.held.is_empty() {
            force = self.complete_by_refused(&plan);
            if !force.is_empty() {
                plan = self.plan(ready_listing(ready), finish, &force, t0);
            }
        }
        let setup = &self.setup;
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
            outputs: self.outputs.as_ref(),
            ..Default::default()
        };
        let out = night::run_night(&plan, setup, &opts);
        self.cache.hold(false);
        self.dirty = provisional;
        self.rebuild = provisional;
        self.cache.prune();
        let counts = self.cache.take_counts();
        let mut catalog = out.catalog;
        self.reduced
            .extend(plan.sequences.iter().chain(&plan.standards).map(|q| q.id.clone()));
        // Frames of reduced templates that vanished: named in the catalog's failures (a
        // frame moved or renamed within the folder is found again under its new name).
        let lost_frames: Vec<Failure> = self
            .vanished
            .iter()
            .filter(|(_, id)| id.as_ref().is_some_and(|id| self.reduced.contains(id)))
            .map(|(p, _)| Failure {
                file: p.display().to_string(),
                error: "vanished from the folder after it arrived: its template was reduced without it".into(),
            })
            .collect();
        catalog.failures.extend(lost_frames.iter().cloned());
        catalog.failures.sort_by(|a, b| a.file.cmp(&b.file));
        let standards: Vec<String> = plan.standards.iter().map(|q| q.id.clone()).collect();
        catalog.provenance.live_standards = Some(standards.clone());
        let (new_targets, changed) = self.compare(&catalog, &standards, &lost_frames);
        self.seen = Seen {
            flats: catalog.provenance.flat.clone(),
            mask_from: catalog.provenance.night_bad_pixel_mask_from.clone(),
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
            lost_frames,
            seconds: t0.elapsed().as_secs_f64(),
        })
    }

    /// Plan the night's ready files, holding back the templates still being observed
    /// (`force`: templates kept whatever their count). Sets `held`.
    fn plan(&mut self, listing: Listing, finish: bool, force: &HashSet<String>, t0: Instant) -> night::NightPlan {
        let templates = std::cell::RefCell::new(std::mem::take(&mut self.templates));
        let held = std::cell::RefCell::new(Vec::new());
        let timeout = self.options.template_timeout;
        let reduced = &self.reduced;
        let keep = |q: &Sequence| {
            let counts: Vec<usize> = q.orientations.iter().map(|o| o.exposures.len()).collect();
            let frames: usize = counts.iter().sum();
            let mut t = templates.borrow_mut();
            let st = t.entry(q.id.clone()).or_insert(TemplateState { frames, since: t0 });
            if st.frames != frames {
                *st = TemplateState { frames, since: t0 };
            }
            let nexp = q.orientations.iter().flat_map(|o| &o.exposures).find_map(|e| e.nexp);
            let idle = t0.saturating_duration_since(st.since);
            let why = held_reason(frames, nexp, &counts);
            let keep = finish || why.is_none() || idle >= timeout || reduced.contains(&q.id) || force.contains(&q.id);
            if !keep {
                held.borrow_mut().push(Held {
                    id: q.id.clone(),
                    frames,
                    nexp,
                    idle_s: idle.as_secs_f64(),
                    why: why.unwrap_or_default(),
                });
            }
            keep
        };
        let setup = &self.setup;
        let headers = &self.headers;
        let read_header = |p: &Path| headers.read(p);
        let plan = night::plan_listing(
            listing,
            &setup.profile,
            setup.params.flat_options.max_frames,
            None,
            |q| crate::calibration::is_standard_sequence(q, &setup.profile),
            keep,
            &read_header,
        );
        self.templates = templates.into_inner();
        self.held = held.into_inner();
        plan
    }

    /// The held templates whose missing frames are all present but refused: a refused
    /// file counts for the template its header names (object and template start) or, when
    /// its header cannot be read, for the template that was receiving frames when it
    /// arrived (the held one whose last frame came before it, latest first).
    fn complete_by_refused(&self, plan: &night::NightPlan) -> HashSet<String> {
        let mut refused: HashMap<String, usize> = HashMap::new();
        // A duplicate of a frame present is no missing frame.
        let refused_files = plan
            .failures
            .iter()
            .chain(&plan.not_science)
            .filter(|f| !f.error.starts_with("duplicate of "));
        for f in refused_files {
            let p = PathBuf::from(&f.file);
            let Some(state) = self.files.get(&p) else { continue };
            let named = self
                .headers
                .read(&p)
                .ok()
                .and_then(|h| sofipol_calib::classify::template_id(&h, &self.setup.profile));
            let id = match named {
                Some(id) => Some(id),
                None => self
                    .held
                    .iter()
                    .filter_map(|h| self.templates.get(&h.id).map(|t| (h, t.since)))
                    .filter(|(_, since)| *since <= state.first_seen)
                    .max_by_key(|(_, since)| *since)
                    .map(|(h, _)| h.id.clone()),
            };
            if let Some(id) = id {
                *refused.entry(id).or_default() += 1;
            }
        }
        self.held
            .iter()
            .filter(|h| {
                h.nexp.is_some_and(|n| {
                    h.frames < n as usize && h.frames + refused.get(&h.id).copied().unwrap_or(0) >= n as usize
                })
            })
            .map(|h| h.id.clone())
            .collect()
    }

    /// Watched folders that are gone or cannot be listed at the last look, with why.
    pub fn missing_roots(&self) -> &[(PathBuf, String)] {
        &self.missing_roots
    }

    /// Whether the next [`LiveNight::update`] has work whatever arrives (after a
    /// provisional update, or when files changed).
    pub fn wants_update(&self) -> bool {
        self.dirty
    }

    /// Whether every template seen is reduced and no file is being written.
    pub fn settled(&self) -> bool {
        self.missing_roots.is_empty() && self.held.is_empty() && !self.dirty && self.files.values().all(|f| f.ready)
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
        let gone: Vec<PathBuf> = self
            .files
            .iter()
            .filter(|(p, _)| listing.files.binary_search(p).is_err())
            .map(|(p, _)| p.clone())
            .collect();
        for p in gone {
            if self.files.remove(&p).is_some_and(|st| st.ready) {
                let id = self
                    .headers
                    .last(&p)
                    .and_then(|h| sofipol_calib::classify::template_id(&h, &self.setup.profile));
                self.vanished.insert(p, id);
            }
            self.dirty = true;
        }
        for p in &listing.files {
            self.vanished.remove(p);
            let stamp = FileStamp::of(p);
            let st = self.files.entry(p.clone()).or_insert(FileState {
                stamp: None,
                since: now,
                first_seen: now,
                ready: false,
            });
            if st.stamp != stamp {
                let was_ready = st.ready;
                *st = FileState {
                    stamp,
                    since: now,
                    first_seen: st.first_seen,
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
                        waiting.push((p.clone(), why.to_string()));
                    }
                }
            }
        }
        // A vanished frame found again under another name (moved within the folder) is
        // not lost: the same template, exposure and orientation is present.
        if !self.vanished.is_empty() {
            let present: HashSet<(String, Option<u32>, String)> = listing
                .files
                .iter()
                .filter(|p| self.files.get(*p).is_some_and(|st| st.ready))
                .filter_map(|p| self.headers.read(p).ok())
                .filter_map(|h| exposure_key(&h, &self.setup.profile))
                .collect();
            let profile = &self.setup.profile;
            let headers = &self.headers;
            self.vanished.retain(|p, _| {
                headers
                    .last(p)
                    .and_then(|h| exposure_key(&h, profile))
                    .is_none_or(|k| !present.contains(&k))
            });
        }
        waiting
    }

    /// The targets new since the last update, and those whose numbers changed with why.
    fn compare(
        &self,
        catalog: &Catalog,
        standards: &[String],
        lost: &[Failure],
    ) -> (Vec<Target>, Vec<(String, String)>) {
        let before: HashMap<&str, &Target> = self
            .seen
            .catalog
            .iter()
            .flat_map(|c| &c.targets)
            .filter_map(|t| t.sequence.as_deref().map(|s| (s, t)))
            .collect();
        let mut reasons = Vec::new();
        let prov = &catalog.provenance;
        if self.seen.flats.is_some() && self.seen.flats != prov.flat {
            reasons.push(format!("the flats changed (now {})", prov.flat_mode()));
        }
        if self.seen.mask_from.is_some() && self.seen.mask_from != prov.night_bad_pixel_mask_from {
            reasons.push("the bad-pixel mask was detected on more frames".into());
        }
        let added = standards.iter().filter(|s| !self.seen.standards.contains(s)).count();
        if added > 0 {
            reasons.push(format!(
                "{added} standard(s) arrived: {} now calibrate the night",
                standards.len()
            ));
        }
        if !lost.is_empty() {
            reasons.push(format!(
                "{} frame(s) vanished from the folder: {}",
                lost.len(),
                lost.iter().map(|f| f.file.as_str()).collect::<Vec<_>>().join(", ")
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

/// Why a watched folder cannot be followed now (`None`: it can): gone, not a folder, or
/// not listable.
fn root_problem(root: &Path) -> Option<String> {
    match std::fs::metadata(root) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Some("gone (removed or renamed)".into()),
        Err(e) => Some(format!("cannot be read: {e}")),
        Ok(m) if !m.is_dir() => Some("no longer a folder".into()),
        Ok(_) => std::fs::read_dir(root).err().map(|e| format!("cannot be listed: {e}")),
    }
}

/// One exposure's identity in its header: template, exposure number and rotator angle
/// (`None` for a file without a template).
fn exposure_key(h: &Header, profile: &sofipol_calib::Profile) -> Option<(String, Option<u32>, String)> {
    let id = sofipol_calib::classify::template_id(h, profile)?;
    let k = &profile.keywords;
    let expno = h.opt_f64(&k.tpl_expno).ok().flatten().map(|x| x as u32);
    let pa = h.get_str(&k.posang).unwrap_or_default();
    Some((id, expno, pa))
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
