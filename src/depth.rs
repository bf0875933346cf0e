//! Depth beside a colour frame: the `LeanGateDepthMeta` an RGB-D source (the `leangatedepthmux`
//! element, an application's `appsrc`, the eval) attaches to each colour buffer, and the depth
//! picture on the model's grid that the metric gate ([`crate::metric`]) works on.
//!
//! `LeanGateDepthMeta` is a `GstCustomMeta` whose structure holds:
//!
//! | field | type | meaning |
//! |---|---|---|
//! | `depth` | GstBuffer | the depth image, registered to the colour frame (same field of view; any resolution) |
//! | `format` | string | `GRAY16_LE` (integer units, `scale` of them per metre; 0 = no reading) or `GRAY32F` (metres; 0, NaN, inf = no reading) |
//! | `width`, `height` | guint | the depth image's size |
//! | `stride` | guint | bytes per row of `depth` |
//! | `scale` | double | depth units per metre (1000 for RealSense/Kinect millimetres, 5000 for TUM; 1 for GRAY32F) |
//! | `fx`, `fy`, `cx`, `cy` | double | the colour frame's pinhole intrinsics, in its own pixels (centres at integers) |
//!
//! From Python: `m = buf.add_custom_meta("LeanGateDepthMeta"); s = m.get_structure()` and set the
//! fields (the plugin registers the meta when it loads).

use crate::overlap::Pinhole;

pub const DEPTH_META_NAME: &str = "LeanGateDepthMeta";

/// The depth picture formats read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DepthFormat {
    Gray16Le,
    Gray32F,
}

impl DepthFormat {
    pub fn as_str(self) -> &'static str {
        match self {
            DepthFormat::Gray16Le => "GRAY16_LE",
            DepthFormat::Gray32F => "GRAY32F",
        }
    }

    pub fn parse(s: &str) -> Option<DepthFormat> {
        match s {
            "GRAY16_LE" => Some(DepthFormat::Gray16Le),
            "GRAY32F" => Some(DepthFormat::Gray32F),
            _ => None,
        }
    }

    /// Bytes per pixel.
    pub fn bytes(self) -> usize {
        match self {
            DepthFormat::Gray16Le => 2,
            DepthFormat::Gray32F => 4,
        }
    }
}

/// Whether `size` bytes hold a `width` x `height` depth image of `format` with rows `stride`
/// bytes apart; else what is wrong, in a few words.
pub fn check_layout(
    format: DepthFormat,
    width: u32,
    height: u32,
    stride: u32,
    size: usize,
) -> Result<(), String> {
    if width == 0 || height == 0 {
        return Err(format!("empty depth image {width}x{height}"));
    }
    let row = width as u64 * format.bytes() as u64;
    if (stride as u64) < row {
        return Err(format!(
            "stride {stride} is below a row of {width} {} pixels",
            format.as_str()
        ));
    }
    let need = stride as u64 * (height as u64 - 1) + row;
    if (size as u64) < need {
        return Err(format!(
            "{size} bytes of depth for {width}x{height} (stride {stride}) need {need}"
        ));
    }
    Ok(())
}

/// What a `LeanGateDepthMeta` says.
#[derive(Debug, Clone)]
pub struct DepthInput {
    pub depth: gst::Buffer,
    pub format: DepthFormat,
    pub width: u32,
    pub height: u32,
    pub stride: u32,
    pub scale: f64,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

pub fn register() {
    if !gst::meta::CustomMeta::is_registered(DEPTH_META_NAME) {
        gst::meta::CustomMeta::register(DEPTH_META_NAME, &[]);
    }
}

impl DepthInput {
    /// Attach to `buffer` (replacing one already there).
    pub fn attach(&self, buffer: &mut gst::BufferRef) -> Result<(), gst::glib::BoolError> {
        register();
        let mut m = match gst::meta::CustomMeta::from_mut_buffer(buffer, DEPTH_META_NAME) {
            Ok(m) => m,
            Err(_) => gst::meta::CustomMeta::add(buffer, DEPTH_META_NAME)?,
        };
        let s = m.mut_structure();
        s.set("depth", &self.depth);
        s.set("format", self.format.as_str());
        s.set("width", self.width);
        s.set("height", self.height);
        s.set("stride", self.stride);
        s.set("scale", self.scale);
        s.set("fx", self.fx);
        s.set("fy", self.fy);
        s.set("cx", self.cx);
        s.set("cy", self.cy);
        Ok(())
    }

    /// The meta on `buffer`: `None` when there is none, an error naming the problem when it
    /// is malformed (a missing or mistyped field, a buffer too small for its size and stride, a
    /// scale or intrinsics that are not finite and positive).
    pub fn read(buffer: &gst::BufferRef) -> Option<Result<DepthInput, String>> {
        let m = gst::meta::CustomMeta::from_buffer(buffer, DEPTH_META_NAME).ok()?;
        Some(Self::from_structure(m.structure()))
    }

    fn from_structure(s: &gst::StructureRef) -> Result<DepthInput, String> {
        let field = |name: &str| format!("{DEPTH_META_NAME} has no usable `{name}`");
        let num = |name: &str| -> Result<f64, String> {
            let v = s.value(name).map_err(|_| field(name))?;
            v.get::<f64>()
                .or_else(|_| v.get::<f32>().map(f64::from))
                .or_else(|_| v.get::<i32>().map(f64::from))
                .or_else(|_| v.get::<u32>().map(f64::from))
                .map_err(|_| field(name))
        };
        let uint = |name: &str| -> Result<u32, String> {
            let x = num(name)?;
            (x >= 0.0 && x <= u32::MAX as f64 && x.fract() == 0.0)
                .then_some(x as u32)
                .ok_or_else(|| field(name))
        };
        let depth: gst::Buffer = s.get("depth").map_err(|_| field("depth"))?;
        let format = s
            .get::<&str>("format")
            .ok()
            .and_then(DepthFormat::parse)
            .ok_or_else(|| format!("{DEPTH_META_NAME}: `format` must be GRAY16_LE or GRAY32F"))?;
        let (width, height, stride) = (uint("width")?, uint("height")?, uint("stride")?);
        check_layout(format, width, height, stride, depth.size())
            .map_err(|e| format!("{DEPTH_META_NAME}: {e}"))?;
        let scale = if format == DepthFormat::Gray32F {
            1.0
        } else {
            num("scale")?
        };
        let (fx, fy, cx, cy) = (num("fx")?, num("fy")?, num("cx")?, num("cy")?);
        let positive = |x: f64| x.is_finite() && x > 0.0;
        if !positive(scale) {
            return Err(format!(
                "{DEPTH_META_NAME}: scale {scale} (depth units per metre) must be positive"
            ));
        }
        if !(positive(fx) && positive(fy) && cx.is_finite() && cy.is_finite()) {
            return Err(format!(
                "{DEPTH_META_NAME}: intrinsics fx {fx} fy {fy} cx {cx} cy {cy} are not a camera"
            ));
        }
        Ok(DepthInput {
            depth,
            format,
            width,
            height,
            stride,
            scale,
            fx,
            fy,
            cx,
            cy,
        })
    }

    /// The depth (metres, 0 = no reading) on a `grid_w` x `grid_h` grid that covers the colour
    /// frame (`src_w` x `src_h`) from `(x_off, y_off)` over `x_span` x `y_span` source pixels (the
    /// model picture's crop), nearest sample (no averaging, which would make flying points at
    /// depth edges), and the camera of that grid.
    #[allow(clippy::too_many_arguments)]
    pub fn on_grid(
        &self,
        src_w: u32,
        src_h: u32,
        (x_off, x_span): (f64, f64),
        (y_off, y_span): (f64, f64),
        grid_w: usize,
        grid_h: usize,
    ) -> Result<(Vec<f32>, Pinhole), String> {
        let map = self
            .depth
            .map_readable()
            .map_err(|_| format!("{DEPTH_META_NAME}: the depth buffer cannot be read"))?;
        let bytes = map.as_slice();
        let (dw, dh) = (self.width as f64, self.height as f64);
        let (sw, sh) = (src_w as f64, src_h as f64);
        let (gw, gh) = (grid_w as f64, grid_h as f64);
        let col = |x: usize| -> usize {
            let u = x_off + (x as f64 + 0.5) * x_span / gw; // source pixel edges
            ((u * dw / sw) as usize).min(self.width as usize - 1)
        };
        let row = |y: usize| -> usize {
            let v = y_off + (y as f64 + 0.5) * y_span / gh;
            ((v * dh / sh) as usize).min(self.height as usize - 1)
        };
        let cols: Vec<usize> = (0..grid_w).map(col).collect();
        let mut out = Vec::with_capacity(grid_w * grid_h);
        for y in 0..grid_h {
            let base = row(y) * self.stride as usize;
            for &c in &cols {
                let z = match self.format {
                    DepthFormat::Gray16Le => {
                        let i = base + 2 * c;
                        u16::from_le_bytes([bytes[i], bytes[i + 1]]) as f64 / self.scale
                    }
                    DepthFormat::Gray32F => {
                        let i = base + 4 * c;
                        f32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]])
                            as f64
                    }
                };
                out.push(if z.is_finite() && z > 0.0 {
                    z as f32
                } else {
                    0.0
                });
            }
        }
        // The grid's camera: grid pixel centre x maps to source x_off + (x + 0.5) x_span / gw
        // (edges), i.e. source centre coordinate that minus 0.5.
        let (kx, ky) = (gw / x_span, gh / y_span);
        let cam = Pinhole {
            fx: self.fx * kx,
            fy: self.fy * ky,
            cx: (self.cx + 0.5 - x_off) * kx - 0.5,
            cy: (self.cy + 0.5 - y_off) * ky - 0.5,
        };
        Ok((out, cam))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input(format: DepthFormat, w: u32, h: u32, f: impl Fn(u32, u32) -> f32) -> DepthInput {
        let mut data = Vec::new();
        for y in 0..h {
            for x in 0..w {
                match format {
                    DepthFormat::Gray16Le => {
                        data.extend_from_slice(&((f(x, y) * 1000.0) as u16).to_le_bytes())
                    }
                    DepthFormat::Gray32F => data.extend_from_slice(&f(x, y).to_le_bytes()),
                }
            }
        }
        DepthInput {
            depth: gst::Buffer::from_mut_slice(data),
            format,
            width: w,
            height: h,
            stride: w * format.bytes() as u32,
            scale: 1000.0,
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
        }
    }

    #[test]
    fn round_trip_and_refusals() {
        gst::init().unwrap();
        let d = input(DepthFormat::Gray16Le, 64, 48, |x, _| 1.0 + x as f32 / 100.0);
        let mut buf = gst::Buffer::with_size(16).unwrap();
        d.attach(buf.get_mut().unwrap()).unwrap();
        let back = DepthInput::read(&buf).unwrap().unwrap();
        assert_eq!((back.width, back.height, back.stride), (64, 48, 128));
        assert_eq!(back.format, DepthFormat::Gray16Le);
        assert!(DepthInput::read(&gst::Buffer::new()).is_none());
        // A stride too small, a buffer too short, a zero scale: named.
        for (field, value, what) in [
            ("stride", 100u32.to_send_value(), "stride 100"),
            ("height", 4800u32.to_send_value(), "need"),
            ("scale", 0.0f64.to_send_value(), "scale 0"),
            ("fx", (-1.0f64).to_send_value(), "intrinsics"),
        ] {
            let mut b = buf.copy();
            let mut m =
                gst::meta::CustomMeta::from_mut_buffer(b.get_mut().unwrap(), DEPTH_META_NAME)
                    .unwrap();
            m.mut_structure().set_value(field, value);
            let e = DepthInput::read(&b).unwrap().unwrap_err();
            assert!(e.contains(what), "{field}: {e}");
        }
    }

    use gst::prelude::*;

    #[test]
    fn depth_on_the_model_grid_with_its_camera() {
        gst::init().unwrap();
        // 640x480 depth, 320x240 colour (registered, half the resolution), a 160x120 grid over
        // the whole frame: each grid pixel samples depth pixel (4x, 4y) region.
        let d = input(DepthFormat::Gray32F, 640, 480, |x, y| (x + 1000 * y) as f32);
        let (g, cam) = d
            .on_grid(320, 240, (0.0, 320.0), (0.0, 240.0), 160, 120)
            .unwrap();
        assert_eq!(g.len(), 160 * 120);
        assert_eq!(g[0], (2 + 1000 * 2) as f32);
        assert_eq!(g[161], (6 + 1000 * 6) as f32);
        assert!((cam.fx - 250.0).abs() < 1e-9);
        // A point on the optical axis projects to cx in both: 319.5 of 640 -> 79.75 of 160
        // at half scale twice... the colour intrinsics are given in colour pixels here.
        assert!((cam.cx - ((319.5 + 0.5) * 0.5 - 0.5)).abs() < 1e-9);
        // Invalid readings are 0.
        let d = input(DepthFormat::Gray32F, 4, 4, |_, _| f32::NAN);
        let (g, _) = d.on_grid(4, 4, (0.0, 4.0), (0.0, 4.0), 2, 2).unwrap();
        assert_eq!(g, vec![0.0; 4]);
    }
}
