//! `python -m training.quantize --fuse-relu-only DIR` (the Conv+ReLU Q/DQ fusion of an INT8 build,
//! in place) on the shipped INT8 build copied aside: idempotent, and hostile input (a missing
//! model, a file that is not ONNX) is one line naming the file, with neither model rewritten.
//! Runs `.venv/bin/python` (the fusion needs onnx alone); skips with a message when that venv is
//! absent.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

#[path = "common/refusal.rs"]
mod refusal;
use refusal::assert_refused;

const BUILD: [&str; 2] = ["leangate-s-int8-encoder.onnx", "leangate-s-int8-head.onnx"];

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn fuse(python: &Path, dir: &Path) -> Output {
    Command::new(python)
        .current_dir(repo())
        .args(["-m", "training.quantize", "--fuse-relu-only"])
        .arg(dir)
        .output()
        .unwrap()
}

fn files(dir: &Path) -> Vec<Option<Vec<u8>>> {
    BUILD
        .iter()
        .map(|f| std::fs::read(dir.join(f)).ok())
        .collect()
}

/// A refusal: non-zero, no traceback, the last line naming `needle`, and the folder as it was.
fn refused(python: &Path, dir: &Path, needle: &str) {
    let before = files(dir);
    let err = assert_refused(&fuse(python, dir), &dir.display().to_string(), needle);
    assert!(files(dir) == before, "{} rewritten: {err}", dir.display());
    let left: Vec<_> = std::fs::read_dir(dir)
        .map(|d| d.map(|e| e.unwrap().file_name()).collect())
        .unwrap_or_default();
    assert!(
        left.iter()
            .all(|n| !n.to_string_lossy().ends_with(".partial")),
        "{left:?}"
    );
}

#[test]
fn fuse_relu_only_is_idempotent_and_refuses_bad_builds_without_rewriting_either_model() {
    let python = repo().join(".venv/bin/python");
    if !python.exists() {
        eprintln!("SKIPPED: {} missing (run `make setup`)", python.display());
        return;
    }
    let models = repo().join("models");
    let tmp = tempfile::tempdir().unwrap();
    let copy = |name: &str| {
        let d = tmp.path().join(name);
        std::fs::create_dir_all(&d).unwrap();
        for f in BUILD {
            std::fs::copy(models.join(f), d.join(f)).unwrap();
        }
        d
    };

    // Fused once (pairs dropped), then again: nothing more to drop, the same bytes.
    let ok = copy("ok");
    let out = fuse(&python, &ok);
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!said.contains(": 0 Q/DQ pairs dropped"), "{said}");
    let fused = files(&ok);
    assert!(fused != files(&models), "nothing fused: {said}");
    let out = fuse(&python, &ok);
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    assert_eq!(said.matches(": 0 Q/DQ pairs dropped").count(), 2, "{said}");
    assert!(files(&ok) == fused, "a second fusion changed the build");

    // The head missing: the encoder is not rewritten before that is found.
    let half = copy("half");
    std::fs::remove_file(half.join(BUILD[1])).unwrap();
    refused(&python, &half, "leangate-s-int8-head.onnx is missing");
    // Not ONNX (either one): named, the other model untouched.
    for junk in BUILD {
        let d = copy(&format!("junk-{junk}"));
        std::fs::write(d.join(junk), "not a model").unwrap();
        refused(&python, &d, &format!("{junk}: not a readable ONNX model"));
    }
    // No such folder.
    refused(&python, &tmp.path().join("nowhere"), "nowhere");
}

/// `python -m training.quantize --head-only` (after `training.experiments.finetune`: keep an INT8 encoder,
/// quantize the head alone) refuses what it cannot use before anything is written: no such INT8
/// encoder, a file that is not ONNX, an FP32 encoder given as the INT8 one, a folder without the
/// calibrated FP32 student. One line naming it, no traceback, the output folder not created.
#[test]
fn head_only_refuses_an_unusable_int8_encoder_before_writing_anything() {
    let python = repo().join(".venv/bin/python");
    if !python.exists() {
        eprintln!("SKIPPED: {} missing (run `make setup`)", python.display());
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let junk = tmp.path().join("junk.onnx");
    std::fs::write(&junk, "not a model").unwrap();
    let models = repo().join("models");
    let fp32 = models.join("leangate-s-encoder.onnx");
    let missing = tmp.path().join("missing.onnx");
    let cases: [(&Path, &Path, &str); 4] = [
        (&models, &missing, "missing.onnx: no such file"),
        (&models, &junk, "junk.onnx: not an ONNX model"),
        (&models, &fp32, "not an INT8 encoder"),
        (tmp.path(), &fp32, "leangate-s-encoder.onnx: no such file"),
    ];
    for (k, (from, int8, needle)) in cases.into_iter().enumerate() {
        let out_dir = tmp.path().join(format!("out{k}"));
        let out = Command::new(&python)
            .current_dir(repo())
            .args(["-m", "training.quantize", "--head-only", "--models"])
            .arg(from)
            .arg("--out-dir")
            .arg(&out_dir)
            .arg("--int8-encoder")
            .arg(int8)
            .output()
            .unwrap();
        assert_refused(&out, &format!("case {k}"), needle);
        assert!(!out_dir.exists(), "case {k}: {} created", out_dir.display());
    }
}
