//! Where frames are scored: locally on ONNX Runtime, or on a V2 server.

use super::{Canceller, RemoteScorer};
use crate::scorer::{IdleHandle, ModelInfo, RunStop, Scorer, ScorerError};
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

    /// The handle a state change or flush uses to stop this backend's stream from another
    /// thread, without the lock the streaming thread scores under.
    pub fn interrupt(&self) -> Interrupt {
        match self {
            Backend::Local(s) => Interrupt {
                batch: s.idle_handle(),
                remote: None,
                local: Some(s.run_stop()),
            },
            Backend::Remote(r) => Interrupt {
                batch: None,
                remote: Some(r.canceller()),
                local: None,
            },
        }
    }

    /// The stream stops for now (EOS): see [`Interrupt::idle`].
    pub fn idle(&self) {
        if let Backend::Local(s) = self {
            s.idle();
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

/// Stops a [`Backend`]'s stream from another thread (see [`Backend::interrupt`]).
#[derive(Debug, Clone, Default)]
pub struct Interrupt {
    batch: Option<IdleHandle>,
    remote: Option<Canceller>,
    local: Option<RunStop>,
}

impl Interrupt {
    /// The stream pauses (PAUSED, EOS): the elements batching with it stop waiting for its
    /// frames until it scores again.
    pub fn idle(&self) {
        if let Some(b) = &self.batch {
            b.idle();
        }
    }

    /// The stream stops or flushes: as [`Interrupt::idle`], and a server request or a local model
    /// run in flight fails at once with [`ScorerError::Interrupted`] (as do the next ones, until
    /// [`Interrupt::resume`]; a local run ends at the model's next operator).
    pub fn cancel(&self) {
        self.idle();
        if let Some(c) = &self.remote {
            c.cancel();
        }
        if let Some(l) = &self.local {
            l.stop();
        }
    }

    /// After a flush: requests may go again.
    pub fn resume(&self) {
        if let Some(c) = &self.remote {
            c.resume();
        }
        if let Some(l) = &self.local {
            l.resume();
        }
    }
}
