//! Timing helpers: the median of repeated runs, and the stack kernels of sofipol-calib timed
//! on sky-like frames (`sofipol bench stages`, the timing tests of bench/tests/).
use std::time::Instant;

use ndarray::{Array2, ArrayView2};
use sofipol_calib::stack::{leave_one_out_medians_affine, median_stack, Affine};

/// Benchmark: median wall time (ms) of computing all `n_frames` leave-one-out medians of
/// `n_frames` frames of `ny` x `nx` pseudo-random sky-like values, over `repeats` runs
/// (after one warm-up), on the current rayon pool.
pub fn bench_leave_one_out(n_frames: usize, ny: usize, nx: usize, repeats: usize) -> f64 {
    let frames = bench_frames(n_frames, ny, nx);
    let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.view()).collect();
    let maps: Vec<Affine> = (0..n_frames)
        .map(|j| Affine {
            scale: 1.0 / (1500.0 + j as f32),
            offset: 0.0,
        })
        .collect();
    median_ms(repeats, || {
        let r = leave_one_out_medians_affine(&views, &maps).expect("valid bench stack");
        std::hint::black_box(r);
    })
}

/// Benchmark: median wall time (ms) of one per-pixel median of `n_frames` frames.
pub fn bench_median(n_frames: usize, ny: usize, nx: usize, repeats: usize) -> f64 {
    let frames = bench_frames(n_frames, ny, nx);
    let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.view()).collect();
    median_ms(repeats, || {
        let r = median_stack(&views).expect("valid bench stack");
        std::hint::black_box(r);
    })
}

/// Median of `repeats` timings (ms) of `f`, after one warm-up call.
pub fn median_ms(repeats: usize, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..repeats.max(1))
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(|a, b| a.total_cmp(b));
    t[t.len() / 2]
}

/// Sky-like pseudo-random frames (xorshift; Irwin-Hall approximately normal noise).
pub fn bench_frames(n: usize, ny: usize, nx: usize) -> Vec<Array2<f32>> {
    (0..n)
        .map(|j| {
            let mut s = 0x9E37_79B9_7F4A_7C15u64 ^ (j as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03);
            let mut next = move || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 40) as f32 / (1u64 << 24) as f32
            };
            Array2::from_shape_fn((ny, nx), |_| {
                1500.0 + j as f32 + 12.0 * (next() + next() + next() - 1.5)
            })
        })
        .collect()
}
