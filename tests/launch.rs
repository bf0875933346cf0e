//! The plugin as a user runs it from the shell: `gst-inspect-1.0` / `gst-launch-1.0` on the built
//! `libgstleangate.so`.

mod common;

use std::path::PathBuf;
use std::process::Command;

/// target/debug (holds libgstleangate.so).
fn target_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    exe.parent().unwrap().parent().unwrap().to_path_buf()
}

fn gst_cmd(tool: &str) -> Command {
    let mut c = Command::new(tool);
    c.env("GST_PLUGIN_PATH", target_dir())
        .env("GST_REGISTRY", target_dir().join("test-registry.bin"));
    c
}

/// Run `c`, check that it succeeded (else fail with its output), return its stdout.
fn succeeds(c: &mut Command) -> String {
    let out = c.output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

#[test]
fn gst_inspect_documents_every_property() {
    let out = gst_cmd("gst-inspect-1.0").arg("leangate").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for p in common::PROPERTIES {
        assert!(
            text.contains(&format!("  {p}  ")) || text.contains(&format!("  {p} ")),
            "{p} not in gst-inspect output"
        );
    }
    assert!(text.contains("tau_keep") && text.contains("annotate"));
    // The model card it points at is where a user has it: the source's models/README.md, and
    // the copy `make install` puts under the prefix (tests/install.rs checks the copy is there).
    let flat = text.split_whitespace().collect::<Vec<_>>().join(" ");
    assert!(
        flat.contains("share/doc/leangate/models/README.md") && flat.contains("models/README.md"),
        "{flat}"
    );
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    assert!(root.join("models/README.md").is_file());
    let installer = std::fs::read_to_string(root.join("scripts/install.sh")).unwrap();
    assert!(
        installer.contains("share/doc/leangate"),
        "install.sh installs the card"
    );
}

#[test]
fn gst_launch_missing_model_fails_cleanly_with_the_path() {
    let out = gst_cmd("gst-launch-1.0")
        .args([
            "videotestsrc",
            "num-buffers=3",
            "!",
            "leangate",
            "model=/no/such/student.onnx",
            "!",
            "fakesink",
        ])
        .output()
        .unwrap();
    let err =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("/no/such/student.onnx"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn gst_launch_without_onnx_runtime_names_ort_dylib_path() {
    let out = gst_cmd("gst-launch-1.0")
        .env("ORT_DYLIB_PATH", "/nonexistent/libonnxruntime.so")
        .args(["videotestsrc", "num-buffers=3", "!", "leangate"])
        .arg(format!("model={}", common::fixture("mad.onnx")))
        .args(["!", "fakesink"])
        .output()
        .unwrap();
    let err =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("ORT_DYLIB_PATH=/nonexistent/libonnxruntime.so") && err.contains("make setup"),
        "{err}"
    );
}

#[test]
fn gst_launch_runs_a_real_pipeline() {
    let text = succeeds(
        gst_cmd("gst-launch-1.0")
            .args([
                "-m",
                "videotestsrc",
                "num-buffers=20",
                "pattern=ball",
                "!",
                "video/x-raw,width=160,height=120",
                "!",
                "leangate",
            ])
            .arg(format!("model={}", common::fixture("mad.onnx")))
            .args(["threshold=0.01", "!", "fakesink"]),
    );
    assert!(
        text.contains("leangate-stats") && text.contains("frames-in=(guint64)20"),
        "{text}"
    );
}

/// The README's keyframe-extraction pipeline (`... ! leangate ! videoconvert ! jpegenc !
/// multifilesink`) on a real clip: one decodable JPEG per kept frame, as many as the element's
/// `leangate-stats` counts, in the clip's size. (The fixture model, whose utility is a mean
/// absolute difference, keeps a number of frames that does not move with the embedded student.)
#[test]
fn gst_launch_writes_one_jpeg_per_kept_frame() {
    let Some(clip) = common::shared_data("cotracker_clips/bear.mp4") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let text = succeeds(
        gst_cmd("gst-launch-1.0")
            .args(["-m", "filesrc"])
            .arg(format!("location={}", clip.display()))
            .args(["!", "decodebin", "!", "leangate", "threshold=0.05"])
            .arg(format!("model={}", common::fixture("mad.onnx")))
            .arg("!")
            .args([
                "videoconvert",
                "!",
                "jpegenc",
                "quality=95",
                "!",
                "multifilesink",
            ])
            .arg(format!("location={}/kf_%06d.jpg", dir.path().display())),
    );
    let count = |field: &str| -> usize {
        let key = format!("{field}=(guint64)");
        let at = text
            .find(&key)
            .unwrap_or_else(|| panic!("no {field} in:\n{text}"));
        let digits: String = text[at + key.len()..]
            .chars()
            .take_while(char::is_ascii_digit)
            .collect();
        digits.parse().unwrap()
    };
    let (frames_in, kept) = (count("frames-in"), count("frames-kept"));
    assert_eq!(frames_in, 82, "bear.mp4 has 82 frames");
    assert!(kept > 1 && kept < frames_in, "{kept} kept of {frames_in}");
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    let expected: Vec<String> = (0..kept).map(|i| format!("kf_{i:06}.jpg")).collect();
    assert_eq!(names, expected, "one image per kept frame");
    for n in &names {
        let bytes = std::fs::read(dir.path().join(n)).unwrap();
        assert_eq!(common::jpeg_size(&bytes), Some((854, 480)), "{n}");
    }
}

/// A run leaves nothing of the user's machine behind it: in a fresh HOME (and no XDG_CACHE_HOME),
/// `videotestsrc ! leangate ! fakesink` with the embedded default on the CPU writes no file at
/// all. ONNX Runtime's own telemetry (a persistent device id and queued usage events under
/// `~/.cache/Microsoft/DeveloperTools/.onnxruntime`) is off, and the TensorRT engine cache
/// (`~/.cache/leangate/tensorrt`) is created only when TensorRT runs.
#[test]
fn gst_launch_in_a_fresh_home_writes_nothing_there() {
    let home = tempfile::tempdir().unwrap();
    let text = succeeds(
        gst_cmd("gst-launch-1.0")
            .env("HOME", home.path())
            .env_remove("XDG_CACHE_HOME")
            .env_remove("ORT_DISABLE_TELEMETRY")
            .env_remove("XDG_DATA_HOME")
            .env_remove("XDG_CONFIG_HOME")
            .args([
                "-m",
                "videotestsrc",
                "num-buffers=30",
                "pattern=ball",
                "!",
                "video/x-raw,width=320,height=240",
                "!",
                "leangate",
                "!",
                "fakesink",
            ]),
    );
    assert!(text.contains("frames-in=(guint64)30"), "{text}");
    let left = common::files_below(home.path());
    assert!(left.is_empty(), "left in HOME: {left:?}");
}

/// Every `gst-launch-1.0` line of the README runs as written, on a real clip: `walk.mp4` stands
/// for bear.mp4 (../shared), `other.onnx` for the shipped pair model, and the camera line's
/// `v4l2src` for 30 frames of `videotestsrc` with `autovideosink` as `fakesink` (no camera, no
/// display here). Each one gates every frame (its `leangate-stats` at EOS counts them); the
/// debug-log line prints one ` keep ` line per frame.
#[test]
fn every_readme_gst_launch_line_runs() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let clip = common::shared_data("cotracker_clips/bear.mp4");
    let model = root.join("models/leangate-s.onnx");
    let mut in_sh = false;
    let mut ran = 0;
    for line in readme.lines() {
        if line.starts_with("```") {
            in_sh = line == "```sh";
            continue;
        }
        if !in_sh || !line.contains("gst-launch-1.0") {
            continue;
        }
        // The command: from gst-launch-1.0 up to a comment, a redirection or a pipe.
        let debug = line.starts_with("GST_DEBUG=");
        let cmd = &line[line.find("gst-launch-1.0").unwrap() + "gst-launch-1.0".len()..];
        let cmd = cmd.split(" #").next().unwrap();
        let cmd = cmd
            .split(" 2>")
            .next()
            .unwrap()
            .split(" | ")
            .next()
            .unwrap();
        let mut args: Vec<String> = Vec::new();
        let mut frames = None;
        for t in cmd.split_whitespace() {
            match t {
                "location=walk.mp4" => match &clip {
                    Some(c) => {
                        args.push(format!("location={}", c.display()));
                        frames = Some(82);
                    }
                    None => break,
                },
                "model=other.onnx" => args.push(format!("model={}", model.display())),
                "v4l2src" => {
                    args.extend(["videotestsrc", "num-buffers=30"].map(String::from));
                    frames = Some(30);
                }
                "autovideosink" => args.push("fakesink".into()),
                _ => args.push(t.to_string()),
            }
        }
        let Some(frames) = frames else {
            eprintln!("SKIPPED without bear.mp4: {line}");
            continue;
        };
        let mut c = gst_cmd("gst-launch-1.0");
        c.args(&args);
        if debug {
            c.env("GST_DEBUG", "leangate:7");
        }
        let out = c.output().unwrap();
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        assert!(out.status.success(), "{line}\n{stdout}{stderr}");
        if debug {
            let keeps = stderr.lines().filter(|l| l.contains(" keep ")).count();
            assert_eq!(keeps, frames, "{line}: one ` keep ` line per frame");
        } else {
            assert!(
                stdout.contains(&format!("frames-in=(guint64){frames}")),
                "{line}: every frame gated\n{stdout}"
            );
        }
        ran += 1;
    }
    assert!(
        ran >= 2,
        "the README's gst-launch lines were found ({ran} ran)"
    );
}
