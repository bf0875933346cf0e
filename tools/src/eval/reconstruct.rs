//! `leangate eval --reconstruct`: what a reconstruction engine makes of each policy's frames.
//!
//! For every policy of the report (and a `dense` reference: every k-th frame) the kept frames
//! go, one policy after the other, into COLMAP's incremental SfM through the Python consumer
//! `pipelines/reconstruct.py --frames @LIST` (pycolmap: SIFT, exhaustive matching up to 40
//! images and sequential above, a shared PINHOLE camera from `intrinsics.txt` when the sequence
//! has one). Each policy's JSON entry gains:
//!
//! - `registered`: frames registered in the largest model; `models`: models COLMAP built;
//! - `ate_rmse_cm` (sequences with ground truth): RMSE of the registered camera centres against
//!   the ground-truth centres after the least-squares similarity alignment (Umeyama 1991, with
//!   scale: SfM has no metric scale), in centimetres, computed here ([`ate_rmse`]); None with
//!   fewer than 3 registered frames;
//! - `sfm_reproj_px` (mean reprojection error), `sfm_points`;
//! - `sfm_seconds`: COLMAP's own time (feature extraction + matching + mapping, as the consumer
//!   measures it; `sfm_wall_seconds` adds the interpreter's start and the image links);
//! - relative to `dense` ([`relative_to_dense`]): `ate_vs_dense` (ATE / dense's ATE),
//!   `sfm_speedup` (dense's `sfm_seconds` / this policy's); `gate_seconds`, the gate's own time
//!   (the element's pipeline for `model`: frames / its fps; 0 for `stride` and `dense`; null for
//!   the policies whose cost is not measured: `oracle` needs the teacher, the cheap baselines run
//!   on the model pass's thumbnails), and `end_to_end_speedup` = dense's SfM time / (gate + SfM).
//!
//! A policy whose reconstruction fails (COLMAP aborts, too few readable images) gets
//! `sfm_error` with the consumer's message, and the others still run; the run fails only when
//! every policy fails. `--trajectory-dir DIR` writes each policy's registered camera poses as a
//! TUM trajectory (`DIR/<policy>.txt`, camera-to-world, in the SfM's frame and scale) and the
//! sequence's ground truth (`DIR/groundtruth.txt`), for `evo_ape tum DIR/groundtruth.txt
//! DIR/model.txt --align --correct_scale`.
//!
//! Where the consumer and its interpreter come from ([`consumer_home`], the one lookup): an
//! installed `leangate` (`$PREFIX/bin/leangate` of `make install`) runs the consumer installed
//! beside it, `$PREFIX/lib/leangate/python/reconstruct.py` (with the `leangate_client` it
//! imports); any other build runs its checkout's `pipelines/reconstruct.py`. The interpreter:
//! `--sfm-python`, else `$LEANGATE_SFM_PYTHON`, else, only when running from the checkout, its
//! `.venv-sfm/bin/python` (made by `scripts/setup.sh`), else `/usr/bin/python3`; it needs
//! pycolmap and PyGObject, checked first with an error naming what is missing.

use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::{Isometry3, Matrix3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::{EvalError, EvalReport, PlotData, Source};

/// Default `--dense-every`.
pub const DENSE_EVERY: usize = 10;

/// Settings of `--reconstruct`.
#[derive(Debug, Clone)]
pub struct SfmConfig {
    /// The Python interpreter (None: [`find_python`]).
    pub python: Option<PathBuf>,
    /// The `dense` reference keeps every this-many-th frame.
    pub dense_every: usize,
    /// Keep each policy's database and sparse model under this directory (`<dir>/<policy>/`);
    /// None: a temporary directory, removed afterwards.
    pub work_dir: Option<PathBuf>,
    /// COLMAP matcher: `auto`, `exhaustive` or `sequential`.
    pub matcher: String,
    /// SIFT features per image.
    pub max_features: u32,
    /// Write each policy's trajectory (TUM format) and the ground truth here.
    pub trajectory_dir: Option<PathBuf>,
}

impl Default for SfmConfig {
    fn default() -> Self {
        SfmConfig {
            python: None,
            dense_every: DENSE_EVERY,
            work_dir: None,
            matcher: "auto".into(),
            max_features: 4096,
            trajectory_dir: None,
        }
    }
}

impl SfmConfig {
    /// The same settings with `work_dir` and `trajectory_dir` (where given) one level down, in
    /// `name`: one sequence's share of a run over several.
    pub fn in_subdirectory(&self, name: &str) -> SfmConfig {
        SfmConfig {
            work_dir: self.work_dir.as_ref().map(|d| d.join(name)),
            trajectory_dir: self.trajectory_dir.as_ref().map(|d| d.join(name)),
            ..self.clone()
        }
    }
}

/// What the report records about the reconstruction run (`reconstruction` in the JSON).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ReconstructionInfo {
    pub engine: String,
    pub python: String,
    pub dense_every: usize,
    pub matcher: String,
    pub ate: String,
}

/// The checkout this binary was built from (pipelines/ and .venv-sfm live there).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// Where `--reconstruct` takes its consumer (and, for a checkout, its venv) from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConsumerHome {
    /// This binary is `$PREFIX/bin/leangate` of `make install`: the consumer installed beside
    /// it, `$PREFIX/lib/leangate/python/reconstruct.py`.
    Installed(PathBuf),
    /// Any other build: the checkout it was built from, [`repo_root`].
    Checkout(PathBuf),
}

/// The one lookup of the consumer: [`ConsumerHome::Installed`] when the running binary has
/// `../lib/leangate/python/reconstruct.py` beside it (the layout of scripts/install.sh), else
/// [`ConsumerHome::Checkout`].
pub fn consumer_home() -> ConsumerHome {
    let bin = std::env::current_exe()
        .and_then(|e| e.canonicalize())
        .ok()
        .and_then(|e| e.parent().map(Path::to_path_buf));
    if let Some(prefix) = bin.as_deref().and_then(Path::parent) {
        let script = prefix.join("lib/leangate/python/reconstruct.py");
        if script.is_file() {
            return ConsumerHome::Installed(script);
        }
    }
    ConsumerHome::Checkout(repo_root())
}

/// `explicit`, else `$LEANGATE_SFM_PYTHON`, else (running from the checkout only)
/// `<repo>/.venv-sfm/bin/python`, else `/usr/bin/python3`.
pub fn find_python(explicit: Option<&Path>) -> PathBuf {
    if let Some(p) = explicit {
        return p.to_path_buf();
    }
    if let Some(p) = std::env::var_os("LEANGATE_SFM_PYTHON").filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    if let ConsumerHome::Checkout(repo) = consumer_home() {
        let venv = repo.join(".venv-sfm/bin/python");
        if venv.exists() {
            return venv;
        }
    }
    PathBuf::from("/usr/bin/python3")
}

/// The consumer script ([`consumer_home`]): the installed one, or the checkout's
/// `pipelines/reconstruct.py`.
pub fn consumer_script() -> Result<PathBuf, EvalError> {
    match consumer_home() {
        ConsumerHome::Installed(script) => Ok(script),
        ConsumerHome::Checkout(repo) => {
            let p = repo.join("pipelines/reconstruct.py");
            if p.is_file() {
                Ok(p)
            } else {
                Err(EvalError(format!(
                    "--reconstruct: the consumer `{}` is missing: this leangate is not installed \
                     (`make install` puts the consumer in $PREFIX/lib/leangate/python/) and the \
                     checkout it was built in is gone",
                    p.display()
                )))
            }
        }
    }
}

/// Check that `python` imports pycolmap (first: see pipelines/reconstruct.py) and the GStreamer
/// bindings; returns pycolmap's version, or an error naming what is missing and how to get it.
pub fn check_python(python: &Path) -> Result<String, EvalError> {
    let code = "import sys\n\
        try:\n    import pycolmap\n\
        except ImportError as e:\n    print('pycolmap', e, file=sys.stderr); sys.exit(3)\n\
        try:\n    import gi; gi.require_version('Gst', '1.0'); from gi.repository import Gst\n\
        except (ImportError, ValueError) as e:\n    print('gi', e, file=sys.stderr); sys.exit(4)\n\
        print(pycolmap.__version__)\n";
    let out = Command::new(python)
        .args(["-c", code])
        .output()
        .map_err(|e| {
            EvalError(format!(
                "--reconstruct: cannot run the Python interpreter `{}` ({e}); set \
                 LEANGATE_SFM_PYTHON or --sfm-python, or run `bash scripts/setup.sh` (makes .venv-sfm)",
                python.display()
            ))
        })?;
    let stderr = String::from_utf8_lossy(&out.stderr).trim().to_string();
    match out.status.code() {
        Some(0) => Ok(String::from_utf8_lossy(&out.stdout).trim().to_string()),
        Some(3) => Err(EvalError(format!(
            "--reconstruct: pycolmap is not importable by `{}` ({}); in the checkout, run `bash \
             scripts/setup.sh` (it makes .venv-sfm with pycolmap and the system's PyGObject); \
             else make one: `/usr/bin/python3 -m venv --system-site-packages ~/.venv-sfm && \
             ~/.venv-sfm/bin/pip install pycolmap==4.2.1`; and point LEANGATE_SFM_PYTHON / \
             --sfm-python at it",
            python.display(),
            stderr.trim_start_matches("pycolmap ")
        ))),
        Some(4) => Err(EvalError(format!(
            "--reconstruct: the GStreamer Python bindings (gi) are not importable by `{}` ({}); \
             use a Python that sees python3-gi (Debian's /usr/bin/python3, or a venv made with \
             --system-site-packages such as .venv-sfm from `bash scripts/setup.sh`)",
            python.display(),
            stderr.trim_start_matches("gi ")
        ))),
        _ => Err(EvalError(format!(
            "--reconstruct: `{} -c 'import pycolmap'` failed ({}): {stderr}",
            python.display(),
            out.status
        ))),
    }
}

/// Check the interpreter and the consumer before a long evaluation: the Python found and
/// pycolmap's version.
pub fn preflight(cfg: &SfmConfig) -> Result<(PathBuf, String), EvalError> {
    if cfg.dense_every == 0 {
        return Err(EvalError("--dense-every must be at least 1".into()));
    }
    if cfg.max_features == 0 {
        return Err(EvalError("--sfm-max-features must be at least 1".into()));
    }
    let python = find_python(cfg.python.as_deref());
    let version = check_python(&python)?;
    consumer_script()?;
    Ok((python, version))
}

/// One frame of the consumer's JSON: `center` and `rotation` (quaternion x, y, z, w) are the
/// camera-to-world pose in the largest model.
#[derive(Debug, Clone, Deserialize)]
pub struct ConsumerFrame {
    pub frame: usize,
    pub registered: bool,
    pub center: Option<[f64; 3]>,
    #[serde(default)]
    pub rotation: Option<[f64; 4]>,
    #[serde(default)]
    pub timestamp: Option<f64>,
}

/// The consumer's JSON (`reconstruct.py --json`), the fields eval uses.
#[derive(Debug, Clone, Deserialize)]
pub struct ConsumerResult {
    pub registered: usize,
    pub models: usize,
    pub mean_reprojection_error_px: Option<f64>,
    #[serde(rename = "points3D")]
    pub points3d: usize,
    pub frames: Vec<ConsumerFrame>,
    /// COLMAP's time per stage (features, matching, mapping).
    #[serde(default)]
    pub seconds: std::collections::BTreeMap<String, f64>,
}

/// A policy's reconstruction as it goes into the report.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SfmOutcome {
    pub registered: usize,
    pub models: usize,
    pub ate_rmse_cm: Option<f64>,
    pub sfm_reproj_px: Option<f64>,
    pub sfm_points: usize,
    pub sfm_seconds: f64,
    pub sfm_wall_seconds: f64,
}

/// The consumer's `--frames @LIST` file: `index [image path]` per line. Paths are made absolute:
/// the consumer resolves a relative one against the sequence's folder, not the working directory
/// (a sequence given as `../data/seq` would otherwise be looked up in `../data/seq/../data/seq`).
fn frame_list(frames: &[(usize, Option<PathBuf>)]) -> String {
    let mut text = String::from("# index [image path]\n");
    for (i, p) in frames {
        match p {
            Some(p) => {
                let p = std::path::absolute(p).unwrap_or_else(|_| p.clone());
                text.push_str(&format!("{i} {}\n", p.display()))
            }
            None => text.push_str(&format!("{i}\n")),
        }
    }
    text
}

/// Run the consumer on `frames` (`(index, image path)`; the path None for a video frame, which
/// the consumer decodes) of `input`, in `out_dir`. `progress` hears each COLMAP stage as the
/// consumer starts it ([`consumer_step`]): feature extraction, matching, mapping and, every
/// tenth of the frames, how many the mapping has registered.
pub fn run_consumer(
    python: &Path,
    input: &Path,
    frames: &[(usize, Option<PathBuf>)],
    out_dir: &Path,
    cfg: &SfmConfig,
    mut progress: impl FnMut(&str),
) -> Result<ConsumerResult, EvalError> {
    use std::io::BufRead;
    let script = consumer_script()?;
    std::fs::create_dir_all(out_dir)
        .map_err(|e| EvalError(format!("`{}`: {e}", out_dir.display())))?;
    let list = out_dir.join("frames.txt");
    std::fs::write(&list, frame_list(frames))
        .map_err(|e| EvalError(format!("`{}`: {e}", list.display())))?;
    let json = out_dir.join("result.json");
    let mut frames_arg = std::ffi::OsString::from("@");
    frames_arg.push(&list);
    // -v: the consumer says each stage on its standard error, read here as it comes.
    let mut child = Command::new(python)
        .arg(&script)
        .arg(input)
        .arg("--frames")
        .arg(frames_arg)
        .arg("--out")
        .arg(out_dir)
        .arg("--json")
        .arg(&json)
        .args(["--matcher", &cfg.matcher])
        .args(["--max-features", &cfg.max_features.to_string()])
        .arg("-v")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .map_err(|e| EvalError(format!("cannot run `{}`: {e}", python.display())))?;
    let mut stderr = Vec::new();
    if let Some(pipe) = child.stderr.take() {
        let mut reader = std::io::BufReader::new(pipe);
        let mut line = Vec::new();
        let mut registered_tenth = None;
        while reader.read_until(b'\n', &mut line).is_ok_and(|n| n > 0) {
            let text = String::from_utf8_lossy(&line);
            if let Some(step) = consumer_step(text.trim_end(), frames.len(), &mut registered_tenth)
            {
                progress(&step);
            }
            stderr.append(&mut line);
        }
    }
    let status = child
        .wait()
        .map_err(|e| EvalError(format!("`{}`: {e}", python.display())))?;
    if !status.success() {
        return Err(EvalError(consumer_failure(&status, &stderr)));
    }
    let text = std::fs::read_to_string(&json)
        .map_err(|e| EvalError(format!("`{}`: {e}", json.display())))?;
    serde_json::from_str(&text).map_err(|e| EvalError(format!("`{}`: {e}", json.display())))
}

/// A line of the consumer's standard error (`reconstruct: LEVEL: message`) as a progress step,
/// or None: the start of each COLMAP stage (`SIFT features of N images ...`, `exhaustive
/// matching: N pairs`, `incremental mapping`); the mapping's `N images registered` once per
/// tenth of the `frames` (`registered_tenth` remembers the last one said); warnings.
pub fn consumer_step(
    line: &str,
    frames: usize,
    registered_tenth: &mut Option<usize>,
) -> Option<String> {
    if let Some((_, m)) = line.split_once(": warning: ") {
        return Some(format!("warning: {m}"));
    }
    let (_, m) = line.split_once(": info: ")?;
    if let Some(rest) = m.strip_prefix("mapping: ") {
        let n: usize = rest.split(' ').next()?.parse().ok()?;
        let tenth = (n * 10).checked_div(frames).unwrap_or(0);
        if *registered_tenth == Some(tenth) {
            return None;
        }
        *registered_tenth = Some(tenth);
        return Some(format!(
            "mapping: the initial pair and {n} more of the {frames} frames registered"
        ));
    }
    const STAGES: [&str; 4] = [
        "SIFT features of ",
        "exhaustive matching",
        "sequential matching",
        "incremental mapping",
    ];
    STAGES
        .iter()
        .any(|s| m.starts_with(s))
        .then(|| m.to_string())
}

/// What to say when the consumer failed: its `error:` lines (the consumer reports COLMAP's
/// failures, aborts included, that way), else the tail of its stderr, and the exit status.
fn consumer_failure(status: &std::process::ExitStatus, stderr: &[u8]) -> String {
    let stderr = String::from_utf8_lossy(stderr);
    let errors: Vec<&str> = stderr
        .lines()
        .filter_map(|l| l.split_once(": error: ").map(|(_, m)| m.trim()))
        .collect();
    let text = if errors.is_empty() {
        let tail: Vec<&str> = stderr
            .lines()
            .filter(|l| !l.contains(": info: "))
            .rev()
            .take(15)
            .collect();
        tail.into_iter().rev().collect::<Vec<_>>().join("\n")
    } else {
        errors.join("; ")
    };
    format!("the reconstruction consumer failed ({status}): {text}")
}

/// Least-squares similarity `dst ≈ s R src + t` (Umeyama 1991). None with fewer than 3 points,
/// different lengths, or degenerate (all equal) source points.
pub fn umeyama(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
) -> Option<(f64, Matrix3<f64>, Vector3<f64>)> {
    let n = src.len();
    if n < 3 || dst.len() != n {
        return None;
    }
    let nf = n as f64;
    let mu_s = src.iter().sum::<Vector3<f64>>() / nf;
    let mu_d = dst.iter().sum::<Vector3<f64>>() / nf;
    let var_s = src.iter().map(|p| (p - mu_s).norm_squared()).sum::<f64>() / nf;
    if var_s <= 0.0 {
        return None;
    }
    let cov = src
        .iter()
        .zip(dst)
        .map(|(s, d)| (d - mu_d) * (s - mu_s).transpose())
        .sum::<Matrix3<f64>>()
        / nf;
    let svd = cov.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut sign = Matrix3::identity();
    if u.determinant() * vt.determinant() < 0.0 {
        sign[(2, 2)] = -1.0;
    }
    let r = u * sign * vt;
    let s = (svd.singular_values.component_mul(&sign.diagonal())).sum() / var_s;
    let t = mu_d - s * r * mu_s;
    Some((s, r, t))
}

/// ATE: RMSE of `est` against `gt` after the [`umeyama`] similarity alignment (units of `gt`).
pub fn ate_rmse(est: &[Vector3<f64>], gt: &[Vector3<f64>]) -> Option<f64> {
    let (s, r, t) = umeyama(est, gt)?;
    let se = est
        .iter()
        .zip(gt)
        .map(|(e, g)| (s * r * e + t - g).norm_squared())
        .sum::<f64>();
    Some((se / est.len() as f64).sqrt())
}

/// A frame of the report: its image (None for a video frame), timestamp and ground-truth
/// camera-to-world pose, where known.
type FrameInfo = (Option<PathBuf>, Option<f64>, Option<Isometry3<f64>>);

/// Reconstruct every policy's kept frames (`data.kept`) and a `dense` reference, one after the
/// other, and add the fields to `report.policies` (the `dense` entry is created). A policy whose
/// reconstruction fails gets `sfm_error` and the others go on; the result is an error only when
/// every policy failed. `progress(k, runs, policy, step)` says each step of the `k`-th of the
/// `runs` reconstructions (0-based): its start (`N frames`), each COLMAP stage ([`consumer_step`])
/// and its outcome; `k == runs` at the end.
pub fn add_reconstruction(
    path: &Path,
    report: &mut EvalReport,
    data: &PlotData,
    cfg: &SfmConfig,
    mut progress: impl FnMut(usize, usize, &str, &str),
) -> Result<(), EvalError> {
    let (python, version) = preflight(cfg)?;
    let source = Source::open(path)?;
    let n = report.frames;
    // Image path, timestamp and ground-truth pose per frame index of the report.
    let frames_of: Vec<FrameInfo> = match &source {
        Source::Sequence(seq) => seq
            .frames
            .iter()
            .map(|f| (Some(f.rgb.clone()), Some(f.timestamp), f.pose))
            .collect(),
        Source::Video(_) => vec![(None, None, None); n],
    };
    if frames_of.len() != n {
        return Err(EvalError(format!(
            "--reconstruct: the sequence has {} frames, the report {n}",
            frames_of.len()
        )));
    }
    if let Some(dir) = &cfg.trajectory_dir {
        std::fs::create_dir_all(dir).map_err(|e| EvalError(format!("`{}`: {e}", dir.display())))?;
        let gt: Vec<(f64, Isometry3<f64>)> = frames_of
            .iter()
            .filter_map(|(_, t, p)| Some(((*t)?, (*p)?)))
            .collect();
        if !gt.is_empty() {
            write_tum(&dir.join("groundtruth.txt"), &gt)?;
        }
    }
    let mut runs: Vec<(String, Vec<bool>)> = data.kept.clone();
    let dense: Vec<bool> = (0..n).map(|i| i % cfg.dense_every == 0).collect();
    runs.push(("dense".into(), dense.clone()));
    let kept_dense = dense.iter().filter(|k| **k).count();
    report.policies.insert(
        "dense".into(),
        json!({
            "kept": kept_dense,
            "keep_ratio": if n > 0 { kept_dense as f64 / n as f64 } else { 0.0 },
            "downsample": if kept_dense > 0 { n as f64 / kept_dense as f64 } else { 0.0 },
            "every": cfg.dense_every,
        }),
    );
    let tmp;
    let root = match &cfg.work_dir {
        Some(d) => d.clone(),
        None => {
            tmp = TempDir::new()?;
            tmp.0.clone()
        }
    };
    let total = runs.len();
    let mut failures = Vec::new();
    for (k, (name, keep)) in runs.iter().enumerate() {
        let frames: Vec<(usize, Option<PathBuf>)> = keep
            .iter()
            .enumerate()
            .filter(|(_, k)| **k)
            .map(|(i, _)| (i, frames_of[i].0.clone()))
            .collect();
        let plural = if frames.len() == 1 { "" } else { "s" };
        progress(k, total, name, &format!("{} frame{plural}", frames.len()));
        let t0 = std::time::Instant::now();
        let step = |s: &str| progress(k, total, name, s);
        let fields = match run_consumer(&python, path, &frames, &root.join(name), cfg, step) {
            Ok(res) => {
                progress(
                    k,
                    total,
                    name,
                    &format!(
                        "{} of {} registered, {} model{}, {:.1} s",
                        res.registered,
                        frames.len(),
                        res.models,
                        if res.models == 1 { "" } else { "s" },
                        t0.elapsed().as_secs_f64()
                    ),
                );
                let (mut est, mut truth, mut trajectory) = (Vec::new(), Vec::new(), Vec::new());
                for f in res.frames.iter().filter(|f| f.registered) {
                    let Some(c) = f.center else { continue };
                    let (_, t, pose) = frames_of.get(f.frame).cloned().unwrap_or_default();
                    if let Some(g) = pose {
                        est.push(Vector3::from(c));
                        truth.push(g.translation.vector);
                    }
                    if let (Some(t), Some(q)) = (t.or(f.timestamp), f.rotation) {
                        trajectory.push((t, consumer_pose(c, q)));
                    }
                }
                if let Some(dir) = &cfg.trajectory_dir {
                    write_tum(&dir.join(format!("{name}.txt")), &trajectory)?;
                }
                let outcome = SfmOutcome {
                    registered: res.registered,
                    models: res.models,
                    ate_rmse_cm: ate_rmse(&est, &truth).map(|e| e * 100.0),
                    sfm_reproj_px: res.mean_reprojection_error_px,
                    sfm_points: res.points3d,
                    sfm_seconds: res.seconds.values().fold(0.0, |a, b| a + b),
                    sfm_wall_seconds: t0.elapsed().as_secs_f64(),
                };
                serde_json::to_value(&outcome).unwrap()
            }
            Err(e) => {
                progress(k, total, name, "failed");
                eprintln!("leangate: warning: reconstructing policy {name} failed: {e}");
                failures.push(format!("{name}: {e}"));
                json!({ "sfm_error": e.0 })
            }
        };
        if let (Some(Value::Object(entry)), Value::Object(fields)) =
            (report.policies.get_mut(name), fields)
        {
            entry.extend(fields);
        }
    }
    progress(total, total, "", "done");
    if failures.len() == total {
        return Err(EvalError(format!(
            "--reconstruct: every policy failed: {}",
            failures.join("; ")
        )));
    }
    relative_to_dense(&mut report.policies, n);
    report.reconstruction = Some(ReconstructionInfo {
        engine: format!("COLMAP incremental SfM (pycolmap {version})"),
        python: python.display().to_string(),
        dense_every: cfg.dense_every,
        matcher: cfg.matcher.clone(),
        ate: "camera centres of the largest model vs ground truth after a Umeyama similarity \
              alignment (with scale), RMSE in cm"
            .into(),
    });
    Ok(())
}

/// Policies whose gate costs nothing to run: the frame index alone decides.
const FREE_GATES: [&str; 2] = ["stride", "dense"];

/// Add each policy's figures relative to `dense`: `ate_vs_dense`, `sfm_speedup`,
/// `gate_seconds` (`model`: `frames` / its `fps`; 0 for [`FREE_GATES`]; otherwise not
/// measured, null) and `end_to_end_speedup` (dense's SfM time / (gate + SfM time)). A ratio
/// whose parts are missing (no ATE, a failed run) is null, and so are the speed-ups of a policy
/// that built no model (too few frames: being fast at nothing is no speed-up).
pub fn relative_to_dense(policies: &mut serde_json::Map<String, Value>, frames: usize) {
    let num = |p: &Value, k: &str| p.get(k).and_then(Value::as_f64);
    let dense = policies.get("dense");
    let dense_ate = dense.and_then(|d| num(d, "ate_rmse_cm"));
    let dense_sfm = dense.and_then(|d| num(d, "sfm_seconds"));
    let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) if b > 0.0 && a.is_finite() && b.is_finite() => Some(a / b),
        _ => None,
    };
    for (name, p) in policies.iter_mut() {
        let gate = if FREE_GATES.contains(&name.as_str()) {
            Some(0.0)
        } else {
            num(p, "fps")
                .filter(|f| *f > 0.0)
                .map(|f| frames as f64 / f)
        };
        let built = num(p, "models").is_some_and(|m| m >= 1.0);
        let sfm = num(p, "sfm_seconds").filter(|_| built);
        let fields = json!({
            "ate_vs_dense": ratio(num(p, "ate_rmse_cm"), dense_ate),
            "sfm_speedup": ratio(dense_sfm, sfm),
            "gate_seconds": gate,
            "end_to_end_speedup": ratio(dense_sfm, gate.zip(sfm).map(|(g, s)| g + s)),
        });
        if let (Value::Object(entry), Value::Object(fields)) = (p, fields) {
            entry.extend(fields);
        }
    }
}

/// A pose of the consumer's JSON (camera centre, camera-to-world quaternion x, y, z, w) as an
/// isometry (camera-to-world).
fn consumer_pose(c: [f64; 3], q: [f64; 4]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(Vector3::from(c)),
        UnitQuaternion::from_quaternion(Quaternion::new(q[3], q[0], q[1], q[2])),
    )
}

/// [`crate::dataset::write_trajectory`] with an eval error.
fn write_tum(path: &Path, poses: &[(f64, Isometry3<f64>)]) -> Result<(), EvalError> {
    crate::dataset::write_trajectory(path, poses).map_err(|e| EvalError(e.to_string()))
}

/// A temporary directory removed on drop (no extra dependency).
struct TempDir(PathBuf);

impl TempDir {
    fn new() -> Result<TempDir, EvalError> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        let p = std::env::temp_dir().join(format!("leangate-sfm-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&p).map_err(|e| EvalError(format!("`{}`: {e}", p.display())))?;
        Ok(TempDir(p))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    fn cloud() -> Vec<Vector3<f64>> {
        (0..12)
            .map(|i| {
                let t = i as f64;
                Vector3::new(t.sin() * 2.0, 0.3 * t, (0.7 * t).cos() - 1.0)
            })
            .collect()
    }

    /// A sequence given by a relative path (`leangate eval --sequence ../data/seq`): the frame
    /// list holds absolute paths that name the same files, and video frames carry no path.
    #[test]
    fn frame_list_paths_are_absolute() {
        let rel = PathBuf::from("../data/seq/rgb/0001.png");
        let text = frame_list(&[(3, Some(rel.clone())), (5, None)]);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "# index [image path]");
        let (idx, path) = lines[1].split_once(' ').unwrap();
        assert_eq!(idx, "3");
        let path = Path::new(path);
        assert!(path.is_absolute(), "{text}");
        assert_eq!(path, std::env::current_dir().unwrap().join(&rel));
        assert_eq!(lines[2], "5");
    }

    #[test]
    fn umeyama_recovers_a_similarity() {
        let src = cloud();
        let r = Rotation3::from_euler_angles(0.3, -1.1, 2.0).into_inner();
        let t = Vector3::new(1.0, -2.0, 0.5);
        let dst: Vec<_> = src.iter().map(|p| 0.37 * r * p + t).collect();
        let (s, r2, t2) = umeyama(&src, &dst).unwrap();
        assert!((s - 0.37).abs() < 1e-9, "{s}");
        assert!((r2 - r).norm() < 1e-9);
        assert!((t2 - t).norm() < 1e-9);
        assert!(ate_rmse(&src, &dst).unwrap() < 1e-9);
    }

    #[test]
    fn ate_measures_what_alignment_cannot_remove() {
        let gt = cloud();
        // A scaled, rotated copy with a known perturbation of one point.
        let r = Rotation3::from_euler_angles(0.0, 0.0, 0.5).into_inner();
        let mut est: Vec<_> = gt.iter().map(|p| r * p * 3.0).collect();
        est[5] += Vector3::new(0.3, 0.0, 0.0);
        let e = ate_rmse(&est, &gt).unwrap();
        assert!(e > 0.0 && e < 0.1 / (12f64).sqrt() + 1e-3, "{e}");
        // Mirror images are not a rotation: the reflection guard keeps det(R) = +1.
        let mirrored: Vec<_> = gt.iter().map(|p| Vector3::new(-p.x, p.y, p.z)).collect();
        let (_, r, _) = umeyama(&mirrored, &gt).unwrap();
        assert!((r.determinant() - 1.0).abs() < 1e-9);
    }

    /// One sequence of several: its models and trajectories one level down, nothing else moved.
    #[test]
    fn in_subdirectory_moves_only_the_output_directories() {
        let cfg = SfmConfig {
            work_dir: Some("sfm".into()),
            trajectory_dir: Some("traj".into()),
            dense_every: 7,
            ..Default::default()
        };
        let sub = cfg.in_subdirectory("2-tum_fr1_desk");
        assert_eq!(sub.work_dir, Some(PathBuf::from("sfm/2-tum_fr1_desk")));
        assert_eq!(
            sub.trajectory_dir,
            Some(PathBuf::from("traj/2-tum_fr1_desk"))
        );
        assert_eq!(sub.dense_every, 7);
        let none = SfmConfig::default().in_subdirectory("x");
        assert!(none.work_dir.is_none() && none.trajectory_dir.is_none());
    }

    /// Each policy against dense: ratios where both parts exist, the gate's time where known.
    #[test]
    fn relative_to_dense_fills_the_ratios_it_can() {
        let mut p = match json!({
            "dense": {"ate_rmse_cm": 2.0, "sfm_seconds": 100.0, "models": 1},
            "model": {"ate_rmse_cm": 2.4, "sfm_seconds": 50.0, "fps": 100.0, "models": 1},
            "stride": {"ate_rmse_cm": 1.8, "sfm_seconds": 40.0, "models": 2},
            "oracle": {"ate_rmse_cm": null, "sfm_seconds": 60.0, "models": 1},
            "pixel_diff": {"ate_rmse_cm": null, "sfm_seconds": 0.0, "models": 0, "fps": 9.0},
            "motion": {"sfm_error": "COLMAP failed"},
        }) {
            Value::Object(m) => m,
            _ => unreachable!(),
        };
        relative_to_dense(&mut p, 700);
        let f = |name: &str, k: &str| p[name][k].as_f64();
        assert_eq!(f("dense", "ate_vs_dense"), Some(1.0));
        assert_eq!(f("dense", "end_to_end_speedup"), Some(1.0));
        assert!((f("model", "ate_vs_dense").unwrap() - 1.2).abs() < 1e-12);
        assert_eq!(f("model", "sfm_speedup"), Some(2.0));
        assert_eq!(f("model", "gate_seconds"), Some(7.0));
        assert_eq!(f("model", "end_to_end_speedup"), Some(100.0 / 57.0));
        assert_eq!(f("stride", "gate_seconds"), Some(0.0));
        assert_eq!(f("stride", "end_to_end_speedup"), Some(2.5));
        assert_eq!(f("oracle", "ate_vs_dense"), None);
        assert_eq!(f("oracle", "sfm_speedup"), Some(100.0 / 60.0));
        assert_eq!(f("oracle", "gate_seconds"), None);
        assert_eq!(f("oracle", "end_to_end_speedup"), None);
        for k in ["ate_vs_dense", "sfm_speedup", "end_to_end_speedup"] {
            assert!(p["motion"][k].is_null(), "{k}");
            assert!(p["pixel_diff"][k].is_null(), "{k}: no model, no speed-up");
        }
        assert_eq!(p["motion"]["sfm_error"], "COLMAP failed");
    }

    /// The consumer's `error:` lines make the message; without any, the tail of its stderr.
    #[test]
    fn consumer_failure_quotes_the_error_lines() {
        use std::os::unix::process::ExitStatusExt;
        let status = std::process::ExitStatus::from_raw(1 << 8);
        let msg = consumer_failure(
            &status,
            b"reconstruct: info: x\nreconstruct: error: COLMAP failed during exhaustive matching\n",
        );
        assert!(
            msg.ends_with(": COLMAP failed during exhaustive matching"),
            "{msg}"
        );
        assert!(!msg.contains("info"), "{msg}");
        let msg = consumer_failure(&status, b"Segmentation fault\n");
        assert!(msg.ends_with("Segmentation fault"), "{msg}");
    }

    #[test]
    fn too_few_or_degenerate_points() {
        let p = Vector3::new(1.0, 2.0, 3.0);
        assert!(ate_rmse(&[p, p], &[p, p]).is_none());
        assert!(ate_rmse(&[p, p, p], &[p, p, p]).is_none());
        assert!(ate_rmse(&cloud(), &cloud()[..5]).is_none());
    }
}
