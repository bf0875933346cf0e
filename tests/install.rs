//! `make install` / `make uninstall` (scripts/install.sh) into a temporary prefix under a temporary
//! HOME, then used as a user would: a clean environment (no GST_PLUGIN_PATH, no ORT_DYLIB_PATH),
//! another working directory, and the checkout's `target/` and `.deps/` hidden (empty directories
//! mounted over them in a private mount namespace, where `unshare` allows it; the ONNX Runtime the
//! process loads is checked through the dynamic loader's own log either way).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The cdylib built with this test binary and the `leangate` CLI (`cargo build --workspace`).
fn built() -> (PathBuf, PathBuf) {
    let exe = std::env::current_exe().unwrap();
    let deps = exe.parent().unwrap();
    let profile = deps.parent().unwrap();
    let plugin = [
        deps.join("libgstleangate.so"),
        profile.join("libgstleangate.so"),
    ]
    .into_iter()
    .find(|p| p.exists())
    .expect("libgstleangate.so built (cargo build)");
    let cli = profile.join("leangate");
    assert!(
        cli.exists(),
        "{} missing: run `cargo build --workspace`",
        cli.display()
    );
    (plugin, cli)
}

fn install(home: &Path, prefix: &Path, uninstall: bool) -> Output {
    let (plugin, cli) = built();
    let mut c = Command::new("bash");
    c.arg(root().join("scripts/install.sh"));
    if uninstall {
        c.arg("--uninstall");
    }
    let out = c
        .env("HOME", home)
        .env_remove("XDG_DATA_HOME")
        .env_remove("GST_LINK_DIR")
        .env("PREFIX", prefix)
        .env("PLUGIN", plugin)
        .env("CLI", cli)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "install.sh failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Whether `unshare` can give us a private mount namespace here (root or user namespaces).
fn can_hide() -> bool {
    Command::new("unshare")
        .args(["--mount", "--map-root-user", "true"])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Run `args` in a clean environment as a user of the installed files would: HOME and PATH only
/// (plus `extra`), from `cwd`, with the checkout's target/ and .deps/ hidden when `hide`.
fn user_run(
    home: &Path,
    prefix: &Path,
    cwd: &Path,
    hide: bool,
    extra: &[(&str, &str)],
    args: &[&str],
) -> Output {
    let empty = home.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let mut c = if hide {
        let mut c = Command::new("unshare");
        c.args(["--mount", "--map-root-user", "sh", "-c"]).arg(
            "mount --bind \"$0\" \"$1\" && mount --bind \"$0\" \"$2\" && shift 3 && exec \"$@\"",
        );
        c.arg(&empty)
            .arg(root().join("target"))
            .arg(root().join(".deps"))
            .arg("--");
        c.args(args);
        c
    } else {
        let mut c = Command::new(args[0]);
        c.args(&args[1..]);
        c
    };
    c.env_clear()
        .env("HOME", home)
        .env(
            "PATH",
            format!(
                "{}:/usr/local/bin:/usr/bin:/bin",
                prefix.join("bin").display()
            ),
        )
        .current_dir(cwd);
    for (k, v) in extra {
        c.env(k, v);
    }
    c.output().unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

#[test]
fn make_install_runs_from_the_installed_files_alone_and_uninstall_removes_them() {
    let tmp = tempfile::tempdir().unwrap();
    let home = tmp.path().join("home");
    let prefix = home.join(".local");
    let work = tmp.path().join("work");
    std::fs::create_dir_all(&work).unwrap();
    install(&home, &prefix, false);

    let link = home.join(".local/share/gstreamer-1.0/plugins/libgstleangate.so");
    let installed = [
        prefix.join("lib/gstreamer-1.0/libgstleangate.so"),
        prefix.join("lib/leangate/libonnxruntime.so"),
        prefix.join("lib/leangate/python/leangate_client/__init__.py"),
        prefix.join("bin/leangate"),
        prefix.join("bin/leangate-client"),
        link.clone(),
    ];
    for f in &installed {
        assert!(f.exists(), "{} not installed", f.display());
    }
    assert_eq!(
        std::fs::read_link(&link).unwrap(),
        prefix.join("lib/gstreamer-1.0/libgstleangate.so")
    );

    let hide = can_hide();
    if !hide {
        eprintln!(
            "NOTE: unshare unavailable: target/ and .deps/ stay visible; the loader log is checked"
        );
    }
    let run =
        |extra: &[(&str, &str)], args: &[&str]| user_run(&home, &prefix, &work, hide, extra, args);

    // GStreamer finds the plugin through the link in the user's plugin directory.
    let o = run(&[], &["gst-inspect-1.0", "leangate"]);
    let t = text(&o);
    assert!(o.status.success(), "gst-inspect-1.0 leangate: {t}");
    assert!(
        t.contains("Drops video frames") && t.contains(&link.display().to_string()),
        "{t}"
    );

    // A pipeline scores with the ONNX Runtime installed beside the plugin (the loader's log
    // names the library it initialises), never the checkout's.
    let o = run(
        &[("LD_DEBUG", "libs")],
        &[
            "gst-launch-1.0",
            "-q",
            "videotestsrc",
            "num-buffers=20",
            "pattern=ball",
            "!",
            "video/x-raw,width=96,height=64",
            "!",
            "leangate",
            "mode=annotate",
            "!",
            "fakesink",
        ],
    );
    let t = text(&o);
    assert!(
        o.status.success(),
        "pipeline with the installed plugin: {t}"
    );
    let ort = prefix.join("lib/leangate/libonnxruntime.so");
    assert!(
        t.contains(&format!("calling init: {}", ort.display())),
        "ONNX Runtime not loaded from {}: {}",
        ort.display(),
        t.lines()
            .filter(|l| l.contains("onnxruntime"))
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert!(!t.contains(&format!("calling init: {}", root().display())));

    // The CLI and the Python client from $PREFIX/bin, on a clip made here.
    let o = run(&[], &["leangate", "--help"]);
    assert!(o.status.success(), "leangate --help: {}", text(&o));
    let o = run(
        &[],
        &[
            "gst-launch-1.0",
            "-q",
            "videotestsrc",
            "num-buffers=30",
            "pattern=ball",
            "!",
            "video/x-raw,width=96,height=64,framerate=30/1",
            "!",
            "jpegenc",
            "!",
            "avimux",
            "!",
            "filesink",
            "location=clip.avi",
        ],
    );
    assert!(o.status.success(), "making the clip: {}", text(&o));
    let o = run(&[], &["leangate-client", "clip.avi"]);
    let t = text(&o);
    assert!(o.status.success(), "leangate-client clip.avi: {t}");
    assert!(
        t.contains("frames-in=30"),
        "leangate-client reports the 30 frames: {t}"
    );

    install(&home, &prefix, true);
    for f in &installed {
        assert!(
            !f.exists() && f.symlink_metadata().is_err(),
            "{} left behind",
            f.display()
        );
    }
    let o = run(&[], &["gst-inspect-1.0", "leangate"]);
    assert!(
        !o.status.success(),
        "leangate still found after uninstall: {}",
        text(&o)
    );
}
