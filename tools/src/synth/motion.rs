//! Camera paths: motion profiles integrated from smoothed velocity targets.

use std::f64::consts::PI;
use std::fmt;
use std::str::FromStr;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use super::noise::{mix64, noise1, SplitMix64};
use super::{Scene, SynthConfig};

/// Camera path style.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum MotionProfile {
    /// Handheld but still: sub-millimetre tremor only.
    Static,
    /// Slow pan (about 18 deg/s).
    Pan,
    /// Fast shaky handheld motion.
    Shaky,
    /// Walking forward (about 1 m/s) with head bob.
    Walk,
    /// Pure rotation about the camera centre (about 40 deg/s, with tilt).
    Rotate,
    /// Pauses (1.2 s) and fast bursts (0.8 s).
    Bursts,
    /// Random segments of 1.5 to 4 s of all the others but `orbit`.
    #[default]
    Mixed,
    /// Handheld orbit (15 to 30 deg/s) around a textured object 0.6 to 0.9 m away, aimed at it:
    /// a near object before the room's far walls, the parallax a homography cannot follow.
    Orbit,
}

impl MotionProfile {
    /// All profiles; `mixed` draws its segments from the first six.
    pub const ALL: [MotionProfile; 8] = [
        MotionProfile::Static,
        MotionProfile::Pan,
        MotionProfile::Shaky,
        MotionProfile::Walk,
        MotionProfile::Rotate,
        MotionProfile::Bursts,
        MotionProfile::Mixed,
        MotionProfile::Orbit,
    ];

    /// Lower-case name, as accepted by [`FromStr`].
    pub fn name(self) -> &'static str {
        match self {
            MotionProfile::Static => "static",
            MotionProfile::Pan => "pan",
            MotionProfile::Shaky => "shaky",
            MotionProfile::Walk => "walk",
            MotionProfile::Rotate => "rotate",
            MotionProfile::Bursts => "bursts",
            MotionProfile::Mixed => "mixed",
            MotionProfile::Orbit => "orbit",
        }
    }
}

impl fmt::Display for MotionProfile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for MotionProfile {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        MotionProfile::ALL
            .iter()
            .copied()
            .find(|p| p.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                format!(
                    "unknown motion `{s}` (expected one of: static, pan, shaky, walk, rotate, bursts, mixed, orbit)"
                )
            })
    }
}

/// A motion segment of a generated path: `profile` from frame `start` on.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Segment {
    /// First frame of the segment.
    pub start: usize,
    /// Its profile (never `Mixed`).
    pub profile: MotionProfile,
}

pub(crate) const SUBSTEPS: usize = 4;

/// Camera-to-world pose from position and yaw (about world z, 0 = looking along +x), pitch
/// (positive = up) and roll (about the optical axis).
pub fn pose_from_angles(pos: Vector3<f64>, yaw: f64, pitch: f64, roll: f64) -> Isometry3<f64> {
    let f = Vector3::new(
        pitch.cos() * yaw.cos(),
        pitch.cos() * yaw.sin(),
        pitch.sin(),
    );
    let right = Vector3::new(yaw.sin(), -yaw.cos(), 0.0);
    let down = f.cross(&right);
    let base = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[right, down, f]));
    let r = base * Rotation3::from_axis_angle(&Vector3::z_axis(), roll);
    Isometry3::from_parts(
        Translation3::from(pos),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

fn wrap_angle(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

/// The object an `orbit` path circles: its centre and half size (metres), and the orbit's
/// radius about its vertical axis. Inside the camera region, which furniture keeps clear of.
pub(crate) fn orbit_target(scene: &Scene, seed: u64) -> (Vector3<f64>, f64, f64) {
    let mut rng = SplitMix64::new(seed ^ 0x0B17_0B17);
    let (rlo, rhi) = scene.camera_region;
    // the path breathes to 1.1 radii and stays in the region (at least 1.6 m wide: radius >= 0.72)
    let half_span = 0.5 * (rhi[0] - rlo[0]).min(rhi[1] - rlo[1]);
    let radius = rng.range(0.6, 0.9).min(half_span / 1.1 - 0.01);
    let centre = Vector3::new(
        rng.range(rlo[0] + 1.1 * radius, rhi[0] - 1.1 * radius),
        rng.range(rlo[1] + 1.1 * radius, rhi[1] - 1.1 * radius),
        rng.range(0.85, 1.1),
    );
    (centre, rng.range(0.12, 0.25), radius)
}

/// An `orbit` path: the camera circles [`orbit_target`] at its radius (breathing by +-10 %), at
/// 15 to 30 deg/s that wanders with time, 0.35 to 0.6 m above the object's centre, aimed at it
/// with a few degrees of handheld error, and turns back now and then (every 3 to 6 s).
fn orbit_path(scene: &Scene, fps: f64, frames: usize, seed: u64) -> Vec<Isometry3<f64>> {
    let (c, _, radius) = orbit_target(scene, seed);
    let mut rng = SplitMix64::new(seed ^ 0x0B17_5EED);
    let dt = 1.0 / (fps * SUBSTEPS as f64);
    let deg = PI / 180.0;
    let s = rng.next_u64();
    let rate = rng.range(15.0, 30.0) * deg;
    let lift = rng.range(0.35, 0.6);
    let mut theta = rng.range(-PI, PI);
    let mut dir = if rng.f64() < 0.5 { 1.0 } else { -1.0 };
    let mut turn_at = rng.range(3.0, 6.0);
    let mut speed = 0.0f64;
    (0..frames * SUBSTEPS + SUBSTEPS)
        .map(|k| {
            let t = k as f64 * dt;
            let n = |c: u64, f: f64| noise1(t * f, s ^ c.wrapping_mul(0x1234_5678_9ABC));
            if t >= turn_at {
                dir = -dir;
                turn_at += rng.range(3.0, 6.0);
            }
            let target = dir * rate * (1.0 + 0.4 * n(1, 0.3));
            speed += (target - speed) * (1.0 - (-dt / 0.4f64).exp());
            theta += speed * dt;
            let r = radius * (1.0 + 0.1 * n(2, 0.2));
            let pos = c
                + Vector3::new(r * theta.cos(), r * theta.sin(), lift + 0.05 * n(3, 0.3))
                + Vector3::new(n(20, 3.0), n(21, 3.1), n(22, 2.9)) * 0.0008;
            let to = c - pos;
            let aim = 3.0 * deg;
            let yaw = to.y.atan2(to.x) + aim * n(4, 0.5);
            let pitch = to.z.atan2(to.xy().norm()) + aim * n(5, 0.5);
            pose_from_angles(pos, yaw, pitch, 2.0 * deg * n(6, 0.3))
        })
        .collect()
}

/// Generates `n_samples` camera poses at `SUBSTEPS` samples per frame (frame `i` is sample
/// `SUBSTEPS * i`), plus the motion segments.
pub(crate) fn generate_path(
    scene: &Scene,
    profile: MotionProfile,
    fps: f64,
    frames: usize,
    seed: u64,
) -> (Vec<Isometry3<f64>>, Vec<Segment>) {
    if profile == MotionProfile::Orbit {
        let segments = vec![Segment { start: 0, profile }];
        return (orbit_path(scene, fps, frames, seed), segments);
    }
    let mut rng = SplitMix64::new(seed ^ 0xCA3E_8A7A);
    let dt = 1.0 / (fps * SUBSTEPS as f64);
    let n_samples = frames * SUBSTEPS + SUBSTEPS;
    let (rlo, rhi) = scene.camera_region;
    let centre = Vector3::new(
        (rlo[0] + rhi[0]) / 2.0,
        (rlo[1] + rhi[1]) / 2.0,
        (rlo[2] + rhi[2]) / 2.0,
    );
    // Segments (in frames).
    let mut segments = Vec::new();
    if profile == MotionProfile::Mixed {
        let mut start = 0usize;
        let mut last = None;
        while start < frames.max(1) {
            let mut p;
            loop {
                p = MotionProfile::ALL[rng.below(6)];
                if Some(p) != last {
                    break;
                }
            }
            last = Some(p);
            segments.push(Segment { start, profile: p });
            start += (rng.range(1.5, 4.0) * fps).round().max(1.0) as usize;
        }
    } else {
        segments.push(Segment { start: 0, profile });
    }
    let mut pos = Vector3::new(
        rng.range(rlo[0], rhi[0]),
        rng.range(rlo[1], rhi[1]),
        rng.range(1.3, 1.6),
    );
    let base_z = pos.z;
    let mut yaw = rng.range(-PI, PI);
    let (mut pitch, mut roll) = (rng.range(-0.15, 0.05), 0.0f64);
    let base_pitch = pitch;
    let (mut v_f, mut v_l, mut v_z, mut yaw_rate) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let mut dir = if rng.f64() < 0.5 { 1.0 } else { -1.0 };
    let s = rng.next_u64();
    let deg = PI / 180.0;
    let mut seg_idx = 0usize;
    let mut poses = Vec::with_capacity(n_samples);
    for k in 0..n_samples {
        let t = k as f64 * dt;
        let frame = k / SUBSTEPS;
        while seg_idx + 1 < segments.len() && segments[seg_idx + 1].start <= frame {
            seg_idx += 1;
            if rng.f64() < 0.5 {
                dir = -dir;
            }
        }
        let seg = segments[seg_idx];
        let tau = t - seg.start as f64 / fps;
        let n = |c: u64, f: f64| noise1(t * f, s ^ c.wrapping_mul(0x1234_5678_9ABC));
        // targets: forward, lateral, vertical speed, yaw rate, pitch, roll, smoothing time
        let (mut tf, mut tl, mut tz, mut tyr, tp, tr, tc) = match seg.profile {
            MotionProfile::Static | MotionProfile::Mixed | MotionProfile::Orbit => {
                (0.0, 0.0, 0.0, 0.0, base_pitch, 0.0, 0.3)
            }
            MotionProfile::Pan => (
                0.0,
                0.0,
                0.0,
                dir * 18.0 * deg * (1.0 + 0.3 * n(1, 0.5)),
                base_pitch + 3.0 * deg * n(2, 0.2),
                1.0 * deg * n(3, 0.3),
                0.3,
            ),
            MotionProfile::Shaky => (
                0.4 * n(4, 1.5),
                0.4 * n(5, 1.7),
                0.2 * n(6, 2.0),
                110.0 * deg * n(7, 2.5),
                base_pitch + 10.0 * deg * n(8, 2.0),
                6.0 * deg * n(9, 2.2),
                0.06,
            ),
            MotionProfile::Walk => (
                1.0 + 0.1 * n(10, 0.5),
                0.05 * n(11, 0.7),
                0.0,
                15.0 * deg * n(12, 0.3),
                base_pitch - 4.0 * deg + 2.0 * deg * n(13, 0.4),
                1.5 * deg * (PI * 1.8 * t).sin(),
                0.25,
            ),
            MotionProfile::Rotate => (
                0.0,
                0.0,
                0.0,
                dir * 40.0 * deg * (1.0 + 0.3 * n(14, 0.4)),
                base_pitch + 15.0 * deg * n(15, 0.3),
                2.0 * deg * n(16, 0.3),
                0.25,
            ),
            MotionProfile::Bursts => {
                let period = 2.0;
                let cycle = (tau / period).floor();
                let ph = tau - cycle * period;
                let bdir = if mix64(s ^ cycle as u64) & 1 == 0 {
                    1.0
                } else {
                    -1.0
                };
                let bump = if ph > 1.2 {
                    (PI * (ph - 1.2) / 0.8).sin().powi(2)
                } else {
                    0.0
                };
                (
                    0.6 * bump,
                    0.0,
                    0.0,
                    bdir * 110.0 * deg * bump,
                    base_pitch + 5.0 * deg * bump * n(17, 1.0),
                    0.0,
                    0.08,
                )
            }
        };
        // Steer back toward the centre of the camera region when close to its border.
        let to_c = centre - pos;
        let d_edge = (pos.x - rlo[0])
            .min(rhi[0] - pos.x)
            .min(pos.y - rlo[1])
            .min(rhi[1] - pos.y);
        if tf.abs() + tl.abs() > 0.05 && d_edge < 0.6 {
            let want = to_c.y.atan2(to_c.x);
            let w = ((0.6 - d_edge) / 0.6).clamp(0.0, 1.0);
            tyr += w * 3.0 * wrap_angle(want - yaw);
            tf *= 1.0 - 0.7 * w;
            tl *= 1.0 - w;
        }
        tz += -0.8 * (pos.z - base_z);
        let a = 1.0 - (-dt / tc).exp();
        v_f += (tf - v_f) * a;
        v_l += (tl - v_l) * a;
        v_z += (tz - v_z) * a;
        yaw_rate += (tyr - yaw_rate) * a;
        pitch += (tp - pitch) * a;
        roll += (tr - roll) * a;
        yaw = wrap_angle(yaw + yaw_rate * dt);
        let fwd = Vector3::new(yaw.cos(), yaw.sin(), 0.0);
        let right = Vector3::new(yaw.sin(), -yaw.cos(), 0.0);
        pos += (fwd * v_f + right * v_l + Vector3::z() * v_z) * dt;
        for a in 0..3 {
            pos[a] = pos[a].clamp(rlo[a], rhi[a]);
        }
        // Output-only tremor and head bob (not integrated).
        let mut out = pos;
        let tremor = 0.0008;
        out += Vector3::new(n(20, 3.0), n(21, 3.1), n(22, 2.9)) * tremor;
        if seg.profile == MotionProfile::Walk {
            out.z += 0.025 * (2.0 * PI * 1.8 * t).sin();
        }
        let tp_tremor = 0.03 * deg * n(23, 4.0);
        poses.push(pose_from_angles(out, yaw, pitch + tp_tremor, roll));
    }
    (poses, segments)
}

pub(crate) fn interpolate(a: &Isometry3<f64>, b: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    let t = a.translation.vector.lerp(&b.translation.vector, s);
    let r = a.rotation.slerp(&b.rotation, s);
    Isometry3::from_parts(Translation3::from(t), r)
}

/// The generated camera path of a configuration's motion profile (camera-to-world per frame)
/// and its segments, without rendering. It ignores `cfg.replay`: use
/// [`super::try_camera_path`] for a path that may be replayed.
pub fn camera_path(cfg: &SynthConfig, scene: &Scene) -> (Vec<Isometry3<f64>>, Vec<Segment>) {
    let (samples, segs) = generate_path(scene, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
    (
        samples
            .iter()
            .step_by(SUBSTEPS)
            .take(cfg.frames)
            .copied()
            .collect(),
        segs,
    )
}
