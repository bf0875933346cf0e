//! `LeanGateMeta`: the per-buffer verdict, as a `GstCustomMeta` so that C, Python and Rust
//! consumers can all read it (`buf.get_custom_meta("LeanGateMeta").get_structure()` in Python).
//!
//! Fields of the structure:
//! | field | type | meaning |
//! |---|---|---|
//! | `utility` | double | predicted tau (NaN for a frame with no reference, or when inference failed; for a `screened` frame the largest utility the model could have given, below the threshold) |
//! | `keep` | boolean | the gate's decision |
//! | `reason` | string | `first`, `warmup`, `score`, `max-gap`, `forced`, `error`, `junk` (dropped: no usable picture) |
//! | `keyframe-index` | guint64 | frames kept so far, this one included |
//! | `reference-pts` | guint64 | PTS (ns) of the reference the frame was scored against (its own PTS for `first`; `GST_CLOCK_TIME_NONE` when unknown) |
//! | `frames-since-keyframe` | guint | frames since that reference (0 for a kept frame) |
//! | `inference-us` | guint64 | time spent preprocessing and scoring this frame, microseconds |
//! | `quality` | string | `usable`, or what [`crate::quality::assess`] found: `dark`, `saturated`, `noise` (junk: never kept), `textureless` (utility 0), or `corrupted` (the buffer flagged CORRUPTED or GAP: junk); `usable` when `reject-junk` is off or the frame could not be read |
//! | `depth` | string | what depth did for the frame (RGB-D input, `LeanGateDepthMeta`): `none` (the stream carries no depth), `used` (the utility is the metric gate's: the teacher's S with the pose fitted from the frames), `missing` (this frame came without depth: gated colour-only), `lost` (its pose could not be fitted: gated colour-only) |
//! | `screened` | boolean | the model did not run: the geometric prior alone bounded the utility below the threshold (the `screen` property); the frame is dropped unless `warmup`, `max-gap` or a forced keyframe keeps it |

use crate::policy::Reason;
use crate::quality::Quality;
use crate::utility::DepthUse;

/// The registered name of the custom meta.
pub const META_NAME: &str = "LeanGateMeta";

/// The verdict carried by every buffer leaving the element.
#[derive(Debug, Clone, PartialEq)]
pub struct GateMeta {
    pub utility: f64,
    pub keep: bool,
    pub reason: Reason,
    pub keyframe_index: u64,
    pub reference_pts: Option<gst::ClockTime>,
    pub frames_since_keyframe: u32,
    pub inference_us: u64,
    /// The prior alone decided (the model did not run); `utility` is then its bound.
    pub screened: bool,
    /// Whether the frame carries a usable picture ([`crate::quality`]).
    pub quality: Quality,
    pub depth: DepthUse,
}

/// Register the custom meta (idempotent). Called from `plugin_init`.
pub fn register() {
    if !gst::meta::CustomMeta::is_registered(META_NAME) {
        // No tags: transforms that copy untagged metas (most do) carry it along.
        gst::meta::CustomMeta::register(META_NAME, &[]);
    }
}

impl GateMeta {
    fn fill(&self, s: &mut gst::StructureRef) {
        s.set("utility", self.utility);
        s.set("keep", self.keep);
        s.set("reason", self.reason.as_str());
        s.set("keyframe-index", self.keyframe_index);
        s.set(
            "reference-pts",
            self.reference_pts.map(|t| t.nseconds()).unwrap_or(u64::MAX),
        );
        s.set("frames-since-keyframe", self.frames_since_keyframe);
        s.set("inference-us", self.inference_us);
        s.set("screened", self.screened);
        s.set("quality", self.quality.as_str());
        s.set("depth", self.depth.as_str());
    }

    /// Attach (or overwrite) the meta on a buffer.
    pub fn attach(&self, buffer: &mut gst::BufferRef) -> Result<(), gst::glib::BoolError> {
        if let Ok(mut m) = gst::meta::CustomMeta::from_mut_buffer(buffer, META_NAME) {
            self.fill(m.mut_structure());
            return Ok(());
        }
        let mut m = gst::meta::CustomMeta::add(buffer, META_NAME)?;
        self.fill(m.mut_structure());
        Ok(())
    }

    /// Read the meta back from a buffer, if it carries one.
    pub fn read(buffer: &gst::BufferRef) -> Option<GateMeta> {
        let m = gst::meta::CustomMeta::from_buffer(buffer, META_NAME).ok()?;
        let s = m.structure();
        let pts: u64 = s.get("reference-pts").ok()?;
        Some(GateMeta {
            utility: s.get("utility").ok()?,
            keep: s.get("keep").ok()?,
            reason: Reason::parse(s.get::<&str>("reason").ok()?)?,
            keyframe_index: s.get("keyframe-index").ok()?,
            reference_pts: if pts == u64::MAX {
                None
            } else {
                Some(gst::ClockTime::from_nseconds(pts))
            },
            frames_since_keyframe: s.get("frames-since-keyframe").ok()?,
            inference_us: s.get("inference-us").ok()?,
            screened: s.get("screened").unwrap_or(false),
            quality: s
                .get::<&str>("quality")
                .ok()
                .and_then(Quality::parse)
                .unwrap_or_default(),
            depth: s
                .get::<&str>("depth")
                .ok()
                .and_then(DepthUse::parse)
                .unwrap_or_default(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn meta_round_trip_and_overwrite() {
        gst::init().unwrap();
        register();
        let mut buf = gst::Buffer::with_size(4).unwrap();
        let m = GateMeta {
            utility: 0.25,
            keep: false,
            reason: Reason::Score,
            keyframe_index: 3,
            reference_pts: Some(gst::ClockTime::from_mseconds(40)),
            frames_since_keyframe: 2,
            inference_us: 1234,
            screened: true,
            quality: Quality::Textureless,
            depth: DepthUse::Lost,
        };
        m.attach(buf.get_mut().unwrap()).unwrap();
        assert_eq!(GateMeta::read(&buf), Some(m.clone()));
        let m2 = GateMeta {
            utility: f64::NAN,
            keep: true,
            reason: Reason::First,
            reference_pts: None,
            screened: false,
            quality: Quality::Dark,
            ..m
        };
        m2.attach(buf.get_mut().unwrap()).unwrap();
        let back = GateMeta::read(&buf).unwrap();
        assert!(back.utility.is_nan());
        assert_eq!(back.reason, Reason::First);
        assert_eq!(back.reference_pts, None);
        assert!(!back.screened);
        assert_eq!(back.quality, Quality::Dark);
        let n = buf.iter_meta::<gst::Meta>().count();
        assert_eq!(n, 1, "overwriting must not stack a second meta");
    }
}
