//! The sky stage's last pass over the frames of an orientation ([`subtract_skies`]), in
//! their own buffers, row block by row block in parallel: all frames of a block together,
//! so that the flat's rows are read once for all of them and, with the plain leave-one-out
//! median ([`SkySource::Loo`]), the block's medians are computed first from the raw rows
//! while they are in cache (the same numbers as computing them over whole frames first;
//! test `the_fused_sky_pass_matches_the_two_pass_stage`). The arithmetic on each block is
//! [`super::lanes::subtract_block`].
use std::mem::MaybeUninit;

use ndarray::Array2;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::stack;

use super::lanes::{subtract_block, Finish, FinishInputs, Kernel, Rows, Tally};

/// Where the last pass gets each frame's level-normalized sky.
pub(super) enum SkySource<'a> {
    /// Estimated before, over whole frames.
    Given(Vec<Array2<f32>>),
    /// The leave-one-out medians, computed by the pass itself row by row.
    Loo(stack::LooRows<'a>),
}

/// A frame's sky buffer in [`subtract_skies`] (it becomes the frame's data): the given
/// sky, or fresh storage (not zeroed: the leave-one-out medians write every element first).
enum SkyBuf {
    Given(Array2<f32>),
    Fresh(Vec<f32>),
}

/// A frame's sky rows of one block: estimated already, or storage the leave-one-out
/// medians are written to first.
enum SkyRows<'a> {
    Ready(&'a mut [f32]),
    Fresh(&'a mut [MaybeUninit<f32>]),
}

/// One frame's rows of one block in [`subtract_skies`], before its sky rows are ready.
struct BlockRows<'a> {
    sky: SkyRows<'a>,
    raw: &'a mut [f32],
    mask: &'a mut [u8],
    vin: Option<&'a mut [f32]>,
    count: Option<&'a [u8]>,
}

/// One frame in the pass: the frame (mask, header, history), its raw data, its sky buffer
/// and its input variance map, if any.
type Part = (Frame, Array2<f32>, SkyBuf, Option<Array2<f32>>);

/// Rows per parallel task.
const BLOCK: usize = 4;

/// The frames (raw data, masks, variance maps if any) minus their skies, with variance
/// and mask bits, divided by the flat when there is one, computed in the frames' own
/// buffers by `kernel` ([`subtract_block`]). Counts non-finite inputs, which the medians
/// cannot handle (checked here rather than in a separate pass): an error names the first
/// frame holding any. Returns with each frame its cosmic-ray candidates (flat indices in
/// row-major order; empty without `fin.cosmic_k2`).
pub(super) fn subtract_skies(
    fin: &Finish,
    frames: Vec<Frame>,
    skies: SkySource,
    inp: &FinishInputs,
    kernel: Kernel,
) -> Result<(Vec<Frame>, Vec<Vec<u32>>)> {
    let n = frames.len();
    let (ny, nx) = frames[0].shape();
    let len = ny * nx;
    // Each frame's sky buffer, which becomes its data: the given sky, or fresh storage
    // (not zeroed: the leave-one-out medians write every element first).
    let (given, loo) = match skies {
        SkySource::Given(g) => (Some(g), None),
        SkySource::Loo(l) => (None, Some(l)),
    };
    let mut given = given.map(|g| g.into_iter().map(standard));
    let mut parts: Vec<Part> = frames
        .into_iter()
        .map(|mut f| {
            let raw = standard(std::mem::take(&mut f.data));
            f.mask = standard(std::mem::take(&mut f.mask));
            let vin = f.variance.take().map(standard);
            let sky = match given.as_mut().and_then(|g| g.next()) {
                Some(s) => SkyBuf::Given(s),
                None => SkyBuf::Fresh(Vec::with_capacity(len)),
            };
            (f, raw, sky, vin)
        })
        .collect();
    let blocks = split_blocks(&mut parts, ny, nx, inp);
    // Per block (in order): non-finite counts and cosmic-ray candidates per frame.
    let per_block: Vec<Tally> = blocks
        .into_par_iter()
        .enumerate()
        .map_init(
            || loo.as_ref().map(|l| l.scratch()).unwrap_or_default(),
            |w, (b, rows)| {
                let mut rows = BlockRows::ready(rows, nx, loo.as_ref(), w);
                let mut t = Tally::new(n);
                subtract_block(kernel, fin, b * BLOCK, nx, &mut rows, inp, &mut t);
                t
            },
        )
        .collect();
    let Tally { nonfinite, candidates } = per_block.into_iter().fold(Tally::new(n), Tally::then);
    if let Some(i) = nonfinite.iter().position(|&c| c > 0) {
        return Err(Error::Stage {
            stage: "sky",
            reason: format!(
                "{}: {} non-finite pixel values (NaN/inf); sky medians need finite data",
                inp.names[i], nonfinite[i]
            ),
        });
    }
    let frames = parts
        .into_iter()
        .map(|(mut f, raw, sky, vin)| {
            f.data = match sky {
                SkyBuf::Given(s) => s,
                SkyBuf::Fresh(mut v) => {
                    // SAFETY: the capacity is `len` and every block wrote its rows of
                    // this buffer (BlockRows::ready: all `nx` values of each row), the
                    // blocks covering all `ny` rows; an error or panic never gets here.
                    #[allow(unsafe_code)]
                    unsafe {
                        v.set_len(len)
                    };
                    Array2::from_shape_vec((ny, nx), v).expect("ny x nx elements")
                }
            };
            f.variance = Some(vin.unwrap_or(raw));
            if let Some(fl) = inp.flat {
                f.history.push(fl.history());
            }
            f
        })
        .collect();
    Ok((frames, candidates))
}

/// The frames' buffers (`parts`: frame, raw data, sky buffer, input variance) cut into
/// blocks of [`BLOCK`] rows: `blocks[b][i]` holds frame i's rows of block b.
fn split_blocks<'a>(parts: &'a mut [Part], ny: usize, nx: usize, inp: &'a FinishInputs) -> Vec<Vec<BlockRows<'a>>> {
    let (n, len, chunk) = (parts.len(), ny * nx, BLOCK * nx);
    let mut blocks: Vec<Vec<BlockRows>> = (0..ny.div_ceil(BLOCK)).map(|_| Vec::with_capacity(n)).collect();
    for (i, (f, raw, sky, vin)) in parts.iter_mut().enumerate() {
        let cnt = inp.counts[i].as_ref().map(|c| c.as_slice().expect("standard layout"));
        let mut vin = vin
            .as_mut()
            .map(|v| v.as_slice_mut().expect("standard layout").chunks_mut(chunk));
        let skies: Box<dyn Iterator<Item = SkyRows>> = match sky {
            SkyBuf::Given(s) => Box::new(
                s.as_slice_mut()
                    .expect("standard layout")
                    .chunks_mut(chunk)
                    .map(SkyRows::Ready),
            ),
            SkyBuf::Fresh(v) => Box::new(v.spare_capacity_mut()[..len].chunks_mut(chunk).map(SkyRows::Fresh)),
        };
        let it = skies
            .zip(raw.as_slice_mut().expect("standard layout").chunks_mut(chunk))
            .zip(f.mask.as_slice_mut().expect("standard layout").chunks_mut(chunk));
        for (b, ((s, r), m)) in it.enumerate() {
            blocks[b].push(BlockRows {
                sky: s,
                raw: r,
                mask: m,
                vin: vin.as_mut().and_then(|v| v.next()),
                count: cnt.map(|c| &c[b * chunk..(b * chunk + chunk).min(c.len())]),
            });
        }
    }
    blocks
}

impl<'a> BlockRows<'a> {
    /// The leave-one-out medians of the block's rows (`nx` each) into the `Fresh` sky rows
    /// of every frame (from the frames' raw rows, read before the pass overwrites them),
    /// then the rows for [`subtract_block`].
    fn ready(
        rows: Vec<BlockRows<'a>>,
        nx: usize,
        loo: Option<&stack::LooRows>,
        w: &mut [[f32; stack::BLOCK]],
    ) -> Vec<Rows<'a>> {
        let mut rows = rows;
        if let Some(loo) = loo {
            let nrows = rows[0].raw.len() / nx;
            for r in 0..nrows {
                let span = r * nx..(r + 1) * nx;
                let mut raws: Vec<&[f32]> = Vec::with_capacity(rows.len());
                let mut outs: Vec<&mut [MaybeUninit<f32>]> = Vec::with_capacity(rows.len());
                for BlockRows { sky, raw, .. } in rows.iter_mut() {
                    raws.push(&raw[span.clone()]);
                    match sky {
                        SkyRows::Fresh(o) => outs.push(&mut o[span.clone()]),
                        SkyRows::Ready(_) => unreachable!("leave-one-out rows are fresh storage"),
                    }
                }
                loo.row(w, &raws, &mut outs);
            }
        }
        rows.into_iter()
            .map(|b| Rows {
                sky: match b.sky {
                    SkyRows::Ready(s) => s,
                    // SAFETY: `Fresh` rows exist only with `loo`, whose `row` wrote every
                    // element of every row of the block just above (LooRows::row writes all
                    // `nx` values of each output); MaybeUninit<f32> has f32's layout.
                    #[allow(unsafe_code)]
                    SkyRows::Fresh(o) => unsafe { &mut *(o as *mut [MaybeUninit<f32>] as *mut [f32]) },
                },
                raw: b.raw,
                mask: b.mask,
                vin: b.vin,
                count: b.count,
            })
            .collect()
    }
}

/// The array itself when it is in standard layout (no copy), else a standard copy.
fn standard<T: Clone>(a: Array2<T>) -> Array2<T> {
    if a.is_standard_layout() {
        a
    } else {
        a.as_standard_layout().into_owned()
    }
}
