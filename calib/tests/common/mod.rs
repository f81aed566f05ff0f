//! Shared helpers of the calib integration tests.
#![allow(dead_code)]
use ndarray::Array2;
use sofipol_calib::{Frame, Header};

/// A complete header of a SOFI polarimetric science frame, built in code.
pub fn sofi_science_header(posang_deg: f64, expno: i64) -> Header {
    let mut h = Header::new("");
    h.set_with_comment("INSTRUME", "SOFI", "instrument used");
    h.set("OBJECT", "HK Tau");
    h.set("DATE-OBS", "1999-03-03T02:11:05.123");
    h.set("MJD-OBS", 51240.0911236111);
    h.set("EXPTIME", 10.0);
    h.set("RA", 67.86);
    h.set("DEC", 24.41);
    h.set("ESO DPR CATG", "SCIENCE");
    h.set("ESO DPR TYPE", "OBJECT");
    h.set("ESO DPR TECH", "POLARIMETRY");
    h.set_with_comment("ESO TPL ID", "SOFI_img_obs_Polarimetry", "template");
    h.set("ESO TPL START", "1999-03-03T02:10:41");
    h.set("ESO TPL NEXP", 10i64);
    h.set("ESO TPL EXPNO", expno);
    h.set("ESO OBS TARG NAME", "HK_Tau");
    h.set("ESO INS FILT1 ID", "Ks");
    h.set("ESO INS OPTI1 ID", "MASK_POL");
    h.set("ESO INS OPTI3 ID", "WOLLASTON");
    h.set("ESO INS PIXSCALE", 0.288);
    h.set_with_comment("ESO ADA POSANG", posang_deg, "rotator position angle [deg]");
    h.set("ESO SEQ CUMOFFSETX", 86.8);
    h.set("ESO SEQ CUMOFFSETY", 0.0);
    h.set("ESO DET DIT", 10.0);
    h.set("ESO DET NDIT", 6i64);
    h.set("ESO TEL PARANG START", -157.1);
    h.set("ESO TEL AIRM START", 1.04);
    h
}

/// A smooth image with a few bright spots: compresses well, values are integers.
pub fn smooth_image(ny: usize, nx: usize) -> Array2<f32> {
    Array2::from_shape_fn((ny, nx), |(y, x)| {
        let (fy, fx) = (y as f32, x as f32);
        let bg = 1000.0 + 0.5 * fx + 0.25 * fy;
        let star = |cx: f32, cy: f32, a: f32| {
            let r2 = (fx - cx).powi(2) + (fy - cy).powi(2);
            a * (-r2 / 8.0).exp()
        };
        let sy = ny as f32;
        (bg + star(nx as f32 * 0.4, sy * 0.45, 8000.0) + star(nx as f32 * 0.4, sy * 0.45 + sy * 0.16, 7000.0)).round()
    })
}

/// A frame with the SOFI header, the smooth image and two history records.
pub fn sofi_frame(ny: usize, nx: usize, posang_deg: f64) -> Frame {
    Frame::new(smooth_image(ny, nx), sofi_science_header(posang_deg, 1))
        .with_history("sim", "scene=binary seed=42")
        .with_history("badpix", "hot>5 sigma, 3 clusters repaired")
}

/// The raw header text of a FITS file (every HDU's cards are plain ASCII in the file).
pub fn raw_text(path: &std::path::Path) -> String {
    let bytes = std::fs::read(path).unwrap();
    bytes
        .iter()
        .map(|&b| if (32..127).contains(&b) { b as char } else { '\u{1}' })
        .collect()
}

/// The 80-character cards of the file whose text starts with `name` (first match).
pub fn raw_card(path: &std::path::Path, name: &str) -> Option<String> {
    let text = raw_text(path);
    let bytes = text.as_bytes();
    (0..bytes.len() / 80)
        .map(|i| &text[i * 80..i * 80 + 80])
        .find(|c| c.starts_with(name))
        .map(|c| c.trim_end().to_string())
}
