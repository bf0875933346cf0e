//! Where the test fixtures and the shared development data are, for the tests of both crates of
//! the workspace (`tests/common` of the plugin, `tools/tests` include this file by path).

use std::path::{Path, PathBuf};

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

/// A directory for GST_PLUGIN_PATH holding only `libgstleangate.so`, linked to the cdylib built
/// with this test binary. The test binary lives in target/<profile>/deps, next to that cdylib;
/// `cargo test` rebuilds it there but only `cargo build` copies it up to target/<profile>, so
/// the copy there may be stale. (Pointing GST_PLUGIN_PATH at deps/ itself would make GStreamer
/// scan every shared object in it.)
pub fn plugin_dir() -> tempfile::TempDir {
    let exe = std::env::current_exe().expect("current_exe");
    let deps = exe.parent().expect("test binary in target/<profile>/deps");
    let candidates = [
        deps.join("libgstleangate.so"),
        deps.parent().unwrap().join("libgstleangate.so"),
    ];
    let lib = candidates
        .iter()
        .find(|p| p.exists())
        .unwrap_or_else(|| panic!("no libgstleangate.so in {candidates:?} (cargo build)"));
    let dir = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink(lib, dir.path().join("libgstleangate.so")).unwrap();
    dir
}

/// Two files in `dir` named like videos that are not: 64 KiB of pseudo-random bytes, and an empty
/// file (typefind fails on both).
pub fn not_videos(dir: &Path) -> [PathBuf; 2] {
    let noise = dir.join("noise.mp4");
    let bytes: Vec<u8> = (0..65536u32)
        .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
        .collect();
    std::fs::write(&noise, bytes).unwrap();
    let empty = dir.join("empty.mp4");
    std::fs::write(&empty, b"").unwrap();
    [noise, empty]
}

/// Width and height of a baseline or progressive JPEG (from its SOF marker), None when `bytes`
/// is not a JPEG with one.
pub fn jpeg_size(bytes: &[u8]) -> Option<(u32, u32)> {
    if bytes.get(..2)? != [0xFF, 0xD8] {
        return None;
    }
    let mut i = 2;
    while i + 9 < bytes.len() {
        if bytes[i] != 0xFF {
            return None;
        }
        let marker = bytes[i + 1];
        let len = u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]) as usize;
        if matches!(marker, 0xC0..=0xC3) {
            let h = u16::from_be_bytes([bytes[i + 5], bytes[i + 6]]) as u32;
            let w = u16::from_be_bytes([bytes[i + 7], bytes[i + 8]]) as u32;
            return Some((w, h));
        }
        i += 2 + len;
    }
    None
}

/// Width and height of a PNG (from its IHDR chunk), None when `bytes` is not a PNG.
pub fn png_size(bytes: &[u8]) -> Option<(u32, u32)> {
    if bytes.get(..8)? != b"\x89PNG\r\n\x1a\n" || bytes.get(12..16)? != b"IHDR" {
        return None;
    }
    let w = u32::from_be_bytes(bytes.get(16..20)?.try_into().ok()?);
    let h = u32::from_be_bytes(bytes.get(20..24)?.try_into().ok()?);
    Some((w, h))
}
