//! Replayed camera paths: a real trajectory (TUM `groundtruth.txt`, 7-Scenes, or a NeRF/COLMAP
//! `transforms.json`) moved into the synthetic room and resampled to the sequence's frame rate.
//!
//! # Reading
//!
//! - A text file is a TUM trajectory (`t tx ty tz qx qy qz qw`, camera-to-world, OpenCV camera
//!   axes: x right, y down, z forward), read by [`crate::dataset::read_trajectory`]. Its units are
//!   metres ([`Trajectory::metric`]).
//! - A `.json` file is a NeRF `transforms.json` (instant-ngp, nerfstudio; e.g. fox_orbit's COLMAP
//!   poses): `frames[].transform_matrix` is a 4x4 camera-to-world matrix in the OpenGL/NeRF camera
//!   convention (x right, y up, z backward), converted to the renderer's camera axes by
//!   `R_cv = R_gl diag(1, -1, -1)` (the camera centre is unchanged). Frames are ordered by
//!   `file_path` (natural video order). They carry no timestamps, so consecutive frames are spaced
//!   by `median rotation between consecutive frames / 30 deg/s` (a typical handheld turn rate;
//!   0.5 s when the camera does not rotate). The scale of such poses is arbitrary
//!   (`metric = false`).
//!
//! # Placing the trajectory in the room
//!
//! World frames of real datasets have arbitrary orientation, so the trajectory is moved by a
//! similarity `p' = s A (p - c) + m` (rotation `A`, scale `s`) applied to every pose:
//! 1. **up**: `A` maps the mean of the cameras' "down" axes (the image y axis; handheld cameras
//!    are level on average, and an orbit's tilts cancel) to the room's -z;
//! 2. **heading**: then turns about z so that the principal horizontal axis of the camera centres
//!    lies along the longer side of the room's camera region;
//! 3. **centre**: the bounding-box centre `c` of the camera centres goes to the centre `m` of the
//!    camera region (height: its middle, 1.45 m or so);
//! 4. **scale**: metric trajectories keep `s = 1` — *relative motion is preserved exactly* — when
//!    their bounding box fits the free space (the camera region grown by 0.4 m horizontally, which
//!    no furniture enters, and 0.3 m below the ceiling / above the floor); a larger one is shrunk
//!    uniformly to fit (relative rotations stay exact, relative translations scale by `s`;
//!    `synth.json` records `s`). Non-metric trajectories (transforms.json) are scaled so that
//!    their bounding box fills 80 % of the camera region (the tightest axis decides).
//!
//! # Resampling and the end of the file
//!
//! The path is sampled at `SUBSTEPS` samples per output frame at times `t0 + start + k / (fps *
//! SUBSTEPS)` (`t0` the first timestamp, `start` = `--replay-start`): translation is interpolated
//! linearly and rotation by slerp between the bracketing poses. When `--frames` asks for more than
//! the file holds, [`ReplayEnd`] decides: `stop` (default) writes only the frames the file
//! covers; `loop` starts over (the pose jumps back at the seam); `bounce` plays it backwards
//! and forwards again (continuous, velocity reverses).

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, UnitVector3, Vector3};

use super::motion::{interpolate, MotionProfile, SUBSTEPS};
use super::{Scene, SynthError};
use crate::dataset::{self, DatasetError};

/// Turn rate used to space the frames of a timestamp-less `transforms.json` (degrees per second).
pub const UNTIMED_TURN_RATE_DEG_S: f64 = 30.0;

/// What happens when `--frames` asks for more than the replayed file covers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ReplayEnd {
    /// Write only the frames the trajectory covers (the sequence is shorter than `--frames`).
    #[default]
    Stop,
    /// Start over from the beginning (the pose jumps at the seam).
    Loop,
    /// Play backwards, then forwards again (continuous; the velocity reverses).
    Bounce,
}

impl FromStr for ReplayEnd {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "stop" => Ok(ReplayEnd::Stop),
            "loop" => Ok(ReplayEnd::Loop),
            "bounce" => Ok(ReplayEnd::Bounce),
            _ => Err(format!(
                "unknown replay end `{s}` (expected stop, loop or bounce)"
            )),
        }
    }
}

impl fmt::Display for ReplayEnd {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ReplayEnd::Stop => "stop",
            ReplayEnd::Loop => "loop",
            ReplayEnd::Bounce => "bounce",
        })
    }
}

/// The `--motion` argument: a profile name or `replay:FILE`.
#[derive(Debug, Clone, PartialEq)]
pub enum MotionSpec {
    /// A generated path.
    Profile(MotionProfile),
    /// A trajectory file to replay.
    Replay(PathBuf),
}

impl FromStr for MotionSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().strip_prefix("replay:") {
            Some(file) if !file.is_empty() => Ok(MotionSpec::Replay(PathBuf::from(file))),
            Some(_) => Err("`replay:` needs a file: replay:FILE".into()),
            None => s.parse::<MotionProfile>().map(MotionSpec::Profile).map_err(|_| {
                format!(
                    "unknown motion `{s}` (expected static, pan, shaky, walk, rotate, bursts, mixed, orbit or replay:FILE)"
                )
            }),
        }
    }
}

/// A replayed camera path: which file, from where, and what happens at its end.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Replay {
    /// TUM trajectory (`t tx ty tz qx qy qz qw`) or NeRF `transforms.json`.
    pub path: PathBuf,
    /// Seconds into the file at which the sequence starts (default 0).
    pub start: f64,
    /// Behaviour past the end of the file.
    pub end: ReplayEnd,
}

/// A camera trajectory as read from a file, before placing it in a room.
#[derive(Debug, Clone)]
pub struct Trajectory {
    /// `(time in seconds, camera-to-world pose with OpenCV camera axes)`, sorted by time.
    pub poses: Vec<(f64, Isometry3<f64>)>,
    /// Whether the units are metres (TUM) rather than arbitrary (NeRF/COLMAP).
    pub metric: bool,
}

impl Trajectory {
    /// Reads a TUM trajectory or, for a `.json` file, a NeRF `transforms.json`.
    pub fn read(path: &Path) -> Result<Trajectory, DatasetError> {
        let is_json = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("json"));
        let t = if is_json {
            read_transforms_json(path)?
        } else {
            Trajectory {
                poses: dataset::read_trajectory(path)?,
                metric: true,
            }
        };
        if t.poses.len() < 2 {
            return Err(DatasetError::Invalid {
                path: path.to_path_buf(),
                message: format!(
                    "a replayed trajectory needs 2 poses or more, got {}",
                    t.poses.len()
                ),
            });
        }
        Ok(t)
    }

    /// Duration in seconds.
    pub fn duration(&self) -> f64 {
        self.poses.last().map_or(0.0, |p| p.0) - self.poses.first().map_or(0.0, |p| p.0)
    }

    /// The pose at time `t` (seconds, clamped to the file's span): lerp / slerp between the
    /// bracketing poses.
    pub fn pose_at(&self, t: f64) -> Isometry3<f64> {
        let p = &self.poses;
        if t <= p[0].0 {
            return p[0].1;
        }
        let last = p.len() - 1;
        if t >= p[last].0 {
            return p[last].1;
        }
        // first index with time > t (>= 1 here)
        let k = p.partition_point(|q| q.0 <= t);
        let (t0, a) = p[k - 1];
        let (t1, b) = p[k];
        let span = t1 - t0;
        if span <= 0.0 {
            return b;
        }
        interpolate(&a, &b, (t - t0) / span)
    }
}

/// OpenGL/NeRF camera axes (x right, y up, z backward) to OpenCV (x right, y down, z forward).
pub fn opengl_to_opencv(pose: &Isometry3<f64>) -> Isometry3<f64> {
    let flip = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    Isometry3::from_parts(pose.translation, pose.rotation * flip)
}

fn read_transforms_json(path: &Path) -> Result<Trajectory, DatasetError> {
    let bad = |message: String| DatasetError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| bad(format!("not JSON: {e}")))?;
    let frames = json
        .get("frames")
        .and_then(|f| f.as_array())
        .ok_or_else(|| bad("no `frames` array".into()))?;
    let mut named = Vec::with_capacity(frames.len());
    for (k, f) in frames.iter().enumerate() {
        let name = f
            .get("file_path")
            .and_then(|n| n.as_str())
            .unwrap_or_default()
            .to_string();
        let rows = f
            .get("transform_matrix")
            .and_then(|m| m.as_array())
            .filter(|m| m.len() >= 3)
            .ok_or_else(|| bad(format!("frame {k}: no 4x4 `transform_matrix`")))?;
        let mut m = [[0.0f64; 4]; 3];
        for (r, row) in rows.iter().take(3).enumerate() {
            let row = row.as_array().filter(|row| row.len() == 4).ok_or_else(|| {
                bad(format!(
                    "frame {k}: row {r} of `transform_matrix` is not 4 numbers"
                ))
            })?;
            for (c, v) in row.iter().enumerate() {
                m[r][c] = v
                    .as_f64()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| bad(format!("frame {k}: non-numeric matrix entry")))?;
            }
        }
        let rot = Matrix3::new(
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        );
        // Nearest rotation (the matrices may carry scale or round-off): U V^T of the SVD.
        let svd = rot.svd(true, true);
        let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
            return Err(bad(format!("frame {k}: degenerate rotation")));
        };
        let r = u * v_t;
        if r.determinant() < 0.0 {
            return Err(bad(format!(
                "frame {k}: `transform_matrix` is a reflection"
            )));
        }
        let rot = Rotation3::from_matrix_unchecked(r);
        let gl = Isometry3::from_parts(
            Translation3::new(m[0][3], m[1][3], m[2][3]),
            UnitQuaternion::from_rotation_matrix(&rot),
        );
        named.push((name, opengl_to_opencv(&gl)));
    }
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let mut steps: Vec<f64> = named
        .windows(2)
        .map(|w| w[0].1.rotation.angle_to(&w[1].1.rotation))
        .collect();
    steps.sort_by(|a, b| a.total_cmp(b));
    let median = steps.get(steps.len() / 2).copied().unwrap_or(0.0);
    let dt = if median > 1e-6 {
        median / UNTIMED_TURN_RATE_DEG_S.to_radians()
    } else {
        0.5
    };
    Ok(Trajectory {
        poses: named
            .into_iter()
            .enumerate()
            .map(|(k, (_, p))| (k as f64 * dt, p))
            .collect(),
        metric: false,
    })
}

/// How a trajectory was placed in the room (written to `synth.json`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Placement {
    /// Uniform scale `s` (1 for a metric trajectory that fits: relative motion exact).
    pub scale: f64,
    /// Whether the file's units are metres.
    pub metric: bool,
    /// Rotation from the file's world frame to the room, as a quaternion `[x, y, z, w]`.
    pub rotation: [f64; 4],
    /// Camera-centre bounding box of the file's trajectory (file units): `[min, max]`.
    pub source_bbox: [[f64; 3]; 2],
    /// Duration of the file in seconds.
    pub duration: f64,
    /// Seconds of the file the rendered frames span (after `start` and the end rule).
    pub start: f64,
    /// End rule.
    pub end: ReplayEnd,
    /// Frames the sequence has (fewer than requested with `stop` on a short file).
    pub frames: usize,
}

/// A similarity `p' = s a (p - c_src) + m` from a file's world to the room.
struct Similarity {
    a: UnitQuaternion<f64>,
    s: f64,
    c_src: Vector3<f64>,
    m: Vector3<f64>,
    /// Camera-centre bounding box in the file's frame.
    source_bbox: [[f64; 3]; 2],
}

/// The similarity that places trajectory `traj` in `scene` (see the module documentation).
fn placement(traj: &Trajectory, scene: &Scene) -> Similarity {
    // 1. up: mean camera "down" axis -> -z
    let mut down = Vector3::zeros();
    for (_, p) in &traj.poses {
        down += p.rotation * Vector3::y();
    }
    if down.norm() < 1e-6 * traj.poses.len() as f64 {
        down = traj.poses[0].1.rotation * Vector3::y();
    }
    let up_fix = UnitQuaternion::rotation_between(&down, &(-Vector3::z())).unwrap_or_else(|| {
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    });
    // 2. heading: principal horizontal axis of the centres -> longer side of the camera region
    let centres: Vec<Vector3<f64>> = traj
        .poses
        .iter()
        .map(|(_, p)| up_fix * p.translation.vector)
        .collect();
    let n = centres.len() as f64;
    let mean = centres.iter().fold(Vector3::zeros(), |a, c| a + c) / n;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for c in &centres {
        let d = c - mean;
        sxx += d.x * d.x;
        sxy += d.x * d.y;
        syy += d.y * d.y;
    }
    let principal = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let (rlo, rhi) = scene.camera_region;
    let target = if rhi[0] - rlo[0] >= rhi[1] - rlo[1] {
        0.0
    } else {
        std::f64::consts::FRAC_PI_2
    };
    let z = UnitVector3::new_normalize(Vector3::z());
    let a = UnitQuaternion::from_axis_angle(&z, target - principal) * up_fix;
    // 3. bounding boxes
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    let (mut slo, mut shi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for (_, p) in &traj.poses {
        let q = a * p.translation.vector;
        lo = lo.inf(&q);
        hi = hi.sup(&q);
        for k in 0..3 {
            slo[k] = slo[k].min(p.translation.vector[k]);
            shi[k] = shi[k].max(p.translation.vector[k]);
        }
    }
    let c = (lo + hi) / 2.0;
    let ext = hi - lo;
    let m = Vector3::new(
        (rlo[0] + rhi[0]) / 2.0,
        (rlo[1] + rhi[1]) / 2.0,
        (rlo[2] + rhi[2]) / 2.0,
    );
    // 4. scale
    let s = if traj.metric {
        let room_h = scene.room[2];
        let free = [
            rhi[0] - rlo[0] + 0.8,
            rhi[1] - rlo[1] + 0.8,
            // from 0.3 m above the floor to 0.3 m below the ceiling, centred on m.z
            2.0 * (m.z - 0.3).min(room_h - 0.3 - m.z),
        ];
        (0..3)
            .map(|k| {
                if ext[k] > 1e-9 {
                    free[k] / ext[k]
                } else {
                    f64::INFINITY
                }
            })
            .fold(1.0f64, f64::min)
    } else {
        let region = [rhi[0] - rlo[0], rhi[1] - rlo[1], rhi[2] - rlo[2]];
        let fit = (0..3)
            .map(|k| {
                if ext[k] > 1e-9 {
                    0.8 * region[k] / ext[k]
                } else {
                    f64::INFINITY
                }
            })
            .fold(f64::INFINITY, f64::min);
        if fit.is_finite() {
            fit
        } else {
            1.0
        }
    };
    // a * (p - c_src) with c = a * c_src
    let c_src = a.inverse() * c;
    Similarity {
        a,
        s,
        c_src,
        m,
        source_bbox: [slo, shi],
    }
}

/// Samples of a replayed path: `frames * SUBSTEPS + SUBSTEPS` poses (frame `i` is sample
/// `SUBSTEPS * i`) in the room, and the placement. `frames` may be lowered by [`ReplayEnd::Stop`].
pub(crate) fn replay_path(
    replay: &Replay,
    scene: &Scene,
    fps: f64,
    frames: usize,
) -> Result<(Vec<Isometry3<f64>>, Placement), SynthError> {
    let traj = Trajectory::read(&replay.path)?;
    let duration = traj.duration();
    if !(replay.start.is_finite() && replay.start >= 0.0 && replay.start < duration) {
        return Err(SynthError::Config(format!(
            "replay start {} s is outside the trajectory ({duration:.3} s long)",
            replay.start
        )));
    }
    let avail = duration - replay.start;
    let frames = match replay.end {
        // frames whose time is within the file (1e-9 s tolerance on the timestamps' rounding)
        ReplayEnd::Stop => frames.min((avail * fps + 1e-6).floor() as usize + 1),
        _ => frames,
    };
    let Similarity {
        a,
        s,
        c_src,
        m,
        source_bbox,
    } = placement(&traj, scene);
    let t0 = traj.poses[0].0;
    let period = avail;
    let n = frames * SUBSTEPS + SUBSTEPS;
    let samples = (0..n)
        .map(|k| {
            let tau = k as f64 / (fps * SUBSTEPS as f64);
            let tau = match replay.end {
                ReplayEnd::Stop => tau.min(period),
                ReplayEnd::Loop => tau.rem_euclid(period),
                ReplayEnd::Bounce => {
                    let x = tau.rem_euclid(2.0 * period);
                    if x > period {
                        2.0 * period - x
                    } else {
                        x
                    }
                }
            };
            let p = traj.pose_at(t0 + replay.start + tau);
            let pos = a * (p.translation.vector - c_src) * s + m;
            Isometry3::from_parts(Translation3::from(pos), a * p.rotation)
        })
        .collect();
    let q = a.quaternion();
    Ok((
        samples,
        Placement {
            scale: s,
            metric: traj.metric,
            rotation: [q.i, q.j, q.k, q.w],
            source_bbox,
            duration,
            start: replay.start,
            end: replay.end,
            frames,
        },
    ))
}
