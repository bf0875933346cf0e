//! The pair overlap: MASt3R-SLAM's keyframe criterion `S = min(f_m, f_u)` computed exactly from
//! the depth of two views and their relative pose.
//!
//! This is the one implementation of the overlap: the teacher (`leangate_tools::teacher`, which
//! labels training pairs and judges every gate from ground-truth depth and poses) scores its pairs
//! with [`score_pair`], and so can any code of the element that has depth. It is plain Rust (no
//! GStreamer, no linear-algebra crate): poses are [`Rigid`] transforms, intrinsics a [`Pinhole`].
//!
//! # Definition
//!
//! For a pair (current frame `i`, keyframe `j`), each pixel of `i` with a valid depth is
//! unprojected, moved by the relative pose into `j`'s camera and projected into `j`. The match
//! is *valid* when it lands inside `j` on a pixel with valid depth and the two 3-D points (the
//! transformed point of `i`, and `j`'s own unprojected point at that pixel, both in `j`'s
//! camera frame) are closer than `max_dist_m` (the teacher's default is 0.1 m). Then
//!
//! * `f_m` = valid matches / valid-depth pixels of `i`;
//! * `f_u` = distinct pixels of `j` hit by valid matches / valid-depth pixels of `j`;
//! * `S = min(f_m, f_u)`, `tau = 1 - S` (utility: 0 = nothing new, 1 = all new).
//!
//! If `i` or `j` has no valid depth pixel, `S = 0` (`tau = 1`, [`PairScore::NOTHING_SHARED`]).
//!
//! # Conventions
//!
//! OpenCV/TUM camera frame (x right, y down, z forward); [`score_pair`] takes the relative pose
//! *current camera → keyframe camera* (a point `p` of `i`'s camera frame is `r p + t` in `j`'s;
//! with camera-to-world poses `P_i`, `P_j` that is `P_j⁻¹ P_i`, [`Rigid::inverse`] and
//! [`Rigid::compose`]); pixel `(u, v)` at integer coordinates of pixel centres; projection
//! `u = fx X/Z + cx` rounded to the nearest integer; inside when `0 <= u < W`, `0 <= v < H` and
//! `Z > 0`. Depth is in metres; 0 (and anything non-finite or non-positive) is invalid.
//!
//! # Working resolution
//!
//! Depth is scored at a working resolution. [`DepthView::from_full`] subsamples a full-resolution
//! image by an integer step `k` (the teacher's is `max(1, round(W / working_width))`, about 160
//! pixels wide): every `k`-th pixel of every `k`-th row is taken, without averaging (which would
//! create flying points at depth edges). The subsampled intrinsics are exactly
//! `fx/k, fy/k, cx/k, cy/k`, since subsampled pixel `u'` is full-resolution pixel `k u'`.
//! [`DepthView::from_working`] takes depth that is already at the working resolution.
//!
//! A [`DepthView`] stores the working depth plus per-column and per-row ray factors
//! `(u - cx)/fx`, `(v - cy)/fy`, so a 3-D point is `(xr[u] z, yr[v] z, z)`: the unprojection is
//! precomputed once per view while memory stays at 4 bytes per working pixel (77 KB per frame
//! at 160x120), which matters for sequences of thousands of frames.
//!
//! # Speed
//!
//! [`score_pair`] is one pass over the current view with `f32` arithmetic and a reusable
//! per-thread bitmap for distinct hits (no allocation per pair after a thread's first). On the
//! 7-Scenes clip at 160x120 (strongly overlapping pairs, the slow case) it scores about 4,000
//! pairs/s per core (the tools' `cargo test -p leangate-tools teacher_speed -- --ignored
//! --nocapture`); the teacher spreads pairs over rayon's pool.

use std::cell::Cell;

use crate::geometry::Mat3;

/// Pinhole intrinsics in pixels (pixel centres at integer coordinates).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    /// Focal length along x.
    pub fx: f64,
    /// Focal length along y.
    pub fy: f64,
    /// Principal point x.
    pub cx: f64,
    /// Principal point y.
    pub cy: f64,
}

/// A rigid transform `p ↦ r p + t` (a rotation matrix, row-major, and a translation in metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rigid {
    /// Rotation matrix, row-major.
    pub r: Mat3,
    /// Translation.
    pub t: [f64; 3],
}

impl Rigid {
    /// The identity transform.
    pub const IDENTITY: Rigid = Rigid {
        r: crate::geometry::IDENTITY,
        t: [0.0; 3],
    };

    /// A pure translation.
    pub fn translation(x: f64, y: f64, z: f64) -> Rigid {
        Rigid {
            t: [x, y, z],
            ..Rigid::IDENTITY
        }
    }

    /// `r p + t`.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.r;
        [0, 1, 2].map(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + self.t[i])
    }

    /// The inverse transform `p ↦ rᵀ (p - t)` (`r` is taken to be a rotation).
    pub fn inverse(&self) -> Rigid {
        let r = &self.r;
        let rt: Mat3 = [0, 1, 2].map(|i| [r[0][i], r[1][i], r[2][i]]);
        let t = self.t;
        let t = [0, 1, 2].map(|i| -(rt[i][0] * t[0] + rt[i][1] * t[1] + rt[i][2] * t[2]));
        Rigid { r: rt, t }
    }

    /// `self ∘ other`: applies `other` first, then `self` (as `self * other` with matrices).
    /// With camera-to-world poses, `key.inverse().compose(&cur)` is current → keyframe camera.
    pub fn compose(&self, other: &Rigid) -> Rigid {
        Rigid {
            r: crate::geometry::mat_mul(&self.r, &other.r),
            t: self.apply(other.t),
        }
    }
}

/// Why a [`DepthView`] cannot be built.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ViewError {
    /// The depth slice does not hold `width * height` values.
    #[error("{len} values for {width}x{height}")]
    Size {
        /// Values given.
        len: usize,
        /// Width given.
        width: u32,
        /// Height given.
        height: u32,
    },
    /// Zero width or height.
    #[error("empty image")]
    Empty,
    /// `fx` or `fy` is not positive (or not a number).
    #[error("non-positive focal length")]
    Focal,
    /// A subsampling step of 0.
    #[error("subsampling step 0")]
    Step,
}

/// Depth at the working resolution with its intrinsics and precomputed ray factors.
#[derive(Debug, Clone)]
pub struct DepthView {
    /// Working width.
    pub width: u32,
    /// Working height.
    pub height: u32,
    /// Working-resolution intrinsics (`fx/k` etc.).
    pub intrinsics: Pinhole,
    /// Subsampling step `k` from the full resolution (1 for [`DepthView::from_working`]).
    pub step: u32,
    /// Depth in metres, row-major, 0.0 = invalid (non-finite or non-positive inputs too).
    pub depth: Vec<f32>,
    /// `(u - cx) / fx` per working column.
    xr: Vec<f32>,
    /// `(v - cy) / fy` per working row.
    yr: Vec<f32>,
    /// Number of valid-depth pixels.
    pub valid_count: usize,
}

/// The checks both constructors make, in the teacher's order.
fn check(len: usize, width: u32, height: u32, intr: &Pinhole) -> Result<(), ViewError> {
    if len != width as usize * height as usize {
        return Err(ViewError::Size { len, width, height });
    }
    if width == 0 || height == 0 {
        return Err(ViewError::Empty);
    }
    if !(intr.fx > 0.0 && intr.fy > 0.0) {
        return Err(ViewError::Focal);
    }
    Ok(())
}

/// A depth reading, or 0.0 (invalid) when it is non-finite or non-positive.
fn sanitize(d: f32) -> f32 {
    if d.is_finite() && d > 0.0 {
        d
    } else {
        0.0
    }
}

impl DepthView {
    /// Subsamples full-resolution `depth` (`width` x `height` metres, row-major, intrinsics
    /// `intrinsics`) by the integer `step` `k`: every `k`-th pixel of every `k`-th row, no
    /// averaging; the view is `ceil(W / k)` x `ceil(H / k)` with intrinsics divided by `k`.
    pub fn from_full(
        depth: &[f32],
        width: u32,
        height: u32,
        intrinsics: Pinhole,
        step: u32,
    ) -> Result<DepthView, ViewError> {
        check(depth.len(), width, height, &intrinsics)?;
        if step == 0 {
            return Err(ViewError::Step);
        }
        let (w, h, k) = (width as usize, height as usize, step as usize);
        let (ww, wh) = (w.div_ceil(k), h.div_ceil(k));
        let mut data = Vec::with_capacity(ww * wh);
        for v in 0..wh {
            let row = &depth[v * k * w..(v * k + 1) * w];
            data.extend(row.iter().step_by(k).map(|&d| sanitize(d)));
        }
        let kf = k as f64;
        let sub = Pinhole {
            fx: intrinsics.fx / kf,
            fy: intrinsics.fy / kf,
            cx: intrinsics.cx / kf,
            cy: intrinsics.cy / kf,
        };
        Ok(Self::from_valid(ww as u32, wh as u32, sub, step, data))
    }

    /// A view of depth already at the working resolution (`width` x `height` metres, row-major,
    /// `intrinsics` of that resolution); step 1. Non-finite and non-positive values become 0.0.
    pub fn from_working(
        mut depth: Vec<f32>,
        width: u32,
        height: u32,
        intrinsics: Pinhole,
    ) -> Result<DepthView, ViewError> {
        check(depth.len(), width, height, &intrinsics)?;
        depth.iter_mut().for_each(|d| *d = sanitize(*d));
        Ok(Self::from_valid(width, height, intrinsics, 1, depth))
    }

    /// Builds a view from checked, sanitized working depth.
    fn from_valid(w: u32, h: u32, intr: Pinhole, step: u32, depth: Vec<f32>) -> DepthView {
        let xr = (0..w)
            .map(|u| ((u as f64 - intr.cx) / intr.fx) as f32)
            .collect();
        let yr = (0..h)
            .map(|v| ((v as f64 - intr.cy) / intr.fy) as f32)
            .collect();
        let valid_count = depth.iter().filter(|&&d| d > 0.0).count();
        DepthView {
            width: w,
            height: h,
            intrinsics: intr,
            step,
            depth,
            xr,
            yr,
            valid_count,
        }
    }

    /// The 3-D point (camera frame) of working pixel `(u, v)`, if its depth is valid.
    pub fn point(&self, u: u32, v: u32) -> Option<[f32; 3]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        let z = self.depth[v as usize * self.width as usize + u as usize];
        (z > 0.0).then(|| [self.xr[u as usize] * z, self.yr[v as usize] * z, z])
    }
}

/// The overlap score of one pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairScore {
    /// Fraction of the current frame's valid pixels with a valid match in the keyframe.
    pub f_m: f64,
    /// Fraction of the keyframe's valid pixels hit by at least one valid match.
    pub f_u: f64,
    /// `min(f_m, f_u)`.
    pub s: f64,
    /// `1 - s`.
    pub tau: f64,
}

impl PairScore {
    /// The degenerate score (no valid depth): `S = 0`, `tau = 1`.
    pub const NOTHING_SHARED: PairScore = PairScore {
        f_m: 0.0,
        f_u: 0.0,
        s: 0.0,
        tau: 1.0,
    };
}

thread_local! {
    /// Reusable bitmap of keyframe pixels already hit (one bit per working pixel).
    static HIT_BITMAP: Cell<Vec<u64>> = const { Cell::new(Vec::new()) };
}

/// Scores the pair (current view `cur`, keyframe view `key`); `cur_to_key` moves points of the
/// current camera frame into the keyframe's camera frame; matches farther apart than
/// `max_dist_m` (metres) are not valid. Allocation-free after the first call on a thread.
pub fn score_pair(
    cur: &DepthView,
    key: &DepthView,
    cur_to_key: &Rigid,
    max_dist_m: f64,
) -> PairScore {
    if cur.valid_count == 0 || key.valid_count == 0 {
        return PairScore::NOTHING_SHARED;
    }
    let m = &cur_to_key.r;
    let rm: [[f32; 3]; 3] = m.map(|row| row.map(|x| x as f32));
    let t = cur_to_key.t;
    let (tx, ty, tz) = (t[0] as f32, t[1] as f32, t[2] as f32);
    let ki = &key.intrinsics;
    let (kfx, kfy, kcx, kcy) = (ki.fx as f32, ki.fy as f32, ki.cx as f32, ki.cy as f32);
    let (kw, kh) = (key.width as usize, key.height as usize);
    let (kwf, khf) = (kw as f32, kh as f32);
    let max_d2 = (max_dist_m * max_dist_m) as f32;
    let cw = cur.width as usize;

    // Take the thread's bitmap out of the thread-local so the hot loop works on locals.
    let mut bm = HIT_BITMAP.with(|b| b.take());
    let words = (kw * kh).div_ceil(64);
    bm.clear();
    bm.resize(words, 0);
    let mut valid = 0usize;
    let mut distinct = 0usize;
    for (v, row) in cur.depth.chunks_exact(cw).enumerate() {
        let yr = cur.yr[v];
        // Row-constant parts of R * (x z, y z, z) = z * (R (x, y, 1)).
        let (b0, b1, b2) = (
            rm[0][1] * yr + rm[0][2],
            rm[1][1] * yr + rm[1][2],
            rm[2][1] * yr + rm[2][2],
        );
        for (&z, &xr) in row.iter().zip(&cur.xr) {
            if z <= 0.0 {
                continue;
            }
            let qz = z * (rm[2][0] * xr + b2) + tz;
            if qz <= 0.0 {
                continue;
            }
            let qx = z * (rm[0][0] * xr + b0) + tx;
            let qy = z * (rm[1][0] * xr + b1) + ty;
            let inv = 1.0 / qz;
            let uf = kfx * qx * inv + kcx + 0.5;
            let vf = kfy * qy * inv + kcy + 0.5;
            // round-to-nearest lands inside iff 0 <= u + 0.5 < W; then truncation is floor
            if !(uf >= 0.0 && uf < kwf && vf >= 0.0 && vf < khf) {
                continue;
            }
            let ku = (uf as usize).min(kw - 1);
            let kv = (vf as usize).min(kh - 1);
            let idx = kv * kw + ku;
            let kz = key.depth[idx];
            if kz <= 0.0 {
                continue;
            }
            let dx = key.xr[ku] * kz - qx;
            let dy = key.yr[kv] * kz - qy;
            let dz = kz - qz;
            if dx * dx + dy * dy + dz * dz >= max_d2 {
                continue;
            }
            valid += 1;
            let (w, b) = (idx >> 6, 1u64 << (idx & 63));
            let word = &mut bm[w];
            distinct += (*word & b == 0) as usize;
            *word |= b;
        }
    }
    HIT_BITMAP.with(|b| b.set(bm));
    let f_m = valid as f64 / cur.valid_count as f64;
    let f_u = distinct as f64 / key.valid_count as f64;
    let s = f_m.min(f_u);
    PairScore {
        f_m,
        f_u,
        s,
        tau: 1.0 - s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: u32 = 160;
    const H: u32 = 120;
    const F: f64 = 140.0;

    fn intr() -> Pinhole {
        Pinhole {
            fx: F,
            fy: F,
            cx: (W as f64 - 1.0) / 2.0,
            cy: (H as f64 - 1.0) / 2.0,
        }
    }

    /// A rotation by `angle` about the camera's y axis.
    fn yaw(angle: f64) -> Rigid {
        let (s, c) = angle.sin_cos();
        Rigid {
            r: [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]],
            t: [0.0; 3],
        }
    }

    /// Ray-casts a scene given as a list of axis-aligned boxes (world frame) plus a plane
    /// z = `plane_z` (world), camera at `pose` (camera-to-world); W x H z-depths.
    fn render(pose: &Rigid, plane_z: f64, boxes: &[([f64; 3], [f64; 3])]) -> Vec<f32> {
        let k = intr();
        let mut d = vec![0.0f32; (W * H) as usize];
        let o = pose.t;
        for v in 0..H {
            for u in 0..W {
                let dc = [(u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0];
                let dw = Rigid {
                    t: [0.0; 3],
                    ..*pose
                }
                .apply(dc);
                let mut best = f64::INFINITY;
                if dw[2].abs() > 1e-12 {
                    let t = (plane_z - o[2]) / dw[2];
                    if t > 0.0 {
                        best = t;
                    }
                }
                for (lo, hi) in boxes {
                    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
                    for a in 0..3 {
                        let inv = 1.0 / dw[a];
                        let (mut ta, mut tb) = ((lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv);
                        if ta > tb {
                            std::mem::swap(&mut ta, &mut tb);
                        }
                        t0 = t0.max(ta);
                        t1 = t1.min(tb);
                    }
                    if t0 <= t1 && t0 > 0.0 && t0 < best {
                        best = t0;
                    }
                }
                // t is the z-depth because the camera-frame ray has z = 1
                if best.is_finite() {
                    d[(v * W + u) as usize] = best as f32;
                }
            }
        }
        d
    }

    fn view(d: &[f32]) -> DepthView {
        DepthView::from_working(d.to_vec(), W, H, intr()).unwrap()
    }

    /// Current → keyframe camera from camera-to-world poses.
    fn rel(cur: &Rigid, key: &Rigid) -> Rigid {
        key.inverse().compose(cur)
    }

    #[test]
    fn identity_on_a_plane_gives_s_one() {
        let v = view(&render(&Rigid::IDENTITY, 2.0, &[]));
        assert_eq!(v.valid_count, (W * H) as usize);
        let s = score_pair(&v, &v, &Rigid::IDENTITY, 0.1);
        assert_eq!(s.s, 1.0);
        assert_eq!((s.f_m, s.f_u, s.tau), (1.0, 1.0, 0.0));
    }

    #[test]
    fn turned_away_gives_tau_one() {
        let p0 = Rigid::IDENTITY;
        let p1 = yaw(std::f64::consts::PI);
        let v0 = view(&render(&p0, 2.0, &[]));
        let v1 = view(&render(&p1, -2.0, &[]));
        assert!(v1.valid_count > 0);
        let s = score_pair(&v1, &v0, &rel(&p1, &p0), 0.1);
        assert_eq!(s.tau, 1.0);
        assert_eq!(s.f_m, 0.0);
    }

    #[test]
    fn sideways_translation_matches_overlap_formula() {
        let z = 2.0;
        for &t in &[0.1, 0.3, 0.6] {
            let p0 = Rigid::IDENTITY;
            let p1 = Rigid::translation(t, 0.0, 0.0);
            let v0 = view(&render(&p0, z, &[]));
            let v1 = view(&render(&p1, z, &[]));
            let s = score_pair(&v1, &v0, &rel(&p1, &p0), 0.1);
            let expected = 1.0 - F * t / (z * W as f64);
            assert!(
                (s.s - expected).abs() < 0.02,
                "t={t}: S={} expected {expected}",
                s.s
            );
            assert!((s.f_m - s.f_u).abs() < 0.02);
        }
        // A shift of a whole number of pixels at the plane's depth: exactly the columns that
        // stay in view match, one to one.
        let px = 20.0;
        let t = px * z / F;
        let v0 = view(&render(&Rigid::IDENTITY, z, &[]));
        let s = score_pair(&v0, &v0, &Rigid::translation(-t, 0.0, 0.0), 0.1);
        let expected = (W as f64 - px) / W as f64;
        assert!((s.f_m - expected).abs() < 1e-9, "{s:?}");
        assert!((s.f_u - expected).abs() < 1e-9, "{s:?}");
    }

    #[test]
    fn empty_depth_gives_tau_one() {
        let full = view(&render(&Rigid::IDENTITY, 2.0, &[]));
        let empty = view(&vec![0.0; (W * H) as usize]);
        assert_eq!(empty.valid_count, 0);
        let id = Rigid::IDENTITY;
        assert_eq!(
            score_pair(&full, &empty, &id, 0.1),
            PairScore::NOTHING_SHARED
        );
        assert_eq!(
            score_pair(&empty, &full, &id, 0.1),
            PairScore::NOTHING_SHARED
        );
        assert_eq!(score_pair(&empty, &empty, &id, 0.1).tau, 1.0);
    }

    #[test]
    fn occluded_points_do_not_match() {
        // Plane at z = 3; a box in front of it. Two views separated sideways: plane pixels
        // visible in i but hidden behind the box in j must fail the 3-D distance test.
        let boxes = [([-0.3, -0.3, 1.3], [0.3, 0.3, 1.7])];
        let p0 = Rigid::IDENTITY;
        let p1 = Rigid::translation(0.4, 0.0, 0.0);
        let d0 = render(&p0, 3.0, &boxes);
        let d1 = render(&p1, 3.0, &boxes);
        let (v0, v1) = (view(&d0), view(&d1));
        let r = rel(&p1, &p0);
        let s = score_pair(&v1, &v0, &r, 0.1);
        // Reference computed by brute force with an explicit visibility test: a point of i
        // matches if it is within the field of view of j and visible (not behind the box).
        let k = intr();
        let (mut ok, mut total, mut occluded) = (0usize, 0usize, 0usize);
        for v in 0..H {
            for u in 0..W {
                let z = d1[(v * W + u) as usize] as f64;
                total += 1;
                let pc = [
                    (u as f64 - k.cx) / k.fx * z,
                    (v as f64 - k.cy) / k.fy * z,
                    z,
                ];
                let q = r.apply(pc);
                let uu = (k.fx * q[0] / q[2] + k.cx).round();
                let vv = (k.fy * q[1] / q[2] + k.cy).round();
                if uu < 0.0 || vv < 0.0 || uu >= W as f64 || vv >= H as f64 {
                    continue;
                }
                let kz = d0[(vv as u32 * W + uu as u32) as usize] as f64;
                if kz < q[2] - 0.2 {
                    occluded += 1;
                    continue;
                }
                ok += 1;
            }
        }
        assert!(
            occluded > 200,
            "test scene must have occlusion ({occluded})"
        );
        let expected = ok as f64 / total as f64;
        assert!(
            (s.f_m - expected).abs() < 0.02,
            "f_m {} expected {expected}",
            s.f_m
        );
        // Without the distance test the occluded points would count.
        let loose = score_pair(&v1, &v0, &r, 10.0);
        assert!(loose.f_m > s.f_m + (occluded as f64 / total as f64) * 0.8);
    }

    #[test]
    fn the_hit_bitmap_is_cleared_between_pairs_of_any_size() {
        let v0 = view(&render(&Rigid::IDENTITY, 2.0, &[]));
        let v1 = view(&render(&Rigid::translation(0.2, 0.0, 0.0), 2.0, &[]));
        let small =
            DepthView::from_full(&render(&Rigid::IDENTITY, 2.0, &[]), W, H, intr(), 4).unwrap();
        let r = Rigid::translation(0.2, 0.0, 0.0);
        let first = score_pair(&v1, &v0, &r, 0.1);
        let _ = score_pair(&small, &small, &Rigid::IDENTITY, 0.1);
        let _ = score_pair(&v0, &v0, &Rigid::IDENTITY, 0.1);
        assert_eq!(score_pair(&v1, &v0, &r, 0.1), first);
        assert_eq!(score_pair(&small, &small, &Rigid::IDENTITY, 0.1).s, 1.0);
    }

    #[test]
    fn subsampling_takes_every_kth_pixel_and_divides_the_intrinsics() {
        let k = Pinhole {
            fx: 585.0,
            fy: 585.0,
            cx: 320.0,
            cy: 240.0,
        };
        let v = DepthView::from_full(&vec![1.0; 640 * 480], 640, 480, k, 4).unwrap();
        assert_eq!((v.width, v.height, v.step), (160, 120, 4));
        assert_eq!(v.intrinsics.fx, 585.0 / 4.0);
        assert_eq!(v.intrinsics.cx, 80.0);
        assert_eq!(v.valid_count, 160 * 120);
        // 7x5 by 3: columns 0, 3, 6 of rows 0 and 3; no averaging; bad readings become 0.
        let mut d: Vec<f32> = (0..35).map(|i| 1.0 + i as f32).collect();
        d[3] = f32::NAN;
        d[21] = -1.0;
        d[24] = f32::INFINITY;
        let v = DepthView::from_full(&d, 7, 5, k, 3).unwrap();
        assert_eq!((v.width, v.height), (3, 2));
        assert_eq!(v.depth, vec![1.0, 0.0, 7.0, 0.0, 0.0, 28.0]);
        assert_eq!(v.valid_count, 3);
        let (xr, yr) = (
            ((2.0 - 320.0 / 3.0) / 195.0) as f32,
            ((1.0 - 80.0) / 195.0) as f32,
        );
        assert_eq!(v.point(2, 1), Some([xr * 28.0, yr * 28.0, 28.0]));
        assert_eq!(v.point(1, 1), None);
        assert_eq!(v.point(3, 0), None);
        // Step 1 is the image itself.
        let same = DepthView::from_full(&d, 7, 5, k, 1).unwrap();
        assert_eq!((same.width, same.height, same.intrinsics), (7, 5, k));
    }

    #[test]
    fn from_working_sanitizes_and_counts() {
        let d = vec![2.0, f32::NAN, -3.0, f32::INFINITY, 0.0, 1.5];
        let v = DepthView::from_working(d, 3, 2, intr()).unwrap();
        assert_eq!(v.depth, vec![2.0, 0.0, 0.0, 0.0, 0.0, 1.5]);
        assert_eq!((v.valid_count, v.step), (2, 1));
        let p = v.point(0, 0).unwrap();
        assert_eq!(p[2], 2.0);
        assert_eq!(p[0], ((0.0 - intr().cx) / F) as f32 * 2.0);
    }

    #[test]
    fn bad_input_is_refused() {
        let k = intr();
        let e = DepthView::from_full(&[1.0; 5], 10, 10, k, 1).unwrap_err();
        assert_eq!(e.to_string(), "5 values for 10x10");
        let e = DepthView::from_full(&[], 0, 10, k, 1).unwrap_err();
        assert_eq!(e, ViewError::Empty);
        assert_eq!(e.to_string(), "empty image");
        let flat = Pinhole { fx: 0.0, ..k };
        let e = DepthView::from_working(vec![1.0], 1, 1, flat).unwrap_err();
        assert_eq!(e.to_string(), "non-positive focal length");
        let nan = Pinhole { fy: f64::NAN, ..k };
        assert_eq!(
            DepthView::from_working(vec![1.0], 1, 1, nan).unwrap_err(),
            ViewError::Focal
        );
        assert_eq!(
            DepthView::from_full(&[1.0], 1, 1, k, 0).unwrap_err(),
            ViewError::Step
        );
    }

    #[test]
    fn rigid_inverse_and_compose() {
        let a = Rigid {
            t: [0.3, -0.2, 1.0],
            ..yaw(0.7)
        };
        let b = Rigid {
            t: [-1.0, 0.5, 0.25],
            ..yaw(-0.2)
        };
        let p = [0.4, 1.1, 2.5];
        let close = |x: [f64; 3], y: [f64; 3]| (0..3).all(|i| (x[i] - y[i]).abs() < 1e-12);
        assert!(close(a.inverse().apply(a.apply(p)), p));
        assert!(close(a.compose(&a.inverse()).apply(p), p));
        assert!(close(a.compose(&b).apply(p), a.apply(b.apply(p))));
        assert_eq!(Rigid::IDENTITY.compose(&a), a);
        assert_eq!(
            Rigid::translation(1.0, 2.0, 3.0).apply([0.0; 3]),
            [1.0, 2.0, 3.0]
        );
    }
}
