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
    /// Sharpness of every frame ([`gstleangate::quality::sharpness`] of its grey picture at
    /// [`SHARP_W`] x [`SHARP_H`]; None: junk), for [`super::judge::kept_sharpness`].
    pub sharpness: Vec<Option<f64>>,
    /// Every frame's presentation time (seconds), as it left the element.
    pub pts: Vec<Option<f64>>,
    pub fps: f64,
    pub threshold: f64,
    pub provider: String,
    pub model_name: String,
    /// `model-precision` of the element's stats (`fp32`, `int8`).
    pub model_precision: String,
    /// With feedback: the element's `feedback-offset` at the end of the run.
    pub feedback_offset: Option<f64>,
    /// The element's first warning about a failed inference (`inference failed ...: kept`), when
    /// the model failed on a frame: those frames are kept (fail open), not judged by the model.
    pub failure_warning: Option<String>,
}

impl ModelRun {
    /// Frames kept because the model failed on them (reason `error`, fail open).
    pub fn failed_frames(&self) -> usize {
        self.metas
            .iter()
            .filter(|m| m.reason == Reason::Error)
            .count()
    }

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

/// The picture size the eval measures each frame's sharpness at.
pub const SHARP_W: u32 = 320;
pub const SHARP_H: u32 = 240;

type PreCache = Option<(gst::Caps, gst_video::VideoInfo, Preprocessor)>;

/// RGB thumbnail of a raw buffer, through the same preprocessing the element uses.
fn thumbnail(cache: &mut PreCache, sample: &gst::Sample) -> Result<image::RgbImage, EvalError> {
    let (t, plane) = resized(cache, sample, THUMB_W, THUMB_H)?;
    let rgb = (0..plane)
        .flat_map(|i| [t[i], t[plane + i], t[2 * plane + i]])
        .map(|v| v.round().clamp(0.0, 255.0) as u8)
        .collect();
    Ok(image::RgbImage::from_raw(THUMB_W, THUMB_H, rgb).expect("thumbnail size"))
}

/// The sharpness of a raw buffer's grey picture at [`SHARP_W`] x [`SHARP_H`].
fn sharpness(cache: &mut PreCache, sample: &gst::Sample) -> Result<Option<f64>, EvalError> {
    let (t, plane) = resized(cache, sample, SHARP_W, SHARP_H)?;
    let grey: Vec<f32> = (0..plane)
        .map(|i| (t[i] + t[plane + i] + t[2 * plane + i]) / 3.0)
        .collect();
    Ok(gstleangate::quality::sharpness(
        &grey,
        SHARP_W as usize,
        SHARP_H as usize,
    ))
}

/// A raw buffer resized to `w` x `h`, planar RGB 0–255, and the plane size.
fn resized(
    cache: &mut PreCache,
    sample: &gst::Sample,
    w: u32,
    h: u32,
) -> Result<(Vec<f32>, usize), EvalError> {
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
                width: w,
                height: h,
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
    Ok((t, (w * h) as usize))
}

/// The feeder waits for the sink: frame `i` is fed once `i` frames have left the element.
#[derive(Default)]
struct LockStep {
    /// (frames the sink has finished, whether it stopped pulling)
    state: std::sync::Mutex<(usize, bool)>,
    cv: std::sync::Condvar,
}

impl LockStep {
    /// Block until `i` frames are finished; false when the sink stopped first.
    fn wait_for(&self, i: usize) -> bool {
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        while st.0 < i && !st.1 {
            st = self
                .cv
                .wait_timeout(st, std::time::Duration::from_millis(100))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
        st.0 >= i
    }

    fn finished(&self, n: usize) {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).0 = n;
        self.cv.notify_all();
    }

    fn stop(&self) {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).1 = true;
        self.cv.notify_all();
    }
}

/// The stream time of a frame `seconds` after the first (0 for a negative value), or None
/// beyond what a `ClockTime` holds, about 584 years (e.g. nanosecond timestamps read as seconds).
fn stream_time(seconds: f64) -> Option<gst::ClockTime> {
    let ns = seconds.max(0.0) * 1e9;
    (ns.is_finite() && ns < gst::ClockTime::MAX.nseconds() as f64)
        .then(|| gst::ClockTime::from_nseconds(ns as u64))
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
    /// Act as a consumer that reports, for each kept frame, the teacher's tau against the
    /// previous kept frame (`leangate-feedback`; what MASt3R-SLAM measures on the frames it gets),
    /// this many frames after the keep (its latency).
    pub feedback: Option<usize>,
    /// `--depth`: the `model` row is the metric gate over the sequence's colour and depth
    /// ([`super::depth`]).
    pub depth: bool,
    /// Element properties set after the eval's own (`leangate eval --set`), as text.
    pub properties: &'a [(String, String)],
}

/// Sets `name` to `value` (as gst-launch reads it) on the eval's element, or says why not.
fn set_from_text(gate: &gst::Element, name: &str, value: &str) -> Result<(), EvalError> {
    use gst::glib;
    use gst::prelude::*;
    if name == "model" {
        return Err(EvalError(format!(
            "--set model={value}: give the model with --model (the eval checks that none of its \
             outputs is the model or a file the model reads)"
        )));
    }
    if name == "mode" {
        return Err(EvalError(
            "--set mode: the eval runs the element in annotate mode (it reads every frame's verdict)"
                .into(),
        ));
    }
    let pspec = gate.find_property(name).ok_or_else(|| {
        EvalError(format!(
            "--set {name}: leangate has no such property (gst-inspect-1.0 leangate lists them)"
        ))
    })?;
    if !pspec.flags().contains(glib::ParamFlags::WRITABLE) {
        return Err(EvalError(format!(
            "--set {name}: the property is read-only"
        )));
    }
    let v = glib::Value::deserialize_with_pspec(value, &pspec)
        .ok()
        .filter(|v| in_range(&pspec, v))
        .ok_or_else(|| {
            EvalError(format!(
                "--set {name}={value}: not a valid value of {} `{name}`{}",
                pspec.value_type().name(),
                accepted(&pspec).map_or_else(String::new, |a| format!(" (it takes {a})"))
            ))
        })?;
    gate.set_property(name, &v);
    // The element refuses some values that GLib's range allows (a negative threshold other
    // than -1): it keeps its value and warns on a bus the eval has not attached yet.
    let got = gate.property_value(name);
    if v.compare(&got) != Some(std::cmp::Ordering::Equal) {
        return Err(EvalError(format!(
            "--set {name}={value}: leangate refused it (it keeps {}; gst-inspect-1.0 leangate \
             says which values it takes)",
            got.serialize()
                .map_or_else(|_| "its value".to_string(), |s| s.to_string())
        )));
    }
    Ok(())
}

/// What a numeric, boolean or enum property takes, in words (`0 to 30`, `true or false`, its
/// nicks), for the error that refuses a value.
fn accepted(pspec: &gst::glib::ParamSpec) -> Option<String> {
    use gst::glib;
    macro_rules! range {
        ($($t:ty),*) => {$(
            if let Some(p) = pspec.downcast_ref::<$t>() {
                return Some(format!("{} to {}", p.minimum(), p.maximum()));
            }
        )*};
    }
    range!(
        glib::ParamSpecUInt,
        glib::ParamSpecInt,
        glib::ParamSpecUInt64,
        glib::ParamSpecInt64,
        glib::ParamSpecDouble,
        glib::ParamSpecFloat
    );
    if pspec.downcast_ref::<glib::ParamSpecBoolean>().is_some() {
        return Some("true or false".into());
    }
    pspec.downcast_ref::<glib::ParamSpecEnum>().map(|p| {
        p.enum_class()
            .values()
            .iter()
            .map(|v| v.nick())
            .collect::<Vec<_>>()
            .join(", ")
    })
}

/// Whether `v` is within `pspec`'s range (GLib would refuse it with a warning otherwise).
fn in_range(pspec: &gst::glib::ParamSpec, v: &gst::glib::Value) -> bool {
    use gst::glib::translate::{ToGlibPtr, ToGlibPtrMut};
    let mut copy = v.clone();
    // SAFETY: both pointers are valid for the call; validation changes only `copy`, which holds
    // a value of the pspec's type (deserialized with it).
    let changed = unsafe {
        gst::glib::gobject_ffi::g_param_value_validate(
            pspec.to_glib_none().0,
            copy.to_glib_none_mut().0,
        )
    };
    changed == 0
}

/// Run the real element in annotate mode over the source, with `model`. `progress(done)` is
/// called per frame. With `feedback` (the sequence's teacher), each kept frame's teacher tau
/// against the previous kept frame is sent back to the element as a `leangate-feedback` event,
/// as a consumer would, `model.feedback` frames after the keep; the frames then travel one at a
/// time (the next is fed once the last one has left the element), so the report of a keep at
/// frame j reaches the element exactly before frame j + 1 + delay, whatever the threads do.
pub fn run_model(
    source: &Source,
    model: GateModel<'_>,
    threshold: Option<f64>,
    feedback: Option<&super::GroundTruth>,
    mut progress: impl FnMut(usize),
) -> Result<ModelRun, EvalError> {
    let delay = model.feedback.unwrap_or(0);
    let step = std::sync::Arc::new(LockStep::default());
    init_gstreamer()?;
    let gate = gst::ElementFactory::make("leangate")
        .build()
        .map_err(err("creating leangate"))?;
    if let Some(m) = model.path {
        gate.set_property("model", m.display().to_string());
    }
    if let Some(p) = model.precision {
        // By its name: the element may come from the plugin file on GStreamer's path, which
        // registered the enum type itself (this binary's copy of it must not register again).
        let nick = match p {
            gstleangate::PrecisionChoice::Fp32 => "fp32",
            gstleangate::PrecisionChoice::Int8 => "int8",
            _ => "auto",
        };
        gate.set_property_from_str("precision", nick);
    }
    gate.set_property_from_str("mode", "annotate");
    // The model scores every frame, so that its utility (RMSE, plots) is judged everywhere. The
    // decisions are those of `screen=true screen-step=0` (the element's tests check this); the
    // default's score step may move a keep where the student's score jumps by more than the
    // step just as the utility reaches the threshold: `--set screen=true` judges the default
    // itself (models/README.md: the same keeps on every real sequence here at 0.5).
    gate.set_property("screen", false);
    if let Some(t) = threshold {
        gate.set_property("threshold", t);
    }
    for (name, value) in model.properties {
        set_from_text(&gate, name, value)?;
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
            // `--depth`: each frame's depth image rides along as an RGB-D camera's would, as
            // metres (GRAY32F) with the colour camera's intrinsics.
            let depth_intrinsics = match (model.depth, seq.intrinsics.as_ref()) {
                (false, _) => None,
                (true, Some(i)) => Some(*i),
                (true, None) => {
                    return Err(EvalError(format!(
                        "--depth needs {}",
                        seq.root.join("intrinsics.txt").display()
                    )))
                }
            };
            if model.depth && seq.frames.iter().all(|f| f.depth.is_none()) {
                return Err(EvalError(format!(
                    "--depth needs the sequence's depth images, and {} lists none",
                    seq.root.display()
                )));
            }
            let lock_step = feedback.is_some().then(|| step.clone());
            // Frames held for `sharpness-lookback` leave that many frames later.
            let held = gate.property::<u32>("sharpness-lookback") as usize;
            feeder = Some(std::thread::spawn(move || -> Result<(), EvalError> {
                // EOS however the feeding ends (done, an error, even a panic): the sink must
                // not wait for frames that never come.
                struct EndOfStream(gst_app::AppSrc);
                impl Drop for EndOfStream {
                    fn drop(&mut self) {
                        let _ = self.0.end_of_stream();
                    }
                }
                let eos = EndOfStream(src);
                let src = &eos.0;
                let t0 = seq.frames.first().map(|f| f.timestamp).unwrap_or(0.0);
                let feed = || {
                    for i in 0..seq.len() {
                        if lock_step
                            .as_ref()
                            .is_some_and(|s| !s.wait_for(i.saturating_sub(held)))
                        {
                            break; // the sink stopped pulling (an error, reported there)
                        }
                        let img = seq.load_rgb(i).map_err(err("frame"))?;
                        if img.dimensions() != (w, h) {
                            return Err(EvalError(format!(
                                "`{}` (frame {i}) is {}x{}, the first frame is {w}x{h}",
                                seq.frames[i].rgb.display(),
                                img.width(),
                                img.height()
                            )));
                        }
                        let pts = stream_time(seq.frames[i].timestamp - t0).ok_or_else(|| {
                            EvalError(format!(
                                "`{}`: frame {i} is {:e} s after the first, beyond what a \
                                 stream time holds (timestamps must be in seconds)",
                                seq.root.join("rgb.txt").display(),
                                seq.frames[i].timestamp - t0
                            ))
                        })?;
                        let mut b = gst::Buffer::from_mut_slice(img.into_raw());
                        let bm = b.get_mut().unwrap();
                        bm.set_pts(pts);
                        // The rows are packed (3 * width bytes), which is not GStreamer's default
                        // stride (rounded up to 4) when the width is not a multiple of 4: say so.
                        gst_video::VideoMeta::add_full(
                            bm,
                            gst_video::VideoFrameFlags::empty(),
                            gst_video::VideoFormat::Rgb,
                            w,
                            h,
                            &[0],
                            &[3 * w as i32],
                        )
                        .map_err(err("video meta"))?;
                        if let (Some(intr), Some(_)) = (&depth_intrinsics, &seq.frames[i].depth) {
                            let d = seq.load_depth_m(i).map_err(err("depth"))?;
                            let bytes: Vec<u8> =
                                d.data.iter().flat_map(|v| v.to_le_bytes()).collect();
                            gstleangate::depth::DepthInput {
                                depth: gst::Buffer::from_mut_slice(bytes),
                                format: gstleangate::depth::DepthFormat::Gray32F,
                                width: d.width,
                                height: d.height,
                                stride: 4 * d.width,
                                scale: 1.0,
                                fx: intr.fx,
                                fy: intr.fy,
                                cx: intr.cx,
                                cy: intr.cy,
                            }
                            .attach(bm)
                            .map_err(err("depth meta"))?;
                        }
                        if src.push_buffer(b).is_err() {
                            break; // pipeline stopped (error reported on the bus)
                        }
                    }
                    Ok(())
                };
                feed()
            }));
        }
    }

    let bus = pipeline.bus().unwrap();
    let mut log = BusLog::new(source, &gate);
    let start = Instant::now();
    if pipeline.set_state(gst::State::Playing).is_err() {
        log.drain(&bus);
        let _ = pipeline.set_state(gst::State::Null);
        step.stop(); // a feeder waiting for the sink stops too
        return Err(log
            .error
            .unwrap_or_else(|| EvalError("pipeline failed to start".into())));
    }
    let mut metas = Vec::new();
    let mut thumbs = Vec::new();
    let mut kept_thumbs = Vec::new();
    let mut cache = None;
    let (mut sharp_cache, mut frame_sharpness) = (None, Vec::new());
    let mut frame_pts = Vec::new();
    let mut failure = None;
    // Reports not yet sent: (the frame at which the consumer sends it, tau).
    let mut reports = std::collections::VecDeque::new();
    // Pull until EOS, watching the bus: a source that fails (a file that is not a video, an
    // unreadable image) posts an error and never reaches EOS.
    while log.error.is_none() {
        let Some(sample) = sink.try_pull_sample(gst::ClockTime::from_mseconds(100)) else {
            log.drain(&bus);
            if sink.is_eos() {
                break;
            }
            continue;
        };
        let Some(buf) = sample.buffer() else { continue };
        frame_pts.push(buf.pts().map(|t| t.nseconds() as f64 * 1e-9));
        let Some(m) = GateMeta::read(buf) else {
            failure = Some(EvalError(
                "a buffer left leangate without LeanGateMeta".into(),
            ));
            break;
        };
        let rgb = match thumbnail(&mut cache, &sample) {
            Ok(rgb) => rgb,
            Err(e) => {
                failure = Some(e);
                break;
            }
        };
        match sharpness(&mut sharp_cache, &sample) {
            Ok(s) => frame_sharpness.push(s),
            Err(e) => {
                failure = Some(e);
                break;
            }
        }
        thumbs.push(grey(&rgb));
        let i = metas.len();
        if m.keep {
            // A consumer measures what it gets; a pair without ground truth is not reported.
            if let (Some(teacher), Some(&(prev, _))) = (feedback, kept_thumbs.last()) {
                if let Some(p) = teacher.score(i, prev) {
                    reports.push_back((i + delay, p.tau));
                }
            }
            kept_thumbs.push((i, rgb));
        }
        while reports.front().is_some_and(|&(due, _)| due <= i) {
            let (_, tau) = reports.pop_front().unwrap();
            let s = gst::Structure::builder(gstleangate::FEEDBACK_EVENT)
                .field("tau", tau)
                .build();
            sink.send_event(gst::event::CustomUpstream::new(s));
        }
        metas.push(m);
        step.finished(metas.len());
        progress(metas.len());
    }
    step.stop();
    let elapsed = start.elapsed().as_secs_f64();
    log.drain(&bus);
    // Read before the element stops (its start resets it).
    let feedback_offset = feedback.map(|_| gate.property::<f64>("feedback-offset"));
    let _ = pipeline.set_state(gst::State::Null);
    if let Some(f) = feeder {
        f.join()
            .map_err(|_| EvalError("frame feeder panicked".into()))??;
    }
    if let Some(e) = log.error.or(failure) {
        return Err(e);
    }
    if metas.is_empty() {
        return Err(EvalError("no frame came out of the pipeline".into()));
    }
    let stats = log.stats;
    Ok(ModelRun {
        fps: metas.len() as f64 / elapsed.max(1e-9),
        threshold: stats
            .as_ref()
            .map(|s| s.threshold)
            .or(threshold)
            .unwrap_or(0.5),
        metas,
        thumbs,
        kept_thumbs,
        sharpness: frame_sharpness,
        pts: frame_pts,
        provider: stats
            .as_ref()
            .map(|s| s.execution_provider.clone())
            .unwrap_or_default(),
        model_name: stats.as_ref().map(|s| s.model.clone()).unwrap_or_default(),
        model_precision: stats.map(|s| s.model_precision).unwrap_or_default(),
        feedback_offset,
        failure_warning: log.warning,
    })
}

/// What the bus said during a run: the first error (shown to the user) and the last
/// `leangate-stats`. Read in one pass: `pop_filtered` would discard the messages it does not match.
struct BusLog {
    /// Names the input in errors from the source part of the pipeline.
    input: String,
    gate: gst::Element,
    error: Option<EvalError>,
    stats: Option<StatsMessage>,
    /// The element's first warning (a failed inference, rate-limited by the element).
    warning: Option<String>,
}

impl BusLog {
    fn new(source: &Source, gate: &gst::Element) -> BusLog {
        BusLog {
            input: match source {
                Source::Video(path) => path.display().to_string(),
                Source::Sequence(seq) => seq.root.display().to_string(),
            },
            gate: gate.clone(),
            error: None,
            stats: None,
            warning: None,
        }
    }

    fn drain(&mut self, bus: &gst::Bus) {
        while let Some(msg) = bus.pop() {
            match msg.view() {
                gst::MessageView::Error(e) if self.error.is_none() => {
                    // The element's errors name their subject (the model); the source part's
                    // name the input (the video file or the sequence directory).
                    let from_gate = msg
                        .src()
                        .is_some_and(|src| src == self.gate.upcast_ref::<gst::Object>());
                    let who = (!from_gate).then(|| format!("`{}`", self.input));
                    self.error = Some(EvalError(user_error(e, who.as_deref())));
                }
                gst::MessageView::Warning(w)
                    if self.warning.is_none()
                        && msg
                            .src()
                            .is_some_and(|src| src == self.gate.upcast_ref::<gst::Object>()) =>
                {
                    self.warning = Some(w.error().to_string());
                }
                gst::MessageView::Element(_) => {
                    if let Some(stats) = msg
                        .structure()
                        .and_then(|s| StatsMessage::from_structure(s).ok())
                    {
                        self.stats = Some(stats);
                    }
                }
                _ => {}
            }
        }
    }
}

/// An error message as the user sees it, `[WHO: ]message`, without GStreamer's debug detail
/// (source file, line and function), which goes to the debug log (`GST_DEBUG=leangate-tools:1`).
fn user_error(e: &gst::message::Error, who: Option<&str>) -> String {
    static CAT: std::sync::LazyLock<gst::DebugCategory> = std::sync::LazyLock::new(|| {
        gst::DebugCategory::new(
            "leangate-tools",
            gst::DebugColorFlags::empty(),
            Some("leangate command-line tools"),
        )
    });
    let mut text = match who {
        Some(who) => format!("{who}: {}", e.error()),
        None => e.error().to_string(),
    };
    // GStreamer's "Internal data stream error" says why only in its debug text.
    let why = e.debug().and_then(|d| {
        if d.contains("not-negotiated") {
            Some("the frames' format or size is not one leangate accepts")
        } else if d.contains("not-linked") {
            Some("no video stream reached leangate")
        } else {
            None
        }
    });
    if let Some(why) = why {
        text = format!("{text} ({why})");
    }
    if let Some(d) = e.debug() {
        gst::error!(CAT, "{text} ({d})");
    }
    text
}
