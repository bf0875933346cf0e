//! `leangate`: the command-line tool around the plugin's library.
//!
//! - `leangate synth`: render a synthetic RGB-D sequence (TUM layout) with a human-like camera path;
//! - `leangate label`: the exact geometric teacher on pairs of a sequence with depth and poses;
//! - `leangate geometry`: the element's geometric prior (chained homographies) on pairs;
//! - `leangate eval`: judge gating policies (the model in the real element, the oracle, stride,
//!   pixel difference) against the teacher.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use gstleangate::GateConfig;
use leangate_tools::args;
use leangate_tools::dataset::{RgbFormat, Sequence};
use leangate_tools::eval;
use leangate_tools::output::{Inputs, OutputFile};
use leangate_tools::synth::{self, MotionSpec, Replay, ReplayEnd, SensorConfig, SynthConfig};
use leangate_tools::teacher::{self, Teacher, TeacherConfig};

#[derive(Parser)]
#[command(
    name = "leangate",
    version,
    about = "LeanGate: geometric-utility frame gating for monocular SLAM"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

// Parsed once per process: the size of the largest variant (`Eval`'s options) does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    /// Render a synthetic indoor RGB-D sequence (rgb/, depth/, rgb.txt, depth.txt,
    /// groundtruth.txt, intrinsics.txt).
    Synth {
        /// Output directory: new, empty, or an earlier synth output (replaced when the new one is
        /// complete); a folder holding anything else is refused.
        #[arg(long)]
        out: PathBuf,
        /// Seed: scene, textures, camera path and noise are determined by it.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Number of frames (1 to 1000000).
        #[arg(long, default_value_t = 300, value_parser = args::synth_frames)]
        frames: usize,
        /// Camera path: static, pan, shaky, walk, rotate, bursts, mixed, orbit, or replay:FILE (a TUM
        /// trajectory `t tx ty tz qx qy qz qw`, or a NeRF transforms.json), placed in the room and
        /// resampled to --fps.
        #[arg(long, default_value = "mixed")]
        motion: MotionSpec,
        /// With replay:FILE: seconds into the file at which the sequence starts.
        #[arg(long, default_value_t = 0.0, value_parser = args::finite_non_negative)]
        replay_start: f64,
        /// With replay:FILE, when --frames outlasts the file: stop (fewer frames), loop, bounce.
        #[arg(long, default_value = "stop")]
        replay_end: ReplayEnd,
        /// Folder of jpg/png images tiled on some surfaces.
        #[arg(long)]
        textures: Option<PathBuf>,
        /// Frame width, 2 to 4096 pixels.
        #[arg(long, default_value_t = 640, value_parser = args::synth_side)]
        width: u32,
        /// Frame height, 2 to 4096 pixels.
        #[arg(long, default_value_t = 480, value_parser = args::synth_side)]
        height: u32,
        #[arg(long, default_value_t = 30.0, value_parser = args::finite_positive)]
        fps: f64,
        /// Gaussian sensor noise (standard deviation, 0..1 intensity).
        #[arg(long, default_value_t = 0.01, value_parser = args::unit_interval)]
        noise: f64,
        /// Motion blur (3 sub-frame renders per frame).
        #[arg(long)]
        blur: bool,
        /// Exposure drift and a dimming in the middle of the sequence.
        #[arg(long)]
        lighting: bool,
        /// Write colour frames as JPEG (quality 90) instead of PNG.
        #[arg(long)]
        jpeg: bool,
        /// Sensor realism (opt-in): none, realistic (all), or a comma-separated list of
        /// exposure, wb, blur, rolling, depth-noise, holes, vignette, jpeg.
        #[arg(long, default_value = "none")]
        sensor: SensorConfig,
    },
    /// Label pairs with the exact geometric teacher (needs depth, poses and intrinsics).
    /// Without --pairs/--within/--random: every frame against the oracle gate's reference.
    Label {
        /// Sequence directory (TUM layout).
        #[arg(long)]
        sequence: PathBuf,
        /// CSV of pairs `i,j` (current, keyframe; frame indices; a header line is allowed).
        #[arg(long, conflicts_with_all = ["within", "random"])]
        pairs: Option<PathBuf>,
        /// Every frame against each of its K predecessors.
        #[arg(long, value_name = "K", conflicts_with = "random", value_parser = args::nonzero)]
        within: Option<usize>,
        /// N random pairs (i != j, |i-j| <= --max-gap), both orders, trajectory-agnostic.
        #[arg(long, value_name = "N", value_parser = args::random_pairs)]
        random: Option<usize>,
        /// Largest frame gap for --random.
        #[arg(long, default_value_t = 90, value_parser = args::nonzero)]
        max_gap: usize,
        /// Seed for --random.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Threshold of the oracle gate (gate mode), 0 to 1.
        #[arg(long, default_value_t = 0.5, value_parser = args::unit_interval)]
        threshold: f64,
        /// Working width of the depth (subsampled by an integer step), 1 to 8192.
        #[arg(long, default_value_t = 160, value_parser = args::working_width)]
        working_width: u32,
        /// 3-D distance below which a match is valid, metres (above 0).
        #[arg(long, default_value_t = 0.1, value_parser = args::finite_positive)]
        max_dist: f64,
        /// Output CSV (default: standard output).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The element's geometric prior on pairs of a sequence: frame-to-frame homographies (LK
    /// on the model-input picture) chained from the reference, scored like the teacher
    /// (`tau_geo`, `f_m`, `f_u`; empty when the chain is lost). Needs only the colour frames.
    Geometry {
        /// Sequence directory (TUM layout, or rgb.txt/images only).
        #[arg(long)]
        sequence: PathBuf,
        /// CSV of pairs `i,j` (current, reference; j < i; a header line is allowed).
        #[arg(long)]
        pairs: PathBuf,
        /// Picture size the tracker runs on: the model's input (the embedded model's 160x120).
        #[arg(long, default_value = "160x120", value_parser = args::picture_size)]
        size: (u32, u32),
        /// How frames are mapped to that size: short-side-crop (the embedded model's) or stretch.
        #[arg(long, default_value = "short-side-crop")]
        resize: String,
        /// Output CSV (default: standard output).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Run the gating policies over a sequence or video and judge them against the teacher.
    Eval {
        /// Sequence directory (TUM layout, or rgb.txt/images only) or a video file. Repeat it
        /// (`--sequence A --sequence B`) for one table per sequence and the sums per policy over
        /// all of them (JSON: `sequences`, `sums`, and `sweep_sums` with --sweep).
        #[arg(long, required = true)]
        sequence: Vec<PathBuf>,
        /// LeanGate model (.onnx, pair model or split encoder); default: the embedded leangate-s.
        #[arg(long)]
        model: Option<PathBuf>,
        /// The element's `precision`: which build of the embedded student runs (auto: INT8 on
        /// the CPU; fp32; int8). Default: the element's default, auto.
        #[arg(long, value_parser = ["auto", "fp32", "int8"])]
        precision: Option<String>,
        /// tau_keep, 0 to 1 (default: the model's leangate.threshold, else 0.5).
        #[arg(long, value_parser = args::unit_interval)]
        threshold: Option<f64>,
        /// Act as a consumer that reports what it measured: each kept frame's teacher tau against
        /// the previous kept frame goes back to the element as a `leangate-feedback` event (what
        /// a SLAM front end that sends its S upstream gives the gate), DELAY frames after the
        /// keep (default 3: its latency). Frames then go through one at a time. Needs depth and
        /// poses.
        #[arg(long, value_name = "DELAY", num_args = 0..=1, default_missing_value = "3",
              value_parser = clap::value_parser!(u16).range(0..=1000))]
        feedback: Option<u16>,
        /// Feed the element each frame's depth beside its colour, as an RGB-D camera would (a
        /// LeanGateDepthMeta in metres with the sequence's intrinsics): the `model` row is then
        /// the depth-fed gate (the teacher's own S with the pose fitted from the frames, never
        /// the ground truth; colour-only where the pose fails; JSON: `depth_pose_failures`).
        /// Needs depth images and intrinsics.txt
        #[arg(long)]
        depth: bool,
        /// Set a property of the element the model runs in, as gst-launch would
        /// (`--set sharpness-lookback=0`; repeatable): how to judge the gate with other settings.
        /// `mode` stays annotate (the eval reads every frame's verdict).
        #[arg(long = "set", value_name = "PROPERTY=VALUE", value_parser = args::property_setting)]
        set: Vec<(String, String)>,
        /// Write the JSON report here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Write the plot (PNG) here (with several sequences, one per sequence: `NAME-K-SEQ.png`).
        #[arg(long)]
        plot: Option<PathBuf>,
        /// Write a contact sheet (PNG) of the frames the model kept here (with several sequences,
        /// one per sequence, named like --plot's).
        #[arg(long)]
        contact_sheet: Option<PathBuf>,
        /// Also run the equal-budget sweep: the model at each of --sweep-thresholds (one pipeline
        /// run each), the oracle at the same threshold, stride, pixel_diff, motion and overlap at the model's
        /// budget; written into the JSON (`sweep`) and printed. Needs depth and poses.
        #[arg(long)]
        sweep: bool,
        /// Thresholds for --sweep (comma-separated).
        #[arg(long, value_delimiter = ',', default_values_t = eval::SWEEP_THRESHOLDS,
              value_parser = args::unit_interval)]
        sweep_thresholds: Vec<f64>,
        /// Write the sweep plot (PNG: late keeps and min pair S against frames kept) here; with
        /// several sequences, of the sums over them.
        #[arg(long)]
        sweep_plot: Option<PathBuf>,
        /// Evaluate each sequence N times, the k-th run started k frames in (k = 0 .. N-1), and
        /// print the sums over the runs: a keyframe chain depends on the frame it starts on, so
        /// one run can move by a keyframe or a late keep by chance. JSON: every run in `sequences`
        /// (with its `phase`) and each sequence's sums in `phase_sums`. Sequence directories only;
        /// not with --plot, --contact-sheet or --reconstruct.
        #[arg(long, default_value_t = 1, value_name = "N", value_parser = args::phases)]
        phases: usize,
        /// Report progress on standard error also when it is not a terminal (a log, CI): a line
        /// per stage and every tenth of it; with --reconstruct, a line per step of each
        /// reconstruction (its frames, each COLMAP stage, the outcome). On a terminal a progress
        /// bar is always shown.
        #[arg(long)]
        progress: bool,
        #[arg(long, default_value_t = 160, value_parser = args::working_width)]
        working_width: u32,
        #[arg(long, default_value_t = 0.1, value_parser = args::finite_positive)]
        max_dist: f64,
        /// Also reconstruct each policy's kept frames, and a dense reference (every
        /// --dense-every-th frame), with COLMAP incremental SfM (pycolmap, through
        /// pipelines/reconstruct.py), one policy after the other: `registered`, `models` and,
        /// with ground truth, `ate_rmse_cm` (camera centres after a Umeyama similarity
        /// alignment) per policy, in the JSON and printed. Needs pycolmap (`make setup`).
        #[arg(long)]
        reconstruct: bool,
        /// The dense reference of --reconstruct keeps every K-th frame.
        #[arg(long, value_name = "K", default_value_t = eval::reconstruct::DENSE_EVERY,
              value_parser = args::nonzero, requires = "reconstruct")]
        dense_every: usize,
        /// Python for --reconstruct (default: $LEANGATE_SFM_PYTHON, else .venv-sfm/bin/python of
        /// the checkout, else /usr/bin/python3); needs pycolmap and PyGObject.
        #[arg(long, requires = "reconstruct")]
        sfm_python: Option<PathBuf>,
        /// Keep the databases and sparse models of --reconstruct here (DIR/POLICY/sparse/N);
        /// default: a temporary directory.
        #[arg(long, value_name = "DIR", requires = "reconstruct")]
        sfm_dir: Option<PathBuf>,
        /// COLMAP matcher for --reconstruct: auto (exhaustive up to 40 frames, else
        /// sequential), exhaustive, sequential.
        #[arg(long, default_value = "auto", value_parser = ["auto", "exhaustive", "sequential"],
              requires = "reconstruct")]
        sfm_matcher: String,
        /// SIFT features per frame for --reconstruct.
        #[arg(long, default_value_t = 4096, value_parser = args::nonzero_u32, requires = "reconstruct")]
        sfm_max_features: u32,
        /// With --reconstruct: write each policy's camera trajectory (TUM format, camera-to-world,
        /// the SfM's frame and scale) as DIR/POLICY.txt and the ground truth as
        /// DIR/groundtruth.txt, for `evo_ape tum DIR/groundtruth.txt DIR/model.txt --align
        /// --correct_scale`.
        #[arg(long, value_name = "DIR", requires = "reconstruct")]
        trajectory_dir: Option<PathBuf>,
    },
}

/// The report's printed lines go through `say!`: a standard output that fails (a full disk, a
/// reader that went away) must not panic halfway and lose the files still to be written. The
/// first failure is kept, printing stops, and `eval` reports it once its files are written.
static STDOUT_ERROR: std::sync::Mutex<Option<std::io::Error>> = std::sync::Mutex::new(None);

macro_rules! say {
    ($($arg:tt)*) => {
        say_line(format_args!($($arg)*))
    };
}

fn say_line(args: std::fmt::Arguments) {
    let mut failed = STDOUT_ERROR.lock().unwrap_or_else(|e| e.into_inner());
    if failed.is_none() {
        let mut out = std::io::stdout().lock();
        if let Err(e) = out.write_fmt(args).and_then(|()| out.write_all(b"\n")) {
            *failed = Some(e);
        }
    }
}

/// The standard-output failure `say!` met, if any (a reader that went away is not one).
fn stdout_result() -> Res {
    let failed = STDOUT_ERROR
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .take();
    match failed {
        Some(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
            Err(format!("cannot print the report on standard output: {e}").into())
        }
        _ => Ok(()),
    }
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("leangate: {e}");
            ExitCode::FAILURE
        }
    }
}

type Res = Result<(), Box<dyn std::error::Error>>;

fn run(cli: Cli) -> Res {
    match cli.command {
        Command::Synth {
            out,
            seed,
            frames,
            motion,
            textures,
            width,
            height,
            fps,
            noise,
            blur,
            lighting,
            jpeg,
            replay_start,
            replay_end,
            sensor,
        } => {
            let (motion, replay) = match motion {
                MotionSpec::Profile(p) => (p, None),
                MotionSpec::Replay(path) => (
                    Default::default(),
                    Some(Replay {
                        path,
                        start: replay_start,
                        end: replay_end,
                    }),
                ),
            };
            let cfg = SynthConfig {
                seed,
                frames,
                width,
                height,
                fps,
                motion,
                replay,
                sensor,
                textures,
                noise: noise as f32,
                blur,
                lighting_changes: lighting,
                rgb_format: if jpeg {
                    RgbFormat::Jpeg(90)
                } else {
                    RgbFormat::Png
                },
            };
            // Rendered under a temporary name beside `--out` and moved there when complete; an
            // earlier synth output there is replaced, anything else refused now.
            let stage = leangate_tools::output::OutputDir::create("--out", &out, |d| {
                std::fs::read_to_string(d.join("rgb.txt"))
                    .is_ok_and(|t| t.starts_with(synth::HEADER_PREFIX))
            })?;
            // An earlier output is replaced whole: textures or a trajectory inside it would go.
            Inputs::new(cfg.input_files()).refuse("--out", &out, true)?;
            let s = synth::render_sequence(&cfg, stage.path())?;
            stage.commit()?;
            eprintln!(
                "wrote {} frames {}x{} to {} (render {:.1} frames/s, with writing {:.1} frames/s)",
                s.frames,
                s.width,
                s.height,
                out.display(),
                s.render_fps(),
                s.total_fps()
            );
            Ok(())
        }
        Command::Label {
            sequence,
            pairs,
            within,
            random,
            max_gap,
            seed,
            threshold,
            working_width,
            max_dist,
            out,
        } => {
            check_csv_out(out.as_deref(), &sequence, pairs.as_deref())?;
            let seq = Sequence::open(&sequence)?;
            let cfg = TeacherConfig {
                working_width,
                max_dist_m: max_dist,
            };
            let teacher = Teacher::from_sequence(&seq, &cfg)?;
            let list = if let Some(p) = pairs {
                Some(read_pairs(&p, teacher.len(), false)?)
            } else if let Some(k) = within {
                Some(teacher::pairs_within(teacher.len(), k))
            } else if let (Some(_), true) = (random, teacher.len() < 2) {
                return Err(format!(
                    "--random: `{}` has {} frame(s); a pair needs 2",
                    sequence.display(),
                    teacher.len()
                )
                .into());
            } else {
                random.map(|n| random_pairs(teacher.len(), n, max_gap, seed))
            };
            // Written beside `--out` and renamed over it at the end: a bad pairs file, an error
            // or an interrupt leaves it as it was.
            let mut sink = csv_sink(out.as_deref())?;
            match list {
                Some(list) => teacher::label_pairs_csv(&teacher, &list, &mut sink)?,
                None => {
                    let (trace, used) = eval::oracle_gate(
                        &teacher,
                        GateConfig {
                            threshold,
                            ..Default::default()
                        },
                    );
                    let ts = teacher.timestamps();
                    writeln!(sink, "i,ref,t_i,t_ref,f_m,f_u,s,tau,keep")?;
                    for (i, u) in used.iter().enumerate() {
                        match u {
                            Some((r, s)) => writeln!(
                                sink,
                                "{i},{r},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{}",
                                ts[i], ts[*r], s.f_m, s.f_u, s.s, s.tau, trace.keep[i] as u8
                            )?,
                            None => writeln!(sink, "{i},,{:.6},,,,,,1", ts[i])?,
                        }
                    }
                    eprintln!(
                        "oracle gate at threshold {threshold}: kept {} of {} frames",
                        trace.kept(),
                        trace.keep.len()
                    );
                }
            }
            Ok(sink.commit()?)
        }
        Command::Geometry {
            sequence,
            pairs,
            size,
            resize,
            out,
        } => {
            let (w, h) = size;
            let resize = gstleangate::ResizeMode::parse(&resize).ok_or_else(|| {
                format!("--resize {resize:?}: expected short-side-crop or stretch")
            })?;
            check_csv_out(out.as_deref(), &sequence, Some(&pairs))?;
            let seq = Sequence::open(&sequence)?;
            let list = read_pairs(&pairs, seq.len(), true)?;
            let rows = leangate_tools::geometry::pair_geometry(&seq, &list, w, h, resize)?;
            let mut sink = csv_sink(out.as_deref())?;
            writeln!(sink, "i,j,tau_geo,f_m,f_u")?;
            for ((i, j), r) in list.iter().zip(&rows) {
                match r {
                    Some((t, fm, fu)) => writeln!(sink, "{i},{j},{t:.6},{fm:.6},{fu:.6}")?,
                    None => writeln!(sink, "{i},{j},,,")?,
                }
            }
            sink.commit()?;
            let lost = rows.iter().filter(|r| r.is_none()).count();
            eprintln!("{} pairs, chain lost on {lost}", rows.len());
            Ok(())
        }
        Command::Eval {
            sequence,
            model,
            precision,
            threshold,
            feedback,
            depth,
            set,
            json,
            plot,
            contact_sheet,
            sweep,
            sweep_thresholds,
            sweep_plot,
            phases,
            progress,
            working_width,
            max_dist,
            reconstruct,
            dense_every,
            sfm_python,
            sfm_dir,
            sfm_matcher,
            sfm_max_features,
            trajectory_dir,
        } => {
            if let (Some(t), Some((_, v))) = (threshold, set.iter().find(|(k, _)| k == "threshold"))
            {
                return Err(format!(
                    "--threshold {t} and --set threshold={v} both set the threshold; give one"
                )
                .into());
            }
            if let (Some(m), Some(p)) = (&model, &precision) {
                if p != "auto" {
                    eprintln!(
                        "note: --precision {p} chooses a build of the embedded student; `{}` runs as it is",
                        m.display()
                    );
                }
            }
            // A threshold given twice would run the same pipeline twice.
            let mut thresholds: Vec<f64> = Vec::with_capacity(sweep_thresholds.len());
            for t in sweep_thresholds {
                if !thresholds.contains(&t) {
                    thresholds.push(t);
                }
            }
            eval_cmd(
                &sequence[..],
                eval::GateModel {
                    path: model.as_deref(),
                    precision: precision.as_deref().map(|p| match p {
                        "fp32" => gstleangate::PrecisionChoice::Fp32,
                        "int8" => gstleangate::PrecisionChoice::Int8,
                        _ => gstleangate::PrecisionChoice::Auto,
                    }),
                    feedback: feedback.map(usize::from),
                    depth,
                    properties: &set,
                },
                threshold,
                EvalOutputs {
                    json,
                    plot,
                    contact_sheet,
                    sweep: (sweep || sweep_plot.is_some()).then_some(thresholds),
                    sweep_plot,
                    phases,
                    progress,
                    reconstruct: reconstruct.then_some(eval::reconstruct::SfmConfig {
                        python: sfm_python,
                        dense_every,
                        work_dir: sfm_dir,
                        matcher: sfm_matcher,
                        max_features: sfm_max_features,
                        trajectory_dir,
                    }),
                },
                TeacherConfig {
                    working_width,
                    max_dist_m: max_dist,
                },
            )
        }
    }
}

/// What `leangate eval` writes besides the printed table.
struct EvalOutputs {
    json: Option<PathBuf>,
    plot: Option<PathBuf>,
    contact_sheet: Option<PathBuf>,
    /// Thresholds of the equal-budget sweep, when asked for.
    sweep: Option<Vec<f64>>,
    sweep_plot: Option<PathBuf>,
    /// `--phases`: runs per sequence, each started a frame later.
    phases: usize,
    /// `--progress`: progress lines on a standard error that is not a terminal.
    progress: bool,
    /// `--reconstruct` and its settings.
    reconstruct: Option<eval::reconstruct::SfmConfig>,
}

fn eval_cmd(
    sequences: &[PathBuf],
    model: eval::GateModel<'_>,
    threshold: Option<f64>,
    out: EvalOutputs,
    cfg: TeacherConfig,
) -> Res {
    let EvalOutputs {
        json,
        plot,
        contact_sheet,
        sweep,
        sweep_plot,
        phases,
        progress,
        reconstruct,
    } = out;
    if phases > 1 {
        let per_run = [
            ("--plot", plot.is_some()),
            ("--contact-sheet", contact_sheet.is_some()),
            ("--reconstruct", reconstruct.is_some()),
        ];
        if let Some((flag, _)) = per_run.iter().find(|(_, on)| *on) {
            return Err(format!(
                "--phases {phases} with {flag}: that writes one file per run; use it with one phase"
            )
            .into());
        }
    }
    if let Some(sfm) = &reconstruct {
        // Folders the reconstruction writes into: a file there fails only after the long part.
        let dirs = [
            ("--trajectory-dir", &sfm.trajectory_dir),
            ("--sfm-dir", &sfm.work_dir),
        ];
        for (flag, dir) in dirs {
            if let Some(d) = dir.as_deref().filter(|d| d.exists() && !d.is_dir()) {
                return Err(format!("{flag} `{}`: is a file, not a folder", d.display()).into());
            }
        }
        eval::reconstruct::preflight(sfm)?; // before the long part: a missing pycolmap fails now
    }
    // Where the files go, checked before the long part rather than after it.
    let outputs = [
        ("--json", &json),
        ("--plot", &plot),
        ("--contact-sheet", &contact_sheet),
        ("--sweep-plot", &sweep_plot),
    ];
    for (flag, path) in outputs {
        if let Some(p) = path {
            check_output(flag, p)?;
        }
    }

    for s in sequences {
        if !s.exists() {
            return Err(format!(
                "`{}`: no such sequence directory or video file",
                s.display()
            )
            .into());
        }
        if phases > 1 {
            // a video, or too few frames for the last start: said now, not after the long part
            eval::Source::open_from(s, phases - 1).map_err(|e| e.to_string())?;
        }
        if model.feedback.is_some() {
            eval::check_feedback(s)?;
        }
    }
    // Two outputs at one path: the second would replace the first.
    let mut seen: Vec<(&str, PathBuf)> = Vec::new();
    for (flag, path) in outputs {
        let Some(p) = path else { continue };
        let dir = p.parent().filter(|d| !d.as_os_str().is_empty());
        let parent = dir.map_or_else(|| Path::new(".").canonicalize(), Path::canonicalize);
        let key = parent.map(|d| d.join(p.file_name().unwrap_or_default()));
        let key = key.unwrap_or_else(|_| p.clone());
        if let Some((other, _)) = seen.iter().find(|(_, k)| *k == key) {
            return Err(format!(
                "{other} and {flag} both write `{}`: the second would replace the first",
                p.display()
            )
            .into());
        }
        seen.push((flag, key));
    }
    let several = sequences.len() > 1 || phases > 1;
    // Nothing the eval reads may be what it writes: `--json SEQ/rgb.txt` would replace the list,
    // `--trajectory-dir SEQ` its groundtruth.txt, before anything is judged.
    let inputs = eval::input_files(sequences, model.path)?;
    for (flag, path) in outputs {
        if let Some(p) = path {
            inputs.refuse(flag, p, false)?;
            // With several sequences, --plot and --contact-sheet write one file per sequence.
            if several && matches!(flag, "--plot" | "--contact-sheet") {
                for (k, s) in sequences.iter().enumerate() {
                    inputs.refuse(flag, &per_sequence_path(p, k, s), false)?;
                }
            }
        }
    }
    // The pictures' format, by the extension: a .txt fails only after the long part otherwise.
    for (flag, path) in &outputs[1..] {
        if let Some(p) = path {
            leangate_tools::output::image_format(flag, p)?;
        }
    }
    if let Some(sfm) = &reconstruct {
        for (k, s) in sequences.iter().enumerate() {
            let one = match sequences.len() > 1 || phases > 1 {
                true => sfm.in_subdirectory(&format!("{}-{}", k + 1, sequence_name(s))),
                false => sfm.clone(),
            };
            // What a reconstruction writes there: a TUM trajectory per run and the ground
            // truth; a COLMAP folder per run.
            let runs = eval::POLICIES.iter().chain(&["dense"]);
            if let Some(d) = &one.trajectory_dir {
                inputs.refuse("--trajectory-dir", &d.join("groundtruth.txt"), false)?;
                for p in runs.clone() {
                    inputs.refuse("--trajectory-dir", &d.join(format!("{p}.txt")), false)?;
                }
            }
            if let Some(d) = &one.work_dir {
                for p in runs {
                    inputs.refuse("--sfm-dir", &d.join(p), true)?;
                }
            }
        }
    }
    // On a terminal a bar (indicatif draws nothing elsewhere); with --progress elsewhere, lines.
    let lines = progress && !std::io::IsTerminal::is_terminal(&std::io::stderr());
    let bar = match lines {
        true => indicatif::ProgressBar::hidden(),
        false => indicatif::ProgressBar::new(0),
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg:>8} [{bar:40}] {pos}/{len} frames, {eta} left",
        )
        .unwrap()
        .progress_chars("=> "),
    );
    let mut said: Option<(String, usize)> = None;
    let mut show = |stage: &str, done: usize, total: usize| {
        bar.set_message(stage.to_string());
        if total > 0 {
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
        if lines {
            let tenth = (done * 10).checked_div(total).unwrap_or(0);
            if said.as_ref() != Some(&(stage.to_string(), tenth)) {
                eprintln!("leangate eval: {stage} {done}/{total} frames");
                said = Some((stage.to_string(), tenth));
            }
        }
    };
    // The reconstructions (--reconstruct): a bar of the policies reconstructed, or with
    // --progress elsewhere a line per step of each (its frames, each COLMAP stage, the outcome).
    let sfm_bar = match lines {
        true => indicatif::ProgressBar::hidden(),
        false => indicatif::ProgressBar::new(0),
    };
    sfm_bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg:>14} [{bar:40}] {pos}/{len} reconstructions, {elapsed} so far",
        )
        .unwrap()
        .progress_chars("=> "),
    );
    let show_sfm = |k: usize, runs: usize, policy: &str, step: &str| {
        sfm_bar.set_message(format!("sfm {policy}"));
        sfm_bar.set_length(runs as u64);
        sfm_bar.set_position(k as u64);
        if lines {
            match k < runs {
                true => eprintln!("leangate eval: sfm {}/{runs} {policy}: {step}", k + 1),
                false => eprintln!("leangate eval: sfm {runs}/{runs} {step}"),
            }
        }
    };
    // Which sequences the sweep can run on, known before the long part: alone, a sequence the
    // teacher cannot judge is an error now; among several, it is evaluated without a sweep (said
    // below its table) and the summed curves cover the others.
    let sweepable: Vec<bool> = match &sweep {
        None => vec![false; sequences.len()],
        Some(_) => {
            let checks: Vec<_> = sequences.iter().map(|s| eval::check_sweep(s)).collect();
            if let (1, Some(Err(e))) = (sequences.len(), checks.first()) {
                return Err(e.to_string().into());
            }
            if checks.iter().all(Result::is_err) {
                return Err(
                    "--sweep needs depth, poses and intrinsics in at least one sequence; none has them"
                        .into(),
                );
            }
            checks.iter().map(Result::is_ok).collect()
        }
    };
    let mut reports = Vec::with_capacity(sequences.len() * phases);
    let mut phase_sums = Vec::new();
    for (k, sequence) in sequences.iter().enumerate() {
        let name = sequence_name(sequence);
        let first_run = reports.len();
        for phase in 0..phases {
            let (mut report, data) =
                eval::evaluate(sequence, phase, model, threshold, &cfg, &mut show)?;
            report.phase = (phases > 1).then_some(phase);
            if let (Some(thresholds), true) = (&sweep, sweepable[k]) {
                report.sweep = Some(eval::sweep(
                    sequence, phase, model, thresholds, &cfg, &mut show,
                )?);
            }
            bar.finish_and_clear();
            warn_model_failures(&report);
            if phases > 1 {
                // one line per run; the sums over the runs follow (per-run files are refused)
                print_run_line(&report, phase);
                reports.push(report);
                continue;
            }
            if let Some(sfm) = &reconstruct {
                // Several sequences: each one's models and trajectories in DIR/K-SEQ/.
                let sfm = match several {
                    true => sfm.in_subdirectory(&format!("{}-{}", k + 1, name)),
                    false => sfm.clone(),
                };
                eval::reconstruct::add_reconstruction(
                    sequence,
                    &mut report,
                    &data,
                    &sfm,
                    show_sfm,
                )?;
                sfm_bar.finish_and_clear();
            }
            let per_sequence = |p: &Path| -> PathBuf {
                match several {
                    true => per_sequence_path(p, k, sequence),
                    false => p.to_path_buf(),
                }
            };
            print_summary(&report);
            if report.reconstruction.is_some() {
                print_reconstruction(&report);
            }
            if let Some(points) = &report.sweep {
                print_sweep(points);
            } else if sweep.is_some() {
                say!("no equal-budget sweep here: no depth, poses or intrinsics for the teacher");
            }
            if let (Some(points), Some(p), false) = (&report.sweep, &sweep_plot, several) {
                eval::plot_sweep(points, &format!("{name}: equal-budget curves"), p)?;
                eprintln!("sweep plot written to {}", p.display());
            }
            if let Some(p) = plot.as_deref().map(per_sequence) {
                let title = format!("{name} — threshold {:.3}", report.threshold);
                eval::plot(&data, &title, &p)?;
                eprintln!("plot written to {}", p.display());
            }
            if let Some(p) = contact_sheet.as_deref().map(per_sequence) {
                eval::contact_sheet(&data.kept_thumbs, &data.kept_labels, 64, &p)?;
                eprintln!(
                    "contact sheet of the kept frames written to {}",
                    p.display()
                );
            }
            if several {
                say!("");
            }
            reports.push(report);
        }
        if phases > 1 {
            let sum = eval::sum_phases(&reports[first_run..]);
            print_sums(
                &format!(
                    "{name}, from {phases} start frames (0 to {} frames in)",
                    phases - 1
                ),
                &sum.sums,
            );
            let ranges: Vec<String> = sum
                .kept_range
                .iter()
                .map(|(p, (lo, hi))| format!("{p} {lo}–{hi}"))
                .collect();
            say!("kept in one run: {}", ranges.join(", "));
            if let Some(points) = &sum.sweep_sums {
                say!("summed over the {phases} runs:");
                print_sweep(points);
            } else if sweep.is_some() {
                say!("no equal-budget sweep here: no depth, poses or intrinsics for the teacher");
            }
            say!("");
            phase_sums.push(sum);
        }
    }
    let text = if several {
        let sweeps: Vec<Vec<eval::SweepPoint>> =
            reports.iter().filter_map(|r| r.sweep.clone()).collect();
        let swept = sweeps.len();
        let multi = eval::MultiReport {
            sums: eval::sum_policies(&reports),
            sweep_sums: (swept > 0).then(|| eval::sum_sweeps(&sweeps)),
            sequences: reports,
            phase_sums: (phases > 1).then_some(phase_sums),
        };
        // runs: sequences, or sequences x start frames with --phases
        let runs = match phases {
            1 => "sequences".to_string(),
            _ => format!(
                "runs ({} sequences x {phases} start frames)",
                sequences.len()
            ),
        };
        let frames = multi.sums.first().map_or(0, |s| s.frames);
        // one sequence from several start frames: its sums above are the whole
        if sequences.len() > 1 {
            print_sums(
                &format!(
                    "sums over {} {runs} ({frames} frames)",
                    multi.sequences.len()
                ),
                &multi.sums,
            );
        }
        if let (Some(points), true) = (&multi.sweep_sums, sequences.len() > 1) {
            match swept == multi.sequences.len() {
                true => say!("summed over the {swept} {runs}:"),
                false => say!(
                    "summed over the {swept} {runs} with ground truth (of {}):",
                    multi.sequences.len()
                ),
            }
            print_sweep(points);
        }
        if let Some(points) = &multi.sweep_sums {
            if let Some(p) = &sweep_plot {
                let title = format!("{swept} {runs}: summed equal-budget curves");
                eval::plot_sweep(points, &title, p)?;
                eprintln!("sweep plot of the sums written to {}", p.display());
            }
        }
        serde_json::to_string_pretty(&multi)?
    } else {
        serde_json::to_string_pretty(&reports[0])?
    };
    if let Some(p) = &json {
        leangate_tools::output::write(p, text.as_bytes())?;
    }
    stdout_result()
}

/// Where `label` and `geometry` write their CSV: `--out`, whole or not at all (a failed or
/// interrupted run leaves the file that was there), or standard output.
fn csv_sink(out: Option<&Path>) -> Result<OutputFile, String> {
    match out {
        Some(p) => OutputFile::create(p),
        None => Ok(OutputFile::stdout()),
    }
}

/// `--out` of `label` and `geometry`, checked before any work: a file in a directory that exists,
/// and none of the files the command reads (the sequence's lists and images, the pairs file).
fn check_csv_out(out: Option<&Path>, sequence: &Path, pairs: Option<&Path>) -> Res {
    let Some(p) = out else { return Ok(()) };
    check_output("--out", p)?;
    let inputs = eval::input_files(&[sequence.to_path_buf()], pairs)?;
    Ok(inputs.refuse("--out", p, false)?)
}

/// An output file `path` can be written: not a directory, in a directory that exists.
fn check_output(flag: &str, path: &Path) -> Res {
    if path.is_dir() {
        return Err(format!("{flag} `{}`: is a directory, not a file", path.display()).into());
    }
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() && !dir.is_dir() => Err(format!(
            "{flag} `{}`: no directory `{}`",
            path.display(),
            dir.display()
        )
        .into()),
        _ => Ok(()),
    }
}

/// One line per run of `--phases`: where it started, what the model and the oracle kept.
/// A model that failed on frames (kept, fail open) is said on standard error, whatever else is
/// printed: its `model` row would otherwise read as the model's own keeps.
fn warn_model_failures(r: &eval::EvalReport) {
    if r.model_failed_frames > 0 {
        // On standard error whatever --json says: the model row's keeps are then not the model's.
        eprintln!(
            "warning: {}: the model failed on {} of {} frames, which were kept (fail open): the \
         `model` row and the budget of every other policy count them{}",
            r.sequence,
            r.model_failed_frames,
            r.frames,
            r.model_failure
                .as_deref()
                .map_or(String::new(), |w| format!(" (the element: {w})"))
        );
    }
}

fn print_run_line(report: &eval::EvalReport, phase: usize) {
    let kept = |p: &str| {
        report
            .policies
            .get(p)
            .and_then(|r| r.get("kept"))
            .and_then(|v| v.as_u64())
    };
    let late = report
        .policies
        .get("model")
        .and_then(|r| r.get("late_keeps"))
        .and_then(|v| v.as_u64());
    let judged = match (kept("oracle"), late) {
        (Some(o), Some(l)) => format!(", oracle {o}, late {l}"),
        _ => String::new(),
    };
    say!(
        "{}: started {phase} frames in, {} frames: model kept {}{judged}",
        report.sequence,
        report.frames,
        kept("model").unwrap_or(0)
    );
}

/// The table of sums per policy over several sequences (or runs), under `heading`.
fn print_sums(heading: &str, sums: &[eval::PolicySum]) {
    if sums.is_empty() {
        return;
    }
    let first = &sums[0];
    say!("{heading}:");
    // Some sequences without ground truth: the teacher's columns are over the others, and
    // `judged` is each policy's kept frames there (what kept/oracle divides).
    let partial = first.judged_sequences < first.sequences;
    if partial {
        say!(
            "(oracle, kept/oracle, late, breaks, min S: over the {} with ground truth; judged = kept there)",
            first.judged_sequences
        );
    }
    let judged = |s: &eval::PolicySum| match partial {
        true => format!(" {:>6}", s.judged_kept),
        false => String::new(),
    };
    say!(
        "{:<11} {:>5}{} {:>8} {:>11} {:>6} {:>6} {:>7}",
        "policy",
        "kept",
        if partial { " judged" } else { "" },
        "oracle",
        "kept/oracle",
        "late",
        "breaks",
        "min S"
    );
    let u = |v: Option<usize>| v.map_or("-".to_string(), |x| x.to_string());
    let f = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.3}"));
    for s in sums {
        say!(
            "{:<11} {:>5}{} {:>8} {:>11} {:>6} {:>6} {:>7}",
            s.policy,
            s.kept,
            judged(s),
            u(s.oracle_kept),
            f(s.kept_over_oracle),
            u(s.late_keeps),
            u(s.breaks),
            f(s.min_pair_s)
        );
    }
}

fn print_summary(r: &eval::EvalReport) {
    let feedback = r.feedback_offset.map_or(String::new(), |o| {
        format!(", with feedback (offset {o:+.3} at the end)")
    });
    let unjudged = match r.frames_without_ground_truth {
        Some(k) if k > 0 => format!(" ({k} without ground truth: gated, not judged)"),
        _ => String::new(),
    };
    say!(
        "{}: {} frames{unjudged}, model {} ({}, {}), threshold {:.3}{feedback}",
        r.sequence,
        r.frames,
        r.model,
        r.model_precision,
        r.execution_provider,
        r.threshold
    );
    say!(
        "{:<11} {:>5} {:>7} {:>6} {:>5} {:>6} {:>7} {:>7} {:>7} {:>6} {:>7} {:>7}",
        "policy",
        "kept",
        "ratio",
        "x",
        "breaks",
        "late",
        "min S",
        "med S",
        "overdue",
        "sharp",
        "rmse",
        "fps"
    );
    let f = |v: &serde_json::Value, digits: usize| match v.as_f64() {
        Some(x) if v.is_u64() => format!("{x:.0}"),
        Some(x) => format!("{x:.digits$}"),
        None => "-".to_string(),
    };
    for (name, p) in &r.policies {
        let g = |k: &str| p.get(k).cloned().unwrap_or(serde_json::Value::Null);
        say!(
            "{:<11} {:>5} {:>7} {:>6} {:>5} {:>6} {:>7} {:>7} {:>7} {:>6} {:>7} {:>7}",
            name,
            f(&g("kept"), 0),
            f(&g("keep_ratio"), 3),
            f(&g("downsample"), 1),
            f(&g("breaks"), 0),
            f(&g("late_keeps"), 0),
            f(&g("min_pair_S"), 3),
            f(&g("median_pair_S"), 3),
            f(&g("overdue_drops"), 0),
            f(&g("kept_sharpness"), 2),
            f(&g("utility_rmse"), 3),
            f(&g("fps"), 1),
        );
    }
    // What the columns mean, under the first table of a run (docs: README, "The tools").
    static LEGEND: std::sync::Once = std::sync::Once::new();
    LEGEND.call_once(|| say!("{EVAL_LEGEND}"));
}

/// The legend of the eval table's columns, printed once per run under the first table.
const EVAL_LEGEND: &str = "columns:
  kept: frames the policy kept; ratio: kept / frames; x: frames / kept (the downsampling)
  every judged pair (consecutive keeps a, b) by the teacher's S(b, a):
    breaks: S < 0.05 (MASt3R-SLAM's tracking fails); late: S < 0.333 (a keyframe was due in
    between); min S, med S: the smallest and median S
  overdue: dropped frames whose teacher tau against the policy's reference was already >= the
    threshold; sharp: the kept frames' median sharpness as a fraction of the sharpest frame
    within +-3 of each (variance of the Laplacian at 320x240; JSON also `kept_blurred`, the share
    below one half); rmse: the policy's utility against the teacher's tau; fps: frames/s of the model
    run (the element in a pipeline, with the eval's own decoding)
  oracle: the gate driven by the exact teacher (the upper bound on utility), deciding each frame
    at once, without the look-back and blind to sharpness: its keeps are not picked for
    sharpness, and one where tau jumps past 0.667 in a single frame (fast motion) is late
  stride, pixel_diff, motion, overlap: cheap gates tuned to the model's kept count (an equal
    budget)";

/// With several sequences, the file `--plot` or `--contact-sheet` writes for the `k`-th
/// (0-based): NAME-K-SEQ.ext beside the given path.
fn per_sequence_path(p: &Path, k: usize, sequence: &Path) -> PathBuf {
    let stem = p
        .file_stem()
        .map(|s| s.to_string_lossy())
        .unwrap_or_default();
    let ext = p
        .extension()
        .map(|s| format!(".{}", s.to_string_lossy()))
        .unwrap_or_default();
    p.with_file_name(format!("{stem}-{}-{}{ext}", k + 1, sequence_name(sequence)))
}

/// The last component of a sequence's path (its name in titles and file names).
fn sequence_name(sequence: &Path) -> String {
    // `.` or `..` have no file name of their own: the directory's real one.
    let named = sequence
        .file_name()
        .map(|s| s.to_os_string())
        .or_else(|| Some(sequence.canonicalize().ok()?.file_name()?.to_os_string()));
    named.map_or_else(|| "sequence".into(), |s| s.to_string_lossy().to_string())
}

/// The `--reconstruct` table: per policy, frames kept, registered / kept, ATE and ATE relative to
/// dense, COLMAP's time and the speed-up against dense, the gate's own time and the end-to-end
/// speed-up (gate + SfM); then the model's headline in one sentence.
fn print_reconstruction(r: &eval::EvalReport) {
    if let Some(info) = &r.reconstruction {
        say!(
            "reconstruction ({}; dense = every {}th frame; ATE after a similarity alignment; \
             speed-up = dense's SfM time / the policy's):",
            info.engine,
            info.dense_every
        );
    }
    say!(
        "{:<11} {:>5} {:>10} {:>6} {:>7} {:>8} {:>7} {:>8} {:>7} {:>9}",
        "policy",
        "kept",
        "registered",
        "models",
        "ATE cm",
        "ATE/dns",
        "SfM s",
        "speed-up",
        "gate s",
        "end-to-end"
    );
    let num = |p: &serde_json::Value, k: &str, d: usize, suffix: &str| {
        p.get(k)
            .and_then(|v| v.as_f64())
            .map(|x| format!("{x:.d$}{suffix}"))
            .unwrap_or_else(|| "-".into())
    };
    for (name, p) in &r.policies {
        let kept = p.get("kept").and_then(|v| v.as_u64()).unwrap_or(0);
        if let Some(e) = p.get("sfm_error").and_then(|v| v.as_str()) {
            say!("{name:<11} {kept:>5} failed: {e}");
            continue;
        }
        let Some(reg) = p.get("registered").and_then(|v| v.as_u64()) else {
            continue;
        };
        say!(
            "{:<11} {:>5} {:>10} {:>6} {:>7} {:>8} {:>7} {:>8} {:>7} {:>9}",
            name,
            kept,
            format!("{reg}/{kept}"),
            num(p, "models", 0, ""),
            num(p, "ate_rmse_cm", 2, ""),
            num(p, "ate_vs_dense", 2, "x"),
            num(p, "sfm_seconds", 1, ""),
            num(p, "sfm_speedup", 2, "x"),
            num(p, "gate_seconds", 1, ""),
            num(p, "end_to_end_speedup", 2, "x"),
        );
    }
    let model = r.policies.get("model");
    let field = |k: &str| model.and_then(|p| p.get(k)).and_then(|v| v.as_f64());
    if let (Some(speed), Some(ate)) = (field("sfm_speedup"), field("ate_vs_dense")) {
        let e2e = field("end_to_end_speedup")
            .map(|x| format!(" ({x:.2}x counting the gate)"))
            .unwrap_or_default();
        say!("model: SfM {speed:.2}x faster than dense{e2e} at {ate:.2}x dense's ATE");
    }
    // What the columns mean, under the first reconstruction table of a run.
    static LEGEND: std::sync::Once = std::sync::Once::new();
    LEGEND.call_once(|| say!("{RECONSTRUCTION_LEGEND}"));
}

/// The legend of the `--reconstruct` table's columns, printed once per run under the first one.
const RECONSTRUCTION_LEGEND: &str = "reconstruction columns:
  kept: frames given to COLMAP (dense: every K-th frame); registered: of those, frames posed in
    the largest model; models: models COLMAP built that hold frames no larger one has (more
    than 1: the reconstruction fell apart)
  ATE cm: RMSE of the registered camera centres against the ground truth after a similarity
    alignment (with scale; - without ground truth or under 3 frames); ATE/dns: that ATE / dense's
  SfM s: COLMAP's own time (features, matching, mapping); speed-up: dense's SfM s / the
    policy's; gate s: the gate's own time (model: its pipeline; stride, dense: 0; - not
    measured: the oracle needs the teacher, the cheap gates run on the eval's thumbnails);
    end-to-end: dense's SfM s / (gate s + SfM s)";

fn print_sweep(points: &[eval::SweepPoint]) {
    say!(
        "equal-budget sweep (each cell: kept k, late keeps l, breaks b, at each model threshold):"
    );
    let header: String = eval::POLICIES.iter().map(|p| format!(" {p:>12}")).collect();
    say!("{:>6}{header}", "T");
    let mut thresholds: Vec<f64> = points.iter().map(|p| p.threshold).collect();
    thresholds.dedup();
    for t in thresholds {
        let cell = |policy: &str| {
            points
                .iter()
                .find(|p| p.threshold == t && p.policy == policy)
                .map(|p| format!("{}k {}l {}b", p.kept, p.late_keeps, p.breaks))
                .unwrap_or_else(|| "-".into())
        };
        let row: String = eval::POLICIES
            .iter()
            .map(|p| format!(" {:>12}", cell(p)))
            .collect();
        say!("{t:>6.3}{row}");
    }
}

/// Pairs `i,j` (frame indices below `n`; further columns are ignored) from a CSV file. Blank
/// lines and `#` comments are skipped; only the first other line may be a header (it is one when
/// no field of it looks like a number); any later line that is not two frame indices is an error
/// naming the line.
/// `i,j` pairs of frame indices below `n`, one per line (a header line is allowed); with
/// `ordered`, the reference `j` must come before the current frame `i`. Errors name the line.
fn read_pairs(path: &Path, n: usize, ordered: bool) -> Result<Vec<(usize, usize)>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("`{}`: {e}", path.display()))?;
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    let mut out = Vec::new();
    let mut first = true;
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let at = || format!("`{}` line {}", path.display(), k + 1);
        let fields: Vec<&str> = line
            .split([',', ' ', '\t'])
            .filter(|s| !s.is_empty())
            .collect();
        let numeric =
            |f: &&str| f.starts_with(|c: char| c.is_ascii_digit() || c == '-' || c == '+');
        if std::mem::take(&mut first) && !fields.iter().any(numeric) {
            continue; // header
        }
        let [a, b, ..] = fields[..] else {
            return Err(format!(
                "{}: expected `i,j` frame indices, got {line:?}",
                at()
            ));
        };
        let index = |f: &str| {
            f.parse::<usize>()
                .map_err(|e| format!("{}: {f:?} is not a frame index ({e})", at()))
        };
        let (i, j) = (index(a)?, index(b)?);
        if i >= n || j >= n {
            return Err(format!(
                "{}: pair ({i}, {j}) out of range ({n} frames)",
                at()
            ));
        }
        if ordered && j >= i {
            return Err(format!(
                "{}: pair {i},{j}: the reference must come before the current frame",
                at()
            ));
        }
        out.push((i, j));
    }
    Ok(out)
}

fn random_pairs(n: usize, count: usize, max_gap: usize, seed: u64) -> Vec<(usize, usize)> {
    let mut rng = synth::SplitMix64::new(seed ^ 0x5eed_1abe1);
    let mut out = Vec::with_capacity(count);
    if n < 2 {
        return out;
    }
    while out.len() < count {
        let i = rng.below(n);
        let gap = 1 + rng.below(max_gap.max(1).min(n - 1));
        let j = if rng.below(2) == 0 {
            i.checked_sub(gap)
        } else {
            Some(i + gap).filter(|&j| j < n)
        };
        if let Some(j) = j {
            out.push((i, j));
        }
    }
    out
}
