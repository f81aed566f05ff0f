//! Flats as FITS files.
use std::path::Path;

use ndarray::Array2;

use super::*;

/// Conventional file name of a flat: `flat_<kind>_<filter>[_pa<angle>].fits`.
pub fn flat_file_name(flat: &Flat) -> String {
    let filt: String = flat
        .filter
        .as_deref()
        .unwrap_or("any")
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    match flat.posang_deg {
        Some(p) => format!("flat_{}_{filt}_pa{:03}.fits", flat.kind.name(), p.round() as i64),
        None => format!("flat_{}_{filt}.fits", flat.kind.name()),
    }
}

/// Write a flat as FITS (atomically): the response in the primary HDU, UNCERT (variance) and MASK
/// (1 = unusable) extensions, kind / angle / filter / frame count in the header, the
/// detail and the files combined as HISTORY.
pub fn write_flat(path: &Path, flat: &Flat) -> Result<()> {
    let mut h = Header::new(path);
    h.set(KIND_KEYWORD, flat.kind.name());
    if let Some(p) = flat.posang_deg {
        h.set(POSANG_KEYWORD, p);
    }
    if let Some(f) = &flat.filter {
        h.set(FILTER_KEYWORD, f.as_str());
    }
    h.set(NCOMBINE_KEYWORD, flat.sources.len() as i64);
    // A product: found again in a night folder, it is skipped by name, never read as raw.
    h.set_with_comment(
        crate::classify::PRODUCT_KEYWORD,
        "FLAT",
        "sofipol product (calibration flat), not a raw frame",
    );
    let mut frame = Frame {
        data: flat.data.clone(),
        variance: Some(flat.variance.clone()),
        mask: flat.bad.clone(),
        header: h,
        history: vec![HistoryRecord::new("flat", flat.detail.clone())],
    };
    for s in &flat.sources {
        frame.history.push(HistoryRecord::new("flat-input", s.clone()));
    }
    crate::fits::write_frame(
        path,
        &frame,
        &crate::fits::WriteOptions {
            with_variance_and_mask: true,
            ..Default::default()
        },
    )
}

/// Read a flat written by [`write_flat`], or any FITS image of the pixel response (then:
/// kind superflat unless the header says otherwise, variance 0 when there is no UNCERT (or
/// legacy VARIANCE) extension, unusable where MASK is nonzero or the value is not finite or <= 0). The
/// data are used as they are (not renormalized).
pub fn read_flat(path: &Path) -> Result<Flat> {
    let f = crate::fits::read_frame(path)?;
    let kind = match f.header.opt_str(KIND_KEYWORD).as_deref().map(str::trim) {
        Some("dome") => FlatKind::Dome,
        Some("superflat") | None => FlatKind::Superflat,
        Some(other) => {
            return Err(Error::BadKeyword {
                path: path.to_path_buf(),
                keyword: KIND_KEYWORD.into(),
                value: other.into(),
                reason: "expected 'dome' or 'superflat'".into(),
            })
        }
    };
    let posang_deg = f.header.opt_f64(POSANG_KEYWORD)?;
    let filter = f.header.opt_str(FILTER_KEYWORD).map(|s| s.trim().to_string());
    let mut data = f.data;
    let mut bad = f.mask;
    let mut variance = f.variance.unwrap_or_else(|| Array2::zeros(data.raw_dim()));
    ndarray::Zip::from(&mut data)
        .and(&mut variance)
        .and(&mut bad)
        .for_each(|d, v, b| {
            if *b != 0 || !d.is_finite() || *d <= 0.0 || !v.is_finite() {
                *d = 1.0;
                *v = 0.0;
                *b = 1;
            }
        });
    let detail = f
        .history
        .iter()
        .find(|r| r.stage == "flat")
        .map(|r| r.detail.clone())
        .unwrap_or_else(|| "flat read from file".into());
    let sources = f
        .history
        .iter()
        .filter(|r| r.stage == "flat-input")
        .map(|r| r.detail.clone())
        .collect();
    Ok(Flat {
        data,
        variance,
        bad,
        kind,
        posang_deg,
        filter,
        sources,
        detail,
        path: Some(path.to_path_buf()),
    })
}
