//! Line plots as PNG through `plotters` (its bitmap backend; text through `ab_glyph`, with a
//! TrueType font of the system: DejaVu Sans or Liberation Sans, or the file `GLASSHOUSE_FONT`
//! names), encoded in memory by the `png` crate.

use std::fmt;
use std::sync::OnceLock;

use plotters::element::DashedPathElement;
use plotters::prelude::*;

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

/// Why a plot could not be produced.
#[derive(Debug, Clone)]
pub struct PlotError(String);

impl fmt::Display for PlotError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "plot: {}", self.0)
    }
}

impl std::error::Error for PlotError {}

/// The font family plots are drawn with (registered from a system font on first use).
const FONT: &str = "sans-serif";

/// Where the font is looked for, after `GLASSHOUSE_FONT`: Debian's and Arch's DejaVu Sans and
/// Debian's Liberation Sans.
const FONT_PATHS: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// Registers the plots' font once; a clear error when the system has none.
fn register_font() -> Result<(), PlotError> {
    static REGISTERED: OnceLock<Result<(), PlotError>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            let candidates = std::env::var("GLASSHOUSE_FONT")
                .ok()
                .into_iter()
                .chain(FONT_PATHS.iter().map(|p| p.to_string()));
            for path in candidates {
                if let Ok(bytes) = std::fs::read(&path) {
                    // plotters keeps registered fonts for the process's lifetime.
                    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                    return plotters::style::register_font(FONT, FontStyle::Normal, bytes)
                        .map_err(|_| PlotError(format!("{path} is not a TrueType font")));
                }
            }
            Err(PlotError(
                "no TrueType font for the plots: install Debian's fonts-dejavu-core, or set \
                 GLASSHOUSE_FONT to a .ttf file"
                    .into(),
            ))
        })
        .clone()
}

fn drawing<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> PlotError {
    PlotError(e.to_string())
}

/// The runs of finite points of a series (NaN `y` breaks the line), `y` clamped to the axis.
fn segments(points: &[(f64, f64)], y_min: f64, y_max: f64) -> Vec<Vec<(f64, f64)>> {
    let mut runs = vec![Vec::new()];
    for &(x, y) in points {
        if y.is_finite() && x.is_finite() {
            if let Some(run) = runs.last_mut() {
                run.push((x, y.clamp(y_min, y_max)));
            }
        } else if runs.last().is_some_and(|r| !r.is_empty()) {
            runs.push(Vec::new());
        }
    }
    runs.retain(|r| !r.is_empty());
    runs
}

/// Draws the series into an RGB8 buffer of `spec`'s size: axes with ticks and labels, a light
/// grid, a legend.
pub fn render_rgb(spec: &PlotSpec, series: &[Series]) -> Result<(u32, u32, Vec<u8>), PlotError> {
    register_font()?;
    let (w, h) = (spec.width.max(200), spec.height.max(150));
    let x_max = if spec.x_max > 0.0 { spec.x_max } else { 1.0 };
    let (y_min, y_max) = if spec.y_max > spec.y_min {
        (spec.y_min, spec.y_max)
    } else {
        (spec.y_min, spec.y_min + 1.0)
    };
    let mut rgb = vec![255u8; (w as usize) * (h as usize) * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(drawing)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(&spec.title, (FONT, 22))
            .margin(14)
            .x_label_area_size(46)
            .y_label_area_size(62)
            .build_cartesian_2d(0.0..x_max, y_min..y_max)
            .map_err(drawing)?;
        chart
            .configure_mesh()
            .x_desc(&spec.x_label)
            .y_desc(&spec.y_label)
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 15))
            .light_line_style(RGBColor(238, 238, 238))
            .bold_line_style(RGBColor(215, 215, 215))
            .draw()
            .map_err(drawing)?;
        for s in series {
            let colour = RGBColor(s.color[0], s.color[1], s.color[2]);
            let style = colour.stroke_width(2);
            for (i, run) in segments(&s.points, y_min, y_max).into_iter().enumerate() {
                let drawn = if s.dashed {
                    chart.draw_series(DashedLineSeries::new(run, 9, 6, style))
                } else {
                    chart.draw_series(LineSeries::new(run, style))
                }
                .map_err(drawing)?;
                if i == 0 {
                    let dashed = s.dashed;
                    drawn.label(s.label.as_str()).legend(move |(x, y)| {
                        let sample = vec![(x, y), (x + 24, y)];
                        let style = colour.stroke_width(3);
                        if dashed {
                            DashedPathElement::new(sample, 6, 4, style).into_dyn()
                        } else {
                            PathElement::new(sample, style).into_dyn()
                        }
                    });
                }
            }
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(180, 180, 180))
            .label_font((FONT, 14))
            .draw()
            .map_err(drawing)?;
        root.present().map_err(drawing)?;
    }
    Ok((w, h, rgb))
}

/// [`render_rgb`] encoded as PNG.
pub fn render_png(spec: &PlotSpec, series: &[Series]) -> Result<Vec<u8>, PlotError> {
    let (w, h, rgb) = render_rgb(spec, series)?;
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, w, h);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder
            .write_header()
            .map_err(|e| PlotError(e.to_string()))?;
        writer
            .write_image_data(&rgb)
            .map_err(|e| PlotError(e.to_string()))?;
        writer.finish().map_err(|e| PlotError(e.to_string()))?;
    }
    Ok(out)
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

    fn pixels_of(rgb: &[u8], colour: [u8; 3]) -> Vec<(usize, usize)> {
        rgb.chunks(3)
            .enumerate()
            .filter(|(_, p)| *p == colour)
            .map(|(i, _)| (i % 900, i / 900))
            .collect()
    }

    #[test]
    fn a_flat_line_stops_at_nan_and_its_colour_is_in_the_legend() {
        let red = [214, 39, 40];
        let series = [Series {
            label: "ours-uu".into(),
            color: red,
            dashed: false,
            points: vec![(0.0, 0.5), (90.0, 0.5), (120.0, f64::NAN), (180.0, 0.5)],
        }];
        let (_, _, rgb) = render_rgb(&spec(), &series).unwrap();
        let red_pixels = pixels_of(&rgb, red);
        // The line: one row (two, stroke width 2) holds most red pixels, spanning the left half.
        let mut rows = std::collections::BTreeMap::<usize, Vec<usize>>::new();
        for (x, y) in &red_pixels {
            rows.entry(*y).or_default().push(*x);
        }
        let (_, xs) = rows.iter().max_by_key(|(_, xs)| xs.len()).unwrap();
        let (min_x, max_x) = (xs.iter().min().unwrap(), xs.iter().max().unwrap());
        assert!(max_x - min_x > 300, "the line spans {min_x}..{max_x}");
        // Past the NaN (x > 90 s, the single point at 180 s draws nothing) no line at that row.
        assert!(*max_x < 500, "the line goes on past the NaN to {max_x}");
        // The legend's sample is red too, away from the line's row.
        assert!(rows.len() > 2, "no legend sample: rows {:?}", rows.keys());
    }

    #[test]
    fn png_decodes_to_the_drawing() {
        let series = [Series {
            label: "explo-up".into(),
            color: PALETTE[1],
            dashed: true,
            points: (0..=180).map(|t| (t as f64, t as f64 / 180.0)).collect(),
        }];
        let (_, _, rgb) = render_rgb(&spec(), &series).unwrap();
        let bytes = render_png(&spec(), &series).unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (900, 560));
        assert_eq!(&buf[..info.buffer_size()], &rgb[..]);
        assert!(!pixels_of(&rgb, PALETTE[1]).is_empty());
    }

    #[test]
    fn nan_breaks_a_series_into_runs() {
        let runs = segments(
            &[(0.0, 0.1), (1.0, f64::NAN), (2.0, 3.0), (3.0, 0.2)],
            0.0,
            1.0,
        );
        assert_eq!(runs, vec![vec![(0.0, 0.1)], vec![(2.0, 1.0), (3.0, 0.2)]]);
    }
}
