//! What the `leangate` CLI tests share: the binary, and one eval run read back as its JSON.

use std::path::Path;
use std::process::Command;

/// The `leangate` binary built with these tests (no `LEANGATE_MODEL` from the environment).
pub fn leangate() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_leangate"));
    c.env_remove("LEANGATE_MODEL");
    c
}

/// Run `leangate eval --sequence SEQ EXTRA... --json OUT`, check that it succeeded, and return
/// the parsed report.
pub fn eval_json(seq: &Path, extra: &[&str]) -> serde_json::Value {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("eval.json");
    let out = leangate()
        .args(["eval", "--sequence"])
        .arg(seq)
        .args(extra)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "leangate eval --sequence {}: {}",
        seq.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap()
}
