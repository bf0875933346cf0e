fn main() {
    gst_plugin_version_helper::info();
    rerun_on_new_commit();
    // Bake the project-local ONNX Runtime path (installed by `make setup`) into the plugin, so it is
    // found without ORT_DYLIB_PATH. Runtime order: $ORT_DYLIB_PATH, this baked path, the system loader.
    println!("cargo:rerun-if-env-changed=LEANGATE_ORT_LIB");
    let baked = std::env::var("LEANGATE_ORT_LIB").unwrap_or_else(|_| {
        let dir = std::env::var("CARGO_MANIFEST_DIR").unwrap();
        format!("{dir}/.deps/onnxruntime/libonnxruntime.so")
    });
    println!("cargo:rustc-env=LEANGATE_BAKED_ORT_LIB={baked}");
}

/// The version helper bakes the checkout's commit into the plugin (gst-inspect-1.0 shows it),
/// but a build script that names what it depends on is re-run only when those change: name the
/// files that move with HEAD, so a new commit is not shown as the old one. Nothing to name
/// outside a git checkout (a release tarball).
fn rerun_on_new_commit() {
    let git = std::path::Path::new(&std::env::var("CARGO_MANIFEST_DIR").unwrap()).join(".git");
    if !git.is_dir() {
        return;
    }
    let head = git.join("HEAD");
    let mut watch = vec![head.clone(), git.join("packed-refs")];
    if let Ok(text) = std::fs::read_to_string(&head) {
        if let Some(r) = text.trim().strip_prefix("ref: ") {
            watch.push(git.join(r));
        }
    }
    // Only files that exist: cargo re-runs a script on every build for a missing one.
    for f in watch.iter().filter(|f| f.exists()) {
        println!("cargo:rerun-if-changed={}", f.display());
    }
}
