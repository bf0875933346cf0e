//! Procedural RGB-D sequences: CPU ray casting of indoor-like box rooms with furniture, along
//! human-like camera paths, written in the TUM layout of [`crate::dataset`].
//!
//! # World and camera conventions
//!
//! The world frame is z-up: the room is the box `[0, L] x [0, D] x [0, H]`, floor at `z = 0`.
//! Poses are camera-to-world with the OpenCV/TUM camera frame (x right, y down, z forward), as
//! everywhere in LeanGate. A pixel `(u, v)` (integer coordinates at pixel centres) casts the ray
//! `R (( u - cx)/fx, (v - cy)/fy, 1)` from the camera centre; because that camera-frame direction
//! has `z = 1`, the ray parameter of the first hit *is* the z-depth written to the depth image,
//! so depth and poses are exactly consistent with the teacher's projection model.
//!
//! # Scene
//!
//! [`Scene::new`] draws, from a seed: the room size, per-surface materials (value noise,
//! checker, stripes, bricks, wood, or an image tiled from `--textures`), furniture boxes standing
//! on the floor or fixed to walls, and thin pillars acting as occluders. The camera is confined
//! to a central region of the room that no furniture overlaps, so it is never inside an object.
//! Shading is Lambertian with ceiling point lights plus ambient light (no shadows), times a
//! fine-grain detail texture so that every surface has image features.
//!
//! # Motion
//!
//! [`MotionProfile`] selects the camera path, integrated at 4 sub-steps per frame from smoothed
//! velocity / angular-rate targets (so paths are continuous and human-like): `static` (tremor
//! only), `pan`, `shaky`, `walk`, `rotate`, `bursts` (pauses and bursts), `mixed` (random
//! segments of 1.5 to 4 s of the six before it; the default), and `orbit` (a handheld orbit,
//! aimed at a textured cube 0.6 to 0.9 m away placed for it: a near object before the room's far
//! walls, as in TUM's teddy sequence). Alternatively [`replay`] replays a
//! real camera trajectory (TUM `groundtruth.txt`, NeRF `transforms.json`), placed in the room and
//! resampled to the frame rate (`--motion replay:FILE`).
//!
//! # Sensor
//!
//! By default the colour image is the ideal render plus Gaussian noise (`--noise`), with
//! optional `--blur` and `--lighting`, and depth is exact. [`sensor`] adds opt-in camera effects
//! (`--sensor realistic` or a list): auto-exposure, white-balance drift, motion blur over the
//! exposure time, rolling shutter, vignetting, JPEG, Kinect-like depth noise and depth holes.
//! With none of them on, output is byte-identical to earlier versions.
//!
//! # Modules
//!
//! `noise` (splitmix64, hashes, value noise), `materials` (patterns, texture images), `scene`
//! (room generation and the ray caster), `motion` (profiles and path integration), [`replay`],
//! [`sensor`], `render` (configuration, frames, sequences and `synth.json`).
//!
//! # Speed
//!
//! Per frame, each box's projected screen rectangle is computed once and each image row only
//! tests the boxes whose rectangle covers it; rows are rendered in parallel with rayon. On a
//! 2-core machine a 640x480 frame renders at about 70 frames/s (about 50 frames/s including
//! PNG encoding and writing; `cargo bench -p leangate-tools --bench tools`). `--blur` renders 3
//! sub-frames and costs about 3x; `--sensor blur` renders 1 to 9 depending on the motion, and
//! `--sensor rolling` costs about 2x (depth is rendered separately).
//!
//! Everything is deterministic for a seed: random numbers come from a splitmix64 generator and
//! from counter-based hashes (noise is a function of frame, pixel and channel), so results do not
//! depend on thread scheduling.

mod materials;
mod motion;
mod noise;
mod render;
pub mod replay;
mod scene;
pub mod sensor;
#[cfg(test)]
mod tests;

pub use materials::load_textures;
pub use motion::{camera_path, pose_from_angles, MotionProfile, Segment};
pub use noise::SplitMix64;
pub use render::{
    render_sequence, try_camera_path, SynthConfig, SynthSummary, HEADER_PREFIX, MAX_FRAMES,
    MAX_SIDE,
};
pub use replay::{MotionSpec, Replay, ReplayEnd, Trajectory};
pub use scene::{Lighting, Scene};
pub use sensor::SensorConfig;

use crate::dataset::DatasetError;

/// Errors of the synthetic generator.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// Writing the sequence (or reading textures or a trajectory) failed.
    #[error("{0}")]
    Dataset(#[from] DatasetError),
    /// Bad configuration.
    #[error("synth configuration: {0}")]
    Config(String),
}
