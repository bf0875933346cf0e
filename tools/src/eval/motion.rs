//! The `motion` baseline: keep a frame when the mean image displacement since the last keep
//! exceeds a pixel threshold — the classical pre-filter of DROID-SLAM's motion filter and DSO.
//!
//! Method (documented in README): on the grey 160x120 thumbnails every policy sees, a 12x9 grid
//! of points is laid on each kept frame and tracked frame to frame (chained) with sparse
//! pyramidal Lucas-Kanade (3 levels, 9x9 window, up to 10 Gauss-Newton iterations per level;
//! the element's tracker, `gstleangate::geometry`).
//! A point is lost when it leaves the image or its gradient matrix is singular. The displacement
//! of a frame is the mean distance of the surviving points from their positions in the last kept
//! frame, in pixels of a 640-pixel-wide image (thumbnail pixels x 4); when fewer than a quarter
//! of the points survive it is infinite (the view has changed: keep). A frame is kept when the
//! displacement reaches the threshold; it then becomes the new reference.

use super::{Trace, THUMB_H, THUMB_W};

use gstleangate::geometry::{grid as grid_of, track, Pyramid};

const GRID_X: usize = 12;
const GRID_Y: usize = 9;
/// Thumbnail pixels to pixels of a 640-wide frame.
const TO_640: f64 = 640.0 / THUMB_W as f64;

fn grid() -> Vec<(f32, f32)> {
    grid_of(THUMB_W as usize, THUMB_H as usize, GRID_X, GRID_Y)
}

/// Pyramids of every thumbnail (built once, shared by every threshold tried).
pub fn pyramids(thumbs: &[Vec<u8>]) -> Vec<Pyramid> {
    thumbs
        .iter()
        .map(|t| Pyramid::from_u8(t, THUMB_W as usize, THUMB_H as usize))
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
pub(crate) mod tests {
    use super::*;

    /// A smooth texture shifted by (dx, dy) thumbnail pixels (also the `overlap` tests').
    pub(crate) fn texture(dx: f32, dy: f32) -> Vec<u8> {
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
