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
/// files that move with HEAD, so a new commit is not shown as the old one. Git says where they
/// are, as the helper asks git for the commit: `.git` is a folder in a plain checkout, a file
/// naming the real one in a `git worktree` or a submodule, and the branches live in the common
/// folder (loose, in `packed-refs`, or in a reftable). Nothing to name outside a git checkout (a
/// release tarball, or no git installed).
fn rerun_on_new_commit() {
    use std::path::PathBuf;
    let dir = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").unwrap());
    let out = std::process::Command::new("git")
        .arg("-C")
        .arg(&dir)
        .args(["rev-parse", "--git-dir", "--git-common-dir"])
        .output();
    let Some(out) = out.ok().filter(|o| o.status.success()) else {
        return;
    };
    let text = String::from_utf8_lossy(&out.stdout);
    // Relative to `dir` (an absolute path stays as it is).
    let mut lines = text.lines().map(|l| dir.join(l));
    let (Some(git), Some(common)) = (lines.next(), lines.next()) else {
        return;
    };
    let head = git.join("HEAD");
    let mut watch = vec![
        head.clone(),
        common.join("packed-refs"),
        common.join("reftable").join("tables.list"),
    ];
    if let Ok(text) = std::fs::read_to_string(&head) {
        if let Some(r) = text.trim().strip_prefix("ref: ") {
            // A branch: its loose ref file, in the common folder.
            let loose = common.join(r);
            // A branch only in packed-refs gets its loose file back at its next commit: watch
            // the folder it appears in (cargo scans a folder for changes).
            match loose.parent() {
                Some(parent) if !loose.exists() => watch.push(parent.to_path_buf()),
                _ => watch.push(loose),
            }
        }
    }
    // Only paths that exist: cargo re-runs a script on every build for a missing one. A branch
    // packed later loses its loose file, which cargo sees as a change, and the script runs again.
    for f in watch.iter().filter(|f| f.exists()) {
        println!("cargo:rerun-if-changed={}", f.display());
    }
}
