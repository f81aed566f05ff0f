//! The conversion of a plain image's raw big-endian pixels (BITPIX 16 or -32) to `f32`,
//! with their [`PixelSummary`](crate::frame::PixelSummary) taken on the way: the portable
//! build [`convert_portable`] and the run-time chosen vector build [`convert`] (the same
//! numbers; test `the_conversion_is_the_same_in_every_vector_build` in `raw.rs`). The
//! numbers are cfitsio's (see `raw.rs`).
use crate::frame::SummaryLanes;

/// Pixels per conversion block (16 kB of output).
pub(super) const BLOCK: usize = 4096;

/// The raw bytes `raw` of pixel type `bitpix` (16 or -32) as `f32` appended to `out`, and
/// their summary added to `lanes`, taken block by block as they are converted (the block
/// is still in the first-level cache): the portable build, and the definition [`convert`]
/// must equal bit for bit.
#[inline(always)]
pub(super) fn convert_portable(
    raw: &[u8],
    bitpix: i64,
    scale: f64,
    zero: f64,
    out: &mut Vec<f32>,
    lanes: &mut SummaryLanes,
) {
    let width = if bitpix == 16 { 2 } else { 4 };
    for block in raw.chunks(BLOCK * width) {
        let start = out.len();
        if bitpix == 16 {
            convert_i16(block, scale, zero, out)
        } else {
            convert_f32(block, scale, zero, out)
        }
        lanes.add(&out[start..]);
    }
}

/// [`convert_portable`] compiled for AVX2 too (byte shuffles), the build chosen at run time.
#[multiversion::multiversion(targets("x86_64+avx2"))]
pub(super) fn convert(raw: &[u8], bitpix: i64, scale: f64, zero: f64, out: &mut Vec<f32>, lanes: &mut SummaryLanes) {
    convert_portable(raw, bitpix, scale, zero, out, lanes)
}

/// Big-endian 16-bit integers to `f32`, `(float)(v * scale + zero)` as cfitsio computes
/// it. With scale 1 and an integer zero the sum is exact in `i32` as in `f64`, and both
/// round the same exact value to `f32`: the integer form is taken (it vectorises).
#[inline(always)]
fn convert_i16(raw: &[u8], scale: f64, zero: f64, out: &mut Vec<f32>) {
    let words = raw.chunks_exact(2).map(|b| i16::from_be_bytes([b[0], b[1]]));
    if scale == 1.0 && zero == zero.trunc() && zero.abs() <= (1 << 30) as f64 {
        let z = zero as i32;
        out.extend(words.map(|v| (v as i32 + z) as f32));
    } else {
        out.extend(words.map(|v| (v as f64 * scale + zero) as f32));
    }
}

/// Big-endian IEEE floats to `f32`: copied, or `(float)(v * scale + zero)` when scaled.
#[inline(always)]
fn convert_f32(raw: &[u8], scale: f64, zero: f64, out: &mut Vec<f32>) {
    let floats = raw
        .chunks_exact(4)
        .map(|b| f32::from_be_bytes([b[0], b[1], b[2], b[3]]));
    if scale == 1.0 && zero == 0.0 {
        out.extend(floats);
    } else {
        out.extend(floats.map(|v| (v as f64 * scale + zero) as f32));
    }
}
