//! The default student, `leangate-s`, compiled into the plugin: the element uses it when its
//! `model` property is unset, and `leangate eval` when no `--model` is given.
//!
//! It is embedded in its split form (encoder + head; see `models/README.md`), so the element
//! encodes each frame once and keeps the reference keyframe's features until the next keep,
//! in two builds: FP32, and INT8 for the CPU (`precision`).

use crate::scorer::ModelSource;

/// Name of the embedded model.
pub const NAME: &str = "leangate-s";

/// The encoder (`image` → `features`).
pub static ENCODER: &[u8] = include_bytes!("../models/leangate-s-encoder.onnx");
/// The head (`reference_features`, `current_features` → `utility`).
pub static HEAD: &[u8] = include_bytes!("../models/leangate-s-head.onnx");

/// The INT8 build of the same student (`training/quantize.py`): its convolutions in 8-bit
/// integers, run on the CPU by default (`precision`).
pub static INT8_ENCODER: &[u8] = include_bytes!("../models/leangate-s-int8-encoder.onnx");
/// The INT8 build's head.
pub static INT8_HEAD: &[u8] = include_bytes!("../models/leangate-s-int8-head.onnx");

/// The embedded model as a scorer source.
pub fn source() -> ModelSource {
    ModelSource::Memory {
        name: NAME.to_string(),
        bytes: ENCODER,
        head: Some(HEAD),
        int8: Some((INT8_ENCODER, INT8_HEAD)),
    }
}
