//! Pictures of an evaluation: the utility plot, the contact sheet, the equal-budget sweep plot.

use std::path::Path;
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::{BitMapBackend, DrawingArea, IntoDrawingArea};

use super::{err, EvalError, PlotData, SweepPoint, THUMB_H, THUMB_W};

/// One colour per policy row or curve, in display order (model, oracle, then the baselines).
const PALETTE: [plotters::style::RGBColor; 5] = [
    plotters::style::RGBColor(220, 80, 20),
    plotters::style::RGBColor(30, 30, 30),
    plotters::style::RGBColor(40, 120, 200),
    plotters::style::RGBColor(60, 160, 60),
    plotters::style::RGBColor(150, 60, 180),
];

/// A grid of the kept frames' thumbnails (at most `max_tiles`, evenly sampled), 8 per row.
pub fn contact_sheet(
    kept: &[(usize, image::RgbImage)],
    max_tiles: usize,
    out: &Path,
) -> Result<(), EvalError> {
    if kept.is_empty() {
        return Err(EvalError("no kept frame to put on a contact sheet".into()));
    }
    let n = kept.len().min(max_tiles.max(1));
    let cols = n.min(8) as u32;
    let rows = n.div_ceil(cols as usize) as u32;
    let pad = 4;
    let mut sheet = image::RgbImage::from_pixel(
        cols * (THUMB_W + pad) + pad,
        rows * (THUMB_H + pad) + pad,
        image::Rgb([255, 255, 255]),
    );
    for k in 0..n {
        let (_, t) = &kept[k * kept.len() / n];
        let (c, r) = (k as u32 % cols, k as u32 / cols);
        image::imageops::replace(
            &mut sheet,
            t,
            (pad + c * (THUMB_W + pad)) as i64,
            (pad + r * (THUMB_H + pad)) as i64,
        );
    }
    save(&sheet, out)
}

/// Write a picture (format by the extension of `out`); an error names the file.
fn save(img: &image::RgbImage, out: &Path) -> Result<(), EvalError> {
    img.save(out)
        .map_err(|e| EvalError(format!("`{}`: {e}", out.display())))
}

type Canvas<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

/// Draw on a `size` canvas in memory, then [`save`] it to `out` (plotters' own file output
/// reports a failure in Debug form, without the path).
fn render(
    size: (u32, u32),
    out: &Path,
    draw: impl FnOnce(Canvas<'_>) -> Result<(), EvalError>,
) -> Result<(), EvalError> {
    let mut rgb = vec![0; size.0 as usize * size.1 as usize * 3];
    draw(BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area())?;
    save(
        &image::RgbImage::from_raw(size.0, size.1, rgb).expect("canvas size"),
        out,
    )
}

/// Draw teacher and predicted tau over time, the threshold, and kept frames per policy.
pub fn plot(data: &PlotData, title: &str, out: &Path) -> Result<(), EvalError> {
    let size = (1200, 520 + 28 * data.kept.len() as u32);
    render(size, out, |root| draw_plot(root, data, title))
}

fn draw_plot(root: Canvas<'_>, data: &PlotData, title: &str) -> Result<(), EvalError> {
    use plotters::prelude::*;
    register_font();
    let n = data.predicted_tau.len().max(2);
    let rows = data.kept.len();
    root.fill(&WHITE).map_err(err("plot"))?;
    let (top, bottom) = root.split_vertically(480);
    let e = err::<String>("plot");
    let mut chart = ChartBuilder::on(&top)
        .caption(title, ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(0f64..(n - 1) as f64, -0.02f64..1.02f64)
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .x_desc("frame")
        .y_desc("tau (utility)")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    let series = |v: &[Option<f64>]| -> Vec<Vec<(f64, f64)>> {
        // Break the line where there is no value.
        let mut out = vec![Vec::new()];
        for (i, x) in v.iter().enumerate() {
            match x {
                Some(y) => out.last_mut().unwrap().push((i as f64, *y)),
                None if !out.last().unwrap().is_empty() => out.push(Vec::new()),
                None => {}
            }
        }
        out
    };
    let teacher_color = RGBColor(30, 30, 30);
    let pred_color = RGBColor(220, 80, 20);
    for (k, seg) in series(&data.teacher_tau).into_iter().enumerate() {
        let s = chart
            .draw_series(LineSeries::new(seg, teacher_color.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?;
        if k == 0 {
            s.label("teacher tau vs model's reference")
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], teacher_color));
        }
    }
    for (k, seg) in series(&data.predicted_tau).into_iter().enumerate() {
        let s = chart
            .draw_series(LineSeries::new(seg, pred_color.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?;
        if k == 0 {
            s.label("predicted tau (model)")
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], pred_color));
        }
    }
    chart
        .draw_series(LineSeries::new(
            [(0.0, data.threshold), ((n - 1) as f64, data.threshold)],
            BLUE.stroke_width(1),
        ))
        .map_err(|x| e(x.to_string()))?
        .label(format!("threshold {:.3}", data.threshold))
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLUE));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;

    let mut keep_chart = ChartBuilder::on(&bottom)
        .margin(10)
        .x_label_area_size(5)
        .y_label_area_size(45)
        .build_cartesian_2d(0f64..(n - 1) as f64, 0f64..rows as f64)
        .map_err(|x| e(x.to_string()))?;
    let palette = PALETTE;
    for (row, (name, kept)) in data.kept.iter().enumerate() {
        let y = (rows - row) as f64 - 0.5;
        let c = palette[row % palette.len()];
        keep_chart
            .draw_series(
                kept.iter()
                    .enumerate()
                    .filter(|(_, k)| **k)
                    .map(|(i, _)| Circle::new((i as f64, y), 3, c.filled())),
            )
            .map_err(|x| e(x.to_string()))?;
        keep_chart
            .draw_series(std::iter::once(Text::new(
                format!("{name} ({})", kept.iter().filter(|k| **k).count()),
                (0.0, y + 0.3),
                ("sans-serif", 14),
            )))
            .map_err(|x| e(x.to_string()))?;
    }
    root.present().map_err(err("plot"))?;
    Ok(())
}

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        for p in [
            "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
            "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
        ] {
            if let Ok(bytes) = std::fs::read(p) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                let _ = plotters::style::register_font(
                    "sans-serif",
                    plotters::style::FontStyle::Normal,
                    bytes,
                );
                break;
            }
        }
    });
}

/// The equal-budget curves of `--sweep`: late keeps (top) and min pair S (bottom) against the
/// number of frames kept, one line per policy.
pub fn plot_sweep(points: &[SweepPoint], title: &str, out: &Path) -> Result<(), EvalError> {
    render((1000, 900), out, |root| draw_sweep(root, points, title))
}

fn draw_sweep(root: Canvas<'_>, points: &[SweepPoint], title: &str) -> Result<(), EvalError> {
    use plotters::prelude::*;
    register_font();
    let e = err::<String>("sweep plot");
    let mut policies: Vec<&str> = Vec::new();
    for p in points {
        if !policies.contains(&p.policy.as_str()) {
            policies.push(&p.policy);
        }
    }
    let max_kept = points.iter().map(|p| p.kept).max().unwrap_or(1).max(1) as f64;
    let max_late = points
        .iter()
        .map(|p| p.late_keeps)
        .max()
        .unwrap_or(1)
        .max(1) as f64;
    root.fill(&WHITE).map_err(err("sweep plot"))?;
    let (top, bottom) = root.split_vertically(450);
    let palette = PALETTE;
    let series = |policy: &str, f: &dyn Fn(&SweepPoint) -> Option<f64>| -> Vec<(f64, f64)> {
        let mut v: Vec<(f64, f64)> = points
            .iter()
            .filter(|p| p.policy == policy)
            .filter_map(|p| f(p).map(|y| (p.kept as f64, y)))
            .collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        v
    };
    type Getter = fn(&SweepPoint) -> Option<f64>;
    let panels: [(
        &DrawingArea<BitMapBackend, plotters::coord::Shift>,
        &str,
        f64,
        Getter,
    ); 2] = [
        (&top, "late keeps (S < 0.333)", max_late * 1.05, |p| {
            Some(p.late_keeps as f64)
        }),
        (&bottom, "min pair S", 1.0, |p| p.min_pair_s),
    ];
    for (k, (area, ylabel, ymax, get)) in panels.into_iter().enumerate() {
        let mut chart = ChartBuilder::on(area)
            .caption(if k == 0 { title } else { "" }, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(0f64..max_kept * 1.05, 0f64..ymax)
            .map_err(|x| e(x.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("frames kept")
            .y_desc(ylabel)
            .draw()
            .map_err(|x| e(x.to_string()))?;
        for (i, policy) in policies.iter().enumerate() {
            let c = palette[i % palette.len()];
            let data = series(policy, &get);
            chart
                .draw_series(LineSeries::new(data.clone(), c.stroke_width(2)))
                .map_err(|x| e(x.to_string()))?
                .label(policy.to_string())
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], c));
            chart
                .draw_series(data.into_iter().map(|p| Circle::new(p, 3, c.filled())))
                .map_err(|x| e(x.to_string()))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|x| e(x.to_string()))?;
    }
    root.present().map_err(err("sweep plot"))?;
    Ok(())
}
