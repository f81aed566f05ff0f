//! Structural keywords (BITPIX, NAXISn, ZIMAGE, BSCALE...) read straight from an HDU's raw
//! cards, for the image checks (`read.rs`) and the plain reads (`raw.rs`).
use crate::header::HeaderValue;

use super::cards::{parse_card, Parsed};

/// The value of a structural keyword straight from the raw cards. Cards whose name field
/// cannot give `key` are skipped without parsing them (this runs a dozen times per file
/// read): the same answer as parsing every card.
pub(super) fn raw_value(cards: &[String], key: &str) -> Option<HeaderValue> {
    cards
        .iter()
        .filter(|c| may_define(c, key))
        .find_map(|c| match parse_card(c) {
            Parsed::Key { key: k, value, .. } if k == key => Some(value),
            _ => None,
        })
}

/// Whether [`parse_card`] could return `key` for this card: its 8-character name field (as
/// parse_card reads it: non-ASCII as '?', upper case, trailing blanks dropped) is `key`, or
/// the card is a HIERARCH card whose key (the text between the name field and '=', trimmed,
/// upper case) is `key`. ASCII cards are judged on their bytes (a SOFI header is mostly
/// HIERARCH cards, looked up a dozen times per file); others as parse_card reads them.
fn may_define(card: &str, key: &str) -> bool {
    let b = card.as_bytes();
    let head = &b[..b.len().min(8)];
    if !head.is_ascii() {
        return may_define_chars(card, key);
    }
    // Blanks as `char::is_whitespace` has them among ASCII characters.
    let blank = |c: &u8| matches!(c, b' ' | b'\t' | b'\n' | 0x0b | 0x0c | b'\r');
    let trimmed = |s: &[u8]| -> std::ops::Range<usize> {
        let start = s.iter().position(|c| !blank(c)).unwrap_or(s.len());
        let end = s.iter().rposition(|c| !blank(c)).map_or(start, |i| i + 1);
        start..end
    };
    let upper_is =
        |s: &[u8], k: &[u8]| s.len() == k.len() && s.iter().zip(k).all(|(c, k)| c.to_ascii_uppercase() == *k);
    let name = &head[..head.iter().rposition(|c| !blank(c)).map_or(0, |i| i + 1)];
    if upper_is(name, key.as_bytes()) {
        return true;
    }
    if !upper_is(name, b"HIERARCH") || b.get(8) != Some(&b' ') {
        // Only a HIERARCH card (name field and a blank) takes its key from further on.
        return false;
    }
    let Some(eq) = b.iter().position(|&c| c == b'=') else {
        return false; // commentary
    };
    if !b[..eq].is_ascii() {
        return true; // parse_card decides
    }
    // normalize_key: "HIERARCH " dropped, then trimmed (a blank key is "HIERARCH" itself,
    // matched above).
    let rest = &b[9..eq]; // eq > 8: b[8] is a blank
    upper_is(&rest[trimmed(rest)], key.as_bytes())
}

/// [`may_define`] of any card, char by char as [`parse_card`] reads it.
fn may_define_chars(card: &str, key: &str) -> bool {
    let mut name = [b' '; 8];
    for (slot, c) in name.iter_mut().zip(card.chars()) {
        *slot = if c.is_ascii() {
            c.to_ascii_uppercase() as u8
        } else {
            b'?'
        };
    }
    let len = name
        .iter()
        .rposition(|&b| !(b as char).is_whitespace())
        .map_or(0, |i| i + 1);
    let name = &name[..len];
    name == key.as_bytes() || name == b"HIERARCH"
}

/// The integer value of a structural keyword straight from the raw cards.
pub(super) fn raw_int(cards: &[String], key: &str) -> Option<i64> {
    match raw_value(cards, key)? {
        HeaderValue::Int(i) => Some(i),
        _ => None,
    }
}

/// Whether the cards are those of a tile-compressed image (ZIMAGE = T).
pub(super) fn is_compressed(cards: &[String]) -> bool {
    matches!(raw_value(cards, "ZIMAGE"), Some(HeaderValue::Bool(true)))
}
