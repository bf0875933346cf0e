//! Finding and loading ONNX Runtime (`libonnxruntime.so`), once per process.
//!
//! Search order: `$ORT_DYLIB_PATH` (alone, when set), else the path baked in at build time (the project-local copy that
//! `make setup` extracts from the `onnxruntime==1.31.1` wheel), then the system loader
//! (`libonnxruntime.so.1`, `libonnxruntime.so`). No ort API may be touched before this succeeds: ort
//! would otherwise try its own default and panic.

use std::path::PathBuf;
use std::sync::Mutex;

/// The path baked in by build.rs.
pub const BAKED_ORT_LIB: &str = env!("LEANGATE_BAKED_ORT_LIB");

/// Why ONNX Runtime could not be loaded: every attempt, with its reason.
#[derive(Debug, Clone, thiserror::Error)]
#[error(
    "ONNX Runtime (libonnxruntime.so, version 1.31) could not be loaded. Tried: {}. Install it \
     with `make setup` (extracts libonnxruntime.so.1.31.1 from the PyPI wheel \
     onnxruntime==1.31.1, or onnxruntime-gpu==1.31.1 for CUDA), or point ORT_DYLIB_PATH at a \
     libonnxruntime.so of version 1.31 or newer",
    attempts_text(.attempts)
)]
pub struct RuntimeError {
    pub attempts: Vec<(String, String)>,
}

fn attempts_text(attempts: &[(String, String)]) -> String {
    attempts
        .iter()
        .map(|(what, why)| format!("{what}: {why}"))
        .collect::<Vec<_>>()
        .join("; ")
}

static ENV: Mutex<Option<(ort::environment::Environment, String)>> = Mutex::new(None);

/// Candidate library paths, in search order, each with a description. An explicit
/// `$ORT_DYLIB_PATH` is the only candidate: a wrong explicit path is an error, not a silent
/// fallback to another library.
pub fn candidates() -> Vec<(String, PathBuf)> {
    match std::env::var("ORT_DYLIB_PATH") {
        Ok(p) if !p.is_empty() => {
            return vec![(format!("ORT_DYLIB_PATH={p}"), PathBuf::from(p))];
        }
        _ => {}
    }
    let mut v = vec![(
        format!("built-in path {BAKED_ORT_LIB}"),
        PathBuf::from(BAKED_ORT_LIB),
    )];
    for name in ["libonnxruntime.so.1", "libonnxruntime.so"] {
        v.push((format!("system loader ({name})"), PathBuf::from(name)));
    }
    v
}

/// The process-wide ort environment, loading the library on first use. Returns the environment and
/// the path it was loaded from. A failure is not cached: a later call tries again.
pub fn environment() -> Result<(ort::environment::Environment, String), RuntimeError> {
    let mut guard = ENV.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(env) = guard.as_ref() {
        return Ok(env.clone());
    }
    let mut attempts = Vec::new();
    if std::env::var_os("ORT_DYLIB_PATH").is_none_or(|v| v.is_empty()) {
        attempts.push(("ORT_DYLIB_PATH".to_string(), "not set".to_string()));
    }
    for (what, path) in candidates() {
        if path.is_absolute() && !path.exists() {
            attempts.push((what, "no such file".to_string()));
            continue;
        }
        match ort::init_from(&path) {
            Ok(builder) => match builder.with_name("leangate").build() {
                Ok(env) => {
                    let loaded = (env, path.display().to_string());
                    *guard = Some(loaded.clone());
                    return Ok(loaded);
                }
                Err(e) => attempts.push((what, e.to_string())),
            },
            Err(e) => attempts.push((what, e.to_string())),
        }
    }
    Err(RuntimeError { attempts })
}
