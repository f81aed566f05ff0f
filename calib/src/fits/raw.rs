//! The pixels of a plain FITS image read straight from the file: the frames of a night
//! (BITPIX 16 with BZERO/BSCALE, or -32, uncompressed) are read this way, a row range at a
//! time, and converted to `f32` in one pass, without cfitsio's zero-filled output buffer,
//! its I/O buffers and its separate byte-swap and scaling passes. A file that is one plain
//! 2-D primary image and nothing else has its header read here too ([`plain_primary`]);
//! for other plain files cfitsio finds the HDU and says where its data start; every other
//! file (tile-compressed, gzip, other BITPIX, odd scaling keywords) is read by cfitsio.
//!
//! The numbers are cfitsio's, bit for bit: integers are scaled as `(float)(v * BSCALE +
//! BZERO)` in double precision (cfitsio's `fffi2r4`), floats copied (or scaled the same
//! way when BSCALE/BZERO are not 1/0), NaN passed through; no BLANK substitution, like the
//! cfitsio reads of this crate (null value 0: no null checking). The test
//! `plain_reads_equal_cfitsio_reads` compares the two for both pixel types, many scalings,
//! extreme values and row ranges.
use std::cell::RefCell;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use fitsio::FitsFile;
use ndarray::Array2;

use crate::error::{Error, Result};
use crate::frame::{PixelSummary, SummaryLanes};
use crate::header::HeaderValue;

use super::cfitsio::{data_start, fits_err};
use super::convert::{convert, BLOCK};
use super::keys::{is_compressed, raw_int, raw_value};
use super::to_array;

/// How to read and convert the pixels of a plain image HDU.
#[derive(Debug, Clone, Copy)]
pub(super) struct PlainImage {
    /// File offset of the first data byte.
    start: u64,
    /// 16 or -32.
    bitpix: i64,
    scale: f64,
    zero: f64,
}

/// The value of a scaling keyword: absent = `default`; `None` when it is present but not a
/// finite number this module is sure to parse as cfitsio does (left to cfitsio).
fn scaling(cards: &[String], key: &str, default: f64) -> Option<f64> {
    let v = match raw_value(cards, key) {
        None => return Some(default),
        Some(HeaderValue::Int(i)) => i as f64,
        Some(HeaderValue::Float(x)) => x,
        Some(_) => return None,
    };
    v.is_finite().then_some(v)
}

/// Whether the file is plain FITS on disk (it starts with the SIMPLE card), so that file
/// offsets are data offsets (cfitsio reads gzip, compress... files through memory).
fn plain_file(path: &Path) -> bool {
    let mut m = [0u8; 9];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut m))
        .map(|_| &m == b"SIMPLE  =")
        .unwrap_or(false)
}

/// The plan for reading HDU `index` (header `cards`) directly, or `None` when cfitsio must
/// read it.
pub(super) fn plain_image(f: &mut FitsFile, path: &Path, index: usize, cards: &[String]) -> Result<Option<PlainImage>> {
    if plain_pixels(cards).is_none() || !plain_file(path) {
        return Ok(None);
    }
    let start = data_start(f, index).map_err(|e| fits_err(path, &format!("locating the data of HDU {index}"), e))?;
    Ok(PlainImage::at(cards, start))
}

/// BITPIX, BSCALE and BZERO of an image this module reads: uncompressed, BITPIX 16 or -32,
/// finite numeric scaling with BSCALE != 0.
fn plain_pixels(cards: &[String]) -> Option<(i64, f64, f64)> {
    if is_compressed(cards) {
        return None;
    }
    let bitpix @ (16 | -32) = raw_int(cards, "BITPIX")? else {
        return None;
    };
    let (scale, zero) = (scaling(cards, "BSCALE", 1.0)?, scaling(cards, "BZERO", 0.0)?);
    (scale != 0.0).then_some((bitpix, scale, zero))
}

impl PlainImage {
    /// The image of `cards` whose data start at byte `start`, when this module reads it.
    pub(super) fn at(cards: &[String], start: u64) -> Option<PlainImage> {
        plain_pixels(cards).map(|(bitpix, scale, zero)| PlainImage {
            start,
            bitpix,
            scale,
            zero,
        })
    }
}

/// A FITS file that is one primary image and nothing else, its header read straight from
/// the file (see [`plain_primary`]).
pub(super) struct PlainPrimary {
    /// The header cards as cfitsio lists them: END and the blank cards just before it
    /// left out, trailing blanks removed.
    pub cards: Vec<String>,
    /// File offset of the first data byte.
    pub start: u64,
}

/// Header blocks read before giving up on finding END (and leaving the file to cfitsio).
const MAX_HEADER_BLOCKS: usize = 64;

/// The header of a night frame read without cfitsio (whose open, HDU map and card-by-card
/// reads cost more than reading the pixels' header twice over): the file starts with the
/// mandatory keywords of a primary image in order (SIMPLE = T, BITPIX, NAXIS = 2, NAXIS1,
/// NAXIS2, all positive), its header is printable ASCII up to an END card within
/// [`MAX_HEADER_BLOCKS`] blocks, and the file ends with the image's data (padded to a
/// 2880-byte block or not): no extension. Anything else (compressed, gzip, extensions,
/// another layout, an unreadable or truncated file) gives None, and cfitsio reads the file
/// and words any error as before. The cards and data offset are cfitsio's (test
/// `plain_primary_headers_are_cfitsio_headers`).
pub(super) fn plain_primary(path: &Path) -> Option<PlainPrimary> {
    const BLOCK_BYTES: usize = 2880;
    // A regular file only, checked before opening (opening a named pipe would wait for a
    // writer); cfitsio's path refuses the others by name.
    let len = std::fs::metadata(path).ok().filter(|m| m.is_file())?.len();
    let mut file = std::fs::File::open(path).ok()?;
    let mut cards: Vec<String> = Vec::new();
    // Blank cards since the last non-blank one (cfitsio leaves those just before END out).
    let mut blanks = 0;
    let mut block = [0u8; BLOCK_BYTES];
    for b in 0..MAX_HEADER_BLOCKS {
        file.read_exact(&mut block).ok()?;
        if (b == 0 && !block.starts_with(b"SIMPLE  =")) || !block.iter().all(|c| (b' '..=b'~').contains(c)) {
            return None;
        }
        for card in block.chunks_exact(80) {
            if card.starts_with(b"END     ") {
                cards.truncate(cards.len() - blanks);
                let start = ((b + 1) * BLOCK_BYTES) as u64;
                return primary_layout_ok(&cards, start, len).then_some(PlainPrimary { cards, start });
            }
            let text = std::str::from_utf8(card).ok()?.trim_end_matches(' ');
            blanks = if text.is_empty() { blanks + 1 } else { 0 };
            cards.push(text.to_string());
        }
    }
    None
}

/// The mandatory keywords of a 2-D primary image in order, and a file that ends with its
/// data.
fn primary_layout_ok(cards: &[String], start: u64, len: u64) -> bool {
    use super::cards::{parse_card, Parsed};
    let value = |i: usize, key: &str| match cards.get(i).map(|c| parse_card(c)) {
        Some(Parsed::Key { key: k, value, .. }) if k == key => Some(value),
        _ => None,
    };
    let int = |i: usize, key: &str| match value(i, key) {
        Some(HeaderValue::Int(v)) => Some(v),
        _ => None,
    };
    if value(0, "SIMPLE") != Some(HeaderValue::Bool(true)) || int(2, "NAXIS") != Some(2) {
        return false;
    }
    let (Some(bitpix @ (8 | 16 | 32 | 64 | -32 | -64)), Some(nx @ 1..), Some(ny @ 1..)) =
        (int(1, "BITPIX"), int(3, "NAXIS1"), int(4, "NAXIS2"))
    else {
        return false;
    };
    let bytes = (nx as u64)
        .checked_mul(ny as u64)
        .and_then(|p| p.checked_mul(bitpix.unsigned_abs() / 8));
    match bytes.and_then(|b| Some((b, b.checked_next_multiple_of(2880)?))) {
        Some((b, padded)) => len == start.saturating_add(b) || len == start.saturating_add(padded),
        None => false,
    }
}

thread_local! {
    /// The raw bytes of the last rows read on this thread (reused: no allocation, no
    /// zeroing per frame).
    static RAW: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
}

impl PlainImage {
    /// Rows `[r0, r0 + n)` of an image `nx` pixels wide, as `f32`, and their summary.
    pub(super) fn read_rows(&self, path: &Path, nx: usize, r0: usize, n: usize) -> Result<(Array2<f32>, PixelSummary)> {
        let width = if self.bitpix == 16 { 2 } else { 4 };
        let bytes = n * nx * width;
        let offset = self.start + (r0 * nx * width) as u64;
        RAW.with_borrow_mut(|raw| {
            let io = |source: std::io::Error| Error::Io {
                path: path.to_path_buf(),
                source,
            };
            let mut file = std::fs::File::open(path).map_err(io)?;
            file.seek(SeekFrom::Start(offset)).map_err(io)?;
            // Read and converted a piece at a time: each piece is converted while it is
            // still in the cache the read copied it to.
            let piece = READ_PIECE_PX * width;
            raw.resize(piece.min(bytes), 0);
            let mut out = Vec::with_capacity(n * nx);
            let mut lanes = SummaryLanes::new();
            let mut done = 0;
            while done < bytes {
                let len = piece.min(bytes - done);
                file.read_exact(&mut raw[..len]).map_err(|e| match e.kind() {
                    std::io::ErrorKind::UnexpectedEof => Error::Fits {
                        path: path.to_path_buf(),
                        message: format!(
                            "reading rows [{r0}, {}): the file ends inside the image data (is the file truncated?)",
                            r0 + n
                        ),
                    },
                    _ => io(e),
                })?;
                convert(&raw[..len], self.bitpix, self.scale, self.zero, &mut out, &mut lanes);
                done += len;
            }
            Ok((to_array(out, n, nx, path)?, lanes.finish()))
        })
    }
}

/// Pixels read per `read` call of [`PlainImage::read_rows`] (a whole number of conversion
/// blocks, so that the blocks and their summaries are those of one conversion of the whole
/// range).
const READ_PIECE_PX: usize = 8 * BLOCK;

#[cfg(test)]
mod tests {
    use super::super::convert::convert_portable;
    use super::*;
    use crate::fits::{read_frame, read_frame_rows, read_frame_rows_with_summary};

    /// A minimal plain FITS file: the given extra cards, big-endian `data` bytes.
    fn fits_bytes(bitpix: i64, nx: usize, ny: usize, extra: &[&str], data: &[u8]) -> Vec<u8> {
        let mut cards = vec![
            format!("{:<8}= {:>20}", "SIMPLE", "T"),
            format!("{:<8}= {:>20}", "BITPIX", bitpix),
            format!("{:<8}= {:>20}", "NAXIS", 2),
            format!("{:<8}= {:>20}", "NAXIS1", nx),
            format!("{:<8}= {:>20}", "NAXIS2", ny),
        ];
        cards.extend(extra.iter().map(|s| s.to_string()));
        cards.push("END".into());
        let mut out: Vec<u8> = cards.iter().flat_map(|c| format!("{c:<80}").into_bytes()).collect();
        out.resize(out.len().div_ceil(2880) * 2880, b' ');
        out.extend_from_slice(data);
        out.resize(out.len().div_ceil(2880) * 2880, 0);
        out
    }

    use rand::{rngs::Xoshiro256PlusPlus, RngExt, SeedableRng};

    type Rng = Xoshiro256PlusPlus;

    /// Pixel bytes with the extreme values first, then random ones.
    fn pixels(bitpix: i64, n: usize, rng: &mut Rng) -> Vec<u8> {
        if bitpix == 16 {
            let special: [i16; 5] = [i16::MIN, i16::MAX, 0, -1, 1];
            (0..n)
                .flat_map(|i| {
                    special
                        .get(i)
                        .copied()
                        .unwrap_or_else(|| rng.random::<i16>())
                        .to_be_bytes()
                })
                .collect()
        } else {
            let special = [
                f32::NAN,
                f32::INFINITY,
                f32::NEG_INFINITY,
                -0.0,
                f32::MIN_POSITIVE / 4.0,
                f32::MAX,
                f32::MIN,
            ];
            (0..n)
                .flat_map(|i| {
                    let v = special.get(i).copied().unwrap_or_else(|| {
                        // Mostly sky-like values, sometimes any bit pattern.
                        if rng.random_range(0..8) == 0 {
                            f32::from_bits(rng.random::<u32>())
                        } else {
                            rng.random_range(0..2_000_000) as f32 * 0.01 - 100.0
                        }
                    });
                    v.to_be_bytes()
                })
                .collect()
        }
    }

    fn plain_summary(v: &[f32]) -> PixelSummary {
        let fin: Vec<f32> = v.iter().copied().filter(|x| x.is_finite()).collect();
        PixelSummary {
            non_finite: v.len() - fin.len(),
            min: fin.iter().copied().fold(f32::INFINITY, f32::min),
            max: fin.iter().copied().fold(f32::NEG_INFINITY, f32::max),
        }
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// The direct reads give cfitsio's numbers bit for bit (cfitsio read through `fitsio`
    /// is the reference): both pixel types, scalings that take the integer, the double and
    /// the copying conversions, keywords written in several forms, extreme values, NaN and
    /// infinities, whole images and row ranges; and the summary is that of the pixels.
    #[test]
    fn plain_reads_equal_cfitsio_reads() {
        let dir = tempfile::tempdir().unwrap();
        // More pixels than two read pieces (READ_PIECE_PX), not a whole number of them.
        let (nx, ny) = (301, 233);
        assert!(nx * ny > 2 * READ_PIECE_PX && (nx * ny) % READ_PIECE_PX != 0);
        let mut rng = Rng::seed_from_u64(0x9e37_79b9_7f4a_7c15);
        let scalings: &[&[&str]] = &[
            &[],
            &["BZERO   =                32768", "BSCALE  =                    1"],
            &["BZERO   =                  0.0", "BSCALE  =                  1.0"],
            &["BZERO   =               -17.25", "BSCALE  =                  2.5"],
            &["BZERO   =              32768.5"],
            &["BZERO   =         3000000000.0"],
            &["BSCALE  =                 -1.0"],
            &["BSCALE  =               1.0E-3", "BZERO   =               1.0E+4"],
            &["BSCALE  =                2.0D0"],
            &["BZERO   =     0.30000000000000004"],
            &["BLANK   =                -32768", "BZERO   =                32768"],
        ];
        let mut n_plain = 0;
        for bitpix in [16, -32] {
            for (k, extra) in scalings.iter().enumerate() {
                let path = dir.path().join(format!("f{bitpix}_{k}.fits"));
                std::fs::write(
                    &path,
                    fits_bytes(bitpix, nx, ny, extra, &pixels(bitpix, nx * ny, &mut rng)),
                )
                .unwrap();
                let mut f = FitsFile::open(&path).unwrap();
                let hdu = f.hdu(0).unwrap();
                let whole: Vec<f32> = hdu.read_image(&mut f).unwrap();
                // Which keyword forms this module reads itself (the others go to cfitsio).
                let cards = super::super::read::hdu_cards(&mut f, &path, 0).unwrap().unwrap();
                n_plain += plain_image(&mut f, &path, 0, &cards).unwrap().is_some() as usize;
                for rows in [None, Some((0, ny)), Some((3, 17)), Some((3, 150)), Some((ny - 1, ny))] {
                    let (r0, n) = rows.map_or((0, ny), |(a, b)| (a, b - a));
                    let want: Vec<f32> = hdu.read_rows(&mut f, r0, n).unwrap();
                    assert_eq!(bits(&want), bits(&whole[r0 * nx..(r0 + n) * nx]));
                    let (got, summary) = read_frame_rows_with_summary(&path, rows).unwrap();
                    let what = format!("BITPIX {bitpix}, {extra:?}, rows {rows:?}");
                    assert_eq!(bits(got.data.as_slice().unwrap()), bits(&want), "{what}");
                    let s = plain_summary(&want);
                    assert_eq!(
                        (summary.non_finite, summary.min.to_bits(), summary.max.to_bits()),
                        (s.non_finite, s.min.to_bits(), s.max.to_bits()),
                        "{what}"
                    );
                    let plain = read_frame_rows(&path, rows).unwrap();
                    assert_eq!(bits(plain.data.as_slice().unwrap()), bits(&want), "{what}");
                }
            }
        }
        // All but the Fortran exponent are read directly, in both pixel types.
        assert!(n_plain >= 2 * (scalings.len() - 1), "{n_plain} direct reads");
    }

    /// The header read without cfitsio is cfitsio's: the same cards (trailing blanks
    /// removed, the blank cards just before END left out, blank and commentary cards
    /// elsewhere kept) and the same data offset, for headers of one to three blocks, data
    /// padded or not; and it declines (cfitsio reads the file) whatever is not one plain
    /// 2-D primary image: extensions, a short or long file, another NAXIS, the mandatory
    /// keywords out of order, a non-ASCII byte in the header, no END, a gzip file.
    #[test]
    fn plain_primary_headers_are_cfitsio_headers() {
        let dir = tempfile::tempdir().unwrap();
        let (nx, ny) = (37, 21);
        let mut rng = Rng::seed_from_u64(5);
        let data = pixels(16, nx * ny, &mut rng);
        let many: Vec<String> = (0..70).map(|i| format!("HIERARCH ESO DET CHIP{i} X = {i}")).collect();
        let mut headers: Vec<Vec<&str>> = vec![
            vec![],
            vec![
                "BZERO   =                32768",
                "OBJECT  = 'HK Tau  '   / target",
                "",
                "COMMENT a comment   ",
            ],
            vec!["HIERARCH ESO ADA POSANG = 45.0", "", "HISTORY x", "  ", "", ""],
        ];
        headers.push(many.iter().map(|s| s.as_str()).collect());
        let mut checked = 0;
        for (k, extra) in headers.iter().enumerate() {
            for padded in [true, false] {
                let mut bytes = fits_bytes(16, nx, ny, extra, &data);
                if !padded {
                    let head = bytes.len() - data.len().next_multiple_of(2880);
                    bytes.truncate(head + data.len());
                }
                let path = dir.path().join(format!("h{k}_{padded}.fits"));
                std::fs::write(&path, &bytes).unwrap();
                let got = plain_primary(&path).expect("a plain primary image");
                let mut f = FitsFile::open(&path).unwrap();
                let want = super::super::read::hdu_cards(&mut f, &path, 0).unwrap().unwrap();
                assert_eq!(got.cards, want, "header {k}");
                assert_eq!(got.start, data_start(&mut f, 0).unwrap(), "header {k}");
                checked += 1;
            }
        }
        assert_eq!(checked, 8);
        // Declined.
        let good = fits_bytes(16, nx, ny, &[], &data);
        let mut cases: Vec<(&str, Vec<u8>)> = vec![
            ("an extension after the image", [good.clone(), good.clone()].concat()),
            ("a file cut inside the data", good[..good.len() - 2880].to_vec()),
            ("a byte after the padding", [good.clone(), vec![0]].concat()),
            ("NAXIS 3", fits_bytes(16, nx, ny, &[], &data)),
            ("NAXIS1 after NAXIS2", fits_bytes(16, nx, ny, &[], &data)),
            ("a non-ASCII byte", fits_bytes(16, nx, ny, &["OBJECT  = 'x'"], &data)),
            (
                "no END",
                good[..2880].iter().map(|&b| if b == b'E' { b'X' } else { b }).collect(),
            ),
            ("SIMPLE = F", fits_bytes(16, nx, ny, &[], &data)),
        ];
        let find = |b: &[u8], key: &str| {
            (0..b.len() / 80)
                .map(|i| i * 80)
                .find(|&i| b[i..].starts_with(key.as_bytes()))
                .unwrap()
        };
        let at = find(&cases[3].1, "NAXIS   ");
        cases[3].1[at..at + 30].copy_from_slice(format!("{:<8}= {:>20}", "NAXIS", 3).as_bytes());
        let (a, b) = (find(&cases[4].1, "NAXIS1"), find(&cases[4].1, "NAXIS2"));
        let (c1, c2) = (cases[4].1[a..a + 80].to_vec(), cases[4].1[b..b + 80].to_vec());
        cases[4].1[a..a + 80].copy_from_slice(&c2);
        cases[4].1[b..b + 80].copy_from_slice(&c1);
        let at = find(&cases[5].1, "OBJECT");
        cases[5].1[at + 12] = 0xe9;
        let at = find(&cases[7].1, "SIMPLE");
        cases[7].1[at + 29] = b'F';
        for (what, bytes) in &cases {
            let path = dir.path().join("declined.fits");
            std::fs::write(&path, bytes).unwrap();
            assert!(plain_primary(&path).is_none(), "{what}");
        }
        // gzip
        let path = dir.path().join("g.fits.gz");
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        std::io::Write::write_all(&mut enc, &good).unwrap();
        std::fs::write(&path, enc.finish().unwrap()).unwrap();
        assert!(plain_primary(&path).is_none());
        // An unsigned 64-bit image (BITPIX 64, BZERO 2^63) has a plain header, and its header
        // and pixels are still refused by name, as through cfitsio.
        let u64_bytes = fits_bytes(64, nx, ny, &["BZERO   =  9223372036854775808"], &vec![0u8; nx * ny * 8]);
        let path = dir.path().join("u64.fits");
        std::fs::write(&path, &u64_bytes).unwrap();
        assert!(plain_primary(&path).is_some());
        for e in [
            crate::fits::read_header(&path).unwrap_err().to_string(),
            crate::fits::read_frame(&path).unwrap_err().to_string(),
        ] {
            assert!(e.contains("u64.fits") && e.contains("unsupported pixel type"), "{e}");
        }
        // The control: the good file is taken.
        let path = dir.path().join("good.fits");
        std::fs::write(&path, &good).unwrap();
        assert!(plain_primary(&path).is_some());
        // A named pipe is declined without opening it (opening would wait for a writer),
        // and the reader refuses it by name.
        let fifo = dir.path().join("pipe.fits");
        if std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .is_ok_and(|s| s.success())
        {
            // On a thread: a reader that opened the pipe would wait forever.
            let (tx, rx) = std::sync::mpsc::channel();
            let f = fifo.clone();
            std::thread::spawn(move || {
                let _ = tx.send((plain_primary(&f).is_none(), crate::fits::read_header(&f).map(|_| ())));
            });
            let (declined, read) = rx
                .recv_timeout(std::time::Duration::from_secs(10))
                .expect("reading a named pipe's header must not wait for a writer");
            assert!(declined);
            let e = read.unwrap_err().to_string();
            assert!(e.contains("pipe.fits") && e.contains("not a regular file"), "{e}");
        }
    }

    /// An image in the first extension of a plain file (empty primary HDU) is read
    /// directly too, from that extension's data offset, with cfitsio's numbers.
    #[test]
    fn an_image_extension_is_read_from_its_own_offset() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ext.fits");
        let (nx, ny) = (20, 11);
        let mut rng = Rng::seed_from_u64(99);
        let mut primary: Vec<u8> = [
            "SIMPLE  =                    T",
            "BITPIX  =                    8",
            "NAXIS   =                    0",
            "EXTEND  =                    T",
            "END",
        ]
        .iter()
        .flat_map(|c| format!("{c:<80}").into_bytes())
        .collect();
        primary.resize(2880, b' ');
        let mut ext = fits_bytes(
            16,
            nx,
            ny,
            &[
                "PCOUNT  =                    0",
                "GCOUNT  =                    1",
                "BZERO   =                32768",
            ],
            &pixels(16, nx * ny, &mut rng),
        );
        // XTENSION replaces SIMPLE as the extension's first card.
        ext[..80].copy_from_slice(format!("{:<80}", "XTENSION= 'IMAGE   '").as_bytes());
        primary.extend(ext);
        std::fs::write(&path, &primary).unwrap();
        let mut f = FitsFile::open(&path).unwrap();
        let cards = super::super::read::hdu_cards(&mut f, &path, 1).unwrap().unwrap();
        assert!(plain_image(&mut f, &path, 1, &cards).unwrap().is_some());
        let hdu = f.hdu(1).unwrap();
        let want: Vec<f32> = hdu.read_rows(&mut f, 2, 7).unwrap();
        let got = read_frame_rows(&path, Some((2, 9))).unwrap();
        assert_eq!(bits(got.data.as_slice().unwrap()), bits(&want));
    }

    /// The AVX2 build of the conversion gives the baseline build's numbers and summary.
    #[test]
    fn the_conversion_is_the_same_in_every_vector_build() {
        let mut rng = Rng::seed_from_u64(12345);
        for bitpix in [16, -32] {
            for n in [0, 1, 15, 16, 17, 4095, 4096, 4097, 10_000] {
                let raw = pixels(bitpix, n, &mut rng);
                for (scale, zero) in [(1.0, 0.0), (1.0, 32768.0), (2.5, -17.25), (1.0, 0.5)] {
                    let (mut a, mut b) = (Vec::new(), Vec::new());
                    let (mut la, mut lb) = (SummaryLanes::new(), SummaryLanes::new());
                    convert(&raw, bitpix, scale, zero, &mut a, &mut la);
                    convert_portable(&raw, bitpix, scale, zero, &mut b, &mut lb);
                    let (sa, sb) = (la.finish(), lb.finish());
                    assert_eq!(bits(&a), bits(&b), "BITPIX {bitpix} n {n} scale {scale} zero {zero}");
                    assert_eq!(sa, sb);
                    let s = plain_summary(&b);
                    assert_eq!((sb.non_finite, sb.min, sb.max), (s.non_finite, s.min, s.max));
                }
            }
        }
    }

    /// A file cut inside its data (but not by a whole block, which the size check before
    /// allocating catches) is an error naming the file and the rows.
    #[test]
    fn a_file_cut_inside_its_data_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cut.fits");
        let mut rng = Rng::seed_from_u64(7);
        let mut b = fits_bytes(-32, 100, 100, &[], &pixels(-32, 100 * 100, &mut rng));
        b.truncate(2880 + 100 * 100 * 4 - 1000);
        std::fs::write(&path, b).unwrap();
        let e = read_frame(&path).unwrap_err().to_string();
        assert!(e.contains("cut.fits") && e.contains("truncated"), "{e}");
        let e = read_frame_rows(&path, Some((90, 100))).unwrap_err().to_string();
        assert!(e.contains("cut.fits") && e.contains("rows [90, 100)"), "{e}");
        // Rows before the cut read.
        assert_eq!(read_frame_rows(&path, Some((0, 50))).unwrap().shape(), (50, 100));
    }
}
