//! Unit tests of the card parser and formatter, file names and pixel conversion.
use std::path::Path;

use super::cards::*;
use super::cfitsio::cfitsio_name;
use super::write::to_u16;
use super::{read_frame, read_header, HISTORY_CHUNK};
use crate::frame::HistoryRecord;
use crate::header::{Card, HeaderValue};

fn card(key: &str, value: impl Into<HeaderValue>, comment: Option<&str>) -> Card {
    Card {
        key: key.into(),
        value: value.into(),
        comment: comment.map(String::from),
    }
}

fn roundtrip(c: &Card) -> Card {
    let lines = format_card(c, Path::new("t.fits")).unwrap();
    for l in &lines {
        assert!(l.len() <= 80, "{l:?}");
    }
    let (h, _) = parse_cards(&lines, Path::new("t.fits"));
    assert_eq!(h.cards.len(), 1, "{lines:?}");
    h.cards[0].clone()
}

#[test]
fn cards_round_trip() {
    for c in [
        card("OBJECT", "HK Tau", Some("target")),
        card("ESO ADA POSANG", 45.0, Some("deg")),
        card("ESO OBS TARG NAME", "it's a 'quoted' name", None),
        card("NDIT", 6i64, None),
        card("ESO DET NDIT", -7i64, Some("x")),
        card("FLAG", true, None),
        card("ESO SEQ FLAG", false, None),
        card("EMPTY", "", None),
        card("LEADING", "  padded", None),
        card("TINY", 1.2345678901234567e-300, None),
        card("HUGE", -9.87654321e250, None),
        card("THIRD", 1.0 / 3.0, None),
        card("MJD-OBS", 51240.09112345679, None),
        card("DATE-OBS", "1999-03-03T02:11:05.123", None),
    ] {
        assert_eq!(roundtrip(&c), c, "{c:?}");
    }
}

#[test]
fn long_strings_use_continue() {
    let long: String = (0..300)
        .map(|i| {
            if i % 7 == 0 {
                '\''
            } else {
                (b'a' + (i % 26) as u8) as char
            }
        })
        .collect();
    for key in ["LONGSTR", "ESO SOME VERY LONG HIERARCH KEYWORD NAME"] {
        let c = card(key, long.as_str(), Some("end"));
        let lines = format_card(&c, Path::new("t.fits")).unwrap();
        assert!(lines.len() > 3);
        assert!(lines[1].starts_with("CONTINUE  '"));
        assert_eq!(roundtrip(&c), c);
    }
}

#[test]
fn parses_foreign_cards() {
    let cards: Vec<String> = [
        "SIMPLE  =                    T / conforms",
        "BITPIX  =                   16",
        "NAXIS1  =                 1024",
        "HIERARCH ESO DET DIT         =    10.0000000 / Integration Time",
        "HIERARCH ESO INS OPTI3 ID = 'WOLLASTON' / OPTIi ID",
        "EXPTIME =              1.0D+01 / Fortran exponent",
        "BIGINT  = 123456789012345678901234",
        "UNDEF   =",
        "CPLX    = (1.0, 2.0)",
        "COMMENT this is a comment = with equals",
        "HISTORY some foreign step",
        "        blank keyword card",
        "ZTILE1  =                 1024",
        "ZENITH  =                 12.5",
        "NEGFRAC =                  -.5",
        "PLUSEXP =             +1.0E+01",
        "TRAIL   =                   5.",
        "NOTNUM  =                  NaN",
        "DUP     =                    1",
        "DUP     =                    2",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let (h, hist) = parse_cards(&cards, Path::new("x.fits"));
    let keys: Vec<&str> = h.cards.iter().map(|c| c.key.as_str()).collect();
    assert_eq!(
        keys,
        [
            "ESO DET DIT",
            "ESO INS OPTI3 ID",
            "EXPTIME",
            "BIGINT",
            "CPLX",
            "ZENITH",
            "NEGFRAC",
            "PLUSEXP",
            "TRAIL",
            "NOTNUM",
            "DUP"
        ]
    );
    assert_eq!(h.get("NEGFRAC"), Some(&HeaderValue::Float(-0.5)));
    assert_eq!(h.get("PLUSEXP"), Some(&HeaderValue::Float(10.0)));
    assert_eq!(h.get("TRAIL"), Some(&HeaderValue::Float(5.0)));
    assert_eq!(h.get("NOTNUM"), Some(&HeaderValue::Str("NaN".into())));
    assert_eq!(h.get("DUP"), Some(&HeaderValue::Int(1)));
    assert_eq!(h.get("ESO DET DIT"), Some(&HeaderValue::Float(10.0)));
    assert_eq!(h.cards[0].comment.as_deref(), Some("Integration Time"));
    assert_eq!(h.get_str("ESO INS OPTI3 ID").unwrap(), "WOLLASTON");
    assert_eq!(h.get("EXPTIME"), Some(&HeaderValue::Float(10.0)));
    assert_eq!(h.get("BIGINT"), Some(&HeaderValue::Float(1.2345678901234568e23)));
    assert_eq!(hist, vec![HistoryRecord::new("file", "some foreign step")]);
}

#[test]
fn history_split_and_join() {
    let recs = vec![
        HistoryRecord::new("sky", "x".repeat(69) + "  two spaces then more" + &"y".repeat(150)),
        HistoryRecord::new("badpix", ""),
        HistoryRecord::new("flat", "short: with colon"),
    ];
    let cards = format_history(&recs);
    assert!(cards.iter().all(|c| c.len() <= 8 + HISTORY_CHUNK), "{cards:#?}");
    // cfitsio trims trailing blanks of every card.
    let trimmed: Vec<String> = cards.iter().map(|c| c.trim_end().to_string()).collect();
    let (_, back) = parse_cards(&trimmed, Path::new("x.fits"));
    assert_eq!(back[0], recs[0]);
    assert_eq!(back[1], recs[1]);
    assert_eq!(back[2], recs[2]);
}

#[test]
fn bad_keywords_are_errors() {
    let p = Path::new("out.fits");
    let e = format_card(&card("ESO X", f64::NAN, None), p).unwrap_err().to_string();
    assert!(e.contains("out.fits") && e.contains("ESO X"), "{e}");
    let e = format_card(&card("OBJECT", "Ωmega", None), p).unwrap_err().to_string();
    assert!(e.contains("OBJECT") && e.contains("ASCII"), "{e}");
    let long_key = "ESO ".to_string() + &"K".repeat(80);
    assert!(format_card(&card(&long_key, 1i64, None), p).is_err());
}

#[test]
fn cfitsio_names() {
    assert!(cfitsio_name(Path::new("a[1].fits")).is_err());
    assert!(cfitsio_name(Path::new("x.fits+1")).is_err());
    assert_eq!(cfitsio_name(Path::new("-x.fits")).unwrap(), "./-x.fits");
    assert_eq!(cfitsio_name(Path::new("/d/x.fits")).unwrap(), "/d/x.fits");
}

#[test]
fn u16_conversion() {
    assert_eq!(to_u16(-3.0), 0);
    assert_eq!(to_u16(1.5), 2);
    assert_eq!(to_u16(2.49), 2);
    assert_eq!(to_u16(70000.0), 65535);
    assert_eq!(to_u16(f32::NAN), 0);
}

#[test]
fn a_corrupt_naxis_larger_than_the_file_is_refused_before_allocating() {
    // Regression: NAXIS1 = NAXIS2 = 100000 in a 4 MB file asked for a 40 GB allocation
    // and aborted the whole night.
    let good = std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../testdata/fits/sofi_pol_64x64_i16.fits"
    ));
    let mut b = std::fs::read(good).unwrap();
    for key in [&b"NAXIS1  ="[..], &b"NAXIS2  ="[..]] {
        let at = (0..b.len() / 80)
            .map(|i| i * 80)
            .find(|&i| b[i..].starts_with(key))
            .unwrap();
        let card = format!("{:<8}= {:>20}", std::str::from_utf8(&key[..8]).unwrap().trim(), 100000);
        b[at..at + 30].copy_from_slice(card.as_bytes());
    }
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("corrupt.fits");
    std::fs::write(&p, &b).unwrap();
    let e = read_frame(&p).unwrap_err().to_string();
    assert!(e.contains("corrupt header") && e.contains("100000 x 100000"), "{e}");
    // The header alone still reads (classification names the file, the reduction drops it).
    assert_eq!(read_header(&p).unwrap().get_str("INSTRUME").unwrap(), "SOFI");
    // The same through gzip: the compressed size bounds the output too.
    let gz = d.path().join("corrupt.fits.gz");
    let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    std::io::Write::write_all(&mut enc, &b).unwrap();
    std::fs::write(&gz, enc.finish().unwrap()).unwrap();
    let e = read_frame(&gz).unwrap_err().to_string();
    assert!(e.contains("corrupt header"), "{e}");
    // Valid files, plain and compressed, still read.
    assert_eq!(read_frame(good).unwrap().shape(), (64, 64));
    let fz = std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../testdata/fits/sofi_pol_64x64_i16.fits.fz"
    ));
    assert_eq!(read_frame(fz).unwrap().shape(), (64, 64));
}

/// `read_frame_rows` gives the frame `read_frame(..).crop_rows(..)` gives: 16-bit, tile
/// compressed, and float with UNCERT and MASK extensions; too-short images stay whole.
#[test]
fn read_frame_rows_equals_read_then_crop() {
    use super::{read_frame, read_frame_rows, write_frame};
    let dir = tempfile::tempdir().unwrap();
    let base = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../testdata/fits"));
    let mut f32_frame = read_frame(&base.join("sofi_pol_64x64_i16.fits")).unwrap();
    f32_frame
        .data
        .iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v += i as f32 * 0.001);
    f32_frame.variance = Some(f32_frame.data.mapv(|v| v.abs() + 1.5));
    f32_frame
        .mask
        .iter_mut()
        .enumerate()
        .for_each(|(i, m)| *m = (i % 7 == 0) as u8);
    let written = dir.path().join("f.fits");
    write_frame(&written, &f32_frame, &Default::default()).unwrap();
    for path in [
        base.join("sofi_pol_64x64_i16.fits"),
        base.join("sofi_pol_64x64_i16.fits.fz"),
        written,
    ] {
        let full = read_frame(&path).unwrap();
        let want = full.crop_rows(11, 40);
        let got = read_frame_rows(&path, Some((11, 40))).unwrap();
        assert_eq!(got.shape(), (29, 64), "{}", path.display());
        let bits = |a: &ndarray::Array2<f32>| a.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got.data), bits(&want.data), "{}", path.display());
        assert_eq!(got.mask, want.mask);
        assert_eq!(got.variance.as_ref().map(bits), want.variance.as_ref().map(bits));
        assert_eq!(
            got.history.last().map(|h| &h.detail),
            want.history.last().map(|h| &h.detail)
        );
        // Rows beyond the image: read whole, uncropped.
        assert_eq!(read_frame_rows(&path, Some((11, 65))).unwrap().shape(), (64, 64));
    }
}

/// `raw_value` skips cards by their name field: the same answers as parsing every card,
/// for standard, HIERARCH (a HIERARCH card may define a short key), lower-case, non-ASCII,
/// blank-padded and tab-padded names, commentary cards and short cards.
#[test]
fn raw_value_finds_what_parsing_every_card_finds() {
    use super::keys::raw_value;
    let cards: Vec<String> = [
        "SIMPLE  =                    T",
        "COMMENT NAXIS = 3",
        "HISTORY NAXIS = 4",
        "naxis   =                    2 / lower case",
        "NAXIS1  =                   64",
        "NAXIS\t  =                    5 / tab in the name field",
        "HIERARCH NAXIS2 = 99",
        "NAXIS2  =                   64",
        "BZ\u{e9}RO   =                    7",
        "BZERO   =                32768",
        "BSCALE  = 'text'",
        "BSCALE  =                  1.0",
        "EXTNAME = 'MASK    '",
        "ZIMAGE",
        "",
        "CONTINUE  'x'",
        "HIERARCH ESO ADA POSANG = 45.0",
        "HIERARCH  naxis3\t = 7 / lower case, blanks and a tab around the key",
        "hierarch eso det dit = 1.5",
        "HIERARCH \u{e9}SO X = 1",
        "HIERARCH    = 5",
        "HIERARCH NAXIS4",
        "HIERARCH=6",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let every = |key: &str| {
        cards.iter().find_map(|c| match parse_card(c) {
            Parsed::Key { key: k, value, .. } if k == key => Some(value),
            _ => None,
        })
    };
    for key in [
        "SIMPLE",
        "NAXIS",
        "NAXIS1",
        "NAXIS2",
        "NAXIS3",
        "BZERO",
        "BZ?RO",
        "BSCALE",
        "EXTNAME",
        "ZIMAGE",
        "ESO ADA POSANG",
        "NAXIS3",
        "NAXIS4",
        "ESO DET DIT",
        "?SO X",
        "HIERARCH",
        "COMMENT",
        "HISTORY",
        "CONTINUE",
        "",
    ] {
        assert_eq!(raw_value(&cards, key), every(key), "{key}");
    }
    // The cases that matter here: the lower-case and tab-padded names, and HIERARCH.
    assert_eq!(raw_value(&cards, "NAXIS"), Some(HeaderValue::Int(2)));
    assert_eq!(raw_value(&cards, "NAXIS2"), Some(HeaderValue::Int(99)));
    assert_eq!(raw_value(&cards, "NAXIS3"), Some(HeaderValue::Int(7)));
    assert_eq!(raw_value(&cards, "ESO DET DIT"), Some(HeaderValue::Float(1.5)));
    assert_eq!(raw_value(&cards, "?SO X"), Some(HeaderValue::Int(1)));
    assert_eq!(raw_value(&cards, "HIERARCH"), Some(HeaderValue::Int(5)));
}

/// `write_images`: the primary and every named extension come back with their pixels,
/// cards (HIERARCH included) and HISTORY; `read_frame` finds VARIANCE and MASK among other
/// extensions.
#[test]
fn write_images_writes_every_hdu_with_its_cards() {
    use super::{write_images, ImageHdu, ImagePixels};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("product.fits");
    let data = ndarray::Array2::from_shape_fn((5, 7), |(y, x)| (10 * y + x) as f32 - 3.5);
    let var = data.mapv(|v| v * v + 1.0);
    let mask = ndarray::Array2::from_shape_fn((5, 7), |(y, x)| u8::from(x == y));
    let other = ndarray::Array2::from_shape_fn((5, 7), |(y, x)| if x == 2 { f32::NAN } else { y as f32 });
    let mut h0 = crate::Header::new("");
    h0.set_with_comment("ESO PRO CATG", "SOFIPOL_TEST", "product category");
    h0.set("BUNIT", "adu");
    let history = [HistoryRecord::new(
        "combine",
        format!(
            "{}end",
            "a record long enough to need more than one HISTORY card: ".repeat(3)
        ),
    )];
    let mut hv = crate::Header::new("");
    hv.set("BUNIT", "adu2");
    let empty = crate::Header::new("");
    write_images(
        &path,
        &[
            ImageHdu {
                extname: "",
                header: &h0,
                history: &history,
                pixels: ImagePixels::F32(&data),
            },
            ImageHdu {
                extname: "OTHER",
                header: &empty,
                history: &[],
                pixels: ImagePixels::F32(&other),
            },
            ImageHdu {
                extname: "VARIANCE",
                header: &hv,
                history: &[],
                pixels: ImagePixels::F32(&var),
            },
            ImageHdu {
                extname: "MASK",
                header: &empty,
                history: &[],
                pixels: ImagePixels::U8(&mask),
            },
        ],
    )
    .unwrap();
    let back = read_frame(&path).unwrap();
    assert_eq!(back.data, data);
    assert_eq!(back.variance.as_ref(), Some(&var));
    assert_eq!(back.mask, mask);
    assert_eq!(back.header.get_str("ESO PRO CATG").unwrap(), "SOFIPOL_TEST");
    assert_eq!(back.history, history);
    // The extension by name, through cfitsio: its pixels (NaN kept) and its own cards.
    let mut f = fitsio::FitsFile::open(&path).unwrap();
    let hdu = f.hdu("OTHER").unwrap();
    let v: Vec<f32> = hdu.read_image(&mut f).unwrap();
    for (a, b) in v.iter().zip(other.iter()) {
        assert!(a == b || (a.is_nan() && b.is_nan()), "{a} vs {b}");
    }
    let hdu = f.hdu("VARIANCE").unwrap();
    let unit: String = hdu.read_key(&mut f, "BUNIT").unwrap();
    assert_eq!(unit, "adu2");
    // Nothing but the file was written into the folder.
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("product.fits")]);
}

/// The variance is written as astropy's `CCDData` reads an uncertainty (extension `UNCERT`,
/// `UTYPE` = 'VarianceUncertainty'); an `UNCERT` written by another tool is read as the kind
/// its `UTYPE` says (a standard deviation without one, as astropy does), a legacy `VARIANCE`
/// as a variance, and an unknown `UTYPE` is refused naming the file and the value.
#[test]
fn the_uncertainty_extension_is_read_as_its_utype_says() {
    use super::{write_frame, write_images, ImageHdu, ImagePixels, VARIANCE_EXTNAME, VARIANCE_UTYPE};
    let dir = tempfile::tempdir().unwrap();
    let data = ndarray::Array2::from_shape_fn((4, 6), |(y, x)| (y * 6 + x) as f32);
    let sigma = data.mapv(|v| 0.5 + v);
    // write_frame: UNCERT with UTYPE, read back as the same variance.
    let mut frame = read_frame(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../testdata/fits/sofi_pol_64x64_i16.fits"
    )))
    .unwrap();
    frame.variance = Some(frame.data.mapv(|v| v.abs() + 2.0));
    let written = dir.path().join("frame.fits");
    let opts = super::WriteOptions {
        with_variance_and_mask: true,
        ..Default::default()
    };
    write_frame(&written, &frame, &opts).unwrap();
    let mut f = fitsio::FitsFile::open(&written).unwrap();
    let hdu = f.hdu(VARIANCE_EXTNAME).unwrap();
    assert_eq!(hdu.read_key::<String>(&mut f, "UTYPE").unwrap(), VARIANCE_UTYPE);
    assert_eq!(read_frame(&written).unwrap().variance, frame.variance);
    // Foreign files: (EXTNAME, UTYPE, values) -> the variance read.
    let inverse = sigma.mapv(|s| 1.0 / (s * s));
    let cases: [(&str, Option<&str>, &ndarray::Array2<f32>); 4] = [
        ("UNCERT", Some("StdDevUncertainty"), &sigma),
        ("UNCERT", None, &sigma),
        ("UNCERT", Some("InverseVariance"), &inverse),
        ("VARIANCE", None, &sigma),
    ];
    for (k, (name, utype, values)) in cases.into_iter().enumerate() {
        let path = dir.path().join(format!("foreign{k}.fits"));
        let mut hu = crate::Header::new("");
        if let Some(u) = utype {
            hu.set("UTYPE", u);
        }
        let empty = crate::Header::new("");
        write_images(
            &path,
            &[
                ImageHdu {
                    extname: "",
                    header: &empty,
                    history: &[],
                    pixels: ImagePixels::F32(&data),
                },
                ImageHdu {
                    extname: name,
                    header: &hu,
                    history: &[],
                    pixels: ImagePixels::F32(values),
                },
            ],
        )
        .unwrap();
        let var = read_frame(&path).unwrap().variance.unwrap();
        let want = if name == "VARIANCE" {
            sigma.clone()
        } else {
            sigma.mapv(|s| s * s)
        };
        for (a, b) in var.iter().zip(want.iter()) {
            assert!((a - b).abs() <= 1e-5 * b.abs(), "{name} {utype:?}: {a} vs {b}");
        }
    }
    let path = dir.path().join("unknown.fits");
    let mut hu = crate::Header::new("");
    hu.set("UTYPE", "Smoothness");
    let empty = crate::Header::new("");
    write_images(
        &path,
        &[
            ImageHdu {
                extname: "",
                header: &empty,
                history: &[],
                pixels: ImagePixels::F32(&data),
            },
            ImageHdu {
                extname: "UNCERT",
                header: &hu,
                history: &[],
                pixels: ImagePixels::F32(&sigma),
            },
        ],
    )
    .unwrap();
    let err = read_frame(&path).unwrap_err().to_string();
    assert!(err.contains("unknown.fits") && err.contains("Smoothness"), "{err}");
}
