//! Opt-in sensor realism: what a real RGB-D camera does to the ideal render.
//!
//! All effects are off by default (the default output is unchanged, byte for byte). Each is
//! switched on by name (`--sensor exposure,wb,...`, or `--sensor realistic` for all of them) and
//! its strength is drawn once per sequence from the seed (ranges below), so a set of sequences
//! covers a range of cameras while each sequence is deterministic.
//!
//! | name | effect |
//! |---|---|
//! | `exposure` | auto-exposure: the camera meters each frame's mean linear luminance (a 1/8-resolution render) and moves its log gain toward `target / mean` (target 0.24: mean display level about 0.47) with a time constant of 0.15-0.6 s and one frame of delay; the target itself drifts by about +-10 % (slow noise). The gain is split into exposure time (up to 0.9 / fps) and analog gain, which multiplies the colour noise by its square root. |
//! | `wb` | white-balance drift: red and blue gains wander slowly (0.1 Hz noise) by 3-8 %. |
//! | `blur` | motion blur from the actual motion during the exposure: the exposure time (`t_ref * gain`, `t_ref` 4-14 ms, at most 0.9 / fps) is covered by `n` evenly spaced sub-frame renders along the pose interpolation, averaged: `n = 1` below 1 px of image motion during the exposure, else `2 ceil(motion / 4 px) + 1`, at most 9 (sub-frames about 2 px apart; faster motion shows faint ghosts). Image motion is estimated as `f * (rotation angle + translation / 1 m)` between the exposure's start and end. Replaces `--blur`. |
//! | `rolling` | rolling shutter: row `v` is exposed at `t + readout * (v / (H-1) - 1/2)`, readout 10-30 ms, each row ray-cast from its own pose (combined with `blur`, per sub-frame). Depth stays global-shutter at the frame time, like an RGB-D sensor's separate depth camera, so depth and `groundtruth.txt` stay exact. |
//! | `depth-noise` | Kinect-like depth noise: Gaussian in inverse depth, sigma 1.0-2.0e-3 /m (so `sigma_z` is about 1.4e-3 z^2 m: 1.3 cm at 3 m), then quantised in inverse depth with step 2.85e-3 /m (disparity quantisation: 2.6 cm steps at 3 m, 10 cm at 6 m). |
//! | `holes` | invalid depth (written as 0): out of range (nearer than 0.4 m or beyond 5.5-9 m); a 1-pixel band at depth discontinuities (mixed pixels); the projector shadow left of foreground edges, `f * 0.075 m * (1/z_fg - 1/z_bg)` pixels wide (structured light, projector 7.5 cm to the camera's right); random dropout blobs (radius 2-8 px, 0.5-4 % of the image, new every frame) and 0.2 % single-pixel speckle. The teacher treats 0 as invalid. |
//! | `vignette` | radial fall-off `1 - k r^2` (`r` = 1 at the corners, `k` 0.15-0.4), applied in linear light. |
//! | `jpeg` | colour frames written as JPEG at a per-sequence quality 70-95 (unless `--jpeg` already chose JPEG). |
//!
//! The effects apply in this order: render (sub-frames, rolling shutter) -> vignetting, white
//! balance and exposure gain in linear light -> tone curve and colour noise -> JPEG; depth:
//! noise -> holes.

use std::fmt;
use std::str::FromStr;

use nalgebra::Isometry3;

use super::motion::{interpolate, SUBSTEPS};
use super::noise::{mix64, noise1, SplitMix64};
use super::{Lighting, Scene};
use crate::dataset::{DepthImage, Intrinsics};

/// Which sensor effects are on (all off by default). Parsed from `none`, `realistic` or a
/// comma-separated list of names (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct SensorConfig {
    /// Auto-exposure (`exposure`).
    pub auto_exposure: bool,
    /// White-balance drift (`wb`).
    pub white_balance: bool,
    /// Motion blur over the exposure time (`blur`).
    pub motion_blur: bool,
    /// Rolling shutter (`rolling`).
    pub rolling_shutter: bool,
    /// Depth noise and quantisation (`depth-noise`).
    pub depth_noise: bool,
    /// Depth holes (`holes`).
    pub depth_holes: bool,
    /// Vignetting (`vignette`).
    pub vignetting: bool,
    /// JPEG colour frames (`jpeg`).
    pub jpeg: bool,
}

impl SensorConfig {
    /// Every effect on.
    pub const REALISTIC: SensorConfig = SensorConfig {
        auto_exposure: true,
        white_balance: true,
        motion_blur: true,
        rolling_shutter: true,
        depth_noise: true,
        depth_holes: true,
        vignetting: true,
        jpeg: true,
    };

    /// The names accepted by [`FromStr`], in order.
    pub const NAMES: [&'static str; 8] = [
        "exposure",
        "wb",
        "blur",
        "rolling",
        "depth-noise",
        "holes",
        "vignette",
        "jpeg",
    ];

    fn flags(&self) -> [bool; 8] {
        [
            self.auto_exposure,
            self.white_balance,
            self.motion_blur,
            self.rolling_shutter,
            self.depth_noise,
            self.depth_holes,
            self.vignetting,
            self.jpeg,
        ]
    }

    /// Whether any effect is on.
    pub fn any(&self) -> bool {
        self.flags().iter().any(|&f| f)
    }

    /// Whether any effect on the colour image is on.
    pub fn any_colour(&self) -> bool {
        self.auto_exposure
            || self.white_balance
            || self.motion_blur
            || self.rolling_shutter
            || self.vignetting
    }
}

impl FromStr for SensorConfig {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut c = SensorConfig::default();
        for name in s.split(',').map(|n| n.trim().to_ascii_lowercase()) {
            match name.as_str() {
                "" | "none" => {}
                "realistic" | "all" => c = SensorConfig::REALISTIC,
                "exposure" | "ae" => c.auto_exposure = true,
                "wb" | "white-balance" => c.white_balance = true,
                "blur" | "motion-blur" => c.motion_blur = true,
                "rolling" | "rolling-shutter" => c.rolling_shutter = true,
                "depth-noise" => c.depth_noise = true,
                "holes" | "depth-holes" => c.depth_holes = true,
                "vignette" | "vignetting" => c.vignetting = true,
                "jpeg" => c.jpeg = true,
                other => {
                    return Err(format!(
                    "unknown sensor effect `{other}` (expected none, realistic or a list of: {})",
                    SensorConfig::NAMES.join(", ")
                ))
                }
            }
        }
        Ok(c)
    }
}

impl fmt::Display for SensorConfig {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if *self == SensorConfig::default() {
            return f.write_str("none");
        }
        if *self == SensorConfig::REALISTIC {
            return f.write_str("realistic");
        }
        let on: Vec<&str> = SensorConfig::NAMES
            .iter()
            .zip(self.flags())
            .filter_map(|(n, on)| on.then_some(*n))
            .collect();
        f.write_str(&on.join(","))
    }
}

/// Per-sequence camera parameters, drawn from the seed.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SensorParams {
    /// Auto-exposure time constant, seconds.
    pub ae_tau_s: f64,
    /// Exposure time at gain 1, seconds.
    pub t_ref_s: f64,
    /// Rolling-shutter readout time (first to last row), seconds.
    pub readout_s: f64,
    /// White-balance drift amplitude (relative gain).
    pub wb_amplitude: f64,
    /// Vignetting strength `k` (`1 - k r^2`).
    pub vignette_k: f32,
    /// Inverse-depth noise, 1/m.
    pub inv_depth_sigma: f64,
    /// Farthest valid depth, metres.
    pub max_range_m: f32,
    /// Fraction of the image covered by dropout blobs.
    pub dropout_fraction: f64,
    /// JPEG quality.
    pub jpeg_quality: u8,
}

/// Inverse-depth quantisation step (1/m), Kinect v1's 1/8-pixel disparity.
pub const INV_DEPTH_STEP: f64 = 2.85e-3;
/// Nearest valid depth, metres.
pub const MIN_RANGE_M: f32 = 0.4;
/// Projector-camera baseline of the shadow model, metres.
pub const BASELINE_M: f64 = 0.075;
/// Mean linear luminance the auto-exposure aims at: a mean display level of about 0.45-0.5 after
/// the tone curve and vignetting, like the real sequences in `shared/data` (0.43-0.53; the
/// default renders average about 0.7).
pub const AE_TARGET: f64 = 0.24;

impl SensorParams {
    /// Parameters of the sequence with `seed`.
    pub fn new(seed: u64) -> SensorParams {
        let mut rng = SplitMix64::new(seed ^ 0x5E25_0C0F_FEE5);
        SensorParams {
            ae_tau_s: rng.range(0.15, 0.6),
            t_ref_s: rng.range(0.004, 0.014),
            readout_s: rng.range(0.010, 0.030),
            wb_amplitude: rng.range(0.03, 0.08),
            vignette_k: rng.range(0.15, 0.4) as f32,
            inv_depth_sigma: rng.range(1.0e-3, 2.0e-3),
            max_range_m: rng.range(5.5, 9.0) as f32,
            dropout_fraction: rng.range(0.005, 0.04),
            jpeg_quality: (70 + rng.below(26)) as u8,
        }
    }
}

/// The camera state of one frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FrameSensor {
    /// Total exposure gain (exposure time and analog gain) applied in linear light.
    pub gain: f64,
    /// Exposure time, seconds.
    pub exposure_s: f64,
    /// Analog part of the gain (>= 1 once the exposure time is at its maximum).
    pub analog_gain: f64,
    /// White-balance gains `[r, g, b]`.
    pub wb: [f32; 3],
}

impl Default for FrameSensor {
    fn default() -> Self {
        FrameSensor {
            gain: 1.0,
            exposure_s: 0.0,
            analog_gain: 1.0,
            wb: [1.0; 3],
        }
    }
}

/// The pose at fractional sample index `x` of a path sampled `SUBSTEPS` times per frame
/// (interpolated; extrapolated linearly before the first and after the last sample).
pub(crate) fn sample_at(samples: &[Isometry3<f64>], x: f64) -> Isometry3<f64> {
    if samples.len() < 2 {
        return samples.first().copied().unwrap_or_else(Isometry3::identity);
    }
    let k = (x.floor().max(0.0) as usize).min(samples.len() - 2);
    let s = x - k as f64;
    if s == 0.0 {
        return samples[k];
    }
    interpolate(&samples[k], &samples[k + 1], s)
}

/// Mean linear luminance of a low-resolution render at `pose`.
fn meter(
    scene: &Scene,
    pose: &Isometry3<f64>,
    intr: &Intrinsics,
    w: u32,
    h: u32,
    light: &Lighting,
) -> f64 {
    let (mw, mh) = ((w / 8).max(8), (h / 8).max(6));
    let sx = mw as f64 / w as f64;
    let sy = mh as f64 / h as f64;
    let k = Intrinsics {
        fx: intr.fx * sx,
        fy: intr.fy * sy,
        cx: (intr.cx + 0.5) * sx - 0.5,
        cy: (intr.cy + 0.5) * sy - 0.5,
        depth_scale: intr.depth_scale,
    };
    let mut acc = vec![0.0f32; mw as usize * mh as usize * 3];
    scene.render_into(pose, &k, mw, mh, light, &mut acc, None);
    let sum: f64 = acc
        .chunks_exact(3)
        .map(|p| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64)
        .sum();
    sum / (mw as f64 * mh as f64)
}

/// The per-frame camera state of a whole sequence (auto-exposure is sequential).
#[allow(clippy::too_many_arguments)]
pub(crate) fn sensor_track(
    cfg: &SensorConfig,
    params: &SensorParams,
    seed: u64,
    fps: f64,
    scene: &Scene,
    samples: &[Isometry3<f64>],
    intr: &Intrinsics,
    (w, h): (u32, u32),
    lighting: &dyn Fn(usize) -> Lighting,
    frames: usize,
) -> Vec<FrameSensor> {
    let max_exposure = 0.9 / fps;
    let a = 1.0 - (-1.0 / (fps * params.ae_tau_s)).exp();
    let mut log_gain = None::<f64>;
    let mut desired_prev = 0.0;
    (0..frames)
        .map(|i| {
            let t = i as f64 / fps;
            let gain = if cfg.auto_exposure {
                let m = meter(scene, &samples[i * SUBSTEPS], intr, w, h, &lighting(i)).max(1e-4);
                let target = AE_TARGET * (0.1 * noise1(t * 0.2, seed ^ 0xAE7A)).exp();
                let desired = (target / m).ln().clamp(-2.5, 2.5);
                // one frame of metering delay; the first frame starts converged
                let g = match log_gain {
                    None => desired,
                    Some(g) => g + a * (desired_prev - g),
                };
                log_gain = Some(g);
                desired_prev = desired;
                g.exp()
            } else {
                1.0
            };
            let exposure_s = (params.t_ref_s * gain).clamp(0.0005, max_exposure);
            let analog_gain = (gain * params.t_ref_s / exposure_s).max(1.0);
            let wb = if cfg.white_balance {
                let d = |c: u64| (params.wb_amplitude * noise1(t * 0.1, seed ^ c)).exp() as f32;
                [d(0x3B1), 1.0, d(0x3B3)]
            } else {
                [1.0; 3]
            };
            FrameSensor {
                gain,
                exposure_s,
                analog_gain,
                wb,
            }
        })
        .collect()
}

/// Renders the colour of frame `i` with the colour effects (blur, rolling shutter, vignetting,
/// white balance, exposure) into `acc` (linear, already divided by the sub-frame count).
/// `acc` holds the global-shutter render at the frame time on entry; it is reused as the
/// central sub-frame when there is one and no rolling shutter, and cleared otherwise.
/// Returns the colour-noise multiplier (`sqrt(analog gain)`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn render_colour(
    cfg: &SensorConfig,
    params: &SensorParams,
    fs: &FrameSensor,
    scene: &Scene,
    samples: &[Isometry3<f64>],
    intr: &Intrinsics,
    (w, h): (u32, u32),
    light: &Lighting,
    fps: f64,
    i: usize,
    legacy_blur: bool,
    acc: &mut [f32],
) -> f32 {
    let per_s = fps * SUBSTEPS as f64; // samples per second
    let c = (i * SUBSTEPS) as f64;
    // sub-frame time offsets (seconds) within the exposure
    let offsets: Vec<f64> = if cfg.motion_blur {
        let half = fs.exposure_s / 2.0 * per_s;
        let a = sample_at(samples, c - half);
        let b = sample_at(samples, c + half);
        let rel = a.inverse() * b;
        let px = intr.fx * (rel.rotation.angle() + rel.translation.vector.norm() / 1.0);
        // an odd count, so that the central sub-frame is the frame time
        let n = 2 * ((px / 4.0).ceil() as usize).min(4) + 1;
        let n = if px < 1.0 { 1 } else { n };
        (0..n)
            .map(|k| {
                if 2 * k + 1 == n {
                    0.0
                } else {
                    fs.exposure_s * ((k as f64 + 0.5) / n as f64 - 0.5)
                }
            })
            .collect()
    } else if legacy_blur {
        // `--blur`: the frame time and a quarter frame either side
        vec![0.0, -1.0 / per_s, 1.0 / per_s]
    } else {
        vec![0.0]
    };
    let n = offsets.len();
    let rs = if cfg.rolling_shutter {
        params.readout_s
    } else {
        0.0
    };
    let hm1 = (h.max(2) - 1) as f64;
    let reuse = rs == 0.0 && offsets.contains(&0.0);
    if !reuse {
        acc.iter_mut().for_each(|x| *x = 0.0);
    }
    for &off in &offsets {
        if reuse && off == 0.0 {
            continue;
        }
        if rs > 0.0 {
            let row_pose =
                |v: usize| sample_at(samples, c + (off + rs * (v as f64 / hm1 - 0.5)) * per_s);
            scene.render_into_rows(&row_pose, intr, w, h, light, acc, None);
        } else {
            let p = sample_at(samples, c + off * per_s);
            scene.render_into(&p, intr, w, h, light, acc, None);
        }
    }
    let (cx, cy) = (intr.cx as f32, intr.cy as f32);
    let r2max = (cx * cx + cy * cy).max(1e-6);
    let g = fs.gain as f32 / n as f32;
    let k_v = if cfg.vignetting {
        params.vignette_k
    } else {
        0.0
    };
    let wu = w as usize;
    for (v, row) in acc.chunks_exact_mut(wu * 3).enumerate() {
        let dy = v as f32 - cy;
        for (u, px) in row.chunks_exact_mut(3).enumerate() {
            let dx = u as f32 - cx;
            let vig = 1.0 - k_v * (dx * dx + dy * dy) / r2max;
            for (x, wb) in px.iter_mut().zip(fs.wb) {
                *x *= g * vig * wb;
            }
        }
    }
    fs.analog_gain.sqrt() as f32
}

/// A Gaussian-ish deviate (Irwin-Hall of 4 bytes, unit standard deviation) from a hash.
#[inline]
fn gauss(h: u64) -> f64 {
    let s = (h & 0xFF) + ((h >> 8) & 0xFF) + ((h >> 16) & 0xFF) + ((h >> 24) & 0xFF);
    (s as f64 - 510.0) / 147.8
}

/// Applies depth noise and holes (0 = invalid) to the clean depth of frame `i`.
pub(crate) fn degrade_depth(
    cfg: &SensorConfig,
    params: &SensorParams,
    depth: &mut DepthImage,
    fx: f64,
    seed: u64,
    i: usize,
) {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let fseed = mix64(seed ^ 0xDE97_0000 ^ (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let clean = depth.data.clone();
    if cfg.depth_noise {
        for (k, z) in depth.data.iter_mut().enumerate() {
            if *z > 0.0 {
                let inv = 1.0 / *z as f64
                    + params.inv_depth_sigma
                        * gauss(mix64(
                            fseed ^ (k as u64).wrapping_mul(0xA24B_AED4_963E_E407),
                        ));
                let q = (inv / INV_DEPTH_STEP).round().max(1.0) * INV_DEPTH_STEP;
                *z = (1.0 / q) as f32;
            }
        }
    }
    if !cfg.depth_holes {
        return;
    }
    let d = &mut depth.data;
    // range
    for (z, &c) in d.iter_mut().zip(&clean) {
        if !(MIN_RANGE_M..=params.max_range_m).contains(&c) {
            *z = 0.0;
        }
    }
    // discontinuities (on the clean depth): mixed pixels and the projector shadow
    let disc = |a: f32, b: f32| (a - b).abs() > 0.04 * a.min(b) + 0.02;
    let mut holes = vec![false; w * h];
    for v in 0..h {
        let row = &clean[v * w..(v + 1) * w];
        for u in 1..w {
            let (za, zb) = (row[u - 1], row[u]);
            if za <= 0.0 || zb <= 0.0 || !disc(za, zb) {
                continue;
            }
            holes[v * w + u - 1] = true;
            holes[v * w + u] = true;
            if za > zb {
                // background on the left of a foreground edge: projector shadow
                let width =
                    (fx * BASELINE_M * (1.0 / zb as f64 - 1.0 / za as f64)).round() as usize;
                for x in (u.saturating_sub(width)..u).rev() {
                    if row[x] <= zb * 1.04 {
                        break;
                    }
                    holes[v * w + x] = true;
                }
            }
        }
        if v > 0 {
            for u in 0..w {
                let (za, zb) = (clean[(v - 1) * w + u], row[u]);
                if za > 0.0 && zb > 0.0 && disc(za, zb) {
                    holes[(v - 1) * w + u] = true;
                    holes[v * w + u] = true;
                }
            }
        }
    }
    // dropout blobs and speckle
    let mut rng = SplitMix64::new(fseed ^ 0xB10B);
    let area = (w * h) as f64;
    let mean_r2 = (2.0f64 * 2.0 + 2.0 * 8.0 + 8.0 * 8.0) / 3.0; // E[r^2], r uniform in [2, 8]
    let n_blobs =
        (params.dropout_fraction * area / (std::f64::consts::PI * mean_r2)).round() as usize;
    for _ in 0..n_blobs {
        let (bx, by) = (rng.range(0.0, w as f64), rng.range(0.0, h as f64));
        let r = rng.range(2.0, 8.0);
        let (x0, x1) = (
            (bx - r).max(0.0) as usize,
            ((bx + r).ceil() as usize).min(w),
        );
        let (y0, y1) = (
            (by - r).max(0.0) as usize,
            ((by + r).ceil() as usize).min(h),
        );
        for y in y0..y1 {
            for x in x0..x1 {
                let (dx, dy) = (x as f64 + 0.5 - bx, y as f64 + 0.5 - by);
                if dx * dx + dy * dy <= r * r {
                    holes[y * w + x] = true;
                }
            }
        }
    }
    for (k, hole) in holes.iter_mut().enumerate() {
        if mix64(fseed ^ 0x5BEC ^ (k as u64).wrapping_mul(0x9E37_79B9)).is_multiple_of(500) {
            *hole = true;
        }
    }
    for (z, &hole) in d.iter_mut().zip(&holes) {
        if hole {
            *z = 0.0;
        }
    }
}
