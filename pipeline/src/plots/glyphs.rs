//! A bitmap backend whose text is drawn from rasterised glyphs kept per thread: plotters
//! rasterises every glyph's outline each time it draws it, which was the largest share of a
//! target figure's cost (a night draws the same few dozen glyphs some 100 000 times).
//!
//! [`CachedText`] wraps plotters' `BitMapBackend` and passes every call through, except
//! `draw_text` of the embedded font (family `FONT`, normal or bold, unrotated): that one
//! lays the text out and places each glyph's coverage exactly as plotters' ab_glyph font
//! does (the glyph rasterised at the origin, shifted by whole pixels: the truncated
//! advance and kerning, `size / 2 + top` down), so the pixels are the same
//! (`tests::cached_text_draws_the_same_pixels_as_plotters`). One difference on purpose:
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
    /// Coverage of each pixel it touches, relative to the top-left of its pixel bounds.
    coverage: Vec<(i32, i32, f32)>,
    /// The bounds' top-left corner as plotters places it: (0, `size / 2 + min.y`) truncated.
    y_shift: i32,
}

/// Glyphs of the embedded fonts, per (bold, size bits, char).
type Cache = HashMap<(bool, u64, char), Rc<Glyph>>;

thread_local! {
    static GLYPHS: RefCell<Cache> = RefCell::new(HashMap::new());
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
        q.draw(|x, y, a| coverage.push((x as i32, y as i32, a)));
    }
    Glyph {
        id,
        advance: scaled.h_advance(id),
        coverage,
        y_shift,
    }
}

/// The kerning between two glyphs of a font at a size.
fn kern(bold: bool, size: f64, a: GlyphId, b: GlyphId) -> f32 {
    thread_local! {
        static FONTS: [FontRef<'static>; 2] = [font(false), font(true)];
    }
    FONTS.with(|f| f[usize::from(bold)].as_scaled(size as f32).kern(a, b))
}

/// A bitmap backend drawing the embedded font's text from cached glyphs (module docs).
pub struct CachedText<'a> {
    inner: BitMapBackend<'a>,
}

impl<'a> CachedText<'a> {
    /// Over an RGB buffer of `size` (width, height).
    pub fn with_buffer(buf: &'a mut [u8], size: (u32, u32)) -> Self {
        CachedText {
            inner: BitMapBackend::with_buffer(buf, size),
        }
    }
}

type Res<T> = Result<T, DrawingErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>>;

impl DrawingBackend for CachedText<'_> {
    type ErrorType = <BitMapBackend<'static> as DrawingBackend>::ErrorType;

    fn get_size(&self) -> (u32, u32) {
        self.inner.get_size()
    }

    fn ensure_prepared(&mut self) -> Res<()> {
        self.inner.ensure_prepared()
    }

    fn present(&mut self) -> Res<()> {
        self.inner.present()
    }

    fn draw_pixel(&mut self, point: BackendCoord, color: BackendColor) -> Res<()> {
        self.inner.draw_pixel(point, color)
    }

    fn draw_line<S: BackendStyle>(&mut self, from: BackendCoord, to: BackendCoord, style: &S) -> Res<()> {
        self.inner.draw_line(from, to, style)
    }

    fn draw_rect<S: BackendStyle>(
        &mut self,
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Res<()> {
        self.inner.draw_rect(upper_left, bottom_right, style, fill)
    }

    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(&mut self, path: I, style: &S) -> Res<()> {
        self.inner.draw_path(path, style)
    }

    fn draw_circle<S: BackendStyle>(&mut self, center: BackendCoord, radius: u32, style: &S, fill: bool) -> Res<()> {
        self.inner.draw_circle(center, radius, style, fill)
    }

    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(&mut self, vert: I, style: &S) -> Res<()> {
        self.inner.fill_polygon(vert, style)
    }

    fn estimate_text_size<TStyle: BackendTextStyle>(&self, text: &str, style: &TStyle) -> Res<(u32, u32)> {
        self.inner.estimate_text_size(text, style)
    }

    fn blit_bitmap(&mut self, pos: BackendCoord, (iw, ih): (u32, u32), src: &[u8]) -> Res<()> {
        self.inner.blit_bitmap(pos, (iw, ih), src)
    }

    fn draw_text<TStyle: BackendTextStyle>(&mut self, text: &str, style: &TStyle, pos: BackendCoord) -> Res<()> {
        let bold = match style.style() {
            FontStyle::Bold => true,
            FontStyle::Normal => false,
            _ => return self.inner.draw_text(text, style, pos),
        };
        if style.family().as_str() != FONT || !matches!(style.transform(), FontTransform::None) {
            return self.inner.draw_text(text, style, pos);
        }
        let color = style.color();
        if color.alpha == 0.0 {
            return Ok(());
        }
        // plotters' layout and anchor (DrawingBackend::draw_text's default).
        let ((min_x, min_y), (max_x, max_y)) = style
            .layout_box(text)
            .map_err(|e| DrawingErrorKind::FontError(Box::new(e)))?;
        let (width, height) = (max_x - min_x, max_y - min_y);
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
        let size = style.size();
        let (ox, oy) = (pos.0 + dx - min_x, pos.1 + dy - min_y);
        // plotters' ab_glyph font's draw: the glyphs one after another.
        let mut x_shift = 0f32;
        let mut prev: Option<GlyphId> = None;
        for c in text.chars() {
            let g = GLYPHS.with(|cache| {
                cache
                    .borrow_mut()
                    .entry((bold, size.to_bits(), c))
                    .or_insert_with(|| Rc::new(rasterise(bold, size, c)))
                    .clone()
            });
            if let Some(p) = prev {
                x_shift += kern(bold, size, p, g.id);
            }
            prev = Some(g.id);
            let xs = x_shift as i32;
            for &(x, y, a) in &g.coverage {
                let (x, y) = (ox + x + xs, oy + y + g.y_shift);
                if x >= 0 && x < w as i32 && y >= 0 && y < h as i32 {
                    self.inner.draw_pixel((x, y), color.mix(a as f64))?;
                }
            }
            x_shift += g.advance;
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
}
