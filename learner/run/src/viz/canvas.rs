//! An indexed-colour raster: filled polygons and discs, thick lines and 8×8 bitmap text.
//!
//! Indexed because both outputs want it: GIF frames are palette images, and one fixed
//! palette for a whole animation makes every frame a plain copy with no quantisation.

use std::io::Write;

/// Colours, by index into [`PALETTE`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Colour {
    White = 0,
    Black,
    Grey,
    LightGrey,
    Blue,
    Orange,
    Green,
    Red,
    Purple,
    Brown,
    LightBlue,
    LightOrange,
    LightGreen,
    LightRed,
    Sky,
    Ground,
}

/// RGB of each [`Colour`], in order. The light variants are the raw points behind a curve.
pub const PALETTE: [[u8; 3]; 16] = [
    [255, 255, 255],
    [20, 20, 20],
    [128, 128, 128],
    [220, 220, 220],
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [174, 199, 232],
    [255, 187, 120],
    [152, 223, 138],
    [255, 152, 150],
    [235, 243, 250],
    [205, 190, 160],
];

/// Pixels of one glyph side at scale 1.
pub const GLYPH: i32 = 8;

#[derive(Debug, Clone)]
pub struct Canvas {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<u8>,
}

impl Canvas {
    pub fn new(width: u32, height: u32, background: Colour) -> Self {
        Self { width, height, pixels: vec![background as u8; width as usize * height as usize] }
    }

    pub fn fill(&mut self, colour: Colour) {
        self.pixels.fill(colour as u8);
    }

    pub fn set(&mut self, x: i32, y: i32, colour: Colour) {
        if x >= 0 && y >= 0 && (x as u32) < self.width && (y as u32) < self.height {
            self.pixels[y as usize * self.width as usize + x as usize] = colour as u8;
        }
    }

    pub fn get(&self, x: u32, y: u32) -> Option<Colour> {
        let index = *self.pixels.get(y as usize * self.width as usize + x as usize)?;
        COLOURS.get(index as usize).copied()
    }

    /// Fills the span `x0..x1` (exclusive) of row `y`, clipped.
    fn span(&mut self, y: i32, x0: i32, x1: i32, colour: Colour) {
        if y < 0 || y >= self.height as i32 {
            return;
        }
        let (x0, x1) = (x0.max(0), x1.min(self.width as i32));
        if x0 >= x1 {
            return;
        }
        let row = y as usize * self.width as usize;
        self.pixels[row + x0 as usize..row + x1 as usize].fill(colour as u8);
    }

    pub fn fill_rect(&mut self, x: i32, y: i32, width: i32, height: i32, colour: Colour) {
        for row in y..y + height {
            self.span(row, x, x + width, colour);
        }
    }

    pub fn rect(&mut self, x: i32, y: i32, width: i32, height: i32, colour: Colour) {
        self.fill_rect(x, y, width, 1, colour);
        self.fill_rect(x, y + height - 1, width, 1, colour);
        self.fill_rect(x, y, 1, height, colour);
        self.fill_rect(x + width - 1, y, 1, height, colour);
    }

    /// Fills a polygon given in pixel coordinates (sample points at pixel centres).
    pub fn fill_polygon(&mut self, points: &[(f64, f64)], colour: Colour) {
        if points.len() < 3 {
            return;
        }
        let top = points.iter().map(|p| p.1).fold(f64::INFINITY, f64::min).floor().max(0.0) as i32;
        let bottom =
            points.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max).ceil().min(f64::from(self.height)) as i32;
        let mut crossings = Vec::with_capacity(points.len());
        for y in top..bottom {
            let sample = f64::from(y) + 0.5;
            crossings.clear();
            for (i, &(x0, y0)) in points.iter().enumerate() {
                let (x1, y1) = points[(i + 1) % points.len()];
                if (y0 <= sample && y1 > sample) || (y1 <= sample && y0 > sample) {
                    crossings.push(x0 + (sample - y0) / (y1 - y0) * (x1 - x0));
                }
            }
            crossings.sort_by(f64::total_cmp);
            for pair in crossings.chunks_exact(2) {
                let x0 = (pair[0] - 0.5).ceil() as i32;
                let x1 = (pair[1] - 0.5).ceil() as i32;
                self.span(y, x0, x1, colour);
            }
        }
    }

    pub fn fill_circle(&mut self, cx: f64, cy: f64, radius: f64, colour: Colour) {
        let top = (cy - radius).floor() as i32;
        let bottom = (cy + radius).ceil() as i32;
        for y in top..=bottom {
            let dy = f64::from(y) + 0.5 - cy;
            let half = radius * radius - dy * dy;
            if half < 0.0 {
                continue;
            }
            let half = half.sqrt();
            self.span(y, (cx - half - 0.5).ceil() as i32, (cx + half - 0.5).ceil() as i32, colour);
        }
    }

    /// A line `width` pixels thick with square ends (a filled quad).
    pub fn line(&mut self, from: (f64, f64), to: (f64, f64), width: f64, colour: Colour) {
        let (dx, dy) = (to.0 - from.0, to.1 - from.1);
        let length = (dx * dx + dy * dy).sqrt();
        if length < 1e-9 {
            self.fill_circle(from.0, from.1, width / 2.0, colour);
            return;
        }
        // Thin lines still cover at least one pixel across.
        let half = (width / 2.0).max(0.5);
        let (nx, ny) = (-dy / length * half, dx / length * half);
        // Extend by half a pixel along the line so consecutive segments join.
        let (ex, ey) = (dx / length * 0.5, dy / length * 0.5);
        self.fill_polygon(
            &[
                (from.0 + nx - ex, from.1 + ny - ey),
                (to.0 + nx + ex, to.1 + ny + ey),
                (to.0 - nx + ex, to.1 - ny + ey),
                (from.0 - nx - ex, from.1 - ny - ey),
            ],
            colour,
        );
    }

    /// A polyline; non-finite points break it.
    pub fn polyline(&mut self, points: &[(f64, f64)], width: f64, colour: Colour) {
        for pair in points.windows(2) {
            let finite = |p: (f64, f64)| p.0.is_finite() && p.1.is_finite();
            if finite(pair[0]) && finite(pair[1]) {
                self.line(pair[0], pair[1], width, colour);
            }
        }
    }

    /// A capsule: a thick line with round ends.
    pub fn capsule(&mut self, from: (f64, f64), to: (f64, f64), radius: f64, colour: Colour) {
        self.line(from, to, 2.0 * radius, colour);
        self.fill_circle(from.0, from.1, radius, colour);
        self.fill_circle(to.0, to.1, radius, colour);
    }

    /// ASCII text with its top-left corner at (x, y), each glyph `scale`×8 pixels. Characters
    /// outside ASCII are drawn as '?'.
    pub fn text(&mut self, x: i32, y: i32, text: &str, scale: i32, colour: Colour) {
        for (i, c) in text.chars().enumerate() {
            let glyph = glyph(c);
            let left = x + i as i32 * GLYPH * scale;
            for (row, bits) in glyph.iter().enumerate() {
                for column in 0..8 {
                    if bits & (1 << column) != 0 {
                        self.fill_rect(left + column * scale, y + row as i32 * scale, scale, scale, colour);
                    }
                }
            }
        }
    }

    /// Text turned 90° anticlockwise (reading upwards), its bounding box's top-left at (x, y).
    pub fn text_vertical(&mut self, x: i32, y: i32, text: &str, scale: i32, colour: Colour) {
        let length = text.chars().count() as i32;
        for (i, c) in text.chars().enumerate() {
            let glyph = glyph(c);
            // Character i occupies rows counted from the bottom of the box.
            let bottom = y + (length - i as i32) * GLYPH * scale;
            for (row, bits) in glyph.iter().enumerate() {
                for column in 0..8 {
                    if bits & (1 << column) != 0 {
                        let px = x + row as i32 * scale;
                        let py = bottom - (column + 1) * scale;
                        self.fill_rect(px, py, scale, scale, colour);
                    }
                }
            }
        }
    }
}

const COLOURS: [Colour; 16] = [
    Colour::White,
    Colour::Black,
    Colour::Grey,
    Colour::LightGrey,
    Colour::Blue,
    Colour::Orange,
    Colour::Green,
    Colour::Red,
    Colour::Purple,
    Colour::Brown,
    Colour::LightBlue,
    Colour::LightOrange,
    Colour::LightGreen,
    Colour::LightRed,
    Colour::Sky,
    Colour::Ground,
];

fn glyph(c: char) -> [u8; 8] {
    let index = if c.is_ascii() { c as usize } else { '?' as usize };
    font8x8::legacy::BASIC_LEGACY[index]
}

/// Width in pixels of `text` at `scale`.
pub fn text_width(text: &str, scale: i32) -> i32 {
    text.chars().count() as i32 * GLYPH * scale
}

/// An animated GIF of palette frames, all with the same size and delay.
pub struct GifWriter<W: Write> {
    encoder: gif::Encoder<W>,
    delay_centiseconds: u16,
    frames: usize,
}

impl<W: Write> std::fmt::Debug for GifWriter<W> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GifWriter").field("frames", &self.frames).finish_non_exhaustive()
    }
}

impl<W: Write> GifWriter<W> {
    pub fn new(output: W, width: u16, height: u16, delay_centiseconds: u16) -> Result<Self, gif::EncodingError> {
        let palette: Vec<u8> = PALETTE.iter().flatten().copied().collect();
        let mut encoder = gif::Encoder::new(output, width, height, &palette)?;
        encoder.set_repeat(gif::Repeat::Infinite)?;
        Ok(Self { encoder, delay_centiseconds, frames: 0 })
    }

    pub fn add(&mut self, canvas: &Canvas) -> Result<(), gif::EncodingError> {
        let width = u16::try_from(canvas.width).unwrap_or(u16::MAX);
        let height = u16::try_from(canvas.height).unwrap_or(u16::MAX);
        let mut frame = gif::Frame::from_indexed_pixels(width, height, canvas.pixels.clone(), None);
        frame.delay = self.delay_centiseconds;
        self.encoder.write_frame(&frame)?;
        self.frames += 1;
        Ok(())
    }

    pub fn frames(&self) -> usize {
        self.frames
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_cover_the_expected_pixels() {
        let mut canvas = Canvas::new(40, 40, Colour::White);
        canvas.fill_rect(2, 3, 4, 5, Colour::Red);
        assert_eq!(canvas.pixels.iter().filter(|&&p| p == Colour::Red as u8).count(), 20);
        canvas.fill_circle(20.0, 20.0, 5.0, Colour::Blue);
        let disc = canvas.pixels.iter().filter(|&&p| p == Colour::Blue as u8).count() as f64;
        assert!((disc - std::f64::consts::PI * 25.0).abs() < 8.0, "{disc}");
        canvas.line((0.0, 39.5), (39.0, 39.5), 1.0, Colour::Green);
        assert_eq!(canvas.get(0, 39), Some(Colour::Green));
        assert_eq!(canvas.get(38, 39), Some(Colour::Green));
        // Shapes off the canvas are clipped, not a panic.
        canvas.fill_polygon(&[(-50.0, -50.0), (500.0, -40.0), (30.0, 900.0)], Colour::Purple);
        canvas.text(-5, 35, "clip", 3, Colour::Black);
    }

    #[test]
    fn text_draws_glyph_bits() {
        let mut canvas = Canvas::new(16, 8, Colour::White);
        canvas.text(0, 0, "|", 1, Colour::Black);
        // '|' in the 8×8 font is a vertical bar: some column is set in most rows.
        let set = canvas.pixels.iter().filter(|&&p| p == Colour::Black as u8).count();
        assert!(set >= 6, "{set}");
        assert_eq!(text_width("abc", 2), 48);
    }
}
