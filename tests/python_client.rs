//! The Python hand-off (the package `pipelines/leangate_client`, its wrapper
//! `pipelines/slam_client.py` and `python3 -m leangate_client`) and the example scripts in
//! `pipelines/`, run for real: Debian's /usr/bin/python3 with python3-gi, the `leangate` plugin
//! built beside this test (target/<profile>/libgstleangate.so), ONNX Runtime, and the fixture
//! model `mad.onnx` (utility = mean absolute difference of the two 64x64 pictures), so that the
//! drop-mode and annotate-mode runs of the same deterministic input can be checked against each
//! other. The package itself is checked as a package too: it imports from a clean interpreter
//! with only PYTHONPATH pointing at `pipelines/`, installs with `pip install --no-deps
//! --target`, and logs its diagnostics to stderr, leaving stdout to the frames and the summary.

#[path = "common/paths.rs"]
#[allow(dead_code)]
mod paths;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const PYTHON: &str = "/usr/bin/python3";
const REASONS: [&str; 9] = [
    "first", "warmup", "score", "max-gap", "forced", "error", "junk", "deferred", "sharper",
];

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn model() -> String {
    repo().join("tests/fixtures/mad.onnx").display().to_string()
}

/// None (with a SKIPPED message) when /usr/bin/python3 cannot import the GStreamer bindings.
fn python_ok() -> bool {
    let out = Command::new(PYTHON)
        .args([
            "-c",
            "import gi, numpy; gi.require_version('Gst', '1.0'); \
             gi.require_version('GstVideo', '1.0'); from gi.repository import Gst, GstVideo",
        ])
        .output();
    match out {
        Ok(o) if o.status.success() => true,
        Ok(o) => {
            eprintln!(
                "SKIPPED: {PYTHON} lacks python3-gi / GstVideo / numpy: {}",
                String::from_utf8_lossy(&o.stderr).trim()
            );
            false
        }
        Err(e) => {
            eprintln!("SKIPPED: cannot run {PYTHON}: {e}");
            false
        }
    }
}

fn command(program: &str) -> Command {
    let mut c = Command::new(program);
    c.current_dir(repo())
        .env("LEANGATE_MODEL", model())
        .env_remove("GST_PLUGIN_PATH_1_0");
    c
}

fn run(mut c: Command) -> Output {
    let plugins = paths::plugin_dir();
    c.env("GST_PLUGIN_PATH", plugins.path());
    let out = c.output().expect("spawn");
    eprintln!("--- {c:?}\nstatus {}", out.status);
    eprintln!("stderr:\n{}", String::from_utf8_lossy(&out.stderr));
    out
}

/// The directory holding the package `leangate_client` (and its `pyproject.toml`).
fn pkg_dir() -> PathBuf {
    repo().join("pipelines")
}

/// The command line through the repository's wrapper script `pipelines/slam_client.py`.
fn client(args: &[&str]) -> Output {
    let mut c = command(PYTHON);
    c.arg("pipelines/slam_client.py").args(args);
    run(c)
}

/// The command line as `python3 -m leangate_client`, the package found through PYTHONPATH.
fn client_module(args: &[&str]) -> Output {
    let mut c = command(PYTHON);
    c.env("PYTHONPATH", pkg_dir())
        .args(["-m", "leangate_client"])
        .args(args);
    run(c)
}

/// `python3 -c SCRIPT ARGS...`, the package found through PYTHONPATH.
fn client_script<S: AsRef<std::ffi::OsStr>>(script: &str, args: &[S]) -> Output {
    let mut c = command(PYTHON);
    c.env("PYTHONPATH", pkg_dir())
        .args(["-c", script])
        .args(args);
    run(c)
}

/// Whether every GStreamer element named exists (SKIPPED message otherwise).
fn have_elements(names: &[&str]) -> bool {
    for n in names {
        let ok = Command::new("gst-inspect-1.0")
            .args(["--exists", n])
            .status()
            .map(|s| s.success())
            .unwrap_or(false);
        if !ok {
            eprintln!("SKIPPED: GStreamer element {n} is not installed");
            return false;
        }
    }
    true
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// `key=value` pairs of the client's `summary:` line.
fn summary(o: &Output) -> std::collections::HashMap<String, String> {
    let text = stdout(o);
    let line = text
        .lines()
        .rev()
        .find(|l| l.starts_with("summary:"))
        .unwrap_or_else(|| panic!("no summary line in:\n{text}"));
    line["summary:".len()..]
        .split_whitespace()
        .filter_map(|kv| kv.split_once('='))
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

fn num(s: &std::collections::HashMap<String, String>, k: &str) -> u64 {
    s.get(k)
        .unwrap_or_else(|| panic!("summary lacks {k}: {s:?}"))
        .parse()
        .unwrap()
}

#[derive(Debug, Clone)]
struct Row {
    frame: u64,
    pts: u64,
    utility: f64,
    keep: bool,
    reason: String,
    keyframe_index: u64,
    frames_since_keyframe: u64,
    inference_us: u64,
}

fn read_csv(path: &Path) -> Vec<Row> {
    let text = std::fs::read_to_string(path).expect("csv written");
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some(
            "frame,pts_ns,utility,keep,reason,keyframe_index,frames_since_keyframe,inference_us,\
             depth"
        )
    );
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            assert_eq!(f.len(), 9, "row {l:?}");
            assert!(
                ["none", "used", "missing", "lost"].contains(&f[8]),
                "row {l:?}"
            );
            Row {
                frame: f[0].parse().unwrap(),
                pts: f[1].parse().unwrap(),
                utility: f[2].parse().unwrap(), // "nan" parses to NaN
                keep: match f[3] {
                    "1" => true,
                    "0" => false,
                    o => panic!("keep {o:?}"),
                },
                reason: f[4].to_string(),
                keyframe_index: f[5].parse().unwrap(),
                frames_since_keyframe: f[6].parse().unwrap(),
                inference_us: f[7].parse().unwrap(),
            }
        })
        .collect()
}

/// Invariants of an annotate-mode dump of a whole stream: one row per input frame, in order,
/// and the bookkeeping (keyframe index, frames since keyframe, NaN only for the first frame)
/// consistent with the keep decisions.
fn check_annotate_rows(rows: &[Row], frames: u64, threshold: f64) {
    assert_eq!(rows.len() as u64, frames, "one row per input frame");
    let mut kf = 0;
    let mut since = 0;
    let mut old: Option<(u64, usize)> = None;
    for (i, r) in rows.iter().enumerate() {
        assert_eq!(r.frame, i as u64, "frame column counts input frames");
        if i > 0 {
            assert!(r.pts > rows[i - 1].pts, "pts increase");
        }
        assert!(
            REASONS.contains(&r.reason.as_str()),
            "reason {:?}",
            r.reason
        );
        assert_eq!(
            r.utility.is_nan(),
            i == 0,
            "utility NaN only for the first: {r:?}"
        );
        if i == 0 {
            assert!(r.keep && r.reason == "first");
        } else if r.reason == "score" && !r.keep && r.utility >= threshold {
            // The keep due on it went back to a sharper frame held (`sharpness-lookback`, 3 by
            // default): one of the 3 before it.
            assert!(
                rows[i.saturating_sub(3)..i]
                    .iter()
                    .any(|p| p.reason == "sharper"),
                "a due frame dropped with no sharper keep before it: {r:?}"
            );
        } else if r.reason == "score" {
            assert_eq!(r.keep, r.utility >= threshold, "score decision {r:?}");
        } else if r.reason == "deferred" {
            assert!(
                !r.keep && r.utility >= threshold,
                "deferred: due, waiting {r:?}"
            );
        } else if r.reason == "sharper" {
            // Only a nearly-due frame is gone back to (within 0.1 of the threshold).
            assert!(r.keep && r.utility >= threshold - 0.1, "{r:?}");
        }
        if r.keep {
            // After a `sharper` keep, the frames held behind it up to the one whose keep went
            // back to it were compared with the reference before it, and count from there.
            old = (r.reason == "sharper").then_some((since + 1, i));
            kf += 1;
            since = 0;
        } else {
            since += 1;
            old = old.map(|(n, at)| (n + 1, at));
        }
        assert_eq!(r.keyframe_index, kf, "keyframe-index {r:?}");
        let from_old = old.is_some_and(|(n, at)| i - at <= 3 && r.frames_since_keyframe == n);
        assert!(
            r.frames_since_keyframe == since || from_old,
            "frames-since-keyframe {r:?}: {since} since the last keep"
        );
        assert!(r.inference_us > 0 && r.inference_us < 5_000_000, "{r:?}");
    }
}

#[test]
fn module_yields_rgb_arrays_with_their_meta() {
    if !python_ok() {
        return;
    }
    // 322 px wide RGB rows are 966 bytes, padded to a 968-byte stride: the arrays must not be
    // skewed. The top 60% of SMPTE bars is the same in every row; the 6th of 7 bars is red.
    // The package comes from PYTHONPATH alone: no sys.path edits.
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, LeanGateStats
from leangate_client._gst import Gst
src = LeanGateSource("test://smpte?num-buffers=12&width=322&height=242", model=sys.argv[1],
                     threshold=0.5, mode="annotate")
with src:
    for f, m in src:
        h, w = f.shape[:2]
        u = m.pop("utility")
        print(json.dumps({"shape": list(f.shape), "dtype": str(f.dtype),
            "contiguous": bool(f.flags.c_contiguous),
            "rows_equal": bool((f[: h * 6 // 10] == f[0]).all()),
            "px_white": f[0, w // 14].tolist(), "px_red": f[0, int(w * 5.5 / 7)].tolist(),
            "utility_nan": u != u, "utility": 0.0 if u != u else u, **m}))
st = src.stats
print(json.dumps({"end": True, "frames_in": src.frames_in, "received": src.received,
                  "stats_frames_in": (src.stats or {}).get("frames-in"),
                  "stats_model": (src.stats or {}).get("model"),
                  "stats_typed": isinstance(st, LeanGateStats),
                  "stats": [st.frames_in, st.frames_kept, st.keep_ratio, st.execution_provider,
                            st.model, st.model_precision, st.threshold, st.extra,
                            st.inference_p50_us is not None, st.interval_frames_in],
                  "stats_timings": [type(st.inference_mean_us).__name__,
                                    type(st.inference_p99_us).__name__],
                  "stats_dict": st.to_dict(),
                  "module": sys.modules["leangate_client"].__file__,
                  "plugin": Gst.ElementFactory.find("leangate").get_plugin().get_filename()}))
"#;
    let out = client_script(script, &[model()]);
    assert!(out.status.success());
    let vals: Vec<serde_json::Value> = stdout(&out)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect();
    let (end, frames) = vals.split_last().unwrap();
    assert_eq!(end["end"], true);
    assert_eq!(frames.len(), 12);
    assert_eq!(end["frames_in"], 12);
    assert_eq!(end["received"], 12);
    assert_eq!(
        end["stats_frames_in"], 12,
        "leangate-stats read from the bus at EOS"
    );
    assert_eq!(end["stats_model"], "fixture-mad");
    // The typed view of the same message.
    assert_eq!(end["stats_typed"], true);
    assert_eq!(
        end["stats"],
        serde_json::json!([
            12,
            1,
            1.0 / 12.0,
            "cpu",
            "fixture-mad",
            "fp32",
            0.5,
            {},
            true,
            12
        ])
    );
    assert_eq!(end["stats_timings"], serde_json::json!(["float", "int"]));
    let keys: Vec<&str> = end["stats_dict"]
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.as_str())
        .collect();
    for k in [
        "frames-in",
        "frames-kept",
        "keep-ratio",
        "inference-mean-us",
        "inference-p99-us",
        "execution-provider",
        "model",
        "model-precision",
        "threshold",
    ] {
        assert!(keys.contains(&k), "{k} missing from {keys:?}");
    }
    let module = end["module"].as_str().unwrap();
    assert!(
        Path::new(module).starts_with(pkg_dir().join("leangate_client")),
        "{module}"
    );
    // Loaded through GST_PLUGIN_PATH (the freshly built cdylib), not the client's fallback to
    // the repository's target/ directories.
    let plugin = end["plugin"].as_str().unwrap();
    assert!(
        plugin.ends_with("/libgstleangate.so") && !plugin.starts_with(env!("CARGO_MANIFEST_DIR")),
        "{plugin}"
    );
    let mut last_pts = None;
    for (i, v) in frames.iter().enumerate() {
        assert_eq!(v["shape"], serde_json::json!([242, 322, 3]), "{v}");
        assert_eq!(v["dtype"], "uint8");
        assert_eq!(v["contiguous"], true);
        assert_eq!(v["rows_equal"], true, "stride not honoured: {v}");
        let px = |k: &str| -> Vec<i64> {
            v[k].as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_i64().unwrap())
                .collect()
        };
        let white = px("px_white");
        assert!(white.iter().all(|&c| (150..=255).contains(&c)), "{white:?}");
        let red = px("px_red");
        assert!(red[0] > 150 && red[1] < 40 && red[2] < 40, "{red:?}");
        assert_eq!(v["frame"], i as u64);
        let pts = v["pts"].as_u64().unwrap();
        assert!(last_pts.is_none_or(|p| pts > p));
        last_pts = Some(pts);
        assert_eq!(v["utility_nan"], i == 0);
        assert!(REASONS.contains(&v["reason"].as_str().unwrap()));
        // A static pattern (the SMPTE noise patch aside) is far below 0.5: only the first kept.
        assert_eq!(v["keep"], i == 0, "{v}");
        assert_eq!(v["keyframe_index"], 1);
        assert_eq!(v["frames_since_keyframe"], i as u64);
        if i == 0 {
            assert_eq!(v["reason"], "first");
            assert_eq!(v["reference_pts"], v["pts"]);
        } else {
            assert_eq!(v["reason"], "score");
            assert!(v["utility"].as_f64().unwrap() < 0.5);
            assert_eq!(v["reference_pts"], frames[0]["pts"]);
        }
    }
}

#[test]
fn drop_mode_delivers_exactly_the_frames_annotate_mode_marks_kept() {
    if !python_ok() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (drop_csv, ann_csv) = (dir.path().join("drop.csv"), dir.path().join("ann.csv"));
    let src = "test://ball?num-buffers=45&width=320&height=240";
    let threshold = 0.02;
    let t = threshold.to_string();
    let drop = client(&[src, "--threshold", &t, "--csv", drop_csv.to_str().unwrap()]);
    assert!(drop.status.success());
    let ann = client(&[
        src,
        "--threshold",
        &t,
        "--mode",
        "annotate",
        "--quiet",
        "--csv",
        ann_csv.to_str().unwrap(),
    ]);
    assert!(ann.status.success());

    let ann_rows = read_csv(&ann_csv);
    check_annotate_rows(&ann_rows, 45, threshold);
    let drop_rows = read_csv(&drop_csv);
    let s = summary(&drop);
    assert_eq!(num(&s, "frames-in"), 45);
    assert_eq!(num(&s, "received"), drop_rows.len() as u64);
    assert_eq!(s["shape"], "240x320x3:uint8");
    // The per-frame lines report each array's shape.
    let shape_lines = stdout(&drop)
        .lines()
        .filter(|l| l.contains("shape (240, 320, 3)"))
        .count();
    assert_eq!(shape_lines, drop_rows.len());

    // The moving ball crosses the threshold every few frames: some, not all, frames kept.
    assert!(
        drop_rows.len() > 2 && drop_rows.len() < 45,
        "{} kept",
        drop_rows.len()
    );
    for (i, r) in drop_rows.iter().enumerate() {
        assert!(r.keep, "drop mode delivers only kept frames: {r:?}");
        assert!(
            ["first", "score", "sharper"].contains(&r.reason.as_str()),
            "{r:?}"
        );
        assert_eq!(
            r.keyframe_index,
            i as u64 + 1,
            "keyframe-index increases by one"
        );
        assert_eq!(r.frames_since_keyframe, 0);
        assert_eq!(r.utility.is_nan(), i == 0, "NaN only for the first: {r:?}");
        if i > 0 {
            // A `sharper` keep may be a frame that came within 0.1 of the threshold.
            let least = if r.reason == "sharper" {
                threshold - 0.1
            } else {
                threshold
            };
            assert!(
                r.utility >= least && r.frame > drop_rows[i - 1].frame,
                "{r:?}"
            );
        }
    }
    // Same deterministic input, same model: identical decisions in both modes.
    let kept_ann: Vec<(u64, u64)> = ann_rows
        .iter()
        .filter(|r| r.keep)
        .map(|r| (r.frame, r.pts))
        .collect();
    let kept_drop: Vec<(u64, u64)> = drop_rows.iter().map(|r| (r.frame, r.pts)).collect();
    assert_eq!(kept_drop, kept_ann);
    for (d, a) in drop_rows.iter().zip(ann_rows.iter().filter(|r| r.keep)) {
        assert!((d.utility.is_nan() && a.utility.is_nan()) || (d.utility - a.utility).abs() < 1e-5);
    }
}

#[test]
fn force_every_produces_forced_keyframes() {
    if !python_ok() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("forced.csv");
    // threshold 1: no score can keep a frame (the MAD of two frames of the ball is far below
    // 1), so every keep after the first must come from the upstream force-keyframe events.
    // (Run as `python3 -m leangate_client`; the other tests run the wrapper script.)
    let out = client_module(&[
        "--source",
        "videotestsrc",
        "test://ball?num-buffers=60&width=320&height=240",
        "--threshold",
        "1",
        "--mode",
        "annotate",
        "--force-every",
        "7",
        "--quiet",
        "--csv",
        csv.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let rows = read_csv(&csv);
    check_annotate_rows(&rows, 60, 1.0);
    let s = summary(&out);
    let events = num(&s, "force-events");
    // One event per 7 received frames; the last (frame 56) may come after end-of-stream has
    // reached the gate, which is then not sent (nothing left to keep).
    assert!(
        events == 60 / 7 || events == 60 / 7 - 1,
        "one event per 7 received frames: {events}"
    );
    let forced: Vec<&Row> = rows.iter().filter(|r| r.reason == "forced").collect();
    assert_eq!(num(&s, "forced"), forced.len() as u64);
    // Each event keeps exactly one later frame (the last may arrive after the last frame).
    assert!(
        forced.len() as u64 >= events - 1 && forced.len() as u64 <= events,
        "{} forced for {events} events",
        forced.len()
    );
    for r in &rows {
        assert_eq!(
            r.keep,
            r.reason == "first" || r.reason == "forced",
            "only first/forced frames kept at threshold 1: {r:?}"
        );
    }
    // An event sent after the k-th batch of 7 frames lands on a later frame.
    for (k, r) in forced.iter().enumerate() {
        assert!(r.frame >= 7 * (k as u64 + 1), "{r:?}");
        assert!(!r.utility.is_nan() && r.utility < 1.0);
    }

    // A force on every frame: the last 3 leave the gate (which holds 3) after end-of-stream
    // reached it, when no frame is left to keep: not counted as sent (they used to be).
    let out = client_module(&[
        "--source",
        "videotestsrc",
        "test://ball?num-buffers=10&width=160&height=120",
        "--threshold",
        "1",
        "--mode",
        "annotate",
        "--force-every",
        "1",
        "--quiet",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let s = summary(&out);
    assert!(num(&s, "force-events") <= 7, "{s:?}");
    assert!(num(&s, "forced") <= num(&s, "force-events"), "{s:?}");
}

#[test]
fn annotate_csv_script_writes_one_row_per_frame() {
    if !python_ok() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("scores.csv");
    let mut c = command("bash");
    c.args([
        "pipelines/annotate_csv.sh",
        "test://ball?num-buffers=30&width=160&height=120",
        csv.to_str().unwrap(),
        "0.03",
    ]);
    let out = run(c);
    assert!(out.status.success());
    let rows = read_csv(&csv);
    check_annotate_rows(&rows, 30, 0.03);
    let kept = rows.iter().filter(|r| r.keep).count();
    assert!(kept > 1 && kept < 30, "{kept} kept");
    assert_eq!(num(&summary(&out), "kept"), kept as u64);
}

#[test]
fn real_clip_drop_and_annotate_agree() {
    if !python_ok() {
        return;
    }
    let Some(clip) = paths::shared_data("cotracker_clips/bear.mp4") else {
        return;
    };
    let clip = clip.to_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (drop_csv, ann_csv) = (dir.path().join("drop.csv"), dir.path().join("ann.csv"));
    let drop = client(&[
        clip,
        "--threshold",
        "0.05",
        "--quiet",
        "--csv",
        drop_csv.to_str().unwrap(),
    ]);
    assert!(drop.status.success());
    let ann = client(&[
        clip,
        "--threshold",
        "0.05",
        "--mode",
        "annotate",
        "--quiet",
        "--csv",
        ann_csv.to_str().unwrap(),
    ]);
    assert!(ann.status.success());
    let s_ann = summary(&ann);
    let frames = num(&s_ann, "frames-in");
    assert!(frames > 30, "a few seconds of video: {frames}");
    let ann_rows = read_csv(&ann_csv);
    check_annotate_rows(&ann_rows, frames, 0.05);
    let s = summary(&drop);
    assert_eq!(num(&s, "frames-in"), frames);
    assert_eq!(s["shape"], "480x854x3:uint8", "bear.mp4 is 854x480");
    let drop_rows = read_csv(&drop_csv);
    assert!(drop_rows.len() > 1 && (drop_rows.len() as u64) < frames);
    let kept_ann: Vec<u64> = ann_rows
        .iter()
        .filter(|r| r.keep)
        .map(|r| r.frame)
        .collect();
    let kept_drop: Vec<u64> = drop_rows.iter().map(|r| r.frame).collect();
    assert_eq!(kept_drop, kept_ann);
    for (i, r) in drop_rows.iter().enumerate() {
        assert!(r.keep && r.keyframe_index == i as u64 + 1);
    }
    // The pipelines/file.sh example reports the same counts from gst-launch's -m output.
    let mut c = command("bash");
    c.args(["pipelines/file.sh", clip, "0.05"]);
    let out = run(c);
    assert!(out.status.success());
    let s_file = summary(&out);
    assert_eq!(num(&s_file, "frames-in"), frames);
    assert_eq!(num(&s_file, "frames-kept"), drop_rows.len() as u64);
    // The threshold as given, not as GStreamer prints the double (0.050000000000000003).
    assert_eq!(s_file["threshold"], "0.05", "{s_file:?}");
}

#[test]
fn errors_are_reported_clearly() {
    if !python_ok() {
        return;
    }
    let out = client(&["/nonexistent/clip.mp4"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("input file not found: /nonexistent/clip.mp4"),
        "{err}"
    );

    // A model that violates the input contract: the element's error reaches the user.
    let bad = repo().join("tests/fixtures/wrong_names.onnx");
    let out = client(&[
        "test://ball?num-buffers=5",
        "--model",
        bad.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("pipeline error: gate:"), "{err}");

    let out = client(&["test://nosuchpattern?num-buffers=5"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("slam_client:"), "{err}");
    // The message names the accepted patterns.
    assert!(err.contains("pattern") && err.contains("smpte"), "{err}");

    // The same diagnostics from the package's own entry point, under its own name.
    let out = client_module(&["/nonexistent/clip.mp4"]);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(
        err.contains("leangate-client: error: input file not found: /nonexistent/clip.mp4"),
        "{err}"
    );
    assert!(stdout(&out).is_empty(), "diagnostics stay off stdout");

    // An explicit plugin path that holds no plugin.
    let dir = tempfile::tempdir().unwrap();
    let out = client_module(&[
        "test://ball?num-buffers=5",
        "--plugin-path",
        dir.path().to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("leangate plugin not found"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn camera_pipeline_parses() {
    if !python_ok() {
        return;
    }
    let mut c = command("bash");
    c.args(["pipelines/camera.sh", "--check"]);
    let out = run(c);
    assert!(out.status.success());
    let text = stdout(&out);
    let elements: BTreeSet<&str> = text
        .lines()
        .find_map(|l| l.strip_prefix("camera.sh: elements: "))
        .expect("element list")
        .split_whitespace()
        .collect();
    for e in ["v4l2src", "videoconvert", "leangate"] {
        assert!(elements.contains(e), "{e} missing from {elements:?}");
    }
    assert!(!text.contains("sharpness-lookback"), "{text}");
    // LOOKBACK=0 for a live camera where latency matters; a bad value is refused.
    let mut c = command("bash");
    c.args(["pipelines/camera.sh", "--check"])
        .env("LOOKBACK", "0");
    let out = run(c);
    assert!(out.status.success());
    assert!(stdout(&out).contains(" max-gap=30 sharpness-lookback=0 "));
    let mut c = command("bash");
    c.args(["pipelines/camera.sh", "--check"])
        .env("LOOKBACK", "31");
    let out = run(c);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("LOOKBACK=31"), "{}", stderr(&out));
}

#[test]
fn feedback_reaches_the_gate_and_a_bad_tau_is_refused() {
    if !python_ok() {
        return;
    }
    // The appsink holds at most 8 frames, so a report sent while frame 2 is handled reaches the
    // gate well before frame 60; tau 0.75 at threshold 0.5, the stream's first report (counted
    // at 0.7, above the default rate 0.2), moves the gate's utility up by 0.175 (feedback-offset).
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, FEEDBACK_EVENT
src = LeanGateSource("test://ball?num-buffers=60&width=160&height=120", model=sys.argv[1],
                     threshold=0.5, mode="annotate")
out = {"event": FEEDBACK_EVENT}
with src:
    for k, (f, m) in enumerate(src):
        if k == 0:
            out["before"] = src.gate.get_property("feedback-offset")
        if k == 2:
            src.feedback(0.75)
            for bad in (1.5, -0.1, float("nan")):
                try:
                    src.feedback(bad)
                    out.setdefault("accepted", []).append(bad)
                except ValueError as e:
                    out.setdefault("refused", []).append(str(e))
        if k == 59:
            out["after"] = src.gate.get_property("feedback-offset")
out["stats_offset"] = src.stats.feedback_offset
out["stats_extra"] = src.stats.extra
print(json.dumps(out))
"#;
    let out = client_script(script, &[model()]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(v["event"], "leangate-feedback");
    assert_eq!(v["before"], 0.0);
    assert!((v["after"].as_f64().unwrap() - 0.175).abs() < 1e-9, "{v}");
    // The EOS statistics carry it too (a typed field, not an unknown extra).
    assert!(
        (v["stats_offset"].as_f64().unwrap() - 0.175).abs() < 1e-9,
        "{v}"
    );
    assert_eq!(v["stats_extra"], serde_json::json!({}));
    assert!(v.get("accepted").is_none(), "{v}");
    let refused = v["refused"].as_array().unwrap();
    assert_eq!(refused.len(), 3, "{v}");
    assert!(
        refused[0].as_str().unwrap().contains("not in [0, 1]"),
        "{v}"
    );
}

#[test]
fn package_imports_from_a_clean_interpreter() {
    if !python_ok() {
        return;
    }
    // Nothing but PATH and PYTHONPATH (pointing at the folder holding the package), started
    // outside the repository: the import needs no sys.path edits, no plugin and no Gst.init.
    let dir = tempfile::tempdir().unwrap();
    let script = r#"
import json, sys
import leangate_client as lc
from leangate_client._gst import Gst
print(json.dumps({
    "file": lc.__file__, "version": lc.__version__,
    "missing": [n for n in lc.__all__ if not hasattr(lc, n)],
    "api": all(hasattr(lc.LeanGateSource, n) for n in
               ("force_keyframe", "reset", "feedback", "start", "close", "gate", "description",
                "__iter__")),
    "gst_initialized": Gst.is_initialized(),
    "slam_client_loaded": "slam_client" in sys.modules,
}))
"#;
    let out = Command::new(PYTHON)
        .env_clear()
        .env("PATH", "/usr/bin:/bin")
        .env("PYTHONPATH", pkg_dir())
        .current_dir(dir.path())
        .args(["-c", script])
        .output()
        .expect("spawn");
    eprintln!("stderr:\n{}", stderr(&out));
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert!(
        Path::new(v["file"].as_str().unwrap()).starts_with(pkg_dir().join("leangate_client")),
        "{v}"
    );
    assert_eq!(v["version"], "0.1.0");
    assert_eq!(v["missing"], serde_json::json!([]));
    assert_eq!(v["api"], true);
    assert_eq!(
        v["gst_initialized"], false,
        "importing must not initialise GStreamer"
    );
    assert_eq!(v["slam_client_loaded"], false);
}

/// A copy of the package's source (pyproject.toml, README.md, leangate_client/) under `dir`, to
/// build from, so that the checkout gets no build/ or *.egg-info.
fn package_copy(dir: &Path) -> PathBuf {
    let src = dir.join("src");
    std::fs::create_dir_all(src.join("leangate_client")).unwrap();
    for f in ["pyproject.toml", "README.md"] {
        std::fs::copy(pkg_dir().join(f), src.join(f)).unwrap();
    }
    for e in std::fs::read_dir(pkg_dir().join("leangate_client")).unwrap() {
        let p = e.unwrap().path();
        if p.is_file() {
            std::fs::copy(&p, src.join("leangate_client").join(p.file_name().unwrap())).unwrap();
        }
    }
    src
}

/// `pip install` arguments that build the package offline: no index, and no build isolation
/// (the setuptools that comes with Debian's Python builds it).
const PIP_INSTALL: [&str; 8] = [
    "-m",
    "pip",
    "install",
    "--no-deps",
    "--no-build-isolation",
    "--no-index",
    "--no-cache-dir",
    "--disable-pip-version-check",
];

/// The installed console script runs a pipeline and the installed copy of the package is the
/// one imported (`python` is the interpreter the script was installed for).
fn check_installed(python: &Path, script: &Path, pythonpath: Option<&Path>, prefix: &Path) {
    assert!(
        script.is_file(),
        "console script {} installed",
        script.display()
    );
    let mut c = Command::new(python);
    if let Some(p) = pythonpath {
        c.env("PYTHONPATH", p);
    }
    let out = c
        .current_dir(prefix)
        .args([
            "-c",
            "import leangate_client; print(leangate_client.__file__)",
        ])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        Path::new(stdout(&out).trim()).starts_with(prefix),
        "{} imported, not the copy installed under {}",
        stdout(&out),
        prefix.display()
    );

    let mut c = command(script.to_str().unwrap());
    if let Some(p) = pythonpath {
        c.env("PYTHONPATH", p);
    }
    c.current_dir(prefix).args([
        "test://ball?num-buffers=10&width=160&height=120",
        "--threshold",
        "0.03",
        "--quiet",
    ]);
    let out = run(c);
    assert!(out.status.success());
    let s = summary(&out);
    assert_eq!(num(&s, "frames-in"), 10);
    assert_eq!(s["model"], "fixture-mad");
}

#[test]
fn package_installs_with_pip_no_deps_into_a_target_directory() {
    if !python_ok() {
        return;
    }
    let pip_ok = Command::new(PYTHON)
        .args(["-c", "import pip, setuptools"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !pip_ok {
        eprintln!("SKIPPED: {PYTHON} lacks pip or setuptools (apt install python3-pip)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let src = package_copy(dir.path());
    let site = dir.path().join("site");
    let mut c = Command::new(PYTHON);
    c.args(PIP_INSTALL)
        .arg("--target")
        .arg(&site)
        .arg(&src)
        .current_dir(dir.path());
    let out = run(c);
    assert!(out.status.success(), "{}", stdout(&out));
    assert!(site.join("leangate_client/__init__.py").is_file());
    check_installed(
        Path::new(PYTHON),
        &site.join("bin/leangate-client"),
        Some(&site),
        &site,
    );
}

#[test]
fn package_installs_into_a_venv_that_sees_the_system_bindings() {
    if !python_ok() {
        return;
    }
    // The documented route: a venv with --system-site-packages (gi and numpy from Debian),
    // pip install --no-deps. The venv's own pip comes from ensurepip (python3-venv).
    let dir = tempfile::tempdir().unwrap();
    let venv = dir.path().join("venv");
    let made = Command::new(PYTHON)
        .args(["-m", "venv", "--system-site-packages"])
        .arg(&venv)
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !made {
        eprintln!("SKIPPED: {PYTHON} -m venv failed (apt install python3-venv)");
        return;
    }
    let src = package_copy(dir.path());
    let python = venv.join("bin/python");
    let mut c = Command::new(&python);
    c.args(PIP_INSTALL).arg(&src).current_dir(dir.path());
    let out = run(c);
    assert!(out.status.success(), "{}", stdout(&out));
    check_installed(&python, &venv.join("bin/leangate-client"), None, &venv);
}

#[test]
fn diagnostics_are_logged_to_stderr_and_stdout_is_the_product() {
    if !python_ok() {
        return;
    }
    let src = "test://ball?num-buffers=10&width=160&height=120";
    // Command line, -v: info records on stderr as `PROG: info: ...`; stdout holds only the
    // per-frame lines and the summary.
    let out = client(&[src, "--threshold", "0.03", "-v"]);
    assert!(out.status.success());
    let err = stderr(&out);
    assert!(err.contains("slam_client: info: plugin: "), "{err}");
    assert!(
        err.contains("slam_client: info: pipeline: videotestsrc pattern=ball"),
        "{err}"
    );
    let text = stdout(&out);
    assert!(
        text.lines()
            .all(|l| l.starts_with("frame ") || l.starts_with("summary: ")),
        "{text}"
    );
    assert_eq!(
        text.lines().filter(|l| l.starts_with("summary: ")).count(),
        1
    );
    assert!(!text.contains("info:"), "{text}");

    // Without -v only warnings and errors are logged.
    let out = client(&[src, "--threshold", "0.03", "--quiet"]);
    assert!(out.status.success());
    assert!(!stderr(&out).contains("info:"), "{}", stderr(&out));

    // The library logs through `logging` (logger leangate_client.*) and never prints: with
    // logging configured by the application, its records appear on stderr, stdout is the
    // application's own.
    let script = r#"
import logging, sys
logging.basicConfig(level=logging.DEBUG, format="LOG %(name)s %(levelname)s %(message)s")
from leangate_client import LeanGateSource
n = sum(1 for _ in LeanGateSource(sys.argv[2], model=sys.argv[1], threshold=0.03))
print("received", n)
"#;
    let out = client_script(script, &[model().as_str(), src]);
    assert!(out.status.success());
    let text = stdout(&out);
    assert!(
        text.starts_with("received ") && text.lines().count() == 1,
        "{text}"
    );
    let err = stderr(&out);
    assert!(
        err.contains("LOG leangate_client.source INFO pipeline: "),
        "{err}"
    );
    assert!(
        err.contains("LOG leangate_client.source DEBUG stats from gate"),
        "{err}"
    );
}

#[test]
fn decoded_files_are_linked_on_pad_added_whatever_their_name() {
    if !python_ok() || !have_elements(&["jpegenc", "avimux", "wavenc", "audiotestsrc", "jpegdec"]) {
        return;
    }
    // A video with an audio track (decodebin exposes both; only the video is gated), renamed
    // to a name that a gst-launch description would need quoting for.
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("av.avi");
    let wav = dir.path().join("audio only.wav");
    let wav_plain = dir.path().join("a.wav");
    let status = Command::new("gst-launch-1.0")
        .args([
            "-q",
            "videotestsrc",
            "pattern=ball",
            "num-buffers=20",
            "!",
            "video/x-raw,width=160,height=120,framerate=10/1",
            "!",
            "jpegenc",
            "!",
            "avimux",
            "name=m",
            "!",
            "filesink",
            &format!("location={}", plain.display()),
            "audiotestsrc",
            "num-buffers=20",
            "samplesperbuffer=4410",
            "!",
            "audio/x-raw,rate=44100,channels=1",
            "!",
            "m.",
        ])
        .status()
        .unwrap();
    assert!(status.success());
    let status = Command::new("gst-launch-1.0")
        .args([
            "-q",
            "audiotestsrc",
            "num-buffers=20",
            "!",
            "wavenc",
            "!",
            "filesink",
            &format!("location={}", wav_plain.display()),
        ])
        .status()
        .unwrap();
    assert!(status.success());
    let odd_dir = dir.path().join("a dir");
    std::fs::create_dir(&odd_dir).unwrap();
    let odd = odd_dir.join("clip \"1\" ! name=x.avi");
    std::fs::rename(&plain, &odd).unwrap();
    std::fs::rename(&wav_plain, &wav).unwrap();

    // The same file as a path (filesrc ! decodebin) and as a file:// URI (uridecodebin).
    let script = r#"
import json, pathlib, sys
from leangate_client import LeanGateSource
for s in (sys.argv[2], pathlib.Path(sys.argv[2]).as_uri()):
    src = LeanGateSource(s, model=sys.argv[1], threshold=0.03)
    kept = [(m["frame"], list(f.shape)) for f, m in src]
    print(json.dumps({"source": s, "kept": kept, "frames_in": src.frames_in,
                      "received": src.received, "stats_kept": src.stats.frames_kept,
                      "stats_in": src.stats.frames_in}))
"#;
    let out = client_script(script, &[model().as_str(), odd.to_str().unwrap()]);
    assert!(out.status.success());
    let runs: Vec<serde_json::Value> = stdout(&out)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(runs.len(), 2);
    for r in &runs {
        assert_eq!(r["frames_in"], 20, "{r}");
        assert_eq!(r["stats_in"], 20, "{r}");
        assert_eq!(r["received"], r["stats_kept"], "{r}");
        let kept = r["kept"].as_array().unwrap();
        assert!(!kept.is_empty() && kept.len() < 20, "{r}");
        assert_eq!(kept[0], serde_json::json!([0, [120, 160, 3]]), "{r}");
    }
    assert!(runs[1]["source"].as_str().unwrap().starts_with("file:///"));
    assert_eq!(
        runs[0]["kept"], runs[1]["kept"],
        "path and URI decode the same"
    );

    // The command line on the same file.
    let out = client(&[odd.to_str().unwrap(), "--threshold", "0.03", "--quiet"]);
    assert!(out.status.success());
    let s = summary(&out);
    assert_eq!(num(&s, "frames-in"), 20);
    assert_eq!(num(&s, "received"), runs[0]["received"].as_u64().unwrap());

    // A file without video: a pipeline error saying so.
    let out = client(&[wav.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stderr(&out).contains("pipeline error: no video stream in"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn stats_message_has_a_typed_view_that_keeps_unknown_fields() {
    if !python_ok() {
        return;
    }
    let script = r#"
import json
from leangate_client import LeanGateStats
from leangate_client._gst import Gst
Gst.init(None)
s = Gst.Structure.new_from_string(
    "leangate-stats, frames-in=(guint64)30, frames-kept=(guint64)4, keep-ratio=(double)0.125,"
    " inference-mean-us=(double)812.5, inference-p99-us=(guint64)2000,"
    " execution-provider=(string)cpu, model=(string)leangate-s, threshold=(double)0.63,"
    " inference-p50-us=(guint64)700, future-field=(guint64)7,"
    " server=(string)http://127.0.0.1:8000, server-requests=(guint64)5")
st = LeanGateStats.from_structure(s)
back = LeanGateStats.from_structure(st.to_structure())
old = LeanGateStats.from_structure(Gst.Structure.new_from_string(
    "leangate-stats, frames-in=(guint64)3, frames-kept=(guint64)1"))
try:
    LeanGateStats.from_structure(Gst.Structure.new_from_string("other, a=(int)1"))
    wrong = "accepted"
except ValueError:
    wrong = "rejected"
print(json.dumps({
    "typed": [st.frames_in, st.frames_kept, st.keep_ratio, st.inference_mean_us,
              st.inference_p99_us, st.execution_provider, st.model, st.threshold,
              st.inference_p50_us, st.server, st.server_requests],
    "extra": st.extra, "p50": st["inference-p50-us"], "get": st.get("model"),
    "len": len(st), "round_trip": back == st,
    "wire": st.to_structure().to_string(),
    "partial": [old.frames_in, old.frames_kept, old.model, old.threshold, sorted(old)],
    "wrong_name": wrong,
}))
"#;
    let out = client_script::<&str>(script, &[]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(
        v["typed"],
        serde_json::json!([
            30,
            4,
            0.125,
            812.5,
            2000,
            "cpu",
            "leangate-s",
            0.63,
            700,
            "http://127.0.0.1:8000",
            5
        ])
    );
    assert_eq!(v["extra"], serde_json::json!({"future-field": 7}));
    assert_eq!(v["p50"], 700);
    assert_eq!(v["get"], "leangate-s");
    assert_eq!(v["len"], 12);
    assert_eq!(v["round_trip"], true);
    let wire = v["wire"].as_str().unwrap();
    for f in [
        "frames-in=(guint64)30",
        "inference-p99-us=(guint64)2000",
        "keep-ratio=(double)0.125",
        "model=(string)leangate-s",
    ] {
        assert!(wire.contains(f), "{f} not in {wire}");
    }
    assert_eq!(
        v["partial"],
        serde_json::json!([3, 1, null, null, ["frames-in", "frames-kept"]])
    );
    assert_eq!(v["wrong_name"], "rejected");
}

#[test]
fn plugin_path_argument_finds_the_plugin_without_gst_plugin_path() {
    if !python_ok() {
        return;
    }
    let plugins = paths::plugin_dir();
    let empty = tempfile::tempdir().unwrap();
    // A registry of its own, so that these runs neither see nor rewrite the shared cache.
    let registry = empty.path().join("registry.bin");
    let out = command(PYTHON)
        .env("PYTHONPATH", pkg_dir())
        .env("GST_PLUGIN_PATH", empty.path())
        .env("GST_REGISTRY", &registry)
        .args([
            "-m",
            "leangate_client",
            "test://ball?num-buffers=5&width=160&height=120",
        ])
        .args(["--quiet", "-v", "--plugin-path"])
        .arg(plugins.path())
        .output()
        .expect("spawn");
    eprintln!("stderr:\n{}", stderr(&out));
    assert!(out.status.success());
    assert_eq!(num(&summary(&out), "frames-in"), 5);
    let lib = plugins.path().join("libgstleangate.so");
    assert!(
        stderr(&out).contains(&format!("info: plugin: {}", lib.display())),
        "{}",
        stderr(&out)
    );

    // Without it (and without the wrapper's fallback to target/), a clear setup error. (No
    // system plugin directory either, in case a leangate is installed there.)
    let out = command(PYTHON)
        .env("PYTHONPATH", pkg_dir())
        .env("GST_PLUGIN_PATH", empty.path())
        .env("GST_PLUGIN_SYSTEM_PATH", empty.path())
        .env("GST_REGISTRY", empty.path().join("registry-none.bin"))
        .args(["-m", "leangate_client", "test://ball?num-buffers=5"])
        .output()
        .expect("spawn");
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(
        err.contains("`leangate` not found") && err.contains("GST_PLUGIN_PATH"),
        "{err}"
    );
}

/// `precision` picks the embedded student's build from Python (and from the CLI), the stats say
/// which ran, and a value the element does not know is a setup error naming the choices.
#[test]
fn precision_from_python_and_the_cli() {
    if !python_ok() {
        return;
    }
    let script = r#"
import json
from leangate_client import LeanGateSource, SetupError
out = {}
for p in ("int8", "fp32"):
    src = LeanGateSource("test://ball?num-buffers=4&width=160&height=120", precision=p,
                         execution_provider="cpu", arrays=False)
    with src:
        n = sum(1 for _ in src)
    out[p] = [n, src.stats.model_precision]
try:
    LeanGateSource("videotestsrc", precision="fp16")
except SetupError as e:
    out["error"] = str(e)
print(json.dumps(out))
"#;
    let out = client_script::<&str>(script, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(v["int8"][1], "int8");
    assert_eq!(v["fp32"][1], "fp32");
    assert!(v["int8"][0].as_u64().unwrap() >= 1);
    let e = v["error"].as_str().unwrap();
    assert!(e.contains("auto, fp32, int8") && e.contains("fp16"), "{e}");
    let o = client(&[
        "test://ball?num-buffers=4&width=160&height=120",
        "--precision",
        "fp32",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("precision=fp32") || stdout(&o).contains("precision=fp32"),
        "{}\n{}",
        stdout(&o),
        stderr(&o)
    );
}

#[test]
fn numeric_arguments_are_checked_at_parse_time() {
    if !python_ok() {
        return;
    }
    for (flag, value) in [
        ("--stats-interval", "nan"),
        ("--stats-interval", "inf"),
        ("--stats-interval", "-1"),
        ("--threshold", "nan"),
        ("--threshold", "2"),
        ("--warmup", "-1"),
        ("--max-gap", "4294967296"),
        ("--max-frames", "-1"),
        ("--force-every", "-2"),
    ] {
        let args = ["test://ball?num-buffers=3", flag, value];
        for out in [client(&args), client_module(&args)] {
            let err = stderr(&out);
            assert_eq!(out.status.code(), Some(2), "{flag} {value}: {err}");
            assert!(
                err.contains(&format!("argument {flag}: expected "))
                    && err.contains(&format!("got '{value}'")),
                "{flag} {value}: names the argument, the range and the value: {err}"
            );
            assert!(!err.contains("Traceback"), "{err}");
        }
    }
    // The library checks the same way.
    let script = r#"
from leangate_client import LeanGateSource, SetupError
for kw in ({"stats_interval": float("nan")}, {"threshold": 1.5}, {"warmup": -1},
           {"max_frames": 2.5}, {"timeout_s": 0}):
    try:
        LeanGateSource("test://ball?num-buffers=3", **kw)
        print("accepted", kw)
    except SetupError as e:
        print("refused", e)
"#;
    let out = client_script::<&str>(script, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 5, "{text}");
    for (line, name) in lines.iter().zip([
        "stats_interval",
        "threshold",
        "warmup",
        "max_frames",
        "timeout_s",
    ]) {
        assert!(
            line.starts_with(&format!("refused {name} must be ")),
            "{line}"
        );
    }
}

#[test]
fn pipeline_errors_name_the_input_without_debug_detail() {
    if !python_ok() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    for input in paths::not_videos(dir.path()) {
        let start = std::time::Instant::now();
        let out = client(&[input.to_str().unwrap()]);
        assert!(start.elapsed().as_secs() < 30, "no hang");
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(
            err.contains(&format!("pipeline error: {}: ", input.display())),
            "names the input: {err}"
        );
        assert!(!err.contains(".c(") && !err.contains("Traceback"), "{err}");
    }
    // The element's own error: its message, no source location (kept for -vv).
    let bad = repo().join("tests/fixtures/wrong_names.onnx");
    let args = [
        "test://ball?num-buffers=5",
        "--model",
        bad.to_str().unwrap(),
    ];
    let out = client(&args);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("pipeline error: gate: "), "{err}");
    assert!(!err.contains("imp.rs"), "{err}");
    let mut verbose = args.to_vec();
    verbose.push("-vv");
    let err = stderr(&client(&verbose));
    assert!(err.contains("(debug)") && err.contains("imp.rs"), "{err}");
}

/// Names of the files in `dir`, sorted.
fn dir_names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    v.sort();
    v
}

/// The saved keyframes' tables, checked against each other and against the image files: the
/// same rows in keyframes.csv and keyframes.json, one per image, named kf_000000.EXT, ...,
/// and nothing else in the directory. Returns the CSV's rows as their fields.
fn check_saved(dir: &Path, ext: &str) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(dir.join("keyframes.csv")).expect("keyframes.csv");
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some(
            "image,frame,pts_ns,utility,reason,keyframe_index,frames_since_keyframe,inference_us,\
             depth"
        )
    );
    let rows: Vec<Vec<String>> = lines
        .map(|l| l.split(',').map(String::from).collect())
        .collect();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("keyframes.json")).unwrap())
            .unwrap();
    let frames = json["frames"].as_array().unwrap();
    assert_eq!(frames.len(), rows.len(), "JSON and CSV rows");
    assert_eq!(json["kept"].as_u64(), Some(rows.len() as u64));
    let mut expected: Vec<String> = (0..rows.len())
        .map(|i| format!("kf_{i:06}.{ext}"))
        .collect();
    for (i, (r, j)) in rows.iter().zip(frames).enumerate() {
        assert_eq!(r.len(), 9, "{r:?}");
        assert_eq!(r[0], expected[i]);
        assert_eq!(j["depth"], r[8].as_str());
        assert_eq!(j["image"], r[0].as_str());
        assert_eq!(j["frame"].as_u64(), Some(r[1].parse().unwrap()), "{j}");
        assert_eq!(j["pts_ns"].as_u64(), Some(r[2].parse().unwrap()), "{j}");
        assert_eq!(j["reason"], r[4].as_str());
        assert_eq!(j["keyframe_index"].as_u64(), Some(r[5].parse().unwrap()));
        if r[4] == "first" {
            assert!(r[3] == "nan" && j["utility"].is_null(), "{r:?} {j}");
        } else {
            let u: f64 = r[3].parse().unwrap();
            assert!(
                (j["utility"].as_f64().unwrap() - u).abs() < 1e-6,
                "{r:?} {j}"
            );
        }
        let bytes = std::fs::read(dir.join(&r[0])).unwrap();
        let size = if ext == "png" {
            paths::png_size(&bytes)
        } else {
            paths::jpeg_size(&bytes)
        };
        assert!(size.is_some(), "{} is not a {ext}", r[0]);
    }
    expected.extend(["keyframes.csv".into(), "keyframes.json".into()]);
    expected.sort();
    assert_eq!(dir_names(dir), expected, "one image per row, nothing else");
    rows
}

/// `--save-kept DIR` on a real clip: one JPEG per kept frame, in the clip's size, whose rows in
/// keyframes.csv/.json carry the same frame, PTS, utility and reason as the frames the client
/// received; a progress line on stderr; and the README's plain gst-launch pipeline writes the
/// very same files.
#[test]
fn save_kept_writes_the_kept_frames_of_a_real_clip_with_their_meta() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let Some(clip) = paths::shared_data("cotracker_clips/bear.mp4") else {
        return;
    };
    let clip = clip.to_str().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let kf = tmp.path().join("new/kf"); // created, parents too
    let received = tmp.path().join("received.csv");
    let out = client_module(&[
        clip,
        "--threshold",
        "0.05",
        "--quiet",
        "--csv",
        received.to_str().unwrap(),
        "--save-kept",
        kf.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let s = summary(&out);
    let (frames_in, kept) = (num(&s, "frames-in"), num(&s, "kept"));
    assert_eq!(frames_in, 82);
    assert!(kept > 1 && kept < frames_in, "{kept}");
    assert_eq!(num(&s, "saved"), kept);
    let rows = check_saved(&kf, "jpg");
    assert_eq!(rows.len() as u64, kept, "one image per kept frame");
    let got = read_csv(&received);
    assert_eq!(got.len(), rows.len());
    for (r, g) in rows.iter().zip(&got) {
        assert_eq!(r[1], g.frame.to_string());
        assert_eq!(r[2], g.pts.to_string());
        assert_eq!(r[4], g.reason);
        assert_eq!(r[5], g.keyframe_index.to_string());
        assert_eq!(r[3] == "nan", g.utility.is_nan());
        if !g.utility.is_nan() {
            assert_eq!(r[3], format!("{:.6}", g.utility));
        }
    }
    for r in &rows {
        let bytes = std::fs::read(kf.join(&r[0])).unwrap();
        assert_eq!(paths::jpeg_size(&bytes), Some((854, 480)), "{}", r[0]);
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(kf.join("keyframes.json")).unwrap()).unwrap();
    assert_eq!(json["frames_in"].as_u64(), Some(frames_in));
    assert_eq!(json["format"], "jpg");
    let progress = format!(
        "leangate-client: {frames_in} frames in, {kept} kept, {kept} images written to {}",
        kf.display()
    );
    assert!(stderr(&out).contains(&progress), "{}", stderr(&out));

    // The plain pipeline of the README, same model and threshold: the same images. (Compared
    // as PNG, byte for byte: jpegenc fills the partial 16-pixel block at the right edge of an
    // 854-pixel row from the decoder's row padding, which differs from run to run, so two runs
    // of either pipeline differ there by a few levels.)
    let plain = tmp.path().join("plain");
    let png = tmp.path().join("png");
    std::fs::create_dir(&plain).unwrap();
    let mut c = command("gst-launch-1.0");
    c.args([
        "filesrc",
        &format!("location={clip}"),
        "!",
        "decodebin",
        "!",
    ])
    .args([
        "leangate",
        &format!("model={}", model()),
        "threshold=0.05",
        "!",
    ])
    .args(["videoconvert", "!", "pngenc", "compression-level=1", "!"])
    .arg("multifilesink")
    .arg(format!("location={}/kf_%06d.png", plain.display()));
    assert!(run(c).status.success());
    let out = client_module(&[
        clip,
        "--threshold",
        "0.05",
        "--quiet",
        "--format",
        "png",
        "--save-kept",
        png.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let rows = check_saved(&png, "png");
    assert_eq!(rows.len() as u64, kept);
    let images: Vec<&String> = rows.iter().map(|r| &r[0]).collect();
    assert_eq!(dir_names(&plain).iter().collect::<Vec<_>>(), images);
    for n in images {
        assert!(
            std::fs::read(plain.join(n)).unwrap() == std::fs::read(png.join(n)).unwrap(),
            "{n} differs between gst-launch and the client"
        );
    }
}

/// The library: `save_kept=` on a `LeanGateSource` in annotate mode saves only the kept frames
/// (as PNG); the `save_kept()` helper honours `max_frames`; a caller that stops iterating
/// early still gets every kept frame it was handed on disk, listed in the tables, and no
/// half-written file.
#[test]
fn save_kept_from_the_library_annotate_mode_and_early_stops() {
    if !python_ok() || !have_elements(&["pngenc", "jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let Some(clip) = paths::shared_data("cotracker_clips/teddy.mp4") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let d: Vec<PathBuf> = (1..=3).map(|i| tmp.path().join(format!("d{i}"))).collect();
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, save_kept
clip, d1, d2, d3, model = sys.argv[1:]
src = LeanGateSource(clip, model=model, threshold=0.15, mode="annotate", arrays=False,
                     save_kept=d1, save_format="png")
with src:
    kept = [m["frame"] for _, m in src if m["keep"]]
saver = save_kept(clip, d2, format="jpg", model=model, threshold=0.15, max_frames=5)
src3 = LeanGateSource(clip, model=model, threshold=0.15, save_kept=d3)
with src3:
    for i, (f, m) in enumerate(src3):
        if i == 2:
            break
print(json.dumps({"kept": kept, "rows1": [r["frame"] for r in src.saver.rows],
                  "frames_in": src.frames_in, "n2": len(saver.rows),
                  "n3": len(src3.saver.rows), "received3": src3.received}))
"#;
    let mut args: Vec<PathBuf> = vec![clip.clone()];
    args.extend(d.iter().cloned());
    args.push(model().into());
    let out = client_script(script, &args);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    let kept = v["kept"].as_array().unwrap();
    assert_eq!(v["frames_in"], 141, "teddy.mp4 has 141 frames");
    assert!(kept.len() > 5 && kept.len() < 141, "{kept:?}");
    assert_eq!(
        &v["rows1"], &v["kept"],
        "annotate mode: exactly the kept frames"
    );
    let rows = check_saved(&d[0], "png");
    assert_eq!(rows.len(), kept.len());
    for r in &rows {
        let bytes = std::fs::read(d[0].join(&r[0])).unwrap();
        assert_eq!(paths::png_size(&bytes), Some((368, 480)), "{}", r[0]);
    }
    assert_eq!(v["n2"], 5);
    assert_eq!(
        check_saved(&d[1], "jpg").len(),
        5,
        "max_frames caps the images"
    );
    let n3 = v["n3"].as_u64().unwrap();
    assert_eq!(v["received3"], 3);
    assert!(n3 >= 3, "every frame handed out is on disk: {v}");
    assert_eq!(check_saved(&d[2], "jpg").len() as u64, n3);
}

/// Directories `--save-kept` cannot use are refused before anything runs, with a message
/// naming the directory and the way out, and nothing in them is touched; `--overwrite`
/// replaces an earlier run's output and leaves other files alone.
#[test]
fn save_kept_refuses_unusable_directories() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let src = "test://ball?num-buffers=12&width=160&height=120";
    let tmp = tempfile::tempdir().unwrap();
    let kf = tmp.path().join("kf");
    std::fs::create_dir(&kf).unwrap();
    std::fs::write(kf.join("notes.txt"), "mine").unwrap();
    let kf_s = kf.to_str().unwrap();

    let out = client_module(&[src, "--quiet", "--save-kept", kf_s]);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(
        err.contains(&format!("leangate-client: error: {kf_s} is not empty"))
            && err.contains("notes.txt")
            && err.contains("--overwrite"),
        "{err}"
    );
    assert_eq!(dir_names(&kf), ["notes.txt"], "nothing written");
    assert!(stdout(&out).is_empty());

    // A first run into a fresh directory, then --overwrite with fewer frames: the earlier
    // images are gone, notes.txt stays (with a warning that it is there).
    let fresh = tmp.path().join("fresh");
    let out = client_module(&[
        src,
        "--threshold",
        "0.001",
        "--quiet",
        "--save-kept",
        fresh.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let first = dir_names(&fresh).len() - 2;
    assert!(first > 3, "{:?}", dir_names(&fresh));
    std::fs::write(fresh.join("notes.txt"), "mine").unwrap();
    let out = client_module(&[
        src,
        "--threshold",
        "0.001",
        "--quiet",
        "--max-frames",
        "2",
        "--overwrite",
        "--save-kept",
        fresh.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    assert!(
        stderr(&out).contains("not leangate output"),
        "{}",
        stderr(&out)
    );
    assert_eq!(
        dir_names(&fresh),
        [
            "keyframes.csv",
            "keyframes.json",
            "kf_000000.jpg",
            "kf_000001.jpg",
            "notes.txt"
        ]
    );

    // A file, a path that cannot be created, and --overwrite alone.
    let file = tmp.path().join("file.txt");
    std::fs::write(&file, "x").unwrap();
    let out = client_module(&[src, "--save-kept", file.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains(&format!(
            "{}: it exists and is not a directory",
            file.display()
        )),
        "{}",
        stderr(&out)
    );
    let out = client_module(&[src, "--save-kept", "/proc/leangate-kf/sub"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("cannot create the directory /proc/leangate-kf/sub"),
        "{}",
        stderr(&out)
    );
    let out = client_module(&[src, "--overwrite"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("--overwrite applies to --save-kept"));

    // Writing fails half-way (files over 100 KiB fail with EFBIG, as on a full disk; Python
    // ignores SIGXFSZ): a pipeline error naming the directory and the file, exit 1, and nothing
    // saved: the directory the run created is gone again, and so is its staging directory.
    if let Some(clip) = paths::shared_data("cotracker_clips/bear.mp4") {
        let full = tmp.path().join("full");
        let mut c = command("bash");
        c.env("PYTHONPATH", pkg_dir())
            .arg("-c")
            .arg(format!(
                "ulimit -f 100 && exec {PYTHON} -m leangate_client \"$1\" --quiet \
                 --threshold 0.05 --save-kept \"$2\""
            ))
            .args(["bash", clip.to_str().unwrap(), full.to_str().unwrap()]);
        let out = run(c);
        assert_eq!(out.status.code(), Some(1));
        let err = stderr(&out);
        assert!(
            err.contains(&format!(
                "error: pipeline error: cannot save the kept frames to {}: ",
                full.display()
            )) && err.contains("kf_000000.jpg")
                && err.contains("File too large"),
            "{err}"
        );
        assert!(
            err.contains(&format!(
                "error: nothing saved: {} is as it was before this run",
                full.display()
            )),
            "{err}"
        );
        assert!(!full.exists(), "the failed run's directory is removed");
        assert_eq!(staging_dirs(tmp.path()), Vec::<String>::new());
        assert!(!err.contains("Traceback"), "{err}");
    }

    // A directory without write permission (root writes anyway: then only say so).
    let ro = tmp.path().join("ro");
    std::fs::create_dir(&ro).unwrap();
    std::fs::set_permissions(&ro, std::os::unix::fs::PermissionsExt::from_mode(0o555)).unwrap();
    if std::fs::write(ro.join("probe"), "x").is_ok() {
        eprintln!("SKIPPED (read-only directory case): running as root, permissions do not bind");
        return;
    }
    let out = client_module(&[src, "--save-kept", ro.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains(&format!("cannot write to {}", ro.display())),
        "{}",
        stderr(&out)
    );
}

/// Every file in `dir` with its bytes (hidden ones too), to compare a directory before and after.
fn snapshot(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    dir_names(dir)
        .into_iter()
        .map(|n| {
            let bytes = std::fs::read(dir.join(&n)).unwrap_or_else(|e| panic!("{n}: {e}"));
            (n, bytes)
        })
        .collect()
}

/// The staging directories (`.DIR.leangate-staging-*`, `.leangate-staging-*`) a run of
/// `--save-kept` left in `dir`.
fn staging_dirs(dir: &Path) -> Vec<String> {
    dir_names(dir)
        .into_iter()
        .filter(|n| n.contains(".leangate-staging-"))
        .collect()
}

/// `--save-kept DIR` is all or nothing: a run that fails (an input that is not a video, a CSV
/// that cannot be opened), is interrupted with Ctrl-C (SIGINT), or ends in an exception out of
/// the library's `with` block leaves DIR byte for byte as it was (with --overwrite, the previous
/// run's keyframes survive; a DIR the run created is removed again), deletes its staging
/// directory, and says so. DIR's name has a space and a `%` (multifilesink's pattern character).
#[test]
fn save_kept_a_failed_or_interrupted_run_leaves_the_directory_as_it_was() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let kf = tmp.path().join("key frames 100%");
    let kf_s = kf.to_str().unwrap();
    let out = client_module(&[
        "test://ball?num-buffers=12&width=160&height=120",
        "--threshold",
        "0.001",
        "--quiet",
        "--save-kept",
        kf_s,
    ]);
    assert!(out.status.success());
    let before = snapshot(&kf);
    let images = check_saved(&kf, "jpg").len();
    assert!(images > 3, "{:?}", before.keys());
    let [noise, _] = paths::not_videos(tmp.path());
    let others = || {
        let mut v = dir_names(tmp.path());
        v.retain(|n| n != "noise.mp4" && n != "empty.mp4");
        v
    };
    let nothing_saved = |o: &Output, dir: &Path| {
        let err = stderr(o);
        assert!(
            err.contains(&format!(
                "leangate-client: error: nothing saved: {} is as it was before this run",
                dir.display()
            )),
            "{err}"
        );
        assert!(!err.contains("Traceback"), "{err}");
    };

    // Random bytes as the input, --overwrite: exit 1, the keyframes of the earlier run intact.
    let out = client_module(&[
        noise.to_str().unwrap(),
        "--quiet",
        "--overwrite",
        "--save-kept",
        kf_s,
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stderr(&out).contains("pipeline error: "),
        "{}",
        stderr(&out)
    );
    nothing_saved(&out, &kf);
    assert!(snapshot(&kf) == before, "{:?}", dir_names(&kf));
    assert_eq!(others(), ["key frames 100%"], "no staging directory left");

    // A DIR that does not exist yet (nor its parent): not left behind by a failed run, whether
    // the pipeline fails or the CSV cannot be written.
    let fresh = tmp.path().join("new/deep dir");
    let out = client_module(&[
        noise.to_str().unwrap(),
        "--quiet",
        "--save-kept",
        fresh.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    nothing_saved(&out, &fresh);
    let out = client_module(&[
        "test://ball?num-buffers=12&width=160&height=120",
        "--csv",
        "/nonexistent/scores.csv",
        "--save-kept",
        fresh.to_str().unwrap(),
    ]);
    // (The CSV is checked before anything is made: DIR is never created.)
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains(
            "leangate-client: error: --csv /nonexistent/scores.csv: the directory /nonexistent \
             does not exist"
        ),
        "{}",
        stderr(&out)
    );
    assert!(!fresh.exists());
    assert_eq!(others(), ["key frames 100%"], "new/ is removed again");

    // Ctrl-C (SIGINT) or a SIGTERM (a service stopped, `timeout`) in the middle of a long run
    // with --overwrite: exit 130 or 143 once images are being written (into the staging
    // directory), the earlier run intact and the staging directory gone (SIGTERM left it).
    let plugins = paths::plugin_dir();
    for (signal, code, said) in [("-INT", 130, "interrupted"), ("-TERM", 143, "terminated")] {
        // A shell's background job starts with SIGINT ignored, and the client rightly keeps an
        // inherited "ignore" (as `nohup` means it to): run it with the default disposition, as
        // from a terminal (`env --default-signal`, GNU coreutils).
        let mut c = command("env");
        c.args(["--default-signal=INT,TERM", PYTHON])
            .env("PYTHONPATH", pkg_dir())
            .env("GST_PLUGIN_PATH", plugins.path())
            .args(["-m", "leangate_client"])
            .args([
                "test://ball?num-buffers=1000000&width=160&height=120",
                "--threshold",
                "0.001",
                "--quiet",
                "--overwrite",
                "--save-kept",
                kf_s,
            ])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped());
        let child = c.spawn().expect("spawn");
        let start = std::time::Instant::now();
        let staged = loop {
            let staged: Vec<PathBuf> = staging_dirs(tmp.path())
                .iter()
                .map(|n| tmp.path().join(n))
                .collect();
            if let Some(d) = staged.first() {
                if std::fs::read_dir(d).map(|r| r.count()).unwrap_or(0) >= 20 {
                    break d.clone();
                }
            }
            assert!(
                start.elapsed().as_secs() < 60,
                "no staging directory with images beside {kf_s} after 60 s"
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        };
        assert!(
            staged
                .file_name()
                .unwrap()
                .to_str()
                .unwrap()
                .starts_with(".key frames 100%.leangate-staging-"),
            "{}",
            staged.display()
        );
        assert!(
            snapshot(&kf) == before,
            "DIR untouched while the run goes on"
        );
        let killed = Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let mut child = child;
        let waited = std::time::Instant::now();
        while child.try_wait().unwrap().is_none() {
            if waited.elapsed().as_secs() >= 60 {
                child.kill().ok();
                panic!("the client did not end within 60 s of kill {signal}");
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        let out = child.wait_with_output().unwrap();
        eprintln!("interrupted run: {}\n{}", out.status, stderr(&out));
        assert_eq!(out.status.code(), Some(code), "{signal}");
        assert!(stderr(&out).contains(&format!("leangate-client: error: {said}")));
        nothing_saved(&out, &kf);
        assert!(snapshot(&kf) == before, "{:?}", dir_names(&kf));
        assert_eq!(
            others(),
            ["key frames 100%"],
            "the staging directory is deleted"
        );
    }

    // The library: an exception out of the `with` block (the caller's SLAM failed) saves
    // nothing; the same run ended by `break` replaces the earlier one.
    let script = r#"
import json, sys
from leangate_client import LeanGateSource
model, d = sys.argv[1:]
def run(fail):
    src = LeanGateSource("test://ball?num-buffers=30&width=160&height=120", model=model,
                         threshold=0.001, save_kept=d, overwrite=True)
    try:
        with src:
            for i, (f, m) in enumerate(src):
                if i == 2:
                    if fail:
                        raise ValueError("the SLAM failed")
                    break
    except ValueError as e:
        pass
    return {"committed": src.saver.committed, "discarded": src.saver.discarded,
            "rows": len(src.saver.rows)}
print(json.dumps([run(True), run(False)]))
"#;
    let out = client_script(script, &[model().as_str(), kf_s]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(
        v[0],
        serde_json::json!({"committed": false, "discarded": true, "rows": 0})
    );
    assert_eq!(v[1]["committed"], true, "{v}");
    let rows = check_saved(&kf, "jpg");
    assert_eq!(v[1]["rows"], rows.len(), "{v}");
    assert!(rows.len() >= 3, "every frame handed out is saved: {rows:?}");
    assert_eq!(others(), ["key frames 100%"]);
}

/// `--overwrite` replaces only what the client wrote: the tables of the earlier run and the
/// images they list. A DIR with `kf_*` images no table lists (the plain gst-launch pipeline's,
/// or one dropped in by hand) is refused before anything runs, naming them, and nothing in it
/// is touched; a table cannot make it delete anything else (`../victim.txt`, `notes.txt`).
#[test]
fn save_kept_overwrite_never_deletes_files_the_client_did_not_write() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let src = "test://ball?num-buffers=12&width=160&height=120";
    let tmp = tempfile::tempdir().unwrap();
    let kf = tmp.path().join("kf");
    let kf_s = kf.to_str().unwrap();
    let save = |extra: &[&str]| {
        let mut args = vec![src, "--threshold", "0.001", "--quiet", "--save-kept", kf_s];
        args.extend(extra);
        client_module(&args)
    };
    assert!(save(&[]).status.success());
    let n = check_saved(&kf, "jpg").len();

    // A stray image in the client's naming scheme that the tables do not list.
    let stray = format!("kf_{:06}.jpg", n + 5);
    std::fs::write(kf.join(&stray), "a photo of mine").unwrap();
    let before = snapshot(&kf);
    let out = save(&["--overwrite"]);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(
        err.contains(&format!(
            "leangate-client: error: --overwrite: {kf_s} holds 1 entry"
        )) && err.contains(&stray)
            && err.contains("replaces only what it wrote"),
        "{err}"
    );
    assert!(snapshot(&kf) == before, "nothing touched");
    std::fs::remove_file(kf.join(&stray)).unwrap();

    // Images without tables (the plain pipeline writes these names): refused likewise.
    let plain = tmp.path().join("plain");
    std::fs::create_dir(&plain).unwrap();
    for i in 0..3 {
        std::fs::copy(
            kf.join(format!("kf_{i:06}.jpg")),
            plain.join(format!("kf_{i:06}.jpg")),
        )
        .unwrap();
    }
    let out = client_module(&[
        src,
        "--quiet",
        "--overwrite",
        "--save-kept",
        plain.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("holds 3 entries named like the client's output"),
        "{}",
        stderr(&out)
    );
    assert_eq!(dir_names(&plain).len(), 3);

    // Tables edited to list names the client never writes: they are not deleted.
    std::fs::write(tmp.path().join("victim.txt"), "keep me").unwrap();
    std::fs::write(kf.join("notes.txt"), "mine").unwrap();
    let csv = std::fs::read_to_string(kf.join("keyframes.csv")).unwrap();
    std::fs::write(
        kf.join("keyframes.csv"),
        format!("{csv}../victim.txt,0,0,,first,1,0,1\nnotes.txt,0,0,,first,1,0,1\n"),
    )
    .unwrap();
    let out = save(&["--overwrite", "--max-frames", "2"]);
    assert!(out.status.success());
    assert_eq!(
        dir_names(&kf),
        [
            "keyframes.csv",
            "keyframes.json",
            "kf_000000.jpg",
            "kf_000001.jpg",
            "notes.txt"
        ]
    );
    assert_eq!(
        std::fs::read_to_string(tmp.path().join("victim.txt")).unwrap(),
        "keep me"
    );
    assert_eq!(staging_dirs(tmp.path()), Vec::<String>::new());
}

/// `force_keyframe`, `reset` and `feedback` need the running pipeline: before the source starts
/// and after it closes they raise NotRunningError (a RuntimeError naming the call and the
/// state) instead of returning False as if the event had been sent; while it runs they return
/// True (the event reached the gate), with and without the `tee` of `save_kept`. A closed
/// source does not run again.
#[test]
fn control_calls_outside_a_running_source_raise() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, NotRunningError
model, d = sys.argv[1:]
calls = {"force_keyframe": lambda s: s.force_keyframe(), "reset": lambda s: s.reset(),
         "feedback": lambda s: s.feedback(0.5)}
def outcome(src, name):
    try:
        return calls[name](src)
    except NotRunningError as e:
        return {"state": e.state, "runtime": isinstance(e, RuntimeError), "msg": str(e)}
res = []
for save in (None, d):
    # Long enough that the gate, up to a second of frames (the queue of save_kept) and 3 held
    # frames ahead of the loop, has not reached end-of-stream at the 4th frame.
    src = LeanGateSource("test://ball?num-buffers=80&width=160&height=120", model=model,
                         mode="annotate", save_kept=save)
    r = {"before": {n: outcome(src, n) for n in calls}}
    with src:
        for i, (f, m) in enumerate(src):
            if i == 3:
                r["during"] = {n: outcome(src, n) for n in calls}
    r["after"] = {n: outcome(src, n) for n in calls}
    r["forced_events"] = src.forced_events
    for again in ("iterate", "start"):
        try:
            list(src) if again == "iterate" else src.start()
            r[again] = "ran"
        except NotRunningError as e:
            r[again] = str(e)
    res.append(r)
print(json.dumps(res))
"#;
    let d = tmp.path().join("kf");
    let out = client_script(script, &[model(), d.display().to_string()]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    for r in v.as_array().unwrap() {
        for (when, state) in [("before", "not started"), ("after", "closed")] {
            for call in ["force_keyframe", "reset", "feedback"] {
                let o = &r[when][call];
                assert_eq!(o["state"], state, "{call} {when}: {r}");
                assert_eq!(o["runtime"], true);
                let msg = o["msg"].as_str().unwrap();
                assert!(
                    msg.starts_with(&format!("{call}(): the source is {state}")),
                    "{msg}"
                );
            }
        }
        assert_eq!(
            r["during"],
            serde_json::json!({"force_keyframe": true, "reset": true, "feedback": true}),
            "{r}"
        );
        assert_eq!(r["forced_events"], 1);
        for again in ["iterate", "start"] {
            assert!(
                r[again].as_str().unwrap().contains("the source is closed"),
                "{r}"
            );
        }
    }
    assert!(d.join("keyframes.csv").is_file(), "the save_kept run saved");
}

/// After the `for` loop has run to end-of-stream (before `close()`), no frame will come through
/// the gate to act on a control call: `force_keyframe`, `reset` and `feedback` raise
/// NotRunningError with state "ended" (they used to return True and count a forced event).
/// Inside the loop on the stream's last frames, which the default gate (holding 3 frames) lets
/// out only after end-of-stream has reached it, they return False and count nothing (they used
/// to return True and do nothing); on the first frame they reach the gate.
#[test]
fn control_calls_after_end_of_stream_raise_ended() {
    if !python_ok() {
        return;
    }
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, NotRunningError
calls = {"force_keyframe": lambda s: s.force_keyframe(), "reset": lambda s: s.reset(),
         "feedback": lambda s: s.feedback(0.5)}
def outcome(src, name):
    try:
        return calls[name](src)
    except NotRunningError as e:
        return {"state": e.state, "runtime": isinstance(e, RuntimeError), "msg": str(e)}
src = LeanGateSource("test://ball?num-buffers=30", model=sys.argv[1], mode="annotate")
r = {"frames": 0, "last": []}
for f, m in src:
    r["frames"] += 1
    if r["frames"] == 1:
        r["first"] = {n: outcome(src, n) for n in calls}
    if r["frames"] >= 28:
        r["last"].append({n: outcome(src, n) for n in calls})
r["forced_before"] = src.forced_events
r["ended"] = src.ended
r["after_eos"] = {n: outcome(src, n) for n in calls}
r["forced_after"] = src.forced_events
src.close()
r["closed"] = outcome(src, "force_keyframe")
print(json.dumps(r))
"#;
    let out = client_script(script, &[model()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(r["frames"], 30, "{r}");
    assert_eq!(
        r["first"],
        serde_json::json!({"force_keyframe": true, "reset": true, "feedback": true}),
        "inside the loop, on the first frame: {r}"
    );
    // Frames 28-30 leave the gate at end-of-stream (the 3 it holds): nothing left to act on.
    let none = serde_json::json!({"force_keyframe": false, "reset": false, "feedback": false});
    assert_eq!(r["last"], serde_json::json!([none, none, none]), "{r}");
    assert_eq!(r["ended"], true, "{r}");
    for call in ["force_keyframe", "reset", "feedback"] {
        let o = &r["after_eos"][call];
        assert_eq!(o["state"], "ended", "{call} after EOS: {r}");
        assert_eq!(o["runtime"], true);
        let msg = o["msg"].as_str().unwrap();
        assert!(
            msg.starts_with(&format!("{call}(): the stream has ended")),
            "{msg}"
        );
    }
    assert_eq!(r["forced_before"], 1, "{r}");
    assert_eq!(r["forced_after"], 1, "not counted after EOS: {r}");
    assert_eq!(r["closed"]["state"], "closed", "{r}");
}

/// Two runs saving into the same empty DIR at once: the one that finishes second used to take
/// the first one's files for "an earlier run's output" and replace them without --overwrite,
/// both reporting success. Now, without overwrite, a run that finds keyframes output in DIR at
/// commit time (DIR was empty when it started) refuses: PipelineError, its staging directory
/// removed, the other run's output left as it is. The second run is made to finish inside the
/// first one's loop, so the order is certain.
#[test]
fn save_kept_does_not_replace_a_concurrent_runs_output_without_overwrite() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("same");
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, PipelineError, save_kept
model, d = sys.argv[1:]
first = LeanGateSource("test://ball?num-buffers=20&width=160&height=120", model=model,
                       mode="annotate", save_kept=d)
r = {}
try:
    with first:
        for i, _ in enumerate(first):
            if i == 2:
                second = save_kept("test://ball?num-buffers=10&width=160&height=120", d,
                                   model=model)
                r["second_committed"] = second.committed
    r["first"] = "committed"
except PipelineError as e:
    r["first"] = str(e)
r["first_committed"] = first.saver.committed
print(json.dumps(r))
"#;
    let out = client_script(script, &[model(), d.display().to_string()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(r["second_committed"], true, "{r}");
    assert_eq!(r["first_committed"], false, "{r}");
    let msg = r["first"].as_str().unwrap();
    assert!(
        msg.contains("now holds keyframes output that was not there when this run started")
            && msg.contains("not replaced without --overwrite"),
        "{msg}"
    );
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("keyframes.json")).unwrap()).unwrap();
    assert_eq!(doc["frames_in"], 10, "the second run's output stays: {doc}");
    assert!(staging_dirs(tmp.path()).is_empty() && staging_dirs(&d).is_empty());
}

/// A signal at any step of `--save-kept DIR --overwrite`'s swap leaves DIR as it was or
/// completely the new run's, never a mix, and no staging folder: Ctrl-C, SIGTERM and SIGHUP all
/// wait for the swap's end and then end the run (exit 130, 143, 129). The CLI runs in one
/// Python process, its file operations counted from the moment `close()` would write the tables;
/// run after run the process sends itself the signal (kill(2), rotating SIGTERM, SIGHUP and
/// SIGINT) just after the first, second, ... of them, until a run ends with none left to count:
/// every step of the swap is hit. Each of the three ways the swap can go is walked: DIR and the
/// staging folder trading places in one `renameat2(RENAME_EXCHANGE)`, two renames where the
/// system has no exchange, and file by file when the staging folder lies inside DIR (DIR a
/// mount point). DIR holds files of the user's (a file, a folder) beside the earlier run's.
/// A signal just before `finish` (while `close()` stops the pipeline) saves nothing. Before,
/// SIGTERM at the swap's start left DIR without its tables, mixing both runs' images, and the
/// staging folder beside it.
#[test]
fn save_kept_a_signal_at_any_step_of_the_swap_leaves_dir_old_or_new() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let script = r#"
import hashlib, json, os, shutil, signal, sys
from leangate_client import _outdir, cli, keyframes

model, top = sys.argv[1:]
signal.signal(signal.SIGINT, signal.default_int_handler)  # not an inherited "ignore"
d = os.path.join(top, "kf")
pristine = os.path.join(top, "pristine")

def args(src):
    return [src, "--model", model, "--threshold", "0.001", "--quiet", "--overwrite",
            "--save-kept", d]

def snapshot(p):
    """Every file under p with its bytes; the tables without inference_us (a timing)."""
    out = {}
    for root, dirs, files in os.walk(p):
        for n in files:
            q = os.path.join(root, n)
            with open(q, "rb") as f:
                data = f.read()
            if n == "keyframes.json":
                doc = json.loads(data)
                for r in doc["frames"]:
                    del r["inference_us"]
                data = json.dumps(doc).encode()
            elif n == "keyframes.csv":
                data = b"\n".join(b",".join(f for i, f in enumerate(l.split(b",")) if i != 7)
                                 for l in data.splitlines())  # column 7: inference_us
            out[os.path.relpath(q, p)] = hashlib.sha1(data).hexdigest()
    return out

assert cli.main(args("test://ball?num-buffers=12&width=64&height=48")) == 0
with open(os.path.join(d, "notes.txt"), "w") as f:
    f.write("mine")
os.mkdir(os.path.join(d, "colmap"))
with open(os.path.join(d, "colmap", "database.db"), "w") as f:
    f.write("mine too")
shutil.copytree(d, pristine)
old = snapshot(d)
NEW = args("test://ball?num-buffers=6&width=80&height=60")
assert cli.main(NEW) == 0
new = snapshot(d)
assert new != old and "notes.txt" in new and "colmap/database.db" in new

MUTATIONS = ("unlink", "rename", "replace", "link", "rmdir", "mkdir", "chmod", "chown",
             "setxattr", "symlink", "remove")
state = {"active": False, "count": 0, "at": None, "sig": None, "sent": False}
def counted(f):
    def call(*a, **k):
        r = f(*a, **k)
        if state["active"]:
            state["count"] += 1
            if state["count"] == state["at"]:
                state["sent"] = True
                os.kill(os.getpid(), state["sig"])
        return r
    return call
for n in MUTATIONS:
    setattr(os, n, counted(getattr(os, n)))
if hasattr(_outdir, "exchange"):  # (absent before the swap was made one step)
    _outdir.exchange = counted(_outdir.exchange)
finish = keyframes.KeptFrameSaver.finish
def finish_counted(self, *a, **k):
    state["active"] = True
    try:
        if state["at"] == 0:  # before finish: while close() is about to call it
            state["sent"] = True
            os.kill(os.getpid(), state["sig"])
        return finish(self, *a, **k)
    finally:
        state["active"] = False
keyframes.KeptFrameSaver.finish = finish_counted

variants = {
    "exchange": lambda: None,
    "two renames": lambda: setattr(_outdir, "exchange", counted(lambda a, b: False)),
    "file by file": lambda: setattr(os.path, "ismount", lambda p, _m=os.path.ismount:
                                    os.path.realpath(p) == os.path.realpath(d) or _m(p)),
}
sigs = [signal.SIGTERM, signal.SIGHUP, signal.SIGINT]
runs = []
for variant, setup in variants.items():
    setup()
    at = 0
    while True:
        shutil.rmtree(d)
        shutil.copytree(pristine, d)
        sig = sigs[at % 3]
        state.update(count=0, at=at, sig=sig, sent=False)
        status = cli.main(NEW)
        snap = snapshot(d)
        left = sorted(set(os.listdir(top)) - {"kf", "pristine"})
        for n in left:
            shutil.rmtree(os.path.join(top, n), ignore_errors=True)
        runs.append({"variant": variant, "at": at, "signal": signal.Signals(sig).name,
                     "sent": state["sent"], "steps": state["count"], "status": status,
                     "dir": "old" if snap == old else "new" if snap == new else sorted(snap),
                     "left": left})
        if not state["sent"] or at > 200:
            break
        at += 1
print("result: " + json.dumps(runs))
"#;
    let tmp = tempfile::tempdir().unwrap();
    let out = client_script(script, &[model(), tmp.path().display().to_string()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    let line = text
        .lines()
        .find_map(|l| l.strip_prefix("result: "))
        .unwrap_or_else(|| panic!("no result in:\n{text}"));
    let runs: Vec<serde_json::Value> = serde_json::from_str(line).unwrap();
    let mut wrong = Vec::new();
    for variant in ["exchange", "two renames", "file by file"] {
        let v: Vec<&serde_json::Value> = runs.iter().filter(|r| r["variant"] == variant).collect();
        let last = v.last().unwrap();
        assert_eq!(last["sent"], false, "{last}");
        let steps = last["steps"].as_u64().unwrap();
        assert!(steps >= 10, "{variant}: {steps} steps");
        assert_eq!(v.len() as u64, steps + 2, "{variant}: every step hit");
        let mut signals = BTreeSet::new();
        for r in &v {
            let at = r["at"].as_u64().unwrap();
            // Before finish: nothing saved; during the swap: the signal waits for its end.
            let (status, dir) = match (r["sent"].as_bool().unwrap(), r["signal"].as_str()) {
                (false, _) => (0, "new"),
                (true, Some("SIGTERM")) => (143, if at == 0 { "old" } else { "new" }),
                (true, Some("SIGHUP")) => (129, if at == 0 { "old" } else { "new" }),
                (true, _) => (130, if at == 0 { "old" } else { "new" }),
            };
            if r["status"] != status || r["dir"] != dir || r["left"] != serde_json::json!([]) {
                wrong.push(format!(
                    "{variant}, {} after step {at}: exit {} (not {status}), DIR {} (not {dir}), \
                     left beside it: {}",
                    r["signal"].as_str().unwrap(),
                    r["status"],
                    r["dir"],
                    r["left"]
                ));
            }
            if at > 0 && r["sent"] == true {
                signals.insert(r["signal"].as_str().unwrap().to_string());
            }
        }
        assert_eq!(signals.len(), 3, "{variant}: {signals:?}");
    }
    assert!(
        wrong.is_empty(),
        "{} of {} runs:\n{}",
        wrong.len(),
        runs.len(),
        wrong.join("\n")
    );
    let err = stderr(&out);
    assert!(
        err.contains("error: terminated")
            && err.contains("error: interrupted")
            && err.contains(&format!(
                "error: the kept frames had been saved to {} before that",
                tmp.path().join("kf").display()
            )),
        "{err}"
    );
}

/// `--save-kept DIR` checked from outside: whether DIR holds its tables (`keyframes.csv`,
/// `keyframes.json`) and a file of the user's, looked up over and over while `--overwrite` runs
/// replace an earlier run of about 1,500 images. A reader never finds DIR without them (before,
/// the swap deleted the earlier tables first and DIR had none for a good part of a second). A
/// SIGTERM or SIGHUP sent with `kill` as soon as the run's tables appear in its staging folder
/// (the swap begins) ends the run with 143 or 129, DIR either as it was or the new run's,
/// complete (every image its tables list, in the new run's size, and no other), and no
/// staging folder left.
#[test]
fn save_kept_overwrite_readers_always_find_dir_complete() {
    if !python_ok() || !have_elements(&["jpegenc", "multifilesink", "tee"]) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let kf = tmp.path().join("key frames");
    let kf_s = kf.to_str().unwrap();
    let source = |w: u32| format!("test://ball?num-buffers=1500&width={w}&height=48");
    let out = client_module(&[
        &source(64),
        "--threshold",
        "0.001",
        "--quiet",
        "--save-kept",
        kf_s,
    ]);
    assert!(out.status.success());
    std::fs::write(kf.join("notes.txt"), "mine").unwrap();
    // DIR complete: the tables list every kf_* image in it, each `width` wide; notes.txt kept.
    let complete = |width: u32| -> bool {
        let Ok(text) = std::fs::read_to_string(kf.join("keyframes.csv")) else {
            return false;
        };
        let listed: BTreeSet<String> = text
            .lines()
            .skip(1)
            .map(|l| l.split(',').next().unwrap().to_string())
            .collect();
        let doc: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(kf.join("keyframes.json")).unwrap())
                .unwrap();
        let images: BTreeSet<String> = dir_names(&kf)
            .into_iter()
            .filter(|n| n.starts_with("kf_"))
            .collect();
        listed == images
            && doc["kept"] == images.len()
            && images.len() > 1000
            && std::fs::read_to_string(kf.join("notes.txt")).unwrap() == "mine"
            && images.iter().all(|n| {
                paths::jpeg_size(&std::fs::read(kf.join(n)).unwrap()).map(|s| s.0) == Some(width)
            })
    };
    assert!(complete(64));
    let plugins = paths::plugin_dir();
    for (i, (signal, code)) in [(None, 0), (Some("-TERM"), 143), (Some("-HUP"), 129)]
        .into_iter()
        .enumerate()
    {
        let before = snapshot(&kf);
        let width = 80 + 16 * i as u32;
        let mut c = command("env");
        c.args(["--default-signal=INT,TERM,HUP", PYTHON])
            .env("PYTHONPATH", pkg_dir())
            .env("GST_PLUGIN_PATH", plugins.path())
            .args(["-m", "leangate_client", &source(width)])
            .args([
                "--threshold",
                "0.001",
                "--quiet",
                "--overwrite",
                "--save-kept",
                kf_s,
            ])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped());
        let mut child = c.spawn().expect("spawn");
        let start = std::time::Instant::now();
        let (mut looks, mut missing, mut sent) = (0u64, Vec::new(), false);
        while child.try_wait().unwrap().is_none() {
            looks += 1;
            for n in ["keyframes.csv", "keyframes.json", "notes.txt"] {
                if !kf.join(n).exists() {
                    missing.push((start.elapsed().as_millis(), n));
                }
            }
            if let (Some(sig), false) = (signal, sent) {
                let swapping = staging_dirs(tmp.path())
                    .iter()
                    .any(|s| tmp.path().join(s).join("keyframes.json").exists());
                if swapping {
                    let id = child.id().to_string();
                    assert!(Command::new("kill")
                        .args([sig, &id])
                        .status()
                        .unwrap()
                        .success());
                    sent = true;
                }
            }
            assert!(start.elapsed().as_secs() < 120, "the run did not end");
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
        let out = child.wait_with_output().unwrap();
        let replaced = snapshot(&kf) != before;
        eprintln!(
            "run {i} ({signal:?}, {looks} looks): {}, DIR replaced: {replaced}\n{}",
            out.status,
            stderr(&out)
        );
        assert!(
            missing.is_empty(),
            "a reader found DIR without {:?} ({} times)",
            missing.first(),
            missing.len()
        );
        assert_eq!(staging_dirs(tmp.path()), Vec::<String>::new());
        assert_eq!(signal.is_some(), sent, "the swap was seen");
        // (A signal that came only once the run had ended, its summary printed, kills the
        // process as it would any other: rare, and not what this checks.)
        let late = std::os::unix::process::ExitStatusExt::signal(&out.status).is_some()
            && stdout(&out).contains("summary:");
        assert!(
            out.status.code() == Some(code) || late,
            "{signal:?}: {}",
            out.status
        );
        if signal.is_none() || replaced {
            assert!(complete(width), "DIR mixed: {:?}", dir_names(&kf).len());
        }
    }
}

/// The README's `LeanGateMeta` table names every field of the meta on a real buffer (the
/// GstStructure names) and every key of the dict the Python client yields for it (its own
/// column), and nothing else, so that neither can drift from the docs; each Python key is its
/// field's name with underscores, and `leangate_client.META_KEYS` lists the same keys.
#[test]
fn readme_metadata_table_documents_every_field_and_python_key() {
    if !python_ok() {
        return;
    }
    let readme = std::fs::read_to_string(repo().join("docs/element.md")).unwrap();
    let section = readme
        .split("## Metadata: `LeanGateMeta`")
        .nth(1)
        .expect("docs/element.md section `## Metadata: `LeanGateMeta``");
    let section = section.split("\n#").next().unwrap();
    let mut rows = section.lines().filter(|l| l.starts_with('|')).map(|l| {
        l.trim_matches('|')
            .split('|')
            .map(|c| c.trim().trim_matches('`').to_string())
            .collect::<Vec<String>>()
    });
    let header = rows.next().expect("a table");
    assert_eq!(header[..2], ["field", "Python key"], "{header:?}");
    let mut fields = BTreeSet::new();
    let mut keys = BTreeSet::new();
    for r in rows.filter(|r| !r[0].starts_with("---")) {
        let (field, key) = (r[0].as_str(), r[1].as_str());
        assert!(keys.insert(key.to_string()), "{key} twice");
        if field != "–" {
            assert_eq!(key, field.replace('-', "_"), "{r:?}");
            fields.insert(field.to_string());
        }
    }

    let script = r#"
import json, sys
from leangate_client import LeanGateSource, META_KEYS, META_NAME
from leangate_client._gst import Gst
keys = set()
with LeanGateSource("test://ball?num-buffers=8&width=160&height=120", model=sys.argv[1],
                    threshold=0.001, mode="annotate") as src:
    for f, m in src:
        keys |= set(m)
pipe = Gst.parse_launch("videotestsrc num-buffers=3 ! video/x-raw,width=160,height=120 ! "
                        f"leangate model={sys.argv[1]} mode=annotate ! appsink name=sink")
pipe.set_state(Gst.State.PLAYING)
fields = set()
for _ in range(3):
    sample = pipe.get_by_name("sink").emit("try-pull-sample", 10 * Gst.SECOND)
    s = sample.get_buffer().get_custom_meta(META_NAME).get_structure()
    fields |= {s.nth_field_name(i) for i in range(s.n_fields())}
pipe.set_state(Gst.State.NULL)
print(json.dumps({"keys": sorted(keys), "fields": sorted(fields), "META_KEYS": list(META_KEYS)}))
"#;
    let out = client_script(script, &[model()]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    let set = |k: &str| -> BTreeSet<String> {
        v[k].as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(set("keys"), keys, "README Python keys vs the client's dict");
    assert_eq!(
        set("fields"),
        fields,
        "README fields vs the buffer's LeanGateMeta"
    );
    assert_eq!(set("META_KEYS"), keys, "leangate_client.META_KEYS");
    assert!(keys.contains("frame") && keys.contains("pts"));
}

/// `leangate-client --version` and `reconstruct.py --version` say the project's version, the
/// same as the plugin's and the `leangate` CLI's (one workspace version).
#[test]
fn the_python_tools_say_their_version() {
    if !python_ok() {
        return;
    }
    let want = env!("CARGO_PKG_VERSION");
    let o = client_module(&["--version"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stdout(&o).trim(), format!("leangate-client {want}"));
    let o = run({
        let mut c = command(PYTHON);
        c.arg(repo().join("pipelines/reconstruct.py"))
            .arg("--version");
        c
    });
    assert!(
        stdout(&o).trim().ends_with(&format!(" {want}")),
        "{}",
        stdout(&o)
    );
}

/// The package's modules import one another without a cycle, counting the imports inside
/// functions too (a cycle works until the order of first imports changes, then fails at import).
/// Parsed, not imported: no bindings needed.
#[test]
fn the_python_package_has_no_import_cycle() {
    let script = r#"
import ast, pathlib, sys
pkg = pathlib.Path(sys.argv[1])
mods = {p.stem for p in pkg.glob("*.py")}
graph = {}
for m in mods:
    deps = set()
    for node in ast.walk(ast.parse((pkg / f"{m}.py").read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            if node.module:
                deps.add(node.module.split(".")[0])
            else:
                for a in node.names:
                    deps.add(a.name if a.name in mods else "__init__")
    graph[m] = deps & mods - {m}
state = {}
def visit(m, path):
    if state.get(m) == 1:
        sys.exit("import cycle: " + " -> ".join(path[path.index(m):] + [m]))
    if state.get(m) == 2:
        return
    state[m] = 1
    for d in sorted(graph[m]):
        visit(d, path + [m])
    state[m] = 2
for m in sorted(graph):
    visit(m, [])
edges = sum(len(d) for d in graph.values())
print(f"{len(graph)} modules, {edges} imports, no cycle")
"#;
    let out = Command::new(PYTHON)
        .args(["-c", script])
        .arg(repo().join("pipelines/leangate_client"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("no cycle"),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The names in `dir` that look like a leftover temporary output file (`.NAME.XXXXXXXX.tmp*`).
fn temp_files(dir: &Path) -> Vec<String> {
    dir_names(dir)
        .into_iter()
        .filter(|n| n.starts_with('.') && n.contains(".tmp"))
        .collect()
}

/// `--csv OUT` loses nothing. Checked before anything is opened: OUT the input video itself
/// (it used to be truncated to a CSV header), a path inside the --save-kept DIR (the saver's own
/// keyframes.csv replaced it), a directory that does not exist: one line naming it, exit 2, the
/// file untouched. Written to a temporary file beside OUT that replaces it only when the run
/// succeeds: a run that fails (not a video) or is interrupted (SIGINT, SIGTERM midway) leaves
/// an earlier OUT byte for byte and no temporary file. A write error (`/dev/full`) is one
/// line, not a traceback; a special file (/dev/stdout) is written directly.
#[test]
fn csv_output_is_checked_up_front_and_replaced_only_by_a_successful_run() {
    if !python_ok() {
        return;
    }
    let Some(clip) = paths::shared_data("cotracker_clips/apple.mp4") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let ball = "test://ball?num-buffers=12&width=160&height=120";
    let refused = |o: &Output, expect: &str| {
        let err = stderr(o);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(
            err.starts_with("leangate-client: error: ") && err.contains(expect),
            "expected {expect:?} in {err}"
        );
        assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
        assert!(!err.contains("Traceback"), "{err}");
    };

    // The input as the CSV.
    let video = dir.join("clip.mp4");
    std::fs::copy(&clip, &video).unwrap();
    let original = std::fs::read(&video).unwrap();
    let v = video.to_str().unwrap();
    refused(
        &client_module(&[v, "--quiet", "--csv", v]),
        &format!("--csv {v} is the input, which would be overwritten"),
    );
    assert!(
        std::fs::read(&video).unwrap() == original,
        "the input is untouched"
    );
    // Also through another name (a symbolic link) and a file:// URI.
    let alias = dir.join("alias.csv");
    std::os::unix::fs::symlink(&video, &alias).unwrap();
    let uri = format!("file://{v}");
    refused(
        &client_module(&[&uri, "--quiet", "--csv", alias.to_str().unwrap()]),
        "is the input",
    );
    assert!(std::fs::read(&video).unwrap() == original);

    // Inside the --save-kept DIR (its keyframes.csv, or any other name): refused, DIR not made.
    let kf = dir.join("kf");
    for name in ["keyframes.csv", "scores.csv"] {
        let csv = kf.join(name);
        refused(
            &client_module(&[
                ball,
                "--quiet",
                "--save-kept",
                kf.to_str().unwrap(),
                "--overwrite",
                "--csv",
                csv.to_str().unwrap(),
            ]),
            &format!("lies in the --save-kept directory {}", kf.display()),
        );
        assert!(!kf.exists());
    }
    // A directory that does not exist, and a directory as OUT.
    let missing = dir.join("nodir/x.csv");
    refused(
        &client_module(&[ball, "--quiet", "--csv", missing.to_str().unwrap()]),
        &format!(
            "the directory {} does not exist",
            dir.join("nodir").display()
        ),
    );
    refused(
        &client_module(&[ball, "--quiet", "--csv", dir.to_str().unwrap()]),
        "is a directory",
    );

    // An earlier CSV survives a failed run.
    let prev = dir.join("prev.csv");
    std::fs::write(&prev, "an earlier run's rows\n").unwrap();
    let p = prev.to_str().unwrap();
    let [noise, _] = paths::not_videos(dir);
    let out = client_module(&[noise.to_str().unwrap(), "--quiet", "--csv", p]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert_eq!(std::fs::read(&prev).unwrap(), b"an earlier run's rows\n");
    assert!(temp_files(dir).is_empty(), "{:?}", dir_names(dir));

    // ... and an interrupted one (Ctrl-C, SIGTERM), caught while its rows are being written.
    let plugins = paths::plugin_dir();
    for (signal, code) in [("-INT", 130), ("-TERM", 143)] {
        let mut c = command("env");
        c.args(["--default-signal=INT,TERM", PYTHON])
            .env("PYTHONPATH", pkg_dir())
            .env("GST_PLUGIN_PATH", plugins.path())
            .args(["-m", "leangate_client"])
            .args([
                "test://ball?num-buffers=1000000&width=160&height=120",
                "--quiet",
                "--mode",
                "annotate",
                "--csv",
                p,
            ])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped());
        let mut child = c.spawn().expect("spawn");
        let start = std::time::Instant::now();
        loop {
            let written = temp_files(dir)
                .iter()
                .any(|n| std::fs::metadata(dir.join(n)).map(|m| m.len()).unwrap_or(0) > 0);
            if written {
                break;
            }
            assert!(
                start.elapsed().as_secs() < 60,
                "no temporary CSV beside {p} after 60 s: {:?}",
                dir_names(dir)
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        std::thread::sleep(std::time::Duration::from_millis(500));
        assert_eq!(std::fs::read(&prev).unwrap(), b"an earlier run's rows\n");
        let killed = Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let waited = std::time::Instant::now();
        while child.try_wait().unwrap().is_none() {
            if waited.elapsed().as_secs() >= 60 {
                child.kill().ok();
                panic!("the client did not end within 60 s of kill {signal}");
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        let out = child.wait_with_output().unwrap();
        assert_eq!(out.status.code(), Some(code), "{signal}: {}", stderr(&out));
        assert_eq!(
            std::fs::read(&prev).unwrap(),
            b"an earlier run's rows\n",
            "{signal}: the earlier CSV is as it was"
        );
        assert!(temp_files(dir).is_empty(), "{signal}: {:?}", dir_names(dir));
    }

    // A run that succeeds replaces it (rows for every frame), leaving no temporary file.
    let out = client_module(&[ball, "--quiet", "--mode", "annotate", "--csv", p]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(read_csv(&prev).len(), 12);
    assert!(temp_files(dir).is_empty(), "{:?}", dir_names(dir));

    // A write error is one line, exit 2 (it used to be a traceback from a `finally`).
    if Path::new("/dev/full").exists() {
        let out = client_module(&[ball, "--quiet", "--csv", "/dev/full"]);
        refused(&out, "--csv /dev/full: No space left on device");
    }
    // A special file is written directly.
    let out = client_module(&[ball, "--quiet", "--csv", "/dev/stdout"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stdout(&out).starts_with("frame,pts_ns,utility,keep,"),
        "{}",
        stdout(&out)
    );
}

/// `LeanGateSource` takes a `pathlib.Path` (any os.PathLike) as its source, as it does for
/// `model=` and `save_kept=` (it raised AttributeError: 'PosixPath' object has no attribute
/// 'startswith'); anything else that is not a str is a SetupError naming its type, not an
/// AttributeError.
#[test]
fn library_source_takes_a_path_object_and_names_a_wrong_type() {
    if !python_ok() {
        return;
    }
    let Some(clip) = paths::shared_data("cotracker_clips/apple.mp4") else {
        return;
    };
    let script = r#"
import json, pathlib, sys
from leangate_client import LeanGateSource, SetupError
src = LeanGateSource(pathlib.Path(sys.argv[1]), mode="annotate", arrays=False, max_frames=3)
with src:
    n = sum(1 for _ in src)
errors = []
for bad in (42, b"clip.mp4", None):
    try:
        LeanGateSource(bad)
        errors.append("accepted")
    except SetupError as e:
        errors.append(str(e))
print(json.dumps({"source": src.source, "received": n, "errors": errors}))
"#;
    let out = client_script(script, &[clip.to_str().unwrap()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(v["source"], clip.to_str().unwrap());
    assert_eq!(v["received"], 3, "{v}");
    let errors = v["errors"].as_array().unwrap();
    for (e, kind) in errors.iter().zip(["int", "bytes", "NoneType"]) {
        let e = e.as_str().unwrap();
        assert!(
            e.starts_with("source must be a file path (str or os.PathLike)")
                && e.contains(&format!("not {kind} ")),
            "{e}"
        );
    }
}

/// The example scripts take any file name (spaces, quotes, backslashes; a model path with a
/// space), and Ctrl-C to a `gst-launch -e ... | leangate_summarise` run (the foreground process
/// group, as a terminal sends it) still ends with the final statistics and the summary: the
/// reader used to die of the same SIGINT before gst-launch's last lines. scripts/demo.sh takes
/// relative paths from where it is run.
#[test]
fn example_scripts_take_any_path_and_a_ctrl_c_keeps_the_summary() {
    if !python_ok() {
        return;
    }
    let Some(clip) = paths::shared_data("cotracker_clips/apple.mp4") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let model_dir = dir.path().join("m dir");
    std::fs::create_dir(&model_dir).unwrap();
    let model_copy = model_dir.join("model.onnx");
    std::fs::copy(model(), &model_copy).unwrap();
    for name in ["a\"b c.mp4", "back\\slash.mp4", "it's $x!.mp4"] {
        let video = dir.path().join(name);
        std::fs::copy(&clip, &video).unwrap();
        let mut c = command("bash");
        c.arg("pipelines/file.sh")
            .arg(&video)
            .env("LEANGATE_MODEL", &model_copy);
        let out = run(c);
        assert!(out.status.success(), "{name}: {}", stderr(&out));
        let s = summary(&out);
        assert_eq!(num(&s, "frames-in"), 50, "{name}");
    }

    // Ctrl-C: a live source, SIGINT to the whole process group after a second.
    let script = format!(
        ". pipelines/common.sh; gst-launch-1.0 -e -m videotestsrc is-live=true ! \
         video/x-raw,width=160,height=120,framerate=30/1 ! leangate model=\"{}\" ! fakesink \
         | leangate_summarise",
        model()
    );
    let mut c = command("setsid");
    c.args(["bash", "-c", &script])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    let plugins = paths::plugin_dir();
    c.env("GST_PLUGIN_PATH", plugins.path());
    let child = c.spawn().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    let group = format!("-{}", child.id());
    let killed = Command::new("kill")
        .args(["-INT", "--", &group])
        .status()
        .unwrap();
    assert!(killed.success());
    let out = child.wait_with_output().unwrap();
    let text = stdout(&out);
    assert!(
        text.contains("EOS") && text.contains("summary: frames-in="),
        "{text}{}",
        stderr(&out)
    );

    // demo.sh: OUT_DIR and VIDEO relative to the working directory, a quote in OUT_DIR.
    let cwd = dir.path().join("work");
    std::fs::create_dir(&cwd).unwrap();
    std::fs::copy(&clip, cwd.join("clip.mp4")).unwrap();
    let release = repo().join("target/release/leangate");
    if !release.exists() {
        eprintln!("SKIPPED: demo.sh part: no target/release/leangate (make release)");
        return;
    }
    let mut c = Command::new("bash");
    c.arg(repo().join("scripts/demo.sh"))
        .arg("it's out")
        .current_dir(&cwd)
        .env("VIDEO", "clip.mp4")
        .env("MODEL", &model_copy);
    let out = run(c);
    let text = stdout(&out);
    assert!(out.status.success(), "{text}{}", stderr(&out));
    assert!(cwd.join("it's out/eval.json").is_file());
    assert!(text.contains("== frames in / kept: 50 / "), "{text}");
}

/// A started source that is not closed is shut down anyway: stopping the `for` loop early
/// (`break`, no `with`, no `close()`) or reaching `max_frames` closes it, and a started source
/// that is simply dropped is garbage-collected (its `__del__` closes it). Its pad probe and the
/// decoder's `pad-added` / `no-more-pads` handlers used to hold bound methods of the source, a
/// reference cycle through GObject closures that Python's collector cannot see: every
/// abandoned source stayed PLAYING with its streaming threads. `ended` is True only at a real
/// end-of-stream, not when `close()` from another thread stops the loop.
#[test]
fn abandoned_sources_are_shut_down_and_collected() {
    if !python_ok() || !have_elements(&["jpegenc", "avimux", "avidemux", "jpegdec"]) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let clip = tmp.path().join("clip.avi");
    let script = r#"
import gc, json, os, sys, threading, time, weakref
from leangate_client import LeanGateSource
from leangate_client import _gst
model, clip = sys.argv[1:]
Gst = _gst.Gst
_gst.ensure_plugin()
p = Gst.parse_launch("videotestsrc num-buffers=200 pattern=ball ! video/x-raw,width=160,height=120 "
                     f"! jpegenc ! avimux ! filesink location={clip}")
p.set_state(Gst.State.PLAYING)
p.get_bus().timed_pop_filtered(30 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
p.set_state(Gst.State.NULL)
del p

def threads():
    return len(os.listdir("/proc/self/task"))

def src(**kw):
    return LeanGateSource(clip, model=model, mode="annotate", arrays=False, **kw)

r = {}
for _ in range(2):  # closed properly: what lasts after a run (idle pool threads)
    with src(max_frames=1) as s:
        for _ in s:
            pass
gc.collect()
r["start"] = threads()
for _ in range(5):
    for f, m in src():
        break
    for f, m in src(max_frames=2):
        pass
gc.collect()
r["after_abandoned"] = threads()

s = src(max_frames=2)
r["max_frames_received"] = sum(1 for _ in s)
r["max_frames_stopped"] = s.gate is None
r["max_frames_ended"] = s.ended
s = src()
for f, m in s:
    break
r["break_stopped"] = s.gate is None
s = src()
s.start()
time.sleep(0.2)
w = weakref.ref(s)
del s
gc.collect()
r["dropped_collected"] = w() is None
r["after_dropped"] = threads()

s = src(timeout_s=20)
n = 0
for f, m in s:
    n += 1
    if n == 1:
        threading.Thread(target=s.close).start()
    time.sleep(0.01)
r["closed_from_thread"] = {"frames": n, "ended": s.ended}
s = src()
r["eos_frames"] = sum(1 for _ in s)
r["eos_ended"] = s.ended
s.close()
print(json.dumps(r))
"#;
    let out = client_script(script, &[model(), clip.display().to_string()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    let start = r["start"].as_u64().unwrap();
    // Each abandoned source used to keep ~5 streaming threads (10 sources: ~50); a few idle
    // threads of GStreamer's task pool may linger.
    for k in ["after_abandoned", "after_dropped"] {
        assert!(r[k].as_u64().unwrap() <= start + 6, "{k}: {r}");
    }
    assert_eq!(r["max_frames_received"], 2, "{r}");
    assert_eq!(
        r["max_frames_stopped"], true,
        "max_frames shuts the pipeline down: {r}"
    );
    assert_eq!(r["max_frames_ended"], false, "{r}");
    assert_eq!(
        r["break_stopped"], true,
        "a break shuts the pipeline down: {r}"
    );
    assert_eq!(
        r["dropped_collected"], true,
        "a dropped started source is collected: {r}"
    );
    let closed = &r["closed_from_thread"];
    assert!(closed["frames"].as_u64().unwrap() < 200, "{r}");
    assert_eq!(closed["ended"], false, "close() is no end-of-stream: {r}");
    assert_eq!(r["eos_frames"], 200, "{r}");
    assert_eq!(r["eos_ended"], true, "{r}");
}

/// `properties=` values are checked against the property's range (its GParamSpec): GLib only
/// printed a warning and the element ran with another value. NaN is refused for a float. The
/// limits themselves are accepted. `threads` has a limit (256; it had none, and 10,000 threads
/// took minutes to stop). `name` is refused: the source finds its element as `gate`
/// (a renamed gate made force_keyframe fail with a bare AttributeError).
#[test]
fn out_of_range_properties_and_a_name_are_refused() {
    if !python_ok() {
        return;
    }
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, SetupError
from leangate_client import _gst
model = sys.argv[1]
_gst.ensure_plugin()
el = _gst.Gst.ElementFactory.make("leangate", None)
spec = "test://ball?num-buffers=5&width=160&height=120"
def limits(k):
    p = el.find_property(k)
    return p.minimum, p.maximum
r = {"refused": [], "accepted": []}
for k, v in (("sharpness-wait", limits("sharpness-wait")[1] + 1), ("threshold", 1.5),
             ("feedback-rate", float("nan")), ("batch-size", limits("batch-size")[0] - 1),
             ("threads", 100000), ("name", "mygate")):
    try:
        with LeanGateSource(spec, model=model, properties={k: v}, max_frames=1) as s:
            for _ in s:
                pass
        r["refused"].append({"prop": k, "error": None})
    except SetupError as e:
        r["refused"].append({"prop": k, "value": repr(v), "limits": None if k == "name" else
                             "[%s, %s]" % limits(k), "error": str(e)})
# Long enough that the gate has frames left to act on when the loop holds its first one.
longer = "test://ball?num-buffers=60&width=160&height=120"
for k, v in (("threshold", limits("threshold")[0]), ("sharpness-wait", limits("sharpness-wait")[1])):
    with LeanGateSource(longer, model=model, mode="annotate", properties={k: v}) as s:
        for _ in s:
            r["accepted"].append({"prop": k, "value": v, "set": s.gate.get_property(k),
                                  "forced": s.force_keyframe()})
            break
print(json.dumps(r))
"#;
    let out = client_script(script, &[model()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    let refused = r["refused"].as_array().unwrap();
    assert_eq!(refused.len(), 6, "{r}");
    for e in refused {
        let msg = e["error"]
            .as_str()
            .unwrap_or_else(|| panic!("accepted: {e}"));
        let prop = e["prop"].as_str().unwrap();
        assert!(msg.contains(prop), "{msg}");
        if let Some(limits) = e["limits"].as_str() {
            let value = e["value"].as_str().unwrap();
            assert!(msg.contains(value) && msg.contains(limits), "{msg}");
        }
    }
    let accepted = r["accepted"].as_array().unwrap();
    assert_eq!(accepted.len(), 2, "{r}");
    for a in accepted {
        assert_eq!(a["set"], a["value"], "{a}");
        assert_eq!(a["forced"], true, "{a}");
    }
}

/// `properties=` values of another type than the property's are converted only when that is
/// exact, as gst-launch-1.0 reads text (`"false"` for a boolean is False, `"12"` or `"0x10"` for
/// an integer, `3.0` for an integer is 3), and refused otherwise with a SetupError naming the
/// property, the value and what the property takes. PyGObject alone converted silently:
/// `{"reject-junk": "false"}` ran with reject-junk=True (any non-empty string is true),
/// `{"max-gap": 2.7}` with 2, `{"sharpness-lookback": 3.5}` with 3 and `True` with 1.
#[test]
fn wrong_typed_properties_are_refused_or_converted_exactly() {
    if !python_ok() {
        return;
    }
    let script = r#"
import json, sys
from leangate_client import LeanGateSource, SetupError
model = sys.argv[1]
r = {"refused": [], "accepted": []}
for k, v in (("reject-junk", "maybe"), ("reject-junk", 2), ("max-gap", 2.7), ("max-gap", "2.7"),
             ("max-gap", True), ("sharpness-lookback", 3.5), ("sharpness-lookback", True),
             ("sharpness-lookback", "three"), ("threshold", True), ("threshold", "half"),
             ("mode", True), ("mode", "both"), ("model", 3)):
    try:
        with LeanGateSource("test://ball?num-buffers=5&width=160&height=120", model=model,
                            properties={k: v}, max_frames=1) as s:
            for _ in s:
                pass
        r["refused"].append({"prop": k, "value": repr(v), "error": None})
    except Exception as e:  # (PipelineError: the element got a value it then failed on)
        r["refused"].append({"prop": k, "value": repr(v), "error": str(e),
                             "type": type(e).__name__})
longer = "test://ball?num-buffers=60&width=160&height=120"
for k, v in (("reject-junk", "false"), ("reject-junk", "FALSE"), ("reject-junk", "no"),
             ("reject-junk", 0), ("geometry", "0"), ("screen", "f"), ("ort-spinning", "yes"),
             ("max-gap", "12"), ("max-gap", "0x10"), ("max-gap", 7.0),
             ("sharpness-lookback", 3.0), ("sharpness-lookback", "5"),
             ("threshold", "0.25"), ("threshold", 1), ("mode", "annotate"), ("mode", "1")):
    try:
        with LeanGateSource(longer, model=model, properties={k: v}) as s:
            for _ in s:
                got = s.gate.get_property(k)
                got = got.value_nick if k == "mode" else got
                r["accepted"].append({"prop": k, "value": v, "set": got})
                break
    except SetupError as e:
        r["accepted"].append({"prop": k, "value": v, "set": None, "error": str(e)})
print(json.dumps(r))
"#;
    let out = client_script(script, &[model()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    let refused = r["refused"].as_array().unwrap();
    assert_eq!(refused.len(), 13, "{r}");
    for e in refused {
        let prop = e["prop"].as_str().unwrap();
        let value = e["value"].as_str().unwrap();
        let msg = e["error"]
            .as_str()
            .unwrap_or_else(|| panic!("{prop}={value} was accepted: {e}"));
        assert_eq!(e["type"], "SetupError", "{e}");
        assert!(
            msg.starts_with(&format!(
                "bad value {value} for leangate property {prop}: it takes "
            )),
            "{msg}"
        );
    }
    let takes = |prop: &str| {
        refused.iter().find(|e| e["prop"] == prop).unwrap()["error"]
            .as_str()
            .unwrap()
            .to_string()
    };
    assert!(takes("max-gap").ends_with("an integer in [0, 4294967295]"));
    assert!(takes("reject-junk").contains("a boolean (True or False; as text true/false"));
    assert!(takes("mode").ends_with("one of: annotate, drop"));
    assert!(takes("threshold").ends_with("a number in [-1.0, 1.0]"));
    let expected = serde_json::json!([
        ["reject-junk", false],
        ["reject-junk", false],
        ["reject-junk", false],
        ["reject-junk", false],
        ["geometry", false],
        ["screen", false],
        ["ort-spinning", true],
        ["max-gap", 12],
        ["max-gap", 16],
        ["max-gap", 7],
        ["sharpness-lookback", 3],
        ["sharpness-lookback", 5],
        ["threshold", 0.25],
        ["threshold", 1.0],
        ["mode", "annotate"],
        ["mode", "annotate"],
    ]);
    let accepted: Vec<serde_json::Value> = r["accepted"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| serde_json::json!([a["prop"], a["set"]]))
        .collect();
    assert_eq!(serde_json::Value::Array(accepted), expected, "{r}");
}

/// Issue 52, the Python client's depth input: `leangate-client DIR --depth` gates a TUM-layout
/// RGB-D directory (the shared 7-Scenes frames) through `leangatedepthmux` into `leangate`,
/// every frame with its depth (the meta's `depth` "used", counted in the summary), and
/// `--save-kept` saves its keyframes as usual; the library call does the same.
#[test]
fn depth_sequence_directory_is_gated_with_its_depth() {
    if !python_ok() || !have_elements(&["multifilesrc", "jpegdec", "pngdec", "videoconvert"]) {
        return;
    }
    let Some(seq) = paths::shared_data("7scenes_redkitchen_dev") else {
        return;
    };
    let seq = seq.to_str().unwrap();
    let ann = client_module(&[seq, "--depth", "--mode", "annotate", "-v"]);
    assert!(ann.status.success(), "{}", stderr(&ann));
    let s = summary(&ann);
    assert_eq!(s["frames-in"], "60");
    assert_eq!(s["received"], "60");
    assert!(stderr(&ann)
        .contains("leangatedepthmux name=m intrinsics=585,585,320,240 depth-scale=1000"));
    let text = stdout(&ann);
    let frames: Vec<&str> = text.lines().filter(|l| l.starts_with("frame ")).collect();
    assert_eq!(frames.len(), 60, "{text}");
    for (i, l) in frames.iter().enumerate() {
        assert!(
            l.starts_with(&format!("frame {i} ")),
            "frames out of order: {l}"
        );
        if i > 0 {
            assert!(
                l.ends_with(" depth used"),
                "frame {i} not gated with depth: {l}"
            );
        }
    }
    let used: usize = s["depth-used"].parse().unwrap();
    assert!(used >= 59, "depth-used={used}");

    // --save-kept: the kept frames and their tables, the input named by its directory.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("kf");
    let drop = client_module(&[
        seq,
        "--depth",
        "--quiet",
        "--save-kept",
        out.to_str().unwrap(),
    ]);
    assert!(drop.status.success(), "{}", stderr(&drop));
    let s = summary(&drop);
    assert_eq!(s["frames-in"], "60");
    let kept: usize = s["kept"].parse().unwrap();
    assert!(kept >= 1 && s["saved"] == s["kept"], "{s:?}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("keyframes.json")).unwrap())
            .unwrap();
    assert_eq!(json["source"], seq);
    assert_eq!(json["frames_in"], 60);
    assert_eq!(json["frames"].as_array().unwrap().len(), kept);
    assert!(out.join("kf_000000.jpg").is_file());
    let csv = std::fs::read_to_string(out.join("keyframes.csv")).unwrap();
    assert!(csv.lines().next().unwrap().ends_with(",depth"), "{csv}");
    assert!(
        csv.lines().skip(1).all(|l| l.ends_with(",used")),
        "every keyframe gated with depth: {csv}"
    );

    // The library: open_input + attach_depth + SequenceGateSource.
    let script = r#"
import sys, collections
from leangate_client._inputs import open_input, attach_depth, SequenceGateSource
seq = open_input(sys.argv[1])
attach_depth(seq)
src = SequenceGateSource(seq.frames, depth_intrinsics=seq.intrinsics,
                         depth_scale=seq.depth_scale, mode="annotate", arrays=False)
with src:
    metas = [m for _, m in src]
used = collections.Counter(m["depth"] for m in metas[1:])["used"]
print([m["frame"] for m in metas] == list(range(60)), seq.depth_scale, used)
"#;
    let lib = client_script(script, &[seq]);
    assert!(lib.status.success(), "{}", stderr(&lib));
    assert_eq!(stdout(&lib).trim(), "True 1000.0 59");
}

/// `--depth` without depth to read: a video, a directory without depth.txt, a colour frame
/// without a depth image: one error line naming what is missing, exit 2, nothing written.
#[test]
fn depth_is_refused_without_a_depth_sequence() {
    if !python_ok() {
        return;
    }
    let Some(seq) = paths::shared_data("7scenes_redkitchen_dev") else {
        return;
    };
    let Some(clip) = paths::shared_data("cotracker_clips/apple.mp4") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("kf");
    let refused = |input: &Path, what: &str| {
        let o = client_module(&[
            input.to_str().unwrap(),
            "--depth",
            "--save-kept",
            out.to_str().unwrap(),
        ]);
        assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
        let err = stderr(&o);
        assert!(err.contains("depth") && err.contains(what), "{err}");
        assert!(stdout(&o).is_empty());
        assert!(!out.exists(), "--save-kept DIR created by a refused run");
    };
    refused(&clip, "(a video file)");
    // rgb.txt only: no depth.txt
    let bare = dir.path().join("bare");
    std::fs::create_dir(&bare).unwrap();
    let rgb = std::fs::read_to_string(seq.join("rgb.txt")).unwrap();
    let rgb_abs: String = rgb
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            let (t, p) = l.split_once(' ').unwrap();
            format!("{t} {}\n", seq.join(p).display())
        })
        .collect();
    std::fs::write(bare.join("rgb.txt"), &rgb_abs).unwrap();
    refused(&bare, "has no depth.txt");
    // depth.txt lacking the last frame's depth
    std::fs::write(bare.join("intrinsics.txt"), "585 585 320 240 1000\n").unwrap();
    let depth = std::fs::read_to_string(seq.join("depth.txt")).unwrap();
    let mut lines: Vec<String> = depth
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            let (t, p) = l.split_once(' ').unwrap();
            format!("{t} {}", seq.join(p).display())
        })
        .collect();
    lines.pop();
    std::fs::write(bare.join("depth.txt"), lines.join("\n")).unwrap();
    refused(&bare, "1 of 60 colour frames");
}

/// Python: decode the pictures at `paths` to arrays with GStreamer (`decodebin ! videoconvert`
/// to `fmt`: RGB or GRAY16_LE), the tests' way to get numpy frames without OpenCV.
const DECODE_PY: &str = r#"
import os, tempfile, numpy as np
import gi
gi.require_version("Gst", "1.0")
from gi.repository import Gst
Gst.init(None)
def decode(paths, fmt):
    d = tempfile.mkdtemp()
    ext = os.path.splitext(paths[0])[1]
    for k, p in enumerate(paths):
        os.symlink(os.path.abspath(p), f"{d}/{k:06d}{ext}")
    pl = Gst.parse_launch(
        f"multifilesrc location={d}/%06d{ext} index=0 stop-index={len(paths) - 1} ! decodebin "
        f"! videoconvert ! video/x-raw,format={fmt} ! appsink name=s sync=false")
    s = pl.get_by_name("s")
    pl.set_state(Gst.State.PLAYING)
    out = []
    while len(out) < len(paths):
        smp = s.emit("try-pull-sample", 10 * Gst.SECOND)
        assert smp is not None, "decoding stalled"
        st = smp.get_caps().get_structure(0)
        w, h = st.get_value("width"), st.get_value("height")
        b = smp.get_buffer()
        ok, mi = b.map(Gst.MapFlags.READ)
        bpp = 3 if fmt == "RGB" else 2
        stride = (w * bpp + 3) & ~3
        a = np.frombuffer(mi.data, np.uint8).reshape(h, stride)[:, : w * bpp].copy()
        b.unmap(mi)
        out.append(a.reshape(h, w, 3) if fmt == "RGB" else a.view("<u2"))
    pl.set_state(Gst.State.NULL)
    return out
"#;

/// `FrameGate`, the application's frames pushed one at a time with their depth: the same
/// decisions as the sequence client (`multifilesrc` and `leangatedepthmux`) on the first 150 real
/// frames of tum_fr1_desk; a frame pushed without depth is gated colour-only (`missing`) and waits for nothing
/// (the first, a run of ten, the last); raw arrays go in as well as JPEG bytes.
#[test]
fn frame_gate_takes_pushed_frames_with_their_depth() {
    if !python_ok() || !have_elements(&["jpegdec", "pngdec", "videoconvert", "appsrc"]) {
        return;
    }
    let Some(seq) = paths::shared_data("tum_fr1_desk") else {
        return;
    };
    let script = format!(
        "{DECODE_PY}{}",
        r#"
import sys, collections
from leangate_client import FrameGate
from leangate_client._inputs import open_input, attach_depth, SequenceGateSource
seq = open_input(sys.argv[1])
attach_depth(seq)
seq.frames = seq.frames[:150]
depths = decode([f.depth for f in seq.frames], "GRAY16_LE")
kw = dict(mode="annotate", arrays=False)
with SequenceGateSource(seq.frames, depth_intrinsics=seq.intrinsics,
                        depth_scale=seq.depth_scale, **kw) as src:
    want = [(m["frame"], m["keep"], m["reason"], m["depth"]) for _, m in src]
def run(images, fmt, skip=()):
    got = []
    with FrameGate(depth_intrinsics=seq.intrinsics, depth_scale=seq.depth_scale, **kw) as g:
        for i, (f, img, d) in enumerate(zip(seq.frames, images, depths)):
            pts = int(round(f.timestamp * 1e9))
            out = g.push(img, pts, depth=None if i in skip else d, format=fmt)
            got += [(m["frame"], m["keep"], m["reason"], m["depth"]) for _, m in out]
        got += [(m["frame"], m["keep"], m["reason"], m["depth"]) for _, m in g.finish()]
        assert g.stats.frames_in == len(seq.frames), g.stats
    return got
jpegs = [open(f.path, "rb").read() for f in seq.frames]
same = run(jpegs, "jpeg") == want
skip = {0, *range(20, 30), len(seq.frames) - 1}
lacking = run(jpegs, "jpeg", skip)
order = [r[0] for r in lacking] == list(range(len(seq.frames)))
marked = all(r[3] == ("none" if r[0] == 0 else "missing") for r in lacking if r[0] in skip)
others = collections.Counter(r[3] for r in lacking if r[0] not in skip)
rgb = run(decode([f.path for f in seq.frames], "RGB"), None)
print(same, order, marked, others["used"] + others["lost"] == len(seq.frames) - len(skip),
      [r[0] for r in rgb] == list(range(len(seq.frames))), sum(r[1] for r in rgb),
      sum(r[1] for r in want))
"#
    );
    let out = client_script(&script, &[seq.to_str().unwrap()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    let v: Vec<&str> = text.split_whitespace().collect();
    assert_eq!(v[..5], ["True"; 5], "{text}");
    // Raw RGB arrays: the frames decoded and converted before the gate (JPEG's I420 to RGB),
    // so its picture differs by rounding: the same keyframes within one.
    let (rgb, want): (i64, i64) = (v[5].parse().unwrap(), v[6].parse().unwrap());
    assert!(want >= 2 && (rgb - want).abs() <= 1, "{text}");
}

/// `FrameGate`: raw arrays of every format it takes, of odd sizes (rows padded to 4 bytes for
/// GStreamer) and changing size mid-stream, come out of the gate exactly as pushed (annotate mode,
/// RGB arrays); bad frames and calls raise a clear error before anything is sent, and the gate
/// goes on with the next good frame.
#[test]
fn frame_gate_raw_formats_strides_and_bad_input() {
    if !python_ok() || !have_elements(&["appsrc", "videoconvert"]) {
        return;
    }
    let script = r#"
import numpy as np
from leangate_client import FrameGate, NotRunningError, SetupError
rng = np.random.default_rng(1)
def rgb(h, w):
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
frames = [rgb(61, 83), rgb(61, 83), rgb(40, 30), rgb(41, 17)]
ok = []
with FrameGate(mode="annotate", model=None) as g:
    out = []
    for k, f in enumerate(frames):
        out += g.push(f, k * 40_000_000)
    # the same pictures in other layouts: BGR, BGRx, RGBA
    out += g.push(np.ascontiguousarray(frames[0][:, :, ::-1]), 200_000_000, format="BGR")
    bgrx = np.zeros((61, 83, 4), np.uint8); bgrx[..., :3] = frames[0][:, :, ::-1]
    out += g.push(bgrx, 240_000_000, format="BGRx")
    rgba = np.full((61, 83, 4), 255, np.uint8); rgba[..., :3] = frames[0]
    out += g.push(rgba, 280_000_000)
    errors = []
    def refused(exc, call, *words):
        try:
            call()
        except exc as e:
            errors.append(all(w in str(e) for w in words) or str(e))
        else:
            errors.append(f"not refused: {words}")
    refused(ValueError, lambda: g.push(rgb(8, 8), 280_000_000), "pts must increase")
    refused(TypeError, lambda: g.push(rgb(8, 8), 1.5e9), "int of nanoseconds")
    refused(ValueError, lambda: g.push(np.zeros((8, 8, 3), np.float32), 3 * 10**8), "format")
    refused(ValueError, lambda: g.push(np.zeros((8, 8, 2), np.uint8), 3 * 10**8), "(H, W, 3)")
    refused(ValueError, lambda: g.push(rgb(8, 8), 3 * 10**8, format="GRAY16_BE"), ">u2")
    refused(ValueError, lambda: g.push(rgb(8, 8), 3 * 10**8, format="GRAY8"), "GRAY8")
    refused(ValueError, lambda: g.push(b"\xff\xd8", 3 * 10**8), "format='jpeg'")
    refused(ValueError, lambda: g.push(b"\xff\xd8", 3 * 10**8, format="jpeg"), "takes raw")
    refused(TypeError, lambda: g.push([[1, 2]], 3 * 10**8), "numpy array")
    refused(SetupError, lambda: g.push(rgb(8, 8), 3 * 10**8, depth=np.zeros((8, 8), np.uint16)),
            "depth_intrinsics")
    out += g.push(frames[0], 320_000_000)  # the gate goes on
    out += g.finish()
    refused(NotRunningError, lambda: g.push(rgb(8, 8), 4 * 10**8), "ended")
back = [f for f, _ in out]
pts = [m["pts"] for _, m in out]
print(pts == [k * 40_000_000 for k in (0, 1, 2, 3, 5, 6, 7, 8)] or pts)
print(all(np.array_equal(a, b) for a, b in zip(back[:4], frames)),
      all(np.array_equal(b, frames[0]) for b in back[4:]))
print([m["frame"] for _, m in out] == list(range(8)), g.stats.frames_in)
print(errors)
for bad in (dict(depth_intrinsics=(1, 2, 3)), dict(depth_intrinsics=(500, 500, 3, 3), depth_scale=0),
            dict(queue=0), dict(max_frames=3)):
    try:
        FrameGate(**bad)
        print("accepted", bad)
    except SetupError as e:
        print("refused:", str(e).split(" ")[0])
"#;
    let out = client_script(script, &[] as &[&str]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "True", "{text}");
    assert_eq!(lines[1], "True True", "{text}");
    assert_eq!(lines[2], "True 8", "{text}");
    assert_eq!(lines[3], format!("[{}]", ["True"; 11].join(", ")), "{text}");
    assert_eq!(
        &lines[4..],
        [
            "refused: depth_intrinsics",
            "refused: depth_scale",
            "refused: queue",
            "refused: FrameGate"
        ],
        "{text}"
    );
}
