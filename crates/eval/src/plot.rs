//! Line plots as PNG without font or drawing libraries: lines are rasterised into an RGB buffer,
//! text uses a built-in 3×5 pixel font (upper case, digits and a few signs), and the `png` crate
//! encodes the result in memory.

use std::fmt;

/// One line of a plot; NaN `y` values break the line.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    pub label: String,
    pub color: [u8; 3],
    pub dashed: bool,
    pub points: Vec<(f64, f64)>,
}

/// Axes and size of a plot.
#[derive(Clone, Debug, PartialEq)]
pub struct PlotSpec {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub x_max: f64,
    pub y_min: f64,
    pub y_max: f64,
    pub width: u32,
    pub height: u32,
}

/// Colours of the four methods (the usual categorical palette).
pub const PALETTE: [[u8; 3]; 6] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
];

const BLACK: [u8; 3] = [0, 0, 0];
const GRID: [u8; 3] = [225, 225, 225];

/// Why a plot could not be produced.
#[derive(Debug)]
pub struct PlotError(String);

impl fmt::Display for PlotError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "plot: {}", self.0)
    }
}

impl std::error::Error for PlotError {}

/// An RGB8 raster.
#[derive(Clone, Debug)]
pub struct Canvas {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Canvas {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            rgb: vec![255; width as usize * height as usize * 3],
        }
    }

    pub fn pixel(&self, x: u32, y: u32) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = 3 * (y as usize * self.width as usize + x as usize);
        Some([self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]])
    }

    fn put(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return;
        }
        let i = 3 * (y as usize * self.width as usize + x as usize);
        self.rgb[i..i + 3].copy_from_slice(&c);
    }

    fn rect(&mut self, x0: i64, y0: i64, w: i64, h: i64, c: [u8; 3]) {
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                self.put(x, y, c);
            }
        }
    }

    /// A line `thickness` pixels wide; dashed lines draw 8 pixels, skip 5.
    pub fn line(
        &mut self,
        (x0, y0): (f64, f64),
        (x1, y1): (f64, f64),
        c: [u8; 3],
        thickness: i64,
        dashed: bool,
        dash_phase: &mut f64,
    ) {
        if ![x0, y0, x1, y1].iter().all(|v| v.is_finite()) {
            return;
        }
        let length = ((x1 - x0).powi(2) + (y1 - y0).powi(2)).sqrt();
        let steps = length.ceil().clamp(1.0, 1e5) as usize;
        let half = thickness / 2;
        for i in 0..=steps {
            let t = i as f64 / steps as f64;
            let on = !dashed || (*dash_phase + t * length) % 13.0 < 8.0;
            if on {
                let x = (x0 + t * (x1 - x0)).round() as i64;
                let y = (y0 + t * (y1 - y0)).round() as i64;
                self.rect(x - half, y - half, thickness, thickness, c);
            }
        }
        *dash_phase += length;
    }

    /// Text in the 3×5 font, `scale` pixels per font pixel, top-left at `(x, y)`.
    pub fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, c: [u8; 3]) {
        let mut cx = x;
        for ch in s.chars() {
            let glyph = glyph(ch);
            for (row, bits) in glyph.iter().enumerate() {
                for col in 0..3 {
                    if bits & (0b100 >> col) != 0 {
                        self.rect(cx + col * scale, y + row as i64 * scale, scale, scale, c);
                    }
                }
            }
            cx += 4 * scale;
        }
    }

    /// Text rotated by 90° (reading bottom to top), bottom-left at `(x, y)`.
    fn text_vertical(&mut self, x: i64, y: i64, s: &str, scale: i64, c: [u8; 3]) {
        let mut cy = y;
        for ch in s.chars() {
            let glyph = glyph(ch);
            for (row, bits) in glyph.iter().enumerate() {
                for col in 0..3 {
                    if bits & (0b100 >> col) != 0 {
                        self.rect(x + row as i64 * scale, cy - col * scale, scale, scale, c);
                    }
                }
            }
            cy -= 4 * scale;
        }
    }

    /// PNG bytes of the canvas.
    pub fn to_png(&self) -> Result<Vec<u8>, PlotError> {
        let mut out = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut out, self.width, self.height);
            encoder.set_color(png::ColorType::Rgb);
            encoder.set_depth(png::BitDepth::Eight);
            let mut writer = encoder
                .write_header()
                .map_err(|e| PlotError(e.to_string()))?;
            writer
                .write_image_data(&self.rgb)
                .map_err(|e| PlotError(e.to_string()))?;
            writer.finish().map_err(|e| PlotError(e.to_string()))?;
        }
        Ok(out)
    }
}

/// Text width in pixels at a scale.
pub fn text_width(s: &str, scale: i64) -> i64 {
    (s.chars().count() as i64 * 4 - 1).max(0) * scale
}

/// 3×5 glyphs, one row per entry, bit 2 = left column. Lower case is drawn as upper case;
/// unknown characters as a blank.
fn glyph(ch: char) -> [u8; 5] {
    match ch.to_ascii_uppercase() {
        '0' | 'O' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' | 'S' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        ',' => [0, 0, 0, 2, 4],
        '-' => [0, 0, 7, 0, 0],
        '_' => [0, 0, 0, 0, 7],
        '(' => [1, 2, 2, 2, 1],
        ')' => [4, 2, 2, 2, 4],
        '/' => [1, 1, 2, 4, 4],
        '>' => [4, 2, 1, 2, 4],
        '<' => [1, 2, 4, 2, 1],
        ':' => [0, 2, 0, 2, 0],
        '=' => [0, 7, 0, 7, 0],
        '%' => [5, 1, 2, 4, 5],
        'A' => [2, 5, 7, 5, 5],
        'B' => [6, 5, 6, 5, 6],
        'C' => [7, 4, 4, 4, 7],
        'D' => [6, 5, 5, 5, 6],
        'E' => [7, 4, 7, 4, 7],
        'F' => [7, 4, 7, 4, 4],
        'G' => [7, 4, 5, 5, 7],
        'H' => [5, 5, 7, 5, 5],
        'I' => [7, 2, 2, 2, 7],
        'J' => [1, 1, 1, 5, 7],
        'K' => [5, 5, 6, 5, 5],
        'L' => [4, 4, 4, 4, 7],
        'M' => [5, 7, 7, 5, 5],
        'N' => [6, 5, 5, 5, 5],
        'P' => [7, 5, 7, 4, 4],
        'Q' => [7, 5, 5, 7, 1],
        'R' => [6, 5, 6, 5, 5],
        'T' => [7, 2, 2, 2, 2],
        'U' => [5, 5, 5, 5, 7],
        'V' => [5, 5, 5, 5, 2],
        'W' => [5, 5, 7, 7, 5],
        'X' => [5, 5, 2, 5, 5],
        'Y' => [5, 5, 2, 2, 2],
        'Z' => [7, 1, 2, 4, 7],
        _ => [0; 5],
    }
}

/// A "nice" tick step giving about `target` intervals over `span`.
fn tick_step(span: f64, target: f64) -> f64 {
    if !(span.is_finite() && span > 0.0) {
        return 1.0;
    }
    let raw = span / target;
    let magnitude = 10f64.powf(raw.log10().floor());
    let norm = raw / magnitude;
    let nice = if norm <= 1.0 {
        1.0
    } else if norm <= 2.0 {
        2.0
    } else if norm <= 2.5 {
        2.5
    } else if norm <= 3.0 {
        3.0
    } else if norm <= 5.0 {
        5.0
    } else {
        10.0
    };
    nice * magnitude
}

fn tick_label(v: f64, step: f64) -> String {
    // The fewest decimals that show the step exactly.
    let decimals = (0..6)
        .find(|&d| {
            let scaled = step * 10f64.powi(d);
            (scaled - scaled.round()).abs() < 1e-6
        })
        .unwrap_or(6) as usize;
    format!("{v:.decimals$}")
}

/// Renders the series into a canvas: axes with ticks and labels, a light grid, a legend on the
/// right.
pub fn render(spec: &PlotSpec, series: &[Series]) -> Canvas {
    let (w, h) = (spec.width.max(200), spec.height.max(150));
    let mut canvas = Canvas::new(w, h);
    let scale = 2;
    let (left, right, top, bottom) = (70i64, 190i64, 40i64, 60i64);
    let (pw, ph) = (i64::from(w) - left - right, i64::from(h) - top - bottom);
    let x_max = if spec.x_max > 0.0 { spec.x_max } else { 1.0 };
    let (y_min, y_max) = if spec.y_max > spec.y_min {
        (spec.y_min, spec.y_max)
    } else {
        (spec.y_min, spec.y_min + 1.0)
    };
    let to_px = |x: f64, y: f64| {
        let y = y.clamp(y_min, y_max);
        (
            left as f64 + x / x_max * pw as f64,
            (top + ph) as f64 - (y - y_min) / (y_max - y_min) * ph as f64,
        )
    };
    // Grid and ticks.
    let x_step = tick_step(x_max, 6.0);
    let y_step = tick_step(y_max - y_min, 5.0);
    let mut phase = 0.0;
    let mut i = 0;
    loop {
        let x = f64::from(i) * x_step;
        if x > x_max + 1e-9 {
            break;
        }
        let (px, _) = to_px(x, y_min);
        canvas.line(
            (px, top as f64),
            (px, (top + ph) as f64),
            GRID,
            1,
            false,
            &mut phase,
        );
        let label = tick_label(x, x_step);
        canvas.text(
            px.round() as i64 - text_width(&label, scale) / 2,
            top + ph + 8,
            &label,
            scale,
            BLACK,
        );
        i += 1;
    }
    let mut j = 0;
    loop {
        let y = y_min + f64::from(j) * y_step;
        if y > y_max + 1e-9 {
            break;
        }
        let (_, py) = to_px(0.0, y);
        canvas.line(
            (left as f64, py),
            ((left + pw) as f64, py),
            GRID,
            1,
            false,
            &mut phase,
        );
        let label = tick_label(y, y_step);
        canvas.text(
            left - 8 - text_width(&label, scale),
            py.round() as i64 - 5,
            &label,
            scale,
            BLACK,
        );
        j += 1;
    }
    // Axes.
    let origin = (left as f64, (top + ph) as f64);
    canvas.line(
        origin,
        ((left + pw) as f64, (top + ph) as f64),
        BLACK,
        2,
        false,
        &mut phase,
    );
    canvas.line(
        origin,
        (left as f64, top as f64),
        BLACK,
        2,
        false,
        &mut phase,
    );
    // Series.
    for s in series {
        let mut phase = 0.0;
        for pair in s.points.windows(2) {
            let ((x0, y0), (x1, y1)) = (pair[0], pair[1]);
            if y0.is_nan() || y1.is_nan() {
                continue;
            }
            canvas.line(
                to_px(x0, y0),
                to_px(x1, y1),
                s.color,
                2,
                s.dashed,
                &mut phase,
            );
        }
    }
    // Titles.
    canvas.text(left, 12, &spec.title, scale, BLACK);
    canvas.text(
        left + pw / 2 - text_width(&spec.x_label, scale) / 2,
        i64::from(h) - 22,
        &spec.x_label,
        scale,
        BLACK,
    );
    canvas.text_vertical(
        10,
        top + ph / 2 + text_width(&spec.y_label, scale) / 2,
        &spec.y_label,
        scale,
        BLACK,
    );
    // Legend.
    let lx = left + pw + 16;
    for (k, s) in series.iter().enumerate() {
        let ly = top + 10 + k as i64 * 22;
        let mut phase = 0.0;
        canvas.line(
            (lx as f64, (ly + 5) as f64),
            ((lx + 34) as f64, (ly + 5) as f64),
            s.color,
            2,
            s.dashed,
            &mut phase,
        );
        canvas.text(lx + 42, ly, &s.label, scale, BLACK);
    }
    canvas
}

/// [`render`] encoded as PNG.
pub fn render_png(spec: &PlotSpec, series: &[Series]) -> Result<Vec<u8>, PlotError> {
    render(spec, series).to_png()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn spec() -> PlotSpec {
        PlotSpec {
            title: "covered roi volume".into(),
            x_label: "time (s)".into(),
            y_label: "share".into(),
            x_max: 180.0,
            y_min: 0.0,
            y_max: 1.0,
            width: 900,
            height: 560,
        }
    }

    #[test]
    fn lines_land_where_the_data_is() {
        let red = [214, 39, 40];
        let series = [Series {
            label: "ours-uu".into(),
            color: red,
            dashed: false,
            points: vec![(0.0, 0.5), (90.0, 0.5), (180.0, f64::NAN)],
        }];
        let canvas = render(&spec(), &series);
        // Plot area: x from 70 to 710, y from 40 to 500; y = 0.5 is row 270.
        assert_eq!(canvas.pixel(200, 270), Some(red));
        // Past the NaN nothing is drawn at that height.
        assert_ne!(canvas.pixel(600, 270), Some(red));
        // The legend shows the colour.
        assert_eq!(canvas.pixel(730, 55), Some(red));
    }

    #[test]
    fn png_decodes_to_the_canvas() {
        let series = [Series {
            label: "explo-up".into(),
            color: PALETTE[1],
            dashed: true,
            points: (0..=180).map(|t| (t as f64, t as f64 / 180.0)).collect(),
        }];
        let canvas = render(&spec(), &series);
        let bytes = canvas.to_png().unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (900, 560));
        assert_eq!(&buf[..info.buffer_size()], &canvas.rgb[..]);
    }

    #[test]
    fn ticks_are_round() {
        assert_eq!(tick_step(180.0, 6.0), 30.0);
        assert_eq!(tick_step(1.0, 5.0), 0.2);
        assert_eq!(tick_step(60.0, 6.0), 10.0);
        assert_eq!(tick_label(0.4, 0.2), "0.4");
        assert_eq!(tick_label(0.25, 0.25), "0.25");
        assert_eq!(tick_label(30.0, 10.0), "30");
        assert_eq!(text_width("ab", 2), 14);
    }
}
