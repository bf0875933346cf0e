//! Preprocessing: straight from a raw video frame (any supported format, any stride) to the model's
//! float32 CHW input tensor, in one pass, so decoders can link to `leangate` without `videoconvert`.
//!
//! Steps, fused: colour conversion to RGB (YUV through the caps' matrix and range), geometric mapping
//! (`short-side-crop`: scale so the short side fits, centre-crop the long side, as the paper's loader
//! does; or `stretch`), area-averaging when shrinking / bilinear when enlarging (separable), scale
//! to [0,1], then `(x - mean) / std` per channel.

mod kernels;
pub(crate) use kernels::has_avx2;
use kernels::*;

/// Pixel formats accepted by the element (its caps list exactly these, in this order of
/// preference): packed RGB and grey, and what decoders output for phone and camera video (8-, 10-,
/// 12- and 16-bit YUV in 4:2:0, 4:2:2 and 4:4:4, planar and semi-planar and packed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    Rgb,
    Bgr,
    Rgbx,
    Rgba,
    Bgrx,
    Bgra,
    Gray8,
    Nv12,
    I420,
    Nv21,
    Yuy2,
    Uyvy,
    Y42b,
    Y444,
    Gbr,
    Gray16Le,
    I42010le,
    I42012le,
    P01010le,
    P012Le,
    P016Le,
    I42210le,
    I42212le,
    Y44410le,
    Y44412le,
}

/// Where one pass of the preprocessor reads its samples: plane `plane`, in units of `bpp`
/// interleaved samples covering `sub.0` pixels across and `sub.1` rows down (2 for subsampled
/// chroma, and for the chroma of packed 4:2:2), and which sample of a unit feeds which output slot
/// (R, G, B, or Y, U, V).
#[derive(Debug, Clone, Copy)]
struct PassDesc {
    plane: usize,
    bpp: usize,
    sub: (usize, usize),
    chans: &'static [(usize, usize)],
}

/// How a format lays out its samples in memory.
#[derive(Debug, Clone, Copy)]
struct FormatDesc {
    /// Bytes per sample: 1, or 2 (a 16-bit little-endian word).
    bytes: usize,
    /// Bits a stored sample has above an 8-bit code value: 0; 2 for 10-bit and 4 for 12-bit
    /// samples (in the low bits of their word); 8 for 16-bit and MSB-aligned words (P010, P012).
    /// The same scaling as `videoconvert`'s.
    shift: u32,
    /// YUV (converted to RGB through the caps' matrix and range) rather than RGB or grey.
    yuv: bool,
    /// Per plane: samples per unit and the unit's size in pixels (across, down).
    planes: &'static [(usize, (usize, usize))],
    passes: &'static [PassDesc],
}

const fn pass(
    plane: usize,
    bpp: usize,
    sub: (usize, usize),
    chans: &'static [(usize, usize)],
) -> PassDesc {
    PassDesc {
        plane,
        bpp,
        sub,
        chans,
    }
}

type Planes = &'static [(usize, (usize, usize))];

const FULL: (usize, usize) = (1, 1);
const RGB: &[(usize, usize)] = &[(0, 0), (1, 1), (2, 2)];
const BGR: &[(usize, usize)] = &[(2, 0), (1, 1), (0, 2)];
const S0: &[(usize, usize)] = &[(0, 0)];
const S1: &[(usize, usize)] = &[(0, 1)];
const S2: &[(usize, usize)] = &[(0, 2)];
const LUMA: PassDesc = pass(0, 1, FULL, S0);

const PACKED_3: (Planes, &[PassDesc]) = (&[(3, FULL)], &[pass(0, 3, FULL, RGB)]);
const PACKED_3_BGR: (Planes, &[PassDesc]) = (&[(3, FULL)], &[pass(0, 3, FULL, BGR)]);
const PACKED_4: (Planes, &[PassDesc]) = (&[(4, FULL)], &[pass(0, 4, FULL, RGB)]);
const PACKED_4_BGR: (Planes, &[PassDesc]) = (&[(4, FULL)], &[pass(0, 4, FULL, BGR)]);
const GREY: (Planes, &[PassDesc]) = (&[(1, FULL)], &[pass(0, 1, FULL, &[(0, 0), (0, 1), (0, 2)])]);
/// Planes G, B, R.
const GBR: (Planes, &[PassDesc]) = (
    &[(1, FULL), (1, FULL), (1, FULL)],
    &[
        pass(0, 1, FULL, S1),
        pass(1, 1, FULL, S2),
        pass(2, 1, FULL, S0),
    ],
);
/// Y plane, then U and V interleaved at half width and height (NV12, P010; NV21: V first).
const NV12: (Planes, &[PassDesc]) = (
    &[(1, FULL), (2, (2, 2))],
    &[LUMA, pass(1, 2, (2, 2), &[(0, 1), (1, 2)])],
);
const NV21: (Planes, &[PassDesc]) = (
    &[(1, FULL), (2, (2, 2))],
    &[LUMA, pass(1, 2, (2, 2), &[(1, 1), (0, 2)])],
);
/// Planes Y, U, V; chroma at half width and height (4:2:0), half width (4:2:2), or full (4:4:4).
const I420: (Planes, &[PassDesc]) = (
    &[(1, FULL), (1, (2, 2)), (1, (2, 2))],
    &[LUMA, pass(1, 1, (2, 2), S1), pass(2, 1, (2, 2), S2)],
);
const I422: (Planes, &[PassDesc]) = (
    &[(1, FULL), (1, (2, 1)), (1, (2, 1))],
    &[LUMA, pass(1, 1, (2, 1), S1), pass(2, 1, (2, 1), S2)],
);
const I444: (Planes, &[PassDesc]) = (
    &[(1, FULL), (1, FULL), (1, FULL)],
    &[LUMA, pass(1, 1, FULL, S1), pass(2, 1, FULL, S2)],
);
/// Packed 4:2:2, two pixels in four samples `Y0 U Y1 V` (YUY2) or `U Y0 V Y1` (UYVY): the chroma
/// read per pair of pixels (four samples), the luma per pixel (two samples). Chroma first: its
/// vertically averaged row holds every luma sample too, and the fast path reads luma from it.
const YUY2: (Planes, &[PassDesc]) = (
    &[(4, (2, 1))],
    &[pass(0, 4, (2, 1), &[(1, 1), (3, 2)]), pass(0, 2, FULL, S0)],
);
const UYVY: (Planes, &[PassDesc]) = (
    &[(4, (2, 1))],
    &[
        pass(0, 4, (2, 1), &[(0, 1), (2, 2)]),
        pass(0, 2, FULL, &[(1, 0)]),
    ],
);

const fn rgb(
    bytes: usize,
    shift: u32,
    (planes, passes): (Planes, &'static [PassDesc]),
) -> FormatDesc {
    FormatDesc {
        bytes,
        shift,
        yuv: false,
        planes,
        passes,
    }
}

const fn yuv(
    bytes: usize,
    shift: u32,
    (planes, passes): (Planes, &'static [PassDesc]),
) -> FormatDesc {
    FormatDesc {
        bytes,
        shift,
        yuv: true,
        planes,
        passes,
    }
}

impl PixelFormat {
    pub const ALL: [PixelFormat; 25] = [
        PixelFormat::Rgb,
        PixelFormat::Rgbx,
        PixelFormat::Rgba,
        PixelFormat::Bgr,
        PixelFormat::Bgrx,
        PixelFormat::Bgra,
        PixelFormat::Gray8,
        PixelFormat::Nv12,
        PixelFormat::I420,
        PixelFormat::Nv21,
        PixelFormat::Yuy2,
        PixelFormat::Uyvy,
        PixelFormat::Y42b,
        PixelFormat::Y444,
        PixelFormat::Gbr,
        PixelFormat::Gray16Le,
        PixelFormat::I42010le,
        PixelFormat::I42012le,
        PixelFormat::P01010le,
        PixelFormat::P012Le,
        PixelFormat::P016Le,
        PixelFormat::I42210le,
        PixelFormat::I42212le,
        PixelFormat::Y44410le,
        PixelFormat::Y44412le,
    ];

    pub fn from_video_format(f: gst_video::VideoFormat) -> Option<PixelFormat> {
        PixelFormat::ALL
            .into_iter()
            .find(|p| p.to_video_format() == f)
    }

    pub fn to_video_format(self) -> gst_video::VideoFormat {
        use gst_video::VideoFormat as V;
        match self {
            PixelFormat::Rgb => V::Rgb,
            PixelFormat::Bgr => V::Bgr,
            PixelFormat::Rgbx => V::Rgbx,
            PixelFormat::Rgba => V::Rgba,
            PixelFormat::Bgrx => V::Bgrx,
            PixelFormat::Bgra => V::Bgra,
            PixelFormat::Gray8 => V::Gray8,
            PixelFormat::Nv12 => V::Nv12,
            PixelFormat::I420 => V::I420,
            PixelFormat::Nv21 => V::Nv21,
            PixelFormat::Yuy2 => V::Yuy2,
            PixelFormat::Uyvy => V::Uyvy,
            PixelFormat::Y42b => V::Y42b,
            PixelFormat::Y444 => V::Y444,
            PixelFormat::Gbr => V::Gbr,
            PixelFormat::Gray16Le => V::Gray16Le,
            PixelFormat::I42010le => V::I42010le,
            PixelFormat::I42012le => V::I42012le,
            PixelFormat::P01010le => V::P01010le,
            PixelFormat::P012Le => V::P012Le,
            PixelFormat::P016Le => V::P016Le,
            PixelFormat::I42210le => V::I42210le,
            PixelFormat::I42212le => V::I42212le,
            PixelFormat::Y44410le => V::Y44410le,
            PixelFormat::Y44412le => V::Y44412le,
        }
    }

    fn desc(self) -> FormatDesc {
        match self {
            PixelFormat::Rgb => rgb(1, 0, PACKED_3),
            PixelFormat::Bgr => rgb(1, 0, PACKED_3_BGR),
            PixelFormat::Rgbx | PixelFormat::Rgba => rgb(1, 0, PACKED_4),
            PixelFormat::Bgrx | PixelFormat::Bgra => rgb(1, 0, PACKED_4_BGR),
            PixelFormat::Gbr => rgb(1, 0, GBR),
            PixelFormat::Gray8 => rgb(1, 0, GREY),
            PixelFormat::Gray16Le => rgb(2, 8, GREY),
            PixelFormat::Nv12 => yuv(1, 0, NV12),
            PixelFormat::Nv21 => yuv(1, 0, NV21),
            PixelFormat::P01010le | PixelFormat::P012Le | PixelFormat::P016Le => yuv(2, 8, NV12),
            PixelFormat::I420 => yuv(1, 0, I420),
            PixelFormat::I42010le => yuv(2, 2, I420),
            PixelFormat::I42012le => yuv(2, 4, I420),
            PixelFormat::Y42b => yuv(1, 0, I422),
            PixelFormat::I42210le => yuv(2, 2, I422),
            PixelFormat::I42212le => yuv(2, 4, I422),
            PixelFormat::Y444 => yuv(1, 0, I444),
            PixelFormat::Y44410le => yuv(2, 2, I444),
            PixelFormat::Y44412le => yuv(2, 4, I444),
            PixelFormat::Yuy2 => yuv(1, 0, YUY2),
            PixelFormat::Uyvy => yuv(1, 0, UYVY),
        }
    }

    /// What one step of a stored sample is worth in 8-bit code values. A full-range 16-bit grey
    /// sample spans 0..=65535 for 0..=255 (`videoconvert` writes GRAY8's `v` as `v * 257`), so
    /// 65535 reads as full scale, 1.0, like 255 in every 8-bit format; the others scale by their
    /// extra bits (`shift`), as `videoconvert` does.
    fn unit(self) -> f32 {
        match self {
            PixelFormat::Gray16Le => 1.0 / 257.0,
            _ => 1.0 / (1u32 << self.desc().shift) as f32,
        }
    }

    /// Number of planes.
    pub fn n_planes(self) -> usize {
        self.desc().planes.len()
    }

    /// YUV (converted through the caps' colour matrix), not RGB or grey.
    pub fn is_yuv(self) -> bool {
        self.desc().yuv
    }

    /// One grey channel.
    pub fn is_grey(self) -> bool {
        matches!(self, PixelFormat::Gray8 | PixelFormat::Gray16Le)
    }

    /// Bytes per row and rows of each plane of a tightly packed `w`x`h` frame (`(0, 0)` past the
    /// last plane).
    pub fn plane_sizes(self, w: usize, h: usize) -> [(usize, usize); 3] {
        let d = self.desc();
        let mut out = [(0, 0); 3];
        for (o, &(spu, (sx, sy))) in out.iter_mut().zip(d.planes) {
            *o = (w.div_ceil(sx) * spu * d.bytes, h.div_ceil(sy));
        }
        out
    }
}

/// The error for fixed raw-video caps (system memory) in a format the element cannot read: a
/// message naming the format and the fix, and details listing the formats it reads; `None` for
/// anything else (a readable format, unfixed caps, other media). The sink posts it where
/// negotiation refuses such caps, so that a decoder's output it cannot read (e.g. `Y41B` from a
/// DV or FFV1 4:1:1 clip) says more than the decoder's `not-negotiated`.
pub fn unreadable_format_error(caps: &gst::CapsRef) -> Option<(String, String)> {
    if !caps.is_fixed() {
        return None;
    }
    let s = caps.structure(0)?;
    let system = caps
        .features(0)
        .is_none_or(|f| f.is_equal(&gst::CAPS_FEATURES_MEMORY_SYSTEM_MEMORY));
    if s.name() != "video/x-raw" || !system {
        return None;
    }
    let name = s.get::<&str>("format").ok()?;
    if PixelFormat::from_video_format(gst_video::VideoFormat::from_string(name)).is_some() {
        return None;
    }
    let readable: Vec<&str> = PixelFormat::ALL
        .iter()
        .map(|f| f.to_video_format().to_str().as_str())
        .collect();
    Some((
        format!(
            "leangate cannot read {name} video: put videoconvert before it (`... ! videoconvert \
             ! leangate`)"
        ),
        format!("caps {caps}; leangate reads {}", readable.join(", ")),
    ))
}

/// How the frame is mapped onto the model's input rectangle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ResizeMode {
    /// Resize so the short side matches, then centre-crop (the paper's loader; the default).
    #[default]
    ShortSideCrop,
    /// Resize each axis independently (aspect ratio not kept).
    Stretch,
}

impl ResizeMode {
    pub fn parse(s: &str) -> Option<ResizeMode> {
        match s.trim() {
            "short-side-crop" => Some(ResizeMode::ShortSideCrop),
            "stretch" => Some(ResizeMode::Stretch),
            _ => None,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            ResizeMode::ShortSideCrop => "short-side-crop",
            ResizeMode::Stretch => "stretch",
        }
    }
}

/// YUV → RGB matrix and range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct YuvMatrix {
    pub kr: f32,
    pub kb: f32,
    pub full_range: bool,
}

impl YuvMatrix {
    pub const BT601: YuvMatrix = YuvMatrix {
        kr: 0.299,
        kb: 0.114,
        full_range: false,
    };
    pub const BT709: YuvMatrix = YuvMatrix {
        kr: 0.2126,
        kb: 0.0722,
        full_range: false,
    };

    /// From the caps' colorimetry (unknown matrices fall back to BT.601 below 720 lines, BT.709 above,
    /// as GStreamer does).
    pub fn from_colorimetry(c: &gst_video::VideoColorimetry, height: u32) -> YuvMatrix {
        use gst_video::VideoColorMatrix as M;
        let (kr, kb) = match c.matrix() {
            M::Bt601 => (0.299, 0.114),
            M::Bt709 => (0.2126, 0.0722),
            M::Bt2020 => (0.2627, 0.0593),
            M::Smpte240m => (0.212, 0.087),
            M::Fcc => (0.30, 0.11),
            _ if height >= 720 => (0.2126, 0.0722),
            _ => (0.299, 0.114),
        };
        YuvMatrix {
            kr,
            kb,
            full_range: c.range() == gst_video::VideoColorRange::Range0_255,
        }
    }

    /// The conversion as one affine map (for the fast path): `R = ys (Y - y0) + rv (V - 128)`,
    /// `G = ys (Y - y0) - gu (U - 128) - gv (V - 128)`, `B = ys (Y - y0) + bu (U - 128)`.
    fn coefficients(self) -> YuvCoefficients {
        let (ys, y0, cs) = if self.full_range {
            (1.0, 0.0, 1.0)
        } else {
            (255.0 / 219.0, 16.0, 255.0 / 224.0)
        };
        let kg = 1.0 - self.kr - self.kb;
        let rv = 2.0 * (1.0 - self.kr) * cs;
        let bu = 2.0 * (1.0 - self.kb) * cs;
        YuvCoefficients {
            ys,
            y0,
            rv,
            bu,
            gu: self.kb * bu / kg,
            gv: self.kr * rv / kg,
        }
    }

    /// Convert (averaged) Y, U, V code values to RGB in 0..255. The map is affine, so averaging
    /// YUV first and converting once per output pixel equals converting every source pixel and
    /// averaging (up to the final clamp).
    #[inline(always)]
    fn to_rgb(self, yuv: [f32; 3]) -> [f32; 3] {
        let [y, u, v] = yuv;
        let (y, cb, cr) = if self.full_range {
            (y, u - 128.0, v - 128.0)
        } else {
            (
                (y - 16.0) * (255.0 / 219.0),
                (u - 128.0) * (255.0 / 224.0),
                (v - 128.0) * (255.0 / 224.0),
            )
        };
        let kg = 1.0 - self.kr - self.kb;
        let r = y + 2.0 * (1.0 - self.kr) * cr;
        let b = y + 2.0 * (1.0 - self.kb) * cb;
        let g = (y - self.kr * r - self.kb * b) / kg;
        [
            r.clamp(0.0, 255.0),
            g.clamp(0.0, 255.0),
            b.clamp(0.0, 255.0),
        ]
    }
}

#[derive(Debug, Clone, Copy)]
struct YuvCoefficients {
    ys: f32,
    y0: f32,
    rv: f32,
    bu: f32,
    gu: f32,
    gv: f32,
}

/// A borrowed raw frame: up to three planes with their strides.
///
/// `planes[p]` holds plane `p`'s bytes from its lowest address. A positive stride is the usual
/// top-down layout (row `y` starts at `y * stride`); a negative stride is a bottom-up image
/// (row 0, the top of the picture, is the last row in memory: row `y` starts at
/// `(rows - 1 - y) * |stride|`), as GstVideoMeta allows and `videoconvert` reads.
#[derive(Debug, Clone, Copy)]
pub struct RawFrame<'a> {
    pub format: PixelFormat,
    pub width: u32,
    pub height: u32,
    pub planes: [&'a [u8]; 3],
    pub strides: [isize; 3],
}

impl<'a> RawFrame<'a> {
    /// A tightly packed top-down RGB picture (`3 * width` bytes a row), as image decoders give.
    pub fn rgb(data: &'a [u8], width: u32, height: u32) -> RawFrame<'a> {
        RawFrame {
            format: PixelFormat::Rgb,
            width,
            height,
            planes: [data, &[], &[]],
            strides: [3 * width as isize, 0, 0],
        }
    }
}

/// Largest accepted frame side, pixels (the resampling taps grow with the frame size).
pub const MAX_FRAME_SIDE: u32 = 1 << 15;

/// A zero-filled `Vec<f32>` of `len` elements, allocated fallibly (a huge model input must be a
/// clear error, not an abort of the host process).
pub fn try_zeroed(len: usize) -> Result<Vec<f32>, PreprocessError> {
    try_filled(len, 0.0f32)
}

pub(crate) fn try_filled<T: Clone>(len: usize, v: T) -> Result<Vec<T>, PreprocessError> {
    let mut out = Vec::new();
    out.try_reserve_exact(len).map_err(|e| {
        PreprocessError(format!(
            "cannot allocate {len} elements of {} bytes: {e}",
            std::mem::size_of::<T>()
        ))
    })?;
    out.resize(len, v);
    Ok(out)
}

/// Row addressing of one checked plane: row `y` starts at `origin + y * stride`.
#[derive(Debug, Clone, Copy, Default)]
struct Rows {
    origin: isize,
    stride: isize,
}

impl Rows {
    #[inline(always)]
    fn at(self, y: usize) -> usize {
        // In range: checked by `Preprocessor::check` for every row of the plane.
        (self.origin + y as isize * self.stride) as usize
    }
}

/// The part of a `src_w` x `src_h` frame the model's picture covers, in source pixels (edges):
/// `((x_off, x_span), (y_off, y_span))` (stretch: all of it; short-side crop: the centre).
pub fn crop(src_w: u32, src_h: u32, spec: &TensorSpec) -> ((f64, f64), (f64, f64)) {
    let (sw, sh) = (src_w as f64, src_h as f64);
    let (dw, dh) = (spec.width as f64, spec.height as f64);
    match spec.resize {
        ResizeMode::Stretch => ((0.0, sw), (0.0, sh)),
        ResizeMode::ShortSideCrop => {
            let s = (sw / dw).min(sh / dh);
            let (cw, ch) = (dw * s, dh * s);
            (((sw - cw) / 2.0, cw), ((sh - ch) / 2.0, ch))
        }
    }
}

/// Model-side parameters of the tensor.
#[derive(Debug, Clone, PartialEq)]
pub struct TensorSpec {
    pub width: u32,
    pub height: u32,
    pub resize: ResizeMode,
    pub mean: [f32; 3],
    pub std: [f32; 3],
}

impl TensorSpec {
    pub fn len(&self) -> usize {
        3 * self.width as usize * self.height as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A frame that cannot be read (wrong size, short plane, bad stride) or a failed allocation.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct PreprocessError(pub String);

/// Resampling taps for one output coordinate: source indices `start..start+weights.len()`.
#[derive(Debug, Clone)]
struct Taps {
    start: usize,
    weights: Vec<f32>,
}

fn make_taps(src_len: usize, dst_len: usize, src_off: f64, src_span: f64) -> Vec<Taps> {
    let scale = src_span / dst_len as f64; // source pixels per output pixel
    (0..dst_len)
        .map(|o| {
            if scale > 1.0 {
                // Area average over [a, b).
                let a = src_off + o as f64 * scale;
                let b = a + scale;
                let i0 = a.floor().max(0.0) as usize;
                let i1 = (b.ceil() as usize).min(src_len);
                let mut w: Vec<f32> = (i0..i1)
                    .map(|i| {
                        let lo = (i as f64).max(a);
                        let hi = ((i + 1) as f64).min(b);
                        (hi - lo).max(0.0) as f32
                    })
                    .collect();
                let sum: f32 = w.iter().sum();
                w.iter_mut().for_each(|x| *x /= sum);
                Taps {
                    start: i0,
                    weights: w,
                }
            } else {
                // Bilinear at the output pixel's centre.
                let c = (src_off + (o as f64 + 0.5) * scale - 0.5).clamp(0.0, (src_len - 1) as f64);
                let i0 = c.floor() as usize;
                let f = (c - i0 as f64) as f32;
                if i0 + 1 < src_len && f > 0.0 {
                    Taps {
                        start: i0,
                        weights: vec![1.0 - f, f],
                    }
                } else {
                    Taps {
                        start: i0,
                        weights: vec![1.0],
                    }
                }
            }
        })
        .collect()
}

/// Converts frames of one format and size into tensors of one spec. Built once per caps.
#[derive(Debug)]
pub struct Preprocessor {
    format: PixelFormat,
    src_w: u32,
    src_h: u32,
    spec: TensorSpec,
    yuv: YuvMatrix,
    x_taps: Vec<Taps>,
    y_taps: Vec<Taps>,
    /// Source column range needed by the horizontal pass.
    x_range: (usize, usize),
    /// The fast path: one pass per plane (vertical then horizontal), straight from the planes.
    passes: Vec<PlanePass>,
    /// Use the AVX2+FMA build of the kernels (checked once at construction).
    avx2: bool,
    /// Working buffers, allocated at the first frame and reused (a concurrent caller of the same
    /// preprocessor gets its own, allocated for that call).
    scratch: std::sync::Mutex<Option<FastScratch>>,
}

impl Clone for Preprocessor {
    fn clone(&self) -> Self {
        Preprocessor {
            format: self.format,
            src_w: self.src_w,
            src_h: self.src_h,
            spec: self.spec.clone(),
            yuv: self.yuv,
            x_taps: self.x_taps.clone(),
            y_taps: self.y_taps.clone(),
            x_range: self.x_range,
            passes: self.passes.clone(),
            avx2: self.avx2,
            scratch: std::sync::Mutex::new(None),
        }
    }
}

impl Preprocessor {
    pub fn new(
        format: PixelFormat,
        src_w: u32,
        src_h: u32,
        yuv: YuvMatrix,
        spec: TensorSpec,
    ) -> Result<Preprocessor, PreprocessError> {
        if src_w == 0 || src_h == 0 {
            return Err(PreprocessError(format!(
                "frame size {src_w}x{src_h} is empty"
            )));
        }
        if src_w > MAX_FRAME_SIDE || src_h > MAX_FRAME_SIDE {
            return Err(PreprocessError(format!(
                "frame size {src_w}x{src_h} is too large (each side at most {MAX_FRAME_SIDE})"
            )));
        }
        if spec.width == 0 || spec.height == 0 {
            return Err(PreprocessError(format!(
                "model input size {}x{} is empty",
                spec.width, spec.height
            )));
        }
        let ((x_off, x_span), (y_off, y_span)) = crop(src_w, src_h, &spec);
        let x_taps = make_taps(src_w as usize, spec.width as usize, x_off, x_span);
        let y_taps = make_taps(src_h as usize, spec.height as usize, y_off, y_span);
        let x_range = (
            x_taps.first().map(|t| t.start).unwrap_or(0),
            x_taps
                .last()
                .map(|t| t.start + t.weights.len())
                .unwrap_or(0),
        );
        let passes = make_passes(format, &x_taps, &y_taps);
        Ok(Preprocessor {
            format,
            src_w,
            src_h,
            spec,
            yuv,
            x_taps,
            y_taps,
            x_range,
            passes,
            avx2: has_avx2(),
            scratch: std::sync::Mutex::new(None),
        })
    }

    pub fn spec(&self) -> &TensorSpec {
        &self.spec
    }

    /// Check that every row of every plane lies inside its slice (checked arithmetic: hostile
    /// strides and sizes are errors, never wrapped or panicking), and return the row addressing.
    fn check(&self, f: &RawFrame) -> Result<[Rows; 3], PreprocessError> {
        if f.format != self.format || f.width != self.src_w || f.height != self.src_h {
            return Err(PreprocessError(format!(
                "frame is {:?} {}x{}, preprocessor was built for {:?} {}x{}",
                f.format, f.width, f.height, self.format, self.src_w, self.src_h
            )));
        }
        let mut rows_out = [Rows::default(); 3];
        let layout = f.format.plane_sizes(f.width as usize, f.height as usize);
        for (p, &(row_bytes, rows)) in layout.iter().enumerate() {
            if rows == 0 {
                continue;
            }
            let err = |what: String| PreprocessError(format!("plane {p}: {what}"));
            let stride = f.strides[p];
            let abs = stride.unsigned_abs();
            if abs < row_bytes {
                return Err(err(format!(
                    "stride {stride} is smaller than a row ({row_bytes} bytes)"
                )));
            }
            let need = abs
                .checked_mul(rows - 1)
                .and_then(|v| v.checked_add(row_bytes))
                .filter(|&v| v <= isize::MAX as usize)
                .ok_or_else(|| err(format!("stride {stride} x {rows} rows overflows")))?;
            if f.planes[p].len() < need {
                return Err(err(format!("{} bytes, need {need}", f.planes[p].len())));
            }
            let origin = if stride < 0 {
                (abs * (rows - 1)) as isize
            } else {
                0
            };
            rows_out[p] = Rows { origin, stride };
        }
        Ok(rows_out)
    }

    /// Fill `out` (length `3*H*W`, CHW) from the frame.
    ///
    /// One pass per plane, straight from the plane's bytes: for each output row, the source
    /// rows under it are averaged (weighted) into one row of floats (contiguous, vectorised),
    /// which the horizontal taps then reduce to the output pixels; chroma planes are averaged at
    /// their own resolution with the luma taps merged 2:1 (exactly the average of the chroma
    /// upsampled by repetition). The buffers are reused from frame to frame.
    pub fn run(&self, frame: &RawFrame, out: &mut [f32]) -> Result<(), PreprocessError> {
        let rows = self.check(frame)?;
        if out.len() != self.spec.len() {
            return Err(PreprocessError(format!(
                "output tensor has {} elements, need {}",
                out.len(),
                self.spec.len()
            )));
        }
        let mut own = None;
        let mut guard = self.scratch.try_lock().ok();
        let slot: &mut Option<FastScratch> = match guard.as_deref_mut() {
            Some(s) => s,
            None => &mut own,
        };
        if slot.is_none() {
            *slot = Some(self.fast_scratch()?);
        }
        let scratch = slot.as_mut().expect("allocated above");
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: the CPU has AVX2 and FMA (checked at construction).
            unsafe { self.fast_avx2(frame, rows, scratch, out) };
            return Ok(());
        }
        self.fast_generic(frame, rows, scratch, out);
        Ok(())
    }

    /// The straightforward float path (horizontal pass per source row, then vertical), kept as
    /// the reference the fast path is tested and benchmarked against.
    #[doc(hidden)]
    pub fn run_reference(&self, frame: &RawFrame, out: &mut [f32]) -> Result<(), PreprocessError> {
        let rows = self.check(frame)?;
        if out.len() != self.spec.len() {
            return Err(PreprocessError(format!(
                "output tensor has {} elements, need {}",
                out.len(),
                self.spec.len()
            )));
        }
        let yuv = self.yuv;
        let d = self.format.desc();
        let unit = self.format.unit();
        // Per output slot (R, G, B or Y, U, V): plane, samples per unit, unit size, sample.
        let mut slots = [(0usize, 1usize, FULL, 0usize); 3];
        for p in d.passes {
            for &(sample, slot) in p.chans {
                slots[slot] = (p.plane, p.bpp, p.sub, sample);
            }
        }
        let fetch = |x: usize, y: usize| {
            slots.map(|(plane, bpp, (sx, sy), k)| {
                let at = rows[plane].at(y / sy) + ((x / sx) * bpp + k) * d.bytes;
                let p = &frame.planes[plane][at..];
                if d.bytes == 1 {
                    sample::<1>(p)
                } else {
                    sample::<2>(p) * unit
                }
            })
        };
        let scratch = Scratch::new(self)?;
        if d.yuv {
            self.resample(out, scratch, fetch, |v| yuv.to_rgb(v));
        } else {
            self.resample(out, scratch, fetch, |v| v);
        }
        Ok(())
    }

    /// Read a GStreamer video buffer described by `info` (plane offsets and strides from its
    /// GstVideoMeta when present, negative strides included) and fill `out`. Every offset and
    /// size is checked: a buffer that does not hold the frame is an error, never a panic.
    pub fn run_buffer(
        &self,
        buf: &gst::BufferRef,
        info: &gst_video::VideoInfo,
        out: &mut [f32],
    ) -> Result<(), PreprocessError> {
        let format = PixelFormat::from_video_format(info.format())
            .ok_or_else(|| PreprocessError(format!("unsupported format {:?}", info.format())))?;
        let n = format.n_planes();
        let mut offsets = [0usize; 3];
        let mut strides = [0isize; 3];
        match buf.meta::<gst_video::VideoMeta>() {
            Some(m) => {
                if m.format() != info.format()
                    || m.width() != info.width()
                    || m.height() != info.height()
                    || m.n_planes() as usize != n
                {
                    return Err(PreprocessError(format!(
                        "the buffer's video meta ({:?} {}x{}, {} planes) disagrees with the caps \
                         ({:?} {}x{})",
                        m.format(),
                        m.width(),
                        m.height(),
                        m.n_planes(),
                        info.format(),
                        info.width(),
                        info.height()
                    )));
                }
                for p in 0..n {
                    offsets[p] = m.offset()[p];
                    strides[p] = m.stride()[p] as isize;
                }
            }
            None => {
                for p in 0..n {
                    offsets[p] = info.offset()[p];
                    strides[p] = info.stride()[p] as isize;
                }
            }
        }
        let map = buf
            .map_readable()
            .map_err(|e| PreprocessError(format!("cannot map the buffer: {e}")))?;
        let data = map.as_slice();
        let layout = format.plane_sizes(info.width() as usize, info.height() as usize);
        let mut planes: [&[u8]; 3] = [&[], &[], &[]];
        for p in 0..n {
            let (row_bytes, rows) = layout[p];
            let (offset, stride) = (offsets[p], strides[p]);
            let err = |what: String| {
                PreprocessError(format!(
                    "plane {p} (offset {offset}, stride {stride}, {rows} rows of {row_bytes} \
                     bytes): {what}"
                ))
            };
            let abs = stride.unsigned_abs();
            if abs < row_bytes {
                return Err(err("the stride is smaller than a row".into()));
            }
            let back = abs
                .checked_mul(rows.saturating_sub(1))
                .ok_or_else(|| err("overflows".into()))?;
            let span = back
                .checked_add(row_bytes)
                .ok_or_else(|| err("overflows".into()))?;
            // Lowest address of the plane: the first row, or the last one when bottom-up.
            let start = if stride < 0 {
                offset
                    .checked_sub(back)
                    .ok_or_else(|| err("the rows start before the buffer".into()))?
            } else {
                offset
            };
            let end = start
                .checked_add(span)
                .ok_or_else(|| err("overflows".into()))?;
            planes[p] = data.get(start..end).ok_or_else(|| {
                err(format!(
                    "needs bytes {start}..{end}, the buffer has {}",
                    data.len()
                ))
            })?;
        }
        let raw = RawFrame {
            format,
            width: info.width(),
            height: info.height(),
            planes,
            strides,
        };
        self.run(&raw, out)
    }
}

#[cfg(test)]
#[path = "../tests/common/pack.rs"]
mod test_pack;

#[cfg(test)]
mod tests {
    use super::*;

    use super::test_pack::{pack_rgb, raw_frame};

    fn spec(w: u32, h: u32, resize: ResizeMode) -> TensorSpec {
        TensorSpec {
            width: w,
            height: h,
            resize,
            mean: [0.0; 3],
            std: [1.0; 3],
        }
    }

    /// A smooth test picture (smooth so chroma subsampling stays within rounding).
    fn picture(w: u32, h: u32, gray: bool) -> Vec<u8> {
        let mut v = Vec::with_capacity((w * h * 3) as usize);
        for y in 0..h {
            for x in 0..w {
                let fx = x as f32 / w as f32;
                let fy = y as f32 / h as f32;
                let r = (40.0 + 180.0 * fx) as u8;
                let g = (60.0 + 150.0 * fy) as u8;
                let b = (100.0 + 100.0 * (fx * fy)) as u8;
                if gray {
                    v.extend_from_slice(&[g, g, g]);
                } else {
                    v.extend_from_slice(&[r, g, b]);
                }
            }
        }
        v
    }

    fn tensor(
        rgb: &[u8],
        w: u32,
        h: u32,
        format: PixelFormat,
        pad: usize,
        s: &TensorSpec,
    ) -> Vec<f32> {
        let (planes, strides) = pack_rgb(rgb, w, h, format, pad);
        let frame = raw_frame(format, w, h, &planes, &strides);
        let p = Preprocessor::new(format, w, h, YuvMatrix::BT601, s.clone()).unwrap();
        let mut out = vec![0.0; s.len()];
        p.run(&frame, &mut out).unwrap();
        out
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    #[test]
    fn every_format_matches_rgb_odd_sizes_and_padding() {
        for &(w, h) in &[(64u32, 48u32), (37, 23), (101, 75)] {
            let s = spec(32, 32, ResizeMode::ShortSideCrop);
            for gray in [false, true] {
                let pic = picture(w, h, gray);
                let reference = tensor(&pic, w, h, PixelFormat::Rgb, 0, &s);
                for f in PixelFormat::ALL {
                    if f.is_grey() && !gray {
                        continue;
                    }
                    for pad in [0usize, 5, 64] {
                        let t = tensor(&pic, w, h, f, pad, &s);
                        let d = max_diff(&reference, &t);
                        let mean: f32 = reference
                            .iter()
                            .zip(&t)
                            .map(|(a, b)| (a - b).abs())
                            .sum::<f32>()
                            / t.len() as f32;
                        // YUV: 8-bit limited-range rounding plus 2x2 chroma subsampling of a
                        // steep ramp (up to ~5 code values per pixel here): a few codes at most,
                        // about one on average.
                        let (tol, mean_tol) = if f.is_yuv() {
                            (6.0 / 255.0, 1.5 / 255.0)
                        } else {
                            (1e-6, 1e-7)
                        };
                        assert!(
                            d <= tol && mean <= mean_tol,
                            "{f:?} {w}x{h} pad {pad} gray {gray}: max diff {d}, mean {mean}"
                        );
                    }
                }
            }
        }
    }

    /// The fast path against the straightforward float path (`run_reference`), on noisy
    /// pictures (every format, odd sizes, padding, both resize modes, shrinking and enlarging,
    /// full and limited range): within 1e-4 of each other (1/255 = 4e-3).
    #[test]
    fn fast_path_matches_the_float_reference() {
        let mut x = 0x1234_5678u32;
        let mut rnd = move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x >> 24) as u8
        };
        for &(w, h, ow, oh) in &[
            (64u32, 48u32, 32u32, 32u32),
            (37, 23, 16, 16),
            (101, 75, 24, 20),
            (640, 480, 64, 64),
            (333, 211, 256, 256),
            (7, 5, 16, 12),
            // The default student's input from 1080p: 9 whole rows per output row (u16 sums).
            (1920, 1080, 160, 120),
            // More interior rows than a u16 sum holds when stretched: the float path.
            (40, 2100, 8, 4),
        ] {
            let pic: Vec<u8> = (0..w * h * 3).map(|_| rnd()).collect();
            for resize in [ResizeMode::ShortSideCrop, ResizeMode::Stretch] {
                let s = TensorSpec {
                    width: ow,
                    height: oh,
                    resize,
                    mean: [0.485, 0.456, 0.406],
                    std: [0.229, 0.224, 0.225],
                };
                // Every format at the small sizes; at the large ones, one of each kind of
                // layout (packed, grey, semi-planar, planar 4:2:0 / 4:2:2, packed 4:2:2, wide).
                let formats: &[PixelFormat] = if w * h <= 101 * 75 {
                    &PixelFormat::ALL
                } else {
                    &[
                        PixelFormat::Rgb,
                        PixelFormat::Bgra,
                        PixelFormat::Gray8,
                        PixelFormat::Nv12,
                        PixelFormat::I420,
                        PixelFormat::Y42b,
                        PixelFormat::Uyvy,
                        PixelFormat::P01010le,
                        PixelFormat::I42010le,
                    ]
                };
                for &f in formats {
                    for (pad, yuv) in [
                        (0usize, YuvMatrix::BT601),
                        (
                            3,
                            YuvMatrix {
                                full_range: true,
                                ..YuvMatrix::BT709
                            },
                        ),
                    ] {
                        let (planes, strides) = pack_rgb(&pic, w, h, f, pad);
                        let frame = raw_frame(f, w, h, &planes, &strides);
                        let p = Preprocessor::new(f, w, h, yuv, s.clone()).unwrap();
                        let mut fast = vec![0.0; s.len()];
                        let mut slow = vec![0.0; s.len()];
                        p.run(&frame, &mut fast).unwrap();
                        p.run_reference(&frame, &mut slow).unwrap();
                        let d = max_diff(&fast, &slow);
                        assert!(d < 1e-4, "{f:?} {w}x{h} -> {ow}x{oh} {resize:?}: {d}");
                        // The build without AVX2 (this machine's CPU picks the AVX2 one).
                        let mut generic = p.clone();
                        generic.avx2 = false;
                        let mut plain = vec![0.0; s.len()];
                        generic.run(&frame, &mut plain).unwrap();
                        let d = max_diff(&plain, &slow);
                        assert!(
                            d < 1e-4,
                            "generic {f:?} {w}x{h} -> {ow}x{oh} {resize:?}: {d}"
                        );
                        // Again (the reused buffers give the same result), and from a clone.
                        let mut again = vec![0.0; s.len()];
                        p.clone().run(&frame, &mut again).unwrap();
                        assert_eq!(fast, again);
                        p.run(&frame, &mut again).unwrap();
                        assert_eq!(fast, again);
                    }
                }
            }
        }
    }

    /// Packed 4:2:2 averages each source row once: its luma pass reads the chroma pass's
    /// vertically averaged row (which holds every luma sample), at the default student's 1080p
    /// input and an odd size; no other layout shares (their passes read other planes). The
    /// result is checked against the float path in `fast_path_matches_the_float_reference`.
    #[test]
    fn packed_422_averages_each_row_once() {
        for (w, h, ow, oh) in [(1920u32, 1080u32, 160u32, 120u32), (37, 23, 16, 16)] {
            for f in PixelFormat::ALL {
                let p = Preprocessor::new(
                    f,
                    w,
                    h,
                    YuvMatrix::BT709,
                    spec(ow, oh, ResizeMode::ShortSideCrop),
                )
                .unwrap();
                let shared: Vec<_> = p.passes.iter().filter_map(|p| p.acc_from).collect();
                if matches!(f, PixelFormat::Yuy2 | PixelFormat::Uyvy) {
                    assert_eq!(shared.len(), 1, "{f:?} {w}x{h}");
                    assert_eq!(shared[0].0, 0, "{f:?}: luma reads the chroma pass's row");
                } else {
                    assert!(shared.is_empty(), "{f:?} {w}x{h}: {shared:?}");
                }
            }
        }
    }

    #[test]
    fn constant_picture_gives_constant_normalised_tensor() {
        let (w, h) = (50, 30);
        let pic = vec![128u8; (w * h * 3) as usize];
        let s = TensorSpec {
            width: 16,
            height: 16,
            resize: ResizeMode::Stretch,
            mean: [0.5, 0.25, 0.0],
            std: [0.5, 0.25, 2.0],
        };
        let t = tensor(&pic, w, h, PixelFormat::Rgb, 0, &s);
        let v = 128.0 / 255.0;
        for (c, chunk) in t.chunks(256).enumerate() {
            let want = (v - s.mean[c]) / s.std[c];
            assert!(chunk.iter().all(|x| (x - want).abs() < 1e-5), "channel {c}");
        }
    }

    /// Full scale reads as 1.0 in every format that has one: 65535 in GRAY16_LE as 255 in GRAY8
    /// and RGB (it read 65535 / 256 / 255 = 1.0039).
    #[test]
    fn full_scale_grey16_reads_as_one() {
        let (w, h) = (20u32, 10u32);
        let s = spec(8, 8, ResizeMode::Stretch);
        let run = |format: PixelFormat, bytes: Vec<u8>| {
            let stride = bytes.len() / h as usize;
            let planes = [bytes];
            let frame = raw_frame(format, w, h, &planes, &[stride]);
            let p = Preprocessor::new(format, w, h, YuvMatrix::BT601, s.clone()).unwrap();
            let mut out = vec![0.0; s.len()];
            p.run(&frame, &mut out).unwrap();
            out
        };
        let n = (w * h) as usize;
        let white16 = run(PixelFormat::Gray16Le, vec![0xff; 2 * n]);
        let white8 = run(PixelFormat::Gray8, vec![255; n]);
        assert!(
            white16.iter().all(|&v| (v - 1.0).abs() < 1e-6),
            "{white16:?}"
        );
        assert!(white8.iter().all(|&v| (v - 1.0).abs() < 1e-6), "{white8:?}");
        // Mid-grey as videoconvert writes it (v * 257) reads as v / 255.
        let mid16 = run(
            PixelFormat::Gray16Le,
            (0..n).flat_map(|_| (128u16 * 257).to_le_bytes()).collect(),
        );
        assert!(mid16.iter().all(|&v| (v - 128.0 / 255.0).abs() < 1e-6));
    }

    #[test]
    fn short_side_crop_keeps_centre_and_stretch_keeps_edges() {
        // 40x20 image: left quarter red, right quarter blue, middle green.
        let (w, h) = (40u32, 20u32);
        let mut pic = vec![0u8; (w * h * 3) as usize];
        for y in 0..h {
            for x in 0..w {
                let i = (3 * (y * w + x)) as usize;
                let c = if x < 10 {
                    0
                } else if x >= 30 {
                    2
                } else {
                    1
                };
                pic[i + c] = 255;
            }
        }
        let crop = tensor(
            &pic,
            w,
            h,
            PixelFormat::Rgb,
            0,
            &spec(10, 10, ResizeMode::ShortSideCrop),
        );
        // Crop keeps x in [10, 30): only green.
        assert!(
            crop[..100].iter().all(|&r| r == 0.0),
            "no red in the centre crop"
        );
        assert!(crop[100..200].iter().all(|&g| (g - 1.0).abs() < 1e-6));
        let st = tensor(
            &pic,
            w,
            h,
            PixelFormat::Rgb,
            0,
            &spec(8, 8, ResizeMode::Stretch),
        );
        assert!(
            (st[0] - 1.0).abs() < 1e-6,
            "stretch keeps the red left edge"
        );
        assert!(
            (st[2 * 64 + 7] - 1.0).abs() < 1e-6,
            "and the blue right edge"
        );
    }

    #[test]
    fn upscaling_is_bilinear_and_bounded() {
        let (w, h) = (4u32, 4u32);
        let pic = picture(w, h, false);
        let t = tensor(
            &pic,
            w,
            h,
            PixelFormat::Rgb,
            0,
            &spec(16, 16, ResizeMode::Stretch),
        );
        assert!(t.iter().all(|v| (0.0..=1.0).contains(v)));
    }

    #[test]
    fn short_buffers_are_rejected_not_read() {
        let p = Preprocessor::new(
            PixelFormat::Rgb,
            10,
            10,
            YuvMatrix::BT601,
            spec(4, 4, ResizeMode::Stretch),
        )
        .unwrap();
        let data = vec![0u8; 299];
        let f = RawFrame {
            format: PixelFormat::Rgb,
            width: 10,
            height: 10,
            planes: [&data, &[], &[]],
            strides: [30, 0, 0],
        };
        let mut out = vec![0.0; 48];
        let e = p.run(&f, &mut out).unwrap_err();
        assert!(e.0.contains("need 300"), "{e}");
        // Hostile strides: errors, never wrapped sizes or panics.
        for stride in [isize::MAX, isize::MIN, -29, 29, isize::MAX / 4] {
            let f = RawFrame {
                strides: [stride, 0, 0],
                ..f
            };
            assert!(p.run(&f, &mut out).is_err(), "stride {stride}");
        }
    }

    #[test]
    fn absurd_frame_sizes_are_refused() {
        let s = spec(16, 16, ResizeMode::ShortSideCrop);
        let e =
            Preprocessor::new(PixelFormat::Rgb, 2_000_000_000, 4, YuvMatrix::BT601, s).unwrap_err();
        assert!(e.0.contains("too large"), "{e}");
    }

    #[test]
    fn bottom_up_rows_match_top_down() {
        let (w, h) = (23u32, 17u32);
        let pic = picture(w, h, false);
        let s = spec(16, 16, ResizeMode::Stretch);
        let want = tensor(&pic, w, h, PixelFormat::Rgb, 0, &s);
        // Store the rows bottom-up with a padded stride.
        let stride = 3 * w as usize + 7;
        let mut mem = vec![0u8; stride * h as usize];
        for y in 0..h as usize {
            let dst = (h as usize - 1 - y) * stride;
            mem[dst..dst + 3 * w as usize]
                .copy_from_slice(&pic[3 * w as usize * y..3 * w as usize * (y + 1)]);
        }
        let f = RawFrame {
            format: PixelFormat::Rgb,
            width: w,
            height: h,
            planes: [&mem, &[], &[]],
            strides: [-(stride as isize), 0, 0],
        };
        let p = Preprocessor::new(PixelFormat::Rgb, w, h, YuvMatrix::BT601, s.clone()).unwrap();
        let mut out = vec![0.0; s.len()];
        p.run(&f, &mut out).unwrap();
        assert_eq!(out, want);
    }
}
