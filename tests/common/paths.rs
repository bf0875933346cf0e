//! Where the test fixtures and the shared development data are, for the tests of both crates of
//! the workspace (`tests/common` of the plugin, `tools/tests` include this file by path).

use std::path::PathBuf;

/// The repository root (the plugin crate's directory) from either crate of the workspace.
fn repo_root() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    if dir.join("tests/fixtures").is_dir() {
        dir
    } else {
        dir.parent().map(PathBuf::from).unwrap_or(dir)
    }
}

/// A fixture model of `tests/fixtures/` (made by `make fixtures`).
pub fn fixture(name: &str) -> String {
    let p = repo_root().join("tests/fixtures").join(name);
    assert!(
        p.exists(),
        "fixture {} missing: run `make fixtures`",
        p.display()
    );
    p.display().to_string()
}

/// `../shared/data/<rel>` beside the checkout, or None (with a message) when absent.
pub fn shared_data(rel: &str) -> Option<PathBuf> {
    let p = repo_root().join("../shared/data").join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!(
            "SKIPPED: {} is absent (the shared development data lives beside the checkout)",
            p.display()
        );
        None
    }
}
