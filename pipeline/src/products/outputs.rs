//! Every per-target output of a reduction goes to disk through here, named here, into the
//! folder beside its catalog ([`products_dir`]: `<catalog stem>_products/`):
//!
//! ```text
//! <slug>.png                figure of each target           night (unless --no-png), demo
//! regions/<frame>.reg       DS9 regions of each frame       --regions (night, target, watch)
//! fits/...                  FITS products (docs/products.md) --fits-products (night, target, watch)
//! ```
//!
//! Files are written atomically from the reduction's threads. One that cannot be written is
//! counted (a FITS product also flags its target), never a failed night; the command then
//! exits 2. [`Outputs::finish`] says what was written and, for a whole night, clears the
//! folder of what earlier runs left there and this one did not write.
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use sofipol_calib::Profile;

use super::badpix::NightMask;
use super::{products_dir, regions, slug, FitsProducts, ProductError};
use crate::catalog::polarimetric_calibration::Calibration;
use crate::catalog::{Flag, Target};
use crate::plots::target::TargetFigure;
use crate::reduce::run::TargetOutcome;
use crate::reduce::{MeasureParams, TargetParams};

/// Which per-target outputs a run writes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct OutputChoice {
    /// A PNG figure per target.
    pub figures: bool,
    /// DS9 region files, one per frame.
    pub regions: bool,
    /// FITS products: cut-outs, Stokes maps, the night's bad-pixel mask.
    pub fits: bool,
}

/// Files of one kind written into one folder from many threads.
pub(crate) struct Files {
    dir: PathBuf,
    written: Mutex<Vec<PathBuf>>,
    failed: Mutex<Vec<String>>,
}

/// What one kind of output came to.
#[derive(Debug, Clone, Default)]
pub struct Written {
    /// The folder.
    pub dir: PathBuf,
    /// Files written, sorted.
    pub files: Vec<PathBuf>,
    /// Their size, bytes.
    pub bytes: u64,
    /// One line per file that could not be written (file and reason).
    pub failed: Vec<String>,
}

impl Files {
    /// Files written into `dir` (which exists).
    pub(crate) fn new(dir: PathBuf) -> Files {
        Files {
            dir,
            written: Mutex::default(),
            failed: Mutex::default(),
        }
    }

    /// The folder.
    pub(crate) fn dir(&self) -> &Path {
        &self.dir
    }

    /// Record a file's outcome; the line naming it and why when it was not written.
    pub(crate) fn record(&self, path: &Path, result: Result<(), ProductError>) -> Option<String> {
        match result {
            Ok(()) => {
                self.written
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push(path.to_path_buf());
                None
            }
            Err(e) => {
                let line = format!("{}: {e}", path.display());
                self.failed.lock().unwrap_or_else(|e| e.into_inner()).push(line.clone());
                Some(line)
            }
        }
    }

    /// What was written. With `clean`, the folder loses the files this run did not write
    /// that `stale` recognises (an earlier run's outputs), and the temporaries of
    /// interrupted writes.
    pub(crate) fn finish(self, clean: bool, stale: impl Fn(&Path) -> bool) -> Written {
        let mut files = self.written.into_inner().unwrap_or_else(|e| e.into_inner());
        files.sort();
        files.dedup();
        if clean {
            for e in std::fs::read_dir(&self.dir).into_iter().flatten().flatten() {
                let (path, name) = (e.path(), e.file_name().to_string_lossy().into_owned());
                let Ok(kind) = e.file_type() else { continue };
                let temporary = name.starts_with('.') && (name.contains(".tmp-") || name.ends_with(".tmp"));
                if kind.is_dir() && temporary {
                    let _ = std::fs::remove_dir_all(&path);
                } else if kind.is_file() && (temporary || (!files.contains(&path) && stale(&path))) {
                    let _ = std::fs::remove_file(&path);
                }
            }
        }
        let bytes = files
            .iter()
            .filter_map(|p| std::fs::metadata(p).ok())
            .map(|m| m.len())
            .sum();
        Written {
            dir: self.dir,
            files,
            bytes,
            failed: self.failed.into_inner().unwrap_or_else(|e| e.into_inner()),
        }
    }
}

/// The DS9 regions of a run: the apertures and annuli as measured.
struct Regions {
    files: Files,
    measure: MeasureParams,
    software: String,
}

/// The per-target outputs of one run (night, target, watch, demo), written while it runs.
pub struct Outputs {
    figures: Option<Files>,
    regions: Option<Regions>,
    fits: Option<FitsProducts>,
}

/// What a run's outputs came to, by kind (none: not asked for).
#[derive(Debug, Clone, Default)]
pub struct OutputsSummary {
    /// The figures.
    pub figures: Option<Written>,
    /// The region files.
    pub regions: Option<Written>,
    /// The FITS products.
    pub fits: Option<Written>,
}

impl OutputsSummary {
    /// Whether a file could not be written (the products are incomplete).
    pub fn incomplete(&self) -> bool {
        [&self.figures, &self.regions, &self.fits]
            .into_iter()
            .flatten()
            .any(|w| !w.failed.is_empty())
    }
}

impl Outputs {
    /// No per-target output.
    pub fn none() -> Outputs {
        Outputs {
            figures: None,
            regions: None,
            fits: None,
        }
    }

    /// The outputs `choice` asks for, beside the catalog `catalog`; their folders are
    /// created. `measure`: the apertures' settings the regions draw.
    pub fn create(catalog: &Path, choice: OutputChoice, measure: &MeasureParams) -> std::io::Result<Outputs> {
        let root = products_dir(catalog);
        let folder = |want: bool, sub: &str| -> std::io::Result<Option<PathBuf>> {
            if !want {
                return Ok(None);
            }
            let dir = if sub.is_empty() { root.clone() } else { root.join(sub) };
            std::fs::create_dir_all(&dir)?;
            Ok(Some(dir))
        };
        Ok(Outputs {
            figures: folder(choice.figures, "")?.map(Files::new),
            regions: folder(choice.regions, REGIONS_DIR)?.map(|dir| Regions {
                files: Files::new(dir),
                measure: measure.clone(),
                software: format!(
                    "sofipol {} (commit {})",
                    env!("CARGO_PKG_VERSION"),
                    crate::build_info::commit()
                ),
            }),
            fits: folder(choice.fits, FITS_DIR)?.map(FitsProducts::new),
        })
    }

    /// Whether each target's figure is drawn.
    pub fn wants_figures(&self) -> bool {
        self.figures.is_some()
    }

    /// Whether FITS products are written (they may flag a target after the calibration).
    pub fn wants_fits(&self) -> bool {
        self.fits.is_some()
    }

    /// Whether a reduced target's frames are kept until [`Outputs::reduced`] (the FITS
    /// products need them; the regions only the measured positions).
    pub fn wants_frames(&self) -> bool {
        self.fits.is_some()
    }

    /// The folder of the figures, when written.
    pub fn figures_dir(&self) -> Option<&Path> {
        self.figures.as_ref().map(Files::dir)
    }

    /// The folder of the region files, when written.
    pub fn regions_dir(&self) -> Option<&Path> {
        self.regions.as_ref().map(|r| r.files.dir())
    }

    /// Write a reduced target's region files and FITS products (its frames kept); the flags
    /// of the FITS products not written are added to the target.
    pub fn reduced(&self, out: &mut TargetOutcome, profile: &Profile, params: &TargetParams) {
        if let Some(r) = &self.regions {
            let files = regions::target_regions(out, &r.measure, &r.software);
            if !files.is_empty() {
                for (path, result) in regions::write_regions(r.files.dir(), &files) {
                    r.files.record(&path, result);
                }
            }
        }
        if let Some(p) = &self.fits {
            let not_written: Vec<Flag> = p.write_target(out, profile, params);
            if !not_written.is_empty() {
                out.target.flags.get_or_insert_with(Vec::new).extend(not_written);
            }
        }
    }

    /// Write the Stokes maps of the targets reduced (FITS products), with the night's
    /// calibration `cal` applied as to the calibrated catalog `targets`; a map not written
    /// is a flag on its target.
    pub fn calibrated(&self, targets: &mut [Target], cal: Option<&Calibration>, profile: &Profile) {
        if let Some(p) = &self.fits {
            p.write_stokes_maps(targets, cal, profile);
        }
    }

    /// Write a target's figure as `<slug>.png` (renamed into place whole; synced to disk with
    /// the others by [`Outputs::finish`]).
    pub fn figure(&self, fig: &TargetFigure) {
        if let Some(f) = &self.figures {
            let path = f.dir().join(format!("{}.png", slug(fig.target.sequence_id())));
            let r = fig.png_deferred(&path).map_err(|source| ProductError::Figure {
                path: path.clone(),
                source,
            });
            f.record(&path, r);
        }
    }

    /// Write the night's bad-pixel mask (a FITS product).
    pub fn night_mask(&self, mask: &NightMask, params: &TargetParams) {
        if let Some(p) = &self.fits {
            p.write_bad_pixel_mask(mask, params);
        }
    }

    /// What was written. `clean`: the run reduced the whole night, so what earlier runs
    /// left in the folders and this one did not write goes (figures and FITS products of
    /// targets no longer reduced, region files of frames no longer used); a live night,
    /// whose targets are written across runs, keeps them.
    pub fn finish(self, clean: bool) -> OutputsSummary {
        let is_png = |p: &Path| p.extension().is_some_and(|e| e == "png");
        let is_reg = |p: &Path| p.extension().is_some_and(|e| e == "reg");
        // The figures were renamed into place one by one and are synced here together.
        let figures = self.figures.map(|f| {
            let mut w = f.finish(clean, is_png);
            for e in sofipol_calib::atomic::sync_files(&w.files) {
                w.failed.push(format!("not synced to disk: {e}"));
            }
            w
        });
        OutputsSummary {
            figures,
            regions: self.regions.map(|r| r.files.finish(clean, is_reg)),
            fits: self.fits.map(|p| p.finish(clean)),
        }
    }
}

/// The region files' folder in the products folder.
pub const REGIONS_DIR: &str = "regions";

/// The FITS products' folder in the products folder.
pub const FITS_DIR: &str = "fits";
