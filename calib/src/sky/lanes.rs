//! The arithmetic of the sky stage's last pass on one block of rows of every frame of an
//! orientation ([`subtract_block`]): the sky brought back to the frame's level, data =
//! raw - sky, the variance map, the mask bits, the flat divided out, the non-finite inputs
//! counted and the cosmic-ray candidates collected. Written so that every row loop
//! vectorises: the portable build [`subtract_block_portable`] and the run-time chosen
//! vector build [`subtract_block_vector`] (AVX2 when the CPU has it) give the same numbers
//! (test `the_sky_pass_is_the_same_in_every_vector_build`).
use crate::flat::{FlatRow, FlatRows};
use crate::frame::mask;
use crate::stack;

use super::cosmic;
use super::SkyScaling;

/// Which build of the row kernel runs: the fastest this CPU has (what the reduction uses)
/// or the portable one (the reference the tests compare it with).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kernel {
    /// The widest vectors the CPU has, chosen at run time.
    Fastest,
    /// The portable build (SSE2 on x86_64).
    #[cfg_attr(not(test), allow(dead_code))]
    Portable,
}

/// The settings of the last pass, shared by every frame of an orientation.
pub(super) struct Finish {
    pub(super) scaling: SkyScaling,
    /// Rows outside every strip (OFF_STRIP).
    pub(super) off_rows: Vec<bool>,
    pub(super) sat: f32,
    pub(super) nonlin: f32,
    /// c(m)/m with m = N - 1 (every pixel's sky from all other dithers).
    pub(super) c_over_m: f32,
    /// c(k)/k by the number k of dithers in a pixel's sky (source-masked pass).
    pub(super) c_over_count: [f32; stack::MAX_STACK + 1],
    /// With cosmic-ray flagging: the squared threshold of its candidate test, run on each
    /// row as it is written ([`cosmic::push_candidates`]).
    pub(super) cosmic_k2: Option<f32>,
}

/// Per-frame inputs of the last pass.
pub(super) struct FinishInputs<'a> {
    /// Per-pixel counts of the dithers in each sky (source-masked pass), else None.
    pub(super) counts: &'a [Option<ndarray::Array2<u8>>],
    /// Sky level L_i, ADU.
    pub(super) levels: Vec<f32>,
    /// (1 / effective gain, read variance), ADU and ADU^2.
    pub(super) noise: &'a [(f32, f32)],
    /// Names for error messages.
    pub(super) names: &'a [String],
    /// The flat divided out in the pass, if any.
    pub(super) flat: Option<&'a FlatRows<'a>>,
}

/// One frame's rows of one block, all of `nx` pixels.
pub(super) struct Rows<'a> {
    /// The level-normalized sky on input; the data (raw - sky, flat divided) on output.
    pub(super) sky: &'a mut [f32],
    /// The raw values on input; the variance on output when there is no `vin`.
    pub(super) raw: &'a mut [f32],
    pub(super) mask: &'a mut [u8],
    /// The input variance map's rows, when the frame has one (the variance on output).
    pub(super) vin: Option<&'a mut [f32]>,
    /// The per-pixel dither counts of the skies (source-masked pass).
    pub(super) count: Option<&'a [u8]>,
}

/// What the last pass counts per frame (over a block of rows, then over the frames):
/// non-finite raw values, and the cosmic-ray candidates (flat indices, row-major).
pub(super) struct Tally {
    pub(super) nonfinite: Vec<usize>,
    pub(super) candidates: Vec<Vec<u32>>,
}

impl Tally {
    /// Nothing counted yet, for `n` frames.
    pub(super) fn new(n: usize) -> Tally {
        Tally {
            nonfinite: vec![0; n],
            candidates: vec![Vec::new(); n],
        }
    }

    /// This tally followed by `next` (the next block: candidates stay in row order).
    pub(super) fn then(mut self, next: Tally) -> Tally {
        for (i, (c, cd)) in next.nonfinite.into_iter().zip(next.candidates).enumerate() {
            self.nonfinite[i] += c;
            self.candidates[i].extend(cd);
        }
        self
    }
}

/// The rows of one block (first row `y0`, `nx` pixels wide) of every frame, with the
/// `kernel` build: sky <- level-scaled estimate, data = raw - sky (in the sky's buffer),
/// the variance in the input's variance map or else in the raw data's buffer, mask bits
/// alongside, then the flat divided out when there is one; non-finite raw values and
/// cosmic-ray candidates added to `tally`.
pub(super) fn subtract_block(
    kernel: Kernel,
    fin: &Finish,
    y0: usize,
    nx: usize,
    rows: &mut [Rows],
    inp: &FinishInputs,
    tally: &mut Tally,
) {
    match kernel {
        Kernel::Fastest => subtract_block_vector(fin, y0, nx, rows, inp, tally),
        Kernel::Portable => subtract_block_portable(fin, y0, nx, rows, inp, tally),
    }
}

/// [`subtract_block_portable`] compiled for AVX2 too, the build chosen at run time.
#[multiversion::multiversion(targets("x86_64+avx2"))]
pub(super) fn subtract_block_vector(
    fin: &Finish,
    y0: usize,
    nx: usize,
    rows: &mut [Rows],
    inp: &FinishInputs,
    tally: &mut Tally,
) {
    subtract_block_portable(fin, y0, nx, rows, inp, tally)
}

/// See [`subtract_block`]: the portable build.
#[inline(always)]
pub(super) fn subtract_block_portable(
    fin: &Finish,
    y0: usize,
    nx: usize,
    rows: &mut [Rows],
    inp: &FinishInputs,
    tally: &mut Tally,
) {
    for r in 0..rows[0].sky.len() / nx {
        let y = y0 + r;
        let span = r * nx..(r + 1) * nx;
        for (i, fr) in rows.iter_mut().enumerate() {
            // The frame's row y: a block of one row.
            let row = Rows {
                sky: &mut fr.sky[span.clone()],
                raw: &mut fr.raw[span.clone()],
                mask: &mut fr.mask[span.clone()],
                vin: fr.vin.as_deref_mut().map(|v| &mut v[span.clone()]),
                count: fr.count.map(|c| &c[span.clone()]),
            };
            let px = (inp.levels[i], inp.noise[i]);
            tally.nonfinite[i] += match inp.flat {
                None => subtract_row::<false>(fin, y, row, px, None),
                Some(fl) => subtract_row::<true>(fin, y, row, px, Some(fl.row(y))),
            };
            if let Some(k2) = fin.cosmic_k2 {
                // The row's final data and variance, still in cache.
                let var: &[f32] = match fr.vin.as_deref() {
                    Some(v) => &v[span.clone()],
                    None => &fr.raw[span.clone()],
                };
                cosmic::push_candidates(
                    &fr.sky[span.clone()],
                    var,
                    k2,
                    (y * nx) as u32,
                    &mut tally.candidates[i],
                );
            }
        }
    }
}

/// One row `y` of one frame (`row`, a block of one row): mask bits from the raw values,
/// the variance (into the row's `vin` when the frame has a variance map, else over the raw
/// values), data = raw - sky into the sky's row; with `FLAT`, divided by the flat's row in
/// the same loop ([`crate::flat::FlatRows`]: data / f, variance / f^2 + max(data / f, 0)^2
/// var_f / f^2, BAD and no division where the flat is unusable). `(level, (inv_g, rv))`
/// is the frame's sky level and noise, as [`FinishInputs`] holds them. Returns the count
/// of non-finite raw values.
#[inline(always)]
fn subtract_row<const FLAT: bool>(
    fin: &Finish,
    y: usize,
    row: Rows,
    (level, (inv_g, rv)): (f32, (f32, f32)),
    flat: Option<FlatRow>,
) -> usize {
    let Rows {
        sky: srow,
        raw: rrow,
        mask: mrow,
        vin: vrow,
        count: cnt,
    } = row;
    let (scaling, c_over_m) = (fin.scaling, fin.c_over_m);
    mask_row(fin, y, mrow, rrow);
    let bad = rrow.iter().filter(|r| !r.is_finite()).count();
    let nx = srow.len();
    // Every row resliced to nx: the index checks of the loops below fold away and the
    // loops vectorise.
    let rrow = &mut rrow[..nx];
    let cnt = cnt.map(|c| &c[..nx]);
    let (finv, fvar) = match flat {
        Some(f) => {
            mrow.iter_mut().zip(&f.bad[..nx]).for_each(|(m, b)| *m |= b);
            (&f.inv[..nx], &f.var[..nx])
        }
        None => (&[][..], &[][..]),
    };
    // data and variance of one pixel, divided by the flat with FLAT.
    let divided = |x: usize, d: f32, v: f32| -> (f32, f32) {
        if FLAT {
            let a = finv[x];
            let o = d * a;
            let ex = o.max(0.0);
            (o, (v + ex * ex * fvar[x]) * (a * a))
        } else {
            (d, v)
        }
    };
    match vrow {
        Some(vrow) => {
            let vrow = &mut vrow[..nx];
            let mut one = |x: usize, com: f32| {
                let r = rrow[x];
                let s = scale(srow[x], level, scaling);
                (srow[x], vrow[x]) = divided(x, r - s, vrow[x] + com * (s.max(0.0) * inv_g + rv));
            };
            match cnt {
                None => (0..nx).for_each(|x| one(x, c_over_m)),
                Some(c) => (0..nx).for_each(|x| one(x, fin.c_over_count[c[x] as usize])),
            }
        }
        None => {
            let mut one = |x: usize, com: f32| {
                let r = rrow[x];
                let s = scale(srow[x], level, scaling);
                (srow[x], rrow[x]) = divided(x, r - s, r.max(0.0) * inv_g + rv + com * (s.max(0.0) * inv_g + rv));
            };
            match cnt {
                None => (0..nx).for_each(|x| one(x, c_over_m)),
                Some(c) => (0..nx).for_each(|x| one(x, fin.c_over_count[c[x] as usize])),
            }
        }
    }
    bad
}

/// OFF_STRIP, SATURATED and NONLINEAR bits of one row (from the raw values).
fn mask_row(fin: &Finish, y: usize, mrow: &mut [u8], rrow: &[f32]) {
    let off = if fin.off_rows[y] { mask::OFF_STRIP } else { 0 };
    let (sat, nonlin) = (fin.sat, fin.nonlin);
    for (b, &r) in mrow.iter_mut().zip(rrow) {
        *b |= off | (((r >= sat) as u8) * mask::SATURATED) | (((r >= nonlin) as u8) * mask::NONLINEAR);
    }
}

/// The sky at one pixel from the level-normalized estimate.
#[inline(always)]
fn scale(s: f32, level: f32, scaling: SkyScaling) -> f32 {
    match scaling {
        SkyScaling::Multiplicative => s * level,
        SkyScaling::Additive => s + level,
    }
}
