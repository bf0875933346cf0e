//! Finding and loading ONNX Runtime (`libonnxruntime.so`), once per process.
//!
//! Search order: `$ORT_DYLIB_PATH` (alone, when set), else the copy `make install` puts beside the
//! loaded plugin or binary (`../leangate/` from `$PREFIX/lib/gstreamer-1.0/libgstleangate.so`,
//! `../lib/leangate/` from `$PREFIX/bin/leangate`; symlinks resolved), then the path baked in at
//! build time (the project-local copy that `make setup` extracts from the `onnxruntime==1.31.1`
//! wheel), then the system loader (`libonnxruntime.so.1`, `libonnxruntime.so`). No ort API may be touched before this succeeds: ort
//! would otherwise try its own default and panic.

use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
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
    let mut v: Vec<(String, PathBuf)> = module_path()
        .map(|m| installed_candidates(&m))
        .unwrap_or_default()
        .into_iter()
        .map(|p| (format!("beside the installed plugin {}", p.display()), p))
        .collect();
    v.push((
        format!("built-in path {BAKED_ORT_LIB}"),
        PathBuf::from(BAKED_ORT_LIB),
    ));
    for name in ["libonnxruntime.so.1", "libonnxruntime.so"] {
        v.push((format!("system loader ({name})"), PathBuf::from(name)));
    }
    v
}

/// Where `make install` puts ONNX Runtime relative to the loaded module `module` (the plugin in
/// `$PREFIX/lib/gstreamer-1.0/`, or the `leangate` binary in `$PREFIX/bin/`): `$PREFIX/lib/leangate/`.
pub fn installed_candidates(module: &Path) -> Vec<PathBuf> {
    let Some(up) = module.parent().and_then(Path::parent) else {
        return Vec::new();
    };
    ["leangate", "lib/leangate"]
        .iter()
        .map(|rel| up.join(rel).join("libonnxruntime.so"))
        .collect()
}

/// The file this code was loaded from (the plugin `libgstleangate.so`, or the executable it is
/// linked into), symlinks resolved: `dladdr` on one of its own functions.
pub fn module_path() -> Option<PathBuf> {
    let mut info = std::mem::MaybeUninit::<libc::Dl_info>::zeroed();
    let addr = module_path as fn() -> Option<PathBuf> as *const libc::c_void;
    // SAFETY: `addr` is an address in this module and `info` is a valid place for the answer.
    let found = unsafe { libc::dladdr(addr, info.as_mut_ptr()) };
    if found == 0 {
        return None;
    }
    // SAFETY: dladdr succeeded, so `info` is filled; `dli_fname` is null or a C string.
    let fname = unsafe { info.assume_init().dli_fname };
    if fname.is_null() {
        return None;
    }
    // SAFETY: non-null, NUL-terminated, owned by the dynamic loader for the module's lifetime.
    let name = unsafe { std::ffi::CStr::from_ptr(fname) };
    let path = PathBuf::from(std::ffi::OsStr::from_bytes(name.to_bytes()));
    std::fs::canonicalize(&path).ok().or(Some(path))
}

/// Microsoft's builds of ONNX Runtime (the PyPI wheels LeanGate loads) start a telemetry system
/// with the first environment: a persistent device id and a queue of usage events under
/// `~/.cache/Microsoft/DeveloperTools/.onnxruntime/`, to be sent to Microsoft. The API's
/// `DisableTelemetryEvents` (ort's `with_telemetry(false)`, also set) comes too late to stop
/// those files; the library's own switch, `ORT_DISABLE_TELEMETRY=1` in the environment before
/// the library is loaded, stops all of it. It is set here, once, before the library is loaded,
/// unless the process already has a value of its own (a user's explicit choice is kept).
fn no_telemetry() {
    if std::env::var_os(NO_TELEMETRY_VAR).is_none() {
        // Once per process, before ONNX Runtime exists; GStreamer reads no such variable.
        std::env::set_var(NO_TELEMETRY_VAR, "1");
    }
}

/// ONNX Runtime's telemetry switch (see [`no_telemetry`]).
pub const NO_TELEMETRY_VAR: &str = "ORT_DISABLE_TELEMETRY";

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
    no_telemetry();
    for (what, path) in candidates() {
        if path.is_absolute() && !path.exists() {
            attempts.push((what, "no such file".to_string()));
            continue;
        }
        match ort::init_from(&path) {
            Ok(builder) => match builder
                .with_name("leangate")
                // Microsoft's builds of ONNX Runtime record usage events (and a persistent device
                // id under ~/.cache/Microsoft) unless told not to; LeanGate sends nothing home.
                .with_telemetry(false)
                .build()
            {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_installed_library_is_looked_up_beside_the_loaded_module() {
        // In a test, the module is the test executable itself.
        let exe = std::fs::canonicalize(std::env::current_exe().unwrap()).unwrap();
        assert_eq!(module_path().as_deref(), Some(exe.as_path()));
        let plugin = Path::new("/opt/lg/lib/gstreamer-1.0/libgstleangate.so");
        let cli = Path::new("/opt/lg/bin/leangate");
        let lib = Path::new("/opt/lg/lib/leangate/libonnxruntime.so");
        assert!(installed_candidates(plugin).iter().any(|p| p == lib));
        assert!(installed_candidates(cli).iter().any(|p| p == lib));
    }
}
