//! The header cards every FITS product carries: what it is (`SOFIPROD`, the ESO product
//! keywords `HIERARCH ESO PRO ...`), what made it (software, version, commit), what it was
//! made from (`PRO REC1 RAWi NAME`), what it shows (OBJECT, FILTER, POSANG, BUNIT) and the
//! quality-control numbers (`HIERARCH ESO QC ...`). Keys longer than 8 characters are
//! written as `HIERARCH` cards by [`sofipol_calib::fits::write_images`].
use std::path::Path;

use sofipol_calib::classify::PRODUCT_KEYWORD;
use sofipol_calib::{Header, HeaderValue};

use crate::catalog::Target;

/// The kind of a product: its `SOFIPROD` value (what a later scan skips it by) and its ESO
/// product category (`HIERARCH ESO PRO CATG`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProductKind {
    /// `SOFIPROD` value.
    pub sofiprod: &'static str,
    /// `HIERARCH ESO PRO CATG` value.
    pub catg: &'static str,
    /// What the product is, in words (the `SOFIPROD` card's comment).
    pub what: &'static str,
}

/// The o-beam dithers of one orientation, registered and combined.
pub const COMBINED_O: ProductKind = ProductKind {
    sofiprod: "COMBINED",
    catg: "SOFIPOL_COMBINED_O",
    what: "sofipol product (combined o beam), not a raw frame",
};
/// The e-beam dithers of one orientation, registered and combined.
pub const COMBINED_E: ProductKind = ProductKind {
    sofiprod: "COMBINED",
    catg: "SOFIPOL_COMBINED_E",
    what: "sofipol product (combined e beam), not a raw frame",
};
/// Stokes I, Q, U maps of one target (instrumental: before the night's calibration).
pub const STOKES: ProductKind = ProductKind {
    sofiprod: "STOKES",
    catg: "SOFIPOL_STOKES_IQU",
    what: "sofipol product (Stokes I, Q, U), not a raw frame",
};
/// The night's bad-pixel mask.
pub const BADPIX: ProductKind = ProductKind {
    sofiprod: "BADPIX",
    catg: "SOFIPOL_BADPIX",
    what: "sofipol product (bad-pixel mask), not a raw frame",
};

/// The cards every product starts with: `SOFIPROD`, `HIERARCH ESO PRO CATG`, `PRO TYPE`,
/// `PRO REC1 ID` (`'sofipol'`), `PRO REC1 DRS ID` (`'sofipol-<version>'`), `PROCSOFT`
/// (`'sofipol <version> (commit <hash>)'`, as `sofipol --version` prints it) and `DATE`
/// (when the file was written, UTC).
pub fn product_header(kind: ProductKind) -> Header {
    let version = env!("CARGO_PKG_VERSION");
    let mut h = Header::new("");
    h.set_with_comment(PRODUCT_KEYWORD, kind.sofiprod, kind.what);
    h.set_with_comment("ESO PRO CATG", kind.catg, "product category");
    h.set_with_comment("ESO PRO TYPE", "REDUCED", "product type");
    h.set_with_comment("ESO PRO REC1 ID", "sofipol", "pipeline recipe");
    h.set_with_comment(
        "ESO PRO REC1 DRS ID",
        format!("sofipol-{version}"),
        "data reduction software",
    );
    h.set_with_comment(
        "PROCSOFT",
        format!("sofipol {version} (commit {})", crate::build_info::commit()),
        "software and git commit",
    );
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0);
    h.set_with_comment(
        "DATE",
        crate::sim::effects::iso_from_mjd(40587.0 + now / 86400.0, false),
        "file written (UTC)",
    );
    h
}

/// Set `key` to `value` with `comment`. A non-finite number is left out (FITS cannot store
/// it); a string's characters that a FITS string cannot hold (anything but printable
/// ASCII: an OBJECT read from a header may hold anything) become `?`.
pub fn set(h: &mut Header, key: &str, value: impl Into<HeaderValue>, comment: &str) {
    let value = match value.into() {
        HeaderValue::Float(x) if !x.is_finite() => return,
        HeaderValue::Str(s) => HeaderValue::Str(
            s.chars()
                .map(|c| if (' '..='~').contains(&c) { c } else { '?' })
                .collect(),
        ),
        v => v,
    };
    h.set_with_comment(key, value, comment);
}

/// A quality-control card, `HIERARCH ESO QC <name>` (left out when not finite).
pub fn qc(h: &mut Header, name: &str, value: impl Into<HeaderValue>, comment: &str) {
    set(h, &format!("ESO QC {name}"), value, comment);
}

/// What the target's catalog entry says about the observation: OBJECT, FILTER, the
/// template start (`HIERARCH ESO TPL START`), the mean pointing (RA, DEC) and time
/// (MJD-OBS), and the sequence id.
pub fn target_cards(h: &mut Header, target: &Target) {
    set(h, "OBJECT", target.object.as_str(), "target");
    if let Some(f) = &target.filter {
        set(h, "FILTER", f.as_str(), "filter");
    }
    if let Some(t) = &target.tpl_start {
        set(h, "ESO TPL START", t.as_str(), "template start");
    }
    if let Some(s) = &target.sequence {
        set(h, "SEQUENCE", s.as_str(), "sofipol sequence id (object@TPL START)");
    }
    if let Some(ra) = target.ra_deg {
        set(h, "RA", ra, "deg, mean pointing of the frames");
    }
    if let Some(dec) = target.dec_deg {
        set(h, "DEC", dec, "deg, mean pointing of the frames");
    }
    if let Some(mjd) = target.mjd_mean {
        set(h, "MJD-OBS", mjd, "mean MJD-OBS of the frames");
    }
}

/// The linear part of a cut-out's WCS, deg per px: the `CD` matrix `[[CD1_1, CD1_2], [CD2_1,
/// CD2_2]]` of a detector whose +y points to position angle `posang_deg` and whose -x points
/// east at POSANG 0 (the frame contract: a star at separation r and PA psi from another sits
/// `(-r sin(psi - theta), r cos(psi - theta))/scale` px from it, `companion_offset_px`).
pub fn cd_matrix(posang_deg: f64, scale_arcsec: f64) -> [[f64; 2]; 2] {
    let (s, t) = (scale_arcsec / 3600.0, posang_deg.to_radians());
    [[-s * t.cos(), s * t.sin()], [s * t.sin(), s * t.cos()]]
}

/// The celestial WCS of a cut-out (gnomonic, ICRS): the target star (A) at FITS pixel
/// `crpix` is at the pointing (`ra_deg`, `dec_deg`), the axes turned by the rotator angle
/// ([`cd_matrix`]). Absolute positions are as good as the telescope's pointing; offsets
/// within the cut-out as the pixel scale.
pub fn wcs_cards(h: &mut Header, (ra_deg, dec_deg): (f64, f64), crpix: (f64, f64), posang_deg: f64, scale_arcsec: f64) {
    let cd = cd_matrix(posang_deg, scale_arcsec);
    set(h, "WCSAXES", 2i64, "celestial WCS: the target star at the pointing");
    set(h, "CTYPE1", "RA---TAN", "gnomonic projection");
    set(h, "CTYPE2", "DEC--TAN", "gnomonic projection");
    set(h, "CUNIT1", "deg", "");
    set(h, "CUNIT2", "deg", "");
    set(h, "CRPIX1", crpix.0, "FITS px of the target star (QC TARGET X)");
    set(h, "CRPIX2", crpix.1, "FITS px of the target star (QC TARGET Y)");
    set(h, "CRVAL1", ra_deg, "deg, the pointing, taken as the target star's RA");
    set(
        h,
        "CRVAL2",
        dec_deg,
        "deg, the pointing, taken as the target star's Dec",
    );
    set(h, "CD1_1", cd[0][0], "deg/px; +y at PA POSANG, -x east at POSANG 0");
    set(h, "CD1_2", cd[0][1], "deg/px");
    set(h, "CD2_1", cd[1][0], "deg/px");
    set(h, "CD2_2", cd[1][1], "deg/px");
    set(h, "RADESYS", "ICRS", "");
}

/// The input frames, ESO style: `HIERARCH ESO PRO REC1 RAWi NAME` (file names, i from 1),
/// `RAWi CATG`, and `HIERARCH ESO PRO DATANCOM` (how many).
pub fn raw_cards<P: AsRef<Path>>(h: &mut Header, files: &[P], catg: &str) {
    for (i, f) in files.iter().enumerate() {
        let name = f
            .as_ref()
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| f.as_ref().display().to_string());
        set(h, &format!("ESO PRO REC1 RAW{} NAME", i + 1), name, "input frame");
        set(h, &format!("ESO PRO REC1 RAW{} CATG", i + 1), catg, "its category");
    }
    set(h, "ESO PRO DATANCOM", files.len() as i64, "number of input frames");
}

/// The header of an extension: `BUNIT` and a one-line description (`COMMENT`).
pub fn extension_header(bunit: Option<&str>, what: &str) -> Header {
    let mut h = Header::new("");
    if let Some(u) = bunit {
        h.set_with_comment("BUNIT", u, unit_comment(u));
    }
    h.set("COMMENT", what);
    h
}

/// The header of a variance extension (`UNCERT`): `BUNIT` adu2, `UTYPE` =
/// 'VarianceUncertainty' (what astropy's `CCDData.read` needs to take it as the variance of the
/// primary image) and a one-line description.
pub fn variance_header(what: &str) -> Header {
    let mut h = extension_header(Some("adu2"), what);
    h.set_with_comment(
        "UTYPE",
        sofipol_calib::fits::VARIANCE_UTYPE,
        "astropy uncertainty class of this extension",
    );
    h
}

/// The comment of a `BUNIT` card.
pub fn unit_comment(unit: &str) -> &'static str {
    match unit {
        "adu" => "ADU per DIT, averaged over NDIT reads",
        "adu2" => "ADU^2 (variance)",
        _ => "",
    }
}

#[cfg(test)]
mod tests {
    use super::cd_matrix;
    use crate::stokes::model::companion_offset_px;

    /// The CD matrix takes the detector offset of a companion (the frame contract, as the
    /// reduction places it) to its offset on the sky: east rho sin(psi), north rho cos(psi),
    /// at every rotator angle; the pixel area is the scale squared and the parity is the
    /// sky's (east left of north: negative determinant).
    #[test]
    fn the_cd_matrix_maps_a_companions_detector_offset_to_its_sky_offset() {
        let scale = 0.288;
        for posang in [0.0, 45.0, 90.0, 135.0, -30.0, 217.5] {
            let cd = cd_matrix(posang, scale);
            let det = cd[0][0] * cd[1][1] - cd[0][1] * cd[1][0];
            assert!((det + (scale / 3600.0f64).powi(2)).abs() < 1e-18, "{posang}: det {det}");
            for (rho, psi) in [(2.0f64, 30.0f64), (5.3, 200.0), (0.6, 359.0)] {
                let (dx, dy) = companion_offset_px(rho, psi, posang, scale);
                let east = (cd[0][0] * dx + cd[0][1] * dy) * 3600.0;
                let north = (cd[1][0] * dx + cd[1][1] * dy) * 3600.0;
                assert!(
                    (east - rho * psi.to_radians().sin()).abs() < 1e-9,
                    "{posang} {psi}: east {east}"
                );
                assert!(
                    (north - rho * psi.to_radians().cos()).abs() < 1e-9,
                    "{posang} {psi}: north {north}"
                );
            }
        }
    }
}
