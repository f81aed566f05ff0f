//! sofipol reads FITS files it did not write: `testdata/fits/` was written once by astropy
//! (`testdata/fits/make_fits.py`, versions in its docstring). The pixels are checked against
//! the content stated in that script and in testdata/fits/README.md (recomputed here), and
//! against the numbers astropy printed when it wrote them; the header against the values it
//! wrote. Nothing here regenerates the files.
use std::path::PathBuf;

use ndarray::Array2;
use sofipol_calib::classify::classify;
use sofipol_calib::fits::{read_frame, read_header};
use sofipol_calib::Profile;

fn testdata_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata/fits")
}

/// The stated content: tilted background 1000 + 0.5 x + 0.25 y plus two Gaussian spots
/// (sigma 2 px) of 8000 and 7000 ADU at (25.6, 28.8) and (25.6, 39.04), in f64, rounded
/// half to even as numpy does (the background has exact .5 values).
fn stated_image() -> Array2<f64> {
    Array2::from_shape_fn((64, 64), |(y, x)| {
        let (fx, fy) = (x as f64, y as f64);
        let star = |cx: f64, cy: f64, a: f64| a * (-((fx - cx).powi(2) + (fy - cy).powi(2)) / 8.0).exp();
        (1000.0 + 0.5 * fx + 0.25 * fy + star(25.6, 28.8, 8000.0) + star(25.6, 39.04, 7000.0)).round_ties_even()
    })
}

/// (file, rotator angle, EXPNO) as written by make_fits.py.
const FILES: [(&str, f64, i64); 3] = [
    ("sofi_pol_64x64_i16.fits", 45.0, 6),
    ("sofi_pol_64x64_i16.fits.fz", 45.0, 6),
    ("sofi_pol_64x64_f32.fits", 0.0, 1),
];

#[test]
fn astropy_written_files_read_back_exactly() {
    let stated = stated_image();
    for (name, posang, expno) in FILES {
        let path = testdata_dir().join(name);
        let frame = read_frame(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(frame.shape(), (64, 64), "{name}");
        let data = frame.data.mapv(f64::from);
        // Printed by astropy when it wrote the files (make_fits.py): sum and two pixels.
        assert_eq!(data.sum(), 4_569_857.0, "{name}: pixel sum");
        assert_eq!(data[[28, 25]], 8079.0, "{name}: peak pixel [y=28, x=25]");
        assert_eq!(
            data[[0, 63]],
            1032.0,
            "{name}: corner pixel [y=0, x=63] (row 0 = FITS row 1)"
        );
        let worst = data
            .iter()
            .zip(stated.iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert_eq!(worst, 0.0, "{name}: differs from the stated content");

        let h = &frame.header;
        assert_eq!(h.get_str("INSTRUME").unwrap(), "SOFI", "{name}");
        assert_eq!(h.get_str("OBJECT").unwrap(), "HK Tau", "{name}");
        assert_eq!(h.get_str("ESO TPL ID").unwrap(), "SOFI_img_obs_Polarimetry", "{name}");
        assert_eq!(h.get_f64("ESO ADA POSANG").unwrap(), posang, "{name}");
        assert_eq!(h.get_f64("ESO INS PIXSCALE").unwrap(), 0.288, "{name}");
        assert_eq!(h.get_f64("MJD-OBS").unwrap(), 51240.0911236111, "{name}");
        assert_eq!(h.get_f64("ESO SEQ CUMOFFSETX").unwrap(), 86.8, "{name}");
        // Structural and compression keywords are not returned as science keywords.
        for k in ["BITPIX", "NAXIS1", "BZERO", "ZCMPTYPE", "ZBITPIX"] {
            assert!(
                h.get_str(k).is_err() && h.get_f64(k).is_err(),
                "{name}: {k} leaked into the header"
            );
        }
        // A foreign HISTORY card becomes a record of stage "file".
        assert!(
            frame
                .history
                .iter()
                .any(|r| r.stage == "file" && r.detail.contains("make_fits.py")),
            "{name}: {:?}",
            frame.history
        );
        // Header-only read agrees with the full read.
        assert_eq!(read_header(&path).unwrap().cards, frame.header.cards, "{name}");

        let c = classify(&frame.header, &Profile::sofi());
        let info = c.science().unwrap_or_else(|| panic!("{name}: {c:?}"));
        assert_eq!(info.posang_deg, posang, "{name}");
        assert_eq!(info.expno, Some(expno as u32), "{name}");
        assert_eq!(info.path, path);
    }
}
