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
//! oracle or a model failure, nothing below applies). One rule: **a keep due on score goes to
//! the sharpest nearly-due frame still held, and is never owed past the frames held.**
//! - *Where a keep goes.* With a look-back ([`GateConfig::sharpness_lookback`] > 0) the caller
//!   holds that many frames, and the gate remembers which of them were dropped with a utility
//!   within [`LOOKBACK_NEAR`] of the threshold (the candidates: frames that were nearly due
//!   themselves, not ones that saw little new). A keep made on score stays on the frame in hand
//!   when that frame is nearly due and at least [`LOOKBACK_RATIO`] as sharp as the sharpest
//!   candidate held; otherwise it goes to that candidate: [`Decision::kept_back`] says how many
//!   frames back, the frame in hand is dropped, and the earlier one is kept with reason
//!   `sharper` and becomes the reference.
//! - *When a keep waits.* A keep due on score may be owed instead of made at once: the frame is
//!   dropped with reason `deferred` (and is a candidate), and each later frame either settles the
//!   keep (then it goes where the first point says) or waits too. Which frames wait:
//!   - the blur margin (a look-back, [`GateConfig::sharpness_margin`] > 0, no
//!     [`GateConfig::sharpness_wait`]; the element's default): a frame that is blurred (below
//!     [`SHARPER_RATIO`] of the sharpest of the [`SHARPNESS_HISTORY`] frames before it) while
//!     its utility is below `threshold + sharpness_margin`;
//!   - the settle (a look-back and `sharpness_wait` > 0): the first `sharpness_wait` frames from
//!     the due one (at most the look-back), unless a frame's utility reaches [`settle_cap`]
//!     (halfway to a late keep), and only when a candidate is held before the due frame (a
//!     utility that leapt past the threshold, fast motion, keeps at once);
//!   - the wait alone (`sharpness_wait` > 0, no look-back, nothing held): a blurred frame, at
//!     most `sharpness_wait` of them (blurred against the frames before the wait); the keep
//!     lands on the frame that settles it.
//! - *Never owed past what is held.* An owed keep settles, whatever the rules above say, at
//!   `max_gap` drops, on the last frame before the due frame would leave the frames held, and
//!   when the caller lets the held frames go (end of stream, a new segment or caps:
//!   [`Gate::settle_pending`]). A keep for any other reason (first, forced, warm-up, error,
//!   max-gap) is made where it falls and ends a wait.
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
    /// Sharpness of the last usable frames, newest last (without those a wait alone went
    /// through: [`Gate::defer`]).
    sharpness: std::collections::VecDeque<f64>,
    /// The position of the frame a keep fell due on that has not been made yet (it waits for a
    /// sharper frame); `None`: no keep is owed.
    owed: Option<u64>,
    /// Frames decided so far (junk included): the position of the next frame.
    position: u64,
    /// (position, sharpness) of the nearly-due frames dropped since the last keep that are still
    /// held, the candidates a keep may go to, oldest first.
    candidates: std::collections::VecDeque<(u64, f64)>,
    /// The look-back in force at the last decision: how many of the frames before the next one
    /// the caller still holds (it let older ones go then), so the farthest a keep may go back.
    held: u64,
}

/// How a keep due on score waits for a sharper frame (from [`GateConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wait {
    /// Made at once (possibly on a sharper held frame).
    Never,
    /// While the frame is blurred and within `threshold + sharpness_margin` (look-back).
    Margin,
    /// `sharpness_wait` frames from the due one (look-back).
    Settle,
    /// While the frame is blurred, at most `sharpness_wait` frames (nothing held).
    Blurred,
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
            owed: None,
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
    /// (`max-gap`), or, when a keep is due or owed, that keep is made without waiting.
    fn gap_reached(&self) -> bool {
        self.cfg.max_gap > 0 && self.since_keyframe >= self.cfg.max_gap
    }

    /// Forget the reference: the next frame is kept as `first`. Warm-up is not restarted.
    pub fn drop_reference(&mut self) {
        self.has_reference = false;
        self.since_keyframe = 0;
        self.sharpness.clear();
        self.owed = None;
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

    /// The caller let the held frames go without their owed keep ([`Gate::settle_pending`]
    /// first when they leave downstream): no keep can go to them, and none is owed any more.
    pub fn forget_candidates(&mut self) {
        self.candidates.clear();
        self.owed = None;
    }

    /// `n` keeps the gate counted never left the caller (held frames a flush discarded): the
    /// count, and so the next keyframe index, goes back by as many.
    pub fn discard_kept(&mut self, n: u64) {
        self.kept = self.kept.saturating_sub(n);
    }

    /// Keep the next frame whatever its score (`leangate-force-keyframe`).
    pub fn force_keyframe(&mut self) {
        self.force_next = true;
    }

    /// Decide the fate of the next frame.
    pub fn decide(&mut self, score: Score) -> Decision {
        self.decide_with(score, None)
    }

    /// How a keep due on score waits, from the configuration.
    fn wait_rule(&self) -> Wait {
        let lookback = self.cfg.sharpness_lookback.min(MAX_LOOKBACK) > 0;
        match (lookback, self.cfg.sharpness_wait > 0) {
            (true, true) => Wait::Settle,
            (true, false) if self.cfg.sharpness_margin > 0.0 => Wait::Margin,
            (false, true) => Wait::Blurred,
            _ => Wait::Never,
        }
    }

    /// Drop the candidates the caller no longer holds: with `reach` frames held before
    /// `position`, those before `position - reach`.
    fn prune(&mut self, position: u64, reach: u64) {
        while self
            .candidates
            .front()
            .is_some_and(|&(p, _)| p + reach < position)
        {
            self.candidates.pop_front();
        }
    }

    /// Decide the fate of the next frame, given its sharpness
    /// ([`crate::quality::sharpness`]) for the sharpness rules (module doc).
    pub fn decide_with(&mut self, score: Score, sharpness: Option<f64>) -> Decision {
        let position = self.position;
        self.position += 1;
        let lookback = self.cfg.sharpness_lookback.min(MAX_LOOKBACK);
        // A look-back raised since the last frame reaches no further back than what is held.
        let reach = lookback.min(self.held);
        self.held = lookback;
        self.prune(position, reach);
        let decision = self.decide_frame(position, reach, score, sharpness);
        // What the caller holds after this frame: the candidates follow it.
        self.prune(self.position, lookback);
        decision
    }

    fn decide_frame(
        &mut self,
        position: u64,
        reach: u64,
        score: Score,
        sharpness: Option<f64>,
    ) -> Decision {
        let lookback = self.cfg.sharpness_lookback.min(MAX_LOOKBACK) > 0;
        if score == Score::Junk {
            // Not a frame of the stream's pictures: no reference, warm-up or keep changes, but
            // an owed keep is made before its due frame leaves the frames held.
            if self.has_reference {
                self.since_keyframe += 1;
            }
            if let (Some(q), true) = (self.owed, lookback) {
                if position - q >= reach || self.gap_reached() {
                    if let Some((p, _)) = self.sharpest_candidate() {
                        return self.keep_back(position, p, Reason::Junk);
                    }
                    self.owed = None;
                }
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
        let utility = match score {
            Score::Utility(u) if u.is_finite() => Some(u),
            _ => None,
        };
        let reason = if score == Score::Failed && !self.has_reference {
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
            match utility {
                None => Some(Reason::Error),
                Some(u) if u >= self.cfg.threshold => Some(Reason::Score),
                _ => None,
            }
        };
        let nearly_due = utility.is_some_and(|u| u >= self.cfg.threshold - LOOKBACK_NEAR);
        // A keep due on score now, or owed since an earlier frame and not overtaken by a keep
        // for another reason.
        let due = reason == Some(Reason::Score) || (reason.is_none() && self.owed.is_some());
        let reason = match (reason, due, sharpness) {
            (_, true, Some(s)) => {
                let q = self.owed.unwrap_or(position);
                if self.waits(q, position, reach, utility, s) {
                    return self.defer(q, s, nearly_due && lookback);
                }
                // Settled here: on the sharpest nearly-due frame held.
                if let Some((p, b)) = self.sharpest_candidate() {
                    if !nearly_due || s < LOOKBACK_RATIO * b {
                        self.remember_sharpness(Some(s));
                        return self.keep_back(position, p, Reason::Score);
                    }
                }
                Some(Reason::Score)
            }
            // An owed keep and a frame without sharpness: to the sharpest candidate held.
            (None, true, None) => match self.sharpest_candidate() {
                Some((p, _)) => return self.keep_back(position, p, Reason::Score),
                None => Some(Reason::Score),
            },
            (None, false, _) if self.gap_reached() => Some(Reason::MaxGap),
            (r, _, _) => r,
        };
        self.remember_sharpness(sharpness);
        self.frames_since_restart = self.frames_since_restart.saturating_add(1);
        match reason {
            Some(reason) => {
                self.has_reference = true;
                self.candidates.clear();
                self.owed = None;
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
                let candidate = sharpness.is_some() && lookback && nearly_due;
                if let (Some(s), true) = (sharpness, candidate) {
                    self.candidates.push_back((position, s));
                }
                Decision {
                    keep: false,
                    reason: Reason::Score,
                    keyframe_index: self.kept,
                    frames_since_keyframe: self.since_keyframe,
                    kept_back: 0,
                    candidate,
                }
            }
        }
    }

    /// Whether the keep due since position `q` waits on this frame (at `position`, utility
    /// `u`, sharpness `s`) rather than settling here (module doc, "When a keep waits").
    fn waits(&self, q: u64, position: u64, reach: u64, u: Option<f64>, s: f64) -> bool {
        if self.gap_reached() {
            return false;
        }
        let waited = position - q;
        let below = |limit: f64| u.is_none_or(|u| u < limit);
        match self.wait_rule() {
            Wait::Never => false,
            Wait::Margin => {
                waited < reach
                    && self.blurred(Some(s))
                    && below(self.cfg.threshold + self.cfg.sharpness_margin)
            }
            // The settle waits for a utility that rose to the threshold, a nearly-due frame held
            // before the due one; one that leapt past it (fast motion) is kept at once.
            Wait::Settle => {
                waited < self.cfg.sharpness_wait.min(reach)
                    && below(settle_cap(self.cfg.threshold))
                    && (waited > 0 || !self.candidates.is_empty())
            }
            Wait::Blurred => waited < self.cfg.sharpness_wait && self.blurred(Some(s)),
        }
    }

    /// The keep due since `q` waits: this frame (sharpness `s`) is dropped as `deferred`, a
    /// candidate when `candidate`. It joins the measure of what is sharp unless nothing is held
    /// (the wait alone, which may outlast [`SHARPNESS_HISTORY`]: a run of blurred frames must not
    /// become the measure of what is sharp); with a look-back the wait ends within the frames
    /// held, and the keep goes to the sharpest of them anyway.
    fn defer(&mut self, q: u64, s: f64, candidate: bool) -> Decision {
        let position = self.position - 1;
        if self.wait_rule() != Wait::Blurred {
            self.remember_sharpness(Some(s));
        }
        self.owed = Some(q);
        self.frames_since_restart = self.frames_since_restart.saturating_add(1);
        self.since_keyframe += 1;
        if candidate {
            self.candidates.push_back((position, s));
        }
        Decision {
            keep: false,
            reason: Reason::Deferred,
            keyframe_index: self.kept,
            frames_since_keyframe: self.since_keyframe,
            kept_back: 0,
            candidate,
        }
    }

    /// The caller lets the held frames go (end of stream, a new segment or caps, the look-back
    /// switched off) while a keep is owed: it is made now, on the sharpest candidate still held.
    /// Returns how many frames before the last decided frame that one is (0: the last) and its
    /// keyframe index; `None` when no keep is owed.
    pub fn settle_pending(&mut self) -> Option<(u64, u64)> {
        self.owed?;
        // (The candidates are those still held: pruned after every decision.)
        let last = self.position.checked_sub(1)?;
        let Some((p, _)) = self.sharpest_candidate() else {
            self.owed = None;
            return None;
        };
        self.candidates.clear();
        self.owed = None;
        self.force_next = false;
        self.has_reference = true;
        self.since_keyframe = last - p;
        self.kept += 1;
        Some((last - p, self.kept))
    }

    /// The sharpest candidate still held (the earliest of equals).
    fn sharpest_candidate(&self) -> Option<(u64, f64)> {
        self.candidates
            .iter()
            .copied()
            .fold(None, |m: Option<(u64, f64)>, c| match m {
                Some(m) if m.1 >= c.1 => Some(m),
                _ => Some(c),
            })
    }

    /// The keep due on this frame (dropped with `reason`) goes to the candidate at `p`.
    fn keep_back(&mut self, position: u64, p: u64, reason: Reason) -> Decision {
        if reason != Reason::Junk {
            self.frames_since_restart = self.frames_since_restart.saturating_add(1);
        }
        self.candidates.clear();
        self.owed = None;
        self.force_next = false;
        // This frame was compared with the reference before the keep: its count is from there;
        // the next frames count from the frame kept instead.
        let compared = if reason == Reason::Junk {
            self.since_keyframe
        } else {
            self.since_keyframe + 1
        };
        self.since_keyframe = position - p;
        self.kept += 1;
        Decision {
            keep: false,
            reason,
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
        // the margin does nothing (the settle, with nothing nearly due held, keeps at once).
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

    fn margin_gate() -> Gate {
        Gate::new(GateConfig {
            sharpness_lookback: 3,
            sharpness_margin: 0.05,
            ..Default::default()
        })
    }

    /// (keep, reason, kept_back) of one frame.
    fn at(g: &mut Gate, u: f64, s: f64) -> (bool, Reason, u64) {
        let d = g.decide_with(Score::Utility(u), Some(s));
        (d.keep, d.reason, d.kept_back)
    }

    #[test]
    fn a_keep_owed_when_the_held_frames_are_let_go_settles_on_a_frame_still_held() {
        // Issue 53, 1: frame 1 sharp and nearly due (0.45), frames 2-3 see little, frame 4 due
        // but blurred, so owed; the stream ends. Frame 1 left the three frames held when frame 4
        // came: the keep settles on frame 4 (the last decided), not on frame 1.
        let mut g = margin_gate();
        g.decide_with(Score::NoReference, Some(100.0));
        assert_eq!(at(&mut g, 0.45, 100.0), (false, Reason::Score, 0));
        at(&mut g, 0.1, 100.0);
        at(&mut g, 0.1, 100.0);
        assert_eq!(at(&mut g, 0.52, 50.0), (false, Reason::Deferred, 0));
        assert_eq!(g.settle_pending(), Some((0, 2)));
        assert_eq!(g.kept(), 2);
        // While frame 1 is still held (one frame later), it is the one.
        let mut g = margin_gate();
        g.decide_with(Score::NoReference, Some(100.0));
        at(&mut g, 0.45, 100.0);
        at(&mut g, 0.1, 100.0);
        assert_eq!(at(&mut g, 0.52, 50.0), (false, Reason::Deferred, 0));
        assert_eq!(g.settle_pending(), Some((2, 2)));
        // Let go without it (a flush): nothing is owed after.
        let mut g = margin_gate();
        g.decide_with(Score::NoReference, Some(100.0));
        at(&mut g, 0.1, 100.0);
        at(&mut g, 0.52, 50.0);
        g.forget_candidates();
        assert_eq!(g.settle_pending(), None);
        assert_eq!(at(&mut g, 0.3, 100.0), (false, Reason::Score, 0));
    }

    #[test]
    fn an_owed_keep_is_never_abandoned_when_the_utility_dips() {
        // Issue 53, 2: frame 4 due (0.52) but blurred, owed; the next frames are sharp at 0.30.
        // The first of them settles the keep: it is not nearly due, so the keep goes back to the
        // owed frame 4.
        let mut g = margin_gate();
        g.decide_with(Score::NoReference, Some(100.0));
        for _ in 0..3 {
            at(&mut g, 0.1, 100.0);
        }
        assert_eq!(at(&mut g, 0.52, 50.0), (false, Reason::Deferred, 0));
        let d = g.decide_with(Score::Utility(0.3), Some(100.0));
        assert_eq!((d.keep, d.kept_back, d.keyframe_index), (false, 1, 2));
        for _ in 0..5 {
            assert_eq!(at(&mut g, 0.3, 100.0), (false, Reason::Score, 0));
        }
        assert_eq!(g.kept(), 2);
        // Blurred frames after it: the keep waits while the owed frame is held, and is made on
        // the last frame before it would leave (3 frames held), back to it.
        let mut g = margin_gate();
        g.decide_with(Score::NoReference, Some(100.0));
        at(&mut g, 0.1, 100.0);
        assert_eq!(at(&mut g, 0.52, 50.0), (false, Reason::Deferred, 0));
        assert_eq!(at(&mut g, 0.3, 40.0), (false, Reason::Deferred, 0));
        assert_eq!(at(&mut g, 0.3, 40.0), (false, Reason::Deferred, 0));
        assert_eq!(at(&mut g, 0.3, 40.0), (false, Reason::Score, 3));
        // A junk frame at that point makes it the same way.
        let mut g = margin_gate();
        g.decide_with(Score::NoReference, Some(100.0));
        at(&mut g, 0.1, 100.0);
        at(&mut g, 0.52, 50.0);
        at(&mut g, 0.3, 40.0);
        assert_eq!(g.decide(Score::Junk).kept_back, 0);
        let d = g.decide(Score::Junk);
        assert_eq!((d.keep, d.reason, d.kept_back), (false, Reason::Junk, 3));
        assert_eq!(g.kept(), 2);
        // The next frames count from the frame kept.
        let d = g.decide_with(Score::Utility(0.2), Some(100.0));
        assert_eq!((d.keyframe_index, d.frames_since_keyframe), (2, 4));
    }

    #[test]
    fn discarded_keeps_are_not_counted() {
        let mut g = margin_gate();
        g.decide_with(Score::NoReference, Some(100.0));
        at(&mut g, 0.9, 100.0);
        g.discard_kept(1);
        g.restart();
        assert_eq!(g.decide(Score::NoReference).keyframe_index, 2);
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
