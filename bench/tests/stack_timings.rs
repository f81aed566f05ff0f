//! Timings of the stack kernels of sofipol-calib on 1024 x 1024 frames. Not a pass/fail test:
//! `cargo test --release -p sofipol-bench --test stack_timings -- --ignored --nocapture`.
use ndarray::{Array2, ArrayView2};
use sofipol_bench::timing::{bench_frames, bench_leave_one_out, bench_median, median_ms};
use sofipol_calib::stack::{leave_one_out_medians_into, running_median_x, Affine};

#[test]
#[ignore = "timing: cargo test --release -p sofipol-bench --test stack_timings -- --ignored --nocapture"]
fn print_timings() {
    let t = rayon::current_num_threads();
    for n in [3, 4, 5, 10, 12] {
        let loo = bench_leave_one_out(n, 1024, 1024, 11);
        let med = bench_median(n, 1024, 1024, 11);
        let frames = bench_frames(n, 1024, 1024);
        let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.view()).collect();
        let maps = vec![Affine::IDENTITY; n];
        let mut outs = vec![Array2::<f32>::zeros((1024, 1024)); n];
        let into = median_ms(11, || leave_one_out_medians_into(&views, &maps, &mut outs).unwrap());
        println!("{n:2} x 1024^2, {t} threads: leave-one-out into reused buffers {into:.2} ms");
        if n == 5 {
            let rm = median_ms(11, || {
                std::hint::black_box(running_median_x(frames[0].view(), 7).unwrap());
            });
            println!("running median along x, window 15, 1024^2: {rm:.2} ms");
        }
        println!("{n:2} x 1024^2, {t} threads: all {n} leave-one-out medians {loo:.2} ms; one median {med:.2} ms");
    }
}
