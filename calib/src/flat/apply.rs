//! Dividing frames by a flat, with the flat's noise in the variance.
use super::*;

/// Whether `flat` can be applied to `frame` whose row 0 is row `row0` of the flat: same
/// width and the frame's rows inside the flat (`row0 = 0`: the same shape). Returns the
/// frame's Poisson factor 1/g and read variance (ADU^2). Errors name the frame and flat.
pub fn check_flat(frame: &Frame, flat: &Flat, row0: usize, profile: &Profile) -> Result<(f32, f32)> {
    let (ny, nx) = frame.shape();
    let (fny, fnx) = flat.shape();
    let fits = fnx == nx && if row0 == 0 { fny == ny } else { row0 + ny <= fny };
    if !fits {
        return Err(Error::Stage {
            stage: "flat",
            reason: format!(
                "{}: frame shape {:?}{} differs from the flat's {:?}{}",
                name_of(frame, 0),
                frame.shape(),
                if row0 == 0 {
                    String::new()
                } else {
                    format!(" at flat row {row0}")
                },
                flat.shape(),
                flat.path
                    .as_ref()
                    .map(|p| format!(" ({})", p.display()))
                    .unwrap_or_default()
            ),
        });
    }
    raw_variance(frame, profile)
}

/// Divide a raw frame by a flat of the same shape (crop the flat with
/// [`Flat::crop_rows`] for a cropped frame; `profile` then the matching
/// [`Profile::cropped_rows`]). The output carries a variance map: the frame's own
/// (Poisson + read noise of the raw values when it has none) divided by flat^2, plus the
/// flat's noise on the signal above the strip's sky level (module documentation). Pixels
/// the flat marks unusable keep their raw value and get [`mask::BAD`].
pub fn apply_flat(frame: &Frame, flat: &Flat, profile: &Profile) -> Result<Frame> {
    check_flat(frame, flat, 0, profile)?;
    let mut out = frame.clone();
    apply_flat_in_place(&mut out, flat, 0, profile)?;
    Ok(out)
}

/// [`apply_flat`] in place, without copying the frame, the frame's row 0 being row `row0`
/// of the flat (a frame read as the target strips of a full-frame flat: no cropped copy of
/// the flat either; `profile` matches the frame). Same numbers as [`apply_flat`] bit for
/// bit. On error the frame is unchanged.
pub fn apply_flat_in_place(frame: &mut Frame, flat: &Flat, row0: usize, profile: &Profile) -> Result<()> {
    let (inv_g, rv) = check_flat(frame, flat, row0, profile)?;
    let (ny, nx) = frame.shape();
    let g = &profile.geometry;
    let sat = profile.detector.saturation_adu as f32;
    // Sky level of each strip (rows outside strips: 0).
    let mut level_of_row = vec![0f32; ny];
    for (_, [a, b]) in g.strips() {
        let (a, b) = (a.min(ny), b.min(ny));
        if a >= b {
            continue;
        }
        let l = strip_median_step(&frame.data, &frame.mask, a, b, 16, |v| v < sat).unwrap_or(0.0);
        for lr in &mut level_of_row[a..b] {
            *lr = l;
        }
    }
    standardize(&mut frame.data);
    standardize(&mut frame.mask);
    let has_var = frame.variance.is_some();
    let mut var = match frame.variance.take() {
        Some(mut v) => {
            standardize(&mut v);
            v
        }
        None => Array2::<f32>::zeros((ny, nx)),
    };
    let rows = ndarray::s![row0..row0 + ny, ..];
    let (fd, fv, fb) = (flat.data.slice(rows), flat.variance.slice(rows), flat.bad.slice(rows));
    let n_bad: usize = frame
        .data
        .as_slice_mut()
        .expect("standard")
        .par_chunks_mut(nx)
        .zip(var.as_slice_mut().expect("standard").par_chunks_mut(nx))
        .zip(frame.mask.as_slice_mut().expect("standard").par_chunks_mut(nx))
        .enumerate()
        .map(|(y, ((drow, vrow), mrow))| {
            let l = level_of_row[y];
            let (fd, fv, fb) = (fd.row(y), fv.row(y), fb.row(y));
            let mut n = 0;
            // Branch-free (vectorised): both results computed, the flat's bad pixels keep
            // the raw value and its variance.
            for x in 0..nx {
                let raw = drow[x];
                let v0 = if has_var { vrow[x] } else { raw.max(0.0) * inv_g + rv };
                let bad = fb[x] != 0;
                let f = fd[x];
                let out = raw / f;
                let excess = (out - l).max(0.0);
                let v = (v0 + excess * excess * fv[x]) / (f * f);
                drow[x] = if bad { raw } else { out };
                vrow[x] = if bad { v0 } else { v };
                mrow[x] |= u8::from(bad) * mask::BAD;
                n += usize::from(bad);
            }
            n
        })
        .sum();
    frame.variance = Some(var);
    frame.history.push(HistoryRecord::new(
        "flat",
        format!(
            "divided by the {}; variance = raw variance / flat^2 + (signal above strip sky)^2 var_flat / flat^2; \
             {n_bad} pixels unusable in the flat marked BAD",
            flat.describe()
        ),
    ));
    Ok(())
}

/// Make an array standard layout (a copy only when it is not).
fn standardize<T: Clone>(a: &mut Array2<T>) {
    if !a.is_standard_layout() {
        *a = a.as_standard_layout().into_owned();
    }
}

/// The rows of a flat matching frames whose row 0 is row `row0` of the flat, prepared to
/// be divided out inside the sky stage's last pass ([`crate::sky::sky_subtract_flat`])
/// instead of in a pass of its own: the frames are sky-subtracted raw, and raw - sky is
/// then divided by the flat in the same loop. With the sky scaled multiplicatively this is
/// the same reduction as dividing first (the per-pixel median of the other dithers commutes
/// with a response they share). Made once per orientation ([`FlatRows::new`]): per pixel
/// the inverse response and the flat's variance (1 and 0 where unusable) and the BAD bit,
/// so that each frame costs two multiplications per pixel and no division, copy, variance
/// map or pass of its own.
#[derive(Debug, Clone)]
pub struct FlatRows<'a> {
    /// The flat.
    pub flat: &'a Flat,
    /// Flat row of the frames' row 0.
    pub row0: usize,
    maps: std::sync::Arc<Prepared>,
}

/// The per-pixel maps of [`FlatRows`] (shared between the targets of a night through
/// [`FlatSet::rows`]).
#[derive(Debug)]
pub(crate) struct Prepared {
    nx: usize,
    /// 1 / flat, 1 where unusable.
    inv: Vec<f32>,
    /// var_flat, 0 where unusable.
    var: Vec<f32>,
    /// [`mask::BAD`] where unusable, else 0.
    bad: Vec<u8>,
    /// Unusable pixels in these rows.
    n_bad: usize,
}

impl Prepared {
    /// Rows `row0..row0 + ny` of `flat`, clamped to the flat's rows.
    pub(crate) fn new(flat: &Flat, row0: usize, ny: usize) -> Prepared {
        let (fny, nx) = flat.shape();
        let (a, b) = (row0.min(fny), (row0 + ny).min(fny));
        let rows = s![a..b, ..];
        let (d, v, bad) = (flat.data.slice(rows), flat.variance.slice(rows), flat.bad.slice(rows));
        let inv = ndarray::Zip::from(&d)
            .and(&bad)
            .map_collect(|&f, &b| if b != 0 { 1.0 } else { 1.0 / f });
        let var = ndarray::Zip::from(&v)
            .and(&bad)
            .map_collect(|&v, &b| if b != 0 { 0.0 } else { v });
        let bits = bad.map(|&b| u8::from(b != 0) * mask::BAD);
        let n_bad = bad.iter().filter(|&&b| b != 0).count();
        Prepared {
            nx,
            inv: inv.into_raw_vec_and_offset().0,
            var: var.into_raw_vec_and_offset().0,
            bad: bits.into_raw_vec_and_offset().0,
            n_bad,
        }
    }
}

/// One row of [`FlatRows`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct FlatRow<'a> {
    pub(crate) inv: &'a [f32],
    pub(crate) var: &'a [f32],
    pub(crate) bad: &'a [u8],
}

impl<'a> FlatRows<'a> {
    /// Rows `row0..row0 + ny` of `flat` (clamped to the flat's rows; the sky stage refuses
    /// frames the rows do not cover). [`FlatSet::rows`] shares them between targets.
    pub fn new(flat: &'a Flat, row0: usize, ny: usize) -> FlatRows<'a> {
        FlatRows {
            flat,
            row0,
            maps: std::sync::Arc::new(Prepared::new(flat, row0, ny)),
        }
    }

    pub(crate) fn from_prepared(flat: &'a Flat, row0: usize, maps: std::sync::Arc<Prepared>) -> FlatRows<'a> {
        FlatRows { flat, row0, maps }
    }

    /// Frame rows covered.
    pub fn ny(&self) -> usize {
        self.maps.inv.len() / self.maps.nx.max(1)
    }

    /// Frame row `y`.
    pub(crate) fn row(&self, y: usize) -> FlatRow<'_> {
        let nx = self.maps.nx;
        let r = y * nx..(y + 1) * nx;
        FlatRow {
            inv: &self.maps.inv[r.clone()],
            var: &self.maps.var[r.clone()],
            bad: &self.maps.bad[r],
        }
    }

    /// History record of a frame flat-fielded this way.
    pub(crate) fn history(&self) -> HistoryRecord {
        HistoryRecord::new(
            "flat",
            format!(
                "divided by the {} in the sky stage's last pass: data = (raw - sky) / flat; variance = \
                 (raw variance + sky-estimate variance) / flat^2 + data^2 var_flat / flat^2 (the flat's noise \
                 on the signal above the sky); {} pixels unusable in the flat marked BAD",
                self.flat.describe(),
                self.maps.n_bad
            ),
        )
    }
}
