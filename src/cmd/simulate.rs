//! `sofipol simulate SCENE.toml -o DIR`: SOFI-like raw frames plus truth.json, or with a
//! half-wave-plate profile (the scene's `profile` or `--profile`) a half-wave-plate night.
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use sofipol_calib::profile::ModulationKind;
use sofipol_calib::Profile;
use sofipol_pipeline::sim::{HwpSimulator, Scene, Simulator, Truth};

use super::common::{progress, ProfileArgs};

/// Arguments of `sofipol simulate`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene file (TOML): observing setup, binaries, effects. See docs/simulator.md.
    pub scene: PathBuf,
    /// Output directory (created; required).
    #[arg(short, long, value_name = "DIR")]
    pub output: PathBuf,
    /// Replace the scene's seed [default: the scene's `seed`].
    #[arg(long)]
    pub seed: Option<u64>,
    /// Also write the true bad-pixel map as a FITS mask (1 = bad), e.g. for `--badpix`
    /// [default: none, not written].
    #[arg(long, value_name = "FILE")]
    pub badpix_mask: Option<PathBuf>,
    /// Print only errors (no progress bar or summary).
    #[arg(short, long)]
    pub quiet: bool,
    /// Write the frames even when they take more than 4 GiB (docs/simulator.md).
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub profile: ProfileArgs,
}

/// Load a scene file.
pub fn load_scene(path: &Path) -> anyhow::Result<Scene> {
    let text = sofipol_calib::input::read_to_string(path, sofipol_calib::input::MAX_OPTION_FILE_BYTES)
        .with_context(|| format!("reading scene {}", path.display()))?;
    Scene::from_toml(&text, &path.display().to_string()).map_err(anyhow::Error::msg)
}

/// Most bytes `simulate` writes without `--force` (a night of 50 targets is about 1 GB).
pub const MAX_OUTPUT_BYTES: u64 = 4 << 30;

/// Refuse, before writing anything, a scene whose frames would take more than
/// [`MAX_OUTPUT_BYTES`] (unless `force`).
pub fn check_output_size(sim: &Simulator, dir: &Path, force: bool) -> anyhow::Result<()> {
    let bytes = sim.output_bytes();
    anyhow::ensure!(
        force || bytes <= MAX_OUTPUT_BYTES,
        "the scene's {} frames would take {:.1} GB in {} (more than the {:.1} GB simulate writes \
         without --force): fewer targets, orientations or dithers, or --force",
        sim.file_names().len() - 1,
        bytes as f64 / 1e9,
        dir.display(),
        MAX_OUTPUT_BYTES as f64 / 1e9
    );
    Ok(())
}

/// Simulate into `dir` with a progress bar unless quiet (and the true bad-pixel map into
/// `badpix`). Returns the truth.
pub fn simulate_with(sim: &Simulator, dir: &Path, badpix: Option<&Path>, quiet: bool) -> anyhow::Result<Truth> {
    let total = (sim.frames_per_target() * sim.scene().binary.len()) as u64;
    let pb = progress(total, "simulate", quiet);
    let truth = sim
        .write_to_dir(dir, &|name| {
            pb.inc(1);
            pb.set_message(name.to_string());
        })
        .map_err(anyhow::Error::msg)?;
    pb.finish_and_clear();
    if let Some(path) = badpix {
        write_badpix_mask(path, sim.bad_pixel_mask(), sim.scene())?;
    }
    Ok(truth)
}

/// Refuse, before anything is written, an output folder that holds anything but this
/// scene's own files (`names`: its frames and truth.json, or their temporaries): another
/// night's frames would be reduced with these, and its truth.json overwritten. Simulating
/// the same scene again into its folder, or into an empty or new one, is fine.
pub fn check_simulate_dir(dir: &Path, names: &[String]) -> anyhow::Result<()> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    for e in entries {
        let e = e.with_context(|| format!("-o {}: listing the folder", dir.display()))?;
        let name = e.file_name().to_string_lossy().into_owned();
        let ours = names
            .iter()
            .any(|n| *n == name || name.strip_prefix(&format!(".{n}.tmp-")).is_some());
        anyhow::ensure!(
            ours && e.file_type().is_ok_and(|t| t.is_file()),
            "-o {}: {} is not a file of this scene: a night reduced from the folder would mix it \
             with the simulated frames (and another scene's truth.json would be overwritten); give \
             an empty or new folder",
            dir.display(),
            e.path().display()
        );
    }
    Ok(())
}

/// The profile of a scene: `--profile` when given, else the scene's `profile` (an embedded
/// name, or a file relative to the scene's folder), else SOFI's; then the scene's
/// `profile_set`, then `--set`.
pub fn scene_profile(args: &ProfileArgs, scene: &Scene, scene_path: &Path) -> anyhow::Result<Profile> {
    let base = match (&args.profile, &scene.profile) {
        (None, Some(name)) => match Profile::embedded(name) {
            Some(p) => p?,
            None => {
                let path = scene_path.parent().unwrap_or(Path::new(".")).join(name);
                Profile::sofi_with_override(&path)
                    .with_context(|| format!("scene {}: profile = '{name}'", scene_path.display()))?
            }
        },
        _ => ProfileArgs {
            profile: args.profile.clone(),
            sets: Vec::new(),
        }
        .load()?,
    };
    base.with_overrides(&scene.profile_set)
        .with_context(|| format!("scene {}: profile_set", scene_path.display()))?
        .with_overrides(&args.sets)
        .context("applying --set overrides")
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let mut scene = load_scene(&args.scene)?;
    if let Some(s) = args.seed {
        scene.seed = s;
    }
    let profile = scene_profile(&args.profile, &scene, &args.scene)?;
    if profile.modulation_kind() == ModulationKind::HalfWavePlate {
        return run_half_wave_plate(&args, scene, profile);
    }
    let t0 = std::time::Instant::now();
    let sim = Simulator::new(scene, profile).map_err(anyhow::Error::msg)?;
    check_output_size(&sim, &args.output, args.force)?;
    check_simulate_dir(&args.output, &sim.file_names())?;
    let truth = simulate_with(&sim, &args.output, args.badpix_mask.as_deref(), args.quiet)?;
    if !args.quiet {
        let nframes: usize = truth.targets.iter().map(|t| t.frames.len()).sum();
        println!(
            "simulated {} target(s), {nframes} frames into {} in {:.2} s; effects: [{}]",
            truth.targets.len(),
            args.output.display(),
            t0.elapsed().as_secs_f64(),
            truth.effects.join(", ")
        );
        if !truth.ignored_sections.is_empty() {
            println!(
                "ignored (configured but not listed in effects): {}",
                truth.ignored_sections.join(", ")
            );
        }
        println!("truth: {}", args.output.join("truth.json").display());
    }
    Ok(ExitCode::SUCCESS)
}

/// A half-wave-plate scene (`[half_wave_plate]`) for a half-wave-plate profile.
fn run_half_wave_plate(args: &Args, scene: Scene, profile: Profile) -> anyhow::Result<ExitCode> {
    let t0 = std::time::Instant::now();
    let sim = HwpSimulator::new(scene, profile).map_err(anyhow::Error::msg)?;
    let bytes = sim.output_bytes();
    let names = sim.file_names();
    anyhow::ensure!(
        args.force || bytes <= MAX_OUTPUT_BYTES,
        "the scene's {} frames would take {:.1} GB in {} (more than the {:.1} GB simulate writes \
         without --force): fewer stars or cycles, or --force",
        names.len() - 1,
        bytes as f64 / 1e9,
        args.output.display(),
        MAX_OUTPUT_BYTES as f64 / 1e9
    );
    check_simulate_dir(&args.output, &names)?;
    let pb = progress((names.len() - 1) as u64, "simulate", args.quiet);
    let truth = sim
        .write_to_dir(&args.output, &|name| {
            pb.inc(1);
            pb.set_message(name.to_string());
        })
        .map_err(anyhow::Error::msg)?;
    pb.finish_and_clear();
    if let Some(path) = &args.badpix_mask {
        write_badpix_mask(path, sim.bad_pixel_mask(), sim.scene())?;
    }
    if !args.quiet {
        let nframes: usize = truth.stars.iter().map(|t| t.frames.len()).sum();
        println!(
            "simulated {} star(s) through the half-wave plate ({} profile), {nframes} frames, {} sky frames, {} darks into {} in {:.2} s; effects: [{}]",
            truth.stars.len(),
            truth.profile,
            truth.skies.len(),
            truth.darks.len(),
            args.output.display(),
            t0.elapsed().as_secs_f64(),
            truth.effects.join(", ")
        );
        if !truth.ignored_sections.is_empty() {
            println!(
                "ignored (configured but not listed in effects): {}",
                truth.ignored_sections.join(", ")
            );
        }
        println!("truth: {}", args.output.join("truth.json").display());
    }
    Ok(ExitCode::SUCCESS)
}

/// Write the scene's true bad-pixel map (`--badpix-mask`) to `path`; `mask` is None when the
/// scene has no `bad_pixels` effect.
fn write_badpix_mask(
    path: &std::path::Path,
    mask: Option<ndarray::Array2<u8>>,
    scene: &sofipol_pipeline::sim::Scene,
) -> anyhow::Result<()> {
    let mask = mask.context("--badpix-mask needs the bad_pixels effect in the scene")?;
    let mut h = sofipol_calib::Header::new(path);
    h.set("OBJECT", "sofipol true bad-pixel map");
    let frame = sofipol_calib::Frame::new(mask.mapv(|v| v as f32), h).with_history(
        "simulate",
        format!("true bad-pixel map of scene '{}' seed {}", scene.name, scene.seed),
    );
    sofipol_calib::fits::write_frame(path, &frame, &Default::default())?;
    Ok(())
}
