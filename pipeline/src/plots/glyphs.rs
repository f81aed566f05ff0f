//! A bitmap backend whose text is drawn from rasterised glyphs kept per thread: plotters
//! rasterises every glyph's outline each time it draws it, which was the largest share of a
//! target figure's cost (a night draws the same few dozen glyphs some 100 000 times).
//!
//! [`CachedText`] holds the RGB buffer and passes every call to plotters' `BitMapBackend`
//! over it, except the text of the embedded font (family `FONT`, normal or bold,
//! unrotated): its layout ([`text_size`]: plotters' sums of advances and kerning) and its
//! drawing, which places each glyph's coverage exactly as plotters' ab_glyph font does
//! (the glyph rasterised at the origin, shifted by whole pixels: the truncated advance and
//! kerning, `size / 2 + top` down) and blends it into the buffer with plotters' integer
//! arithmetic, so the pixels are the same
//! (`tests::cached_text_draws_the_same_pixels_as_plotters`). Laying out through plotters
//! looked the font up in its shared registry for every text, and drawing through it cost a
//! call and a colour per pixel: together a fifth of a figure's drawing. One difference on purpose:
//! plotters' `FontDesc::style` keeps the face the font was made with, so text styled bold
//! that way was drawn in the regular face; here every text is drawn in the face its style
//! names (the figures' titles and labels are bold, as meant).
use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

use ab_glyph::{Font, FontRef, GlyphId, ScaleFont};
use plotters::prelude::*;
use plotters_backend::text_anchor::{HPos, VPos};
use plotters_backend::{
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind, FontStyle, FontTransform,
};

use super::FONT;

/// One glyph of one font at one size, rasterised at the origin.
struct Glyph {
    id: GlyphId,
    /// Its horizontal advance, px.
    advance: f32,
    /// Coverage of each pixel it covers (coverage > 0), relative to the top-left of its
    /// pixel bounds, with the blending weight of an opaque colour ([`weight`]).
    coverage: Vec<(i32, i32, f32, u16)>,
    /// The bounds' top-left corner as plotters places it: (0, `size / 2 + min.y`) truncated.
    y_shift: i32,
}

/// A multiply-and-rotate hasher for the caches' small keys (the standard SipHash cost more
/// than the lookups it served; no key here comes from outside the program).
#[derive(Default, Clone, Copy)]
struct KeyHasher(u64);

impl std::hash::Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }

    fn write_u32(&mut self, v: u32) {
        self.write_u64(u64::from(v));
    }

    fn write_u16(&mut self, v: u16) {
        self.write_u64(u64::from(v));
    }

    fn write_u8(&mut self, v: u8) {
        self.write_u64(u64::from(v));
    }

    fn write_usize(&mut self, v: usize) {
        self.write_u64(v as u64);
    }
}

type KeyMap<K, V> = HashMap<K, V, std::hash::BuildHasherDefault<KeyHasher>>;

/// Glyphs of the embedded fonts, per (bold, size bits, char).
type Cache = KeyMap<(bool, u64, char), Rc<Glyph>>;

/// Kerning of the embedded fonts, per (bold, size bits, left glyph, right glyph).
type Kerning = KeyMap<(bool, u64, u16, u16), f32>;

thread_local! {
    static GLYPHS: RefCell<Cache> = RefCell::new(Cache::default());
    static KERNING: RefCell<Kerning> = RefCell::new(Kerning::default());
}

/// The embedded font of a style (plotters falls back to the normal face for styles it has
/// no face for).
fn font(bold: bool) -> FontRef<'static> {
    let bytes = if bold {
        dejavu::sans::bold()
    } else {
        dejavu::sans::regular()
    };
    FontRef::try_from_slice(bytes).expect("the embedded DejaVu font parses")
}

fn rasterise(bold: bool, size: f64, c: char) -> Glyph {
    let f = font(bold);
    let scaled = f.as_scaled(size as f32);
    let id = scaled.glyph_id(c);
    let mut coverage = Vec::new();
    let mut y_shift = 0;
    if let Some(q) = scaled.outline_glyph(scaled.scaled_glyph(c)) {
        y_shift = ((size as f32) / 2.0 + q.px_bounds().min.y) as i32;
        // A pixel of zero coverage is left as it is: not kept.
        q.draw(|x, y, a| {
            if a > 0.0 {
                coverage.push((x as i32, y as i32, a, weight(f64::from(a))));
            }
        });
    }
    Glyph {
        id,
        advance: scaled.h_advance(id),
        coverage,
        y_shift,
    }
}

/// plotters' blending weight of opacity `alpha`, in 256ths: 256 (opaque) from 255/256 up,
/// 0 at 0 or below, else floor(alpha * 256) (truncation of a positive value).
#[inline]
fn weight(alpha: f64) -> u16 {
    if alpha >= 1.0 - 1.0 / 256.0 {
        256
    } else if alpha > 0.0 {
        (alpha * 256.0) as u16
    } else {
        0
    }
}

/// The kerning between two glyphs of a font at a size (looked up in the font once per
/// thread).
fn kern(bold: bool, size: f64, a: GlyphId, b: GlyphId) -> f32 {
    thread_local! {
        static FONTS: [FontRef<'static>; 2] = [font(false), font(true)];
    }
    KERNING.with(|cache| {
        *cache
            .borrow_mut()
            .entry((bold, size.to_bits(), a.0, b.0))
            .or_insert_with(|| FONTS.with(|f| f[usize::from(bold)].as_scaled(size as f32).kern(a, b)))
    })
}

/// The cached glyph of `c` in a face at a size.
fn glyph(bold: bool, size: f64, c: char) -> Rc<Glyph> {
    GLYPHS.with(|cache| {
        cache
            .borrow_mut()
            .entry((bold, size.to_bits(), c))
            .or_insert_with(|| Rc::new(rasterise(bold, size, c)))
            .clone()
    })
}

/// The width and height, px, plotters' ab_glyph font gives `text` in the embedded font
/// (`FontDesc::box_size` of an unrotated font, the same sums in the same order: advances and
/// kerning, truncated; the height is `size / 1.24` truncated), from the cached glyphs.
pub fn text_size(bold: bool, size: f64, text: &str) -> (u32, u32) {
    layout(bold, size, text).0
}

/// A glyph of a text and the whole-pixel x it is drawn at.
type Placed = (Rc<Glyph>, i32);

/// A text's size as [`text_size`] gives it and its glyphs, each with the whole-pixel x at
/// which plotters' ab_glyph font draws it (the kerning before it added, then its advance
/// after it). The two sums are kept apart: plotters adds the same terms in two orders.
fn layout(bold: bool, size: f64, text: &str) -> ((u32, u32), Vec<Placed>) {
    let mut width = 0f32;
    let mut x_shift = 0f32;
    let mut prev: Option<GlyphId> = None;
    let mut glyphs = Vec::with_capacity(text.len());
    for c in text.chars() {
        let g = glyph(bold, size, c);
        width += g.advance;
        if let Some(p) = prev {
            let k = kern(bold, size, p, g.id);
            width += k;
            x_shift += k;
        }
        prev = Some(g.id);
        let xs = x_shift as i32;
        x_shift += g.advance;
        glyphs.push((g, xs));
    }
    let size_px = ((width as i32).unsigned_abs(), ((size / 1.24) as i32).unsigned_abs());
    (size_px, glyphs)
}

/// Whether a text style is one [`CachedText`] draws itself: the embedded font (`FONT`),
/// normal or bold, unrotated; which face.
fn cached_face<S: BackendTextStyle>(style: &S) -> Option<bool> {
    let bold = match style.style() {
        FontStyle::Bold => true,
        FontStyle::Normal => false,
        _ => return None,
    };
    (style.family().as_str() == FONT && matches!(style.transform(), FontTransform::None)).then_some(bold)
}

/// A bitmap backend drawing the embedded font's text from cached glyphs (module docs).
pub struct CachedText<'a> {
    /// The RGB pixels, row by row.
    buf: &'a mut [u8],
    /// (width, height), px.
    size: (u32, u32),
}

impl<'a> CachedText<'a> {
    /// Over an RGB buffer of `size` (width, height).
    ///
    /// # Panics
    /// When the buffer holds fewer than width x height x 3 bytes (as plotters'
    /// `BitMapBackend::with_buffer`).
    pub fn with_buffer(buf: &'a mut [u8], size: (u32, u32)) -> Self {
        assert!(
            buf.len() >= size.0 as usize * size.1 as usize * 3,
            "a {} x {} RGB image needs {} bytes, the buffer has {}",
            size.0,
            size.1,
            size.0 as usize * size.1 as usize * 3,
            buf.len()
        );
        CachedText { buf, size }
    }

    /// plotters' bitmap backend over the buffer, for everything but the cached text (it
    /// holds nothing between calls: made for each).
    fn inner(&mut self) -> BitMapBackend<'_> {
        BitMapBackend::with_buffer(self.buf, self.size)
    }

    /// Blend `rgb` with weight `w` ([`weight`]) into pixel (x, y) (inside the image),
    /// exactly as plotters' RGB bitmap does: set at 256, else each channel moved by w / 256
    /// of the way, in integers.
    #[inline]
    fn blend(&mut self, x: usize, y: usize, rgb: (u8, u8, u8), w: u16) {
        let i = (y * self.size.0 as usize + x) * 3;
        let px = &mut self.buf[i..i + 3];
        if w >= 256 {
            px.copy_from_slice(&[rgb.0, rgb.1, rgb.2]);
        } else if w > 0 {
            let a = u32::from(w);
            for (p, new) in px.iter_mut().zip([rgb.0, rgb.1, rgb.2]) {
                if new > *p {
                    *p += (u32::from(new - *p) * a / 256) as u8;
                } else {
                    *p -= (u32::from(*p - new) * a / 256) as u8;
                }
            }
        }
    }
}

type Res<T> = Result<T, DrawingErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>>;

impl DrawingBackend for CachedText<'_> {
    type ErrorType = <BitMapBackend<'static> as DrawingBackend>::ErrorType;

    fn get_size(&self) -> (u32, u32) {
        self.size
    }

    fn ensure_prepared(&mut self) -> Res<()> {
        Ok(())
    }

    fn present(&mut self) -> Res<()> {
        Ok(())
    }

    fn draw_pixel(&mut self, point: BackendCoord, color: BackendColor) -> Res<()> {
        self.inner().draw_pixel(point, color)
    }

    fn draw_line<S: BackendStyle>(&mut self, from: BackendCoord, to: BackendCoord, style: &S) -> Res<()> {
        self.inner().draw_line(from, to, style)
    }

    fn draw_rect<S: BackendStyle>(
        &mut self,
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Res<()> {
        self.inner().draw_rect(upper_left, bottom_right, style, fill)
    }

    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(&mut self, path: I, style: &S) -> Res<()> {
        self.inner().draw_path(path, style)
    }

    fn draw_circle<S: BackendStyle>(&mut self, center: BackendCoord, radius: u32, style: &S, fill: bool) -> Res<()> {
        self.inner().draw_circle(center, radius, style, fill)
    }

    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(&mut self, vert: I, style: &S) -> Res<()> {
        self.inner().fill_polygon(vert, style)
    }

    fn estimate_text_size<TStyle: BackendTextStyle>(&self, text: &str, style: &TStyle) -> Res<(u32, u32)> {
        match cached_face(style) {
            Some(bold) => Ok(text_size(bold, style.size(), text)),
            // plotters' default (DrawingBackend::estimate_text_size).
            None => {
                let ((x0, y0), (x1, y1)) = style
                    .layout_box(text)
                    .map_err(|e| DrawingErrorKind::FontError(Box::new(e)))?;
                Ok(((x1 - x0) as u32, (y1 - y0) as u32))
            }
        }
    }

    fn blit_bitmap(&mut self, pos: BackendCoord, (iw, ih): (u32, u32), src: &[u8]) -> Res<()> {
        self.inner().blit_bitmap(pos, (iw, ih), src)
    }

    fn draw_text<TStyle: BackendTextStyle>(&mut self, text: &str, style: &TStyle, pos: BackendCoord) -> Res<()> {
        let Some(bold) = cached_face(style) else {
            return self.inner().draw_text(text, style, pos);
        };
        let color = style.color();
        if color.alpha == 0.0 {
            return Ok(());
        }
        // plotters' layout (its box starts at (0, 0)) and anchor (DrawingBackend::draw_text's
        // default).
        let size = style.size();
        let ((width, height), glyphs) = layout(bold, size, text);
        let (width, height) = (width as i32, height as i32);
        let dx = match style.anchor().h_pos {
            HPos::Left => 0,
            HPos::Right => -width,
            HPos::Center => -width / 2,
        };
        let dy = match style.anchor().v_pos {
            VPos::Top => 0,
            VPos::Center => -height / 2,
            VPos::Bottom => -height,
        };
        let (w, h) = self.get_size();
        let (ox, oy) = (pos.0 + dx, pos.1 + dy);
        // plotters' ab_glyph font's draw: the glyphs one after another.
        for (g, xs) in &glyphs {
            for &(x, y, a, opaque_w) in &g.coverage {
                let (x, y) = (ox + x + xs, oy + y + g.y_shift);
                if x >= 0 && x < w as i32 && y >= 0 && y < h as i32 {
                    // plotters mixes the colour's opacity with the coverage in f64.
                    let wt = if color.alpha == 1.0 {
                        opaque_w
                    } else {
                        weight(color.alpha * a as f64)
                    };
                    self.blend(x as usize, y as usize, color.rgb, wt);
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plotters::style::text_anchor::Pos;

    /// Draws one text with a style at a position.
    type Draw<'a> = dyn FnMut(&str, &TextStyle, (i32, i32)) + 'a;

    /// Text of every anchor, both faces, several sizes and colours (one translucent), in
    /// the clear and across the image's edges: the same bytes as plotters draws.
    #[test]
    fn cached_text_draws_the_same_pixels_as_plotters() {
        super::super::ensure_font().unwrap();
        let (w, h) = (300u32, 160u32);
        let texts = [
            (
                "P = 1.23 +- 0.04 % (AVg) ×°′",
                12.0,
                false,
                Pos::new(HPos::Left, VPos::Top),
                (5, 5),
            ),
            (
                "Wolf 2001: Δγ = 13°",
                15.0,
                true,
                Pos::new(HPos::Center, VPos::Center),
                (150, 60),
            ),
            (
                "edge text goes off",
                22.0,
                false,
                Pos::new(HPos::Right, VPos::Bottom),
                (310, 170),
            ),
            ("left off", 18.0, true, Pos::new(HPos::Left, VPos::Center), (-20, 100)),
            (
                "ffi kern AV To",
                13.5,
                false,
                Pos::new(HPos::Right, VPos::Top),
                (290, 120),
            ),
        ];
        let draw = |cached: bool| -> Vec<u8> {
            let mut buf = vec![255u8; (w * h * 3) as usize];
            {
                let colours = [BLACK.to_rgba(), RGBColor(200, 30, 40).to_rgba(), BLUE.mix(0.4)];
                let put = |backend: &mut Draw| {
                    for (k, (t, size, bold, anchor, at)) in texts.iter().enumerate() {
                        let style = FontDesc::new(
                            FontFamily::Name(FONT),
                            *size,
                            if *bold { FontStyle::Bold } else { FontStyle::Normal },
                        )
                        .color(&colours[k % 3])
                        .pos(*anchor);
                        backend(t, &style, *at);
                    }
                };
                if cached {
                    let mut b = CachedText::with_buffer(&mut buf, (w, h));
                    put(&mut |t, s, at| b.draw_text(t, s, at).unwrap());
                } else {
                    let mut b = BitMapBackend::with_buffer(&mut buf, (w, h));
                    put(&mut |t, s, at| b.draw_text(t, s, at).unwrap());
                }
            }
            buf
        };
        let (plain, cached) = (draw(false), draw(true));
        assert!(plain.iter().any(|&v| v != 255), "nothing drawn");
        let differ = plain.iter().zip(&cached).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "{differ} bytes differ");
        // Twice in a row (the glyphs now from the cache): the same again.
        assert!(draw(true) == plain);
    }

    /// The layout from cached glyphs is plotters' (`FontDesc::box_size` of the same face and
    /// size) for texts with kerning pairs, symbols, spaces and none.
    #[test]
    fn cached_text_size_is_plotters_layout() {
        super::super::ensure_font().unwrap();
        let texts = [
            "",
            " ",
            "AVAWAY To Ty",
            "P = 1.23 +- 0.04 % (ΔγΠ°′×)",
            "ffi,.;: |[]{}",
            "Bench 48 1999-03-03T01:00:00",
        ];
        for bold in [false, true] {
            for size in [7.0, 10.5, 12.0, 15.0, 31.25] {
                let font = FontDesc::new(
                    FontFamily::Name(FONT),
                    size,
                    if bold { FontStyle::Bold } else { FontStyle::Normal },
                );
                for t in texts {
                    assert_eq!(
                        text_size(bold, size, t),
                        font.box_size(t).unwrap(),
                        "{t:?} bold {bold} size {size}"
                    );
                }
            }
        }
    }
}
