//! Success and precision plots as tracking papers show them (PNG and SVG): one curve per tracker,
//! labelled with its score, best first. The font is embedded (no system fonts needed).

use std::path::Path;

use plotters::prelude::*;
use prl_track::ope::{norm_precision_thresholds, precision_thresholds, success_thresholds};

use super::write_atomically;

const SIZE: (u32, u32) = (640, 480);
const FONT: &str = "sans-serif";

/// One tracker's curve and the score its label shows.
pub struct Curve<'a> {
    /// Tracker name.
    pub name: &'a str,
    /// The score in the legend (AUC, or precision at 20 px).
    pub score: f64,
    /// y values, one per threshold.
    pub values: &'a [f64],
}

/// Which plot.
#[derive(Clone, Copy)]
pub enum Kind {
    /// Success rate against the overlap threshold, legend by AUC.
    Success,
    /// Precision against the location error threshold (px), legend by precision at 20 px.
    Precision,
    /// Normalised precision against the normalised threshold, legend at 0.2.
    NormPrecision,
}

fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // The embedded Ubuntu Light face; a failure would only lose the text.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, epaint_default_fonts::UBUNTU_LIGHT);
    });
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    kind: Kind,
    curves: &[Curve],
) -> Result<(), String>
where
    DB::ErrorType: 'static,
{
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    root.fill(&WHITE).map_err(e)?;
    let (xs, xmax, xlabel) = match kind {
        Kind::Success => (success_thresholds(), 1.0, "Overlap threshold"),
        Kind::Precision => (precision_thresholds(), 50.0, "Location error threshold (px)"),
        Kind::NormPrecision => (norm_precision_thresholds(), 0.5, "Normalised location error threshold"),
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FONT, 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..xmax, 0.0..1.0)
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc(xlabel)
        .y_desc(if matches!(kind, Kind::Success) { "Success rate" } else { "Precision" })
        .label_style((FONT, 14))
        .draw()
        .map_err(e)?;
    for (i, c) in curves.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let points = xs.iter().copied().zip(c.values.iter().copied());
        chart
            .draw_series(LineSeries::new(points, color.stroke_width(2)))
            .map_err(e)?
            .label(format!("{} [{:.3}]", c.name, c.score))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .position(if matches!(kind, Kind::Success) {
            SeriesLabelPosition::LowerLeft
        } else {
            SeriesLabelPosition::LowerRight
        })
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font((FONT, 14))
        .draw()
        .map_err(e)?;
    root.present().map_err(e)
}

/// Write `<stem>.png` and `<stem>.svg` of one plot; curves are drawn best first.
pub fn plot(stem: &Path, title: &str, kind: Kind, curves: &mut [Curve]) -> anyhow::Result<()> {
    register_font();
    curves.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut svg = String::new();
    draw(SVGBackend::with_string(&mut svg, SIZE).into_drawing_area(), title, kind, curves)
        .map_err(|m| anyhow::anyhow!("{}.svg: {m}", stem.display()))?;
    write_atomically(&stem.with_extension("svg"), svg.as_bytes())?;
    let mut rgb = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
    draw(BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area(), title, kind, curves)
        .map_err(|m| anyhow::anyhow!("{}.png: {m}", stem.display()))?;
    let img = image::RgbImage::from_raw(SIZE.0, SIZE.1, rgb).expect("buffer of the plot's size");
    let mut png = std::io::Cursor::new(Vec::new());
    img.write_to(&mut png, image::ImageFormat::Png)?;
    write_atomically(&stem.with_extension("png"), png.get_ref())?;
    Ok(())
}
