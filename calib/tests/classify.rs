//! Classification of every kind of frame from its header alone.
mod common;

use common::sofi_science_header;
use sofipol_calib::classify::{classify, classify_file, Classification, ScienceInfo};
use sofipol_calib::{Header, Profile};

fn science(h: &Header) -> ScienceInfo {
    match classify(h, &Profile::sofi()) {
        Classification::Science(info) => *info,
        Classification::Rejected { reason } => panic!("rejected: {reason}"),
    }
}

fn reason(h: &Header) -> String {
    match classify(h, &Profile::sofi()) {
        Classification::Science(info) => panic!("accepted as science: {info:?}"),
        Classification::Rejected { reason } => reason,
    }
}

#[test]
fn polarimetric_science_at_0_and_45() {
    for (posang, expno) in [(0.0, 1), (45.0, 6)] {
        let mut h = sofi_science_header(posang, expno);
        h.path = "night1/SOFI.1999-03-03T02:11:05.123.fits".into();
        let info = science(&h);
        assert_eq!(info.posang_deg, posang);
        assert_eq!(info.object, "HK Tau");
        assert_eq!(info.tpl_start, "1999-03-03T02:10:41");
        assert_eq!(info.sequence, "HK Tau@1999-03-03T02:10:41");
        assert_eq!(info.offset_px, [86.8, 0.0]);
        assert_eq!(info.filter, "Ks");
        assert_eq!(info.wollaston, "WOLLASTON");
        assert_eq!(info.dit_s, 10.0);
        assert_eq!(info.ndit, 6);
        assert_eq!(info.expno, Some(expno as u32));
        assert_eq!(info.nexp, Some(10));
        assert_eq!(info.mjd, Some(51240.0911236111));
        assert_eq!(info.pixscale_arcsec, 0.288);
        assert_eq!(info.path, h.path);
    }
}

#[test]
fn standard_star_uses_obs_targ_name() {
    let mut h = sofi_science_header(45.0, 1);
    h.set("OBJECT", "STD");
    h.set("ESO DPR TYPE", "STD");
    h.set("ESO DPR CATG", "CALIB"); // ESO files standards as calibrations: still science here
    h.set("ESO OBS TARG NAME", "HD 64299");
    let info = science(&h);
    assert_eq!(info.object, "HD 64299");
    assert_eq!(info.sequence, "HD 64299@1999-03-03T02:10:41");
    // Without OBS TARG NAME the reason names it.
    h.cards.retain(|c| c.key != "ESO OBS TARG NAME");
    let r = reason(&h);
    assert!(
        r.contains("OBJECT = 'STD'") && r.contains("missing keyword ESO OBS TARG NAME"),
        "{r}"
    );
}

#[test]
fn flat_from_another_template() {
    let mut h = sofi_science_header(0.0, 1);
    h.set("ESO TPL ID", "SOFI_img_cal_SkyFlats");
    h.set("ESO DPR CATG", "CALIB");
    h.set("ESO DPR TYPE", "FLAT");
    h.set("ESO DPR TECH", "IMAGE");
    let r = reason(&h);
    assert!(
        r.starts_with("not polarimetric: ESO TPL ID = 'SOFI_img_cal_SkyFlats'"),
        "{r}"
    );
    assert!(
        r.contains("ESO DPR TECH = 'IMAGE'") && r.contains("ESO DPR TYPE = 'FLAT'"),
        "{r}"
    );
}

#[test]
fn flat_taken_in_polarimetric_mode_is_calibration() {
    let mut h = sofi_science_header(0.0, 1);
    h.set("ESO TPL ID", "SOFI_img_cal_PolFlats");
    h.set("ESO DPR CATG", "CALIB");
    h.set("ESO DPR TYPE", "FLAT");
    let r = reason(&h);
    assert!(r.starts_with("calibration frame: ESO DPR TYPE = 'FLAT'"), "{r}");
}

#[test]
fn dark() {
    let mut h = Header::new("dark.fits");
    h.set("INSTRUME", "SOFI");
    h.set("OBJECT", "DARK");
    h.set("ESO TPL ID", "SOFI_img_cal_Darks");
    h.set("ESO DPR CATG", "CALIB");
    h.set("ESO DPR TYPE", "DARK");
    h.set("ESO DPR TECH", "IMAGE");
    h.set("ESO DET DIT", 10.0);
    let r = reason(&h);
    assert!(
        r.contains("not polarimetric") && r.contains("'SOFI_img_cal_Darks'") && r.contains("'DARK'"),
        "{r}"
    );
    // A dark inside a polarimetric template is still a calibration frame.
    h.set("ESO DPR TECH", "POLARIMETRY");
    assert_eq!(
        reason(&h),
        "calibration frame: ESO DPR TYPE = 'DARK' (science types: OBJECT, STD)"
    );
}

#[test]
fn sky_and_catg_without_type() {
    let mut h = sofi_science_header(0.0, 1);
    h.set("ESO DPR TYPE", "SKY");
    assert!(reason(&h).contains("ESO DPR TYPE = 'SKY'"));
    // Without DPR TYPE, a non-science DPR CATG rejects; absent DPR CATG and TYPE accept.
    h.cards.retain(|c| c.key != "ESO DPR TYPE");
    h.set("ESO DPR CATG", "ACQUISITION");
    assert_eq!(
        reason(&h),
        "calibration frame: ESO DPR CATG = 'ACQUISITION' (ESO DPR TYPE absent)"
    );
    h.cards.retain(|c| c.key != "ESO DPR CATG");
    science(&h);
}

#[test]
fn non_sofi_file() {
    let mut h = sofi_science_header(0.0, 1);
    h.set("INSTRUME", "ISAAC");
    assert_eq!(reason(&h), "not SOFI: INSTRUME = 'ISAAC'");
    h.cards.retain(|c| c.key != "INSTRUME");
    assert_eq!(reason(&h), "not SOFI: missing keyword INSTRUME");
}

#[test]
fn science_frame_without_wollaston() {
    let mut h = sofi_science_header(0.0, 1);
    h.set("ESO INS OPTI3 ID", "OPEN");
    let r = reason(&h);
    assert!(r.starts_with("no Wollaston in ESO INS OPTI1..9 ID"), "{r}");
    assert!(
        r.contains("ESO INS OPTI1 ID = 'MASK_POL'") && r.contains("ESO INS OPTI3 ID = 'OPEN'"),
        "{r}"
    );
    // Any slot 1..=opti_max works, and the match ignores case.
    h.set("ESO INS OPTI7 ID", "Woll_Prism");
    assert_eq!(science(&h).wollaston, "Woll_Prism");
}

#[test]
fn polarimetric_by_technique_only() {
    let mut h = sofi_science_header(0.0, 1);
    h.set("ESO TPL ID", "SOFI_img_obs_GenericOffset");
    h.set("ESO DPR TECH", "IMAGE,POLARIMETRY");
    science(&h);
}

#[test]
fn missing_required_keywords_are_named() {
    let profile = Profile::sofi();
    let k = &profile.keywords;
    for key in [&k.posang, &k.offset_x, &k.offset_y, &k.tpl_start, &k.filter, &k.ndit] {
        let mut h = sofi_science_header(45.0, 1);
        h.cards.retain(|c| &c.key != key);
        assert_eq!(reason(&h), format!("missing keyword {key}"));
    }
    // DIT falls back to EXPTIME; both missing is reported.
    let mut h = sofi_science_header(45.0, 1);
    h.cards.retain(|c| c.key != "ESO DET DIT");
    assert_eq!(science(&h).dit_s, 10.0);
    h.cards.retain(|c| c.key != "EXPTIME");
    assert_eq!(reason(&h), "missing keyword ESO DET DIT (and EXPTIME)");
    // OBJECT falls back to OBS TARG NAME.
    let mut h = sofi_science_header(45.0, 1);
    h.cards.retain(|c| c.key != "OBJECT");
    assert_eq!(science(&h).object, "HK_Tau");
}

#[test]
fn malformed_values_are_named() {
    let mut h = sofi_science_header(45.0, 1);
    h.set("ESO ADA POSANG", "forty-five");
    assert_eq!(
        reason(&h),
        "bad keyword ESO ADA POSANG = 'forty-five': expected a number"
    );
    let mut h = sofi_science_header(45.0, 1);
    h.set("ESO DET NDIT", 0i64);
    assert_eq!(reason(&h), "bad keyword ESO DET NDIT = 0: expected an integer >= 1");
    let mut h = sofi_science_header(45.0, 1);
    h.set("ESO TPL EXPNO", 2.5);
    assert!(reason(&h).starts_with("bad keyword ESO TPL EXPNO = 2.5"));
    let mut h = sofi_science_header(45.0, 1);
    h.set("ESO DET DIT", -1.0);
    assert!(reason(&h).starts_with("bad keyword ESO DET DIT = -1"));
}

#[test]
fn optional_keywords_and_profile_pixel_scale() {
    let mut h = sofi_science_header(45.0, 1);
    for key in ["ESO INS PIXSCALE", "ESO TPL EXPNO", "ESO TPL NEXP", "MJD-OBS"] {
        h.cards.retain(|c| c.key != key);
    }
    let info = science(&h);
    assert_eq!((info.expno, info.nexp, info.mjd), (None, None, None));
    assert_eq!(info.pixscale_arcsec, Profile::sofi().geometry.pixscale_arcsec);
    h.set("ESO INS PIXSCALE", 0.292);
    assert_eq!(science(&h).pixscale_arcsec, 0.292);
}

#[test]
fn keyword_names_come_from_the_profile() {
    // Another instrument whose headers use different names and values.
    let p = Profile::sofi()
        .with_overrides(&[
            "match.instrument=\"MYPOL\"".into(),
            "keywords.posang=\"ROTANGLE\"".into(),
            "keywords.opti_prefix=\"OPT\"".into(),
            "keywords.opti_max=2".into(),
            "match.wollaston_contains=\"WP\"".into(),
        ])
        .unwrap();
    let mut h = sofi_science_header(45.0, 1);
    h.set("INSTRUME", "MYPOL");
    h.set("ROTANGLE", 90.0);
    h.set("OPT2 ID", "WP-1");
    let c = classify(&h, &p);
    let info = c.science().unwrap_or_else(|| panic!("{c:?}"));
    assert_eq!(info.posang_deg, 90.0);
    assert_eq!(info.wollaston, "WP-1");
    h.cards.retain(|c| c.key != "ROTANGLE");
    assert_eq!(classify(&h, &p).reason(), Some("missing keyword ROTANGLE"));
}

#[test]
fn classify_a_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f.fits");
    let frame = common::sofi_frame(8, 8, 45.0);
    sofipol_calib::fits::write_frame(&path, &frame, &Default::default()).unwrap();
    let c = classify_file(&path, &Profile::sofi()).unwrap();
    assert!(c.is_science());
    assert_eq!(c.science().unwrap().path, path);
    assert!(classify_file(&dir.path().join("none.fits"), &Profile::sofi()).is_err());
}

/// `RA` and `DEC` (profile keys `ra`, `dec`) are read in degrees when present, absent
/// otherwise; a declination outside [-90, 90] rejects the frame naming the keyword.
#[test]
fn ra_and_dec_are_optional_degrees() {
    let h = sofi_science_header(0.0, 1);
    let info = science(&h);
    assert_eq!((info.ra_deg, info.dec_deg), (Some(67.86), Some(24.41)));
    let mut h = sofi_science_header(0.0, 1);
    h.cards.retain(|c| c.key != "RA" && c.key != "DEC");
    let info = science(&h);
    assert_eq!((info.ra_deg, info.dec_deg), (None, None));
    let mut h = sofi_science_header(0.0, 1);
    h.set("DEC", 95.0);
    let r = reason(&h);
    assert!(r.contains("DEC") && r.contains("95"), "{r}");
    let mut h = sofi_science_header(0.0, 1);
    h.set("RA", "04:31:26.2");
    let r = reason(&h);
    assert!(r.contains("RA"), "{r}");
}
