//! The line an observer reads when a template has been reduced: P/sigma of each component
//! and, for one below the cut, how many more cycles of the same template would reach it.
use crate::catalog::{Component, FlagCode, Status, Target};
use sofipol_calib::text::printable;

/// Most cycles worth naming: beyond, the line says the polarization is too small to reach.
const MAX_CYCLES: f64 = 50.0;

/// Cycles of the same template (this one included) for P / sigma_P to reach `cut`, from the
/// measured debiased P and sigma_P: the error falls as 1/sqrt(cycles), so
/// `n = (cut sigma_P / P)^2`, rounded up. `None` when P is consistent with zero (debiased
/// to 0) or the numbers are not finite: no exposure can be predicted.
pub fn cycles_needed(p_debiased: f64, sigma_p: f64, cut: f64) -> Option<u32> {
    if !(p_debiased > 0.0) || !(sigma_p > 0.0) || !cut.is_finite() {
        return None;
    }
    let n = (cut * sigma_p / p_debiased).powi(2);
    n.is_finite().then(|| n.ceil().max(1.0) as u32)
}

/// Why a component whose P/sigma is above the cut fails it: the flag that refuses it
/// (`uncalibrated` first: its numbers still change with the calibration), else its first flag.
fn cut_reason(c: &Component) -> String {
    let refusing = [
        FlagCode::Uncalibrated,
        FlagCode::PAboveOne,
        FlagCode::UsedFlaggedDithers,
        FlagCode::AbIdentityUnverified,
        FlagCode::StokesMethodFailed,
    ];
    refusing
        .iter()
        .find_map(|&code| c.flags.iter().find(|f| f.is(code)))
        .or(c.flags.first())
        .map(|f| printable(&f.to_string()).into_owned())
        .unwrap_or_default()
}

/// One component: `A P/sig 5.2 ok`, `B P/sig 1.9: ~2 more cycles`, ...
fn component_words(c: &Component, cut: f64) -> String {
    let snr = c.sigma_p.is_finite().then(|| c.p / c.sigma_p).filter(|s| s.is_finite());
    let Some(snr) = snr else {
        return format!("{} P/sig -", printable(&c.name));
    };
    let head = format!(
        "{} P {:.2}+-{:.2} % gamma {:.0} deg P/sig {snr:.1}",
        printable(&c.name),
        100.0 * c.p,
        100.0 * c.sigma_p,
        c.gamma_deg
    );
    if c.passes_cut {
        return format!("{head} ok");
    }
    match cycles_needed(c.p_debiased, c.sigma_p, cut) {
        Some(n) if (n as f64) <= MAX_CYCLES && n > 1 => format!("{head}: {} more cycle(s) for P/sig > {cut}", n - 1),
        Some(1) => format!("{head}: below the cut ({})", cut_reason(c)),
        Some(_) => format!("{head}: more than {MAX_CYCLES} cycles for P/sig > {cut}"),
        // Debiased to 0: not detected. The measured P is the most it is likely to be, so
        // its cycles are the fewest that could reach the cut; a true P below it needs more.
        None => match cycles_needed(c.p, c.sigma_p, cut) {
            Some(n) if (n as f64) <= MAX_CYCLES && n > 1 => format!(
                "{head}: not detected; if P is the {:.2} % measured, at least {} more cycle(s) for P/sig > {cut}",
                100.0 * c.p,
                n - 1
            ),
            _ => format!("{head}: not detected; more than {MAX_CYCLES} cycles even at the measured P"),
        },
    }
}

/// Delta-gamma and its error at the precision the error allows: `13+-2`, `13.4+-0.6`.
fn delta_gamma_words(d: f64, e: f64) -> String {
    if e < 1.0 {
        format!("dgamma {d:.1}+-{e:.1} deg")
    } else {
        format!("dgamma {d:.0}+-{e:.0} deg")
    }
}

/// The observer's line for a reduced target: object, status, each component.
pub fn target_line(t: &Target, cut: f64) -> String {
    let status = match t.status {
        Status::Ok => "ok",
        Status::Partial => "partial",
        Status::Failed => "FAILED",
    };
    let mut s = format!("{} {status}", printable(&t.object));
    if let Some(e) = &t.error {
        s += &format!(": {}", printable(e));
    }
    for c in &t.components {
        s += " | ";
        s += &component_words(c, cut);
    }
    if let (Some(d), Some(e)) = (t.delta_gamma_deg, t.sigma_delta_gamma_deg) {
        s += &format!(" | {}", delta_gamma_words(d, e));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::catalog::Flag;
    use crate::stokes::inversion::{Debias, LinearPolarization};

    /// A bright star not yet calibrated (no standard reduced before it) says so, whatever
    /// flag its photometry put first: its P/sig still changes with the calibration.
    #[test]
    fn an_uncalibrated_star_above_the_cut_says_it_is_uncalibrated() {
        let lp = LinearPolarization::from_qu(0.05, 0.02, 2.3e-4, 2.3e-4, Debias::WardleKronberg);
        let mut c = Component::new("A", lp.pol);
        c.flags = vec![
            Flag::with_detail(FlagCode::BadPixels, "1 of 10 dithers dropped"),
            Flag::new(FlagCode::TelescopeUncorrected),
            Flag::new(FlagCode::Uncalibrated),
        ];
        let words = component_words(&c, 3.0);
        assert!(words.ends_with("P/sig 234.1: below the cut (uncalibrated)"), "{words}");
        // Otherwise the first flag, as before.
        c.flags.retain(|f| !f.is(FlagCode::Uncalibrated));
        let words = component_words(&c, 3.0);
        assert!(words.contains("below the cut (bad_pixels"), "{words}");
    }

    /// A 1 % star measured at 0.56 +- 0.56 % (debiased to 0) is not "never": at the measured
    /// P it needs (3 x 0.56 / 0.56)^2 = 9 cycles, 8 more; Delta-gamma's error below 1 deg is
    /// not printed as 0.
    #[test]
    fn an_undetected_star_gets_the_cycles_of_its_measured_p_and_small_errors_show() {
        let lp = LinearPolarization::from_qu(0.0056, 0.0, 0.0056, 0.0056, Debias::WardleKronberg);
        assert_eq!(lp.pol.p_debiased, 0.0);
        let c = Component::new("B", lp.pol);
        let words = component_words(&c, 3.0);
        assert!(
            words.ends_with("not detected; if P is the 0.56 % measured, at least 8 more cycle(s) for P/sig > 3"),
            "{words}"
        );
        let tiny = Component::new(
            "B",
            LinearPolarization::from_qu(1e-5, 0.0, 0.0056, 0.0056, Debias::WardleKronberg).pol,
        );
        assert!(component_words(&tiny, 3.0).ends_with("more than 50 cycles even at the measured P"));
        assert_eq!(delta_gamma_words(13.04, 0.41), "dgamma 13.0+-0.4 deg");
        assert_eq!(delta_gamma_words(13.4, 2.2), "dgamma 13+-2 deg");
    }

    /// The prediction against noise draws: with sigma_1 the error of one cycle, n cycles
    /// average to sigma_1/sqrt(n); at the predicted n the mean P/sigma is >= the cut and at
    /// n - 1 below it (for the true P).
    #[test]
    fn cycles_bring_the_error_down_as_one_over_the_square_root() {
        let (p, s1, cut) = (0.012, 0.007, 3.0);
        let n = cycles_needed(p, s1, cut).unwrap();
        assert_eq!(n, 4); // (3 * 0.007 / 0.012)^2 = 3.06
        let snr = |k: u32| p / (s1 / (k as f64).sqrt());
        assert!(snr(n) > cut && snr(n - 1) < cut, "{} {}", snr(n), snr(n - 1));
        assert_eq!(cycles_needed(0.05, 0.01, 3.0), Some(1));
        assert_eq!(cycles_needed(0.0, 0.01, 3.0), None);
        assert_eq!(cycles_needed(f64::NAN, 0.01, 3.0), None);
        assert_eq!(cycles_needed(0.01, 0.0, 3.0), None);
    }
}
