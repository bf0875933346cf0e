//! The teacher: MASt3R-SLAM's keyframe criterion computed exactly from ground-truth depth and
//! poses.
//!
//! # Definition
//!
//! For a pair (current frame `i`, keyframe `j`), each pixel of `i` with a valid depth is
//! unprojected, moved by the relative pose into `j`'s camera and projected into `j`. The match
//! is *valid* when it lands inside `j` on a pixel with valid depth and the two 3-D points (the
//! transformed point of `i`, and `j`'s own unprojected point at that pixel, both in `j`'s
//! camera frame) are closer than `max_dist_m` (0.1 m by default). Then
//!
//! * `f_m` = valid matches / valid-depth pixels of `i`;
//! * `f_u` = distinct pixels of `j` hit by valid matches / valid-depth pixels of `j`;
//! * `S = min(f_m, f_u)`, `tau = 1 - S` (utility: 0 = nothing new, 1 = all new).
//!
//! If `i` or `j` has no valid depth pixel, `S = 0` (`tau = 1`).
//!
//! # Conventions
//!
//! OpenCV/TUM camera frame (x right, y down, z forward); poses camera-to-world; pixel `(u, v)`
//! at integer coordinates of pixel centres; projection `u = fx X/Z + cx` rounded to the nearest
//! integer; inside when `0 <= u < W`, `0 <= v < H` and `Z > 0`.
//!
//! # Working resolution
//!
//! Depth is subsampled by an integer step `k = max(1, round(W / working_width))`: every `k`-th
//! pixel of every `k`-th row is taken, without averaging (which would create flying points at
//! depth edges). The subsampled intrinsics are exactly `fx/k, fy/k, cx/k, cy/k`, since
//! subsampled pixel `u'` is full-resolution pixel `k u'`.
//!
//! A [`DepthView`] stores the subsampled depth plus per-column and per-row ray factors
//! `(u - cx)/fx`, `(v - cy)/fy`, so a 3-D point is `(xr[u] z, yr[v] z, z)`: the unprojection is
//! precomputed once per view while memory stays at 4 bytes per working pixel (77 KB per frame
//! at 160x120), which matters for sequences of thousands of frames.
//!
//! # Speed
//!
//! [`score_pair`] is one pass over the current view with `f32` arithmetic and a reusable
//! per-thread bitmap for distinct hits (no allocation per pair). On the 7-Scenes clip at 160x120
//! (strongly overlapping pairs, the slow case) it scores about 4,000 pairs/s per core
//! (`cargo test teacher_speed -- --ignored --nocapture`); [`Teacher::score_pairs`] spreads pairs
//! over rayon's pool.

use std::cell::Cell;
use std::fmt;
use std::io::Write;

use nalgebra::Isometry3;
use rayon::prelude::*;

use crate::dataset::{DatasetError, DepthImage, Intrinsics, Sequence};

/// Configuration of the teacher.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TeacherConfig {
    /// Target width of the working resolution (the step is `max(1, round(W / working_width))`).
    pub working_width: u32,
    /// Largest 3-D distance (metres) between a transformed point and the keyframe's point for a
    /// valid match.
    pub max_dist_m: f64,
}

impl Default for TeacherConfig {
    fn default() -> Self {
        TeacherConfig {
            working_width: 160,
            max_dist_m: 0.1,
        }
    }
}

impl TeacherConfig {
    /// Subsampling step for a full-resolution width.
    pub fn step_for_width(&self, width: u32) -> u32 {
        if self.working_width == 0 {
            return 1;
        }
        ((width as f64 / self.working_width as f64).round() as u32).max(1)
    }
}

/// Errors of the teacher.
#[derive(Debug)]
pub enum TeacherError {
    /// Reading the sequence failed.
    Dataset(DatasetError),
    /// The sequence lacks depth, poses or intrinsics.
    NoGroundTruth(String),
    /// A depth image is inconsistent (size mismatch, empty).
    BadDepth(String),
    /// `intrinsics.txt` does not fit the depth images (a principal point off them, a
    /// depth_scale that reads no camera's distances); the message names the file.
    BadIntrinsics(String),
    /// A pair index is out of range.
    IndexOutOfRange {
        /// Requested index.
        index: usize,
        /// Number of frames.
        len: usize,
    },
}

impl fmt::Display for TeacherError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TeacherError::Dataset(e) => write!(f, "{e}"),
            TeacherError::NoGroundTruth(m) => write!(f, "no ground truth: {m}"),
            TeacherError::BadDepth(m) => write!(f, "bad depth image: {m}"),
            TeacherError::BadIntrinsics(m) => write!(f, "bad intrinsics: {m}"),
            TeacherError::IndexOutOfRange { index, len } => {
                write!(f, "frame index {index} out of range ({len} frames)")
            }
        }
    }
}

impl std::error::Error for TeacherError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            TeacherError::Dataset(e) => Some(e),
            _ => None,
        }
    }
}

impl From<DatasetError> for TeacherError {
    fn from(e: DatasetError) -> Self {
        TeacherError::Dataset(e)
    }
}

/// Depth at the working resolution with its intrinsics and precomputed ray factors.
#[derive(Debug, Clone)]
pub struct DepthView {
    /// Working width.
    pub width: u32,
    /// Working height.
    pub height: u32,
    /// Working-resolution intrinsics (`fx/k` etc.; `depth_scale` copied).
    pub intrinsics: Intrinsics,
    /// Subsampling step `k` from the full resolution.
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

impl DepthView {
    /// Subsamples `depth` (full resolution, intrinsics `intr`) to the working resolution.
    pub fn new(
        depth: &DepthImage,
        intr: &Intrinsics,
        cfg: &TeacherConfig,
    ) -> Result<DepthView, TeacherError> {
        let (w, h) = (depth.width as usize, depth.height as usize);
        if depth.data.len() != w * h {
            return Err(TeacherError::BadDepth(format!(
                "{} values for {}x{}",
                depth.data.len(),
                w,
                h
            )));
        }
        if w == 0 || h == 0 {
            return Err(TeacherError::BadDepth("empty image".into()));
        }
        if !(intr.fx > 0.0 && intr.fy > 0.0) {
            return Err(TeacherError::BadDepth("non-positive focal length".into()));
        }
        let k = cfg.step_for_width(depth.width) as usize;
        let (ww, wh) = (w.div_ceil(k), h.div_ceil(k));
        let mut data = Vec::with_capacity(ww * wh);
        for v in 0..wh {
            let row = &depth.data[v * k * w..(v * k + 1) * w];
            data.extend(row.iter().step_by(k).map(
                |&d| {
                    if d.is_finite() && d > 0.0 {
                        d
                    } else {
                        0.0
                    }
                },
            ));
        }
        let kf = k as f64;
        let sub = Intrinsics {
            fx: intr.fx / kf,
            fy: intr.fy / kf,
            cx: intr.cx / kf,
            cy: intr.cy / kf,
            depth_scale: intr.depth_scale,
        };
        Ok(Self::from_parts(ww as u32, wh as u32, sub, k as u32, data))
    }

    /// Builds a view from depth already at working resolution (no subsampling).
    fn from_parts(w: u32, h: u32, intr: Intrinsics, step: u32, depth: Vec<f32>) -> DepthView {
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

/// Teacher score of one pair.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
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

/// Scores the pair (current `cur` at `cur_pose`, keyframe `key` at `key_pose`); poses are
/// camera-to-world. Allocation-free after the first call on a thread.
pub fn score_pair(
    cur: &DepthView,
    cur_pose: &Isometry3<f64>,
    key: &DepthView,
    key_pose: &Isometry3<f64>,
    max_dist_m: f64,
) -> PairScore {
    if cur.valid_count == 0 || key.valid_count == 0 {
        return PairScore::NOTHING_SHARED;
    }
    // current camera -> keyframe camera
    let rel = key_pose.inverse() * cur_pose;
    let r = rel.rotation.to_rotation_matrix();
    let m = r.matrix();
    let rm: [[f32; 3]; 3] = [
        [m[(0, 0)] as f32, m[(0, 1)] as f32, m[(0, 2)] as f32],
        [m[(1, 0)] as f32, m[(1, 1)] as f32, m[(1, 2)] as f32],
        [m[(2, 0)] as f32, m[(2, 1)] as f32, m[(2, 2)] as f32],
    ];
    let t = rel.translation.vector;
    let (tx, ty, tz) = (t.x as f32, t.y as f32, t.z as f32);
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

/// All depth views and poses of a sequence, ready to score any pair.
#[derive(Debug, Clone)]
pub struct Teacher {
    views: Vec<DepthView>,
    poses: Vec<Isometry3<f64>>,
    timestamps: Vec<f64>,
    max_dist_m: f64,
}

/// The median depth (metres) a sequence may have: beyond it `depth_scale` is wrong, not the scene.
pub const MEDIAN_DEPTH_M: (f64, f64) = (0.02, 500.0);

/// What the teacher needs of a sequence's depth: one image size (the intrinsics are of that
/// camera), the principal point on it, and some valid reading somewhere. Each refusal names the
/// file.
fn check_depth(
    seq: &Sequence,
    intr: &Intrinsics,
    loaded: &[((u32, u32), DepthView)],
) -> Result<(), TeacherError> {
    let depth_path = |i: usize| {
        seq.frames[i]
            .depth
            .as_deref()
            .map(|p| p.display().to_string())
            .unwrap_or_default()
    };
    let Some(&((w, h), _)) = loaded.first() else {
        return Ok(());
    };
    if let Some(i) = loaded.iter().position(|(d, _)| *d != (w, h)) {
        let (wi, hi) = loaded[i].0;
        return Err(TeacherError::BadDepth(format!(
            "`{}` (frame {i}) is {wi}x{hi}, the first depth image is {w}x{h}",
            depth_path(i)
        )));
    }
    let (cx, cy) = (intr.cx, intr.cy);
    if !(0.0..=w as f64).contains(&cx) || !(0.0..=h as f64).contains(&cy) {
        return Err(TeacherError::BadIntrinsics(format!(
            "`{}`: the principal point ({cx}, {cy}) lies outside the {w}x{h} depth images",
            seq.root.join("intrinsics.txt").display()
        )));
    }
    // Metres that no camera sequence has: a depth_scale off by orders of magnitude (1 on TUM's
    // 5000 units per metre reads kilometres), which would judge every pair as a break.
    let mut sample: Vec<f32> = loaded
        .iter()
        .step_by(loaded.len().div_ceil(16).max(1))
        .flat_map(|(_, v)| v.depth.iter().copied().filter(|&d| d > 0.0))
        .collect();
    if !sample.is_empty() {
        let mid = sample.len() / 2;
        let median = *sample.select_nth_unstable_by(mid, f32::total_cmp).1 as f64;
        if !(MEDIAN_DEPTH_M.0..=MEDIAN_DEPTH_M.1).contains(&median) {
            return Err(TeacherError::BadIntrinsics(format!(
                "`{}`: with depth_scale {} the median depth is {median:.3e} m, outside the \
                 {}..{} m of any camera sequence; depth_scale is depth units per metre (1000 for \
                 millimetres as in 7-Scenes, 5000 for TUM RGB-D)",
                seq.root.join("intrinsics.txt").display(),
                intr.depth_scale,
                MEDIAN_DEPTH_M.0,
                MEDIAN_DEPTH_M.1
            )));
        }
    }
    if loaded.iter().all(|(_, v)| v.valid_count == 0) {
        return Err(TeacherError::BadDepth(format!(
            "no depth image of `{}` has a valid reading (all 0 or {}), e.g. `{}`",
            seq.root.display(),
            crate::dataset::NO_READING_MAX,
            depth_path(0)
        )));
    }
    Ok(())
}

impl Teacher {
    /// Loads every depth frame of `seq` (in parallel) at the working resolution.
    pub fn from_sequence(seq: &Sequence, cfg: &TeacherConfig) -> Result<Teacher, TeacherError> {
        let intr = seq.intrinsics.ok_or_else(|| {
            TeacherError::NoGroundTruth(format!(
                "`{}` has no intrinsics.txt",
                seq.root.join("intrinsics.txt").display()
            ))
        })?;
        let mut poses = Vec::with_capacity(seq.len());
        for (i, f) in seq.frames.iter().enumerate() {
            if f.depth.is_none() {
                return Err(TeacherError::NoGroundTruth(format!(
                    "frame {i} ({}) of `{}` has no depth",
                    f.rgb.display(),
                    seq.root.display()
                )));
            }
            poses.push(f.pose.ok_or_else(|| {
                TeacherError::NoGroundTruth(format!(
                    "frame {i} ({}) of `{}` has no pose",
                    f.rgb.display(),
                    seq.root.display()
                ))
            })?);
        }
        let loaded = (0..seq.len())
            .into_par_iter()
            .map(|i| {
                let d = seq.load_depth_m(i)?;
                Ok(((d.width, d.height), DepthView::new(&d, &intr, cfg)?))
            })
            .collect::<Result<Vec<_>, TeacherError>>()?;
        check_depth(seq, &intr, &loaded)?;
        let views = loaded.into_iter().map(|(_, v)| v).collect();
        Ok(Teacher {
            views,
            poses,
            timestamps: seq.timestamps(),
            max_dist_m: cfg.max_dist_m,
        })
    }

    /// Builds a teacher from views and camera-to-world poses (timestamps = indices / 30).
    pub fn from_views(
        views: Vec<DepthView>,
        poses: Vec<Isometry3<f64>>,
        max_dist_m: f64,
    ) -> Result<Teacher, TeacherError> {
        if views.len() != poses.len() {
            return Err(TeacherError::NoGroundTruth(format!(
                "{} views but {} poses",
                views.len(),
                poses.len()
            )));
        }
        let timestamps = (0..views.len()).map(|i| i as f64 / 30.0).collect();
        Ok(Teacher {
            views,
            poses,
            timestamps,
            max_dist_m,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.views.len()
    }

    /// Whether there is no frame.
    pub fn is_empty(&self) -> bool {
        self.views.is_empty()
    }

    /// Depth view of frame `i`.
    pub fn view(&self, i: usize) -> Option<&DepthView> {
        self.views.get(i)
    }

    /// Camera-to-world pose of frame `i`.
    pub fn pose(&self, i: usize) -> Option<&Isometry3<f64>> {
        self.poses.get(i)
    }

    /// Timestamps of the frames, seconds.
    pub fn timestamps(&self) -> &[f64] {
        &self.timestamps
    }

    /// Score of current frame `i` against keyframe `j`.
    ///
    /// # Panics
    /// If `i` or `j` is out of range; see [`Teacher::try_score`].
    pub fn score(&self, i: usize, j: usize) -> PairScore {
        score_pair(
            &self.views[i],
            &self.poses[i],
            &self.views[j],
            &self.poses[j],
            self.max_dist_m,
        )
    }

    /// Score of `(i, j)`, or an error when an index is out of range.
    pub fn try_score(&self, i: usize, j: usize) -> Result<PairScore, TeacherError> {
        self.check(&[(i, j)])?;
        Ok(self.score(i, j))
    }

    fn check(&self, pairs: &[(usize, usize)]) -> Result<(), TeacherError> {
        let len = self.len();
        match pairs.iter().flat_map(|&(i, j)| [i, j]).find(|&x| x >= len) {
            Some(index) => Err(TeacherError::IndexOutOfRange { index, len }),
            None => Ok(()),
        }
    }

    /// Scores many `(current, keyframe)` pairs in parallel, in order.
    ///
    /// # Panics
    /// If an index is out of range; see [`Teacher::try_score_pairs`].
    pub fn score_pairs(&self, pairs: &[(usize, usize)]) -> Vec<PairScore> {
        pairs
            .par_iter()
            .with_min_len(16)
            .map(|&(i, j)| self.score(i, j))
            .collect()
    }

    /// As [`Teacher::score_pairs`], with an error instead of a panic on a bad index.
    pub fn try_score_pairs(
        &self,
        pairs: &[(usize, usize)],
    ) -> Result<Vec<PairScore>, TeacherError> {
        self.check(pairs)?;
        Ok(self.score_pairs(pairs))
    }
}

/// Pairs `(i, j)` with `0 < i - j <= max_gap`, i.e. each frame against its `max_gap`
/// predecessors (a typical labelling set).
pub fn pairs_within(n: usize, max_gap: usize) -> Vec<(usize, usize)> {
    (0..n)
        .flat_map(|i| (i.saturating_sub(max_gap)..i).map(move |j| (i, j)))
        .collect()
}

/// Scores `pairs` and writes CSV `i,j,t_i,t_j,f_m,f_u,s,tau` with a header line.
pub fn label_pairs_csv<W: Write>(
    teacher: &Teacher,
    pairs: &[(usize, usize)],
    mut out: W,
) -> Result<(), TeacherError> {
    let scores = teacher.try_score_pairs(pairs)?;
    let ts = teacher.timestamps();
    let io = |e: std::io::Error| {
        TeacherError::Dataset(DatasetError::Io {
            path: "<csv output>".into(),
            source: e,
        })
    };
    writeln!(out, "i,j,t_i,t_j,f_m,f_u,s,tau").map_err(io)?;
    for (&(i, j), sc) in pairs.iter().zip(&scores) {
        writeln!(
            out,
            "{i},{j},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6}",
            ts[i], ts[j], sc.f_m, sc.f_u, sc.s, sc.tau
        )
        .map_err(io)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use std::path::Path;

    const W: u32 = 160;
    const H: u32 = 120;
    const F: f64 = 140.0;

    fn intr() -> Intrinsics {
        Intrinsics {
            fx: F,
            fy: F,
            cx: (W as f64 - 1.0) / 2.0,
            cy: (H as f64 - 1.0) / 2.0,
            depth_scale: 1000.0,
        }
    }

    fn cfg() -> TeacherConfig {
        TeacherConfig::default()
    }

    /// Ray-casts a scene given as a list of axis-aligned boxes (world frame) plus a plane
    /// z = `plane_z` (world), camera at `pose` (camera-to-world).
    fn render(pose: &Isometry3<f64>, plane_z: f64, boxes: &[([f64; 3], [f64; 3])]) -> DepthImage {
        let k = intr();
        let mut d = DepthImage::new(W, H);
        for v in 0..H {
            for u in 0..W {
                let dc = Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
                let dw = pose.rotation * dc;
                let o = pose.translation.vector;
                let mut best = f64::INFINITY;
                if dw.z.abs() > 1e-12 {
                    let t = (plane_z - o.z) / dw.z;
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
                    d.data[(v * W + u) as usize] = best as f32;
                }
            }
        }
        d
    }

    fn view(d: &DepthImage) -> DepthView {
        DepthView::new(d, &intr(), &cfg()).unwrap()
    }

    #[test]
    fn identical_frames_give_tau_zero() {
        let pose = Isometry3::identity();
        let d = render(&pose, 2.0, &[]);
        let v = view(&d);
        let s = score_pair(&v, &pose, &v, &pose, 0.1);
        assert_eq!(s.s, 1.0);
        assert_eq!(s.tau, 0.0);
    }

    #[test]
    fn turned_away_gives_tau_one() {
        let p0 = Isometry3::identity();
        let p1 = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
        );
        let d0 = render(&p0, 2.0, &[]);
        let d1 = render(&p1, -2.0, &[]);
        let s = score_pair(&view(&d1), &p1, &view(&d0), &p0, 0.1);
        assert_eq!(s.tau, 1.0);
        assert_eq!(s.f_m, 0.0);
    }

    #[test]
    fn sideways_translation_matches_overlap_formula() {
        let z = 2.0;
        for &t in &[0.1, 0.3, 0.6] {
            let p0 = Isometry3::identity();
            let p1 = Isometry3::translation(t, 0.0, 0.0);
            let v0 = view(&render(&p0, z, &[]));
            let v1 = view(&render(&p1, z, &[]));
            let s = score_pair(&v1, &p1, &v0, &p0, 0.1);
            let expected = 1.0 - F * t / (z * W as f64);
            assert!(
                (s.s - expected).abs() < 0.02,
                "t={t}: S={} expected {expected}",
                s.s
            );
            assert!((s.f_m - s.f_u).abs() < 0.02);
        }
    }

    #[test]
    fn empty_depth_gives_tau_one() {
        let pose = Isometry3::identity();
        let full = view(&render(&pose, 2.0, &[]));
        let empty = view(&DepthImage::new(W, H));
        assert_eq!(score_pair(&full, &pose, &empty, &pose, 0.1).tau, 1.0);
        assert_eq!(score_pair(&empty, &pose, &full, &pose, 0.1).tau, 1.0);
    }

    #[test]
    fn occluded_points_do_not_match() {
        // Plane at z = 3; a box in front of it. Two views separated sideways: plane pixels
        // visible in i but hidden behind the box in j must fail the 3-D distance test.
        let boxes = [([-0.3, -0.3, 1.3], [0.3, 0.3, 1.7])];
        let p0 = Isometry3::identity();
        let p1 = Isometry3::translation(0.4, 0.0, 0.0);
        let d0 = render(&p0, 3.0, &boxes);
        let d1 = render(&p1, 3.0, &boxes);
        let v0 = view(&d0);
        let v1 = view(&d1);
        let s = score_pair(&v1, &p1, &v0, &p0, 0.1);
        // Reference computed by brute force with an explicit visibility test: a point of i
        // matches if it is within the field of view of j and visible (not behind the box).
        let k = intr();
        let rel = p0.inverse() * p1;
        let (mut ok, mut total, mut occluded) = (0usize, 0usize, 0usize);
        for v in 0..H {
            for u in 0..W {
                let z = d1.data[(v * W + u) as usize] as f64;
                total += 1;
                let pc = Vector3::new(
                    (u as f64 - k.cx) / k.fx * z,
                    (v as f64 - k.cy) / k.fy * z,
                    z,
                );
                let q = rel * nalgebra::Point3::from(pc);
                let uu = (k.fx * q.x / q.z + k.cx).round();
                let vv = (k.fy * q.y / q.z + k.cy).round();
                if uu < 0.0 || vv < 0.0 || uu >= W as f64 || vv >= H as f64 {
                    continue;
                }
                let kz = d0.data[(vv as u32 * W + uu as u32) as usize] as f64;
                if kz < q.z - 0.2 {
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
        let loose = score_pair(&v1, &p1, &v0, &p0, 10.0);
        assert!(loose.f_m > s.f_m + (occluded as f64 / total as f64) * 0.8);
    }

    #[test]
    fn subsampling_step_and_intrinsics() {
        let d = DepthImage {
            width: 640,
            height: 480,
            data: vec![1.0; 640 * 480],
        };
        let k = Intrinsics {
            fx: 585.0,
            fy: 585.0,
            cx: 320.0,
            cy: 240.0,
            depth_scale: 1000.0,
        };
        let v = DepthView::new(&d, &k, &cfg()).unwrap();
        assert_eq!((v.width, v.height, v.step), (160, 120, 4));
        assert_eq!(v.intrinsics.fx, 585.0 / 4.0);
        assert_eq!(v.intrinsics.cx, 80.0);
        let bad = DepthImage {
            width: 10,
            height: 10,
            data: vec![1.0; 5],
        };
        assert!(DepthView::new(&bad, &k, &cfg()).is_err());
    }

    #[test]
    fn pairs_within_lists_predecessors() {
        assert_eq!(pairs_within(3, 5), vec![(1, 0), (2, 0), (2, 1)]);
        assert_eq!(pairs_within(4, 1), vec![(1, 0), (2, 1), (3, 2)]);
    }

    /// Timing helper, not a test: `cargo test teacher_speed -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn teacher_speed() {
        if !Path::new(REDKITCHEN).is_dir() {
            eprintln!("skipping: real data `{REDKITCHEN}` absent");
            return;
        }
        let seq = Sequence::open(Path::new(REDKITCHEN)).unwrap();
        let t0 = std::time::Instant::now();
        let t = Teacher::from_sequence(&seq, &cfg()).unwrap();
        let load = t0.elapsed().as_secs_f64();
        let pairs = pairs_within(t.len(), t.len());
        let t1 = std::time::Instant::now();
        let mut n = 0;
        for _ in 0..5 {
            n += t.score_pairs(&pairs).len();
        }
        let par = n as f64 / t1.elapsed().as_secs_f64();
        let t2 = std::time::Instant::now();
        let mut acc = 0.0;
        for &(i, j) in &pairs {
            acc += t.score(i, j).tau;
        }
        let single = pairs.len() as f64 / t2.elapsed().as_secs_f64();
        let v = t.view(0).unwrap();
        eprintln!(
            "{}x{} views; load {:.2} s for {} frames; {:.0} pairs/s parallel, {:.0} pairs/s one thread (mean tau {:.3})",
            v.width,
            v.height,
            load,
            t.len(),
            par,
            single,
            acc / pairs.len() as f64
        );
    }

    const REDKITCHEN: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/7scenes_redkitchen_dev"
    );

    #[test]
    fn redkitchen_scores() {
        if !Path::new(REDKITCHEN).is_dir() {
            eprintln!("skipping: real data `{REDKITCHEN}` absent");
            return;
        }
        let seq = Sequence::open(Path::new(REDKITCHEN)).unwrap();
        let t = Teacher::from_sequence(&seq, &cfg()).unwrap();
        assert_eq!(t.len(), 60);
        let same = t.score(0, 0);
        assert_eq!(same.tau, 0.0);
        let s = t.score_pairs(&[(1, 0), (59, 0), (0, 59)]);
        assert!(s[1].tau > 0.0 && s[1].tau < 1.0, "{:?}", s[1]);
        assert!(s[1].tau > s[0].tau, "{:?} vs {:?}", s[1], s[0]);
        assert!(t.try_score(0, 60).is_err());
        let mut csv = Vec::new();
        label_pairs_csv(&t, &[(1, 0)], &mut csv).unwrap();
        let text = String::from_utf8(csv).unwrap();
        assert!(text.starts_with("i,j,t_i,t_j,f_m,f_u,s,tau\n1,0,0.033333,0.000000,"));
    }
}
