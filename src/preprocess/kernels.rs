//! The preprocessing kernels: the fast path (taps flattened per plane, rows summed in u16, AVX2
//! and a generic build of one body) and the straightforward reference resampler with its row
//! helpers. The API they serve (formats, [`Preprocessor`], [`RawFrame`]) is in `preprocess.rs`.

use super::*;

/// Horizontal taps of one plane, flattened: output `o` reads pixels `start[o]..start[o] + t`
/// (relative to the pass's first pixel) with weights `w[o * t..(o + 1) * t]` (zero-padded).
#[derive(Debug, Clone)]
pub(super) struct FlatTaps {
    pub(super) t: usize,
    pub(super) start: Vec<usize>,
    pub(super) w: Vec<f32>,
}

/// How one plane contributes to the output pixels.
#[derive(Debug, Clone)]
pub(super) struct PlanePass {
    pub(super) plane: usize,
    /// Interleaved samples per pixel in the plane (1, 2, 3 or 4).
    pub(super) bpp: usize,
    /// Pixel range of the plane the horizontal taps read.
    pub(super) x0: usize,
    pub(super) x1: usize,
    pub(super) x: FlatTaps,
    /// Vertical taps, in rows of this plane.
    pub(super) y: Vec<Taps>,
    /// Per vertical tap: its interior rows (all but the first and last, at least two, at most
    /// [`MAX_U16_ROWS`]) share one weight, so the fast path sums them in u16 (decided once here,
    /// not per frame).
    pub(super) y_sum: Vec<bool>,
    /// (sample within the pixel, output slot 0..3), per used sample.
    pub(super) chans: Vec<(usize, usize)>,
    /// `Some((j, offset))`: an earlier pass `j` reads the same plane through the same vertical
    /// taps over a sample range that covers this one's (packed 4:2:2: the chroma pass over pixel
    /// pairs holds every luma sample too), so this pass reads its vertically averaged row from
    /// `j`'s, `offset` samples in, instead of averaging the same bytes again.
    pub(super) acc_from: Option<(usize, usize)>,
}

/// The fast path's buffers.
#[derive(Debug)]
pub(super) struct FastScratch {
    /// Per pass: the vertically averaged samples of the pass's pixel range, plus `t` zeroed
    /// pixels of padding for the fixed-length horizontal taps.
    pub(super) acc: Vec<Vec<f32>>,
    /// Per pass: one output row per sample (`bpp` rows of the output width, one after the
    /// other).
    pub(super) rows: Vec<Vec<f32>>,
    /// Per pass: the exact integer sum of the interior source rows of a vertical tap (area
    /// averaging gives every row but the first and last the same weight).
    pub(super) sums: Vec<Vec<u16>>,
}

/// Most interior rows summed in u16 without overflow (257 x 255 <= 65535).
pub(super) const MAX_U16_ROWS: usize = 257;

/// Taps of a plane subsampled 2:1 (chroma): luma taps merged by `index / 2`. With chroma
/// upsampled by repetition (nearest), this is exactly the luma-resolution average.
pub(super) fn halve_taps(taps: &[Taps]) -> Vec<Taps> {
    taps.iter()
        .map(|t| {
            let start = t.start / 2;
            let end = (t.start + t.weights.len() - 1) / 2 + 1;
            let mut weights = vec![0f32; end - start];
            for (k, &w) in t.weights.iter().enumerate() {
                weights[(t.start + k) / 2 - start] += w;
            }
            Taps { start, weights }
        })
        .collect()
}

pub(super) fn flatten(taps: &[Taps]) -> (usize, usize, FlatTaps) {
    let x0 = taps.iter().map(|t| t.start).min().unwrap_or(0);
    let x1 = taps
        .iter()
        .map(|t| t.start + t.weights.len())
        .max()
        .unwrap_or(0);
    let t = taps.iter().map(|t| t.weights.len()).max().unwrap_or(1);
    let mut w = vec![0f32; t * taps.len()];
    let mut start = Vec::with_capacity(taps.len());
    for (o, tap) in taps.iter().enumerate() {
        start.push(tap.start - x0);
        w[o * t..o * t + tap.weights.len()].copy_from_slice(&tap.weights);
    }
    (x0, x1, FlatTaps { t, start, w })
}

pub(super) fn plane_pass(
    desc: &PassDesc,
    x_taps: &[Taps],
    y_taps: Vec<Taps>,
    sums: bool,
) -> PlanePass {
    let (x0, x1, x) = flatten(x_taps);
    let y_sum = y_taps
        .iter()
        .map(|t| {
            let w = &t.weights;
            sums && w.len() >= 4
                && w.len() - 2 <= MAX_U16_ROWS
                && w[1..w.len() - 1].iter().all(|&x| x == w[1])
        })
        .collect();
    PlanePass {
        plane: desc.plane,
        bpp: desc.bpp,
        x0,
        x1,
        x,
        y: y_taps,
        y_sum,
        chans: desc.chans.to_vec(),
        acc_from: None,
    }
}

/// Marks each pass whose vertically averaged row an earlier pass already holds: same plane, same
/// vertical taps, and a covering sample range with room for this pass's horizontal taps.
fn share_rows(passes: &mut [PlanePass]) {
    for k in 1..passes.len() {
        let found = (0..k).find_map(|j| {
            let (a, b) = (&passes[j], &passes[k]);
            let (a0, b0) = (a.x0 * a.bpp, b.x0 * b.bpp);
            let a_len = (a.x1 - a.x0 + a.x.t) * a.bpp;
            let b_len = (b.x1 - b.x0 + b.x.t) * b.bpp;
            // (Equal taps also mean equal `y_sum`: it follows from the weights and the format.)
            let same_rows = a.plane == b.plane
                && a.y.len() == b.y.len()
                && a.y
                    .iter()
                    .zip(&b.y)
                    .all(|(s, t)| s.start == t.start && s.weights == t.weights);
            (a.acc_from.is_none()
                && same_rows
                && a0 <= b0
                && b.x1 * b.bpp <= a.x1 * a.bpp
                && b0 - a0 + b_len <= a_len)
                .then(|| (j, b0 - a0))
        });
        passes[k].acc_from = found;
    }
}

/// One pass per [`PassDesc`] of the format; chroma taps merged 2:1 where it is subsampled. Wide
/// samples are brought to 8-bit code values through the vertical weights (a power of two: exact),
/// and are never summed in u16.
pub(super) fn make_passes(format: PixelFormat, x_taps: &[Taps], y_taps: &[Taps]) -> Vec<PlanePass> {
    let d = format.desc();
    let unit = format.unit();
    let taps = |taps: &[Taps], sub: usize| {
        if sub == 2 {
            halve_taps(taps)
        } else {
            taps.to_vec()
        }
    };
    let mut passes = d
        .passes
        .iter()
        .map(|p| {
            let mut y = taps(y_taps, p.sub.1);
            y.iter_mut()
                .flat_map(|t| t.weights.iter_mut())
                .for_each(|w| *w *= unit);
            plane_pass(p, &taps(x_taps, p.sub.0), y, d.bytes == 1)
        })
        .collect::<Vec<_>>();
    share_rows(&mut passes);
    passes
}

pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

impl Preprocessor {
    pub(super) fn fast_scratch(&self) -> Result<FastScratch, PreprocessError> {
        let mut acc = Vec::new();
        let mut rows = Vec::new();
        let mut sums = Vec::new();
        let e = |e: std::collections::TryReserveError| {
            PreprocessError(format!("cannot allocate row buffers: {e}"))
        };
        acc.try_reserve_exact(self.passes.len()).map_err(e)?;
        rows.try_reserve_exact(self.passes.len()).map_err(e)?;
        sums.try_reserve_exact(self.passes.len()).map_err(e)?;
        for p in &self.passes {
            // A pass reading another's averaged row needs neither buffer of its own.
            let (n, pad) = match p.acc_from {
                None => ((p.x1 - p.x0) * p.bpp, p.x.t * p.bpp),
                Some(_) => (0, 0),
            };
            acc.push(try_zeroed(n + pad)?);
            rows.push(try_zeroed(self.spec.width as usize * p.bpp)?);
            sums.push(try_filled(n, 0u16)?);
        }
        Ok(FastScratch { acc, rows, sums })
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn fast_avx2(
        &self,
        frame: &RawFrame,
        rows: [Rows; 3],
        scratch: &mut FastScratch,
        out: &mut [f32],
    ) {
        self.fast_body(frame, rows, scratch, out)
    }

    pub(super) fn fast_generic(
        &self,
        frame: &RawFrame,
        rows: [Rows; 3],
        scratch: &mut FastScratch,
        out: &mut [f32],
    ) {
        self.fast_body(frame, rows, scratch, out)
    }

    #[inline(always)]
    pub(super) fn fast_body(
        &self,
        frame: &RawFrame,
        rows: [Rows; 3],
        s: &mut FastScratch,
        out: &mut [f32],
    ) {
        let ow = self.spec.width as usize;
        let oh = self.spec.height as usize;
        let plane_len = ow * oh;
        let (m, sd) = (self.spec.mean, self.spec.std);
        let scale = [
            1.0 / (255.0 * sd[0]),
            1.0 / (255.0 * sd[1]),
            1.0 / (255.0 * sd[2]),
        ];
        let offset = [m[0] / sd[0], m[1] / sd[1], m[2] / sd[2]];
        let desc = self.format.desc();
        let (yuv, wide) = (desc.yuv, desc.bytes == 2);
        let c = self.yuv.coefficients();
        let FastScratch {
            acc: accs,
            rows: hrows,
            sums,
        } = s;
        // Where each output slot (R, G, B or Y, U, V) is read: (pass, samples per pixel, sample).
        let mut slots = [(0usize, 1usize, 0usize); 3];
        for (k, pass) in self.passes.iter().enumerate() {
            for &(sample, slot) in &pass.chans {
                slots[slot] = (k, pass.bpp, sample);
            }
        }
        let (out_r, rest) = out.split_at_mut(plane_len);
        let (out_g, out_b) = rest.split_at_mut(plane_len);
        for oy in 0..oh {
            for (k, pass) in self.passes.iter().enumerate() {
                let bpp = pass.bpp;
                let acc: &[f32] = match pass.acc_from {
                    Some((j, offset)) => &accs[j][offset..],
                    None => {
                        let n = (pass.x1 - pass.x0) * bpp;
                        let (data, r) = (frame.planes[pass.plane], rows[pass.plane]);
                        let (acc, sum) = (&mut accs[k], &mut sums[k]);
                        if wide {
                            vertical::<2>(&mut acc[..n], sum, data, r, pass, oy);
                        } else {
                            vertical::<1>(&mut acc[..n], sum, data, r, pass, oy);
                        }
                        acc
                    }
                };
                let hrow = &mut hrows[k];
                match bpp {
                    1 => hpass::<1>(acc, pass, hrow),
                    2 => hpass::<2>(acc, pass, hrow),
                    3 => hpass::<3>(acc, pass, hrow),
                    _ => hpass::<4>(acc, pass, hrow),
                }
            }
            let slot = |k: usize| {
                let (pass, _, sample) = slots[k];
                hrows[pass][sample * ow..(sample + 1) * ow].iter()
            };
            let row = oy * ow;
            let (r, g, b) = (
                &mut out_r[row..row + ow],
                &mut out_g[row..row + ow],
                &mut out_b[row..row + ow],
            );
            let px = slot(0).zip(slot(1)).zip(slot(2));
            let out = r.iter_mut().zip(g.iter_mut()).zip(b.iter_mut());
            if yuv {
                for (((y, u), v), ((r, g), b)) in px.zip(out) {
                    let y = (y - c.y0) * c.ys;
                    let cb = u - 128.0;
                    let cr = v - 128.0;
                    let rv = (y + c.rv * cr).clamp(0.0, 255.0);
                    let gv = (y - c.gu * cb - c.gv * cr).clamp(0.0, 255.0);
                    let bv = (y + c.bu * cb).clamp(0.0, 255.0);
                    *r = rv * scale[0] - offset[0];
                    *g = gv * scale[1] - offset[1];
                    *b = bv * scale[2] - offset[2];
                }
            } else {
                for (((p0, p1), p2), ((r, g), b)) in px.zip(out) {
                    *r = p0 * scale[0] - offset[0];
                    *g = p1 * scale[1] - offset[1];
                    *b = p2 * scale[2] - offset[2];
                }
            }
        }
    }

    /// Separable resampling in the source's colour space: a horizontal pass per needed source row
    /// (each row computed once, buffers reused), a vertical pass per output row, then `post`
    /// (colour conversion to RGB) and normalisation per output pixel.
    #[inline(always)]
    pub(super) fn resample<F, P>(&self, out: &mut [f32], scratch: Scratch, fetch: F, post: P)
    where
        F: Fn(usize, usize) -> [f32; 3],
        P: Fn([f32; 3]) -> [f32; 3],
    {
        let ow = self.spec.width as usize;
        let oh = self.spec.height as usize;
        let plane = ow * oh;
        let x0 = self.x_range.0;
        let Scratch {
            mut src_row,
            mut acc,
            mut spare,
        } = scratch;
        // Horizontally resampled source rows, by source row index; the taps only move forward.
        let mut rows: Vec<(usize, Vec<[f32; 3]>)> = Vec::with_capacity(spare.len());
        let (m, s) = (self.spec.mean, self.spec.std);
        let scale = [
            1.0 / (255.0 * s[0]),
            1.0 / (255.0 * s[1]),
            1.0 / (255.0 * s[2]),
        ];
        let offset = [m[0] / s[0], m[1] / s[1], m[2] / s[2]];
        for (oy, ty) in self.y_taps.iter().enumerate() {
            // Recycle rows no longer needed.
            let mut k = 0;
            while k < rows.len() {
                if rows[k].0 < ty.start {
                    spare.push(rows.swap_remove(k).1);
                } else {
                    k += 1;
                }
            }
            acc.iter_mut().for_each(|a| *a = [0.0; 3]);
            for (j, &wy) in ty.weights.iter().enumerate() {
                let sy = ty.start + j;
                let pos = match rows.iter().position(|(r, _)| *r == sy) {
                    Some(p) => p,
                    None => {
                        for (i, p) in src_row.iter_mut().enumerate() {
                            *p = fetch(x0 + i, sy);
                        }
                        let mut h = spare.pop().unwrap_or_else(|| vec![[0f32; 3]; ow]);
                        for (hx, tx) in h.iter_mut().zip(&self.x_taps) {
                            let mut a = [0f32; 3];
                            let px = &src_row[tx.start - x0..tx.start - x0 + tx.weights.len()];
                            for (p, &wx) in px.iter().zip(&tx.weights) {
                                a[0] += wx * p[0];
                                a[1] += wx * p[1];
                                a[2] += wx * p[2];
                            }
                            *hx = a;
                        }
                        rows.push((sy, h));
                        rows.len() - 1
                    }
                };
                for (a, p) in acc.iter_mut().zip(&rows[pos].1) {
                    a[0] += wy * p[0];
                    a[1] += wy * p[1];
                    a[2] += wy * p[2];
                }
            }
            for (ox, a) in acc.iter().enumerate() {
                let v = post(*a);
                for c in 0..3 {
                    out[c * plane + oy * ow + ox] = v[c] * scale[c] - offset[c];
                }
            }
        }
    }
}

/// The resampler's working buffers, allocated fallibly before a frame is read.
pub(super) struct Scratch {
    pub(super) src_row: Vec<[f32; 3]>,
    pub(super) acc: Vec<[f32; 3]>,
    /// Buffers for the horizontally resampled rows alive at once.
    pub(super) spare: Vec<Vec<[f32; 3]>>,
}

impl Scratch {
    pub(super) fn new(p: &Preprocessor) -> Result<Scratch, PreprocessError> {
        let ow = p.spec.width as usize;
        let (x0, x1) = p.x_range;
        let live = p.y_taps.iter().map(|t| t.weights.len()).max().unwrap_or(1) + 1;
        let mut spare = Vec::new();
        spare
            .try_reserve_exact(live)
            .map_err(|e| PreprocessError(format!("cannot allocate row buffers: {e}")))?;
        for _ in 0..live {
            spare.push(try_filled(ow, [0f32; 3])?);
        }
        Ok(Scratch {
            src_row: try_filled(x1.saturating_sub(x0), [0f32; 3])?,
            acc: try_filled(ow, [0f32; 3])?,
            spare,
        })
    }
}

/// The vertical pass of one output row over one plane: the source rows under output row `oy`,
/// weighted, into `acc` (the pass's `n` samples; `S` bytes per sample). In range: `check`
/// validated every row of the plane, and the pass's pixel range lies inside a row.
#[inline(always)]
pub(super) fn vertical<const S: usize>(
    acc: &mut [f32],
    sum: &mut [u16],
    data: &[u8],
    r: Rows,
    pass: &PlanePass,
    oy: usize,
) {
    let n = acc.len() * S;
    let ty = &pass.y[oy];
    let src = |j: usize| {
        let at = r.at(ty.start + j) + pass.x0 * pass.bpp * S;
        &data[at..at + n]
    };
    let w = &ty.weights;
    if pass.y_sum[oy] {
        // (8-bit samples only: `make_passes` never sums wider ones.)
        let last = w.len() - 1;
        // Area averaging: the interior rows share one weight. Sum them exactly in u16 (16
        // samples per instruction), then one multiply-add; the two partial edge rows as floats.
        let sum = &mut sum[..acc.len()];
        vsum2(sum, src(1), src(2));
        for k in 3..last {
            vsum(sum, src(k));
        }
        vinit2::<S>(acc, src(0), w[0], src(last), w[last]);
        vacc_sum(acc, sum, w[1]);
    } else {
        // Two source rows per sweep over the accumulator.
        let mut j = if w.len() >= 2 {
            vinit2::<S>(acc, src(0), w[0], src(1), w[1]);
            2
        } else {
            vinit::<S>(acc, src(0), w[0]);
            1
        };
        while j + 1 < w.len() {
            vacc2::<S>(acc, src(j), w[j], src(j + 1), w[j + 1]);
            j += 2;
        }
        if j < w.len() {
            vacc::<S>(acc, src(j), w[j]);
        }
    }
}

/// One sample of `S` bytes (a byte, or a 16-bit little-endian word) as a float.
#[inline(always)]
pub(super) fn sample<const S: usize>(p: &[u8]) -> f32 {
    if S == 1 {
        p[0] as f32
    } else {
        u16::from_le_bytes([p[0], p[1]]) as f32
    }
}

/// `acc = w * src` (samples of `S` bytes to float), vectorised.
#[inline(always)]
pub(super) fn vinit<const S: usize>(acc: &mut [f32], src: &[u8], w: f32) {
    if S == 1 {
        for (a, &p) in acc.iter_mut().zip(src) {
            *a = w * p as f32;
        }
    } else {
        for (a, p) in acc.iter_mut().zip(src.chunks_exact(S)) {
            *a = w * sample::<S>(p);
        }
    }
}

/// `acc = w0 * s0 + w1 * s1`, vectorised.
#[inline(always)]
pub(super) fn vinit2<const S: usize>(acc: &mut [f32], s0: &[u8], w0: f32, s1: &[u8], w1: f32) {
    if S == 1 {
        for ((a, &p), &q) in acc.iter_mut().zip(s0).zip(s1) {
            *a = w0 * p as f32 + w1 * q as f32;
        }
    } else {
        for ((a, p), q) in acc
            .iter_mut()
            .zip(s0.chunks_exact(S))
            .zip(s1.chunks_exact(S))
        {
            *a = w0 * sample::<S>(p) + w1 * sample::<S>(q);
        }
    }
}

/// `acc += w0 * s0 + w1 * s1`, vectorised.
#[inline(always)]
pub(super) fn vacc2<const S: usize>(acc: &mut [f32], s0: &[u8], w0: f32, s1: &[u8], w1: f32) {
    if S == 1 {
        for ((a, &p), &q) in acc.iter_mut().zip(s0).zip(s1) {
            *a = *a + w0 * p as f32 + w1 * q as f32;
        }
    } else {
        for ((a, p), q) in acc
            .iter_mut()
            .zip(s0.chunks_exact(S))
            .zip(s1.chunks_exact(S))
        {
            *a = *a + w0 * sample::<S>(p) + w1 * sample::<S>(q);
        }
    }
}

/// `sum = s0 + s1` (u8 samples to u16), vectorised.
#[inline(always)]
pub(super) fn vsum2(sum: &mut [u16], s0: &[u8], s1: &[u8]) {
    for ((s, &p), &q) in sum.iter_mut().zip(s0).zip(s1) {
        *s = p as u16 + q as u16;
    }
}

/// `sum += src` (u8 samples to u16), vectorised; the caller bounds the rows summed.
#[inline(always)]
pub(super) fn vsum(sum: &mut [u16], src: &[u8]) {
    for (s, &p) in sum.iter_mut().zip(src) {
        *s += p as u16;
    }
}

/// `acc += w * sum`, vectorised.
#[inline(always)]
pub(super) fn vacc_sum(acc: &mut [f32], sum: &[u16], w: f32) {
    for (a, &s) in acc.iter_mut().zip(sum) {
        *a += w * s as f32;
    }
}

/// `acc += w * src`, vectorised.
#[inline(always)]
pub(super) fn vacc<const S: usize>(acc: &mut [f32], src: &[u8], w: f32) {
    if S == 1 {
        for (a, &p) in acc.iter_mut().zip(src) {
            *a += w * p as f32;
        }
    } else {
        for (a, p) in acc.iter_mut().zip(src.chunks_exact(S)) {
            *a += w * sample::<S>(p);
        }
    }
}

/// Horizontal taps over one vertically averaged row of `B` samples per pixel, into `out`: `B`
/// rows of the output width, one per sample.
#[inline(always)]
pub(super) fn hpass<const B: usize>(acc: &[f32], pass: &PlanePass, out: &mut [f32]) {
    if B > 1 && pass.chans.len() == 1 && pass.x.t <= 10 {
        // One sample of several is used (packed 4:2:2 luma): the others are never computed.
        let n = pass.x.start.len();
        let c = pass.chans[0].0;
        let out = &mut out[c * n..(c + 1) * n];
        return match pass.x.t {
            1 => hpass_one::<B, 1>(acc, pass, c, out),
            2 => hpass_one::<B, 2>(acc, pass, c, out),
            3 => hpass_one::<B, 3>(acc, pass, c, out),
            4 => hpass_one::<B, 4>(acc, pass, c, out),
            5 => hpass_one::<B, 5>(acc, pass, c, out),
            6 => hpass_one::<B, 6>(acc, pass, c, out),
            7 => hpass_one::<B, 7>(acc, pass, c, out),
            8 => hpass_one::<B, 8>(acc, pass, c, out),
            9 => hpass_one::<B, 9>(acc, pass, c, out),
            _ => hpass_one::<B, 10>(acc, pass, c, out),
        };
    }
    match pass.x.t {
        1 => hpass_t::<B, 1>(acc, pass, out),
        2 => hpass_t::<B, 2>(acc, pass, out),
        3 => hpass_t::<B, 3>(acc, pass, out),
        4 => hpass_t::<B, 4>(acc, pass, out),
        5 => hpass_t::<B, 5>(acc, pass, out),
        6 => hpass_t::<B, 6>(acc, pass, out),
        7 => hpass_t::<B, 7>(acc, pass, out),
        8 => hpass_t::<B, 8>(acc, pass, out),
        9 => hpass_t::<B, 9>(acc, pass, out),
        10 => hpass_t::<B, 10>(acc, pass, out),
        _ => hpass_any::<B>(acc, pass, out),
    }
}

/// [`hpass`] with `T` taps per output (unrolled).
#[inline(always)]
pub(super) fn hpass_t<const B: usize, const T: usize>(
    acc: &[f32],
    pass: &PlanePass,
    out: &mut [f32],
) {
    let n = pass.x.start.len();
    let mut rows = out.chunks_exact_mut(n);
    let outs: [&mut [f32]; B] = std::array::from_fn(|_| rows.next().expect("B rows"));
    for (o, (&st, w)) in pass
        .x
        .start
        .iter()
        .zip(pass.x.w.chunks_exact(T))
        .enumerate()
    {
        let w: &[f32; T] = w.try_into().expect("T taps");
        let src: &[f32] = &acc[st * B..(st + T) * B];
        let mut a = [0f32; B];
        for k in 0..T {
            for c in 0..B {
                a[c] += w[k] * src[k * B + c];
            }
        }
        for c in 0..B {
            outs[c][o] = a[c];
        }
    }
}

/// [`hpass`] of sample `c` only, `T` taps per output (unrolled), into one output row.
#[inline(always)]
pub(super) fn hpass_one<const B: usize, const T: usize>(
    acc: &[f32],
    pass: &PlanePass,
    c: usize,
    out: &mut [f32],
) {
    for ((&st, w), o) in pass
        .x
        .start
        .iter()
        .zip(pass.x.w.chunks_exact(T))
        .zip(out.iter_mut())
    {
        let w: &[f32; T] = w.try_into().expect("T taps");
        let src: &[f32] = &acc[st * B..(st + T) * B];
        let mut a = 0f32;
        for k in 0..T {
            a += w[k] * src[k * B + c];
        }
        *o = a;
    }
}

#[inline(always)]
pub(super) fn hpass_any<const B: usize>(acc: &[f32], pass: &PlanePass, out: &mut [f32]) {
    let t = pass.x.t;
    let n = pass.x.start.len();
    let mut rows = out.chunks_exact_mut(n);
    let outs: [&mut [f32]; B] = std::array::from_fn(|_| rows.next().expect("B rows"));
    for (o, (&st, w)) in pass
        .x
        .start
        .iter()
        .zip(pass.x.w.chunks_exact(t))
        .enumerate()
    {
        let src = &acc[st * B..(st + t) * B];
        let mut a = [0f32; B];
        for (&wk, p) in w.iter().zip(src.chunks_exact(B)) {
            for c in 0..B {
                a[c] += wk * p[c];
            }
        }
        for c in 0..B {
            outs[c][o] = a[c];
        }
    }
}
