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
//! only), `pan`, `shaky`, `walk`, `rotate`, `bursts` (pauses and bursts), and `mixed` (random
//! segments of 1.5 to 4 s of all the others; the default).
//!
//! # Speed
//!
//! Per frame, each box's projected screen rectangle is computed once and each image row only
//! tests the boxes whose rectangle covers it; rows are rendered in parallel with rayon. On a
//! 2-core machine a 640x480 frame renders at about 70 frames/s (about 50 frames/s including
//! PNG encoding and writing; `cargo test synth_speed -- --ignored --nocapture`). Motion blur
//! renders 3 sub-frames and costs about 3x.
//!
//! Everything is deterministic for a seed: random numbers come from a splitmix64 generator and
//! from counter-based hashes (noise is a function of frame, pixel and channel), so results do not
//! depend on thread scheduling.

use std::f64::consts::PI;
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Instant;

use image::RgbImage;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rayon::prelude::*;

use crate::dataset::{self, DatasetError, DepthImage, Intrinsics, RgbFormat, SequenceWriter};

// ---------------------------------------------------------------------------------------------
// Random numbers and noise
// ---------------------------------------------------------------------------------------------

/// splitmix64: a small, fast, seedable generator (good enough for scene layout).
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.0)
    }

    /// Uniform in `[0, 1)`.
    pub fn f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[a, b)`.
    pub fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.f64()
    }

    /// Uniform integer in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        ((self.next_u64() >> 32) as usize * n) >> 32
    }
}

#[inline]
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of a 2-D lattice point to `[0, 1)`.
#[inline]
fn hash2(x: i32, y: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8DA6_B343)
        ^ (y as u32).wrapping_mul(0xD816_3841)
        ^ seed.wrapping_mul(0xCB1A_B31F);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2C1B_3C6D);
    h ^= h >> 12;
    h = h.wrapping_mul(0x297A_2D39);
    h ^= h >> 15;
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// `floor` for `f32` without a libm call (x86-64 baseline has no SSE4.1 `roundss`); exact
/// for |x| < 2^31.
#[inline(always)]
fn ffloor(x: f32) -> f32 {
    let i = x as i32 as f32;
    if i > x {
        i - 1.0
    } else {
        i
    }
}

/// 2-D value noise in `[0, 1)` with smoothstep interpolation.
#[inline]
fn value_noise(x: f32, y: f32, seed: u32) -> f32 {
    let (xf, yf) = (ffloor(x), ffloor(y));
    let (xi, yi) = (xf as i32, yf as i32);
    let (fx, fy) = (x - xf, y - yf);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let a = hash2(xi, yi, seed);
    let b = hash2(xi + 1, yi, seed);
    let c = hash2(xi, yi + 1, seed);
    let d = hash2(xi + 1, yi + 1, seed);
    let top = a + (b - a) * sx;
    let bot = c + (d - c) * sx;
    top + (bot - top) * sy
}

/// Three-octave fractal value noise in about `[0, 1)`.
#[inline]
fn fbm(x: f32, y: f32, seed: u32) -> f32 {
    (value_noise(x, y, seed) * 0.57
        + value_noise(x * 2.03, y * 2.03, seed ^ 0x55) * 0.29
        + value_noise(x * 4.11, y * 4.11, seed ^ 0xAA) * 0.14)
        .min(0.9999)
}

/// Smooth 1-D noise in about `[-1, 1]` (cubic interpolation of lattice values).
fn noise1(t: f64, seed: u64) -> f64 {
    let i = t.floor();
    let f = t - i;
    let s = f * f * (3.0 - 2.0 * f);
    let h = |k: i64| {
        (mix64(seed ^ (k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)) >> 11) as f64
            / (1u64 << 53) as f64
            * 2.0
            - 1.0
    };
    let a = h(i as i64);
    let b = h(i as i64 + 1);
    a + (b - a) * s
}

// ---------------------------------------------------------------------------------------------
// Materials
// ---------------------------------------------------------------------------------------------

#[derive(Debug, Clone, Copy, PartialEq)]
enum Pattern {
    Noise,
    Checker,
    Stripes,
    Bricks,
    Wood,
    Image(usize),
}

#[derive(Debug, Clone, Copy)]
struct Material {
    pattern: Pattern,
    c0: [f32; 3],
    c1: [f32; 3],
    /// Pattern cells per metre.
    scale: f32,
    seed: u32,
}

fn random_colour(rng: &mut SplitMix64) -> [f32; 3] {
    let base = rng.range(0.25, 0.85) as f32;
    let mut c = [0.0; 3];
    for x in c.iter_mut() {
        *x = (base + rng.range(-0.25, 0.25) as f32).clamp(0.05, 0.95);
    }
    c
}

impl Material {
    fn random(rng: &mut SplitMix64, n_images: usize, kind_hint: Option<Pattern>) -> Material {
        let pattern = if n_images > 0 && rng.f64() < 0.5 {
            Pattern::Image(rng.below(n_images))
        } else if let Some(p) = kind_hint.filter(|_| rng.f64() < 0.6) {
            p
        } else {
            [
                Pattern::Noise,
                Pattern::Checker,
                Pattern::Stripes,
                Pattern::Bricks,
                Pattern::Wood,
            ][rng.below(5)]
        };
        let c0 = random_colour(rng);
        let contrast = rng.range(0.25, 0.7) as f32;
        let c1 = if rng.f64() < 0.5 {
            random_colour(rng)
        } else {
            c0.map(|x| (x * (1.0 - contrast)).max(0.02))
        };
        let scale = match pattern {
            Pattern::Noise => rng.range(2.0, 8.0),
            Pattern::Checker => rng.range(1.5, 5.0),
            Pattern::Stripes => rng.range(2.0, 10.0),
            Pattern::Bricks => rng.range(0.8, 1.5),
            Pattern::Wood => rng.range(0.5, 1.5),
            Pattern::Image(_) => rng.range(0.4, 1.0),
        } as f32;
        Material {
            pattern,
            c0,
            c1,
            scale,
            seed: rng.next_u64() as u32,
        }
    }

    /// Albedo at surface coordinates `(s, t)` (metres).
    #[inline]
    fn albedo(&self, s: f32, t: f32, images: &[TextureImage]) -> [f32; 3] {
        let (x, y) = (s * self.scale, t * self.scale);
        let mix = |k: f32| -> [f32; 3] {
            [
                self.c0[0] + (self.c1[0] - self.c0[0]) * k,
                self.c0[1] + (self.c1[1] - self.c0[1]) * k,
                self.c0[2] + (self.c1[2] - self.c0[2]) * k,
            ]
        };
        let base = match self.pattern {
            Pattern::Noise => mix(fbm(x, y, self.seed)),
            Pattern::Checker => {
                let k = ((ffloor(x) as i32 + ffloor(y) as i32) & 1) as f32;
                mix(k * 0.8 + 0.2 * value_noise(x * 3.0, y * 3.0, self.seed))
            }
            Pattern::Stripes => {
                let f = x + 0.3 * value_noise(y * 0.5, 0.0, self.seed);
                mix(if f - ffloor(f) < 0.5 { 0.0 } else { 1.0 })
            }
            Pattern::Bricks => {
                // bricks 0.25 x 0.08 (at scale 1) with 1 cm mortar
                let (bw, bh) = (0.25f32, 0.08f32);
                let row = ffloor(y / bh);
                let xo = x / bw + if (row as i32) & 1 == 1 { 0.5 } else { 0.0 };
                let col = ffloor(xo);
                let (fx, fy) = ((xo - col) * bw, (y / bh - row) * bh);
                if fx < 0.012 || fy < 0.012 {
                    self.c1.map(|c| c * 0.5 + 0.4)
                } else {
                    let k = hash2(col as i32, row as i32, self.seed) * 0.5;
                    mix(k)
                }
            }
            Pattern::Wood => {
                let r = y * 6.0 + 2.5 * fbm(x * 0.7, y * 3.0, self.seed);
                let f = r - ffloor(r);
                mix(f * f)
            }
            Pattern::Image(i) => images.get(i).map_or(self.c0, |im| im.sample(x, y)),
        };
        base
    }
}

/// A texture image stored as linear floats for fast nearest-neighbour sampling.
#[derive(Debug, Clone)]
struct TextureImage {
    w: usize,
    h: usize,
    px: Vec<[f32; 3]>,
}

impl TextureImage {
    fn from_rgb(img: &RgbImage) -> TextureImage {
        let img = if img.width() > 512 || img.height() > 512 {
            image::imageops::thumbnail(img, 512.min(img.width()), 512.min(img.height()))
        } else {
            img.clone()
        };
        TextureImage {
            w: img.width().max(1) as usize,
            h: img.height().max(1) as usize,
            px: img
                .pixels()
                .map(|p| p.0.map(|c| c as f32 / 255.0))
                .collect(),
        }
    }

    /// Tiled sample at texture coordinates (one tile per unit).
    #[inline]
    fn sample(&self, x: f32, y: f32) -> [f32; 3] {
        let u = ((x - ffloor(x)) * self.w as f32) as usize;
        let v = ((1.0 - (y - ffloor(y))) * self.h as f32) as usize;
        self.px
            .get(v.min(self.h - 1) * self.w + u.min(self.w - 1))
            .copied()
            .unwrap_or([0.5; 3])
    }
}

// ---------------------------------------------------------------------------------------------
// Scene
// ---------------------------------------------------------------------------------------------

/// Most boxes a scene holds (furniture and pillars; the generator makes at most 15).
const MAX_BOXES: usize = 32;

#[derive(Debug, Clone, Copy)]
struct Aabb {
    lo: [f32; 3],
    hi: [f32; 3],
    /// Material of the side faces and of the top/bottom faces.
    side: u16,
    top: u16,
}

/// Lighting of one rendered frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lighting {
    /// Global gain (camera exposure).
    pub exposure: f32,
    /// Gain of each ceiling light (up to 3; missing lights are ignored).
    pub light_gains: [f32; 3],
}

impl Default for Lighting {
    fn default() -> Self {
        Lighting {
            exposure: 1.0,
            light_gains: [1.0; 3],
        }
    }
}

/// A procedural indoor room with furniture, lights and materials.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Room extent `[L, D, H]` in metres (the room is `[0, L] x [0, D] x [0, H]`, z up).
    pub room: [f64; 3],
    /// Region the camera may occupy: `(min corner, max corner)`; no furniture overlaps it.
    pub camera_region: ([f64; 3], [f64; 3]),
    boxes: Vec<Aabb>,
    /// Room face materials: x-, x+, y-, y+, floor, ceiling.
    room_mats: [u16; 6],
    materials: Vec<Material>,
    images: Vec<TextureImage>,
    lights: Vec<([f32; 3], f32)>,
    ambient: f32,
}

/// Errors of the synthetic generator.
#[derive(Debug)]
pub enum SynthError {
    /// Writing the sequence failed.
    Dataset(DatasetError),
    /// Bad configuration.
    Config(String),
}

impl fmt::Display for SynthError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SynthError::Dataset(e) => write!(f, "{e}"),
            SynthError::Config(m) => write!(f, "synth configuration: {m}"),
        }
    }
}

impl std::error::Error for SynthError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            SynthError::Dataset(e) => Some(e),
            SynthError::Config(_) => None,
        }
    }
}

impl From<DatasetError> for SynthError {
    fn from(e: DatasetError) -> Self {
        SynthError::Dataset(e)
    }
}

/// Loads every `png`/`jpg`/`jpeg` image of `dir` (sorted by name) as a texture.
pub fn load_textures(dir: &Path) -> Result<Vec<RgbImage>, DatasetError> {
    let files = dataset::list_images(dir)?;
    if files.is_empty() {
        return Err(DatasetError::Missing {
            path: dir.to_path_buf(),
            what: "png/jpg texture images".into(),
        });
    }
    files
        .par_iter()
        .map(|p| {
            image::open(p)
                .map(|i| i.into_rgb8())
                .map_err(|source| DatasetError::Image {
                    path: p.clone(),
                    source,
                })
        })
        .collect()
}

fn boxes_overlap_xy(a_lo: [f64; 2], a_hi: [f64; 2], b_lo: [f64; 2], b_hi: [f64; 2]) -> bool {
    a_lo[0] < b_hi[0] && b_lo[0] < a_hi[0] && a_lo[1] < b_hi[1] && b_lo[1] < a_hi[1]
}

impl Scene {
    /// A random room from `seed`, with procedural textures only.
    pub fn new(seed: u64) -> Scene {
        Self::with_textures(seed, &[])
    }

    /// A random room from `seed`; about half of the surfaces use one of `textures` (tiled).
    pub fn with_textures(seed: u64, textures: &[RgbImage]) -> Scene {
        let mut rng = SplitMix64::new(seed ^ 0x05EE_D0F5_CE4E);
        let images: Vec<TextureImage> = textures.iter().map(TextureImage::from_rgb).collect();
        let n_img = images.len();
        let room = [
            rng.range(5.0, 9.0),
            rng.range(4.5, 7.0),
            rng.range(2.5, 3.2),
        ];
        let region_lo = [room[0] * 0.32, room[1] * 0.32, 1.1];
        let region_hi = [room[0] * 0.68, room[1] * 0.68, 1.8];
        let mut materials = Vec::new();
        let add = |m: Material, mats: &mut Vec<Material>| {
            mats.push(m);
            (mats.len() - 1) as u16
        };
        let wall_hint = Some(if rng.f64() < 0.5 {
            Pattern::Bricks
        } else {
            Pattern::Noise
        });
        let room_mats = [
            add(Material::random(&mut rng, n_img, wall_hint), &mut materials),
            add(Material::random(&mut rng, n_img, wall_hint), &mut materials),
            add(Material::random(&mut rng, n_img, wall_hint), &mut materials),
            add(Material::random(&mut rng, n_img, wall_hint), &mut materials),
            add(
                Material::random(&mut rng, n_img, Some(Pattern::Wood)),
                &mut materials,
            ),
            add(
                Material::random(&mut rng, n_img, Some(Pattern::Noise)),
                &mut materials,
            ),
        ];
        // Furniture and occluders keep 0.5 m away from the camera region.
        let keep_lo = [region_lo[0] - 0.5, region_lo[1] - 0.5];
        let keep_hi = [region_hi[0] + 0.5, region_hi[1] + 0.5];
        let mut boxes = Vec::new();
        let n_furniture = 6 + rng.below(7);
        let n_pillars = 1 + rng.below(3);
        let mut tries = 0;
        while boxes.len() < n_furniture + n_pillars && tries < 400 {
            tries += 1;
            let pillar = boxes.len() >= n_furniture;
            let (sx, sy, z0, z1) = if pillar {
                let w = rng.range(0.15, 0.35);
                (w, w, 0.0, room[2])
            } else if rng.f64() < 0.25 {
                // wall shelf / cabinet
                let z0 = rng.range(0.9, 1.6);
                (
                    rng.range(0.3, 1.5),
                    rng.range(0.2, 0.45),
                    z0,
                    z0 + rng.range(0.05, 0.7),
                )
            } else {
                (
                    rng.range(0.3, 1.6),
                    rng.range(0.3, 1.6),
                    0.0,
                    rng.range(0.4, 2.2),
                )
            };
            let (sx, sy) = if rng.f64() < 0.5 { (sx, sy) } else { (sy, sx) };
            let x0 = rng.range(0.02, room[0] - sx - 0.02);
            let y0 = rng.range(0.02, room[1] - sy - 0.02);
            let (lo, hi) = ([x0, y0], [x0 + sx, y0 + sy]);
            if boxes_overlap_xy(lo, hi, keep_lo, keep_hi) {
                continue;
            }
            let side = add(Material::random(&mut rng, n_img, None), &mut materials);
            let top = if rng.f64() < 0.5 {
                side
            } else {
                add(
                    Material::random(&mut rng, n_img, Some(Pattern::Wood)),
                    &mut materials,
                )
            };
            boxes.push(Aabb {
                lo: [lo[0] as f32, lo[1] as f32, z0 as f32],
                hi: [hi[0] as f32, hi[1] as f32, z1 as f32],
                side,
                top,
            });
        }
        let n_lights = 1 + rng.below(3);
        let lights = (0..n_lights)
            .map(|_| {
                (
                    [
                        rng.range(0.2, 0.8) as f32 * room[0] as f32,
                        rng.range(0.2, 0.8) as f32 * room[1] as f32,
                        room[2] as f32 - 0.15,
                    ],
                    rng.range(1.6, 3.0) as f32 / n_lights as f32,
                )
            })
            .collect();
        Scene {
            room,
            camera_region: (region_lo, region_hi),
            boxes,
            room_mats,
            materials,
            images,
            lights,
            ambient: rng.range(0.2, 0.35) as f32,
        }
    }

    /// Renders colour and z-depth (metres) at pose `pose` (camera-to-world) with default lighting.
    pub fn render(
        &self,
        pose: &Isometry3<f64>,
        intr: &Intrinsics,
        w: u32,
        h: u32,
    ) -> (RgbImage, DepthImage) {
        let mut acc = vec![0.0f32; w as usize * h as usize * 3];
        let mut depth = DepthImage::new(w, h);
        self.render_into(
            pose,
            intr,
            w,
            h,
            &Lighting::default(),
            &mut acc,
            Some(&mut depth.data),
        );
        (to_rgb(&acc, w, h, 1.0, 0.0, 0), depth)
    }

    /// Conservative screen rectangles `(box, u0, u1, v0, v1)` of the boxes that may be visible:
    /// boxes entirely behind the camera are dropped; boxes straddling the image plane cover the
    /// whole image.
    fn screen_rects(
        &self,
        pose: &Isometry3<f64>,
        intr: &Intrinsics,
        w: u32,
        h: u32,
    ) -> Vec<(u16, i32, i32, i32, i32)> {
        let inv = pose.inverse();
        let full = (-1, w as i32, -1, h as i32);
        self.boxes
            .iter()
            .enumerate()
            .take(MAX_BOXES)
            .filter_map(|(i, b)| {
                let (mut behind, mut front) = (0, 0);
                let (mut u0, mut u1, mut v0, mut v1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
                for c in 0..8 {
                    let p = nalgebra::Point3::new(
                        if c & 1 == 0 { b.lo[0] } else { b.hi[0] } as f64,
                        if c & 2 == 0 { b.lo[1] } else { b.hi[1] } as f64,
                        if c & 4 == 0 { b.lo[2] } else { b.hi[2] } as f64,
                    );
                    let q = inv * p;
                    if q.z <= 1e-3 {
                        behind += 1;
                        continue;
                    }
                    front += 1;
                    let (u, v) = (intr.fx * q.x / q.z + intr.cx, intr.fy * q.y / q.z + intr.cy);
                    u0 = u0.min(u);
                    u1 = u1.max(u);
                    v0 = v0.min(v);
                    v1 = v1.max(v);
                }
                let r = if front == 0 {
                    return None;
                } else if behind > 0 {
                    full
                } else {
                    let cl = |x: f64, n: u32| x.clamp(-2.0, n as f64 + 1.0) as i32;
                    (
                        cl(u0.floor() - 1.0, w),
                        cl(u1.ceil() + 1.0, w),
                        cl(v0.floor() - 1.0, h),
                        cl(v1.ceil() + 1.0, h),
                    )
                };
                (r.0 <= w as i32 && r.1 >= 0 && r.2 <= h as i32 && r.3 >= 0)
                    .then_some((i as u16, r.0, r.1, r.2, r.3))
            })
            .collect()
    }

    /// Adds the shaded colour (linear, 0..1) of every pixel to `acc` (`3 w h` floats) and, if
    /// given, writes the z-depth to `depth`. Rows are rendered in parallel.
    #[allow(clippy::too_many_arguments)]
    pub fn render_into(
        &self,
        pose: &Isometry3<f64>,
        intr: &Intrinsics,
        w: u32,
        h: u32,
        light: &Lighting,
        acc: &mut [f32],
        depth: Option<&mut [f32]>,
    ) {
        let (wu, hu) = (w as usize, h as usize);
        if wu == 0 || hu == 0 || acc.len() < wu * hu * 3 {
            return;
        }
        let r = pose.rotation.to_rotation_matrix();
        let m = r.matrix();
        let rm: [[f32; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)] as f32));
        let o = pose.translation.vector;
        let o = [o.x as f32, o.y as f32, o.z as f32];
        let (fx, fy, cx, cy) = (
            intr.fx as f32,
            intr.fy as f32,
            intr.cx as f32,
            intr.cy as f32,
        );
        let lights: Vec<([f32; 3], f32)> = self
            .lights
            .iter()
            .enumerate()
            .map(|(k, &(p, i))| (p, i * light.light_gains.get(k).copied().unwrap_or(1.0)))
            .collect();
        let exposure = light.exposure;
        let room_hi = self.room.map(|x| x as f32);
        let rects = self.screen_rects(pose, intr, w, h);
        let shade_row = |v: usize, acc_row: &mut [f32], depth_row: Option<&mut [f32]>| {
            let yc = (v as f32 - cy) / fy;
            let mut depth_row = depth_row;
            // Boxes whose screen rectangle covers this row.
            let mut row_boxes = [(0u16, 0i32, 0i32); MAX_BOXES];
            let mut n_row = 0;
            for &(bi, u0, u1, v0, v1) in &rects {
                if (v as i32) >= v0 && (v as i32) <= v1 && n_row < MAX_BOXES {
                    row_boxes[n_row] = (bi, u0, u1);
                    n_row += 1;
                }
            }
            let row_boxes = &row_boxes[..n_row];
            for u in 0..wu {
                let xc = (u as f32 - cx) / fx;
                let d = [
                    rm[0][0] * xc + rm[0][1] * yc + rm[0][2],
                    rm[1][0] * xc + rm[1][1] * yc + rm[1][2],
                    rm[2][0] * xc + rm[2][1] * yc + rm[2][2],
                ];
                let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
                // Exit of the room box (camera inside).
                let mut best = f32::INFINITY;
                let mut axis = 0usize;
                let mut mat = 0u16;
                for a in 0..3 {
                    let wall = if d[a] > 0.0 { room_hi[a] } else { 0.0 };
                    let t = (wall - o[a]) * inv[a];
                    if t < best {
                        best = t;
                        axis = a;
                        mat = self.room_mats[2 * a + (d[a] > 0.0) as usize];
                    }
                }
                // Furniture (slab test).
                for &(bi, u0, u1) in row_boxes {
                    if (u as i32) < u0 || (u as i32) > u1 {
                        continue;
                    }
                    let b = &self.boxes[bi as usize];
                    let t0x = (b.lo[0] - o[0]) * inv[0];
                    let t1x = (b.hi[0] - o[0]) * inv[0];
                    let t0y = (b.lo[1] - o[1]) * inv[1];
                    let t1y = (b.hi[1] - o[1]) * inv[1];
                    let t0z = (b.lo[2] - o[2]) * inv[2];
                    let t1z = (b.hi[2] - o[2]) * inv[2];
                    let (nx, fxx) = (t0x.min(t1x), t0x.max(t1x));
                    let (ny, fyy) = (t0y.min(t1y), t0y.max(t1y));
                    let (nz, fzz) = (t0z.min(t1z), t0z.max(t1z));
                    let tn = nx.max(ny).max(nz);
                    let tf = fxx.min(fyy).min(fzz);
                    if tn <= tf && tn > 0.0 && tn < best {
                        best = tn;
                        axis = if tn == nx {
                            0
                        } else if tn == ny {
                            1
                        } else {
                            2
                        };
                        mat = if axis == 2 { b.top } else { b.side };
                    }
                }
                let (z, rgb) = if best.is_finite() && best > 0.0 {
                    let p = [o[0] + best * d[0], o[1] + best * d[1], o[2] + best * d[2]];
                    let mut n = [0.0f32; 3];
                    n[axis] = if d[axis] > 0.0 { -1.0 } else { 1.0 };
                    let (s, t) = match axis {
                        0 => (p[1], p[2]),
                        1 => (p[0], p[2]),
                        _ => (p[0], p[1]),
                    };
                    let m = &self.materials[mat as usize];
                    let alb = m.albedo(s, t, &self.images);
                    let detail = 0.86 + 0.28 * value_noise(s * 37.0, t * 37.0, m.seed ^ 7);
                    let mut shade = self.ambient;
                    for (lp, li) in &lights {
                        let l = [lp[0] - p[0], lp[1] - p[1], lp[2] - p[2]];
                        let d2 = l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
                        let ndl = n[0] * l[0] + n[1] * l[1] + n[2] * l[2];
                        if ndl > 0.0 {
                            shade += li * ndl / (d2.sqrt() * (1.0 + 0.08 * d2));
                        }
                    }
                    let k = shade * detail * exposure;
                    (best, [alb[0] * k, alb[1] * k, alb[2] * k])
                } else {
                    (0.0, [0.0; 3])
                };
                if let Some(dr) = depth_row.as_deref_mut() {
                    dr[u] = z;
                }
                acc_row[3 * u] += rgb[0];
                acc_row[3 * u + 1] += rgb[1];
                acc_row[3 * u + 2] += rgb[2];
            }
        };
        let acc = &mut acc[..wu * hu * 3];
        match depth {
            Some(dep) if dep.len() >= wu * hu => acc
                .par_chunks_mut(wu * 3)
                .zip(dep[..wu * hu].par_chunks_mut(wu))
                .enumerate()
                .for_each(|(v, (a, d))| shade_row(v, a, Some(d))),
            _ => acc
                .par_chunks_mut(wu * 3)
                .enumerate()
                .for_each(|(v, a)| shade_row(v, a, None)),
        }
    }
}

/// Converts accumulated linear colour (divided by `div`) to 8-bit sRGB-ish, adding Gaussian
/// noise of standard deviation `noise` (0..1 units) seeded by `noise_seed`.
fn to_rgb(acc: &[f32], w: u32, h: u32, div: f32, noise: f32, noise_seed: u64) -> RgbImage {
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

// ---------------------------------------------------------------------------------------------
// Camera motion
// ---------------------------------------------------------------------------------------------

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
    /// Random segments of 1.5 to 4 s of all the others.
    #[default]
    Mixed,
}

impl MotionProfile {
    /// All profiles, `mixed` last.
    pub const ALL: [MotionProfile; 7] = [
        MotionProfile::Static,
        MotionProfile::Pan,
        MotionProfile::Shaky,
        MotionProfile::Walk,
        MotionProfile::Rotate,
        MotionProfile::Bursts,
        MotionProfile::Mixed,
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
                    "unknown motion `{s}` (expected one of: static, pan, shaky, walk, rotate, bursts, mixed)"
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

const SUBSTEPS: usize = 4;

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

/// Generates `n_samples` camera poses at `SUBSTEPS` samples per frame (frame `i` is sample
/// `SUBSTEPS * i`), plus the motion segments.
fn generate_path(
    scene: &Scene,
    profile: MotionProfile,
    fps: f64,
    frames: usize,
    seed: u64,
) -> (Vec<Isometry3<f64>>, Vec<Segment>) {
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
            MotionProfile::Static | MotionProfile::Mixed => {
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

fn interpolate(a: &Isometry3<f64>, b: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    let t = a.translation.vector.lerp(&b.translation.vector, s);
    let r = a.rotation.slerp(&b.rotation, s);
    Isometry3::from_parts(Translation3::from(t), r)
}

// ---------------------------------------------------------------------------------------------
// Sequences
// ---------------------------------------------------------------------------------------------

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

/// The generated camera path of a configuration (camera-to-world per frame) and its segments,
/// without rendering.
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

fn lighting_at(cfg: &SynthConfig, i: usize) -> Lighting {
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

/// Renders one frame `i` of a configuration: colour (with blur/noise) and depth.
fn render_frame(
    cfg: &SynthConfig,
    scene: &Scene,
    samples: &[Isometry3<f64>],
    i: usize,
) -> (RgbImage, DepthImage) {
    let (w, h) = (cfg.width, cfg.height);
    let intr = cfg.intrinsics();
    let light = lighting_at(cfg, i);
    let mut acc = vec![0.0f32; w as usize * h as usize * 3];
    let mut depth = DepthImage::new(w, h);
    let c = i * SUBSTEPS;
    scene.render_into(
        &samples[c],
        &intr,
        w,
        h,
        &light,
        &mut acc,
        Some(&mut depth.data),
    );
    let mut div = 1.0;
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
    let rgb = to_rgb(
        &acc,
        w,
        h,
        div,
        cfg.noise,
        mix64(cfg.seed ^ (i as u64 + 1).wrapping_mul(0xA5A5_5A5A)),
    );
    (rgb, depth)
}

/// Renders a whole sequence into `out` (TUM layout, depth_scale 1000, camera-to-world
/// ground truth) plus `synth.json` describing the configuration and segments.
pub fn render_sequence(cfg: &SynthConfig, out: &Path) -> Result<SynthSummary, SynthError> {
    if cfg.frames == 0 || cfg.width < 2 || cfg.height < 2 {
        return Err(SynthError::Config(format!(
            "need frames > 0 and at least 2x2 pixels (got {} frames, {}x{})",
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
    let scene = Scene::with_textures(cfg.seed, &textures);
    let (samples, segments) = generate_path(&scene, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
    let intr = cfg.intrinsics();
    let mut writer = SequenceWriter::create(out, intr, cfg.rgb_format)?;
    writer.set_header(&format!(
        "LeanGate synthetic sequence: seed {} motion {} {}x{} at {} fps",
        cfg.seed, cfg.motion, cfg.width, cfg.height, cfg.fps
    ));
    let (mut render_s, mut write_s) = (0.0, 0.0);
    let chunk = 8;
    for start in (0..cfg.frames).step_by(chunk) {
        let end = (start + chunk).min(cfg.frames);
        let t0 = Instant::now();
        let rendered: Vec<(RgbImage, DepthImage)> = (start..end)
            .map(|i| render_frame(cfg, &scene, &samples, i))
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
    let meta = serde_json::json!({
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::Sequence;
    use crate::teacher::{score_pair, DepthView, TeacherConfig};

    fn small_cfg(motion: MotionProfile, frames: usize) -> SynthConfig {
        SynthConfig {
            seed: 7,
            frames,
            width: 64,
            height: 48,
            motion,
            ..Default::default()
        }
    }

    #[test]
    fn profile_names_round_trip() {
        for p in MotionProfile::ALL {
            assert_eq!(p.name().parse::<MotionProfile>().unwrap(), p);
        }
        assert!("fly".parse::<MotionProfile>().is_err());
    }

    #[test]
    fn render_is_deterministic() {
        let cfg = SynthConfig {
            blur: true,
            lighting_changes: true,
            ..small_cfg(MotionProfile::Shaky, 12)
        };
        let scene = Scene::new(cfg.seed);
        let (samples, _) = generate_path(&scene, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
        let a = render_frame(&cfg, &scene, &samples, 5);
        let scene2 = Scene::new(cfg.seed);
        let (samples2, _) = generate_path(&scene2, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
        let b = render_frame(&cfg, &scene2, &samples2, 5);
        assert_eq!(a.0.as_raw(), b.0.as_raw());
        assert_eq!(a.1, b.1);
        let other = Scene::new(cfg.seed + 1);
        assert_ne!(other.room, scene.room);
    }

    #[test]
    fn camera_stays_in_region_and_depth_is_valid() {
        for p in MotionProfile::ALL {
            let cfg = small_cfg(p, 240);
            let scene = Scene::new(cfg.seed);
            let (poses, segs) = camera_path(&cfg, &scene);
            assert_eq!(poses.len(), 240);
            assert!(!segs.is_empty());
            let (lo, hi) = scene.camera_region;
            for pose in &poses {
                let t = pose.translation.vector;
                for a in 0..3 {
                    assert!(t[a] > lo[a] - 0.1 && t[a] < hi[a] + 0.1, "{p}: {t:?}");
                }
            }
            let intr = cfg.intrinsics();
            let (_, d) = scene.render(&poses[100], &intr, cfg.width, cfg.height);
            assert!(d.data.iter().all(|&z| z > 0.05 && z < 15.0), "{p}");
        }
    }

    /// The per-row box culling must not change the result: compare with an exhaustive f64
    /// ray cast against the room and every box.
    #[test]
    fn culled_render_matches_brute_force() {
        let cfg = SynthConfig {
            width: 80,
            height: 60,
            ..small_cfg(MotionProfile::Shaky, 120)
        };
        let scene = Scene::new(5);
        let (poses, _) = camera_path(&cfg, &scene);
        let k = cfg.intrinsics();
        let mut box_hits = 0;
        for pose in poses.iter().step_by(10) {
            let (_, d) = scene.render(pose, &k, cfg.width, cfg.height);
            for v in 0..cfg.height {
                for u in 0..cfg.width {
                    let dc = Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
                    let dw = pose.rotation * dc;
                    let o = pose.translation.vector;
                    let mut best = f64::INFINITY;
                    for a in 0..3 {
                        let wall = if dw[a] > 0.0 { scene.room[a] } else { 0.0 };
                        best = best.min((wall - o[a]) / dw[a]);
                    }
                    let room_t = best;
                    for b in &scene.boxes {
                        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
                        for a in 0..3 {
                            let (mut ta, mut tb) = (
                                (b.lo[a] as f64 - o[a]) / dw[a],
                                (b.hi[a] as f64 - o[a]) / dw[a],
                            );
                            if ta > tb {
                                std::mem::swap(&mut ta, &mut tb);
                            }
                            t0 = t0.max(ta);
                            t1 = t1.min(tb);
                        }
                        if t0 <= t1 && t0 > 0.0 {
                            best = best.min(t0);
                        }
                    }
                    if best < room_t {
                        box_hits += 1;
                    }
                    let got = d.data[(v * cfg.width + u) as usize] as f64;
                    assert!(
                        (got - best).abs() < 1e-3 * best,
                        "({u},{v}): {got} vs {best}"
                    );
                }
            }
        }
        assert!(
            box_hits > 1000,
            "scene should show furniture ({box_hits} pixels)"
        );
    }

    #[test]
    fn motion_profiles_have_expected_speeds() {
        let speed = |p: MotionProfile| {
            let cfg = small_cfg(p, 150);
            let scene = Scene::new(3);
            let (poses, _) = camera_path(&cfg, &scene);
            let rot: f64 = poses
                .windows(2)
                .map(|w| (w[0].inverse() * w[1]).rotation.angle())
                .sum();
            rot.to_degrees() / 5.0 // deg/s over 5 s
        };
        let st = speed(MotionProfile::Static);
        let pan = speed(MotionProfile::Pan);
        let rot = speed(MotionProfile::Rotate);
        assert!(st < 2.0, "static {st} deg/s");
        assert!(pan > 10.0 && pan < 40.0, "pan {pan} deg/s");
        assert!(rot > pan, "rotate {rot} vs pan {pan}");
    }

    #[test]
    fn depth_is_consistent_with_poses() {
        let cfg = SynthConfig {
            width: 160,
            height: 120,
            ..small_cfg(MotionProfile::Walk, 30)
        };
        let scene = Scene::new(11);
        let (poses, _) = camera_path(&cfg, &scene);
        let intr = cfg.intrinsics();
        let tc = TeacherConfig::default();
        let view = |p: &Isometry3<f64>| {
            let (_, d) = scene.render(p, &intr, cfg.width, cfg.height);
            DepthView::new(&d, &intr, &tc).unwrap()
        };
        let v0 = view(&poses[0]);
        let same = score_pair(&v0, &poses[0], &view(&poses[0]), &poses[0], 0.1);
        assert_eq!(same.tau, 0.0);
        // a tiny motion: 5 mm sideways
        let tiny = poses[0] * Isometry3::translation(0.005, 0.0, 0.0);
        let s = score_pair(&view(&tiny), &tiny, &v0, &poses[0], 0.1);
        assert!(s.tau < 0.05, "tiny motion tau {}", s.tau);
        // a few frames of walking: still mostly overlapping, and not trivially so
        let s = score_pair(&view(&poses[5]), &poses[5], &v0, &poses[0], 0.1);
        assert!(s.tau > 0.0 && s.tau < 0.5, "walk tau {:?}", s);
    }

    #[test]
    fn written_sequence_loads_back() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = SynthConfig {
            rgb_format: RgbFormat::Jpeg(90),
            lighting_changes: true,
            ..small_cfg(MotionProfile::Mixed, 6)
        };
        let out = dir.path().join("synth");
        let sum = render_sequence(&cfg, &out).unwrap();
        assert_eq!(sum.frames, 6);
        let seq = Sequence::open(&out).unwrap();
        assert_eq!(seq.len(), 6);
        assert!(seq.has_ground_truth());
        assert_eq!(seq.intrinsics, Some(cfg.intrinsics()));
        assert_eq!(seq.load_rgb(3).unwrap().dimensions(), (64, 48));
        let d = seq.load_depth_m(3).unwrap();
        assert!(d.data.iter().all(|&z| z > 0.0));
        assert!(out.join("synth.json").is_file());
        let teacher =
            crate::teacher::Teacher::from_sequence(&seq, &TeacherConfig::default()).unwrap();
        assert_eq!(teacher.score(2, 2).tau, 0.0);
    }

    #[test]
    fn image_textures_are_used() {
        let dir = tempfile::tempdir().unwrap();
        let tex = dir.path().join("tex");
        std::fs::create_dir(&tex).unwrap();
        // a pure red texture: some surfaces must come out red-dominant
        RgbImage::from_pixel(16, 16, image::Rgb([255, 0, 0]))
            .save(tex.join("red.png"))
            .unwrap();
        let cfg = SynthConfig {
            textures: Some(tex.clone()),
            noise: 0.0,
            ..small_cfg(MotionProfile::Rotate, 3)
        };
        let textures = load_textures(&tex).unwrap();
        let scene = Scene::with_textures(cfg.seed, &textures);
        assert!(scene
            .materials
            .iter()
            .any(|m| matches!(m.pattern, Pattern::Image(0))));
        let out = dir.path().join("seq");
        render_sequence(&cfg, &out).unwrap();
        assert_eq!(Sequence::open(&out).unwrap().len(), 3);
        let empty = dir.path().join("empty");
        std::fs::create_dir(&empty).unwrap();
        assert!(load_textures(&empty).is_err());
    }

    #[test]
    fn bad_config_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = SynthConfig {
            frames: 0,
            ..Default::default()
        };
        assert!(render_sequence(&cfg, dir.path()).is_err());
        let cfg = SynthConfig {
            textures: Some(dir.path().join("nope")),
            ..small_cfg(MotionProfile::Static, 2)
        };
        assert!(render_sequence(&cfg, &dir.path().join("o")).is_err());
    }

    /// Writes a visual sample, not a test: `LEANGATE_SYNTH_SAMPLE=/tmp/x cargo test synth_sample -- --ignored`.
    #[test]
    #[ignore]
    fn synth_sample() {
        let Ok(out) = std::env::var("LEANGATE_SYNTH_SAMPLE") else {
            eprintln!("set LEANGATE_SYNTH_SAMPLE to an output directory");
            return;
        };
        let cfg = SynthConfig {
            frames: 90,
            seed: std::env::var("LEANGATE_SYNTH_SEED")
                .ok()
                .and_then(|s| s.parse().ok())
                .unwrap_or(1),
            blur: true,
            lighting_changes: true,
            ..Default::default()
        };
        let sum = render_sequence(&cfg, Path::new(&out)).unwrap();
        eprintln!("{:?}", sum.segments);
    }

    /// Timing helper, not a test: `cargo test --release synth_speed -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn synth_speed() {
        let cfg = SynthConfig {
            frames: 60,
            ..Default::default()
        };
        let scene = Scene::new(cfg.seed);
        let (samples, _) = generate_path(&scene, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
        let t0 = Instant::now();
        for i in 0..cfg.frames {
            let _ = render_frame(&cfg, &scene, &samples, i);
        }
        let r = cfg.frames as f64 / t0.elapsed().as_secs_f64();
        let dir = tempfile::tempdir().unwrap();
        let sum = render_sequence(&cfg, &dir.path().join("s")).unwrap();
        eprintln!(
            "render only: {r:.1} frames/s at 640x480; render_sequence: render {:.1} fps, with writing {:.1} fps",
            sum.render_fps(),
            sum.total_fps()
        );
    }
}
