//! Text from files (header values, file names) shown on a terminal or in a log: every
//! character that is not printable is escaped, so that a header cannot move the cursor,
//! clear the screen, retitle the terminal or forge a log line (an OBJECT holding ESC,
//! CR or LF). JSON outputs keep the value (JSON escapes it itself).
use std::borrow::Cow;

/// Whether `c` is shown as an escape: control characters (C0, DEL, C1: ESC, CR, LF, BEL,
/// TAB...), the Unicode line and paragraph separators and the bidirectional-text
/// controls (which reorder what follows them on the line).
fn hidden(c: char) -> bool {
    c.is_control()
        || matches!(c, '\u{2028}' | '\u{2029}' | '\u{200e}' | '\u{200f}' | '\u{061c}')
        || ('\u{202a}'..='\u{202e}').contains(&c)
        || ('\u{2066}'..='\u{2069}').contains(&c)
}

fn escape_into(out: &mut String, c: char) {
    match c {
        '\n' => out.push_str("\\n"),
        '\r' => out.push_str("\\r"),
        '\t' => out.push_str("\\t"),
        c if (c as u32) < 0x100 => out.push_str(&format!("\\x{:02x}", c as u32)),
        c => out.push_str(&format!("\\u{{{:x}}}", c as u32)),
    }
}

/// `s` as one line of printable text: every character of `hidden` kind (newlines
/// included) written as an escape (`\x1b`, `\n`, `\r`, `\u{202e}`). The string itself
/// when there is nothing to escape. Use it wherever a value read from a file (OBJECT,
/// FILTER, a file name) reaches stdout or stderr.
pub fn printable(s: &str) -> Cow<'_, str> {
    escape(s, false)
}

/// [`printable`] keeping the line breaks (`\n`) and tabs of text that sofipol laid out in
/// lines itself; every other hidden character is escaped (the last line of defence of the
/// command-line printing).
pub fn printable_lines(s: &str) -> Cow<'_, str> {
    escape(s, true)
}

fn escape(s: &str, keep_lines: bool) -> Cow<'_, str> {
    let keep = |c: char| keep_lines && (c == '\n' || c == '\t');
    if !s.chars().any(|c| hidden(c) && !keep(c)) {
        return Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        if hidden(c) && !keep(c) {
            escape_into(&mut out, c);
        } else {
            out.push(c);
        }
    }
    Cow::Owned(out)
}

/// A number for a message: as Rust writes it when that is short (`80.2`, `0.0088`),
/// else in scientific notation with at most 6 significant digits (`1e300`, `1.23457e-9`),
/// so that `1e300` is never printed with 300 digits.
pub fn short_number(x: f64) -> String {
    let plain = format!("{x}");
    if plain.len() <= 16 {
        return plain;
    }
    let e = format!("{x:.5e}");
    // Trailing zeros of the mantissa dropped: 1.00000e300 -> 1e300.
    match e.split_once('e') {
        Some((m, exp)) if m.contains('.') => {
            let m = m.trim_end_matches('0').trim_end_matches('.');
            format!("{m}e{exp}")
        }
        _ => e,
    }
}

/// `s` cut to at most `max` characters for a message, with how much was left out
/// (`…(1048576 characters)`), and made [`printable`]: a value of a megabyte or with
/// newlines is never echoed whole.
pub fn short_text(s: &str, max: usize) -> String {
    let n = s.chars().count();
    if n <= max {
        return printable(s).into_owned();
    }
    let head: String = s.chars().take(max).collect();
    format!("{}…({n} characters)", printable(&head))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_numbers_stay_short() {
        assert_eq!(short_number(80.2), "80.2");
        assert_eq!(short_number(-0.0088), "-0.0088");
        assert_eq!(short_number(1e300), "1e300");
        assert_eq!(short_number(-1.234567891e-9), "-1.23457e-9");
        assert_eq!(short_number(f64::NAN), "NaN");
        assert!(short_number(f64::MAX).len() <= 16, "{}", short_number(f64::MAX));
    }

    #[test]
    fn long_text_is_cut_and_made_printable() {
        assert_eq!(short_text("HK Tau", 10), "HK Tau");
        let big = "x".repeat(1 << 20);
        let t = short_text(&big, 40);
        assert!(t.len() < 80 && t.ends_with("(1048576 characters)"), "{t}");
        assert_eq!(short_text("a\nb", 10), "a\\nb");
    }

    #[test]
    fn control_and_bidi_characters_are_escaped_and_plain_text_is_untouched() {
        let evil = "\u{1b}[2J\r\n[2/2] X ok\u{1b}]0;t\u{7}\u{9b}\u{202e}gpj";
        let p = printable(evil);
        assert_eq!(p, "\\x1b[2J\\r\\n[2/2] X ok\\x1b]0;t\\x07\\x9b\\u{202e}gpj");
        assert!(!p.chars().any(hidden), "{p}");
        // The escaped text is one line.
        assert_eq!(p.lines().count(), 1);
        assert!(matches!(printable("Alpha Cen B, Ks 2.2µm"), Cow::Borrowed(_)));
        assert_eq!(printable("a\tb"), "a\\tb");
        // Lines laid out by sofipol keep their breaks; everything else is escaped.
        assert_eq!(printable_lines("a\n\u{1b}[1mb\tc\r"), "a\n\\x1b[1mb\tc\\r");
        assert!(matches!(printable_lines("x\ny\n"), Cow::Borrowed(_)));
    }
}
