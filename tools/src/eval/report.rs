//! Pictures of an evaluation: the utility plot, the contact sheet, the equal-budget sweep plot.

use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::{CoordTranslate, Shift};
use plotters::element::{Drawable, PointCollection};
use plotters::prelude::*;
use plotters_backend::{BackendCoord, DrawingErrorKind};

use super::{err, EvalError, PlotData, SweepPoint, THUMB_H, THUMB_W};

/// The shape drawn at each point of a policy's curve (and in its legend entry).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Marker {
    Circle,
    Square,
    Diamond,
    TriangleUp,
    TriangleDown,
    Cross,
}

/// How one policy is drawn, the same in every figure: colour, marker, dashed line or not.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Style {
    pub color: RGBColor,
    pub marker: Marker,
    pub dashed: bool,
}

const fn style_of(rgb: (u8, u8, u8), marker: Marker, dashed: bool) -> Style {
    Style {
        color: RGBColor(rgb.0, rgb.1, rgb.2),
        marker,
        dashed,
    }
}

/// Every policy's style (the Tableau-10 hues, and black for the oracle, the upper bound, drawn
/// dashed); every figure draws a policy with [`style`].
pub const STYLES: [(&str, Style); 6] = [
    ("model", style_of((214, 39, 40), Marker::Circle, false)),
    ("oracle", style_of((0, 0, 0), Marker::Diamond, true)),
    ("stride", style_of((31, 119, 180), Marker::Square, false)),
    (
        "pixel_diff",
        style_of((44, 160, 44), Marker::TriangleUp, false),
    ),
    ("motion", style_of((148, 103, 189), Marker::Cross, false)),
    (
        "overlap",
        style_of((255, 127, 14), Marker::TriangleDown, false),
    ),
];

/// A policy's style; a name not in [`STYLES`] is drawn grey with circles.
pub fn style(policy: &str) -> Style {
    STYLES
        .iter()
        .find(|(p, _)| *p == policy)
        .map(|(_, s)| *s)
        .unwrap_or(style_of((127, 127, 127), Marker::Circle, false))
}

/// Lines that are not a policy: the teacher's tau and the threshold.
const TEACHER: RGBColor = RGBColor(90, 90, 90);
const THRESHOLD: Style = style_of((127, 127, 127), Marker::Circle, true);
/// Width of the column right of the plot areas that holds the legend (off the data).
const LEGEND_W: u32 = 230;
const LINE_W: u32 = 2;
/// Height of the sweep figure.
const SWEEP_H: u32 = 930;
/// The fine grid lines: faint, so that the curves stand out.
const MESH: RGBColor = RGBColor(238, 238, 238);
const MARK: i32 = 4;

/// An axis label for a count: the integer, and no label between integers.
fn int_label(v: &f64) -> String {
    if (v - v.round()).abs() < 1e-9 {
        format!("{v:.0}")
    } else {
        String::new()
    }
}

/// A marker at one point, drawn in pixels (its size does not depend on the axes).
struct Mark<C> {
    at: C,
    marker: Marker,
    size: i32,
    style: ShapeStyle,
}

impl<C> Mark<C> {
    fn new(at: C, s: &Style) -> Self {
        Mark {
            at,
            marker: s.marker,
            size: MARK,
            style: if s.marker == Marker::Cross {
                s.color.stroke_width(2)
            } else {
                s.color.filled()
            },
        }
    }
}

impl<'a, C: 'a> PointCollection<'a, C> for &'a Mark<C> {
    type Point = &'a C;
    type IntoIter = std::iter::Once<&'a C>;
    fn point_iter(self) -> Self::IntoIter {
        std::iter::once(&self.at)
    }
}

impl<C, DB: DrawingBackend> Drawable<DB> for Mark<C> {
    fn draw<I: Iterator<Item = BackendCoord>>(
        &self,
        mut points: I,
        backend: &mut DB,
        _: (u32, u32),
    ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
        let Some((x, y)) = points.next() else {
            return Ok(());
        };
        let (s, st) = (self.size, &self.style);
        match self.marker {
            Marker::Circle => backend.draw_circle((x, y), s as u32, st, true),
            Marker::Square => backend.draw_rect((x - s, y - s), (x + s, y + s), st, true),
            Marker::Diamond => {
                let d = s + 1;
                backend.fill_polygon([(x, y - d), (x + d, y), (x, y + d), (x - d, y)], st)
            }
            Marker::TriangleUp => {
                backend.fill_polygon([(x, y - s - 1), (x + s + 1, y + s), (x - s - 1, y + s)], st)
            }
            Marker::TriangleDown => {
                backend.fill_polygon([(x, y + s + 1), (x + s + 1, y - s), (x - s - 1, y - s)], st)
            }
            Marker::Cross => {
                backend.draw_line((x - s, y - s), (x + s, y + s), st)?;
                backend.draw_line((x - s, y + s), (x + s, y - s), st)
            }
        }
    }
}

/// A line through `points` in a policy's style (dashed for a dashed style), without markers.
fn draw_line<DB, CT>(
    chart: &mut ChartContext<'_, DB, CT>,
    points: Vec<(f64, f64)>,
    s: &Style,
) -> Result<(), EvalError>
where
    DB: DrawingBackend,
    CT: CoordTranslate<From = (f64, f64)>,
{
    let line = s.color.stroke_width(LINE_W);
    let r = if s.dashed {
        chart.draw_series(DashedLineSeries::new(points, 8, 5, line))
    } else {
        chart.draw_series(LineSeries::new(points, line))
    };
    r.map(|_| ()).map_err(|e| EvalError(format!("plot: {e}")))
}

/// One legend entry: a line sample (dashed or not), optionally a marker on it, and the label.
struct Entry {
    label: String,
    style: Style,
    marker: bool,
}

/// The legend in its own column (`area`, right of the plot areas): one entry per line, the
/// first at pixel offset `top`, then every `step` pixels.
fn legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    top: i32,
    step: i32,
    entries: &[Entry],
) -> Result<(), EvalError> {
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| EvalError(format!("legend: {x}"));
    for (k, en) in entries.iter().enumerate() {
        let y = top + step * k as i32;
        let (x0, x1) = (12, 48);
        let line = en.style.color.stroke_width(LINE_W);
        if en.style.dashed {
            for (a, b) in [(x0, x0 + 9), (x0 + 14, x0 + 23), (x0 + 28, x1)] {
                area.draw(&PathElement::new(vec![(a, y), (b, y)], line))
                    .map_err(e)?;
            }
        } else {
            area.draw(&PathElement::new(vec![(x0, y), (x1, y)], line))
                .map_err(e)?;
        }
        if en.marker {
            area.draw(&Mark::new(((x0 + x1) / 2, y), &en.style))
                .map_err(e)?;
        }
        area.draw(&Text::new(
            en.label.clone(),
            (x1 + 10, y - 8),
            ("sans-serif", 15).into_font(),
        ))
        .map_err(e)?;
    }
    Ok(())
}

/// Height of the label strip under each contact-sheet thumbnail.
pub const LABEL_H: u32 = 16;

/// A grid of the kept frames' thumbnails (at most `max_tiles`, evenly sampled), 8 per row, each
/// with its label (`labels[k]` for `kept[k]`, e.g. [`super::kept_label`]: index, time, utility)
/// in a strip under it.
pub fn contact_sheet(
    kept: &[(usize, image::RgbImage)],
    labels: &[String],
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
    let (tile_w, tile_h) = (THUMB_W + pad, THUMB_H + LABEL_H + pad);
    let mut sheet = image::RgbImage::from_pixel(
        cols * tile_w + pad,
        rows * tile_h + pad,
        image::Rgb([255, 255, 255]),
    );
    let picked: Vec<usize> = (0..n).map(|k| k * kept.len() / n).collect();
    for (k, &j) in picked.iter().enumerate() {
        let (c, r) = (k as u32 % cols, k as u32 / cols);
        image::imageops::replace(
            &mut sheet,
            &kept[j].1,
            (pad + c * tile_w) as i64,
            (pad + r * tile_h) as i64,
        );
    }
    register_font()?;
    let size = sheet.dimensions();
    {
        let root = BitMapBackend::with_buffer(&mut sheet, size).into_drawing_area();
        let font = ("sans-serif", 12).into_font().color(&BLACK);
        for (k, &j) in picked.iter().enumerate() {
            let Some(label) = labels.get(j) else { continue };
            let (c, r) = (k as u32 % cols, k as u32 / cols);
            let at = (
                (pad + c * tile_w + 2) as i32,
                (pad + r * tile_h + THUMB_H + 2) as i32,
            );
            root.draw(&Text::new(label.as_str(), at, font.clone()))
                .map_err(err("contact sheet"))?;
        }
        root.present().map_err(err("contact sheet"))?;
    }
    save(&sheet, out)
}

/// Write a picture (format by the extension of `out`), whole or not at all; an error names the
/// file.
fn save(img: &image::RgbImage, out: &Path) -> Result<(), EvalError> {
    crate::output::save_image(img, out).map_err(EvalError)
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

/// Teacher and predicted tau over time with the threshold (top), and the frames each policy
/// keeps, one row per policy in its style (bottom); the legend and the row names sit in a
/// column right of the data.
pub fn plot(data: &PlotData, title: &str, out: &Path) -> Result<(), EvalError> {
    let size = (1200, 540 + 28 * data.kept.len() as u32 + CAPTION_H);
    render(size, out, |root| draw_plot(root, data, title))
}

/// Height of the caption line under the utility plot.
const CAPTION_H: u32 = 22;

/// What the utility plot's grey curve is (under the plot when there is a teacher).
pub const TEACHER_CAPTION: &str = "teacher tau (model's ref.): the exact teacher's tau of each \
     frame against the last frame the MODEL kept, so it restarts at every model keep (the oracle \
     row keeps against its own frames).";

fn draw_plot(root: Canvas<'_>, data: &PlotData, title: &str) -> Result<(), EvalError> {
    register_font()?;
    let (_, full_h) = root.dim_in_pixel();
    let (root, caption) = root.split_vertically(full_h - CAPTION_H);
    caption.fill(&WHITE).map_err(err("plot"))?;
    if data.teacher_tau.iter().any(Option::is_some) {
        caption
            .draw(&Text::new(
                TEACHER_CAPTION,
                (10, 2),
                ("sans-serif", 13).into_font().color(&BLACK),
            ))
            .map_err(err("plot"))?;
    }
    let n = data.predicted_tau.len().max(2);
    let rows = data.kept.len();
    let e = err::<String>("plot");
    root.fill(&WHITE).map_err(err("plot"))?;
    let body = root
        .titled(title, ("sans-serif", 20))
        .map_err(|x| e(x.to_string()))?;
    let (top, bottom) = body.split_vertically(470);
    let (top, top_legend) = top.split_horizontally(1200 - LEGEND_W);
    let (bottom, bottom_labels) = bottom.split_horizontally(1200 - LEGEND_W);
    let x_range = 0f64..(n - 1) as f64;
    let mut chart = ChartBuilder::on(&top)
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(x_range.clone(), -0.02f64..1.02f64)
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .light_line_style(MESH)
        .x_label_formatter(&int_label)
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
    let teacher = Style {
        color: TEACHER,
        marker: Marker::Circle,
        dashed: false,
    };
    let model = style("model");
    for seg in series(&data.teacher_tau) {
        draw_line(&mut chart, seg, &teacher)?;
    }
    for seg in series(&data.predicted_tau) {
        draw_line(&mut chart, seg, &model)?;
    }
    draw_line(
        &mut chart,
        vec![(0.0, data.threshold), ((n - 1) as f64, data.threshold)],
        &THRESHOLD,
    )?;
    let mut entries = vec![
        Entry {
            label: "predicted tau (model)".into(),
            style: model,
            marker: false,
        },
        Entry {
            label: format!("threshold {:.3}", data.threshold),
            style: THRESHOLD,
            marker: false,
        },
    ];
    if data.teacher_tau.iter().any(Option::is_some) {
        entries.insert(
            0,
            Entry {
                label: "teacher tau (model's ref.)".into(),
                style: teacher,
                marker: false,
            },
        );
    }
    legend(&top_legend, 30, 24, &entries)?;

    let mut keep_chart = ChartBuilder::on(&bottom)
        .margin(10)
        .x_label_area_size(5)
        .y_label_area_size(45)
        .build_cartesian_2d(x_range, 0f64..rows.max(1) as f64)
        .map_err(|x| e(x.to_string()))?;
    let mut labels = Vec::new();
    for (row, (name, kept)) in data.kept.iter().enumerate() {
        let y = (rows - row) as f64 - 0.5;
        let st = style(name);
        keep_chart
            .draw_series(
                kept.iter()
                    .enumerate()
                    .filter(|(_, k)| **k)
                    .map(|(i, _)| Mark::new((i as f64, y), &st)),
            )
            .map_err(|x| e(x.to_string()))?;
        labels.push(Entry {
            label: format!("{name} ({} kept)", kept.iter().filter(|k| **k).count()),
            style: st,
            marker: true,
        });
    }
    // Each row's name beside its row, in the legend column.
    let (_, row0) = keep_chart.backend_coord(&(0.0, rows as f64 - 0.5));
    let (_, origin) = bottom_labels.get_base_pixel();
    let step = if rows > 1 {
        keep_chart.backend_coord(&(0.0, rows as f64 - 1.5)).1 - row0
    } else {
        24
    };
    legend(&bottom_labels, row0 - origin, step, &labels)?;
    root.present().map_err(err("plot"))?;
    Ok(())
}

/// The fonts the pictures' text is drawn with: the first of these that exists (DejaVu Sans where
/// Debian/Ubuntu, Fedora and Arch put it, else Liberation Sans).
pub const FONTS: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// Register the first of [`FONTS`] found as plotters' "sans-serif" (once); without one no label
/// could be drawn, so that is an error naming the fonts looked for and the package to install.
fn register_font() -> Result<(), EvalError> {
    static FOUND: OnceLock<bool> = OnceLock::new();
    let found = *FOUND.get_or_init(|| {
        FONTS.iter().any(|p| {
            let Ok(bytes) = std::fs::read(p) else {
                return false;
            };
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, bytes)
                .is_ok()
        })
    });
    if found {
        Ok(())
    } else {
        Err(EvalError(format!(
            "no font to write the pictures' text with: install DejaVu Sans (Debian/Ubuntu: \
             fonts-dejavu-core); looked for {}",
            FONTS.join(", ")
        )))
    }
}

/// The equal-budget curves of `--sweep`: late keeps (top) and min pair S (bottom) against the
/// number of frames kept, one line per policy in its style; the legend in a column right of
/// both panels.
pub fn plot_sweep(points: &[SweepPoint], title: &str, out: &Path) -> Result<(), EvalError> {
    render((1000 + LEGEND_W, SWEEP_H), out, |root| {
        draw_sweep(root, points, title)
    })
}

/// A sweep point's threshold label (`t 0.50`).
fn threshold_label(t: f64) -> String {
    format!("t {t:.2}")
}

/// The note under the sweep plot's legend: what the `t` labels are, and where the other
/// policies' points come from.
pub const SWEEP_NOTE: [&str; 4] = [
    "t 0.50: the threshold the model",
    "(above its point) and the oracle",
    "(below) ran at; the others run at",
    "the model's budget at each t",
];

fn draw_sweep(root: Canvas<'_>, points: &[SweepPoint], title: &str) -> Result<(), EvalError> {
    register_font()?;
    let e = err::<String>("sweep plot");
    let mut policies: Vec<&str> = Vec::new();
    for p in points {
        if !policies.contains(&p.policy.as_str()) {
            policies.push(&p.policy);
        }
    }
    let kept = |f: fn(usize, usize) -> usize| points.iter().map(|p| p.kept).reduce(f);
    let (lo, hi) = (kept(usize::min).unwrap_or(0), kept(usize::max).unwrap_or(1));
    // The budgets span: a margin of 5% of it (at least one frame) each side.
    let pad = ((hi - lo) as f64 * 0.05).max(1.0);
    let x_range = (lo as f64 - pad).max(0.0)..hi as f64 + pad;
    let max_late = points
        .iter()
        .map(|p| p.late_keeps)
        .max()
        .unwrap_or(1)
        .max(1) as f64;
    let (w, h) = (1000 + LEGEND_W, SWEEP_H);
    root.fill(&WHITE).map_err(err("sweep plot"))?;
    let body = root
        .titled(title, ("sans-serif", 20))
        .map_err(|x| e(x.to_string()))?;
    let (plots, legend_area) = body.split_horizontally(w - LEGEND_W);
    let (top, bottom) = plots.split_vertically((h - 30) / 2);
    let series = |policy: &str, f: &dyn Fn(&SweepPoint) -> Option<f64>| -> Vec<(f64, f64)> {
        let mut v: Vec<(f64, f64)> = points
            .iter()
            .filter(|p| p.policy == policy)
            .filter_map(|p| f(p).map(|y| (p.kept as f64, y)))
            .collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        v
    };
    /// One panel: axis label, top of the axis, decimals of its labels, the value drawn.
    struct Panel {
        ylabel: &'static str,
        ymax: f64,
        decimals: usize,
        get: fn(&SweepPoint) -> Option<f64>,
    }
    let panels = [
        (
            &top,
            Panel {
                ylabel: "late keeps (S < 0.333)",
                ymax: max_late * 1.05,
                decimals: 0,
                get: |p| Some(p.late_keeps as f64),
            },
        ),
        (
            &bottom,
            Panel {
                ylabel: "min pair S",
                ymax: 1.0,
                decimals: 1,
                get: |p| p.min_pair_s,
            },
        ),
    ];
    for (
        area,
        Panel {
            ylabel,
            ymax,
            decimals,
            get,
        },
    ) in panels
    {
        let mut chart = ChartBuilder::on(area)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(x_range.clone(), 0f64..ymax)
            .map_err(|x| e(x.to_string()))?;
        chart
            .configure_mesh()
            .light_line_style(MESH)
            .x_label_formatter(&int_label)
            .y_label_formatter(&|y| {
                if decimals == 0 {
                    int_label(y)
                } else {
                    format!("{y:.decimals$}")
                }
            })
            .x_desc("frames kept")
            .y_desc(ylabel)
            .draw()
            .map_err(|x| e(x.to_string()))?;
        // The first policies (model, oracle) drawn last: on top where curves meet.
        for policy in policies.iter().rev() {
            let st = style(policy);
            let data = series(policy, &get);
            draw_line(&mut chart, data.clone(), &st)?;
            chart
                .draw_series(data.into_iter().map(|p| Mark::new(p, &st)))
                .map_err(|x| e(x.to_string()))?;
        }
        // Each of the model's points (above it) and the oracle's (below it) carries the
        // threshold it was run at; the other policies are at the model's budget of that
        // threshold, so they have none of their own.
        for (policy, at) in [("model", (6, -16)), ("oracle", (6, 5))] {
            let font = ("sans-serif", 12).into_font().color(&style(policy).color);
            chart
                .draw_series(
                    points
                        .iter()
                        .filter(|p| p.policy == policy)
                        .filter_map(|p| get(p).map(|y| (p, y)))
                        .map(|(p, y)| {
                            // On a pale box, legible where it crosses a curve.
                            EmptyElement::at((p.kept as f64, y))
                                + Rectangle::new(
                                    [(at.0 - 2, at.1 - 1), (at.0 + 38, at.1 + 13)],
                                    WHITE.mix(0.6).filled(),
                                )
                                + Text::new(threshold_label(p.threshold), at, font.clone())
                        }),
                )
                .map_err(|x| e(x.to_string()))?;
        }
    }
    let entries: Vec<Entry> = policies
        .iter()
        .map(|p| Entry {
            label: p.to_string(),
            style: style(p),
            marker: true,
        })
        .collect();
    legend(&legend_area, 40, 24, &entries)?;
    let note = ("sans-serif", 13).into_font().color(&BLACK);
    for (k, line) in SWEEP_NOTE.iter().enumerate() {
        legend_area
            .draw(&Text::new(
                *line,
                (10, 40 + 24 * entries.len() as i32 + 8 + 17 * k as i32),
                note.clone(),
            ))
            .map_err(err("sweep plot"))?;
    }
    root.present().map_err(err("sweep plot"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::POLICIES;

    fn distance(a: RGBColor, b: RGBColor) -> f64 {
        let d = |x: u8, y: u8| (x as f64 - y as f64).powi(2);
        (d(a.0, b.0) + d(a.1, b.1) + d(a.2, b.2)).sqrt()
    }

    #[test]
    fn every_policy_has_its_own_colour_and_marker() {
        for p in POLICIES {
            assert!(STYLES.iter().any(|(n, _)| *n == p), "{p} has no style");
        }
        for (i, (a, sa)) in STYLES.iter().enumerate() {
            for (b, sb) in &STYLES[i + 1..] {
                assert!(
                    distance(sa.color, sb.color) > 100.0,
                    "{a} and {b} have alike colours"
                );
                assert_ne!(sa.marker, sb.marker, "{a} and {b}");
            }
        }
        let dashed: Vec<&str> = STYLES
            .iter()
            .filter(|(_, s)| s.dashed)
            .map(|(p, _)| *p)
            .collect();
        assert_eq!(
            dashed,
            ["oracle"],
            "only the oracle, the upper bound, is dashed"
        );
        assert_eq!(style("no-such-policy").color, RGBColor(127, 127, 127));
    }

    /// Pixels of exactly `c` left (`left` true) or right of column `x`.
    fn count(img: &image::RgbImage, x: u32, left: bool, c: RGBColor) -> usize {
        img.enumerate_pixels()
            .filter(|(px, _, p)| (*px < x) == left && p.0 == [c.0, c.1, c.2])
            .count()
    }

    /// Every policy's colour is in the plot areas (curves and markers) and in the legend column
    /// right of them; the plot areas hold no legend.
    fn check_colours(img: &image::RgbImage) {
        let x = img.width() - LEGEND_W;
        for (p, st) in STYLES {
            let (data, legend) = (
                count(img, x, true, st.color),
                count(img, x, false, st.color),
            );
            assert!(data > 40, "{p}: {data} pixels of its colour in the plots");
            assert!(
                legend > 10,
                "{p}: {legend} pixels of its colour in the legend"
            );
        }
    }

    #[test]
    fn contact_sheet_labels_each_thumbnail_under_it() {
        let grey = image::RgbImage::from_pixel(THUMB_W, THUMB_H, image::Rgb([128, 128, 128]));
        let kept = vec![(3, grey.clone()), (250, grey)];
        let labels = vec![
            "#3  0.10 s  u 0.52".to_string(),
            "#250  8.33 s  u 0.61  max-gap".to_string(),
        ];
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("sheet.png");
        contact_sheet(&kept, &labels, 64, &out).unwrap();
        let img = image::open(&out).unwrap().to_rgb8();
        let pad = 4;
        assert_eq!(img.height(), THUMB_H + LABEL_H + 2 * pad);
        // The strip under each thumbnail holds dark text; the two labels differ.
        let strip = |k: u32| -> Vec<bool> {
            let x0 = pad + k * (THUMB_W + pad);
            (0..LABEL_H)
                .flat_map(|y| (0..THUMB_W).map(move |x| (x0 + x, pad + THUMB_H + y)))
                .map(|(x, y)| img.get_pixel(x, y)[0] < 128)
                .collect()
        };
        let (a, b) = (strip(0), strip(1));
        let ink = |v: &[bool]| v.iter().filter(|&&d| d).count();
        assert!(ink(&a) > 30 && ink(&b) > ink(&a), "{} {}", ink(&a), ink(&b));
        assert_ne!(a, b);
        // The thumbnails themselves are untouched.
        assert_eq!(img.get_pixel(pad + 10, pad + 10)[0], 128);
    }

    /// Three points per policy, the model's and oracle's run at `0.3 + step * k`.
    fn sweep_points(step: f64) -> Vec<SweepPoint> {
        (0..3)
            .flat_map(|k| {
                POLICIES.iter().enumerate().map(move |(i, p)| SweepPoint {
                    policy: p.to_string(),
                    threshold: 0.3 + step * k as f64,
                    kept: 20 + 10 * k + i,
                    late_keeps: 12 - 4 * k + i,
                    breaks: 0,
                    min_pair_s: Some(0.1 + 0.1 * k as f64 + 0.02 * i as f64),
                    median_pair_s: None,
                })
            })
            .collect()
    }

    fn sweep_png(points: &[SweepPoint]) -> image::RgbImage {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("sweep.png");
        plot_sweep(points, "sweep", &out).unwrap();
        image::open(&out).unwrap().to_rgb8()
    }

    #[test]
    fn sweep_plot_draws_each_policy_in_its_style_beside_the_legend() {
        let img = sweep_png(&sweep_points(0.1));
        assert_eq!(img.dimensions(), (1000 + LEGEND_W, 930));
        check_colours(&img);
    }

    #[test]
    fn sweep_plot_labels_the_model_and_oracle_points_with_their_threshold() {
        assert_eq!(threshold_label(0.5), "t 0.50");
        assert_eq!(threshold_label(0.449999), "t 0.45");
        // The same points run at other thresholds: only the labels change, in the plot areas,
        // drawn in the model's and the oracle's colours (or their anti-aliased edges).
        let (a, b) = (
            sweep_png(&sweep_points(0.1)),
            sweep_png(&sweep_points(0.15)),
        );
        let changed: Vec<(u32, u32)> = a
            .enumerate_pixels()
            .filter(|(x, y, p)| b.get_pixel(*x, *y) != *p)
            .map(|(x, y, _)| (x, y))
            .collect();
        assert!(changed.len() > 100, "{} pixels changed", changed.len());
        assert!(changed.iter().all(|&(x, _)| x < a.width() - LEGEND_W));
        // A pixel of text in colour c, anti-aliased on white: white * (1 - a) + c * a, a >= 0.3.
        let tinted = |p: &image::Rgb<u8>, c: RGBColor| {
            let c = [c.0, c.1, c.2].map(f64::from);
            let p = p.0.map(f64::from);
            let k = (0..3).max_by(|&i, &j| c[j].total_cmp(&c[i])).unwrap();
            let a = (255.0 - p[k]) / (255.0 - c[k]);
            a >= 0.3 && (0..3).all(|i| (255.0 * (1.0 - a) + c[i] * a - p[i]).abs() < 25.0)
        };
        for policy in ["model", "oracle"] {
            let c = style(policy).color;
            let ink = changed
                .iter()
                .filter(|&&(x, y)| tinted(a.get_pixel(x, y), c) || tinted(b.get_pixel(x, y), c))
                .count();
            assert!(ink > 40, "{policy}: {ink} changed pixels of its colour");
        }
    }

    #[test]
    fn utility_plot_draws_each_policy_row_in_its_style_beside_its_name() {
        let n = 120;
        let kept: Vec<(String, Vec<bool>)> = POLICIES
            .iter()
            .enumerate()
            .map(|(i, p)| (p.to_string(), (0..n).map(|f| f % (5 + i) == 0).collect()))
            .collect();
        let data = PlotData {
            teacher_tau: (0..n).map(|f| Some((f % 10) as f64 / 10.0)).collect(),
            predicted_tau: (0..n).map(|f| Some((f % 9) as f64 / 9.0)).collect(),
            threshold: 0.5,
            kept,
            kept_thumbs: Vec::new(),
            kept_labels: Vec::new(),
        };
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("utility.png");
        plot(&data, "utility", &out).unwrap();
        let img = image::open(&out).unwrap().to_rgb8();
        assert_eq!(
            img.dimensions(),
            (1200, 540 + 28 * POLICIES.len() as u32 + CAPTION_H)
        );
        check_colours(&img);
        // The caption says what the teacher curve is: text in the strip at the bottom.
        let h = img.height();
        let ink = (h - CAPTION_H..h)
            .flat_map(|y| (0..600).map(move |x| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y)[0] < 100)
            .count();
        assert!(ink > 200, "caption ink {ink}");
    }
}
