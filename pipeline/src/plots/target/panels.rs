//! The panels: per-dither F by orientation, and the polarization vectors on the sky.
use super::*;

/// Where a panel goes in the figure: its top-left corner and size.
#[derive(Debug, Clone, Copy)]
pub(super) struct PanelPlace {
    /// Left edge, px from the figure's left.
    pub(super) x0_px: u32,
    /// Top edge, px from the figure's top.
    pub(super) y0_px: u32,
    /// Width, px.
    pub(super) w_px: u32,
    /// Height, px.
    pub(super) h_px: u32,
}

/// Colour of the model of F without the telescope's term: the component's, paler.
pub(super) const MODEL_NO_T_MIX: f64 = 0.4;
/// Colour of the model of F: the component's, a little paler than its points.
pub(super) const MODEL_MIX: f64 = 0.8;

/// The F panel of orientation `k` at `place`: per-dither F of each component with its
/// error, and the model of F from the catalog's q, u and the calibration: dashed,
/// `q cos 2phi + u sin 2phi + c + T`, T the telescope's term at this orientation's
/// parallactic angle when the calibration removed it; dotted, the same without T, with T's
/// value written above the plot.
pub(super) fn f_panel(root: &Area, place: PanelPlace, m: &Measured, k: usize, nums: &FigureNumbers) -> io::Result<()> {
    let area = root
        .clone()
        .shrink((place.x0_px, place.y0_px), (place.w_px, place.h_px));
    let per: Vec<&[DitherValue]> = m
        .dithers
        .iter()
        .filter_map(|c| c.get(k).map(|v| v.as_slice()))
        .collect();
    let nd = per.iter().map(|v| v.len()).max().unwrap_or(0);
    // Model F from the catalog's q, u (and offset c, and the telescope's T) of each
    // component, and the same without T where T is in it.
    let model: Vec<Option<f64>> = (0..per.len())
        .map(|c| {
            let v = *nums.components.get(c)?.model_f.get(k)?;
            v.is_finite().then_some(100.0 * v)
        })
        .collect();
    let tel: Vec<Option<f64>> = (0..per.len())
        .map(|c| {
            let t = (*nums.components.get(c)?.telescope_f.get(k)?)?;
            t.is_finite().then_some(100.0 * t)
        })
        .collect();
    let without_t: Vec<Option<f64>> = model.iter().zip(&tel).map(|(m, t)| Some((*m)? - (*t)?)).collect();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for d in per.iter().flat_map(|v| v.iter()) {
        let (f, s) = (100.0 * d.f, 100.0 * d.sigma_f);
        if f.is_finite() && f.abs() < 200.0 {
            let s = if s.is_finite() && s < 100.0 { s } else { 0.0 };
            lo = lo.min(f - s);
            hi = hi.max(f + s);
        }
    }
    for v in model.iter().chain(&without_t).flatten() {
        lo = lo.min(*v);
        hi = hi.max(*v);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        (lo, hi) = (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.12).max(0.05);
    let (lo, hi) = (lo - pad, hi + pad);
    let xmax = nd.max(1) as f64 + 0.5;
    let mut chart = ChartBuilder::on(&area)
        .margin_right(8)
        // Room above the plot for the telescope's note (kept without one: the same layout).
        .margin_top(16)
        .x_label_area_size(34)
        .y_label_area_size(52)
        .build_cartesian_2d(0.5..xmax, lo..hi)
        .map_err(de)?;
    let xfmt = |v: &f64| {
        if (v - v.round()).abs() < 1e-6 {
            format!("{}", v.round() as i64)
        } else {
            String::new()
        }
    };
    let yfmt = |v: &f64| crate::plots::tick(*v);
    chart
        .configure_mesh()
        .x_labels(nd.max(1) + 1)
        .y_labels(6)
        .x_label_formatter(&xfmt)
        .y_label_formatter(&yfmt)
        .x_desc("dither")
        .y_desc("F = (o−e)/(o+e) [%]")
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 13))
        .light_line_style(RGBColor(240, 240, 240))
        .bold_line_style(RGBColor(215, 215, 215))
        .draw()
        .map_err(de)?;
    let nc = per.len();
    for (c, vals) in per.iter().enumerate() {
        let col = comp_color(c, false);
        if let Some(v) = without_t[c] {
            chart
                .draw_series(DashedLineSeries::new(
                    vec![(0.5, v), (xmax, v)],
                    2,
                    3,
                    col.mix(MODEL_NO_T_MIX).stroke_width(1),
                ))
                .map_err(de)?;
        }
        if let Some(v) = model[c] {
            chart
                .draw_series(DashedLineSeries::new(
                    vec![(0.5, v), (xmax, v)],
                    6,
                    4,
                    col.mix(MODEL_MIX).stroke_width(1),
                ))
                .map_err(de)?;
        }
        let shift = if nc > 1 {
            (c as f64 - 0.5 * (nc - 1) as f64) * 0.14
        } else {
            0.0
        };
        for (i, d) in vals.iter().enumerate() {
            let (f, s) = (100.0 * d.f, 100.0 * d.sigma_f);
            if !f.is_finite() {
                continue;
            }
            let f = f.clamp(lo, hi);
            let x = i as f64 + 1.0 + shift;
            let rej = d.rejected.is_some();
            let ecol = if rej { REJECT } else { col };
            if s.is_finite() && s > 0.0 {
                let (a, b) = ((f - s).max(lo), (f + s).min(hi));
                chart
                    .draw_series(std::iter::once(PathElement::new(
                        vec![(x, a), (x, b)],
                        ecol.stroke_width(1),
                    )))
                    .map_err(de)?;
                for y in [a, b] {
                    chart
                        .draw_series(std::iter::once(PathElement::new(
                            vec![(x - 0.05, y), (x + 0.05, y)],
                            ecol.stroke_width(1),
                        )))
                        .map_err(de)?;
                }
            }
            if rej {
                chart
                    .draw_series(std::iter::once(Circle::new((x, f), 4, WHITE.filled())))
                    .map_err(de)?;
                chart
                    .draw_series(std::iter::once(Circle::new((x, f), 4, REJECT.stroke_width(2))))
                    .map_err(de)?;
            } else {
                chart
                    .draw_series(std::iter::once(Circle::new((x, f), 4, col.filled())))
                    .map_err(de)?;
            }
        }
    }
    // The telescope's term of the models, above the plot, right.
    if let Some(note) = telescope_note(nums, &tel) {
        let st = (FONT, 11)
            .into_font()
            .color(&RGBColor(90, 90, 90))
            .pos(Pos::new(HPos::Right, VPos::Top));
        area.draw(&Text::new(note, (place.w_px as i32 - 10, 1), st))
            .map_err(de)?;
    }
    if nd == 0 {
        let st = (FONT, 13)
            .into_font()
            .color(&RGBColor(120, 120, 120))
            .pos(Pos::new(HPos::Center, VPos::Center));
        area.draw(&Text::new(
            "no per-dither values",
            ((place.w_px / 2) as i32, (place.h_px / 2) as i32),
            st,
        ))
        .map_err(de)?;
    }
    Ok(())
}

/// The telescope's term in the models of an orientation's panel (`tel`: per component, %):
/// `model with telescope T = +0.432 %`, per component when they differ (their orientations
/// weigh the dithers' parallactic angles with their own errors).
fn telescope_note(nums: &FigureNumbers, tel: &[Option<f64>]) -> Option<String> {
    let shown: Vec<(&str, String)> = tel
        .iter()
        .enumerate()
        .filter_map(|(c, t)| {
            let name = nums.components.get(c).map_or("", |n| n.name.as_str());
            Some((name, format!("{:+.3} %", (*t)?)))
        })
        .collect();
    let first = &shown.first()?.1;
    Some(if shown.iter().all(|(_, v)| v == first) {
        format!("model with telescope T = {first}")
    } else {
        let parts: Vec<String> = shown.iter().map(|(n, v)| format!("{n} {v}")).collect();
        format!("model with telescope T: {}", parts.join(", "))
    })
}

// ---------------------------------------------------------------------------------------
// Polarization on the sky

pub(super) fn nice_ceil(v: f64) -> f64 {
    if !(v > 0.0 && v.is_finite()) {
        return 1.0;
    }
    let e = 10f64.powf(v.log10().floor());
    for k in [1.0, 2.0, 2.5, 5.0, 10.0] {
        if k * e >= v * (1.0 - 1e-9) {
            return k * e;
        }
    }
    10.0 * e
}

/// Screen direction (y down) for a star's label: off the polarization vector's axis
/// (`gamma_deg` east of north, drawn with north up and east left) and away from the other
/// star.
pub(super) fn label_dir(star: (f64, f64), other: Option<(f64, f64)>, gamma_deg: Option<f64>) -> (f64, f64) {
    let away = other.map(|o| {
        let (dx, dy) = (star.0 - o.0, star.1 - o.1);
        let l = dx.hypot(dy).max(1e-9);
        (dx / l, dy / l)
    });
    let mut best = (f64::NEG_INFINITY, (0.7, 0.7));
    for k in 0..16 {
        let a = (k as f64 * 22.5).to_radians();
        let d = (a.cos(), a.sin());
        let mut score = 0.0;
        if let Some(g) = gamma_deg {
            // Angle between the label direction and the (axial) vector, 0..90 deg.
            let gv = (-g.to_radians().sin(), -g.to_radians().cos());
            let c = (d.0 * gv.0 + d.1 * gv.1).abs().min(1.0);
            score += c.acos().to_degrees();
        }
        if let Some(w) = away {
            score += 40.0 * (d.0 * w.0 + d.1 * w.1);
        }
        // Slight preference for the right-hand side (text reads better there).
        score += 2.0 * d.0;
        if score > best.0 {
            best = (score, d);
        }
    }
    best.1
}

pub(super) fn pol_panel(
    root: &Area,
    x0: u32,
    y0: u32,
    s: u32,
    nums: &FigureNumbers,
    m: Option<&Measured>,
) -> io::Result<()> {
    let (x0i, y0i, si) = (x0 as i32, y0 as i32, s as i32);
    let title = FontDesc::new(FontFamily::Name(FONT), 16.0, FontStyle::Bold)
        .color(&BLACK)
        .pos(Pos::new(HPos::Center, VPos::Top));
    root.draw(&Text::new("Polarization on the sky", (x0i + si / 2, y0i), title))
        .map_err(de)?;
    let top = y0i + 24;
    let side = si - 24;
    let left = x0i + (si - side) / 2;
    root.draw(&Rectangle::new(
        [(left, top), (left + side, top + side)],
        RGBColor(250, 250, 250).filled(),
    ))
    .map_err(de)?;
    root.draw(&Rectangle::new(
        [(left, top), (left + side, top + side)],
        RGBColor(150, 150, 150).stroke_width(1),
    ))
    .map_err(de)?;
    let grey = RGBColor(110, 110, 110);
    // Compass, top left: north up, east left.
    draw_compass(root, (left + 54, top + 46), grey)?;
    let comps = &nums.components;
    if comps.is_empty() {
        let st = (FONT, 14)
            .into_font()
            .color(&grey)
            .pos(Pos::new(HPos::Center, VPos::Center));
        root.draw(&Text::new(
            "no polarization measured",
            (left + side / 2, top + side / 2),
            st,
        ))
        .map_err(de)?;
        return Ok(());
    }
    let cx = (left + side / 2) as f64;
    let cy = (top + side / 2) as f64;
    let geometry = m
        .and_then(|m| m.geometry)
        .filter(|g| g.0.is_finite() && g.1.is_finite());
    let dstar = 0.40 * side as f64;
    let pos: Vec<(f64, f64)> = match comps.len() {
        1 => vec![(cx, cy)],
        _ => {
            let (ux, uy) = match geometry {
                Some((_, pa)) => (-pa.to_radians().sin(), -pa.to_radians().cos()),
                None => (1.0, 0.0),
            };
            let a = (cx - ux * dstar / 2.0, cy - uy * dstar / 2.0);
            let b = (cx + ux * dstar / 2.0, cy + uy * dstar / 2.0);
            let mut v = vec![a, b];
            v.extend((2..comps.len()).map(|_| (cx, cy)));
            v
        }
    };
    let ps: Vec<f64> = comps
        .iter()
        .map(|c| c.p)
        .filter(|p| p.is_finite() && *p > 0.0 && *p < 1.0)
        .collect();
    let pmax = ps.iter().copied().fold(0.0, f64::max);
    let scale_p = nice_ceil(pmax);
    let full = if comps.len() == 1 { 0.7 } else { 0.38 } * side as f64; // length of a scale_p vector
    for (i, comp) in comps.iter().enumerate().take(2) {
        let col = comp_color(i, false);
        let (sx, sy) = pos[i];
        let ok = comp.p.is_finite() && comp.p > 0.0 && comp.p < 1.0 && comp.gamma_deg.is_finite();
        if ok {
            let half = 0.5 * full * comp.p / scale_p;
            let g = comp.gamma_deg.to_radians();
            let (dx, dy) = (-g.sin(), -g.cos()); // east left, north up (screen y down)
                                                 // Error wedge ±sigma_gamma, both ends (axial).
            let sg = if comp.sigma_gamma_deg.is_finite() {
                comp.sigma_gamma_deg.clamp(0.0, 90.0)
            } else {
                90.0
            };
            let rw = half.max(10.0);
            if sg > 0.05 {
                for end in [0.0, 180.0] {
                    let mut poly = vec![(sx as i32, sy as i32)];
                    let steps = ((2.0 * sg / 3.0).ceil() as usize).clamp(2, 60);
                    for t in 0..=steps {
                        let a = (comp.gamma_deg + end - sg + 2.0 * sg * t as f64 / steps as f64).to_radians();
                        poly.push(((sx - rw * a.sin()).round() as i32, (sy - rw * a.cos()).round() as i32));
                    }
                    root.draw(&Polygon::new(poly, col.mix(0.22).filled())).map_err(de)?;
                }
            }
            let a = ((sx - dx * half).round() as i32, (sy - dy * half).round() as i32);
            let b = ((sx + dx * half).round() as i32, (sy + dy * half).round() as i32);
            let style = if comp.passes_cut {
                col.stroke_width(4)
            } else {
                col.mix(0.55).stroke_width(3)
            };
            root.draw(&PathElement::new(vec![a, b], style)).map_err(de)?;
        }
        root.draw(&Circle::new((sx as i32, sy as i32), 6, col.filled()))
            .map_err(de)?;
        root.draw(&Circle::new((sx as i32, sy as i32), 6, BLACK.stroke_width(1)))
            .map_err(de)?;
        // Name next to the star: away from the other star and off the vector's axis.
        let other = if pos.len() > 1 { Some(pos[1 - i.min(1)]) } else { None };
        let axis = if ok { Some(comp.gamma_deg) } else { None };
        let (ox, oy) = label_dir((sx, sy), other, axis);
        let lp = ((sx + ox * 22.0) as i32, (sy + oy * 22.0) as i32);
        let st = FontDesc::new(FontFamily::Name(FONT), 17.0, FontStyle::Bold)
            .color(&col)
            .pos(Pos::new(HPos::Center, VPos::Center));
        root.draw(&Text::new(comp.name.clone(), lp, st)).map_err(de)?;
        if !ok {
            let st = (FONT, 12)
                .into_font()
                .color(&col)
                .pos(Pos::new(HPos::Center, VPos::Top));
            root.draw(&Text::new("P undefined", ((sx) as i32, (sy + 10.0) as i32), st))
                .map_err(de)?;
        }
    }
    // Scale bar, bottom left, and a note on the layout.
    draw_scale_and_note(root, (left, top, side), comps.len(), scale_p, geometry, grey)?;
    Ok(())
}

/// The compass at `c`: north up, east left.
fn draw_compass(root: &Area, c: (i32, i32), grey: RGBColor) -> io::Result<()> {
    for ((dx, dy), name) in [((0, -26), "N"), ((-26, 0), "E")] {
        let tip = (c.0 + dx, c.1 + dy);
        root.draw(&PathElement::new(vec![c, tip], grey.stroke_width(2)))
            .map_err(de)?;
        let lp = (c.0 + dx * 3 / 2 - if dx != 0 { 2 } else { 0 }, c.1 + dy * 3 / 2);
        root.draw(&Text::new(
            name,
            lp,
            (FONT, 13)
                .into_font()
                .color(&grey)
                .pos(Pos::new(HPos::Center, VPos::Center)),
        ))
        .map_err(de)?;
    }
    Ok(())
}

/// The P scale bar (bottom left) and the note on the wedge and B's position (bottom right)
/// of the square panel `(left, top, side)`.
fn draw_scale_and_note(
    root: &Area,
    (left, top, side): (i32, i32, i32),
    ncomp: usize,
    scale_p: f64,
    geometry: Option<(f64, f64)>,
    grey: RGBColor,
) -> io::Result<()> {
    let bar = (if ncomp == 1 { 0.7 } else { 0.38 } * side as f64 * 0.5).round() as i32;
    let by = top + side - 18;
    let bx = left + 14;
    root.draw(&PathElement::new(vec![(bx, by), (bx + bar, by)], BLACK.stroke_width(3)))
        .map_err(de)?;
    let st = (FONT, 13)
        .into_font()
        .color(&BLACK)
        .pos(Pos::new(HPos::Left, VPos::Center));
    root.draw(&Text::new(
        format!("P = {} %", crate::plots::tick(50.0 * scale_p)),
        (bx + bar + 8, by),
        st,
    ))
    .map_err(de)?;
    let st = (FONT, 12)
        .into_font()
        .color(&grey)
        .pos(Pos::new(HPos::Right, VPos::Bottom));
    let note = match (ncomp, geometry) {
        (1, _) => "wedge: ±σγ".to_string(),
        (_, Some((sep, pa))) => format!("B at ρ = {sep:.2}″, PA {pa:.1}° (not to scale); wedge ±σγ"),
        (_, None) => "B position unknown; wedge ±σγ".to_string(),
    };
    root.draw(&Text::new(note, (left + side - 6, top + side - 34), st))
        .map_err(de)?;
    Ok(())
}
