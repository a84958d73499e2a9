//! Line charts written as SVG (crisp, for papers) and PNG (for a quick look), with nothing but
//! a public-domain 8x8 bitmap font for the PNG's text: no system fonts, no renderer.
//!
//! ```no_run
//! use flowmimic_plot::{Chart, Series};
//! let chart = Chart::new("reward", "iteration", "mean reward")
//!     .series(Series::line("reward", vec![(1.0, 0.5), (2.0, 0.8)]));
//! chart.save(std::path::Path::new("runs/reward")).unwrap(); // reward.svg and reward.png
//! ```

use font8x8::UnicodeFonts;
use std::fmt::Write;
use std::path::Path;

const WIDTH: usize = 800;
const HEIGHT: usize = 500;
const LEFT: f64 = 100.0;
const RIGHT: f64 = 20.0;
const TOP: f64 = 48.0;
const BOTTOM: f64 = 64.0;
/// The PNG's text: the 8x8 font drawn at twice its size (16 px), legible at 800 x 500.
const TEXT_SCALE: i64 = 2;
const CHAR: f64 = 8.0 * TEXT_SCALE as f64;
/// The legend's rows and its margin from the plot's edges, pixels.
const LEGEND_ROW: f64 = 22.0;
const LEGEND_MARGIN: f64 = 8.0;
const PALETTE: [[u8; 3]; 6] =
    [[31, 119, 180], [214, 39, 40], [44, 160, 44], [255, 127, 14], [148, 103, 189], [127, 127, 127]];

/// Fraction of `values` in each of `bins` equal bins on `[lo, hi)`, as (bin centre, fraction);
/// values outside count in the total but in no bin.
pub fn histogram(values: &[f64], lo: f64, hi: f64, bins: usize) -> Vec<(f64, f64)> {
    let mut counts = vec![0.0; bins];
    for v in values {
        let b = (((v - lo) / (hi - lo)) * bins as f64).floor();
        if b >= 0.0 && (b as usize) < bins {
            counts[b as usize] += 1.0;
        }
    }
    let total = values.len().max(1) as f64;
    counts.iter().enumerate().map(|(b, c)| (lo + (b as f64 + 0.5) * (hi - lo) / bins as f64, c / total)).collect()
}

/// One line, optionally with a shaded band (e.g. mean +- std).
#[derive(Clone, Debug)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// (x, low, high).
    pub band: Vec<(f64, f64, f64)>,
}

impl Series {
    pub fn line(name: &str, points: Vec<(f64, f64)>) -> Self {
        Self { name: name.into(), points, band: Vec::new() }
    }

    pub fn with_band(mut self, band: Vec<(f64, f64, f64)>) -> Self {
        self.band = band;
        self
    }
}

/// A chart of one or more series.
#[derive(Clone, Debug)]
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub series: Vec<Series>,
}

/// Maps data to pixels.
struct Frame {
    x: (f64, f64),
    y: (f64, f64),
    log_x: bool,
}

impl Frame {
    fn px(&self, x: f64) -> f64 {
        let t = |v: f64| if self.log_x { v.max(1e-300).log10() } else { v };
        LEFT + (t(x) - t(self.x.0)) / (t(self.x.1) - t(self.x.0)).max(1e-12) * (WIDTH as f64 - LEFT - RIGHT)
    }

    fn py(&self, y: f64) -> f64 {
        HEIGHT as f64 - BOTTOM - (y - self.y.0) / (self.y.1 - self.y.0).max(1e-12) * (HEIGHT as f64 - TOP - BOTTOM)
    }
}

/// About five round tick values covering `[lo, hi]`.
fn ticks(lo: f64, hi: f64) -> Vec<f64> {
    let span = (hi - lo).max(1e-12);
    let raw = span / 5.0;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * mag).find(|s| span / s <= 6.0).unwrap_or(10.0 * mag);
    let first = (lo / step).ceil();
    // At most a dozen, even where the values are so large that k and k + 1 give the same
    // float (an axis near 1e18 with a span of 100 once looped for practically ever).
    (0..12).map(|k| (first + k as f64) * step).take_while(|v| *v <= hi + 1e-9 * span).collect()
}

fn label(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e5 || v.abs() < 1e-3) {
        format!("{v:.0e}")
    } else {
        let s = format!("{v:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

impl Chart {
    pub fn new(title: &str, x_label: &str, y_label: &str) -> Self {
        Self { title: title.into(), x_label: x_label.into(), y_label: y_label.into(), log_x: false, series: Vec::new() }
    }

    pub fn series(mut self, s: Series) -> Self {
        self.series.push(s);
        self
    }

    pub fn log_x(mut self) -> Self {
        self.log_x = true;
        self
    }

    fn frame(&self) -> Frame {
        let xs = self.series.iter().flat_map(|s| s.points.iter().map(|p| p.0));
        let ys =
            self.series.iter().flat_map(|s| s.points.iter().map(|p| p.1).chain(s.band.iter().flat_map(|b| [b.1, b.2])));
        let finite = |v: f64| v.is_finite() && (!self.log_x || v > 0.0);
        let (mut x0, mut x1) = xs.filter(|v| finite(*v)).fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
        let (mut y0, mut y1) =
            ys.filter(|v| v.is_finite()).fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
        if x0 > x1 {
            (x0, x1) = (0.0, 1.0);
        }
        if y0 > y1 {
            (y0, y1) = (0.0, 1.0);
        }
        if x0 == x1 {
            x1 = x0 + 1.0;
        }
        let pad = if y1 > y0 { 0.05 * (y1 - y0) } else { 0.5 };
        Frame { x: (x0, x1), y: (y0 - pad, y1 + pad), log_x: self.log_x }
    }

    /// The legend's size in pixels (line sample and names).
    fn legend_size(&self) -> (f64, f64) {
        let longest = self.series.iter().map(|s| s.name.chars().count()).max().unwrap_or(0);
        (36.0 + CHAR * longest as f64 + 8.0, LEGEND_ROW * self.series.len() as f64 + 4.0)
    }

    /// The frame and the legend's top-left corner: the corner of the plot where the legend
    /// covers the fewest data points; where every corner covers some, the y range grows at the
    /// top to leave the legend room there.
    fn layout(&self) -> (Frame, (f64, f64)) {
        let mut f = self.frame();
        let (w, h) = self.legend_size();
        let (x0, x1, y0, y1) = (LEFT, WIDTH as f64 - RIGHT, TOP, HEIGHT as f64 - BOTTOM);
        let m = LEGEND_MARGIN;
        let corners = [(x0 + m, y0 + m), (x1 - m - w, y0 + m), (x1 - m - w, y1 - m - h), (x0 + m, y1 - m - h)];
        // Pixels of the lines (sampled every 4 px along each segment) and bands inside a box.
        let covered = |f: &Frame, (cx, cy): (f64, f64)| {
            let inside = |(px, py): (f64, f64)| px >= cx && px <= cx + w && py >= cy && py <= cy + h;
            let along = |a: (f64, f64), b: (f64, f64)| {
                // Segments leave the plot at most by its diagonal; a segment to infinity, not at all.
                let length = (b.0 - a.0).hypot(b.1 - a.1);
                let steps = if length.is_finite() { (length / 4.0).ceil().clamp(1.0, 400.0) as usize } else { 0 };
                (0..=steps).filter(move |&i| {
                    let t = i as f64 / steps as f64;
                    inside((a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1)))
                })
            };
            self.series
                .iter()
                .map(|s| {
                    let pts: Vec<(f64, f64)> =
                        s.points.iter().filter(|p| p.1.is_finite()).map(|p| (f.px(p.0), f.py(p.1))).collect();
                    let line: usize = pts.windows(2).map(|p| along(p[0], p[1]).count()).sum();
                    let alone = usize::from(pts.len() == 1 && inside(pts[0]));
                    let band =
                        s.band.iter().filter(|b| inside((f.px(b.0), f.py(b.1))) || inside((f.px(b.0), f.py(b.2))));
                    line + alone + band.count()
                })
                .sum::<usize>()
        };
        if self.series.len() < 2 && self.series.iter().all(|s| s.name.is_empty()) {
            return (f, corners[0]);
        }
        let best = corners.iter().copied().min_by_key(|&c| covered(&f, c)).expect("four corners");
        if covered(&f, best) == 0 {
            return (f, best);
        }
        // Headroom: the data's top stays below the legend.
        let plot = y1 - y0;
        let room = (h + 2.0 * m) / plot;
        f.y.1 += (f.y.1 - f.y.0) * room / (1.0 - room).max(0.2);
        (f, corners[0])
    }

    fn x_ticks(&self, f: &Frame) -> Vec<f64> {
        if self.log_x {
            let (a, b) = (f.x.0.log10().floor() as i32, f.x.1.log10().ceil() as i32);
            (a..=b)
                .flat_map(|e| [1.0, 2.0, 5.0].map(|m| m * 10f64.powi(e)))
                .filter(|v| *v >= f.x.0 * 0.999 && *v <= f.x.1 * 1.001)
                .collect()
        } else {
            ticks(f.x.0, f.x.1)
        }
    }

    /// The chart as an SVG document.
    pub fn svg(&self) -> String {
        let (f, (lx, ly)) = self.layout();
        let mut s = String::new();
        let _ = writeln!(
            s,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" font-family="sans-serif" font-size="13">"#
        );
        let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
        let (x0, x1, y0, y1) = (LEFT, WIDTH as f64 - RIGHT, TOP, HEIGHT as f64 - BOTTOM);
        let _ = writeln!(
            s,
            r#"<rect x="{x0}" y="{y0}" width="{}" height="{}" fill="none" stroke="black"/>"#,
            x1 - x0,
            y1 - y0
        );
        for t in self.x_ticks(&f) {
            let x = f.px(t);
            let _ = writeln!(
                s,
                r##"<line x1="{x:.1}" y1="{y1}" x2="{x:.1}" y2="{y0}" stroke="#ddd"/><text x="{x:.1}" y="{}" text-anchor="middle">{}</text>"##,
                y1 + 18.0,
                label(t)
            );
        }
        for t in ticks(f.y.0, f.y.1) {
            let y = f.py(t);
            let _ = writeln!(
                s,
                r##"<line x1="{x0}" y1="{y:.1}" x2="{x1}" y2="{y:.1}" stroke="#ddd"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
                x0 - 6.0,
                y + 4.0,
                label(t)
            );
        }
        for (k, series) in self.series.iter().enumerate() {
            let [r, g, b] = PALETTE[k % PALETTE.len()];
            if !series.band.is_empty() {
                let upper = series.band.iter().map(|p| format!("{:.1},{:.1}", f.px(p.0), f.py(p.2)));
                let lower = series.band.iter().rev().map(|p| format!("{:.1},{:.1}", f.px(p.0), f.py(p.1)));
                let pts: Vec<String> = upper.chain(lower).collect();
                let _ =
                    writeln!(s, r#"<polygon points="{}" fill="rgb({r},{g},{b})" fill-opacity="0.2"/>"#, pts.join(" "));
            }
            let pts: Vec<String> = series
                .points
                .iter()
                .filter(|p| p.1.is_finite())
                .map(|p| format!("{:.1},{:.1}", f.px(p.0), f.py(p.1)))
                .collect();
            let _ = writeln!(
                s,
                r#"<polyline points="{}" fill="none" stroke="rgb({r},{g},{b})" stroke-width="2"/>"#,
                pts.join(" ")
            );
            let row = ly + LEGEND_ROW * (k as f64 + 0.5) + 2.0;
            let _ = writeln!(
                s,
                r#"<line x1="{}" y1="{row}" x2="{}" y2="{row}" stroke="rgb({r},{g},{b})" stroke-width="3"/><text x="{}" y="{}" font-size="15">{}</text>"#,
                lx + 6.0,
                lx + 28.0,
                lx + 36.0,
                row + 5.0,
                escape(&series.name)
            );
        }
        let _ = writeln!(
            s,
            r#"<text x="{}" y="24" text-anchor="middle" font-size="16">{}</text>"#,
            WIDTH / 2,
            escape(&self.title)
        );
        let _ = writeln!(
            s,
            r#"<text x="{}" y="{}" text-anchor="middle">{}</text>"#,
            (x0 + x1) / 2.0,
            HEIGHT - 15,
            escape(&self.x_label)
        );
        let _ = writeln!(
            s,
            r#"<text x="18" y="{}" text-anchor="middle" transform="rotate(-90 18 {})">{}</text>"#,
            (y0 + y1) / 2.0,
            (y0 + y1) / 2.0,
            escape(&self.y_label)
        );
        s.push_str("</svg>\n");
        s
    }

    /// The chart as PNG bytes.
    pub fn png(&self) -> Vec<u8> {
        let (f, (lx, ly)) = self.layout();
        let mut c = Canvas { px: vec![255; WIDTH * HEIGHT * 3] };
        let (x0, x1, y0, y1) = (LEFT, WIDTH as f64 - RIGHT, TOP, HEIGHT as f64 - BOTTOM);
        let grey = [221, 221, 221];
        for t in self.x_ticks(&f) {
            let x = f.px(t);
            c.line((x, y0), (x, y1), grey, 1);
            c.text(&label(t), x, y1 + 8.0, true);
        }
        for t in ticks(f.y.0, f.y.1) {
            let y = f.py(t);
            c.line((x0, y), (x1, y), grey, 1);
            let l = label(t);
            c.text(&l, x0 - 6.0 - CHAR * l.len() as f64 / 2.0, y - CHAR / 2.0, true);
        }
        for (k, series) in self.series.iter().enumerate() {
            let colour = PALETTE[k % PALETTE.len()];
            for w in series.band.windows(2) {
                let (xa, xb) = (f.px(w[0].0), f.px(w[1].0));
                for x in xa.round() as i64..=xb.round() as i64 {
                    let t = if xb > xa { (x as f64 - xa) / (xb - xa) } else { 0.0 };
                    let lo = f.py(w[0].1 + t * (w[1].1 - w[0].1));
                    let hi = f.py(w[0].2 + t * (w[1].2 - w[0].2));
                    for y in hi.round() as i64..=lo.round() as i64 {
                        c.blend(x, y, colour, 0.2);
                    }
                }
            }
            let pts: Vec<(f64, f64)> =
                series.points.iter().filter(|p| p.1.is_finite()).map(|p| (f.px(p.0), f.py(p.1))).collect();
            for w in pts.windows(2) {
                c.line(w[0], w[1], colour, 2);
            }
            let row = ly + LEGEND_ROW * (k as f64 + 0.5) + 2.0;
            c.line((lx + 6.0, row), (lx + 28.0, row), colour, 3);
            c.text(&series.name, lx + 36.0, row - CHAR / 2.0, false);
        }
        for (a, b) in [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))] {
            c.line(a, b, [0, 0, 0], 1);
        }
        c.fitted(&self.title, WIDTH as f64 / 2.0, 4.0);
        c.fitted(&self.x_label, (x0 + x1) / 2.0, HEIGHT as f64 - CHAR - 6.0);
        c.text(&self.y_label, 4.0, TOP - CHAR - 6.0, false);
        c.encode()
    }

    /// Writes `<stem>.svg` and `<stem>.png` atomically.
    pub fn save(&self, stem: &Path) -> Result<(), flowmimic_io::FileError> {
        flowmimic_io::write_atomic(&stem.with_extension("svg"), self.svg().as_bytes())?;
        flowmimic_io::write_atomic(&stem.with_extension("png"), &self.png())
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

struct Canvas {
    px: Vec<u8>,
}

impl Canvas {
    fn blend(&mut self, x: i64, y: i64, c: [u8; 3], alpha: f64) {
        if x < 0 || y < 0 || x >= WIDTH as i64 || y >= HEIGHT as i64 {
            return;
        }
        let i = (y as usize * WIDTH + x as usize) * 3;
        for k in 0..3 {
            self.px[i + k] = (f64::from(self.px[i + k]) * (1.0 - alpha) + f64::from(c[k]) * alpha).round() as u8;
        }
    }

    fn line(&mut self, a: (f64, f64), b: (f64, f64), c: [u8; 3], width: i64) {
        let steps = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().max(1.0) as i64;
        for s in 0..=steps {
            let t = s as f64 / steps as f64;
            let (x, y) = ((a.0 + t * (b.0 - a.0)).round() as i64, (a.1 + t * (b.1 - a.1)).round() as i64);
            for dx in 0..width {
                for dy in 0..width {
                    self.blend(x + dx - width / 2, y + dy - width / 2, c, 1.0);
                }
            }
        }
    }

    /// Text in the 8x8 font at [`TEXT_SCALE`], its top-left at (x, y), or centred on x.
    fn text(&mut self, s: &str, x: f64, y: f64, centred: bool) {
        self.text_at(s, x, y, centred, TEXT_SCALE);
    }

    /// Text at [`TEXT_SCALE`], or at half of it where that is too wide for the image (a long
    /// title), centred on x.
    fn fitted(&mut self, s: &str, x: f64, y: f64) {
        let fits = CHAR * s.chars().count() as f64 <= WIDTH as f64 - 8.0;
        self.text_at(s, x, y, true, if fits { TEXT_SCALE } else { (TEXT_SCALE / 2).max(1) });
    }

    fn text_at(&mut self, s: &str, x: f64, y: f64, centred: bool, scale: i64) {
        let char = 8.0 * scale as f64;
        let x = if centred { x - char / 2.0 * s.chars().count() as f64 } else { x };
        for (k, ch) in s.chars().enumerate() {
            let glyph = font8x8::BASIC_FONTS.get(ch).or_else(|| font8x8::BASIC_FONTS.get('?')).unwrap_or([0; 8]);
            for (row, bits) in glyph.iter().enumerate() {
                for col in 0..8 {
                    if bits & (1 << col) != 0 {
                        for (dx, dy) in (0..scale).flat_map(|dx| (0..scale).map(move |dy| (dx, dy))) {
                            let px = x as i64 + char as i64 * k as i64 + scale * col + dx;
                            self.blend(px, y as i64 + scale * row as i64 + dy, [0, 0, 0], 1.0);
                        }
                    }
                }
            }
        }
    }

    fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, WIDTH as u32, HEIGHT as u32);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header().expect("in-memory PNG header");
            w.write_image_data(&self.px).expect("in-memory PNG data");
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_end_on_absurd_ranges() {
        assert!(ticks(1e18, 1e18 + 100.0).len() <= 12);
        assert!(ticks(-f64::MAX, f64::MAX).len() <= 12);
        let chart = Chart::new("t", "x", "y")
            .series(Series::line("a", vec![(1e18, 1.0), (1e18 + 50.0, 2.0), (f64::INFINITY, 3.0)]));
        assert!(!chart.svg().is_empty());
    }

    #[test]
    fn ticks_are_round_and_cover_the_range() {
        let close = |a: Vec<f64>, b: &[f64]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12);
        assert!(close(ticks(0.0, 10.0), &[0.0, 2.0, 4.0, 6.0, 8.0, 10.0]));
        assert!(close(ticks(0.13, 0.61), &[0.2, 0.3, 0.4, 0.5, 0.6]));
    }

    #[test]
    fn the_legend_goes_where_it_covers_no_data() {
        // A falling line through the top-left and bottom-right corners, a flat one along the
        // middle: the legend takes the top-right corner.
        let falling: Vec<(f64, f64)> = (0..=100).map(|i| (i as f64, 100.0 - i as f64)).collect();
        let flat: Vec<(f64, f64)> = (0..=100).map(|i| (i as f64, 50.0)).collect();
        let chart = Chart::new("t", "x", "y")
            .series(Series::line("falling", falling.clone()))
            .series(Series::line("flat", flat.clone()));
        let (f, (lx, ly)) = chart.layout();
        let (w, h) = chart.legend_size();
        assert!(lx > WIDTH as f64 / 2.0 && ly < HEIGHT as f64 / 2.0, "legend at ({lx}, {ly})");
        let covered = falling.iter().chain(&flat).filter(|p| {
            let (x, y) = (f.px(p.0), f.py(p.1));
            x >= lx && x <= lx + w && y >= ly && y <= ly + h
        });
        assert_eq!(covered.count(), 0);
        // Data in every corner: the y range grows so that the legend sits above it.
        let corners = vec![(0.0, 0.0), (0.0, 100.0), (100.0, 100.0), (100.0, 0.0), (0.0, 0.0)];
        let chart = Chart::new("t", "x", "y").series(Series::line("box", corners)).series(Series::line("b", flat));
        let (f, (_, ly)) = chart.layout();
        assert!(f.py(100.0) > ly + chart.legend_size().1, "the data's top below the legend");
    }

    #[test]
    fn charts_render_lines_where_the_data_is() {
        let chart = Chart::new("t", "x", "y")
            .series(Series::line("a", vec![(0.0, 0.0), (1.0, 1.0)]).with_band(vec![(0.0, -0.1, 0.1), (1.0, 0.9, 1.1)]));
        let svg = chart.svg();
        assert!(svg.starts_with("<svg") && svg.contains("<polyline") && svg.contains("<polygon"));
        let png = chart.png();
        assert_eq!(&png[1..4], b"PNG");
        // Decode and check the line's colour at the middle of the plot.
        let decoder = png::Decoder::new(std::io::Cursor::new(png));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut buf).unwrap();
        let f = chart.layout().0;
        let (x, y) = (f.px(0.5).round() as usize, f.py(0.5).round() as usize);
        let i = (y * WIDTH + x) * 3;
        assert_eq!(&buf[i..i + 3], &PALETTE[0], "line drawn through (0.5, 0.5)");
    }
}
