//! ONNX Runtime sessions and execution providers.

use std::fmt;
use std::path::{Path, PathBuf};

use ort::ep;
use ort::session::Session;

use super::{ExecutionProvider, ScorerError, ScorerOptions};

/// What a session is built from. A file is loaded by ONNX Runtime from its path, so that a model
/// with external data (`.onnx` + `.onnx.data`) finds that data next to it whatever the working
/// directory.
#[derive(Debug, Clone, Copy)]
pub(super) enum Input<'a> {
    File(&'a Path),
    Memory(&'a [u8]),
}

pub(super) enum BuildError {
    Parse(String),
    Provider(String),
}

/// Clear errors for a path that cannot be a model, before ONNX Runtime sees it.
pub(super) fn check_model_file(p: &Path) -> Result<(), ScorerError> {
    let err = |reason: String| ScorerError::Read {
        path: p.display().to_string(),
        reason,
    };
    if p.as_os_str().is_empty() {
        return Err(err("no path given".into()));
    }
    let md = std::fs::metadata(p).map_err(|e| err(e.to_string()))?;
    if md.is_dir() {
        return Err(err("it is a directory".into()));
    }
    // Opening a FIFO blocks until something writes to it, and a device reads as endless or empty
    // bytes: only a regular file (or a link to one) can be a model.
    if !md.is_file() {
        return Err(err(
            "it is not a regular file (a FIFO, a device or a socket)".into(),
        ));
    }
    // Readable? (ONNX Runtime's own message for an unreadable file is less clear.)
    std::fs::File::open(p).map_err(|e| err(e.to_string()))?;
    if md.len() == 0 {
        return Err(err("the file is empty".into()));
    }
    Ok(())
}

/// The providers to try, in order.
pub(super) fn provider_order(choice: ExecutionProvider) -> &'static [ExecutionProvider] {
    match choice {
        ExecutionProvider::Auto => &[
            ExecutionProvider::TensorRt,
            ExecutionProvider::Cuda,
            ExecutionProvider::Cpu,
        ],
        ExecutionProvider::Cpu => &[ExecutionProvider::Cpu],
        ExecutionProvider::Cuda => &[ExecutionProvider::Cuda],
        ExecutionProvider::TensorRt => &[ExecutionProvider::TensorRt],
    }
}

pub(super) fn build_session(
    env: &ort::environment::Environment,
    input: Input<'_>,
    provider: ExecutionProvider,
    opts: &ScorerOptions,
) -> Result<Session, BuildError> {
    let parse = |e: &dyn fmt::Display| BuildError::Parse(e.to_string());
    let mut b = Session::builder(env).map_err(|e| parse(&e))?;
    b = b
        .with_intra_op_spinning(opts.spinning)
        .map_err(|e| parse(&e))?;
    b = b
        .with_inter_op_spinning(opts.spinning)
        .map_err(|e| parse(&e))?;
    b = b.with_inter_threads(1).map_err(|e| parse(&e))?;
    b = b
        .with_intra_threads(opts.effective_threads())
        .map_err(|e| parse(&e))?;
    let dispatch = match provider {
        ExecutionProvider::Cpu | ExecutionProvider::Auto => None,
        ExecutionProvider::Cuda => Some(
            ep::CUDA::default()
                .with_device_id(opts.device_id)
                .build()
                .error_on_failure(),
        ),
        ExecutionProvider::TensorRt => {
            // Asked first, so that a CPU-only ONNX Runtime (where `auto` tries TensorRT and
            // moves on) never creates the engine cache folder in the user's HOME.
            use ort::ep::ExecutionProvider as _;
            if !ep::TensorRT::is_available().unwrap_or(false) {
                return Err(BuildError::Provider(
                    "this ONNX Runtime library was built without the TensorRT execution provider"
                        .into(),
                ));
            }
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
    let committed = match input {
        Input::File(p) => b.commit_from_file(p),
        Input::Memory(bytes) => b.commit_from_memory(bytes),
    };
    committed.map_err(|e| {
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
