//! Dome flats: lamp on minus lamp off per rotator angle, strips normalized separately.
use std::path::PathBuf;

use ndarray::Array2;
use rayon::prelude::*;

use super::*;
use crate::header::HeaderValue;

/// What the header says about a dome-flat frame.
#[derive(Debug, Clone, PartialEq)]
pub struct DomeFlatInfo {
    /// Rotator angle, deg.
    pub posang_deg: f64,
    /// Lamp on (T) or off (F).
    pub lamp_on: bool,
    /// Filter, when present.
    pub filter: Option<String>,
}

/// Whether a header is a dome flat (DPR TYPE 'FLAT', or TPL ID the dome-flat template), and
/// its rotator angle and lamp state. `Ok(None)`: not a flat; `Err`: a flat whose lamp or
/// angle keyword is missing or malformed (the error names the file and the keyword).
pub fn dome_flat_info(header: &Header, profile: &Profile) -> Result<Option<DomeFlatInfo>> {
    let kw = &profile.keywords;
    let is = |k: &str, want: &str| header.opt_str(k).is_some_and(|v| v.trim().eq_ignore_ascii_case(want));
    // The dome-flat template, or a flat (DPR TYPE) that carries the lamp keyword: a flat of
    // another template without it (a sky flat) is not a dome flat.
    let template = is(&kw.tpl_id, DOME_FLAT_TEMPLATE);
    if !(template || (is(&kw.dpr_type, FLAT_TYPE) && header.contains(LAMP_KEYWORD))) {
        return Ok(None);
    }
    let lamp_on = match header.get(LAMP_KEYWORD) {
        Some(HeaderValue::Bool(b)) => *b,
        Some(HeaderValue::Str(s)) if matches!(s.trim(), "T" | "t" | "ON" | "on") => true,
        Some(HeaderValue::Str(s)) if matches!(s.trim(), "F" | "f" | "OFF" | "off") => false,
        Some(v) => {
            return Err(Error::BadKeyword {
                path: header.path.clone(),
                keyword: LAMP_KEYWORD.into(),
                value: v.to_string(),
                reason: "expected T (lamp on) or F (lamp off)".into(),
            })
        }
        None => {
            return Err(Error::MissingKeyword {
                path: header.path.clone(),
                keyword: LAMP_KEYWORD.into(),
            })
        }
    };
    let posang_deg = header.get_f64(&kw.posang)?;
    Ok(Some(DomeFlatInfo {
        posang_deg,
        lamp_on,
        filter: header.opt_str(&kw.filter).map(|s| s.trim().to_string()),
    }))
}

/// Dome flat of one rotator angle: mean(on) - mean(off), each strip normalized separately
/// (see the module documentation). Needs at least one frame of each; all of one shape.
pub fn dome_flat(on: &[Frame], off: &[Frame], profile: &Profile, opts: &FlatOptions) -> Result<Flat> {
    const STAGE: &str = "flat";
    if on.is_empty() || off.is_empty() {
        return Err(Error::Stage {
            stage: STAGE,
            reason: format!(
                "dome flat needs lamp-on and lamp-off frames: {} on, {} off",
                on.len(),
                off.len()
            ),
        });
    }
    let all: Vec<&Frame> = on.iter().chain(off.iter()).collect();
    let shape = check_shapes(&all, profile, STAGE)?;
    let mut resp = Array2::<f32>::zeros(shape);
    let mut var = Array2::<f32>::zeros(shape);
    let mut bad = Array2::<u8>::zeros(shape);
    let sat = profile.detector.nonlinear_warn_adu as f32;
    for (set, sign) in [(on, 1.0f32), (off, -1.0f32)] {
        let n = set.len() as f32;
        for f in set {
            let (inv_g, rv) = raw_variance(f, profile)?;
            ndarray::Zip::from(&mut resp)
                .and(&mut var)
                .and(&mut bad)
                .and(&f.data)
                .and(&f.mask)
                .par_for_each(|r, v, b, &d, &m| {
                    *r += sign * d / n;
                    *v += (d.max(0.0) * inv_g + rv) / (n * n);
                    if m != 0 || !d.is_finite() || d >= sat {
                        *b = 1;
                    }
                });
        }
    }
    let levels = normalize_strips(&mut resp, &mut var, &mut bad, profile, opts, STAGE)?;
    let info = dome_flat_info(&on[0].header, profile).ok().flatten();
    let sources: Vec<String> = all.iter().enumerate().map(|(i, f)| name_of(f, i)).collect();
    let detail = format!(
        "dome flat = mean of {} lamp-on - mean of {} lamp-off frames; strips normalized separately by their median \
         (lamp-on - off levels {}); unusable outside [{}, {}]: {} pixels",
        on.len(),
        off.len(),
        levels
            .iter()
            .map(|(n, l)| format!("{n} {l:.1}"))
            .collect::<Vec<_>>()
            .join(", "),
        opts.min_response,
        opts.max_response,
        bad.iter().filter(|&&b| b != 0).count()
    );
    Ok(Flat {
        data: resp,
        variance: var,
        bad,
        kind: FlatKind::Dome,
        posang_deg: info.as_ref().map(|i| i.posang_deg),
        filter: info.and_then(|i| i.filter),
        sources,
        detail,
        path: None,
    })
}

/// Dome flats of a night: read the headers of `paths`, keep the dome-flat frames, group
/// them by (filter, rotator angle), and build one flat per group that has lamp-on and
/// lamp-off frames. Returns the flats and the files that could not be used, with the
/// reason (unreadable, bad keyword, a group without on or off frames, a failed build).
pub fn build_flats(paths: &[PathBuf], profile: &Profile, opts: &FlatOptions) -> (FlatSet, Vec<(PathBuf, String)>) {
    let mut problems = Vec::new();
    type Key = (String, i64);
    let mut groups: std::collections::BTreeMap<Key, (Vec<PathBuf>, Vec<PathBuf>)> = Default::default();
    let infos: Vec<(PathBuf, Result<Option<DomeFlatInfo>>)> = paths
        .par_iter()
        .map(|p| {
            (
                p.clone(),
                crate::fits::read_header(p).and_then(|h| dome_flat_info(&h, profile)),
            )
        })
        .collect();
    for (p, r) in infos {
        match r {
            Ok(Some(i)) => {
                let key = (
                    i.filter.clone().unwrap_or_default(),
                    (i.posang_deg.rem_euclid(360.0) * 100.0).round() as i64,
                );
                let g = groups.entry(key).or_default();
                if i.lamp_on {
                    g.0.push(p);
                } else {
                    g.1.push(p);
                }
            }
            Ok(None) => {}
            Err(e) => problems.push((p, e.to_string())),
        }
    }
    let mut flats = Vec::new();
    for ((filter, pa), (on, off)) in groups {
        if on.is_empty() || off.is_empty() {
            for p in on.iter().chain(off.iter()) {
                problems.push((
                    p.clone(),
                    format!(
                        "dome flat filter '{filter}' POSANG {}: {} lamp-on and {} lamp-off frames, need both",
                        pa as f64 / 100.0,
                        on.len(),
                        off.len()
                    ),
                ));
            }
            continue;
        }
        let read = |ps: &[PathBuf], problems: &mut Vec<(PathBuf, String)>| -> Vec<Frame> {
            let r: Vec<(PathBuf, Result<Frame>)> =
                ps.par_iter().map(|p| (p.clone(), crate::fits::read_frame(p))).collect();
            r.into_iter()
                .filter_map(|(p, f)| match f {
                    Ok(f) => Some(f),
                    Err(e) => {
                        problems.push((p, e.to_string()));
                        None
                    }
                })
                .collect()
        };
        let on_f = read(&on, &mut problems);
        let off_f = read(&off, &mut problems);
        match dome_flat(&on_f, &off_f, profile, opts) {
            Ok(f) => flats.push(f),
            Err(e) => {
                for p in on.iter().chain(off.iter()) {
                    problems.push((p.clone(), e.to_string()));
                }
            }
        }
    }
    (FlatSet::new(flats), problems)
}
