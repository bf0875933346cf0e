//! `leangate eval`: run gating policies over a sequence and judge each against the teacher.
//!
//! Policies:
//! - `model`: the real `leangate` element, in annotate mode, in a real pipeline (appsrc for image
//!   sequences, filesrc ! decodebin for videos), with the given model;
//! - `oracle`: the same gate ([`gstleangate::Gate`]) driven by the teacher's tau (the upper bound);
//! - `stride`: every s-th frame, s chosen so the kept count matches `model`'s;
//! - `pixel_diff`: an mpdecimate-like gate (8x8 block SADs against the last kept frame, on a
//!   160x120 grey thumbnail), its thresholds scaled so the kept count matches `model`'s;
//! - `motion`: mean sparse pyramidal Lucas-Kanade displacement since the last keep above a pixel
//!   threshold (DROID-SLAM's motion filter, DSO), the threshold chosen for `model`'s budget;
//! - `overlap`: the view overlap since the last keep from chained frame-to-frame homographies (the
//!   element's geometric prior, no depth), scored like the teacher; keep below a threshold chosen
//!   for `model`'s budget (the classical tracked-overlap keyframe rule).
//!
//! `--sweep` ([`sweep`]) repeats this over a range of model thresholds: every policy at every
//! budget the model reaches, the honest equal-budget comparison.
//!
//! Judging (all against the teacher, so only with depth + poses): for consecutive kept frames
//! (a, b) the teacher's S(b, a): `breaks` (S < 0.05, where MASt3R-SLAM tracking fails),
//! `late_keeps` (S < 0.333: a keyframe was due in between), `min_pair_S`, `median_pair_S`;
//! `overdue_drops`: dropped frames whose teacher tau against the gate's reference was already
//! at or above the threshold; for scored policies `utility_mae` / `utility_rmse` of the gate's utility
//! against the teacher's tau on the same (reference, frame) pairs.

use std::path::{Path, PathBuf};

use gstleangate::GateConfig;
use serde::Serialize;

use crate::dataset::Sequence;
use crate::teacher::{PairScore, Teacher};

mod baselines;
mod judge;
mod model_run;
pub mod motion;
mod multi;
pub mod overlap;
pub mod reconstruct;
mod report;

pub use crate::output::Inputs;
pub use baselines::{
    oracle_gate, pixel_diff_for_budget, pixel_diff_gate, stride_for_budget, stride_gate,
};
pub use judge::{judge, PolicyReport, TeacherCache};
pub use model_run::{init_gstreamer, run_model, GateModel, ModelRun};
pub use motion::{motion_for_budget, motion_gate};
pub use multi::{sum_phases, sum_policies, sum_sweeps, MultiReport, PhaseSum, PolicySum};
pub use overlap::{overlap_for_budget, overlap_gate};
pub use report::{contact_sheet, plot, plot_sweep, LABEL_H};

/// Every policy `evaluate` runs and `sweep` samples, in report order.
pub const POLICIES: [&str; 6] = [
    "model",
    "oracle",
    "stride",
    "pixel_diff",
    "motion",
    "overlap",
];

/// S below which MASt3R-SLAM's tracking breaks.
pub const BREAK_S: f64 = 0.05;
/// MASt3R-SLAM's keyframe threshold on S.
pub const KEYFRAME_S: f64 = gstleangate::KEYFRAME_S;
/// Thumbnail size used by `pixel_diff` and `motion`.
pub const THUMB_W: u32 = 160;
pub const THUMB_H: u32 = 120;
/// Thresholds `--sweep` tries by default.
pub const SWEEP_THRESHOLDS: [f64; 12] = [
    0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.8,
];

/// Any failure of an evaluation, with its context.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct EvalError(pub String);

fn err<E: std::fmt::Display>(ctx: &str) -> impl Fn(E) -> EvalError + '_ {
    move |e| EvalError(format!("{ctx}: {e}"))
}

/// One policy's decisions over a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct Trace {
    pub keep: Vec<bool>,
    /// The gate's own utility for frame i against its reference (None: not scored).
    pub utility: Vec<Option<f64>>,
}

impl Trace {
    pub fn kept(&self) -> usize {
        self.keep.iter().filter(|k| **k).count()
    }

    /// Reference of each frame: the last kept frame before it (kept frames become references).
    pub fn references(&self) -> Vec<Option<usize>> {
        let mut r = None;
        self.keep
            .iter()
            .enumerate()
            .map(|(i, &k)| {
                let this = r;
                if k {
                    r = Some(i);
                }
                this
            })
            .collect()
    }

    /// Consecutive kept pairs (earlier, later).
    pub fn kept_pairs(&self) -> Vec<(usize, usize)> {
        let kept: Vec<usize> = (0..self.keep.len()).filter(|&i| self.keep[i]).collect();
        kept.windows(2).map(|w| (w[0], w[1])).collect()
    }
}

/// The teacher over the frames of a sequence that have ground truth (a depth image and a pose),
/// addressed by a frame's index in the stream the gate sees. Frames without it are gated like the
/// others and not judged: no pair with such a frame is scored, and the oracle runs on the others.
pub struct GroundTruth {
    teacher: Teacher,
    /// Stream frame -> teacher frame.
    index: Vec<Option<usize>>,
    /// Teacher frame -> stream frame.
    frames: Vec<usize>,
}

impl GroundTruth {
    /// The teacher of `seq`'s judged frames; `None` when it cannot judge (no intrinsics, or
    /// fewer than two frames with depth and a pose).
    pub fn of(
        seq: &Sequence,
        cfg: &crate::teacher::TeacherConfig,
    ) -> Result<Option<GroundTruth>, EvalError> {
        if seq.judged_frames() < 2 {
            return Ok(None);
        }
        let frames: Vec<usize> = (0..seq.len())
            .filter(|&i| seq.frames[i].depth.is_some() && seq.frames[i].pose.is_some())
            .collect();
        let judged = Sequence {
            frames: frames.iter().map(|&i| seq.frames[i].clone()).collect(),
            ..seq.clone()
        };
        let teacher = Teacher::from_sequence(&judged, cfg).map_err(|e| EvalError(e.to_string()))?;
        let mut index = vec![None; seq.len()];
        for (k, &i) in frames.iter().enumerate() {
            index[i] = Some(k);
        }
        Ok(Some(GroundTruth {
            teacher,
            index,
            frames,
        }))
    }

    /// Frames of the stream.
    pub fn len(&self) -> usize {
        self.index.len()
    }

    /// Whether the stream has no frame.
    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }

    /// Frames of the stream without ground truth (gated, not judged).
    pub fn lacking(&self) -> usize {
        self.index.len() - self.frames.len()
    }

    /// Whether stream frame `i` has ground truth.
    pub fn judges(&self, i: usize) -> bool {
        self.index.get(i).is_some_and(Option::is_some)
    }

    /// The teacher's score of stream frame `cur` against stream frame `key`; `None` when either
    /// lacks ground truth or is past the end.
    pub fn score(&self, cur: usize, key: usize) -> Option<PairScore> {
        let at = |i: usize| self.index.get(i).copied().flatten();
        Some(self.teacher.score(at(cur)?, at(key)?))
    }

    /// Many [`GroundTruth::score`]s, in parallel.
    pub fn score_pairs(&self, pairs: &[(usize, usize)]) -> Vec<Option<PairScore>> {
        let at = |i: usize| self.index.get(i).copied().flatten();
        let mapped: Vec<(usize, usize)> = pairs
            .iter()
            .filter_map(|&(c, k)| Some((at(c)?, at(k)?)))
            .collect();
        let mut scores = self.teacher.score_pairs(&mapped).into_iter();
        pairs
            .iter()
            .map(|&(c, k)| at(c).zip(at(k)).and_then(|_| scores.next()))
            .collect()
    }

    /// The oracle over the stream: the gate driven by the teacher on the judged frames (a frame
    /// without ground truth is never kept by it).
    pub fn oracle(&self, cfg: GateConfig) -> Trace {
        let (judged, _) = oracle_gate(&self.teacher, cfg);
        let mut keep = vec![false; self.len()];
        let mut utility = vec![None; self.len()];
        for (k, &i) in self.frames.iter().enumerate() {
            keep[i] = judged.keep[k];
            utility[i] = judged.utility[k];
        }
        Trace { keep, utility }
    }
}

/// What the eval runs on.
#[derive(Debug, Clone)]
pub enum Source {
    /// A directory sequence (TUM layout or rgb.txt / images only): every colour frame, matched
    /// to depth and a pose or not.
    Sequence(Sequence),
    /// A video file, decoded by GStreamer.
    Video(PathBuf),
}

impl Source {
    pub fn open(path: &Path) -> Result<Source, EvalError> {
        if path.is_dir() {
            // The gate sees every colour frame, with ground truth or not (a frame without it is
            // gated and not judged: [`GroundTruth`]).
            let all = crate::dataset::OpenOptions {
                drop_unmatched: false,
                ..Default::default()
            };
            Sequence::open_with(path, &all)
                .map(Source::Sequence)
                .map_err(|e| EvalError(e.to_string()))
        } else if path.is_file() {
            Ok(Source::Video(path.to_path_buf()))
        } else {
            Err(EvalError(format!(
                "`{}`: no such sequence directory or video file",
                path.display()
            )))
        }
    }

    /// [`Source::open`] started `start` frames into the sequence (`leangate eval --phases`): its
    /// first `start` frames dropped. A video cannot be started later, and at least two frames
    /// must be left.
    pub fn open_from(path: &Path, start: usize) -> Result<Source, EvalError> {
        let mut source = Source::open(path)?;
        if start > 0 {
            match &mut source {
                Source::Sequence(seq) if seq.len() >= start + 2 => {
                    seq.frames.drain(..start);
                }
                Source::Sequence(seq) => {
                    return Err(EvalError(format!(
                        "`{}`: {} frames, too few to start {start} frames in (--phases)",
                        path.display(),
                        seq.len()
                    )))
                }
                Source::Video(_) => {
                    return Err(EvalError(format!(
                        "`{}`: --phases needs a sequence directory, not a video file",
                        path.display()
                    )))
                }
            }
        }
        Ok(source)
    }
}

/// The full report written as JSON.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub sequence: String,
    /// With `--phases`: how many frames into the sequence this run started.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub phase: Option<usize>,
    pub frames: usize,
    /// Frames the gate saw that have no ground truth (no depth image or pose within the
    /// association window): gated, not judged. Absent when nothing is judged.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames_without_ground_truth: Option<usize>,
    pub threshold: f64,
    /// The model the element ran (its `leangate.name`) and the execution provider, from the
    /// element's `leangate-stats` message.
    pub model: String,
    /// `fp32` or `int8` (the element's `precision`; the embedded student runs INT8 on the CPU).
    pub model_precision: String,
    pub execution_provider: String,
    /// Frames kept because the model failed on them (NaN, an error: kept, fail open), so that
    /// a model failing on every frame is not read as one that keeps every frame.
    pub model_failed_frames: usize,
    /// The element's first warning about such a failure.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_failure: Option<String>,
    /// With `--feedback`: what the element's `feedback-offset` had settled at when the run ended
    /// (the correction the teacher's reports taught it; `model` is that run).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub feedback_offset: Option<f64>,
    /// With `--depth`: frames whose pose the metric gate could not fit (gated by the fallback).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_pose_failures: Option<usize>,
    pub policies: serde_json::Map<String, serde_json::Value>,
    /// Equal-budget curves (`--sweep`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sweep: Option<Vec<SweepPoint>>,
    /// How `--reconstruct` ran ([`reconstruct`]); its per-policy fields (`registered`,
    /// `models`, `ate_rmse_cm`, ...) are in `policies`, with a `dense` reference entry.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reconstruction: Option<reconstruct::ReconstructionInfo>,
}

/// Everything a plot needs.
#[derive(Debug, Clone)]
pub struct PlotData {
    /// Teacher tau of each frame against the model gate's reference (None: no ground truth).
    pub teacher_tau: Vec<Option<f64>>,
    pub predicted_tau: Vec<Option<f64>>,
    pub threshold: f64,
    /// Kept flags per policy, in display order.
    pub kept: Vec<(String, Vec<bool>)>,
    /// Thumbnails of the frames the model kept.
    pub kept_thumbs: Vec<(usize, image::RgbImage)>,
    /// What the contact sheet writes under each of them ([`kept_label`]).
    pub kept_labels: Vec<String>,
}

/// Run every policy and judge it, on the sequence started `start` frames in ([`Source::open_from`]).
/// `progress(stage, done, total)`.
pub fn evaluate(
    path: &Path,
    start: usize,
    model: GateModel<'_>,
    threshold: Option<f64>,
    teacher_cfg: &crate::teacher::TeacherConfig,
    mut progress: impl FnMut(&str, usize, usize),
) -> Result<(EvalReport, PlotData), EvalError> {
    let source = Source::open_from(path, start)?;
    let n_hint = match &source {
        Source::Sequence(s) => s.len(),
        Source::Video(_) => 0,
    };
    let teacher = match &source {
        Source::Sequence(seq) => GroundTruth::of(seq, teacher_cfg)?,
        Source::Video(_) => None,
    };
    if model.feedback.is_some() {
        judged(&source, path, "--feedback")?;
    }
    let fb = teacher.as_ref().filter(|_| model.feedback.is_some());
    let with_depth = model.depth;
    if with_depth {
        if let Source::Video(v) = &source {
            return Err(EvalError(format!(
                "--depth needs a sequence directory with depth and intrinsics, not the video {}",
                v.display()
            )));
        }
    }
    let run = run_model(&source, model, threshold, fb, |d| {
        progress("model", d, n_hint)
    })?;
    let n = run.metas.len();
    let t = run.threshold;
    if let Source::Sequence(seq) = &source {
        if seq.len() != n {
            return Err(EvalError(format!(
                "the pipeline returned {n} frames for a sequence of {}",
                seq.len()
            )));
        }
    }
    let mut cache = teacher.as_ref().map(TeacherCache::new);

    let model_trace = run.trace();
    // `--depth`: frames the element gated colour-only though they had depth (no pose).
    let depth_pose_failures = with_depth.then(|| {
        run.metas
            .iter()
            .filter(|m| m.depth == gstleangate::DepthUse::Lost)
            .count()
    });
    let budget = model_trace.kept();
    let mut policies = serde_json::Map::new();
    let mut kept_rows = Vec::new();
    let sharpness = run.sharpness.clone();
    let mut add = |name: &str, mut report: PolicyReport, trace: &Trace| {
        if let Some((median, blurred)) = judge::kept_sharpness(&trace.keep, &sharpness) {
            report.kept_sharpness = Some(median);
            report.kept_blurred = Some(blurred);
        }
        policies.insert(name.to_string(), serde_json::to_value(report).unwrap());
        kept_rows.push((name.to_string(), trace.keep.clone()));
    };
    add(
        "model",
        judge(&model_trace, cache.as_mut(), t, true, Some(run.fps)),
        &model_trace,
    );
    if let Some(teacher) = teacher.as_ref() {
        progress("oracle", 0, n);
        let oracle = teacher.oracle(GateConfig {
            threshold: t,
            ..Default::default()
        });
        progress("oracle", n, n);
        add(
            "oracle",
            judge(&oracle, cache.as_mut(), t, true, None),
            &oracle,
        );
    }
    let stride = stride_gate(n, stride_for_budget(n, budget));
    add(
        "stride",
        judge(&stride, cache.as_mut(), t, false, None),
        &stride,
    );
    let pd = pixel_diff_for_budget(&run.thumbs, budget);
    add(
        "pixel_diff",
        judge(&pd, cache.as_mut(), t, false, None),
        &pd,
    );
    progress("motion", 0, n);
    let (mo, _) = motion_for_budget(&motion::pyramids(&run.thumbs), budget);
    progress("motion", n, n);
    add("motion", judge(&mo, cache.as_mut(), t, false, None), &mo);
    progress("overlap", 0, n);
    let (ov, _) = overlap_for_budget(&overlap::steps(&run.thumbs), budget);
    progress("overlap", n, n);
    add("overlap", judge(&ov, cache.as_mut(), t, false, None), &ov);

    let refs = model_trace.references();
    let teacher_tau = refs
        .iter()
        .enumerate()
        .map(|(i, r)| match (r, cache.as_mut()) {
            (Some(r), Some(c)) => c.get(i, *r).map(|s| s.tau),
            _ => None,
        })
        .collect();
    Ok((
        EvalReport {
            sequence: path.display().to_string(),
            phase: None,
            frames: n,
            // Also when too few frames have it for the teacher (one): said, not silent.
            frames_without_ground_truth: teacher.as_ref().map(GroundTruth::lacking).or(
                match &source {
                    Source::Sequence(seq) if seq.judged_frames() > 0 => {
                        Some(n - seq.judged_frames())
                    }
                    _ => None,
                },
            ),
            threshold: t,
            model: run.model_name.clone(),
            model_precision: run.model_precision.clone(),
            execution_provider: run.provider.clone(),
            model_failed_frames: run.failed_frames(),
            model_failure: run
                .failure_warning
                .clone()
                .filter(|_| run.failed_frames() > 0),
            feedback_offset: run.feedback_offset,
            depth_pose_failures,
            policies,
            sweep: None,
            reconstruction: None,
        },
        PlotData {
            teacher_tau,
            predicted_tau: model_trace.utility.clone(),
            threshold: t,
            kept: kept_rows,
            kept_labels: run
                .kept_thumbs
                .iter()
                .map(|&(i, _)| kept_label(i, &run))
                .collect(),
            kept_thumbs: run.kept_thumbs,
        },
    ))
}

/// The label of a kept frame on the contact sheet: its index, its time from the first frame, the
/// utility that kept it and, unless it was kept on its score, why (`first`, `max-gap`, ...).
pub fn kept_label(i: usize, run: &ModelRun) -> String {
    let t0 = run.pts.first().copied().flatten();
    let time = match (run.pts.get(i).copied().flatten(), t0) {
        (Some(t), Some(t0)) => format!("{:.2} s", t - t0),
        _ => "- s".into(),
    };
    let Some(m) = run.metas.get(i) else {
        return format!("#{i}  {time}");
    };
    let u = if m.utility.is_finite() {
        format!("u {:.2}", m.utility)
    } else {
        "u -".into()
    };
    match m.reason {
        gstleangate::Reason::Score => format!("#{i}  {time}  {u}"),
        r => format!("#{i}  {time}  {u}  {r}"),
    }
}

/// Every file an eval of `sequences` with `model` reads, as canonical paths: the video file, or
/// the sequence's lists (`rgb.txt`, `depth.txt`, ground truth, `intrinsics.txt`) and every image
/// they name; and the model with the files it reads (a split model's head, external tensor
/// data: [`gstleangate::files_read`]; for `label` and `geometry`: the pairs file). What must never
/// be an output.
pub fn input_files(sequences: &[PathBuf], model: Option<&Path>) -> Result<Inputs, EvalError> {
    let mut files: Vec<PathBuf> = model.into_iter().map(Path::to_path_buf).collect();
    if let Some(m) = model {
        files.extend(gstleangate::files_read(m));
    }
    for s in sequences {
        if !s.is_dir() {
            files.push(s.clone());
            continue;
        }
        for name in crate::dataset::LIST_FILES {
            files.push(s.join(name));
        }
        let all = crate::dataset::OpenOptions {
            drop_unmatched: false,
            ..Default::default()
        };
        let seq = Sequence::open_with(s, &all).map_err(|e| EvalError(e.to_string()))?;
        for f in &seq.frames {
            files.push(f.rgb.clone());
            files.extend(f.depth.clone());
        }
    }
    Ok(Inputs::new(files))
}

/// Whether the teacher can judge a sweep on the sequence at `path` (depth, poses and
/// intrinsics); the error says what it lacks. Cheap: it reads the lists, not the images.
pub fn check_sweep(path: &Path) -> Result<(), EvalError> {
    judged(&Source::open(path)?, path, "--sweep").map(|_| ())
}

/// Whether `--feedback` can run on `path` (the teacher measures what the consumer reports).
pub fn check_feedback(path: &Path) -> Result<(), EvalError> {
    judged(&Source::open(path)?, path, "--feedback").map(|_| ())
}

/// The sequence, when the teacher can judge it (`flag` names what needs it).
fn judged<'a>(source: &'a Source, path: &Path, flag: &str) -> Result<&'a Sequence, EvalError> {
    match source {
        Source::Video(_) => Err(EvalError(format!(
            "{flag} needs a sequence with depth and poses; `{}` is a video",
            path.display()
        ))),
        Source::Sequence(seq) if seq.judged_frames() < 2 => Err(EvalError(format!(
            "{flag} needs depth, poses and intrinsics; `{}` lacks them",
            path.display()
        ))),
        Source::Sequence(seq) => Ok(seq),
    }
}

/// One point of an equal-budget curve: a policy at one setting, judged by the teacher.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SweepPoint {
    pub policy: String,
    /// The model's (and oracle's) threshold this budget comes from.
    pub threshold: f64,
    pub kept: usize,
    pub late_keeps: usize,
    pub breaks: usize,
    #[serde(rename = "min_pair_S")]
    pub min_pair_s: Option<f64>,
    #[serde(rename = "median_pair_S")]
    pub median_pair_s: Option<f64>,
}

/// Equal-budget curves: the model at each threshold (the real element, one pipeline run per
/// threshold), the oracle at the same threshold, and `stride`, `pixel_diff`, `motion` and
/// `overlap` each at the model's budget. Needs depth and poses (the teacher judges every point).
/// On the sequence started `start` frames in, like [`evaluate`].
pub fn sweep(
    path: &Path,
    start: usize,
    model: GateModel<'_>,
    thresholds: &[f64],
    teacher_cfg: &crate::teacher::TeacherConfig,
    mut progress: impl FnMut(&str, usize, usize),
) -> Result<Vec<SweepPoint>, EvalError> {
    let source = Source::open_from(path, start)?;
    let seq = judged(&source, path, "--sweep")?;
    let teacher = GroundTruth::of(seq, teacher_cfg)?.ok_or_else(|| {
        EvalError(format!(
            "--sweep: `{}` has no judged frames",
            path.display()
        ))
    })?;
    let mut cache = TeacherCache::new(&teacher);
    let n = seq.len();
    let mut points = Vec::new();
    let mut pyramids = None;
    let mut thumbs = None;
    let mut steps = None;
    let mut point = |policy: &str, t: f64, trace: &Trace, cache: &mut TeacherCache| {
        let r = judge(trace, Some(cache), t, false, None);
        points.push(SweepPoint {
            policy: policy.to_string(),
            threshold: t,
            kept: r.kept,
            late_keeps: r.late_keeps.unwrap_or(0),
            breaks: r.breaks.unwrap_or(0),
            min_pair_s: r.min_pair_s,
            median_pair_s: r.median_pair_s,
        });
    };
    for (k, &t) in thresholds.iter().enumerate() {
        progress("sweep", k, thresholds.len());
        let fb = model.feedback.map(|_| &teacher);
        let run = run_model(&source, model, Some(t), fb, |_| {})?;
        if run.metas.len() != n {
            return Err(EvalError(format!(
                "the pipeline returned {} frames for a sequence of {n}",
                run.metas.len()
            )));
        }
        let trace = run.trace();
        let budget = trace.kept();
        point("model", t, &trace, &mut cache);
        let cfg = GateConfig {
            threshold: t,
            ..Default::default()
        };
        point("oracle", t, &teacher.oracle(cfg), &mut cache);
        point(
            "stride",
            t,
            &stride_gate(n, stride_for_budget(n, budget)),
            &mut cache,
        );
        let th = thumbs.get_or_insert_with(|| run.thumbs.clone());
        point(
            "pixel_diff",
            t,
            &pixel_diff_for_budget(th, budget),
            &mut cache,
        );
        let pyr = pyramids.get_or_insert_with(|| motion::pyramids(th));
        point("motion", t, &motion_for_budget(pyr, budget).0, &mut cache);
        let st = steps.get_or_insert_with(|| overlap::steps(th));
        point("overlap", t, &overlap_for_budget(st, budget).0, &mut cache);
    }
    progress("sweep", thresholds.len(), thresholds.len());
    Ok(points)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A trace from 0/1 keep flags, unscored.
    pub(crate) fn trace(keep: &[u8]) -> Trace {
        Trace {
            keep: keep.iter().map(|&k| k == 1).collect(),
            utility: vec![None; keep.len()],
        }
    }

    #[test]
    fn references_and_pairs() {
        let t = trace(&[1, 0, 0, 1, 0, 1]);
        assert_eq!(
            t.references(),
            vec![None, Some(0), Some(0), Some(0), Some(3), Some(3)]
        );
        assert_eq!(t.kept_pairs(), vec![(0, 3), (3, 5)]);
        assert_eq!(t.kept(), 3);
    }
}
