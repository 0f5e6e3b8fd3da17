//! PNG plots drawn with `plotters` (its bitmap backend; text in DejaVu Sans, embedded through the `dejavu`
//! crate, so that a plot reads the same on every machine and needs no system font): cumulative error
//! distribution curves and time series (load-test latency, jitter) with axes, tick labels, axis titles and a
//! legend; and [`Canvas`], the RGB surface annotated frames are drawn on, whose text uses the same font.

use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

/// One curve of a CED plot.
#[derive(Debug, Clone)]
pub struct Curve {
    /// Legend label.
    pub label: String,
    /// Per-sample errors (infinite or NaN = no answer).
    pub errors: Vec<f64>,
}

const W: usize = 800;
const H: usize = 500;
const COLOURS: [[u8; 3]; 6] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [255, 127, 14],
    [148, 103, 189],
    [23, 23, 23],
];

/// The font every plot and canvas writes with, registered once.
fn font() -> &'static str {
    static REGISTERED: std::sync::Once = std::sync::Once::new();
    REGISTERED.call_once(|| {
        // DejaVu Sans is a valid TrueType font: registering it cannot fail.
        let _ = register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
    });
    "sans-serif"
}

/// One line of a chart: its legend label, colour and points.
type Line<'a> = (&'a str, [u8; 3], Vec<(f64, f64)>);

fn rgb(c: [u8; 3]) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

/// Encodes `w` x `h` RGB pixels as PNG.
fn png(px: &[u8], w: usize, h: usize) -> Vec<u8> {
    let mut out = Vec::new();
    // An in-memory buffer of the right size: the encoder has nothing to fail on.
    let _ = image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut out),
        px,
        w as u32,
        h as u32,
        image::ExtendedColorType::Rgb8,
    );
    out
}

/// Draws a line chart on a fresh white `W` x `H` picture: `lines` (label, colour, points) over `x` and `y`,
/// with a grid, tick labels, axis titles and a legend; the picture as PNG.
fn line_chart(
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    x_title: &str,
    y_title: &str,
    lines: &[Line<'_>],
    y_ticks: impl Fn(&f64) -> String,
) -> Vec<u8> {
    let mut px = vec![255u8; W * H * 3];
    {
        let root = BitMapBackend::with_buffer(&mut px, (W as u32, H as u32)).into_drawing_area();
        let font = font();
        // The drawing cannot fail on an in-memory buffer of the right size; a failure would leave a blank plot.
        let _ = (|| -> Result<(), Box<dyn std::error::Error + '_>> {
            let mut chart = ChartBuilder::on(&root)
                .margin(16)
                .x_label_area_size(44)
                .y_label_area_size(64)
                .build_cartesian_2d(x, y)?;
            chart
                .configure_mesh()
                .x_desc(x_title)
                .y_desc(y_title)
                .y_label_formatter(&y_ticks)
                .label_style((font, 15))
                .axis_desc_style((font, 17))
                .light_line_style(RGBColor(235, 235, 235))
                .draw()?;
            for (label, colour, points) in lines {
                let c = rgb(*colour);
                chart
                    .draw_series(LineSeries::new(points.iter().copied(), c.stroke_width(2)))?
                    .label(*label)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(3)));
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::LowerRight)
                .label_font((font, 15))
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()?;
            root.present()?;
            Ok(())
        })();
    }
    png(&px, W, H)
}

/// Renders the CED of each curve from 0 to `max_error` as a PNG: x = error (normalised by the outer eye
/// corners), y = share of samples with error ≤ x. Samples without an answer count in the denominator, never in
/// the curve.
pub fn ced_plot_png(curves: &[Curve], max_error: f64) -> Vec<u8> {
    let steps = 400;
    let lines: Vec<Line<'_>> = curves
        .iter()
        .enumerate()
        .map(|(ci, curve)| {
            let mut sorted: Vec<f64> = curve.errors.iter().copied().filter(|e| e.is_finite()).collect();
            sorted.sort_by(f64::total_cmp);
            let total = curve.errors.len().max(1) as f64;
            let points = (0..=steps)
                .map(|k| {
                    let e = max_error * k as f64 / steps as f64;
                    (e, sorted.partition_point(|&x| x <= e) as f64 / total)
                })
                .collect();
            (curve.label.as_str(), COLOURS[ci % COLOURS.len()], points)
        })
        .collect();
    line_chart(
        0.0..max_error,
        0.0..1.0,
        "NME (outer eye corners)",
        "share of faces",
        &lines,
        |v| format!("{v:.2}"),
    )
}

/// One series of a time plot.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend label.
    pub label: String,
    /// (x, y) points in data units.
    pub points: Vec<(f64, f64)>,
}

/// A line plot of `series` (x from 0 to the largest x, y from 0 to the largest y and a tenth), with axis
/// titles and a legend.
pub fn series_plot_png(series: &[Series], x_label: &str, y_label: &str) -> Vec<u8> {
    let x_max = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.0))
        .filter(|v| v.is_finite())
        .fold(1e-9, f64::max);
    let y_max = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.1))
        .filter(|v| v.is_finite())
        .fold(1e-9, f64::max)
        * 1.1;
    let lines: Vec<Line<'_>> = series
        .iter()
        .enumerate()
        .map(|(ci, s)| {
            let points = s
                .points
                .iter()
                .copied()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .collect();
            (s.label.as_str(), COLOURS[ci % COLOURS.len()], points)
        })
        .collect();
    line_chart(0.0..x_max, 0.0..y_max, x_label, y_label, &lines, |v| {
        format!("{v:.1}")
    })
}

/// An RGB drawing surface.
#[derive(Debug, Clone)]
pub struct Canvas {
    w: usize,
    h: usize,
    px: Vec<u8>,
}

impl Canvas {
    /// A white `w` x `h` canvas.
    pub fn new(w: usize, h: usize) -> Self {
        Self {
            w,
            h,
            px: vec![255; w * h * 3],
        }
    }
    /// Sets one pixel (outside = ignored).
    pub fn set(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < self.w && (y as usize) < self.h {
            let i = (y as usize * self.w + x as usize) * 3;
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }
    /// A filled square of side `2r+1` centred on (x, y).
    pub fn dot(&mut self, x: f64, y: f64, r: i64, c: [u8; 3]) {
        let (cx, cy) = (x.round() as i64, y.round() as i64);
        for dy in -r..=r {
            for dx in -r..=r {
                self.set(cx + dx, cy + dy, c);
            }
        }
    }
    /// Copies gray pixels (`w` x `h`, row-major) to (x0, y0), keeping every `step`-th pixel.
    pub fn blit_gray(&mut self, x0: i64, y0: i64, gray: &[u8], w: usize, h: usize, step: usize) {
        let step = step.max(1);
        for y in (0..h).step_by(step) {
            for x in (0..w).step_by(step) {
                let v = gray[y * w + x];
                self.set(x0 + (x / step) as i64, y0 + (y / step) as i64, [v, v, v]);
            }
        }
    }
    /// Width, pixels.
    pub fn width(&self) -> usize {
        self.w
    }
    /// Height, pixels.
    pub fn height(&self) -> usize {
        self.h
    }
    /// The pixels: rows of `width` RGB triples.
    pub fn rgb(&self) -> &[u8] {
        &self.px
    }
    /// The pixels to change in place: rows of `width` RGB triples.
    pub fn rgb_mut(&mut self) -> &mut [u8] {
        &mut self.px
    }
    /// Encodes as PNG.
    pub fn to_png(&self) -> Vec<u8> {
        png(&self.px, self.w, self.h)
    }
    /// A line of thickness `thick`.
    pub fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), c: [u8; 3], thick: i64) {
        let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
        for k in 0..=n {
            let t = k as f64 / n as f64;
            let (x, y) = (
                (x0 + t * (x1 - x0)).round() as i64,
                (y0 + t * (y1 - y0)).round() as i64,
            );
            for dx in 0..thick {
                for dy in 0..thick {
                    self.set(x + dx - thick / 2, y + dy - thick / 2, c);
                }
            }
        }
    }
    /// Text in DejaVu Sans, 13 px high (a line every 14 px), its top-left corner at (x, y).
    pub fn text(&mut self, x: i64, y: i64, s: &str, c: [u8; 3]) {
        let (w, h) = (self.w as u32, self.h as u32);
        let root = BitMapBackend::with_buffer(&mut self.px, (w, h)).into_drawing_area();
        let colour = rgb(c);
        let style = TextStyle::from((font(), 13).into_font()).color(&colour);
        let at = (
            i32::try_from(x).unwrap_or(i32::MAX),
            i32::try_from(y).unwrap_or(i32::MAX),
        );
        // Drawing into the canvas's own buffer cannot fail; a failure would leave the text out.
        let _ = root.draw_text(s, &style, at);
        let _ = root.present();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plot_is_a_png_with_the_curve_drawn() {
        let curve = |errors| {
            ced_plot_png(
                &[Curve {
                    label: "dan".into(),
                    errors,
                }],
                0.08,
            )
        };
        let img = image::load_from_memory(&curve(vec![0.01, 0.02, 0.03, f64::INFINITY]))
            .unwrap()
            .to_rgb8();
        assert_eq!(img.dimensions(), (W as u32, H as u32));
        let blue = |img: &image::RgbImage| img.pixels().filter(|p| p.0 == COLOURS[0]).count();
        // The curve is drawn, and it is the data's: a curve that stays at 0 draws less of it above the axis.
        let flat = image::load_from_memory(&curve(vec![f64::INFINITY; 4]))
            .unwrap()
            .to_rgb8();
        let top_half = |img: &image::RgbImage| {
            (0..H as u32 / 2)
                .flat_map(|y| (0..W as u32).map(move |x| (x, y)))
                .filter(|&(x, y)| img.get_pixel(x, y).0 == COLOURS[0])
                .count()
        };
        assert!(blue(&img) > 500, "{}", blue(&img));
        assert!(top_half(&img) > top_half(&flat) + 300);
    }

    #[test]
    fn text_is_drawn_in_a_real_font() {
        let mut cv = Canvas::new(200, 40);
        cv.text(4, 4, "holoface 0.5", [0, 0, 0]);
        let dark = cv.rgb().chunks(3).filter(|p| p[0] < 128).count();
        // Anti-aliased glyphs: some dark pixels and some grey ones, not the 3x5 font's blocks.
        let grey = cv.rgb().chunks(3).filter(|p| p[0] > 32 && p[0] < 224).count();
        assert!(dark > 50 && grey > 20, "dark {dark}, grey {grey}");
        let mut empty = Canvas::new(200, 40);
        empty.text(4, 4, "", [0, 0, 0]);
        assert!(empty.rgb().iter().all(|&v| v == 255));
    }

    #[test]
    fn series_plot_draws_each_series() {
        let png = series_plot_png(
            &[
                Series {
                    label: "p50".into(),
                    points: vec![(0.0, 1.0), (10.0, 1.0)],
                },
                Series {
                    label: "p99".into(),
                    points: vec![(0.0, 4.0), (10.0, 4.0)],
                },
            ],
            "s",
            "ms",
        );
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
        assert!(count(COLOURS[0]) > 500 && count(COLOURS[1]) > 500);
    }
}
