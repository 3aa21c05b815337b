//! Line charts on a [`Canvas`]: axes with round-number ticks, labels, series and a legend.

use super::canvas::{Canvas, Colour, GLYPH, text_width};

#[derive(Debug, Clone)]
pub struct Series {
    pub label: String,
    pub colour: Colour,
    /// Line width in pixels; 0 draws each point as a dot instead of joining them.
    pub width: f64,
    pub points: Vec<(f64, f64)>,
}

#[derive(Debug, Clone, Default)]
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Fixed y range; by default the data's, padded.
    pub y_range: Option<(f64, f64)>,
}

/// The pixel rectangle a chart is drawn in.
#[derive(Debug, Clone, Copy)]
pub struct Area {
    pub x: i32,
    pub y: i32,
    pub width: i32,
    pub height: i32,
}

/// Round tick positions covering `low..=high`: steps of 1, 2 or 5 × 10^k, about `target` of them.
pub fn ticks(low: f64, high: f64, target: usize) -> (Vec<f64>, f64) {
    let span = (high - low).abs().max(1e-12);
    let raw = span / target.max(1) as f64;
    let magnitude = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * magnitude).find(|s| *s >= raw).unwrap_or(10.0 * magnitude);
    let first = (low / step).ceil() as i64;
    let last = (high / step).floor() as i64;
    ((first..=last).map(|i| i as f64 * step).collect(), step)
}

/// A tick label: SI suffixes for large numbers, enough decimals for the step.
pub fn tick_label(value: f64, step: f64) -> String {
    let magnitude = value.abs().max(step.abs());
    let (scaled, scaled_step, suffix) = if magnitude >= 1e6 {
        (value / 1e6, step / 1e6, "M")
    } else if magnitude >= 1e4 {
        (value / 1e3, step / 1e3, "k")
    } else {
        (value, step, "")
    };
    let decimals = if scaled_step >= 1.0 { 0 } else { (-scaled_step.log10()).ceil().clamp(0.0, 6.0) as usize };
    let text = format!("{scaled:.decimals$}");
    // "-0" reads as a bug.
    let text = if text.trim_start_matches('-').chars().all(|c| c == '0' || c == '.') { "0".to_string() } else { text };
    format!("{text}{suffix}")
}

fn range(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (low, high) =
        values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| (l.min(v), h.max(v)));
    (low <= high).then_some((low, high))
}

impl Chart {
    /// Draws the chart into `area` of `canvas`.
    pub fn draw(&self, canvas: &mut Canvas, area: Area) {
        let scale = 1;
        let glyph = GLYPH * scale;
        let left = area.x + 2 * glyph + 7 * glyph; // y label + tick labels
        let right = area.x + area.width - glyph;
        let top = area.y + 2 * glyph;
        let bottom = area.y + area.height - 3 * glyph - 4;
        if right - left < 20 || bottom - top < 20 {
            return;
        }
        canvas.text(
            area.x + (area.width - text_width(&self.title, scale)) / 2,
            area.y + 4,
            &self.title,
            scale,
            Colour::Black,
        );

        let points = || self.series.iter().flat_map(|s| s.points.iter());
        let (x_low, x_high) = range(points().map(|p| p.0)).unwrap_or((0.0, 1.0));
        let (mut y_low, mut y_high) = self.y_range.or_else(|| range(points().map(|p| p.1))).unwrap_or((0.0, 1.0));
        if self.y_range.is_none() {
            let pad = ((y_high - y_low) * 0.05).max(1e-9);
            y_low -= pad;
            y_high += pad;
        }
        let x_high = if x_high > x_low { x_high } else { x_low + 1.0 };
        let to_pixel = |(x, y): (f64, f64)| {
            let px = f64::from(left) + (x - x_low) / (x_high - x_low) * f64::from(right - left);
            let py = f64::from(bottom) - (y - y_low) / (y_high - y_low) * f64::from(bottom - top);
            (px, py)
        };

        let (x_ticks, x_step) = ticks(x_low, x_high, 6);
        for &x in &x_ticks {
            let (px, _) = to_pixel((x, y_low));
            canvas.fill_rect(px as i32, top, 1, bottom - top, Colour::LightGrey);
            let label = tick_label(x, x_step);
            canvas.text(px as i32 - text_width(&label, scale) / 2, bottom + 6, &label, scale, Colour::Black);
        }
        let (y_ticks, y_step) = ticks(y_low, y_high, 5);
        for &y in &y_ticks {
            let (_, py) = to_pixel((x_low, y));
            canvas.fill_rect(left, py as i32, right - left, 1, Colour::LightGrey);
            let label = tick_label(y, y_step);
            canvas.text(left - 4 - text_width(&label, scale), py as i32 - glyph / 2, &label, scale, Colour::Black);
        }
        canvas.rect(left, top, right - left + 1, bottom - top + 1, Colour::Black);
        let x_label_x = left + (right - left - text_width(&self.x_label, scale)) / 2;
        canvas.text(x_label_x, bottom + 8 + glyph + 4, &self.x_label, scale, Colour::Black);
        let y_label_y = top + (bottom - top - text_width(&self.y_label, scale)) / 2;
        canvas.text_vertical(area.x + 2, y_label_y, &self.y_label, scale, Colour::Black);

        // Clip series to the plot box by drawing on a scratch canvas region copy.
        let mut plot = Canvas::new(canvas.width, canvas.height, Colour::White);
        plot.pixels.copy_from_slice(&canvas.pixels);
        for series in &self.series {
            let pixels: Vec<(f64, f64)> = series.points.iter().map(|&p| to_pixel(p)).collect();
            if series.width <= 0.0 {
                for &(x, y) in pixels.iter().filter(|p| p.0.is_finite() && p.1.is_finite()) {
                    plot.fill_rect(x as i32 - 1, y as i32 - 1, 2, 2, series.colour);
                }
                continue;
            }
            if pixels.len() == 1 {
                plot.fill_circle(pixels[0].0, pixels[0].1, series.width.max(2.0), series.colour);
            }
            plot.polyline(&pixels, series.width, series.colour);
        }
        for y in top + 1..bottom {
            let row = y as usize * canvas.width as usize;
            let (from, to) = (row + (left + 1) as usize, row + right as usize);
            canvas.pixels[from..to].copy_from_slice(&plot.pixels[from..to]);
        }

        // Legend: labelled series only, top-left inside the box.
        let mut legend_y = top + 6;
        for series in self.series.iter().filter(|s| !s.label.is_empty()) {
            canvas.fill_rect(left + 8, legend_y + glyph / 2 - 1, 16, 3, series.colour);
            canvas.text(left + 28, legend_y, &series.label, scale, Colour::Black);
            legend_y += glyph + 4;
        }
    }
}

/// A time-weighted exponential moving average, as in the study's figures: a point `Δx`
/// after the previous one keeps `exp(−Δx/τ)` of the average, so unevenly spaced points
/// (episodes end at irregular env steps) are smoothed evenly along x. Debiased at the start.
pub fn time_weighted_ema(points: &[(f64, f64)], tau: f64) -> Vec<(f64, f64)> {
    let mut smoothed = Vec::with_capacity(points.len());
    let (mut average, mut weight) = (0.0, 0.0);
    let mut previous_x: Option<f64> = None;
    for &(x, y) in points {
        if !y.is_finite() {
            continue;
        }
        let keep = previous_x.map_or(0.0, |p| (-(x - p).max(0.0) / tau.max(1e-12)).exp());
        // Points at the same x still average rather than replace.
        let keep = if previous_x == Some(x) { keep.max(0.9) } else { keep };
        average = keep * average + (1.0 - keep) * y;
        weight = keep * weight + (1.0 - keep);
        previous_x = Some(x);
        smoothed.push((x, if weight > 0.0 { average / weight } else { y }));
    }
    smoothed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_cover_the_range() {
        let (ticks, step) = ticks(0.0, 1.0, 5);
        assert_eq!(step, 0.2);
        assert_eq!(ticks.len(), 6);
        let (ticks, step) = super::ticks(3_200.0, 9_870_000.0, 6);
        assert_eq!(step, 2_000_000.0);
        assert_eq!(ticks, vec![2e6, 4e6, 6e6, 8e6]);
        assert_eq!(tick_label(4e6, 2e6), "4M");
        assert_eq!(tick_label(2.5e6, 5e5), "2.5M");
        assert_eq!(tick_label(0.25, 0.05), "0.25");
        assert_eq!(tick_label(-0.0, 0.5), "0");
        assert_eq!(tick_label(20_000.0, 10_000.0), "20k");
    }

    #[test]
    fn ema_follows_a_step_and_weights_by_distance() {
        let points: Vec<(f64, f64)> = (0..100).map(|i| (f64::from(i), if i < 50 { 0.0 } else { 1.0 })).collect();
        let smoothed = time_weighted_ema(&points, 5.0);
        assert_eq!(smoothed[0].1, 0.0);
        assert!(smoothed[49].1.abs() < 1e-12);
        // One τ after the step: 1 − e^(−1) of the way (within a discretisation step).
        assert!((smoothed[54].1 - (1.0 - (-1.0f64).exp())).abs() < 0.1, "{}", smoothed[54].1);
        assert!(smoothed[99].1 > 0.99);
        // The first point is the average (debiased), whatever its value.
        assert_eq!(time_weighted_ema(&[(3.0, 7.0), (3.5, 7.0)], 1.0)[1].1, 7.0);
    }
}
