//! The element: its state, the streaming thread (score, gate, hold, push), events, queries.
//! Its properties (defaults, specs, how a change applies) are in `imp/settings.rs`.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{LazyLock, Mutex, MutexGuard};
use std::time::Instant;

use gst::glib;
use gst::prelude::*;
use gst::subclass::prelude::*;
use gst_base::prelude::*;
use gst_base::subclass::prelude::*;

use super::{
    ExecutionProviderChoice, GateMode, PrecisionChoice, FEEDBACK_EVENT, FORCE_KEYFRAME_EVENT,
    RESET_EVENT,
};
use crate::depth::DepthInput;
use crate::meta::GateMeta;
use crate::policy::{Gate, GateConfig, Reason, Score};
use crate::preprocess::{try_zeroed, PixelFormat, Preprocessor, YuvMatrix};
use crate::quality::Quality;
use crate::remote::{Backend, Interrupt, RemoteOptions, RemoteScorer};
use crate::scorer::{ModelSource, Scorer, ScorerError, ScorerOptions};
use crate::stats::{InferenceStats, StatsMessage};
use crate::utility::{Composed, Utility, FEEDBACK_LIMIT};

mod settings;
use settings::{FrameSettings, Settings, FALLBACK_THRESHOLD};

static CAT: LazyLock<gst::DebugCategory> = LazyLock::new(|| {
    gst::DebugCategory::new(
        "leangate",
        gst::DebugColorFlags::empty(),
        Some("LeanGate geometric-utility frame gate"),
    )
});

/// Most `leangate-feedback` reports held between two frames (the oldest are dropped beyond).
const MAX_PENDING_FEEDBACK: usize = 256;

/// Minimum time between two run-time warnings posted on the bus.
const WARN_EVERY: std::time::Duration = std::time::Duration::from_secs(5);

/// The `tau` of a `leangate-feedback` structure: any number type (the range is checked where it
/// is applied, `Utility::feedback`). Refusals name the problem in a few words, never the
/// structure itself (a report may carry anything, and refusals are held until the next frame).
fn feedback_tau(s: &gst::StructureRef) -> Result<f64, String> {
    let v = s
        .value("tau")
        .map_err(|_| "it has no `tau` field".to_string())?;
    v.get::<f64>()
        .or_else(|_| v.get::<f32>().map(f64::from))
        .or_else(|_| v.get::<i32>().map(f64::from))
        .or_else(|_| v.get::<u32>().map(f64::from))
        .or_else(|_| v.get::<i64>().map(|x| x as f64))
        .or_else(|_| v.get::<u64>().map(|x| x as f64))
        .map_err(|_| format!("its `tau` is a {}, not a number", v.type_().name()))
}

struct State {
    scorer: Backend,
    model_threshold: Option<f64>,
    /// How the frame's utility is composed: the model's score, fused with the geometric prior
    /// when the model has a `leangate.geometry` fusion.
    utility: Utility,
    pre: Option<(gst_video::VideoInfo, Preprocessor)>,
    gate: Gate,
    reference: Vec<f32>,
    reference_pts: Option<gst::ClockTime>,
    current: Vec<f32>,
    /// The model pictures of the recent frames that `sharpness-lookback` may still keep
    /// (candidates of [`Gate`]), oldest first.
    recent: std::collections::VecDeque<Recent>,
    stats: InferenceStats,
    last_stats_pts: Option<gst::ClockTime>,
    /// `frames-in` / `frames-kept` at the previous stats message (for the interval fields).
    /// `frames-in`, `frames-kept` and `frames-screened` when the current stats interval began.
    interval_start: (u64, u64, u64),
    /// Run-time failures on frames (unreadable, inference failed): each kept, fail open.
    frame_warnings: RateLimit,
    /// Unusable `leangate-feedback` reports: counted apart, so that neither kind of warning
    /// silences or is counted as the other.
    feedback_warnings: RateLimit,
    /// Unusable depth (`LeanGateDepthMeta`), counted apart too.
    depth_warnings: RateLimit,
}

/// Posts one warning of a kind at most every WARN_EVERY, counting those held back.
#[derive(Debug, Default)]
struct RateLimit {
    last: Option<Instant>,
    suppressed: u64,
}

impl RateLimit {
    /// `msg` for the bus now (with how many were held back since the last one), or None.
    fn admit(&mut self, msg: &str) -> Option<String> {
        let now = Instant::now();
        if self
            .last
            .is_some_and(|t| now.duration_since(t) < WARN_EVERY)
        {
            self.suppressed += 1;
            return None;
        }
        let msg = match std::mem::take(&mut self.suppressed) {
            0 => msg.to_string(),
            n => format!("{msg} ({n} similar warnings suppressed)"),
        };
        self.last = Some(now);
        Some(msg)
    }
}

/// What the streaming thread posts or pushes, collected under the state lock and sent after it
/// is released (a synchronous bus handler may call back into the element).
#[derive(Debug, Default)]
struct Outbox {
    warnings: Vec<String>,
    stats: Vec<gst::Structure>,
}

/// Locking: `settings` and `state` are never held at the same time, and nothing is posted,
/// pushed or called out while either is held. `interrupt` is taken alone, briefly.
#[derive(Default)]
pub struct LeanGate {
    settings: Mutex<Settings>,
    state: Mutex<Option<State>>,
    /// Stops the scorer's stream from a state change or flush while the streaming thread holds
    /// `state` (leaves the batch, interrupts a server request in flight); set between start
    /// and stop.
    interrupt: Mutex<Option<Interrupt>>,
    frames_in: AtomicU64,
    frames_kept: AtomicU64,
    frames_screened: AtomicU64,
    frames_junk: AtomicU64,
    force_pending: AtomicBool,
    reset_pending: AtomicBool,
    /// `leangate-feedback` events not yet applied (their `tau` and the `feedback-rate` when they
    /// arrived, or in a few words why one is unusable); taken alone, briefly, and applied by the
    /// streaming thread at the next frame.
    feedback: Mutex<std::collections::VecDeque<Result<(f64, f64), String>>>,
    /// The utility's offset learnt from feedback (f64 bits), for the `feedback-offset` property.
    feedback_offset: AtomicU64,
    /// Frames held for `sharpness-lookback`, oldest first (only the streaming thread and
    /// serialized events touch it; taken alone, never with `settings` or `state`).
    held: Mutex<std::collections::VecDeque<Held>>,
    /// One frame's duration from the caps (ns; 0: unknown), for the latency query.
    frame_ns: AtomicU64,
    /// With a variable framerate (caps 0/1): the longest frame interval seen since the caps (a
    /// buffer's duration, else the step between timestamps; ns, 0: none yet), so that the
    /// latency query still covers the frames `sharpness-lookback` holds; and the last
    /// timestamp (ns, u64::MAX: none). Only the streaming thread writes them.
    vfr_frame_ns: AtomicU64,
    vfr_last_pts: AtomicU64,
    /// Refused property values whose warning found no bus (set before the element was in a
    /// pipeline: gst-launch sets properties first); posted at the next start. Taken alone.
    unposted: Mutex<Vec<String>>,
    /// The last caps refusal said on the bus: negotiation retries the same caps (set-caps) and
    /// asks again and again about the same format (accept-caps, a dozen times through
    /// decodebin), and the application needs to be told once. Nothing else is taken while it
    /// is held.
    refused_caps: Mutex<Option<String>>,
}

impl State {
    /// A keep went to the recent frame `back` frames before the last decided one (a
    /// `sharpness-lookback` keep, or one settled when the held frames were let go): it is the
    /// reference now, and the prior's chain goes on from it. Returns its timestamp.
    fn keep_back(&mut self, back: u64) -> Option<gst::ClockTime> {
        let at = self.gate.position().checked_sub(1 + back);
        match self.recent.iter().position(|r| Some(r.position) == at) {
            Some(i) => {
                std::mem::swap(&mut self.reference, &mut self.recent[i].tensor);
                self.reference_pts = self.recent[i].pts;
                self.utility.on_keep_back(back);
                self.scorer.on_keep(false);
                self.reference_pts
            }
            // Not remembered (cannot happen: the gate's candidates are these frames); the next
            // frame starts afresh rather than comparing with the wrong picture.
            None => {
                self.gate.drop_reference();
                None
            }
        }
    }
}

/// Mark the held frame `back` before the last one kept (reason `sharper`, keep `index`); the
/// frames after it leave after it, so their count of keeps includes it (their reference and
/// frames since it stay the ones they were compared with). Whether that frame was held.
fn mark_kept_back(held: &mut std::collections::VecDeque<Held>, back: u64, index: u64) -> bool {
    let Some(at) = held.len().checked_sub(1 + back as usize) else {
        return false;
    };
    let Some(h) = held.get_mut(at) else {
        return false;
    };
    h.meta.keep = true;
    h.meta.reason = Reason::Sharper;
    h.meta.keyframe_index = index;
    h.meta.frames_since_keyframe = 0;
    for h in held.iter_mut().skip(at + 1) {
        h.meta.keyframe_index = index;
    }
    true
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// What one frame turned into.
struct Verdict {
    keep: bool,
    meta: GateMeta,
    /// The keep due on this frame went to the frame this many before it (`sharpness-lookback`).
    kept_back: u64,
}

/// A recent frame's model picture, kept for `sharpness-lookback`.
struct Recent {
    /// The frame's position in the gate ([`Gate::position`]).
    position: u64,
    pts: Option<gst::ClockTime>,
    tensor: Vec<f32>,
}

/// A frame the element holds for `sharpness-lookback`, until it is that many frames old (a
/// later keep may still go back to it until then).
struct Held {
    buf: gst::Buffer,
    meta: GateMeta,
    /// Serialized events that came after this frame (and before the next): they leave with it,
    /// in order, rather than letting every held frame out first (see `sink_event`).
    events_after: Vec<gst::Event>,
}

impl LeanGate {
    /// With a variable framerate, the held frames' latency follows the longest frame interval
    /// seen: a longer one than before (by a tenth) is remembered and the pipeline told to query
    /// the latency again (a hostile probe: a live VFR source lost 87 of 90 frames at a
    /// synchronised sink, told of no latency while 3 frames were held). No lock is held here.
    fn track_variable_framerate(&self, buf: &gst::BufferRef) {
        if self.frame_ns.load(Ordering::Relaxed) != 0 {
            return;
        }
        let pts = buf.pts().map(|t| t.nseconds());
        let last = self.vfr_last_pts.load(Ordering::Relaxed);
        if let Some(p) = pts {
            self.vfr_last_pts.store(p, Ordering::Relaxed);
        }
        // A discontinuity (a seek, lost data) is no frame interval.
        let discont = buf.flags().contains(gst::BufferFlags::DISCONT);
        let step = pts
            .filter(|&p| !discont && last != u64::MAX && p > last)
            .map(|p| p - last);
        let Some(interval) = buf.duration().map(|d| d.nseconds()).or(step) else {
            return;
        };
        let known = self.vfr_frame_ns.load(Ordering::Relaxed);
        if interval > known.saturating_add(known / 10) {
            self.vfr_frame_ns.store(interval, Ordering::Relaxed);
            let obj = self.obj();
            let _ = obj.post_message(gst::message::Latency::builder().src(&*obj).build());
        }
    }

    /// A new run or new caps: no variable-framerate interval seen yet.
    fn forget_frame_intervals(&self) {
        self.vfr_frame_ns.store(0, Ordering::Relaxed);
        self.vfr_last_pts.store(u64::MAX, Ordering::Relaxed);
    }

    /// Whether `msg` (a caps refusal) is new this run and should be said on the bus; remembers
    /// it. The lock is released before the caller posts.
    fn first_refusal(&self, msg: &str) -> bool {
        let mut last = lock(&self.refused_caps);
        if last.as_deref() == Some(msg) {
            return false;
        }
        *last = Some(msg.to_owned());
        true
    }

    fn gate_config(settings: &FrameSettings, model_threshold: Option<f64>) -> GateConfig {
        GateConfig {
            threshold: if settings.threshold >= 0.0 {
                settings.threshold
            } else {
                model_threshold.unwrap_or(FALLBACK_THRESHOLD)
            },
            warmup: settings.warmup as u64,
            max_gap: settings.max_gap as u64,
            sharpness_wait: settings.sharpness_wait as u64,
            sharpness_lookback: settings.sharpness_lookback as u64,
            sharpness_margin: settings.sharpness_margin,
        }
    }

    /// Apply `f` to the scorer's [`Interrupt`] (between start and stop), with no lock held.
    fn interrupt(&self, f: impl FnOnce(&Interrupt)) {
        let i = lock(&self.interrupt).clone();
        if let Some(i) = i {
            f(&i);
        }
    }

    fn frame_settings(&self) -> FrameSettings {
        FrameSettings::from(&*lock(&self.settings))
    }

    /// Forget what the consumer's feedback taught the utility (a new stream or new caps).
    fn reset_feedback(&self, state: &mut State) {
        state.utility.reset_feedback();
        self.feedback_offset
            .store(0f64.to_bits(), Ordering::Relaxed);
    }

    /// A run-time failure on a frame (which is kept, fail open): on the bus and in the debug log
    /// at WARNING at most every WARN_EVERY (with how many were suppressed), every one at DEBUG.
    fn warn_rate_limited(&self, state: &mut State, out: &mut Outbox, msg: &str) {
        let msg = format!("{msg}; the frame was kept (fail open)");
        match state.frame_warnings.admit(&msg) {
            Some(admitted) => {
                gst::warning!(CAT, imp = self, "{admitted}");
                out.warnings.push(admitted);
            }
            None => gst::debug!(CAT, imp = self, "{msg}"),
        }
    }

    /// Depth that cannot be used (a malformed `LeanGateDepthMeta`): the frame is gated
    /// colour-only. Rate-limited apart from the frames' failures.
    fn warn_depth(&self, state: &mut State, out: &mut Outbox, msg: &str) {
        let msg = format!("depth ignored: {msg}; the frame is gated colour-only");
        match state.depth_warnings.admit(&msg) {
            Some(admitted) => {
                gst::warning!(CAT, imp = self, "{admitted}");
                out.warnings.push(admitted);
            }
            None => gst::debug!(CAT, imp = self, "{msg}"),
        }
    }

    /// The `leangate-stats` structure; starts a new interval.
    fn stats_structure(&self, state: &mut State) -> gst::Structure {
        let frames_in = self.frames_in.load(Ordering::Relaxed);
        let frames_kept = self.frames_kept.load(Ordering::Relaxed);
        let frames_screened = self.frames_screened.load(Ordering::Relaxed);
        let frames_junk = self.frames_junk.load(Ordering::Relaxed);
        let (in0, kept0, screened0) = state.interval_start;
        let interval = state.stats.interval();
        let s = StatsMessage {
            frames_in,
            frames_kept,
            frames_screened,
            frames_junk,
            keep_ratio: if frames_in > 0 {
                frames_kept as f64 / frames_in as f64
            } else {
                0.0
            },
            inference_mean_us: state.stats.mean_us(),
            inference_p50_us: state.stats.percentile_us(50.0),
            inference_p99_us: state.stats.percentile_us(99.0),
            interval_frames_in: frames_in.saturating_sub(in0),
            interval_frames_kept: frames_kept.saturating_sub(kept0),
            interval_frames_screened: frames_screened.saturating_sub(screened0),
            interval_inference_mean_us: interval.mean(),
            interval_inference_p50_us: interval.percentile(50.0),
            interval_inference_p99_us: interval.percentile(99.0),
            execution_provider: state.scorer.provider().to_string(),
            model: state.scorer.info().name.clone(),
            model_precision: state.scorer.info().precision.clone(),
            threshold: state.gate.config().threshold,
            feedback_offset: state.utility.offset(),
            server: state.scorer.server_stats(),
        }
        .to_structure();
        state.interval_start = (frames_in, frames_kept, frames_screened);
        state.stats.start_interval();
        s
    }

    /// Post what was collected under the lock. Must be called with no lock held.
    fn send(&self, out: Outbox) {
        for w in out.warnings {
            gst::element_imp_warning!(self, gst::StreamError::Failed, ("{}", w));
        }
        for s in out.stats {
            let obj = self.obj();
            let _ = obj.post_message(gst::message::Element::builder(s).src(&*obj).build());
        }
    }

    /// Handle the custom events (both directions, in-band or out of band); returns true when it
    /// was one of ours.
    fn note_custom_event(&self, event: &gst::Event) -> bool {
        let Some(s) = event.structure() else {
            return false;
        };
        if s.name() == FORCE_KEYFRAME_EVENT {
            gst::debug!(CAT, imp = self, "force-keyframe requested");
            self.force_pending.store(true, Ordering::SeqCst);
            true
        } else if s.name() == FEEDBACK_EVENT {
            // The rate in force when the report arrives (0: ignored from the start).
            let rate = lock(&self.settings).feedback_rate;
            if rate == 0.0 {
                gst::debug!(CAT, imp = self, "feedback ignored (feedback-rate 0)");
                return true;
            }
            let report = feedback_tau(s).map(|tau| (tau, rate));
            gst::debug!(CAT, imp = self, "feedback: {report:?}");
            let mut pending = lock(&self.feedback);
            // A consumer that reports faster than frames arrive (or while the stream waits)
            // must not grow this without bound: the oldest reports go first.
            if pending.len() >= MAX_PENDING_FEEDBACK {
                pending.pop_front();
            }
            pending.push_back(report);
            true
        } else if s.name() == RESET_EVENT {
            gst::debug!(CAT, imp = self, "reset requested");
            self.reset_pending.store(true, Ordering::SeqCst);
            true
        } else {
            false
        }
    }

    /// Push frames leaving the look-back (`sharpness-lookback`), in order: kept ones (every one
    /// in annotate mode) with their LeanGateMeta, a gap for each dropped one. No lock is held.
    /// A kept frame that could not be pushed (flushing, downstream gone) is not counted, nor
    /// are the kept frames after it, which go nowhere either.
    fn output_held(
        &self,
        ready: Vec<Held>,
        mode: GateMode,
    ) -> Result<gst::FlowSuccess, gst::FlowError> {
        let src = self.obj().src_pad().clone();
        let mut ready = ready.into_iter();
        while let Some(h) = ready.next() {
            if !h.meta.keep && mode == GateMode::Drop {
                if let Some(pts) = h.buf.pts().or(h.buf.dts()) {
                    let gap = gst::event::Gap::builder(pts)
                        .duration(h.buf.duration())
                        .build();
                    let _ = src.push_event(gap);
                }
            } else {
                let kept = h.meta.keep;
                let mut buf = h.buf;
                if let Err(e) = h.meta.attach(buf.make_mut()) {
                    gst::warning!(CAT, imp = self, "cannot attach LeanGateMeta: {e}");
                }
                if let Err(e) = src.push(buf) {
                    let lost = u64::from(kept) + ready.filter(|h| h.meta.keep).count() as u64;
                    self.uncount_kept(lost);
                    return Err(e);
                }
            }
            for event in h.events_after {
                let _ = src.push_event(event);
            }
        }
        Ok(gst::FlowSuccess::Ok)
    }

    /// `n` kept frames never left the element (a flush discarded them while held, or their push
    /// failed): `frames-kept` and the next keyframe index do not count them. Takes `state`.
    fn uncount_kept(&self, n: u64) {
        if n == 0 {
            return;
        }
        let _ = self
            .frames_kept
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |k| {
                Some(k.saturating_sub(n))
            });
        if let Some(state) = lock(&self.state).as_mut() {
            state.gate.discard_kept(n);
        }
    }

    /// Let every held frame go with its fate as it stands (pushed when `push`, else discarded:
    /// a flush), and tell the gate they can no longer be kept instead of a later frame.
    fn release_held(&self, push: bool) {
        if lock(&self.held).is_empty() {
            return;
        }
        if !push {
            // A flush: the held frames go nowhere, so their keeps were never made.
            let discarded = std::mem::take(&mut *lock(&self.held));
            let kept = discarded.iter().filter(|h| h.meta.keep).count() as u64;
            drop(discarded);
            if let Some(state) = lock(&self.state).as_mut() {
                state.gate.forget_candidates();
            }
            self.uncount_kept(kept);
            return;
        }
        // A keep owed (waiting for a sharper frame) is made now, on the sharpest frame still
        // held, instead of being lost with the stream's end.
        let settled = match lock(&self.state).as_mut() {
            Some(state) => {
                let settled = state.gate.settle_pending();
                // The settled frame is the reference from now on (the stream may go on after a
                // segment), as for a keep that went back while frames came.
                let settled = settled.map(|(back, index)| (back, index, state.keep_back(back)));
                state.gate.forget_candidates();
                settled
            }
            None => None,
        };
        let (ready, marked): (Vec<Held>, bool) = {
            let mut held = lock(&self.held);
            let marked = settled.is_some_and(|(back, index, _)| {
                let marked = mark_kept_back(&mut held, back, index);
                if marked {
                    self.frames_kept.fetch_add(1, Ordering::Relaxed);
                }
                marked
            });
            (held.drain(..).collect(), marked)
        };
        if settled.is_some() && !marked {
            // Not held (cannot happen: the gate settles on a frame it knows is held): the keep
            // was not made, so it is not counted.
            if let Some(state) = lock(&self.state).as_mut() {
                state.gate.discard_kept(1);
            }
        }
        if let Some((back, _, pts)) = settled {
            gst::trace!(
                CAT,
                imp = self,
                "pts {} keep true (sharper: settled when the held frames were let go, {} frames \
                 before the last)",
                pts.display(),
                back
            );
        }
        let mode = self.frame_settings().mode;
        let _ = self.output_held(ready, mode);
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

    /// Score and decide one frame under the state lock; what is to be posted goes to `out`.
    /// `None`: the scoring was interrupted (stopping or flushing, see `interrupt`).
    fn gate_frame(
        &self,
        buf: &gst::BufferRef,
        fs: &FrameSettings,
        out: &mut Outbox,
    ) -> Result<Option<Verdict>, gst::FlowError> {
        // Taken alone, before the state lock.
        let feedback = std::mem::take(&mut *lock(&self.feedback));
        let mut guard = lock(&self.state);
        let Some(state) = guard.as_mut() else {
            return Err(gst::FlowError::Flushing);
        };
        state
            .gate
            .set_config(Self::gate_config(fs, state.model_threshold));
        self.frames_in.fetch_add(1, Ordering::Relaxed);
        if self.reset_pending.swap(false, Ordering::SeqCst) {
            state.gate.drop_reference();
        }
        if self.force_pending.swap(false, Ordering::SeqCst) {
            state.gate.force_keyframe();
        }
        // The threshold in force for this frame: the reports are measured against it, and the
        // frame is screened and gated by it below.
        let threshold = state.gate.config().threshold;
        state.utility.set_feedback_lower(fs.feedback_lower);
        self.feedback_offset
            .store(state.utility.offset().to_bits(), Ordering::Relaxed);
        for report in feedback {
            match report.and_then(|(tau, rate)| state.utility.feedback(tau, threshold, rate)) {
                Ok(offset) => self
                    .feedback_offset
                    .store(offset.to_bits(), Ordering::Relaxed),
                Err(e) => {
                    let msg = format!("{FEEDBACK_EVENT} ignored: {e}");
                    gst::warning!(CAT, imp = self, "{msg}");
                    out.warnings.extend(state.feedback_warnings.admit(&msg));
                }
            }
        }

        let t0 = Instant::now();
        let pre = self.preprocess(state, buf);
        let frame_readable = pre.is_ok();
        let has_reference = state.gate.has_reference();
        let spec = &state.scorer.info().spec;
        let frame = frame_readable.then_some((&state.current[..], spec));
        state.utility.set_quality_check(fs.reject_junk);
        state
            .utility
            .set_sharpness_measure(fs.sharpness_wait > 0 || fs.sharpness_lookback > 0);
        // A picture its decoder flagged as damaged (concealment after lost data) or a gap
        // filler is junk, whatever its pixels (`reject-junk`).
        let damaged = buf
            .flags()
            .intersects(gst::BufferFlags::CORRUPTED | gst::BufferFlags::GAP);
        if damaged && fs.reject_junk && frame_readable {
            state.utility.observe_damaged();
        } else {
            state.utility.observe(frame, has_reference, fs.geometry);
        }
        let model_step = state.scorer.info().geometry.and_then(|f| f.s_step);
        state.utility.set_score_step(if fs.screen_step < 0.0 {
            model_step
        } else {
            Some(fs.screen_step)
        });
        let quality = state.utility.quality();
        // Depth beside the colour (`LeanGateDepthMeta`): the metric gate's pose and utility.
        let depth =
            DepthInput::read(buf).and_then(|d| d.map_err(|e| self.warn_depth(state, out, &e)).ok());
        match (&state.pre, frame_readable && !quality.is_junk()) {
            (Some((info, _)), true) => {
                let spec = &state.scorer.info().spec;
                let src = (info.width(), info.height());
                let frame = (&state.current[..], spec);
                if let Err(e) =
                    state
                        .utility
                        .observe_depth(frame, depth.as_ref(), src, has_reference)
                {
                    self.warn_depth(state, out, &e);
                }
            }
            _ => state.utility.skip_depth(),
        }
        let mut screened = false;
        let (score, utility) = match pre {
            Err(e) => {
                self.warn_rate_limited(state, out, &format!("cannot read frame: {e}"));
                (Score::Failed, f64::NAN)
            }
            // No usable picture: never kept, never the reference (crate::quality).
            Ok(()) if quality.is_junk() => (Score::Junk, f64::NAN),
            Ok(()) if !has_reference => (Score::NoReference, f64::NAN),
            // With depth and a pose: the teacher's own utility, no model run.
            Ok(()) if let Some(tau) = state.utility.metric_tau() => (Score::Utility(tau), tau),
            Ok(()) => {
                let (scorer, reference, current) =
                    (&mut state.scorer, &state.reference, &state.current);
                let model = || scorer.score(reference, current).map(f64::from);
                match state
                    .utility
                    .score_with(threshold, fs.geometry, fs.screen, model)
                {
                    Ok(Composed::Textureless) => (Score::Utility(0.0), 0.0),
                    Ok(Composed::Screened(bound)) => {
                        screened = true;
                        gst::trace!(CAT, imp = self, "screened: utility <= {bound:.4}");
                        (Score::Utility(bound), bound)
                    }
                    Ok(Composed::Scored {
                        utility,
                        s,
                        tau_geo,
                    }) => {
                        if let Some(g) = tau_geo {
                            gst::trace!(CAT, imp = self, "student {s:.4} geometry {g:.4}");
                        }
                        (Score::Utility(utility), utility)
                    }
                    // Stopping or flushing (see `interrupt`): the frame goes nowhere.
                    Err(ScorerError::Interrupted) => return Ok(None),
                    Err(e) => {
                        self.warn_rate_limited(state, out, &e.to_string());
                        (Score::Failed, f64::NAN)
                    }
                }
            }
        };
        if let Some((s, max)) = state.utility.take_broken_bound() {
            let msg = format!(
                "the model scored {s:.6}, above the {max} its leangate.score_max promises: \
                 screening no longer relies on it (frames screened before were judged by it; \
                 correct or remove the model's leangate.score_max)"
            );
            gst::warning!(CAT, imp = self, "{msg}");
            // Once per start (the bound is dropped with it), so never rate-limited: the frames'
            // own warnings must not swallow it.
            out.warnings.push(msg);
        }
        let inference_us = t0.elapsed().as_micros().min(u64::MAX as u128) as u64;
        if screened {
            self.frames_screened.fetch_add(1, Ordering::Relaxed);
        } else if score == Score::Junk {
            self.frames_junk.fetch_add(1, Ordering::Relaxed);
        } else if matches!(score, Score::Utility(_)) && quality == Quality::Usable {
            state.stats.record(inference_us);
        }
        let pts = buf.pts();
        let position = state.gate.position();
        let sharpness = state.utility.sharpness();
        let decision = state.gate.decide_with(score, sharpness);
        let reference_pts = if decision.keep && score == Score::NoReference {
            pts
        } else {
            state.reference_pts
        };
        if decision.kept_back > 0 {
            // The keep went to a sharper recent frame (held by `submit_input_buffer`): it is the
            // reference now, and the prior's chain goes on from it.
            let kept_pts = state.keep_back(decision.kept_back);
            gst::trace!(
                CAT,
                imp = self,
                "pts {} keep true (sharper: the keep due at pts {}, {} frames later)",
                kept_pts.display(),
                pts.display(),
                decision.kept_back
            );
            self.frames_kept.fetch_add(1, Ordering::Relaxed);
        } else if decision.candidate && frame_readable && fs.sharpness_lookback > 0 {
            // A candidate for a later keep (the gate says so: dropped on score, or waited on
            // while a keep settles).
            // Entries the gate no longer asks for (older, or before the last keep) are reused.
            let mut tensor = Vec::new();
            while state.recent.len() >= fs.sharpness_lookback as usize {
                if let Some(r) = state.recent.pop_front() {
                    tensor = r.tensor;
                }
            }
            tensor.clear();
            tensor.extend_from_slice(&state.current);
            state.recent.push_back(Recent {
                position,
                pts,
                tensor,
            });
        }
        if decision.keep {
            // A split model reuses the features it just computed for this frame.
            state
                .scorer
                .on_keep(matches!(score, Score::Utility(_)) && !screened);
            if !frame_readable {
                // The frame could not be read: it cannot serve as a reference tensor.
                state.gate.drop_reference();
            } else {
                std::mem::swap(&mut state.reference, &mut state.current);
                state.utility.on_keep();
            }
            state.reference_pts = pts;
            self.frames_kept.fetch_add(1, Ordering::Relaxed);
        }

        if let (Some(pts), true) = (pts, fs.stats_interval > 0) {
            // Stream time in either direction: reverse playback (a negative rate) brings PTS
            // down frame by frame, and a looping source jumps back; both count as time passed.
            match state.last_stats_pts {
                None => state.last_stats_pts = Some(pts),
                Some(last) if pts.nseconds().abs_diff(last.nseconds()) >= fs.stats_interval => {
                    state.last_stats_pts = Some(pts);
                    let s = self.stats_structure(state);
                    out.stats.push(s);
                }
                _ => {}
            }
        }

        gst::trace!(
            CAT,
            imp = self,
            "pts {} utility {:.4} keep {} ({}, {})",
            pts.display(),
            utility,
            decision.keep,
            decision.reason,
            quality.as_str()
        );
        Ok(Some(Verdict {
            keep: decision.keep,
            meta: GateMeta {
                utility,
                keep: decision.keep,
                reason: decision.reason,
                keyframe_index: decision.keyframe_index,
                reference_pts,
                frames_since_keyframe: decision.frames_since_keyframe.min(u32::MAX as u64) as u32,
                inference_us,
                screened,
                quality,
                depth: state.utility.depth_use(),
            },
            kept_back: decision.kept_back,
        }))
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
        static PROPERTIES: LazyLock<Vec<glib::ParamSpec>> = LazyLock::new(settings::specs);
        PROPERTIES.as_ref()
    }

    fn set_property(&self, _id: usize, value: &glib::Value, pspec: &glib::ParamSpec) {
        self.set_property_value(value, pspec);
    }

    fn property(&self, _id: usize, pspec: &glib::ParamSpec) -> glib::Value {
        let settings = lock(&self.settings);
        self.property_value(&settings, pspec.name())
    }
}

impl GstObjectImpl for LeanGate {}

impl ElementImpl for LeanGate {
    fn change_state(
        &self,
        transition: gst::StateChange,
    ) -> Result<gst::StateChangeSuccess, gst::StateChangeError> {
        // Before the pads deactivate (which waits for the streaming thread): the elements
        // batching with this one stop waiting for it, and a server request in flight is
        // interrupted instead of running to its timeout.
        match transition {
            gst::StateChange::PlayingToPaused => self.interrupt(Interrupt::idle),
            gst::StateChange::PausedToReady => self.interrupt(Interrupt::cancel),
            _ => {}
        }
        let r = self.parent_change_state(transition);
        if r.is_err() && transition == gst::StateChange::PausedToReady {
            self.interrupt(Interrupt::resume);
        }
        r
    }

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
        // A new run is told about caps it cannot gate again.
        *lock(&self.refused_caps) = None;
        self.forget_frame_intervals();
        // Refusals from before the element had a bus: it has one now.
        let unposted = std::mem::take(&mut *lock(&self.unposted));
        for why in unposted {
            gst::element_imp_warning!(self, gst::CoreError::StateChange, ("{}", why));
        }
        // Mark the model settings in use before reading them, so that a concurrent change is
        // refused rather than reported but not used.
        let settings = {
            let mut s = lock(&self.settings);
            s.in_use = true;
            s.clone()
        };
        let release = || lock(&self.settings).in_use = false;
        let source = match settings.model.clone().filter(|m| !m.is_empty()) {
            Some(path) => ModelSource::File(path.into()),
            None => crate::default_model::source(),
        };
        let server = settings.server.clone().filter(|s| !s.trim().is_empty());
        let opts = ScorerOptions {
            execution_provider: settings.execution_provider.into(),
            device_id: settings.device_id,
            threads: settings.threads as usize,
            spinning: settings.ort_spinning,
            shared: settings.shared_session,
            batch_size: settings.batch_size as usize,
            batch_timeout: std::time::Duration::from_micros(settings.batch_timeout_us),
            max_sessions: settings.max_sessions as usize,
            // On a server (`server`) the encoder is the FP32 one of models/triton: the head
            // that runs here is then FP32 too, unless INT8 is asked for explicitly.
            precision: match settings.precision {
                PrecisionChoice::Auto if server.is_some() => crate::scorer::Precision::Fp32,
                p => p.into(),
            },
        };
        let scorer = Scorer::load(&source, &opts).map_err(|e| {
            release();
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
        let scorer = match server {
            None => Backend::Local(scorer),
            Some(url) => {
                let opts = RemoteOptions {
                    url,
                    model: settings.server_model.clone(),
                    timeout: std::time::Duration::from_millis(settings.server_timeout_ms as u64),
                    max_in_flight: settings.server_max_in_flight,
                };
                let remote = RemoteScorer::connect(scorer, &opts).map_err(|e| {
                    release();
                    gst::error_msg!(gst::ResourceError::OpenRead, ("{}", e))
                })?;
                Backend::Remote(Box::new(remote))
            }
        };
        let info = scorer.info().clone();
        gst::info!(
            CAT,
            imp = self,
            "model {} ({}x{}, {}), provider {}, geometric prior {}",
            info.name,
            info.spec.width,
            info.spec.height,
            info.spec.resize.as_str(),
            scorer.provider(),
            info.geometry
                .map_or("none".to_string(), |f| f.to_metadata())
        );
        let alloc = |what: &str| {
            try_zeroed(info.spec.len()).map_err(|e| {
                release();
                gst::error_msg!(
                    gst::ResourceError::NoSpaceLeft,
                    (
                        "cannot allocate the {} tensor of {}: {}",
                        what,
                        info.name,
                        e
                    )
                )
            })
        };
        let reference = alloc("reference")?;
        let current = alloc("current")?;
        *lock(&self.interrupt) = Some(scorer.interrupt());
        let cfg = Self::gate_config(&FrameSettings::from(&settings), info.threshold);
        self.frames_in.store(0, Ordering::Relaxed);
        self.frames_kept.store(0, Ordering::Relaxed);
        self.frames_screened.store(0, Ordering::Relaxed);
        self.frames_junk.store(0, Ordering::Relaxed);
        self.force_pending.store(false, Ordering::SeqCst);
        self.reset_pending.store(false, Ordering::SeqCst);
        lock(&self.feedback).clear();
        self.feedback_offset
            .store(0f64.to_bits(), Ordering::Relaxed);
        *lock(&self.state) = Some(State {
            scorer,
            model_threshold: info.threshold,
            utility: Utility::new(info.geometry),
            pre: None,
            gate: Gate::new(cfg),
            reference,
            reference_pts: None,
            current,
            recent: std::collections::VecDeque::new(),
            stats: InferenceStats::default(),
            last_stats_pts: None,
            interval_start: (0, 0, 0),
            frame_warnings: RateLimit::default(),
            feedback_warnings: RateLimit::default(),
            depth_warnings: RateLimit::default(),
        });
        Ok(())
    }

    fn stop(&self) -> Result<(), gst::ErrorMessage> {
        lock(&self.interrupt).take();
        let held = std::mem::take(&mut *lock(&self.held));
        drop(held);
        let state = lock(&self.state).take();
        // Dropping the session happens outside the lock.
        drop(state);
        lock(&self.settings).in_use = false;
        Ok(())
    }

    fn set_caps(&self, incaps: &gst::Caps, _outcaps: &gst::Caps) -> Result<(), gst::LoggableError> {
        let info = gst_video::VideoInfo::from_caps(incaps)
            .map_err(|_| gst::loggable_error!(CAT, "cannot parse video caps {incaps}"))?;
        let format = PixelFormat::from_video_format(info.format())
            .ok_or_else(|| gst::loggable_error!(CAT, "unsupported format {:?}", info.format()))?;
        // Reports waiting for the next frame are about the old pictures (taken alone).
        lock(&self.feedback).clear();
        let mut guard = lock(&self.state);
        let state = guard
            .as_mut()
            .ok_or_else(|| gst::loggable_error!(CAT, "caps set before start"))?;
        let yuv = YuvMatrix::from_colorimetry(&info.colorimetry(), info.height());
        let pre = match Preprocessor::new(
            format,
            info.width(),
            info.height(),
            yuv,
            state.scorer.info().spec.clone(),
        ) {
            Ok(pre) => pre,
            Err(e) => {
                // Said on the bus (the state lock released first), so that the application sees
                // why, not only upstream's "not-negotiated".
                drop(guard);
                let msg = format!("cannot gate frames of caps {incaps}: {e}");
                if self.first_refusal(&msg) {
                    gst::element_imp_error!(self, gst::StreamError::Format, ("{}", msg));
                }
                return Err(gst::loggable_error!(CAT, "{e}"));
            }
        };
        gst::debug!(CAT, imp = self, "configured for {incaps}");
        *lock(&self.refused_caps) = None;
        let fps = info.fps();
        let frame_ns = if fps.numer() > 0 && fps.denom() > 0 {
            (1_000_000_000u128 * fps.denom() as u128 / fps.numer() as u128).min(u64::MAX as u128)
                as u64
        } else {
            0
        };
        self.frame_ns.store(frame_ns, Ordering::Relaxed);
        self.forget_frame_intervals();
        // New caps (a new picture geometry, format or rate): the old reference is not
        // comparable any more, nor what the consumer reported about the old pictures.
        state.gate.drop_reference();
        self.reset_feedback(state);
        state.pre = Some((info, pre));
        Ok(())
    }

    fn query(&self, direction: gst::PadDirection, query: &mut gst::QueryRef) -> bool {
        let unreadable = match query.view() {
            gst::QueryView::AcceptCaps(q) if direction == gst::PadDirection::Sink => {
                crate::preprocess::unreadable_format_error(q.caps())
            }
            _ => None,
        };
        let res = BaseTransformImplExt::parent_query(self, direction, query);
        if let (true, gst::PadDirection::Src, gst::QueryViewMut::Latency(q)) =
            (res, direction, query.view_mut())
        {
            // Frames held for `sharpness-lookback` leave that many frame durations later.
            // Saturating below GST_CLOCK_TIME_NONE (u64::MAX): absurd caps (a frame every 68
            // years) must not panic here.
            let frames = lock(&self.settings).sharpness_lookback as u64;
            let most = gst::ClockTime::MAX.nseconds();
            let frame_ns = match self.frame_ns.load(Ordering::Relaxed) {
                0 => self.vfr_frame_ns.load(Ordering::Relaxed),
                ns => ns,
            };
            let extra = frames.saturating_mul(frame_ns).min(most);
            if extra > 0 {
                let add = |t: gst::ClockTime| {
                    gst::ClockTime::from_nseconds(t.nseconds().saturating_add(extra).min(most))
                };
                let (live, min, max) = q.result();
                q.set(live, add(min), max.map(add));
            }
        }
        let refused = match query.view() {
            gst::QueryView::AcceptCaps(q) => !res || !q.result(),
            _ => false,
        };
        if let (true, Some((msg, details))) = (refused, unreadable) {
            // Upstream will only say `not-negotiated`: name the format and the fix first.
            if !self.first_refusal(&msg) {
                return res;
            }
            gst::element_imp_error!(
                self,
                gst::CoreError::Negotiation,
                ("{}", msg),
                ["{}", details]
            );
        }
        res
    }

    fn sink_event(&self, event: gst::Event) -> bool {
        match event.view() {
            // Frames held for `sharpness-lookback` go before the serialized events that end or
            // change what they belong to (EOS, caps, segment, stream-start, segment-done,
            // stream-group-done) with their fate as it stands; a flush discards them. Every other
            // serialized event (a forced keyframe, a reset, a gap, a tag, a TOC, an application's
            // own) waits in line behind them instead: letting every held frame out at once would
            // hand a synchronised sink frames due up to the whole look-back later (it would block
            // the streaming thread that long), and forget what a later keep could go back to (a
            // parser's bitrate tags changed which frames were kept).
            gst::EventView::FlushStop(_) => self.release_held(false),
            gst::EventView::Eos(_)
            | gst::EventView::Caps(_)
            | gst::EventView::Segment(_)
            | gst::EventView::StreamStart(_)
            | gst::EventView::SegmentDone(_)
            | gst::EventView::StreamGroupDone(_) => self.release_held(true),
            _ if event.is_serialized() => {
                let queued = match lock(&self.held).back_mut() {
                    Some(last) => {
                        last.events_after.push(event.clone());
                        true
                    }
                    None => false,
                };
                if queued {
                    // What it asks of the gate applies from the next frame all the same.
                    self.note_custom_event(&event);
                    return true;
                }
            }
            _ => {}
        }
        match event.view() {
            // Not serialized: the streaming thread may be scoring a frame; interrupt it.
            gst::EventView::FlushStart(_) => self.interrupt(Interrupt::cancel),
            gst::EventView::CustomDownstream(_)
            | gst::EventView::CustomDownstreamOob(_)
            | gst::EventView::CustomBoth(_)
            | gst::EventView::CustomBothOob(_) => {
                self.note_custom_event(&event);
            }
            gst::EventView::FlushStop(_) | gst::EventView::StreamStart(_) => {
                // A new stream (stream-start) may be another scene: its feedback starts afresh.
                // A flush (a seek) stays in the stream and keeps it.
                let new_stream = matches!(event.view(), gst::EventView::StreamStart(_));
                self.interrupt(Interrupt::resume);
                if new_stream {
                    lock(&self.feedback).clear();
                }
                if let Some(state) = lock(&self.state).as_mut() {
                    state.gate.restart();
                    state.last_stats_pts = None;
                    if new_stream {
                        self.reset_feedback(state);
                    }
                }
                self.force_pending.store(false, Ordering::SeqCst);
                self.reset_pending.store(false, Ordering::SeqCst);
            }
            gst::EventView::Eos(_) => {
                self.interrupt(Interrupt::idle);
                let stats = lock(&self.state)
                    .as_mut()
                    .map(|state| self.stats_structure(state));
                if let Some(s) = stats {
                    self.send(Outbox {
                        stats: vec![s],
                        ..Outbox::default()
                    });
                }
            }
            _ => {}
        }
        self.parent_sink_event(event)
    }

    fn src_event(&self, event: gst::Event) -> bool {
        if let gst::EventView::CustomUpstream(_)
        | gst::EventView::CustomBoth(_)
        | gst::EventView::CustomBothOob(_) = event.view()
        {
            self.note_custom_event(&event);
        }
        self.parent_src_event(event)
    }

    fn propose_allocation(
        &self,
        decide_query: Option<&gst::query::Allocation>,
        query: &mut gst::query::Allocation,
    ) -> Result<(), gst::LoggableError> {
        let downstream = self.parent_propose_allocation(decide_query, query);
        // Frames held for `sharpness-lookback` are buffers upstream cannot reuse meanwhile: ask
        // for that many more, so that a decoder with a bounded pool does not stall on them. Also
        // when downstream answered nothing (appsink, fakesink, queue, tee do not): the held
        // frames are ours to account for (a hostile probe stalled a source with a pool of its
        // own minimum + 2 behind the default element and an appsink).
        let held = lock(&self.settings).sharpness_lookback;
        if held == 0 {
            return downstream;
        }
        let pools: Vec<_> = query.allocation_pools().collect();
        if pools.is_empty() {
            let size = query
                .get_owned()
                .0
                .and_then(|caps| gst_video::VideoInfo::from_caps(&caps).ok())
                .map_or(0, |info| info.size() as u32);
            query.add_allocation_pool(None::<&gst::BufferPool>, size, held, 0);
        } else {
            for (i, (pool, size, min, max)) in pools.into_iter().enumerate() {
                let min = min.saturating_add(held);
                let max = if max == 0 { 0 } else { max.max(min) };
                query.set_nth_allocation_pool(i as u32, pool.as_ref(), size, min, max);
            }
        }
        Ok(())
    }

    fn submit_input_buffer(
        &self,
        is_discont: bool,
        inbuf: gst::Buffer,
    ) -> Result<gst::FlowSuccess, gst::FlowError> {
        let fs = self.frame_settings();
        if fs.sharpness_lookback == 0 {
            // Frames held before `sharpness-lookback` went to 0 go first.
            self.release_held(true);
            return self.parent_submit_input_buffer(is_discont, inbuf);
        }
        self.track_variable_framerate(&inbuf);
        // Held frames are pushed here, in order; the base class then has nothing to output.
        let mut out = Outbox::default();
        let verdict = self.gate_frame(&inbuf, &fs, &mut out);
        self.send(out);
        let verdict = match verdict {
            Ok(Some(v)) => v,
            Ok(None) => return Err(gst::FlowError::Flushing),
            Err(e) => {
                gst::element_imp_error!(
                    self,
                    gst::CoreError::Negotiation,
                    ("buffer received before the element started")
                );
                return Err(e);
            }
        };
        let ready: Vec<Held> = {
            let mut held = lock(&self.held);
            held.push_back(Held {
                buf: inbuf,
                meta: verdict.meta.clone(),
                events_after: Vec::new(),
            });
            let n = held.len();
            if verdict.kept_back > 0 {
                mark_kept_back(&mut held, verdict.kept_back, verdict.meta.keyframe_index);
            }
            // A frame leaves when it is `sharpness-lookback` frames old (this one included in
            // the count), when no later keep can go back to it any more: one frame out for one
            // in, even when a keep settles the fate of the frames before it sooner. Letting
            // those out at once would hand a synchronised sink frames due up to the whole
            // look-back later, and it would block the streaming thread (a live source's) that
            // long.
            let leaving = n.saturating_sub(fs.sharpness_lookback as usize);
            held.drain(..leaving).collect()
        };
        self.output_held(ready, fs.mode)
    }

    fn transform_ip(&self, buf: &mut gst::BufferRef) -> Result<gst::FlowSuccess, gst::FlowError> {
        let fs = self.frame_settings();
        let mut out = Outbox::default();
        let verdict = self.gate_frame(buf, &fs, &mut out);
        // The state lock is released: post, then push.
        self.send(out);
        let verdict = match verdict {
            Ok(Some(v)) => v,
            Ok(None) => return Err(gst::FlowError::Flushing),
            Err(e) => {
                gst::element_imp_error!(
                    self,
                    gst::CoreError::Negotiation,
                    ("buffer received before the element started")
                );
                return Err(e);
            }
        };
        if !verdict.keep && fs.mode == GateMode::Drop {
            // Tell time-driven elements downstream (aggregators such as compositor, muxers,
            // live sinks) that nothing comes for this span, instead of letting them wait for it.
            // The span starts at the PTS, else the DTS (as GstBaseSink times a buffer); a buffer
            // with neither has no span to announce.
            if let Some(pts) = buf.pts().or(buf.dts()) {
                let gap = gst::event::Gap::builder(pts)
                    .duration(buf.duration())
                    .build();
                let _ = self.obj().src_pad().push_event(gap);
            }
            return Ok(gst_base::BASE_TRANSFORM_FLOW_DROPPED);
        }
        if let Err(e) = verdict.meta.attach(buf) {
            gst::warning!(CAT, imp = self, "cannot attach LeanGateMeta: {e}");
        }
        Ok(gst::FlowSuccess::Ok)
    }
}
