//! The reconstruction consumer (`pipelines/reconstruct.py`, COLMAP through pycolmap) and
//! `leangate eval --reconstruct`, run for real on the shared 7-Scenes kitchen (60 frames) and a
//! short real clip. Needs pycolmap in the interpreter eval would use (`make setup` installs it
//! into `.venv-sfm`), and the plugin built beside this test (`cargo build --workspace`); each
//! test says SKIPPED when something it needs is absent.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use leangate_tools::eval::reconstruct::{find_python, repo_root};

#[path = "../../tests/common/paths.rs"]
#[allow(dead_code)]
mod paths;
use paths::shared_data;

/// The interpreter `eval --reconstruct` finds, when it imports pycolmap and gi.
fn sfm_python() -> Option<PathBuf> {
    let py = find_python(None);
    let ok = Command::new(&py)
        .args([
            "-c",
            "import pycolmap, gi; gi.require_version('Gst', '1.0'); from gi.repository import Gst",
        ])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if ok {
        Some(py)
    } else {
        eprintln!(
            "SKIPPED: {} cannot import pycolmap and gi (run `make setup`: it makes .venv-sfm)",
            py.display()
        );
        None
    }
}

/// The directory of the libgstleangate.so built with this test (target/<profile>).
fn plugin_dir() -> Option<PathBuf> {
    let exe = std::env::current_exe().unwrap();
    let profile = exe.parent()?.parent()?.to_path_buf();
    if profile.join("libgstleangate.so").exists() {
        Some(profile)
    } else {
        eprintln!(
            "SKIPPED: no libgstleangate.so in {} (cargo build --workspace)",
            profile.display()
        );
        None
    }
}

/// Asserts that a run left nothing in its own `TMPDIR` (COLMAP's glog wrote its log files there,
/// or in /tmp, until it was told to log to stderr).
fn assert_tmpdir_untouched(tmp: &Path, what: &str) {
    let left: Vec<_> = std::fs::read_dir(tmp)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(left.is_empty(), "{what} left {left:?} in its TMPDIR");
}

fn consumer(python: &Path, args: &[&str], extra: &[&Path]) -> Output {
    let tmp = tempfile::tempdir().unwrap();
    let mut c = Command::new(python);
    c.arg(repo_root().join("pipelines/reconstruct.py"))
        .args(args)
        .args(extra)
        .env_remove("LEANGATE_MODEL")
        .env("TMPDIR", tmp.path());
    let out = c.output().unwrap();
    assert_tmpdir_untouched(tmp.path(), "reconstruct.py");
    eprintln!(
        "--- {c:?}: {}\nstdout:\n{}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The consumer gating `input` through the plugin in `plugins` with `args`, its output in
/// `dir/rec` and its JSON report at the returned path (`dir/rec.json`).
fn gated(
    python: &Path,
    plugins: &Path,
    input: &Path,
    args: &[&str],
    dir: &Path,
) -> (Output, PathBuf) {
    let (out_dir, json) = (dir.join("rec"), dir.join("rec.json"));
    let mut a = args.to_vec();
    a.push("--plugin-path");
    let out = consumer(
        python,
        &a,
        &[
            plugins,
            input,
            Path::new("--out"),
            &out_dir,
            Path::new("--json"),
            &json,
        ],
    );
    (out, json)
}

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

fn summary(out: &Output) -> std::collections::HashMap<String, String> {
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.starts_with("summary: "))
        .unwrap_or_else(|| panic!("no summary line in {text}"));
    line["summary: ".len()..]
        .split_whitespace()
        .filter_map(|kv| kv.split_once('='))
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

#[test]
fn consumer_gates_an_image_sequence_and_reconstructs_the_kept_frames() {
    let (Some(seq), Some(py), Some(plugins)) = (
        shared_data("7scenes_redkitchen_dev"),
        sfm_python(),
        plugin_dir(),
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (out_dir, json, ply) = (
        dir.path().join("rec"),
        dir.path().join("rec.json"),
        dir.path().join("points.ply"),
    );
    // The embedded student keeps 1 of these 60 frames; max-gap 6 makes the gate keep enough
    // (every 7th frame at least) to reconstruct, through the real element in drop mode.
    let out = consumer(
        &py,
        &["--max-gap", "6", "-v", "--plugin-path"],
        &[
            &plugins,
            &seq,
            Path::new("--out"),
            &out_dir,
            Path::new("--json"),
            &json,
            Path::new("--ply"),
            &ply,
        ],
    );
    assert!(out.status.success());
    let s = summary(&out);
    assert_eq!(s["frames-in"], "60");
    let kept: usize = s["kept"].parse().unwrap();
    assert!((9..=60).contains(&kept), "{s:?}");
    assert_eq!(s["registered"], format!("{kept}/{kept}"), "{s:?}");
    assert_eq!(s["models"], "1");
    assert_eq!(
        s["camera"], "PINHOLE",
        "intrinsics.txt gives a PINHOLE camera"
    );
    // Progress is logged on stderr.
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("kept frame 0 (first"), "{err}");
    assert!(err.contains("mapping:"), "{err}");

    let v = read_json(&json);
    assert_eq!(v["kind"], "sequence");
    assert_eq!(v["frames_in"], 60);
    assert_eq!(v["registered"], kept);
    assert_eq!(v["models"], 1);
    let ate = v["ate_rmse_cm"].as_f64().expect("ground truth: an ATE");
    assert!(ate.is_finite() && ate < 3.0, "ATE {ate} cm");
    let reproj = v["mean_reprojection_error_px"].as_f64().unwrap();
    assert!(reproj > 0.0 && reproj < 2.0, "{reproj}");
    assert!(v["points3D"].as_u64().unwrap() > 300);
    // The gate's meta came with every frame, in stream order, kept, with max-gap respected.
    let gate = v["gate"].as_array().unwrap();
    assert_eq!(gate.len(), kept);
    let idx: Vec<u64> = gate.iter().map(|m| m["frame"].as_u64().unwrap()).collect();
    assert_eq!(idx[0], 0);
    assert!(
        idx.windows(2).all(|w| w[0] < w[1] && w[1] - w[0] <= 7),
        "{idx:?}"
    );
    assert!(gate.iter().all(|m| m["keep"] == true));
    assert_eq!(gate[0]["reason"], "first");
    let frames = v["frames"].as_array().unwrap();
    assert!(frames
        .iter()
        .all(|f| f["registered"] == true && f["center"].as_array().unwrap().len() == 3));
    // COLMAP sees each frame by its index (OUT/images/frame_<index>.jpg, a link to the file).
    assert_eq!(frames[1]["name"], format!("images/frame_{:06}.jpg", idx[1]));
    assert!(frames[1]["path"]
        .as_str()
        .unwrap()
        .ends_with(&format!("rgb/{:06}.jpg", idx[1])));
    // The sparse model and the PLY are on disk.
    let model = PathBuf::from(v["model_dir"].as_str().unwrap());
    for f in ["cameras.bin", "images.bin", "points3D.bin"] {
        assert!(model.join(f).exists(), "{f} in {}", model.display());
    }
    let ply_text = std::fs::read(&ply).unwrap();
    assert!(ply_text.starts_with(b"ply"));
}

/// `--sharpness-wait 2 --sharpness-lookback 4` reach the element: on the first 150 frames of
/// tum_fr1_desk (a fast sweep) keeps settle on sharper frames held (reason `sharper`), every kept
/// frame is the picture the gate chose (COLMAP gets each by its index) and the reference is never
/// lost on the way (no `first` after frame 0).
#[test]
fn consumer_passes_the_sharpness_settings_to_the_gate() {
    let (Some(seq), Some(py), Some(plugins)) =
        (shared_data("tum_fr1_desk"), sfm_python(), plugin_dir())
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (out, json) = gated(
        &py,
        &plugins,
        &seq,
        &[
            "--max-frames",
            "150",
            "--sharpness-wait",
            "2",
            "--sharpness-lookback",
            "4",
        ],
        dir.path(),
    );
    assert!(out.status.success());
    let v = read_json(&json);
    let gate = v["gate"].as_array().unwrap();
    let reasons: Vec<&str> = gate.iter().map(|m| m["reason"].as_str().unwrap()).collect();
    assert_eq!(reasons[0], "first");
    assert!(reasons.contains(&"sharper"), "{reasons:?}");
    assert!(!reasons[1..].contains(&"first"), "{reasons:?}");
    let idx: Vec<u64> = gate.iter().map(|m| m["frame"].as_u64().unwrap()).collect();
    assert!(idx.windows(2).all(|w| w[0] < w[1]), "{idx:?}");

    // --sharpness-margin reaches the element: with a margin of 1 a blurred due frame never keeps
    // (its keep waits for a sharp one), with 0 it keeps at once; the kept frames differ.
    let kept = |margin: &str| -> Vec<u64> {
        let sub = dir.path().join(format!("margin-{margin}"));
        std::fs::create_dir_all(&sub).unwrap();
        let (out, json) = gated(
            &py,
            &plugins,
            &seq,
            &["--max-frames", "150", "--sharpness-margin", margin],
            &sub,
        );
        assert!(out.status.success());
        read_json(&json)["gate"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| m["frame"].as_u64().unwrap())
            .collect()
    };
    let (none, all) = (kept("0"), kept("1"));
    assert_ne!(none, all, "the margin changed nothing: {none:?}");
}

#[test]
fn consumer_reconstructs_what_the_gate_keeps_of_a_real_clip() {
    let (Some(clip), Some(py), Some(plugins)) = (
        shared_data("cotracker_clips/cat.mp4"),
        sfm_python(),
        plugin_dir(),
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("rec");
    let (out, json) = gated(
        &py,
        &plugins,
        &clip,
        &["--max-gap", "3", "--max-frames", "8", "--threads", "1"],
        dir.path(),
    );
    assert!(out.status.success());
    let v = read_json(&json);
    assert_eq!(v["kind"], "video");
    assert_eq!(v["kept"], 8);
    assert_eq!(
        v["camera_model"], "SIMPLE_RADIAL",
        "no intrinsics: COLMAP's default"
    );
    assert!(v["ate_rmse_cm"].is_null(), "no ground truth, no ATE");
    // The kept frames were written as images and fed to COLMAP.
    let frames = v["frames"].as_array().unwrap();
    for f in frames {
        assert!(out_dir.join(f["name"].as_str().unwrap()).exists(), "{f}");
    }
    let reg = v["registered"].as_u64().unwrap();
    assert!(reg >= 5, "{reg} of 8 registered");
    // COLMAP's incremental mapper is not deterministic: on one CI run the last three frames of
    // this handheld clip formed a second model beside the five-frame one. The largest model
    // holds at least 5 of the 8 kept frames either way.
    let models = v["models"].as_u64().unwrap();
    assert!((1..=2).contains(&models), "{models} models");

    // Explicit frames of a video (what eval --reconstruct asks for): decoded, no gate.
    let json2 = dir.path().join("frames.json");
    let out = consumer(
        &py,
        &["--frames", "0,6,12,18", "--out"],
        &[&dir.path().join("rec2"), Path::new("--json"), &json2, &clip],
    );
    assert!(out.status.success());
    let v = read_json(&json2);
    assert!(v.get("gate").is_none());
    let names: Vec<&str> = v["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        [
            "images/frame_000000.png",
            "images/frame_000006.png",
            "images/frame_000012.png",
            "images/frame_000018.png"
        ]
    );
    assert!(v["registered"].as_u64().unwrap() >= 3, "{v}");
}

/// `evo_ape tum GT EST --align --correct_scale`'s RMSE (m), with the evo that `make setup`
/// installs beside the SfM interpreter.
fn evo_ape_rmse(py: &Path, gt: &Path, est: &Path) -> f64 {
    let evo = py.with_file_name("evo_ape");
    assert!(
        evo.exists(),
        "{} missing: `make setup` installs evo into .venv-sfm",
        evo.display()
    );
    // evo keeps its settings in ~/.evo, made on its first run: the tests leave HOME alone.
    let home = tempfile::tempdir().unwrap();
    let out = Command::new(&evo)
        .env("HOME", home.path())
        .arg("tum")
        .args([gt, est])
        .args(["--align", "--correct_scale", "--no_warnings"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    text.lines()
        .find_map(|l| {
            let mut it = l.split_whitespace();
            (it.next() == Some("rmse")).then(|| it.next().unwrap().parse().unwrap())
        })
        .unwrap_or_else(|| panic!("no rmse in {text}"))
}

/// The eval run on 7-Scenes with `--reconstruct`: every policy and a dense reference are
/// reconstructed, the table relates each to dense, the trajectories are what evo reads (and evo
/// measures the ATE eval does), and one policy's failure (its work directory's `images` is taken
/// by a file, so its consumer fails) is reported for that policy while the others come out.
#[test]
fn eval_reconstruct_reports_every_policy_and_a_dense_reference() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("eval.json");
    let (sfm, traj) = (dir.path().join("sfm"), dir.path().join("traj"));
    std::fs::create_dir_all(sfm.join("stride")).unwrap();
    std::fs::write(sfm.join("stride/images"), "not a directory").unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_leangate"))
        .env("TMPDIR", tmp.path())
        .args(["eval", "--sequence"])
        .arg(&seq)
        .args(["--reconstruct", "--dense-every", "6", "--sfm-dir"])
        .arg(&sfm)
        .arg("--trajectory-dir")
        .arg(&traj)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("{stdout}\n{stderr}");
    assert!(out.status.success());
    assert_tmpdir_untouched(tmp.path(), "leangate eval --reconstruct");
    assert!(stdout.contains("reconstruction (COLMAP"), "{stdout}");
    assert!(
        !stderr.contains("leangate eval:"),
        "no --progress: {stderr}"
    );
    let v = read_json(&json);
    let info = &v["reconstruction"];
    assert_eq!(info["dense_every"], 6);
    assert!(info["engine"].as_str().unwrap().contains("pycolmap"));
    let policies = v["policies"].as_object().unwrap();

    // The failed policy: its error in the JSON, the table and a warning; no panic, no trace.
    let stride = &policies["stride"];
    let err = stride["sfm_error"]
        .as_str()
        .unwrap_or_else(|| panic!("{stride}"));
    assert!(
        err.contains("images") && err.contains("is not a folder"),
        "{err}"
    );
    assert!(
        stdout.contains("stride") && stdout.contains("failed: "),
        "{stdout}"
    );
    assert!(
        stderr.contains("reconstructing policy stride failed"),
        "{stderr}"
    );
    assert!(!stderr.contains("Traceback"), "{stderr}");

    for name in leangate_tools::eval::POLICIES
        .iter()
        .copied()
        .filter(|p| *p != "stride")
        .chain(["dense"])
    {
        let p = &policies[name];
        let kept = p["kept"].as_u64().unwrap();
        let reg = p["registered"]
            .as_u64()
            .unwrap_or_else(|| panic!("{name}: {p}"));
        assert!(reg <= kept, "{name}: {p}");
        assert!(p["models"].is_u64(), "{name}: {p}");
        assert!(p.get("ate_rmse_cm").is_some(), "{name}: {p}");
        assert!(
            dir.path()
                .join("sfm")
                .join(name)
                .join("frames.txt")
                .exists(),
            "{name}"
        );
    }
    // The dense reference: 10 frames, all registered into one model, centimetre-level ATE.
    let d = &policies["dense"];
    assert_eq!(d["kept"], 10);
    assert_eq!(d["registered"], 10, "{d}");
    assert_eq!(d["models"], 1, "{d}");
    let ate = d["ate_rmse_cm"].as_f64().unwrap();
    assert!(ate.is_finite() && ate < 3.0, "dense ATE {ate} cm");
    assert!(d["sfm_reproj_px"].as_f64().unwrap() < 2.0);
    // Relative to dense: dense is 1x itself; its gate is free; COLMAP's own time is measured.
    assert_eq!(d["ate_vs_dense"], 1.0);
    assert_eq!(d["sfm_speedup"], 1.0);
    assert_eq!(d["gate_seconds"], 0.0);
    assert!(d["sfm_seconds"].as_f64().unwrap() > 0.0);
    assert!(d["sfm_wall_seconds"].as_f64().unwrap() >= d["sfm_seconds"].as_f64().unwrap());
    // The model's gate time is its pipeline's: frames / fps.
    let m = &policies["model"];
    let gate = m["gate_seconds"].as_f64().unwrap();
    let fps = m["fps"].as_f64().unwrap();
    assert!((gate - 60.0 / fps).abs() < 1e-9 * gate.max(1.0), "{m}");
    assert!(
        stdout.contains("speed-up") && stdout.contains("end-to-end"),
        "{stdout}"
    );

    // The trajectories: TUM lines (t x y z qx qy qz qw, unit quaternions), one per registered
    // frame, and evo's APE with Sim(3) alignment equals eval's ATE (evo prints 6 decimals, m).
    let text = std::fs::read_to_string(traj.join("dense.txt")).unwrap();
    let rows: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(' ').map(|x| x.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 10, "{text}");
    for r in &rows {
        assert_eq!(r.len(), 8);
        let norm: f64 = r[4..].iter().map(|q| q * q).sum();
        assert!((norm - 1.0).abs() < 1e-6, "{r:?}");
    }
    assert!(traj.join("model.txt").exists() && !traj.join("stride.txt").exists());
    let evo = evo_ape_rmse(&py, &traj.join("groundtruth.txt"), &traj.join("dense.txt"));
    assert!(
        (evo - ate / 100.0).abs() < 2e-6 + 1e-3 * evo,
        "evo {evo} m, eval {ate} cm"
    );
}

/// `eval --reconstruct` runs COLMAP for minutes: with `--progress` (standard error not a
/// terminal here) each reconstruction says its frames, each COLMAP stage and its outcome (it
/// printed one line per policy, counted as "frames"); its table has a legend under it, as the
/// eval's table has. Without `--progress`, no progress lines.
#[test]
fn eval_reconstruct_says_its_progress_and_explains_its_columns() {
    let (Some(seq), Some(_)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_leangate"))
        .env("TMPDIR", tmp.path())
        .args(["eval", "--sequence"])
        .arg(&seq)
        .args(["--reconstruct", "--dense-every", "6", "--progress"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("{stdout}\n{stderr}");
    assert!(out.status.success());
    assert_tmpdir_untouched(tmp.path(), "leangate eval --reconstruct --progress");
    let runs = leangate_tools::eval::POLICIES.len() + 1;
    for (k, name) in leangate_tools::eval::POLICIES
        .iter()
        .copied()
        .chain(["dense"])
        .enumerate()
    {
        let at = format!("leangate eval: sfm {}/{runs} {name}: ", k + 1);
        let steps: Vec<&str> = stderr
            .lines()
            .filter_map(|l| l.strip_prefix(at.as_str()))
            .collect();
        assert!(
            steps
                .first()
                .is_some_and(|s| s.ends_with(" frame") || s.ends_with(" frames")),
            "{name}: {steps:?}"
        );
        assert!(
            steps.last().is_some_and(|s| s.contains(" registered, ")),
            "{name}: {steps:?}"
        );
    }
    // The dense reference (10 frames) goes through every COLMAP stage.
    let dense: Vec<&str> = stderr
        .lines()
        .filter_map(|l| {
            l.strip_prefix(format!("leangate eval: sfm {runs}/{runs} dense: ").as_str())
        })
        .collect();
    for stage in [
        "10 frames",
        "SIFT features of 10 images",
        "exhaustive matching",
        "incremental mapping",
        "mapping: the initial pair and ",
        "10 of 10 registered, 1 model, ",
    ] {
        assert!(
            dense.iter().any(|s| s.starts_with(stage)),
            "{stage}: {dense:?}"
        );
    }
    assert!(
        stderr.contains(&format!("leangate eval: sfm {runs}/{runs} done")),
        "{stderr}"
    );
    // The legend, once, every column of the table explained.
    assert_eq!(
        stdout.matches("reconstruction columns:").count(),
        1,
        "{stdout}"
    );
    let legend = &stdout[stdout.find("reconstruction columns:").unwrap()..];
    for col in [
        "kept:",
        "registered:",
        "models:",
        "ATE cm:",
        "ATE/dns:",
        "SfM s:",
        "speed-up:",
        "gate s:",
        "end-to-end:",
    ] {
        assert!(legend.contains(col), "{col} not explained: {legend}");
    }
}

#[test]
fn explicit_frames_and_a_python_without_pycolmap() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("r.json");
    // --frames: no gate, these frames (COLMAP sees rgb/000000.jpg, ...). Repeated, the lists
    // add up (the last one alone used to win: 36, 48, 59 here).
    let out = consumer(
        &py,
        &["--frames", "0,12,24", "--frames", "36,48,59", "--out"],
        &[&dir.path().join("rec"), Path::new("--json"), &json, &seq],
    );
    assert!(out.status.success());
    let v = read_json(&json);
    assert!(v.get("gate").is_none(), "no gate with --frames");
    let idx: Vec<u64> = v["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["frame"].as_u64().unwrap())
        .collect();
    assert_eq!(idx, [0, 12, 24, 36, 48, 59]);
    assert_eq!(v["registered"], 6, "{v}");
    assert!(v["ate_rmse_cm"].as_f64().unwrap() < 3.0);

    // An out-of-range frame is a usage error (exit 2) naming it. (--out in the temporary
    // directory: the default, out/reconstruct, would be under the working directory.)
    let out = consumer(
        &py,
        &["--frames", "0,60", "--out"],
        &[&dir.path().join("range"), &seq],
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("frame 60 out of range"));

    // eval --reconstruct with an interpreter that lacks pycolmap says so, and how to fix it.
    let fake = dir.path().join("python-without-pycolmap");
    std::fs::write(
        &fake,
        "#!/bin/sh\necho \"No module named 'pycolmap'\" >&2\nexit 3\n",
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_leangate"))
        .args(["eval", "--sequence"])
        .arg(&seq)
        .args(["--reconstruct", "--sfm-python"])
        .arg(&fake)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("pycolmap is not importable") && err.contains("scripts/setup.sh"),
        "{err}"
    );
}

/// Every argument is checked before any work: a clear error naming it, exit 2, no traceback and
/// no COLMAP abort (`--overlap 0 --matcher sequential` used to SIGABRT inside COLMAP; `--every
/// -2` ran backwards, `--every 0` was ignored; the others raised Python tracebacks). So are the
/// inputs: a non-numeric timestamp in rgb.txt names the line, and a folder of images COLMAP
/// (or, gated, the decoder) cannot read is an error (it used to exit 0 with nothing
/// reconstructed).
#[test]
fn consumer_refuses_bad_arguments_and_inputs_with_a_clear_error() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("rec");
    let check = |args: &[&str], input: &Path, expect: &str| {
        let out = consumer(&py, args, &[Path::new("--out"), &out_dir, input]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains(expect),
            "{args:?}: expected {expect:?} in {err}"
        );
        assert!(
            !err.contains("Traceback") && !err.contains("SIGABRT") && !err.contains("Aborted"),
            "{args:?}: {err}"
        );
    };
    let cases: [(&[&str], &str); 14] = [
        (
            &["--sharpness-lookback", "31"],
            "argument --sharpness-lookback: must be at most 30, got 31",
        ),
        (
            &["--sharpness-margin", "nan"],
            "argument --sharpness-margin: expected a finite number, got 'nan'",
        ),
        (
            &[
                "--frames",
                "0,12,24",
                "--overlap",
                "0",
                "--matcher",
                "sequential",
            ],
            "argument --overlap: must be at least 1, got 0",
        ),
        (
            &["--frames", "a,b"],
            "argument --frames: 'a' is not a frame index",
        ),
        (&["--frames", "0,-3"], "frame -3 is negative"),
        (&["--frames", "3,7,3"], "frame 3 is listed twice"),
        (
            &["--frames", "3,7", "--frames", "12,7"],
            "argument --frames: frame 7 is listed twice",
        ),
        (&["--camera-model", "BOGUS"], "invalid choice: 'BOGUS'"),
        (
            &["--max-features", "0"],
            "argument --max-features: must be at least 1",
        ),
        (
            &["--threads", "-5"],
            "argument --threads: must be at least 1 or -1",
        ),
        (
            &["--every", "0"],
            "argument --every: must be at least 1, got 0",
        ),
        (
            &["--every", "-2"],
            "argument --every: must be at least 1, got -2",
        ),
        (
            &["--threshold", "nan"],
            "argument --threshold: expected a finite number",
        ),
        (
            &["--every", "10", "--intrinsics", "500,500,320"],
            "expected FX,FY,CX,CY",
        ),
    ];
    for (args, expect) in cases {
        check(args, &seq, expect);
    }
    // --frames @FILE: the file and line of a bad entry.
    let list = dir.path().join("frames.txt");
    std::fs::write(&list, "0\n12 rgb/000012.jpg\nx\n").unwrap();
    let arg = format!("@{}", list.display());
    check(
        &["--frames", &arg],
        &seq,
        "frames.txt line 3: 'x' is not a frame index",
    );

    // A non-numeric timestamp in rgb.txt.
    let bad_ts = dir.path().join("bad_ts");
    std::fs::create_dir(&bad_ts).unwrap();
    std::os::unix::fs::symlink(seq.join("rgb"), bad_ts.join("rgb")).unwrap();
    std::fs::write(
        bad_ts.join("rgb.txt"),
        "# t path\n0.0 rgb/000000.jpg\nnoon rgb/000012.jpg\n",
    )
    .unwrap();
    check(
        &["--every", "1"],
        &bad_ts,
        "rgb.txt line 3: expected `timestamp path` with a numeric timestamp, got 'noon",
    );

    // A folder of files named .png that are not images.
    let junk = dir.path().join("junk");
    std::fs::create_dir(&junk).unwrap();
    for i in 0..3 {
        std::fs::write(junk.join(format!("{i}.png")), vec![i as u8; 500]).unwrap();
    }
    check(
        &["--every", "1"],
        &junk,
        "COLMAP could read 0 of 3 images (not an image, or corrupt:",
    );
    // The same through the gate: the decoder skips each file with a warning, nothing comes out.
    if let Some(plugins) = plugin_dir() {
        check(
            &["--plugin-path", plugins.to_str().unwrap()],
            &junk,
            "could be decoded (the first: ",
        );
    }
}

/// A TUM-layout rgb.txt that lists one image twice (a pause written by repeating a frame) used
/// to abort the whole run (SQLite constraint: two images of one name). COLMAP now sees each
/// frame by index, each file once; the repeat takes its image's pose.
#[test]
fn consumer_reconstructs_a_sequence_that_lists_an_image_twice() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("paused");
    std::fs::create_dir(&input).unwrap();
    std::os::unix::fs::symlink(seq.join("rgb"), input.join("rgb")).unwrap();
    std::fs::copy(seq.join("intrinsics.txt"), input.join("intrinsics.txt")).unwrap();
    std::fs::write(
        input.join("rgb.txt"),
        "0.0 rgb/000000.jpg\n0.4 rgb/000012.jpg\n0.8 rgb/000024.jpg\n0.833 rgb/000024.jpg\n\
         1.2 rgb/000036.jpg\n1.6 rgb/000048.jpg\n",
    )
    .unwrap();
    let json = dir.path().join("r.json");
    let out = consumer(
        &py,
        &["--every", "1", "--out"],
        &[&dir.path().join("rec"), Path::new("--json"), &json, &input],
    );
    assert!(out.status.success());
    let v = read_json(&json);
    let frames = v["frames"].as_array().unwrap();
    let names: Vec<&str> = frames.iter().map(|f| f["name"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "images/frame_000000.jpg",
            "images/frame_000001.jpg",
            "images/frame_000002.jpg",
            "images/frame_000002.jpg",
            "images/frame_000004.jpg",
            "images/frame_000005.jpg"
        ]
    );
    assert_eq!(v["images"], 5, "each file once: {v}");
    assert_eq!(v["registered"], 6, "{v}");
    assert_eq!(frames[2]["center"], frames[3]["center"]);
    assert_eq!(frames[3]["timestamp"], 0.833);
}

/// COLMAP ends its process on a failed internal check or an uncaught C++ exception (SIGABRT).
/// `run_sfm` runs it in a child process, so the caller gets a PipelineError naming COLMAP's
/// message and the stage, and goes on. Provoked here with COLMAP's own abort on two images of
/// one name, through the library (the command line no longer lets that through).
#[test]
fn a_colmap_abort_is_an_error_for_the_caller_not_a_crash() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let code = "import sys, pycolmap\n\
        from leangate_client.reconstruct import run_sfm\n\
        from leangate_client.errors import PipelineError\n\
        try:\n\
        \x20   run_sfm(sys.argv[1], ['rgb/000000.jpg', 'rgb/000000.jpg', 'rgb/000012.jpg'], sys.argv[2])\n\
        except PipelineError as e:\n\
        \x20   print('caught:', e)\n\
        print('still running')\n";
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(&py)
        .args(["-c", code])
        .arg(&seq)
        .arg(dir.path())
        .env("PYTHONPATH", repo_root().join("pipelines"))
        .env("TMPDIR", tmp.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{:?}", out.status);
    assert_tmpdir_untouched(tmp.path(), "run_sfm after a COLMAP abort");
    assert!(
        stdout.contains(
            "caught: COLMAP failed during feature extraction of 3 images (killed by SIGABRT)"
        ) && stdout.contains("SQLite error: constraint failed"),
        "{stdout}"
    );
    assert!(stdout.contains("still running"));
    let log = std::fs::read_to_string(dir.path().join("colmap.log")).unwrap();
    assert!(log.contains("constraint failed"), "{log}");
}

/// Every regular file under `dir` (relative path, contents), links not followed.
fn tree(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            let m = std::fs::symlink_metadata(&p).unwrap();
            if m.is_dir() {
                stack.push(p);
            } else if m.is_file() {
                let rel = p.strip_prefix(dir).unwrap().display().to_string();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

/// `--out` never deletes the input or folders the consumer did not make. It used to empty
/// OUT/images (and OUT/sparse) whatever they held: `--out SEQ` on a sequence whose images are
/// in SEQ/images deleted the input; a user's OUT/images/holiday.jpg, a COLMAP project's
/// sparse/, or the target of a symlinked images/ went the same way. Now OUT/images and
/// OUT/sparse are replaced only when they hold the marker a run writes into them; otherwise
/// the run stops with exit status 2 and a message naming the folder, and nothing is deleted.
#[test]
fn consumer_never_deletes_the_input_or_folders_it_did_not_make() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let run = |input: &Path, out: &Path, args: &[&str]| {
        consumer(&py, args, &[Path::new("--out"), out, input])
    };
    let refused = |o: &Output, expect: &str| {
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(err.contains(expect), "expected {expect:?} in {err}");
        assert!(!err.contains("Traceback"), "{err}");
    };
    let marker = ".leangate-reconstruct";

    // A TUM-layout sequence with its images in SEQ/images, reconstructed into SEQ itself.
    let iseq = root.join("iseq");
    std::fs::create_dir_all(iseq.join("images")).unwrap();
    let mut rows = String::new();
    for (k, n) in ["000000", "000012", "000024", "000036"].iter().enumerate() {
        std::fs::copy(
            seq.join(format!("rgb/{n}.jpg")),
            iseq.join(format!("images/{n}.jpg")),
        )
        .unwrap();
        rows.push_str(&format!("{k}.0 images/{n}.jpg\n"));
    }
    std::fs::write(iseq.join("rgb.txt"), rows).unwrap();
    let pristine = tree(&iseq);
    let before = pristine.clone();
    let o = run(&iseq, &iseq, &["--every", "2"]);
    refused(&o, "lies in");
    assert_eq!(tree(&iseq), before, "the input is untouched");
    // Even when that folder carries the marker of an earlier run.
    std::fs::write(iseq.join("images").join(marker), "").unwrap();
    let before = tree(&iseq);
    refused(
        &run(&iseq, &iseq, &["--every", "2"]),
        "the input would be deleted",
    );
    assert_eq!(tree(&iseq), before);
    std::fs::remove_file(iseq.join("images").join(marker)).unwrap();

    // A hard link to an input file in a (marked) OUT/images.
    let hard = root.join("hard");
    std::fs::create_dir_all(hard.join("images")).unwrap();
    std::fs::write(hard.join("images").join(marker), "").unwrap();
    std::fs::hard_link(
        iseq.join("images/000000.jpg"),
        hard.join("images/frame_000000.jpg"),
    )
    .unwrap();
    refused(&run(&iseq, &hard, &["--every", "2"]), "a hard link");
    assert!(hard.join("images/frame_000000.jpg").is_file());

    // A video inside OUT/images.
    if let Some(clip) = shared_data("cotracker_clips/cat.mp4") {
        let v = root.join("v");
        std::fs::create_dir_all(v.join("images")).unwrap();
        std::fs::write(v.join("images").join(marker), "").unwrap();
        std::fs::copy(&clip, v.join("images/cat.mp4")).unwrap();
        refused(
            &run(&v.join("images/cat.mp4"), &v, &["--frames", "0,5"]),
            "is (or holds) the input",
        );
        assert!(v.join("images/cat.mp4").is_file());
    }

    // Folders the consumer did not make: a user's images, a COLMAP project's sparse model.
    for (sub, file) in [("images", "holiday.jpg"), ("sparse", "0/cameras.bin")] {
        let out = root.join(format!("user_{sub}"));
        let p = out.join(sub).join(file);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(&p, "mine").unwrap();
        refused(
            &run(&iseq, &out, &["--every", "2"]),
            &format!("{sub} is not empty and was not made by reconstruct.py"),
        );
        assert_eq!(std::fs::read(&p).unwrap(), b"mine");
    }
    // A symlinked images/ (or sparse/) is refused, never followed.
    for sub in ["images", "sparse"] {
        let out = root.join(format!("link_{sub}"));
        std::fs::create_dir_all(out.join("elsewhere")).unwrap();
        std::fs::write(out.join("elsewhere").join(marker), "").unwrap();
        std::fs::write(out.join("elsewhere/keep.txt"), "keep").unwrap();
        std::os::unix::fs::symlink("elsewhere", out.join(sub)).unwrap();
        refused(
            &run(&iseq, &out, &["--every", "2"]),
            &format!("{sub} is a symbolic link"),
        );
        assert!(out.join("elsewhere/keep.txt").is_file());
    }

    // What a run makes carries the marker, and a second run into the same --out replaces it;
    // an empty images/ without the marker is taken too.
    let ok = root.join("ok");
    std::fs::create_dir_all(ok.join("images")).unwrap();
    for _ in 0..2 {
        let o = run(&iseq, &ok, &["--every", "1"]);
        assert!(o.status.success());
        assert!(ok.join("images").join(marker).is_file());
        assert!(ok.join("sparse").join(marker).is_file());
        assert!(ok.join("images/frame_000003.jpg").exists());
    }
    assert_eq!(tree(&iseq), pristine, "the input is untouched");
    // --help says so.
    let help = consumer(&py, &["--help"], &[]);
    let text: String = String::from_utf8_lossy(&help.stdout)
        .split_whitespace()
        .collect();
    assert!(
        text.contains("onlywhenitmadethemitself(eachholdsa.leangate-reconstructfile)"),
        "{text}"
    );
}

/// A TUM-layout copy of the shared kitchen in `dir/name`: its list files and `depth/000000.png`
/// copied (so that nothing under the shared data is ever in reach of a write), `rgb/` linked.
fn sequence_copy(seq: &Path, dir: &Path, name: &str) -> PathBuf {
    let input = dir.join(name);
    std::fs::create_dir_all(input.join("depth")).unwrap();
    std::os::unix::fs::symlink(seq.join("rgb"), input.join("rgb")).unwrap();
    for f in ["rgb.txt", "intrinsics.txt", "groundtruth.txt"] {
        std::fs::copy(seq.join(f), input.join(f)).unwrap();
    }
    std::fs::write(input.join("depth/000000.png"), b"a depth image").unwrap();
    input
}

/// The names in `dir` that look like a leftover temporary output (`.NAME.XXXXXXXX.tmp*`).
fn temp_files(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.') && n.contains(".tmp"))
        .collect()
}

/// `--json` and `--ply` lose nothing. Checked before any work (no COLMAP run, OUT not even
/// made): an input as the output (the sequence's rgb.txt, a file of its folder, one of its
/// images: they used to be overwritten, exit 0), one path for both, a file the run writes
/// itself, a directory, a directory that does not exist (these used to fail only after the whole
/// run): exit 2, one line naming it, the file untouched. Both are written beside the path and
/// moved over it when complete: a failed run leaves an earlier file as it was, and a write error
/// (/dev/full) is one line, not a traceback.
#[test]
fn consumer_checks_its_output_files_up_front_and_writes_them_whole() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let input = sequence_copy(&seq, root, "seq");
    let before = tree(&input);
    let out_dir = root.join("rec");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let refused = |args: &[String], expect: &str| {
        let mut a: Vec<&str> = vec!["--every", "12", "--out"];
        let od = s(&out_dir);
        a.push(&od);
        a.extend(args.iter().map(|x| x.as_str()));
        let o = consumer(&py, &a, &[&input]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.starts_with("reconstruct: error: ") && err.contains(expect),
            "{args:?}: expected {expect:?} in {err}"
        );
        assert_eq!(err.trim().lines().count(), 1, "{args:?}: one line: {err}");
        assert!(!out_dir.exists(), "{args:?}: refused before any work");
        assert_eq!(tree(&input), before, "{args:?}: the input is untouched");
    };
    let j = |p: PathBuf| vec!["--json".to_string(), s(&p)];
    refused(&j(input.join("rgb.txt")), "is a file of the input");
    refused(&j(input.join("depth/000000.png")), "is a file of the input");
    refused(
        &["--ply".to_string(), s(&input.join("rgb/000000.jpg"))],
        "would be overwritten",
    );
    let same = s(&root.join("same.out"));
    refused(
        &["--json".into(), same.clone(), "--ply".into(), same],
        "--json and --ply are the same file",
    );
    refused(&j(out_dir.join("colmap.log")), "a file the run writes");
    refused(
        &["--ply".to_string(), s(&out_dir.join("sparse/points.ply"))],
        "which the run replaces",
    );
    refused(&j(root.join("nodir/r.json")), "does not exist");
    refused(&j(root.to_path_buf()), "is a directory");

    // An earlier JSON survives a run that fails; one that succeeds replaces it, PLY too.
    let json = root.join("r.json");
    let ply = root.join("r.ply");
    std::fs::write(&json, "earlier").unwrap();
    std::fs::write(&ply, "earlier").unwrap();
    // The consumer with ARGS, writing OUT, the JSON and the PLY.
    let both = |args: &[&str]| {
        consumer(
            &py,
            args,
            &[
                &out_dir,
                Path::new("--json"),
                &json,
                Path::new("--ply"),
                &ply,
                &input,
            ],
        )
    };
    let o = both(&["--frames", "0,60", "--out"]);
    assert_eq!(o.status.code(), Some(2));
    assert_eq!(std::fs::read(&json).unwrap(), b"earlier");
    assert_eq!(std::fs::read(&ply).unwrap(), b"earlier");
    let o = both(&["--every", "12", "--out"]);
    assert!(o.status.success());
    assert_eq!(read_json(&json)["kept"], 5);
    assert!(std::fs::read(&ply).unwrap().starts_with(b"ply\n"));
    assert!(temp_files(root).is_empty(), "{:?}", temp_files(root));
    assert_eq!(tree(&input), before);

    // A write error at the end: one line, exit 2.
    if Path::new("/dev/full").exists() {
        let o = consumer(
            &py,
            &["--every", "12", "--out"],
            &[
                &out_dir,
                Path::new("--json"),
                Path::new("/dev/full"),
                &input,
            ],
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(
            err.contains("reconstruct: error: --json /dev/full: No space left on device"),
            "{err}"
        );
        assert!(!err.contains("Traceback"), "{err}");
    }
}

/// SIGTERM (`kill PID`, systemd) or SIGINT sent to the consumer's process alone while COLMAP
/// runs stops the run: COLMAP's child process (its own process group) is stopped too, one line
/// says so, exit 143 / 130, within seconds. SIGTERM used to end in glog's C stack dump ("***
/// Aborted at") with the child left running and writing into OUT; SIGINT waited for COLMAP to
/// finish.
#[test]
fn a_signal_to_the_consumer_stops_colmap_too() {
    let (Some(seq), Some(py)) = (shared_data("7scenes_redkitchen_dev"), sfm_python()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let children = |pid: u32| -> Vec<u32> {
        let o = Command::new("pgrep")
            .args(["-P", &pid.to_string()])
            .output()
            .unwrap();
        String::from_utf8_lossy(&o.stdout)
            .split_whitespace()
            .filter_map(|x| x.parse().ok())
            .collect()
    };
    // Gone, or a zombie nobody reaps (PID 1 of a container may not).
    let alive = |pid: u32| match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => stat
            .rsplit_once(')')
            .map(|(_, rest)| !rest.trim_start().starts_with('Z'))
            .unwrap_or(false),
        Err(_) => false,
    };
    for (signal, code, said) in [("-TERM", 143, "terminated"), ("-INT", 130, "interrupted")] {
        // The default disposition for both (a background job starts with SIGINT ignored), and
        // a process group of its own, so that the signal reaches the consumer alone.
        use std::os::unix::process::CommandExt;
        let out_dir = dir.path().join(format!("rec{code}"));
        let mut c = Command::new("env");
        c.arg("--default-signal=INT,TERM")
            .arg(&py)
            .arg(repo_root().join("pipelines/reconstruct.py"))
            .args(["--every", "1", "--out"])
            .arg(&out_dir)
            .arg(&seq)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .process_group(0);
        let mut child = c.spawn().unwrap();
        let pid = child.id();
        let start = std::time::Instant::now();
        let colmap = loop {
            if let Some(&k) = children(pid).first() {
                break k;
            }
            if child.try_wait().unwrap().is_some() || start.elapsed().as_secs() > 60 {
                let _ = child.kill();
                panic!("COLMAP's child process did not start within 60 s");
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        };
        std::thread::sleep(std::time::Duration::from_millis(1500)); // COLMAP at work
        assert!(alive(colmap), "COLMAP still runs before the signal");
        let killed = Command::new("kill")
            .args([signal, &pid.to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let sent = std::time::Instant::now();
        while child.try_wait().unwrap().is_none() {
            if sent.elapsed().as_secs() >= 20 {
                let _ = child.kill();
                panic!("kill {signal}: the consumer did not end within 20 s");
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        eprintln!(
            "kill {signal}: {} after {:?}\n{err}",
            out.status,
            sent.elapsed()
        );
        assert!(
            sent.elapsed().as_secs() < 10,
            "{signal}: {:?}",
            sent.elapsed()
        );
        assert_eq!(out.status.code(), Some(code), "{signal}: {err}");
        assert!(
            err.contains(&format!("reconstruct: error: {said}")),
            "{signal}: {err}"
        );
        assert!(
            !err.contains("*** Aborted at") && !err.contains("SIGTERM received"),
            "{signal}: no stack dump: {err}"
        );
        let waited = std::time::Instant::now();
        while alive(colmap) && waited.elapsed().as_secs() < 5 {
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        assert!(
            !alive(colmap),
            "{signal}: COLMAP's process {colmap} is left running"
        );
    }
}
