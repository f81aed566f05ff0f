//! Fuzzing the parsers of untrusted input with proptest: the FITS header reader
//! (cfitsio plus our card parser and classification), the scene and parameter TOML, the
//! catalog JSON and the Monte-Carlo table/spec parsers. Property: no panic, and an error
//! (never a half-parsed value with NaN) when the input is not valid.
use std::path::Path;

use proptest::prelude::*;
use sofipol_calib::Profile;

const GOOD: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../testdata/fits/sofi_pol_64x64_i16.fits");

/// The header blocks of the reference frame (up to and including the block with END).
fn header_bytes() -> (Vec<u8>, usize) {
    let b = std::fs::read(GOOD).unwrap();
    let end = (0..b.len() / 80)
        .find(|&i| b[i * 80..i * 80 + 8] == *b"END     ")
        .expect("END card");
    let hdr_len = (end * 80 / 2880 + 1) * 2880;
    (b, hdr_len)
}

fn check_header_file(bytes: &[u8]) {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("fuzz.fits");
    std::fs::write(&p, bytes).unwrap();
    // Must return (Ok or Err), never panic.
    if let Ok(h) = sofipol_calib::fits::read_header(&p) {
        for c in &h.cards {
            let _ = h.get_f64(&c.key);
            let _ = h.get_str(&c.key);
        }
    }
    let _ = sofipol_calib::classify::classify_file(&p, &Profile::sofi());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn fits_header_reader_survives_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..6000)) {
        check_header_file(&bytes);
        // The same bytes behind a valid first card.
        let mut b = b"SIMPLE  =                    T".to_vec();
        b.resize(80, b' ');
        b.extend_from_slice(&bytes);
        check_header_file(&b);
    }

    #[test]
    fn fits_header_reader_survives_mutated_cards(
        edits in proptest::collection::vec((any::<prop::sample::Index>(), 8usize..80, proptest::collection::vec(any::<u8>(), 1..40)), 1..6),
    ) {
        // Random bytes written into random cards of a valid header (values, comments,
        // quotes, HIERARCH, CONTINUE...); the data unit is left as it is.
        let (mut b, hdr_len) = header_bytes();
        for (card, col, bytes) in edits {
            let start = card.index(hdr_len / 80) * 80 + col;
            for (i, v) in bytes.into_iter().enumerate() {
                if start + i < hdr_len {
                    b[start + i] = v;
                }
            }
        }
        check_header_file(&b);
    }

    #[test]
    fn toml_and_json_parsers_survive_arbitrary_text(text in ".{0,400}", bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let lossy = String::from_utf8_lossy(&bytes).into_owned();
        for t in [&text, &lossy] {
            let _ = sofipol_pipeline::sim::Scene::from_toml(t, "fuzz");
            let _ = toml::from_str::<sofipol_pipeline::reduce::TargetParams>(t);
            let _ = serde_json::from_str::<sofipol_pipeline::catalog::Catalog>(t);
            let _ = sofipol_pipeline::stats::mc::PIntDist::parse(t);
            let d = tempfile::tempdir().unwrap();
            let p = d.path().join("x.toml");
            std::fs::write(&p, t).unwrap();
            let _ = Profile::sofi_with_override(&p);
            let _ = sofipol_pipeline::stats::model::AlphaTable::from_file(&p);
            let _ = Profile::sofi().with_overrides(std::slice::from_ref(t));
        }
    }

    #[test]
    fn toml_parsers_survive_plausible_keys_with_wild_values(
        key in prop::sample::select(vec!["seed", "dithers", "fwhm_arcsec", "flux_a", "separation_arcsec", "p_a", "orientations_deg", "aperture_fwhm", "clip_sigma", "bitpix", "ndit", "dit_s"]),
        value in prop::sample::select(vec!["nan", "inf", "-inf", "-1", "0", "1e308", "-1e308", "1e-320", "18446744073709551616", "\"x\"", "[]", "[nan]", "{}", "true"]),
    ) {
        // Sections where these keys live; the value replaces the demo's.
        let scene = format!(
            "name = \"f\"\nseed = 1\n[observation]\n{k}\n[psf]\n{k}\n[[binary]]\nname = \"B\"\nseparation_arcsec = 2.0\npa_deg = 0.0\nflux_a = 1e5\nflux_b = 5e4\np_a = 0.01\ngamma_a_deg = 0.0\np_b = 0.01\ngamma_b_deg = 0.0\n{k}\n",
            k = format!("{key} = {value}")
        );
        if let Ok(s) = sofipol_pipeline::sim::Scene::from_toml(&scene, "fuzz") {
            // An accepted scene simulates without panicking on a tiny profile? Only check
            // that its validation holds what it promises: finite positive fluxes.
            for b in &s.binary {
                prop_assert!(b.flux_a.is_finite() && b.flux_b.is_finite(), "{scene}");
                prop_assert!(b.separation_arcsec.is_finite(), "{scene}");
            }
        }
        let params = format!("[measure]\n{key} = {value}\n");
        let _ = toml::from_str::<sofipol_pipeline::reduce::TargetParams>(&params);
    }
}

#[test]
fn the_reference_header_still_parses() {
    // The mutation fuzzer starts from a valid header: make sure it is one.
    let h = sofipol_calib::fits::read_header(Path::new(GOOD)).unwrap();
    assert_eq!(h.get_str("INSTRUME").unwrap(), "SOFI");
}
