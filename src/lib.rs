//! LeanGate: geometric-utility frame gating for monocular SLAM, as a GStreamer plugin.
//!
//! The element `leangate` scores each frame against the last kept frame (the reference) with a small
//! ONNX "student" that predicts MASt3R-SLAM's keyframe utility `tau = 1 - min(f_m, f_u)`, and drops
//! frames whose utility is below the threshold. Everything but the glue is plain Rust:
//! [`policy`] (the gate), [`scorer`] (ONNX Runtime), [`preprocess`] (frame → tensor), [`meta`]
//! (`LeanGateMeta`), [`runtime`] (finding libonnxruntime), [`stats`]; and for the tools:
//! [`dataset`] (TUM-layout sequences), [`teacher`] (the exact geometric score), [`synth`]
//! (procedural RGB-D scenes).

use gst::glib;

pub mod dataset;
pub mod default_model;
pub mod eval;
pub mod leangate;
pub mod meta;
pub mod policy;
pub mod preprocess;
pub mod runtime;
pub mod scorer;
pub mod stats;
pub mod synth;
pub mod teacher;

fn plugin_init(plugin: &gst::Plugin) -> Result<(), glib::BoolError> {
    meta::register();
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
