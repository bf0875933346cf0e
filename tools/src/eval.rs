//! `leangate eval`: run gating policies over a sequence and judge each against the teacher.
//!
//! Policies:
//! - `model`: the real `leangate` element, in annotate mode, in a real pipeline (appsrc for image
//!   sequences, filesrc ! decodebin for videos), with the given model;
//! - `oracle`: the same gate ([`gstleangate::Gate`]) driven by the teacher's tau (the upper bound);
//! - `stride`: every s-th frame, s chosen so the kept count matches `model`'s;
//! - `pixel_diff`: an mpdecimate-like gate (8x8 block SADs against the last kept frame, on a
//!   160x120 grey thumbnail), its thresholds scaled so the kept count matches `model`'s.
//!
//! Judging (all against the teacher, so only with depth + poses): for consecutive kept frames
//! (a, b) the teacher's S(b, a): `breaks` (S < 0.05, where MASt3R-SLAM tracking fails),
//! `late_keeps` (S < 0.333: a keyframe was due in between), `min_pair_S`, `median_pair_S`;
//! `overdue_drops`: dropped frames whose teacher tau against the gate's reference was already
//! at or above the threshold; for scored policies `utility_mae` / `utility_rmse` of the gate's utility
//! against the teacher's tau on the same (reference, frame) pairs.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Once;
use std::time::Instant;

use gst::prelude::*;
use serde::Serialize;

use crate::dataset::Sequence;
use crate::teacher::{PairScore, Teacher};
use gstleangate::GateMeta;
use gstleangate::{Gate, GateConfig, Reason, Score};
use gstleangate::{PixelFormat, Preprocessor, ResizeMode, TensorSpec, YuvMatrix};

/// S below which MASt3R-SLAM's tracking breaks.
pub const BREAK_S: f64 = 0.05;
/// MASt3R-SLAM's keyframe threshold on S.
pub const KEYFRAME_S: f64 = 0.333;
/// Thumbnail size used by `pixel_diff`.
pub const THUMB_W: u32 = 160;
pub const THUMB_H: u32 = 120;

#[derive(Debug)]
pub struct EvalError(pub String);

impl std::fmt::Display for EvalError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for EvalError {}

fn err<E: std::fmt::Display>(ctx: &str) -> impl Fn(E) -> EvalError + '_ {
    move |e| EvalError(format!("{ctx}: {e}"))
}

/// One policy's decisions over a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct Trace {
    pub keep: Vec<bool>,
    /// The gate's own utility for frame i against its reference (None: not scored).
    pub utility: Vec<Option<f64>>,
}

impl Trace {
    pub fn kept(&self) -> usize {
        self.keep.iter().filter(|k| **k).count()
    }

    /// Reference of each frame: the last kept frame before it (kept frames become references).
    pub fn references(&self) -> Vec<Option<usize>> {
        let mut r = None;
        self.keep
            .iter()
            .enumerate()
            .map(|(i, &k)| {
                let this = r;
                if k {
                    r = Some(i);
                }
                this
            })
            .collect()
    }

    /// Consecutive kept pairs (earlier, later).
    pub fn kept_pairs(&self) -> Vec<(usize, usize)> {
        let kept: Vec<usize> = (0..self.keep.len()).filter(|&i| self.keep[i]).collect();
        kept.windows(2).map(|w| (w[0], w[1])).collect()
    }
}

/// The gate driven by the teacher: the oracle policy. Returns the trace and, per frame, the
/// reference and teacher score used (None for the first frame).
pub fn oracle_gate(teacher: &Teacher, cfg: GateConfig) -> (Trace, Vec<Option<(usize, PairScore)>>) {
    let mut gate = Gate::new(cfg);
    let mut reference = None;
    let mut keep = Vec::with_capacity(teacher.len());
    let mut utility = Vec::with_capacity(teacher.len());
    let mut used = Vec::with_capacity(teacher.len());
    for i in 0..teacher.len() {
        let (score, u) = match reference {
            Some(r) => {
                let s = teacher.score(i, r);
                used.push(Some((r, s)));
                (Score::Utility(s.tau), Some(s.tau))
            }
            None => {
                used.push(None);
                (Score::NoReference, None)
            }
        };
        let d = gate.decide(score);
        if d.keep {
            reference = Some(i);
        }
        keep.push(d.keep);
        utility.push(u);
    }
    (Trace { keep, utility }, used)
}

/// Keep every `stride`-th frame, starting with the first.
pub fn stride_gate(frames: usize, stride: usize) -> Trace {
    let stride = stride.max(1);
    Trace {
        keep: (0..frames).map(|i| i % stride == 0).collect(),
        utility: vec![None; frames],
    }
}

/// The stride whose kept count is closest to `target`.
pub fn stride_for_budget(frames: usize, target: usize) -> usize {
    (1..=frames.max(1))
        .min_by_key(|&s| (frames.div_ceil(s) as i64 - target as i64).abs())
        .unwrap_or(1)
}

/// mpdecimate-like gate on grey thumbnails (THUMB_W x THUMB_H, 0..255): a frame is a duplicate of
/// the last kept one when no 8x8 block differs by more than `hi` (sum of absolute differences)
/// and at most `frac` of the blocks differ by more than `lo`. `scale` multiplies hi and lo.
pub fn pixel_diff_gate(thumbs: &[Vec<u8>], scale: f64) -> Trace {
    let (hi, lo, frac) = (64.0 * 12.0 * scale, 64.0 * 5.0 * scale, 0.33);
    let (bw, bh) = ((THUMB_W / 8) as usize, (THUMB_H / 8) as usize);
    let w = THUMB_W as usize;
    let mut keep = Vec::with_capacity(thumbs.len());
    let mut reference: Option<&Vec<u8>> = None;
    for t in thumbs {
        let k = match reference {
            None => true,
            Some(r) => {
                let mut over_lo = 0usize;
                let mut over_hi = false;
                for by in 0..bh {
                    for bx in 0..bw {
                        let mut sad = 0.0f64;
                        for y in 0..8 {
                            let row = (by * 8 + y) * w + bx * 8;
                            for x in 0..8 {
                                sad +=
                                    (t[row + x] as i32 - r[row + x] as i32).unsigned_abs() as f64;
                            }
                        }
                        over_hi |= sad > hi;
                        over_lo += (sad > lo) as usize;
                    }
                }
                over_hi || over_lo as f64 > frac * (bw * bh) as f64
            }
        };
        if k {
            reference = Some(t);
        }
        keep.push(k);
    }
    Trace {
        utility: vec![None; keep.len()],
        keep,
    }
}

/// `pixel_diff` with its thresholds scaled so the kept count is as close as possible to `target`.
pub fn pixel_diff_for_budget(thumbs: &[Vec<u8>], target: usize) -> Trace {
    // Kept count falls as the scale grows: bisect on log(scale).
    let (mut lo, mut hi) = (-12.0f64, 6.0f64);
    let mut best = pixel_diff_gate(thumbs, 1.0);
    let dist = |t: &Trace| (t.kept() as i64 - target as i64).abs();
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        let t = pixel_diff_gate(thumbs, mid.exp());
        if dist(&t) < dist(&best) {
            best = t.clone();
        }
        if t.kept() > target {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    best
}

/// Judgement of one policy. Field names are the JSON keys.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PolicyReport {
    pub kept: usize,
    pub keep_ratio: f64,
    pub downsample: f64,
    pub breaks: Option<usize>,
    pub late_keeps: Option<usize>,
    #[serde(rename = "min_pair_S")]
    pub min_pair_s: Option<f64>,
    #[serde(rename = "median_pair_S")]
    pub median_pair_s: Option<f64>,
    pub overdue_drops: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub utility_mae: Option<Option<f64>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub utility_rmse: Option<Option<f64>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
}

/// Teacher scores, memoised (policies share many pairs).
pub struct TeacherCache<'a> {
    teacher: &'a Teacher,
    memo: HashMap<(usize, usize), PairScore>,
}

impl<'a> TeacherCache<'a> {
    pub fn new(teacher: &'a Teacher) -> Self {
        TeacherCache {
            teacher,
            memo: HashMap::new(),
        }
    }

    /// Score many (current, keyframe) pairs in parallel, remembering them.
    pub fn prefetch(&mut self, pairs: &[(usize, usize)]) {
        let todo: Vec<_> = pairs
            .iter()
            .copied()
            .filter(|p| !self.memo.contains_key(p))
            .collect::<std::collections::HashSet<_>>()
            .into_iter()
            .collect();
        let scores = self.teacher.score_pairs(&todo);
        self.memo.extend(todo.into_iter().zip(scores));
    }

    pub fn get(&mut self, cur: usize, key: usize) -> PairScore {
        if let Some(s) = self.memo.get(&(cur, key)) {
            return *s;
        }
        let s = self.teacher.score(cur, key);
        self.memo.insert((cur, key), s);
        s
    }
}

/// Judge a trace. `scored`: whether the policy has its own utility (MAE/RMSE keys present).
pub fn judge(
    trace: &Trace,
    teacher: Option<&mut TeacherCache>,
    threshold: f64,
    scored: bool,
    fps: Option<f64>,
) -> PolicyReport {
    let n = trace.keep.len();
    let kept = trace.kept();
    let mut r = PolicyReport {
        kept,
        keep_ratio: if n > 0 { kept as f64 / n as f64 } else { 0.0 },
        downsample: if kept > 0 {
            n as f64 / kept as f64
        } else {
            0.0
        },
        breaks: None,
        late_keeps: None,
        min_pair_s: None,
        median_pair_s: None,
        overdue_drops: None,
        utility_mae: scored.then_some(None),
        utility_rmse: scored.then_some(None),
        fps,
    };
    let Some(tc) = teacher else {
        return r;
    };
    let refs = trace.references();
    let pairs = trace.kept_pairs();
    let mut wanted: Vec<(usize, usize)> = pairs.iter().map(|&(a, b)| (b, a)).collect();
    wanted.extend(
        refs.iter()
            .enumerate()
            .filter_map(|(i, r)| r.map(|r| (i, r))),
    );
    tc.prefetch(&wanted);
    let mut s: Vec<f64> = pairs.iter().map(|&(a, b)| tc.get(b, a).s).collect();
    r.breaks = Some(s.iter().filter(|&&v| v < BREAK_S).count());
    r.late_keeps = Some(s.iter().filter(|&&v| v < KEYFRAME_S).count());
    s.sort_by(|a, b| a.total_cmp(b));
    r.min_pair_s = s.first().copied();
    r.median_pair_s = if s.is_empty() {
        None
    } else if s.len() % 2 == 1 {
        Some(s[s.len() / 2])
    } else {
        Some(0.5 * (s[s.len() / 2 - 1] + s[s.len() / 2]))
    };
    let mut overdue = 0;
    let (mut abs_sum, mut sq_sum, mut count) = (0.0, 0.0, 0usize);
    for (i, reference) in refs.iter().enumerate() {
        let Some(reference) = *reference else {
            continue;
        };
        let t = tc.get(i, reference).tau;
        if !trace.keep[i] && t >= threshold {
            overdue += 1;
        }
        if let Some(u) = trace.utility[i] {
            abs_sum += (u - t).abs();
            sq_sum += (u - t) * (u - t);
            count += 1;
        }
    }
    r.overdue_drops = Some(overdue);
    if scored && count > 0 {
        r.utility_mae = Some(Some(abs_sum / count as f64));
        r.utility_rmse = Some(Some((sq_sum / count as f64).sqrt()));
    }
    r
}

/// What the eval runs on.
#[derive(Debug, Clone)]
pub enum Source {
    /// A directory sequence (TUM layout or rgb.txt / images only). Without full ground truth
    /// every colour frame is used, matched to a pose or not.
    Sequence(Sequence),
    /// A video file, decoded by GStreamer.
    Video(PathBuf),
}

impl Source {
    pub fn open(path: &Path) -> Result<Source, EvalError> {
        if path.is_dir() {
            let seq = Sequence::open(path).map_err(|e| EvalError(e.to_string()))?;
            if seq.has_ground_truth() {
                return Ok(Source::Sequence(seq));
            }
            // No teacher possible: gate every colour frame, poses or not.
            let all = crate::dataset::OpenOptions {
                drop_unmatched: false,
                ..Default::default()
            };
            Sequence::open_with(path, &all)
                .map(Source::Sequence)
                .map_err(|e| EvalError(e.to_string()))
        } else if path.is_file() {
            Ok(Source::Video(path.to_path_buf()))
        } else {
            Err(EvalError(format!(
                "`{}`: no such sequence directory or video file",
                path.display()
            )))
        }
    }
}

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

/// A grid of the kept frames' thumbnails (at most `max_tiles`, evenly sampled), 8 per row.
pub fn contact_sheet(
    kept: &[(usize, image::RgbImage)],
    max_tiles: usize,
    out: &Path,
) -> Result<(), EvalError> {
    if kept.is_empty() {
        return Err(EvalError("no kept frame to put on a contact sheet".into()));
    }
    let n = kept.len().min(max_tiles.max(1));
    let cols = n.min(8) as u32;
    let rows = n.div_ceil(cols as usize) as u32;
    let pad = 4;
    let mut sheet = image::RgbImage::from_pixel(
        cols * (THUMB_W + pad) + pad,
        rows * (THUMB_H + pad) + pad,
        image::Rgb([255, 255, 255]),
    );
    for k in 0..n {
        let (_, t) = &kept[k * kept.len() / n];
        let (c, r) = (k as u32 % cols, k as u32 / cols);
        image::imageops::replace(
            &mut sheet,
            t,
            (pad + c * (THUMB_W + pad)) as i64,
            (pad + r * (THUMB_H + pad)) as i64,
        );
    }
    sheet
        .save(out)
        .map_err(|e| EvalError(format!("`{}`: {e}", out.display())))
}

/// Run the real element in annotate mode over the source, with `model` (None: the embedded
/// default). `progress(done)` is called per frame.
pub fn run_model(
    source: &Source,
    model: Option<&Path>,
    threshold: Option<f64>,
    mut progress: impl FnMut(usize),
) -> Result<ModelRun, EvalError> {
    init_gstreamer()?;
    let gate = gst::ElementFactory::make("leangate")
        .build()
        .map_err(err("creating leangate"))?;
    if let Some(m) = model {
        gate.set_property("model", m.display().to_string());
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
                if let Some(s) = msg
                    .structure()
                    .filter(|s| s.name() == gstleangate::STATS_MESSAGE)
                {
                    stats_threshold = s.get::<f64>("threshold").ok();
                    provider = s.get::<String>("execution-provider").unwrap_or_default();
                    name = s.get::<String>("model").unwrap_or_default();
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

/// The full report written as JSON.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub sequence: String,
    pub frames: usize,
    pub threshold: f64,
    pub policies: serde_json::Map<String, serde_json::Value>,
}

/// Everything a plot needs.
#[derive(Debug, Clone)]
pub struct PlotData {
    /// Teacher tau of each frame against the model gate's reference (None: no ground truth).
    pub teacher_tau: Vec<Option<f64>>,
    pub predicted_tau: Vec<Option<f64>>,
    pub threshold: f64,
    /// Kept flags per policy, in display order.
    pub kept: Vec<(String, Vec<bool>)>,
    /// Thumbnails of the frames the model kept.
    pub kept_thumbs: Vec<(usize, image::RgbImage)>,
}

/// Run every policy and judge it. `progress(stage, done, total)`.
pub fn evaluate(
    path: &Path,
    model: Option<&Path>,
    threshold: Option<f64>,
    teacher_cfg: &crate::teacher::TeacherConfig,
    mut progress: impl FnMut(&str, usize, usize),
) -> Result<(EvalReport, PlotData), EvalError> {
    let source = Source::open(path)?;
    let n_hint = match &source {
        Source::Sequence(s) => s.len(),
        Source::Video(_) => 0,
    };
    let run = run_model(&source, model, threshold, |d| progress("model", d, n_hint))?;
    let n = run.metas.len();
    let t = run.threshold;
    let teacher = match &source {
        Source::Sequence(seq) if seq.has_ground_truth() => {
            if seq.len() != n {
                return Err(EvalError(format!(
                    "the pipeline returned {n} frames for a sequence of {}",
                    seq.len()
                )));
            }
            Some(Teacher::from_sequence(seq, teacher_cfg).map_err(|e| EvalError(e.to_string()))?)
        }
        _ => None,
    };
    let mut cache = teacher.as_ref().map(TeacherCache::new);

    let model_trace = run.trace();
    let budget = model_trace.kept();
    let mut policies = serde_json::Map::new();
    let mut kept_rows = Vec::new();
    let mut add = |name: &str, report: PolicyReport, trace: &Trace| {
        policies.insert(name.to_string(), serde_json::to_value(report).unwrap());
        kept_rows.push((name.to_string(), trace.keep.clone()));
    };
    add(
        "model",
        judge(&model_trace, cache.as_mut(), t, true, Some(run.fps)),
        &model_trace,
    );
    if let Some(teacher) = teacher.as_ref() {
        progress("oracle", 0, n);
        let (oracle, _) = oracle_gate(
            teacher,
            GateConfig {
                threshold: t,
                ..Default::default()
            },
        );
        progress("oracle", n, n);
        add(
            "oracle",
            judge(&oracle, cache.as_mut(), t, true, None),
            &oracle,
        );
    }
    let stride = stride_gate(n, stride_for_budget(n, budget));
    add(
        "stride",
        judge(&stride, cache.as_mut(), t, false, None),
        &stride,
    );
    let pd = pixel_diff_for_budget(&run.thumbs, budget);
    add(
        "pixel_diff",
        judge(&pd, cache.as_mut(), t, false, None),
        &pd,
    );

    let refs = model_trace.references();
    let teacher_tau = refs
        .iter()
        .enumerate()
        .map(|(i, r)| match (r, cache.as_mut()) {
            (Some(r), Some(c)) => Some(c.get(i, *r).tau),
            _ => None,
        })
        .collect();
    Ok((
        EvalReport {
            sequence: path.display().to_string(),
            frames: n,
            threshold: t,
            policies,
        },
        PlotData {
            teacher_tau,
            predicted_tau: model_trace.utility.clone(),
            threshold: t,
            kept: kept_rows,
            kept_thumbs: run.kept_thumbs,
        },
    ))
}

/// Draw teacher and predicted tau over time, the threshold, and kept frames per policy.
pub fn plot(data: &PlotData, title: &str, out: &Path) -> Result<(), EvalError> {
    use plotters::prelude::*;
    register_font();
    let n = data.predicted_tau.len().max(2);
    let rows = data.kept.len();
    let root = BitMapBackend::new(out, (1200, 520 + 28 * rows as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(err("plot"))?;
    let (top, bottom) = root.split_vertically(480);
    let e = err::<String>("plot");
    let mut chart = ChartBuilder::on(&top)
        .caption(title, ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(0f64..(n - 1) as f64, -0.02f64..1.02f64)
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .x_desc("frame")
        .y_desc("tau (utility)")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    let series = |v: &[Option<f64>]| -> Vec<Vec<(f64, f64)>> {
        // Break the line where there is no value.
        let mut out = vec![Vec::new()];
        for (i, x) in v.iter().enumerate() {
            match x {
                Some(y) => out.last_mut().unwrap().push((i as f64, *y)),
                None if !out.last().unwrap().is_empty() => out.push(Vec::new()),
                None => {}
            }
        }
        out
    };
    let teacher_color = RGBColor(30, 30, 30);
    let pred_color = RGBColor(220, 80, 20);
    for (k, seg) in series(&data.teacher_tau).into_iter().enumerate() {
        let s = chart
            .draw_series(LineSeries::new(seg, teacher_color.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?;
        if k == 0 {
            s.label("teacher tau vs model's reference")
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], teacher_color));
        }
    }
    for (k, seg) in series(&data.predicted_tau).into_iter().enumerate() {
        let s = chart
            .draw_series(LineSeries::new(seg, pred_color.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?;
        if k == 0 {
            s.label("predicted tau (model)")
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], pred_color));
        }
    }
    chart
        .draw_series(LineSeries::new(
            [(0.0, data.threshold), ((n - 1) as f64, data.threshold)],
            BLUE.stroke_width(1),
        ))
        .map_err(|x| e(x.to_string()))?
        .label(format!("threshold {:.3}", data.threshold))
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLUE));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;

    let mut keep_chart = ChartBuilder::on(&bottom)
        .margin(10)
        .x_label_area_size(5)
        .y_label_area_size(45)
        .build_cartesian_2d(0f64..(n - 1) as f64, 0f64..rows as f64)
        .map_err(|x| e(x.to_string()))?;
    let palette = [
        RGBColor(220, 80, 20),
        RGBColor(30, 30, 30),
        RGBColor(40, 120, 200),
        RGBColor(60, 160, 60),
    ];
    for (row, (name, kept)) in data.kept.iter().enumerate() {
        let y = (rows - row) as f64 - 0.5;
        let c = palette[row % palette.len()];
        keep_chart
            .draw_series(
                kept.iter()
                    .enumerate()
                    .filter(|(_, k)| **k)
                    .map(|(i, _)| Circle::new((i as f64, y), 3, c.filled())),
            )
            .map_err(|x| e(x.to_string()))?;
        keep_chart
            .draw_series(std::iter::once(Text::new(
                format!("{name} ({})", kept.iter().filter(|k| **k).count()),
                (0.0, y + 0.3),
                ("sans-serif", 14),
            )))
            .map_err(|x| e(x.to_string()))?;
    }
    root.present().map_err(err("plot"))?;
    Ok(())
}

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        for p in [
            "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
            "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
        ] {
            if let Ok(bytes) = std::fs::read(p) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                let _ = plotters::style::register_font(
                    "sans-serif",
                    plotters::style::FontStyle::Normal,
                    bytes,
                );
                break;
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trace(keep: &[u8]) -> Trace {
        Trace {
            keep: keep.iter().map(|&k| k == 1).collect(),
            utility: vec![None; keep.len()],
        }
    }

    #[test]
    fn references_and_pairs() {
        let t = trace(&[1, 0, 0, 1, 0, 1]);
        assert_eq!(
            t.references(),
            vec![None, Some(0), Some(0), Some(0), Some(3), Some(3)]
        );
        assert_eq!(t.kept_pairs(), vec![(0, 3), (3, 5)]);
        assert_eq!(t.kept(), 3);
    }

    #[test]
    fn stride_budget() {
        assert_eq!(stride_for_budget(60, 6), 10);
        assert_eq!(stride_for_budget(60, 60), 1);
        assert_eq!(stride_gate(10, 3).kept(), 4);
        assert_eq!(stride_for_budget(60, 1), 60);
    }

    #[test]
    fn pixel_diff_static_and_changing() {
        let a = vec![10u8; (THUMB_W * THUMB_H) as usize];
        let b = vec![200u8; (THUMB_W * THUMB_H) as usize];
        let still = vec![a.clone(); 5];
        assert_eq!(pixel_diff_gate(&still, 1.0).kept(), 1);
        let alternating = vec![a.clone(), b.clone(), a.clone(), b.clone()];
        assert_eq!(pixel_diff_gate(&alternating, 1.0).kept(), 4);
        // Budget tuning reaches a target between the extremes.
        let mut ramp = Vec::new();
        for i in 0..20 {
            ramp.push(vec![i as u8 * 4; (THUMB_W * THUMB_H) as usize]);
        }
        let t = pixel_diff_for_budget(&ramp, 5);
        assert!((t.kept() as i64 - 5).abs() <= 1, "kept {}", t.kept());
    }

    #[test]
    fn judge_without_teacher_has_counts_only() {
        let t = trace(&[1, 0, 1, 0]);
        let r = judge(&t, None, 0.5, true, Some(12.0));
        assert_eq!((r.kept, r.keep_ratio, r.downsample), (2, 0.5, 2.0));
        assert_eq!(r.breaks, None);
        let v = serde_json::to_value(&r).unwrap();
        let keys: Vec<_> = v.as_object().unwrap().keys().cloned().collect();
        for k in [
            "kept",
            "keep_ratio",
            "downsample",
            "breaks",
            "late_keeps",
            "min_pair_S",
            "median_pair_S",
            "overdue_drops",
            "utility_mae",
            "utility_rmse",
            "fps",
        ] {
            assert!(keys.contains(&k.to_string()), "{k} missing in {keys:?}");
        }
        assert!(v["breaks"].is_null() && v["utility_mae"].is_null());
        let unscored = serde_json::to_value(judge(&t, None, 0.5, false, None)).unwrap();
        assert_eq!(unscored.as_object().unwrap().len(), 8);
    }
}
