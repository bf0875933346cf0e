//! The default student, `leangate-s`, compiled into the plugin: the element uses it when its
//! `model` property is unset, and `leangate eval` when no `--model` is given.
//!
//! It is embedded in its split form (encoder + head; see `models/README.md`), so the element
//! encodes each frame once and keeps the reference keyframe's features until the next keep.

use crate::scorer::ModelSource;

/// Name of the embedded model.
pub const NAME: &str = "leangate-s";

/// The encoder (`image` → `features`).
pub static ENCODER: &[u8] = include_bytes!("../models/leangate-s-encoder.onnx");
/// The head (`reference_features`, `current_features` → `utility`).
pub static HEAD: &[u8] = include_bytes!("../models/leangate-s-head.onnx");

/// The embedded model as a scorer source.
pub fn source() -> ModelSource {
    ModelSource::Memory {
        name: NAME.to_string(),
        bytes: ENCODER,
        head: Some(HEAD),
    }
}
