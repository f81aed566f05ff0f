//! The night's bad-pixel mask as a FITS image (`SOFIPROD = 'BADPIX'`): 1 = bad, 0 = good,
//! one unsigned byte per detector pixel, readable back by `--badpix FILE` (nonzero = bad).
use std::path::Path;

use ndarray::Array2;
use sofipol_calib::fits::{write_images, ImageHdu, ImagePixels};
use sofipol_calib::HistoryRecord;

use super::headers;
use crate::reduce::TargetParams;

/// The night's bad-pixel mask ([`crate::night::night_bad_pixel_mask`]), as this file writes it.
#[derive(Debug, Clone)]
pub struct NightMask {
    /// Full-frame mask (`BAD` where defective). With `rows`, only those rows were examined:
    /// the others are 0 and must not be used (the reduction uses only those rows).
    pub mask: ndarray::Array2<u8>,
    /// The frames it was detected on.
    pub files: Vec<String>,
    /// The rows examined (`[r0, r1)`), when not the whole frame.
    pub rows: Option<(usize, usize)>,
}

/// File name of the night's mask in the products folder.
pub const FILE_NAME: &str = "night_badpix.fits";

/// Write `mask` to `path` (atomically) with its header: product cards, the frames it was
/// detected on (`PRO REC1 RAWi NAME`), `QC BADPIX NBAD`, the rows examined (`QC BADPIX ROW0`,
/// `ROW1`, FITS rows; the others hold 0 and were not examined) and HISTORY.
pub fn write(path: &Path, mask: &NightMask, params: &TargetParams) -> sofipol_calib::Result<()> {
    let bad: Array2<u8> = mask.mask.mapv(|v| u8::from(v != 0));
    let nbad = bad.iter().filter(|&&v| v != 0).count();
    let mut h = headers::product_header(headers::BADPIX);
    headers::raw_cards(&mut h, &mask.files, "POL_SCIENCE");
    headers::qc(&mut h, "BADPIX NBAD", nbad as i64, "bad pixels");
    let (ny, _) = bad.dim();
    let (r0, r1) = mask.rows.unwrap_or((0, ny));
    headers::qc(&mut h, "BADPIX ROW0", (r0 + 1) as i64, "first FITS row examined");
    headers::qc(&mut h, "BADPIX ROW1", r1 as i64, "last FITS row examined");
    h.set(
        "COMMENT",
        "1 = bad pixel, 0 = good (or not examined: rows outside ROW0..ROW1)",
    );
    let settings = serde_json::to_string(&params.bad_pixels).unwrap_or_default();
    let history = [
        HistoryRecord::new(
            "badpix",
            format!(
                "the night's detector defects: median stack of {} frames from many sequences, each scaled \
                 by its sky level (the stars move between dithers and sequences, the defects stay); \
                 settings {settings}; {nbad} pixels bad",
                mask.files.len()
            ),
        ),
        HistoryRecord::new(
            "rows",
            match mask.rows {
                Some((r0, r1)) => format!(
                    "only FITS rows {}..{} (the target strips, all the reduction reads) were examined; the \
                     other rows hold 0",
                    r0 + 1,
                    r1
                ),
                None => "every row examined".into(),
            },
        ),
        HistoryRecord::new(
            "use",
            "sofipol night|target --badpix FILE reads it back (nonzero = bad)",
        ),
    ];
    write_images(
        path,
        &[ImageHdu {
            extname: "",
            header: &h,
            history: &history,
            pixels: ImagePixels::U8(&bad),
        }],
    )
}
