//! The SVG plot of a client-count sweep: delivered samples/s (back at the subscribing client
//! and into DDS) and latency percentiles against the number of publishing clients.

use plotters::prelude::*;

/// One point of a sweep.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SweepPoint {
    /// Publishing clients.
    pub clients: u32,
    /// Samples/s back at the subscribing XRCE client.
    pub samples_per_second: f64,
    /// Samples/s counted by the independent DDS reader (if it ran).
    pub into_dds_per_second: Option<f64>,
    /// Latency client → agent → DDS → agent → client, µs.
    pub p50_us: f64,
    /// Its 99th percentile, µs.
    pub p99_us: f64,
    /// Fraction of the samples sent that never came back.
    pub lost_fraction: f64,
}

/// Writes the plot to `path`.
pub fn write_svg(path: &std::path::Path, title: &str, points: &[SweepPoint]) -> Result<(), String> {
    let e = |e: &dyn std::fmt::Display| e.to_string();
    let root = SVGBackend::new(path, (1000, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let root = root.titled(title, ("sans-serif", 18)).map_err(|x| e(&x))?;
    let (left, right) = root.split_horizontally(500);
    let max_clients = points.iter().map(|p| p.clients).max().unwrap_or(1).max(2) as f64;
    let x_range = (1.0f64..max_clients * 1.5).log_scale();

    let max_rate = points
        .iter()
        .flat_map(|p| [Some(p.samples_per_second), p.into_dds_per_second])
        .flatten()
        .fold(1.0f64, f64::max)
        * 1.2;
    let mut chart = ChartBuilder::on(&left)
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(64)
        .caption("delivered samples/s", ("sans-serif", 15))
        .build_cartesian_2d(x_range.clone(), 0.0f64..max_rate)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("publishing clients")
        .y_desc("samples/s")
        .draw()
        .map_err(|x| e(&x))?;
    let back: Vec<(f64, f64)> = points
        .iter()
        .map(|p| (f64::from(p.clients), p.samples_per_second))
        .collect();
    chart
        .draw_series(LineSeries::new(back.clone(), &BLUE).point_size(3))
        .map_err(|x| e(&x))?
        .label("back at the XRCE subscriber")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLUE));
    let dds: Vec<(f64, f64)> = points
        .iter()
        .filter_map(|p| Some((f64::from(p.clients), p.into_dds_per_second?)))
        .collect();
    if !dds.is_empty() {
        chart
            .draw_series(LineSeries::new(dds, &GREEN).point_size(3))
            .map_err(|x| e(&x))?
            .label("into DDS (independent reader)")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], GREEN));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::LowerLeft)
        .draw()
        .map_err(|x| e(&x))?;

    let max_lat = points.iter().map(|p| p.p99_us).fold(10.0f64, f64::max) * 2.0;
    let min_lat = points
        .iter()
        .map(|p| p.p50_us)
        .fold(f64::INFINITY, f64::min)
        .clamp(1.0, max_lat / 4.0)
        / 2.0;
    let mut chart = ChartBuilder::on(&right)
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(64)
        .caption(
            "latency client → agent → DDS → agent → client",
            ("sans-serif", 15),
        )
        .build_cartesian_2d(x_range, (min_lat..max_lat).log_scale())
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("publishing clients")
        .y_desc("µs")
        .draw()
        .map_err(|x| e(&x))?;
    for (label, color, pick) in [
        (
            "p50",
            BLUE,
            (|p: &SweepPoint| p.p50_us) as fn(&SweepPoint) -> f64,
        ),
        ("p99", RED, |p: &SweepPoint| p.p99_us),
    ] {
        let series: Vec<(f64, f64)> = points
            .iter()
            .map(|p| (f64::from(p.clients), pick(p).max(min_lat)))
            .collect();
        chart
            .draw_series(LineSeries::new(series, &color).point_size(3))
            .map_err(|x| e(&x))?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}
