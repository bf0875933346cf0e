//! LeanGate: geometric-utility frame gating for monocular SLAM, as a GStreamer plugin.
//!
//! The element `leangate` scores each frame against the last kept frame (the reference) with a small
//! ONNX "student" that predicts MASt3R-SLAM's keyframe utility `tau = 1 - min(f_m, f_u)`, and drops
//! frames whose utility is below the threshold. Everything but the GStreamer glue is plain Rust,
//! and this crate's public API is what the element is made of, so that the tools (`leangate eval`
//! in the `leangate-tools` crate), the benchmarks and the tests use the very same code:
//!
//! - the gate: [`Gate`], [`GateConfig`], [`Decision`], [`Reason`], [`Score`];
//! - the scorer (ONNX Runtime): [`Scorer`], [`ScorerOptions`], [`ModelSource`], [`ModelInfo`],
//!   [`ExecutionProvider`], [`ScorerError`], and the embedded default model [`default_model`];
//! - preprocessing (frame → tensor): [`Preprocessor`], [`RawFrame`], [`PixelFormat`],
//!   [`ResizeMode`], [`TensorSpec`], [`YuvMatrix`], [`PreprocessError`];
//! - what leaves the element: [`GateMeta`] (`LeanGateMeta` on every buffer), [`StatsMessage`]
//!   (the `leangate-stats` bus message), the custom event names;
//! - remote scoring on a KServe V2 server: [`RemoteScorer`], [`RemoteOptions`], [`Backend`]
//!   (module [`remote`], its HTTP client in [`remote::client`]);
//! - the geometric prior (chained homographies → the teacher's overlap): module [`geometry`];
//! - the pair overlap itself from depth and a relative pose (`S = min(f_m, f_u)`, the teacher's
//!   one implementation): module [`overlap`];
//! - with depth beside the colour (RGB-D), the pose from tracked corners and that overlap with
//!   it: module [`metric`]; the depth a colour buffer carries (`LeanGateDepthMeta`): [`depth`];
//! - what a frame's utility is made of (the model's score fused with the prior): [`Utility`];
//! - whether a frame carries a usable picture (junk never becomes a keyframe): module [`quality`];
//! - the element type [`LeanGate`] and its property enums.

use gst::glib;

mod default_model;
pub mod depth;
mod depthmux;
pub mod geometry;
mod leangate;
mod meta;
pub mod metric;
pub mod overlap;
mod policy;
mod preprocess;
pub mod quality;
pub mod remote;
mod runtime;
mod scorer;
mod stats;
mod utility;

pub use default_model::{source as default_model, NAME as DEFAULT_MODEL_NAME};
pub use leangate::{
    ExecutionProviderChoice, GateMode, LeanGate, PrecisionChoice, FEEDBACK_EVENT,
    FORCE_KEYFRAME_EVENT, RESET_EVENT,
};
pub use meta::{GateMeta, META_NAME};
pub use policy::{Decision, Gate, GateConfig, Reason, Score, KEYFRAME_S};
pub use preprocess::{
    PixelFormat, PreprocessError, Preprocessor, RawFrame, ResizeMode, TensorSpec, YuvMatrix,
};
pub use quality::Quality;
pub use remote::{Backend, Interrupt, RemoteError, RemoteOptions, RemoteScorer};
pub use runtime::RuntimeError;
pub use scorer::{
    default_max_sessions, files_read, ExecutionProvider, IdleHandle, ModelInfo, ModelSource,
    Precision, RunStop, Scorer, ScorerError, ScorerOptions, MAX_INPUT_SIDE, MAX_TENSOR_BYTES,
};
pub use stats::{ServerStats, StatsMessage, StatsParseError, STATS_MESSAGE};
pub use utility::{Composed, DepthUse, Utility};

fn plugin_init(plugin: &gst::Plugin) -> Result<(), glib::BoolError> {
    meta::register();
    depth::register();
    depthmux::register(plugin)?;
    leangate::register(plugin)
}

gst::plugin_define!(
    leangate,
    env!("CARGO_PKG_DESCRIPTION"),
    plugin_init,
    concat!(env!("CARGO_PKG_VERSION"), "-", env!("COMMIT_ID")),
    "MIT/X11",
    env!("CARGO_PKG_NAME"),
    env!("CARGO_PKG_NAME"),
    env!("CARGO_PKG_REPOSITORY"),
    env!("BUILD_REL_DATE")
);
