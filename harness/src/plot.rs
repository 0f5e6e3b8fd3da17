//! Self-contained PNG plots (no font files needed): cumulative error distribution curves, time series
//! (load-test latency) and annotated frame strips, with text in a built-in 3×5 pixel font.

/// One curve of a CED plot.
#[derive(Debug, Clone)]
pub struct Curve {
    /// Legend label (lowercase letters, digits, `-`, `.`, `%`, space).
    pub label: String,
    /// Per-sample errors (infinite or NaN = no answer).
    pub errors: Vec<f64>,
}

const W: usize = 640;
const H: usize = 420;
const LEFT: usize = 50;
const BOTTOM: usize = 40;
const TOP: usize = 20;
const RIGHT: usize = 20;
const COLOURS: [[u8; 3]; 6] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [255, 127, 14],
    [148, 103, 189],
    [23, 23, 23],
];

/// 3×5 glyphs, one row per 3 bits (MSB left).
fn glyph(c: char) -> [u8; 5] {
    match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '%' => [5, 1, 2, 4, 5],
        '+' => [0, 2, 7, 2, 0],
        '-' => [0, 0, 7, 0, 0],
        '=' => [0, 7, 0, 7, 0],
        'a' => [2, 5, 7, 5, 5],
        'b' => [6, 5, 6, 5, 6],
        'c' => [7, 4, 4, 4, 7],
        'd' => [6, 5, 5, 5, 6],
        'e' => [7, 4, 6, 4, 7],
        'f' => [7, 4, 6, 4, 4],
        'g' => [7, 4, 5, 5, 7],
        'h' => [5, 5, 7, 5, 5],
        'i' => [7, 2, 2, 2, 7],
        'j' => [1, 1, 1, 5, 7],
        'k' => [5, 5, 6, 5, 5],
        'l' => [4, 4, 4, 4, 7],
        'm' => [5, 7, 7, 5, 5],
        'n' => [6, 5, 5, 5, 5],
        'o' => [7, 5, 5, 5, 7],
        'p' => [7, 5, 7, 4, 4],
        'q' => [7, 5, 5, 7, 1],
        'r' => [6, 5, 6, 5, 5],
        's' => [7, 4, 7, 1, 7],
        't' => [7, 2, 2, 2, 2],
        'u' => [5, 5, 5, 5, 7],
        'v' => [5, 5, 5, 5, 2],
        'w' => [5, 5, 7, 7, 5],
        'x' => [5, 5, 2, 5, 5],
        'y' => [5, 5, 2, 2, 2],
        'z' => [7, 1, 2, 4, 7],
        _ => [0; 5],
    }
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
    /// Encodes as PNG.
    pub fn to_png(&self) -> Vec<u8> {
        let mut png = Vec::new();
        let enc = image::codecs::png::PngEncoder::new(&mut png);
        // Encoding an in-memory RGB buffer of the right size cannot fail; an empty Vec shows as a bad file.
        let _ = image::ImageEncoder::write_image(
            enc,
            &self.px,
            self.w as u32,
            self.h as u32,
            image::ExtendedColorType::Rgb8,
        );
        png
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
    /// Text in the built-in font (2x scale, 8 px per character).
    pub fn text(&mut self, x: i64, y: i64, s: &str, c: [u8; 3]) {
        let scale = 2;
        for (k, ch) in s.chars().enumerate() {
            let g = glyph(ch.to_ascii_lowercase());
            for (row, bits) in g.iter().enumerate() {
                for col in 0..3 {
                    if bits & (4 >> col) != 0 {
                        for sy in 0..scale {
                            for sx in 0..scale {
                                self.set(
                                    x + (k as i64) * 4 * scale + col * scale + sx,
                                    y + row as i64 * scale + sy,
                                    c,
                                );
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Renders the CED of each curve from 0 to `max_error` as a PNG: x = error (normalised), y = share of
/// samples with error ≤ x. Samples without an answer count in the denominator, never in the curve.
pub fn ced_plot_png(curves: &[Curve], max_error: f64) -> Vec<u8> {
    let mut cv = Canvas::new(W, H);
    let (pw, ph) = ((W - LEFT - RIGHT) as f64, (H - TOP - BOTTOM) as f64);
    let to_px = |e: f64, f: f64| (LEFT as f64 + e / max_error * pw, TOP as f64 + (1.0 - f) * ph);
    let grey = [200, 200, 200];
    let black = [0, 0, 0];
    for k in 0..=4 {
        let f = k as f64 / 4.0;
        cv.line(to_px(0.0, f), to_px(max_error, f), grey, 1);
        cv.text(8, to_px(0.0, f).1 as i64 - 5, &format!("{:.2}", f), black);
    }
    for k in 0..=8 {
        let e = max_error * k as f64 / 8.0;
        cv.line(to_px(e, 0.0), to_px(e, 1.0), grey, 1);
        cv.text(
            to_px(e, 0.0).0 as i64 - 12,
            (H - BOTTOM + 8) as i64,
            &format!("{:.3}", e),
            black,
        );
    }
    cv.line(to_px(0.0, 0.0), to_px(max_error, 0.0), black, 1);
    cv.line(to_px(0.0, 0.0), to_px(0.0, 1.0), black, 1);
    cv.text(
        (W / 2 - 40) as i64,
        (H - 14) as i64,
        "nme - outer eye corners",
        black,
    );
    for (ci, curve) in curves.iter().enumerate() {
        let colour = COLOURS[ci % COLOURS.len()];
        let mut sorted: Vec<f64> = curve.errors.iter().copied().filter(|e| e.is_finite()).collect();
        sorted.sort_by(f64::total_cmp);
        let total = curve.errors.len().max(1) as f64;
        let steps = 400;
        let mut prev = to_px(0.0, sorted.partition_point(|&e| e <= 0.0) as f64 / total);
        for k in 1..=steps {
            let e = max_error * k as f64 / steps as f64;
            let cur = to_px(e, sorted.partition_point(|&x| x <= e) as f64 / total);
            cv.line(prev, cur, colour, 2);
            prev = cur;
        }
        let ly = TOP as i64 + 10 + 16 * ci as i64;
        cv.line(
            ((LEFT + 20) as f64, ly as f64 + 4.0),
            ((LEFT + 40) as f64, ly as f64 + 4.0),
            colour,
            3,
        );
        cv.text((LEFT + 48) as i64, ly, &curve.label, colour);
    }
    cv.to_png()
}

/// One series of a time plot.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend label.
    pub label: String,
    /// (x, y) points in data units.
    pub points: Vec<(f64, f64)>,
}

/// A line plot of `series` (x from 0 to the largest x, y from 0 to the largest y), with axis labels.
pub fn series_plot_png(series: &[Series], x_label: &str, y_label: &str) -> Vec<u8> {
    let mut cv = Canvas::new(W, H);
    let x_max = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.0))
        .fold(1e-9, f64::max);
    let y_max = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.1))
        .fold(1e-9, f64::max)
        * 1.1;
    let (pw, ph) = ((W - LEFT - RIGHT) as f64, (H - TOP - BOTTOM) as f64);
    let to_px = |x: f64, y: f64| (LEFT as f64 + x / x_max * pw, TOP as f64 + (1.0 - y / y_max) * ph);
    let (grey, black) = ([200, 200, 200], [0, 0, 0]);
    for k in 0..=4 {
        let y = y_max * k as f64 / 4.0;
        cv.line(to_px(0.0, y), to_px(x_max, y), grey, 1);
        cv.text(4, to_px(0.0, y).1 as i64 - 5, &format!("{y:.1}"), black);
        let x = x_max * k as f64 / 4.0;
        cv.line(to_px(x, 0.0), to_px(x, y_max), grey, 1);
        cv.text(
            to_px(x, 0.0).0 as i64 - 12,
            (H - BOTTOM + 8) as i64,
            &format!("{x:.0}"),
            black,
        );
    }
    cv.line(to_px(0.0, 0.0), to_px(x_max, 0.0), black, 1);
    cv.line(to_px(0.0, 0.0), to_px(0.0, y_max), black, 1);
    cv.text((W / 2 - 40) as i64, (H - 14) as i64, x_label, black);
    cv.text(LEFT as i64 + 4, 4, y_label, black);
    for (ci, s) in series.iter().enumerate() {
        let colour = COLOURS[ci % COLOURS.len()];
        for w in s.points.windows(2) {
            cv.line(to_px(w[0].0, w[0].1), to_px(w[1].0, w[1].1), colour, 2);
        }
        let ly = TOP as i64 + 10 + 16 * ci as i64;
        cv.line(
            ((W - 200) as f64, ly as f64 + 4.0),
            ((W - 180) as f64, ly as f64 + 4.0),
            colour,
            3,
        );
        cv.text((W - 172) as i64, ly, &s.label, colour);
    }
    cv.to_png()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plot_is_a_png_with_the_curve_drawn() {
        let png = ced_plot_png(
            &[Curve {
                label: "dan".into(),
                errors: vec![0.01, 0.02, 0.03, f64::INFINITY],
            }],
            0.08,
        );
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (W as u32, H as u32));
        // The curve reaches 3/4 at the right edge: a blue pixel near (x_max, 1/4 from the top of the plot).
        let y = TOP as f64 + 0.25 * (H - TOP - BOTTOM) as f64;
        let x = (W - RIGHT - 2) as u32;
        let found = (y as u32 - 3..y as u32 + 3).any(|yy| img.get_pixel(x, yy).0 == COLOURS[0]);
        assert!(found);
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
