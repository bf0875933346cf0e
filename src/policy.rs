//! The gating policy: which frames to keep, given the utility the scorer predicted.
//!
//! This is the one implementation of the gate. The element drives it with the student's utility,
//! `leangate eval` drives it with the teacher's (the `oracle` policy), and the tests drive it by hand.
//!
//! Rules, in order of precedence, for each frame:
//! 0. the frame carries no usable picture ([`Score::Junk`]: dark, saturated, noise; see
//!    [`crate::quality`]) → drop, `junk`, whatever else holds: it never becomes the reference. A
//!    pending forced keyframe, the warm-up and `max-gap` wait for the next usable frame (junk
//!    frames count towards `max-gap`, so after a long run of them the next usable frame is kept);
//! 1. no reference yet (start, flush, stream-start, caps change, `leangate-reset`) → keep, `first`;
//! 2. a force-keyframe request is pending → keep, `forced`;
//! 3. fewer than `warmup` frames seen since the stream (re)started → keep, `warmup`;
//! 4. the scorer failed (error, NaN) → keep, `error` (fail open: never lose a frame to a fault);
//! 5. `utility >= threshold` → keep, `score`;
//! 6. `max_gap > 0` and already `max_gap` consecutive drops → keep, `max-gap`;
//! 7. otherwise drop (reason `score`).
//!
//! Sharper keyframes (each frame's sharpness given to [`Gate::decide_with`]; without it, the
//! oracle or a model failure, nothing below applies):
//! - Sharpest of the recent frames ([`GateConfig::sharpness_lookback`] > 0): a keep due on score
//!   (rule 5) on a frame blurrier than [`LOOKBACK_RATIO`] of the sharpest usable frame among the
//!   `sharpness_lookback` frames before it (dropped since the last keep) goes to that sharper
//!   frame instead: [`Decision::kept_back`] says how many frames back it is, the current frame is
//!   dropped (reason `score`), and the earlier frame is kept with reason `sharper` and becomes the
//!   reference. The element holds that many frames to make this possible (its latency grows by as
//!   many frame durations). Only frames whose utility came within [`LOOKBACK_NEAR`] of the
//!   threshold are candidates: a keep goes back to a frame that was nearly due itself, not to
//!   one that saw little new (on fast motion, where the utility leaps from frame to frame, there
//!   is then nothing to go back to, and the keep is made where it fell due).
//! - With a look-back, [`GateConfig::sharpness_margin`] > 0 and no
//!   [`GateConfig::sharpness_wait`] (the element's default): a keep due on score on a blurred
//!   frame (below [`SHARPER_RATIO`] of the sharpest of the [`SHARPNESS_HISTORY`] frames before
//!   it) is not made while the utility is below `threshold + sharpness_margin`: the frame is
//!   dropped with reason `deferred` (and held as a candidate), and the keep falls to the next
//!   frame that is not so blurred or whose utility passes the margin, and from there, through
//!   the look-back, to the sharpest nearly-due frame held. Never past `max_gap` drops.
//! - With [`GateConfig::sharpness_wait`] > 0 as well, the keep settles that many frames later:
//!   the due frame and the next `sharpness_wait - 1` are dropped with reason `deferred` (whatever
//!   their utility: the keep was due) and held as candidates, and the frame after them is kept
//!   unless it is blurrier than [`LOOKBACK_RATIO`] of the sharpest candidate still held, which is
//!   kept instead (before or after the due frame). So the keep goes to the sharpest frame of a
//!   window around the due frame. A frame whose utility has reached [`settle_cap`] (halfway to
//!   a late keep) settles the keep at once, the same way.
//! - [`GateConfig::sharpness_wait`] alone (no look-back, no buffering): a keep due on a frame
//!   blurrier than [`SHARPER_RATIO`] of the sharpest of the [`SHARPNESS_HISTORY`] frames before
//!   it waits, the frame dropped with reason `deferred`, and goes to the first following frame
//!   that is not that blurry, or to the last one the wait allows.
//!
//! Keeps for any other reason end a wait.
//!
//! Every kept frame becomes the new reference.

use std::fmt;

/// Why a frame was kept (or, for `Score`, also why it was dropped).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Reason {
    First,
    Warmup,
    Score,
    MaxGap,
    Forced,
    Error,
    /// Dropped: no usable picture ([`Score::Junk`]).
    Junk,
    /// Dropped: a keep is due but waits for a sharper frame ([`GateConfig::sharpness_wait`]).
    Deferred,
    /// Kept in place of a later, blurrier frame on which a keep was due
    /// ([`GateConfig::sharpness_lookback`]).
    Sharper,
}

impl Reason {
    pub const ALL: [Reason; 9] = [
        Reason::First,
        Reason::Warmup,
        Reason::Score,
        Reason::MaxGap,
        Reason::Forced,
        Reason::Error,
        Reason::Junk,
        Reason::Deferred,
        Reason::Sharper,
    ];

    /// The string written into `LeanGateMeta`'s `reason` field.
    pub fn as_str(self) -> &'static str {
        match self {
            Reason::First => "first",
            Reason::Warmup => "warmup",
            Reason::Score => "score",
            Reason::MaxGap => "max-gap",
            Reason::Forced => "forced",
            Reason::Error => "error",
            Reason::Junk => "junk",
            Reason::Deferred => "deferred",
            Reason::Sharper => "sharper",
        }
    }

    pub fn parse(s: &str) -> Option<Reason> {
        Reason::ALL.into_iter().find(|r| r.as_str() == s)
    }
}

impl fmt::Display for Reason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// What the scorer said about the current frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Score {
    /// There is no reference to score against (the gate asked for none: see [`Gate::has_reference`]).
    NoReference,
    /// The predicted utility tau (high = novel).
    Utility(f64),
    /// Inference failed or returned a non-finite value.
    Failed,
    /// The frame carries no usable picture (black, saturated, noise): never kept.
    Junk,
}

/// Gate parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GateConfig {
    /// tau_keep: a frame whose utility is at least this is kept.
    pub threshold: f64,
    /// The first `warmup` frames after a (re)start are always kept.
    pub warmup: u64,
    /// Force a keep after this many consecutive drops; 0 disables.
    pub max_gap: u64,
    /// Most frames a keep due on a blurred frame waits for a sharper one (with a look-back: how
    /// many frames later it settles on the sharpest held); 0 = never waits.
    pub sharpness_wait: u64,
    /// How many frames back a keep due on a blurred frame may go for a sharper one; 0 = none.
    pub sharpness_lookback: u64,
    /// With a look-back and no `sharpness_wait`: how far above the threshold a blurred frame's
    /// utility must be for a keep to be made on it at once; below, it waits for a sharper frame
    /// (0 = never waits).
    pub sharpness_margin: f64,
}

/// A frame is blurred, for [`GateConfig::sharpness_wait`], when its sharpness is below this
/// fraction of the sharpest of the [`SHARPNESS_HISTORY`] frames before it.
pub const SHARPER_RATIO: f64 = 0.8;
/// How many preceding frames a frame's sharpness is compared with.
pub const SHARPNESS_HISTORY: usize = 3;
/// A keep due on a frame goes back to an earlier frame ([`GateConfig::sharpness_lookback`])
/// when the due frame's sharpness is below this fraction of that frame's.
pub const LOOKBACK_RATIO: f64 = 0.9;
/// MASt3R-SLAM's keyframe threshold on S: a keep whose S with the previous keyframe is below it
/// came late (its utility tau = 1 − S above 0.667).
pub const KEYFRAME_S: f64 = 0.333;

/// A keep settling later ([`GateConfig::sharpness_wait`] with a look-back) stops waiting on a
/// frame whose utility has reached this: halfway from `threshold` to a late keep's utility
/// (1 − [`KEYFRAME_S`]), so that on fast motion the wait does not run into late keeps.
pub fn settle_cap(threshold: f64) -> f64 {
    threshold + (1.0 - KEYFRAME_S - threshold) / 2.0
}

/// The most frames [`GateConfig::sharpness_lookback`] may hold.
pub const MAX_LOOKBACK: u64 = 30;
/// A frame dropped on score is a look-back candidate only when its utility came this close to
/// the threshold (at least `threshold - LOOKBACK_NEAR`).
pub const LOOKBACK_NEAR: f64 = 0.1;

impl Default for GateConfig {
    fn default() -> Self {
        GateConfig {
            threshold: 0.5,
            warmup: 0,
            max_gap: 0,
            sharpness_wait: 0,
            sharpness_lookback: 0,
            sharpness_margin: 0.0,
        }
    }
}

/// The decision for one frame, with the bookkeeping the metadata carries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Decision {
    pub keep: bool,
    pub reason: Reason,
    /// Number of frames kept so far, this one included.
    pub keyframe_index: u64,
    /// Frames since the reference this frame was compared with (0 for a kept frame).
    pub frames_since_keyframe: u64,
    /// With [`GateConfig::sharpness_lookback`]: the keep due on this frame went to the frame
    /// this many frames before it (kept, reason [`Reason::Sharper`], the new reference); 0: none.
    /// This frame itself is dropped.
    pub kept_back: u64,
    /// With [`GateConfig::sharpness_lookback`]: this dropped frame is one a later keep may go
    /// back to (the caller holds its picture until the look-back passes it or a keep is made).
    pub candidate: bool,
}

/// The gate's state machine.
#[derive(Debug, Clone)]
pub struct Gate {
    cfg: GateConfig,
    has_reference: bool,
    frames_since_restart: u64,
    since_keyframe: u64,
    force_next: bool,
    kept: u64,
    /// Sharpness of the last usable frames, newest last.
    sharpness: std::collections::VecDeque<f64>,
    /// Frames a due keep has waited for a sharper frame (0: none waiting).
    waited: u64,
    /// A keep fell due on a blurred frame within [`GateConfig::sharpness_margin`] and has not
    /// been made yet (the stream's end settles it: [`Gate::settle_pending`]).
    margin_due: bool,
    /// Frames decided so far (junk included): the position of the next frame.
    position: u64,
    /// (position, sharpness) of the recent frames dropped on score since the last keep, the
    /// candidates of [`GateConfig::sharpness_lookback`], oldest first.
    candidates: std::collections::VecDeque<(u64, f64)>,
    /// The look-back in force at the last decision: the frames before the next one that are
    /// still held (the element let older ones go then), so the farthest a keep may go back.
    held: u64,
}

impl Gate {
    pub fn new(cfg: GateConfig) -> Gate {
        Gate {
            cfg,
            has_reference: false,
            frames_since_restart: 0,
            since_keyframe: 0,
            force_next: false,
            kept: 0,
            sharpness: std::collections::VecDeque::with_capacity(SHARPNESS_HISTORY + 1),
            waited: 0,
            margin_due: false,
            position: 0,
            candidates: std::collections::VecDeque::new(),
            held: 0,
        }
    }

    pub fn config(&self) -> &GateConfig {
        &self.cfg
    }

    pub fn set_config(&mut self, cfg: GateConfig) {
        self.cfg = cfg;
    }

    /// Whether the next frame can be scored against a reference.
    pub fn has_reference(&self) -> bool {
        self.has_reference
    }

    /// Number of frames kept since the gate was created.
    pub fn kept(&self) -> u64 {
        self.kept
    }

    /// Whether the next frame's fate is already decided whatever its score (then scoring it only
    /// serves the metadata).
    pub fn next_is_forced(&self) -> bool {
        !self.has_reference
            || self.force_next
            || self.frames_since_restart < self.cfg.warmup
            || self.gap_reached()
    }

    /// Whether `max_gap` drops in a row were made since the last keep: the next frame is kept
    /// (`max-gap`), or, when a keep is due on its score, kept without waiting for a sharper one.
    fn gap_reached(&self) -> bool {
        self.cfg.max_gap > 0 && self.since_keyframe >= self.cfg.max_gap
    }

    /// Forget the reference: the next frame is kept as `first`. Warm-up is not restarted.
    pub fn drop_reference(&mut self) {
        self.has_reference = false;
        self.since_keyframe = 0;
        self.sharpness.clear();
        self.waited = 0;
        self.margin_due = false;
        self.candidates.clear();
    }

    /// A new stream or a flush: forget the reference and restart the warm-up count.
    pub fn restart(&mut self) {
        self.drop_reference();
        self.frames_since_restart = 0;
        self.force_next = false;
    }

    /// Frames decided so far (junk included): the position the next frame will have.
    pub fn position(&self) -> u64 {
        self.position
    }

    /// The recent frames can no longer be kept instead of a later one (the element let them go).
    pub fn forget_candidates(&mut self) {
        self.candidates.clear();
    }

    /// Keep the next frame whatever its score (`leangate-force-keyframe`).
    pub fn force_keyframe(&mut self) {
        self.force_next = true;
    }

    /// Decide the fate of the next frame.
    pub fn decide(&mut self, score: Score) -> Decision {
        self.decide_with(score, None)
    }

    /// Decide the fate of the next frame, given its sharpness
    /// ([`crate::quality::sharpness`]) for [`GateConfig::sharpness_wait`].
    pub fn decide_with(&mut self, score: Score, sharpness: Option<f64>) -> Decision {
        let position = self.position;
        self.position += 1;
        let lookback = self.cfg.sharpness_lookback.min(MAX_LOOKBACK);
        // A look-back raised since the last frame reaches no further back than what is held.
        let reach = lookback.min(self.held);
        self.held = lookback;
        while self
            .candidates
            .front()
            .is_some_and(|&(p, _)| p + reach < position)
        {
            self.candidates.pop_front();
        }
        if score == Score::Junk {
            // Not a frame of the stream's pictures: no reference, warm-up or keep changes.
            if self.has_reference {
                self.since_keyframe += 1;
            }
            return Decision {
                keep: false,
                reason: Reason::Junk,
                keyframe_index: self.kept,
                frames_since_keyframe: self.since_keyframe,
                kept_back: 0,
                candidate: false,
            };
        }
        let mut reason = if score == Score::Failed && !self.has_reference {
            // An unreadable frame with no reference (the stream's first, or one after another
            // unreadable frame) is kept as what it is: it cannot become the reference.
            Some(Reason::Error)
        } else if !self.has_reference || score == Score::NoReference {
            Some(Reason::First)
        } else if self.force_next {
            Some(Reason::Forced)
        } else if self.frames_since_restart < self.cfg.warmup {
            Some(Reason::Warmup)
        } else {
            match score {
                Score::Failed => Some(Reason::Error),
                Score::Utility(u) if !u.is_finite() => Some(Reason::Error),
                Score::Utility(u) if u >= self.cfg.threshold => Some(Reason::Score),
                _ if self.gap_reached() => Some(Reason::MaxGap),
                _ => None,
            }
        };
        // With a look-back, a keep due on a blurred frame within the margin waits for a sharper
        // frame (or a clearly due one); this frame stays a candidate to go back to.
        let mut margin_wait = false;
        if let (Some(Reason::Score), Score::Utility(u)) = (reason, score) {
            margin_wait = lookback > 0
                && self.cfg.sharpness_wait == 0
                && u < self.cfg.threshold + self.cfg.sharpness_margin
                && !self.gap_reached()
                && self.blurred(sharpness);
            if margin_wait {
                reason = None;
                self.margin_due = true;
            }
        }
        // A keep due on score (now, or settling since an earlier frame) with a look-back: it
        // settles `sharpness_wait` frames later, on the sharpest frame held. Never past
        // `max_gap` drops: a keep due then is made now (or goes back), not deferred.
        let due = reason == Some(Reason::Score) || (reason.is_none() && self.waited > 0);
        let gap_due = self.gap_reached();
        if due && lookback > 0 {
            if let (Some(s), Some((p, b))) = (sharpness, self.sharpest_candidate()) {
                let cap = settle_cap(self.cfg.threshold);
                let near_late = matches!(score, Score::Utility(u) if u >= cap);
                if self.waited < self.cfg.sharpness_wait && !near_late && !gap_due {
                    return self.settle_later(position, s);
                }
                if s < LOOKBACK_RATIO * b {
                    return self.keep_back(position, p, s);
                }
            }
            reason = Some(Reason::Score);
        }
        // Without a look-back, a keep due on a blurred frame waits for a sharper one.
        let mut deferred = false;
        if due && lookback == 0 && self.cfg.sharpness_wait > 0 {
            if self.blurred(sharpness) && self.waited < self.cfg.sharpness_wait && !gap_due {
                reason = None;
                deferred = true;
                self.waited += 1;
            } else {
                reason = Some(Reason::Score);
            }
        }
        // The frames a keep waits through are not the baseline they are compared with: a run of
        // blurred frames must not become the measure of what is sharp.
        if !deferred {
            self.remember_sharpness(sharpness);
        }
        self.frames_since_restart = self.frames_since_restart.saturating_add(1);
        match reason {
            Some(reason) => {
                self.has_reference = true;
                self.candidates.clear();
                self.waited = 0;
                self.margin_due = false;
                self.force_next = false;
                self.since_keyframe = 0;
                self.kept += 1;
                Decision {
                    keep: true,
                    reason,
                    keyframe_index: self.kept,
                    frames_since_keyframe: 0,
                    kept_back: 0,
                    candidate: false,
                }
            }
            None => {
                self.since_keyframe += 1;
                let near = matches!(score, Score::Utility(u)
                    if u >= self.cfg.threshold - LOOKBACK_NEAR);
                let candidate = sharpness.is_some() && !deferred && lookback > 0 && near;
                if let (Some(s), true) = (sharpness, candidate) {
                    self.candidates.push_back((position, s));
                }
                Decision {
                    keep: false,
                    reason: if deferred || margin_wait {
                        Reason::Deferred
                    } else {
                        Reason::Score
                    },
                    keyframe_index: self.kept,
                    frames_since_keyframe: self.since_keyframe,
                    kept_back: 0,
                    candidate,
                }
            }
        }
    }

    /// The stream ends (EOS) while a keep due on score waits to settle
    /// ([`GateConfig::sharpness_wait`] with a look-back, or a blurred frame within
    /// [`GateConfig::sharpness_margin`]): it settles now, on the sharpest frame held (the due
    /// one or a later one). Returns how many frames before the last decided frame
    /// that one is (0: the last) and its keyframe index; `None` when no keep waits.
    pub fn settle_pending(&mut self) -> Option<(u64, u64)> {
        if self.waited == 0 && !self.margin_due {
            return None;
        }
        let (p, _) = self.sharpest_candidate()?;
        let last = self.position.checked_sub(1)?;
        self.candidates.clear();
        self.waited = 0;
        self.margin_due = false;
        self.force_next = false;
        self.since_keyframe = last - p;
        self.kept += 1;
        Some((last - p, self.kept))
    }

    /// The sharpest candidate of the look-back (the earliest of equals).
    fn sharpest_candidate(&self) -> Option<(u64, f64)> {
        self.candidates
            .iter()
            .copied()
            .fold(None, |m: Option<(u64, f64)>, c| match m {
                Some(m) if m.1 >= c.1 => Some(m),
                _ => Some(c),
            })
    }

    /// The keep due settles on a later frame: this one (sharpness `s`) is dropped as `deferred`
    /// and held as a candidate.
    fn settle_later(&mut self, position: u64, s: f64) -> Decision {
        self.waited += 1;
        self.remember_sharpness(Some(s));
        self.frames_since_restart = self.frames_since_restart.saturating_add(1);
        self.since_keyframe += 1;
        self.candidates.push_back((position, s));
        Decision {
            keep: false,
            reason: Reason::Deferred,
            keyframe_index: self.kept,
            frames_since_keyframe: self.since_keyframe,
            kept_back: 0,
            candidate: true,
        }
    }

    /// The keep due on this frame (sharpness `s`, dropped) goes to the candidate at `p`.
    fn keep_back(&mut self, position: u64, p: u64, s: f64) -> Decision {
        self.remember_sharpness(Some(s));
        self.frames_since_restart = self.frames_since_restart.saturating_add(1);
        self.candidates.clear();
        self.waited = 0;
        self.margin_due = false;
        self.force_next = false;
        // This frame was compared with the reference before the keep: its count is from there;
        // the next frames count from the frame kept instead.
        let compared = self.since_keyframe + 1;
        self.since_keyframe = position - p;
        self.kept += 1;
        Decision {
            keep: false,
            reason: Reason::Score,
            keyframe_index: self.kept,
            frames_since_keyframe: compared,
            kept_back: position - p,
            candidate: false,
        }
    }

    /// Whether a frame of this sharpness is blurred: below [`SHARPER_RATIO`] of the sharpest of
    /// the [`SHARPNESS_HISTORY`] frames before it (unknown sharpness: not blurred).
    fn blurred(&self, sharpness: Option<f64>) -> bool {
        let best = self
            .sharpness
            .iter()
            .copied()
            .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))));
        sharpness
            .zip(best)
            .is_some_and(|(s, b)| s < SHARPER_RATIO * b)
    }

    fn remember_sharpness(&mut self, sharpness: Option<f64>) {
        if let Some(s) = sharpness {
            if self.sharpness.len() == SHARPNESS_HISTORY {
                self.sharpness.pop_front();
            }
            self.sharpness.push_back(s);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(gate: &mut Gate, utilities: &[f64]) -> Vec<(bool, Reason)> {
        utilities
            .iter()
            .map(|&u| {
                let s = if gate.has_reference() {
                    Score::Utility(u)
                } else {
                    Score::NoReference
                };
                let d = gate.decide(s);
                (d.keep, d.reason)
            })
            .collect()
    }

    #[test]
    fn first_frame_kept_then_threshold() {
        let mut g = Gate::new(GateConfig::default());
        let out = run(&mut g, &[0.0, 0.1, 0.49, 0.5, 0.2, 0.9]);
        assert_eq!(
            out,
            vec![
                (true, Reason::First),
                (false, Reason::Score),
                (false, Reason::Score),
                (true, Reason::Score),
                (false, Reason::Score),
                (true, Reason::Score)
            ]
        );
        assert_eq!(g.kept(), 3);
    }

    #[test]
    fn warmup_keeps_first_n_frames() {
        let mut g = Gate::new(GateConfig {
            warmup: 3,
            ..Default::default()
        });
        let out = run(&mut g, &[0.0, 0.0, 0.0, 0.0, 0.0]);
        let keeps: Vec<_> = out.iter().map(|o| o.1).collect();
        assert_eq!(
            keeps,
            vec![
                Reason::First,
                Reason::Warmup,
                Reason::Warmup,
                Reason::Score,
                Reason::Score
            ]
        );
        assert_eq!(out.iter().filter(|o| o.0).count(), 3);
    }

    #[test]
    fn max_gap_forces_keep_after_n_drops() {
        let mut g = Gate::new(GateConfig {
            max_gap: 2,
            ..Default::default()
        });
        let out = run(&mut g, &[0.0; 7]);
        let kept: Vec<_> = out.iter().map(|o| o.0).collect();
        assert_eq!(kept, vec![true, false, false, true, false, false, true]);
        assert_eq!(out[3].1, Reason::MaxGap);
    }

    #[test]
    fn a_long_wait_compares_with_the_frames_before_the_due_keep_not_the_blurred_run() {
        // sharpness-wait 30: four blurred frames reach the threshold after three sharp ones.
        // The keep waits through all four (they were the baseline of "sharp" once three of them
        // had entered it) and goes to the first sharp frame.
        let mut g = Gate::new(GateConfig {
            sharpness_wait: 30,
            ..Default::default()
        });
        assert!(g.decide_with(Score::NoReference, Some(100.0)).keep);
        for _ in 0..3 {
            assert!(!g.decide_with(Score::Utility(0.1), Some(100.0)).keep);
        }
        for k in 0..4 {
            let d = g.decide_with(Score::Utility(0.9), Some(10.0));
            assert_eq!(
                (d.keep, d.reason),
                (false, Reason::Deferred),
                "blurred frame {k}"
            );
        }
        let d = g.decide_with(Score::Utility(0.9), Some(100.0));
        assert_eq!((d.keep, d.reason), (true, Reason::Score));
    }

    #[test]
    fn a_keep_waiting_for_a_sharper_frame_never_outlasts_max_gap() {
        // max-gap 3 with a long wait, with and without a look-back: a keep due on a blurred
        // frame is deferred only while fewer than max-gap frames were dropped; at the gap it is
        // made (or goes back to a sharper held frame), so no run of drops exceeds 3.
        for lookback in [0, 5] {
            let mut g = Gate::new(GateConfig {
                max_gap: 3,
                sharpness_wait: 5,
                sharpness_lookback: lookback,
                ..Default::default()
            });
            let (mut run, mut longest) = (0u64, 0u64);
            for k in 0..60u64 {
                // Sharp frames that never reach the threshold, then blurred ones that do.
                let (u, sharp) = if k % 8 < 2 { (0.1, 100.0) } else { (0.9, 10.0) };
                let score = if k == 0 {
                    Score::NoReference
                } else {
                    Score::Utility(u)
                };
                let d = g.decide_with(score, Some(sharp));
                if d.kept_back > 0 {
                    // The keep went back: the drops since that frame are the run now.
                    run = d.kept_back;
                } else if d.keep {
                    run = 0;
                } else {
                    run += 1;
                }
                longest = longest.max(run);
            }
            assert!(
                longest <= 3,
                "look-back {lookback}: {longest} drops in a row"
            );
        }
    }

    #[test]
    fn junk_is_never_kept_and_the_keeps_it_blocks_wait_for_a_usable_frame() {
        let mut g = Gate::new(GateConfig {
            max_gap: 3,
            warmup: 2,
            ..Default::default()
        });
        // Junk before any reference: dropped, and the first usable frame is `first`.
        let d = g.decide(Score::Junk);
        assert_eq!(
            (d.keep, d.reason, d.keyframe_index),
            (false, Reason::Junk, 0)
        );
        assert!(!g.has_reference());
        assert_eq!(g.decide(Score::NoReference).reason, Reason::First);
        // Warm-up counts usable frames only.
        assert!(!g.decide(Score::Junk).keep);
        assert_eq!(g.decide(Score::Utility(0.0)).reason, Reason::Warmup);
        assert_eq!(g.decide(Score::Utility(0.0)).reason, Reason::Score);
        // A forced keyframe waits for the next usable frame; junk counts towards max-gap.
        g.force_keyframe();
        assert!(!g.decide(Score::Junk).keep);
        assert_eq!(g.decide(Score::Utility(0.0)).reason, Reason::Forced);
        for _ in 0..5 {
            assert_eq!(g.decide(Score::Junk).reason, Reason::Junk);
        }
        let d = g.decide(Score::Utility(0.0));
        assert_eq!((d.keep, d.reason), (true, Reason::MaxGap));
        // Whatever the utility would have been: a junk frame is not kept.
        assert!(!g.decide(Score::Junk).keep);
        assert_eq!(g.kept(), 4);
    }

    #[test]
    fn a_keep_due_on_a_blurred_frame_waits_for_a_sharper_one_within_its_limit() {
        let mut g = Gate::new(GateConfig {
            sharpness_wait: 2,
            ..Default::default()
        });
        let mut step = |u: f64, s: f64| {
            let d = g.decide_with(Score::Utility(u), Some(s));
            (d.keep, d.reason)
        };
        assert_eq!(step(0.0, 100.0), (true, Reason::First));
        // Sharp history 100; a due keep at sharpness 50 waits, and goes to the next sharp frame,
        // even though that frame's utility is below the threshold.
        assert_eq!(step(0.1, 100.0), (false, Reason::Score));
        assert_eq!(step(0.6, 50.0), (false, Reason::Deferred));
        assert_eq!(step(0.4, 95.0), (true, Reason::Score));
        // Two blurred frames in a row: the wait ends at its limit, on a blurred frame.
        step(0.1, 100.0);
        assert_eq!(step(0.7, 40.0), (false, Reason::Deferred));
        assert_eq!(step(0.7, 30.0), (false, Reason::Deferred));
        assert_eq!(step(0.7, 20.0), (true, Reason::Score));
        // A sharp enough frame keeps at once; off (0), nothing waits.
        step(0.1, 100.0);
        assert_eq!(step(0.6, 85.0), (true, Reason::Score));
        let mut off = Gate::new(GateConfig::default());
        off.decide(Score::NoReference);
        off.decide_with(Score::Utility(0.1), Some(100.0));
        assert!(off.decide_with(Score::Utility(0.6), Some(10.0)).keep);
        // Without sharpness (the oracle) nothing waits either.
        let mut g = Gate::new(GateConfig {
            sharpness_wait: 2,
            ..Default::default()
        });
        g.decide(Score::NoReference);
        assert!(g.decide(Score::Utility(0.6)).keep);
    }

    #[test]
    fn a_keep_due_on_a_blurred_frame_goes_back_to_a_sharper_recent_one() {
        let mut g = Gate::new(GateConfig {
            sharpness_lookback: 2,
            ..Default::default()
        });
        fn step(g: &mut Gate, u: f64, s: f64) -> (bool, Reason, u64, u64, u64) {
            let d = g.decide_with(Score::Utility(u), Some(s));
            (
                d.keep,
                d.reason,
                d.kept_back,
                d.keyframe_index,
                d.frames_since_keyframe,
            )
        }
        assert!(step(&mut g, 0.0, 100.0).0);
        // Candidates (nearly due: within 0.1 of the threshold) 80 (3 back: beyond the
        // look-back), 90, 70; the due frame (40) goes back to the 90 one, two frames before it,
        // which becomes keyframe 2.
        assert_eq!(step(&mut g, 0.41, 80.0), (false, Reason::Score, 0, 1, 1));
        assert_eq!(step(&mut g, 0.43, 90.0), (false, Reason::Score, 0, 1, 2));
        assert_eq!(step(&mut g, 0.45, 70.0), (false, Reason::Score, 0, 1, 3));
        // (The due frame itself was compared with the first frame, 4 frames before it.)
        assert_eq!(step(&mut g, 0.6, 40.0), (false, Reason::Score, 2, 2, 4));
        // The frames before that keep are no candidates any more: a due blurred frame after it
        // keeps at once when nothing since is sharper...
        assert!(step(&mut g, 0.9, 10.0).0);
        // ...and a due frame at least 0.9 as sharp as the best candidate keeps itself.
        step(&mut g, 0.45, 100.0);
        assert_eq!(step(&mut g, 0.6, 91.0), (true, Reason::Score, 0, 4, 0));
        // Junk is never a candidate; off (0) nothing goes back; without sharpness neither.
        step(&mut g, 0.45, 100.0);
        assert!(!g.decide(Score::Junk).keep);
        // (the junk frame in between counts: the element holds every frame)
        assert_eq!(step(&mut g, 0.6, 20.0).2, 2);
        let mut off = Gate::new(GateConfig::default());
        off.decide(Score::NoReference);
        off.decide_with(Score::Utility(0.45), Some(100.0));
        assert!(off.decide_with(Score::Utility(0.6), Some(10.0)).keep);
        let mut g = Gate::new(GateConfig {
            sharpness_lookback: 2,
            ..Default::default()
        });
        g.decide(Score::NoReference);
        g.decide_with(Score::Utility(0.45), Some(100.0));
        assert_eq!(g.decide(Score::Utility(0.6)).kept_back, 0);
        // forget_candidates: the held frames are gone.
        g.decide_with(Score::Utility(0.45), Some(100.0));
        g.forget_candidates();
        assert!(g.decide_with(Score::Utility(0.6), Some(10.0)).keep);
    }

    #[test]
    fn with_a_wait_and_a_lookback_a_due_keep_settles_on_the_sharpest_held_frame() {
        let cfg = GateConfig {
            sharpness_wait: 2,
            sharpness_lookback: 4,
            ..Default::default()
        };
        fn step(g: &mut Gate, u: f64, s: f64) -> (bool, Reason, u64, u64) {
            let d = g.decide_with(Score::Utility(u), Some(s));
            (d.keep, d.reason, d.kept_back, d.frames_since_keyframe)
        }
        let mut g = Gate::new(cfg);
        assert!(step(&mut g, 0.0, 100.0).0);
        for s in [50.0, 60.0, 55.0, 40.0] {
            assert!(!step(&mut g, 0.42, s).0);
        }
        // Due on frame 5 (blurred): it and the next frame wait; on frame 7 the keep settles on
        // the sharpest frame held (frame 6, one back), whatever the utility did meanwhile.
        assert_eq!(step(&mut g, 0.55, 30.0), (false, Reason::Deferred, 0, 5));
        assert_eq!(step(&mut g, 0.45, 90.0), (false, Reason::Deferred, 0, 6));
        // (Frame 7 itself was compared with frame 0.)
        assert_eq!(step(&mut g, 0.7, 45.0), (false, Reason::Score, 1, 7));
        // Frames before frame 3 are out of reach (4 frames back from frame 7): a sharp frame 1
        // would not have been chosen. A settling frame at least 0.9 as sharp as the sharpest
        // held keeps itself, even when the due frame was sharp: the wait always runs its length.
        for s in [100.0, 20.0] {
            assert!(!step(&mut g, 0.42, s).0);
        }
        assert_eq!(step(&mut g, 0.55, 95.0).1, Reason::Deferred);
        assert_eq!(step(&mut g, 0.55, 30.0).1, Reason::Deferred);
        assert_eq!(step(&mut g, 0.6, 92.0), (true, Reason::Score, 0, 0));
        // A frame halfway to a late keep (utility 0.59 against the cap 0.583 at threshold 0.5)
        // settles at once: here on the sharper frame before it.
        step(&mut g, 0.42, 100.0);
        assert_eq!(step(&mut g, 0.55, 30.0).1, Reason::Deferred);
        assert_eq!(step(&mut g, 0.59, 40.0), (false, Reason::Score, 2, 3));
        // A keep for another reason (forced) ends the wait at once.
        step(&mut g, 0.42, 100.0);
        assert_eq!(step(&mut g, 0.55, 30.0).1, Reason::Deferred);
        g.force_keyframe();
        assert_eq!(step(&mut g, 0.6, 30.0), (true, Reason::Forced, 0, 0));
        // Nothing held to compare with (the due frame follows a keep): kept at once.
        assert_eq!(step(&mut g, 0.6, 30.0), (true, Reason::Score, 0, 0));
        // Without a look-back the wait keeps its own rule: the first frame not blurred.
        let mut w = Gate::new(GateConfig {
            sharpness_lookback: 0,
            ..cfg
        });
        w.decide(Score::NoReference);
        w.decide_with(Score::Utility(0.2), Some(100.0));
        assert_eq!(
            w.decide_with(Score::Utility(0.6), Some(30.0)).reason,
            Reason::Deferred
        );
        assert!(w.decide_with(Score::Utility(0.6), Some(95.0)).keep);
    }

    #[test]
    fn a_keep_goes_back_only_to_a_nearly_due_frame_and_waits_within_the_margin_when_blurred() {
        fn step(g: &mut Gate, u: f64, s: f64) -> (bool, Reason, u64) {
            let d = g.decide_with(Score::Utility(u), Some(s));
            (d.keep, d.reason, d.kept_back)
        }
        let cfg = GateConfig {
            sharpness_lookback: 3,
            ..Default::default()
        };
        // A sharp frame that saw little new (0.35: more than LOOKBACK_NEAR below the threshold)
        // is no candidate: the blurred due frame keeps itself. One within 0.1 is.
        let mut g = Gate::new(cfg);
        g.decide(Score::NoReference);
        assert_eq!(step(&mut g, 0.35, 100.0), (false, Reason::Score, 0));
        assert_eq!(step(&mut g, 0.6, 40.0), (true, Reason::Score, 0));
        assert_eq!(step(&mut g, 0.41, 100.0), (false, Reason::Score, 0));
        assert_eq!(step(&mut g, 0.6, 40.0), (false, Reason::Score, 1));

        // The margin: a blurred frame (below 0.8 of the sharpest of the 3 before it) due within
        // threshold + 0.05 waits (reason deferred, held as a candidate)...
        let mut g = Gate::new(GateConfig {
            sharpness_margin: 0.05,
            ..cfg
        });
        g.decide(Score::NoReference);
        step(&mut g, 0.2, 100.0);
        assert_eq!(step(&mut g, 0.52, 70.0), (false, Reason::Deferred, 0));
        // ...the next frame sharp enough takes the keep (it is at least 0.9 as sharp as the
        // deferred one, so it keeps itself)...
        assert_eq!(step(&mut g, 0.53, 95.0), (true, Reason::Score, 0));
        // ...and one past the margin keeps at once, going back to the sharper deferred frame.
        step(&mut g, 0.2, 100.0);
        assert_eq!(step(&mut g, 0.52, 70.0), (false, Reason::Deferred, 0));
        assert_eq!(step(&mut g, 0.56, 30.0), (false, Reason::Score, 1));
        // A frame that is not blurred keeps at once within the margin.
        step(&mut g, 0.2, 100.0);
        assert_eq!(step(&mut g, 0.51, 85.0), (true, Reason::Score, 0));
        // The stream ends while a blurred due frame waits: the keep is made on the sharpest
        // frame held (here the waiting one, the last decided), not lost.
        step(&mut g, 0.2, 100.0);
        assert_eq!(step(&mut g, 0.52, 70.0), (false, Reason::Deferred, 0));
        assert_eq!(g.settle_pending(), Some((0, 5)));
        assert_eq!(g.settle_pending(), None, "settled once");
        // Never past max-gap: the gap's due keep is made on the blurred frame.
        let mut g = Gate::new(GateConfig {
            sharpness_margin: 0.05,
            max_gap: 2,
            ..cfg
        });
        g.decide(Score::NoReference);
        step(&mut g, 0.2, 100.0);
        step(&mut g, 0.2, 100.0);
        assert!(step(&mut g, 0.52, 10.0).0);
        // With sharpness-wait (the settle mode, which has its own rule) or without a look-back
        // the margin does nothing.
        let mut g = Gate::new(GateConfig {
            sharpness_margin: 0.05,
            sharpness_wait: 2,
            ..cfg
        });
        g.decide(Score::NoReference);
        step(&mut g, 0.2, 100.0);
        assert_eq!(step(&mut g, 0.52, 10.0), (true, Reason::Score, 0));
        let mut g = Gate::new(GateConfig {
            sharpness_margin: 0.05,
            sharpness_lookback: 0,
            ..Default::default()
        });
        g.decide(Score::NoReference);
        step(&mut g, 0.2, 100.0);
        assert_eq!(step(&mut g, 0.52, 10.0), (true, Reason::Score, 0));
    }

    #[test]
    fn a_raised_lookback_goes_back_no_further_than_the_frames_still_held() {
        let mut g = Gate::new(GateConfig {
            sharpness_lookback: 2,
            ..Default::default()
        });
        g.decide(Score::NoReference);
        // A sharp candidate, then two blurred ones: with a look-back of 2, the element lets the
        // sharp one go when the second blurred one comes.
        g.decide_with(Score::Utility(0.45), Some(100.0));
        g.decide_with(Score::Utility(0.45), Some(10.0));
        g.decide_with(Score::Utility(0.45), Some(10.0));
        // Raised to 30 before the due frame: the sharp frame (3 back) has left; the keep goes
        // back to the sharpest of the two frames still held (it went to the one that had left).
        g.set_config(GateConfig {
            sharpness_lookback: 30,
            ..Default::default()
        });
        assert_eq!(g.decide_with(Score::Utility(0.6), Some(5.0)).kept_back, 2);
        // From then on the look-back of 30 reaches that far.
        for _ in 0..10 {
            g.decide_with(Score::Utility(0.45), Some(100.0));
        }
        g.decide_with(Score::Utility(0.45), Some(10.0));
        assert_eq!(g.decide_with(Score::Utility(0.6), Some(5.0)).kept_back, 11);
    }

    #[test]
    fn force_and_reset() {
        let mut g = Gate::new(GateConfig::default());
        run(&mut g, &[0.0, 0.0]);
        g.force_keyframe();
        assert!(g.next_is_forced());
        let d = g.decide(Score::Utility(0.0));
        assert_eq!((d.keep, d.reason), (true, Reason::Forced));
        let d = g.decide(Score::Utility(0.0));
        assert!(!d.keep, "force applies to one frame only");
        g.drop_reference();
        assert!(!g.has_reference());
        let d = g.decide(Score::NoReference);
        assert_eq!((d.keep, d.reason), (true, Reason::First));
    }

    #[test]
    fn failure_keeps_frame_fail_open() {
        let mut g = Gate::new(GateConfig::default());
        g.decide(Score::NoReference);
        let d = g.decide(Score::Failed);
        assert_eq!((d.keep, d.reason), (true, Reason::Error));
        let d = g.decide(Score::Utility(f64::NAN));
        assert_eq!((d.keep, d.reason), (true, Reason::Error));
        // Unreadable frames in a row (the element drops the reference after each): every one is
        // `error`, and the next readable frame is `first` (a hostile probe saw `first` on the
        // second and third, which cannot be a reference).
        for _ in 0..3 {
            g.drop_reference();
            let d = g.decide(Score::Failed);
            assert_eq!((d.keep, d.reason), (true, Reason::Error));
        }
        g.drop_reference();
        let d = g.decide(Score::NoReference);
        assert_eq!((d.keep, d.reason), (true, Reason::First));
    }

    #[test]
    fn bookkeeping_counts() {
        let mut g = Gate::new(GateConfig::default());
        let d0 = g.decide(Score::NoReference);
        assert_eq!((d0.keyframe_index, d0.frames_since_keyframe), (1, 0));
        let d1 = g.decide(Score::Utility(0.1));
        let d2 = g.decide(Score::Utility(0.1));
        assert_eq!((d1.keyframe_index, d1.frames_since_keyframe), (1, 1));
        assert_eq!((d2.keyframe_index, d2.frames_since_keyframe), (1, 2));
        let d3 = g.decide(Score::Utility(0.7));
        assert_eq!((d3.keyframe_index, d3.frames_since_keyframe), (2, 0));
    }

    #[test]
    fn restart_restarts_warmup() {
        let mut g = Gate::new(GateConfig {
            warmup: 2,
            ..Default::default()
        });
        run(&mut g, &[0.0, 0.0, 0.0]);
        g.restart();
        let out = run(&mut g, &[0.0, 0.0, 0.0]);
        assert_eq!(
            out,
            vec![
                (true, Reason::First),
                (true, Reason::Warmup),
                (false, Reason::Score)
            ]
        );
    }

    #[test]
    fn reason_strings_round_trip() {
        for r in Reason::ALL {
            assert_eq!(Reason::parse(r.as_str()), Some(r));
        }
        assert_eq!(Reason::parse("nope"), None);
    }
}
