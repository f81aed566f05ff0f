//! One module per subcommand. Each has `Args` (clap) and `run(Args) -> anyhow::Result<ExitCode>`.
pub mod bench;
pub mod calib;
pub mod common;
pub mod demo;
pub mod eta;
pub mod export;
pub mod mc;
pub mod merge;
pub mod night;
pub mod report;
pub mod setup;
pub mod simulate;
pub mod stats;
pub mod summary;
pub mod target;
pub mod watch;

/// An error and its causes in one line, `outer: cause: root`, leaving out a cause whose
/// words the message already holds (an I/O error that names its file is displayed with
/// its cause already: `{e:#}` would repeat it).
pub fn chain_text(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let c = cause.to_string();
        if out.is_empty() {
            out = c;
        } else if !out.contains(&c) {
            out.push_str(": ");
            out.push_str(&c);
        }
    }
    out
}

/// The longest line of an error message shown whole, characters.
const MAX_ERROR_LINE: usize = 400;
/// The most lines of an error message shown.
const MAX_ERROR_LINES: usize = 30;

/// An error message as the terminal shows it: control characters escaped (line breaks
/// kept: a TOML error points at its line), numbers of more than 20 digits written short
/// (`1e300`, not 301 digits), a line longer than [`MAX_ERROR_LINE`] cut in its middle with
/// how much was left out, at most [`MAX_ERROR_LINES`] lines. The start (the file, the key)
/// and the end (why) of every line stay.
pub fn error_text(msg: &str) -> String {
    let msg = sofipol_calib::text::printable_lines(msg);
    let lines: Vec<&str> = msg.lines().collect();
    let mut out: Vec<String> = lines
        .iter()
        .take(MAX_ERROR_LINES)
        .map(|l| elide_middle(&short_digit_runs(l), MAX_ERROR_LINE))
        .collect();
    if lines.len() > MAX_ERROR_LINES {
        out.push(format!("…({} more lines)", lines.len() - MAX_ERROR_LINES));
    }
    out.join("\n")
}

/// Runs of more than 20 digits (with their sign, decimal point and exponent) rewritten by
/// [`sofipol_calib::text::short_number`].
fn short_digit_runs(line: &str) -> String {
    let b = line.as_bytes();
    let mut out = String::with_capacity(line.len());
    let mut i = 0;
    while i < b.len() {
        if b[i].is_ascii_digit() && (i == 0 || !(b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'.')) {
            let mut j = i;
            while j < b.len() && (b[j].is_ascii_digit() || b[j] == b'.') {
                j += 1;
            }
            if j < b.len() && (b[j] == b'e' || b[j] == b'E') {
                let mut k = j + 1;
                if k < b.len() && (b[k] == b'-' || b[k] == b'+') {
                    k += 1;
                }
                if k < b.len() && b[k].is_ascii_digit() {
                    while k < b.len() && b[k].is_ascii_digit() {
                        k += 1;
                    }
                    j = k;
                }
            }
            let run = &line[i..j];
            let digits = run.bytes().filter(u8::is_ascii_digit).count();
            match run.parse::<f64>() {
                Ok(x) if digits > 20 => out.push_str(&sofipol_calib::text::short_number(x)),
                _ => out.push_str(run),
            }
            i = j;
        } else {
            let c = line[i..].chars().next().expect("inside the line");
            out.push(c);
            i += c.len_utf8();
        }
    }
    out
}

/// `line` cut in its middle to about `max` characters, saying how many were left out.
fn elide_middle(line: &str, max: usize) -> String {
    let n = line.chars().count();
    if n <= max {
        return line.to_string();
    }
    let head: String = line.chars().take(max / 2).collect();
    let tail: String = line.chars().skip(n - max / 2).collect();
    format!("{head}…({} characters left out)…{tail}", n - 2 * (max / 2))
}

#[cfg(test)]
mod tests {
    use super::error_text;

    #[test]
    fn a_cause_already_in_the_message_is_not_repeated() {
        let io = std::io::Error::new(std::io::ErrorKind::StorageFull, "No space left on device");
        let e = anyhow::Error::new(sofipol_calib::Error::Io {
            path: "/d/w.json".into(),
            source: io,
        })
        .context("writing the catalog");
        assert_eq!(
            super::chain_text(&e),
            "writing the catalog: /d/w.json: No space left on device"
        );
    }

    #[test]
    fn error_text_is_short_printable_and_keeps_both_ends() {
        let big = format!("1{}", "0".repeat(300));
        let e = error_text(&format!("f.json: key = {big}.0: must be below 1"));
        assert_eq!(e, "f.json: key = 1e300: must be below 1");
        let e = error_text(&format!("f.fits: OBJECT = '{}': too long", "x".repeat(1 << 20)));
        assert!(
            e.starts_with("f.fits: OBJECT = 'xxx") && e.ends_with("xx': too long"),
            "{}",
            &e[..80]
        );
        assert!(e.len() < 600 && e.contains("characters left out"), "{}", e.len());
        assert_eq!(error_text("a\u{1b}[2Jb\nTOML line"), "a\\x1b[2Jb\nTOML line");
        // Ordinary numbers are untouched: a frame name, a date, a float.
        let plain = "SOFI_0001.fits: MJD-OBS = 51240.041898148: 2026-11-29";
        assert_eq!(error_text(plain), plain);
        let many = "x\n".repeat(100);
        assert!(error_text(&many).ends_with("…(70 more lines)"));
    }
}
