//! Surface materials: procedural patterns and tiled texture images.

use std::path::Path;

use image::RgbImage;
use rayon::prelude::*;

use super::noise::{fbm, ffloor, hash2, value_noise, SplitMix64};
use crate::dataset::{self, DatasetError};

#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Pattern {
    Noise,
    Checker,
    Stripes,
    Bricks,
    Wood,
    Image(usize),
}

#[derive(Debug, Clone, Copy)]
pub(crate) struct Material {
    pub(crate) pattern: Pattern,
    c0: [f32; 3],
    c1: [f32; 3],
    /// Pattern cells per metre.
    scale: f32,
    pub(crate) seed: u32,
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
    pub(crate) fn random(
        rng: &mut SplitMix64,
        n_images: usize,
        kind_hint: Option<Pattern>,
    ) -> Material {
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
    pub(crate) fn albedo(&self, s: f32, t: f32, images: &[TextureImage]) -> [f32; 3] {
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
pub(crate) struct TextureImage {
    w: usize,
    h: usize,
    px: Vec<[f32; 3]>,
}

impl TextureImage {
    pub(crate) fn from_rgb(img: &RgbImage) -> TextureImage {
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
    pub(crate) fn sample(&self, x: f32, y: f32) -> [f32; 3] {
        let u = ((x - ffloor(x)) * self.w as f32) as usize;
        let v = ((1.0 - (y - ffloor(y))) * self.h as f32) as usize;
        self.px
            .get(v.min(self.h - 1) * self.w + u.min(self.w - 1))
            .copied()
            .unwrap_or([0.5; 3])
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
