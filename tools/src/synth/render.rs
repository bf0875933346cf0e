//! Frames and sequences: configuration, tone mapping and noise, writing the TUM layout.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::RgbImage;
use nalgebra::Isometry3;
use rayon::prelude::*;

use super::materials::load_textures;
use super::motion::{generate_path, interpolate, orbit_target, MotionProfile, Segment, SUBSTEPS};
use super::noise::{mix64, noise1};
use super::replay::{replay_path, Placement, Replay};
use super::sensor::{self, FrameSensor, SensorConfig, SensorParams};
use super::{Lighting, Scene, SynthError};
use crate::dataset::{DatasetError, DepthImage, Intrinsics, RgbFormat, SequenceWriter};

/// Converts accumulated linear colour (divided by `div`) to 8-bit sRGB-ish, adding Gaussian
/// noise of standard deviation `noise` (0..1 units) seeded by `noise_seed`.
pub(crate) fn to_rgb(
    acc: &[f32],
    w: u32,
    h: u32,
    div: f32,
    noise: f32,
    noise_seed: u64,
) -> RgbImage {
    let n = w as usize * h as usize * 3;
    let mut out = vec![0u8; n];
    let inv = 1.0 / div;
    // Irwin-Hall approximation of a Gaussian: sum of 4 uniform bytes; sd of the sum is 147.8.
    let nscale = noise / 147.8;
    out.par_chunks_mut(w as usize * 3)
        .zip(acc[..n].par_chunks(w as usize * 3))
        .enumerate()
        .for_each(|(v, (o, a))| {
            for (k, (ob, &av)) in o.iter_mut().zip(a).enumerate() {
                // gamma 1/2 as a cheap tone curve
                let mut x = (av * inv).max(0.0).sqrt();
                if noise > 0.0 {
                    let hsh = mix64(
                        noise_seed ^ ((v * w as usize * 3 + k) as u64).wrapping_mul(0x9E37_79B9),
                    );
                    let s = (hsh & 0xFF)
                        + ((hsh >> 8) & 0xFF)
                        + ((hsh >> 16) & 0xFF)
                        + ((hsh >> 24) & 0xFF);
                    x += (s as f32 - 510.0) * nscale;
                }
                *ob = (x * 255.0 + 0.5).clamp(0.0, 255.0) as u8;
            }
        });
    RgbImage::from_raw(w, h, out).unwrap_or_else(|| RgbImage::new(w, h))
}

/// Configuration of [`render_sequence`].
#[derive(Debug, Clone, PartialEq)]
pub struct SynthConfig {
    /// Seed of scene, path and noise.
    pub seed: u64,
    /// Number of frames.
    pub frames: usize,
    /// Image width (default 640).
    pub width: u32,
    /// Image height (default 480).
    pub height: u32,
    /// Frame rate (default 30).
    pub fps: f64,
    /// Camera path style (default `mixed`).
    pub motion: MotionProfile,
    /// Folder of jpg/png images tiled on about half of the surfaces.
    pub textures: Option<PathBuf>,
    /// Standard deviation of Gaussian colour noise, in 0..1 intensity units (default 0.01).
    pub noise: f32,
    /// Motion blur: average 3 sub-frame renders spanning half a frame interval, centred on the
    /// frame time (depth and pose are those of the frame time).
    pub blur: bool,
    /// Slow exposure drift and a light dimming during the middle of the sequence.
    pub lighting_changes: bool,
    /// Encoding of the colour frames (default PNG).
    pub rgb_format: RgbFormat,
    /// Replay a real camera trajectory instead of `motion` (see [`super::replay`]).
    pub replay: Option<Replay>,
    /// Opt-in sensor effects (see [`super::sensor`]; default: none).
    pub sensor: SensorConfig,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            seed: 0,
            frames: 300,
            width: 640,
            height: 480,
            fps: 30.0,
            motion: MotionProfile::Mixed,
            textures: None,
            noise: 0.01,
            blur: false,
            lighting_changes: false,
            rgb_format: RgbFormat::Png,
            replay: None,
            sensor: SensorConfig::default(),
        }
    }
}

impl SynthConfig {
    /// Intrinsics used for a `width x height` render: focal 525 px at 640 wide (scaled with
    /// width), principal point at the image centre `((W-1)/2, (H-1)/2)`, depth_scale 1000.
    pub fn intrinsics(&self) -> Intrinsics {
        let f = 525.0 * self.width as f64 / 640.0;
        Intrinsics {
            fx: f,
            fy: f,
            cx: (self.width as f64 - 1.0) / 2.0,
            cy: (self.height as f64 - 1.0) / 2.0,
            depth_scale: 1000.0,
        }
    }

    /// What a render reads: the `textures` folder and its images, the replayed trajectory. No
    /// output may be or hold one of them ([`crate::output::Inputs`]).
    pub fn input_files(&self) -> Vec<PathBuf> {
        let mut files = Vec::new();
        if let Some(dir) = &self.textures {
            files.push(dir.clone());
            files.extend(crate::dataset::list_images(dir).unwrap_or_default());
        }
        files.extend(self.replay.as_ref().map(|r| r.path.clone()));
        files
    }
}

/// What [`render_sequence`] produced, with timings.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SynthSummary {
    /// Output directory.
    pub out: PathBuf,
    /// Frames written.
    pub frames: usize,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Intrinsics `fx fy cx cy depth_scale`.
    pub intrinsics: [f64; 5],
    /// Motion segments (for `mixed`, one per segment).
    pub segments: Vec<Segment>,
    /// Seconds spent rendering (ray casting, blur, noise).
    pub render_seconds: f64,
    /// Seconds spent encoding and writing files.
    pub write_seconds: f64,
}

impl SynthSummary {
    /// Rendered frames per second (render only).
    pub fn render_fps(&self) -> f64 {
        self.frames as f64 / self.render_seconds.max(1e-9)
    }

    /// Frames per second including file writing.
    pub fn total_fps(&self) -> f64 {
        self.frames as f64 / (self.render_seconds + self.write_seconds).max(1e-9)
    }
}

pub(crate) fn lighting_at(cfg: &SynthConfig, i: usize) -> Lighting {
    if !cfg.lighting_changes {
        return Lighting::default();
    }
    let t = i as f64 / cfg.fps;
    let exposure = (1.0 + 0.3 * noise1(t * 0.25, cfg.seed ^ 0xE8)) as f32;
    let (a, b) = (cfg.frames * 2 / 5, cfg.frames * 3 / 5);
    let dim = if i >= a && i < b { 0.35 } else { 1.0 };
    Lighting {
        exposure,
        light_gains: [dim, 1.0, 1.0],
    }
}

/// The sensor model of a sequence: parameters and per-frame camera state.
#[derive(Debug, Clone)]
pub(crate) struct SensorSetup {
    pub(crate) params: SensorParams,
    pub(crate) track: Vec<FrameSensor>,
}

impl SensorSetup {
    /// Runs the auto-exposure and white balance over the path (`None` when no effect is on).
    pub(crate) fn new(
        cfg: &SynthConfig,
        scene: &Scene,
        samples: &[Isometry3<f64>],
    ) -> Option<SensorSetup> {
        if !cfg.sensor.any() {
            return None;
        }
        let params = SensorParams::new(cfg.seed);
        let track = sensor::sensor_track(
            &cfg.sensor,
            &params,
            cfg.seed,
            cfg.fps,
            scene,
            samples,
            &cfg.intrinsics(),
            (cfg.width, cfg.height),
            &|i| lighting_at(cfg, i),
            cfg.frames,
        );
        Some(SensorSetup { params, track })
    }
}

/// Renders one frame `i` of a configuration: colour (with blur/noise and the sensor effects of
/// `sensor`) and depth.
pub(crate) fn render_frame(
    cfg: &SynthConfig,
    scene: &Scene,
    samples: &[Isometry3<f64>],
    sensor: Option<&SensorSetup>,
    i: usize,
) -> (RgbImage, DepthImage) {
    let (w, h) = (cfg.width, cfg.height);
    let intr = cfg.intrinsics();
    let light = lighting_at(cfg, i);
    let mut acc = vec![0.0f32; w as usize * h as usize * 3];
    let mut depth = DepthImage::new(w, h);
    let c = i * SUBSTEPS;
    let sc = &cfg.sensor;
    let colour_effects = sc.any_colour();
    let mut div = 1.0;
    let mut noise = cfg.noise;
    match sensor {
        Some(setup) if colour_effects => {
            let fs = setup.track.get(i).copied().unwrap_or_default();
            // depth at the frame pose (global shutter); colour from the sensor model, which
            // reuses this render as its central sub-frame when there is no rolling shutter
            if sc.rolling_shutter {
                scene.render_depth(&samples[c], &intr, w, h, &mut depth.data);
            } else {
                scene.render_into(
                    &samples[c],
                    &intr,
                    w,
                    h,
                    &light,
                    &mut acc,
                    Some(&mut depth.data),
                );
            }
            noise *= sensor::render_colour(
                sc,
                &setup.params,
                &fs,
                scene,
                samples,
                &intr,
                (w, h),
                &light,
                cfg.fps,
                i,
                cfg.blur,
                &mut acc,
            );
        }
        _ => {
            scene.render_into(
                &samples[c],
                &intr,
                w,
                h,
                &light,
                &mut acc,
                Some(&mut depth.data),
            );
            if cfg.blur {
                // Samples are a quarter frame apart: c-1 and c+1 span half a frame interval.
                let before = if c > 0 {
                    samples[c - 1]
                } else {
                    interpolate(&samples[c], &samples[c + 1], -1.0)
                };
                for p in [before, samples[c + 1]] {
                    scene.render_into(&p, &intr, w, h, &light, &mut acc, None);
                }
                div = 3.0;
            }
        }
    }
    if let Some(setup) = sensor {
        sensor::degrade_depth(sc, &setup.params, &mut depth, intr.fx, cfg.seed, i);
    }
    let rgb = to_rgb(
        &acc,
        w,
        h,
        div,
        noise,
        mix64(cfg.seed ^ (i as u64 + 1).wrapping_mul(0xA5A5_5A5A)),
    );
    (rgb, depth)
}

/// The camera path of a configuration.
pub(crate) struct PathSamples {
    /// `SUBSTEPS` samples per frame (frame `i` is sample `SUBSTEPS * i`), and one frame more.
    pub(crate) samples: Vec<Isometry3<f64>>,
    /// Motion segments (none for a replay).
    pub(crate) segments: Vec<Segment>,
    /// How a replayed trajectory was placed.
    pub(crate) placement: Option<Placement>,
    /// Number of frames (a replay may stop early).
    pub(crate) frames: usize,
}

/// The camera path of a configuration, generated or replayed.
pub(crate) fn path_samples(cfg: &SynthConfig, scene: &Scene) -> Result<PathSamples, SynthError> {
    match &cfg.replay {
        Some(r) => {
            let (samples, placement) = replay_path(r, scene, cfg.fps, cfg.frames)?;
            Ok(PathSamples {
                samples,
                segments: Vec::new(),
                frames: placement.frames,
                placement: Some(placement),
            })
        }
        None => {
            let (samples, segments) =
                generate_path(scene, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
            Ok(PathSamples {
                samples,
                segments,
                placement: None,
                frames: cfg.frames,
            })
        }
    }
}

/// The camera path of a configuration (camera-to-world per frame, a replay included) and its
/// segments, without rendering.
pub fn try_camera_path(
    cfg: &SynthConfig,
    scene: &Scene,
) -> Result<(Vec<Isometry3<f64>>, Vec<Segment>), SynthError> {
    let p = path_samples(cfg, scene)?;
    Ok((
        p.samples
            .iter()
            .step_by(SUBSTEPS)
            .take(p.frames)
            .copied()
            .collect(),
        p.segments,
    ))
}

/// Largest side of a rendered frame, in pixels (larger sizes are refused, not allocated; a
/// 4096x4096 frame renders in about 10 s on 2 cores with a peak RSS of 0.31 GB).
pub const MAX_SIDE: u32 = 4096;
/// Most frames in one sequence (9 hours at 30 frames/s; the camera path is held in memory).
pub const MAX_FRAMES: usize = 1_000_000;

/// Renders a whole sequence into `out` (TUM layout, depth_scale 1000, camera-to-world
/// ground truth) plus `synth.json` describing the configuration and segments.
/// How the text files of a rendered sequence begin (`rgb.txt`'s first line): what tells an
/// earlier synth output from someone else's folder.
pub const HEADER_PREFIX: &str = "# LeanGate synthetic sequence:";

pub fn render_sequence(cfg: &SynthConfig, out: &Path) -> Result<SynthSummary, SynthError> {
    let side = 2..=MAX_SIDE;
    if !(1..=MAX_FRAMES).contains(&cfg.frames)
        || !side.contains(&cfg.width)
        || !side.contains(&cfg.height)
    {
        return Err(SynthError::Config(format!(
            "need 1 to {MAX_FRAMES} frames and sides of 2 to {MAX_SIDE} pixels (got {} frames, \
             {}x{})",
            cfg.frames, cfg.width, cfg.height
        )));
    }
    let valid = cfg.fps > 0.0 && cfg.fps.is_finite() && cfg.noise >= 0.0 && cfg.noise.is_finite();
    if !valid {
        return Err(SynthError::Config(format!(
            "fps must be positive and noise non-negative (got {} and {})",
            cfg.fps, cfg.noise
        )));
    }
    let textures = match &cfg.textures {
        Some(dir) => load_textures(dir)?,
        None => Vec::new(),
    };
    let mut scene = Scene::with_textures(cfg.seed, &textures);
    let PathSamples {
        samples,
        segments,
        placement,
        frames,
    } = path_samples(cfg, &scene)?;
    if cfg.replay.is_none() && cfg.motion == MotionProfile::Orbit {
        let (centre, half, _) = orbit_target(&scene, cfg.seed);
        scene.add_object(centre, half, cfg.seed);
    }
    if frames < cfg.frames {
        eprintln!(
            "synth: the replayed trajectory covers {frames} of the {} frames asked for (replay end `stop`)",
            cfg.frames
        );
    }
    let cfg = &SynthConfig {
        frames,
        ..cfg.clone()
    };
    let sensor = SensorSetup::new(cfg, &scene, &samples);
    let rgb_format = match (&sensor, cfg.rgb_format) {
        (Some(s), RgbFormat::Png) if cfg.sensor.jpeg => RgbFormat::Jpeg(s.params.jpeg_quality),
        (_, f) => f,
    };
    let intr = cfg.intrinsics();
    let mut writer = SequenceWriter::create(out, intr, rgb_format)?;
    let motion = match &cfg.replay {
        Some(r) => format!("replay:{}", r.path.display()),
        None => cfg.motion.to_string(),
    };
    let sensor_note = if cfg.sensor.any() {
        format!(" sensor {}", cfg.sensor)
    } else {
        String::new()
    };
    writer.set_header(&format!(
        "{} seed {} motion {motion} {}x{} at {} fps{sensor_note}",
        &HEADER_PREFIX[2..],
        cfg.seed,
        cfg.width,
        cfg.height,
        cfg.fps
    ));
    let (mut render_s, mut write_s) = (0.0, 0.0);
    let chunk = 8;
    for start in (0..cfg.frames).step_by(chunk) {
        let end = (start + chunk).min(cfg.frames);
        let t0 = Instant::now();
        let rendered: Vec<(RgbImage, DepthImage)> = (start..end)
            .map(|i| render_frame(cfg, &scene, &samples, sensor.as_ref(), i))
            .collect();
        render_s += t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        rendered
            .par_iter()
            .enumerate()
            .try_for_each(|(k, (rgb, depth))| {
                let i = start + k;
                writer.write_frame(
                    i,
                    i as f64 / cfg.fps,
                    rgb,
                    Some(depth),
                    Some(&samples[i * SUBSTEPS]),
                )
            })?;
        write_s += t1.elapsed().as_secs_f64();
    }
    let t1 = Instant::now();
    let root = writer.finish()?;
    let summary = SynthSummary {
        out: root.clone(),
        frames: cfg.frames,
        width: cfg.width,
        height: cfg.height,
        intrinsics: [intr.fx, intr.fy, intr.cx, intr.cy, intr.depth_scale],
        segments,
        render_seconds: render_s,
        write_seconds: write_s + t1.elapsed().as_secs_f64(),
    };
    let mut meta = serde_json::json!({
        "seed": cfg.seed,
        "frames": cfg.frames,
        "width": cfg.width,
        "height": cfg.height,
        "fps": cfg.fps,
        "motion": cfg.motion,
        "textures": cfg.textures,
        "noise": (cfg.noise as f64 * 1e6).round() / 1e6,
        "blur": cfg.blur,
        "lighting_changes": cfg.lighting_changes,
        "segments": summary.segments,
        "room": scene.room,
    });
    if let Some(p) = &placement {
        meta["motion"] = serde_json::json!("replay");
        meta["replay"] = serde_json::json!({
            "file": cfg.replay.as_ref().map(|r| r.path.clone()),
            "placement": p,
        });
    }
    if let Some(s) = &sensor {
        meta["sensor"] = serde_json::json!(cfg.sensor.to_string());
        meta["sensor_params"] = serde_json::json!(s.params);
        let r3 = |x: f64| (x * 1e3).round() / 1e3;
        meta["exposure_gain"] =
            serde_json::json!(s.track.iter().map(|f| r3(f.gain)).collect::<Vec<_>>());
    }
    let meta_path = root.join("synth.json");
    std::fs::write(
        &meta_path,
        serde_json::to_string_pretty(&meta).unwrap_or_default(),
    )
    .map_err(|source| DatasetError::Io {
        path: meta_path,
        source,
    })?;
    Ok(summary)
}
