//! The geometric prior: how much of the reference frame the camera has left, measured from the
//! images by chaining frame-to-frame homographies, in the teacher's own terms.
//!
//! MASt3R-SLAM's score S = min(f_m, f_u) is, for a camera that mostly rotates, the overlap of the
//! two views. This module estimates that overlap without depth:
//!
//! 1. every frame is turned into a grey image at the model's input size (the same tensor the
//!    student sees, [`grey_from_tensor`]), halved to [`prior_size`] (the embedded student's
//!    160x120 → 80x60) and made a 3-level pyramid ([`Pyramid::for_prior`]);
//! 2. a grid of points ([`GRID_X`] x [`GRID_Y`]) laid on the previous frame is tracked into the
//!    current one with sparse pyramidal Lucas-Kanade ([`track_with`] and [`LK_PRIOR`]: 7x7
//!    window, up to 5 Gauss-Newton iterations per level);
//! 3. a homography is fitted to the tracks ([`fit_homography`]: adaptive RANSAC over 4-point
//!    samples with a fixed seed, 1-pixel inlier threshold, then a least-squares refit on the
//!    inliers);
//! 4. the frame-to-frame homographies are chained from the reference (the last kept frame) to the
//!    current frame ([`Chain`], kept by the element's [`Tracker`]), so the motion may grow far
//!    beyond what one LK step can follow;
//! 5. the chained homography is scored like the teacher scores a pair ([`raster_tau`], on the
//!    prior's picture): every pixel of the current frame is mapped into the reference and rounded
//!    to the nearest pixel; `f_m` = the fraction that lands inside, `f_u` = the fraction of the
//!    reference's pixels hit at least once, `tau_geo = 1 - min(f_m, f_u)`. Rounding matters: under
//!    roll the nearest-pixel map hits fewer distinct pixels, exactly as in the teacher.
//!
//! `tau_geo` ignores depth, so it misses parallax and the teacher's 3-D distance check; the model
//! says how to combine it with the student's utility ([`Fusion`], metadata `leangate.geometry`).
//! When tracking fails (too few tracked points or inliers, a degenerate fit) the chain is lost
//! until the next keep and the element uses the student's utility alone.
//!
//! `leangate eval`'s `motion` baseline uses the same pyramid and the classic LK settings
//! ([`track`], [`LK_CLASSIC`]: 9x9 window, up to 10 iterations), its `overlap` baseline and
//! `leangate geometry` the same prior ([`Pyramid::for_prior`], [`frame_homography`], [`Chain`]).

/// The prior halves the model's picture down to this width at least ([`Pyramid::for_prior`]).
pub const PRIOR_MIN_W: usize = 64;

/// Pyramid levels (level 0 = the full image).
pub const LEVELS: usize = 3;
const HALF_WIN: i32 = 4;
const ITERS: usize = 10;
/// Grid of points the prior tracks per frame (on the [`prior_size`] picture).
pub const GRID_X: usize = 8;
pub const GRID_Y: usize = 6;
/// RANSAC iterations and inlier threshold (pixels of the image the tracker runs on).
const RANSAC_ITERS: usize = 64;
const INLIER_PX: f64 = 1.0;
/// Fewest inliers for a usable frame-to-frame homography.
const MIN_INLIERS: usize = 12;

/// A 3x3 matrix, row-major.
pub type Mat3 = [[f64; 3]; 3];

pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

pub fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut c = [[0.0; 3]; 3];
    for (i, row) in c.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

/// Inverse of `m`, or None when it is (numerically) singular.
pub fn mat_inv(m: &Mat3) -> Option<Mat3> {
    let c = |i: usize, j: usize| {
        let (i1, i2) = ((i + 1) % 3, (i + 2) % 3);
        let (j1, j2) = ((j + 1) % 3, (j + 2) % 3);
        m[i1][j1] * m[i2][j2] - m[i1][j2] * m[i2][j1]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    let scale = m.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    if !det.is_finite() || det.abs() <= 1e-12 * scale.powi(3).max(1e-300) {
        return None;
    }
    let mut r = [[0.0; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = c(j, i) / det;
        }
    }
    Some(r)
}

fn apply(h: &Mat3, x: f64, y: f64) -> Option<(f64, f64)> {
    let z = h[2][0] * x + h[2][1] * y + h[2][2];
    (z > 1e-9).then(|| {
        (
            (h[0][0] * x + h[0][1] * y + h[0][2]) / z,
            (h[1][0] * x + h[1][1] * y + h[1][2]) / z,
        )
    })
}

/// One pyramid level: the image and its central-difference gradients.
#[derive(Debug, Clone)]
struct Level {
    w: usize,
    h: usize,
    img: Vec<f32>,
    gx: Vec<f32>,
    gy: Vec<f32>,
}

impl Level {
    fn new(w: usize, h: usize, img: Vec<f32>) -> Level {
        let mut gx = vec![0.0; w * h];
        let mut gy = vec![0.0; w * h];
        // Central differences, the edges against themselves (each row's interior in one loop
        // without per-pixel index clamping, so that the compiler vectorises it).
        for y in 0..h {
            let row = &img[y * w..(y + 1) * w];
            let (up, down) = (
                &img[y.saturating_sub(1) * w..][..w],
                &img[(y + 1).min(h - 1) * w..][..w],
            );
            let gxr = &mut gx[y * w..(y + 1) * w];
            gxr[0] = 0.5 * (row[1.min(w - 1)] - row[0]);
            if w > 1 {
                gxr[w - 1] = 0.5 * (row[w - 1] - row[w - 2]);
                for (g, (l, r)) in gxr[1..w - 1]
                    .iter_mut()
                    .zip(row[..w - 2].iter().zip(&row[2..]))
                {
                    *g = 0.5 * (r - l);
                }
            }
            for (g, (u, d)) in gy[y * w..(y + 1) * w].iter_mut().zip(up.iter().zip(down)) {
                *g = 0.5 * (d - u);
            }
        }
        Level { w, h, img, gx, gy }
    }
}

/// The bilinear sample of `v` at `(x, y)`, clamped to the image: what [`window_rows`] gives
/// at each pixel of a window (the tests compare them).
#[cfg(test)]
fn sample(v: &[f32], w: usize, h: usize, x: f32, y: f32) -> f32 {
    let x = x.clamp(0.0, (w - 1) as f32);
    let y = y.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (x as usize, y as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let a = v[y0 * w + x0] * (1.0 - fx) + v[y0 * w + x1] * fx;
    let b = v[y1 * w + x0] * (1.0 - fx) + v[y1 * w + x1] * fx;
    a * (1.0 - fy) + b * fy
}

/// `img` (`w` x `h`) halved by 2x2 means (each side at least 1 pixel: a side of 1 is repeated;
/// an odd last row or column of a longer side is left out).
fn half(img: &[f32], w: usize, h: usize) -> (Vec<f32>, usize, usize) {
    let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
    let mut out = vec![0.0; nw * nh];
    if w >= 2 && h >= 2 {
        // Every 2x2 block inside (an odd last row or column is left out): no clamping.
        for (y, o) in out.chunks_exact_mut(nw).enumerate() {
            let (r0, r1) = (
                &img[2 * y * w..][..2 * nw],
                &img[(2 * y + 1) * w..][..2 * nw],
            );
            for ((o, a), b) in o.iter_mut().zip(r0.chunks_exact(2)).zip(r1.chunks_exact(2)) {
                *o = 0.25 * (a[0] + a[1] + b[0] + b[1]);
            }
        }
        return (out, nw, nh);
    }
    for y in 0..nh {
        let (y0, y1) = ((2 * y).min(h - 1), (2 * y + 1).min(h - 1));
        for x in 0..nw {
            let (x0, x1) = ((2 * x).min(w - 1), (2 * x + 1).min(w - 1));
            out[y * nw + x] =
                0.25 * (img[y0 * w + x0] + img[y0 * w + x1] + img[y1 * w + x0] + img[y1 * w + x1]);
        }
    }
    (out, nw, nh)
}

/// The size of the picture the prior works on for a `w` x `h` model input: halved while the half
/// is at least [`PRIOR_MIN_W`] pixels wide (160x120 → 80x60; 64x48 stays).
pub fn prior_size(w: usize, h: usize) -> (usize, usize) {
    let (mut w, mut h) = (w, h);
    while w / 2 >= PRIOR_MIN_W && h >= 2 {
        (w, h) = ((w / 2).max(1), (h / 2).max(1));
    }
    (w, h)
}

/// A grey image pyramid (level 0 = the image), f32, with gradients.
#[derive(Debug, Clone)]
pub struct Pyramid {
    levels: Vec<Level>,
}

impl Pyramid {
    /// Pyramid of a `w` x `h` grey image (row-major, any scale of grey values). Each level
    /// halves the sides (at least 1 pixel). A `grey` whose length is not `w * h` (or an empty
    /// size) gives a 1x1 black pyramid, which nothing can be tracked in.
    pub fn new(grey: Vec<f32>, w: usize, h: usize) -> Pyramid {
        let (w, h, img) = if w == 0 || h == 0 || grey.len() != w * h {
            (1, 1, vec![0.0])
        } else {
            (w, h, grey)
        };
        let mut levels = vec![Level::new(w, h, img)];
        for _ in 1..LEVELS {
            let p = levels.last().unwrap();
            let (img, nw, nh) = half(&p.img, p.w, p.h);
            levels.push(Level::new(nw, nh, img));
        }
        Pyramid { levels }
    }

    /// Pyramid of a `u8` grey image.
    pub fn from_u8(grey: &[u8], w: usize, h: usize) -> Pyramid {
        Pyramid::new(grey.iter().map(|&g| g as f32).collect(), w, h)
    }

    /// The pyramid the geometric prior tracks on: the grey picture halved to [`prior_size`], then
    /// [`Pyramid::new`]. A malformed picture gives the 1x1 black pyramid.
    pub fn for_prior(grey: Vec<f32>, w: usize, h: usize) -> Pyramid {
        let (mut g, mut cw, mut ch) = (grey, w, h);
        if w > 0 && h > 0 && g.len() == w * h {
            let target = prior_size(w, h);
            while (cw, ch) != target {
                (g, cw, ch) = half(&g, cw, ch);
            }
        }
        Pyramid::new(g, cw, ch)
    }

    pub fn width(&self) -> usize {
        self.levels[0].w
    }

    pub fn height(&self) -> usize {
        self.levels[0].h
    }
}

/// Track point `p` (level-0 coordinates) from `a` to `b` with pyramidal Lucas-Kanade. Returns
/// the new position, or None when the point is lost (textureless window, divergence, left the
/// image).
pub fn track(a: &Pyramid, b: &Pyramid, p: (f32, f32)) -> Option<(f32, f32)> {
    track_with(a, b, p, &LK_CLASSIC)
}

/// Settings of the Lucas-Kanade tracker: the window's half side, the most Gauss-Newton iterations
/// per level, and the step (pixels, squared) below which a level stops.
#[derive(Debug, Clone, Copy)]
pub struct Lk {
    pub half_win: usize,
    pub iters: usize,
    pub stop_sq: f32,
}

/// [`track`]'s settings: 9x9 window, up to 10 iterations, stop below 0.01 pixel.
pub const LK_CLASSIC: Lk = Lk {
    half_win: HALF_WIN as usize,
    iters: ITERS,
    stop_sq: 1e-4,
};

/// The prior's settings (on the 80x60 picture of the embedded student): 7x7 window, up to 5
/// iterations per level, stop below 0.05 pixel. About 8x cheaper than [`LK_CLASSIC`] on
/// 160x120 with the same agreement with the teacher (`training/experiments/NOTEBOOK.md`).
pub const LK_PRIOR: Lk = Lk {
    half_win: 3,
    iters: 5,
    stop_sq: 0.0025,
};

/// [`track`] with the settings `lk` (a `half_win` above 4 is taken as 4).
///
/// Windows up to 7 wide (the prior's [`LK_PRIOR`]) are held as rows of 8 lanes, the lanes past
/// the side zero in the gradient windows, so the sums over a window run lane by lane and the
/// lanes are added at the end (a vector instruction per row instead of one addition per sample);
/// the samples are those of [`window_rows`]. On x86-64 CPUs with AVX2 the same code is compiled
/// for AVX2 (the same results: no fused multiply-add, the lanes added in one order). Wider
/// windows add their sums sample by sample ([`track_lanes`]).
pub fn track_with(a: &Pyramid, b: &Pyramid, p: (f32, f32), lk: &Lk) -> Option<(f32, f32)> {
    let hw = lk.half_win.min(HALF_WIN as usize);
    if hw > 3 {
        return track_lanes::<16, true>(a, b, p, lk, hw);
    }
    #[cfg(target_arch = "x86_64")]
    if crate::preprocess::has_avx2() {
        // SAFETY: the CPU has AVX2 and FMA (checked just above).
        return unsafe { track_avx2(a, b, p, lk, hw) };
    }
    track_lanes::<8, false>(a, b, p, lk, hw)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn track_avx2(
    a: &Pyramid,
    b: &Pyramid,
    p: (f32, f32),
    lk: &Lk,
    hw: usize,
) -> Option<(f32, f32)> {
    track_lanes::<8, false>(a, b, p, lk, hw)
}

/// Rows of a window, `L` lanes each (up to the largest side's rows).
type Rows<const L: usize> = [[f32; L]; 2 * HALF_WIN as usize + 1];

/// The lanes of `v` added in a fixed order (the same on every CPU).
#[inline(always)]
fn lane_sum<const L: usize>(v: &[f32; L]) -> f32 {
    v.iter().sum()
}

/// The sum of `x · y` over a window's first `side` rows and lanes: lane by lane, the lanes added
/// at the end (lanes past the side must be zero in `x` or `y`), or (`SEQUENTIAL`) sample by
/// sample in row order.
#[inline(always)]
fn window_dot<const L: usize, const SEQUENTIAL: bool>(
    x: &Rows<L>,
    y: &Rows<L>,
    side: usize,
) -> f32 {
    if SEQUENTIAL {
        let mut s = 0.0f32;
        for (xr, yr) in x.iter().zip(y).take(side) {
            for (a, b) in xr[..side].iter().zip(&yr[..side]) {
                s += a * b;
            }
        }
        s
    } else {
        let mut s = [0.0f32; L];
        for (xr, yr) in x.iter().zip(y).take(side) {
            for c in 0..L {
                s[c] += xr[c] * yr[c];
            }
        }
        lane_sum(&s)
    }
}

/// The tracker of [`track_with`] on windows of `L` lanes. `SEQUENTIAL`: each window's sums
/// added sample by sample in row order instead of lane by lane, as for the wider windows of
/// [`LK_CLASSIC`] (the `motion` baseline of `leangate eval`, whose budget search moves its keeps
/// with the last bit of a sum: its documented figures were measured with these sums).
#[inline(always)]
fn track_lanes<const L: usize, const SEQUENTIAL: bool>(
    a: &Pyramid,
    b: &Pyramid,
    p: (f32, f32),
    lk: &Lk,
    hw: usize,
) -> Option<(f32, f32)> {
    let side = 2 * hw + 1;
    let mut d = (0.0f32, 0.0f32);
    let zero = [[0.0f32; L]; 2 * HALF_WIN as usize + 1];
    let (mut ti, mut tgx, mut tgy, mut cur, mut diff) = (zero, zero, zero, zero, zero);
    for l in (0..a.levels.len().min(b.levels.len())).rev() {
        let la = &a.levels[l];
        let lb = &b.levels[l];
        let s = (1u32 << l) as f32;
        let (px, py) = (p.0 / s, p.1 / s);
        if l + 1 < a.levels.len() {
            d = (d.0 * 2.0, d.1 * 2.0);
        }
        window_rows::<L>(&la.img, la.w, la.h, px, py, hw, &mut ti);
        window_rows::<L>(&la.gx, la.w, la.h, px, py, hw, &mut tgx);
        window_rows::<L>(&la.gy, la.w, la.h, px, py, hw, &mut tgy);
        // Lanes past the side carry no weight: their gradients are zero.
        for r in 0..side {
            tgx[r][side..].fill(0.0);
            tgy[r][side..].fill(0.0);
        }
        let dot = window_dot::<L, SEQUENTIAL>;
        let (gxx, gxy, gyy) = (
            dot(&tgx, &tgx, side),
            dot(&tgx, &tgy, side),
            dot(&tgy, &tgy, side),
        );
        let det = gxx * gyy - gxy * gxy;
        if det.is_nan() || det < 1e-3 * (gxx + gyy).max(1e-6) || gxx + gyy < 1.0 {
            return None;
        }
        for _ in 0..lk.iters {
            window_rows::<L>(&lb.img, lb.w, lb.h, px + d.0, py + d.1, hw, &mut cur);
            for (dr, (tr, cr)) in diff.iter_mut().zip(ti.iter().zip(&cur)).take(side) {
                for c in 0..L {
                    dr[c] = tr[c] - cr[c];
                }
            }
            let (bx, by) = (dot(&diff, &tgx, side), dot(&diff, &tgy, side));
            let dx = (gyy * bx - gxy * by) / det;
            let dy = (gxx * by - gxy * bx) / det;
            d = (d.0 + dx, d.1 + dy);
            if !(d.0.is_finite() && d.1.is_finite()) {
                return None;
            }
            if dx * dx + dy * dy < lk.stop_sq {
                break;
            }
        }
    }
    let q = (p.0 + d.0, p.1 + d.1);
    let (w, h) = (a.width() as f32, a.height() as f32);
    (q.0 >= 0.0 && q.1 >= 0.0 && q.0 <= w - 1.0 && q.1 <= h - 1.0).then_some(q)
}

/// Bilinear samples of `v` on the (2 hw + 1)^2 window centred at `(cx, cy)`, into rows of `L`
/// lanes (`L` > the side): the first `2 hw + 1` lanes of the first `2 hw + 1` rows are the
/// window's samples, those of [`sample`] at each pixel (inside the image one fractional offset
/// serves the whole window, so its weights are computed once: the same up to how a pixel's
/// coordinate rounds).
/// Inside the image all `L` lanes of a row are interpolated at once (lanes past the side hold
/// samples of pixels beyond the window, or zero near the right edge; the caller ignores them);
/// a window that touches the border is sampled with clamping, the clamped columns and rows
/// computed once per window.
#[inline(always)]
fn window_rows<const L: usize>(
    v: &[f32],
    w: usize,
    h: usize,
    cx: f32,
    cy: f32,
    hw: usize,
    out: &mut Rows<L>,
) {
    let side = 2 * hw + 1;
    let (x, y) = (cx - hw as f32, cy - hw as f32);
    if x >= 0.0 && y >= 0.0 && (x as usize) + side < w && (y as usize) + side < h {
        let (x0, y0) = (x as usize, y as usize);
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let mut across = [[0.0f32; L]; 2 * HALF_WIN as usize + 2];
        let mut near_edge = [0.0f32; 2 * 16 + 1];
        for (r, acc) in across.iter_mut().enumerate().take(side + 1) {
            let start = (y0 + r) * w + x0;
            let src: &[f32] = if x0 + L < w {
                &v[start..start + L + 1]
            } else {
                near_edge[..side + 1].copy_from_slice(&v[start..start + side + 1]);
                &near_edge[..L + 1]
            };
            let left: &[f32; L] = src[..L].try_into().unwrap();
            let right: &[f32; L] = src[1..L + 1].try_into().unwrap();
            for c in 0..L {
                acc[c] = left[c] * (1.0 - fx) + right[c] * fx;
            }
        }
        for r in 0..side {
            let (a, b) = (&across[r], &across[r + 1]);
            for c in 0..L {
                out[r][c] = a[c] * (1.0 - fy) + b[c] * fy;
            }
        }
    } else {
        // [`sample`] per pixel, its clamping and weights per column and per row.
        let clamp = |t: f32, n: usize| {
            let t = t.clamp(0.0, (n - 1) as f32);
            let i = t as usize;
            (i, (i + 1).min(n - 1), t - i as f32)
        };
        let mut cols = [(0usize, 0usize, 0.0f32); 2 * HALF_WIN as usize + 1];
        for (c, col) in cols.iter_mut().enumerate().take(side) {
            *col = clamp(x + c as f32, w);
        }
        for (r, row) in out.iter_mut().enumerate().take(side) {
            let (y0, y1, fy) = clamp(y + r as f32, h);
            *row = [0.0; L];
            for (o, &(x0, x1, fx)) in row.iter_mut().zip(&cols[..side]) {
                let a = v[y0 * w + x0] * (1.0 - fx) + v[y0 * w + x1] * fx;
                let b = v[y1 * w + x0] * (1.0 - fx) + v[y1 * w + x1] * fx;
                *o = a * (1.0 - fy) + b * fy;
            }
        }
    }
}

/// An `nx` x `ny` grid of cell centres over a `w` x `h` image.
pub fn grid(w: usize, h: usize, nx: usize, ny: usize) -> Vec<(f32, f32)> {
    let mut pts = Vec::with_capacity(nx * ny);
    for gy in 0..ny {
        for gx in 0..nx {
            pts.push((
                (gx as f32 + 0.5) * w as f32 / nx as f32,
                (gy as f32 + 0.5) * h as f32 / ny as f32,
            ));
        }
    }
    pts
}

/// Solve the n x n system `a x = b` (row-major `a`, partial pivoting); None when singular.
pub(crate) fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    for c in 0..N {
        let p = (c..N).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if a[p][c].is_nan() || a[p][c].abs() <= 1e-12 {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        let pivot = a[c];
        for r in c + 1..N {
            let f = a[r][c] / pivot[c];
            for (x, p) in a[r][c..].iter_mut().zip(&pivot[c..]) {
                *x -= f * p;
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = [0.0; N];
    for r in (0..N).rev() {
        let s: f64 = (r + 1..N).map(|k| a[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Least-squares homography (h33 = 1) mapping `src[i]` to `dst[i]` over the indices `idx`, in
/// coordinates normalised by `(c, s)` (centre, scale) for conditioning.
fn ls_homography(
    src: &[(f64, f64)],
    dst: &[(f64, f64)],
    idx: &[usize],
    c: (f64, f64),
    s: f64,
) -> Option<Mat3> {
    if idx.len() < 4 {
        return None;
    }
    let mut ata = [[0.0; 8]; 8];
    let mut atb = [0.0; 8];
    for &i in idx {
        let (x, y) = ((src[i].0 - c.0) / s, (src[i].1 - c.1) / s);
        let (u, v) = ((dst[i].0 - c.0) / s, (dst[i].1 - c.1) / s);
        let rows = [
            ([x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y], u),
            ([0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y], v),
        ];
        for (r, t) in rows {
            for j in 0..8 {
                atb[j] += r[j] * t;
                for k in 0..8 {
                    ata[j][k] += r[j] * r[k];
                }
            }
        }
    }
    let h = solve(ata, atb)?;
    let hn = [[h[0], h[1], h[2]], [h[3], h[4], h[5]], [h[6], h[7], 1.0]];
    // Undo the normalisation: H = T^-1 Hn T with T = [1/s 0 -cx/s; 0 1/s -cy/s; 0 0 1].
    let t = [
        [1.0 / s, 0.0, -c.0 / s],
        [0.0, 1.0 / s, -c.1 / s],
        [0.0, 0.0, 1.0],
    ];
    let ti = [[s, 0.0, c.0], [0.0, s, c.1], [0.0, 0.0, 1.0]];
    let m = mat_mul(&ti, &mat_mul(&hn, &t));
    m.iter().flatten().all(|v| v.is_finite()).then_some(m)
}

/// Fit a homography mapping `src` to `dst` (RANSAC with a fixed seed, then least squares on
/// the inliers). None with fewer than [`MIN_INLIERS`] inliers or a degenerate fit.
pub fn fit_homography(src: &[(f32, f32)], dst: &[(f32, f32)]) -> Option<(Mat3, usize)> {
    let n = src.len().min(dst.len());
    if n < MIN_INLIERS {
        return None;
    }
    let s: Vec<(f64, f64)> = src[..n].iter().map(|p| (p.0 as f64, p.1 as f64)).collect();
    let d: Vec<(f64, f64)> = dst[..n].iter().map(|p| (p.0 as f64, p.1 as f64)).collect();
    let c = (
        s.iter().map(|p| p.0).sum::<f64>() / n as f64,
        s.iter().map(|p| p.1).sum::<f64>() / n as f64,
    );
    let scale = (s
        .iter()
        .map(|p| ((p.0 - c.0).powi(2) + (p.1 - c.1).powi(2)).sqrt())
        .sum::<f64>()
        / n as f64)
        .max(1e-6);
    let is_inlier = |h: &Mat3, i: usize| {
        apply(h, s[i].0, s[i].1).is_some_and(|q| {
            (q.0 - d[i].0).powi(2) + (q.1 - d[i].1).powi(2) <= INLIER_PX * INLIER_PX
        })
    };
    let inliers_of = |h: &Mat3| -> Vec<usize> { (0..n).filter(|&i| is_inlier(h, i)).collect() };
    let mut rng: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = |m: usize| {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((rng >> 33) as usize) % m
    };
    // Adaptive RANSAC: stop once a better sample than the best so far is unlikely (at most a 0.1 %
    // chance that no all-inlier sample was drawn, at the best inlier ratio seen).
    let (mut best_h, mut best_n, mut needed, mut it) = (None, 0usize, RANSAC_ITERS, 0);
    while it < needed {
        it += 1;
        let mut pick = [0usize; 4];
        for k in 0..4 {
            loop {
                let v = next(n);
                if !pick[..k].contains(&v) {
                    pick[k] = v;
                    break;
                }
            }
        }
        if let Some(h) = ls_homography(&s, &d, &pick, c, scale) {
            let m = (0..n).filter(|&i| is_inlier(&h, i)).count();
            if m > best_n {
                (best_h, best_n) = (Some(h), m);
                let p_all = (m as f64 / n as f64).powi(4);
                needed = if p_all >= 1.0 - 1e-12 {
                    0
                } else {
                    ((0.001f64.ln() / (1.0 - p_all).ln()).ceil() as usize).min(RANSAC_ITERS)
                };
            }
        }
        if best_n == n {
            break;
        }
    }
    if best_n < MIN_INLIERS {
        return None;
    }
    let best = inliers_of(&best_h?);
    let h = ls_homography(&s, &d, &best, c, scale)?;
    let inl = inliers_of(&h);
    (inl.len() >= MIN_INLIERS).then(|| {
        // Normalise h33 to 1 for a stable chain.
        let z = h[2][2];
        let mut m = h;
        if z.abs() > 1e-12 {
            m.iter_mut().flatten().for_each(|v| *v /= z);
        }
        (m, inl.len())
    })
}

/// The teacher's score of a pure image warp: `h_cur_to_ref` maps pixels of the current frame
/// (`w` x `h`) into the reference. Each current pixel is mapped and rounded to the nearest pixel;
/// `f_m` = fraction landing inside the reference, `f_u` = fraction of the reference's pixels hit;
/// returns `(tau, f_m, f_u)` with `tau = 1 - min(f_m, f_u)`. `hit` is scratch space.
pub fn raster_tau(h_cur_to_ref: &Mat3, w: usize, h: usize, hit: &mut Vec<bool>) -> (f64, f64, f64) {
    #[cfg(target_arch = "x86_64")]
    if crate::preprocess::has_avx2() {
        // SAFETY: the CPU has AVX2 and FMA (checked just above).
        return unsafe { raster_tau_avx2(h_cur_to_ref, w, h, hit) };
    }
    raster_tau_body(h_cur_to_ref, w, h, hit)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn raster_tau_avx2(m: &Mat3, w: usize, h: usize, hit: &mut Vec<bool>) -> (f64, f64, f64) {
    raster_tau_body(m, w, h, hit)
}

/// [`raster_tau`]: each row's pixels mapped first (the same arithmetic for every pixel, which
/// the compiler vectorises), then counted.
#[inline(always)]
fn raster_tau_body(m: &Mat3, w: usize, h: usize, hit: &mut Vec<bool>) -> (f64, f64, f64) {
    let total = w * h;
    if total == 0 {
        return (1.0, 0.0, 0.0);
    }
    hit.clear();
    hit.resize(total, false);
    let (mut inside, mut distinct) = (0usize, 0usize);
    // round(u) lands in 0..w exactly when -0.5 < u < w - 0.5, and is then (u + 0.5) truncated
    // (no libm rounding call per pixel; a NaN fails the comparisons).
    let (wl, hl) = (w as f64 - 0.5, h as f64 - 0.5);
    let xs: Vec<f64> = (0..w).map(|x| x as f64).collect();
    let (mut us, mut vs) = (vec![0.0f64; w], vec![0.0f64; w]);
    for y in 0..h {
        let yf = y as f64;
        let (bx, by, bz) = (
            m[0][1] * yf + m[0][2],
            m[1][1] * yf + m[1][2],
            m[2][1] * yf + m[2][2],
        );
        for ((&xf, u), v) in xs.iter().zip(us.iter_mut()).zip(vs.iter_mut()) {
            let z = m[2][0] * xf + bz;
            let r = 1.0 / z;
            // Behind the camera (z <= 1e-9): a NaN, which lands nowhere.
            let r = if z > 1e-9 { r } else { f64::NAN };
            *u = (m[0][0] * xf + bx) * r;
            *v = (m[1][0] * xf + by) * r;
        }
        for (&u, &v) in us.iter().zip(&vs) {
            if u > -0.5 && v > -0.5 && u < wl && v < hl {
                inside += 1;
                let k = (v + 0.5) as usize * w + (u + 0.5) as usize;
                if !hit[k] {
                    hit[k] = true;
                    distinct += 1;
                }
            }
        }
    }
    let fm = inside as f64 / total as f64;
    let fu = distinct as f64 / total as f64;
    (1.0 - fm.min(fu), fm, fu)
}

/// Grey (0-255, BT.601 luma weights) of a planar normalised RGB tensor `[3, h, w]`:
/// `(x * std + mean) * 255` per channel, i.e. the picture the student sees.
pub fn grey_from_tensor(t: &[f32], w: usize, h: usize, mean: [f32; 3], std: [f32; 3]) -> Vec<f32> {
    let n = w * h;
    if t.len() < 3 * n {
        return vec![0.0; n];
    }
    let wts = [0.299f32, 0.587, 0.114];
    let mut g = vec![0.0f32; n];
    for c in 0..3 {
        let (a, b) = (wts[c] * std[c] * 255.0, wts[c] * mean[c] * 255.0);
        for (o, &x) in g.iter_mut().zip(&t[c * n..(c + 1) * n]) {
            *o += a * x + b;
        }
    }
    for v in g.iter_mut() {
        if !v.is_finite() {
            *v = 0.0;
        }
    }
    g
}

/// Frame-to-frame homographies chained from the reference, and the teacher-like score of the
/// chain: the one implementation that the element's [`Tracker`], `leangate geometry` and the
/// `overlap` baseline of `leangate eval` share.
#[derive(Debug, Clone, Default)]
pub struct Chain {
    /// Homography reference → the last frame pushed; None when lost (or never started).
    h: Option<Mat3>,
    hit: Vec<bool>,
}

impl Chain {
    /// The last frame becomes the reference: the chain restarts at the identity.
    pub fn start(&mut self) {
        self.h = Some(IDENTITY);
    }

    /// Lose the chain (until the next [`Chain::start`]).
    pub fn lose(&mut self) {
        self.h = None;
    }

    pub fn is_live(&self) -> bool {
        self.h.is_some()
    }

    /// Extend the chain by the homography previous → next frame; a failed step (None) loses it.
    pub fn push(&mut self, step: Option<Mat3>) {
        self.h = match (self.h, step) {
            (Some(c), Some(s)) => Some(mat_mul(&s, &c)),
            _ => None,
        };
    }

    /// Homography reference → the last frame pushed, if the chain holds.
    pub fn homography(&self) -> Option<Mat3> {
        self.h
    }

    /// An earlier frame of the chain becomes the reference: `to_frame` is the chain's homography
    /// reference → that frame (as [`Chain::homography`] read then). Lost when either is.
    pub fn rebase(&mut self, to_frame: Option<Mat3>) {
        self.h = match (self.h, to_frame.and_then(|m| mat_inv(&m))) {
            (Some(h), Some(inv)) => Some(mat_mul(&h, &inv)),
            _ => None,
        };
    }

    /// `(tau, f_m, f_u)` of the last frame against the reference on a `w` x `h` picture
    /// ([`raster_tau`] of the chain), or None when the chain is lost or not invertible.
    pub fn score(&mut self, w: usize, h: usize) -> Option<(f64, f64, f64)> {
        let inv = mat_inv(&self.h?)?;
        let r = raster_tau(&inv, w, h, &mut self.hit);
        r.0.is_finite().then_some(r)
    }
}

/// The element's tracker: the previous frame's pyramid and the [`Chain`] from the reference.
#[derive(Debug, Clone, Default)]
pub struct Tracker {
    prev: Option<Pyramid>,
    chain: Chain,
}

impl Tracker {
    pub fn new() -> Tracker {
        Tracker::default()
    }

    /// Forget everything (no reference: start, flush, caps change).
    pub fn clear(&mut self) {
        self.prev = None;
        self.chain.lose();
    }

    /// Feed the next frame's pyramid: extends a live chain by the motion from the previous frame.
    pub fn observe(&mut self, cur: Pyramid) {
        if let Some(prev) = self.prev.as_ref().filter(|_| self.chain.is_live()) {
            self.chain.push(frame_homography(prev, &cur));
        }
        self.prev = Some(cur);
    }

    /// The last observed frame becomes the reference: the chain restarts at the identity.
    pub fn set_reference(&mut self) {
        if self.prev.is_some() {
            self.chain.start();
        }
    }

    /// Homography reference → last observed frame, if the chain holds.
    pub fn chain(&self) -> Option<Mat3> {
        self.chain.homography()
    }

    /// An earlier observed frame becomes the reference ([`Chain::rebase`]): `to_frame` is
    /// [`Tracker::chain`] as read when that frame was the last observed.
    pub fn rebase(&mut self, to_frame: Option<Mat3>) {
        self.chain.rebase(to_frame);
    }

    /// The teacher-like utility of the last observed frame against the reference, or None when
    /// the chain is lost.
    pub fn tau(&mut self) -> Option<f64> {
        let prev = self.prev.as_ref()?;
        self.chain.score(prev.width(), prev.height()).map(|r| r.0)
    }
}

/// Homography previous → current frame from a tracked [`GRID_X`] x [`GRID_Y`] grid, or None
/// when too few points track (under a quarter) or no homography fits. The chain of these is
/// what [`Tracker`] keeps; `leangate geometry` chains them the same way.
pub fn frame_homography(prev: &Pyramid, cur: &Pyramid) -> Option<Mat3> {
    if prev.width() != cur.width() || prev.height() != cur.height() {
        return None;
    }
    let pts = grid(prev.width(), prev.height(), GRID_X, GRID_Y);
    let (mut src, mut dst) = (Vec::with_capacity(pts.len()), Vec::with_capacity(pts.len()));
    for &p in pts.iter() {
        if let Some(q) = track_with(prev, cur, p, &LK_PRIOR) {
            src.push(p);
            dst.push(q);
        }
    }
    if src.len() * 4 < pts.len() {
        return None;
    }
    fit_homography(&src, &dst).map(|(h, _)| h)
}

/// How a model combines its utility `s` with `tau_geo` (metadata `leangate.geometry`):
/// `clip(w0 + w1 tau_geo + w2 tau_geo^2 + w3 s, 0, 1)`, or `s` when the geometry is lost.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fusion {
    pub w: [f64; 4],
    /// The largest score `s` the model can give (metadata `leangate.score_max`, 1 when the model
    /// does not say): what [`Fusion::upper`] assumes of the scores it bounds.
    pub s_max: f64,
    /// How much the model's score rises from one frame to the next against the same reference, as
    /// a rule (metadata `leangate.score_step`; None: nothing assumed): what [`Fusion::upper_below`]
    /// adds to the previous frame's score (see [`crate::Utility::screen`]).
    pub s_step: Option<f64>,
}

/// The only fusion form understood so far, named first in the metadata value.
pub const FUSION_FORM: &str = "raster-homography-v1";

impl Fusion {
    /// Parse `raster-homography-v1: w0, w1, w2, w3`.
    pub fn parse(s: &str) -> Result<Fusion, String> {
        let (form, rest) = s.split_once(':').ok_or_else(|| {
            format!("{s:?} is not `{FUSION_FORM}: w0, w1, w2, w3` (no `:` after the form)")
        })?;
        if form.trim() != FUSION_FORM {
            return Err(format!(
                "form {:?} is not understood (only `{FUSION_FORM}`)",
                form.trim()
            ));
        }
        let v: Vec<f64> = rest
            .split(',')
            .map(|t| t.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("{rest:?}: {e}"))?;
        if v.len() != 4 || !v.iter().all(|x| x.is_finite()) {
            return Err(format!(
                "{rest:?} must be four finite numbers w0, w1, w2, w3"
            ));
        }
        Ok(Fusion {
            w: [v[0], v[1], v[2], v[3]],
            s_max: 1.0,
            s_step: None,
        })
    }

    /// The same fusion for a model whose scores never exceed `s_max` (within [0, 1]): its
    /// [`Fusion::upper`] is tighter, so the prior alone decides more frames.
    pub fn with_score_max(self, s_max: f64) -> Fusion {
        Fusion {
            s_max: s_max.clamp(0.0, 1.0),
            ..self
        }
    }

    /// The same fusion for a model whose score rises by at most about `step` from one frame to the
    /// next against the same reference (metadata `leangate.score_step`, within (0, 1]; above 1
    /// counts as 1, and `None`, 0 or less as no step).
    pub fn with_score_step(self, step: Option<f64>) -> Fusion {
        Fusion {
            s_step: step.filter(|s| *s > 0.0).map(|s| s.min(1.0)),
            ..self
        }
    }

    /// The fused utility; `s` itself when `geo` is None or `s` is not finite. `s` is a utility,
    /// so it is taken within [0, 1] (the embedded students' calibration already clips it).
    pub fn fuse(&self, s: f64, geo: Option<f64>) -> f64 {
        match geo {
            Some(g) if s.is_finite() && g.is_finite() => {
                let w = &self.w;
                (w[0] + w[1] * g + w[2] * g * g + w[3] * s.clamp(0.0, 1.0)).clamp(0.0, 1.0)
            }
            _ => s,
        }
    }

    /// The largest fused utility any model score up to [`Fusion::s_max`] can give with this
    /// `tau_geo`: when it is below the threshold, the prior alone decides that the frame is
    /// dropped (see [`crate::Utility::screen`]).
    pub fn upper(&self, g: f64) -> f64 {
        self.upper_below(g, self.s_max)
    }

    /// The largest fused utility any model score up to `s` (and up to [`Fusion::s_max`]) can
    /// give with this `tau_geo`.
    pub fn upper_below(&self, g: f64, s: f64) -> f64 {
        let w = &self.w;
        let s = if s.is_nan() {
            self.s_max
        } else {
            s.clamp(0.0, self.s_max)
        };
        (w[0] + w[1] * g + w[2] * g * g + (w[3] * s).max(0.0)).clamp(0.0, 1.0)
    }

    pub fn to_metadata(&self) -> String {
        format!(
            "{FUSION_FORM}: {}, {}, {}, {}",
            self.w[0], self.w[1], self.w[2], self.w[3]
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: usize = 160;
    const H: usize = 120;

    /// A smooth texture seen through the homography `m` (pixel of the picture → texture coords).
    fn texture(m: &Mat3) -> Vec<f32> {
        let mut v = vec![0.0f32; W * H];
        for y in 0..H {
            for x in 0..W {
                let (u, t) = apply(m, x as f64, y as f64).unwrap_or((0.0, 0.0));
                let (u, t) = (u as f32, t as f32);
                let f = 128.0
                    + 50.0 * (u * 0.21).sin() * (t * 0.17).cos()
                    + 40.0 * ((u + t) * 0.09).sin()
                    + 30.0 * (u * 0.05 - t * 0.11).cos();
                v[y * W + x] = f.clamp(0.0, 255.0);
            }
        }
        v
    }

    fn shift(dx: f64, dy: f64) -> Mat3 {
        [[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]
    }

    fn rot(deg: f64) -> Mat3 {
        let (s, c) = deg.to_radians().sin_cos();
        let (cx, cy) = (W as f64 / 2.0, H as f64 / 2.0);
        mat_mul(
            &shift(cx, cy),
            &mat_mul(
                &[[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
                &shift(-cx, -cy),
            ),
        )
    }

    #[test]
    fn raster_tau_of_known_warps() {
        let mut hit = Vec::new();
        let (t, fm, fu) = raster_tau(&IDENTITY, W, H, &mut hit);
        assert_eq!((t, fm, fu), (0.0, 1.0, 1.0));
        // A shift of a quarter of the width leaves 3/4 of both views.
        let (t, fm, fu) = raster_tau(&shift(40.0, 0.0), W, H, &mut hit);
        assert!((fm - 0.75).abs() < 1e-9 && (fu - 0.75).abs() < 1e-9 && (t - 0.25).abs() < 1e-9);
        // Entirely outside: nothing left.
        assert_eq!(raster_tau(&shift(500.0, 0.0), W, H, &mut hit).0, 1.0);
        // Under a roll the nearest-pixel map hits fewer distinct pixels than it maps inside.
        let (_, fm, fu) = raster_tau(&rot(20.0), W, H, &mut hit);
        assert!(fu < fm, "f_u {fu} f_m {fm}");
        // A zoom-in by 2 (current pixels cover half the reference's span) hits a quarter.
        let zoom = [[0.5, 0.0, 40.0], [0.0, 0.5, 30.0], [0.0, 0.0, 1.0]];
        let (_, fm, fu) = raster_tau(&zoom, W, H, &mut hit);
        assert!(
            (fm - 1.0).abs() < 1e-9 && (fu - 0.25).abs() < 0.01,
            "{fm} {fu}"
        );
    }

    #[test]
    fn homography_fit_recovers_a_warp_despite_outliers() {
        let h = mat_mul(&rot(7.0), &shift(3.0, -2.0));
        let src = grid(W, H, 12, 9);
        let mut dst: Vec<(f32, f32)> = src
            .iter()
            .map(|p| {
                let q = apply(&h, p.0 as f64, p.1 as f64).unwrap();
                (q.0 as f32, q.1 as f32)
            })
            .collect();
        for k in (0..dst.len()).step_by(5) {
            dst[k].0 += 25.0;
        }
        let (f, inl) = fit_homography(&src, &dst).expect("fit");
        assert_eq!(inl, src.len() - src.len().div_ceil(5));
        for p in &src {
            let a = apply(&h, p.0 as f64, p.1 as f64).unwrap();
            let b = apply(&f, p.0 as f64, p.1 as f64).unwrap();
            assert!((a.0 - b.0).abs() < 0.05 && (a.1 - b.1).abs() < 0.05);
        }
        assert!(fit_homography(&src[..5], &dst[..5]).is_none());
    }

    /// Every window side, inside the image, near its right edge (fewer pixels than lanes left)
    /// and across the border, gives the bilinear sample of each pixel (up to how the pixel's
    /// coordinate rounds); the lanes past the side are ignored by the tracker.
    #[test]
    fn window_rows_equal_their_bilinear_samples_exactly() {
        fn check<const L: usize>(img: &[f32], hw: usize) {
            let side = 2 * hw + 1;
            let mut out = [[0.0f32; L]; 2 * HALF_WIN as usize + 1];
            for &(cx, cy) in &[
                (20.3f32, 17.71f32),
                (80.0, 60.0),
                (141.9, 100.05),
                (9.5, 9.25),
                ((W - hw - 2) as f32 + 0.4, 30.6),
                (2.2, 3.7),
                (W as f32 - 1.5, H as f32 - 0.2),
                (-6.0, 50.5),
            ] {
                window_rows::<L>(img, W, H, cx, cy, hw, &mut out);
                let (x, y) = (cx - hw as f32, cy - hw as f32);
                for (r, row) in out.iter().enumerate().take(side) {
                    for (c, &got) in row.iter().enumerate().take(side) {
                        let want = sample(img, W, H, x + c as f32, y + r as f32);
                        assert!(
                            (got - want).abs() <= 1e-5 * want.abs().max(1.0),
                            "hw {hw}, {L} lanes, at ({cx}, {cy}), [{r}][{c}]: {got} against {want}"
                        );
                    }
                }
            }
        }
        let img = texture(&rot(7.0));
        for hw in 1..=3usize {
            check::<8>(&img, hw);
        }
        for hw in 1..=4usize {
            check::<16>(&img, hw);
        }
    }

    /// The AVX2 build of the prior's tracker and the plain one give the same points, bit for bit.
    #[test]
    fn the_avx2_tracker_tracks_exactly_as_the_plain_one() {
        let a = Pyramid::new(texture(&IDENTITY), W, H);
        let b = Pyramid::new(texture(&rot(3.0)), W, H);
        let mut n = 0;
        for p in grid(W, H, 12, 9) {
            let plain = track_lanes::<8, false>(&a, &b, p, &LK_PRIOR, 3);
            let q = track_with(&a, &b, p, &LK_PRIOR);
            let bits = |q: Option<(f32, f32)>| q.map(|q| (q.0.to_bits(), q.1.to_bits()));
            assert_eq!(bits(plain), bits(q), "{p:?}");
            n += plain.is_some() as usize;
        }
        assert!(n > 80, "{n} of 108 points tracked");
    }

    /// The AVX2 build of the raster score and the plain one count the same pixels, also for maps
    /// that put part of the frame behind the camera.
    #[test]
    fn the_avx2_raster_score_equals_the_plain_one() {
        let (mut h1, mut h2) = (Vec::new(), Vec::new());
        let tilt = [[1.0, 0.05, 3.0], [0.02, 0.97, -2.0], [0.004, -0.003, 1.0]];
        let behind = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.02, 0.0, 1.0]];
        for m in [IDENTITY, rot(9.0), shift(-7.5, 3.25), tilt, behind] {
            let a = raster_tau(&m, 80, 60, &mut h1);
            let b = raster_tau_body(&m, 80, 60, &mut h2);
            assert_eq!(a, b, "{m:?}");
        }
        let (_, fm, _) = raster_tau(&behind, 80, 60, &mut h1);
        assert!(fm > 0.2 && fm < 0.9, "{fm}");
    }

    /// The gradients and the halving, written without per-pixel clamping, equal the clamped
    /// formulas bit for bit on every shape, odd and one-pixel sides included.
    #[test]
    fn gradients_and_halving_equal_the_clamped_formulas() {
        for (w, h) in [(1, 1), (1, 5), (5, 1), (2, 2), (7, 5), (80, 60), (81, 61)] {
            let img: Vec<f32> = (0..w * h)
                .map(|i| ((i * 7919 + 13) % 251) as f32 * 1.37)
                .collect();
            let l = Level::new(w, h, img.clone());
            for y in 0..h {
                for x in 0..w {
                    let (xl, xr) = (x.saturating_sub(1), (x + 1).min(w - 1));
                    let (yu, yd) = (y.saturating_sub(1), (y + 1).min(h - 1));
                    let gx = 0.5 * (img[y * w + xr] - img[y * w + xl]);
                    let gy = 0.5 * (img[yd * w + x] - img[yu * w + x]);
                    assert_eq!(
                        l.gx[y * w + x].to_bits(),
                        gx.to_bits(),
                        "{w}x{h} gx {x},{y}"
                    );
                    assert_eq!(
                        l.gy[y * w + x].to_bits(),
                        gy.to_bits(),
                        "{w}x{h} gy {x},{y}"
                    );
                }
            }
            let (out, nw, nh) = half(&img, w, h);
            assert_eq!((nw, nh), ((w / 2).max(1), (h / 2).max(1)));
            for y in 0..nh {
                let (y0, y1) = ((2 * y).min(h - 1), (2 * y + 1).min(h - 1));
                for x in 0..nw {
                    let (x0, x1) = ((2 * x).min(w - 1), (2 * x + 1).min(w - 1));
                    let want = 0.25
                        * (img[y0 * w + x0]
                            + img[y0 * w + x1]
                            + img[y1 * w + x0]
                            + img[y1 * w + x1]);
                    assert_eq!(
                        out[y * nw + x].to_bits(),
                        want.to_bits(),
                        "{w}x{h} half {x},{y}"
                    );
                }
            }
        }
    }

    #[test]
    fn tracks_a_known_shift() {
        let a = Pyramid::new(texture(&IDENTITY), W, H);
        let b = Pyramid::new(texture(&shift(-3.0, 2.0)), W, H);
        let mut errs = Vec::new();
        for p in grid(W, H, 12, 9)
            .into_iter()
            .filter(|p| p.0 > 15.0 && p.0 < 145.0 && p.1 > 15.0 && p.1 < 105.0)
        {
            let q = track(&a, &b, p).expect("tracked");
            errs.push(((q.0 - p.0 - 3.0).abs()).max((q.1 - p.1 + 2.0).abs()));
        }
        errs.sort_by(|a, b| a.total_cmp(b));
        assert!(
            errs[errs.len() / 2] < 0.2,
            "median {}",
            errs[errs.len() / 2]
        );
    }

    #[test]
    fn the_prior_works_on_a_halved_picture_and_tracks_there() {
        assert_eq!(prior_size(160, 120), (80, 60));
        assert_eq!(prior_size(64, 48), (64, 48));
        assert_eq!(prior_size(256, 256), (64, 64));
        assert_eq!(prior_size(1, 1), (1, 1));
        // The halved picture is the 2x2 means of the model's picture.
        let g: Vec<f32> = (0..W * H).map(|i| (i % W) as f32).collect();
        let p = Pyramid::for_prior(g, W, H);
        assert_eq!((p.width(), p.height()), (80, 60));
        assert_eq!(p.levels[0].img[..3], [0.5, 2.5, 4.5]);
        assert_eq!(
            Pyramid::for_prior(vec![1.0; 7], W, H).width(),
            1,
            "malformed: 1x1"
        );
        // Odd and degenerate shapes neither panic nor track.
        for (w, h) in [(131, 3), (129, 1), (2, 200), (1, 1), (300, 2), (127, 95)] {
            let g: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 251) as f32).collect();
            let (a, b) = (
                Pyramid::for_prior(g.clone(), w, h),
                Pyramid::for_prior(g, w, h),
            );
            assert_eq!((a.width(), a.height()), prior_size(w, h));
            let _ = frame_homography(&a, &b);
        }
        // The prior's settings follow a known shift of the halved texture (-3, 2 at 160x120).
        let a = Pyramid::for_prior(texture(&IDENTITY), W, H);
        let b = Pyramid::for_prior(texture(&shift(-3.0, 2.0)), W, H);
        let mut errs = Vec::new();
        for p in grid(80, 60, GRID_X, GRID_Y)
            .into_iter()
            .filter(|p| p.0 > 8.0 && p.0 < 72.0 && p.1 > 8.0 && p.1 < 52.0)
        {
            let q = track_with(&a, &b, p, &LK_PRIOR).expect("tracked");
            errs.push(((q.0 - p.0 - 1.5).abs()).max((q.1 - p.1 + 1.0).abs()));
        }
        errs.sort_by(|a, b| a.total_cmp(b));
        assert!(errs.len() >= 12);
        assert!(
            errs[errs.len() / 2] < 0.1,
            "median {}",
            errs[errs.len() / 2]
        );
        let h = frame_homography(&a, &b).expect("a homography");
        assert!(
            (h[0][2] - 1.5).abs() < 0.1 && (h[1][2] + 1.0).abs() < 0.1,
            "{h:?}"
        );
    }

    #[test]
    fn a_chain_rebased_on_an_earlier_frame_is_the_chain_started_there() {
        let step = |dx: f64, dy: f64, k: f64| [[k, 0.0, dx], [0.0, k, dy], [0.0, 0.0, 1.0]];
        let steps = [
            step(3.0, 1.0, 1.0),
            step(-2.0, 4.0, 1.01),
            step(5.0, 0.0, 0.99),
        ];
        let mut whole = Chain::default();
        whole.start();
        whole.push(Some(steps[0]));
        let at_first = whole.homography();
        for s in &steps[1..] {
            whole.push(Some(*s));
        }
        whole.rebase(at_first);
        let mut from_first = Chain::default();
        from_first.start();
        for s in &steps[1..] {
            from_first.push(Some(*s));
        }
        let (a, b) = (
            whole.homography().unwrap(),
            from_first.homography().unwrap(),
        );
        for r in 0..3 {
            for c in 0..3 {
                assert!((a[r][c] - b[r][c]).abs() < 1e-9, "{a:?} against {b:?}");
            }
        }
        // Rebased on a frame where the chain was lost: lost.
        whole.rebase(None);
        assert!(!whole.is_live());
    }

    #[test]
    fn chained_tracker_follows_a_pan_beyond_one_step() {
        // A pan of 2.5 px per frame over 24 frames: 60 px in all, far more than one LK step.
        let mut t = Tracker::new();
        t.observe(Pyramid::new(texture(&IDENTITY), W, H));
        assert_eq!(t.tau(), None, "no reference yet");
        t.set_reference();
        assert_eq!(t.tau(), Some(0.0));
        for k in 1..=24 {
            t.observe(Pyramid::new(texture(&shift(2.5 * k as f64, 0.0)), W, H));
        }
        let tau = t.tau().expect("chain holds");
        assert!((tau - 60.0 / W as f64).abs() < 0.02, "tau {tau}");
        // A frame of another size loses the chain; a new reference restores it.
        t.observe(Pyramid::new(vec![0.0; 80 * 60], 80, 60));
        assert_eq!(t.tau(), None);
        t.set_reference();
        assert_eq!(t.tau(), Some(0.0));
        // A malformed picture is a 1x1 pyramid, not a panic.
        assert_eq!(Pyramid::new(vec![1.0, 2.0], 5, 5).width(), 1);
        // A textureless frame cannot be tracked: the chain is lost, not guessed.
        t.observe(Pyramid::new(vec![10.0; 80 * 60], 80, 60));
        assert_eq!(t.tau(), None);
        t.clear();
        assert_eq!(t.tau(), None);
    }

    #[test]
    fn grey_inverts_the_normalisation() {
        let (mean, std) = ([0.485, 0.456, 0.406], [0.229, 0.224, 0.225]);
        let px = [0.2f32, 0.6, 0.9];
        let t: Vec<f32> = (0..3).map(|c| (px[c] - mean[c]) / std[c]).collect();
        let g = grey_from_tensor(&t, 1, 1, mean, std);
        let want = 255.0 * (0.299 * 0.2 + 0.587 * 0.6 + 0.114 * 0.9);
        assert!((g[0] - want).abs() < 1e-3, "{} vs {want}", g[0]);
        assert_eq!(grey_from_tensor(&[f32::NAN; 3], 1, 1, mean, std), vec![0.0]);
    }

    #[test]
    fn fusion_parses_fuses_and_falls_back() {
        let f = Fusion::parse("raster-homography-v1: 0.1, 0.5, 0.25, 0.5").unwrap();
        assert_eq!(f.w, [0.1, 0.5, 0.25, 0.5]);
        assert_eq!(Fusion::parse(&f.to_metadata()).unwrap(), f);
        assert!((f.fuse(0.4, Some(0.2)) - (0.1 + 0.1 + 0.01 + 0.2)).abs() < 1e-12);
        assert_eq!(f.fuse(0.4, None), 0.4);
        assert!(f.fuse(f64::NAN, Some(0.2)).is_nan());
        assert_eq!(f.fuse(3.0, Some(1.0)), 1.0);
        for bad in [
            "0.1, 0.5, 0.25, 0.5",
            "other: 1, 2, 3, 4",
            "raster-homography-v1: 1, 2, 3",
            "raster-homography-v1: 1, 2, x, 4",
            "raster-homography-v1: 1, 2, inf, 4",
        ] {
            assert!(Fusion::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_upper_bound_holds_for_every_score() {
        for f in [
            Fusion::parse("raster-homography-v1: 0.121524, 0.698698, 0, 0.25").unwrap(),
            Fusion::parse("raster-homography-v1: 0.1, 0.5, 0.25, -0.3").unwrap(),
        ] {
            for g in [0.0, 0.1, 0.18, 0.3, 0.6, 1.0] {
                let up = f.upper(g);
                let mut max = f64::MIN;
                for s in [-5.0, -1e-9, 0.0, 0.2, 0.5, 0.99, 1.0, 1.5, 1e9] {
                    let u = f.fuse(s, Some(g));
                    assert!(u <= up + 1e-15, "{f:?} g {g} s {s}: {u} > {up}");
                    max = max.max(u);
                }
                // Tight: some score in [0, 1] reaches it.
                assert!((max - up).abs() < 1e-12, "{f:?} g {g}: {max} vs {up}");
            }
        }
        // A model that says its scores stay at or below 0.878 (the embedded student's calibrated
        // range): the bound holds for every such score, is reached by one, and is tighter.
        let wide = Fusion::parse("raster-homography-v1: 0.121524, 0.698698, 0, 0.25").unwrap();
        let f = wide.with_score_max(0.878);
        for g in [0.0, 0.1, 0.2, 0.25, 1.0] {
            let up = f.upper(g);
            let scores = (0..=100).map(|k| 0.878 * k as f64 / 100.0);
            let max = scores.map(|s| f.fuse(s, Some(g))).fold(f64::MIN, f64::max);
            assert!((max - up).abs() < 1e-12, "g {g}: {max} vs {up}");
            assert!(g >= 0.9 || up < wide.upper(g), "g {g}");
        }
        // Where the wide bound could not decide and the tight one does (at threshold 0.5).
        assert!(wide.upper(0.2) >= 0.5 && f.upper(0.2) < 0.5);
        // Scores outside [0, 1] count as its ends.
        let f = Fusion::parse("raster-homography-v1: 0.1, 0.5, 0, 0.25").unwrap();
        assert_eq!(f.fuse(1.7, Some(0.2)), f.fuse(1.0, Some(0.2)));
        assert_eq!(f.fuse(-0.4, Some(0.2)), f.fuse(0.0, Some(0.2)));
    }

    #[test]
    fn the_bound_below_a_score_holds_for_every_score_up_to_it() {
        for f in [
            Fusion::parse("raster-homography-v1: 0.121524, 0.698698, 0, 0.25")
                .unwrap()
                .with_score_max(0.878),
            Fusion::parse("raster-homography-v1: 0.1, 0.5, 0.25, -0.3").unwrap(),
        ] {
            for g in [0.0, 0.2, 0.3, 0.6] {
                for cap in [0.0, 0.2, 0.45, 0.878, 1.0, 2.0] {
                    let up = f.upper_below(g, cap);
                    let scores: Vec<f64> = (0..=50)
                        .map(|k| cap.min(f.s_max) * k as f64 / 50.0)
                        .collect();
                    let max = scores
                        .iter()
                        .map(|&s| f.fuse(s, Some(g)))
                        .fold(f64::MIN, f64::max);
                    assert!(
                        (max - up).abs() < 1e-12,
                        "{f:?} g {g} cap {cap}: {max} vs {up}"
                    );
                    assert!(up <= f.upper(g) + 1e-15);
                }
                // No cap (not a number) is the model's whole range.
                assert_eq!(f.upper_below(g, f64::NAN), f.upper(g));
            }
        }
        // The embedded fusion at tau_geo 0.3: any score could reach 0.5, a score below 0.3 not.
        let f = Fusion::parse("raster-homography-v1: 0.121524, 0.698698, 0, 0.25")
            .unwrap()
            .with_score_max(0.878)
            .with_score_step(Some(0.15));
        assert_eq!(f.s_step, Some(0.15));
        for none in [None, Some(0.0), Some(-1.0), Some(f64::NAN)] {
            assert_eq!(f.with_score_step(none).s_step, None, "{none:?}");
        }
        assert_eq!(f.with_score_step(Some(3.0)).s_step, Some(1.0));
        assert!(f.upper(0.3) >= 0.5 && f.upper_below(0.3, 0.3) < 0.5);
    }
}
