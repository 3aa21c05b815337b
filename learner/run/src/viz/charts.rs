//! Line charts as PNG, drawn with `plotters`: anti-aliased text in an embedded open font
//! (DejaVu Sans, from the `dejavu` crate), round ticks, a light grid and a legend. No system
//! fonts are read, so a figure looks the same on every machine.

use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, RGBColor, register_font};

/// The font family name under which the embedded font is registered.
const FONT: &str = "sans-serif";

/// Series colours, bold and light (for raw points under a smoothed line): Tableau 10.
pub const SERIES_COLOURS: [(RGBColor, RGBColor); 6] = [
    (RGBColor(31, 119, 180), RGBColor(174, 199, 232)),
    (RGBColor(255, 127, 14), RGBColor(255, 187, 120)),
    (RGBColor(44, 160, 44), RGBColor(152, 223, 138)),
    (RGBColor(214, 39, 40), RGBColor(255, 152, 150)),
    (RGBColor(148, 103, 189), RGBColor(197, 176, 213)),
    (RGBColor(140, 86, 75), RGBColor(196, 156, 148)),
];

type DrawError = DrawingAreaErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>;

#[derive(Debug, thiserror::Error)]
pub enum ChartError {
    #[error("drawing {path}: {source}")]
    Draw {
        path: PathBuf,
        #[source]
        source: DrawError,
    },
    #[error("the embedded font could not be loaded")]
    Font,
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mark {
    /// Points joined by a line this many pixels wide.
    Line(u32),
    /// Each point a small dot (raw samples under a smoothed line).
    Dots,
}

#[derive(Debug, Clone)]
pub struct Series {
    /// Shown in the legend; empty: not in the legend.
    pub label: String,
    pub colour: RGBColor,
    pub mark: Mark,
    pub points: Vec<(f64, f64)>,
}

/// One chart: a title, axis names, series, and optionally a fixed y range.
#[derive(Debug, Clone, Default)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Fixed y range; by default the data's, padded.
    pub y_range: Option<(f64, f64)>,
}

fn register_embedded_font() -> Result<(), ChartError> {
    static REGISTER: Once = Once::new();
    let mut result = Ok(());
    REGISTER.call_once(|| {
        result = register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).map_err(|_| ChartError::Font);
    });
    result
}

/// Draws `panels` stacked vertically, each `width × panel_height` pixels, into a PNG.
pub fn write_png(path: &Path, width: u32, panel_height: u32, panels: &[Panel]) -> Result<(), ChartError> {
    register_embedded_font()?;
    let draw_error = |source| ChartError::Draw { path: path.to_path_buf(), source };
    let height = panel_height * panels.len().max(1) as u32;
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_error)?;
    for (area, panel) in root.split_evenly((panels.len().max(1), 1)).iter().zip(panels) {
        draw_panel(area, panel).map_err(draw_error)?;
    }
    root.present().map_err(draw_error)
}

/// The x and y ranges that hold every finite point (padded, never empty).
fn bounds(panel: &Panel) -> ((f64, f64), (f64, f64)) {
    let finite = || panel.series.iter().flat_map(|s| &s.points).filter(|(x, y)| x.is_finite() && y.is_finite());
    let span = |values: &mut dyn Iterator<Item = f64>| {
        let (low, high) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| (l.min(v), h.max(v)));
        if low.is_finite() { (low, if high > low { high } else { low + 1.0 }) } else { (0.0, 1.0) }
    };
    let x = span(&mut finite().map(|p| p.0));
    let y = panel.y_range.unwrap_or_else(|| {
        let (low, high) = span(&mut finite().map(|p| p.1));
        let pad = 0.05 * (high - low);
        (low - pad, high + pad)
    });
    (x, y)
}

fn draw_panel(area: &DrawingArea<BitMapBackend<'_>, Shift>, panel: &Panel) -> Result<(), DrawError> {
    let ((x0, x1), (y0, y1)) = bounds(panel);
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.title, (FONT, 20))
        .margin(12)
        .x_label_area_size(44)
        .y_label_area_size(64)
        .build_cartesian_2d(x0..x1, y0..y1)?;
    chart
        .configure_mesh()
        .x_desc(&panel.x_label)
        .y_desc(&panel.y_label)
        .x_labels(10)
        .y_labels(8)
        .x_label_formatter(&|v| si_label(*v))
        .y_label_formatter(&|v| si_label(*v))
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 15))
        .light_line_style(RGBColor(236, 236, 236))
        .bold_line_style(RGBColor(215, 215, 215))
        .draw()?;
    let finite = |points: &[(f64, f64)]| -> Vec<(f64, f64)> {
        points.iter().copied().filter(|(x, y)| x.is_finite() && y.is_finite()).collect()
    };
    let mut labelled = false;
    for series in &panel.series {
        let points = finite(&series.points);
        let colour = series.colour;
        let drawn = match series.mark {
            Mark::Line(width) => chart.draw_series(LineSeries::new(points, colour.stroke_width(width)))?,
            Mark::Dots => chart.draw_series(points.into_iter().map(|p| Circle::new(p, 1, colour.filled())))?,
        };
        if !series.label.is_empty() {
            labelled = true;
            drawn
                .label(series.label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(3)));
        }
    }
    if labelled {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(190, 190, 190))
            .label_font((FONT, 14))
            .draw()?;
    }
    Ok(())
}

/// A tick label: k and M for large numbers, at most three significant decimals otherwise.
pub fn si_label(value: f64) -> String {
    let magnitude = value.abs();
    let text = if magnitude >= 1e6 {
        format!("{}M", trim(value / 1e6))
    } else if magnitude >= 1e4 {
        format!("{}k", trim(value / 1e3))
    } else {
        trim(value)
    };
    // "-0" reads as a bug.
    if text == "-0" { "0".to_string() } else { text }
}

fn trim(value: f64) -> String {
    let text = format!("{value:.3}");
    let text = text.trim_end_matches('0').trim_end_matches('.');
    text.to_string()
}

/// An exponential moving average over x (time or steps), not over samples: `tau` is its time
/// constant in x units, so bursts of episodes weigh no more than sparse ones of equal span.
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
    fn tick_labels_are_short() {
        assert_eq!(si_label(4e6), "4M");
        assert_eq!(si_label(2.5e6), "2.5M");
        assert_eq!(si_label(0.25), "0.25");
        assert_eq!(si_label(-0.0), "0");
        assert_eq!(si_label(20_000.0), "20k");
        assert_eq!(si_label(0.123_456), "0.123");
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

    #[test]
    fn a_chart_is_drawn_with_text_in_its_series_colour() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("chart.png");
        let (colour, light) = SERIES_COLOURS[0];
        let points: Vec<(f64, f64)> = (0..200).map(|i| (f64::from(i) * 100.0, (f64::from(i) / 20.0).sin())).collect();
        let panel = Panel {
            title: "a sine".into(),
            x_label: "steps".into(),
            y_label: "value".into(),
            series: vec![
                Series { label: String::new(), colour: light, mark: Mark::Dots, points: points.clone() },
                Series { label: "sine".into(), colour, mark: Mark::Line(2), points },
            ],
            y_range: None,
        };
        write_png(&path, 640, 300, &[panel.clone(), panel]).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut pixels).unwrap();
        assert_eq!((info.width, info.height), (640, 600));
        let rgb: Vec<[u8; 3]> = pixels.chunks(info.color_type.samples()).map(|p| [p[0], p[1], p[2]]).collect();
        let count = |c: [u8; 3]| rgb.iter().filter(|p| **p == c).count();
        assert!(count([colour.0, colour.1, colour.2]) > 500, "the line is drawn");
        // Anti-aliased text leaves grey levels between black and white.
        let greys = rgb.iter().filter(|p| p[0] == p[1] && p[1] == p[2] && (40..200).contains(&p[0])).count();
        assert!(greys > 200, "anti-aliased text: {greys} grey pixels");
    }
}
