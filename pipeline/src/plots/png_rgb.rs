//! PNG encoding of the per-target figures: every row Paeth-filtered by a loop the compiler
//! vectorises (one pass over the image, no per-row branching), the filtered image
//! deflated by `fdeflate` in one call, the stream written as one IDAT chunk by the `png`
//! crate. The same filter and deflate as the `png` crate's fast setting, which filters a
//! row at a time with per-pixel branches: that filter was a fifth of a night's figure
//! time. The bytes decode to the input exactly (tests).
use std::io;

/// PNG bytes of an RGB8 image `rgb` (`w * h * 3` bytes, row 0 first), every row
/// Paeth-filtered and fast-deflated.
pub fn encode_rgb8(w: u32, h: u32, rgb: &[u8]) -> io::Result<Vec<u8>> {
    let stride = w as usize * 3;
    if w == 0 || h == 0 || rgb.len() != stride * h as usize {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "an RGB image of {w} x {h} needs {} bytes, got {}",
                stride * h as usize,
                rgb.len()
            ),
        ));
    }
    let mut z = fdeflate::Compressor::new(Vec::with_capacity(rgb.len() / 8 + 1024))?;
    let mut row = vec![0u8; stride + 1];
    for y in 0..h as usize {
        paeth_filter_row(rgb, stride, y, &mut row);
        z.write_data(&row)?;
    }
    let zlib = z.finish()?;
    let mut out = Vec::with_capacity(zlib.len() + 128);
    {
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().map_err(io::Error::other)?;
        writer.write_chunk(png::chunk::IDAT, &zlib).map_err(io::Error::other)?;
        writer.finish().map_err(io::Error::other)?;
    }
    Ok(out)
}

/// Row `y` of the image filtered into `dst` (`stride + 1` bytes): its filter type (4,
/// Paeth), then the differences; the row above row 0 is zeros (PNG's rule).
fn paeth_filter_row(rgb: &[u8], stride: usize, y: usize, dst: &mut [u8]) {
    dst[0] = 4;
    let line = &rgb[y * stride..(y + 1) * stride];
    if y == 0 {
        // Above row 0 everything is zero: the predictor is the byte to the left.
        for i in 0..stride {
            dst[1 + i] = line[i].wrapping_sub(if i >= 3 { line[i - 3] } else { 0 });
        }
    } else {
        paeth_row(&rgb[(y - 1) * stride..y * stride], line, &mut dst[1..]);
    }
}

/// One row of Paeth differences for 3 bytes per pixel: `out[i] = line[i] - paeth(a, b, c)`
/// with `a` the byte to the left, `b` the one above, `c` the one above-left (0 outside).
#[multiversion::multiversion(targets("x86_64+avx2"))]
fn paeth_row(prev: &[u8], line: &[u8], out: &mut [u8]) {
    let n = line.len().min(prev.len()).min(out.len());
    let head = n.min(3);
    // The first pixel: a = c = 0, so the predictor is b.
    for i in 0..head {
        out[i] = line[i].wrapping_sub(prev[i]);
    }
    if n <= 3 {
        return;
    }
    let (x, a) = (&line[3..n], &line[..n - 3]);
    let (b, c) = (&prev[3..n], &prev[..n - 3]);
    for ((((o, &x), &a), &b), &c) in out[3..n].iter_mut().zip(x).zip(a).zip(b).zip(c) {
        *o = x.wrapping_sub(predict(a, b, c));
    }
}

/// The Paeth predictor of PNG (ISO/IEC 15948, 9.4): the one of `a`, `b`, `c` nearest to
/// `a + b - c`, ties in that order.
#[inline(always)]
fn predict(a: u8, b: u8, c: u8) -> u8 {
    let (ai, bi, ci) = (a as i16, b as i16, c as i16);
    let pa = (bi - ci).abs();
    let pb = (ai - ci).abs();
    let pc = (ai + bi - 2 * ci).abs();
    if pa <= pb && pa <= pc {
        a
    } else if pb <= pc {
        b
    } else {
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The predictor as the PNG specification writes it (p = a + b - c, distances to p).
    fn predict_spec(a: u8, b: u8, c: u8) -> u8 {
        let p = a as i32 + b as i32 - c as i32;
        let (pa, pb, pc) = ((p - a as i32).abs(), (p - b as i32).abs(), (p - c as i32).abs());
        if pa <= pb && pa <= pc {
            a
        } else if pb <= pc {
            b
        } else {
            c
        }
    }

    #[test]
    fn predictor_equals_the_specification_for_every_triple() {
        for a in 0..=255u8 {
            for b in 0..=255u8 {
                for c in (0..=255u8).step_by(3) {
                    assert_eq!(predict(a, b, c), predict_spec(a, b, c), "a {a} b {b} c {c}");
                }
            }
        }
    }

    fn decode(png_bytes: &[u8]) -> (u32, u32, Vec<u8>) {
        let dec = png::Decoder::new(std::io::Cursor::new(png_bytes));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf)
    }

    /// A deterministic image mixing flat areas, edges and noise.
    fn image(w: u32, h: u32, seed: u64) -> Vec<u8> {
        let mut s = seed | 1;
        (0..w * h * 3)
            .map(|i| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                let (x, y) = ((i / 3) % w, (i / 3) / w);
                if (x / 7 + y / 5) % 3 == 0 {
                    255
                } else if x % 11 == 0 {
                    (y * 3) as u8
                } else {
                    (s >> 24) as u8
                }
            })
            .collect()
    }

    #[test]
    fn decodes_to_the_input_exactly() {
        for (w, h) in [(1, 1), (2, 3), (5, 1), (37, 19), (1200, 40)] {
            let img = image(w, h, (w * 1000 + h) as u64);
            let bytes = encode_rgb8(w, h, &img).unwrap();
            assert_eq!(decode(&bytes), (w, h, img), "{w} x {h}");
        }
    }

    #[test]
    fn filter_equals_a_per_pixel_reference() {
        let (w, h) = (53u32, 9u32);
        let img = image(w, h, 7);
        let stride = w as usize * 3;
        let mut f = vec![0u8; h as usize * (stride + 1)];
        for (y, row) in f.chunks_exact_mut(stride + 1).enumerate() {
            paeth_filter_row(&img, stride, y, row);
        }
        for y in 0..h as usize {
            assert_eq!(f[y * (stride + 1)], 4);
            for i in 0..stride {
                let at = |yy: usize, ii: usize| img[yy * stride + ii];
                let a = if i >= 3 { at(y, i - 3) } else { 0 };
                let b = if y >= 1 { at(y - 1, i) } else { 0 };
                let c = if i >= 3 && y >= 1 { at(y - 1, i - 3) } else { 0 };
                let want = at(y, i).wrapping_sub(predict_spec(a, b, c));
                assert_eq!(f[y * (stride + 1) + 1 + i], want, "row {y} byte {i}");
            }
        }
    }

    #[test]
    fn wrong_size_is_refused_with_the_sizes() {
        let e = encode_rgb8(4, 4, &[0; 47]).unwrap_err().to_string();
        assert!(e.contains("48") && e.contains("47"), "{e}");
        assert!(encode_rgb8(0, 4, &[]).is_err());
    }
}
