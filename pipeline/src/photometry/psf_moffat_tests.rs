//! Moffat PSF fits on synthetic stars rendered independently of [`super::moffat`] (16 x 16
//! sub-pixels per pixel, each integrated with a 2 x 2 Gauss-Legendre rule, i.e. 32 x 32 nodes
//! per pixel, written out here): recovery of single stars and close pairs, flux errors against
//! Monte Carlo scatter, deblending by `subtract_star`, the polarimetric o/e ratio of a blended
//! pair, and timing.

use super::*;
use ndarray::Array2;

fn rel_err(a: f64, b: f64) -> f64 {
    if a == b {
        0.0
    } else {
        (a - b).abs() / a.abs().max(b.abs())
    }
}

/// alpha of a Moffat of FWHM `fwhm` (written out, not taken from the module under test).
fn alpha_of(fwhm: f64, beta: f64) -> f64 {
    fwhm / (2.0 * (2f64.powf(1.0 / beta) - 1.0).sqrt())
}

/// `sky + sum_k F_k * (pixel integral of the unit Moffat at (x_k, y_k))`, f64, indexed [y, x].
/// Each pixel is split into 16 x 16 sub-pixels integrated with 2 x 2 Gauss-Legendre nodes.
fn render(nx: usize, ny: usize, stars: &[(f64, f64, f64)], alpha: f64, beta: f64, sky: f64) -> Array2<f64> {
    const SUB: usize = 16;
    let g = 0.5 / 3f64.sqrt(); // GL2 node on [-1/2, 1/2]
    let mut offs = Vec::with_capacity(2 * SUB);
    for i in 0..SUB {
        let c = -0.5 + (i as f64 + 0.5) / SUB as f64;
        offs.push(c - g / SUB as f64);
        offs.push(c + g / SUB as f64);
    }
    let w = 1.0 / (offs.len() * offs.len()) as f64;
    let norm = (beta - 1.0) / (std::f64::consts::PI * alpha * alpha);
    Array2::from_shape_fn((ny, nx), |(iy, ix)| {
        let mut v = sky;
        for &(f, x, y) in stars {
            let mut s = 0.0;
            for &a in &offs {
                let dx = ix as f64 + a - x;
                for &b in &offs {
                    let dy = iy as f64 + b - y;
                    s += (1.0 + (dx * dx + dy * dy) / (alpha * alpha)).powf(-beta);
                }
            }
            v += f * norm * w * s;
        }
        v
    })
}

struct Rng(u64);
impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

fn moffat_params(fwhm: f64, fit_radius: f64, background: Option<f64>) -> PsfFitParams {
    PsfFitParams {
        fwhm_px: fwhm,
        fit_radius_px: fit_radius,
        background,
        model: PsfModel::Moffat { beta: None },
        ..PsfFitParams::default()
    }
}

/// Single noiseless stars: flux, position, alpha and beta to 1e-4 (relative; position in px),
/// with the background fixed and fitted.
#[test]
fn photometry_moffat_fit_recovers_single_star() {
    let mut worst = [0.0f64; 4];
    for &(fwhm, beta, sky) in &[
        (2.8, 3.0, 0.0),
        (2.2, 2.5, 0.0),
        (3.6, 4.0, 0.0),
        (2.8, 3.0, 20.0),
        (4.0, 2.5, 15.0),
    ] {
        let alpha = alpha_of(fwhm, beta);
        let (f, x, y) = (5.0e4, 20.37, 19.71);
        let img = render(41, 41, &[(f, x, y)], alpha, beta, sky).mapv(|v| v as f32);
        let bkg = if sky == 0.0 { Some(0.0) } else { None };
        let params = moffat_params(1.25 * fwhm, 4.0 * fwhm, bkg);
        let fit = fit_psf(img.view(), None, None, &[(x - 0.4, y + 0.3)], &params).expect("fit");
        let s = fit.stars[0];
        let errs = [
            rel_err(s.flux, f),
            (s.x - x).hypot(s.y - y),
            rel_err(fit.alpha, alpha),
            rel_err(fit.beta, beta),
        ];
        eprintln!(
            "Moffat single star FWHM {fwhm} beta {beta} sky {sky}: flux {:.1e} pos {:.1e} px alpha {:.1e} beta {:.1e}, {} iterations",
            errs[0], errs[1], errs[2], errs[3], fit.iterations
        );
        assert!(fit.converged && errs.iter().all(|&e| e < 1e-4), "{errs:?} {fit:?}");
        assert!(rel_err(fit.fwhm(), fwhm) < 1e-4 && fit.fwhm_x() == fit.fwhm());
        if sky != 0.0 {
            assert!((fit.background - sky).abs() < 1e-3, "{}", fit.background);
        }
        for (w, e) in worst.iter_mut().zip(errs) {
            *w = w.max(e);
        }
    }
    eprintln!(
        "Moffat single star: worst flux {:.1e}, pos {:.1e} px, alpha {:.1e}, beta {:.1e}",
        worst[0], worst[1], worst[2], worst[3]
    );
}

/// Noiseless pairs 1.0-2.0 FWHM apart, flux ratios 1 to 0.25, beta fitted: fluxes to 1e-3
/// (in practice far better).
#[test]
fn photometry_moffat_fit_recovers_close_pairs() {
    let (fwhm, beta) = (2.8, 3.0);
    let alpha = alpha_of(fwhm, beta);
    let mut worst = 0.0f64;
    for &sep_fwhm in &[1.0, 1.25, 1.5, 2.0] {
        for &ratio in &[1.0, 0.5, 0.25] {
            let pa: f64 = 0.7 + sep_fwhm;
            let (xa, ya) = (15.3, 14.8);
            let (xb, yb) = (xa + sep_fwhm * fwhm * pa.cos(), ya + sep_fwhm * fwhm * pa.sin());
            let (fa, fb) = (8.0e4, 8.0e4 * ratio);
            let img = render(31, 31, &[(fa, xa, ya), (fb, xb, yb)], alpha, beta, 0.0).mapv(|v| v as f32);
            let params = moffat_params(fwhm * 1.15, 2.0 * fwhm, Some(0.0));
            let fit = fit_two_psf(
                img.view(),
                None,
                None,
                (xa + 0.3, ya - 0.4),
                (xb - 0.4, yb + 0.3),
                &params,
            )
            .expect("fit");
            let (a, b) = (fit.stars[0], fit.stars[1]);
            let e = rel_err(a.flux, fa).max(rel_err(b.flux, fb));
            let ep = (a.x - xa).hypot(a.y - ya).max((b.x - xb).hypot(b.y - yb));
            eprintln!(
                "Moffat pair {sep_fwhm} FWHM ratio {ratio}: flux rel err {e:.1e}, pos {ep:.1e} px, beta {:.5}, {} iterations",
                fit.beta, fit.iterations
            );
            assert!(
                fit.converged && e < 1e-3 && ep < 1e-3,
                "sep {sep_fwhm} ratio {ratio}: {fit:?}"
            );
            worst = worst.max(e);
        }
    }
    eprintln!("Moffat pairs 1-2 FWHM: worst flux error {worst:.1e}");
}

/// With Gaussian noise and a variance map, the flux errors from the covariance match the
/// scatter of 200 realisations (within 15%), and the fluxes are unbiased.
#[test]
fn photometry_moffat_flux_errors_match_scatter() {
    let (fwhm, beta) = (2.8, 3.0);
    let alpha = alpha_of(fwhm, beta);
    let (fa, fb) = (6.0e4, 2.5e4);
    let (xa, ya, xb, yb) = (15.2, 15.4, 18.9, 16.9); // 4.0 px = 1.43 FWHM
    let truth = render(31, 31, &[(fa, xa, ya), (fb, xb, yb)], alpha, beta, 0.0);
    let var = truth.mapv(|v| (v.max(0.0) + 400.0) as f32); // gain 1, read noise 20 ADU
    let params = moffat_params(fwhm, 1.5 * fwhm, Some(0.0));
    let mut rng = Rng(11);
    let n = 200;
    let (mut da, mut db, mut ea, mut eb, mut fs) = (Vec::new(), Vec::new(), 0.0, 0.0, Vec::new());
    for _ in 0..n {
        let img = Array2::from_shape_fn(truth.raw_dim(), |(j, i)| {
            (truth[[j, i]] + (var[[j, i]] as f64).sqrt() * rng.normal()) as f32
        });
        let fit = fit_two_psf(
            img.view(),
            Some(var.view()),
            None,
            (xa + 0.2, ya - 0.2),
            (xb - 0.3, yb + 0.2),
            &params,
        )
        .expect("fit");
        assert!(fit.converged);
        da.push(fit.stars[0].flux - fa);
        db.push(fit.stars[1].flux - fb);
        ea += fit.stars[0].flux_err / n as f64;
        eb += fit.stars[1].flux_err / n as f64;
        fs.push(fit.beta);
    }
    let stats = |d: &[f64]| {
        let m = d.iter().sum::<f64>() / d.len() as f64;
        (
            m,
            (d.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (d.len() - 1) as f64).sqrt(),
        )
    };
    let ((ma, sa), (mb, sb), (mbeta, sbeta)) = (stats(&da), stats(&db), stats(&fs));
    eprintln!(
        "Moffat pair, {n} noisy realisations: A scatter {sa:.1} predicted {ea:.1} (ratio {:.3}, bias {ma:.1}); B scatter {sb:.1} predicted {eb:.1} (ratio {:.3}, bias {mb:.1}); beta {mbeta:.3} +- {sbeta:.3}",
        sa / ea,
        sb / eb
    );
    assert!((sa / ea - 1.0).abs() < 0.15 && (sb / eb - 1.0).abs() < 0.15);
    // Unbiased to 4 sigma of the mean (a maximum-likelihood bias this size would be ~ sigma^2/F).
    assert!(
        ma.abs() < 4.0 * sa / (n as f64).sqrt() && mb.abs() < 4.0 * sb / (n as f64).sqrt(),
        "bias {ma} {mb}"
    );
}

/// Deblending a pair 2-3 FWHM apart (the aperture regime): after `subtract_star` of the
/// companion, the primary's aperture (radius 1 FWHM) holds the primary's light to < 1e-3 of
/// the companion's flux.
#[test]
fn photometry_moffat_subtract_star_removes_companion_wings() {
    let (fwhm, beta) = (2.8, 3.0);
    let alpha = alpha_of(fwhm, beta);
    for &(sep_fwhm, ratio) in &[(2.0, 1.0), (2.5, 0.3), (3.0, 3.0)] {
        let (xa, ya) = (20.4, 19.7);
        let (xb, yb) = (xa + sep_fwhm * fwhm * 0.8, ya - sep_fwhm * fwhm * 0.6);
        let (fa, fb) = (5.0e4, 5.0e4 * ratio);
        let img = render(41, 41, &[(fa, xa, ya), (fb, xb, yb)], alpha, beta, 0.0).mapv(|v| v as f32);
        let alone = render(41, 41, &[(fa, xa, ya)], alpha, beta, 0.0).mapv(|v| v as f32);
        let params = moffat_params(fwhm, 1.5 * fwhm, Some(0.0));
        let fit = fit_two_psf(
            img.view(),
            None,
            None,
            (xa + 0.3, ya + 0.2),
            (xb - 0.2, yb - 0.3),
            &params,
        )
        .expect("fit");
        let clean = subtract_star(img.view(), &fit, 1);
        let ap = Aperture { x: xa, y: ya, r: fwhm };
        let got = aperture_sum(clean.view(), None, None, &ap, Method::Exact, MaskFill::Exclude).sum;
        let want = aperture_sum(alone.view(), None, None, &ap, Method::Exact, MaskFill::Exclude).sum;
        let before = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude).sum;
        eprintln!(
            "Moffat deblend {sep_fwhm} FWHM, B/A {ratio}: companion light in A's aperture {:.1e} of F_B before, residual {:.1e} after",
            (before - want) / fb,
            (got - want).abs() / fb
        );
        assert!((got - want).abs() < 1e-3 * fb, "sep {sep_fwhm}: {got} vs {want}");
        // A Gaussian fit leaves the companion's wings (the problem this model solves).
        let gfit = fit_two_psf(
            img.view(),
            None,
            None,
            (xa + 0.3, ya + 0.2),
            (xb - 0.2, yb - 0.3),
            &PsfFitParams {
                model: PsfModel::Gaussian,
                ..params
            },
        )
        .expect("gaussian fit");
        let gclean = subtract_star(img.view(), &gfit, 1);
        let g = aperture_sum(gclean.view(), None, None, &ap, Method::Exact, MaskFill::Exclude).sum;
        eprintln!("    (Gaussian model instead: residual {:.1e})", (g - want).abs() / fb);
    }
}

/// The polarimetric use case: the same blended pair in the o and e beams with different
/// component ratios. F = (o - e)/(o + e) from Moffat-fitted fluxes matches the truth to 1e-4
/// (noiseless); the Gaussian model's bias is printed for comparison.
#[test]
fn photometry_moffat_oe_ratio_of_blended_pair_is_unbiased() {
    let (fwhm, beta) = (2.8, 3.0);
    let alpha = alpha_of(fwhm, beta);
    let (fa, fb) = (8.0e4, 3.0e4);
    let (ka, kb) = ((1.05, 0.95), (0.97, 1.03));
    let truth_f = [(ka.0 - ka.1) / (ka.0 + ka.1), (kb.0 - kb.1) / (kb.0 + kb.1)];
    let mut worst = 0.0f64;
    for &sep_fwhm in &[0.8, 1.0, 1.5, 2.0] {
        let (xa, ya) = (15.4, 15.1);
        let (xb, yb) = (xa + sep_fwhm * fwhm * 0.6, ya + sep_fwhm * fwhm * 0.8);
        let o = render(31, 31, &[(fa * ka.0, xa, ya), (fb * kb.0, xb, yb)], alpha, beta, 0.0).mapv(|v| v as f32);
        let e = render(31, 31, &[(fa * ka.1, xa, ya), (fb * kb.1, xb, yb)], alpha, beta, 0.0).mapv(|v| v as f32);
        let mut dev = [[0.0; 2]; 2];
        for (mi, model) in [PsfModel::Moffat { beta: None }, PsfModel::Gaussian]
            .into_iter()
            .enumerate()
        {
            let params = PsfFitParams {
                model,
                ..moffat_params(fwhm, 1.5 * fwhm, Some(0.0))
            };
            let fo = fit_two_psf(o.view(), None, None, (xa, ya), (xb, yb), &params).expect("fit o");
            let fe = fit_two_psf(e.view(), None, None, (xa, ya), (xb, yb), &params).expect("fit e");
            for k in 0..2 {
                let (so, se) = (fo.stars[k].flux, fe.stars[k].flux);
                dev[mi][k] = (so - se) / (so + se) - truth_f[k];
            }
        }
        eprintln!(
            "o/e of a blended pair at {sep_fwhm} FWHM: F error Moffat fit {:.1e} {:.1e}, Gaussian fit {:.1e} {:.1e}",
            dev[0][0], dev[0][1], dev[1][0], dev[1][1]
        );
        worst = worst.max(dev[0][0].abs()).max(dev[0][1].abs());
    }
    assert!(worst < 1e-4, "{worst}");
}

/// Fixed beta, parameter layout, settings checks, and the TOML form of the model.
#[test]
fn photometry_moffat_fixed_beta_and_settings() {
    let (fwhm, beta) = (3.0, 3.5);
    let alpha = alpha_of(fwhm, beta);
    let img = render(31, 31, &[(4.0e4, 14.6, 15.3), (1.0e4, 18.0, 16.0)], alpha, beta, 7.0).mapv(|v| v as f32);
    let params = PsfFitParams {
        model: PsfModel::Moffat { beta: Some(beta) },
        fwhm_px: 2.5,
        fit_radius_px: 7.0,
        ..PsfFitParams::default()
    };
    let fit = fit_two_psf(img.view(), None, None, (14.8, 15.0), (17.6, 16.3), &params).unwrap();
    assert_eq!(
        fit.param_names,
        ["flux_0", "x_0", "y_0", "flux_1", "x_1", "y_1", "alpha", "background"]
    );
    assert_eq!(fit.beta, beta);
    assert!(
        rel_err(fit.alpha, alpha) < 1e-5 && rel_err(fit.stars[1].flux, 1.0e4) < 1e-4,
        "{fit:?}"
    );
    // model_value and render_star agree with each other and with the fit's model.
    let mut one = Array2::<f32>::zeros((31, 31));
    fit.render_star(1, &mut one.view_mut(), 1.0);
    assert!((one[[16, 18]] as f64 - fit.model_value(1, 18.0, 16.0)).abs() < 1e-2);
    let fitted = moffat_params(2.5, 7.0, None);
    let free = fit_two_psf(img.view(), None, None, (14.8, 15.0), (17.6, 16.3), &fitted).unwrap();
    assert_eq!(free.param_names[6..], ["alpha", "beta", "background"]);
    assert_eq!(free.covariance.len(), 9);
    // An elliptical Moffat fits (e1, e2) after beta (a circular star: e about 0); beta
    // must be > 1.
    let ell = PsfFitParams {
        elliptical: true,
        ..fitted
    };
    let fe = fit_two_psf(img.view(), None, None, (14.8, 15.0), (17.6, 16.3), &ell).unwrap();
    assert_eq!(fe.param_names[6..], ["alpha", "beta", "e1", "e2", "background"]);
    assert!(
        fe.ellipticity[0].hypot(fe.ellipticity[1]) < 1e-4,
        "{:?}",
        fe.ellipticity
    );
    let bad = PsfFitParams {
        model: PsfModel::Moffat { beta: Some(1.0) },
        ..fitted
    };
    assert!(matches!(
        fit_psf(img.view(), None, None, &[(14.8, 15.0)], &bad),
        Err(PsfFitError::InvalidParams { .. })
    ));
    // TOML.
    #[derive(serde::Deserialize, serde::Serialize, Debug, PartialEq)]
    struct W {
        m: PsfModel,
    }
    for (text, m) in [
        ("m = { kind = \"gaussian\" }", PsfModel::Gaussian),
        ("m = { kind = \"moffat\" }", PsfModel::Moffat { beta: None }),
        (
            "m = { kind = \"moffat\", beta = 2.5 }",
            PsfModel::Moffat { beta: Some(2.5) },
        ),
    ] {
        let w: W = toml::from_str(text).unwrap();
        assert_eq!(w.m, m);
        assert_eq!(toml::from_str::<W>(&toml::to_string(&w).unwrap()).unwrap(), w);
    }
    assert_eq!(PsfFitParams::default().model, PsfModel::Gaussian);
}

/// A two-star Moffat fit with free beta on a 31 x 31 cut-out like the reduction's (fit
/// radius 1.5 and 2 FWHM, variance map, noise) converges in few iterations and recovers
/// both fluxes and beta within their errors. (Its cost is printed by `sofipol bench`.)
#[test]
fn photometry_moffat_two_star_fit_converges_on_noisy_cutouts() {
    let (fwhm, beta) = (2.8, 3.0);
    let alpha = alpha_of(fwhm, beta);
    let truth = render(31, 31, &[(9.0e4, 15.2, 15.4), (4.0e4, 18.5, 17.9)], alpha, beta, 0.0);
    let var = truth.mapv(|v| (v.max(0.0) + 400.0) as f32);
    let mut rng = Rng(3);
    let imgs: Vec<Array2<f32>> = (0..8)
        .map(|_| {
            Array2::from_shape_fn(truth.raw_dim(), |(j, i)| {
                (truth[[j, i]] + (var[[j, i]] as f64).sqrt() * rng.normal()) as f32
            })
        })
        .collect();
    for (radius, label) in [(1.5 * fwhm, "1.5 FWHM"), (2.0 * fwhm, "2 FWHM")] {
        let params = moffat_params(fwhm * 1.1, radius, Some(0.0));
        let mut iters = Vec::new();
        for img in &imgs {
            let fit = fit_two_psf(img.view(), Some(var.view()), None, (15.0, 15.6), (18.2, 18.3), &params).unwrap();
            assert!(fit.converged, "{label}");
            for (s, want) in fit.stars.iter().zip([9.0e4, 4.0e4]) {
                assert!(
                    (s.flux - want).abs() < 5.0 * s.flux_err,
                    "{label}: {} +- {} vs {want}",
                    s.flux,
                    s.flux_err
                );
            }
            assert!((fit.beta - beta).abs() < 0.5, "{label}: beta {}", fit.beta);
            iters.push(fit.iterations);
        }
        iters.sort();
        assert!(iters[iters.len() / 2] <= 30, "{label}: iterations {iters:?}");
    }
}

/// `subtract_star_near` equals `subtract_star` bit for bit inside its window and leaves the
/// input alone outside, for both models, stars inside, at the edge of and outside the window.
#[test]
fn photometry_subtract_star_near_is_exact_inside_its_window() {
    use super::{subtract_star, subtract_star_near};
    let mut img = Array2::<f32>::zeros((61, 67));
    for (i, v) in img.iter_mut().enumerate() {
        *v = 100.0 + (i % 17) as f32 * 0.37;
    }
    // A Gaussian, a circular and an elliptical Moffat.
    for (model, ellipticity) in [
        (PsfModel::Gaussian, [0.0; 2]),
        (PsfModel::Moffat { beta: None }, [0.0; 2]),
        (PsfModel::Moffat { beta: None }, [0.12, -0.2]),
    ] {
        for &(x, y) in &[(30.37, 29.81), (3.2, 58.6), (65.9, 0.4), (12.123_456_789, 40.5)] {
            let fit = PsfFit {
                stars: vec![PsfStar {
                    flux: 5e4,
                    x,
                    y,
                    flux_err: 0.0,
                    x_err: 0.0,
                    y_err: 0.0,
                }],
                model,
                sigma_x: 1.3,
                sigma_y: 1.1,
                alpha: 2.6,
                beta: 2.9,
                ellipticity,
                background: 0.0,
                covariance: vec![],
                param_names: vec![],
                chi2: 0.0,
                dof: 0,
                n_pixels: 0,
                iterations: 0,
                converged: true,
            };
            let full = subtract_star(img.view(), &fit, 0);
            for &(c, r) in &[((30.0, 30.0), 12.5), ((10.0, 45.0), 7.0), ((60.0, 5.0), 30.0)] {
                let near = subtract_star_near(img.view(), &fit, 0, c, r);
                let mut changed = 0;
                for ((iy, ix), &v) in near.indexed_iter() {
                    let (fx, fy) = (ix as f64, iy as f64);
                    let inside = fx >= (c.0 - r).floor()
                        && fx <= (c.0 + r).ceil()
                        && fy >= (c.1 - r).floor()
                        && fy <= (c.1 + r).ceil();
                    if inside {
                        assert_eq!(
                            v.to_bits(),
                            full[[iy, ix]].to_bits(),
                            "{model:?} star ({x},{y}) pixel ({ix},{iy})"
                        );
                        changed += (v != img[[iy, ix]]) as usize;
                    } else {
                        assert_eq!(
                            v.to_bits(),
                            img[[iy, ix]].to_bits(),
                            "{model:?} star ({x},{y}) window {c:?} {r}: outside ({ix},{iy})"
                        );
                    }
                }
                // (the Gaussian is rendered within 10 sigma only: nothing to see far away)
                if matches!(model, PsfModel::Moffat { .. }) {
                    assert!(changed > 0, "star ({x},{y}) window {c:?} {r}: nothing subtracted");
                }
                // With a pixel filter (a ring about the window's centre): the kept pixels as
                // above, a Moffat leaves the others alone.
                let keep = |ix: usize, iy: usize| ((ix as f64 - c.0).hypot(iy as f64 - c.1) - 0.6 * r).abs() < 3.0;
                let mut part = img.clone();
                super::subtract_star_near_where(&mut part, &fit, 0, c, r, keep);
                for ((iy, ix), &v) in part.indexed_iter() {
                    let skipped = !keep(ix, iy) && matches!(model, PsfModel::Moffat { .. });
                    let expect = if skipped { img[[iy, ix]] } else { near[[iy, ix]] };
                    assert_eq!(v.to_bits(), expect.to_bits(), "{model:?} filtered ({ix},{iy})");
                }
            }
        }
    }
}
