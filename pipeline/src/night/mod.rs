//! A whole night, one way: every command that reduces frames (`night`, `target`, `demo`,
//! `calib`) and every harness goes through [`run_night`].
//!
//! ```text
//! plan (scan, classify, group, standards apart, mask/superflat frames, shard)
//!   -> night-wide bad-pixel mask  ┐ in parallel
//!   -> night's flats              ┘ (dome flats, else a superflat; or a calibration flat)
//!   -> every science sequence reduced in parallel (reduce::run::reduce_sequence), with its
//!      FITS products written while its frames are in memory (when asked: crate::products)
//!   -> standards reduced as single stars -> calibration -> targets re-solved
//!   -> per-target figures from the calibrated catalog (in parallel; when asked)
//!   -> catalog with provenance
//! ```
//! Nothing dies on one bad input: unreadable, foreign and non-polarimetric files are
//! reported under `failures` with their reason; a degraded sequence is flagged; every other
//! target is still reduced.
use std::path::PathBuf;
use std::time::Instant;

use ndarray::Array2;
use rayon::prelude::*;
use sofipol_calib::flat::FlatSet;
use sofipol_calib::Profile;

use crate::calibration::{CalibSetup, Calibration, CalibrationSummary};
use crate::catalog::{Catalog, Failure, Provenance, Target, SCHEMA_VERSION};
use crate::plots::target::{FigureInputs, TargetFigure};
use crate::reduce::run::{reduce_sequence, StageTimes};
use crate::reduce::TargetParams;
use crate::sequence::Sequence;

mod cache;
mod calibrate;
mod flats;
mod log;
mod mask;
mod merge;
mod plan;

pub use crate::products::badpix::NightMask;
pub use crate::products::{products_dir, slug};
pub use cache::{files_key, CacheCounts, CachedTarget, FileStamp, NightCache};
pub use calibrate::{finish, prepare, reduce_standards, Prepared};
pub use flats::{night_flats, NightFlats};
pub use log::{frame_list_path, log_path, log_ut, night_frame_list, night_log, write_night_log};
pub use mask::night_bad_pixel_mask;
pub use merge::merge;
pub use plan::{pick_superflat_frames, plan, plan_frame_list, plan_listing, stable_hash, NightPlan, Shard};

/// Most frames stacked for the night-wide bad-pixel mask.
pub const MASK_FRAMES: usize = 15;

/// Everything a reduction is set up with, validated before any frame is read.
#[derive(Debug, Clone)]
pub struct NightSetup {
    /// The instrument profile.
    pub profile: Profile,
    /// The reduction settings.
    pub params: TargetParams,
    /// The calibration settings, standards table and any external calibration.
    pub calibration: CalibSetup,
}

impl NightSetup {
    /// The plan of a night in `roots` with these settings: see [`plan`].
    pub fn plan(&self, roots: &[PathBuf], shard: Option<Shard>) -> NightPlan {
        plan(roots, &self.profile, self.params.flat_options.max_frames, shard, |q| {
            crate::calibration::is_standard_sequence(q, &self.profile)
        })
    }

    /// [`NightSetup::plan`] of the command line's inputs: a single set-of-frames file
    /// ([`crate::frame_list`]) is read and planned with its roles ([`plan_frame_list`]);
    /// directories and FITS files are searched and classified by header. A set-of-frames
    /// file among other inputs, or a bad one, is an error naming its file and line.
    pub fn plan_inputs(
        &self,
        roots: &[PathBuf],
        shard: Option<Shard>,
    ) -> Result<NightPlan, crate::frame_list::FrameListError> {
        let lists: Vec<&PathBuf> = roots.iter().filter(|r| crate::frame_list::is_frame_list(r)).collect();
        match (lists.as_slice(), roots.len()) {
            ([], _) => Ok(self.plan(roots, shard)),
            ([one], 1) => {
                let list = crate::frame_list::read(one)?;
                Ok(plan_frame_list(
                    &list,
                    &self.profile,
                    self.params.flat_options.max_frames,
                    shard,
                    |q| crate::calibration::is_standard_sequence(q, &self.profile),
                ))
            }
            (some, _) => Err(crate::frame_list::FrameListError {
                file: some[0].to_path_buf(),
                line: None,
                key: "inputs".into(),
                value: format!("{} input(s)", roots.len()),
                reason: "a set-of-frames file is given alone, not with directories, FITS files or other lists".into(),
            }),
        }
    }
}

/// What a caller is told while the night runs.
#[derive(Default, Clone, Copy)]
pub struct Hooks<'a> {
    /// Called once per finished target (progress).
    pub on_done: Option<&'a (dyn Fn(&Target) + Sync)>,
    /// Called with each science target's figure once the calibration has re-solved the
    /// catalog (in parallel): the figure draws the catalog's final numbers. When given, the
    /// cut-outs the figure shows are stacked while each target's frames are in memory.
    pub on_figure: Option<&'a (dyn Fn(&TargetFigure) + Sync)>,
    /// Called with each science target as its reduction ends (in parallel, before the
    /// calibration): its measured positions and frames, e.g. for DS9 region files
    /// ([`crate::products::regions`]). Not called for targets taken from a cache.
    pub on_reduced: Option<&'a (dyn Fn(&crate::reduce::run::TargetOutcome) + Sync)>,
}

/// How a night is run: what differs between the commands.
#[derive(Default, Clone)]
pub struct RunOptions<'a> {
    /// Detect the detector's defects once for the night (else per target, as a single
    /// sequence needs).
    pub night_mask: bool,
    /// The shard of the night reduced, for the provenance and the flats' failures.
    pub shard: Option<Shard>,
    /// The inputs as given (provenance).
    pub inputs: Vec<PathBuf>,
    /// Progress and products.
    pub hooks: Hooks<'a>,
    /// Results of earlier runs over the same night, reused where their inputs are
    /// unchanged and updated with this run's (live reduction). Not used for the targets
    /// when figures are drawn (`hooks.on_figure` or `outputs` with figures: every target's
    /// figure needs its frames); region files and FITS products are written for the
    /// targets reduced, not for those taken from the cache.
    pub cache: Option<&'a NightCache>,
    /// The per-target outputs written as the night runs (figures, DS9 regions, FITS
    /// products: [`crate::products::Outputs`]): each target's regions and FITS products
    /// while its frames are in memory (a FITS file not written flags the target), its
    /// figure once calibrated, the night's bad-pixel mask once detected.
    pub outputs: Option<&'a crate::products::Outputs>,
}

/// Wall time of the night's stages, seconds.
#[derive(Debug, Clone, Copy, Default)]
pub struct NightSeconds {
    /// The bad-pixel mask (in parallel with the flats).
    pub mask: f64,
    /// The flats (in parallel with the mask).
    pub flats: f64,
    /// Reducing the science sequences.
    pub reduce: f64,
    /// Reducing the standards and calibrating.
    pub calibration: f64,
    /// Drawing the figures after the calibration: all of them when FITS products are
    /// written, else none (they are drawn during the reduction, as the workers run out of
    /// targets, and counted in `reduce`); 0 without figures.
    pub figures: f64,
}

/// What a night produced.
pub struct NightOutput {
    /// The catalog, provenance included.
    pub catalog: Catalog,
    /// Each science target's stage times, in catalog order.
    pub times: Vec<StageTimes>,
    /// The calibration applied (measured from the standards or read), if any.
    pub calibration: Option<Calibration>,
    /// What the calibration did, in lines for a terminal.
    pub summary: CalibrationSummary,
    /// The night's bad-pixel mask, when detected once for the night.
    pub mask: Option<NightMask>,
    /// The night's flats.
    pub flats: NightFlats,
    /// Wall times of the stages.
    pub seconds: NightSeconds,
}

/// Reduce a planned night (in the current rayon pool): the bad-pixel mask and the flats,
/// every science sequence, the standards and the calibration, the provenance.
pub fn run_night(plan: &NightPlan, setup: &NightSetup, opts: &RunOptions) -> NightOutput {
    let (profile, params) = (&setup.profile, &setup.params);
    let compute_mask = || {
        (opts.night_mask && !params.no_detect_bad_pixels)
            .then(|| night_bad_pixel_mask(plan, profile, params, MASK_FRAMES))
            .flatten()
    };
    let compute_flats = || night_flats(&plan.dome_flats, &plan.superflat_frames, profile, params);
    let (((mask, mask_key), t_mask), ((flats, flats_key), t_flats)) = rayon::join(
        || {
            timed(|| match opts.cache {
                Some(c) => c.mask(&plan.mask_frames, compute_mask),
                None => (compute_mask(), 0),
            })
        },
        || {
            timed(|| match opts.cache {
                Some(c) => c.flats(&plan.dome_flats, &plan.superflat_frames, compute_flats),
                None => (compute_flats(), 0),
            })
        },
    );
    if let (Some(o), Some(m)) = (opts.outputs, &mask) {
        o.night_mask(m, params);
    }
    let figures_wanted = opts.hooks.on_figure.is_some() || opts.outputs.is_some_and(|o| o.wants_figures());
    let mask_array = mask.as_ref().map(|m| &m.mask);
    // The calibration is chosen before the science targets are reduced (the standards
    // first), so that each target's figure can be drawn from the numbers the calibrated
    // catalog will hold as soon as the target is reduced. The workers take the targets in
    // turn and draw queued figures only when no target is left to take: the figures fill the
    // cores the reduction's last targets leave idle, the rest are drawn right after. FITS
    // products may flag a target after the calibration (a Stokes map not written): with
    // them, every figure is drawn after the calibration.
    let t = Instant::now();
    let prepared = calibrate::prepare(
        &plan.standards,
        profile,
        params,
        &setup.calibration,
        mask_array,
        flats.set.as_ref(),
    );
    let t_prepare = t.elapsed().as_secs_f64();
    let draw = |fig: &TargetFigure| {
        if let Some(f) = opts.hooks.on_figure {
            f(fig);
        }
        if let Some(o) = opts.outputs {
            o.figure(fig);
        }
    };
    let early = figures_wanted && !opts.outputs.is_some_and(|o| o.wants_fits());
    let queue = FigureQueue::default();
    let draw_one_queued = || match queue.pop() {
        Some((target, inputs)) => {
            let target = prepared.resolved(&target, profile, params, &setup.calibration);
            let calibration = prepared
                .chosen
                .0
                .as_ref()
                .and_then(|c| c.for_filter(target.filter.as_deref().unwrap_or("")));
            draw(&TargetFigure {
                target: &target,
                inputs: &inputs,
                calibration,
            });
            true
        }
        None => false,
    };
    let enqueue = |target: &Target, inputs: FigureInputs| queue.push((target.clone(), inputs));
    let t = Instant::now();
    let cache = opts.cache.filter(|_| !figures_wanted).map(|c| (c, mask_key, flats_key));
    let mut reduced = reduce_sequences_cached(
        &plan.sequences,
        profile,
        params,
        mask_array,
        flats.set.as_ref(),
        (&opts.hooks, opts.outputs),
        cache,
        early.then_some(Figures {
            enqueue: &enqueue,
            draw_one: &draw_one_queued,
        }),
    );
    let t_reduce = t.elapsed().as_secs_f64();
    let mut cat = std::mem::take(&mut reduced.catalog);
    let mut failures: Vec<Failure> = plan.failures.iter().chain(&plan.not_science).cloned().collect();
    failures.sort_by(|a, b| a.file.cmp(&b.file));
    failures.append(&mut cat.failures);
    failures.sort_by(|a, b| a.file.cmp(&b.file));
    cat.failures = failures;
    let t = Instant::now();
    let (calibration, summary) = calibrate::finish(&mut cat, prepared, profile, params, &setup.calibration);
    let t_cal = t_prepare + t.elapsed().as_secs_f64();
    if let Some(o) = opts.outputs {
        o.calibrated(&mut cat.targets, calibration.as_ref(), profile);
    }
    let t = Instant::now();
    if figures_wanted && !early {
        draw_figures(&cat.targets, &reduced.figures, calibration.as_ref(), &draw);
    }
    let t_fig = t.elapsed().as_secs_f64();
    let shard = opts.shard;
    cat.failures.extend(
        flats
            .failures
            .iter()
            .filter(|f| shard.is_none_or(|sh| sh.owns(&f.file)))
            .cloned(),
    );
    cat.failures.sort_by(|a, b| a.file.cmp(&b.file));
    cat.provenance = Provenance {
        shard: Some(shard.map(|s| format!("{}/{}", s.k, s.n))),
        inputs: Some(opts.inputs.iter().map(|p| p.display().to_string()).collect()),
        night_bad_pixel_mask_from: Some(mask.as_ref().map(|m| m.files.clone()).unwrap_or_default()),
        flat: Some(flats.provenance.clone()),
        calibration: Some(setup.calibration.provenance()),
        ..provenance(profile, params)
    };
    NightOutput {
        catalog: cat,
        times: reduced.times,
        calibration,
        summary,
        mask,
        flats,
        seconds: NightSeconds {
            mask: t_mask,
            flats: t_flats,
            reduce: t_reduce,
            calibration: t_cal,
            figures: t_fig,
        },
    }
}

/// Call `draw` with the figure of every target (in parallel, in the current rayon pool):
/// `targets` as calibrated, `figures` the pixels prepared during the reduction (same order).
fn draw_figures(
    targets: &[Target],
    figures: &[FigureInputs],
    calibration: Option<&Calibration>,
    draw: &(dyn Fn(&TargetFigure) + Sync),
) {
    targets.par_iter().zip(figures).for_each(|(target, inputs)| {
        let calibration = calibration.and_then(|c| c.for_filter(target.filter.as_deref().unwrap_or("")));
        draw(&TargetFigure {
            target,
            inputs,
            calibration,
        });
    });
}

/// The value of `f` and the wall time it took, seconds.
fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let v = f();
    (v, t.elapsed().as_secs_f64())
}

/// Sequences reduced, in order: the catalog (provenance left empty) and stage times.
pub struct Reduced {
    /// The targets and the files that could not be used (sorted by file).
    pub catalog: Catalog,
    /// Per-target stage times, in catalog order.
    pub times: Vec<StageTimes>,
    /// Per target, in catalog order, what its figure needs besides the catalog entry
    /// (empty unless `hooks.on_figure` is given).
    pub figures: Vec<FigureInputs>,
}

/// Reduce sequences in parallel (in the current rayon pool), in their order. `night_mask`:
/// the detector's defects found once for the night ([`night_bad_pixel_mask`]), used
/// instead of per-target detection; `flats`: the night's flats. With `hooks.on_figure`,
/// each target's figure cut-outs are stacked while its frames are in memory (the frames are
/// then dropped; the figure itself is drawn later, from the calibrated catalog).
pub fn reduce_sequences(
    sequences: &[Sequence],
    profile: &Profile,
    params: &TargetParams,
    night_mask: Option<&Array2<u8>>,
    flats: Option<&FlatSet>,
    hooks: &Hooks,
) -> Reduced {
    reduce_sequences_cached(sequences, profile, params, night_mask, flats, (hooks, None), None, None)
}

/// The figures of the targets reduced, waiting to be drawn (the inputs taken while the
/// target's frames were in memory).
#[derive(Default)]
struct FigureQueue(std::sync::Mutex<std::collections::VecDeque<(Target, FigureInputs)>>);

impl FigureQueue {
    fn push(&self, job: (Target, FigureInputs)) {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).push_back(job);
    }

    fn pop(&self) -> Option<(Target, FigureInputs)> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).pop_front()
    }
}

/// How a reduction hands over its targets' figures: `enqueue` takes a target just reduced
/// and its figure inputs; `draw_one` draws one figure waiting, if any (`false` when none
/// waits). The workers call `draw_one` only when no target is left to take.
#[derive(Clone, Copy)]
struct Figures<'a> {
    enqueue: &'a (dyn Fn(&Target, FigureInputs) + Sync),
    draw_one: &'a (dyn Fn() -> bool + Sync),
}

/// Run `one(k)` for k = 0..n on every worker of the current rayon pool, the workers taking
/// the k in turn; a worker finding none left calls `idle` (other work, done only then)
/// until every `one` has returned and `idle` finds nothing. The results in the order of k.
fn claim_in_turn<T: Send>(n: usize, one: &(dyn Fn(usize) -> T + Sync), idle: &(dyn Fn() -> bool + Sync)) -> Vec<T> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let slots: Vec<std::sync::Mutex<Option<T>>> = (0..n).map(|_| std::sync::Mutex::new(None)).collect();
    /// Counts an item done when dropped: also when `one` panics, so that the other
    /// workers stop waiting for it and the panic reaches the caller (not a hang).
    struct Done<'a>(&'a AtomicUsize);
    impl Drop for Done<'_> {
        fn drop(&mut self) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
    }
    rayon::broadcast(|_| loop {
        let k = next.fetch_add(1, Ordering::SeqCst);
        if k < n {
            let _done = Done(&done);
            let v = one(k);
            *slots[k].lock().unwrap_or_else(|e| e.into_inner()) = Some(v);
            continue;
        }
        if idle() {
            continue;
        }
        if done.load(Ordering::SeqCst) >= n {
            // Every `one` has returned, so nothing more can be queued for `idle`; what a
            // last `one` queued was found empty above only once taken by another worker.
            if !idle() {
                break;
            }
            continue;
        }
        // The last targets are being reduced by other workers: help with their parallel
        // parts, else wait a little.
        if !matches!(rayon::yield_now(), Some(rayon::Yield::Executed)) {
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
    });
    slots
        .into_iter()
        .map(|m| {
            m.into_inner()
                .unwrap_or_else(|e| e.into_inner())
                .expect("every item was taken and its result stored")
        })
        .collect()
}

/// [`reduce_sequences`], taking each target from `cache` (with the keys of the mask and
/// flats given) when its inputs are unchanged, and keeping the others there; with
/// `outputs`, each target reduced has its regions and FITS products written while its
/// frames are in memory. With `figures_now`, each target's figure inputs are handed over
/// as soon as the target is reduced (not kept in [`Reduced::figures`]) and the figures are
/// drawn by workers that find no target left to reduce ([`claim_in_turn`]).
#[allow(clippy::too_many_arguments)]
fn reduce_sequences_cached(
    sequences: &[Sequence],
    profile: &Profile,
    params: &TargetParams,
    night_mask: Option<&Array2<u8>>,
    flats: Option<&FlatSet>,
    (hooks, outputs): (&Hooks, Option<&crate::products::Outputs>),
    cache: Option<(&NightCache, u64, u64)>,
    figures_now: Option<Figures>,
) -> Reduced {
    let want_figures = hooks.on_figure.is_some() || outputs.is_some_and(|o| o.wants_figures());
    let keep_frames = outputs.is_some_and(|o| o.wants_frames());
    // A target just reduced, its frames in memory: the caller's hook and its outputs.
    let reduced = |out: &mut crate::reduce::run::TargetOutcome| {
        if let Some(f) = hooks.on_reduced {
            f(out);
        }
        if let Some(o) = outputs {
            let t = Instant::now();
            o.reduced(out, profile, params);
            out.times.write += t.elapsed().as_secs_f64();
        }
    };
    let one = |q: &Sequence| {
        let (target, failures, times, fig) = match cache {
            Some((c, mask_key, flats_key)) => {
                let mut times = StageTimes::default();
                let (t, f, _) = c.target(c.target_key(q, mask_key, flats_key), || {
                    let mut out = reduce_sequence(q, profile, params, night_mask, flats, keep_frames);
                    reduced(&mut out);
                    times = out.times;
                    (out.target, out.failures)
                });
                (t, f, times, None)
            }
            None => {
                let mut out = reduce_sequence(q, profile, params, night_mask, flats, want_figures || keep_frames);
                reduced(&mut out);
                let fig = want_figures.then(|| FigureInputs::from_outcome(&out));
                let fig = match (fig, figures_now) {
                    (Some(inputs), Some(f)) => {
                        (f.enqueue)(&out.target, inputs);
                        None
                    }
                    (fig, _) => fig,
                };
                (out.target, out.failures, out.times, fig)
            }
        };
        if let Some(f) = hooks.on_done {
            f(&target);
        }
        (target, failures, times, fig)
    };
    type Out = (Target, Vec<Failure>, StageTimes, Option<FigureInputs>);
    let outs: Vec<Out> = match figures_now {
        Some(f) => claim_in_turn(sequences.len(), &|k| one(&sequences[k]), f.draw_one),
        None => sequences.par_iter().map(one).collect(),
    };
    let mut catalog = Catalog {
        schema_version: SCHEMA_VERSION.into(),
        ..Default::default()
    };
    let mut times = Vec::with_capacity(outs.len());
    let mut figures = Vec::new();
    for (t, f, tm, fig) in outs {
        catalog.targets.push(t);
        catalog.failures.extend(f);
        times.push(tm);
        figures.extend(fig);
    }
    catalog.failures.sort_by(|a, b| a.file.cmp(&b.file));
    Reduced {
        catalog,
        times,
        figures,
    }
}

/// The provenance every catalog starts with: software, git commit of the build
/// ([`crate::build_info::commit`]), command line, time (UTC), instrument
/// profile and reduction settings.
pub fn provenance(profile: &Profile, params: &impl serde::Serialize) -> Provenance {
    Provenance {
        profile: Some(serde_json::json!(profile)),
        parameters: Some(serde_json::json!(params)),
        ..Provenance::now()
    }
}

#[cfg(test)]
mod tests {
    use super::claim_in_turn;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Mutex;

    fn pool(n: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new().num_threads(n).build().unwrap()
    }

    #[test]
    fn every_item_once_in_order_and_idle_work_only_after_the_last_was_taken() {
        for threads in [1, 2, 4] {
            let n = 37;
            let taken = AtomicUsize::new(0);
            let idle_jobs = Mutex::new((0..20).collect::<Vec<usize>>());
            let idle_done = AtomicUsize::new(0);
            let out = pool(threads).install(|| {
                claim_in_turn(
                    n,
                    &|k| {
                        taken.fetch_add(1, Ordering::SeqCst);
                        std::thread::sleep(std::time::Duration::from_micros(200));
                        k * k
                    },
                    &|| {
                        // Idle work starts only once every item has been taken: the other
                        // workers may have taken theirs without having started it yet.
                        let started = taken.load(Ordering::SeqCst);
                        assert!(
                            started + threads > n,
                            "idle work while items were left ({started} of {n} started)"
                        );
                        let job = idle_jobs.lock().unwrap().pop();
                        job.map(|_| idle_done.fetch_add(1, Ordering::SeqCst)).is_some()
                    },
                )
            });
            assert_eq!(out, (0..n).map(|k| k * k).collect::<Vec<_>>(), "{threads} threads");
            assert_eq!(
                idle_done.load(Ordering::SeqCst),
                20,
                "{threads} threads: idle work left"
            );
        }
    }

    #[test]
    fn a_panicking_item_reaches_the_caller_instead_of_hanging_the_others() {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let r = std::panic::catch_unwind(|| {
                pool(2).install(|| {
                    claim_in_turn(
                        8,
                        &|k| {
                            if k == 3 {
                                panic!("item 3 fails");
                            }
                            k
                        },
                        &|| false,
                    )
                })
            });
            let _ = tx.send(r.is_err());
        });
        let panicked = rx
            .recv_timeout(std::time::Duration::from_secs(60))
            .expect("claim_in_turn hung after an item panicked");
        assert!(panicked, "the item's panic did not reach the caller");
    }
}
