//! The scorer: a LeanGate *pair model* in ONNX Runtime, and the model contract it enforces.
//!
//! Contract (also in `models/README.md`): float32 inputs `reference` and `current`, shape `[N,3,H,W]`,
//! RGB in [0,1] before the optional normalisation; output `utility`, `[N]` or `[N,1]`, the predicted
//! tau (high = novel = keep). Optional `metadata_props`: `leangate.input_size` (`WxH`),
//! `leangate.resize` (`short-side-crop` | `stretch`), `leangate.mean`, `leangate.std` (three numbers),
//! `leangate.threshold`, `leangate.name`.

use std::fmt;
use std::path::{Path, PathBuf};

use ort::ep;
use ort::session::Session;
use ort::value::{TensorElementType, TensorRef, ValueType};

use crate::preprocess::{ResizeMode, TensorSpec};
use crate::runtime;

/// Input size used when neither the metadata nor the graph fixes one.
pub const DEFAULT_INPUT_SIZE: (u32, u32) = (256, 256);

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

/// Where the model comes from.
#[derive(Debug, Clone)]
pub enum ModelSource {
    File(PathBuf),
    /// Bytes compiled into the binary; `head` is the second half of a split model.
    Memory {
        name: String,
        bytes: &'static [u8],
        head: Option<&'static [u8]>,
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
    /// CPU intra-op threads; 0 = ONNX Runtime's default.
    pub threads: usize,
}

/// Everything that can go wrong loading or running a model.
#[derive(Debug, Clone)]
pub enum ScorerError {
    Runtime(runtime::RuntimeError),
    /// The model file could not be read.
    Read {
        path: String,
        reason: String,
    },
    /// ONNX Runtime refused the bytes.
    Parse {
        model: String,
        reason: String,
    },
    /// The graph does not follow the contract.
    Contract {
        model: String,
        reason: String,
    },
    /// Bad `leangate.*` metadata.
    Metadata {
        model: String,
        reason: String,
    },
    /// An explicitly requested execution provider failed.
    Provider {
        provider: String,
        reason: String,
    },
    /// Run-time failure.
    Inference(String),
}

pub const CONTRACT: &str = "a LeanGate pair model has float32 inputs `reference` and `current` of \
shape [N,3,H,W] and a float32 output `utility` of shape [N] or [N,1]";

impl fmt::Display for ScorerError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ScorerError::Runtime(e) => e.fmt(f),
            ScorerError::Read { path, reason } => {
                write!(f, "cannot read model file `{path}`: {reason}")
            }
            ScorerError::Parse { model, reason } => {
                write!(f, "{model} is not a valid ONNX model: {reason}")
            }
            ScorerError::Contract { model, reason } => {
                write!(
                    f,
                    "{model} does not follow the model contract: {reason}; {CONTRACT}"
                )
            }
            ScorerError::Metadata { model, reason } => {
                write!(f, "{model} has invalid metadata: {reason}")
            }
            ScorerError::Provider { provider, reason } => {
                write!(f, "execution provider `{provider}` failed: {reason}")
            }
            ScorerError::Inference(e) => write!(f, "inference failed: {e}"),
        }
    }
}

impl std::error::Error for ScorerError {}

/// What the model says about itself (metadata merged with the graph's shapes).
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    pub name: String,
    pub spec: TensorSpec,
    /// `leangate.threshold`, if the model carries one.
    pub threshold: Option<f64>,
}

/// The two model forms.
enum Kind {
    /// One graph: (reference, current) → utility.
    Pair(Session),
    /// `encoder` (image → features) and `head` (features, features → utility); the reference's
    /// features are computed once and kept until the next keep.
    Split {
        encoder: Session,
        head: Session,
        reference: Option<Features>,
        current: Option<Features>,
        encoder_runs: u64,
    },
}

#[derive(Debug, Clone)]
struct Features {
    shape: Vec<usize>,
    data: Vec<f32>,
}

/// A loaded model (pair or split).
pub struct Scorer {
    kind: Kind,
    info: ModelInfo,
    provider: &'static str,
    /// Warnings collected while choosing the provider (`auto` fallbacks).
    pub warnings: Vec<String>,
}

impl fmt::Debug for Scorer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Scorer")
            .field("info", &self.info)
            .field("provider", &self.provider)
            .finish()
    }
}

fn parse_triplet(s: &str) -> Option<[f32; 3]> {
    let v: Vec<f32> = s
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<f32>().ok())
        .collect::<Option<_>>()?;
    (v.len() == 3).then(|| [v[0], v[1], v[2]])
}

/// Parse `WxH`.
pub fn parse_size(s: &str) -> Option<(u32, u32)> {
    let (w, h) = s.trim().split_once(['x', 'X'])?;
    let (w, h) = (w.trim().parse().ok()?, h.trim().parse().ok()?);
    (w > 0 && h > 0).then_some((w, h))
}

fn tensor_dims(vt: &ValueType) -> Option<(TensorElementType, Vec<i64>)> {
    match vt {
        ValueType::Tensor { ty, shape, .. } => Some((*ty, shape.iter().copied().collect())),
        _ => None,
    }
}

impl Scorer {
    /// Load and validate a pair model.
    pub fn load(source: &ModelSource, opts: &ScorerOptions) -> Result<Scorer, ScorerError> {
        let model = source.describe();
        let owned;
        let bytes: &[u8] = match source {
            ModelSource::File(p) => {
                owned = read_model_file(p)?;
                &owned
            }
            ModelSource::Memory { bytes, .. } => bytes,
        };
        let (env, _) = runtime::environment().map_err(ScorerError::Runtime)?;

        let mut warnings = Vec::new();
        let order: &[ExecutionProvider] = match opts.execution_provider {
            ExecutionProvider::Auto => &[
                ExecutionProvider::TensorRt,
                ExecutionProvider::Cuda,
                ExecutionProvider::Cpu,
            ],
            ExecutionProvider::Cpu => &[ExecutionProvider::Cpu],
            ExecutionProvider::Cuda => &[ExecutionProvider::Cuda],
            ExecutionProvider::TensorRt => &[ExecutionProvider::TensorRt],
        };
        let mut last_err = None;
        for &provider in order {
            match build_session(&env, bytes, provider, opts) {
                Ok(session) => {
                    let (kind, info) =
                        match model_kind(&session, &model)? {
                            "pair" => {
                                let info = validate_pair(&session, &model)?;
                                (Kind::Pair(session), info)
                            }
                            "encoder" => {
                                let info = validate_encoder(&session, &model)?;
                                let (head_name, head_bytes) = head_bytes(source, &session, &model)?;
                                let head = build_session(&env, &head_bytes, provider, opts)
                                    .map_err(|e| match e {
                                        BuildError::Parse(reason)
                                        | BuildError::Provider(reason) => ScorerError::Parse {
                                            model: head_name.clone(),
                                            reason,
                                        },
                                    })?;
                                validate_head(&head, &head_name)?;
                                (
                                    Kind::Split {
                                        encoder: session,
                                        head,
                                        reference: None,
                                        current: None,
                                        encoder_runs: 0,
                                    },
                                    info,
                                )
                            }
                            _ => {
                                return Err(ScorerError::Contract {
                                    model,
                                    reason: "it is the head of a split model; set `model` to its \
                                         encoder (leangate.kind = encoder)"
                                        .into(),
                                })
                            }
                        };
                    return Ok(Scorer {
                        kind,
                        info,
                        provider: provider.as_str(),
                        warnings,
                    });
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

    pub fn info(&self) -> &ModelInfo {
        &self.info
    }

    /// The execution provider in use (`cpu`, `cuda`, `tensorrt`).
    pub fn provider(&self) -> &'static str {
        self.provider
    }

    /// Whether this is a split model (encoder + head, with the reference's features cached).
    pub fn is_split(&self) -> bool {
        matches!(self.kind, Kind::Split { .. })
    }

    /// Encoder runs so far (split models; 0 for pair models).
    pub fn encoder_runs(&self) -> u64 {
        match &self.kind {
            Kind::Split { encoder_runs, .. } => *encoder_runs,
            Kind::Pair(_) => 0,
        }
    }

    /// Score one pair of preprocessed tensors (CHW, `spec.len()` elements each). A split model
    /// encodes `reference` only when it has no cached features for it (see [`Scorer::on_keep`]).
    pub fn score(&mut self, reference: &[f32], current: &[f32]) -> Result<f32, ScorerError> {
        let spec = &self.info.spec;
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
        let u = match &mut self.kind {
            Kind::Pair(session) => {
                let r = TensorRef::from_array_view((shape, reference)).map_err(inf)?;
                let c = TensorRef::from_array_view((shape, current)).map_err(inf)?;
                let outputs = session
                    .run(ort::inputs!["reference" => r, "current" => c])
                    .map_err(inf)?;
                first_utility(&outputs)?
            }
            Kind::Split {
                encoder,
                head,
                reference: ref_feat,
                current: cur_feat,
                encoder_runs,
            } => {
                if ref_feat.is_none() {
                    *ref_feat = Some(encode(encoder, shape, reference)?);
                    *encoder_runs += 1;
                }
                let cf = encode(encoder, shape, current)?;
                *encoder_runs += 1;
                let rf = ref_feat.as_ref().unwrap();
                let r =
                    TensorRef::from_array_view((rf.shape.clone(), &rf.data[..])).map_err(inf)?;
                let c =
                    TensorRef::from_array_view((cf.shape.clone(), &cf.data[..])).map_err(inf)?;
                let outputs = head
                    .run(ort::inputs!["reference_features" => r, "current_features" => c])
                    .map_err(inf)?;
                let u = first_utility(&outputs)?;
                drop(outputs);
                *cur_feat = Some(cf);
                u
            }
        };
        if !u.is_finite() {
            return Err(ScorerError::Inference(format!(
                "`utility` is not finite ({u})"
            )));
        }
        Ok(u)
    }

    /// The frame just decided was kept and is the new reference. `scored`: it was scored by the
    /// last [`Scorer::score`] call (its features can be reused); otherwise the reference's
    /// features are recomputed at the next score.
    pub fn on_keep(&mut self, scored: bool) {
        if let Kind::Split {
            reference, current, ..
        } = &mut self.kind
        {
            *reference = if scored { current.take() } else { None };
            *current = None;
        }
    }

    /// Forget the reference (reset, flush, caps change).
    pub fn reset_reference(&mut self) {
        self.on_keep(false);
    }
}

fn encode(
    encoder: &mut Session,
    shape: [usize; 4],
    image: &[f32],
) -> Result<Features, ScorerError> {
    let inf = |e: ort::Error| ScorerError::Inference(e.to_string());
    let t = TensorRef::from_array_view((shape, image)).map_err(inf)?;
    let outputs = encoder.run(ort::inputs!["image" => t]).map_err(inf)?;
    let f = outputs
        .get("features")
        .ok_or_else(|| ScorerError::Inference("no `features` output".into()))?;
    let (shape, data) = f.try_extract_tensor::<f32>().map_err(inf)?;
    Ok(Features {
        shape: shape.iter().map(|&d| d.max(0) as usize).collect(),
        data: data.to_vec(),
    })
}

fn first_utility(outputs: &ort::session::SessionOutputs) -> Result<f32, ScorerError> {
    let out = outputs
        .get("utility")
        .ok_or_else(|| ScorerError::Inference("no `utility` output".into()))?;
    let (_, data) = out
        .try_extract_tensor::<f32>()
        .map_err(|e| ScorerError::Inference(e.to_string()))?;
    data.first()
        .copied()
        .ok_or_else(|| ScorerError::Inference("`utility` output is empty".into()))
}

/// `leangate.kind`: `pair` (default), `encoder` or `head`.
fn model_kind(session: &Session, model: &str) -> Result<&'static str, ScorerError> {
    let meta = session.metadata().map_err(|e| ScorerError::Metadata {
        model: model.to_string(),
        reason: format!("unreadable: {e}"),
    })?;
    match meta.custom("leangate.kind").as_deref().map(str::trim) {
        None | Some("") | Some("pair") => Ok("pair"),
        Some("encoder") => Ok("encoder"),
        Some("head") => Ok("head"),
        Some(other) => Err(ScorerError::Metadata {
            model: model.to_string(),
            reason: format!("leangate.kind = {other:?}, expected `pair`, `encoder` or `head`"),
        }),
    }
}

/// The head of a split model: embedded bytes, or the file named by `leangate.head` beside the
/// encoder.
fn head_bytes(
    source: &ModelSource,
    encoder: &Session,
    model: &str,
) -> Result<(String, std::borrow::Cow<'static, [u8]>), ScorerError> {
    match source {
        ModelSource::Memory {
            name,
            head: Some(h),
            ..
        } => Ok((format!("embedded model `{name}` (head)"), (*h).into())),
        ModelSource::Memory { .. } => Err(ScorerError::Contract {
            model: model.to_string(),
            reason: "an embedded split encoder without its head".into(),
        }),
        ModelSource::File(p) => {
            let meta = encoder.metadata().map_err(|e| ScorerError::Metadata {
                model: model.to_string(),
                reason: format!("unreadable: {e}"),
            })?;
            let name = meta
                .custom("leangate.head")
                .filter(|h| !h.trim().is_empty())
                .ok_or_else(|| ScorerError::Metadata {
                    model: model.to_string(),
                    reason: "a split encoder (leangate.kind = encoder) must name its head file in \
                             leangate.head"
                        .into(),
                })?;
            let path = p.parent().unwrap_or(Path::new(".")).join(name.trim());
            let bytes = read_model_file(&path)?;
            Ok((format!("`{}`", path.display()), bytes.into()))
        }
    }
}

fn read_model_file(p: &Path) -> Result<Vec<u8>, ScorerError> {
    let err = |reason: String| ScorerError::Read {
        path: p.display().to_string(),
        reason,
    };
    if p.as_os_str().is_empty() {
        return Err(err("no path given".into()));
    }
    if p.is_dir() {
        return Err(err("it is a directory".into()));
    }
    let bytes = std::fs::read(p).map_err(|e| err(e.to_string()))?;
    if bytes.is_empty() {
        return Err(err("the file is empty".into()));
    }
    Ok(bytes)
}

enum BuildError {
    Parse(String),
    Provider(String),
}

fn build_session(
    env: &ort::environment::Environment,
    bytes: &[u8],
    provider: ExecutionProvider,
    opts: &ScorerOptions,
) -> Result<Session, BuildError> {
    let parse = |e: &dyn fmt::Display| BuildError::Parse(e.to_string());
    let mut b = Session::builder(env).map_err(|e| parse(&e))?;
    b = b.with_intra_op_spinning(false).map_err(|e| parse(&e))?;
    b = b.with_inter_threads(1).map_err(|e| parse(&e))?;
    if opts.threads > 0 {
        b = b.with_intra_threads(opts.threads).map_err(|e| parse(&e))?;
    }
    let dispatch = match provider {
        ExecutionProvider::Cpu | ExecutionProvider::Auto => None,
        ExecutionProvider::Cuda => Some(
            ep::CUDA::default()
                .with_device_id(opts.device_id)
                .build()
                .error_on_failure(),
        ),
        ExecutionProvider::TensorRt => {
            let cache = std::env::var_os("XDG_CACHE_HOME")
                .map(PathBuf::from)
                .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
                .unwrap_or_else(std::env::temp_dir)
                .join("leangate")
                .join("tensorrt");
            let _ = std::fs::create_dir_all(&cache);
            Some(
                ep::TensorRT::default()
                    .with_device_id(opts.device_id)
                    .with_engine_cache(true)
                    .with_engine_cache_path(cache.display())
                    .build()
                    .error_on_failure(),
            )
        }
    };
    if let Some(d) = dispatch {
        b = b
            .with_execution_providers([d])
            .map_err(|e| BuildError::Provider(e.to_string()))?;
    }
    b.commit_from_memory(bytes).map_err(|e| {
        let msg = e.to_string();
        // A provider that registers but cannot create its kernels also fails here.
        if provider != ExecutionProvider::Cpu
            && (msg.contains("CUDA") || msg.contains("TensorRT") || msg.contains("cuda"))
        {
            BuildError::Provider(msg)
        } else {
            BuildError::Parse(msg)
        }
    })
}

fn input_dims(
    session: &Session,
    want: &str,
    rank4: bool,
    model: &str,
) -> Result<Vec<i64>, ScorerError> {
    let contract = |reason: String| ScorerError::Contract {
        model: model.to_string(),
        reason,
    };
    let names: Vec<&str> = session.inputs().iter().map(|i| i.name()).collect();
    let input = session
        .inputs()
        .iter()
        .find(|i| i.name() == want)
        .ok_or_else(|| contract(format!("it has inputs {names:?}, no `{want}`")))?;
    let (ty, dims) = tensor_dims(input.dtype())
        .ok_or_else(|| contract(format!("input `{want}` is not a tensor")))?;
    if ty != TensorElementType::Float32 {
        return Err(contract(format!("input `{want}` is {ty:?}, not float32")));
    }
    if rank4 && (dims.len() != 4 || (dims[1] != 3 && dims[1] >= 0)) {
        return Err(contract(format!("input `{want}` has shape {dims:?}")));
    }
    Ok(dims)
}

fn check_inputs_count(session: &Session, n: usize, model: &str) -> Result<(), ScorerError> {
    let names: Vec<&str> = session.inputs().iter().map(|i| i.name()).collect();
    if names.len() != n {
        return Err(ScorerError::Contract {
            model: model.to_string(),
            reason: format!("it has {} inputs {names:?}", names.len()),
        });
    }
    Ok(())
}

fn check_output(
    session: &Session,
    want: &str,
    utility: bool,
    model: &str,
) -> Result<(), ScorerError> {
    let contract = |reason: String| ScorerError::Contract {
        model: model.to_string(),
        reason,
    };
    let onames: Vec<&str> = session.outputs().iter().map(|o| o.name()).collect();
    let out = session
        .outputs()
        .iter()
        .find(|o| o.name() == want)
        .ok_or_else(|| contract(format!("it has outputs {onames:?}, no `{want}`")))?;
    let (ty, dims) = tensor_dims(out.dtype())
        .ok_or_else(|| contract(format!("output `{want}` is not a tensor")))?;
    if ty != TensorElementType::Float32 {
        return Err(contract(format!("output `{want}` is {ty:?}, not float32")));
    }
    if utility && !(dims.len() == 1 || (dims.len() == 2 && (dims[1] == 1 || dims[1] < 0))) {
        return Err(contract(format!("output `{want}` has shape {dims:?}")));
    }
    Ok(())
}

/// Check a pair model against the contract and merge it with the metadata.
fn validate_pair(session: &Session, model: &str) -> Result<ModelInfo, ScorerError> {
    let r = input_dims(session, "reference", true, model)?;
    let c = input_dims(session, "current", true, model)?;
    check_inputs_count(session, 2, model)?;
    check_output(session, "utility", true, model)?;
    if (r[2], r[3]) != (c[2], c[3]) {
        return Err(ScorerError::Contract {
            model: model.to_string(),
            reason: format!("inputs `reference` and `current` differ in size ({r:?} vs {c:?})"),
        });
    }
    read_metadata(session, (r[3], r[2]), model)
}

/// The encoder of a split model: `image` [N,3,H,W] → `features`.
fn validate_encoder(session: &Session, model: &str) -> Result<ModelInfo, ScorerError> {
    let d = input_dims(session, "image", true, model).map_err(split_hint)?;
    check_inputs_count(session, 1, model).map_err(split_hint)?;
    check_output(session, "features", false, model).map_err(split_hint)?;
    read_metadata(session, (d[3], d[2]), model)
}

/// The head of a split model: `reference_features`, `current_features` → `utility`.
fn validate_head(session: &Session, model: &str) -> Result<(), ScorerError> {
    input_dims(session, "reference_features", false, model).map_err(split_hint)?;
    input_dims(session, "current_features", false, model).map_err(split_hint)?;
    check_inputs_count(session, 2, model).map_err(split_hint)?;
    check_output(session, "utility", true, model).map_err(split_hint)
}

fn split_hint(e: ScorerError) -> ScorerError {
    match e {
        ScorerError::Contract { model, reason } => ScorerError::Contract {
            model,
            reason: format!(
                "{reason} (a split model is an encoder `image` [N,3,H,W] → `features` and a head \
                 (`reference_features`, `current_features`) → `utility`)"
            ),
        },
        e => e,
    }
}

/// Merge the graph's input size (`(W, H)`, negative = dynamic) with the `leangate.*` metadata.
fn read_metadata(
    session: &Session,
    size: (i64, i64),
    model: &str,
) -> Result<ModelInfo, ScorerError> {
    let meta_err = |reason: String| ScorerError::Metadata {
        model: model.to_string(),
        reason,
    };
    let meta = session
        .metadata()
        .map_err(|e| meta_err(format!("unreadable: {e}")))?;
    let get = |k: &str| meta.custom(k).filter(|v| !v.trim().is_empty());
    let graph_size = match size {
        (w, h) if w > 0 && h > 0 => Some((w as u32, h as u32)),
        _ => None,
    };
    let (width, height) = match get("leangate.input_size") {
        Some(s) => {
            let sz = parse_size(&s).ok_or_else(|| {
                meta_err(format!(
                    "leangate.input_size = {s:?}, expected `WxH` like `256x256`"
                ))
            })?;
            if let Some(g) = graph_size {
                if g != sz {
                    return Err(meta_err(format!(
                        "leangate.input_size {s} disagrees with the graph's fixed input {}x{}",
                        g.0, g.1
                    )));
                }
            }
            sz
        }
        None => graph_size.unwrap_or(DEFAULT_INPUT_SIZE),
    };
    let resize = match get("leangate.resize") {
        Some(s) => ResizeMode::parse(&s).ok_or_else(|| {
            meta_err(format!(
                "leangate.resize = {s:?}, expected `short-side-crop` or `stretch`"
            ))
        })?,
        None => ResizeMode::ShortSideCrop,
    };
    let triplet = |key: &str, default: [f32; 3]| -> Result<[f32; 3], ScorerError> {
        match get(key) {
            Some(s) => parse_triplet(&s)
                .ok_or_else(|| meta_err(format!("{key} = {s:?}, expected three numbers"))),
            None => Ok(default),
        }
    };
    let mean = triplet("leangate.mean", [0.0; 3])?;
    let std = triplet("leangate.std", [1.0; 3])?;
    if std.iter().any(|s| *s == 0.0 || !s.is_finite()) {
        return Err(meta_err(format!("leangate.std = {std:?} has a zero")));
    }
    let threshold = match get("leangate.threshold") {
        Some(s) => Some(
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|t| t.is_finite())
                .ok_or_else(|| meta_err(format!("leangate.threshold = {s:?} is not a number")))?,
        ),
        None => None,
    };
    let name = get("leangate.name")
        .or_else(|| meta.name())
        .unwrap_or_else(|| model.trim_matches('`').to_string());
    Ok(ModelInfo {
        name,
        spec: TensorSpec {
            width,
            height,
            resize,
            mean,
            std,
        },
        threshold,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parsers() {
        assert_eq!(parse_size("256x192"), Some((256, 192)));
        assert_eq!(parse_size(" 64 X 32 "), Some((64, 32)));
        assert_eq!(parse_size("0x5"), None);
        assert_eq!(parse_size("256"), None);
        assert_eq!(
            parse_triplet("0.485, 0.456, 0.406"),
            Some([0.485, 0.456, 0.406])
        );
        assert_eq!(parse_triplet("1 2 3"), Some([1.0, 2.0, 3.0]));
        assert_eq!(parse_triplet("1,2"), None);
        assert_eq!(
            ExecutionProvider::parse("cuda"),
            Some(ExecutionProvider::Cuda)
        );
        assert_eq!(ExecutionProvider::parse("gpu"), None);
    }
}
