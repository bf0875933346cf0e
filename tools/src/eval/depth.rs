//! `leangate eval --depth`: the metric gate ([`gstleangate::metric`]) over a sequence's colour
//! and depth, as an RGB-D camera would feed it (issue 52; the element does not take depth yet).
//!
//! Each frame's grey 160x120 thumbnail (the one every policy sees) and its depth at the teacher's
//! working resolution (every 4th pixel of a 640x480 image: the same 160x120 grid) go to a
//! [`PoseTracker`]; the pose it fits to the reference, never the ground truth, then gives the
//! teacher's own S ([`crate::teacher::score_pair`]) between the frame's and the reference's depth.
//! The gate ([`gstleangate::Gate`], the plain gate, as the oracle's) keeps at `tau >= threshold`;
//! a frame whose pose fails is gated by the geometric prior's overlap since the reference (the
//! colour-only part that needs no model run; [`super::overlap`]), or kept when that chain is lost
//! too (fail open, as the element does).

use gstleangate::geometry::{prior_size, Chain, Mat3};
use gstleangate::metric::{Camera, PoseTracker};
use gstleangate::overlap::score_pair;
use gstleangate::{Gate, GateConfig, Score};

use super::{EvalError, Trace, THUMB_H, THUMB_W};
use crate::dataset::Sequence;
use crate::teacher::{DepthView, DepthViewExt, TeacherConfig};

/// What the depth gate did over a sequence.
#[derive(Debug, Clone)]
pub struct DepthRun {
    pub trace: Trace,
    /// Frames whose pose failed (gated by the fallback).
    pub pose_failures: usize,
}

/// Run the depth gate at `threshold` over `seq` (thumbnails `thumbs`, one per frame; `steps`, the
/// prior's frame-to-frame homographies of them, [`super::overlap::steps`], for the fallback).
pub fn depth_gate(
    seq: &Sequence,
    thumbs: &[Vec<u8>],
    steps: &[Option<Mat3>],
    cfg: &TeacherConfig,
    threshold: f64,
) -> Result<DepthRun, EvalError> {
    let intr = seq
        .intrinsics
        .as_ref()
        .ok_or_else(|| EvalError("--depth needs the sequence's intrinsics.txt".into()))?;
    let (w, h) = (THUMB_W as usize, THUMB_H as usize);
    if seq.frames.iter().all(|f| f.depth.is_none()) {
        return Err(EvalError(
            "--depth needs the sequence's depth images (depth.txt), and it has none".into(),
        ));
    }
    let mut gate = Gate::new(GateConfig {
        threshold,
        ..Default::default()
    });
    let mut tracker: Option<PoseTracker> = None;
    let mut reference: Option<DepthView> = None;
    let (mut keep, mut utility) = (Vec::new(), Vec::new());
    let mut failures = 0;
    let mut chain = Chain::default();
    let (pw, ph) = prior_size(w, h);
    for (i, thumb) in thumbs.iter().enumerate() {
        if i > 0 {
            chain.push(steps.get(i - 1).copied().flatten());
        }
        let grey: Vec<f32> = thumb.iter().map(|&g| g as f32).collect();
        let view = match seq.frames[i].depth {
            Some(_) => {
                let d = seq
                    .load_depth_m(i)
                    .map_err(|e| EvalError(format!("--depth: {e}")))?;
                Some(DepthView::new(&d, intr, cfg).map_err(|e| EvalError(e.to_string()))?)
            }
            None => None,
        };
        // The working grid must be the thumbnail's (640x480 depth at the 160 working width).
        if let Some(v) = view
            .as_ref()
            .filter(|v| (v.width, v.height) != (THUMB_W, THUMB_H))
        {
            return Err(EvalError(format!(
                "--depth: {}'s depth gives a {}x{} working grid, not the {THUMB_W}x{THUMB_H} \
                 of the colour thumbnails (640x480 depth only, for now)",
                seq.frames[i]
                    .depth
                    .as_ref()
                    .map_or(String::new(), |p| p.display().to_string()),
                v.width,
                v.height
            )));
        }
        let pose = match (tracker.as_mut(), gate.has_reference()) {
            (Some(t), true) => t.observe(&grey, w, h),
            _ => None,
        };
        let tau = match (pose, &view, &reference) {
            (Some(p), Some(cur), Some(key)) => {
                // The pose maps the reference camera to this one; the overlap wants this
                // camera's points in the reference's.
                Some(score_pair(cur, key, &p.inverse(), cfg.max_dist_m).tau)
            }
            _ => None,
        };
        let score = if !gate.has_reference() {
            Score::NoReference
        } else if let Some(t) = tau {
            Score::Utility(t)
        } else {
            failures += 1;
            chain
                .score(pw, ph)
                .map_or(Score::Failed, |(tau, _, _)| Score::Utility(tau))
        };
        let d = gate.decide(score);
        keep.push(d.keep);
        utility.push(tau);
        if d.keep {
            chain.start();
            match &view {
                Some(v) => {
                    // The working camera of the thumbnail: a thumbnail pixel is the mean of a
                    // 4x4 block, centred 1.5 full-resolution pixels past the depth's sample.
                    let k = v.step as f64;
                    let cam = Camera {
                        fx: intr.fx / k,
                        fy: intr.fy / k,
                        cx: (intr.cx - (k - 1.0) / 2.0) / k,
                        cy: (intr.cy - (k - 1.0) / 2.0) / k,
                    };
                    let t = tracker.get_or_insert_with(|| PoseTracker::new(cam));
                    t.set_reference(&grey, &v.depth, w, h);
                }
                None => tracker = None,
            }
            reference = view;
        }
    }
    Ok(DepthRun {
        trace: Trace { keep, utility },
        pose_failures: failures,
    })
}
