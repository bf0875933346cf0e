//! The element's properties: their defaults, the settings they fill, their GObject specs, and how
//! a change is applied (or refused while the element runs). The streaming code is in `imp.rs`.

use super::*;

/// `threshold` value meaning "take it from the model's `leangate.threshold` metadata".
pub(super) const THRESHOLD_FROM_MODEL: f64 = FROM_MODEL;
/// `screen-step` value meaning "take it from the model's `leangate.score_step` metadata".
pub(super) const SCREEN_STEP_FROM_MODEL: f64 = FROM_MODEL;
/// The one negative value of `threshold` and `screen-step`: from the model's metadata.
const FROM_MODEL: f64 = -1.0;
/// Threshold used when the property is [`THRESHOLD_FROM_MODEL`] and the model sets none.
pub(super) const FALLBACK_THRESHOLD: f64 = 0.5;

// Property defaults: each defined once, used by `Settings::default` and the ParamSpecs.
const DEFAULT_THRESHOLD: f64 = THRESHOLD_FROM_MODEL;
const DEFAULT_WARMUP: u32 = 0;
const DEFAULT_MAX_GAP: u32 = 0;
const DEFAULT_SHARPNESS_WAIT: u32 = 0;
const DEFAULT_SHARPNESS_LOOKBACK: u32 = 3;
const DEFAULT_SHARPNESS_MARGIN: f64 = 0.05;
const DEFAULT_MODE: GateMode = GateMode::Drop;
const DEFAULT_EXECUTION_PROVIDER: ExecutionProviderChoice = ExecutionProviderChoice::Auto;
const DEFAULT_PRECISION: PrecisionChoice = PrecisionChoice::Auto;
const DEFAULT_DEVICE_ID: i32 = 0;
const DEFAULT_THREADS: u32 = 0;
const DEFAULT_ORT_SPINNING: bool = false;
const DEFAULT_SHARED_SESSION: bool = true;
const DEFAULT_BATCH_SIZE: u32 = 1;
const DEFAULT_BATCH_TIMEOUT_US: u64 = 2000;
const DEFAULT_MAX_SESSIONS: u32 = 0;
const DEFAULT_STATS_INTERVAL: u64 = 0;
const DEFAULT_GEOMETRY: bool = true;
const DEFAULT_SCREEN: bool = true;
const DEFAULT_SCREEN_STEP: f64 = SCREEN_STEP_FROM_MODEL;
const DEFAULT_REJECT_JUNK: bool = true;
const DEFAULT_FEEDBACK_RATE: f64 = 0.2;
const DEFAULT_FEEDBACK_LOWER: f64 = 0.15;
const DEFAULT_SERVER_TIMEOUT_MS: u32 = 1000;
const DEFAULT_SERVER_MAX_IN_FLIGHT: u32 = 16;

#[derive(Debug, Clone)]
pub(super) struct Settings {
    pub(super) model: Option<String>,
    /// [`THRESHOLD_FROM_MODEL`] (-1): from the model's metadata, else FALLBACK_THRESHOLD;
    /// otherwise in [0, 1].
    pub(super) threshold: f64,
    pub(super) warmup: u32,
    pub(super) max_gap: u32,
    pub(super) sharpness_wait: u32,
    pub(super) sharpness_lookback: u32,
    pub(super) sharpness_margin: f64,
    pub(super) mode: GateMode,
    pub(super) execution_provider: ExecutionProviderChoice,
    pub(super) precision: PrecisionChoice,
    pub(super) device_id: i32,
    pub(super) threads: u32,
    pub(super) ort_spinning: bool,
    pub(super) shared_session: bool,
    pub(super) batch_size: u32,
    pub(super) batch_timeout_us: u64,
    pub(super) max_sessions: u32,
    pub(super) stats_interval: u64,
    pub(super) geometry: bool,
    pub(super) screen: bool,
    /// [`SCREEN_STEP_FROM_MODEL`] (-1): the model's `leangate.score_step`; 0: none; else in
    /// (0, 1].
    pub(super) screen_step: f64,
    pub(super) reject_junk: bool,
    pub(super) feedback_rate: f64,
    /// The most the feedback lowers the utility (0: never; at most [`FEEDBACK_LIMIT`]).
    pub(super) feedback_lower: f64,
    /// Remote scoring (crate::remote): the V2 server's URL; None = local ONNX Runtime.
    pub(super) server: Option<String>,
    pub(super) server_model: Option<String>,
    pub(super) server_timeout_ms: u32,
    pub(super) server_max_in_flight: u32,
    /// Between `start` and `stop`: the model and session settings are in use, and changing them
    /// is refused (the properties keep reporting what is in use).
    pub(super) in_use: bool,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            model: None,
            threshold: DEFAULT_THRESHOLD,
            warmup: DEFAULT_WARMUP,
            max_gap: DEFAULT_MAX_GAP,
            sharpness_wait: DEFAULT_SHARPNESS_WAIT,
            sharpness_lookback: DEFAULT_SHARPNESS_LOOKBACK,
            sharpness_margin: DEFAULT_SHARPNESS_MARGIN,
            mode: DEFAULT_MODE,
            execution_provider: DEFAULT_EXECUTION_PROVIDER,
            precision: DEFAULT_PRECISION,
            device_id: DEFAULT_DEVICE_ID,
            threads: DEFAULT_THREADS,
            ort_spinning: DEFAULT_ORT_SPINNING,
            shared_session: DEFAULT_SHARED_SESSION,
            batch_size: DEFAULT_BATCH_SIZE,
            batch_timeout_us: DEFAULT_BATCH_TIMEOUT_US,
            max_sessions: DEFAULT_MAX_SESSIONS,
            stats_interval: DEFAULT_STATS_INTERVAL,
            geometry: DEFAULT_GEOMETRY,
            screen: DEFAULT_SCREEN,
            screen_step: DEFAULT_SCREEN_STEP,
            reject_junk: DEFAULT_REJECT_JUNK,
            feedback_rate: DEFAULT_FEEDBACK_RATE,
            feedback_lower: DEFAULT_FEEDBACK_LOWER,
            server: None,
            server_model: None,
            server_timeout_ms: DEFAULT_SERVER_TIMEOUT_MS,
            server_max_in_flight: DEFAULT_SERVER_MAX_IN_FLIGHT,
            in_use: false,
        }
    }
}

/// The settings the streaming thread needs for one frame (copied out of the settings lock).
#[derive(Debug, Clone, Copy)]
pub(super) struct FrameSettings {
    pub(super) threshold: f64,
    pub(super) warmup: u32,
    pub(super) max_gap: u32,
    pub(super) sharpness_wait: u32,
    pub(super) sharpness_lookback: u32,
    pub(super) sharpness_margin: f64,
    pub(super) mode: GateMode,
    pub(super) stats_interval: u64,
    pub(super) geometry: bool,
    pub(super) screen: bool,
    pub(super) screen_step: f64,
    pub(super) reject_junk: bool,
    pub(super) feedback_lower: f64,
}

impl From<&Settings> for FrameSettings {
    fn from(s: &Settings) -> Self {
        FrameSettings {
            threshold: s.threshold,
            warmup: s.warmup,
            max_gap: s.max_gap,
            sharpness_wait: s.sharpness_wait,
            sharpness_lookback: s.sharpness_lookback,
            sharpness_margin: s.sharpness_margin,
            mode: s.mode,
            stats_interval: s.stats_interval,
            geometry: s.geometry,
            screen: s.screen,
            screen_step: s.screen_step,
            reject_junk: s.reject_junk,
            feedback_lower: s.feedback_lower,
        }
    }
}

/// A double property whose only negative value is -1 (take it from the model's metadata:
/// `threshold`, `screen-step`): sets `slot`, or says why the value is refused (`slot` unchanged).
fn from_model_or_set(name: &str, value: &glib::Value, slot: &mut f64) -> Option<String> {
    let v: f64 = value.get().expect("type checked upstream");
    if v < 0.0 && v != FROM_MODEL {
        Some(format!(
            "{name} {v} refused: the only negative value is -1 (from the model); it stays {slot}"
        ))
    } else {
        *slot = v;
        None
    }
}

/// A property value for a message or a log, as it is written (`auto`, not glib's Debug form of a
/// GValue): the server URL without its credentials.
pub(super) fn shown(name: &str, value: &glib::Value) -> String {
    match (name, value.get::<Option<String>>()) {
        ("server", Ok(Some(url))) => format!("{:?}", crate::remote::display_url(&url)),
        _ => value
            .serialize()
            .map_or_else(|_| "unset".into(), |v| v.to_string()),
    }
}

/// The GObject specs of every property (documented by `gst-inspect-1.0 leangate`).
pub(super) fn specs() -> Vec<glib::ParamSpec> {
    vec![
        glib::ParamSpecString::builder("model")
            .nick("Model")
            .blurb(
                "Path to a LeanGate model: a pair model (.onnx: inputs `reference`, \
                 `current` [N,3,H,W] float32, output `utility`) or the encoder of a split \
                 model; unset = the embedded default student leangate-s. Its model card: \
                 share/doc/leangate/models/README.md under the install prefix (make \
                 install), models/README.md in the source. Set it before the element starts: a change while it \
                 runs is refused with a warning (the property keeps the model in use)",
            )
            .mutable_ready()
            .build(),
        glib::ParamSpecDouble::builder("threshold")
            .nick("Threshold")
            .blurb(
                "tau_keep in [0, 1]: keep a frame when its predicted utility is >= this. \
                 The only negative value is -1 = the model's leangate.threshold \
                 metadata, else 0.5; other negative values are refused with a warning",
            )
            .minimum(THRESHOLD_FROM_MODEL)
            .maximum(1.0)
            .default_value(DEFAULT_THRESHOLD)
            .mutable_playing()
            .build(),
        glib::ParamSpecUInt::builder("warmup")
            .nick("Warm-up frames")
            .blurb("Always keep the first N frames after the stream (re)starts")
            .default_value(DEFAULT_WARMUP)
            .mutable_playing()
            .build(),
        glib::ParamSpecUInt::builder("max-gap")
            .nick("Maximum gap")
            .blurb("Force a keep after this many consecutive dropped frames (0 = off)")
            .default_value(DEFAULT_MAX_GAP)
            .mutable_playing()
            .build(),
        glib::ParamSpecUInt::builder("sharpness-wait")
            .nick("Wait for a sharper frame")
            .blurb(
                "With sharpness-lookback (3 by default): a keep due on score settles this \
                 many frames later (sooner once the utility is halfway to a late keep) on \
                 the sharpest frame held, before or after the due one. With \
                 sharpness-lookback=0: when a keep is due on a frame blurrier than 0.8 of \
                 the sharpest of the 3 frames before it (variance of the Laplacian of the \
                 model's picture), drop it (reason deferred) and keep the first of the next \
                 frames that is not, or the last of this many; no buffering. 0 = keep at once",
            )
            .maximum(30)
            .default_value(DEFAULT_SHARPNESS_WAIT)
            .mutable_playing()
            .build(),
        glib::ParamSpecUInt::builder("sharpness-lookback")
            .nick("Keep the sharpest of the recent frames")
            .blurb(
                "Hold this many frames; when a keep is due on a frame blurrier than 0.9 \
                 of the sharpest of them that came within 0.1 of the threshold (dropped \
                 since the last keep; variance of the Laplacian of the model's picture), \
                 keep that sharper frame instead (reason sharper) and drop the due one \
                 (with sharpness-wait: once the wait is over). Adds this many frame \
                 durations of latency (reported in the latency query). 0 = hold nothing \
                 (and no sharpness-margin)",
            )
            .maximum(crate::policy::MAX_LOOKBACK as u32)
            .default_value(DEFAULT_SHARPNESS_LOOKBACK)
            .mutable_playing()
            .build(),
        glib::ParamSpecDouble::builder("sharpness-margin")
            .nick("Blurred frames wait within this margin")
            .blurb(
                "With sharpness-lookback: a keep due on a frame blurrier than 0.8 of the \
                 sharpest of the 3 frames before it is not made while its utility is \
                 below threshold + this margin; the frame is dropped (reason deferred) \
                 and held, and the keep goes to the next frame that is sharp enough or \
                 clearly due, or back to a sharper held one. Never past max-gap. \
                 0 = keep at once",
            )
            .minimum(0.0)
            .maximum(1.0)
            .default_value(DEFAULT_SHARPNESS_MARGIN)
            .mutable_playing()
            .build(),
        glib::ParamSpecEnum::builder_with_default("mode", DEFAULT_MODE)
            .nick("Mode")
            .blurb(
                "drop: only kept frames leave; annotate: every frame leaves, tagged \
                 with LeanGateMeta (utility, keep, reason, ...)",
            )
            .mutable_playing()
            .build(),
        glib::ParamSpecEnum::builder_with_default(
            "execution-provider",
            DEFAULT_EXECUTION_PROVIDER,
        )
        .nick("Execution provider")
        .blurb(
            "ONNX Runtime execution provider: auto tries tensorrt, cuda, then cpu; an \
             explicit GPU choice that fails is an error",
        )
        .mutable_ready()
        .build(),
        glib::ParamSpecEnum::builder_with_default("precision", DEFAULT_PRECISION)
            .nick("Precision")
            .blurb(
                "Which build of the embedded student runs: auto = INT8 on the CPU \
                 provider, FP32 on GPU providers and with a server; fp32; int8. A model \
                 file runs as it is",
            )
            .mutable_ready()
            .build(),
        glib::ParamSpecInt::builder("device-id")
            .nick("GPU device id")
            .blurb("CUDA/TensorRT device index")
            .minimum(0)
            .default_value(DEFAULT_DEVICE_ID)
            .mutable_ready()
            .build(),
        glib::ParamSpecUInt::builder("threads")
            .nick("CPU threads")
            .blurb(
                "ONNX Runtime intra-op threads on CPU (0 = the plugin's default: 1, \
                 which leaves the other cores to the decoders)",
            )
            .maximum(crate::scorer::MAX_THREADS as u32)
            .default_value(DEFAULT_THREADS)
            .mutable_ready()
            .build(),
        glib::ParamSpecBoolean::builder("ort-spinning")
            .nick("ONNX Runtime spinning")
            .blurb(
                "Let ONNX Runtime's worker threads spin-wait for work \
                 (session.intra_op/inter_op.allow_spinning); off by default so that \
                 they do not take CPU time from the decoders",
            )
            .default_value(DEFAULT_ORT_SPINNING)
            .mutable_ready()
            .build(),
        glib::ParamSpecBoolean::builder("shared-session")
            .nick("Shared session")
            .blurb(
                "Share the ONNX Runtime session with the other leangate elements of the \
                 process that use the same model, execution provider, device, threads \
                 and spinning (each keeps its own reference)",
            )
            .default_value(DEFAULT_SHARED_SESSION)
            .mutable_ready()
            .build(),
        glib::ParamSpecUInt::builder("batch-size")
            .nick("Batch size")
            .blurb(
                "With shared-session: coalesce up to this many concurrent frames of the \
                 elements sharing the session into one batched encoder run (split \
                 models with a dynamic batch dimension; 1 = off)",
            )
            .minimum(1)
            .maximum(256)
            .default_value(DEFAULT_BATCH_SIZE)
            .mutable_ready()
            .build(),
        glib::ParamSpecUInt64::builder("batch-timeout")
            .nick("Batch timeout")
            .blurb(
                "Longest time (µs) a frame waits for others to fill a batch; no wait \
                 when a single element batches on the session",
            )
            .maximum(1_000_000)
            .default_value(DEFAULT_BATCH_TIMEOUT_US)
            .mutable_ready()
            .build(),
        glib::ParamSpecUInt::builder("max-sessions")
            .nick("Maximum sessions")
            .blurb(
                "With shared-session: at most this many ONNX Runtime sessions of the model in the \
                 process; a new element gets its own while there are fewer and otherwise joins the least \
                 used (a session scores one frame at a time). 0 = one per `threads` CPU cores on the CPU \
                 provider, 1 on GPU providers",
            )
            .maximum(1024)
            .default_value(DEFAULT_MAX_SESSIONS)
            .mutable_ready()
            .build(),
        glib::ParamSpecUInt64::builder("stats-interval")
            .nick("Statistics interval")
            .blurb(
                "Post a `leangate-stats` element message every this many nanoseconds of \
                 stream time (0 = only at EOS)",
            )
            .default_value(DEFAULT_STATS_INTERVAL)
            .mutable_playing()
            .build(),
        glib::ParamSpecBoolean::builder("geometry")
            .nick("Geometric prior")
            .blurb(
                "Combine the model's utility with the geometric prior (frame-to-frame \
                 homographies chained from the reference, scored like the teacher) as \
                 the model's leangate.geometry metadata says (training/fuse.py fits and \
                 writes it; the embedded leangate-s carries it, so this is the default \
                 gate). Off, or a model without it: the model's utility alone",
            )
            .default_value(DEFAULT_GEOMETRY)
            .mutable_playing()
            .build(),
        glib::ParamSpecBoolean::builder("screen")
            .nick("Screen by the prior")
            .blurb(
                "With the geometric prior in use: skip the model on a frame when no score \
                 it could give (up to its leangate.score_max, else 1) would lift the fused \
                 utility to the threshold (a small \
                 motion since the reference). The decisions are the same wherever the \
                 model scores (a frame it would have failed on, kept by fail open, is \
                 dropped: it is not asked); such a frame reports that bound as \
                 its utility and screened=true in its meta, and is counted in \
                 frames-screened. Off: the model scores every frame",
            )
            .default_value(DEFAULT_SCREEN)
            .mutable_playing()
            .build(),
        glib::ParamSpecDouble::builder("screen-step")
            .nick("Screening step")
            .blurb(
                "With screen: k frames after one the model scored against the same \
                 reference, also skip the model when that score plus k times this step could \
                 not lift the fused utility to the threshold. A \
                 rule, not a bound: where the score rises more than the step on a frame \
                 whose utility reaches the threshold, that frame is dropped and the keep \
                 goes to the next frame that reaches it. \
                 -1 = the model's leangate.score_step metadata (0.15 for the embedded \
                 student), none if it has none; 0 = off (screening only by what no score \
                 could change: the decisions of the model scoring every frame); other \
                 negative values are refused with a warning",
            )
            .minimum(SCREEN_STEP_FROM_MODEL)
            .maximum(1.0)
            .default_value(DEFAULT_SCREEN_STEP)
            .mutable_playing()
            .build(),
        glib::ParamSpecBoolean::builder("reject-junk")
            .nick("Reject junk frames")
            .blurb(
                "Never keep a frame that carries no usable picture: dark (a lens cap, a \
                 dropped exposure), saturated (a flash) or noise; it is dropped unscored \
                 with reason junk and quality dark/saturated/noise in its meta, never \
                 becomes the reference (the prior's chain bridges it), and is counted in \
                 frames-junk; a forced keyframe or max-gap waits for the next usable \
                 frame. A textureless view (a blank wall) gets utility 0: kept only as a \
                 stream's first frame. Off: every frame is scored",
            )
            .default_value(DEFAULT_REJECT_JUNK)
            .mutable_playing()
            .build(),
        glib::ParamSpecDouble::builder("feedback-rate")
            .nick("Feedback rate")
            .blurb(
                "How far each leangate-feedback event moves the utility: a consumer \
                 (e.g. the SLAM behind the gate) that reports tau = 1 - S it measured \
                 between a kept frame and the previous keyframe moves a sum by \
                 rate * (tau - threshold) (the error within +-0.25, the sum within +-0.3; \
                 a stream's first reports count more, report n at least 0.7 / (1 + n)): \
                 up when that keep came late, down when early; the utility is raised by \
                 the sum's positive part (feedback-offset) and lowered, at most by \
                 feedback-lower, by what lies below -0.05. 0 ignores feedback. Without \
                 feedback events nothing changes",
            )
            .minimum(0.0)
            .maximum(1.0)
            .default_value(DEFAULT_FEEDBACK_RATE)
            .mutable_playing()
            .build(),
        glib::ParamSpecString::builder("server")
            .nick("Inference server")
            .blurb(
                "Score on a KServe V2 / Open Inference Protocol server (Triton, KServe, \
                 MLServer) at http://host:port or https://host:port instead of locally; \
                 unset = local ONNX Runtime. user:password@ in the URL is sent as HTTP \
                 basic authentication and never shown. The local model still fixes the \
                 preprocessing and the contract; a split model's head runs locally. \
                 Set it before the element starts",
            )
            .mutable_ready()
            .build(),
        glib::ParamSpecString::builder("server-model")
            .nick("Model on the server")
            .blurb(
                "The model's name on the server; unset = the local model's name for a \
                 pair model, <name>-encoder for a split model (its encoder runs on the \
                 server)",
            )
            .mutable_ready()
            .build(),
        glib::ParamSpecUInt::builder("server-timeout")
            .nick("Server timeout")
            .blurb(
                "Timeout of each request to the server, milliseconds; a frame whose \
                 request fails or times out is kept (fail open)",
            )
            .minimum(1)
            .default_value(DEFAULT_SERVER_TIMEOUT_MS)
            .mutable_ready()
            .build(),
        glib::ParamSpecUInt::builder("server-max-in-flight")
            .nick("Server requests in flight")
            .blurb(
                "Most requests in flight to the server from this process, all elements \
                 together (0 = no bound from this element). One server however its URL \
                 is spelled (scheme, host in any case or loopback alias, port, prefix); \
                 when elements disagree, the smallest bound among those running applies \
                 to all. A frame that waits longer than server-timeout for a slot is \
                 kept (fail open)",
            )
            .default_value(DEFAULT_SERVER_MAX_IN_FLIGHT)
            .mutable_ready()
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
        glib::ParamSpecDouble::builder("feedback-lower")
            .nick("Feedback lower")
            .blurb(
                "The most the consumer's leangate-feedback lowers the utility: once the \
                 feedback sum (see feedback-rate) is below -0.05, the utility is lowered by \
                 what lies beyond, up to this. 0: never lowered (only raised). \
                 max-gap and the first frame keep as ever, so a consumer that reports early \
                 keeps without end cannot stop the gate keeping",
            )
            .minimum(0.0)
            .maximum(FEEDBACK_LIMIT)
            .default_value(DEFAULT_FEEDBACK_LOWER)
            .mutable_playing()
            .build(),
        glib::ParamSpecDouble::builder("feedback-offset")
            .nick("Feedback offset")
            .blurb(
                "What the consumer's leangate-feedback events add to every frame's \
                 utility now (-feedback-lower to 0.3; 0 without feedback; back to 0 at \
                 start, at a new stream and when the caps change; read-only; see \
                 feedback-rate)",
            )
            .minimum(-FEEDBACK_LIMIT)
            .maximum(FEEDBACK_LIMIT)
            .default_value(0.0)
            .read_only()
            .build(),
        glib::ParamSpecUInt64::builder("frames-screened")
            .nick("Frames screened")
            .blurb(
                "Frames the model did not run on since start because the geometric \
                 prior alone bounded their utility below the threshold (dropped unless \
                 warmup, max-gap or a forced keyframe kept them; read-only; see screen)",
            )
            .read_only()
            .build(),
        glib::ParamSpecUInt64::builder("frames-junk")
            .nick("Frames of junk")
            .blurb(
                "Frames dropped since start because they carry no usable picture (dark, \
                 saturated, noise; read-only; see reject-junk)",
            )
            .read_only()
            .build(),
    ]
}

impl LeanGate {
    /// Apply a property change, or refuse it with a warning (the settings lock is released
    /// before anything is posted).
    pub(super) fn set_property_value(&self, value: &glib::Value, pspec: &glib::ParamSpec) {
        let name = pspec.name();
        let refused = {
            let mut settings = lock(&self.settings);
            match name {
                "model"
                | "execution-provider"
                | "precision"
                | "device-id"
                | "threads"
                | "ort-spinning"
                | "shared-session"
                | "batch-size"
                | "batch-timeout"
                | "max-sessions"
                | "server"
                | "server-model"
                | "server-timeout"
                | "server-max-in-flight"
                    if settings.in_use =>
                {
                    Some(format!(
                        "`{name}` cannot change while the element runs (set it in the NULL or \
                         READY state); it stays {}",
                        shown(name, &self.property_value(&settings, name))
                    ))
                }
                "model" => {
                    settings.model = value.get().expect("type checked upstream");
                    None
                }
                "threshold" => from_model_or_set(name, value, &mut settings.threshold),
                "warmup" => {
                    settings.warmup = value.get().expect("type checked upstream");
                    None
                }
                "max-gap" => {
                    settings.max_gap = value.get().expect("type checked upstream");
                    None
                }
                "sharpness-wait" => {
                    settings.sharpness_wait = value.get().expect("type checked upstream");
                    None
                }
                "sharpness-lookback" => {
                    settings.sharpness_lookback = value.get().expect("type checked upstream");
                    None
                }
                "sharpness-margin" => {
                    settings.sharpness_margin = value.get().expect("type checked upstream");
                    None
                }
                "mode" => {
                    settings.mode = value.get().expect("type checked upstream");
                    None
                }
                "execution-provider" => {
                    settings.execution_provider = value.get().expect("type checked upstream");
                    None
                }
                "precision" => {
                    settings.precision = value.get().expect("type checked upstream");
                    None
                }
                "device-id" => {
                    settings.device_id = value.get().expect("type checked upstream");
                    None
                }
                "threads" => {
                    settings.threads = value.get().expect("type checked upstream");
                    None
                }
                "ort-spinning" => {
                    settings.ort_spinning = value.get().expect("type checked upstream");
                    None
                }
                "shared-session" => {
                    settings.shared_session = value.get().expect("type checked upstream");
                    None
                }
                "batch-size" => {
                    settings.batch_size = value.get().expect("type checked upstream");
                    None
                }
                "batch-timeout" => {
                    settings.batch_timeout_us = value.get().expect("type checked upstream");
                    None
                }
                "max-sessions" => {
                    settings.max_sessions = value.get().expect("type checked upstream");
                    None
                }
                "stats-interval" => {
                    settings.stats_interval = value.get().expect("type checked upstream");
                    None
                }
                "geometry" => {
                    settings.geometry = value.get().expect("type checked upstream");
                    None
                }
                "screen" => {
                    settings.screen = value.get().expect("type checked upstream");
                    None
                }
                "screen-step" => from_model_or_set(name, value, &mut settings.screen_step),
                "reject-junk" => {
                    settings.reject_junk = value.get().expect("type checked upstream");
                    None
                }
                "feedback-rate" => {
                    settings.feedback_rate = value.get().expect("type checked upstream");
                    None
                }
                "feedback-lower" => {
                    settings.feedback_lower = value.get().expect("type checked upstream");
                    None
                }
                "server" => {
                    settings.server = value.get().expect("type checked upstream");
                    None
                }
                "server-model" => {
                    settings.server_model = value.get().expect("type checked upstream");
                    None
                }
                "server-timeout" => {
                    settings.server_timeout_ms = value.get().expect("type checked upstream");
                    None
                }
                "server-max-in-flight" => {
                    settings.server_max_in_flight = value.get().expect("type checked upstream");
                    None
                }
                other => unreachable!("unknown property {other}"),
            }
        };
        // Gate parameters apply from the next frame (the streaming thread reads the settings
        // once per frame): no other lock is taken here, and the warning is posted unlocked.
        let latency_changed = name == "sharpness-lookback" && refused.is_none();
        match refused {
            Some(why) => {
                gst::warning!(CAT, imp = self, "{why}");
                let obj = self.obj();
                let msg = gst::message::Warning::builder(gst::CoreError::StateChange, &why)
                    .src(&*obj)
                    .build();
                if obj.post_message(msg).is_err() {
                    // No bus yet (gst-launch sets properties before it builds the pipeline):
                    // the warning goes out when the element starts.
                    lock(&self.unposted).push(why);
                }
            }
            None => gst::debug!(CAT, imp = self, "{name} set to {}", shown(name, value)),
        }
        if latency_changed {
            // The element's latency changed: let the pipeline query it again.
            let obj = self.obj();
            let _ = obj.post_message(gst::message::Latency::builder().src(&*obj).build());
            // It holds another number of upstream's buffers: let upstream allocate again (the
            // allocation query asks for that many more), lest a bounded pool (a camera's, a
            // hardware decoder's) run dry on the frames held.
            let _ = obj.sink_pad().push_event(gst::event::Reconfigure::new());
        }
    }

    pub(super) fn property_value(&self, settings: &Settings, name: &str) -> glib::Value {
        match name {
            "model" => settings.model.to_value(),
            "threshold" => settings.threshold.to_value(),
            "warmup" => settings.warmup.to_value(),
            "max-gap" => settings.max_gap.to_value(),
            "sharpness-wait" => settings.sharpness_wait.to_value(),
            "sharpness-lookback" => settings.sharpness_lookback.to_value(),
            "sharpness-margin" => settings.sharpness_margin.to_value(),
            "mode" => settings.mode.to_value(),
            "execution-provider" => settings.execution_provider.to_value(),
            "precision" => settings.precision.to_value(),
            "device-id" => settings.device_id.to_value(),
            "threads" => settings.threads.to_value(),
            "ort-spinning" => settings.ort_spinning.to_value(),
            "shared-session" => settings.shared_session.to_value(),
            "batch-size" => settings.batch_size.to_value(),
            "batch-timeout" => settings.batch_timeout_us.to_value(),
            "max-sessions" => settings.max_sessions.to_value(),
            "stats-interval" => settings.stats_interval.to_value(),
            "geometry" => settings.geometry.to_value(),
            "screen" => settings.screen.to_value(),
            "screen-step" => settings.screen_step.to_value(),
            "reject-junk" => settings.reject_junk.to_value(),
            "feedback-rate" => settings.feedback_rate.to_value(),
            "feedback-lower" => settings.feedback_lower.to_value(),
            "feedback-offset" => {
                f64::from_bits(self.feedback_offset.load(Ordering::Relaxed)).to_value()
            }
            "server" => settings.server.to_value(),
            "server-model" => settings.server_model.to_value(),
            "server-timeout" => settings.server_timeout_ms.to_value(),
            "server-max-in-flight" => settings.server_max_in_flight.to_value(),
            "frames-in" => self.frames_in.load(Ordering::Relaxed).to_value(),
            "frames-kept" => self.frames_kept.load(Ordering::Relaxed).to_value(),
            "frames-screened" => self.frames_screened.load(Ordering::Relaxed).to_value(),
            "frames-junk" => self.frames_junk.load(Ordering::Relaxed).to_value(),
            other => unreachable!("unknown property {other}"),
        }
    }
}
