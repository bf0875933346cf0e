//! Where frames are scored: locally on ONNX Runtime, or on a V2 server.

use super::RemoteScorer;
use crate::scorer::{ModelInfo, Scorer, ScorerError};
use crate::stats::ServerStats;

/// The element's scorer: the same calls whichever runs the model.
/// One per element, built at start and never moved per frame: the size gap between the
/// variants costs nothing, and boxing the local scorer would touch every local call.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum Backend {
    /// ONNX Runtime in the element (the `server` property unset).
    Local(Scorer),
    /// A KServe V2 server (see [`crate::remote`]).
    Remote(Box<RemoteScorer>),
}

impl Backend {
    pub fn score(&mut self, reference: &[f32], current: &[f32]) -> Result<f32, ScorerError> {
        match self {
            Backend::Local(s) => s.score(reference, current),
            Backend::Remote(r) => r.score(reference, current),
        }
    }

    pub fn on_keep(&mut self, scored: bool) {
        match self {
            Backend::Local(s) => s.on_keep(scored),
            Backend::Remote(r) => r.on_keep(scored),
        }
    }

    pub fn reset_reference(&mut self) {
        match self {
            Backend::Local(s) => s.reset_reference(),
            Backend::Remote(r) => r.reset_reference(),
        }
    }

    pub fn info(&self) -> &ModelInfo {
        match self {
            Backend::Local(s) => s.info(),
            Backend::Remote(r) => r.info(),
        }
    }

    /// The execution provider (`cpu`, `cuda`, `tensorrt`), or `remote`.
    pub fn provider(&self) -> &'static str {
        match self {
            Backend::Local(s) => s.provider(),
            Backend::Remote(_) => "remote",
        }
    }

    /// The server's figures for `leangate-stats` (None when local).
    pub fn server_stats(&self) -> Option<ServerStats> {
        match self {
            Backend::Local(_) => None,
            Backend::Remote(r) => Some(r.stats()),
        }
    }
}
