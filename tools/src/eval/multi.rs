//! `leangate eval --sequence A --sequence B ...`: one evaluation per sequence and the sums per
//! policy over all of them (the cross-sequence report of the model card), with the equal-budget
//! sweep summed threshold by threshold.

use serde::Serialize;

use super::{EvalReport, SweepPoint, POLICIES};

/// One policy summed over several sequences. The teacher-judged fields (`oracle_kept`,
/// `kept_over_oracle`, `late_keeps`, `breaks`, `min_pair_S`) cover the `judged_sequences` that have
/// ground truth (a video or a sequence without depth has no oracle), `judged_kept` being this
/// policy's kept frames there; they are `None` when no sequence has it.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PolicySum {
    pub policy: String,
    pub sequences: usize,
    pub frames: usize,
    pub kept: usize,
    /// The sequences with ground truth, over which the fields below are summed.
    pub judged_sequences: usize,
    /// This policy's kept frames over the judged sequences.
    pub judged_kept: usize,
    /// The oracle's kept frames over the judged sequences.
    pub oracle_kept: Option<usize>,
    /// `judged_kept / oracle_kept`.
    pub kept_over_oracle: Option<f64>,
    pub late_keeps: Option<usize>,
    pub breaks: Option<usize>,
    /// The smallest teacher S between consecutive keeps over the judged sequences.
    #[serde(rename = "min_pair_S")]
    pub min_pair_s: Option<f64>,
}

/// Every sequence's report and the sums per policy: the JSON of a multi-sequence eval.
#[derive(Debug, Clone, Serialize)]
pub struct MultiReport {
    pub sequences: Vec<EvalReport>,
    pub sums: Vec<PolicySum>,
    /// The equal-budget sweep summed over the sequences at each model threshold (`--sweep`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sweep_sums: Option<Vec<SweepPoint>>,
    /// With `--phases`: each sequence's runs from its different start frames, summed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub phase_sums: Option<Vec<PhaseSum>>,
}

/// One sequence evaluated from several start frames (`leangate eval --phases N`): every policy
/// and the sweep summed over its N runs, with the fewest and most frames one run kept.
#[derive(Debug, Clone, Serialize)]
pub struct PhaseSum {
    pub sequence: String,
    pub phases: usize,
    pub sums: Vec<PolicySum>,
    /// Per policy: the fewest and the most frames it kept in one run.
    pub kept_range: std::collections::BTreeMap<String, (usize, usize)>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sweep_sums: Option<Vec<SweepPoint>>,
}

/// [`PhaseSum`] of one sequence's runs (`runs`: its reports, one per start frame).
pub fn sum_phases(runs: &[EvalReport]) -> PhaseSum {
    let sweeps: Vec<Vec<SweepPoint>> = runs.iter().filter_map(|r| r.sweep.clone()).collect();
    let mut kept_range = std::collections::BTreeMap::new();
    for r in runs {
        for policy in POLICIES {
            if let Some(k) = field_u(r, policy, "kept") {
                let e = kept_range.entry(policy.to_string()).or_insert((k, k));
                *e = (e.0.min(k), e.1.max(k));
            }
        }
    }
    PhaseSum {
        sequence: runs.first().map(|r| r.sequence.clone()).unwrap_or_default(),
        phases: runs.len(),
        sums: sum_policies(runs),
        kept_range,
        sweep_sums: (sweeps.len() == runs.len() && !sweeps.is_empty()).then(|| sum_sweeps(&sweeps)),
    }
}

fn field_u(r: &EvalReport, policy: &str, key: &str) -> Option<usize> {
    r.policies
        .get(policy)?
        .get(key)?
        .as_u64()
        .map(|v| v as usize)
}

fn field_f(r: &EvalReport, policy: &str, key: &str) -> Option<f64> {
    r.policies.get(policy)?.get(key)?.as_f64()
}

/// Sum an optional field over `reports`: `None` when there are none or one lacks it.
fn sum_opt<'a>(
    reports: &[&'a EvalReport],
    value: impl Fn(&'a EvalReport) -> Option<usize>,
) -> Option<usize> {
    match reports.is_empty() {
        true => None,
        false => reports.iter().map(|r| value(r)).sum(),
    }
}

/// Sums per policy over `reports`, in [`POLICIES`] order; a policy missing from every report
/// (the oracle without ground truth) is left out. The teacher's fields are summed over the
/// reports with an oracle (ground truth), see [`PolicySum`].
pub fn sum_policies(reports: &[EvalReport]) -> Vec<PolicySum> {
    let judged: Vec<&EvalReport> = reports
        .iter()
        .filter(|r| r.policies.contains_key("oracle"))
        .collect();
    let oracle_kept = sum_opt(&judged, |r| field_u(r, "oracle", "kept"));
    POLICIES
        .iter()
        .filter(|p| reports.iter().any(|r| r.policies.contains_key(**p)))
        .map(|&policy| {
            let kept = |r: &EvalReport| field_u(r, policy, "kept");
            // On the frames with ground truth only, when some lack it (the oracle's frames).
            let judged_kept: usize = judged
                .iter()
                .filter_map(|r| field_u(r, policy, "judged_kept").or_else(|| kept(r)))
                .sum();
            // A sequence with fewer than two keeps has no pair, so no min pair S: the others
            // decide it.
            let min_pair_s = judged
                .iter()
                .filter_map(|r| field_f(r, policy, "min_pair_S"))
                .reduce(f64::min);
            PolicySum {
                policy: policy.to_string(),
                sequences: reports.len(),
                frames: reports.iter().map(|r| r.frames).sum(),
                kept: reports.iter().filter_map(kept).sum(),
                judged_sequences: judged.len(),
                judged_kept,
                oracle_kept,
                kept_over_oracle: oracle_kept
                    .filter(|&o| o > 0)
                    .map(|o| judged_kept as f64 / o as f64),
                late_keeps: sum_opt(&judged, |r| field_u(r, policy, "late_keeps")),
                breaks: sum_opt(&judged, |r| field_u(r, policy, "breaks")),
                min_pair_s,
            }
        })
        .collect()
}

/// The sweeps of several sequences summed at each (threshold, policy): kept, late keeps and
/// breaks added, min pair S the smallest of those that have one; the median is not summable and
/// left out. Points present in only some sequences are dropped.
pub fn sum_sweeps(sweeps: &[Vec<SweepPoint>]) -> Vec<SweepPoint> {
    let Some(first) = sweeps.first() else {
        return Vec::new();
    };
    first
        .iter()
        .filter_map(|p| {
            let same: Vec<&SweepPoint> = sweeps
                .iter()
                .map(|s| {
                    s.iter()
                        .find(|q| q.policy == p.policy && q.threshold == p.threshold)
                })
                .collect::<Option<_>>()?;
            Some(SweepPoint {
                policy: p.policy.clone(),
                threshold: p.threshold,
                kept: same.iter().map(|q| q.kept).sum(),
                late_keeps: same.iter().map(|q| q.late_keeps).sum(),
                breaks: same.iter().map(|q| q.breaks).sum(),
                min_pair_s: same.iter().filter_map(|q| q.min_pair_s).reduce(f64::min),
                median_pair_s: None,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(name: &str, frames: usize, rows: &[(&str, serde_json::Value)]) -> EvalReport {
        EvalReport {
            sequence: name.into(),
            phase: None,
            frames,
            frames_without_ground_truth: None,
            threshold: 0.5,
            model: "m".into(),
            model_precision: "int8".into(),
            execution_provider: "cpu".into(),
            model_failed_frames: 0,
            model_failure: None,
            feedback_offset: None,
            depth_pose_failures: None,
            policies: rows
                .iter()
                .map(|(k, v)| (k.to_string(), v.clone()))
                .collect(),
            sweep: None,
            reconstruction: None,
        }
    }

    fn row(kept: usize, late: Option<usize>, min_s: Option<f64>) -> serde_json::Value {
        serde_json::json!({"kept": kept, "late_keeps": late, "breaks": late.map(|_| 0), "min_pair_S": min_s})
    }

    #[test]
    fn sums_policies_over_sequences() {
        let a = report(
            "a",
            100,
            &[
                ("model", row(8, Some(1), Some(0.4))),
                ("oracle", row(10, Some(0), Some(0.5))),
                ("motion", row(8, Some(2), Some(0.2))),
            ],
        );
        let b = report(
            "b",
            50,
            &[
                ("model", row(9, Some(0), Some(0.3))),
                ("oracle", row(10, Some(0), Some(0.45))),
                ("motion", row(9, Some(1), Some(0.35))),
            ],
        );
        let s = sum_policies(&[a, b]);
        let names: Vec<&str> = s.iter().map(|p| p.policy.as_str()).collect();
        assert_eq!(names, ["model", "oracle", "motion"]);
        let m = &s[0];
        assert_eq!((m.sequences, m.frames, m.kept), (2, 150, 17));
        assert_eq!(m.oracle_kept, Some(20));
        assert_eq!(m.kept_over_oracle, Some(17.0 / 20.0));
        assert_eq!(
            (m.late_keeps, m.breaks, m.min_pair_s),
            (Some(1), Some(0), Some(0.3))
        );
        assert_eq!(s[2].late_keeps, Some(3));
        assert_eq!(s[2].min_pair_s, Some(0.2));
    }

    #[test]
    fn teacher_sums_cover_the_sequences_with_ground_truth() {
        let a = report(
            "a",
            100,
            &[
                ("model", row(8, Some(1), Some(0.4))),
                ("oracle", row(10, Some(0), Some(0.5))),
            ],
        );
        let b = report("video", 60, &[("model", row(5, None, None))]);
        let s = sum_policies(&[a, b.clone()]);
        let m = &s[0];
        assert_eq!((m.sequences, m.frames, m.kept), (2, 160, 13));
        assert_eq!((m.judged_sequences, m.judged_kept), (1, 8));
        assert_eq!(
            (m.oracle_kept, m.kept_over_oracle),
            (Some(10), Some(8.0 / 10.0))
        );
        assert_eq!(
            (m.late_keeps, m.breaks, m.min_pair_s),
            (Some(1), Some(0), Some(0.4))
        );
        // Nothing judged: the teacher's fields are empty, not zero.
        let s = sum_policies(&[b]);
        assert_eq!(s.len(), 1);
        assert_eq!((s[0].kept, s[0].judged_sequences), (5, 0));
        assert_eq!(
            (s[0].oracle_kept, s[0].late_keeps, s[0].min_pair_s),
            (None, None, None)
        );
    }

    #[test]
    fn a_sequence_with_one_keep_leaves_min_pair_s_to_the_others() {
        // 7scenes_redkitchen_dev: one keep, so no pair and no min pair S.
        let a = report(
            "a",
            100,
            &[
                ("model", row(8, Some(1), Some(0.4))),
                ("oracle", row(10, Some(0), Some(0.5))),
            ],
        );
        let b = report(
            "short",
            60,
            &[
                ("model", row(1, Some(0), None)),
                ("oracle", row(1, Some(0), None)),
            ],
        );
        let s = sum_policies(&[a, b]);
        assert_eq!(s[0].min_pair_s, Some(0.4));
        assert_eq!(s[1].min_pair_s, Some(0.5));
        assert_eq!(s[0].judged_sequences, 2);
    }

    #[test]
    fn sums_sweeps_point_by_point() {
        let p = |policy: &str, t: f64, kept, late, min_s| SweepPoint {
            policy: policy.into(),
            threshold: t,
            kept,
            late_keeps: late,
            breaks: 0,
            min_pair_s: Some(min_s),
            median_pair_s: Some(0.5),
        };
        let a = vec![p("model", 0.4, 10, 1, 0.3), p("motion", 0.4, 10, 2, 0.2)];
        let b = vec![p("model", 0.4, 5, 0, 0.4), p("motion", 0.4, 5, 1, 0.1)];
        let s = sum_sweeps(&[a, b]);
        assert_eq!(s.len(), 2);
        assert_eq!(
            (s[0].kept, s[0].late_keeps, s[0].min_pair_s),
            (15, 1, Some(0.3))
        );
        assert_eq!(
            (s[1].kept, s[1].late_keeps, s[1].min_pair_s),
            (15, 3, Some(0.1))
        );
        assert_eq!(s[0].median_pair_s, None);
    }

    #[test]
    fn phase_sums_hold_each_policys_range_and_sum_the_sweep_only_when_every_run_has_one() {
        let run = |kept: usize, late: usize| {
            report(
                "seq",
                100,
                &[
                    ("model", row(kept, Some(late), Some(0.4))),
                    ("oracle", row(5, Some(0), Some(0.5))),
                ],
            )
        };
        let point = |late: usize| SweepPoint {
            policy: "model".into(),
            threshold: 0.5,
            kept: 4,
            late_keeps: late,
            breaks: 0,
            min_pair_s: Some(0.4),
            median_pair_s: Some(0.5),
        };
        let mut runs = vec![run(2, 1), run(4, 0), run(3, 2)];
        let s = sum_phases(&runs);
        assert_eq!((s.sequence.as_str(), s.phases), ("seq", 3));
        assert_eq!(s.kept_range["model"], (2, 4));
        assert_eq!(s.kept_range["oracle"], (5, 5));
        let model = s.sums.iter().find(|p| p.policy == "model").unwrap();
        assert_eq!((model.kept, model.late_keeps), (9, Some(3)));
        assert_eq!(model.oracle_kept, Some(15));
        assert!(s.sweep_sums.is_none(), "no run has a sweep");
        runs[0].sweep = Some(vec![point(1)]);
        runs[1].sweep = Some(vec![point(2)]);
        assert!(sum_phases(&runs).sweep_sums.is_none(), "one run lacks it");
        runs[2].sweep = Some(vec![point(4)]);
        let swept = sum_phases(&runs).sweep_sums.unwrap();
        assert_eq!((swept[0].kept, swept[0].late_keeps), (12, 7));
    }
}
