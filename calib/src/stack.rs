//! Fast per-pixel statistics across a small stack of equally shaped frames.
//!
//! The sky of a dithered frame is the median of the *other* dithers at each pixel (the
//! stars move between dithers, the sky does not). For N frames that is N
//! "leave-one-out" medians, the hot spot of a whole night's reduction. They are computed
//! here with **one** partial sort of the N values per pixel:
//!
//! * Sort the N values, s\[0\] <= ... <= s\[N-1\]. Removing frame i's value v_i leaves
//!   m = N - 1 values whose median depends only on where v_i sits relative to the middle:
//!   * N odd (N = 2k + 1, m even): v_i < s\[k\] gives (s\[k\] + s\[k+1\])/2,
//!     v_i > s\[k\] gives (s\[k-1\] + s\[k\])/2, v_i = s\[k\] gives (s\[k-1\] + s\[k+1\])/2;
//!   * N even (N = 2k, m odd): v_i >= s\[k\] gives s\[k-1\], otherwise s\[k\].
//!
//!   Ties are harmless: when v_i equals s\[k\] but sits at another rank, the order
//!   statistics involved are equal, so every branch gives the same value.
//! * Only the two or three middle order statistics are needed, so the sort is a
//!   *selection network*: Batcher's odd-even merge sorting network for N (padded to a
//!   power of two, comparators on padding wires dropped), pruned backwards to the
//!   comparators that feed the middle wires. The network runs on blocks of pixels of a
//!   row at once (structure of arrays), which the compiler turns into SIMD min/max.
//! * Rows are distributed over rayon threads in bands; every output pixel depends on its
//!   own inputs only, so results are bit-identical for any thread count.
//!
//! Each frame's values may first go through an affine map `v * scale + offset` (the sky
//! stage divides by each frame's sky level or subtracts it), computed in `f32` exactly as
//! written, in the fast path and in the reference alike.
//!
//! Inputs must be NaN-free (masked pixels carry values; the median is robust to them).
//! The slow, obviously correct `reference_median` and `reference_leave_one_out`
//! (collect, sort, take the middle) define the results; tests compare them bit for bit.
use std::mem::MaybeUninit;

use ndarray::{Array2, ArrayView2, CowArray, Ix2};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// Largest stack handled (frames per call).
pub const MAX_STACK: usize = 32;

/// Pixels processed together per network pass (16 KiB of f32 scratch at N = 32).
pub(crate) const BLOCK: usize = 128;

/// SIMD lanes handled together by a comparator (two SSE or one AVX register).
const LANES: usize = 8;

/// Rows per parallel task.
const BAND_ROWS: usize = 8;

/// Per-frame affine map applied before the statistics: `v * scale + offset` (f32).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Affine {
    /// Multiplier.
    pub scale: f32,
    /// Added after scaling.
    pub offset: f32,
}

impl Affine {
    /// The identity map.
    pub const IDENTITY: Affine = Affine {
        scale: 1.0,
        offset: 0.0,
    };

    /// Apply to one value (the single definition both fast and reference paths use).
    #[inline(always)]
    pub fn apply(self, v: f32) -> f32 {
        v * self.scale + self.offset
    }
}

/// Mean of the two middle values, as both the fast path and the reference compute it.
#[inline(always)]
fn mid(a: f32, b: f32) -> f32 {
    (a + b) * 0.5
}

/// Median of a slice of NaN-free values (sorts a copy; the reference definition).
/// Even counts give the mean of the two middle values. Panics on an empty slice.
#[cfg(test)]
pub(crate) fn reference_median(values: &[f32]) -> f32 {
    let mut v = values.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    assert!(n > 0, "median of no values");
    if n % 2 == 1 {
        v[n / 2]
    } else {
        mid(v[n / 2 - 1], v[n / 2])
    }
}

/// Slow reference: for every frame i and pixel, collect the other frames' mapped values,
/// sort them and take the median. Defines what [`leave_one_out_medians_affine`] returns.
#[cfg(test)]
pub(crate) fn reference_leave_one_out(frames: &[ArrayView2<f32>], maps: &[Affine]) -> Result<Vec<Array2<f32>>> {
    check_stack(frames, maps, 2, "leave-one-out median")?;
    let (ny, nx) = frames[0].dim();
    let n = frames.len();
    Ok((0..n)
        .map(|i| {
            Array2::from_shape_fn((ny, nx), |(y, x)| {
                let others: Vec<f32> = (0..n)
                    .filter(|&j| j != i)
                    .map(|j| maps[j].apply(frames[j][[y, x]]))
                    .collect();
                reference_median(&others)
            })
        })
        .collect())
}

/// Slow reference of [`median_stack_affine`].
#[cfg(test)]
pub(crate) fn reference_median_stack(frames: &[ArrayView2<f32>], maps: &[Affine]) -> Result<Array2<f32>> {
    check_stack(frames, maps, 1, "median stack")?;
    let (ny, nx) = frames[0].dim();
    Ok(Array2::from_shape_fn((ny, nx), |(y, x)| {
        let v: Vec<f32> = frames.iter().zip(maps).map(|(f, m)| m.apply(f[[y, x]])).collect();
        reference_median(&v)
    }))
}

fn check_stack(frames: &[ArrayView2<f32>], maps: &[Affine], min: usize, what: &str) -> Result<()> {
    let n = frames.len();
    if n < min || n > MAX_STACK {
        return Err(Error::Stage {
            stage: "stack",
            reason: format!("{what} of {n} frames: need {min} to {MAX_STACK}"),
        });
    }
    if maps.len() != n {
        return Err(Error::Stage {
            stage: "stack",
            reason: format!("{what}: {} affine maps for {n} frames", maps.len()),
        });
    }
    let d0 = frames[0].dim();
    if let Some((j, f)) = frames.iter().enumerate().find(|(_, f)| f.dim() != d0) {
        return Err(Error::Stage {
            stage: "stack",
            reason: format!(
                "{what}: frame {j} is {}x{} (ny x nx) but frame 0 is {}x{}",
                f.dim().0,
                f.dim().1,
                d0.0,
                d0.1
            ),
        });
    }
    Ok(())
}

/// Compare-exchange pairs `(i, j)`, `i < j`, of Batcher's odd-even merge sort for `n`
/// wires (Knuth's iterative formulation): the network of the next power of two with every
/// pair that touches a wire at `n` or beyond left out (such wires would hold +inf, which
/// never moves: every pair puts its larger value at its higher index).
pub(crate) fn batcher_pairs(n: usize) -> Vec<(u16, u16)> {
    assert!(n <= u16::MAX as usize, "{n} wires");
    let p = n.next_power_of_two();
    let mut all = Vec::new();
    let mut pp = 1;
    while pp < p {
        let mut k = pp;
        while k >= 1 {
            let mut j = k % pp;
            while j + k < p {
                for i in 0..k.min(p - j - k) {
                    let (a, b) = (i + j, i + j + k);
                    if (a / (pp * 2)) == (b / (pp * 2)) && b < n {
                        all.push((a as u16, b as u16));
                    }
                }
                j += 2 * k;
            }
            k /= 2;
        }
        pp *= 2;
    }
    all
}

/// A comparator network on `n` wires: after running, the `wanted` wires hold the sorted
/// values at those ranks.
#[derive(Debug, Clone)]
struct Network {
    comparators: Vec<(u8, u8)>,
}

impl Network {
    /// Batcher's odd-even merge sort for `n` wires (padded to a power of two with +inf
    /// wires, whose comparators are no-ops and are dropped), pruned to the comparators
    /// whose results reach one of the `wanted` output wires.
    fn selecting(n: usize, wanted: &[usize]) -> Network {
        assert!(n <= u8::MAX as usize + 1, "{n} wires");
        let all: Vec<(u8, u8)> = batcher_pairs(n).into_iter().map(|(a, b)| (a as u8, b as u8)).collect();
        // Backward pruning: a comparator matters only if one of its wires is still read.
        let mut needed = vec![false; n];
        for &w in wanted {
            needed[w] = true;
        }
        let mut kept: Vec<(u8, u8)> = Vec::new();
        for &(a, b) in all.iter().rev() {
            if needed[a as usize] || needed[b as usize] {
                needed[a as usize] = true;
                needed[b as usize] = true;
                kept.push((a, b));
            }
        }
        kept.reverse();
        Network { comparators: kept }
    }

    /// Run on `len` lanes of `w[wire][lane]`.
    #[inline]
    fn run(&self, w: &mut [[f32; BLOCK]], len: usize) {
        for &(a, b) in &self.comparators {
            let (a, b) = (a as usize, b as usize);
            // a < b always: split to borrow both rows.
            let (lo_part, hi_part) = w.split_at_mut(b);
            let ra = &mut lo_part[a][..len];
            let rb = &mut hi_part[0][..len];
            // Lanes of 8 computed as whole arrays, then stored: `select(v < u, v, u)` maps
            // to MINPS/MAXPS exactly (no NaN fix-up as with f32::min; inputs are NaN-free),
            // and storing whole arrays keeps LLVM from turning the selects into branchy
            // conditional stores.
            let mut ca = ra.chunks_exact_mut(LANES);
            let mut cb = rb.chunks_exact_mut(LANES);
            for (xa, xb) in (&mut ca).zip(&mut cb) {
                let u: [f32; LANES] = std::array::from_fn(|i| xa[i]);
                let v: [f32; LANES] = std::array::from_fn(|i| xb[i]);
                let lo: [f32; LANES] = std::array::from_fn(|i| if v[i] < u[i] { v[i] } else { u[i] });
                let hi: [f32; LANES] = std::array::from_fn(|i| if v[i] > u[i] { v[i] } else { u[i] });
                xa.copy_from_slice(&lo);
                xb.copy_from_slice(&hi);
            }
            for (x, y) in ca.into_remainder().iter_mut().zip(cb.into_remainder().iter_mut()) {
                let (u, v) = (*x, *y);
                *x = if v < u { v } else { u };
                *y = if v > u { v } else { u };
            }
        }
    }
}

/// Rank(s) that the plain median of `n` values reads.
fn median_ranks(n: usize) -> Vec<usize> {
    if n % 2 == 1 {
        vec![n / 2]
    } else {
        vec![n / 2 - 1, n / 2]
    }
}

/// Ranks the leave-one-out medians of `n` values read.
fn loo_ranks(n: usize) -> Vec<usize> {
    let k = n / 2;
    if n % 2 == 1 {
        vec![k - 1, k, k + 1]
    } else {
        vec![k - 1, k]
    }
}

/// Views in standard layout (copies only inputs that are not).
fn standard<'a>(frames: &'a [ArrayView2<'_, f32>]) -> Vec<CowArray<'a, f32, Ix2>> {
    frames.iter().map(|f| f.as_standard_layout()).collect()
}

/// Load block `[x0, x0+len)` of row `y` of every frame, mapped, into the scratch wires.
#[inline]
fn load(w: &mut [[f32; BLOCK]], rows: &[&[f32]], maps: &[Affine], x0: usize, len: usize) {
    for ((wire, row), m) in w.iter_mut().zip(rows).zip(maps) {
        for (d, &s) in wire[..len].iter_mut().zip(&row[x0..x0 + len]) {
            *d = m.apply(s);
        }
    }
}

/// Row `y` of every frame (`slices`, rows of `nx`), block by block: each block loaded,
/// mapped, into the wires `w` and put through `net`, then `emit(w, rows, x0, len)` with
/// the frames' rows `rows` and the block `[x0, x0+len)`.
#[inline]
fn sort_row_blocks<F>(
    w: &mut [[f32; BLOCK]],
    slices: &[&[f32]],
    maps: &[Affine],
    net: &Network,
    y: usize,
    nx: usize,
    emit: F,
) where
    F: FnMut(&[[f32; BLOCK]], &[&[f32]], usize, usize),
{
    let rows: Vec<&[f32]> = slices.iter().map(|s| &s[y * nx..(y + 1) * nx]).collect();
    sort_rows(w, &rows, maps, net, nx, emit);
}

/// [`sort_row_blocks`] of rows given directly (`rows[i]`: frame i's row of `nx` values).
#[inline]
fn sort_rows<F>(w: &mut [[f32; BLOCK]], rows: &[&[f32]], maps: &[Affine], net: &Network, nx: usize, mut emit: F)
where
    F: FnMut(&[[f32; BLOCK]], &[&[f32]], usize, usize),
{
    let mut x0 = 0;
    while x0 < nx {
        let len = BLOCK.min(nx - x0);
        load(w, rows, maps, x0, len);
        net.run(w, len);
        emit(w, rows, x0, len);
        x0 += len;
    }
}

/// Per-pixel median of a stack of 1..=[`MAX_STACK`] frames (no mapping).
pub fn median_stack(frames: &[ArrayView2<f32>]) -> Result<Array2<f32>> {
    median_stack_affine(frames, &vec![Affine::IDENTITY; frames.len()])
}

/// Per-pixel median of `maps[j].apply(frames[j])` over the stack (even counts: mean of
/// the two middle values). Bit-identical to `reference_median_stack`.
pub fn median_stack_affine(frames: &[ArrayView2<f32>], maps: &[Affine]) -> Result<Array2<f32>> {
    check_stack(frames, maps, 1, "median stack")?;
    let n = frames.len();
    let (ny, nx) = frames[0].dim();
    let frames = standard(frames);
    let slices: Vec<&[f32]> = frames.iter().map(|f| f.as_slice().expect("standard layout")).collect();
    let ranks = median_ranks(n);
    let net = Network::selecting(n, &ranks);
    let mut out = filled_buffers(1, ny * nx, |mut outs| {
        if nx == 0 || ny == 0 {
            return;
        }
        // Every band, row and block of the output is written once.
        outs.pop()
            .expect("one output")
            .par_chunks_mut(nx * BAND_ROWS)
            .enumerate()
            .for_each(|(band, chunk)| {
                let mut w = vec![[0f32; BLOCK]; n];
                for (r, orow) in chunk.chunks_mut(nx).enumerate() {
                    let y = band * BAND_ROWS + r;
                    sort_row_blocks(&mut w, &slices, maps, &net, y, nx, |w, _rows, x0, len| {
                        let o = &mut orow[x0..x0 + len];
                        if ranks.len() == 1 {
                            o.iter_mut().zip(&w[ranks[0]][..len]).for_each(|(o, &v)| o.put(v));
                        } else {
                            let (a, b) = (&w[ranks[0]][..len], &w[ranks[1]][..len]);
                            for ((o, &a), &b) in o.iter_mut().zip(a).zip(b) {
                                o.put(mid(a, b));
                            }
                        }
                    });
                }
            });
    });
    Ok(Array2::from_shape_vec((ny, nx), out.pop().expect("one output")).expect("ny x nx elements"))
}

/// Leave-one-out medians without mapping: element i is the per-pixel median of all
/// frames but frame i.
pub fn leave_one_out_medians(frames: &[ArrayView2<f32>]) -> Result<Vec<Array2<f32>>> {
    leave_one_out_medians_affine(frames, &vec![Affine::IDENTITY; frames.len()])
}

/// Leave-one-out medians of the mapped stack: element i is, at every pixel, the median
/// of `maps[j].apply(frames[j])` over j != i. Needs 2..=[`MAX_STACK`] frames of one
/// shape. One selection network per pixel serves all N outputs; bit-identical to
/// `reference_leave_one_out`.
pub fn leave_one_out_medians_affine(frames: &[ArrayView2<f32>], maps: &[Affine]) -> Result<Vec<Array2<f32>>> {
    check_stack(frames, maps, 2, "leave-one-out median")?;
    let (ny, nx) = frames[0].dim();
    // Fresh outputs are not zeroed first: the kernel writes every element.
    let bufs = filled_buffers(frames.len(), ny * nx, |outs| loo_kernel(frames, maps, outs));
    bufs.into_iter()
        .map(|v| Ok(Array2::from_shape_vec((ny, nx), v).expect("ny x nx elements")))
        .collect()
}

/// One output element, written once: `f32` (caller-owned buffers) or `MaybeUninit<f32>`
/// (fresh buffers, not zeroed first).
trait Slot: Send {
    fn put(&mut self, v: f32);
}

impl Slot for f32 {
    #[inline(always)]
    fn put(&mut self, v: f32) {
        *self = v;
    }
}

impl Slot for MaybeUninit<f32> {
    #[inline(always)]
    fn put(&mut self, v: f32) {
        self.write(v);
    }
}

/// `n` buffers of `len` values filled by `fill`, which is given their uninitialised
/// storage and MUST write every element (the kernels here write each output pixel once):
/// zeroing 4 MiB buffers that are overwritten anyway cost as much as a pass of the median.
fn filled_buffers(n: usize, len: usize, fill: impl FnOnce(Vec<&mut [MaybeUninit<f32>]>)) -> Vec<Vec<f32>> {
    let mut bufs: Vec<Vec<f32>> = (0..n).map(|_| Vec::with_capacity(len)).collect();
    fill(bufs.iter_mut().map(|v| &mut v.spare_capacity_mut()[..len]).collect());
    for v in &mut bufs {
        // SAFETY: the capacity is at least `len` and `fill` wrote all `len` elements (the
        // contract of this private helper, kept by every kernel that calls it: each
        // writes every pixel of every band). A panic in `fill` never gets here.
        #[allow(unsafe_code)]
        unsafe {
            v.set_len(len)
        };
    }
    bufs
}

/// [`leave_one_out_medians_affine`] into caller-owned outputs (one per frame, each of
/// the frames' shape, standard layout), e.g. to reuse buffers across sequences: fresh
/// 4 MiB allocations cost page faults comparable to the medians themselves.
pub fn leave_one_out_medians_into(frames: &[ArrayView2<f32>], maps: &[Affine], outs: &mut [Array2<f32>]) -> Result<()> {
    check_stack(frames, maps, 2, "leave-one-out median")?;
    let n = frames.len();
    let (ny, nx) = frames[0].dim();
    if outs.len() != n || outs.iter().any(|o| o.dim() != (ny, nx) || !o.is_standard_layout()) {
        return Err(Error::Stage {
            stage: "stack",
            reason: format!("leave-one-out median: need {n} standard-layout outputs of {ny}x{nx}"),
        });
    }
    loo_kernel(
        frames,
        maps,
        outs.iter_mut()
            .map(|o| o.as_slice_mut().expect("standard layout"))
            .collect(),
    );
    Ok(())
}

/// The leave-one-out medians of checked inputs into `outs` (one slice of ny x nx per
/// frame), every element written.
fn loo_kernel<T: Slot>(frames: &[ArrayView2<f32>], maps: &[Affine], outs: Vec<&mut [T]>) {
    let n = frames.len();
    let (ny, nx) = frames[0].dim();
    let frames = standard(frames);
    let slices: Vec<&[f32]> = frames.iter().map(|f| f.as_slice().expect("standard layout")).collect();
    let ranks = loo_ranks(n);
    let net = Network::selecting(n, &ranks);
    if nx == 0 || ny == 0 {
        return;
    }
    // Band b of every output, grouped, so that one task writes all N outputs of its rows.
    let mut bands: Vec<Vec<&mut [T]>> = Vec::new();
    for o in outs {
        for (b, chunk) in o.chunks_mut(nx * BAND_ROWS).enumerate() {
            if bands.len() <= b {
                bands.push(Vec::with_capacity(n));
            }
            bands[b].push(chunk);
        }
    }
    bands.into_par_iter().enumerate().for_each(|(band, mut chunks)| {
        let mut w = vec![[0f32; BLOCK]; n];
        let rows_here = chunks[0].len() / nx;
        for r in 0..rows_here {
            let y = band * BAND_ROWS + r;
            sort_row_blocks(&mut w, &slices, maps, &net, y, nx, |w, rows, x0, len| {
                for (i, chunk) in chunks.iter_mut().enumerate() {
                    loo_emit(w, rows[i], maps[i], x0, len, &mut chunk[r * nx + x0..r * nx + x0 + len]);
                }
            });
        }
    });
}

/// Frame `i`'s leave-one-out medians of block `[x0, x0+len)` of a row into `o` (`len`
/// values), from the sorted wires `w` of all frames' mapped values and frame i's own row
/// `src`: the median of the others is read off the sorted stack by where frame i's value
/// sits in it.
#[inline(always)]
fn loo_emit<T: Slot>(w: &[[f32; BLOCK]], src: &[f32], m: Affine, x0: usize, len: usize, o: &mut [T]) {
    let n = w.len();
    let k = n / 2;
    let src = &src[x0..x0 + len];
    if n % 2 == 1 {
        let (lo, md, hi) = (&w[k - 1][..len], &w[k][..len], &w[k + 1][..len]);
        for ((((o, &s), &l), &c), &h) in o.iter_mut().zip(src).zip(lo).zip(md).zip(hi) {
            let v = m.apply(s);
            let below = mid(c, h);
            let above = mid(l, c);
            let equal = mid(l, h);
            let r = if v > c { above } else { equal };
            o.put(if v < c { below } else { r });
        }
    } else {
        let (lo, hi) = (&w[k - 1][..len], &w[k][..len]);
        for (((o, &s), &l), &h) in o.iter_mut().zip(src).zip(lo).zip(hi) {
            let v = m.apply(s);
            o.put(if v >= h { l } else { h });
        }
    }
}

/// [`leave_one_out_medians_affine`] one row at a time, for a caller that consumes each
/// row of medians while it is in cache (the sky stage's last pass): the same kernel, the
/// same numbers.
pub(crate) struct LooRows<'a> {
    maps: &'a [Affine],
    net: Network,
}

impl<'a> LooRows<'a> {
    /// For stacks of `maps.len()` frames (2..=[`MAX_STACK`]), mapped by `maps`.
    pub(crate) fn new(maps: &'a [Affine]) -> LooRows<'a> {
        let n = maps.len();
        assert!((2..=MAX_STACK).contains(&n), "leave-one-out medians of {n} frames");
        LooRows {
            maps,
            net: Network::selecting(n, &loo_ranks(n)),
        }
    }

    /// Scratch wires for [`LooRows::row`] (one set per thread).
    pub(crate) fn scratch(&self) -> Vec<[f32; BLOCK]> {
        vec![[0f32; BLOCK]; self.maps.len()]
    }

    /// The leave-one-out medians of one row: `rows[i]` is frame i's row (all of one
    /// length), `outs[i]` receives its medians, every element written.
    pub(crate) fn row(&self, w: &mut [[f32; BLOCK]], rows: &[&[f32]], outs: &mut [&mut [MaybeUninit<f32>]]) {
        let nx = rows[0].len();
        sort_rows(w, rows, self.maps, &self.net, nx, |w, rows, x0, len| {
            for (i, o) in outs.iter_mut().enumerate() {
                loo_emit(w, rows[i], self.maps[i], x0, len, &mut o[x0..x0 + len]);
            }
        });
    }
}

/// Running median along x of every row: `out[y, x]` is the median of
/// `image[y, x-h ..= x+h]`, the window clipped at the row ends (clipped windows of even
/// length give the upper of the two middle values). `2 h + 1 <= MAX_STACK`. Interior
/// pixels go through a median-selection network on 2h+1 shifted copies of the row;
/// bit-identical to `reference_running_median_x`.
pub fn running_median_x(image: ArrayView2<f32>, half_window: usize) -> Result<Array2<f32>> {
    let h = half_window;
    let n = 2 * h + 1;
    if n > MAX_STACK {
        return Err(Error::Stage {
            stage: "stack",
            reason: format!("running median window 2 x {h} + 1 = {n} px exceeds {MAX_STACK}"),
        });
    }
    let (ny, nx) = image.dim();
    let img = image.as_standard_layout();
    let src = img.as_slice().expect("standard layout");
    let mut out = Array2::<f32>::zeros((ny, nx));
    if nx == 0 || ny == 0 {
        return Ok(out);
    }
    let net = Network::selecting(n, &[h]);
    out.as_slice_mut()
        .expect("fresh array")
        .par_chunks_mut(nx)
        .enumerate()
        .for_each(|(y, orow)| {
            let row = &src[y * nx..(y + 1) * nx];
            let mut w = vec![[0f32; BLOCK]; n];
            let mut buf = Vec::with_capacity(n);
            let mut clipped = |x: usize| {
                buf.clear();
                buf.extend_from_slice(&row[x.saturating_sub(h)..(x + h + 1).min(nx)]);
                let k = buf.len() / 2;
                *buf.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1
            };
            if nx < n {
                for (x, o) in orow.iter_mut().enumerate() {
                    *o = clipped(x);
                }
                return;
            }
            for x in (0..h).chain(nx - h..nx) {
                orow[x] = clipped(x);
            }
            let mut x0 = h;
            while x0 < nx - h {
                let len = BLOCK.min(nx - h - x0);
                for (j, wire) in w.iter_mut().enumerate() {
                    wire[..len].copy_from_slice(&row[x0 - h + j..x0 - h + j + len]);
                }
                net.run(&mut w, len);
                orow[x0..x0 + len].copy_from_slice(&w[h][..len]);
                x0 += len;
            }
        });
    Ok(out)
}

/// Slow reference of [`running_median_x`]: sort each clipped window.
#[cfg(test)]
pub(crate) fn reference_running_median_x(image: ArrayView2<f32>, half_window: usize) -> Array2<f32> {
    let (ny, nx) = image.dim();
    let h = half_window;
    Array2::from_shape_fn((ny, nx), |(y, x)| {
        let mut v: Vec<f32> = (x.saturating_sub(h)..(x + h + 1).min(nx))
            .map(|i| image[[y, i]])
            .collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v[v.len() / 2]
    })
}

#[cfg(test)]
mod tests;
