fn main() {
    gst_plugin_version_helper::info();
    // Bake the project-local ONNX Runtime path (installed by `make setup`) into the plugin, so it is
    // found without ORT_DYLIB_PATH. Runtime order: $ORT_DYLIB_PATH, this baked path, the system loader.
    println!("cargo:rerun-if-env-changed=LEANGATE_ORT_LIB");
    let baked = std::env::var("LEANGATE_ORT_LIB").unwrap_or_else(|_| {
        let dir = std::env::var("CARGO_MANIFEST_DIR").unwrap();
        format!("{dir}/.deps/onnxruntime/libonnxruntime.so")
    });
    println!("cargo:rustc-env=LEANGATE_BAKED_ORT_LIB={baked}");
}
