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

use std::fmt;
use std::path::PathBuf;

use ort::session::Session;
use ort::value::TensorRef;

use crate::preprocess::{try_zeroed, TensorSpec};
use crate::runtime;

mod contract;
mod head;
mod session;

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
        /// How the head is named in messages.
        head_name: String,
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

impl Scorer {
    /// Load and validate a model (pair, or the encoder of a split model with its head), then
    /// prove it with one dry run on a blank frame: a model that loads but cannot score (a fixed
    /// batch of 2, a head that does not fit its encoder, NaN out) is a start error, not a
    /// failure on every frame.
    pub fn load(source: &ModelSource, opts: &ScorerOptions) -> Result<Scorer, ScorerError> {
        let model = source.describe();
        let input = match source {
            ModelSource::File(p) => {
                session::check_model_file(p)?;
                Input::File(p)
            }
            ModelSource::Memory { bytes, .. } => Input::Memory(bytes),
        };
        let (env, _) = runtime::environment()?;

        let mut warnings = Vec::new();
        let mut last_err = None;
        for &provider in session::provider_order(opts.execution_provider) {
            match build_session(&env, input, provider, opts) {
                Ok(session) => {
                    let (kind, info) =
                        Self::assemble(source, &env, session, provider, opts, &model)?;
                    let mut scorer = Scorer {
                        kind,
                        info,
                        provider: provider.as_str(),
                        warnings,
                    };
                    scorer.dry_run(&model)?;
                    return Ok(scorer);
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
    fn assemble(
        source: &ModelSource,
        env: &ort::environment::Environment,
        session: Session,
        provider: ExecutionProvider,
        opts: &ScorerOptions,
        model: &str,
    ) -> Result<(Kind, ModelInfo), ScorerError> {
        match contract::model_kind(&session, model)? {
            "pair" => {
                let info = contract::validate_pair(&session, model)?;
                Ok((Kind::Pair(session), info))
            }
            "encoder" => {
                let (info, features) = contract::validate_encoder(&session, model)?;
                let (head_name, head_path);
                let head_input = match source {
                    ModelSource::Memory {
                        name,
                        head: Some(h),
                        ..
                    } => {
                        head_name = format!("embedded model `{name}` (head)");
                        Input::Memory(h)
                    }
                    ModelSource::Memory { .. } => {
                        return Err(ScorerError::Contract {
                            model: model.to_string(),
                            reason: "an embedded split encoder without its head".into(),
                        })
                    }
                    ModelSource::File(p) => {
                        head_path = contract::head_path(p, &session, model)?;
                        session::check_model_file(&head_path)?;
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
                Ok((
                    Kind::Split {
                        encoder: session,
                        head,
                        head_name,
                        reference: None,
                        current: None,
                        encoder_runs: 0,
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
        let spec = self.info.spec.clone();
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
        if let Kind::Split { encoder_runs, .. } = &mut self.kind {
            *encoder_runs = 0;
        }
        let with = match &self.kind {
            Kind::Split { head_name, .. } => format!(" (with its head {head_name})"),
            Kind::Pair(_) => String::new(),
        };
        r.map(|_| ()).map_err(|e| ScorerError::Contract {
            model: model.to_string(),
            reason: format!("a dry run on a blank frame{with} failed: {e}"),
        })
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
                ..
            } => {
                if ref_feat.is_none() {
                    *ref_feat = Some(encode(encoder, shape, reference)?);
                    *encoder_runs += 1;
                }
                let cf = encode(encoder, shape, current)?;
                *encoder_runs += 1;
                let rf = ref_feat.as_ref().expect("encoded above");
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
    fn provider_names() {
        assert_eq!(
            ExecutionProvider::parse("cuda"),
            Some(ExecutionProvider::Cuda)
        );
        assert_eq!(ExecutionProvider::parse("gpu"), None);
    }
}
