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
        _ => format!("{head}: P consistent with 0, no number of cycles reaches P/sig > {cut}"),
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
        s += &format!(" | dgamma {d:.0}+-{e:.0} deg");
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
