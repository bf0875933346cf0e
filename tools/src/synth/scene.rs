//! The scene (room, furniture, lights, materials) and the ray caster.

use image::RgbImage;
use nalgebra::{Isometry3, Vector3};
use rayon::prelude::*;

use super::materials::{Material, Pattern, TextureImage};
use super::noise::{value_noise, SplitMix64};
use super::render::to_rgb;
use crate::dataset::{DepthImage, Intrinsics};

/// Most boxes a scene holds (furniture and pillars; the generator makes at most 15).
const MAX_BOXES: usize = 32;

#[derive(Debug, Clone, Copy)]
pub(crate) struct Aabb {
    pub(crate) lo: [f32; 3],
    pub(crate) hi: [f32; 3],
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
    pub(crate) boxes: Vec<Aabb>,
    /// Room face materials: x-, x+, y-, y+, floor, ceiling.
    room_mats: [u16; 6],
    pub(crate) materials: Vec<Material>,
    images: Vec<TextureImage>,
    lights: Vec<([f32; 3], f32)>,
    ambient: f32,
}

fn boxes_overlap_xy(a_lo: [f64; 2], a_hi: [f64; 2], b_lo: [f64; 2], b_hi: [f64; 2]) -> bool {
    a_lo[0] < b_hi[0] && b_lo[0] < a_hi[0] && a_lo[1] < b_hi[1] && b_lo[1] < a_hi[1]
}

impl Scene {
    /// Adds a textured cube of half size `half` centred at `centre` (metres), the object an
    /// `orbit` path circles (its random material from `seed`).
    pub(crate) fn add_object(&mut self, centre: Vector3<f64>, half: f64, seed: u64) {
        if self.boxes.len() >= MAX_BOXES {
            return;
        }
        let mut rng = SplitMix64::new(seed ^ 0x00B1_EC70);
        self.materials
            .push(Material::random(&mut rng, self.images.len(), None));
        let side = (self.materials.len() - 1) as u16;
        let (lo, hi) = (centre.add_scalar(-half), centre.add_scalar(half));
        self.boxes.push(Aabb {
            lo: [lo.x as f32, lo.y as f32, lo.z as f32],
            hi: [hi.x as f32, hi.y as f32, hi.z as f32],
            side,
            top: side,
        });
    }

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
        self.render_impl(pose, None, intr, w, h, light, Some(acc), depth);
    }

    /// Writes only the z-depth at `pose` to `depth` (`w h` floats; no shading).
    pub fn render_depth(
        &self,
        pose: &Isometry3<f64>,
        intr: &Intrinsics,
        w: u32,
        h: u32,
        depth: &mut [f32],
    ) {
        let light = Lighting::default();
        self.render_impl(pose, None, intr, w, h, &light, None, Some(depth));
    }

    /// Like [`Scene::render_into`], but row `v` is seen from `row_pose(v)` (a rolling shutter).
    #[allow(clippy::too_many_arguments)]
    pub fn render_into_rows(
        &self,
        row_pose: &(dyn Fn(usize) -> Isometry3<f64> + Sync),
        intr: &Intrinsics,
        w: u32,
        h: u32,
        light: &Lighting,
        acc: &mut [f32],
        depth: Option<&mut [f32]>,
    ) {
        let centre = row_pose(h as usize / 2);
        self.render_impl(&centre, Some(row_pose), intr, w, h, light, Some(acc), depth);
    }

    #[allow(clippy::too_many_arguments)]
    fn render_impl(
        &self,
        pose: &Isometry3<f64>,
        row_pose: Option<&(dyn Fn(usize) -> Isometry3<f64> + Sync)>,
        intr: &Intrinsics,
        w: u32,
        h: u32,
        light: &Lighting,
        acc: Option<&mut [f32]>,
        depth: Option<&mut [f32]>,
    ) {
        let (wu, hu) = (w as usize, h as usize);
        let colour = acc.is_some();
        let acc_ok = acc.as_ref().is_none_or(|a| a.len() >= wu * hu * 3);
        let depth_ok = colour || depth.as_ref().is_some_and(|d| d.len() >= wu * hu);
        if wu == 0 || hu == 0 || !acc_ok || !depth_ok {
            return;
        }
        let setup = |pose: &Isometry3<f64>| {
            let r = pose.rotation.to_rotation_matrix();
            let m = r.matrix();
            let rm: [[f32; 3]; 3] =
                std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)] as f32));
            let o = pose.translation.vector;
            let o = [o.x as f32, o.y as f32, o.z as f32];
            (rm, o)
        };
        let (rm, o) = setup(pose);
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
        let shade_row = |v: usize,
                         acc_row: &mut [f32],
                         depth_row: Option<&mut [f32]>,
                         rm: &[[f32; 3]; 3],
                         o: &[f32; 3],
                         rects: &[(u16, i32, i32, i32, i32)]| {
            let yc = (v as f32 - cy) / fy;
            let mut depth_row = depth_row;
            // Boxes whose screen rectangle covers this row.
            let mut row_boxes = [(0u16, 0i32, 0i32); MAX_BOXES];
            let mut n_row = 0;
            for &(bi, u0, u1, v0, v1) in rects {
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
                if !colour {
                    if let Some(dr) = depth_row.as_deref_mut() {
                        dr[u] = if best.is_finite() && best > 0.0 {
                            best
                        } else {
                            0.0
                        };
                    }
                    continue;
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
        let row = |v: usize, a: &mut [f32], d: Option<&mut [f32]>| match row_pose {
            None => shade_row(v, a, d, &rm, &o, &rects),
            Some(f) => {
                let p = f(v);
                let (rm, o) = setup(&p);
                let rects = self.screen_rects(&p, intr, w, h);
                shade_row(v, a, d, &rm, &o, &rects)
            }
        };
        let Some(acc) = acc else {
            if let Some(dep) = depth {
                dep[..wu * hu]
                    .par_chunks_mut(wu)
                    .enumerate()
                    .for_each(|(v, d)| row(v, &mut [], Some(d)));
            }
            return;
        };
        let acc = &mut acc[..wu * hu * 3];
        match depth {
            Some(dep) if dep.len() >= wu * hu => acc
                .par_chunks_mut(wu * 3)
                .zip(dep[..wu * hu].par_chunks_mut(wu))
                .enumerate()
                .for_each(|(v, (a, d))| row(v, a, Some(d))),
            _ => acc
                .par_chunks_mut(wu * 3)
                .enumerate()
                .for_each(|(v, a)| row(v, a, None)),
        }
    }
}
