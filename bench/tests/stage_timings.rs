//! Timings of the calibration stages (leave-one-out medians, sky subtraction, cosmic rays,
//! bad pixels) on a simulated SOFI sequence. Not a pass/fail test:
//! `cargo test --release -p sofipol-bench --test stage_timings -- --ignored --nocapture`.
use sofipol_bench::timing::{bench_leave_one_out, median_ms};
use sofipol_calib::badpix::{detect_bad_pixels, BadPixelOptions};
use sofipol_calib::sky::{sky_subtract, CosmicOptions, SkyOptions, SkyScaling};
use sofipol_calib::{Frame, Profile};
use sofipol_pipeline::sim::{Scene, SimFrame, Simulator};

/// One target, `orientations` x 5 dithers, exact 87 px jitter (integer star centres:
/// the most peaked, hardest case for the cosmic-ray sharpness test).
fn scene(effects: &str, orientations: &str, extra: &str, seed: u64) -> Scene {
    let text = format!(
        r#"
name = "calib"
seed = {seed}
effects = [{effects}]
[observation]
orientations_deg = [{orientations}]
dithers = 5
jitter_step_px = 87.0
[[binary]]
name = "Calib Tau"
separation_arcsec = 4.0
pa_deg = 130.0
flux_a = 60000.0
flux_b = 20000.0
p_a = 0.05
gamma_a_deg = 30.0
p_b = 0.03
gamma_b_deg = 100.0
[[binary.field_star]]
separation_arcsec = 9.3
pa_deg = 250.0
flux = 150000.0
[[binary.field_star]]
separation_arcsec = 7.1
pa_deg = 65.0
flux = 90000.0
{extra}
"#
    );
    Scene::from_toml(&text, "calib test scene").unwrap()
}

fn run(sc: Scene) -> (Simulator, Vec<SimFrame>) {
    let sim = Simulator::new(sc, Profile::sofi()).unwrap();
    let (frames, _) = sim.run_in_memory();
    (sim, frames)
}

#[test]
#[ignore = "timing: cargo test --release -p sofipol-bench --test stage_timings -- --ignored --nocapture"]
fn print_stage_timings() {
    let p = Profile::sofi();
    let sc = scene(
        "\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\", \"bad_pixels\"",
        "0.0, 45.0",
        "",
        4,
    );
    let (_, sim) = run(sc);
    let frames: Vec<Frame> = sim.iter().map(|s| s.frame.clone()).collect();
    let refs: Vec<&Frame> = frames.iter().collect();
    let t = rayon::current_num_threads();
    let loo = bench_leave_one_out(5, 1024, 1024, 21);
    let sky = median_ms(11, || {
        std::hint::black_box(
            sky_subtract(
                &frames[..5],
                &p,
                &SkyOptions {
                    scaling: SkyScaling::Multiplicative,
                    cosmic_rays: None,
                    ..SkyOptions::default()
                },
            )
            .unwrap(),
        );
    });
    let sky_cr = median_ms(11, || {
        std::hint::black_box(sky_subtract(&frames[..5], &p, &SkyOptions::recommended()).unwrap());
    });
    let subtracted = sky_subtract(&frames[..5], &p, &SkyOptions::default()).unwrap();
    let cr = median_ms(11, || {
        std::hint::black_box(sofipol_calib::sky::flag_cosmic_rays(&subtracted[0], &CosmicOptions::default()).unwrap());
    });
    let bp = median_ms(11, || {
        std::hint::black_box(detect_bad_pixels(&refs, &p, &BadPixelOptions::default()).unwrap());
    });
    println!("{t} threads, medians: leave-one-out medians 5 x 1024^2 {loo:.2} ms; sky_subtract 5 frames {sky:.1} ms (+cosmic rays {sky_cr:.1} ms; flag_cosmic_rays alone, 1 frame {cr:.1} ms); detect_bad_pixels 10 frames {bp:.1} ms");
}
