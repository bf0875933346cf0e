//! The scorer: a LeanGate *pair model* in ONNX Runtime, and the model contract it enforces.
//!
//! Contract (also in `models/README.md`): float32 inputs `reference` and `current`, shape `[N,3,H,W]`,
//! RGB in [0,1] before the optional normalisation; output `utility`, `[N]` or `[N,1]`, the predicted
//! tau (high = novel = keep). Optional `metadata_props`: `leangate.input_size` (`WxH`),
//! `leangate.resize` (`short-side-crop` | `stretch`), `leangate.mean`, `leangate.std` (three numbers),
//! `leangate.threshold`, `leangate.name`.
//!
//! [`contract`] checks a graph and its metadata against the contract; [`session`] builds the ONNX
//! Runtime sessions on the chosen execution provider; this module loads a model (pair or split),
//! proves it with one dry run on a blank frame, and scores frames.

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, LazyLock, Mutex, MutexGuard, Weak};
use std::time::Duration;

use ort::session::{RunOptions, Session};
use ort::value::TensorRef;

use crate::preprocess::{try_zeroed, TensorSpec};
use crate::runtime;

mod batch;
mod contract;
mod head;
mod session;

use batch::{Batcher, Job};
pub use contract::{CONTRACT, MAX_INPUT_SIDE, MAX_TENSOR_BYTES};
use session::{build_session, BuildError, Input};

/// Which execution provider to run on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ExecutionProvider {
    /// Try TensorRT, then CUDA, then CPU; each GPU failure is reported as a warning.
    #[default]
    Auto,
    Cpu,
    Cuda,
    TensorRt,
}

impl ExecutionProvider {
    pub fn as_str(self) -> &'static str {
        match self {
            ExecutionProvider::Auto => "auto",
            ExecutionProvider::Cpu => "cpu",
            ExecutionProvider::Cuda => "cuda",
            ExecutionProvider::TensorRt => "tensorrt",
        }
    }

    pub fn parse(s: &str) -> Option<ExecutionProvider> {
        [
            ExecutionProvider::Auto,
            ExecutionProvider::Cpu,
            ExecutionProvider::Cuda,
            ExecutionProvider::TensorRt,
        ]
        .into_iter()
        .find(|e| e.as_str() == s)
    }
}

/// Which build of the embedded student to run (`precision` property). A model file runs as it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Precision {
    /// INT8 on the CPU provider (measured: the same keep decisions at 1.33-1.70x the speed, by
    /// CPU: more with VNNI), FP32 on GPU providers.
    #[default]
    Auto,
    Fp32,
    Int8,
}

impl Precision {
    pub fn as_str(self) -> &'static str {
        match self {
            Precision::Auto => "auto",
            Precision::Fp32 => "fp32",
            Precision::Int8 => "int8",
        }
    }
}

/// Where the model comes from.
#[derive(Debug, Clone)]
pub enum ModelSource {
    File(PathBuf),
    /// Bytes compiled into the binary; `head` is the second half of a split model; `int8` an
    /// INT8 build of the same split model (encoder, head), chosen by [`ScorerOptions::precision`].
    Memory {
        name: String,
        bytes: &'static [u8],
        head: Option<&'static [u8]>,
        int8: Option<(&'static [u8], &'static [u8])>,
    },
}

impl ModelSource {
    fn describe(&self) -> String {
        match self {
            ModelSource::File(p) => format!("`{}`", p.display()),
            ModelSource::Memory { name, .. } => format!("embedded model `{name}`"),
        }
    }
}

/// Session options.
#[derive(Debug, Clone, Default)]
pub struct ScorerOptions {
    pub execution_provider: ExecutionProvider,
    pub device_id: i32,
    /// CPU intra-op threads; 0 = [`default_threads`].
    pub threads: usize,
    /// Let ONNX Runtime's worker threads spin-wait for work (`session.intra_op.allow_spinning`
    /// and `session.inter_op.allow_spinning`). Off by default: spinning threads take CPU time
    /// from the decoders and other elements of the pipeline for a few microseconds of latency.
    pub spinning: bool,
    /// Share the ONNX Runtime sessions with every other scorer of the process that loads the
    /// same model (same file, size and modification time, and the same of the files it reads,
    /// [`files_read`]; or the same embedded bytes) with the
    /// same provider, device, threads and spinning (a process-wide registry). Each scorer keeps
    /// its own reference features.
    pub shared: bool,
    /// Coalesce up to this many concurrent frames of the scorers sharing a session into one
    /// batched encoder run (split models whose encoder has a dynamic batch dimension; others
    /// run unbatched). 0 or 1 = off. Only with `shared`.
    pub batch_size: usize,
    /// The longest a frame waits for others to fill a batch. No wait when this scorer is the
    /// only one using the session with batching on.
    pub batch_timeout: Duration,
    /// With `shared`: at most this many sessions of one model in the process. A new scorer gets
    /// a session of its own while there are fewer, and otherwise joins the least used one. One
    /// session runs one frame at a time, so on the CPU up to one session per core lets
    /// concurrent streams use every core; on a GPU one session (with batching) is what pays.
    /// 0 = [`default_max_sessions`].
    pub max_sessions: usize,
    /// Which build of an embedded model with an INT8 variant to run (ignored for model files,
    /// with a warning when not `Auto`).
    pub precision: Precision,
}

impl ScorerOptions {
    /// The intra-op thread count actually used (`threads`, or [`default_threads`] for 0).
    pub fn effective_threads(&self) -> usize {
        if self.threads > 0 {
            self.threads.min(MAX_THREADS)
        } else {
            default_threads()
        }
    }

    /// The session cap actually used (`max_sessions`, or [`default_max_sessions`] for 0).
    pub fn effective_max_sessions(&self, provider: &str) -> usize {
        if self.max_sessions > 0 {
            self.max_sessions
        } else {
            default_max_sessions(provider, self.effective_threads())
        }
    }
}

/// Sessions per shared model when `max_sessions` is 0: on the CPU provider, one per
/// `threads` cores (so that concurrent streams can use every core: a session runs one frame at
/// a time); on any other provider one (a GPU gains from batching, not from more sessions).
pub fn default_max_sessions(provider: &str, threads: usize) -> usize {
    if provider == ExecutionProvider::Cpu.as_str() {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        (cores / threads.max(1)).max(1)
    } else {
        1
    }
}

/// Intra-op threads when `threads` is 0: one. The students are small (a few milliseconds of
/// work per frame at most): a second thread gains little for them and competes with the
/// decoder and the rest of the pipeline (measured in `cargo bench --bench perf -- threads`).
pub fn default_threads() -> usize {
    1
}

/// The most intra-op threads a session may have (the element's `threads` maximum; a larger
/// [`ScorerOptions::threads`] counts as this). ONNX Runtime starts them all at once, per session:
/// thousands took minutes to start and stop and gigabytes of stacks, for a model that gains
/// nothing beyond a few.
pub const MAX_THREADS: usize = 256;

/// Everything that can go wrong loading or running a model.
#[derive(Debug, Clone, thiserror::Error)]
pub enum ScorerError {
    #[error(transparent)]
    Runtime(#[from] runtime::RuntimeError),
    /// The model file could not be read.
    #[error("cannot read model file `{path}`: {reason}")]
    Read { path: String, reason: String },
    /// ONNX Runtime refused the model.
    #[error("{model} is not a valid ONNX model: {reason}")]
    Parse { model: String, reason: String },
    /// The graph does not follow the contract (or fails its dry run).
    #[error("{model} does not follow the model contract: {reason}; {}", CONTRACT)]
    Contract { model: String, reason: String },
    /// Bad `leangate.*` metadata.
    #[error("{model} has invalid metadata: {reason}")]
    Metadata { model: String, reason: String },
    /// An explicitly requested execution provider failed.
    #[error("execution provider `{provider}` failed: {reason}")]
    Provider { provider: String, reason: String },
    /// Run-time failure.
    #[error("inference failed: {0}")]
    Inference(String),
    /// The element is stopping or flushing and interrupted the request in flight (remote
    /// scoring): not a failure of the model or the server.
    #[error("interrupted: the element is stopping or flushing")]
    Interrupted,
}

/// What the model says about itself (metadata merged with the graph's shapes).
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    pub name: String,
    pub spec: TensorSpec,
    /// `leangate.threshold`, if the model carries one (in [0, 1]).
    pub threshold: Option<f64>,
    /// `leangate.calibration`: how the model's utility was calibrated to the teacher's units
    /// (informational; the calibration itself is part of the graph).
    pub calibration: Option<String>,
    /// `leangate.geometry`: how the element combines this model's utility with the geometric
    /// prior ([`crate::geometry`]); None: the utility is used alone.
    pub geometry: Option<crate::geometry::Fusion>,
    /// `leangate.score_max`: the largest utility the graph can output (its calibration's top),
    /// within (0, 1]; the fusion's screening bound assumes no score above it
    /// ([`crate::geometry::Fusion::s_max`]), and the element stops assuming it, with a warning,
    /// if a score ever exceeds it. None: 1.
    pub score_max: Option<f64>,
    /// `leangate.score_step`: how much the utility rises, as a rule, from one frame to the next
    /// against the same reference (a high percentile of the rises measured on real video,
    /// `training/score_step.py`), within (0, 1]; with a fusion, screening bounds a frame's score
    /// by the previous frame's plus this ([`crate::Utility::screen`]). None: not used.
    pub score_step: Option<f64>,
    /// `leangate.precision` (`fp32` when absent): the arithmetic of the graph that runs.
    pub precision: String,
}

/// The two model forms, sessions only (shareable between streams).
enum Kind {
    /// One graph: (reference, current) → utility.
    Pair(Mutex<Session>),
    /// `encoder` (image → features) and `head` (features, features → utility); the reference's
    /// features are computed once per stream and kept until the next keep.
    Split {
        encoder: Mutex<Session>,
        head: Mutex<Session>,
        /// How the head is named in messages.
        head_name: String,
        /// The encoder takes a dynamic batch dimension.
        batchable: bool,
    },
}

#[derive(Debug, Clone)]
struct Features {
    shape: Vec<usize>,
    data: Vec<f32>,
}

/// A loaded, validated model: its sessions, shared by the scorers using it.
struct Model {
    kind: Kind,
    info: ModelInfo,
    provider: &'static str,
    warnings: Vec<String>,
    /// Shared with its batch worker, which holds the model itself only while it runs a batch:
    /// the model's last scorer frees it.
    batcher: Arc<Batcher>,
    /// Last, so that it drops after the sessions.
    _give_back: GiveBackOnDrop,
}

/// Dropped after a model's sessions: hands the memory they freed back to the system
/// ([`give_back_free_memory`]).
struct GiveBackOnDrop;

impl Drop for GiveBackOnDrop {
    fn drop(&mut self) {
        give_back_free_memory();
    }
}

/// Return the C allocator's free memory to the system (glibc's `malloc_trim(0)`; nothing
/// elsewhere), once a model's sessions are gone.
///
/// Why: glibc serves a large block with `mmap` (given back when freed) only until a block of
/// that size is freed; then it raises its threshold (up to 32 MiB) so that blocks of that size
/// come from its heaps, where a freed block stays resident. The first model freed raises it
/// above the blocks of ONNX Runtime's sessions, so every later session's memory stayed resident
/// when it went, scattered over the allocator's arenas: creating and destroying elements raised
/// the resident memory by 64-73 MiB over the first round's within 30 rounds of `soak -- churn`
/// (now 25-29 MiB; `MALLOC_MMAP_THRESHOLD_=131072`, a fixed threshold, keeps it flat too).
/// Measured cost: 1 to 10 ms per call on the thread that drops the model, once per model.
fn give_back_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` only releases free memory; no argument points anywhere.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Registry key: what must be equal for two scorers to share sessions.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
struct ModelKey {
    identity: String,
    provider: &'static str,
    device_id: i32,
    threads: usize,
    spinning: bool,
    precision: Precision,
}

/// The loaded instances of one model (at most `max_sessions`), locked while one is loaded.
type Instances = Arc<Mutex<Vec<Weak<Model>>>>;

/// Per key, the loaded instances of the model. The map is locked only to find or add a key; a
/// model is loaded under its own key's lock, so that a slow model's load (a large network, a
/// TensorRT engine build) holds up only the streams starting with the same model.
static REGISTRY: LazyLock<Mutex<HashMap<ModelKey, Instances>>> =
    LazyLock::new(|| Mutex::new(HashMap::new()));

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Every file loading the model at `model` reads, as canonical paths: the model itself, a split
/// model's head (its `leangate.head`), and the tensor data either keeps outside the `.onnx`
/// (ONNX external data, each tensor's `location`). Both are written in the model file as a
/// key-value entry (`StringStringEntryProto`: the key, then the path relative to the model's
/// folder), which is what is read here, without parsing the whole model. Paths that do not
/// exist are left out (loading the model then fails, naming them).
pub fn files_read(model: &Path) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = Vec::new();
    let mut todo = vec![(model.to_path_buf(), true)];
    while let Some((file, may_name_head)) = todo.pop() {
        let Ok(file) = file.canonicalize() else {
            continue;
        };
        if out.contains(&file) {
            continue;
        }
        out.push(file.clone());
        let Some(dir) = file.parent().map(Path::to_path_buf) else {
            continue;
        };
        // Only a regular file is read (a FIFO or a device would block or never end; loading
        // refuses them), and only one a protobuf can be (ONNX's limit is 2 GiB).
        let regular = std::fs::metadata(&file).is_ok_and(|m| m.is_file() && m.len() < 1 << 31);
        if !regular {
            continue;
        }
        let Ok(bytes) = std::fs::read(&file) else {
            continue;
        };
        for (key, is_head) in [(&b"location"[..], false), (&b"leangate.head"[..], true)] {
            if is_head && !may_name_head {
                continue;
            }
            for name in entry_values(&bytes, key) {
                todo.push((dir.join(name), false));
            }
        }
    }
    out
}

/// The values of the protobuf key-value entries (`StringStringEntryProto`: field 1 the key,
/// field 2 the value, both short strings) whose key is `key`, as relative paths; any other
/// bytes are skipped.
fn entry_values<'a>(bytes: &'a [u8], key: &[u8]) -> Vec<&'a str> {
    let mut pattern = vec![0x0a, key.len() as u8];
    pattern.extend_from_slice(key);
    pattern.push(0x12);
    let mut values = Vec::new();
    for i in memchr::memmem::find_iter(bytes, &pattern) {
        let start = i + pattern.len();
        // The value's length, a varint of at most two bytes (a path under 16 KiB).
        let Some(&b0) = bytes.get(start) else {
            continue;
        };
        let (len, skip) = match (b0, bytes.get(start + 1)) {
            (b0, _) if b0 < 0x80 => (b0 as usize, 1),
            (b0, Some(&b1)) if b1 < 0x80 => ((b0 & 0x7f) as usize | (b1 as usize) << 7, 2),
            _ => continue,
        };
        let Some(v) = bytes.get(start + skip..start + skip + len) else {
            continue;
        };
        if let Ok(v) = std::str::from_utf8(v) {
            if !v.is_empty() {
                values.push(v);
            }
        }
    }
    values
}

/// A model's identity for the registry: the canonical paths of the model and the files it reads
/// with their sizes and modification times (a replaced file is a new model), or the embedded
/// bytes' name, address and length.
fn identity(source: &ModelSource) -> Option<String> {
    match source {
        ModelSource::File(p) => {
            // The model and what it reads (a split model's head, external data): replacing any
            // of them makes a new model.
            let mut id = String::from("file");
            std::fs::canonicalize(p).ok()?;
            for f in files_read(p) {
                let md = std::fs::metadata(&f).ok()?;
                let mtime = md
                    .modified()
                    .ok()
                    .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                    .map(|d| d.as_nanos())
                    .unwrap_or(0);
                id.push_str(&format!(":{}:{}:{mtime}", f.display(), md.len()));
            }
            Some(id)
        }
        ModelSource::Memory {
            name,
            bytes,
            head,
            int8,
        } => Some(format!(
            "memory:{name}:{:p}:{}:{:?}:{:?}",
            bytes.as_ptr(),
            bytes.len(),
            head.map(|h| (h.as_ptr(), h.len())),
            int8.map(|(e, h)| (e.as_ptr(), e.len(), h.as_ptr(), h.len()))
        )),
    }
}

/// Stops a scorer's local inference from another thread ([`Scorer::run_stop`]): the element
/// stopping or flushing ends a model run in flight (ONNX Runtime's terminate flag, checked between
/// the graph's operators) instead of waiting for it, and the run fails with
/// [`ScorerError::Interrupted`], as do the next ones until [`RunStop::resume`]. A batched encoder
/// run (`batch-size`) serves other streams too and is let finish.
#[derive(Clone)]
pub struct RunStop {
    options: Option<Arc<RunOptions>>,
    stopped: Arc<AtomicBool>,
}

impl fmt::Debug for RunStop {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RunStop")
            .field("stopped", &self.stopped())
            .finish()
    }
}

impl RunStop {
    fn new() -> RunStop {
        RunStop {
            // Without run options (ONNX Runtime could not make them) runs cannot be stopped.
            options: RunOptions::new().ok().map(|mut o| {
                // A failed run is the element's to report (a warning naming it, the frame kept);
                // a stopped one is no failure. Neither goes to standard error from ONNX Runtime.
                let _ = o.set_log_level(ort::logging::LogLevel::Fatal);
                Arc::new(o)
            }),
            stopped: Arc::default(),
        }
    }

    /// The stream stops or flushes: a run in flight ends, and runs fail until [`RunStop::resume`].
    pub fn stop(&self) {
        self.stopped.store(true, Ordering::SeqCst);
        if let Some(o) = &self.options {
            let _ = o.terminate();
        }
    }

    /// After a flush, or a stop that did not happen: runs may go again.
    pub fn resume(&self) {
        if let Some(o) = &self.options {
            let _ = o.unterminate();
        }
        self.stopped.store(false, Ordering::SeqCst);
    }

    fn stopped(&self) -> bool {
        self.stopped.load(Ordering::SeqCst)
    }

    /// Run `session` on `inputs` with these run options; a run ended by [`RunStop::stop`] is
    /// [`ScorerError::Interrupted`].
    fn run<'s, 'i, 'v: 'i, const N: usize>(
        &'s self,
        session: &'s mut Session,
        inputs: impl Into<ort::session::SessionInputs<'i, 'v, N>>,
    ) -> Result<ort::session::SessionOutputs<'s>, ScorerError> {
        if self.stopped() {
            return Err(ScorerError::Interrupted);
        }
        let r = match &self.options {
            Some(o) => session.run_with_options(inputs, o),
            None => session.run(inputs),
        };
        r.map_err(|e| match self.stopped() {
            true => ScorerError::Interrupted,
            false => ScorerError::Inference(e.to_string()),
        })
    }
}

/// A scorer: one stream's view of a (possibly shared) model, with its own reference features.
pub struct Scorer {
    model: Arc<Model>,
    reference: Option<Features>,
    current: Option<Features>,
    encoder_runs: u64,
    batch_size: usize,
    batch_timeout: Duration,
    /// This scorer's membership of `model.batcher` when batching (it leaves on drop).
    member: Option<u64>,
    /// The buffer a frame is queued in for the batcher, reused.
    staging: Vec<f32>,
    /// Warnings collected while choosing the provider (`auto` fallbacks).
    pub warnings: Vec<String>,
    /// Ends this scorer's local runs when the element stops or flushes.
    stop: RunStop,
}

impl Drop for Scorer {
    fn drop(&mut self) {
        if let Some(m) = self.member {
            self.model.batcher.leave(m);
        }
    }
}

/// See [`Scorer::idle_handle`].
#[derive(Debug, Clone)]
pub struct IdleHandle {
    model: Weak<Model>,
    member: u64,
}

impl IdleHandle {
    /// See [`Scorer::idle`].
    pub fn idle(&self) {
        if let Some(m) = self.model.upgrade() {
            m.batcher.idle(self.member);
        }
    }
}

impl fmt::Debug for Scorer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Scorer")
            .field("info", &self.model.info)
            .field("provider", &self.model.provider)
            .field("batch_size", &self.batch_size)
            .finish()
    }
}

impl Scorer {
    /// Load and validate a model (pair, or the encoder of a split model with its head), then
    /// prove it with one dry run on a blank frame: a model that loads but cannot score (a fixed
    /// batch of 2, a head that does not fit its encoder, NaN out) is a start error, not a
    /// failure on every frame.
    pub fn load(source: &ModelSource, opts: &ScorerOptions) -> Result<Scorer, ScorerError> {
        let mut fallback = None;
        let model = if opts.shared {
            match identity(source) {
                Some(id) => {
                    let key = ModelKey {
                        identity: id,
                        provider: opts.execution_provider.as_str(),
                        device_id: opts.device_id,
                        threads: opts.effective_threads(),
                        spinning: opts.spinning,
                        precision: opts.precision,
                    };
                    let entry = {
                        let mut reg = lock(&REGISTRY);
                        // Keys whose models are all gone go; one that is being loaded (locked)
                        // or about to be (its entry held by a starting scorer) stays.
                        reg.retain(|_, e| {
                            if Arc::strong_count(e) > 1 {
                                return true;
                            }
                            match e.try_lock() {
                                Ok(mut v) => {
                                    v.retain(|w| w.strong_count() > 0);
                                    !v.is_empty()
                                }
                                Err(_) => true,
                            }
                        });
                        reg.entry(key).or_default().clone()
                    };
                    // The instances upgraded below; declared before the lock so that they are
                    // let go after it: if one of them was the last reference, its sessions are
                    // freed (and the memory given back) with the registry unlocked.
                    let live: Vec<Arc<Model>>;
                    // Held while loading: a second stream of the same model starting at the same
                    // time waits for the first's instance instead of loading its own.
                    let mut instances = lock(&entry);
                    instances.retain(|w| w.strong_count() > 0);
                    live = instances.iter().filter_map(Weak::upgrade).collect();
                    // The least used instance (the `live` clones add one to each count).
                    let least = live.iter().min_by_key(|m| Arc::strong_count(m)).cloned();
                    match least {
                        Some(m) if live.len() >= opts.effective_max_sessions(m.provider) => m,
                        least => match Self::load_model(source, opts) {
                            Ok(m) => {
                                let m = Arc::new(m);
                                instances.push(Arc::downgrade(&m));
                                m
                            }
                            // Another instance could not be made (memory, a provider that
                            // refuses a second session): share one that works.
                            Err(e) => match least {
                                Some(m) => {
                                    fallback = Some(format!(
                                        "another session of {} could not be created, sharing an \
                                         existing one: {e}",
                                        source.describe()
                                    ));
                                    m
                                }
                                None => return Err(e),
                            },
                        },
                    }
                }
                None => Arc::new(Self::load_model(source, opts)?),
            }
        } else {
            Arc::new(Self::load_model(source, opts)?)
        };
        let batching = opts.shared
            && opts.batch_size > 1
            && matches!(
                model.kind,
                Kind::Split {
                    batchable: true,
                    ..
                }
            );
        let member = if batching { join_batch(&model) } else { None };
        let mut warnings = model.warnings.clone();
        warnings.extend(fallback);
        if matches!(source, ModelSource::File(_)) && opts.precision != Precision::Auto {
            warnings.push(format!(
                "precision `{}` applies to the embedded student only; {} runs as it is ({})",
                opts.precision.as_str(),
                source.describe(),
                model.info.precision
            ));
        }
        Ok(Scorer {
            stop: RunStop::new(),
            warnings,
            model,
            reference: None,
            current: None,
            encoder_runs: 0,
            batch_size: opts.batch_size.max(1),
            batch_timeout: opts.batch_timeout,
            member,
            staging: Vec::new(),
        })
    }

    /// Load, check and dry-run a model (its sessions, unshared).
    fn load_model(source: &ModelSource, opts: &ScorerOptions) -> Result<Model, ScorerError> {
        let model = source.describe();
        if let ModelSource::File(p) = source {
            session::check_model_file(p)?;
        }
        let (env, _) = runtime::environment()?;

        let mut warnings = Vec::new();
        let mut last_err = None;
        for &provider in session::provider_order(opts.execution_provider) {
            // The graph for this provider: an embedded model's INT8 build runs on the CPU
            // (precision auto) or wherever it is asked for (int8).
            let (input, embedded_head) = match source {
                ModelSource::File(p) => (Input::File(p), None),
                ModelSource::Memory {
                    bytes, head, int8, ..
                } => match int8 {
                    Some((e, h))
                        if opts.precision == Precision::Int8
                            || (opts.precision == Precision::Auto
                                && provider == ExecutionProvider::Cpu) =>
                    {
                        (Input::Memory(e), Some(*h))
                    }
                    _ => (Input::Memory(bytes), *head),
                },
            };
            match build_session(&env, input, provider, opts) {
                Ok(session) => {
                    let (kind, info) = Self::assemble(
                        source,
                        embedded_head,
                        &env,
                        session,
                        provider,
                        opts,
                        &model,
                    )?;
                    let m = Arc::new(Model {
                        kind,
                        info,
                        provider: provider.as_str(),
                        warnings,
                        batcher: Arc::default(),
                        _give_back: GiveBackOnDrop,
                    });
                    let mut scorer = Scorer {
                        stop: RunStop::new(),
                        model: m.clone(),
                        reference: None,
                        current: None,
                        encoder_runs: 0,
                        batch_size: 1,
                        batch_timeout: Duration::ZERO,
                        member: None,
                        staging: Vec::new(),
                        warnings: Vec::new(),
                    };
                    let r = scorer.dry_run(&model);
                    drop(scorer);
                    r?;
                    return Ok(Arc::into_inner(m).expect("not shared yet"));
                }
                Err(BuildError::Parse(reason)) => {
                    return Err(ScorerError::Parse { model, reason });
                }
                Err(BuildError::Provider(reason)) => {
                    if opts.execution_provider == ExecutionProvider::Auto {
                        warnings.push(format!(
                            "execution provider `{}` unavailable, trying the next: {reason}",
                            provider.as_str()
                        ));
                    }
                    last_err = Some(ScorerError::Provider {
                        provider: provider.as_str().to_string(),
                        reason,
                    });
                }
            }
        }
        Err(last_err.expect("at least one provider was tried"))
    }

    /// Check the graph(s) against the contract; for a split model, load and check its head.
    #[allow(clippy::too_many_arguments)]
    fn assemble(
        source: &ModelSource,
        embedded_head: Option<&'static [u8]>,
        env: &ort::environment::Environment,
        session: Session,
        provider: ExecutionProvider,
        opts: &ScorerOptions,
        model: &str,
    ) -> Result<(Kind, ModelInfo), ScorerError> {
        match contract::model_kind(&session, model)? {
            "pair" => {
                let info = contract::validate_pair(&session, model)?;
                Ok((Kind::Pair(Mutex::new(session)), info))
            }
            "encoder" => {
                let (info, features) = contract::validate_encoder(&session, model)?;
                let (head_name, head_path);
                let head_input = match (source, embedded_head) {
                    (ModelSource::Memory { name, .. }, Some(h)) => {
                        head_name = format!("embedded model `{name}` (head)");
                        Input::Memory(h)
                    }
                    (ModelSource::Memory { .. }, None) => {
                        return Err(ScorerError::Contract {
                            model: model.to_string(),
                            reason: "an embedded split encoder without its head".into(),
                        })
                    }
                    (ModelSource::File(p), _) => {
                        head_path = contract::head_path(p, &session, model)?;
                        session::check_model_file(&head_path).map_err(|e| match e {
                            ScorerError::Read { path, reason } => ScorerError::Read {
                                path,
                                reason: format!(
                                    "{reason} (the head that {model}'s leangate.head names)"
                                ),
                            },
                            e => e,
                        })?;
                        head_name = format!("`{}`", head_path.display());
                        Input::File(&head_path)
                    }
                };
                let head = build_session(env, head_input, provider, opts).map_err(|e| match e {
                    BuildError::Parse(reason) | BuildError::Provider(reason) => {
                        ScorerError::Parse {
                            model: head_name.clone(),
                            reason,
                        }
                    }
                })?;
                contract::validate_head(&head, &head_name, &features)?;
                let batchable = contract::dynamic_batch(&session, "image", "features");
                Ok((
                    Kind::Split {
                        encoder: Mutex::new(session),
                        head: Mutex::new(head),
                        head_name,
                        batchable,
                    },
                    info,
                ))
            }
            _ => Err(ScorerError::Contract {
                model: model.to_string(),
                reason: "it is the head of a split model; set `model` to its encoder \
                         (leangate.kind = encoder)"
                    .into(),
            }),
        }
    }

    /// Score a blank (black) frame against itself: the output must be one finite number.
    fn dry_run(&mut self, model: &str) -> Result<(), ScorerError> {
        let spec = self.model.info.spec.clone();
        let mut blank = try_zeroed(spec.len()).map_err(|e| ScorerError::Metadata {
            model: model.to_string(),
            reason: format!(
                "cannot allocate its {}x{} input tensor: {e}",
                spec.width, spec.height
            ),
        })?;
        let plane = spec.len() / 3;
        for (c, chunk) in blank.chunks_mut(plane.max(1)).enumerate().take(3) {
            chunk.fill(-spec.mean[c] / spec.std[c]);
        }
        let r = self.score(&blank, &blank);
        self.reset_reference();
        self.encoder_runs = 0;
        let with = match &self.model.kind {
            Kind::Split { head_name, .. } => format!(" (with its head {head_name})"),
            Kind::Pair(_) => String::new(),
        };
        r.map(|_| ()).map_err(|e| ScorerError::Contract {
            model: model.to_string(),
            reason: format!("a dry run on a blank frame{with} failed: {e}"),
        })?;
        // An encoder that declares a dynamic batch is run in batches (`batch-size`): it must
        // take one, or every batched frame would fail later.
        if let Kind::Split {
            encoder,
            batchable: true,
            ..
        } = &self.model.kind
        {
            let shape = [1, 3, spec.height as usize, spec.width as usize];
            let jobs = [Job::unqueued(blank.clone()), Job::unqueued(blank)];
            run_batch(encoder, shape, &jobs, &mut Vec::new()).map_err(|e| {
                ScorerError::Contract {
                    model: model.to_string(),
                    reason: format!(
                        "its encoder declares a dynamic batch dimension, but a dry run on a \
                         batch of 2 blank frames failed: {e} (make the batch dimension 1 if the \
                         encoder cannot take batches)"
                    ),
                }
            })?;
        }
        Ok(())
    }

    pub fn info(&self) -> &ModelInfo {
        &self.model.info
    }

    /// The execution provider in use (`cpu`, `cuda`, `tensorrt`).
    pub fn provider(&self) -> &'static str {
        self.model.provider
    }

    /// Whether this is a split model (encoder + head, with the reference's features cached).
    pub fn is_split(&self) -> bool {
        matches!(self.model.kind, Kind::Split { .. })
    }

    /// Encoder runs for this scorer's frames so far (split models; 0 for pair models).
    pub fn encoder_runs(&self) -> u64 {
        self.encoder_runs
    }

    /// Whether this scorer shares its sessions with `other` (the same loaded instance of the
    /// model in the registry).
    pub fn shares_session_with(&self, other: &Scorer) -> bool {
        Arc::ptr_eq(&self.model, &other.model)
    }

    /// What stops this scorer's local runs from another thread (see [`RunStop`]).
    pub fn run_stop(&self) -> RunStop {
        self.stop.clone()
    }

    /// Whether this scorer's frames go through the batcher (shared, `batch_size` > 1, and a
    /// model whose encoder takes a dynamic batch).
    pub fn is_batching(&self) -> bool {
        self.member.is_some()
    }

    /// Batched encoder runs of the shared model so far, and the frames in them.
    pub fn batch_counts(&self) -> (u64, u64) {
        self.model.batcher.counts()
    }

    /// The batching scorers of the shared model, and how many of them count as streaming (the
    /// others' frames wait for theirs; see [`Scorer::idle`]).
    pub fn batch_members(&self) -> (usize, usize) {
        self.model.batcher.members()
    }

    /// This stream stops for now (EOS, PAUSED, flush): the scorers batching with it stop waiting
    /// for its frames until it scores again. Nothing to do when not batching.
    pub fn idle(&self) {
        if let Some(m) = self.member {
            self.model.batcher.idle(m);
        }
    }

    /// A handle that does [`Scorer::idle`] from another thread (a state change) without access
    /// to the scorer; `None` when not batching. It keeps no session alive.
    pub fn idle_handle(&self) -> Option<IdleHandle> {
        self.member.map(|member| IdleHandle {
            model: Arc::downgrade(&self.model),
            member,
        })
    }

    /// Score one pair of preprocessed tensors (CHW, `spec.len()` elements each). A split model
    /// encodes `reference` only when it has no cached features for it (see [`Scorer::on_keep`]).
    pub fn score(&mut self, reference: &[f32], current: &[f32]) -> Result<f32, ScorerError> {
        let spec = &self.model.info.spec;
        let shape = [1usize, 3, spec.height as usize, spec.width as usize];
        if reference.len() != spec.len() || current.len() != spec.len() {
            return Err(ScorerError::Inference(format!(
                "tensor length {} / {} does not match [1,3,{},{}]",
                reference.len(),
                current.len(),
                spec.height,
                spec.width
            )));
        }
        let inf = |e: ort::Error| ScorerError::Inference(e.to_string());
        let model = self.model.clone();
        let stop = self.stop.clone();
        let u = match &model.kind {
            Kind::Pair(session) => {
                let r = TensorRef::from_array_view((shape, reference)).map_err(inf)?;
                let c = TensorRef::from_array_view((shape, current)).map_err(inf)?;
                let mut session = lock(session);
                let outputs =
                    stop.run(&mut session, ort::inputs!["reference" => r, "current" => c])?;
                first_utility(&outputs)?
            }
            Kind::Split { encoder, head, .. } => {
                if self.reference.is_none() {
                    self.reference = Some(self.encode(encoder, shape, reference)?);
                    self.encoder_runs += 1;
                }
                let cf = self.encode(encoder, shape, current)?;
                self.encoder_runs += 1;
                let rf = self.reference.as_ref().expect("encoded above");
                let r =
                    TensorRef::from_array_view((rf.shape.clone(), &rf.data[..])).map_err(inf)?;
                let c =
                    TensorRef::from_array_view((cf.shape.clone(), &cf.data[..])).map_err(inf)?;
                let mut head = lock(head);
                let outputs = stop.run(
                    &mut head,
                    ort::inputs!["reference_features" => r, "current_features" => c],
                )?;
                let u = first_utility(&outputs)?;
                drop(outputs);
                drop(head);
                self.current = Some(cf);
                u
            }
        };
        check_utility(u)
    }

    /// Encode one image, through the batcher when batching.
    fn encode(
        &mut self,
        encoder: &Mutex<Session>,
        shape: [usize; 4],
        image: &[f32],
    ) -> Result<Features, ScorerError> {
        if let Some(member) = self.member {
            self.encode_batched(member, image)
        } else {
            encode(&mut lock(encoder), shape, image, &self.stop)
        }
    }

    /// Queue the image in the model's batcher (see [`batch`]) and wait for its features.
    fn encode_batched(&mut self, member: u64, image: &[f32]) -> Result<Features, ScorerError> {
        let mut own = std::mem::take(&mut self.staging);
        own.clear();
        own.try_reserve_exact(image.len())
            .map_err(|e| ScorerError::Inference(format!("cannot queue a frame: {e}")))?;
        own.extend_from_slice(image);
        let (r, own) = self
            .model
            .batcher
            .encode(member, self.batch_size, self.batch_timeout, own);
        self.staging = own;
        r.map_err(ScorerError::Inference)
    }

    /// The frame just decided was kept and is the new reference. `scored`: it was scored by the
    /// last [`Scorer::score`] call (its features can be reused); otherwise the reference's
    /// features are recomputed at the next score.
    pub fn on_keep(&mut self, scored: bool) {
        if self.is_split() {
            self.reference = if scored { self.current.take() } else { None };
            self.current = None;
        }
    }

    /// Forget the reference (reset, flush, caps change).
    pub fn reset_reference(&mut self) {
        self.on_keep(false);
    }
}

type Task = Box<dyn FnOnce() + Send>;
/// An idle worker: its number, and where to send it a task.
type IdleWorker = (u64, std::sync::mpsc::Sender<Task>);

/// Idle batch worker threads, each waiting for a model to serve. A worker outlives its model
/// for [`WORKER_IDLE`], so that the next model's batches run on the same thread (and in the
/// same C allocator arena) instead of a new one each time elements come and go.
static IDLE_WORKERS: LazyLock<Mutex<Vec<IdleWorker>>> = LazyLock::new(|| Mutex::new(Vec::new()));
const WORKER_IDLE: Duration = Duration::from_secs(30);

/// Run `task` on an idle batch worker, or on a new one.
fn on_worker(task: Task) -> std::io::Result<()> {
    let task = {
        let mut idle = lock(&IDLE_WORKERS);
        match idle.pop() {
            // Sent under the lock: a worker that times out checks the list under it too, so a
            // listed worker is still listening.
            Some((_, tx)) => match tx.send(task) {
                Ok(()) => return Ok(()),
                Err(e) => e.0,
            },
            None => task,
        }
    };
    std::thread::Builder::new()
        .name("leangate-batch".into())
        .spawn(move || {
            static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
            let id = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let mut task = task;
            loop {
                task();
                let (tx, rx) = std::sync::mpsc::channel();
                lock(&IDLE_WORKERS).push((id, tx));
                match rx.recv_timeout(WORKER_IDLE) {
                    Ok(t) => task = t,
                    Err(_) => {
                        let mut idle = lock(&IDLE_WORKERS);
                        match idle.iter().position(|(i, _)| *i == id) {
                            Some(k) => {
                                idle.remove(k);
                                return;
                            }
                            // Taken just now: the task was sent under the lock.
                            None => match rx.try_recv() {
                                Ok(t) => task = t,
                                Err(_) => return,
                            },
                        }
                    }
                }
            }
        })
        .map(|_| ())
}

/// Join the model's batcher, starting its batch worker if none runs; `None` (the scorer then
/// runs unbatched) when no thread could be started.
fn join_batch(model: &Arc<Model>) -> Option<u64> {
    model.batcher.join(|| {
        let batcher = model.batcher.clone();
        let model = Arc::downgrade(model);
        on_worker(Box::new(move || {
            batcher.serve(|jobs, input| {
                // Queued frames are of live scorers, so the model is there; it is let go before
                // their features are handed back.
                let m = model.upgrade().ok_or("the model is gone")?;
                let spec = &m.info.spec;
                let shape = [1usize, 3, spec.height as usize, spec.width as usize];
                match &m.kind {
                    Kind::Split { encoder, .. } => run_batch(encoder, shape, jobs, input),
                    Kind::Pair(_) => Err("a pair model has no encoder to batch".into()),
                }
            })
        }))
    })
}

/// Run `jobs` (images of `shape` [1,3,H,W] each) through the encoder as one batch; the
/// features of each, in order.
fn run_batch(
    encoder: &Mutex<Session>,
    shape: [usize; 4],
    jobs: &[Job],
    input: &mut Vec<f32>,
) -> Result<Vec<Features>, String> {
    let n = jobs.len();
    let one = shape[1] * shape[2] * shape[3];
    input.clear();
    input
        .try_reserve(n * one)
        .map_err(|e| format!("cannot allocate a batch of {n}: {e}"))?;
    for j in jobs {
        input.extend_from_slice(&j.image);
    }
    let shape = [n, shape[1], shape[2], shape[3]];
    let t = TensorRef::from_array_view((shape, &input[..])).map_err(|e| e.to_string())?;
    let mut session = lock(encoder);
    let outputs = session
        .run(ort::inputs!["image" => t])
        .map_err(|e| e.to_string())?;
    let f = outputs
        .get("features")
        .ok_or_else(|| "no `features` output".to_string())?;
    let (fshape, data) = f.try_extract_tensor::<f32>().map_err(|e| e.to_string())?;
    if fshape.first().copied() != Some(n as i64) || data.len() % n != 0 {
        return Err(format!(
            "`features` has shape {:?} for a batch of {n}",
            &**fshape
        ));
    }
    let per = data.len() / n;
    let mut item_shape: Vec<usize> = fshape.iter().map(|&d| d.max(0) as usize).collect();
    item_shape[0] = 1;
    let mut out = Vec::with_capacity(n);
    for chunk in data.chunks_exact(per) {
        let mut owned = Vec::new();
        owned
            .try_reserve_exact(per)
            .map_err(|e| format!("cannot allocate {per} features: {e}"))?;
        owned.extend_from_slice(chunk);
        out.push(Features {
            shape: item_shape.clone(),
            data: owned,
        });
    }
    Ok(out)
}

fn encode(
    encoder: &mut Session,
    shape: [usize; 4],
    image: &[f32],
    stop: &RunStop,
) -> Result<Features, ScorerError> {
    let inf = |e: ort::Error| ScorerError::Inference(e.to_string());
    let t = TensorRef::from_array_view((shape, image)).map_err(inf)?;
    let outputs = stop.run(encoder, ort::inputs!["image" => t])?;
    let f = outputs
        .get("features")
        .ok_or_else(|| ScorerError::Inference("no `features` output".into()))?;
    let (shape, data) = f.try_extract_tensor::<f32>().map_err(inf)?;
    let mut owned = Vec::new();
    owned.try_reserve_exact(data.len()).map_err(|e| {
        ScorerError::Inference(format!("cannot allocate {} features: {e}", data.len()))
    })?;
    owned.extend_from_slice(data);
    Ok(Features {
        shape: shape.iter().map(|&d| d.max(0) as usize).collect(),
        data: owned,
    })
}

/// A model's utility is tau = 1 - S, in [0, 1]: anything else is a failed run (the element keeps
/// the frame and warns), as a server's answer out of that range is.
pub(crate) fn check_utility(u: f32) -> Result<f32, ScorerError> {
    if !u.is_finite() {
        return Err(ScorerError::Inference(format!(
            "`utility` is not finite ({u})"
        )));
    }
    if !(0.0..=1.0).contains(&u) {
        return Err(ScorerError::Inference(format!(
            "`utility` {u} is not in [0, 1]"
        )));
    }
    Ok(u)
}

/// The single utility value of a batch of one.
fn first_utility(outputs: &ort::session::SessionOutputs) -> Result<f32, ScorerError> {
    let out = outputs
        .get("utility")
        .ok_or_else(|| ScorerError::Inference("no `utility` output".into()))?;
    let (shape, data) = out
        .try_extract_tensor::<f32>()
        .map_err(|e| ScorerError::Inference(e.to_string()))?;
    match data {
        [u] => Ok(*u),
        [] => Err(ScorerError::Inference("`utility` output is empty".into())),
        _ => Err(ScorerError::Inference(format!(
            "`utility` has shape {:?} ({} values) for a batch of one frame",
            &**shape,
            data.len()
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threads_beyond_the_limit_count_as_the_limit() {
        let opts = |threads| ScorerOptions {
            threads,
            ..Default::default()
        };
        assert_eq!(opts(0).effective_threads(), default_threads());
        assert_eq!(opts(3).effective_threads(), 3);
        assert_eq!(opts(100_000).effective_threads(), MAX_THREADS);
    }

    /// A batching model's sessions go with its last scorer, on that scorer's thread (the element
    /// stopping), not later on the batch worker: the worker holds the model only while it runs
    /// a batch. (Before, the worker held it until it noticed that the last member had left.)
    #[test]
    fn the_last_batching_scorer_frees_the_model() {
        let opts = ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            shared: true,
            max_sessions: 1,
            batch_size: 4,
            batch_timeout: Duration::from_millis(2),
            // Threads: a registry key of its own (no other test's scorers share this model).
            threads: 3,
            ..Default::default()
        };
        for _ in 0..20 {
            let mut scorers: Vec<Scorer> = (0..2)
                .map(|_| Scorer::load(&crate::default_model(), &opts).unwrap())
                .collect();
            assert!(scorers.iter().all(Scorer::is_batching));
            let image = vec![0.5; scorers[0].info().spec.len()];
            std::thread::scope(|s| {
                for sc in scorers.iter_mut() {
                    let image = &image;
                    s.spawn(move || sc.score(image, image).unwrap());
                }
            });
            assert!(scorers[0].batch_counts().0 > 0, "it ran batches");
            let model = Arc::downgrade(&scorers[0].model);
            drop(scorers);
            assert_eq!(
                model.strong_count(),
                0,
                "the model is freed when its last scorer goes"
            );
        }
    }

    #[test]
    fn provider_names() {
        assert_eq!(
            ExecutionProvider::parse("cuda"),
            Some(ExecutionProvider::Cuda)
        );
        assert_eq!(ExecutionProvider::parse("gpu"), None);
    }
}
