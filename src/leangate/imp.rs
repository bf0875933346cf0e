use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{LazyLock, Mutex, MutexGuard};
use std::time::Instant;

use gst::glib;
use gst::prelude::*;
use gst::subclass::prelude::*;
use gst_base::subclass::prelude::*;

use super::{ExecutionProviderChoice, GateMode, FORCE_KEYFRAME_EVENT, RESET_EVENT};
use crate::meta::GateMeta;
use crate::policy::{Gate, GateConfig, Score};
use crate::preprocess::{PixelFormat, Preprocessor, YuvMatrix};
use crate::scorer::{ModelSource, Scorer, ScorerError, ScorerOptions};
use crate::stats::{InferenceStats, StatsMessage};

static CAT: LazyLock<gst::DebugCategory> = LazyLock::new(|| {
    gst::DebugCategory::new(
        "leangate",
        gst::DebugColorFlags::empty(),
        Some("LeanGate geometric-utility frame gate"),
    )
});

/// Threshold used when neither the property nor the model sets one.
const DEFAULT_THRESHOLD: f64 = 0.5;
/// Minimum time between two run-time warnings posted on the bus.
const WARN_EVERY: std::time::Duration = std::time::Duration::from_secs(5);

#[derive(Debug, Clone)]
struct Settings {
    model: Option<String>,
    /// Negative: take it from the model's metadata, else DEFAULT_THRESHOLD.
    threshold: f64,
    warmup: u32,
    max_gap: u32,
    mode: GateMode,
    execution_provider: ExecutionProviderChoice,
    device_id: i32,
    threads: u32,
    stats_interval: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            model: None,
            threshold: -1.0,
            warmup: 0,
            max_gap: 0,
            mode: GateMode::Drop,
            execution_provider: ExecutionProviderChoice::Auto,
            device_id: 0,
            threads: 0,
            stats_interval: 0,
        }
    }
}

struct State {
    scorer: Scorer,
    model_threshold: Option<f64>,
    pre: Option<(gst_video::VideoInfo, Preprocessor)>,
    gate: Gate,
    reference: Vec<f32>,
    reference_pts: Option<gst::ClockTime>,
    current: Vec<f32>,
    stats: InferenceStats,
    last_stats_pts: Option<gst::ClockTime>,
    last_warning: Option<Instant>,
    suppressed_warnings: u64,
}

#[derive(Default)]
pub struct LeanGate {
    settings: Mutex<Settings>,
    state: Mutex<Option<State>>,
    frames_in: AtomicU64,
    frames_kept: AtomicU64,
    force_pending: AtomicBool,
    reset_pending: AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl LeanGate {
    fn gate_config(settings: &Settings, model_threshold: Option<f64>) -> GateConfig {
        GateConfig {
            threshold: if settings.threshold >= 0.0 {
                settings.threshold
            } else {
                model_threshold.unwrap_or(DEFAULT_THRESHOLD)
            },
            warmup: settings.warmup as u64,
            max_gap: settings.max_gap as u64,
        }
    }

    /// Post a warning on the bus at most every WARN_EVERY; always log it.
    fn warn_rate_limited(&self, state: &mut State, msg: &str) {
        gst::warning!(CAT, imp = self, "{msg}");
        let now = Instant::now();
        let due = state
            .last_warning
            .is_none_or(|t| now.duration_since(t) >= WARN_EVERY);
        if due {
            let extra = if state.suppressed_warnings > 0 {
                format!(
                    " ({} similar warnings suppressed)",
                    state.suppressed_warnings
                )
            } else {
                String::new()
            };
            gst::element_imp_warning!(
                self,
                gst::StreamError::Failed,
                ("{}; the frame was kept (fail open){}", msg, extra)
            );
            state.last_warning = Some(now);
            state.suppressed_warnings = 0;
        } else {
            state.suppressed_warnings += 1;
        }
    }

    fn post_stats(&self, state: &State) {
        let frames_in = self.frames_in.load(Ordering::Relaxed);
        let frames_kept = self.frames_kept.load(Ordering::Relaxed);
        let threshold = state.gate.config().threshold;
        let s = StatsMessage {
            frames_in,
            frames_kept,
            keep_ratio: if frames_in > 0 {
                frames_kept as f64 / frames_in as f64
            } else {
                0.0
            },
            inference_mean_us: state.stats.mean_us(),
            inference_p99_us: state.stats.percentile_us(99.0),
            execution_provider: state.scorer.provider().to_string(),
            model: state.scorer.info().name.clone(),
            threshold,
        }
        .to_structure();
        let _ = self
            .obj()
            .post_message(gst::message::Element::builder(s).src(&*self.obj()).build());
    }

    /// Handle the custom events (both directions); returns true when it was one of ours.
    fn note_custom_event(&self, event: &gst::Event) -> bool {
        let Some(s) = event.structure() else {
            return false;
        };
        if s.name() == FORCE_KEYFRAME_EVENT {
            gst::debug!(CAT, imp = self, "force-keyframe requested");
            self.force_pending.store(true, Ordering::SeqCst);
            true
        } else if s.name() == RESET_EVENT {
            gst::debug!(CAT, imp = self, "reset requested");
            self.reset_pending.store(true, Ordering::SeqCst);
            true
        } else {
            false
        }
    }

    /// Preprocess the buffer into `state.current`.
    fn preprocess(&self, state: &mut State, buf: &gst::BufferRef) -> Result<(), String> {
        let State { pre, current, .. } = state;
        let (info, pre) = pre
            .as_ref()
            .ok_or_else(|| "no caps negotiated before the first buffer".to_string())?;
        pre.run_buffer(buf, info, current)
            .map_err(|e| e.to_string())
    }
}

#[glib::object_subclass]
impl ObjectSubclass for LeanGate {
    const NAME: &'static str = "GstLeanGate";
    type Type = super::LeanGate;
    type ParentType = gst_base::BaseTransform;
}

impl ObjectImpl for LeanGate {
    fn properties() -> &'static [glib::ParamSpec] {
        static PROPERTIES: LazyLock<Vec<glib::ParamSpec>> = LazyLock::new(|| {
            vec![
                glib::ParamSpecString::builder("model")
                    .nick("Model")
                    .blurb(
                        "Path to a LeanGate model: a pair model (.onnx: inputs `reference`, \
                         `current` [N,3,H,W] float32, output `utility`) or the encoder of a split \
                         model; unset = the embedded default student leangate-s. See \
                         models/README.md",
                    )
                    .mutable_ready()
                    .build(),
                glib::ParamSpecDouble::builder("threshold")
                    .nick("Threshold")
                    .blurb(
                        "tau_keep: keep a frame when its predicted utility is >= this. \
                         -1 = the model's leangate.threshold metadata, else 0.5",
                    )
                    .minimum(-1.0)
                    .maximum(1.0)
                    .default_value(-1.0)
                    .mutable_playing()
                    .build(),
                glib::ParamSpecUInt::builder("warmup")
                    .nick("Warm-up frames")
                    .blurb("Always keep the first N frames after the stream (re)starts")
                    .default_value(0)
                    .mutable_playing()
                    .build(),
                glib::ParamSpecUInt::builder("max-gap")
                    .nick("Maximum gap")
                    .blurb("Force a keep after this many consecutive dropped frames (0 = off)")
                    .default_value(0)
                    .mutable_playing()
                    .build(),
                glib::ParamSpecEnum::builder_with_default("mode", GateMode::Drop)
                    .nick("Mode")
                    .blurb(
                        "drop: only kept frames leave; annotate: every frame leaves, tagged \
                         with LeanGateMeta (utility, keep, reason, ...)",
                    )
                    .mutable_playing()
                    .build(),
                glib::ParamSpecEnum::builder_with_default(
                    "execution-provider",
                    ExecutionProviderChoice::Auto,
                )
                .nick("Execution provider")
                .blurb(
                    "ONNX Runtime execution provider: auto tries tensorrt, cuda, then cpu; an \
                     explicit GPU choice that fails is an error",
                )
                .mutable_ready()
                .build(),
                glib::ParamSpecInt::builder("device-id")
                    .nick("GPU device id")
                    .blurb("CUDA/TensorRT device index")
                    .minimum(0)
                    .default_value(0)
                    .mutable_ready()
                    .build(),
                glib::ParamSpecUInt::builder("threads")
                    .nick("CPU threads")
                    .blurb("ONNX Runtime intra-op threads on CPU (0 = ONNX Runtime's default)")
                    .default_value(0)
                    .mutable_ready()
                    .build(),
                glib::ParamSpecUInt64::builder("stats-interval")
                    .nick("Statistics interval")
                    .blurb(
                        "Post a `leangate-stats` element message every this many nanoseconds of \
                         stream time (0 = only at EOS)",
                    )
                    .default_value(0)
                    .mutable_playing()
                    .build(),
                glib::ParamSpecUInt64::builder("frames-in")
                    .nick("Frames in")
                    .blurb("Frames received since start (read-only)")
                    .read_only()
                    .build(),
                glib::ParamSpecUInt64::builder("frames-kept")
                    .nick("Frames kept")
                    .blurb("Frames kept since start (read-only)")
                    .read_only()
                    .build(),
            ]
        });
        PROPERTIES.as_ref()
    }

    fn set_property(&self, _id: usize, value: &glib::Value, pspec: &glib::ParamSpec) {
        let mut settings = lock(&self.settings);
        match pspec.name() {
            "model" => settings.model = value.get().expect("type checked upstream"),
            "threshold" => settings.threshold = value.get().expect("type checked upstream"),
            "warmup" => settings.warmup = value.get().expect("type checked upstream"),
            "max-gap" => settings.max_gap = value.get().expect("type checked upstream"),
            "mode" => settings.mode = value.get().expect("type checked upstream"),
            "execution-provider" => {
                settings.execution_provider = value.get().expect("type checked upstream")
            }
            "device-id" => settings.device_id = value.get().expect("type checked upstream"),
            "threads" => settings.threads = value.get().expect("type checked upstream"),
            "stats-interval" => {
                settings.stats_interval = value.get().expect("type checked upstream")
            }
            other => unreachable!("unknown property {other}"),
        }
        // Gate parameters apply from the next frame.
        let settings = settings.clone();
        if let Some(state) = lock(&self.state).as_mut() {
            let cfg = Self::gate_config(&settings, state.model_threshold);
            state.gate.set_config(cfg);
        }
    }

    fn property(&self, _id: usize, pspec: &glib::ParamSpec) -> glib::Value {
        let settings = lock(&self.settings);
        match pspec.name() {
            "model" => settings.model.to_value(),
            "threshold" => settings.threshold.to_value(),
            "warmup" => settings.warmup.to_value(),
            "max-gap" => settings.max_gap.to_value(),
            "mode" => settings.mode.to_value(),
            "execution-provider" => settings.execution_provider.to_value(),
            "device-id" => settings.device_id.to_value(),
            "threads" => settings.threads.to_value(),
            "stats-interval" => settings.stats_interval.to_value(),
            "frames-in" => self.frames_in.load(Ordering::Relaxed).to_value(),
            "frames-kept" => self.frames_kept.load(Ordering::Relaxed).to_value(),
            other => unreachable!("unknown property {other}"),
        }
    }
}

impl GstObjectImpl for LeanGate {}

impl ElementImpl for LeanGate {
    fn metadata() -> Option<&'static gst::subclass::ElementMetadata> {
        static ELEMENT_METADATA: LazyLock<gst::subclass::ElementMetadata> = LazyLock::new(|| {
            gst::subclass::ElementMetadata::new(
                "LeanGate",
                "Filter/Analyzer/Video",
                "Drops video frames that add no new geometry for a monocular SLAM system, using a \
                 learned geometric-utility score against the last kept frame; tags every outgoing \
                 buffer with LeanGateMeta",
                "LeanGate developers",
            )
        });
        Some(&*ELEMENT_METADATA)
    }

    fn pad_templates() -> &'static [gst::PadTemplate] {
        static PAD_TEMPLATES: LazyLock<Vec<gst::PadTemplate>> = LazyLock::new(|| {
            let caps = gst_video::VideoCapsBuilder::new()
                .format_list(PixelFormat::ALL.iter().map(|f| f.to_video_format()))
                .build();
            vec![
                gst::PadTemplate::new(
                    "src",
                    gst::PadDirection::Src,
                    gst::PadPresence::Always,
                    &caps,
                )
                .unwrap(),
                gst::PadTemplate::new(
                    "sink",
                    gst::PadDirection::Sink,
                    gst::PadPresence::Always,
                    &caps,
                )
                .unwrap(),
            ]
        });
        PAD_TEMPLATES.as_ref()
    }
}

impl BaseTransformImpl for LeanGate {
    const MODE: gst_base::subclass::BaseTransformMode =
        gst_base::subclass::BaseTransformMode::AlwaysInPlace;
    const PASSTHROUGH_ON_SAME_CAPS: bool = false;
    const TRANSFORM_IP_ON_PASSTHROUGH: bool = false;

    fn start(&self) -> Result<(), gst::ErrorMessage> {
        let settings = lock(&self.settings).clone();
        let source = match settings.model.clone().filter(|m| !m.is_empty()) {
            Some(path) => ModelSource::File(path.into()),
            None => crate::default_model::source(),
        };
        let opts = ScorerOptions {
            execution_provider: settings.execution_provider.into(),
            device_id: settings.device_id,
            threads: settings.threads as usize,
        };
        let scorer = Scorer::load(&source, &opts).map_err(|e| {
            let kind = match &e {
                ScorerError::Runtime(_) => gst::LibraryError::Init,
                ScorerError::Provider { .. } => gst::LibraryError::Settings,
                _ => gst::LibraryError::Failed,
            };
            gst::error_msg!(kind, ("{}", e))
        })?;
        for w in &scorer.warnings {
            gst::warning!(CAT, imp = self, "{w}");
        }
        let info = scorer.info().clone();
        gst::info!(
            CAT,
            imp = self,
            "model {} ({}x{}, {}), provider {}",
            info.name,
            info.spec.width,
            info.spec.height,
            info.spec.resize.as_str(),
            scorer.provider()
        );
        let cfg = Self::gate_config(&settings, info.threshold);
        self.frames_in.store(0, Ordering::Relaxed);
        self.frames_kept.store(0, Ordering::Relaxed);
        self.force_pending.store(false, Ordering::SeqCst);
        self.reset_pending.store(false, Ordering::SeqCst);
        *lock(&self.state) = Some(State {
            scorer,
            model_threshold: info.threshold,
            pre: None,
            gate: Gate::new(cfg),
            reference: vec![0.0; info.spec.len()],
            reference_pts: None,
            current: vec![0.0; info.spec.len()],
            stats: InferenceStats::default(),
            last_stats_pts: None,
            last_warning: None,
            suppressed_warnings: 0,
        });
        Ok(())
    }

    fn stop(&self) -> Result<(), gst::ErrorMessage> {
        *lock(&self.state) = None;
        Ok(())
    }

    fn set_caps(&self, incaps: &gst::Caps, _outcaps: &gst::Caps) -> Result<(), gst::LoggableError> {
        let info = gst_video::VideoInfo::from_caps(incaps)
            .map_err(|_| gst::loggable_error!(CAT, "cannot parse video caps {incaps}"))?;
        let format = PixelFormat::from_video_format(info.format())
            .ok_or_else(|| gst::loggable_error!(CAT, "unsupported format {:?}", info.format()))?;
        let mut guard = lock(&self.state);
        let state = guard
            .as_mut()
            .ok_or_else(|| gst::loggable_error!(CAT, "caps set before start"))?;
        let yuv = YuvMatrix::from_colorimetry(&info.colorimetry(), info.height());
        let pre = Preprocessor::new(
            format,
            info.width(),
            info.height(),
            yuv,
            state.scorer.info().spec.clone(),
        )
        .map_err(|e| gst::loggable_error!(CAT, "{e}"))?;
        gst::debug!(CAT, imp = self, "configured for {incaps}");
        // A new picture geometry: the old reference is not comparable any more.
        state.gate.drop_reference();
        state.pre = Some((info, pre));
        Ok(())
    }

    fn sink_event(&self, event: gst::Event) -> bool {
        match event.view() {
            gst::EventView::CustomDownstream(_) | gst::EventView::CustomBoth(_) => {
                self.note_custom_event(&event);
            }
            gst::EventView::FlushStop(_) | gst::EventView::StreamStart(_) => {
                if let Some(state) = lock(&self.state).as_mut() {
                    state.gate.restart();
                    state.last_stats_pts = None;
                }
                self.force_pending.store(false, Ordering::SeqCst);
                self.reset_pending.store(false, Ordering::SeqCst);
            }
            gst::EventView::Eos(_) => {
                if let Some(state) = lock(&self.state).as_ref() {
                    self.post_stats(state);
                }
            }
            _ => {}
        }
        self.parent_sink_event(event)
    }

    fn src_event(&self, event: gst::Event) -> bool {
        if let gst::EventView::CustomUpstream(_) | gst::EventView::CustomBoth(_) = event.view() {
            self.note_custom_event(&event);
        }
        self.parent_src_event(event)
    }

    fn transform_ip(&self, buf: &mut gst::BufferRef) -> Result<gst::FlowSuccess, gst::FlowError> {
        let (mode, stats_interval) = {
            let s = lock(&self.settings);
            (s.mode, s.stats_interval)
        };
        let mut guard = lock(&self.state);
        let Some(state) = guard.as_mut() else {
            gst::element_imp_error!(
                self,
                gst::CoreError::Negotiation,
                ("buffer received before the element started")
            );
            return Err(gst::FlowError::Flushing);
        };
        self.frames_in.fetch_add(1, Ordering::Relaxed);
        if self.reset_pending.swap(false, Ordering::SeqCst) {
            state.gate.drop_reference();
        }
        if self.force_pending.swap(false, Ordering::SeqCst) {
            state.gate.force_keyframe();
        }

        let t0 = Instant::now();
        let pre = self.preprocess(state, buf);
        let frame_readable = pre.is_ok();
        let (score, utility) = match pre {
            Err(e) => {
                self.warn_rate_limited(state, &format!("cannot read frame: {e}"));
                (Score::Failed, f64::NAN)
            }
            Ok(()) if !state.gate.has_reference() => (Score::NoReference, f64::NAN),
            Ok(()) => match state.scorer.score(&state.reference, &state.current) {
                Ok(u) => (Score::Utility(u as f64), u as f64),
                Err(e) => {
                    self.warn_rate_limited(state, &e.to_string());
                    (Score::Failed, f64::NAN)
                }
            },
        };
        let inference_us = t0.elapsed().as_micros() as u64;
        if matches!(score, Score::Utility(_)) {
            state.stats.record(inference_us);
        }
        let pts = buf.pts();
        let decision = state.gate.decide(score);
        let reference_pts = if decision.keep && score == Score::NoReference {
            pts
        } else {
            state.reference_pts
        };
        if decision.keep {
            // A split model reuses the features it just computed for this frame.
            state.scorer.on_keep(matches!(score, Score::Utility(_)));
            if !frame_readable {
                // The frame could not be read: it cannot serve as a reference tensor.
                state.gate.drop_reference();
            } else {
                std::mem::swap(&mut state.reference, &mut state.current);
            }
            state.reference_pts = pts;
            self.frames_kept.fetch_add(1, Ordering::Relaxed);
        }

        if let (Some(pts), true) = (pts, stats_interval > 0) {
            match state.last_stats_pts {
                None => state.last_stats_pts = Some(pts),
                Some(last) if pts.nseconds().saturating_sub(last.nseconds()) >= stats_interval => {
                    state.last_stats_pts = Some(pts);
                    self.post_stats(state);
                }
                _ => {}
            }
        }

        gst::trace!(
            CAT,
            imp = self,
            "pts {:?} utility {:.4} keep {} ({})",
            pts,
            utility,
            decision.keep,
            decision.reason
        );

        if !decision.keep && mode == GateMode::Drop {
            return Ok(gst_base::BASE_TRANSFORM_FLOW_DROPPED);
        }
        let meta = GateMeta {
            utility,
            keep: decision.keep,
            reason: decision.reason,
            keyframe_index: decision.keyframe_index,
            reference_pts,
            frames_since_keyframe: decision.frames_since_keyframe.min(u32::MAX as u64) as u32,
            inference_us,
        };
        if let Err(e) = meta.attach(buf) {
            gst::warning!(CAT, imp = self, "cannot attach LeanGateMeta: {e}");
        }
        Ok(gst::FlowSuccess::Ok)
    }
}
