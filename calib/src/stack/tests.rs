use super::*;

/// Small deterministic generator (tests only).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, k: u64) -> u64 {
        self.next() % k
    }
}

/// Stacks of random shapes and sizes; values drawn from a tiny alphabet half of the
/// time so ties are frequent.
fn random_stack(r: &mut Rng, n: usize) -> (Vec<Array2<f32>>, Vec<Affine>) {
    let ny = 1 + r.below(5) as usize;
    let nx = 1 + r.below(300) as usize;
    let ties = r.below(2) == 0;
    let frames = (0..n)
        .map(|_| {
            Array2::from_shape_fn((ny, nx), |_| {
                if ties {
                    r.below(4) as f32
                } else {
                    (r.next() >> 40) as f32 / 1024.0 - 8000.0
                }
            })
        })
        .collect();
    let maps = (0..n)
        .map(|_| match r.below(3) {
            0 => Affine::IDENTITY,
            1 => Affine {
                scale: 1.0 / (1000.0 + r.below(1000) as f32),
                offset: 0.0,
            },
            _ => Affine {
                scale: 1.0,
                offset: -(r.below(3000) as f32),
            },
        })
        .collect();
    (frames, maps)
}

#[test]
fn networks_sort_every_zero_one_input() {
    // 0-1 principle: a comparator network sorts (selects) all inputs iff it does so
    // for all 2^n inputs of zeros and ones.
    for n in 1..=14usize {
        for ranks in [median_ranks(n), if n >= 2 { loo_ranks(n) } else { vec![0] }] {
            let net = Network::selecting(n, &ranks);
            for bits in 0u32..(1 << n) {
                let mut w = vec![[0f32; BLOCK]; n];
                for (i, wire) in w.iter_mut().enumerate() {
                    wire[0] = ((bits >> i) & 1) as f32;
                }
                net.run(&mut w, 1);
                let zeros = n - bits.count_ones() as usize;
                for &k in &ranks {
                    let want = if k < zeros { 0.0 } else { 1.0 };
                    assert_eq!(w[k][0], want, "n {n} rank {k} input {bits:b}");
                }
            }
        }
    }
}

#[test]
fn network_sizes_are_small() {
    // Batcher's full sorting network for 5 wires has 9 comparators; selecting the three
    // middle ranks of 5 must not need more.
    assert!(Network::selecting(5, &loo_ranks(5)).comparators.len() <= 9);
    assert!(Network::selecting(8, &loo_ranks(8)).comparators.len() <= 19);
}

#[test]
fn leave_one_out_matches_reference_exactly() {
    let mut r = Rng(0x1234_5678_9abc_def1);
    for case in 0..300 {
        let n = 2 + r.below(MAX_STACK as u64 - 1) as usize;
        let n = if case % 3 == 0 { n } else { 2 + (n % 11) };
        let (frames, maps) = random_stack(&mut r, n);
        let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.view()).collect();
        let fast = leave_one_out_medians_affine(&views, &maps).unwrap();
        let slow = reference_leave_one_out(&views, &maps).unwrap();
        for i in 0..n {
            for (a, b) in fast[i].iter().zip(slow[i].iter()) {
                assert_eq!(a.to_bits(), b.to_bits(), "case {case} n {n} frame {i}: {a} vs {b}");
            }
        }
    }
}

#[test]
fn every_output_pixel_is_written_for_any_band_and_block_split() {
    // The fresh outputs are not zeroed: shapes around the band height (BAND_ROWS rows)
    // and the block width (BLOCK pixels) must still give every pixel its median, and the
    // caller-owned outputs, filled with NaN first, must come back equal to them.
    let mut r = Rng(0x5eed_0000_0000_0010);
    for ny in [1, BAND_ROWS - 1, BAND_ROWS, BAND_ROWS + 1, 3 * BAND_ROWS + 5] {
        for nx in [1, BLOCK - 1, BLOCK, BLOCK + 1, 2 * BLOCK + 44] {
            for n in [2, 3, 4, 5, 6, 9] {
                let frames: Vec<Array2<f32>> = (0..n)
                    .map(|_| Array2::from_shape_fn((ny, nx), |_| 1.0 + r.below(6) as f32))
                    .collect();
                let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.view()).collect();
                let maps = vec![Affine::IDENTITY; n];
                let fast = leave_one_out_medians_affine(&views, &maps).unwrap();
                let slow = reference_leave_one_out(&views, &maps).unwrap();
                assert_eq!(fast, slow, "{ny}x{nx}, {n} frames");
                let mut outs = vec![Array2::from_elem((ny, nx), f32::NAN); n];
                leave_one_out_medians_into(&views, &maps, &mut outs).unwrap();
                assert_eq!(outs, slow, "into: {ny}x{nx}, {n} frames");
                let med = median_stack_affine(&views, &maps).unwrap();
                assert_eq!(med, reference_median_stack(&views, &maps).unwrap(), "{ny}x{nx}, {n}");
            }
        }
    }
}

#[test]
fn median_matches_reference_exactly() {
    let mut r = Rng(0xfeed_beef_1234_0001);
    for case in 0..300 {
        let n = 1 + r.below(MAX_STACK as u64) as usize;
        let (frames, maps) = random_stack(&mut r, n);
        let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.view()).collect();
        let fast = median_stack_affine(&views, &maps).unwrap();
        let slow = reference_median_stack(&views, &maps).unwrap();
        for (a, b) in fast.iter().zip(slow.iter()) {
            assert_eq!(a.to_bits(), b.to_bits(), "case {case} n {n}: {a} vs {b}");
        }
    }
}

#[test]
fn non_standard_layout_inputs_work() {
    let a = Array2::from_shape_fn((7, 9), |(y, x)| (y * 9 + x) as f32);
    let b = a.mapv(|v| v * 2.0);
    let c = a.mapv(|v| 100.0 - v);
    let views = [a.t(), b.t(), c.t()];
    let fast = leave_one_out_medians(&views).unwrap();
    let slow = reference_leave_one_out(&views, &[Affine::IDENTITY; 3]).unwrap();
    assert_eq!(fast, slow);
    assert_eq!(fast[0].dim(), (9, 7));
}

#[test]
fn bad_stacks_are_errors_naming_the_problem() {
    let a = Array2::<f32>::zeros((4, 5));
    let b = Array2::<f32>::zeros((4, 6));
    let e = leave_one_out_medians(&[a.view()]).unwrap_err().to_string();
    assert!(e.contains("1 frames") && e.contains("need 2"), "{e}");
    let e = median_stack(&[a.view(), b.view()]).unwrap_err().to_string();
    assert!(e.contains("frame 1 is 4x6"), "{e}");
}

#[test]
fn running_median_matches_reference_exactly() {
    let mut r = Rng(77);
    for case in 0..200 {
        let ny = 1 + r.below(4) as usize;
        let nx = 1 + r.below(400) as usize;
        let h = r.below(16) as usize;
        let ties = case % 2 == 0;
        let img = Array2::from_shape_fn((ny, nx), |_| {
            if ties {
                r.below(5) as f32
            } else {
                (r.next() >> 40) as f32 / 7.0
            }
        });
        let fast = running_median_x(img.view(), h).unwrap();
        let slow = reference_running_median_x(img.view(), h);
        for (a, b) in fast.iter().zip(slow.iter()) {
            assert_eq!(a.to_bits(), b.to_bits(), "case {case} {ny}x{nx} h {h}");
        }
    }
    assert!(running_median_x(Array2::<f32>::zeros((2, 2)).view(), 16).is_err());
}
