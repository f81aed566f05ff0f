//! Header cards as raw 80-character records: parsing (HIERARCH, CONTINUE long strings,
//! typed values, HISTORY records) and formatting (shortest exact floats, comments that fit).
use std::path::Path;

use crate::error::{Error, Result};
use crate::frame::HistoryRecord;
use crate::header::{normalize_key, Card, Header, HeaderValue};

use super::{HISTORY_CHUNK, HISTORY_CONTINUATION};

/// One parsed 80-character card.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Parsed {
    /// `KEY = value / comment` (HIERARCH prefix removed from the key).
    Key {
        key: String,
        value: HeaderValue,
        comment: Option<String>,
    },
    /// A keyword with an empty (undefined) value.
    Undefined,
    /// `HISTORY text`.
    History(String),
    /// `CONTINUE  'text'` of a long string.
    Continue { text: String, comment: Option<String> },
    /// COMMENT, blank and anything else without a value.
    Commentary,
}

/// Keywords that describe the file layout rather than the data.
pub(super) fn is_structural(key: &str) -> bool {
    const EXACT: &[&str] = &[
        "SIMPLE", "BITPIX", "NAXIS", "EXTEND", "BZERO", "BSCALE", "BLANK", "PCOUNT", "GCOUNT", "XTENSION", "EXTNAME",
        "EXTVER", "EXTLEVEL", "INHERIT", "TFIELDS", "THEAP", "CHECKSUM", "DATASUM", "BLOCKED", "END", "LONGSTRN",
        "ZIMAGE", "ZBITPIX", "ZNAXIS", "ZCMPTYPE", "ZQUANTIZ", "ZDITHER0", "ZSIMPLE", "ZEXTEND", "ZBLOCKED",
        "ZTENSION", "ZPCOUNT", "ZGCOUNT", "ZHECKSUM", "ZDATASUM", "ZMASKCMP", "ZSCALE", "ZZERO", "ZBLANK", "ZTHEAP",
    ];
    const NUMBERED: &[&str] = &[
        "NAXIS", "ZNAXIS", "ZTILE", "ZNAME", "ZVAL", "TTYPE", "TFORM", "TUNIT", "TDIM", "TSCAL", "TZERO", "TNULL",
        "TDISP",
    ];
    EXACT.contains(&key)
        || NUMBERED.iter().any(|p| {
            key.strip_prefix(p)
                .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
        })
}

/// Parse a quoted FITS string starting at `s[0] == '\''`: (value, rest after the quote).
/// `''` is an escaped quote; trailing blanks of the value are not significant.
pub(super) fn parse_quoted(s: &str) -> (String, &str) {
    let b = s.as_bytes();
    let mut out = String::new();
    let mut i = 1;
    while i < b.len() {
        if b[i] == b'\'' {
            if b.get(i + 1) == Some(&b'\'') {
                out.push('\'');
                i += 2;
                continue;
            }
            return (out.trim_end().to_string(), &s[i + 1..]);
        }
        out.push(b[i] as char);
        i += 1;
    }
    // Unterminated string: take what there is.
    (out.trim_end().to_string(), "")
}

pub(super) fn parse_comment(rest: &str) -> Option<String> {
    let c = rest.trim_start().strip_prefix('/')?.trim();
    (!c.is_empty()).then(|| c.to_string())
}

/// Parse the value field (everything after `=`).
pub(super) fn parse_value(field: &str) -> (Option<HeaderValue>, Option<String>) {
    let t = field.trim_start();
    if t.starts_with('\'') {
        let (s, rest) = parse_quoted(t);
        return (Some(HeaderValue::Str(s)), parse_comment(rest));
    }
    let (v, comment) = match t.find('/') {
        Some(i) => (t[..i].trim(), parse_comment(&t[i..])),
        None => (t.trim(), None),
    };
    if v.is_empty() {
        return (None, comment);
    }
    let value = match v {
        "T" => HeaderValue::Bool(true),
        "F" => HeaderValue::Bool(false),
        _ => {
            let digits = v.strip_prefix(['+', '-']).unwrap_or(v);
            let numeric = !digits.is_empty() && v.bytes().all(|b| b"0123456789+-.EeDd".contains(&b));
            if numeric && digits.bytes().all(|b| b.is_ascii_digit()) {
                match v.parse::<i64>() {
                    Ok(i) => HeaderValue::Int(i),
                    Err(_) => v
                        .parse::<f64>()
                        .map(HeaderValue::Float)
                        .unwrap_or_else(|_| HeaderValue::Str(v.into())),
                }
            } else if numeric {
                match v.replace(['D', 'd'], "E").parse::<f64>() {
                    Ok(x) => HeaderValue::Float(x),
                    Err(_) => HeaderValue::Str(v.to_string()),
                }
            } else {
                // Complex numbers and other oddities: keep the text.
                HeaderValue::Str(v.to_string())
            }
        }
    };
    (Some(value), comment)
}

pub(super) fn parse_card(raw: &str) -> Parsed {
    // Cards are ASCII by the standard; make any stray byte harmless for slicing.
    let card: String = raw.chars().map(|c| if c.is_ascii() { c } else { '?' }).collect();
    let name8 = card.get(..8).unwrap_or(&card).trim_end().to_ascii_uppercase();
    if name8 == "HISTORY" {
        return Parsed::History(card.get(8..).unwrap_or("").trim_end().to_string());
    }
    if name8 == "CONTINUE" {
        let t = card.get(8..).unwrap_or("").trim_start();
        if t.starts_with('\'') {
            let (text, rest) = parse_quoted(t);
            return Parsed::Continue {
                text,
                comment: parse_comment(rest),
            };
        }
        return Parsed::Commentary;
    }
    if name8 == "HIERARCH" && card.as_bytes().get(8) == Some(&b' ') {
        return match card.find('=') {
            Some(eq) => {
                let key = normalize_key(&card[..eq]);
                match parse_value(&card[eq + 1..]) {
                    (Some(value), comment) if !key.is_empty() => Parsed::Key { key, value, comment },
                    _ => Parsed::Undefined,
                }
            }
            None => Parsed::Commentary,
        };
    }
    if name8.is_empty() || name8 == "COMMENT" || card.as_bytes().get(8) != Some(&b'=') {
        return Parsed::Commentary;
    }
    match parse_value(&card[9..]) {
        (Some(value), comment) => Parsed::Key {
            key: name8,
            value,
            comment,
        },
        _ => Parsed::Undefined,
    }
}

/// Turn HISTORY texts into provenance records (see [`read_frame`]).
pub(super) fn history_record(text: &str, records: &mut Vec<HistoryRecord>, continuing: &mut bool) {
    if let Some(rest) = text.strip_prefix(HISTORY_CONTINUATION) {
        if *continuing {
            if let Some(last) = records.last_mut() {
                last.detail.push_str(rest);
                return;
            }
        }
    }
    *continuing = false;
    if let Some(rest) = text.strip_prefix("sofipol ") {
        if let Some((stage, detail)) = rest.split_once(':') {
            if !stage.is_empty() && !stage.contains(' ') {
                let detail = detail.strip_prefix(' ').unwrap_or(detail);
                records.push(HistoryRecord::new(stage, detail));
                *continuing = true;
                return;
            }
        }
    }
    records.push(HistoryRecord::new("file", text));
}

/// Header (structural keys, COMMENT and HISTORY removed) and history records.
pub(super) fn parse_cards(cards: &[String], path: &Path) -> (Header, Vec<HistoryRecord>) {
    let mut header = Header::new(path);
    let mut history = Vec::new();
    let mut continuing = false;
    // Index of the card a CONTINUE card extends, when its string ended in '&'.
    let mut open_string: Option<usize> = None;
    for raw in cards {
        let parsed = parse_card(raw);
        if !matches!(parsed, Parsed::Continue { .. }) {
            open_string = None;
        }
        match parsed {
            Parsed::Key { key, value, comment } => {
                if is_structural(&key) || header.cards.iter().any(|c| c.key == key) {
                    continue;
                }
                if let HeaderValue::Str(s) = &value {
                    if s.ends_with('&') {
                        open_string = Some(header.cards.len());
                    }
                }
                header.cards.push(Card { key, value, comment });
            }
            Parsed::Continue { text, comment } => {
                if let Some(i) = open_string {
                    let card = &mut header.cards[i];
                    if let HeaderValue::Str(s) = &mut card.value {
                        s.pop(); // the '&'
                        s.push_str(&text);
                        if !text.ends_with('&') {
                            open_string = None;
                        }
                    }
                    if comment.is_some() {
                        card.comment = comment;
                    }
                }
            }
            Parsed::History(text) => history_record(&text, &mut history, &mut continuing),
            Parsed::Undefined | Parsed::Commentary => {}
        }
    }
    (header, history)
}

// ---------------------------------------------------------------------------------------
// Header cards: formatting

pub(super) const CARD: usize = 80;

pub(super) fn is_standard_key(key: &str) -> bool {
    !key.is_empty()
        && key.len() <= 8
        && key
            .bytes()
            .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'-' || b == b'_')
}

pub(super) fn ascii_sanitize(s: &str) -> String {
    s.chars()
        .map(|c| if (' '..='~').contains(&c) { c } else { '?' })
        .collect()
}

/// A float in FITS syntax with the shortest digits that read back bit-exactly.
pub(super) fn format_f64(x: f64) -> Option<String> {
    if !x.is_finite() {
        return None;
    }
    // Rust's Debug output is the shortest round-trip representation, with ".0" for
    // integral values and an exponent for very small or large magnitudes.
    let s = format!("{x:?}");
    Some(match s.split_once('e') {
        Some((m, e)) => {
            let m = if m.contains('.') {
                m.to_string()
            } else {
                format!("{m}.0")
            };
            format!("{m}E{e}")
        }
        None => s,
    })
}

pub(super) fn bad_key(path: &Path, card: &Card, reason: &str) -> Error {
    Error::BadKeyword {
        path: path.to_path_buf(),
        keyword: card.key.clone(),
        value: card.value.to_string(),
        reason: reason.to_string(),
    }
}

/// Append ` / comment` when it fits (comments are informational: cut to fit).
pub(super) fn with_comment(mut card: String, comment: Option<&str>) -> String {
    if let Some(c) = comment {
        let c = ascii_sanitize(c.trim());
        if !c.is_empty() && card.len() + 4 < CARD {
            card.push_str(" / ");
            let room = CARD - card.len();
            card.push_str(&c[..c.len().min(room)]);
        }
    }
    card
}

pub(super) fn format_card(card: &Card, path: &Path) -> Result<Vec<String>> {
    let key = normalize_key(&card.key);
    if key.is_empty() || key.contains('=') || !key.chars().all(|c| (' '..='~').contains(&c)) {
        return Err(bad_key(path, card, "keyword names must be printable ASCII without '='"));
    }
    let prefix = if is_standard_key(&key) {
        format!("{key:<8}= ")
    } else {
        format!("HIERARCH {key} = ")
    };
    let comment = card.comment.as_deref();
    let too_long = || bad_key(path, card, "keyword name too long for an 80-character card");
    match &card.value {
        HeaderValue::Str(s) => {
            if !s.chars().all(|c| (' '..='~').contains(&c)) {
                return Err(bad_key(path, card, "FITS strings must be printable ASCII"));
            }
            // Escaped pieces, one per character, so that '' is never split.
            let pieces: Vec<String> = s
                .chars()
                .map(|c| if c == '\'' { "''".into() } else { c.to_string() })
                .collect();
            let escaped: String = pieces.concat();
            if prefix.len() + escaped.len().max(8) + 2 <= CARD {
                let padded = if escaped.len() < 8 {
                    format!("{escaped:<8}")
                } else {
                    escaped
                };
                return Ok(vec![with_comment(format!("{prefix}'{padded}'"), comment)]);
            }
            // Long string: CONTINUE convention; every card but the last ends in '&'.
            let mut out = Vec::new();
            let mut lead = prefix.clone();
            let mut it = pieces.iter().peekable();
            while it.peek().is_some() {
                let room = CARD
                    .checked_sub(lead.len() + 3)
                    .filter(|&r| r > 1)
                    .ok_or_else(too_long)?;
                let mut chunk = String::new();
                while let Some(p) = it.peek() {
                    if chunk.len() + p.len() > room {
                        break;
                    }
                    chunk.push_str(p);
                    it.next();
                }
                if it.peek().is_some() {
                    out.push(format!("{lead}'{chunk}&'"));
                } else {
                    let last = format!("{lead}'{chunk}'");
                    let comment_len = comment.map_or(0, |c| c.trim().len());
                    if comment_len > 0 && last.len() + 3 + comment_len > CARD {
                        // No room for the comment: give it a card of its own.
                        out.push(format!("{lead}'{chunk}&'"));
                        out.push(with_comment("CONTINUE  ''".to_string(), comment));
                    } else {
                        out.push(with_comment(last, comment));
                    }
                }
                lead = "CONTINUE  ".to_string();
            }
            Ok(out)
        }
        v => {
            let text = match v {
                HeaderValue::Bool(b) => (if *b { "T" } else { "F" }).to_string(),
                HeaderValue::Int(i) => i.to_string(),
                HeaderValue::Float(x) => {
                    format_f64(*x).ok_or_else(|| bad_key(path, card, "FITS cannot store a non-finite number"))?
                }
                HeaderValue::Str(_) => unreachable!(),
            };
            // Fixed format (value right-justified in column 30) for standard keys.
            let line = if prefix.len() == 10 && text.len() <= 20 {
                format!("{prefix}{text:>20}")
            } else {
                format!("{prefix}{text}")
            };
            if line.len() > CARD {
                return Err(too_long());
            }
            Ok(vec![with_comment(line, comment)])
        }
    }
}

/// Commentary card(s) for a COMMENT or HISTORY text, at most 72 characters each.
pub(super) fn commentary(name: &str, text: &str) -> Vec<String> {
    let text = ascii_sanitize(text);
    if text.is_empty() {
        return vec![name.to_string()];
    }
    text.as_bytes()
        .chunks(72)
        .map(|c| format!("{name:<8}{}", String::from_utf8_lossy(c)))
        .collect()
}

/// All cards of a header, in order (structural keywords skipped).
pub(super) fn format_header(header: &Header, path: &Path) -> Result<Vec<String>> {
    let mut out = Vec::with_capacity(header.cards.len() + 8);
    for card in &header.cards {
        let key = normalize_key(&card.key);
        if is_structural(&key) {
            continue;
        }
        if key == "COMMENT" || key == "HISTORY" {
            let text = match &card.value {
                HeaderValue::Str(s) => s.clone(),
                v => v.to_string(),
            };
            out.extend(commentary(&key, &text));
            continue;
        }
        out.extend(format_card(card, path)?);
    }
    Ok(out)
}

/// Split a history line into pieces of at most [`HISTORY_CHUNK`] characters. cfitsio
/// drops trailing blanks of a card, so a piece never ends in a blank when avoidable.
pub(super) fn split_history(line: &str) -> Vec<String> {
    let line = ascii_sanitize(line);
    let mut out = Vec::new();
    let mut rest: &str = &line;
    let mut first = true;
    loop {
        let room = if first {
            HISTORY_CHUNK
        } else {
            HISTORY_CHUNK - HISTORY_CONTINUATION.len()
        };
        if rest.len() <= room {
            out.push(rest.to_string());
            break;
        }
        let mut cut = room;
        while cut > 0 && rest.as_bytes()[cut - 1] == b' ' {
            cut -= 1;
        }
        if cut == 0 {
            cut = room;
        }
        out.push(rest[..cut].to_string());
        rest = &rest[cut..];
        first = false;
    }
    out.into_iter()
        .enumerate()
        .map(|(i, piece)| {
            if i == 0 {
                piece
            } else {
                format!("{HISTORY_CONTINUATION}{piece}")
            }
        })
        .collect()
}

pub(super) fn format_history(history: &[HistoryRecord]) -> Vec<String> {
    history
        .iter()
        .flat_map(|r| split_history(&r.line()))
        .map(|t| format!("HISTORY {t}"))
        .collect()
}
