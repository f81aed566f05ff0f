//! Timings of FITS I/O on a full 1024 x 1024 SOFI frame. Not a pass/fail test: run with
//! `cargo test --release -p sofipol-calib --test fits_timing -- --ignored --nocapture`.
mod common;

use std::time::Instant;

use sofipol_calib::fits::{read_frame, write_frame, Bitpix, WriteOptions};

fn median_ms(mut f: impl FnMut(), n: usize) -> f64 {
    let mut t: Vec<f64> = (0..n)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(|a, b| a.total_cmp(b));
    t[n / 2]
}

#[test]
#[ignore]
fn timing_1024_square() {
    let dir = tempfile::tempdir().unwrap();
    let frame = common::sofi_frame(1024, 1024, 45.0);
    for (label, bitpix, compress) in [
        ("f32", Bitpix::F32, false),
        ("i16", Bitpix::I16, false),
        ("i16 Rice .fz", Bitpix::I16, true),
        ("f32 GZIP .fz", Bitpix::F32, true),
    ] {
        let path = dir.path().join(format!("t-{label}.fits").replace(' ', "_"));
        let o = WriteOptions {
            bitpix,
            compress,
            with_variance_and_mask: false,
        };
        let w = median_ms(|| write_frame(&path, &frame, &o).unwrap(), 7);
        let r = median_ms(|| assert_eq!(read_frame(&path).unwrap().shape(), (1024, 1024)), 7);
        let size = std::fs::metadata(&path).unwrap().len();
        println!("{label:>13}: write {w:7.2} ms (incl. fsync), read {r:6.2} ms, {size} bytes");
    }
}
