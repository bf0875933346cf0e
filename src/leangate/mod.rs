//! The `leangate` element: thin GStreamer glue over [`crate::policy`], [`crate::scorer`],
//! [`crate::preprocess`] and [`crate::meta`].

use gst::glib;
use gst::prelude::*;

mod imp;

/// `mode` property: what happens to frames the gate rejects.
#[derive(Debug, Eq, PartialEq, Ord, PartialOrd, Hash, Clone, Copy, glib::Enum, Default)]
#[repr(u32)]
#[enum_type(name = "GstLeanGateMode")]
pub enum GateMode {
    #[default]
    #[enum_value(
        name = "Drop: only frames that add geometry leave the element",
        nick = "drop"
    )]
    Drop = 0,
    #[enum_value(
        name = "Annotate: every frame leaves, tagged with its score and decision",
        nick = "annotate"
    )]
    Annotate = 1,
}

/// `execution-provider` property.
#[derive(Debug, Eq, PartialEq, Ord, PartialOrd, Hash, Clone, Copy, glib::Enum, Default)]
#[repr(u32)]
#[enum_type(name = "GstLeanGateExecutionProvider")]
pub enum ExecutionProviderChoice {
    #[default]
    #[enum_value(
        name = "Auto: TensorRT, then CUDA, then CPU (each failure logged as a warning)",
        nick = "auto"
    )]
    Auto = 0,
    #[enum_value(name = "CPU", nick = "cpu")]
    Cpu = 1,
    #[enum_value(name = "CUDA (an error if unavailable)", nick = "cuda")]
    Cuda = 2,
    #[enum_value(name = "TensorRT (an error if unavailable)", nick = "tensorrt")]
    TensorRt = 3,
}

impl From<ExecutionProviderChoice> for crate::scorer::ExecutionProvider {
    fn from(c: ExecutionProviderChoice) -> Self {
        use crate::scorer::ExecutionProvider as E;
        match c {
            ExecutionProviderChoice::Auto => E::Auto,
            ExecutionProviderChoice::Cpu => E::Cpu,
            ExecutionProviderChoice::Cuda => E::Cuda,
            ExecutionProviderChoice::TensorRt => E::TensorRt,
        }
    }
}

/// `precision` property: which build of the embedded student runs.
#[derive(Debug, Eq, PartialEq, Ord, PartialOrd, Hash, Clone, Copy, glib::Enum, Default)]
#[repr(u32)]
#[enum_type(name = "GstLeanGatePrecision")]
pub enum PrecisionChoice {
    #[default]
    #[enum_value(
        name = "Auto: the INT8 build on the CPU, FP32 on GPUs and with a server",
        nick = "auto"
    )]
    Auto = 0,
    #[enum_value(name = "FP32", nick = "fp32")]
    Fp32 = 1,
    #[enum_value(name = "INT8 (convolutions in 8-bit integers)", nick = "int8")]
    Int8 = 2,
}

impl From<PrecisionChoice> for crate::scorer::Precision {
    fn from(c: PrecisionChoice) -> Self {
        use crate::scorer::Precision as P;
        match c {
            PrecisionChoice::Auto => P::Auto,
            PrecisionChoice::Fp32 => P::Fp32,
            PrecisionChoice::Int8 => P::Int8,
        }
    }
}

glib::wrapper! {
    pub struct LeanGate(ObjectSubclass<imp::LeanGate>) @extends gst_base::BaseTransform, gst::Element, gst::Object;
}

/// Name of the custom event (upstream or downstream) that keeps the next frame.
pub const FORCE_KEYFRAME_EVENT: &str = "leangate-force-keyframe";
/// Name of the custom event (upstream or downstream) that drops the reference.
pub const RESET_EVENT: &str = "leangate-reset";
/// Name of the custom event (upstream, from the consumer) that reports `tau` (a double, 1 − S)
/// measured between a kept frame and the keyframe before it: the element corrects its utility
/// by it (`feedback-rate`, `feedback-offset`).
pub const FEEDBACK_EVENT: &str = "leangate-feedback";

pub fn register(plugin: &gst::Plugin) -> Result<(), glib::BoolError> {
    GateMode::static_type().mark_as_plugin_api(gst::PluginAPIFlags::empty());
    ExecutionProviderChoice::static_type().mark_as_plugin_api(gst::PluginAPIFlags::empty());
    PrecisionChoice::static_type().mark_as_plugin_api(gst::PluginAPIFlags::empty());
    gst::Element::register(
        Some(plugin),
        "leangate",
        gst::Rank::NONE,
        LeanGate::static_type(),
    )
}
