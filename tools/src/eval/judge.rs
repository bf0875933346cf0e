//! Judging a gate's decisions against the exact teacher.

use std::collections::HashMap;

use serde::Serialize;

use super::GroundTruth;
use super::{Trace, BREAK_S, KEYFRAME_S};
use crate::teacher::PairScore;

/// Judgement of one policy. Field names are the JSON keys.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PolicyReport {
    pub kept: usize,
    pub keep_ratio: f64,
    pub downsample: f64,
    pub breaks: Option<usize>,
    pub late_keeps: Option<usize>,
    #[serde(rename = "min_pair_S")]
    pub min_pair_s: Option<f64>,
    #[serde(rename = "median_pair_S")]
    pub median_pair_s: Option<f64>,
    pub overdue_drops: Option<usize>,
    /// With frames lacking ground truth: the kept frames that have it (what `oracle`'s count is
    /// compared with) and the consecutive kept pairs the teacher could judge.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub judged_kept: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub judged_pairs: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub utility_mae: Option<Option<f64>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub utility_rmse: Option<Option<f64>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// The kept frames' sharpness, each as a fraction of the sharpest frame within
    /// ±[`SHARP_NEIGHBOURS`] of it ([`kept_sharpness`]): the median, and the share below one half.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kept_sharpness: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kept_blurred: Option<f64>,
}

/// How many frames on each side a kept frame's sharpness is compared with.
pub const SHARP_NEIGHBOURS: usize = 3;

/// `(median, share below 0.5)` over the kept frames of each one's sharpness divided by the
/// largest within ±[`SHARP_NEIGHBOURS`] frames (itself included): 1 when no neighbour is
/// sharper. Frames without a sharpness (junk) are left out; None when no kept frame has one.
pub fn kept_sharpness(keep: &[bool], sharpness: &[Option<f64>]) -> Option<(f64, f64)> {
    let n = keep.len().min(sharpness.len());
    let mut ratios: Vec<f64> = (0..n)
        .filter(|&i| keep[i])
        .filter_map(|i| {
            let s = sharpness[i]?;
            let lo = i.saturating_sub(SHARP_NEIGHBOURS);
            let hi = (i + SHARP_NEIGHBOURS + 1).min(n);
            let best = sharpness[lo..hi].iter().flatten().fold(s, |m, &v| m.max(v));
            Some(if best > 0.0 { s / best } else { 1.0 })
        })
        .collect();
    if ratios.is_empty() {
        return None;
    }
    ratios.sort_by(|a, b| a.total_cmp(b));
    let m = ratios.len();
    let median = if m % 2 == 1 {
        ratios[m / 2]
    } else {
        0.5 * (ratios[m / 2 - 1] + ratios[m / 2])
    };
    let blurred = ratios.iter().filter(|&&r| r < 0.5).count() as f64 / m as f64;
    Some((median, blurred))
}

/// Teacher scores by stream frame, memoised (policies share many pairs); `None` for a pair with
/// a frame that has no ground truth.
pub struct TeacherCache<'a> {
    teacher: &'a GroundTruth,
    memo: HashMap<(usize, usize), Option<PairScore>>,
}

impl<'a> TeacherCache<'a> {
    pub fn new(teacher: &'a GroundTruth) -> Self {
        TeacherCache {
            teacher,
            memo: HashMap::new(),
        }
    }

    /// Score many (current, keyframe) pairs in parallel, remembering them.
    pub fn prefetch(&mut self, pairs: &[(usize, usize)]) {
        let todo: Vec<_> = pairs
            .iter()
            .copied()
            .filter(|p| !self.memo.contains_key(p))
            .collect::<std::collections::HashSet<_>>()
            .into_iter()
            .collect();
        let scores = self.teacher.score_pairs(&todo);
        self.memo.extend(todo.into_iter().zip(scores));
    }

    /// Whether stream frame `i` has ground truth.
    pub fn judges(&self, i: usize) -> bool {
        self.teacher.judges(i)
    }

    pub fn get(&mut self, cur: usize, key: usize) -> Option<PairScore> {
        if let Some(s) = self.memo.get(&(cur, key)) {
            return *s;
        }
        let s = self.teacher.score(cur, key);
        self.memo.insert((cur, key), s);
        s
    }
}

/// Judge a trace. `scored`: whether the policy has its own utility (MAE/RMSE keys present).
pub fn judge(
    trace: &Trace,
    teacher: Option<&mut TeacherCache>,
    threshold: f64,
    scored: bool,
    fps: Option<f64>,
) -> PolicyReport {
    let n = trace.keep.len();
    let kept = trace.kept();
    let mut r = PolicyReport {
        kept,
        keep_ratio: if n > 0 { kept as f64 / n as f64 } else { 0.0 },
        downsample: if kept > 0 {
            n as f64 / kept as f64
        } else {
            0.0
        },
        breaks: None,
        late_keeps: None,
        min_pair_s: None,
        median_pair_s: None,
        overdue_drops: None,
        judged_kept: None,
        judged_pairs: None,
        utility_mae: scored.then_some(None),
        utility_rmse: scored.then_some(None),
        fps,
        kept_sharpness: None,
        kept_blurred: None,
    };
    let Some(tc) = teacher else {
        return r;
    };
    let refs = trace.references();
    let pairs = trace.kept_pairs();
    let mut wanted: Vec<(usize, usize)> = pairs.iter().map(|&(a, b)| (b, a)).collect();
    wanted.extend(
        refs.iter()
            .enumerate()
            .filter_map(|(i, r)| r.map(|r| (i, r))),
    );
    tc.prefetch(&wanted);
    let mut s: Vec<f64> = pairs
        .iter()
        .filter_map(|&(a, b)| tc.get(b, a).map(|p| p.s))
        .collect();
    // Counts only where something was judged: pairs the teacher could not score (a frame
    // without ground truth) are not "no late keep".
    let judged_all = s.len() == pairs.len();
    if s.is_empty() && !pairs.is_empty() {
        r.breaks = None;
        r.late_keeps = None;
    } else {
        r.breaks = Some(s.iter().filter(|&&v| v < BREAK_S).count());
        r.late_keeps = Some(s.iter().filter(|&&v| v < KEYFRAME_S).count());
    }
    let lacking = (0..n).any(|i| !tc.judges(i));
    if lacking || !judged_all {
        r.judged_kept = Some((0..n).filter(|&i| trace.keep[i] && tc.judges(i)).count());
        r.judged_pairs = Some(s.len());
    }
    s.sort_by(|a, b| a.total_cmp(b));
    r.min_pair_s = s.first().copied();
    r.median_pair_s = if s.is_empty() {
        None
    } else if s.len() % 2 == 1 {
        Some(s[s.len() / 2])
    } else {
        Some(0.5 * (s[s.len() / 2 - 1] + s[s.len() / 2]))
    };
    let (mut overdue, mut judged_frames) = (0, 0);
    let (mut abs_sum, mut sq_sum, mut count) = (0.0, 0.0, 0usize);
    for (i, reference) in refs.iter().enumerate() {
        let Some(reference) = *reference else {
            continue;
        };
        let Some(t) = tc.get(i, reference).map(|p| p.tau) else {
            continue; // this frame or its reference has no ground truth: not judged
        };
        judged_frames += 1;
        if !trace.keep[i] && t >= threshold {
            overdue += 1;
        }
        if let Some(u) = trace.utility[i] {
            abs_sum += (u - t).abs();
            sq_sum += (u - t) * (u - t);
            count += 1;
        }
    }
    r.overdue_drops = (judged_frames > 0 || refs.iter().all(Option::is_none)).then_some(overdue);
    if scored && count > 0 {
        r.utility_mae = Some(Some(abs_sum / count as f64));
        r.utility_rmse = Some(Some((sq_sum / count as f64).sqrt()));
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::tests::trace;

    #[test]
    fn kept_sharpness_compares_each_keep_with_its_neighbours() {
        let s = |v: &[f64]| v.iter().map(|&x| Some(x)).collect::<Vec<_>>();
        // Frame 4 (sharpness 10) has a neighbour at 40 within 3 frames: 0.25; frame 9 is the
        // sharpest around it: 1.
        let sharp = s(&[
            40.0, 40.0, 40.0, 40.0, 10.0, 40.0, 20.0, 20.0, 20.0, 30.0, 5.0,
        ]);
        let mut keep = vec![false; sharp.len()];
        keep[4] = true;
        keep[9] = true;
        let (median, blurred) = kept_sharpness(&keep, &sharp).unwrap();
        assert!((median - 0.625).abs() < 1e-12, "{median}");
        assert_eq!(blurred, 0.5);
        // Junk (no sharpness) is left out; nothing measurable gives None.
        let mut junk = sharp.clone();
        junk[4] = None;
        assert_eq!(kept_sharpness(&keep, &junk), Some((1.0, 0.0)));
        assert_eq!(kept_sharpness(&[true], &[None]), None);
    }

    #[test]
    fn judge_without_teacher_has_counts_only() {
        let t = trace(&[1, 0, 1, 0]);
        let r = judge(&t, None, 0.5, true, Some(12.0));
        assert_eq!((r.kept, r.keep_ratio, r.downsample), (2, 0.5, 2.0));
        assert_eq!(r.breaks, None);
        let v = serde_json::to_value(&r).unwrap();
        let keys: Vec<_> = v.as_object().unwrap().keys().cloned().collect();
        for k in [
            "kept",
            "keep_ratio",
            "downsample",
            "breaks",
            "late_keeps",
            "min_pair_S",
            "median_pair_S",
            "overdue_drops",
            "utility_mae",
            "utility_rmse",
            "fps",
        ] {
            assert!(keys.contains(&k.to_string()), "{k} missing in {keys:?}");
        }
        assert!(v["breaks"].is_null() && v["utility_mae"].is_null());
        let unscored = serde_json::to_value(judge(&t, None, 0.5, false, None)).unwrap();
        assert_eq!(unscored.as_object().unwrap().len(), 8);
    }
}
