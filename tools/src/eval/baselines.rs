//! The cheap gates LeanGate must beat, each run at the model's keep budget, and the oracle.
//!
//! - `oracle`: the element's own gate ([`gstleangate::Gate`]) driven by the exact teacher's tau;
//! - `stride`: every s-th frame;
//! - `pixel_diff`: mpdecimate-like 8x8 block differences on a grey thumbnail;
//! - `motion`: mean sparse optical-flow displacement since the last keep (see [`super::motion`]).

use gstleangate::{Gate, GateConfig, Score};

use super::{Trace, THUMB_H, THUMB_W};
use crate::teacher::{PairScore, Teacher};

/// The gate driven by the teacher: the oracle policy. Returns the trace and, per frame, the
/// reference and teacher score used (None for the first frame).
pub fn oracle_gate(teacher: &Teacher, cfg: GateConfig) -> (Trace, Vec<Option<(usize, PairScore)>>) {
    let mut gate = Gate::new(cfg);
    let mut reference = None;
    let mut keep = Vec::with_capacity(teacher.len());
    let mut utility = Vec::with_capacity(teacher.len());
    let mut used = Vec::with_capacity(teacher.len());
    for i in 0..teacher.len() {
        let (score, u) = match reference {
            Some(r) => {
                let s = teacher.score(i, r);
                used.push(Some((r, s)));
                (Score::Utility(s.tau), Some(s.tau))
            }
            None => {
                used.push(None);
                (Score::NoReference, None)
            }
        };
        let d = gate.decide(score);
        if d.keep {
            reference = Some(i);
        }
        keep.push(d.keep);
        utility.push(u);
    }
    (Trace { keep, utility }, used)
}

/// Keep every `stride`-th frame, starting with the first.
pub fn stride_gate(frames: usize, stride: usize) -> Trace {
    let stride = stride.max(1);
    Trace {
        keep: (0..frames).map(|i| i % stride == 0).collect(),
        utility: vec![None; frames],
    }
}

/// The stride whose kept count is closest to `target`.
pub fn stride_for_budget(frames: usize, target: usize) -> usize {
    (1..=frames.max(1))
        .min_by_key(|&s| (frames.div_ceil(s) as i64 - target as i64).abs())
        .unwrap_or(1)
}

/// mpdecimate-like gate on grey thumbnails (THUMB_W x THUMB_H, 0..255): a frame is a duplicate of
/// the last kept one when no 8x8 block differs by more than `hi` (sum of absolute differences)
/// and at most `frac` of the blocks differ by more than `lo`. `scale` multiplies hi and lo.
pub fn pixel_diff_gate(thumbs: &[Vec<u8>], scale: f64) -> Trace {
    let (hi, lo, frac) = (64.0 * 12.0 * scale, 64.0 * 5.0 * scale, 0.33);
    let (bw, bh) = ((THUMB_W / 8) as usize, (THUMB_H / 8) as usize);
    let w = THUMB_W as usize;
    let mut keep = Vec::with_capacity(thumbs.len());
    let mut reference: Option<&Vec<u8>> = None;
    for t in thumbs {
        let k = match reference {
            None => true,
            Some(r) => {
                let mut over_lo = 0usize;
                let mut over_hi = false;
                for by in 0..bh {
                    for bx in 0..bw {
                        let mut sad = 0.0f64;
                        for y in 0..8 {
                            let row = (by * 8 + y) * w + bx * 8;
                            for x in 0..8 {
                                sad +=
                                    (t[row + x] as i32 - r[row + x] as i32).unsigned_abs() as f64;
                            }
                        }
                        over_hi |= sad > hi;
                        over_lo += (sad > lo) as usize;
                    }
                }
                over_hi || over_lo as f64 > frac * (bw * bh) as f64
            }
        };
        if k {
            reference = Some(t);
        }
        keep.push(k);
    }
    Trace {
        utility: vec![None; keep.len()],
        keep,
    }
}

/// Fit a one-parameter gate to a keep budget: bisect `ln(param)` over `[lo, hi]` (the kept
/// count must fall as the parameter grows) and return the trace closest to `target` with its
/// parameter.
pub fn fit_budget(
    target: usize,
    (lo, hi): (f64, f64),
    steps: usize,
    gate: impl Fn(f64) -> Trace,
) -> (Trace, f64) {
    let (mut lo, mut hi) = (lo.ln(), hi.ln());
    let dist = |t: &Trace| (t.kept() as i64 - target as i64).abs();
    let mut best: Option<(Trace, f64)> = None;
    for _ in 0..steps {
        let mid = 0.5 * (lo + hi);
        let t = gate(mid.exp());
        let kept = t.kept();
        if best.as_ref().is_none_or(|(b, _)| dist(&t) < dist(b)) {
            best = Some((t, mid.exp()));
        }
        if best.as_ref().is_some_and(|(b, _)| dist(b) == 0) {
            break;
        }
        if kept > target {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    best.unwrap_or_else(|| (gate(hi.exp()), hi.exp()))
}

/// `pixel_diff` with its thresholds scaled so the kept count is as close as possible to `target`.
pub fn pixel_diff_for_budget(thumbs: &[Vec<u8>], target: usize) -> Trace {
    fit_budget(target, ((-12.0f64).exp(), 6.0f64.exp()), 40, |scale| {
        pixel_diff_gate(thumbs, scale)
    })
    .0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stride_budget() {
        assert_eq!(stride_for_budget(60, 6), 10);
        assert_eq!(stride_for_budget(60, 60), 1);
        assert_eq!(stride_gate(10, 3).kept(), 4);
        assert_eq!(stride_for_budget(60, 1), 60);
    }

    #[test]
    fn pixel_diff_static_and_changing() {
        let a = vec![10u8; (THUMB_W * THUMB_H) as usize];
        let b = vec![200u8; (THUMB_W * THUMB_H) as usize];
        let still = vec![a.clone(); 5];
        assert_eq!(pixel_diff_gate(&still, 1.0).kept(), 1);
        let alternating = vec![a.clone(), b.clone(), a.clone(), b.clone()];
        assert_eq!(pixel_diff_gate(&alternating, 1.0).kept(), 4);
        // Budget tuning reaches a target between the extremes.
        let mut ramp = Vec::new();
        for i in 0..20 {
            ramp.push(vec![i as u8 * 4; (THUMB_W * THUMB_H) as usize]);
        }
        let t = pixel_diff_for_budget(&ramp, 5);
        assert!((t.kept() as i64 - 5).abs() <= 1, "kept {}", t.kept());
    }
}
