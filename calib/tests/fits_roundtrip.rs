//! FITS round trips through `write_frame` / `read_frame`, checked against the raw file
//! bytes and against cfitsio's own keyword reader.
mod common;

use std::path::Path;

use common::*;
use fitsio::FitsFile;
use ndarray::Array2;
use sofipol_calib::fits::{read_frame, read_header, write_frame, Bitpix, WriteOptions};
use sofipol_calib::{Error, Frame, Header, HeaderValue, HistoryRecord};

fn opts(bitpix: Bitpix, compress: bool) -> WriteOptions {
    WriteOptions {
        bitpix,
        compress,
        with_variance_and_mask: false,
    }
}

/// Header cards must come back identical (order, values, comments).
fn assert_same_header(back: &Header, sent: &Header) {
    assert_eq!(back.cards, sent.cards);
}

fn bits_equal(a: &Array2<f32>, b: &Array2<f32>) -> bool {
    a.shape() == b.shape() && a.iter().zip(b.iter()).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Pseudo-random f32 values spanning many magnitudes, signs and special values.
fn awkward_f32(ny: usize, nx: usize) -> Array2<f32> {
    let mut s: u64 = 0x9E37_79B9_7F4A_7C15;
    Array2::from_shape_fn((ny, nx), |(y, x)| {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        match (y * nx + x) % 97 {
            0 => f32::NAN,
            1 => -0.0,
            2 => f32::MIN_POSITIVE / 4.0, // subnormal
            3 => f32::MAX,
            _ => f32::from_bits((s >> 32) as u32 & 0x7F7F_FFFF) * if s & 1 == 0 { 1.0 } else { -1.0 },
        }
    })
}

#[test]
fn f32_round_trip_is_bit_exact() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f32.fits");
    let mut frame = sofi_frame(40, 50, 45.0);
    frame.data = awkward_f32(40, 50);
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    let back = read_frame(&path).unwrap();
    assert!(bits_equal(&back.data, &frame.data));
    assert_same_header(&back.header, &frame.header);
    assert_eq!(back.header.path, path);
    assert_eq!(back.history, frame.history);
    assert!(back.variance.is_none());
    assert_eq!(back.mask, Array2::<u8>::zeros((40, 50)));
    // Primary HDU image, BITPIX -32, no EXTNAME on the primary.
    assert_eq!(
        raw_card(&path, "BITPIX").unwrap(),
        format!("BITPIX  = {:>20} / number of bits per data pixel", -32)
    );
    assert!(raw_card(&path, "EXTNAME").is_none());
    // Row 0 is FITS row 1: check one pixel through cfitsio directly (1-based x, y).
    let mut f = FitsFile::open(&path).unwrap();
    let hdu = f.primary_hdu().unwrap();
    let row: Vec<f32> = hdu.read_row(&mut f, 0).unwrap();
    assert_eq!(row[7].to_bits(), frame.data[[0, 7]].to_bits());
}

#[test]
fn i16_round_trip_and_raw_cards() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("raw.fits");
    let mut frame = sofi_frame(32, 48, 0.0);
    // Full unsigned range plus values that must be rounded or clipped.
    frame.data[[0, 0]] = 0.0;
    frame.data[[0, 1]] = 65535.0;
    frame.data[[0, 2]] = 32767.0;
    frame.data[[0, 3]] = 32768.0;
    frame.data[[1, 0]] = -5.0;
    frame.data[[1, 1]] = 70000.0;
    frame.data[[1, 2]] = 10.5;
    frame.data[[1, 3]] = 10.49;
    frame.data[[1, 4]] = f32::NAN;
    write_frame(&path, &frame, &opts(Bitpix::I16, false)).unwrap();
    let back = read_frame(&path).unwrap();
    let mut expected = frame.data.clone();
    for (v, want) in [
        ((1, 0), 0.0),
        ((1, 1), 65535.0),
        ((1, 2), 11.0),
        ((1, 3), 10.0),
        ((1, 4), 0.0),
    ] {
        expected[v] = want;
    }
    assert_eq!(back.data, expected);
    assert_same_header(&back.header, &frame.header);
    // Independent check of the file layout: the raw header cards.
    assert!(raw_card(&path, "BITPIX")
        .unwrap()
        .starts_with(&format!("BITPIX  = {:>20}", 16)));
    assert!(raw_card(&path, "BZERO")
        .unwrap()
        .starts_with(&format!("BZERO   = {:>20}", 32768)));
    assert!(raw_card(&path, "BSCALE")
        .unwrap()
        .starts_with(&format!("BSCALE  = {:>20}", 1)));
    // 32 x 48 x 2 bytes of data in 2880-byte blocks after the header.
    let len = std::fs::metadata(&path).unwrap().len();
    assert_eq!(len % 2880, 0);
}

#[test]
fn rice_compressed_i16_is_compressed_and_exact() {
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("raw.fits");
    let fz = dir.path().join("raw.fits.fz");
    let frame = sofi_frame(256, 256, 45.0);
    write_frame(&plain, &frame, &opts(Bitpix::I16, false)).unwrap();
    write_frame(&fz, &frame, &opts(Bitpix::I16, true)).unwrap();
    let back = read_frame(&fz).unwrap();
    assert_eq!(back.data, frame.data);
    assert_same_header(&back.header, &frame.header);
    assert_eq!(back.history, frame.history);
    assert_eq!(
        raw_card(&fz, "ZIMAGE").unwrap(),
        format!("ZIMAGE  = {:>20} / extension contains compressed image", "T")
    );
    assert!(raw_card(&fz, "ZCMPTYPE").unwrap().contains("'RICE_1"));
    assert!(raw_card(&fz, "ZBITPIX")
        .unwrap()
        .starts_with(&format!("ZBITPIX = {:>20}", 16)));
    assert!(raw_card(&fz, "BZERO")
        .unwrap()
        .starts_with(&format!("BZERO   = {:>20}", 32768)));
    let (a, b) = (
        std::fs::metadata(&plain).unwrap().len(),
        std::fs::metadata(&fz).unwrap().len(),
    );
    assert!(b * 2 < a, "compressed {b} bytes vs plain {a} bytes");
    // The image is in HDU 1, the primary is empty.
    let mut f = FitsFile::open(&fz).unwrap();
    assert_eq!(f.num_hdus().unwrap(), 2);
    let h1 = f.hdu(1).unwrap();
    assert!(matches!(h1.info, fitsio::hdu::HduInfo::ImageInfo { ref shape, .. } if shape == &[256, 256]));
}

#[test]
fn compressed_f32_is_lossless_gzip() {
    // Rice on floats would need cfitsio's lossy quantization: write_frame uses GZIP
    // without quantization instead, so floats come back bit for bit.
    let dir = tempfile::tempdir().unwrap();
    let fz = dir.path().join("red.fits.fz");
    let mut frame = sofi_frame(64, 80, 45.0);
    frame.data = awkward_f32(64, 80);
    write_frame(&fz, &frame, &opts(Bitpix::F32, true)).unwrap();
    let back = read_frame(&fz).unwrap();
    assert!(bits_equal(&back.data, &frame.data));
    assert!(raw_card(&fz, "ZCMPTYPE").unwrap().contains("'GZIP_1"));
    assert!(raw_card(&fz, "ZQUANTIZ").unwrap().contains("'NONE"));
    // A smooth float image still shrinks.
    let smooth = sofi_frame(256, 256, 0.0);
    let (p, z) = (dir.path().join("s.fits"), dir.path().join("s.fits.fz"));
    write_frame(&p, &smooth, &opts(Bitpix::F32, false)).unwrap();
    write_frame(&z, &smooth, &opts(Bitpix::F32, true)).unwrap();
    assert!(std::fs::metadata(&z).unwrap().len() < std::fs::metadata(&p).unwrap().len() / 2);
    assert_eq!(read_frame(&z).unwrap().data, smooth.data);
}

#[test]
fn hierarch_keys_and_values_with_spaces() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("h.fits");
    let mut frame = sofi_frame(8, 8, 45.0);
    let h = &mut frame.header;
    h.set("ESO OBS NAME", "HK Tau pol  0/45 run 2");
    h.set_with_comment("ESO INS OPTI9 ID", "  leading blanks", "kept");
    h.set("LONGNAMEKEY", 7i64); // 11 characters: HIERARCH without spaces
    h.set("ESO DET READ CLOCK", "Double Correlated Read 'DCR'");
    h.set("ESO QC FLAG", true);
    h.set("ESO QC OTHER", false);
    // Trailing blanks of FITS strings are not significant: this value has none.
    let long = "a long string value that does not fit on a single card, ".repeat(4) + "it's the end";
    h.set_with_comment("ESO OBS PI-COI NAME", long.as_str(), "continued");
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    let back = read_header(&path).unwrap();
    assert_same_header(&back, &frame.header);
    assert_eq!(back.get_str("ESO OBS NAME").unwrap(), "HK Tau pol  0/45 run 2");
    assert_eq!(back.get("ESO QC FLAG"), Some(&HeaderValue::Bool(true)));
    assert_eq!(back.get_str("ESO OBS PI-COI NAME").unwrap(), long);
    // What is in the file, and what cfitsio makes of it.
    assert!(raw_card(&path, "HIERARCH ESO ADA POSANG = 45.0 / rotator position angle [deg]").is_some());
    assert!(raw_card(&path, "HIERARCH LONGNAMEKEY = 7").is_some());
    let mut f = FitsFile::open(&path).unwrap();
    let hdu = f.primary_hdu().unwrap();
    assert_eq!(hdu.read_key::<f64>(&mut f, "ESO ADA POSANG").unwrap(), 45.0);
    assert_eq!(
        hdu.read_key::<String>(&mut f, "HIERARCH ESO OBS NAME").unwrap(),
        "HK Tau pol  0/45 run 2"
    );
    assert_eq!(hdu.read_key::<i64>(&mut f, "ESO DET NDIT").unwrap(), 6);
    assert_eq!(
        hdu.read_key::<String>(&mut f, "ESO DET READ CLOCK").unwrap(),
        "Double Correlated Read 'DCR'"
    );
}

#[test]
fn f64_keys_round_trip_bit_exactly() {
    // write_frame formats floats itself with the shortest digits that read back exactly
    // (cfitsio's own writer keeps 15 significant digits only).
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f64.fits");
    let mut frame = Frame::new(Array2::zeros((4, 4)), Header::new(""));
    let mut s: u64 = 12345;
    let mut values = vec![
        0.1,
        1.0 / 3.0,
        51240.09112345679,
        -157.1,
        1e-300,
        6.02214076e23,
        f64::MAX,
        f64::MIN_POSITIVE,
        -0.0,
    ];
    for _ in 0..60 {
        s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let x = f64::from_bits(s >> 1);
        if x.is_finite() {
            values.push(if s & 1 == 0 { x } else { -x });
        }
    }
    for (i, v) in values.iter().enumerate() {
        frame.header.set(&format!("ESO TEST VAL{i}"), *v);
    }
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    let back = read_header(&path).unwrap();
    let mut f = FitsFile::open(&path).unwrap();
    let hdu = f.primary_hdu().unwrap();
    for (i, v) in values.iter().enumerate() {
        let key = format!("ESO TEST VAL{i}");
        assert_eq!(back.get_f64(&key).unwrap().to_bits(), v.to_bits(), "{key}");
        // cfitsio's parser (strtod) agrees exactly.
        let c: f64 = hdu.read_key(&mut f, &key).unwrap();
        assert_eq!(c.to_bits(), v.to_bits(), "{key} via cfitsio");
    }
    // Non-finite values cannot be written: an error naming file and keyword.
    frame.header.set("ESO BAD", f64::INFINITY);
    let e = write_frame(&path, &frame, &WriteOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("f64.fits") && e.contains("ESO BAD") && e.contains("inf"),
        "{e}"
    );
}

#[test]
fn history_cards_come_back_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("hist.fits");
    let mut frame = sofi_frame(8, 8, 0.0);
    let long = format!(
        "params: {}",
        (0..40)
            .map(|i| format!("p{i}={}", i as f64 * 0.5))
            .collect::<Vec<_>>()
            .join(" ")
    );
    frame = frame
        .with_history("sky", long.clone())
        .with_history("stack", "5 frames, median");
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    let back = read_frame(&path).unwrap();
    assert_eq!(back.history, frame.history);
    // One card per record, plus continuation cards for the long one, each <= 70 chars.
    let text = raw_text(&path);
    let cards: Vec<&str> = (0..text.len() / 80)
        .map(|i| &text[i * 80..i * 80 + 80])
        .filter(|c| c.starts_with("HISTORY "))
        .collect();
    assert!(cards.len() > 4);
    assert!(cards.iter().all(|c| c[8..].trim_end().len() <= 70));
    assert!(cards[0].starts_with("HISTORY sofipol sim: scene=binary"));
    assert!(!back.header.contains("HISTORY"));
}

#[test]
fn foreign_history_and_cfitsio_written_keys_are_read() {
    // A file written by cfitsio itself (independent of our card formatter).
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfitsio.fits");
    {
        let desc = fitsio::images::ImageDescription {
            data_type: fitsio::images::ImageType::Short,
            dimensions: &[3, 4],
        };
        let mut f = FitsFile::create(&path).with_custom_primary(&desc).open().unwrap();
        let hdu = f.primary_hdu().unwrap();
        hdu.write_key(&mut f, "INSTRUME", ("SOFI", "instrument")).unwrap();
        hdu.write_key(&mut f, "ESO ADA POSANG", 45.0f64).unwrap();
        hdu.write_key(&mut f, "ESO DET NDIT", 6i64).unwrap();
        hdu.write_key(&mut f, "BZERO", 100.0f64).unwrap();
        hdu.write_key(&mut f, "BSCALE", 0.5f64).unwrap();
        hdu.write_image(&mut f, &(0..12).collect::<Vec<i16>>()).unwrap();
    }
    let back = read_frame(&path).unwrap();
    assert_eq!(back.header.get_str("INSTRUME").unwrap(), "SOFI");
    assert_eq!(back.header.cards[0].comment.as_deref(), Some("instrument"));
    assert_eq!(back.header.get_f64("ESO ADA POSANG").unwrap(), 45.0);
    assert_eq!(back.header.get_i64("ESO DET NDIT").unwrap(), 6);
    assert!(!back.header.contains("BZERO") && !back.header.contains("EXTNAME"));
    // BITPIX 16 scaled by BSCALE / BZERO when read as f32; [y, x] with x fastest.
    assert_eq!(back.shape(), (3, 4));
    assert_eq!(back.data[[0, 0]], 100.0);
    assert_eq!(back.data[[0, 1]], 100.5);
    assert_eq!(back.data[[2, 3]], 105.5);
}

#[test]
fn variance_and_mask_extensions() {
    let dir = tempfile::tempdir().unwrap();
    for (compress, bitpix) in [(false, Bitpix::F32), (true, Bitpix::F32), (true, Bitpix::I16)] {
        let path = dir.path().join(format!("vm-{compress}-{bitpix:?}.fits"));
        let mut frame = sofi_frame(20, 30, 45.0);
        frame.variance = Some(awkward_f32(20, 30).mapv(|v| v.abs()));
        frame.mask[[3, 4]] = 1 | 8;
        frame.mask[[19, 29]] = 255;
        let o = WriteOptions {
            bitpix,
            compress,
            with_variance_and_mask: true,
        };
        write_frame(&path, &frame, &o).unwrap();
        let back = read_frame(&path).unwrap();
        assert_eq!(back.data, frame.data);
        assert!(bits_equal(
            back.variance.as_ref().unwrap(),
            frame.variance.as_ref().unwrap()
        ));
        assert_eq!(back.mask, frame.mask);
        assert_same_header(&back.header, &frame.header);
    }
    // Without the option, neither is written.
    let path = dir.path().join("none.fits");
    let mut frame = sofi_frame(5, 5, 0.0);
    frame.variance = Some(Array2::ones((5, 5)));
    frame.mask[[0, 0]] = 1;
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    let back = read_frame(&path).unwrap();
    assert!(back.variance.is_none());
    assert_eq!(back.mask[[0, 0]], 0);
    // Shapes must agree.
    frame.mask = Array2::zeros((4, 5));
    let o = WriteOptions {
        with_variance_and_mask: true,
        ..Default::default()
    };
    let e = write_frame(&path, &frame, &o).unwrap_err().to_string();
    assert!(e.contains("none.fits") && e.contains("MASK"), "{e}");
}

#[test]
fn gzipped_fits_is_read_transparently() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("raw.fits");
    let frame = sofi_frame(16, 16, 45.0);
    write_frame(&path, &frame, &opts(Bitpix::I16, false)).unwrap();
    let gz = dir.path().join("raw.fits.gz");
    let mut enc = flate2::write::GzEncoder::new(std::fs::File::create(&gz).unwrap(), flate2::Compression::default());
    enc.write_all(&std::fs::read(&path).unwrap()).unwrap();
    enc.finish().unwrap();
    let back = read_frame(&gz).unwrap();
    assert_eq!(back.data, frame.data);
    assert_same_header(&back.header, &frame.header);
    // Writing .gz is refused (cfitsio would compress only when closing, out of our sight).
    let e = write_frame(&gz, &frame, &WriteOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("raw.fits.gz"), "{e}");
}

#[test]
fn structural_keywords_in_the_header_are_not_written() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.fits");
    let mut frame = sofi_frame(4, 6, 0.0);
    frame.header.set("BITPIX", 8i64);
    frame.header.set("NAXIS1", 99i64);
    frame.header.set("BZERO", 5.0);
    frame.header.set("EXTNAME", "SCI");
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    let back = read_frame(&path).unwrap();
    assert_eq!(back.shape(), (4, 6));
    assert_eq!(back.data, frame.data);
    assert!(!back.header.contains("BITPIX") && !back.header.contains("NAXIS1") && !back.header.contains("BZERO"));
    assert_eq!(raw_text(&path).matches("BITPIX  =").count(), 1);
}

#[test]
fn writing_is_atomic() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("good.fits");
    let frame = sofi_frame(10, 10, 0.0);
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    let before = std::fs::read(&path).unwrap();
    // Overwriting works (cfitsio alone refuses to create over an existing file)...
    let mut other = sofi_frame(10, 10, 45.0);
    write_frame(&path, &other, &WriteOptions::default()).unwrap();
    assert_eq!(read_header(&path).unwrap().get_f64("ESO ADA POSANG").unwrap(), 45.0);
    write_frame(&path, &frame, &WriteOptions::default()).unwrap();
    assert_eq!(std::fs::read(&path).unwrap(), before);
    // ...and a failed write leaves the old file intact and no temporary file behind.
    other.header.set("ESO BAD VALUE", f64::NAN);
    assert!(write_frame(&path, &other, &WriteOptions::default()).is_err());
    other.header.set("ESO BAD VALUE", 1.0);
    other.mask = Array2::zeros((3, 3));
    let o = WriteOptions {
        with_variance_and_mask: true,
        ..Default::default()
    };
    assert!(write_frame(&path, &other, &o).is_err());
    assert_eq!(std::fs::read(&path).unwrap(), before);
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("good.fits")]);
    // A relative path in the current directory works too (no parent component).
    let e = write_frame(Path::new("no/such/dir/x.fits"), &frame, &WriteOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("no/such/dir"), "{e}");
}

#[test]
fn parallel_reads_and_writes() {
    use rayon::prelude::*;
    let dir = tempfile::tempdir().unwrap();
    let paths: Vec<_> = (0..16).map(|i| dir.path().join(format!("p{i}.fits"))).collect();
    paths.par_iter().enumerate().for_each(|(i, p)| {
        let mut f = sofi_frame(64, 64, i as f64);
        f.data.mapv_inplace(|v| v + i as f32);
        write_frame(
            p,
            &f,
            &opts(if i % 2 == 0 { Bitpix::F32 } else { Bitpix::I16 }, i % 3 == 0),
        )
        .unwrap();
    });
    let ok = paths.par_iter().enumerate().all(|(i, p)| {
        let f = read_frame(p).unwrap();
        f.header.get_f64("ESO ADA POSANG").unwrap() == i as f64
            && f.data[[0, 0]] == smooth_image(64, 64)[[0, 0]] + i as f32
    });
    assert!(ok);
}

// ---------------------------------------------------------------------------------------
// Errors: clean, naming the file.

fn err_of(path: &Path) -> Error {
    read_frame(path).map(|_| ()).unwrap_err()
}

#[test]
fn missing_file_is_a_clean_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("absent_frame.fits");
    let e = err_of(&path);
    assert!(
        matches!(&e, Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound),
        "{e:?}"
    );
    assert!(e.to_string().contains("absent_frame.fits"), "{e}");
    assert!(read_header(&path)
        .unwrap_err()
        .to_string()
        .contains("absent_frame.fits"));
    // A directory is not a file either.
    assert!(err_of(dir.path()).to_string().contains("not a regular file"));
}

#[test]
fn truncated_file_is_a_clean_error() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.fits");
    let frame = sofi_frame(64, 64, 0.0);
    write_frame(&good, &frame, &WriteOptions::default()).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    for (name, len) in [
        ("cut_data.fits", bytes.len() / 2),
        ("cut_header.fits", 1000),
        ("cut_2880.fits", 2880),
        ("empty.fits", 0),
    ] {
        let p = dir.path().join(name);
        std::fs::write(&p, &bytes[..len]).unwrap();
        let e = err_of(&p).to_string();
        assert!(e.contains(name), "{e}");
    }
    // Truncated compressed file.
    let fz = dir.path().join("good.fits.fz");
    write_frame(&fz, &frame, &opts(Bitpix::I16, true)).unwrap();
    let bytes = std::fs::read(&fz).unwrap();
    let p = dir.path().join("cut.fits.fz");
    std::fs::write(&p, &bytes[..bytes.len() - 3000]).unwrap();
    let e = err_of(&p).to_string();
    assert!(e.contains("cut.fits.fz"), "{e}");
}

#[test]
fn text_file_is_a_clean_error() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("notes.txt");
    std::fs::write(
        &p,
        "This is not a FITS file.\nJust some notes about HK Tau.\n".repeat(100),
    )
    .unwrap();
    let e = err_of(&p);
    assert!(matches!(e, Error::Fits { .. }), "{e:?}");
    assert!(e.to_string().contains("notes.txt"), "{e}");
    assert!(read_header(&p).unwrap_err().to_string().contains("notes.txt"));
}

#[test]
fn non_2d_images_are_rejected_with_naxis_values() {
    let dir = tempfile::tempdir().unwrap();
    let cube = dir.path().join("cube.fits");
    {
        let desc = fitsio::images::ImageDescription {
            data_type: fitsio::images::ImageType::Float,
            dimensions: &[2, 4, 5],
        };
        let mut f = FitsFile::create(&cube).with_custom_primary(&desc).open().unwrap();
        let hdu = f.primary_hdu().unwrap();
        hdu.write_image(&mut f, &[1.0f32; 40]).unwrap();
    }
    let e = err_of(&cube);
    assert!(matches!(e, Error::BadImage { .. }), "{e:?}");
    let msg = e.to_string();
    assert!(
        msg.contains("cube.fits")
            && msg.contains("NAXIS = 3")
            && msg.contains("NAXIS1 = 5")
            && msg.contains("NAXIS3 = 2"),
        "{msg}"
    );
    assert!(read_header(&cube).unwrap_err().to_string().contains("NAXIS = 3"));

    let line = dir.path().join("line.fits");
    {
        let desc = fitsio::images::ImageDescription {
            data_type: fitsio::images::ImageType::Float,
            dimensions: &[7],
        };
        let mut f = FitsFile::create(&line).with_custom_primary(&desc).open().unwrap();
        let hdu = f.primary_hdu().unwrap();
        hdu.write_image(&mut f, &[0.0f32; 7]).unwrap();
    }
    let msg = err_of(&line).to_string();
    assert!(
        msg.contains("line.fits") && msg.contains("NAXIS = 1 (NAXIS1 = 7)"),
        "{msg}"
    );

    // Only an empty primary: no image at all.
    let empty = dir.path().join("noimage.fits");
    drop(FitsFile::create(&empty).open().unwrap());
    let msg = err_of(&empty).to_string();
    assert!(msg.contains("noimage.fits") && msg.contains("NAXIS = 0"), "{msg}");

    // A 2-D image with a zero axis.
    let zero = dir.path().join("zero.fits");
    {
        let desc = fitsio::images::ImageDescription {
            data_type: fitsio::images::ImageType::Float,
            dimensions: &[0, 5],
        };
        drop(FitsFile::create(&zero).with_custom_primary(&desc).open().unwrap());
    }
    let msg = err_of(&zero).to_string();
    assert!(
        msg.contains("zero.fits") && msg.contains("empty image") && msg.contains("NAXIS2 = 0"),
        "{msg}"
    );

    // Writing an empty frame is refused too.
    let e = write_frame(
        &dir.path().join("w.fits"),
        &Frame::new(Array2::zeros((0, 3)), Header::new("")),
        &WriteOptions::default(),
    );
    assert!(e.unwrap_err().to_string().contains("w.fits"));
}

#[test]
fn image_in_first_extension_is_found() {
    // Uncompressed multi-extension layout: empty primary, image in HDU 1.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("mef.fits");
    {
        let mut f = FitsFile::create(&p).open().unwrap();
        let desc = fitsio::images::ImageDescription {
            data_type: fitsio::images::ImageType::Float,
            dimensions: &[2, 3],
        };
        let hdu = f.create_image("CHIP1", &desc).unwrap();
        hdu.write_key(&mut f, "ESO ADA POSANG", 90.0f64).unwrap();
        hdu.write_image(&mut f, &[1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]).unwrap();
    }
    let back = read_frame(&p).unwrap();
    assert_eq!(back.shape(), (2, 3));
    assert_eq!(back.data[[1, 2]], 6.0);
    assert_eq!(back.header.get_f64("ESO ADA POSANG").unwrap(), 90.0);
    assert_eq!(back.history, Vec::<HistoryRecord>::new());
}

#[test]
fn unsupported_file_names_are_clean_errors() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("frame[1].fits");
    std::fs::write(&p, b"x").unwrap();
    let e = err_of(&p).to_string();
    assert!(
        e.contains("frame[1].fits") && e.contains("extended file-name syntax"),
        "{e}"
    );
    // Writing to such a name works: the temporary name is plain, rename does the rest.
    let frame = sofi_frame(4, 4, 0.0);
    let w = dir.path().join("odd (copy).fits");
    write_frame(&w, &frame, &WriteOptions::default()).unwrap();
    assert!(w.is_file());
}
