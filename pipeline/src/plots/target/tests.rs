//! The target figure's numbers and pixels on a synthetic binary: the model of F with the
//! telescope's term, and Delta-gamma with its error and interval.
use super::*;
use crate::calibration::FilterCalibration;
use crate::catalog::polarimetric_calibration::TelescopeCalibration;
use crate::catalog::{CombinedF, Component, InstrumentalOffset};
use crate::reduce::BeamFlux;
use crate::stokes::calibration::{AngleCalibration, Offset};
use crate::stokes::inversion::{Debias, LinearPolarization};

/// Rotator angles of the two orientations, deg.
const POSANG: [f64; 2] = [0.0, 45.0];
/// The parallactic angle of each orientation's frames, deg: far apart, so the telescope's
/// term has opposite signs at the two orientations.
const ETA_DEG: [f64; 2] = [-20.0, 70.0];
/// The telescope's (a, b): p_tel = 0.6 %.
const TEL_AB: [f64; 2] = [0.0, 0.006];
/// The calibration's zero-point (parity +1) and offset.
const THETA0: f64 = 3.0;
const C: f64 = 0.015;

fn calibration(telescope: bool) -> FilterCalibration {
    FilterCalibration {
        filter: "Ks".into(),
        offset: Some(Offset { c: C, sigma_c: 3e-4 }),
        offset_standards: vec![],
        angles: Some(AngleCalibration {
            theta0_deg: THETA0,
            sigma_theta0_deg: 0.5,
            parity: 1,
            parity_measured: false,
            n_standards: 2,
        }),
        angle_standards: vec![],
        cov_c_theta0_deg: None,
        incomplete: None,
        telescope: telescope.then_some(TelescopeCalibration {
            p_tel: 0.006,
            sigma_p_tel: 5e-4,
            psi_tel_deg: 45.0,
            sigma_psi_tel_deg: 2.0,
            a: TEL_AB[0],
            b: TEL_AB[1],
        }),
        telescope_uncorrected: None,
        telescope_from_prior: None,
        covariance: None,
        covariance_parameters: None,
        zero_point_from_profile: None,
    }
}

/// The telescope's term at analyzer angle `phi` for frames at parallactic angle `eta`,
/// written out here from docs/calibration.md.
fn t_of(phi_deg: f64, eta_deg: f64) -> f64 {
    let (c, s) = ((2.0 * eta_deg).to_radians().cos(), (2.0 * eta_deg).to_radians().sin());
    let (c2, s2) = ((2.0 * phi_deg).to_radians().cos(), (2.0 * phi_deg).to_radians().sin());
    TEL_AB[0] * (c * c2 + s * s2) + TEL_AB[1] * (c * s2 - s * c2)
}

fn component(name: &str, q: f64, u: f64, telescope_removed: bool) -> Component {
    let lp = LinearPolarization::from_qu(q, u, 5e-4, 5e-4, Debias::WardleKronberg);
    let mut c = Component::new(name, lp.pol);
    c.passes_cut = true;
    c.instrumental_offset = Some(InstrumentalOffset {
        c: C,
        sigma_c: 3e-4,
        source: "calibration".into(),
    });
    c.orientations = Some(
        POSANG
            .iter()
            .zip(ETA_DEG)
            .map(|(&pa, eta)| CombinedF {
                analyzer_deg: pa, // the profile's relation: phi = POSANG
                chi2: 1.0,
                f: 0.0,
                n_dithers: 3,
                n_dithers_total: 3,
                parallactic_2eta: Some([(2.0 * eta).to_radians().cos(), (2.0 * eta).to_radians().sin()]),
                parallactic_deg: Some(eta),
                posang_deg: None,
                sigma_f: 3e-4,
                sigma_f_propagated: 3e-4,
                sigma_f_scatter: 3e-4,
            })
            .collect(),
    );
    c.telescope_qu = telescope_removed.then_some([0.001, 0.002]);
    c
}

fn target() -> Target {
    let mut t = Target::new("Synthetic Tau", Status::Ok);
    t.components = vec![component("A", 0.004, 0.002, true), component("B", -0.003, -0.006, true)];
    t.delta_gamma_deg = Some(12.6);
    t.sigma_delta_gamma_deg = Some(0.43);
    t.delta_gamma_interval_deg = Some([12.17, 13.04]);
    t
}

/// Three dithers per orientation and component whose F span -3 % ... +3 %: the panel's
/// range is set by them, the same with and without the telescope's term.
fn inputs() -> FigureInputs {
    let dither = |f: f64| DitherValue {
        f,
        sigma_f: 1e-3,
        o: BeamFlux::missing(),
        e: BeamFlux::missing(),
        rejected: None,
    };
    let per_orientation = || vec![dither(-0.03), dither(0.0), dither(0.03)];
    FigureInputs {
        orientations: POSANG
            .iter()
            .map(|&pa| OrientationSketch {
                posang_deg: pa,
                analyzer_deg: pa,
                n_frames: 3,
                tiles: [None, None],
            })
            .collect(),
        measured: Some(Measured {
            eo_offset_px: (0.0, 120.0),
            fwhm_px: 2.9,
            frame_fwhm_px: Vec::new(),
            geometry: Some((3.0, 40.0)),
            photometry: "aperture".into(),
            aperture_px: 2.9,
            dithers: vec![vec![per_orientation(), per_orientation()]; 2],
            flags: vec![],
            field: Vec::new(),
        }),
    }
}

#[test]
fn the_model_of_f_holds_the_telescopes_term_of_each_orientation() {
    let (t, inputs) = (target(), inputs());
    let cal = calibration(true);
    let with = TargetFigure {
        target: &t,
        inputs: &inputs,
        calibration: Some(&cal),
    }
    .numbers();
    let cal0 = calibration(false);
    let without = TargetFigure {
        target: &t,
        inputs: &inputs,
        calibration: Some(&cal0),
    }
    .numbers();
    for (n, (cw, c0)) in with.components.iter().zip(&without.components).enumerate() {
        let comp = &t.components[n];
        for k in 0..2 {
            let phi = POSANG[k] + THETA0;
            let t2 = (2.0 * phi).to_radians();
            let plain = comp.q * t2.cos() + comp.u * t2.sin() + C;
            let tk = t_of(phi, ETA_DEG[k]);
            assert!(tk.abs() > 0.003, "T = {tk} too small to test");
            assert!((c0.model_f[k] - plain).abs() < 1e-15, "{} {k}", comp.name);
            assert_eq!(c0.telescope_f[k], None);
            assert!((cw.telescope_f[k].unwrap() - tk).abs() < 1e-15, "{} {k}", comp.name);
            assert!((cw.model_f[k] - (plain + tk)).abs() < 1e-15, "{} {k}", comp.name);
        }
    }
    // T has opposite signs at the two orientations: no single curve of phi draws it.
    assert!(t_of(POSANG[0] + THETA0, ETA_DEG[0]) * t_of(POSANG[1] + THETA0, ETA_DEG[1]) < 0.0);
    // A component the solve did not correct (no parallactic angle...) keeps the model
    // without T: its q and u still hold the telescope's polarization.
    let mut t2 = target();
    t2.components[1].telescope_qu = None;
    let n = TargetFigure {
        target: &t2,
        inputs: &inputs,
        calibration: Some(&cal),
    }
    .numbers();
    assert!(n.components[0].telescope_f.iter().all(Option::is_some));
    assert!(n.components[1].telescope_f.iter().all(Option::is_none));
}

/// The row of the panel `(x0, y0, w, h)` holding the most pixels of colour `rgb` (within 4
/// per channel), and how many it holds.
fn line_row(img: &(u32, u32, Vec<u8>), (x0, y0, w, h): (u32, u32, u32, u32), rgb: [u8; 3]) -> (u32, usize) {
    let (width, _, px) = img;
    (y0..y0 + h)
        .map(|y| {
            let n = (x0..x0 + w)
                .filter(|&x| {
                    let i = 3 * (y * width + x) as usize;
                    (0..3).all(|c| (px[i + c] as i32 - rgb[c] as i32).abs() <= 4)
                })
                .count();
            (y, n)
        })
        .max_by_key(|&(y, n)| (n, std::cmp::Reverse(y)))
        .unwrap()
}

/// With `SOFIPOL_PLOT_EXAMPLES=DIR`, keep the figure as `DIR/name` to look at.
fn keep_example(name: &str, (w, h, rgb): &(u32, u32, Vec<u8>)) {
    if let Ok(dir) = std::env::var("SOFIPOL_PLOT_EXAMPLES") {
        std::fs::create_dir_all(&dir).unwrap();
        image::save_buffer(
            std::path::Path::new(&dir).join(name),
            rgb,
            *w,
            *h,
            image::ColorType::Rgb8,
        )
        .unwrap();
    }
}

/// `col` drawn with opacity `a` on white.
fn on_white(col: RGBColor, a: f64) -> [u8; 3] {
    let m = |v: u8| (v as f64 * a + 255.0 * (1.0 - a)).round() as u8;
    [m(col.0), m(col.1), m(col.2)]
}

#[test]
fn the_model_line_moves_by_the_telescopes_term_at_each_orientation() {
    let (t, inputs) = (target(), inputs());
    let render = |cal: &FilterCalibration| {
        TargetFigure {
            target: &t,
            inputs: &inputs,
            calibration: Some(cal),
        }
        .rgb()
        .unwrap()
    };
    let plain = render(&calibration(false));
    let with_t = render(&calibration(true));
    keep_example("telescope_term_none.png", &plain);
    keep_example("telescope_term.png", &with_t);
    // (The text band below differs: its legend says what is drawn.)
    assert_eq!(plain.0, with_t.0);
    let dashed = on_white(comp_color(0, false), MODEL_MIX);
    let dotted = on_white(comp_color(0, false), MODEL_NO_T_MIX);
    for k in 0..2u32 {
        // Orientation k's F panel (draw_cell's place), left of the axis labels excluded.
        let x0 = (k % 2) * CELL_W + 8 + 60;
        let y0 = TITLE_H + (k / 2) * CELL_H + CELL_LABEL_H + TILE + 6;
        let panel = (x0, y0, 2 * TILE + TILE_GAP - 70, F_H - 34);
        let (r0, n0) = line_row(&plain, panel, dashed);
        assert!(n0 > 80, "orientation {k}: no model line ({n0} px at row {r0})");
        let (_, none) = line_row(&plain, panel, dotted);
        assert!(
            none < 20,
            "orientation {k}: a line without T drawn without a telescope term"
        );
        let (r1, n1) = line_row(&with_t, panel, dashed);
        assert!(n1 > 80, "orientation {k}: no model line with T ({n1} px)");
        let (r2, n2) = line_row(&with_t, panel, dotted);
        assert!(n2 > 40, "orientation {k}: no line without T ({n2} px)");
        // The line without T is where the model was; the model moved by T, up (F larger)
        // where T > 0 and down where T < 0: about 22 px per percent of F here.
        assert!(
            r2.abs_diff(r0) <= 1,
            "orientation {k}: without T at {r2}, model was at {r0}"
        );
        let tk = t_of(POSANG[k as usize] + THETA0, ETA_DEG[k as usize]);
        let moved = r0 as f64 - r1 as f64;
        assert!(
            moved.signum() == tk.signum() && moved.abs() >= 5.0,
            "orientation {k}: T = {:.3} %, the line moved {moved} px",
            100.0 * tk
        );
    }
}

#[test]
fn the_text_gives_delta_gamma_with_its_error_and_its_interval() {
    let (t, inputs) = (target(), inputs());
    let nums = TargetFigure {
        target: &t,
        inputs: &inputs,
        calibration: None,
    }
    .numbers();
    let mut lines = Vec::new();
    component_lines(&nums, &mut lines);
    let text: Vec<&str> = lines.iter().map(|l| l.text.as_str()).collect();
    assert!(text.contains(&"Δγ = |γA − γB| = 12.6 ± 0.4°"), "{text:?}");
    assert!(text.contains(&"      68 % interval of Δγ: [12.2°, 13.0°]"), "{text:?}");
    // Without an error or interval in the catalog: Delta-gamma alone, no made-up numbers.
    let mut bare = nums.clone();
    bare.sigma_delta_gamma_deg = None;
    bare.delta_gamma_interval_deg = None;
    let mut lines = Vec::new();
    delta_gamma_lines(&bare, &mut lines);
    assert_eq!(lines.len(), 1);
    assert_eq!(lines[0].text, "Δγ = |γA − γB| = 12.6°");
    // And the figure draws them: it differs from one without them.
    let (_, _, a) = TargetFigure {
        target: &t,
        inputs: &inputs,
        calibration: None,
    }
    .rgb()
    .unwrap();
    let mut t0 = t.clone();
    t0.sigma_delta_gamma_deg = None;
    t0.delta_gamma_interval_deg = None;
    let (_, _, b) = TargetFigure {
        target: &t0,
        inputs: &inputs,
        calibration: None,
    }
    .rgb()
    .unwrap();
    assert_ne!(a, b);
}

/// The cut-out window equals the point-by-point bilinear sample at every pixel (to float
/// rounding of the weights), on a frame with masked (bad, cosmic, off-strip) and NaN pixels,
/// at fractional and whole-pixel origins and across every edge.
#[test]
fn a_window_is_the_bilinear_sample_at_every_pixel() {
    use sofipol_calib::frame::mask as mbits;
    let (ny, nx) = (23usize, 31usize);
    let data = ndarray::Array2::from_shape_fn((ny, nx), |(j, i)| (j * 37 + i * 11) as f32 * 0.5 - 40.0);
    let mut f = sofipol_calib::Frame::new(data, sofipol_calib::Header::new(""));
    f.mask[[5, 7]] = mbits::BAD;
    f.mask[[12, 20]] = mbits::COSMIC;
    f.mask[[0, 3]] = mbits::OFF_STRIP;
    f.mask[[9, 9]] = mbits::SATURATED; // not a reason to leave a pixel out
    f.data[[17, 2]] = f32::NAN;
    for origin in [(-3.25, -2.5), (4.0, 6.0), (20.6, 14.3), (0.0, 0.75), (-8.0, 10.5)] {
        let n = 15;
        let w = tiles::window(&f, origin, n);
        for j in 0..n {
            for i in 0..n {
                let want = tiles::sample(&f, origin.0 + i as f64, origin.1 + j as f64);
                let got = w[j * n + i];
                match want {
                    None => assert!(got.is_nan(), "{origin:?} ({i}, {j}): {got}, want nothing"),
                    Some(v) => assert!(
                        (got - v).abs() <= 1e-5 * v.abs().max(1.0),
                        "{origin:?} ({i}, {j}): {got}, want {v}"
                    ),
                }
            }
        }
    }
}
