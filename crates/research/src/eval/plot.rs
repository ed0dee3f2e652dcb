//! Line charts written as SVG (plotters), for cumulative error curves, ROC and DET plots.

use std::path::Path;

use plotters::prelude::*;

/// One named curve of (x, y) points.
pub struct Series<'a> {
    pub name: &'a str,
    pub points: Vec<(f64, f64)>,
}

/// Axis scaling of a chart.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Scale {
    Linear,
    /// Base-10 logarithmic; non-positive values are dropped.
    Log,
}

pub struct Chart<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub x_range: (f64, f64),
    pub y_range: (f64, f64),
    pub x_scale: Scale,
    pub y_scale: Scale,
}

const PALETTE: [RGBColor; 12] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(23, 190, 207),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(188, 189, 34),
    RGBColor(127, 127, 127),
    RGBColor(0, 0, 0),
    RGBColor(255, 187, 120),
];

/// Draw `series` as lines on one chart and write it to `path` as SVG (800×600).
pub fn line_chart(path: &Path, chart: &Chart, series: &[Series]) -> anyhow::Result<()> {
    let root = SVGBackend::new(path, (800, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    // Log axes are drawn as linear axes over log10 values, labelled back in the original units.
    let tx = |v: f64, s: Scale| if s == Scale::Log { v.log10() } else { v };
    let (x0, x1) = (tx(chart.x_range.0, chart.x_scale), tx(chart.x_range.1, chart.x_scale));
    let (y0, y1) = (tx(chart.y_range.0, chart.y_scale), tx(chart.y_range.1, chart.y_scale));
    let mut ctx = ChartBuilder::on(&root)
        .caption(chart.title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(x0..x1, y0..y1)?;
    let fmt = |s: Scale| move |v: &f64| if s == Scale::Log { format!("{:.0e}", 10f64.powf(*v)) } else { format!("{v:.3}") };
    ctx.configure_mesh()
        .x_desc(chart.x_label)
        .y_desc(chart.y_label)
        .x_label_formatter(&fmt(chart.x_scale))
        .y_label_formatter(&fmt(chart.y_scale))
        .draw()?;
    for (i, s) in series.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        let pts: Vec<(f64, f64)> = s
            .points
            .iter()
            .filter(|(x, y)| (chart.x_scale == Scale::Linear || *x > 0.0) && (chart.y_scale == Scale::Linear || *y > 0.0))
            .map(|&(x, y)| (tx(x, chart.x_scale), tx(y, chart.y_scale)))
            .collect();
        ctx.draw_series(LineSeries::new(pts, color.stroke_width(2)))?
            .label(s.name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    ctx.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
    root.present()?;
    Ok(())
}

/// The cumulative distribution of `errors` sampled at `steps` points over `0..=max`:
/// (x, share of errors ≤ x).
pub fn cumulative(errors: &[f64], max: f64, steps: usize) -> Vec<(f64, f64)> {
    let mut sorted: Vec<f64> = errors.to_vec();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let n = sorted.len().max(1) as f64;
    (0..=steps)
        .map(|i| {
            let x = max * i as f64 / steps as f64;
            let count = sorted.partition_point(|&e| e <= x);
            (x, count as f64 / n)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cumulative_counts_shares() {
        let c = cumulative(&[0.01, 0.02, 0.2, 0.04], 0.1, 10);
        assert_eq!(c[0], (0.0, 0.0));
        assert!((c[5].1 - 0.75).abs() < 1e-12);
        assert!((c[10].1 - 0.75).abs() < 1e-12);
    }

    #[test]
    fn writes_an_svg_with_each_series() {
        let dir = std::env::temp_dir().join(format!("facegate-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("c.svg");
        let chart = Chart {
            title: "t",
            x_label: "FMR",
            y_label: "FNMR",
            x_range: (1e-4, 1.0),
            y_range: (0.0, 1.0),
            x_scale: Scale::Log,
            y_scale: Scale::Linear,
        };
        let series = [
            Series { name: "alpha", points: vec![(1e-4, 0.5), (1e-2, 0.2), (1.0, 0.0)] },
            Series { name: "beta", points: vec![(0.0, 1.0), (1e-3, 0.3)] },
        ];
        line_chart(&path, &chart, &series).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("<svg") && svg.contains("alpha") && svg.contains("beta"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
