//! Test helper shared by the crate's unit tests and the integration tests: pack an RGB picture into
//! any supported pixel format (with `pad` bytes of row padding), the way a decoder would.

#[allow(unused_imports)]
use super::{PixelFormat, RawFrame, YuvMatrix};

/// Test and tool helper: pack an RGB image (tightly packed rows) into `format` with the given
/// row padding, using the BT.601 limited-range matrix for YUV. Returns the planes and strides.
///
/// Samples wider than 8 bits hold the 8-bit code value `v` as `v * 4` (10-bit), `v * 16`
/// (12-bit), `v * 256` (P016; `v * 257` for GRAY16_LE, full scale 65535, as videoconvert
/// writes it) in the low bits of a little-endian word, or MSB-aligned (P010,
/// P012: `v * 4 << 6`, `v * 16 << 4`); chroma is the average of the RGB under each subsampled
/// block.
pub fn pack_rgb(
    rgb: &[u8],
    width: u32,
    height: u32,
    format: PixelFormat,
    pad: usize,
) -> (Vec<Vec<u8>>, Vec<usize>) {
    use PixelFormat as F;
    let (w, h) = (width as usize, height as usize);
    let px = |x: usize, y: usize| {
        let i = 3 * (y * w + x);
        [rgb[i] as f32, rgb[i + 1] as f32, rgb[i + 2] as f32]
    };
    let to_yuv = |p: [f32; 3]| {
        let m = YuvMatrix::BT601;
        let y = m.kr * p[0] + (1.0 - m.kr - m.kb) * p[1] + m.kb * p[2];
        let cb = (p[2] - y) / (2.0 * (1.0 - m.kb));
        let cr = (p[0] - y) / (2.0 * (1.0 - m.kr));
        [
            16.0 + y * 219.0 / 255.0,
            128.0 + cb * 224.0 / 255.0,
            128.0 + cr * 224.0 / 255.0,
        ]
    };
    // An 8-bit code value as the stored sample, and the bytes of a sample.
    let (bytes, max, scale, lsh) = match format {
        F::I42010le | F::I42210le | F::Y44410le => (2, 1023.0, 4.0, 0),
        F::I42012le | F::I42212le | F::Y44412le => (2, 4095.0, 16.0, 0),
        F::P01010le => (2, 1023.0, 4.0, 6),
        F::P012Le => (2, 4095.0, 16.0, 4),
        F::P016Le => (2, 65535.0, 256.0, 0),
        F::Gray16Le => (2, 65535.0, 257.0, 0),
        _ => (1, 255.0, 1.0, 0),
    };
    let enc = |v: f32| ((v * scale).round().clamp(0.0, max) as u16) << lsh;
    // A plane of `units` samples per row and `rows` rows, padded.
    let plane = |units: usize, rows: usize| {
        let stride = units * bytes + pad;
        (vec![0u8; stride * rows], stride)
    };
    let put = |p: &mut (Vec<u8>, usize), unit: usize, row: usize, v: f32| {
        let at = row * p.1 + unit * bytes;
        let s = enc(v);
        if bytes == 1 {
            p.0[at] = s as u8;
        } else {
            p.0[at..at + 2].copy_from_slice(&s.to_le_bytes());
        }
    };
    let done = |planes: Vec<(Vec<u8>, usize)>| -> (Vec<Vec<u8>>, Vec<usize>) {
        planes.into_iter().unzip()
    };
    // Interleaved RGB-like formats: `order[k]` is the channel of sample k (3: opaque alpha).
    let interleaved = |order: &[usize]| {
        let mut p = plane(order.len() * w, h);
        for y in 0..h {
            for x in 0..w {
                let c = px(x, y);
                for (k, &o) in order.iter().enumerate() {
                    put(
                        &mut p,
                        order.len() * x + k,
                        y,
                        if o < 3 { c[o] } else { 255.0 },
                    );
                }
            }
        }
        done(vec![p])
    };
    // The chroma (U, V) of the `sx` x `sy` block at (cx, cy).
    let chroma = |cx: usize, cy: usize, sx: usize, sy: usize| {
        let mut s = [0f32; 3];
        let mut n = 0.0;
        for y in cy * sy..((cy + 1) * sy).min(h) {
            for x in cx * sx..((cx + 1) * sx).min(w) {
                let p = px(x, y);
                s = [s[0] + p[0], s[1] + p[1], s[2] + p[2]];
                n += 1.0;
            }
        }
        let yuv = to_yuv([s[0] / n, s[1] / n, s[2] / n]);
        (yuv[1], yuv[2])
    };
    let luma = || {
        let mut p = plane(w, h);
        for y in 0..h {
            for x in 0..w {
                put(&mut p, x, y, to_yuv(px(x, y))[0]);
            }
        }
        p
    };
    match format {
        F::Rgb => interleaved(&[0, 1, 2]),
        F::Bgr => interleaved(&[2, 1, 0]),
        F::Rgbx | F::Rgba => interleaved(&[0, 1, 2, 3]),
        F::Bgrx | F::Bgra => interleaved(&[2, 1, 0, 3]),
        F::Gray8 | F::Gray16Le => {
            // The green channel (the grey pictures have R = G = B).
            let mut p = plane(w, h);
            for y in 0..h {
                for x in 0..w {
                    put(&mut p, x, y, px(x, y)[1]);
                }
            }
            done(vec![p])
        }
        F::Gbr => {
            let mut planes = [plane(w, h), plane(w, h), plane(w, h)];
            for y in 0..h {
                for x in 0..w {
                    let c = px(x, y);
                    for (p, ch) in planes.iter_mut().zip([1, 2, 0]) {
                        put(p, x, y, c[ch]);
                    }
                }
            }
            done(planes.into())
        }
        F::Nv12 | F::Nv21 | F::P01010le | F::P012Le | F::P016Le => {
            let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
            let mut uv = plane(2 * cw, ch);
            let (ui, vi) = if format == F::Nv21 { (1, 0) } else { (0, 1) };
            for cy in 0..ch {
                for cx in 0..cw {
                    let (u, v) = chroma(cx, cy, 2, 2);
                    put(&mut uv, 2 * cx + ui, cy, u);
                    put(&mut uv, 2 * cx + vi, cy, v);
                }
            }
            done(vec![luma(), uv])
        }
        F::I420
        | F::I42010le
        | F::I42012le
        | F::Y42b
        | F::I42210le
        | F::I42212le
        | F::Y444
        | F::Y44410le
        | F::Y44412le => {
            let (sx, sy) = match format {
                F::I420 | F::I42010le | F::I42012le => (2, 2),
                F::Y42b | F::I42210le | F::I42212le => (2, 1),
                _ => (1, 1),
            };
            let (cw, ch) = (w.div_ceil(sx), h.div_ceil(sy));
            let (mut up, mut vp) = (plane(cw, ch), plane(cw, ch));
            for cy in 0..ch {
                for cx in 0..cw {
                    let (u, v) = chroma(cx, cy, sx, sy);
                    put(&mut up, cx, cy, u);
                    put(&mut vp, cx, cy, v);
                }
            }
            done(vec![luma(), up, vp])
        }
        F::Yuy2 | F::Uyvy => {
            // Pairs of pixels as Y0 U Y1 V (YUY2) or U Y0 V Y1 (UYVY); an odd last pixel's
            // pair repeats its luma.
            let cw = w.div_ceil(2);
            let mut p = plane(4 * cw, h);
            let (y0, u, y1, v) = if format == F::Yuy2 {
                (0, 1, 2, 3)
            } else {
                (1, 0, 3, 2)
            };
            for y in 0..h {
                for cx in 0..cw {
                    let (cu, cv) = chroma(cx, y, 2, 1);
                    let l0 = to_yuv(px(2 * cx, y))[0];
                    let l1 = to_yuv(px((2 * cx + 1).min(w - 1), y))[0];
                    put(&mut p, 4 * cx + y0, y, l0);
                    put(&mut p, 4 * cx + u, y, cu);
                    put(&mut p, 4 * cx + y1, y, l1);
                    put(&mut p, 4 * cx + v, y, cv);
                }
            }
            done(vec![p])
        }
    }
}

/// The planes and strides [`pack_rgb`] returns, as the `RawFrame` the preprocessor reads.
pub fn raw_frame<'a>(
    format: PixelFormat,
    width: u32,
    height: u32,
    planes: &'a [Vec<u8>],
    strides: &[usize],
) -> RawFrame<'a> {
    let plane = |i: usize| planes.get(i).map(|p| &p[..]).unwrap_or(&[]);
    let stride = |i: usize| strides.get(i).copied().unwrap_or(0) as isize;
    RawFrame {
        format,
        width,
        height,
        planes: [plane(0), plane(1), plane(2)],
        strides: [stride(0), stride(1), stride(2)],
    }
}
