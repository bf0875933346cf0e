//! The `model` policy: the real `leangate` element, in annotate mode, in a real pipeline.

use std::path::Path;
use std::sync::Once;
use std::time::Instant;

use gst::prelude::*;
use gstleangate::{
    GateMeta, PixelFormat, Preprocessor, Reason, ResizeMode, StatsMessage, TensorSpec, YuvMatrix,
};

use super::{err, EvalError, Source, Trace, THUMB_H, THUMB_W};

/// The `model` policy's run: per-frame metas, grey thumbnails, colour thumbnails of the kept
/// frames, and throughput.
#[derive(Debug, Clone)]
pub struct ModelRun {
    pub metas: Vec<GateMeta>,
    /// Grey THUMB_W x THUMB_H thumbnail of every frame (for `pixel_diff`).
    pub thumbs: Vec<Vec<u8>>,
    /// (frame index, RGB thumbnail) of every kept frame.
    pub kept_thumbs: Vec<(usize, image::RgbImage)>,
    pub fps: f64,
    pub threshold: f64,
    pub provider: String,
    pub model_name: String,
    /// `model-precision` of the element's stats (`fp32`, `int8`).
    pub model_precision: String,
}

impl ModelRun {
    pub fn trace(&self) -> Trace {
        Trace {
            keep: self.metas.iter().map(|m| m.keep).collect(),
            utility: self
                .metas
                .iter()
                .map(|m| (m.reason != Reason::First && m.utility.is_finite()).then_some(m.utility))
                .collect(),
        }
    }
}

/// Register the statically linked plugin once per process.
pub fn init_gstreamer() -> Result<(), EvalError> {
    static ONCE: Once = Once::new();
    gst::init().map_err(err("GStreamer init"))?;
    let mut res = Ok(());
    ONCE.call_once(|| {
        if gst::ElementFactory::find("leangate").is_none() {
            res = gstleangate::plugin_register_static().map_err(err("registering leangate"));
        }
    });
    res
}

/// RGB thumbnail of a raw buffer, through the same preprocessing the element uses.
fn thumbnail(
    cache: &mut Option<(gst::Caps, gst_video::VideoInfo, Preprocessor)>,
    sample: &gst::Sample,
) -> Result<image::RgbImage, EvalError> {
    let caps = sample
        .caps()
        .ok_or_else(|| EvalError("sample without caps".into()))?;
    if cache.as_ref().is_none_or(|(c, _, _)| c != caps) {
        let info = gst_video::VideoInfo::from_caps(caps).map_err(err("caps"))?;
        let format = PixelFormat::from_video_format(info.format())
            .ok_or_else(|| EvalError(format!("unsupported format {:?}", info.format())))?;
        let pre = Preprocessor::new(
            format,
            info.width(),
            info.height(),
            YuvMatrix::from_colorimetry(&info.colorimetry(), info.height()),
            TensorSpec {
                width: THUMB_W,
                height: THUMB_H,
                resize: ResizeMode::Stretch,
                mean: [0.0; 3],
                std: [1.0 / 255.0; 3],
            },
        )
        .map_err(err("thumbnail"))?;
        *cache = Some((caps.to_owned(), info, pre));
    }
    let (_, info, pre) = cache.as_ref().unwrap();
    let buf = sample
        .buffer()
        .ok_or_else(|| EvalError("sample without buffer".into()))?;
    let mut t = vec![0.0; pre.spec().len()];
    pre.run_buffer(buf, info, &mut t)
        .map_err(err("thumbnail"))?;
    let plane = (THUMB_W * THUMB_H) as usize;
    let rgb = (0..plane)
        .flat_map(|i| [t[i], t[plane + i], t[2 * plane + i]])
        .map(|v| v.round().clamp(0.0, 255.0) as u8)
        .collect();
    Ok(image::RgbImage::from_raw(THUMB_W, THUMB_H, rgb).expect("thumbnail size"))
}

fn grey(rgb: &image::RgbImage) -> Vec<u8> {
    rgb.pixels()
        .map(|p| ((p[0] as u16 + p[1] as u16 + p[2] as u16) / 3) as u8)
        .collect()
}

/// The model the element runs: `path` (None: the embedded default) and its `precision`
/// property (None: the element's default, auto).
#[derive(Debug, Clone, Copy, Default)]
pub struct GateModel<'a> {
    pub path: Option<&'a Path>,
    pub precision: Option<gstleangate::PrecisionChoice>,
}

/// Run the real element in annotate mode over the source, with `model`. `progress(done)` is
/// called per frame.
pub fn run_model(
    source: &Source,
    model: GateModel<'_>,
    threshold: Option<f64>,
    mut progress: impl FnMut(usize),
) -> Result<ModelRun, EvalError> {
    init_gstreamer()?;
    let gate = gst::ElementFactory::make("leangate")
        .build()
        .map_err(err("creating leangate"))?;
    if let Some(m) = model.path {
        gate.set_property("model", m.display().to_string());
    }
    if let Some(p) = model.precision {
        gate.set_property("precision", p);
    }
    gate.set_property_from_str("mode", "annotate");
    if let Some(t) = threshold {
        gate.set_property("threshold", t);
    }
    let sink = gst_app::AppSink::builder().sync(false).build();
    let pipeline = gst::Pipeline::new();
    let mut feeder = None;
    match source {
        Source::Video(path) => {
            let src = gst::ElementFactory::make("filesrc")
                .property("location", path.display().to_string())
                .build()
                .map_err(err("filesrc"))?;
            let dec = gst::ElementFactory::make("decodebin")
                .build()
                .map_err(err("decodebin"))?;
            pipeline
                .add_many([&src, &dec, &gate, sink.upcast_ref()])
                .map_err(err("pipeline"))?;
            src.link(&dec).map_err(err("link"))?;
            gate.link(&sink).map_err(err("link"))?;
            let gate_weak = gate.downgrade();
            dec.connect_pad_added(move |_, pad| {
                let Some(gate) = gate_weak.upgrade() else {
                    return;
                };
                let is_video = pad
                    .current_caps()
                    .and_then(|c| c.structure(0).map(|s| s.name().starts_with("video/")))
                    .unwrap_or(false);
                let sinkpad = gate.static_pad("sink").unwrap();
                if is_video && !sinkpad.is_linked() {
                    let _ = pad.link(&sinkpad);
                }
            });
        }
        Source::Sequence(seq) => {
            let first = seq.load_rgb(0).map_err(err("first frame"))?;
            let (w, h) = first.dimensions();
            let caps = gst_video::VideoInfo::builder(gst_video::VideoFormat::Rgb, w, h)
                .fps(gst::Fraction::new(30, 1))
                .build()
                .map_err(err("caps"))?
                .to_caps()
                .map_err(err("caps"))?;
            let src = gst_app::AppSrc::builder()
                .caps(&caps)
                .format(gst::Format::Time)
                .block(true)
                .max_bytes(64 << 20)
                .build();
            pipeline
                .add_many([src.upcast_ref(), &gate, sink.upcast_ref()])
                .map_err(err("pipeline"))?;
            src.link(&gate).map_err(err("link"))?;
            gate.link(&sink).map_err(err("link"))?;
            let seq = seq.clone();
            feeder = Some(std::thread::spawn(move || -> Result<(), EvalError> {
                let t0 = seq.frames.first().map(|f| f.timestamp).unwrap_or(0.0);
                for i in 0..seq.len() {
                    let img = seq.load_rgb(i).map_err(err("frame"))?;
                    if img.dimensions() != (w, h) {
                        return Err(EvalError(format!(
                            "frame {i} is {}x{}, the first frame is {w}x{h}",
                            img.width(),
                            img.height()
                        )));
                    }
                    let mut b = gst::Buffer::from_mut_slice(img.into_raw());
                    let pts = ((seq.frames[i].timestamp - t0).max(0.0) * 1e9) as u64;
                    b.get_mut()
                        .unwrap()
                        .set_pts(gst::ClockTime::from_nseconds(pts));
                    if src.push_buffer(b).is_err() {
                        break; // pipeline stopped (error reported on the bus)
                    }
                }
                let _ = src.end_of_stream();
                Ok(())
            }));
        }
    }

    let bus = pipeline.bus().unwrap();
    let start = Instant::now();
    pipeline.set_state(gst::State::Playing).map_err(|_| {
        bus_error(&bus).unwrap_or_else(|| EvalError("pipeline failed to start".into()))
    })?;
    let mut metas = Vec::new();
    let mut thumbs = Vec::new();
    let mut kept_thumbs = Vec::new();
    let mut cache = None;
    let mut failure = None;
    while let Ok(sample) = sink.pull_sample() {
        let Some(buf) = sample.buffer() else { continue };
        let Some(m) = GateMeta::read(buf) else {
            failure = Some(EvalError(
                "a buffer left leangate without LeanGateMeta".into(),
            ));
            break;
        };
        let rgb = thumbnail(&mut cache, &sample)?;
        thumbs.push(grey(&rgb));
        if m.keep {
            kept_thumbs.push((metas.len(), rgb));
        }
        metas.push(m);
        progress(metas.len());
    }
    let elapsed = start.elapsed().as_secs_f64();
    // One pass over the bus: `pop_filtered` would discard the messages it does not match.
    let mut bus_err = None;
    let mut stats_threshold = None;
    let mut provider = String::new();
    let mut name = String::new();
    let mut precision = String::new();
    while let Some(msg) = bus.pop() {
        match msg.view() {
            gst::MessageView::Error(e) if bus_err.is_none() => {
                bus_err = Some(EvalError(format!(
                    "{}{}",
                    e.error(),
                    e.debug().map(|d| format!(" ({d})")).unwrap_or_default()
                )));
            }
            gst::MessageView::Element(_) => {
                if let Some(stats) = msg
                    .structure()
                    .and_then(|s| StatsMessage::from_structure(s).ok())
                {
                    stats_threshold = Some(stats.threshold);
                    provider = stats.execution_provider;
                    name = stats.model;
                    precision = stats.model_precision;
                }
            }
            _ => {}
        }
    }
    let _ = pipeline.set_state(gst::State::Null);
    if let Some(f) = feeder {
        f.join()
            .map_err(|_| EvalError("frame feeder panicked".into()))??;
    }
    if let Some(e) = bus_err.or(failure) {
        return Err(e);
    }
    if metas.is_empty() {
        return Err(EvalError("no frame came out of the pipeline".into()));
    }
    Ok(ModelRun {
        fps: metas.len() as f64 / elapsed.max(1e-9),
        threshold: stats_threshold.or(threshold).unwrap_or(0.5),
        metas,
        thumbs,
        kept_thumbs,
        provider,
        model_name: name,
        model_precision: precision,
    })
}

fn bus_error(bus: &gst::Bus) -> Option<EvalError> {
    while let Some(msg) = bus.pop_filtered(&[gst::MessageType::Error]) {
        if let gst::MessageView::Error(e) = msg.view() {
            return Some(EvalError(format!(
                "{}{}",
                e.error(),
                e.debug().map(|d| format!(" ({d})")).unwrap_or_default()
            )));
        }
    }
    None
}
