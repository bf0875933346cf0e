//! What a frame's utility is made of: the model's score `s`, fused with the geometric prior
//! (`tau_geo` of the homographies chained from the reference, [`crate::geometry`]) when the model
//! carries a [`Fusion`] (metadata `leangate.geometry`, the embedded `leangate-s` among them) and
//! the `geometry` property is on, and corrected by what the consumer reports about the frames it
//! was given ([`Utility::feedback`], the element's `leangate-feedback` event). The one place that
//! composes it: the element calls it for every frame, and the tests drive it without a pipeline.

use crate::geometry::{grey_from_tensor, Fusion, Pyramid, Tracker};
use crate::metric::MAX_DIST_M;
use crate::preprocess::TensorSpec;
use crate::quality::{measure, Quality};

/// The most the consumer's feedback ([`Utility::feedback`]) raises the utility (and the most its
/// sum goes below 0).
pub const FEEDBACK_LIMIT: f64 = 0.3;
/// How far below 0 the feedback's sum goes before it lowers the utility: reports that land a
/// little under the threshold on a stream whose keeps come on time stay within it (the first,
/// at gain 0.7, down to tau 0.43).
pub const FEEDBACK_DEAD_BAND: f64 = 0.05;
/// The first reports count for more than the rate: report `n` (0 for the first since the stream
/// began) moves the sum by at least `FEEDBACK_FIRST_GAIN / (1 + n)` of its error, so that a few
/// keeps teach a stream its correction (a running mean of what they measured) and later ones,
/// at the rate, only track it.
pub const FEEDBACK_FIRST_GAIN: f64 = 0.7;
/// One report's error (`tau - threshold`) counts within ±this: a keep that a sudden jump of the
/// view made very late says that the gate was late, not by how much its utility reads low.
pub const FEEDBACK_ERROR_CLIP: f64 = 0.25;

/// How far a score may exceed the model's `leangate.score_max` by rounding (the graph computes in
/// f32) before the claim counts as broken.
const SCORE_MAX_SLACK: f64 = 1e-5;

/// How the last observed frame's utility was composed ([`Utility::score_with`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Composed {
    /// The prior alone decided: no score of the model could lift the fused utility to the
    /// threshold, so the model did not run; the bound stands for the utility.
    Screened(f64),
    /// The model's score `s`, fused with the prior's `tau_geo` when it was used.
    Scored {
        utility: f64,
        s: f64,
        tau_geo: Option<f64>,
    },
    /// A textureless view ([`Quality::Textureless`]): nothing to match, so nothing new; utility
    /// 0 without asking the model.
    Textureless,
}

impl Composed {
    pub fn utility(&self) -> f64 {
        match *self {
            Composed::Textureless => 0.0,
            Composed::Screened(bound) => bound,
            Composed::Scored { utility, .. } => utility,
        }
    }
}

/// The per-stream state behind a frame's utility (the tracker) and how it is combined.
#[derive(Debug, Clone, Default)]
pub struct Utility {
    fusion: Option<Fusion>,
    tracker: Tracker,
    /// The tracker's `tau_geo` of the last observed frame, once asked for.
    tau: Option<Option<f64>>,
    /// The consumer's reports accumulated (`gain * (tau − threshold)` each, within
    /// ±[`FEEDBACK_LIMIT`]; [`Utility::feedback`]); the utility gets its positive part, and
    /// below 0 what lies past the dead band ([`Utility::offset`]).
    feedback: f64,
    /// How many reports the sum holds (since the stream began).
    feedback_reports: u32,
    /// The most the feedback lowers the utility (the element's `feedback-lower`; 0: never).
    feedback_lower: f64,
    /// Whether frames are checked for a usable picture ([`Utility::set_quality_check`]).
    no_quality_check: bool,
    /// The last observed frame's quality ([`crate::quality::assess`]).
    quality: Quality,
    /// The last observed frame's sharpness ([`crate::quality::sharpness`]), when measured.
    sharpness: Option<f64>,
    /// Whether to measure it ([`Utility::set_sharpness_measure`]).
    measure_sharpness: bool,
    /// Scratch for [`measure`], kept between frames.
    bins: Vec<f32>,
    /// [`Tracker::chain`] after each of the last observed frames (None: not trackable), newest
    /// last, at most [`crate::policy::MAX_LOOKBACK`] + 1: what [`Utility::on_keep_back`] rebases to.
    recent: std::collections::VecDeque<Option<crate::geometry::Mat3>>,
    /// A score above the fusion's [`Fusion::s_max`] (the model's `leangate.score_max` was
    /// wrong), with that bound, not yet reported ([`Utility::take_broken_bound`]).
    broken_bound: Option<(f64, f64)>,
    /// The model's score of the last observed frame, once composed (against the current
    /// reference).
    score: Option<f64>,
    /// The model's last score before the last observed frame, against the same reference, and
    /// how many frames before it that score was given (1: the frame just before). None: no
    /// frame was scored since the reference was set, or an unreadable frame came since. What the
    /// screening with [`Fusion::s_step`] starts from.
    last_score: Option<(f64, u32)>,
    /// With depth beside the colour (RGB-D): the metric gate ([`crate::metric`]).
    metric: Metric,
}

/// What depth did for a frame (the `depth` field of `LeanGateMeta`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum DepthUse {
    /// No depth in this stream (colour only).
    #[default]
    None,
    /// The utility is the metric gate's: the teacher's S with the pose fitted from the frames.
    Used,
    /// The stream carries depth, but this frame came without it: gated colour-only.
    Missing,
    /// The frame had depth, but its pose could not be fitted (too few tracks agree, textureless,
    /// depth holes, no depth at the reference): gated colour-only.
    Lost,
}

impl DepthUse {
    pub fn as_str(self) -> &'static str {
        match self {
            DepthUse::None => "none",
            DepthUse::Used => "used",
            DepthUse::Missing => "missing",
            DepthUse::Lost => "lost",
        }
    }

    pub fn parse(s: &str) -> Option<DepthUse> {
        [
            DepthUse::None,
            DepthUse::Used,
            DepthUse::Missing,
            DepthUse::Lost,
        ]
        .into_iter()
        .find(|d| d.as_str() == s)
    }
}

/// A frame as the metric gate keeps it: its grey picture and depth on the model's grid.
#[derive(Debug, Clone)]
struct DepthFrame {
    grey: Vec<f32>,
    view: crate::overlap::DepthView,
    cam: crate::overlap::Pinhole,
}

/// The metric gate's state: the reference's depth, the pose tracker, the recent frames a keep
/// may go back to.
#[derive(Debug, Clone, Default)]
struct Metric {
    tracker: Option<crate::metric::PoseTracker>,
    reference: Option<crate::overlap::DepthView>,
    /// The observed frames (None: one without depth), newest last, at most
    /// [`crate::policy::MAX_LOOKBACK`] + 1: what a keep (the newest) or a keep that went back
    /// makes the reference.
    recent: std::collections::VecDeque<Option<DepthFrame>>,
    /// The last observed frame's metric utility and what depth did for it.
    tau: Option<f64>,
    used: DepthUse,
    /// Whether this stream has carried depth.
    seen: bool,
}

impl Metric {
    /// The frame just observed.
    fn remember(&mut self, f: Option<DepthFrame>) {
        if self.recent.len() > crate::policy::MAX_LOOKBACK as usize {
            self.recent.pop_front();
        }
        self.recent.push_back(f);
    }

    /// The observed frame `back` frames before the newest (0: the newest), if it had depth.
    fn frame(&self, back: u64) -> Option<DepthFrame> {
        (self.recent.len() as u64)
            .checked_sub(1 + back)
            .and_then(|i| self.recent.get(i as usize).cloned())
            .flatten()
    }

    /// Make `f` (None: a frame without depth) the reference.
    fn set_reference(&mut self, f: Option<DepthFrame>) {
        match f {
            Some(f) => {
                let (w, h) = (f.view.width as usize, f.view.height as usize);
                let t = match self.tracker.take() {
                    Some(t) if t.camera() == &f.cam => t,
                    _ => crate::metric::PoseTracker::new(f.cam),
                };
                let t = self.tracker.insert(t);
                t.set_reference(&f.grey, &f.view.depth, w, h);
                self.reference = Some(f.view);
            }
            None => {
                self.tracker = None;
                self.reference = None;
            }
        }
    }
}

impl Utility {
    /// `fusion`: the model's `leangate.geometry`, if it has one.
    pub fn new(fusion: Option<Fusion>) -> Utility {
        Utility {
            fusion,
            tracker: Tracker::new(),
            tau: None,
            feedback: 0.0,
            feedback_reports: 0,
            feedback_lower: 0.0,
            no_quality_check: false,
            quality: Quality::Usable,
            sharpness: None,
            measure_sharpness: false,
            bins: Vec::new(),
            recent: std::collections::VecDeque::new(),
            broken_bound: None,
            score: None,
            last_score: None,
            metric: Metric::default(),
        }
    }

    /// Give the metric gate this frame's depth (after [`Utility::observe`]): `depth` from the
    /// buffer's `LeanGateDepthMeta` (None: the frame came without it), `src` the colour frame's
    /// size, `frame` the model's picture made from it. The depth is sampled onto the model's grid
    /// ([`crate::depth::DepthInput::on_grid`]); with a reference that has depth, the frame's pose
    /// is fitted and [`Utility::metric_tau`] is the teacher's own utility with it. Errs (the
    /// frame then counts as without depth) when the depth cannot be read.
    pub fn observe_depth(
        &mut self,
        frame: (&[f32], &TensorSpec),
        depth: Option<&crate::depth::DepthInput>,
        src: (u32, u32),
        has_reference: bool,
    ) -> Result<(), String> {
        let (t, spec) = frame;
        let (w, h) = (spec.width as usize, spec.height as usize);
        let mut err = None;
        let f = depth.and_then(|d| {
            let (xs, ys) = crate::preprocess::crop(src.0, src.1, spec);
            let (grid, cam) = d
                .on_grid(src.0, src.1, xs, ys, w, h)
                .map_err(|e| err = Some(e))
                .ok()?;
            let view = crate::overlap::DepthView::from_working(grid, w as u32, h as u32, cam)
                .map_err(|e| err = Some(e.to_string()))
                .ok()?;
            let grey = grey_from_tensor(t, w, h, spec.mean, spec.std);
            Some(DepthFrame { grey, view, cam })
        });
        let m = &mut self.metric;
        m.seen |= f.is_some();
        m.tau = None;
        m.used = match (&f, m.seen) {
            (None, true) => DepthUse::Missing,
            (None, false) => DepthUse::None,
            (Some(_), _) => DepthUse::Lost,
        };
        if let (Some(f), true) = (&f, has_reference) {
            if let (Some(tracker), Some(key)) = (m.tracker.as_mut(), m.reference.as_ref()) {
                if let Some(pose) = tracker.observe(&f.grey, &f.view.depth, w, h) {
                    let cur_to_key = pose.inverse();
                    let s = crate::overlap::score_pair(&f.view, key, &cur_to_key, MAX_DIST_M);
                    m.tau = Some(s.tau);
                    m.used = DepthUse::Used;
                }
            }
        } else if f.is_some() {
            // No reference: this frame's depth is the next one's, if it is kept.
            m.used = DepthUse::Used;
        }
        m.remember(f);
        err.map_or(Ok(()), Err)
    }

    /// The frame was not one to track (junk, unreadable): no depth for it, the tracks bridge it.
    pub fn skip_depth(&mut self) {
        let m = &mut self.metric;
        m.tau = None;
        m.used = if m.seen {
            DepthUse::Missing
        } else {
            DepthUse::None
        };
        m.remember(None);
    }

    /// The metric gate's utility of the last observed frame (None: no depth, or its pose
    /// failed: the colour-only utility stands).
    pub fn metric_tau(&self) -> Option<f64> {
        self.metric.tau
    }

    /// What depth did for the last observed frame.
    pub fn depth_use(&self) -> DepthUse {
        self.metric.used
    }

    /// `Some((score, bound))` once a model score exceeded the bound the model claims for its
    /// scores (metadata `leangate.score_max`): from that frame on, screening assumes any score
    /// up to 1, as for a model that claims nothing. Frames screened before it were judged by the
    /// model's claim. Reported once.
    pub fn take_broken_bound(&mut self) -> Option<(f64, f64)> {
        self.broken_bound.take()
    }

    /// The score step screening assumes ([`Utility::screen`]): the model's own
    /// (`leangate.score_step`) until this is called; `None` or 0: none.
    pub fn set_score_step(&mut self, step: Option<f64>) {
        if let Some(f) = self.fusion.as_mut() {
            *f = f.with_score_step(step);
        }
    }

    /// Check each observed frame for a usable picture (on by default; the element's
    /// `reject-junk`). Off, every frame is [`Quality::Usable`].
    pub fn set_quality_check(&mut self, on: bool) {
        self.no_quality_check = !on;
    }

    /// The last observed frame's quality: [`Quality::Usable`] when unchecked or unreadable. A
    /// junk frame ([`Quality::is_junk`]) is to be dropped unscored; it was not fed to the prior,
    /// whose chain goes from the frame before it to the frame after it.
    pub fn quality(&self) -> Quality {
        self.quality
    }

    /// Measure each checked frame's sharpness too (off by default: a pass over the picture the
    /// gate needs only with the element's `sharpness-wait`).
    pub fn set_sharpness_measure(&mut self, on: bool) {
        self.measure_sharpness = on;
    }

    /// The last observed frame's sharpness ([`crate::quality::sharpness`] of the model's
    /// picture); `None` when not measured, unchecked, unreadable or junk.
    pub fn sharpness(&self) -> Option<f64> {
        self.sharpness
    }

    /// What the consumer's feedback adds to every utility (0 until feedback arrives): the sum's
    /// positive part, or, below [`FEEDBACK_DEAD_BAND`] under 0, the rest of it down to
    /// `-feedback_lower`.
    pub fn offset(&self) -> f64 {
        if self.feedback >= 0.0 {
            self.feedback
        } else {
            -(-self.feedback - FEEDBACK_DEAD_BAND).clamp(0.0, self.feedback_lower)
        }
    }

    /// The most the feedback may lower the utility (`feedback-lower`, within 0 to
    /// [`FEEDBACK_LIMIT`]; 0, a new `Utility`'s, never lowers it; the element sets its
    /// `feedback-lower`, 0.15 by default).
    pub fn set_feedback_lower(&mut self, lower: f64) {
        self.feedback_lower = if lower.is_finite() {
            lower.clamp(0.0, FEEDBACK_LIMIT)
        } else {
            0.0
        };
    }

    /// The consumer's feedback on a kept frame: `tau` = 1 − S that it measured between that frame
    /// and its previous keyframe (MASt3R-SLAM computes S for every frame it tracks). The gate
    /// means to keep a frame when tau reaches `threshold`; a keep measured above it came late
    /// (the utility reads low on this stream), below it early. Each report adds
    /// `gain * (tau − threshold)` to a sum kept within ±[`FEEDBACK_LIMIT`], the error counted
    /// within ±[`FEEDBACK_ERROR_CLIP`] and the gain `rate`, or for the first reports of a stream
    /// more ([`FEEDBACK_FIRST_GAIN`]` / (1 + n)` for report n), so that a short stream is
    /// corrected within a few keeps. The utility is raised by the sum's positive part
    /// ([`Utility::offset`]): a per-stream correction where the scene's depth or parallax,
    /// which the pictures do not show, makes the utility read low. Below 0 the sum lowers the
    /// utility only past [`FEEDBACK_DEAD_BAND`] and by at most `feedback_lower`
    /// ([`Utility::set_feedback_lower`]): lowering it freely let the noise of single reports
    /// delay keeps into late ones where the default is already right, and the sum going below
    /// 0 keeps that noise from ratcheting the offset up on a stream where keeps come on time
    /// (`training/experiments/NOTEBOOK.md`). A `rate` of 0 (or not a number) ignores the report.
    /// Returns the new offset; a `tau` outside [0, 1] (or not a number) is refused and changes
    /// nothing.
    pub fn feedback(&mut self, tau: f64, threshold: f64, rate: f64) -> Result<f64, String> {
        if !(0.0..=1.0).contains(&tau) {
            return Err(format!("its `tau` {tau} is outside [0, 1]"));
        }
        if rate > 0.0 && threshold.is_finite() {
            let first = FEEDBACK_FIRST_GAIN / (1.0 + f64::from(self.feedback_reports));
            let error = (tau - threshold).clamp(-FEEDBACK_ERROR_CLIP, FEEDBACK_ERROR_CLIP);
            self.feedback = (self.feedback + rate.min(1.0).max(first) * error)
                .clamp(-FEEDBACK_LIMIT, FEEDBACK_LIMIT);
            self.feedback_reports = self.feedback_reports.saturating_add(1);
        }
        Ok(self.offset())
    }

    /// Forget the feedback (a new stream: start, stream-start, caps change).
    pub fn reset_feedback(&mut self) {
        self.feedback = 0.0;
        self.feedback_reports = 0;
    }

    /// `u` with the feedback's offset, within [0, 1]; `u` itself while the offset is 0.
    fn corrected(&self, u: f64) -> f64 {
        let o = self.offset();
        if o == 0.0 {
            u
        } else {
            (u + o).clamp(0.0, 1.0)
        }
    }

    pub fn fusion(&self) -> Option<Fusion> {
        self.fusion
    }

    /// Whether the prior is in use for this frame: the model has a fusion and `enabled`.
    pub fn uses_geometry(&self, enabled: bool) -> bool {
        enabled && self.fusion.is_some()
    }

    /// Feed the next frame, the model's input tensor (`None`: it could not be read). The tracker
    /// restarts when there is no reference, and forgets everything while the prior is off or the
    /// frame is unreadable (the chain cannot bridge a gap).
    pub fn observe(
        &mut self,
        frame: Option<(&[f32], &TensorSpec)>,
        has_reference: bool,
        enabled: bool,
    ) {
        self.step(|u| u.observe_frame(frame, has_reference, enabled));
    }

    /// One frame more: the model's last score ages a frame, `look` reads the frame (its quality,
    /// sharpness, the prior's chain), and the chain is remembered for a look-back unless the
    /// frame is junk.
    fn step(&mut self, look: impl FnOnce(&mut Self)) {
        self.last_score = match (self.score.take(), self.last_score) {
            (Some(s), _) => Some((s, 1)),
            (None, Some((s, k))) => Some((s, k.saturating_add(1))),
            (None, None) => None,
        };
        look(self);
        if self.recent.len() > crate::policy::MAX_LOOKBACK as usize {
            self.recent.pop_front();
        }
        let trackable = !self.quality.is_junk();
        self.recent
            .push_back(self.tracker.chain().filter(|_| trackable));
    }

    /// Observe a frame flagged as damaged upstream ([`Quality::Corrupted`]): junk, whatever its
    /// pixels, so it is never kept or the reference and the prior's chain bridges it (as
    /// [`Utility::observe`] does for a dark frame).
    pub fn observe_damaged(&mut self) {
        self.step(|u| {
            u.tau = None;
            u.quality = Quality::Corrupted;
            u.sharpness = None;
        });
    }

    fn observe_frame(
        &mut self,
        frame: Option<(&[f32], &TensorSpec)>,
        has_reference: bool,
        enabled: bool,
    ) {
        self.tau = None;
        self.quality = Quality::Usable;
        self.sharpness = None;
        let Some((tensor, spec)) = frame else {
            self.tracker.clear();
            self.last_score = None;
            return;
        };
        let geometry = self.uses_geometry(enabled);
        if !geometry && self.no_quality_check {
            self.tracker.clear();
            return;
        }
        if !has_reference {
            self.last_score = None;
        }
        let (w, h) = (spec.width as usize, spec.height as usize);
        let grey = grey_from_tensor(tensor, w, h, spec.mean, spec.std);
        if !self.no_quality_check {
            let m = measure(&grey, w, h, &mut self.bins, self.measure_sharpness);
            (self.quality, self.sharpness) = (m.quality, m.sharpness);
            if self.quality.is_junk() {
                return; // not a picture of the scene: the chain bridges it
            }
        }
        if geometry {
            if !has_reference {
                self.tracker.clear();
            }
            self.tracker.observe(Pyramid::for_prior(grey, w, h));
        } else {
            self.tracker.clear();
        }
    }

    /// The utility of the last observed frame given the model's score `s` (fused, plus the
    /// feedback's offset), and the prior's `tau_geo` when it was used (`None`: the model's score
    /// alone: no fusion, the prior off, or the chain lost until the next keep).
    pub fn compose(&mut self, s: f64, enabled: bool) -> (f64, Option<f64>) {
        if let Some(f) = self.fusion.as_mut() {
            if s.is_finite() && s > f.s_max + SCORE_MAX_SLACK {
                self.broken_bound = Some((s, f.s_max));
                f.s_max = 1.0;
            }
        }
        self.score = s.is_finite().then_some(s);
        match self.fusion.filter(|_| enabled) {
            Some(f) => {
                let g = self.tau_geo();
                let u = f.fuse(s, g);
                (self.corrected(u), g.filter(|_| s.is_finite()))
            }
            None => (self.corrected(s), None),
        }
    }

    /// Whether the prior decides that the last observed frame is dropped, without the model: the
    /// fusion is in use, the chain holds, and
    /// - no model score could lift the fused utility to `threshold` ([`Fusion::upper`] is below
    ///   it): the decision is the one any score would have given (the gate keeps a frame on its
    ///   score only when the utility reaches the threshold); or
    /// - the model carries a score step ([`Fusion::s_step`], `leangate.score_step`), scored a
    ///   frame `k` frames before this one against the same reference, and that score plus `k`
    ///   steps could not lift it ([`Fusion::upper_below`]): one step per frame since, so the
    ///   rule loosens each frame until it is the first rule's (the model's top score) and the
    ///   model runs again. The step is a rule, not a bound: where the score rises more than it
    ///   on a frame whose utility reaches the threshold, that frame is dropped and the keep goes
    ///   to the next frame that reaches it (the next one while the utility keeps rising; later,
    ///   or not at all, after a short peak).
    ///
    /// Then the bound stands for the frame's utility and the model need not run. (A model that
    /// would have failed on the frame, which keeps it, is not asked.)
    pub fn screen(&mut self, threshold: f64, enabled: bool) -> Option<f64> {
        let f = self.fusion.filter(|_| enabled)?;
        let g = self.tau_geo()?;
        let up = self.corrected(f.upper(g));
        if up < threshold {
            return Some(up);
        }
        let (s, k) = self.last_score?;
        let cap = s + f.s_step? * f64::from(k);
        let up = self.corrected(f.upper_below(g, cap));
        (up < threshold).then_some(up)
    }

    /// The utility of the last observed frame: screened by the prior when `screen` is on and
    /// [`Utility::screen`] decides it (`model` is not called), else `model`'s score composed
    /// ([`Utility::compose`]). The one sequence the element and the benchmark run per frame.
    pub fn score_with<E>(
        &mut self,
        threshold: f64,
        enabled: bool,
        screen: bool,
        model: impl FnOnce() -> Result<f64, E>,
    ) -> Result<Composed, E> {
        if self.quality == Quality::Textureless {
            return Ok(Composed::Textureless);
        }
        if let Some(bound) = screen.then(|| self.screen(threshold, enabled)).flatten() {
            return Ok(Composed::Screened(bound));
        }
        let s = model()?;
        let (utility, tau_geo) = self.compose(s, enabled);
        Ok(Composed::Scored {
            utility,
            s,
            tau_geo,
        })
    }

    /// The tracker's `tau_geo` of the last observed frame (computed once per frame).
    fn tau_geo(&mut self) -> Option<f64> {
        *self.tau.get_or_insert_with(|| self.tracker.tau())
    }

    /// The last observed frame was kept and is the new reference.
    pub fn on_keep(&mut self) {
        let f = self.metric.frame(0);
        self.metric.set_reference(f);
        self.tracker.set_reference();
        self.tau = None;
        (self.score, self.last_score) = (None, None);
        if let Some(last) = self.recent.back_mut() {
            *last = self.tracker.chain();
        }
    }

    /// The frame observed `back` frames before the last one was kept and is the new reference
    /// ([`crate::policy::Decision::kept_back`]): the prior's chain goes on from it (lost when it
    /// was lost at that frame, or that frame is no longer remembered).
    pub fn on_keep_back(&mut self, back: u64) {
        let f = self.metric.frame(back);
        self.metric.set_reference(f);
        let at = (self.recent.len() as u64)
            .checked_sub(1 + back)
            .and_then(|i| self.recent.get(i as usize).copied())
            .flatten();
        self.tracker.rebase(at);
        self.tau = None;
        (self.score, self.last_score) = (None, None);
        // What the remembered frames' chains were measured from is gone.
        let n = self.recent.len();
        for (i, h) in self.recent.iter_mut().enumerate() {
            *h = (i + 1 == n).then(|| self.tracker.chain()).flatten();
        }
    }

    /// Forget the stream (start, flush, caps change).
    pub fn clear(&mut self) {
        self.metric = Metric::default();
        self.tracker.clear();
        self.tau = None;
        (self.score, self.last_score) = (None, None);
        self.recent.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preprocess::ResizeMode;

    const W: usize = 160;
    const H: usize = 120;

    fn spec() -> TensorSpec {
        TensorSpec {
            width: W as u32,
            height: H as u32,
            resize: ResizeMode::ShortSideCrop,
            mean: [0.0; 3],
            std: [1.0; 3],
        }
    }

    /// A textured picture shifted right by `dx` pixels, as the model's input tensor.
    fn frame(dx: f32) -> Vec<f32> {
        let mut t = vec![0.0; 3 * W * H];
        for y in 0..H {
            for x in 0..W {
                let u = x as f32 - dx;
                let v = y as f32;
                let g = 0.5
                    + 0.2 * (u * 0.21).sin() * (v * 0.17).cos()
                    + 0.15 * ((u + 2.0 * v) * 0.09).sin()
                    + 0.1 * ((3.0 * u - v) * 0.05).cos();
                for c in 0..3 {
                    t[c * W * H + y * W + x] = g;
                }
            }
        }
        t
    }

    /// A utility with the fusion `fusion`, its reference the unshifted picture.
    fn referenced(fusion: &str) -> Utility {
        let mut u = Utility::new(Some(Fusion::parse(fusion).unwrap()));
        u.observe(Some((&frame(0.0), &spec())), false, true);
        u.on_keep();
        u
    }

    #[test]
    fn without_fusion_the_score_passes_through() {
        let mut u = Utility::new(None);
        u.observe(Some((&frame(0.0), &spec())), false, true);
        assert!(!u.uses_geometry(true));
        assert_eq!(u.compose(0.37, true), (0.37, None));
    }

    #[test]
    fn fuses_the_prior_of_a_pan_and_falls_back_when_off() {
        // weights 0, 1, 0, 0: the utility is tau_geo itself.
        let mut u = referenced("raster-homography-v1: 0, 1, 0, 0");
        let sp = spec();
        let mut last = 0.0;
        for k in 1..=10 {
            u.observe(Some((&frame(2.0 * k as f32), &sp)), true, true);
            let (v, g) = u.compose(0.9, true);
            let g = g.expect("the chain holds on a smooth pan");
            assert_eq!(v, g);
            // A pan of d pixels loses about d / W of the view.
            let expected = 2.0 * k as f64 / W as f64;
            assert!(
                (g - expected).abs() < 0.02,
                "step {k}: tau_geo {g} vs {expected}"
            );
            assert!(g >= last);
            last = g;
        }
        // The prior switched off: the model's score alone, and the chain is forgotten.
        u.observe(Some((&frame(30.0), &sp)), true, false);
        assert_eq!(u.compose(0.9, false), (0.9, None));
        u.observe(Some((&frame(32.0), &sp)), true, true);
        assert_eq!(
            u.compose(0.9, true),
            (0.9, None),
            "lost until the next keep"
        );
        u.on_keep();
        u.observe(Some((&frame(34.0), &sp)), true, true);
        let (v, g) = u.compose(0.9, true);
        assert!(g.is_some() && v < 0.05, "restarted at the keep: {v}");
    }

    #[test]
    fn an_unreadable_frame_or_a_failed_score_loses_nothing() {
        let mut u = referenced("raster-homography-v1: 0.1, 0.8, 0, 0.2");
        let sp = spec();
        u.observe(None, true, true);
        assert_eq!(u.compose(0.4, true), (0.4, None));
        // NaN from the model stays NaN (the gate keeps the frame: fail open).
        u.observe(Some((&frame(1.0), &sp)), false, true);
        u.on_keep();
        u.observe(Some((&frame(2.0), &sp)), true, true);
        assert!(u.compose(f64::NAN, true).0.is_nan());
    }

    #[test]
    fn screens_exactly_the_frames_no_score_could_keep() {
        let f = Fusion::parse("raster-homography-v1: 0.121524, 0.698698, 0, 0.25").unwrap();
        let mut u = Utility::new(Some(f));
        let sp = spec();
        u.observe(Some((&frame(0.0), &sp)), false, true);
        // No reference yet: nothing to screen.
        assert_eq!(u.screen(0.5, true), None);
        u.on_keep();
        let (mut screened, mut scored) = (0, 0);
        for k in 1..=30 {
            u.observe(Some((&frame(2.0 * k as f32), &sp)), true, true);
            let bound = u.screen(0.5, true);
            // Whatever the model said, the gate's verdict is the bound's.
            let best = [0.0, 0.3, 0.7, 1.0, 4.0]
                .iter()
                .map(|&s| u.compose(s, true).0)
                .fold(f64::MIN, f64::max);
            match bound {
                Some(b) => {
                    screened += 1;
                    assert!(
                        b < 0.5 && best <= b + 1e-12,
                        "step {k}: {best} vs bound {b}"
                    );
                }
                None => {
                    scored += 1;
                    assert!(best >= 0.5, "step {k}: not screened, yet {best} < 0.5");
                }
            }
            // Asking again gives the same (tau_geo is computed once per frame).
            assert_eq!(u.screen(0.5, true), bound);
        }
        // Small pans are screened; past about a fifth of the view the model decides.
        assert!(
            screened >= 8 && scored >= 8,
            "{screened} screened, {scored} scored"
        );
        // The prior off, or a lower threshold that a score could reach: the model runs.
        assert_eq!(u.screen(0.5, false), None);
        assert_eq!(u.screen(0.0, true), None);
    }

    #[test]
    fn score_with_asks_the_model_only_when_the_prior_cannot_decide() {
        let mut u = referenced("raster-homography-v1: 0.121524, 0.698698, 0, 0.25");
        let sp = spec();
        // 2 px of 160: tau_geo about 0.0125, far below what the threshold needs.
        u.observe(Some((&frame(2.0), &sp)), true, true);
        let never = || -> Result<f64, ()> { panic!("the model ran on a screened frame") };
        let c = u.score_with(0.5, true, true, never).unwrap();
        assert_eq!(c, Composed::Screened(u.screen(0.5, true).unwrap()));
        // Screening off, or an error from the model: the model is asked and its answer used.
        let c = u.score_with(0.5, true, false, || Ok::<_, ()>(0.6)).unwrap();
        assert_eq!(c.utility(), u.compose(0.6, true).0);
        assert!(matches!(c, Composed::Scored { s, tau_geo: Some(_), .. } if s == 0.6));
        assert_eq!(
            u.score_with(0.5, true, false, || Err::<f64, _>("failed")),
            Err("failed")
        );
    }
    #[test]
    fn a_model_that_bounds_its_scores_is_screened_on_more_frames_until_it_breaks_the_bound() {
        let f = "raster-homography-v1: 0.121524, 0.698698, 0, 0.25";
        let (mut wide, mut tight) = (referenced(f), referenced(f));
        tight.fusion = tight.fusion.map(|f| f.with_score_max(0.878));
        let sp = spec();
        let (mut n_wide, mut n_tight) = (0, 0);
        for k in 1..=30 {
            let pic = frame(2.0 * k as f32);
            wide.observe(Some((&pic, &sp)), true, true);
            tight.observe(Some((&pic, &sp)), true, true);
            let (a, b) = (wide.screen(0.5, true), tight.screen(0.5, true));
            n_wide += a.is_some() as usize;
            n_tight += b.is_some() as usize;
            // Tighter, never looser; and no score the model can give reaches the threshold.
            assert!(a.is_none() || b.is_some(), "step {k}");
            if let Some(b) = b {
                assert!(
                    tight.compose(0.878, true).0 <= b + 1e-12 && b < 0.5,
                    "step {k}"
                );
            }
        }
        assert!(n_tight > n_wide, "{n_tight} against {n_wide} screened");
        // A score above the claim: reported once, and screening goes back to the wide bound.
        let pic = frame(36.0);
        tight.observe(Some((&pic, &sp)), true, true);
        wide.observe(Some((&pic, &sp)), true, true);
        assert_eq!(tight.take_broken_bound(), None);
        tight.compose(0.878 + 1e-6, true);
        assert_eq!(
            tight.take_broken_bound(),
            None,
            "rounding is not a broken claim"
        );
        tight.compose(0.95, true);
        assert_eq!(tight.take_broken_bound(), Some((0.95, 0.878)));
        assert_eq!(tight.take_broken_bound(), None);
        assert_eq!(tight.fusion().unwrap().s_max, 1.0);
        for k in 19..=30 {
            let pic = frame(2.0 * k as f32);
            tight.observe(Some((&pic, &sp)), true, true);
            wide.observe(Some((&pic, &sp)), true, true);
            assert_eq!(tight.screen(0.5, true), wide.screen(0.5, true), "step {k}");
        }
    }

    #[test]
    fn a_score_step_screens_the_frames_after_a_low_score_one_step_per_frame() {
        let f = "raster-homography-v1: 0.121524, 0.698698, 0, 0.25";
        let (mut exact, mut step) = (referenced(f), referenced(f));
        exact.fusion = exact.fusion.map(|f| f.with_score_max(0.878));
        step.fusion = step
            .fusion
            .map(|f| f.with_score_max(0.878).with_score_step(Some(0.15)));
        let sp = spec();
        let low = || Ok::<_, ()>(0.1);
        // What each frame of a pan was: e(xactly screened), s(cored), t (screened by the step).
        let mut pattern = String::new();
        // Frames since the step instance's last score.
        let mut since = 0u32;
        for k in 1..=44 {
            let pic = frame(2.0 * k as f32);
            exact.observe(Some((&pic, &sp)), true, true);
            step.observe(Some((&pic, &sp)), true, true);
            let e = exact.score_with(0.5, true, true, low).unwrap();
            let s = step.score_with(0.5, true, true, low).unwrap();
            pattern.push(match (e, s) {
                (Composed::Screened(a), Composed::Screened(b)) => {
                    assert_eq!(a, b, "step {k}");
                    'e'
                }
                (Composed::Scored { .. }, Composed::Scored { .. }) => 's',
                (
                    Composed::Scored {
                        utility, tau_geo, ..
                    },
                    Composed::Screened(b),
                ) => {
                    assert!(pattern.contains('s'), "step {k}: {pattern}");
                    // Below the threshold, and above what any score up to 0.1 plus one step
                    // per frame since the last score gives.
                    let cap = 0.1 + 0.15 * f64::from(since + 1);
                    let g = tau_geo.unwrap();
                    let fusion = step.fusion().unwrap();
                    assert!(b < 0.5 && utility <= b, "step {k}: {utility} vs {b}");
                    for sc in [0.0, 0.1, cap - 0.01, cap] {
                        assert!(fusion.fuse(sc, Some(g)) <= b + 1e-12, "step {k} score {sc}");
                    }
                    assert!(fusion.fuse(cap + 0.01, Some(g)) > b, "step {k}: tight");
                    't'
                }
                other => panic!("step {k}: {other:?}"),
            });
            since = match pattern.chars().last() {
                Some('s') => 0,
                _ => since + 1,
            };
        }
        // Small pans are screened exactly; then by the step, one step more on each frame after
        // a scored one (two frames in a row here), until the model runs again; once the prior
        // alone nearly reaches 0.5, every frame is scored.
        assert!(pattern.starts_with("eeeeeeee"), "{pattern}");
        assert!(pattern.contains("stts"), "{pattern}");
        assert!(pattern.ends_with("ss"), "{pattern}");
        // A score that the step lifts past the model's top (0.75 + 0.15 > 0.878): the step
        // screens nothing more than the exact bound.
        let (mut exact, mut high) = (referenced(f), referenced(f));
        exact.fusion = exact.fusion.map(|f| f.with_score_max(0.878));
        high.fusion = step.fusion();
        for k in 1..=36 {
            let pic = frame(2.0 * k as f32);
            exact.observe(Some((&pic, &sp)), true, true);
            high.observe(Some((&pic, &sp)), true, true);
            let a = exact.score_with(0.5, true, true, || Ok::<_, ()>(0.75));
            let b = high.score_with(0.5, true, true, || Ok::<_, ()>(0.75));
            assert_eq!(a, b, "step {k}");
        }
        // After a keep, the first frame has no score against the new reference to start from.
        step.on_keep();
        let pic = frame(90.0);
        step.observe(Some((&pic, &sp)), true, true);
        assert!(step.last_score.is_none());
        // An unreadable frame: the frame after it has no previous score either.
        step.compose(0.1, true);
        step.observe(None, true, true);
        step.observe(Some((&pic, &sp)), true, true);
        assert!(step.last_score.is_none());
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn feedback_raises_the_utility_by_what_came_late_within_its_limit() {
        let mut u = Utility::new(None);
        u.observe(Some((&frame(0.0), &spec())), false, true);
        assert_eq!(u.compose(0.4, true).0, 0.4, "no feedback, no change");
        // A keep measured at tau 0.7 came late: the utility reads low, so it is raised. The
        // first report counts at FEEDBACK_FIRST_GAIN (0.7), above the rate.
        assert!(close(u.feedback(0.7, 0.5, 0.2).unwrap(), 0.14));
        assert!(close(u.compose(0.4, true).0, 0.54));
        // The second at 0.7 / 2, the third at 0.7 / 3, both above the rate ...
        assert!(close(u.feedback(0.6, 0.5, 0.2).unwrap(), 0.175));
        assert!(close(u.feedback(0.5, 0.5, 0.2).unwrap(), 0.175));
        // ... and from the fourth on (0.7 / 4 < 0.2) at the rate: one measured early takes
        // some back.
        assert!(close(u.feedback(0.45, 0.5, 0.2).unwrap(), 0.165));
        // One report's error counts within +-FEEDBACK_ERROR_CLIP (0.25), late or early.
        assert!(close(u.feedback(1.0, 0.5, 0.2).unwrap(), 0.215));
        assert!(close(u.feedback(0.0, 0.5, 0.2).unwrap(), 0.165));
        // A rate above the first reports' gain counts as it is (within 1).
        assert!(close(u.feedback(0.6, 0.5, 0.9).unwrap(), 0.255));
        for _ in 0..50 {
            u.feedback(1.0, 0.5, 0.4).unwrap();
        }
        assert_eq!(u.offset(), FEEDBACK_LIMIT);
        assert_eq!(u.compose(0.9, true).0, 1.0, "within [0, 1]");
        assert!(
            u.compose(f64::NAN, true).0.is_nan(),
            "a failed score stays failed"
        );
        // Refused: not a tau; rate 0 (or not a number) ignores feedback.
        for bad in [f64::NAN, -0.1, 1.5, f64::INFINITY] {
            assert!(u.feedback(bad, 0.5, 0.4).is_err());
        }
        assert_eq!(u.feedback(0.0, 0.5, 0.0).unwrap(), FEEDBACK_LIMIT);
        assert_eq!(u.feedback(0.0, 0.5, f64::NAN).unwrap(), FEEDBACK_LIMIT);
        // A new stream forgets the sum and the count: its first report counts at 0.7 again.
        u.reset_feedback();
        assert_eq!(u.compose(0.4, true).0, 0.4);
        assert!(close(u.feedback(0.7, 0.5, 0.2).unwrap(), 0.14));
    }

    #[test]
    fn feedback_lowers_the_utility_past_its_dead_band_within_feedback_lower() {
        let mut u = Utility::new(None);
        u.observe(Some((&frame(0.0), &spec())), false, true);
        // feedback-lower 0 (a new Utility's): early keeps never lower the utility.
        for _ in 0..10 {
            assert_eq!(u.feedback(0.2, 0.5, 0.2).unwrap(), 0.0);
        }
        assert_eq!(u.compose(0.6, true).0, 0.6);
        u.reset_feedback();
        u.set_feedback_lower(0.15);
        // A keep measured at tau 0.45 moves the sum by 0.7 * -0.05: within the dead band
        // (-0.05), nothing lowered; the next, at tau 0.4, by 0.35 * -0.1 lowers the utility by
        // what lies beyond it, ...
        assert_eq!(u.feedback(0.45, 0.5, 0.2).unwrap(), 0.0);
        assert!(close(u.feedback(0.4, 0.5, 0.2).unwrap(), -0.02));
        assert!(close(u.compose(0.6, true).0, 0.58));
        // ... down to feedback-lower however many come (a consumer that always says "early").
        for _ in 0..50 {
            u.feedback(0.0, 0.5, 0.2).unwrap();
        }
        assert!(close(u.offset(), -0.15));
        assert!(close(u.compose(0.6, true).0, 0.45));
        assert_eq!(u.compose(0.1, true).0, 0.0, "within [0, 1]");
        // Late keeps bring it back up at the rate, each error within the clip (0.2 * 0.25).
        for _ in 0..10 {
            u.feedback(1.0, 0.5, 0.2).unwrap();
        }
        assert!(close(u.offset(), 0.2));
        // A bad setting is taken as 0 or the limit.
        u.reset_feedback();
        u.set_feedback_lower(f64::NAN);
        for _ in 0..10 {
            u.feedback(0.0, 0.5, 0.2).unwrap();
        }
        assert_eq!(u.offset(), 0.0);
        u.set_feedback_lower(5.0);
        assert!(close(u.offset(), -(FEEDBACK_LIMIT - FEEDBACK_DEAD_BAND)));
    }

    #[test]
    fn feedback_raises_the_fused_utility_and_the_screening_bound_alike() {
        // weights 0, 1, 0, 0.25: utility tau_geo + 0.25 s; a frame is screened when even s = 1
        // cannot lift it to the threshold. A raised utility screens less.
        let mut u = referenced("raster-homography-v1: 0, 1, 0, 0.25");
        let sp = spec();
        u.observe(Some((&frame(8.0), &sp)), true, true);
        let (plain, g) = u.compose(0.5, true);
        let g = g.unwrap();
        assert!((plain - (g + 0.125)).abs() < 1e-9);
        let bound = u.screen(1.0, true).unwrap();
        let t = bound + 0.05; // screened before the feedback, not after it
        assert!(u.screen(t, true).is_some());
        u.feedback(0.75, 0.5, 0.4).unwrap(); // the first report: offset 0.7 * 0.25
        assert!((u.compose(0.5, true).0 - (plain + 0.175)).abs() < 1e-9);
        assert!((u.screen(1.0, true).unwrap() - (bound + 0.175)).abs() < 1e-9);
        assert!(u.screen(t, true).is_none());
    }
}
