//! The `motion` baseline: keep a frame when the mean image displacement since the last keep
//! exceeds a pixel threshold — the classical pre-filter of DROID-SLAM's motion filter and DSO.
//!
//! Method (documented in README): on the grey 160x120 thumbnails every policy sees, a 12x9 grid
//! of points is laid on each kept frame and tracked frame to frame (chained) with sparse
//! pyramidal Lucas-Kanade (3 levels, 9x9 window, up to 10 Gauss-Newton iterations per level).
//! A point is lost when it leaves the image or its gradient matrix is singular. The displacement
//! of a frame is the mean distance of the surviving points from their positions in the last kept
//! frame, in pixels of a 640-pixel-wide image (thumbnail pixels x 4); when fewer than a quarter
//! of the points survive it is infinite (the view has changed: keep). A frame is kept when the
//! displacement reaches the threshold; it then becomes the new reference.

use super::{Trace, THUMB_H, THUMB_W};

const LEVELS: usize = 3;
const HALF_WIN: i32 = 4;
const ITERS: usize = 10;
const GRID_X: usize = 12;
const GRID_Y: usize = 9;
/// Thumbnail pixels to pixels of a 640-wide frame.
const TO_640: f64 = 640.0 / THUMB_W as f64;

/// A grey image pyramid (level 0 = the thumbnail), f32.
#[derive(Debug, Clone)]
pub struct Pyramid {
    levels: Vec<(usize, usize, Vec<f32>)>,
}

impl Pyramid {
    pub fn new(grey: &[u8], w: usize, h: usize) -> Pyramid {
        let mut levels = vec![(w, h, grey.iter().map(|&v| v as f32).collect::<Vec<f32>>())];
        for _ in 1..LEVELS {
            let (pw, ph, prev) = levels.last().unwrap();
            let (nw, nh) = (pw / 2, ph / 2);
            let mut img = vec![0.0; nw * nh];
            for y in 0..nh {
                for x in 0..nw {
                    let i = 2 * y * pw + 2 * x;
                    img[y * nw + x] =
                        0.25 * (prev[i] + prev[i + 1] + prev[i + pw] + prev[i + pw + 1]);
                }
            }
            levels.push((nw, nh, img));
        }
        Pyramid { levels }
    }
}

fn sample(img: &[f32], w: usize, h: usize, x: f32, y: f32) -> f32 {
    let x = x.clamp(0.0, (w - 1) as f32);
    let y = y.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let a = img[y0 * w + x0] * (1.0 - fx) + img[y0 * w + x1] * fx;
    let b = img[y1 * w + x0] * (1.0 - fx) + img[y1 * w + x1] * fx;
    a * (1.0 - fy) + b * fy
}

/// Track point `p` (level-0 coordinates) from `a` to `b`, starting from the guess `p + d0`.
/// Returns the new position, or None when lost.
fn track(a: &Pyramid, b: &Pyramid, p: (f32, f32)) -> Option<(f32, f32)> {
    let mut d = (0.0f32, 0.0f32);
    for l in (0..LEVELS).rev() {
        let (w, h, ia) = &a.levels[l];
        let (_, _, ib) = &b.levels[l];
        let s = (1u32 << l) as f32;
        let (px, py) = (p.0 / s, p.1 / s);
        d = (d.0 * 2.0, d.1 * 2.0);
        if l == LEVELS - 1 {
            d = (0.0, 0.0);
        }
        // Gradient matrix of the template window.
        let (mut gxx, mut gxy, mut gyy) = (0.0f32, 0.0f32, 0.0f32);
        let mut tpl = Vec::with_capacity(((2 * HALF_WIN + 1) * (2 * HALF_WIN + 1)) as usize);
        for wy in -HALF_WIN..=HALF_WIN {
            for wx in -HALF_WIN..=HALF_WIN {
                let (x, y) = (px + wx as f32, py + wy as f32);
                let gx = 0.5 * (sample(ia, *w, *h, x + 1.0, y) - sample(ia, *w, *h, x - 1.0, y));
                let gy = 0.5 * (sample(ia, *w, *h, x, y + 1.0) - sample(ia, *w, *h, x, y - 1.0));
                gxx += gx * gx;
                gxy += gx * gy;
                gyy += gy * gy;
                tpl.push((sample(ia, *w, *h, x, y), gx, gy));
            }
        }
        let det = gxx * gyy - gxy * gxy;
        if det < 1e-3 * (gxx + gyy).max(1e-6) || gxx + gyy < 1.0 {
            return None;
        }
        for _ in 0..ITERS {
            let (mut bx, mut by) = (0.0f32, 0.0f32);
            let mut k = 0;
            for wy in -HALF_WIN..=HALF_WIN {
                for wx in -HALF_WIN..=HALF_WIN {
                    let (x, y) = (px + wx as f32 + d.0, py + wy as f32 + d.1);
                    let (t, gx, gy) = tpl[k];
                    let diff = t - sample(ib, *w, *h, x, y);
                    bx += diff * gx;
                    by += diff * gy;
                    k += 1;
                }
            }
            let dx = (gyy * bx - gxy * by) / det;
            let dy = (gxx * by - gxy * bx) / det;
            d = (d.0 + dx, d.1 + dy);
            if dx * dx + dy * dy < 1e-4 {
                break;
            }
        }
    }
    let q = (p.0 + d.0, p.1 + d.1);
    let (w, h) = (THUMB_W as f32, THUMB_H as f32);
    (q.0 >= 0.0
        && q.1 >= 0.0
        && q.0 <= w - 1.0
        && q.1 <= h - 1.0
        && d.0.is_finite()
        && d.1.is_finite())
    .then_some(q)
}

fn grid() -> Vec<(f32, f32)> {
    let (w, h) = (THUMB_W as f32, THUMB_H as f32);
    let mut pts = Vec::with_capacity(GRID_X * GRID_Y);
    for gy in 0..GRID_Y {
        for gx in 0..GRID_X {
            pts.push((
                (gx as f32 + 0.5) * w / GRID_X as f32,
                (gy as f32 + 0.5) * h / GRID_Y as f32,
            ));
        }
    }
    pts
}

/// Pyramids of every thumbnail (built once, shared by every threshold tried).
pub fn pyramids(thumbs: &[Vec<u8>]) -> Vec<Pyramid> {
    thumbs
        .iter()
        .map(|t| Pyramid::new(t, THUMB_W as usize, THUMB_H as usize))
        .collect()
}

/// The motion gate at `threshold_px` (pixels of a 640-wide frame). The trace's utility is the
/// displacement (not a tau), so it is not judged for MAE/RMSE.
pub fn motion_gate(pyr: &[Pyramid], threshold_px: f64) -> Trace {
    let mut keep = Vec::with_capacity(pyr.len());
    // (position in the last kept frame, tracked position now or None when lost)
    type Track = ((f32, f32), Option<(f32, f32)>);
    let mut points: Vec<Track> = Vec::new();
    let mut prev = 0usize;
    for i in 0..pyr.len() {
        let k = if i == 0 {
            true
        } else {
            for (_, cur) in points.iter_mut() {
                *cur = cur.and_then(|c| track(&pyr[prev], &pyr[i], c));
            }
            let alive: Vec<f64> = points
                .iter()
                .filter_map(|(o, c)| {
                    c.map(|c| (((c.0 - o.0).powi(2) + (c.1 - o.1).powi(2)) as f64).sqrt())
                })
                .collect();
            let disp = if alive.len() * 4 < points.len().max(1) {
                f64::INFINITY
            } else {
                TO_640 * alive.iter().sum::<f64>() / alive.len() as f64
            };
            disp >= threshold_px
        };
        if k {
            points = grid().into_iter().map(|p| (p, Some(p))).collect();
        }
        prev = i;
        keep.push(k);
    }
    Trace {
        utility: vec![None; keep.len()],
        keep,
    }
}

/// The motion gate with its threshold chosen so the kept count is as close as possible to
/// `target` (bisection on the threshold; kept count falls as it grows). Returns the trace and
/// the threshold in pixels.
pub fn motion_for_budget(pyr: &[Pyramid], target: usize) -> (Trace, f64) {
    super::baselines::fit_budget(target, (0.01, 2000.0), 24, |px| motion_gate(pyr, px))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth texture shifted by (dx, dy) thumbnail pixels.
    fn texture(dx: f32, dy: f32) -> Vec<u8> {
        let (w, h) = (THUMB_W as usize, THUMB_H as usize);
        let mut v = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let (u, t) = (x as f32 - dx, y as f32 - dy);
                let f = 128.0
                    + 50.0 * (u * 0.21).sin() * (t * 0.17).cos()
                    + 40.0 * ((u + t) * 0.09).sin()
                    + 30.0 * (u * 0.05 - t * 0.11).cos();
                v[y * w + x] = f.clamp(0.0, 255.0) as u8;
            }
        }
        v
    }

    #[test]
    fn tracks_a_known_shift() {
        let a = Pyramid::new(&texture(0.0, 0.0), THUMB_W as usize, THUMB_H as usize);
        let b = Pyramid::new(&texture(3.0, -2.0), THUMB_W as usize, THUMB_H as usize);
        let mut errs = Vec::new();
        for p in grid()
            .into_iter()
            .filter(|p| p.0 > 15.0 && p.0 < 145.0 && p.1 > 15.0 && p.1 < 105.0)
        {
            let q = track(&a, &b, p).expect("tracked");
            errs.push(((q.0 - p.0 - 3.0).abs()).max((q.1 - p.1 + 2.0).abs()));
        }
        errs.sort_by(|a, b| a.total_cmp(b));
        assert!(
            errs[errs.len() / 2] < 0.2,
            "median error {}",
            errs[errs.len() / 2]
        );
    }

    #[test]
    fn static_keeps_one_and_drift_keeps_more_when_threshold_is_lower() {
        let still: Vec<Vec<u8>> = (0..10).map(|_| texture(0.0, 0.0)).collect();
        assert_eq!(motion_gate(&pyramids(&still), 2.0).kept(), 1);
        // A steady pan of 1 thumbnail pixel (4 px at 640) per frame over 20 frames.
        let pan: Vec<Vec<u8>> = (0..20).map(|i| texture(i as f32, 0.0)).collect();
        let pyr = pyramids(&pan);
        let every_4 = motion_gate(&pyr, 15.0);
        let every_8 = motion_gate(&pyr, 31.0);
        assert!(
            every_4.kept() > every_8.kept(),
            "{} vs {}",
            every_4.kept(),
            every_8.kept()
        );
        assert!((4..=7).contains(&every_4.kept()), "kept {}", every_4.kept());
        let (t, px) = motion_for_budget(&pyr, 3);
        assert_eq!(t.kept(), 3, "threshold {px}");
    }
}
