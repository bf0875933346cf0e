//! The metric gate: where the camera measures depth beside each colour frame, the teacher's own S
//! from the frames, with the pose estimated from them (never from ground truth).
//!
//! 1. At a keep (the reference), up to [`MAX_POINTS`] corners are picked on its grey picture
//!    (Shi-Tomasi: the smaller eigenvalue of the gradients' structure tensor over a 5x5 window, the
//!    strongest of each cell of a [`CELL`]-pixel grid) where its depth is valid, and lifted to 3-D
//!    points in the reference camera with that depth.
//! 2. Each later frame, the points are tracked from the previous frame with pyramidal
//!    Lucas-Kanade ([`crate::geometry::track_with`] with the prior's [`crate::geometry::LK_PRIOR`]:
//!    7x7 window, up to 5 iterations) and kept
//!    only when tracking back lands within [`FB_PX`] of where they started.
//! 3. The current pose relative to the reference is fitted to the tracks by Gauss-Newton on the
//!    reprojection error with Huber weights (PnP from the previous frame's pose; [`fit_pose`]),
//!    then refitted on the inliers (within [`INLIER_PX`]); points found to be outliers stop being
//!    tracked.
//! 4. S is then the teacher's ([`crate::overlap`]): the current frame's depth moved into the
//!    reference with that pose, at the working resolution.
//!
//! The pose fails (None) when fewer than [`MIN_INLIERS`] points, or fewer than half of those
//! tracked, agree with it: too few tracks (the view left the reference, motion blur), a
//! textureless view, depth holes under the corners. The caller then falls back to the colour-only
//! utility for that frame.

use crate::geometry::{solve, track_with, Pyramid, LK_PRIOR};
use crate::overlap::{Pinhole, Rigid};

/// The teacher's distance check (metres): a match counts when its two 3-D points are closer.
pub const MAX_DIST_M: f64 = 0.1;
/// Most corners picked on a reference.
pub const MAX_POINTS: usize = 160;
/// Side of the grid cells corners are picked from (working pixels).
pub const CELL: usize = 10;
/// Forward-backward tracking tolerance (working pixels).
pub const FB_PX: f32 = 1.0;
/// Reprojection error (working pixels) under which a track agrees with the pose.
pub const INLIER_PX: f64 = 2.0;
/// Fewest agreeing tracks for a pose.
pub const MIN_INLIERS: usize = 15;
/// Huber's threshold of the robust fit (working pixels).
const HUBER_PX: f64 = 1.5;
/// Below this many tracked points, a frame whose pose held adds its own corners (lifted with its
/// depth, carried into the reference's camera by the pose): the tracks last as the view moves
/// off the reference.
pub const REPLENISH_BELOW: usize = MAX_POINTS / 2;
/// Frames in a row whose pose may fail (a blurred frame, a sudden jolt) before tracking is lost
/// until the next reference: the tracks wait on the last frame that held, and the next frame is
/// tracked from it.
pub const MAX_MISSES: u32 = 3;

/// `exp(delta) * pose`, `delta` = (translation, rotation vector): a Gauss-Newton step.
fn updated(pose: &Rigid, delta: &[f64; 6]) -> Rigid {
    let w = [delta[3], delta[4], delta[5]];
    let th = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    let k = if th > 1e-12 {
        [w[0] / th, w[1] / th, w[2] / th]
    } else {
        [0.0; 3]
    };
    let (s, c) = th.sin_cos();
    let mut dr = [[0.0; 3]; 3];
    let kx = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    for i in 0..3 {
        for j in 0..3 {
            let kk: f64 = (0..3).map(|m| kx[i][m] * kx[m][j]).sum();
            dr[i][j] = f64::from(u8::from(i == j)) + s * kx[i][j] + (1.0 - c) * kk;
        }
    }
    let d = Rigid {
        r: dr,
        t: [delta[0], delta[1], delta[2]],
    };
    d.compose(pose)
}

/// Corners of a grey picture (`w` x `h`) with valid depth (`depth[i] > 0`, metres, same size):
/// the strongest Shi-Tomasi response (5x5 window) of each [`CELL`]-pixel cell, the
/// [`MAX_POINTS`] strongest of those, away from the border.
pub fn corners(grey: &[f32], depth: &[f32], w: usize, h: usize) -> Vec<(usize, usize)> {
    corners_except(grey, depth, w, h, &[])
}

/// [`corners`], skipping the cells that hold one of `taken` (pixel positions): a corner there
/// would lie within a cell of that point.
fn corners_except(
    grey: &[f32],
    depth: &[f32],
    w: usize,
    h: usize,
    taken: &[(f32, f32)],
) -> Vec<(usize, usize)> {
    const BORDER: usize = 5;
    if w < 12 || h < 12 || grey.len() != w * h || depth.len() != w * h {
        return Vec::new();
    }
    let cells_x = (w - 2 * BORDER).div_ceil(CELL);
    let cells_y = (h - 2 * BORDER).div_ceil(CELL);
    let mut skip = vec![false; cells_x * cells_y];
    for &(x, y) in taken {
        let (cx, cy) = (
            (x - BORDER as f32) / CELL as f32,
            (y - BORDER as f32) / CELL as f32,
        );
        if cx >= 0.0 && cy >= 0.0 && (cx as usize) < cells_x && (cy as usize) < cells_y {
            skip[cy as usize * cells_x + cx as usize] = true;
        }
    }
    // Gradient products, then their 5x5 sums: along rows first, then down the columns.
    let mut prod = vec![[0.0f32; 3]; w * h];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let i = y * w + x;
            let (dx, dy) = (grey[i + 1] - grey[i - 1], grey[i + w] - grey[i - w]);
            prod[i] = [dx * dx, dx * dy, dy * dy];
        }
    }
    let mut rows = vec![[0.0f32; 3]; w * h];
    for y in BORDER - 2..h - BORDER + 2 {
        for x in BORDER..w - BORDER {
            let mut s = [0.0f32; 3];
            for p in &prod[y * w + x - 2..=y * w + x + 2] {
                for k in 0..3 {
                    s[k] += p[k];
                }
            }
            rows[y * w + x] = s;
        }
    }
    let mut best: Vec<(f32, usize, usize)> = Vec::new();
    for (ci, cy) in (BORDER..h - BORDER).step_by(CELL).enumerate() {
        for (cj, cx) in (BORDER..w - BORDER).step_by(CELL).enumerate() {
            if skip[ci * cells_x + cj] {
                continue;
            }
            let mut cell: Option<(f32, usize, usize)> = None;
            for y in cy..(cy + CELL).min(h - BORDER) {
                for x in cx..(cx + CELL).min(w - BORDER) {
                    if depth[y * w + x] <= 0.0 {
                        continue;
                    }
                    let [mut a, mut b, mut c] = [0.0f32; 3];
                    for yy in y - 2..=y + 2 {
                        let r = rows[yy * w + x];
                        a += r[0];
                        b += r[1];
                        c += r[2];
                    }
                    let min_eig = 0.5 * (a + c - ((a - c) * (a - c) + 4.0 * b * b).sqrt());
                    if cell.is_none_or(|(s, _, _)| min_eig > s) {
                        cell = Some((min_eig, x, y));
                    }
                }
            }
            best.extend(cell);
        }
    }
    let top = best.iter().map(|c| c.0).fold(0.0f32, f32::max);
    best.retain(|c| c.0 > 0.01 * top && c.0 > 0.0);
    best.sort_by(|a, b| b.0.total_cmp(&a.0));
    best.truncate(MAX_POINTS);
    best.into_iter().map(|(_, x, y)| (x, y)).collect()
}

/// Fit the pose (reference camera -> current camera) to 3-D points of the reference and their
/// tracked positions in the current picture, starting from `init`. Returns the pose and which
/// points agree with it (reprojection within [`INLIER_PX`]); None when it does not converge to
/// [`MIN_INLIERS`] agreeing points, or half of them.
pub fn fit_pose(
    cam: &Pinhole,
    points: &[[f64; 3]],
    seen: &[(f32, f32)],
    init: &Rigid,
) -> Option<(Rigid, Vec<bool>)> {
    if points.len() != seen.len() || points.len() < MIN_INLIERS {
        return None;
    }
    let mut pose = *init;
    let mut use_all = vec![true; points.len()];
    for round in 0..2 {
        for _ in 0..if round == 0 { 10 } else { 5 } {
            let mut hm = [[0.0f64; 6]; 6];
            let mut g = [0.0f64; 6];
            let mut n = 0;
            for ((p, &(u, v)), &on) in points.iter().zip(seen).zip(&use_all) {
                if !on {
                    continue;
                }
                let q = pose.apply(*p);
                if q[2] <= 1e-6 {
                    continue;
                }
                let (x, y, z) = (q[0], q[1], q[2]);
                let iz = 1.0 / z;
                let eu = cam.fx * x * iz + cam.cx - u as f64;
                let ev = cam.fy * y * iz + cam.cy - v as f64;
                let e = (eu * eu + ev * ev).sqrt();
                let wgt = if e <= HUBER_PX { 1.0 } else { HUBER_PX / e };
                let ju = [
                    cam.fx * iz,
                    0.0,
                    -cam.fx * x * iz * iz,
                    -cam.fx * x * y * iz * iz,
                    cam.fx * (1.0 + x * x * iz * iz),
                    -cam.fx * y * iz,
                ];
                let jv = [
                    0.0,
                    cam.fy * iz,
                    -cam.fy * y * iz * iz,
                    -cam.fy * (1.0 + y * y * iz * iz),
                    cam.fy * x * y * iz * iz,
                    cam.fy * x * iz,
                ];
                for i in 0..6 {
                    g[i] += wgt * (ju[i] * eu + jv[i] * ev);
                    for j in 0..6 {
                        hm[i][j] += wgt * (ju[i] * ju[j] + jv[i] * jv[j]);
                    }
                }
                n += 1;
            }
            if n < 6 {
                return None;
            }
            let delta = solve(hm, g.map(|x| -x))?;
            pose = updated(&pose, &delta);
            if delta.iter().map(|d| d * d).sum::<f64>() < 1e-12 {
                break;
            }
        }
        for ((p, &(u, v)), on) in points.iter().zip(seen).zip(use_all.iter_mut()) {
            let q = pose.apply(*p);
            *on = q[2] > 1e-6 && {
                let eu = cam.fx * q[0] / q[2] + cam.cx - u as f64;
                let ev = cam.fy * q[1] / q[2] + cam.cy - v as f64;
                eu * eu + ev * ev <= INLIER_PX * INLIER_PX
            };
        }
    }
    let inliers = use_all.iter().filter(|&&b| b).count();
    let finite = pose
        .r
        .iter()
        .flatten()
        .chain(&pose.t)
        .all(|v| v.is_finite());
    (finite && inliers >= MIN_INLIERS && 2 * inliers >= points.len()).then_some((pose, use_all))
}

/// Tracks a reference's corners from frame to frame and fits the current pose to them.
#[derive(Debug, Clone)]
pub struct PoseTracker {
    cam: Pinhole,
    /// 3-D points of the reference camera still tracked, with where they were last seen.
    points: Vec<[f64; 3]>,
    seen: Vec<(f32, f32)>,
    prev: Option<Pyramid>,
    /// Reference camera -> the last frame's camera.
    pose: Rigid,
    /// Whether tracking goes on (the reference had points, and no more than [`MAX_MISSES`] frames
    /// in a row failed since the last pose that held).
    live: bool,
    /// Frames in a row whose pose failed; `prev` and `seen` are still the last good frame's.
    misses: u32,
}

impl PoseTracker {
    pub fn new(cam: Pinhole) -> PoseTracker {
        PoseTracker {
            cam,
            points: Vec::new(),
            seen: Vec::new(),
            prev: None,
            pose: Rigid::IDENTITY,
            live: false,
            misses: 0,
        }
    }

    pub fn camera(&self) -> &Pinhole {
        &self.cam
    }

    /// This frame (grey picture and depth in metres, `w` x `h`, the camera's working size) is
    /// the new reference.
    pub fn set_reference(&mut self, grey: &[f32], depth: &[f32], w: usize, h: usize) {
        let pts = corners(grey, depth, w, h);
        self.points = pts.iter().map(|&p| self.lift(p, depth, w)).collect();
        self.seen = pts.iter().map(|&(x, y)| (x as f32, y as f32)).collect();
        self.prev = Some(Pyramid::new(grey.to_vec(), w, h));
        self.pose = Rigid::IDENTITY;
        self.live = !self.points.is_empty();
        self.misses = 0;
    }

    /// The 3-D point (this camera's frame) at pixel `(x, y)` of a depth picture `w` wide.
    fn lift(&self, (x, y): (usize, usize), depth: &[f32], w: usize) -> [f64; 3] {
        let c = &self.cam;
        let z = depth[y * w + x] as f64;
        [
            (x as f64 - c.cx) / c.fx * z,
            (y as f64 - c.cy) / c.fy * z,
            z,
        ]
    }

    /// New corners of the frame just fitted (not within a cell of a tracked point), lifted with
    /// its depth and carried into the reference camera by the inverse of its pose.
    fn replenish(&mut self, grey: &[f32], depth: &[f32], w: usize, h: usize) {
        let to_ref = self.pose.inverse();
        let near = |x: f32, y: f32, s: &[(f32, f32)]| {
            s.iter()
                .any(|&(sx, sy)| (sx - x).abs() < CELL as f32 && (sy - y).abs() < CELL as f32)
        };
        for p in corners_except(grey, depth, w, h, &self.seen) {
            if self.points.len() >= MAX_POINTS {
                break;
            }
            let (x, y) = (p.0 as f32, p.1 as f32);
            if near(x, y, &self.seen) {
                continue;
            }
            let q = to_ref.apply(self.lift(p, depth, w));
            self.points.push(q);
            self.seen.push((x, y));
        }
    }

    /// Track into this frame's grey picture and fit its pose: reference camera -> this camera.
    /// None when the pose fails: the tracks then wait on the last frame whose pose held, and the
    /// next frame is tracked from there; after more than [`MAX_MISSES`] failures in a row,
    /// tracking is lost until the next reference.
    pub fn observe(&mut self, grey: &[f32], depth: &[f32], w: usize, h: usize) -> Option<Rigid> {
        if !self.live {
            return None;
        }
        let cur = Pyramid::new(grey.to_vec(), w, h);
        let prev = self.prev.as_ref()?;
        let mut keep_pts = Vec::with_capacity(self.points.len());
        let mut keep_seen = Vec::with_capacity(self.points.len());
        for (p, &s) in self.points.iter().zip(&self.seen) {
            let Some(q) = track_with(prev, &cur, s, &LK_PRIOR) else {
                continue;
            };
            let Some(back) = track_with(&cur, prev, q, &LK_PRIOR) else {
                continue;
            };
            let (dx, dy) = (back.0 - s.0, back.1 - s.1);
            if dx * dx + dy * dy <= FB_PX * FB_PX {
                keep_pts.push(*p);
                keep_seen.push(q);
            }
        }
        match fit_pose(&self.cam, &keep_pts, &keep_seen, &self.pose) {
            Some((pose, inlier)) => {
                self.points = keep_pts
                    .into_iter()
                    .zip(&inlier)
                    .filter_map(|(p, &i)| i.then_some(p))
                    .collect();
                self.seen = keep_seen
                    .into_iter()
                    .zip(&inlier)
                    .filter_map(|(s, &i)| i.then_some(s))
                    .collect();
                self.pose = pose;
                self.prev = Some(cur);
                self.misses = 0;
                if self.points.len() < REPLENISH_BELOW && depth.len() == w * h {
                    self.replenish(grey, depth, w, h);
                }
                Some(pose)
            }
            None => {
                self.misses += 1;
                self.live = self.misses <= MAX_MISSES;
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured plane 2 m away, seen by a 160x120 camera; `shift` moves the camera sideways
    /// (metres).
    fn scene(shift: f64) -> (Vec<f32>, Vec<f32>) {
        let (w, h) = (160usize, 120usize);
        let cam = cam();
        let mut grey = vec![0.0f32; w * h];
        let depth = vec![2.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                // The plane's point under pixel (x, y), in world coordinates.
                let wx = (x as f64 - cam.cx) / cam.fx * 2.0 + shift;
                let wy = (y as f64 - cam.cy) / cam.fy * 2.0;
                let v = (wx * 9.0).sin() * (wy * 7.0).cos() + (wx * 3.1 + wy * 4.3).sin();
                grey[y * w + x] = (128.0 + 60.0 * v) as f32;
            }
        }
        (grey, depth)
    }

    fn cam() -> Pinhole {
        Pinhole {
            fx: 130.0,
            fy: 130.0,
            cx: 79.5,
            cy: 59.5,
        }
    }

    /// The Shi-Tomasi response of pixel (x, y) straight from its definition.
    fn response(grey: &[f32], w: usize, x: usize, y: usize) -> f32 {
        let (mut a, mut b, mut c) = (0.0f32, 0.0f32, 0.0f32);
        for yy in y - 2..=y + 2 {
            for xx in x - 2..=x + 2 {
                let i = yy * w + xx;
                let (dx, dy) = (grey[i + 1] - grey[i - 1], grey[i + w] - grey[i - w]);
                a += dx * dx;
                b += dx * dy;
                c += dy * dy;
            }
        }
        0.5 * (a + c - ((a - c) * (a - c) + 4.0 * b * b).sqrt())
    }

    /// Each corner is its cell's strongest response by the definition (holes in the depth
    /// skipped), corners come strongest first, and cells that hold a taken point give none.
    #[test]
    fn corners_are_each_cells_strongest_response() {
        let (w, h) = (160usize, 120usize);
        let (grey, mut depth) = scene(0.3);
        for y in 40..70 {
            for x in 20..90 {
                depth[y * w + x] = 0.0;
            }
        }
        let pts = corners(&grey, &depth, w, h);
        assert!(pts.len() > 100, "{} corners", pts.len());
        let mut last = f32::INFINITY;
        for &(x, y) in &pts {
            assert!(
                depth[y * w + x] > 0.0,
                "corner ({x}, {y}) in a hole of the depth"
            );
            let r = response(&grey, w, x, y);
            assert!(r <= last * 1.0001, "corners out of order at ({x}, {y})");
            last = r;
            let (cx, cy) = (5 + (x - 5) / CELL * CELL, 5 + (y - 5) / CELL * CELL);
            for yy in cy..(cy + CELL).min(h - 5) {
                for xx in cx..(cx + CELL).min(w - 5) {
                    if depth[yy * w + xx] > 0.0 {
                        let other = response(&grey, w, xx, yy);
                        assert!(other <= r * 1.0001, "({xx}, {yy}) beats ({x}, {y})");
                    }
                }
            }
        }
        let taken: Vec<(f32, f32)> = pts[..40]
            .iter()
            .map(|&(x, y)| (x as f32 + 0.5, y as f32))
            .collect();
        let rest = corners_except(&grey, &depth, w, h, &taken);
        for &(x, y) in &rest {
            assert!(
                !taken
                    .iter()
                    .any(|&(tx, ty)| (tx as usize - 5) / CELL == (x - 5) / CELL
                        && (ty as usize - 5) / CELL == (y - 5) / CELL),
                "({x}, {y}) shares a cell with a taken point"
            );
        }
        assert!(rest.len() >= pts.len() - 40, "{} corners left", rest.len());
    }

    /// The camera slides sideways 1 cm a frame for `frames` frames from the reference; every
    /// frame's pose must hold. The last pose.
    fn slide(frames: usize) -> Rigid {
        let mut t = PoseTracker::new(cam());
        let (g0, d0) = scene(0.0);
        t.set_reference(&g0, &d0, 160, 120);
        let mut last = None;
        for k in 1..=frames {
            let (g, d) = scene(0.01 * k as f64);
            last = t.observe(&g, &d, 160, 120);
            assert!(last.is_some(), "frame {k}");
        }
        last.unwrap()
    }

    #[test]
    fn a_sideways_move_is_recovered_from_tracks_and_depth() {
        let p = slide(5);
        // The camera moved +5 cm in x: reference points move -5 cm in its frame.
        assert!((p.t[0] + 0.05).abs() < 0.005, "{p:?}");
        assert!(p.t[1].abs() < 0.005 && p.t[2].abs() < 0.01, "{p:?}");
    }

    #[test]
    fn a_view_without_texture_or_depth_has_no_pose() {
        let mut t = PoseTracker::new(cam());
        let flat = vec![100.0f32; 160 * 120];
        t.set_reference(&flat, &vec![2.0; 160 * 120], 160, 120);
        assert_eq!(t.observe(&flat, &vec![2.0; 160 * 120], 160, 120), None);
        let (g, _) = scene(0.0);
        t.set_reference(&g, &vec![0.0; 160 * 120], 160, 120);
        assert_eq!(t.observe(&g, &vec![0.0; 160 * 120], 160, 120), None);
    }

    /// The camera slides 3 m along the plane, more than a view's width: the reference's corners
    /// leave the picture, the corners the tracked frames add carry the pose to the end.
    #[test]
    fn tracks_are_replenished_as_the_view_leaves_the_reference() {
        let p = slide(300);
        assert!((p.t[0] + 3.0).abs() < 0.06, "{p:?}");
        assert!(p.t[1].abs() < 0.03 && p.t[2].abs() < 0.03, "{p:?}");
    }

    /// A frame whose pose fails (here a featureless one, as a blurred frame) is skipped: the next
    /// frame is tracked from the last one that held. More than MAX_MISSES in a row lose tracking
    /// until the next reference.
    #[test]
    fn a_few_failed_frames_are_bridged_more_lose_tracking() {
        let flat = vec![100.0f32; 160 * 120];
        let two = vec![2.0f32; 160 * 120];
        for misses in [1, MAX_MISSES, MAX_MISSES + 1] {
            let mut t = PoseTracker::new(cam());
            let (g0, d0) = scene(0.0);
            t.set_reference(&g0, &d0, 160, 120);
            for k in 1..=3 {
                let (g, d) = scene(0.01 * k as f64);
                assert!(t.observe(&g, &d, 160, 120).is_some());
            }
            for _ in 0..misses {
                assert_eq!(t.observe(&flat, &two, 160, 120), None);
            }
            let (g, d) = scene(0.04);
            let p = t.observe(&g, &d, 160, 120);
            if misses <= MAX_MISSES {
                let p = p.expect("tracked from the last good frame");
                assert!((p.t[0] + 0.04).abs() < 0.005, "{p:?}");
            } else {
                assert_eq!(p, None, "{misses} misses in a row");
            }
        }
    }

    #[test]
    fn pose_algebra() {
        let p = updated(&Rigid::IDENTITY, &[0.1, -0.2, 0.3, 0.05, -0.02, 0.1]);
        let q = p.compose(&p.inverse());
        for i in 0..3 {
            for j in 0..3 {
                assert!((q.r[i][j] - f64::from(u8::from(i == j))).abs() < 1e-12);
            }
            assert!(q.t[i].abs() < 1e-12);
        }
    }
}
