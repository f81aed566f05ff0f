//! Fuzzing `read_frame` (header *and* pixel data) with proptest: arbitrary
//! bytes, and valid FITS files mutated (bytes flipped anywhere, truncated, header values
//! replaced by wild ones). Property: no panic, and an error names the file.
use proptest::prelude::*;
use sofipol_calib::fits;

const GOOD: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../testdata/fits/sofi_pol_64x64_i16.fits");

/// Read `bytes` as a FITS file named `fuzz_input.fits`: whole and by rows, never a panic;
/// an error must name the file.
fn check(bytes: &[u8]) -> Result<(), TestCaseError> {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("fuzz_input.fits");
    std::fs::write(&p, bytes).unwrap();
    for rows in [None, Some((2, 10))] {
        match fits::read_frame_rows(&p, rows) {
            Ok(f) => {
                let (ny, nx) = f.shape();
                prop_assert_eq!(f.mask.dim(), (ny, nx));
            }
            Err(e) => {
                let msg = e.to_string();
                prop_assert!(msg.contains("fuzz_input.fits"), "error does not name the file: {}", msg);
            }
        }
    }
    Ok(())
}

/// Replace the value of header card `key` (value columns 11-30) by `v`.
fn set_card(b: &mut [u8], key: &str, v: &str) {
    let end = (0..b.len() / 80)
        .find(|&i| b[i * 80..i * 80 + 8] == *b"END     ")
        .unwrap_or(0);
    for i in 0..end {
        let card = &mut b[i * 80..(i + 1) * 80];
        if card[..8].starts_with(key.as_bytes()) && card[key.len()..8].iter().all(|&c| c == b' ') {
            let mut val = [b' '; 20];
            let s = format!("{v:>20}");
            val.copy_from_slice(&s.as_bytes()[s.len() - 20..]);
            card[10..30].copy_from_slice(&val);
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn read_frame_survives_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..8000)) {
        check(&bytes)?;
    }

    #[test]
    fn read_frame_survives_a_valid_file_with_flipped_bytes_or_truncated(
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..12),
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
    ) {
        let mut b = std::fs::read(GOOD).unwrap();
        for (i, v) in flips {
            let k = i.index(b.len());
            b[k] = v;
        }
        if truncate {
            let n = cut.index(b.len());
            b.truncate(n);
        }
        check(&b)?;
    }

    #[test]
    fn read_frame_survives_wild_header_values(
        key in prop::sample::select(vec!["BITPIX", "NAXIS", "NAXIS1", "NAXIS2", "BSCALE", "BZERO", "PCOUNT", "GCOUNT"]),
        v in prop::sample::select(vec![
            "0", "-1", "8", "16", "-32", "-64", "64", "7", "3", "100000", "2147483647", "-2147483648",
            "1E308", "NaN", "'text'", "T", "", "1.5", "99999999999999999999",
        ]),
    ) {
        let mut b = std::fs::read(GOOD).unwrap();
        set_card(&mut b, key, v);
        check(&b)?;
    }
}

/// The reference frame still reads (the mutations start from a valid file).
#[test]
fn the_reference_frame_reads() {
    let f = fits::read_frame(std::path::Path::new(GOOD)).unwrap();
    assert_eq!(f.shape(), (64, 64));
}

/// The mutations reach the reader: wild values are refused, naming the file.
#[test]
fn wild_header_values_are_refused_naming_the_file() {
    for (key, v) in [("NAXIS1", "100000"), ("BITPIX", "7"), ("NAXIS", "-1")] {
        let mut b = std::fs::read(GOOD).unwrap();
        set_card(&mut b, key, v);
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("fuzz_input.fits");
        std::fs::write(&p, &b).unwrap();
        let e = fits::read_frame(&p).expect_err(&format!("{key} = {v} accepted"));
        assert!(e.to_string().contains("fuzz_input.fits"), "{e}");
    }
}
