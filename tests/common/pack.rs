//! Test helper shared by the crate's unit tests and the integration tests: pack an RGB picture into
//! any supported pixel format (with `pad` bytes of row padding), the way a decoder would.

#[allow(unused_imports)]
use super::{PixelFormat, RawFrame, YuvMatrix};

/// Test and tool helper: pack an RGB image (tightly packed rows) into `format` with the given
/// row padding, using the BT.601 limited-range matrix for YUV. Returns the planes and strides.
pub fn pack_rgb(
    rgb: &[u8],
    width: u32,
    height: u32,
    format: PixelFormat,
    pad: usize,
) -> (Vec<Vec<u8>>, Vec<usize>) {
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
        (
            (16.0 + y * 219.0 / 255.0).round().clamp(0.0, 255.0) as u8,
            (128.0 + cb * 224.0 / 255.0).round().clamp(0.0, 255.0) as u8,
            (128.0 + cr * 224.0 / 255.0).round().clamp(0.0, 255.0) as u8,
        )
    };
    let packed = |bpp: usize, order: &[usize]| {
        let stride = w * bpp + pad;
        let mut out = vec![0u8; stride * h];
        for y in 0..h {
            for x in 0..w {
                let p = px(x, y);
                for (k, &c) in order.iter().enumerate() {
                    out[y * stride + x * bpp + k] = if c < 3 { p[c] as u8 } else { 255 };
                }
            }
        }
        (vec![out], vec![stride])
    };
    match format {
        PixelFormat::Rgb => packed(3, &[0, 1, 2]),
        PixelFormat::Bgr => packed(3, &[2, 1, 0]),
        PixelFormat::Rgbx | PixelFormat::Rgba => packed(4, &[0, 1, 2, 3]),
        PixelFormat::Bgrx | PixelFormat::Bgra => packed(4, &[2, 1, 0, 3]),
        PixelFormat::Gray8 => {
            let stride = w + pad;
            let mut out = vec![0u8; stride * h];
            for y in 0..h {
                for x in 0..w {
                    out[y * stride + x] = px(x, y)[1] as u8;
                }
            }
            (vec![out], vec![stride])
        }
        PixelFormat::Nv12 | PixelFormat::I420 => {
            let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
            let ys = w + pad;
            let mut yp = vec![0u8; ys * h];
            for y in 0..h {
                for x in 0..w {
                    yp[y * ys + x] = to_yuv(px(x, y)).0;
                }
            }
            // Chroma: average of the 2x2 block's RGB.
            let chroma = |cx: usize, cy: usize| {
                let mut s = [0f32; 3];
                let mut n = 0.0;
                for dy in 0..2 {
                    for dx in 0..2 {
                        let (x, y) = (2 * cx + dx, 2 * cy + dy);
                        if x < w && y < h {
                            let p = px(x, y);
                            s = [s[0] + p[0], s[1] + p[1], s[2] + p[2]];
                            n += 1.0;
                        }
                    }
                }
                let (_, u, v) = to_yuv([s[0] / n, s[1] / n, s[2] / n]);
                (u, v)
            };
            if format == PixelFormat::Nv12 {
                let cs = 2 * cw + pad;
                let mut uv = vec![0u8; cs * ch];
                for cy in 0..ch {
                    for cx in 0..cw {
                        let (u, v) = chroma(cx, cy);
                        uv[cy * cs + 2 * cx] = u;
                        uv[cy * cs + 2 * cx + 1] = v;
                    }
                }
                (vec![yp, uv], vec![ys, cs])
            } else {
                let cs = cw + pad;
                let mut up = vec![0u8; cs * ch];
                let mut vp = vec![0u8; cs * ch];
                for cy in 0..ch {
                    for cx in 0..cw {
                        let (u, v) = chroma(cx, cy);
                        up[cy * cs + cx] = u;
                        vp[cy * cs + cx] = v;
                    }
                }
                (vec![yp, up, vp], vec![ys, cs, cs])
            }
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
