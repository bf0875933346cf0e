//! The teacher: MASt3R-SLAM's keyframe criterion computed exactly from ground-truth depth and
//! poses.
//!
//! The overlap itself (its definition, conventions, working resolution and speed) lives in the
//! plugin crate, [`gstleangate::overlap`], the one implementation that the teacher and the element
//! share; [`DepthView`] and [`PairScore`] are that module's. This module adds what needs ground
//! truth: building views from a [`Sequence`]'s depth images and intrinsics at the working
//! resolution of a [`TeacherConfig`] ([`DepthViewExt::new`]; the step is
//! `max(1, round(W / working_width))`), scoring with camera-to-world `nalgebra` poses
//! ([`score_pair`]), the checks that refuse a sequence whose depth the teacher cannot read, and
//! [`Teacher`], which holds a sequence's views and poses and spreads pairs over rayon's pool.

use std::fmt;
use std::io::Write;

use gstleangate::overlap::{self, Pinhole, Rigid};
use nalgebra::Isometry3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::dataset::{DatasetError, DepthImage, Intrinsics, Sequence};

pub use gstleangate::overlap::{DepthView, PairScore};

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

/// Builds a [`DepthView`] from the tools' depth images (the plugin's [`DepthView::from_full`]
/// at the teacher's step); in scope, `DepthView::new(&depth, &intrinsics, &cfg)`.
pub trait DepthViewExt: Sized {
    /// Subsamples `depth` (full resolution, intrinsics `intr`) to the working resolution of
    /// `cfg`: every `k`-th pixel of every `k`-th row, `k = cfg.step_for_width(depth.width)`.
    fn new(
        depth: &DepthImage,
        intr: &Intrinsics,
        cfg: &TeacherConfig,
    ) -> Result<Self, TeacherError>;
}

impl DepthViewExt for DepthView {
    fn new(
        depth: &DepthImage,
        intr: &Intrinsics,
        cfg: &TeacherConfig,
    ) -> Result<DepthView, TeacherError> {
        let pinhole = Pinhole {
            fx: intr.fx,
            fy: intr.fy,
            cx: intr.cx,
            cy: intr.cy,
        };
        let step = cfg.step_for_width(depth.width);
        DepthView::from_full(&depth.data, depth.width, depth.height, pinhole, step)
            .map_err(|e| TeacherError::BadDepth(e.to_string()))
    }
}

/// `PairScore` through serde: the plugin crate has no serde, so a field of that type is
/// (de)serialized with `#[serde(with = "PairScoreSerde")]` (the same four fields by name).
#[derive(Serialize, Deserialize)]
#[serde(remote = "PairScore")]
pub struct PairScoreSerde {
    /// Fraction of the current frame's valid pixels with a valid match in the keyframe.
    pub f_m: f64,
    /// Fraction of the keyframe's valid pixels hit by at least one valid match.
    pub f_u: f64,
    /// `min(f_m, f_u)`.
    pub s: f64,
    /// `1 - s`.
    pub tau: f64,
}

/// A camera pose (or any rigid transform) in the overlap's plain form.
pub fn rigid(pose: &Isometry3<f64>) -> Rigid {
    let m = pose.rotation.to_rotation_matrix().into_inner();
    let t = pose.translation.vector;
    Rigid {
        r: [0, 1, 2].map(|i| [m[(i, 0)], m[(i, 1)], m[(i, 2)]]),
        t: [t.x, t.y, t.z],
    }
}

/// Scores the pair (current `cur` at `cur_pose`, keyframe `key` at `key_pose`); poses are
/// camera-to-world. The relative pose current → keyframe camera is `key_pose⁻¹ cur_pose`
/// (composed by nalgebra), then [`overlap::score_pair`].
pub fn score_pair(
    cur: &DepthView,
    cur_pose: &Isometry3<f64>,
    key: &DepthView,
    key_pose: &Isometry3<f64>,
    max_dist_m: f64,
) -> PairScore {
    let rel = key_pose.inverse() * cur_pose;
    overlap::score_pair(cur, key, &rigid(&rel), max_dist_m)
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

    fn view(d: &DepthImage) -> DepthView {
        DepthView::new(d, &intr(), &cfg()).unwrap()
    }

    /// A fronto-parallel plane `z` metres ahead of a camera looking along world z.
    fn plane(z: f32) -> DepthImage {
        DepthImage {
            width: W,
            height: H,
            data: vec![z; (W * H) as usize],
        }
    }

    // The overlap itself is tested in the plugin crate (`gstleangate::overlap`); these check the
    // teacher's use of it: poses, views, refusals.

    #[test]
    fn score_pair_is_the_overlap_on_the_relative_pose() {
        let (z, t) = (2.0, 0.3);
        let p0 = Isometry3::identity();
        let p1 = Isometry3::translation(t, 0.0, 0.0);
        let v = view(&plane(z as f32));
        let s = score_pair(&v, &p1, &v, &p0, 0.1);
        let expected = 1.0 - F * t / (z * W as f64);
        assert!(
            (s.s - expected).abs() < 0.02,
            "S={} expected {expected}",
            s.s
        );
        assert_eq!(score_pair(&v, &p0, &v, &p0, 0.1).tau, 0.0);
        // Any common world frame: the same relative pose, the same score.
        let g = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.5),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.4),
        );
        let (q0, q1) = (g * p0, g * p1);
        let rel = rigid(&(q0.inverse() * q1));
        assert_eq!(
            score_pair(&v, &q1, &v, &q0, 0.1),
            overlap::score_pair(&v, &v, &rel, 0.1)
        );
        assert!((score_pair(&v, &q1, &v, &q0, 0.1).s - s.s).abs() < 1e-3);
        let empty = view(&DepthImage::new(W, H));
        assert_eq!(score_pair(&v, &p0, &empty, &p0, 0.1).tau, 1.0);
    }

    #[test]
    fn rigid_is_the_isometry() {
        let iso = Isometry3::from_parts(
            Translation3::new(0.3, -0.1, 2.0),
            UnitQuaternion::from_euler_angles(0.2, -0.7, 1.1),
        );
        let p = nalgebra::Point3::new(0.5, 1.5, -0.25);
        let q = iso * p;
        let r = rigid(&iso).apply([p.x, p.y, p.z]);
        assert!(
            (0..3).all(|i| (r[i] - q[i]).abs() < 1e-12),
            "{r:?} vs {q:?}"
        );
    }

    #[test]
    fn pair_score_serializes_by_field() {
        #[derive(Serialize, Deserialize, PartialEq, Debug)]
        struct Row(#[serde(with = "PairScoreSerde")] PairScore);
        let row = Row(PairScore {
            f_m: 0.5,
            f_u: 0.25,
            s: 0.25,
            tau: 0.75,
        });
        let text = serde_json::to_string(&row).unwrap();
        assert_eq!(text, r#"{"f_m":0.5,"f_u":0.25,"s":0.25,"tau":0.75}"#);
        assert_eq!(serde_json::from_str::<Row>(&text).unwrap(), row);
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
        let err = |d: &DepthImage, k: &Intrinsics| match DepthView::new(d, k, &cfg()) {
            Err(TeacherError::BadDepth(m)) => m,
            other => panic!("{other:?}"),
        };
        assert_eq!(err(&bad, &k), "5 values for 10x10");
        assert_eq!(err(&DepthImage::new(0, 10), &k), "empty image");
        let flat = Intrinsics { fy: 0.0, ..k };
        assert_eq!(err(&d, &flat), "non-positive focal length");
        // A width below the working width is taken whole.
        let small = DepthView::new(&DepthImage::new(100, 80), &k, &cfg()).unwrap();
        assert_eq!((small.width, small.step, small.valid_count), (100, 1, 0));
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
