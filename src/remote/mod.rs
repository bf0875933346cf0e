//! Remote scoring: the model runs on a shared inference server that speaks the KServe V2 / Open
//! Inference Protocol over HTTP(S) (NVIDIA Triton, KServe, Seldon MLServer), with the binary
//! tensor extension.
//!
//! The element still loads the model locally (the `model` property, or the embedded default):
//! its `leangate.*` metadata fixes the preprocessing and the threshold, its graph is the contract
//! the server's model metadata must match, and for a **split** model its small head runs here.
//!
//! - **Pair model**: one request per scored frame to `server-model` (default: the model's name)
//!   with `reference` and `current`; the server answers `utility`.
//! - **Split model**: the encoder runs on the server (`server-model`, default `<name>-encoder`),
//!   the reference keyframe's features are cached in the element until the next keep, and the
//!   head runs locally on ONNX Runtime. A scored frame costs **one** encoder request (plus one
//!   for the reference after a start, reset, flush or failure, when its features are unknown).
//!
//! Faults: every request has a timeout; a failed request fails open (the element keeps the frame
//! and posts a rate-limited warning naming the server and the error), and further requests wait
//! for an exponential backoff (100 ms doubling to 2 s) so that frames keep flowing without each
//! one waiting for a timeout while the server is away; the first request that succeeds resets it.
//! Requests in flight to one server are bounded process-wide (`server-max-in-flight`): one bound
//! per server however its URL is spelled ([`url::ServerUrl::server_key`]), the smallest bound of
//! the elements using it. Stopping or flushing the element interrupts a request in flight
//! ([`Canceller`]) instead of waiting for its timeout.
//!
//! A server URL is shown (errors, warnings, logs, stats) by [`display_url`] only: any
//! credentials in it are sent as HTTP basic authentication and never shown.

use std::collections::HashMap;
use std::sync::{Arc, Condvar, LazyLock, Mutex, Weak};
use std::time::{Duration, Instant};

use crate::scorer::{ModelInfo, Scorer, ScorerError};
use crate::stats::{Histogram, ServerStats};

mod backend;
pub mod client;
pub mod url;

pub use backend::{Backend, Interrupt};
pub use client::Canceller;
use client::{ClientError, InputTensor, ModelMetadata, TensorMeta, V2Client};
pub use url::{display_url, ServerUrl};

static CAT: LazyLock<gst::DebugCategory> = LazyLock::new(|| {
    gst::DebugCategory::new(
        "leangate-remote",
        gst::DebugColorFlags::empty(),
        Some("LeanGate remote scoring (KServe V2)"),
    )
});

/// First retry delay after a failed request; it doubles up to [`BACKOFF_MAX`].
pub const BACKOFF_MIN: Duration = Duration::from_millis(100);
/// Longest delay between two attempts while the server is away.
pub const BACKOFF_MAX: Duration = Duration::from_secs(2);

/// Where and how to reach the server.
#[derive(Debug, Clone)]
pub struct RemoteOptions {
    /// `http://host:port` or `https://host:port` (a path prefix and `user:password@` are
    /// allowed; see [`ServerUrl`]).
    pub url: String,
    /// The model's name on the server; `None`: derived from the local model (see the module
    /// documentation).
    pub model: Option<String>,
    /// Timeout of each request (and of the start checks).
    pub timeout: Duration,
    /// Most requests in flight to this server from this process (0 = no bound from this
    /// element; the smallest bound of the elements using one server applies to all of them).
    pub max_in_flight: u32,
}

/// A start failure, naming the server and what failed.
#[derive(Debug, Clone, thiserror::Error)]
pub enum RemoteError {
    #[error("server `{url}`: invalid URL: {reason}")]
    Url { url: String, reason: String },
    #[error("server `{url}` is unreachable: {reason}")]
    Unreachable { url: String, reason: String },
    /// Connected, but no whole answer in time (an `https://` URL on a plain-HTTP port waits so).
    #[error(
        "server `{url}` did not answer the {what} request within {ms} ms (server-timeout){hint}"
    )]
    NoAnswer {
        url: String,
        what: String,
        ms: u128,
        hint: String,
    },
    /// 401 or 403: the server refused the credentials (or their absence).
    #[error(
        "server `{url}` refused access ({reason}): check the user name and password or token in \
         the URL (`http://user:password@host:port`)"
    )]
    Refused { url: String, reason: String },
    /// The server answered, but not with what was asked for.
    #[error("server `{url}` answered the {what} request for `{model}` with {reason}")]
    Answered {
        url: String,
        what: String,
        model: String,
        reason: String,
    },
    #[error("server `{url}` has no model `{model}` ({reason})")]
    UnknownModel {
        url: String,
        model: String,
        reason: String,
    },
    #[error("model `{model}` on server `{url}` is not ready")]
    NotReady { url: String, model: String },
    #[error(
        "model `{model}` on server `{url}` does not follow the tensor contract: {reason} \
         (its metadata: {metadata})"
    )]
    Contract {
        url: String,
        model: String,
        reason: String,
        metadata: String,
    },
    #[error("model `{model}` on server `{url}` failed a dry run on a blank frame: {reason}")]
    DryRun {
        url: String,
        model: String,
        reason: String,
    },
    /// The local model (metadata, head) could not be loaded.
    #[error(transparent)]
    Local(#[from] ScorerError),
}

impl RemoteError {
    /// An error about the local model rather than the server.
    pub fn local(&self) -> Option<&ScorerError> {
        match self {
            RemoteError::Local(e) => Some(e),
            _ => None,
        }
    }
}

/// A process-wide bound on requests in flight to one server (one per [`ServerUrl::server_key`]).
/// Each element using it registers its bound; the smallest non-zero one applies to every
/// request (0 = no bound from that element). It goes from the registry with its last user.
#[derive(Debug)]
struct Limiter {
    state: Mutex<LimiterState>,
    freed: Condvar,
}

#[derive(Debug, Default)]
struct LimiterState {
    in_flight: usize,
    /// The bounds of the elements using this server, one entry each.
    bounds: Vec<u32>,
}

impl LimiterState {
    fn max(&self) -> Option<usize> {
        self.bounds
            .iter()
            .copied()
            .filter(|&b| b > 0)
            .min()
            .map(|b| b as usize)
    }
}

/// One element's use of a server's limiter; dropping it withdraws the element's bound.
#[derive(Debug)]
struct LimiterUse {
    limiter: Arc<Limiter>,
    bound: u32,
}

impl Drop for LimiterUse {
    fn drop(&mut self) {
        let mut st = self.limiter.state.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(i) = st.bounds.iter().position(|&b| b == self.bound) {
            st.bounds.swap_remove(i);
        }
        drop(st);
        // A larger bound may apply now.
        self.limiter.freed.notify_all();
    }
}

struct Permit(Arc<Limiter>);

impl Drop for Permit {
    fn drop(&mut self) {
        let mut st = self.0.state.lock().unwrap_or_else(|e| e.into_inner());
        st.in_flight = st.in_flight.saturating_sub(1);
        drop(st);
        self.0.freed.notify_one();
    }
}

impl Limiter {
    /// Join the limiter of the server `key` with this element's `bound`.
    fn join(key: &str, bound: u32) -> LimiterUse {
        static ALL: LazyLock<Mutex<HashMap<String, Weak<Limiter>>>> =
            LazyLock::new(Default::default);
        let mut all = ALL.lock().unwrap_or_else(|e| e.into_inner());
        all.retain(|_, l| l.strong_count() > 0);
        let limiter = match all.get(key).and_then(Weak::upgrade) {
            Some(l) => l,
            None => {
                let l = Arc::new(Limiter {
                    state: Mutex::default(),
                    freed: Condvar::new(),
                });
                all.insert(key.to_string(), Arc::downgrade(&l));
                l
            }
        };
        drop(all);
        limiter
            .state
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .bounds
            .push(bound);
        LimiterUse { limiter, bound }
    }
}

impl LimiterUse {
    /// Wait up to `timeout` for a slot; otherwise the bound that was full. A stop or flush
    /// (`canceller`) ends the wait within [`CANCEL_POLL`] (None then).
    fn acquire(&self, timeout: Duration, canceller: &Canceller) -> Result<Permit, Option<usize>> {
        let l = &self.limiter;
        let deadline = Instant::now() + timeout;
        let mut st = l.state.lock().unwrap_or_else(|e| e.into_inner());
        while let Some(max) = st.max().filter(|&m| st.in_flight >= m) {
            let now = Instant::now();
            if canceller.is_cancelled() {
                return Err(None);
            }
            if now >= deadline {
                return Err(Some(max));
            }
            st = l
                .freed
                .wait_timeout(st, (deadline - now).min(CANCEL_POLL))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
        st.in_flight += 1;
        Ok(Permit(l.clone()))
    }
}

/// How often a request waiting for an in-flight slot looks whether it was interrupted.
const CANCEL_POLL: Duration = Duration::from_millis(20);

/// Exponential backoff between attempts while the server fails.
#[derive(Debug, Default)]
struct Backoff {
    failures: u32,
    retry_at: Option<Instant>,
    last_error: String,
}

impl Backoff {
    fn delay(failures: u32) -> Duration {
        let f = failures.saturating_sub(1).min(16);
        (BACKOFF_MIN * 2u32.pow(f)).min(BACKOFF_MAX)
    }

    fn fail(&mut self, error: String) {
        self.failures = self.failures.saturating_add(1);
        self.retry_at = Some(Instant::now() + Self::delay(self.failures));
        self.last_error = error;
    }

    /// Whether a request may go now; otherwise the time left and the last error.
    fn wait_left(&self) -> Option<Duration> {
        let at = self.retry_at?;
        let now = Instant::now();
        (now < at).then(|| at - now)
    }
}

#[derive(Debug, Clone)]
struct Features {
    shape: Vec<usize>,
    data: Vec<f32>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum RemoteKind {
    /// The server runs the pair model.
    Pair,
    /// The server runs the encoder; the head runs locally.
    Encoder,
}

/// Scores frames on a V2 server (see the module documentation).
pub struct RemoteScorer {
    local: Scorer,
    client: V2Client,
    /// The server's URL as shown ([`display_url`]).
    url: String,
    model: String,
    kind: RemoteKind,
    limiter: LimiterUse,
    timeout: Duration,
    reference: Option<Features>,
    current: Option<Features>,
    backoff: Backoff,
    latency: Histogram,
    requests: u64,
    failed: u64,
}

impl std::fmt::Debug for RemoteScorer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteScorer")
            .field("url", &self.url)
            .field("model", &self.model)
            .field("kind", &self.kind)
            .finish()
    }
}

fn describe_meta(m: &ModelMetadata) -> String {
    let t = |v: &[TensorMeta]| {
        v.iter()
            .map(|t| format!("{} {} {:?}", t.name, t.datatype, t.shape))
            .collect::<Vec<_>>()
            .join(", ")
    };
    format!("inputs [{}], outputs [{}]", t(&m.inputs), t(&m.outputs))
}

/// `shape` (from the server, -1 = variable) fits `want` (-1 = anything) when the ranks agree
/// and every fixed dimension matches; the batch dimension may be -1 or 1.
fn dims_fit(shape: &[i64], want: &[i64]) -> bool {
    shape.len() == want.len()
        && shape.first().is_none_or(|&b| b == -1 || b == 1)
        && shape
            .iter()
            .zip(want)
            .skip(1)
            .all(|(&s, &w)| s < 0 || w < 0 || s == w)
}

impl RemoteScorer {
    /// Check the server and its model against the local model's contract, and prove it with a
    /// dry run on a blank frame. `local` is the loaded local model (pair or split).
    pub fn connect(local: Scorer, opts: &RemoteOptions) -> Result<RemoteScorer, RemoteError> {
        let server = ServerUrl::parse(&opts.url).map_err(|reason| RemoteError::Url {
            url: display_url(&opts.url),
            reason,
        })?;
        let url = server.to_string();
        let kind = if local.head_feature_dims().is_some() {
            RemoteKind::Encoder
        } else {
            RemoteKind::Pair
        };
        let model = match opts
            .model
            .as_deref()
            .map(str::trim)
            .filter(|m| !m.is_empty())
        {
            Some(m) => m.to_string(),
            None if kind == RemoteKind::Encoder => format!("{}-encoder", local.info().name),
            None => local.info().name.clone(),
        };
        if model.contains(['/', '?', '#', ' ']) {
            return Err(RemoteError::UnknownModel {
                url,
                model,
                reason: "not a valid model name".into(),
            });
        }
        let timeout = opts.timeout.max(Duration::from_millis(1));
        let client = V2Client::new(&server, timeout);
        let failed = |what: &str, e: ClientError| match e {
            ClientError::Transport(reason) => RemoteError::Unreachable {
                url: url.clone(),
                reason,
            },
            ClientError::Timeout(t) => RemoteError::NoAnswer {
                url: url.clone(),
                what: what.to_string(),
                ms: t.as_millis(),
                hint: match server.is_https() {
                    true => "; is it a plain-HTTP server (http://)?".into(),
                    false => String::new(),
                },
            },
            ClientError::Status { code, message } if matches!(code, 401 | 403) => {
                RemoteError::Refused {
                    url: url.clone(),
                    reason: ClientError::Status { code, message }.to_string(),
                }
            }
            e => RemoteError::Answered {
                url: url.clone(),
                what: what.to_string(),
                model: model.clone(),
                reason: e.to_string(),
            },
        };
        let meta = match client.model_metadata(&model) {
            Ok(m) => m,
            Err(ClientError::Status { code, message })
                if (400..500).contains(&code) && !matches!(code, 401 | 403) =>
            {
                return Err(RemoteError::UnknownModel {
                    reason: ClientError::Status { code, message }.to_string(),
                    url,
                    model,
                })
            }
            Err(e) => return Err(failed("model metadata", e)),
        };
        match client.model_ready(&model) {
            Ok(true) => {}
            Ok(false) => return Err(RemoteError::NotReady { url, model }),
            Err(e) => return Err(failed("model readiness", e)),
        }
        let mut scorer = RemoteScorer {
            limiter: Limiter::join(&server.server_key(), opts.max_in_flight),
            local,
            client,
            url,
            model,
            kind,
            timeout,
            reference: None,
            current: None,
            backoff: Backoff::default(),
            latency: Histogram::default(),
            requests: 0,
            failed: 0,
        };
        scorer.check_contract(&meta)?;
        scorer.dry_run()?;
        gst::info!(
            CAT,
            "scoring on server {} with model {} ({})",
            scorer.url,
            scorer.model,
            match scorer.kind {
                RemoteKind::Pair => "pair model",
                RemoteKind::Encoder => "encoder remote, head local",
            }
        );
        Ok(scorer)
    }

    fn check_contract(&self, meta: &ModelMetadata) -> Result<(), RemoteError> {
        let spec = &self.local.info().spec;
        let image = [-1, 3, spec.height as i64, spec.width as i64];
        let fail = |reason: String| RemoteError::Contract {
            url: self.url.clone(),
            model: self.model.clone(),
            reason,
            metadata: describe_meta(meta),
        };
        let find = |list: &[TensorMeta], name: &str, what: &str, want: &[i64]| {
            let t = list
                .iter()
                .find(|t| t.name == name)
                .ok_or_else(|| fail(format!("no {what} `{name}`")))?;
            if t.datatype != "FP32" {
                return Err(fail(format!(
                    "{what} `{name}` is {}, expected FP32",
                    t.datatype
                )));
            }
            if !want.is_empty() && !dims_fit(&t.shape, want) {
                return Err(fail(format!(
                    "{what} `{name}` has shape {:?}, expected {want:?} (batch -1 or 1)",
                    t.shape
                )));
            }
            Ok(())
        };
        match self.kind {
            RemoteKind::Pair => {
                find(&meta.inputs, "reference", "input", &image)?;
                find(&meta.inputs, "current", "input", &image)?;
                find(&meta.outputs, "utility", "output", &[])?;
                let u = meta.outputs.iter().find(|t| t.name == "utility");
                if let Some(u) =
                    u.filter(|u| !dims_fit(&u.shape, &[-1]) && !dims_fit(&u.shape, &[-1, 1]))
                {
                    return Err(fail(format!(
                        "output `utility` has shape {:?}, expected [N] or [N,1]",
                        u.shape
                    )));
                }
            }
            RemoteKind::Encoder => {
                find(&meta.inputs, "image", "input", &image)?;
                let feat = self.local.head_feature_dims().unwrap_or_default();
                find(&meta.outputs, "features", "output", &feat).map_err(|e| match e {
                    RemoteError::Contract {
                        url,
                        model,
                        reason,
                        metadata,
                    } => RemoteError::Contract {
                        url,
                        model,
                        reason: format!(
                            "{reason}; it must be the encoder of the local split model \
                             `{}` (whose head runs here)",
                            self.local.info().name
                        ),
                        metadata,
                    },
                    e => e,
                })?;
            }
        }
        Ok(())
    }

    fn dry_run(&mut self) -> Result<(), RemoteError> {
        let spec = self.local.info().spec.clone();
        let plane = spec.len() / 3;
        let mut blank = vec![0f32; spec.len()];
        for (c, chunk) in blank.chunks_mut(plane.max(1)).enumerate().take(3) {
            chunk.fill(-spec.mean[c] / spec.std[c]);
        }
        let r = self.score_inner(&blank, &blank);
        self.reset_reference();
        // The dry run does not count in the stream's figures.
        self.latency.clear();
        self.requests = 0;
        self.failed = 0;
        r.map(|_| ()).map_err(|reason| RemoteError::DryRun {
            url: self.url.clone(),
            model: self.model.clone(),
            reason,
        })
    }

    /// One request, bounded in flight and timed.
    fn request(
        &mut self,
        inputs: &[InputTensor<'_>],
        outputs: &[&str],
    ) -> Result<Vec<client::OutputTensor>, String> {
        let canceller = self.client.canceller();
        let _permit = self
            .limiter
            .acquire(self.timeout, &canceller)
            .map_err(|max| match max {
                Some(max) => format!(
                    "{max} requests already in flight to the server for {} ms",
                    self.timeout.as_millis()
                ),
                None => "interrupted while waiting for a request slot".into(),
            })?;
        let t0 = Instant::now();
        self.requests += 1;
        let r = self.client.infer(&self.model, inputs, outputs);
        match r {
            Ok(o) => {
                self.latency
                    .record(t0.elapsed().as_micros().min(u64::MAX as u128) as u64);
                Ok(o)
            }
            Err(e) => {
                // A request interrupted by a stop or flush is not the server's failure.
                if !self.client.canceller().is_cancelled() {
                    self.failed += 1;
                }
                Err(e.to_string())
            }
        }
    }

    fn encode(&mut self, shape: &[usize], image: &[f32]) -> Result<Features, String> {
        let mut out = self.request(
            &[InputTensor {
                name: "image",
                shape,
                data: image,
            }],
            &["features"],
        )?;
        let f = out.pop().ok_or("no `features` output")?;
        // The head gets only a shape it can take: batch one, its feature dimensions, no empty
        // dimension (anything else would fail inside ONNX Runtime, or worse).
        let want = self.local.head_feature_dims().unwrap_or_default();
        let dims: Option<Vec<i64>> = f.shape.iter().map(|&d| i64::try_from(d).ok()).collect();
        if !dims.is_some_and(|d| d.first() == Some(&1) && !d.contains(&0) && dims_fit(&d, &want)) {
            return Err(format!(
                "`features` has shape {:?}, expected {want:?} with batch 1 (-1: any size)",
                f.shape
            ));
        }
        Ok(Features {
            shape: f.shape,
            data: f.data,
        })
    }

    fn score_inner(&mut self, reference: &[f32], current: &[f32]) -> Result<f32, String> {
        let spec = &self.local.info().spec;
        let shape = [1usize, 3, spec.height as usize, spec.width as usize];
        if reference.len() != spec.len() || current.len() != spec.len() {
            return Err(format!(
                "tensor length {} / {} does not match {shape:?}",
                reference.len(),
                current.len()
            ));
        }
        let u = match self.kind {
            RemoteKind::Pair => {
                let out = self.request(
                    &[
                        InputTensor {
                            name: "reference",
                            shape: &shape,
                            data: reference,
                        },
                        InputTensor {
                            name: "current",
                            shape: &shape,
                            data: current,
                        },
                    ],
                    &["utility"],
                )?;
                match out.first().map(|o| &o.data[..]) {
                    Some([u]) => *u,
                    Some(d) => {
                        return Err(format!(
                            "`utility` has {} values for a batch of one frame",
                            d.len()
                        ))
                    }
                    None => return Err("no `utility` output".into()),
                }
            }
            RemoteKind::Encoder => {
                if self.reference.is_none() {
                    self.reference = Some(self.encode(&shape, reference)?);
                }
                let cf = self.encode(&shape, current)?;
                let rf = self.reference.as_ref().expect("encoded above");
                let u = self
                    .local
                    .run_head((&rf.shape, &rf.data), (&cf.shape, &cf.data))
                    .map_err(|e| format!("local head: {e}"))?;
                self.current = Some(cf);
                u
            }
        };
        crate::scorer::check_utility(u).map_err(|e| match e {
            ScorerError::Inference(why) => why,
            e => e.to_string(),
        })
    }

    /// Score one pair of preprocessed tensors. While the server is in backoff after a failure,
    /// fails at once (the element keeps the frame) without a request.
    pub fn score(&mut self, reference: &[f32], current: &[f32]) -> Result<f32, ScorerError> {
        let canceller = self.client.canceller();
        if canceller.is_cancelled() {
            return Err(ScorerError::Interrupted);
        }
        if let Some(left) = self.backoff.wait_left() {
            return Err(ScorerError::Inference(format!(
                "server `{}` (model `{}`) unavailable: {}; next attempt in {} ms",
                self.url,
                self.model,
                self.backoff.last_error,
                left.as_millis()
            )));
        }
        let failed_before = self.failed;
        match self.score_inner(reference, current) {
            Ok(u) => {
                if self.backoff.failures > 0 {
                    gst::info!(
                        CAT,
                        "server {} is back after {} failed attempts",
                        self.url,
                        self.backoff.failures
                    );
                    self.backoff = Backoff::default();
                }
                Ok(u)
            }
            Err(_) if canceller.is_cancelled() => {
                // Interrupted by a state change or flush (see `canceller`): no backoff.
                self.current = None;
                Err(ScorerError::Interrupted)
            }
            Err(e) => {
                // An answer that cannot be used (a utility out of range, features of the wrong
                // shape) is a failed request too, like one that never came.
                if self.failed == failed_before {
                    self.failed += 1;
                }
                self.current = None;
                self.backoff.fail(e.clone());
                gst::debug!(CAT, "server {} failed: {e}", self.url);
                Err(ScorerError::Inference(format!(
                    "server `{}` (model `{}`): {e}",
                    self.url, self.model
                )))
            }
        }
    }

    /// The handle that interrupts this scorer's requests in flight from another thread (a
    /// pipeline stopping or flushing); they fail with [`ScorerError::Interrupted`].
    pub fn canceller(&self) -> Canceller {
        self.client.canceller()
    }

    /// See [`Scorer::on_keep`].
    pub fn on_keep(&mut self, scored: bool) {
        self.reference = if scored { self.current.take() } else { None };
        self.current = None;
    }

    pub fn reset_reference(&mut self) {
        self.on_keep(false);
    }

    pub fn info(&self) -> &ModelInfo {
        self.local.info()
    }

    /// The server's URL as shown ([`display_url`]: without credentials).
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The model's name on the server.
    pub fn server_model(&self) -> &str {
        &self.model
    }

    /// Whether the encoder runs on the server and the head here.
    pub fn is_split(&self) -> bool {
        self.kind == RemoteKind::Encoder
    }

    /// Requests sent since start (the start's dry run not counted).
    pub fn requests(&self) -> u64 {
        self.requests
    }

    /// Server figures for `leangate-stats`.
    pub fn stats(&self) -> ServerStats {
        ServerStats {
            server: self.url.clone(),
            server_model: self.model.clone(),
            requests: self.requests,
            failed_requests: self.failed,
            latency_p50_us: self.latency.percentile(50.0),
            latency_p99_us: self.latency.percentile(99.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A request canceller, as each element's client has one.
    fn canceller() -> Canceller {
        let url = ServerUrl::parse("http://127.0.0.1:9").unwrap();
        V2Client::new(&url, Duration::from_secs(1)).canceller()
    }

    #[test]
    fn a_stop_ends_the_wait_for_an_in_flight_slot() {
        // One slot, taken; a second request waits for it with a 20 s timeout until the element
        // is stopped (a probe measured 18 s for set_state(NULL) before).
        let a = Limiter::join("test://slot-wait", 1);
        let b = Limiter::join("test://slot-wait", 1);
        let canceller = canceller();
        let _held = a
            .acquire(Duration::from_secs(1), &canceller)
            .expect("a free slot");
        let stop = canceller.clone();
        let t = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(100));
            stop.cancel();
        });
        let t0 = Instant::now();
        let r = b.acquire(Duration::from_secs(20), &canceller);
        assert!(matches!(r, Err(None)), "interrupted, not timed out");
        assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
        t.join().unwrap();
        // Without a stop the wait ends at the timeout, naming the bound.
        canceller.resume();
        let r = b.acquire(Duration::from_millis(50), &canceller);
        assert!(matches!(r, Err(Some(1))));
    }

    #[test]
    fn backoff_doubles_and_caps() {
        assert_eq!(Backoff::delay(1), BACKOFF_MIN);
        assert_eq!(Backoff::delay(2), BACKOFF_MIN * 2);
        assert_eq!(Backoff::delay(40), BACKOFF_MAX);
        let mut b = Backoff::default();
        assert!(b.wait_left().is_none());
        b.fail("x".into());
        assert!(b.wait_left().is_some());
    }

    #[test]
    fn shapes() {
        assert!(dims_fit(&[-1, 3, 256, 256], &[-1, 3, 256, 256]));
        assert!(dims_fit(&[1, 3, -1, -1], &[-1, 3, 256, 256]));
        assert!(!dims_fit(&[2, 3, 256, 256], &[-1, 3, 256, 256]));
        assert!(!dims_fit(&[-1, 3, 224, 224], &[-1, 3, 256, 256]));
        assert!(!dims_fit(&[-1, 3, 256], &[-1, 3, 256, 256]));
    }

    #[test]
    fn limiter_bounds() {
        let t = Duration::from_millis(10);
        let c = canceller();
        let l = Limiter::join("http://test-limiter", 1);
        let p = l.acquire(t, &c).unwrap();
        assert_eq!(l.acquire(t, &c).err(), Some(Some(1)));
        drop(p);
        assert!(l.acquire(t, &c).is_ok());
        // No bound from anybody: no wait.
        let free = Limiter::join("http://test-unbounded", 0);
        let _held: Vec<_> = (0..100).map(|_| free.acquire(t, &c).unwrap()).collect();
    }

    #[test]
    fn smallest_bound_of_the_users_applies_while_they_use_it() {
        let t = Duration::from_millis(10);
        let c = canceller();
        let wide = Limiter::join("http://test-smallest", 3);
        let narrow = Limiter::join("http://test-smallest", 1);
        let p = wide.acquire(t, &c).unwrap();
        assert_eq!(wide.acquire(t, &c).err(), Some(Some(1)));
        assert_eq!(narrow.acquire(t, &c).err(), Some(Some(1)));
        drop(narrow);
        let q = wide.acquire(t, &c).unwrap();
        let r = wide.acquire(t, &c).unwrap();
        assert_eq!(wide.acquire(t, &c).err(), Some(Some(3)));
        drop((p, q, r));
        // The last user gone, the server's limiter goes too: a new one starts afresh.
        drop(wide);
        let again = Limiter::join("http://test-smallest", 2);
        assert_eq!(again.limiter.state.lock().unwrap().bounds, vec![2]);
    }
}
