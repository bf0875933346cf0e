//! `make install` / `make uninstall` (scripts/install.sh) into a temporary prefix under a temporary
//! HOME, then used as a user would: a clean environment (no GST_PLUGIN_PATH, no ORT_DYLIB_PATH),
//! another working directory, and the checkout's `target/`, `.deps/`, `pipelines/` and `models/`
//! hidden (empty directories mounted over them in a private mount namespace, where `unshare`
//! allows it; the ONNX Runtime the process loads is checked through the dynamic loader's own log
//! either way). Then what install must not do: write outside PREFIX for a non-standard prefix,
//! replace a file it did not make, leave half an install after a failure, remove what it did not
//! write, run cargo under `make install`.

use std::ffi::OsStr;
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

/// Run scripts/install.sh (`--uninstall` when `uninstall`) with HOME = `home` and PREFIX =
/// `prefix` (any spelling), installing the builds of this test; `env` adds variables
/// (GST_LINK_DIR is unset unless given).
fn installer(
    home: &Path,
    prefix: impl AsRef<OsStr>,
    uninstall: bool,
    env: &[(&str, &OsStr)],
) -> Output {
    let (plugin, cli) = built();
    let mut c = Command::new("bash");
    c.arg(root().join("scripts/install.sh"));
    if uninstall {
        c.arg("--uninstall");
    }
    c.env("HOME", home)
        .env_remove("XDG_DATA_HOME")
        .env_remove("GST_LINK_DIR")
        .env("PREFIX", prefix)
        .env("PLUGIN", plugin)
        .env("CLI", cli);
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

/// [`installer`], which must succeed.
fn install(home: &Path, prefix: impl AsRef<OsStr>, uninstall: bool) -> Output {
    let out = installer(home, prefix, uninstall, &[]);
    assert!(out.status.success(), "install.sh failed: {}", text(&out));
    out
}

/// Every path under `dir` (relative, sorted; symlinks not followed), with `@` after a link and
/// `/` after a directory.
fn tree(dir: &Path) -> Vec<String> {
    fn walk(base: &Path, dir: &Path, out: &mut Vec<String>) {
        let Ok(rd) = std::fs::read_dir(dir) else {
            return;
        };
        for e in rd {
            let p = e.unwrap().path();
            let rel = p.strip_prefix(base).unwrap().display().to_string();
            let m = p.symlink_metadata().unwrap();
            if m.is_symlink() {
                out.push(format!("{rel}@"));
            } else if m.is_dir() {
                out.push(format!("{rel}/"));
                walk(base, &p, out);
            } else {
                out.push(rel);
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// The directory GStreamer scans system-wide (`pkg-config --variable=pluginsdir`), listed now;
/// on drop, any new entry linking into `tmp` (what the old installer left there) is removed.
struct SystemPluginDir {
    dir: PathBuf,
    before: Vec<String>,
    tmp: PathBuf,
}

impl SystemPluginDir {
    fn new(tmp: &Path) -> SystemPluginDir {
        let o = Command::new("pkg-config")
            .args(["--variable=pluginsdir", "gstreamer-1.0"])
            .output()
            .unwrap();
        let dir = PathBuf::from(String::from_utf8_lossy(&o.stdout).trim());
        assert!(
            dir.is_dir(),
            "pkg-config names no plugin directory: {}",
            text(&o)
        );
        let before = tree_top(&dir);
        SystemPluginDir {
            dir,
            before,
            tmp: tmp.to_path_buf(),
        }
    }

    fn unchanged(&self) -> bool {
        tree_top(&self.dir) == self.before
    }
}

impl Drop for SystemPluginDir {
    fn drop(&mut self) {
        for name in tree_top(&self.dir) {
            let p = self.dir.join(&name);
            if !self.before.contains(&name)
                && std::fs::read_link(&p).is_ok_and(|t| t.starts_with(&self.tmp))
            {
                let _ = std::fs::remove_file(&p);
            }
        }
    }
}

/// The names in `dir` (not recursive), sorted.
fn tree_top(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Whether `unshare` can give us a private mount namespace here (root or user namespaces).
fn can_hide() -> bool {
    Command::new("unshare")
        .args(["--mount", "--map-root-user", "true"])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// What of the checkout a user of the installed files does not have: the builds, ONNX Runtime,
/// the Python sources (the reconstruction consumer among them) and the models.
const HIDDEN: [&str; 4] = ["target", ".deps", "pipelines", "models"];

/// Run `args` in a clean environment as a user of the installed files would: HOME and PATH only
/// (plus `extra`), from `cwd`, with the checkout's [`HIDDEN`] directories hidden when `hide`.
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
            "e=$1; shift; while [ \"$1\" != -- ]; do mount --bind \"$e\" \"$1\" || exit 1; \
             shift; done; shift; exec \"$@\"",
        );
        c.args(["sh".as_ref(), empty.as_os_str()]);
        for d in HIDDEN {
            c.arg(root().join(d));
        }
        c.arg("--").args(args);
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
        prefix.join("lib/leangate/python/reconstruct.py"),
        prefix.join("lib/leangate/install-manifest"),
        prefix.join("share/doc/leangate/models/README.md"),
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
            "NOTE: unshare unavailable: the checkout stays visible; the loader log is checked"
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

    // `leangate eval --reconstruct` runs the consumer installed beside the CLI (the checkout's
    // pipelines/ is hidden), and looks for pycolmap in LEANGATE_SFM_PYTHON, else
    // /usr/bin/python3: never the checkout's .venv-sfm.
    let o = run(
        &[],
        &[
            "leangate", "synth", "--out", "seq", "--frames", "24", "--width", "160", "--height",
            "120", "--motion", "pan",
        ],
    );
    assert!(o.status.success(), "leangate synth: {}", text(&o));
    let eval = ["leangate", "eval", "--sequence", "seq", "--reconstruct"];
    let system_has_pycolmap = Command::new("/usr/bin/python3")
        .args(["-c", "import pycolmap"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !system_has_pycolmap {
        let o = run(&[], &eval);
        let t = text(&o);
        assert!(!o.status.success(), "{t}");
        assert!(
            t.contains("pycolmap is not importable by `/usr/bin/python3`")
                && t.contains("pip install pycolmap")
                && !t.contains(&root().join(".venv-sfm").display().to_string()),
            "{t}"
        );
    }
    let venv = root().join(".venv-sfm/bin/python");
    let venv_ok = Command::new(&venv)
        .args(["-c", "import pycolmap"])
        .output()
        .is_ok_and(|o| o.status.success());
    if venv_ok {
        // A Python with pycolmap that logs what it is asked to run.
        let log = tmp.path().join("python.log");
        let py = tmp.path().join("sfm-python");
        std::fs::write(
            &py,
            format!(
                "#!/bin/sh\nprintf '%s\\n' \"$1\" >>'{}'\nexec '{}' \"$@\"\n",
                log.display(),
                venv.display()
            ),
        )
        .unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&py, std::fs::Permissions::from_mode(0o755)).unwrap();
        let py_s = py.display().to_string();
        let o = run(
            &[("LEANGATE_SFM_PYTHON", &py_s)],
            &[&eval[..], &["--dense-every", "3", "--json", "r.json"]].concat(),
        );
        let t = text(&o);
        assert!(o.status.success(), "installed eval --reconstruct: {t}");
        let json = std::fs::read_to_string(work.join("r.json")).unwrap();
        assert!(
            t.contains("reconstruction (COLMAP")
                && json.contains(&format!("{py_s:?}"))
                && json.contains("\"sfm_seconds\"")
                && !json.contains("sfm_error"),
            "the installed consumer ran COLMAP for every policy: {t}\n{json}"
        );
        let script = prefix.join("lib/leangate/python/reconstruct.py");
        let runs: Vec<String> = std::fs::read_to_string(&log)
            .unwrap()
            .lines()
            .filter(|l| *l != "-c")
            .map(str::to_string)
            .collect();
        assert!(
            !runs.is_empty() && runs.iter().all(|l| Path::new(l) == script),
            "the consumer run is {script:?}: {runs:?}"
        );
    } else {
        eprintln!(
            "SKIPPED the installed eval --reconstruct run: {} cannot import pycolmap (make setup)",
            venv.display()
        );
    }

    let o = install(&home, &prefix, true);
    assert!(text(&o).contains("removed LeanGate"), "{}", text(&o));
    for f in &installed {
        assert!(
            !f.exists() && f.symlink_metadata().is_err(),
            "{} left behind",
            f.display()
        );
    }
    // The directories install created went with it: ~/.local did not exist before.
    assert!(!prefix.exists(), "left behind: {:?}", tree(&prefix));
    let o = run(&[], &["gst-inspect-1.0", "leangate"]);
    assert!(
        !o.status.success(),
        "leangate still found after uninstall: {}",
        text(&o)
    );
}

/// The paths of a temporary test tree: HOME, and a directory outside it; with a space in them.
fn dirs() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let home = tmp.path().join("home dir");
    let outside = tmp.path().join("opt dir");
    std::fs::create_dir_all(&home).unwrap();
    std::fs::create_dir_all(&outside).unwrap();
    (tmp, home, outside)
}

/// Nothing outside a non-standard PREFIX: not the system plugin directory (these tests run as
/// root, where the installer used to link a temporary prefix's plugin there, leaving a dangling
/// link once it was deleted), not the user's. GST_LINK_DIR names a directory explicitly.
#[test]
fn a_prefix_other_than_the_standard_ones_gets_no_link_outside_it() {
    let (tmp, home, outside) = dirs();
    let system = SystemPluginDir::new(tmp.path());
    let user_dir = home.join(".local/share/gstreamer-1.0/plugins");
    let prefix = outside.join("leangate");
    let o = install(&home, &prefix, false);
    let t = text(&o);
    assert!(
        system.unchanged(),
        "install wrote into {}: {:?} (was {:?})",
        system.dir.display(),
        tree_top(&system.dir),
        system.before
    );
    assert!(!home.join(".local").exists(), "wrote into HOME: {t}");
    assert!(
        t.contains("no link made") && t.contains("GST_PLUGIN_PATH="),
        "{t}"
    );
    assert!(prefix.join("lib/gstreamer-1.0/libgstleangate.so").is_file());
    install(&home, &prefix, true);
    assert!(!prefix.exists(), "left behind: {:?}", tree(&prefix));

    // A prefix under HOME other than ~/.local: no link either.
    let prefix = home.join("apps/leangate");
    let t = text(&install(&home, &prefix, false));
    assert!(t.contains("no link made") && !user_dir.exists(), "{t}");
    install(&home, &prefix, true);
    assert!(!home.join("apps").exists(), "{:?}", tree(&home));

    // GST_LINK_DIR=DIR: the link there, recorded, and removed with the directories it needed.
    let links = outside.join("links/gst");
    let o = installer(
        &home,
        &prefix,
        false,
        &[("GST_LINK_DIR", links.as_os_str())],
    );
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(
        std::fs::read_link(links.join("libgstleangate.so")).unwrap(),
        prefix.join("lib/gstreamer-1.0/libgstleangate.so")
    );
    install(&home, &prefix, true);
    assert!(!outside.join("links").exists() && !prefix.exists());
    assert!(system.unchanged());
}

/// A regular file, or a link to something else, where the link would go: install refuses before
/// writing anything and leaves it; uninstall never removes it, nor a file of ours changed since.
#[test]
fn a_file_install_did_not_make_is_never_replaced_or_removed() {
    let (tmp, home, outside) = dirs();
    let prefix = home.join(".local");
    let user_dir = home.join(".local/share/gstreamer-1.0/plugins");
    let link = user_dir.join("libgstleangate.so");
    std::fs::create_dir_all(&user_dir).unwrap();
    let other = outside.join("libgstleangate.so");
    std::fs::write(&other, "another build").unwrap();
    for foreign in ["file", "link"] {
        if foreign == "file" {
            std::fs::write(&link, "someone's own build").unwrap();
        } else {
            std::os::unix::fs::symlink(&other, &link).unwrap();
        }
        let before = tree(tmp.path());
        let o = installer(&home, &prefix, false, &[]);
        let t = text(&o);
        assert!(!o.status.success(), "{foreign}: {t}");
        assert!(
            t.contains("refusing to install") && t.contains(&link.display().to_string()),
            "{t}"
        );
        assert_eq!(
            tree(tmp.path()),
            before,
            "{foreign}: install wrote something"
        );
        let t = text(&install(&home, &prefix, true));
        assert!(
            t.contains("nothing installed") && !t.contains("removed LeanGate"),
            "{t}"
        );
        assert_eq!(
            tree(tmp.path()),
            before,
            "{foreign}: uninstall removed something"
        );
        std::fs::remove_file(&link).unwrap();
    }

    // Installed, then replaced by the user (the link by a file, the client edited): kept.
    install(&home, &prefix, false);
    std::fs::remove_file(&link).unwrap();
    std::fs::write(&link, "mine now").unwrap();
    let client = prefix.join("bin/leangate-client");
    let mut edited = std::fs::read_to_string(&client).unwrap();
    edited.push_str("# edited\n");
    std::fs::write(&client, &edited).unwrap();
    let t = text(&install(&home, &prefix, true));
    assert!(t.contains(&format!("kept {}", link.display())), "{t}");
    assert_eq!(std::fs::read_to_string(&link).unwrap(), "mine now");
    assert_eq!(std::fs::read_to_string(&client).unwrap(), edited);
    assert!(!prefix.join("bin/leangate").exists() && !prefix.join("lib").exists());
}

/// Uninstall finds the install whatever the spelling of PREFIX, removes what install wrote and
/// the directories it created (its Python caches too), keeps what was there before, and with
/// nothing installed removes nothing and says so.
#[test]
fn uninstall_removes_exactly_what_install_wrote_under_any_spelling_of_prefix() {
    let (_tmp, home, _) = dirs();
    let prefix = home.join(".local");
    // Already there: bin/ with a program of the same name (no install yet), lib/ empty.
    std::fs::create_dir_all(prefix.join("bin")).unwrap();
    std::fs::create_dir_all(prefix.join("lib")).unwrap();
    std::fs::write(
        prefix.join("bin/leangate"),
        "#!/bin/sh\necho someone else\n",
    )
    .unwrap();
    std::fs::write(prefix.join("bin/other-tool"), "#!/bin/sh\n").unwrap();
    let before = tree(&home);
    for _ in 0..2 {
        let t = text(&install(&home, "~/.local//", true));
        assert!(
            t.contains("nothing installed") && !t.contains("removed LeanGate"),
            "{t}"
        );
        assert_eq!(tree(&home), before);
    }
    std::fs::remove_file(prefix.join("bin/leangate")).unwrap();
    let before = tree(&home);

    let spellings = [
        (
            format!("{}/x/..//.local/", home.display()),
            "~/.local//".to_string(),
        ),
        (
            "~/.local".to_string(),
            format!("{}/./.local///", home.display()),
        ),
    ];
    for (at_install, at_uninstall) in spellings {
        install(&home, &at_install, false);
        install(&home, &at_install, false); // twice: the second replaces the first
        let link = home.join(".local/share/gstreamer-1.0/plugins/libgstleangate.so");
        assert_eq!(
            std::fs::read_link(&link).unwrap(),
            prefix.join("lib/gstreamer-1.0/libgstleangate.so")
        );
        // Python writes its caches beside the installed modules.
        let o = Command::new("/usr/bin/python3")
            .env_clear()
            .env("PYTHONPATH", prefix.join("lib/leangate/python"))
            .args(["-c", "import leangate_client.reconstruct"])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", text(&o));
        assert!(prefix
            .join("lib/leangate/python/leangate_client/__pycache__")
            .is_dir());

        let t = text(&install(&home, &at_uninstall, true));
        assert!(t.contains("removed LeanGate"), "{t}");
        assert_eq!(tree(&home), before, "uninstall: {t}");
        let t = text(&install(&home, &at_uninstall, true));
        assert!(t.contains("nothing installed"), "a second uninstall: {t}");
    }
}

/// An install that fails half-way (a file where bin/ must go, after lib/ is written) leaves
/// nothing of itself, exits nonzero naming the problem; over an earlier install, a failed one
/// (its link directory cannot be made, the last step) leaves the earlier one as it was.
#[test]
fn a_failed_install_leaves_nothing_of_itself() {
    let (tmp, home, outside) = dirs();
    let prefix = outside.join("pre fix");
    std::fs::create_dir_all(&prefix).unwrap();
    std::fs::write(prefix.join("bin"), "a file where a directory must go").unwrap();
    let before = tree(tmp.path());
    let o = installer(&home, &prefix, false, &[]);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(
        t.contains(&format!(
            "cannot create the directory {}: a file is in the way",
            prefix.join("bin").display()
        )) && t.contains("nothing of this install is left"),
        "{t}"
    );
    assert_eq!(tree(tmp.path()), before, "{t}");
    std::fs::remove_file(prefix.join("bin")).unwrap();

    let links = outside.join("links");
    install(&home, &prefix, false);
    let manifest = prefix.join("lib/leangate/install-manifest");
    let first = std::fs::read_to_string(&manifest).unwrap();
    let installed = tree(tmp.path());
    std::fs::write(&links, "a file where the link directory must go").unwrap();
    let o = installer(
        &home,
        &prefix,
        false,
        &[("GST_LINK_DIR", links.join("gst").as_os_str())],
    );
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    let mut now = tree(tmp.path());
    now.retain(|p| !p.ends_with("/links"));
    assert_eq!(now, installed, "the earlier install changed: {t}");
    assert_eq!(std::fs::read_to_string(&manifest).unwrap(), first);
    install(&home, &prefix, true);
    assert_eq!(tree(&prefix), Vec::<String>::new());
}

/// `make install` only copies what `make release` built: with another HOME (as under `sudo`)
/// and no cargo on PATH it works; without the release build it says to run `make release`.
#[test]
fn make_install_only_copies_and_needs_no_toolchain() {
    let (_tmp, home, outside) = dirs();
    let (plugin, cli) = built();
    let prefix = outside.join("usr local");
    let make = |target: &str, plugin: &Path| {
        Command::new("make")
            .current_dir(root())
            .env_clear()
            .env("HOME", &home)
            .env("PATH", "/usr/bin:/bin")
            .env("PLUGIN", plugin)
            .env("CLI", &cli)
            .args(["-s", target])
            .arg(format!("PREFIX={}", prefix.display()))
            .output()
            .unwrap()
    };
    let dry = Command::new("make")
        .current_dir(root())
        .args(["-n", "install", "uninstall"])
        .output()
        .unwrap();
    let t = text(&dry);
    assert!(
        dry.status.success() && !t.contains("cargo") && !t.contains("setup.sh"),
        "make install runs more than the installer: {t}"
    );
    let o = make("install", &plugin);
    assert!(o.status.success(), "make install: {}", text(&o));
    assert!(prefix.join("bin/leangate").is_file());
    assert!(prefix.join("lib/leangate/install-manifest").is_file());
    let o = make("uninstall", &plugin);
    assert!(o.status.success(), "make uninstall: {}", text(&o));
    assert!(!prefix.exists(), "{:?}", tree(&prefix));

    let o = make("install", &outside.join("no-release/libgstleangate.so"));
    let t = text(&o);
    assert!(
        !o.status.success() && t.contains("run `make release` first"),
        "{t}"
    );
    assert!(!prefix.exists());
}

/// Installs into one PREFIX at the same time run one after the other (a lock on the prefix, no
/// file written for it): each succeeds, the manifest matches the disk, and one uninstall leaves
/// the prefix exactly as it was (four parallel installs used to fail half-way or leave a
/// manifest that missed directories another run made).
#[test]
fn concurrent_installs_into_one_prefix_take_turns() {
    let (_tmp, home, outside) = dirs();
    let prefix = outside.join("lg");
    let before = tree(&outside);
    let runs: Vec<_> = (0..3)
        .map(|_| {
            let (home, prefix) = (home.clone(), prefix.clone());
            std::thread::spawn(move || install(&home, &prefix, false))
        })
        .collect();
    for r in runs {
        let o = r.join().unwrap();
        assert!(o.status.success(), "{}", text(&o));
    }
    let o = install(&home, &prefix, true);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(tree(&outside), before, "{}", text(&o));
}

/// A user's own files where install would write (`bin/leangate-client`, a plugin of the same name
/// not from LeanGate) are refused before anything moves, and kept; a re-install interrupted just
/// after it moved a file aside puts it back (the rollback used to miss a backup recorded only
/// after its rename, leaving the earlier install without `__init__.py`).
#[test]
fn install_never_replaces_a_users_file_and_an_interrupted_reinstall_restores_the_old_one() {
    let (tmp, home, outside) = dirs();
    let prefix = outside.join("prefix");
    for (rel, mine) in [
        ("bin/leangate-client", "#!/bin/sh\necho my own script\n"),
        ("lib/gstreamer-1.0/libgstleangate.so", "someone's own build"),
    ] {
        let path = prefix.join(rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, mine).unwrap();
        let before = tree(tmp.path());
        let o = installer(&home, &prefix, false, &[]);
        let t = text(&o);
        assert!(!o.status.success(), "{rel}: {t}");
        assert!(
            t.contains("refusing to install")
                && t.contains(&path.display().to_string())
                && t.contains("not from a LeanGate install"),
            "{t}"
        );
        assert_eq!(tree(tmp.path()), before, "{rel}: install wrote something");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), mine);
        std::fs::remove_file(&path).unwrap();
    }

    // Interrupted while a re-install moves the old package's __init__.py aside: a `mv` that
    // renames, then signals its caller, as a Ctrl-C arriving at that moment would (and again when
    // the rollback moves it back: a second signal must not cut the rollback short). SIGTERM, which
    // the installer handles as it does SIGINT: a test run in the background has SIGINT ignored.
    install(&home, &prefix, false);
    let shim = outside.join("shim");
    std::fs::create_dir_all(&shim).unwrap();
    std::fs::write(
        shim.join("mv"),
        "#!/bin/bash\n/bin/mv \"$@\"; rc=$?\ncase \"$*\" in *__init__.py.leangate-old.*) \
         kill -TERM $PPID ;; esac\nexit $rc\n",
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(shim.join("mv"), std::fs::Permissions::from_mode(0o755)).unwrap();
    let path = format!(
        "{}:{}",
        shim.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let o = installer(&home, &prefix, false, &[("PATH", OsStr::new(&path))]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(130), "{t}");
    assert!(t.contains("undone"), "{t}");
    let package = prefix.join("lib/leangate/python/leangate_client");
    assert!(
        package.join("__init__.py").is_file(),
        "{:?}",
        tree(&package)
    );
    let left: Vec<String> = tree(&prefix)
        .into_iter()
        .filter(|p| p.contains("leangate-old"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
    let o = Command::new(prefix.join("bin/leangate-client"))
        .arg("--version")
        .env_clear()
        .env("HOME", &home)
        .env("PATH", "/usr/bin:/bin")
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "the earlier install works: {}",
        text(&o)
    );
    install(&home, &prefix, true);
}

/// `make install PREFIX=...` passes the prefix exactly as given: spaces, quotes and `$` (make
/// used to expand `$H` and the shell to choke on a `'`).
#[test]
fn make_install_takes_any_prefix_spelling() {
    let (_tmp, home, outside) = dirs();
    let (plugin, cli) = built();
    let prefix = outside.join("it's \"q\" $HOME_x");
    let make = |target: &str| {
        Command::new("make")
            .current_dir(root())
            .env_clear()
            .env("HOME", &home)
            .env("PATH", "/usr/bin:/bin")
            .env("PLUGIN", &plugin)
            .env("CLI", &cli)
            .args(["-s", target])
            .arg(format!("PREFIX={}", prefix.display()))
            .output()
            .unwrap()
    };
    let o = make("install");
    assert!(o.status.success(), "make install: {}", text(&o));
    assert!(
        prefix.join("bin/leangate").is_file(),
        "{:?}",
        tree(&outside)
    );
    let o = make("uninstall");
    assert!(o.status.success(), "make uninstall: {}", text(&o));
    assert!(!prefix.exists(), "{:?}", tree(&outside));
}
