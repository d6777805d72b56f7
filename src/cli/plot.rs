//! Precision-recall plots as PNG, one line per method, with a legend; and the reliability
//! diagram of a method's calibrated `p_correct`.
//!
//! Drawn with plotters' bitmap backend. Text uses the DejaVu Sans font embedded in the binary
//! (the `dejavu` crate) and registered with plotters' `ab_glyph` text renderer under the family
//! name [`FONT_FAMILY`], so plotting needs no system fonts (containers, CI).

use std::path::Path;
use std::sync::OnceLock;

use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

use seasonloc_core::calibration::fit::ReliabilityBin;
use seasonloc_core::eval::PrPoint;
use seasonloc_core::{Error, Result};

/// Width and height of the PNG written by [`plot_pr`], in pixels.
pub const PLOT_SIZE: (u32, u32) = (900, 650);

/// The family name the embedded font is registered under.
const FONT_FAMILY: &str = "sans-serif";

/// Line colours, cycled when there are more methods.
const COLOURS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

/// Registers the embedded DejaVu fonts once per process.
fn ensure_font() -> Result<()> {
    static REGISTERED: OnceLock<std::result::Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            register_font(FONT_FAMILY, FontStyle::Normal, dejavu::sans::regular())
                .and_then(|()| register_font(FONT_FAMILY, FontStyle::Bold, dejavu::sans::bold()))
                .map_err(|_| "the embedded DejaVu font could not be parsed".to_string())
        })
        .clone()
        .map_err(|reason| Error::param("font", reason))
}

/// Writes one PNG ([`PLOT_SIZE`]) to `path` with every method's PR curve: recall on x,
/// precision on y (both 0..1), axis labels, `title`, and a legend with each curve's name (the
/// caller may put AP into the name). Each curve is drawn in sweep order, starting at recall 0
/// with the precision of its first point; an empty curve still gets its legend entry.
pub fn plot_pr(path: &Path, title: &str, curves: &[(String, Vec<PrPoint>)]) -> Result<()> {
    ensure_font()?;
    let draw_err = |e: &dyn std::fmt::Display| Error::Io {
        path: path.to_path_buf(),
        source: std::io::Error::other(format!("cannot draw the PR plot: {e}")),
    };
    let root = BitMapBackend::new(path, PLOT_SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(|e| draw_err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FONT_FAMILY, 26).into_font())
        .margin(20)
        .x_label_area_size(50)
        .y_label_area_size(65)
        .build_cartesian_2d(0f64..1f64, 0f64..1.02f64)
        .map_err(|e| draw_err(&e))?;
    chart
        .configure_mesh()
        .x_desc("recall")
        .y_desc("precision")
        .axis_desc_style((FONT_FAMILY, 20))
        .label_style((FONT_FAMILY, 16))
        .x_labels(11)
        .y_labels(11)
        .light_line_style(WHITE)
        .bold_line_style(RGBColor(225, 225, 225))
        .draw()
        .map_err(|e| draw_err(&e))?;
    for (k, (name, curve)) in curves.iter().enumerate() {
        let colour = COLOURS[k % COLOURS.len()];
        let start = curve.first().map(|p| (0.0, p.precision));
        let points = start
            .into_iter()
            .chain(curve.iter().map(|p| (p.recall, p.precision)));
        chart
            .draw_series(LineSeries::new(points, colour.stroke_width(3)))
            .map_err(|e| draw_err(&e))?
            .label(name.as_str())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(3))
            });
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font((FONT_FAMILY, 17))
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .draw()
        .map_err(|e| draw_err(&e))?;
    root.present().map_err(|e| draw_err(&e))?;
    Ok(())
}

/// Writes one PNG ([`PLOT_SIZE`]) to `path` with the reliability diagram of `bins`: for each
/// bin of predicted probability, the observed fraction of right predictions (bars) against
/// the mean predicted probability (points), with the diagonal of a perfect calibration and the
/// count of each bin above it.
pub fn plot_reliability(path: &Path, title: &str, bins: &[ReliabilityBin]) -> Result<()> {
    ensure_font()?;
    let err = |e: &dyn std::fmt::Display| Error::Io {
        path: path.to_path_buf(),
        source: std::io::Error::other(format!("cannot draw the reliability diagram: {e}")),
    };
    let root = BitMapBackend::new(path, PLOT_SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FONT_FAMILY, 22))
        .margin(20)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(0.0f64..1.0, 0.0f64..1.0)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("predicted p_correct")
        .y_desc("observed fraction right")
        .label_style((FONT_FAMILY, 15))
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(LineSeries::new([(0.0, 0.0), (1.0, 1.0)], BLACK.mix(0.4)))
        .map_err(|e| err(&e))?
        .label("perfect calibration")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK.mix(0.4)));
    let filled: Vec<&ReliabilityBin> = bins.iter().filter(|b| b.count > 0).collect();
    chart
        .draw_series(filled.iter().map(|b| {
            Rectangle::new(
                [(b.lo + 0.005, 0.0), (b.hi - 0.005, b.observed)],
                BLUE.mix(0.35).filled(),
            )
        }))
        .map_err(|e| err(&e))?
        .label("observed (bar), mean predicted (point)")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 20, y + 5)], BLUE.mix(0.35).filled()));
    chart
        .draw_series(
            filled
                .iter()
                .map(|b| Circle::new((b.predicted, b.observed), 4, BLUE.filled())),
        )
        .map_err(|e| err(&e))?;
    chart
        .draw_series(filled.iter().map(|b| {
            Text::new(
                format!("{}", b.count),
                ((b.lo + b.hi) / 2.0 - 0.02, (b.observed + 0.03).min(0.97)),
                (FONT_FAMILY, 13),
            )
        }))
        .map_err(|e| err(&e))?;
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font((FONT_FAMILY, 15))
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curve(points: &[(f64, f64)]) -> Vec<PrPoint> {
        points
            .iter()
            .enumerate()
            .map(|(k, &(recall, precision))| PrPoint {
                threshold: 1.0 - k as f64 * 0.1,
                precision,
                recall,
            })
            .collect()
    }

    #[test]
    fn writes_a_png_of_the_expected_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pr.png");
        let curves = vec![
            (
                "flow (AP 0.66)".to_string(),
                curve(&[(0.1, 1.0), (0.4, 0.95), (0.7, 0.8), (0.9, 0.6)]),
            ),
            (
                "best match (AP 0.09)".to_string(),
                curve(&[(0.02, 0.5), (0.1, 0.2), (0.12, 0.12)]),
            ),
            ("empty".to_string(), Vec::new()),
        ];
        plot_pr(&path, "Nordland winter vs summer", &curves).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        let img = image::open(&path).unwrap();
        assert_eq!((img.width(), img.height()), PLOT_SIZE);
        // Not a blank canvas: the curves and text put non-white pixels on it.
        let rgb = img.to_rgb8();
        let coloured = rgb.pixels().filter(|p| p.0 != [255, 255, 255]).count();
        assert!(coloured > 5_000, "only {coloured} non-white pixels");
        // The first method's colour is present (its line was drawn).
        assert!(rgb.pixels().any(|p| p.0 == [31, 119, 180]));
    }

    #[test]
    fn unwritable_path_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no-such-dir").join("pr.png");
        let err = plot_pr(&path, "t", &[]).unwrap_err();
        assert!(err.to_string().contains("no-such-dir"), "{err}");
    }
}
