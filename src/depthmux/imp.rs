//! `leangatedepthmux`: a `GstAggregator` that matches depth frames to colour frames by running time
//! and attaches each match to its colour buffer as a `LeanGateDepthMeta` ([`crate::depth`]).
//!
//! The matching rule, for each colour buffer at running time `c` (`skew` = `max-skew`, or half the
//! colour frame interval):
//! - depth frames before `c - skew` can match no colour frame from here on: dropped;
//! - the depth frame nearest to `c` within `[c - skew, c + skew]` is attached and used up (a depth
//!   frame serves one colour frame); a later depth frame is waited for only while the one in hand
//!   lies before `c` (a later one might be nearer);
//! - when the next depth frame is after `c + skew`, the depth pad is at EOS, a GAP event on the
//!   depth pad at or after `c` says there is none, or (live) the aggregator's deadline for the
//!   colour frame passed, the colour buffer leaves without depth.
//!
//! The colour buffer is otherwise untouched (same memory, timestamps, flags: made writable only to
//! add the meta). The stream ends when the colour pad ends. No message is posted with the state
//! lock held.

use std::sync::{LazyLock, Mutex, MutexGuard};

use gst::glib;
use gst::prelude::*;
use gst::subclass::prelude::*;
use gst_base::prelude::*;
use gst_base::subclass::prelude::*;
use gst_base::AGGREGATOR_FLOW_NEED_DATA;

use crate::depth::{DepthFormat, DepthInput};

static CAT: LazyLock<gst::DebugCategory> = LazyLock::new(|| {
    gst::DebugCategory::new(
        "leangatedepthmux",
        gst::DebugColorFlags::empty(),
        Some("LeanGate depth muxer"),
    )
});

const DEFAULT_DEPTH_SCALE: f64 = 1000.0;
/// The skew when `max-skew` is 0 and the colour caps give no frame rate (or a variable one): half
/// a frame at 30 fps.
const FALLBACK_SKEW_NS: u64 = 16_666_666;
/// The largest `max-skew` (1 s): it is also latency the element adds in a live pipeline.
const MAX_SKEW_LIMIT_NS: u64 = 1_000_000_000;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

#[derive(Debug, Clone)]
struct Settings {
    depth_scale: f64,
    /// The last `depth-scale` refused (not finite or <= 0): the element does not start until a
    /// valid one is set.
    refused_scale: Option<f64>,
    intrinsics: Option<String>,
    max_skew: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            depth_scale: DEFAULT_DEPTH_SCALE,
            refused_scale: None,
            intrinsics: None,
            max_skew: 0,
        }
    }
}

/// `"fx,fy,cx,cy"` (focal lengths > 0, every number finite).
fn parse_intrinsics(text: &str) -> Result<[f64; 4], String> {
    let bad = || {
        format!(
            "intrinsics \"{text}\" are not \"fx,fy,cx,cy\" (four finite numbers, the colour \
             frames' focal lengths > 0 and principal point in their own pixels, e.g. \
             585,585,320,240)"
        )
    };
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| bad())?;
    match v[..] {
        [fx, fy, cx, cy] if v.iter().all(|x| x.is_finite()) && fx > 0.0 && fy > 0.0 => {
            Ok([fx, fy, cx, cy])
        }
        _ => Err(bad()),
    }
}

/// Half the frame interval of `caps`' frame rate, if it has a fixed positive one.
fn half_interval_ns(caps: &gst::CapsRef) -> Option<u64> {
    let fps = caps.structure(0)?.get::<gst::Fraction>("framerate").ok()?;
    let (n, d) = (fps.numer(), fps.denom());
    if n <= 0 || d <= 0 {
        return None;
    }
    let ns = (d as u128 * 1_000_000_000) / (2 * n as u128);
    (ns > 0).then(|| ns.min(u64::MAX as u128) as u64)
}

/// How the depth frames of the current depth caps lie in memory.
#[derive(Debug, Clone, Copy, PartialEq)]
struct DepthLayout {
    format: DepthFormat,
    width: u32,
    height: u32,
    /// Bytes per row without a `GstVideoMeta` (GStreamer's default: rows padded to 4 bytes).
    stride: u32,
}

impl DepthLayout {
    fn from_caps(caps: &gst::CapsRef) -> Result<DepthLayout, String> {
        let s = caps
            .structure(0)
            .ok_or_else(|| "empty depth caps".to_string())?;
        let format = s
            .get::<&str>("format")
            .ok()
            .and_then(DepthFormat::parse)
            .ok_or_else(|| format!("depth caps {caps} are not GRAY16_LE or GRAY32F"))?;
        let dim = |name: &str| {
            s.get::<i32>(name)
                .ok()
                .filter(|&x| x > 0)
                .map(|x| x as u32)
                .ok_or_else(|| format!("depth caps {caps} have no {name}"))
        };
        let (width, height) = (dim("width")?, dim("height")?);
        let row = width as u64 * format.bytes() as u64;
        let stride = u32::try_from((row + 3) & !3)
            .map_err(|_| format!("depth caps {caps}: rows of {row} bytes are too long"))?;
        Ok(DepthLayout {
            format,
            width,
            height,
            stride,
        })
    }
}

/// A depth frame taken off the depth pad, waiting for its colour frame.
struct Held {
    /// Running time (ns) in the depth pad's segment.
    rt: u64,
    buffer: gst::Buffer,
    /// The depth caps it came with (None: it came before any, which negotiation prevents).
    layout: Option<DepthLayout>,
}

struct State {
    camera: [f64; 4],
    scale: f64,
    /// `max-skew` as set at start (0 = from the colour frame rate).
    max_skew: u64,
    /// The skew in use (ns).
    skew: u64,
    depth_layout: Option<DepthLayout>,
    held: Option<Held>,
    warned_unreadable: bool,
    warned_untimed_colour: bool,
    warned_untimed_depth: bool,
    matched: u64,
    unmatched: u64,
}

impl Default for State {
    fn default() -> Self {
        State {
            camera: [0.0; 4],
            scale: DEFAULT_DEPTH_SCALE,
            max_skew: 0,
            skew: FALLBACK_SKEW_NS,
            depth_layout: None,
            held: None,
            warned_unreadable: false,
            warned_untimed_colour: false,
            warned_untimed_depth: false,
            matched: 0,
            unmatched: 0,
        }
    }
}

/// What a colour frame gets.
enum Match {
    /// Wait for the next depth frame (or the depth pad's EOS, or the live deadline).
    NeedData,
    Without,
    With(Held),
}

/// A gap filler the aggregator makes of a GAP event: no frame.
fn is_gap(b: &gst::BufferRef) -> bool {
    b.flags().contains(gst::BufferFlags::GAP) && b.size() == 0
}

/// The buffer's running time (ns) in `pad`'s segment: its PTS (else DTS), None when it has none
/// or lies outside the segment.
fn running_time_ns(pad: &gst_base::AggregatorPad, b: &gst::BufferRef) -> Option<u64> {
    let ts = b.pts().or_else(|| b.dts())?;
    let segment = pad.segment();
    let segment = segment.downcast_ref::<gst::ClockTime>()?;
    segment.to_running_time(ts).map(|t| t.nseconds())
}

pub struct DepthMux {
    colour_pad: gst_base::AggregatorPad,
    depth_pad: gst_base::AggregatorPad,
    settings: Mutex<Settings>,
    state: Mutex<State>,
}

#[glib::object_subclass]
impl ObjectSubclass for DepthMux {
    const NAME: &'static str = "GstLeanGateDepthMux";
    type Type = super::DepthMux;
    type ParentType = gst_base::Aggregator;

    fn with_class(klass: &Self::Class) -> Self {
        let pad = |name: &str| {
            let templ = klass.pad_template(name).expect("pad template");
            gst::PadBuilder::<gst_base::AggregatorPad>::from_template(&templ).build()
        };
        DepthMux {
            colour_pad: pad("sink"),
            depth_pad: pad("depth"),
            settings: Mutex::default(),
            state: Mutex::default(),
        }
    }
}

impl ObjectImpl for DepthMux {
    fn constructed(&self) {
        self.parent_constructed();
        let obj = self.obj();
        obj.add_pad(&self.colour_pad).unwrap();
        obj.add_pad(&self.depth_pad).unwrap();
    }

    fn properties() -> &'static [glib::ParamSpec] {
        static PROPERTIES: LazyLock<Vec<glib::ParamSpec>> = LazyLock::new(|| {
            vec![
                // The full range, so that 0, negative, infinite and NaN values reach the setter,
                // which refuses them with a message rather than GLib clamping them.
                glib::ParamSpecDouble::builder("depth-scale")
                    .nick("Depth scale")
                    .blurb(
                        "GRAY16_LE depth units per metre: 1000 = millimetres (RealSense, Kinect, \
                         Azure Kinect, Orbbec), 5000 = TUM RGB-D. Must be finite and above 0: \
                         another value is refused and the element does not start. Ignored for \
                         GRAY32F depth (metres)",
                    )
                    .minimum(f64::NEG_INFINITY)
                    .maximum(f64::INFINITY)
                    .default_value(DEFAULT_DEPTH_SCALE)
                    .mutable_ready()
                    .build(),
                glib::ParamSpecString::builder("intrinsics")
                    .nick("Colour intrinsics")
                    .blurb(
                        "Required: the colour frames' pinhole intrinsics \"fx,fy,cx,cy\" in \
                         their own pixels (pixel centres at integers), e.g. 585,585,320,240 for \
                         7-Scenes; the element does not start without them or with a value that \
                         is not four numbers with fx, fy > 0",
                    )
                    .mutable_ready()
                    .build(),
                glib::ParamSpecUInt64::builder("max-skew")
                    .nick("Maximum skew")
                    .blurb(
                        "Nanoseconds: a depth frame is matched to a colour frame when their \
                         running times differ by at most this (the nearest one; each depth frame \
                         serves one colour frame; a colour frame with none passes without depth). \
                         0 = half the colour frame interval from the colour caps' framerate \
                         (16.67 ms when unknown or variable). Also the latency the element adds \
                         in a live pipeline",
                    )
                    .maximum(MAX_SKEW_LIMIT_NS)
                    .default_value(0)
                    .mutable_ready()
                    .build(),
            ]
        });
        PROPERTIES.as_ref()
    }

    fn set_property(&self, _id: usize, value: &glib::Value, pspec: &glib::ParamSpec) {
        let mut s = lock(&self.settings);
        match pspec.name() {
            "depth-scale" => {
                let v: f64 = value.get().expect("type checked upstream");
                if v.is_finite() && v > 0.0 {
                    s.depth_scale = v;
                    s.refused_scale = None;
                } else {
                    s.refused_scale = Some(v);
                    drop(s);
                    gst::error!(
                        CAT,
                        imp = self,
                        "depth-scale {v} refused: depth units per metre must be finite and above 0"
                    );
                }
            }
            "intrinsics" => {
                let v: Option<String> = value.get().expect("type checked upstream");
                s.intrinsics = v.clone();
                drop(s);
                if let Some(Err(e)) = v.as_deref().map(parse_intrinsics) {
                    gst::error!(CAT, imp = self, "{e}");
                }
            }
            "max-skew" => s.max_skew = value.get().expect("type checked upstream"),
            _ => unreachable!("no property {}", pspec.name()),
        }
    }

    fn property(&self, _id: usize, pspec: &glib::ParamSpec) -> glib::Value {
        let s = lock(&self.settings);
        match pspec.name() {
            "depth-scale" => s.depth_scale.to_value(),
            "intrinsics" => s.intrinsics.to_value(),
            "max-skew" => s.max_skew.to_value(),
            _ => unreachable!("no property {}", pspec.name()),
        }
    }
}

impl GstObjectImpl for DepthMux {}

impl ElementImpl for DepthMux {
    fn metadata() -> Option<&'static gst::subclass::ElementMetadata> {
        static METADATA: LazyLock<gst::subclass::ElementMetadata> = LazyLock::new(|| {
            gst::subclass::ElementMetadata::new(
                "LeanGate depth muxer",
                "Video/Combiner",
                "Attaches the depth frame (GRAY16_LE or GRAY32F) nearest in time to each colour \
                 frame as LeanGateDepthMeta, for leangate to gate with depth; the colour stream \
                 passes otherwise unchanged",
                "LeanGate developers",
            )
        });
        Some(&*METADATA)
    }

    fn pad_templates() -> &'static [gst::PadTemplate] {
        static TEMPLATES: LazyLock<Vec<gst::PadTemplate>> = LazyLock::new(|| {
            let colour = gst::Caps::builder("video/x-raw").build();
            let depth = gst::Caps::builder("video/x-raw")
                .field(
                    "format",
                    gst::List::new([
                        DepthFormat::Gray16Le.as_str(),
                        DepthFormat::Gray32F.as_str(),
                    ]),
                )
                .field("width", gst::IntRange::new(1, i32::MAX))
                .field("height", gst::IntRange::new(1, i32::MAX))
                .field(
                    "framerate",
                    gst::FractionRange::new(
                        gst::Fraction::new(0, 1),
                        gst::Fraction::new(i32::MAX, 1),
                    ),
                )
                .build();
            let sink = |name: &str, caps: &gst::Caps| {
                gst::PadTemplate::with_gtype(
                    name,
                    gst::PadDirection::Sink,
                    gst::PadPresence::Always,
                    caps,
                    gst_base::AggregatorPad::static_type(),
                )
                .unwrap()
            };
            vec![
                sink("sink", &colour),
                sink("depth", &depth),
                gst::PadTemplate::with_gtype(
                    "src",
                    gst::PadDirection::Src,
                    gst::PadPresence::Always,
                    &colour,
                    gst_base::AggregatorPad::static_type(),
                )
                .unwrap(),
            ]
        });
        TEMPLATES.as_ref()
    }
}

impl DepthMux {
    fn template_caps(&self, name: &str) -> gst::Caps {
        self.obj()
            .class()
            .pad_template(name)
            .map(|t| t.caps().clone())
            .unwrap_or_else(gst::Caps::new_any)
    }

    /// What the colour pad takes: what downstream takes, within the template.
    fn colour_caps(&self, filter: Option<&gst::Caps>) -> gst::Caps {
        let templ = self.template_caps("sink");
        let filter = filter.map_or_else(
            || templ.clone(),
            |f| f.intersect_with_mode(&templ, gst::CapsIntersectMode::First),
        );
        self.obj()
            .src_pad()
            .peer_query_caps(Some(&filter))
            .intersect_with_mode(&templ, gst::CapsIntersectMode::First)
    }

    fn on_colour_caps(&self, caps: &gst::Caps) {
        let fps_skew = half_interval_ns(caps);
        let (changed, skew) = {
            let mut st = lock(&self.state);
            let skew = if st.max_skew > 0 {
                st.max_skew
            } else {
                fps_skew.unwrap_or(FALLBACK_SKEW_NS)
            };
            let changed = st.skew != skew;
            st.skew = skew;
            (changed, skew)
        };
        gst::debug!(CAT, imp = self, "colour caps {caps}: skew {skew} ns");
        if changed {
            // Posts a latency message: no lock held here.
            let t = gst::ClockTime::from_nseconds(skew);
            self.obj().set_latency(t, Some(t));
        }
        self.obj().set_src_caps(caps);
    }

    fn on_depth_caps(&self, caps: &gst::Caps) -> bool {
        match DepthLayout::from_caps(caps) {
            Ok(layout) => {
                gst::debug!(CAT, imp = self, "depth {layout:?}");
                lock(&self.state).depth_layout = Some(layout);
                true
            }
            Err(e) => {
                gst::element_imp_error!(self, gst::CoreError::Negotiation, ("{}", e));
                false
            }
        }
    }

    /// The depth frame for the colour frame at running time `c` (see the module's rule). Pops
    /// depth buffers; `warn` collects the warnings to post once the state lock is released.
    fn match_depth(&self, st: &mut State, c: u64, timeout: bool, warn: &mut Vec<String>) -> Match {
        let skew = st.skew;
        let no_more = |pad: &gst_base::AggregatorPad| pad.is_eos() || timeout;
        loop {
            if st.held.is_none() {
                let Some(b) = self.depth_pad.pop_buffer() else {
                    return if no_more(&self.depth_pad) {
                        Match::Without
                    } else {
                        Match::NeedData
                    };
                };
                if is_gap(&b) {
                    // A gap at or after the colour frame: the depth stream says it has nothing
                    // for it (an appsrc that lacks this frame's depth sends one).
                    if running_time_ns(&self.depth_pad, &b).is_some_and(|g| g >= c) {
                        return Match::Without;
                    }
                    continue;
                }
                match running_time_ns(&self.depth_pad, &b) {
                    Some(rt) => {
                        st.held = Some(Held {
                            rt,
                            buffer: b,
                            layout: st.depth_layout,
                        })
                    }
                    None => {
                        Self::untimed_depth(st, warn);
                        continue;
                    }
                }
            }
            let d = st.held.as_ref().map_or(0, |h| h.rt);
            if d.saturating_add(skew) < c {
                gst::trace!(
                    CAT,
                    imp = self,
                    "depth at {d} too old for colour at {c}: dropped"
                );
                st.held = None;
                continue;
            }
            if d > c.saturating_add(skew) {
                return Match::Without;
            }
            if d >= c {
                return st.held.take().map_or(Match::Without, Match::With);
            }
            // Within the skew but before the colour frame: the next depth frame may be nearer.
            match self.depth_pad.peek_buffer() {
                Some(n) if is_gap(&n) => {
                    self.depth_pad.drop_buffer();
                }
                Some(n) => match running_time_ns(&self.depth_pad, &n) {
                    Some(next) if next.abs_diff(c) < c - d => st.held = None,
                    Some(_) => return st.held.take().map_or(Match::Without, Match::With),
                    None => {
                        self.depth_pad.drop_buffer();
                        Self::untimed_depth(st, warn);
                    }
                },
                None if no_more(&self.depth_pad) => {
                    return st.held.take().map_or(Match::Without, Match::With)
                }
                None => return Match::NeedData,
            }
        }
    }

    fn untimed_depth(st: &mut State, warn: &mut Vec<String>) {
        if !std::mem::replace(&mut st.warned_untimed_depth, true) {
            warn.push(
                "depth buffers without a timestamp (or outside their segment) cannot be \
                 matched to colour frames: dropped (said once)"
                    .into(),
            );
        }
    }

    /// The meta for `held`, or why it cannot be read.
    fn depth_input(held: Held, scale: f64, camera: [f64; 4]) -> Result<DepthInput, String> {
        let layout = held
            .layout
            .ok_or_else(|| "a depth buffer came before the depth caps".to_string())?;
        let mut buffer = held.buffer;
        let mut stride = layout.stride;
        let video_meta = buffer
            .meta::<gst_video::VideoMeta>()
            .map(|m| (m.offset()[0], m.stride()[0]));
        if let Some((offset, meta_stride)) = video_meta {
            stride = u32::try_from(meta_stride)
                .map_err(|_| format!("depth rows of stride {meta_stride} (bottom-up or none)"))?;
            if offset > 0 {
                buffer = buffer
                    .copy_region(gst::BufferCopyFlags::MEMORY, offset..)
                    .map_err(|_| format!("depth buffer shorter than its plane offset {offset}"))?;
            }
        }
        crate::depth::check_layout(
            layout.format,
            layout.width,
            layout.height,
            stride,
            buffer.size(),
        )?;
        if buffer.map_readable().is_err() {
            return Err("the depth buffer cannot be mapped for reading".into());
        }
        let [fx, fy, cx, cy] = camera;
        Ok(DepthInput {
            depth: buffer,
            format: layout.format,
            width: layout.width,
            height: layout.height,
            stride,
            scale: match layout.format {
                DepthFormat::Gray16Le => scale,
                DepthFormat::Gray32F => 1.0,
            },
            fx,
            fy,
            cx,
            cy,
        })
    }
}

impl AggregatorImpl for DepthMux {
    fn start(&self) -> Result<(), gst::ErrorMessage> {
        let s = lock(&self.settings).clone();
        if let Some(v) = s.refused_scale {
            return Err(gst::error_msg!(
                gst::LibraryError::Settings,
                (
                    "depth-scale {} was refused: depth units per metre must be finite and above \
                     0 (1000 for millimetres, 5000 for TUM)",
                    v
                )
            ));
        }
        let text = s.intrinsics.ok_or_else(|| {
            gst::error_msg!(
                gst::LibraryError::Settings,
                ("the `intrinsics` property is required: the colour frames' pinhole \
                     intrinsics \"fx,fy,cx,cy\" in their own pixels, e.g. \
                     intrinsics=585,585,320,240")
            )
        })?;
        let camera = parse_intrinsics(&text)
            .map_err(|e| gst::error_msg!(gst::LibraryError::Settings, ("{}", e)))?;
        let skew = if s.max_skew > 0 {
            s.max_skew
        } else {
            FALLBACK_SKEW_NS
        };
        *lock(&self.state) = State {
            camera,
            scale: s.depth_scale,
            max_skew: s.max_skew,
            skew,
            ..State::default()
        };
        let t = gst::ClockTime::from_nseconds(skew);
        self.obj().set_latency(t, Some(t));
        gst::debug!(
            CAT,
            imp = self,
            "started: intrinsics {camera:?}, depth-scale {}, skew {skew} ns",
            s.depth_scale
        );
        Ok(())
    }

    fn stop(&self) -> Result<(), gst::ErrorMessage> {
        let st = std::mem::take(&mut *lock(&self.state));
        gst::debug!(
            CAT,
            imp = self,
            "stopped: {} colour frames with depth, {} without",
            st.matched,
            st.unmatched
        );
        Ok(())
    }

    fn flush(&self) -> Result<gst::FlowSuccess, gst::FlowError> {
        lock(&self.state).held = None;
        self.parent_flush()
    }

    fn negotiate(&self) -> bool {
        // The src caps are the colour caps as they come (set in sink_event), nothing to choose.
        true
    }

    fn next_time(&self) -> Option<gst::ClockTime> {
        // Live: the colour frame at the head waits for its depth until its own running time (plus
        // the latency: upstream's, the `latency` property's and the skew).
        let Some(b) = self.colour_pad.peek_buffer() else {
            // The colour stream ended: end at once, whatever the depth pad does.
            return self.colour_pad.is_eos().then_some(gst::ClockTime::ZERO);
        };
        Some(
            running_time_ns(&self.colour_pad, &b)
                .map_or(gst::ClockTime::ZERO, gst::ClockTime::from_nseconds),
        )
    }

    fn sink_event(&self, pad: &gst_base::AggregatorPad, event: gst::Event) -> bool {
        match event.view() {
            gst::EventView::Caps(e) => {
                let caps = e.caps_owned();
                if pad == &self.colour_pad {
                    self.on_colour_caps(&caps);
                    true
                } else {
                    self.on_depth_caps(&caps)
                }
            }
            gst::EventView::Segment(e) => {
                if pad == &self.colour_pad {
                    self.obj().update_segment(e.segment());
                }
                self.parent_sink_event(pad, event)
            }
            _ => self.parent_sink_event(pad, event),
        }
    }

    fn sink_query(&self, pad: &gst_base::AggregatorPad, query: &mut gst::QueryRef) -> bool {
        if pad != &self.colour_pad {
            return self.parent_sink_query(pad, query);
        }
        match query.view_mut() {
            gst::QueryViewMut::Caps(q) => {
                let caps = self.colour_caps(q.filter_owned().as_ref());
                q.set_result(&caps);
                true
            }
            gst::QueryViewMut::AcceptCaps(q) => {
                let ok = q.caps().is_subset(&self.colour_caps(None));
                q.set_result(ok);
                true
            }
            // The colour buffers go downstream as they are: downstream's pools and metas apply.
            gst::QueryViewMut::Allocation(_) => self.obj().src_pad().peer_query(query),
            _ => self.parent_sink_query(pad, query),
        }
    }

    fn src_query(&self, query: &mut gst::QueryRef) -> bool {
        match query.view_mut() {
            gst::QueryViewMut::Caps(q) => {
                let templ = self.template_caps("src");
                let caps = self
                    .colour_pad
                    .peer_query_caps(q.filter_owned().as_ref())
                    .intersect_with_mode(&templ, gst::CapsIntersectMode::First);
                q.set_result(&caps);
                true
            }
            _ => self.parent_src_query(query),
        }
    }

    fn aggregate(&self, timeout: bool) -> Result<gst::FlowSuccess, gst::FlowError> {
        let Some(colour) = self.colour_pad.peek_buffer() else {
            // The stream ends with the colour stream, whatever the depth pad does.
            return if self.colour_pad.is_eos() {
                gst::debug!(CAT, imp = self, "colour at EOS: EOS");
                Err(gst::FlowError::Eos)
            } else {
                Err(AGGREGATOR_FLOW_NEED_DATA)
            };
        };
        if is_gap(&colour) {
            self.colour_pad.drop_buffer();
            return Ok(gst::FlowSuccess::Ok);
        }
        let c = running_time_ns(&self.colour_pad, &colour);
        drop(colour);

        let mut warnings = Vec::new();
        let input = {
            let mut st = lock(&self.state);
            let found = match c {
                Some(c) => self.match_depth(&mut st, c, timeout, &mut warnings),
                None => {
                    if !std::mem::replace(&mut st.warned_untimed_colour, true) {
                        warnings.push(
                            "colour buffers without a timestamp (or outside their segment) \
                             cannot be matched to depth: passed without depth"
                                .into(),
                        );
                    }
                    Match::Without
                }
            };
            match found {
                Match::NeedData => None,
                Match::Without => Some(None),
                Match::With(held) => match Self::depth_input(held, st.scale, st.camera) {
                    Ok(input) => Some(Some(input)),
                    Err(e) => {
                        if !std::mem::replace(&mut st.warned_unreadable, true) {
                            warnings.push(format!(
                                "{e}: the colour frame passes without depth (said once)"
                            ));
                        }
                        Some(None)
                    }
                },
            }
        };
        // No lock held from here on.
        for w in &warnings {
            gst::element_imp_warning!(self, gst::StreamError::Format, ("{}", w));
        }
        let Some(input) = input else {
            return Err(AGGREGATOR_FLOW_NEED_DATA);
        };

        let Some(mut buffer) = self.colour_pad.pop_buffer() else {
            return Err(AGGREGATOR_FLOW_NEED_DATA);
        };
        let with_depth = match input {
            Some(input) => match input.attach(buffer.make_mut()) {
                Ok(()) => true,
                Err(e) => {
                    gst::element_imp_warning!(
                        self,
                        gst::StreamError::Failed,
                        ("could not attach the depth meta: {}", e)
                    );
                    false
                }
            },
            None => false,
        };
        {
            let mut st = lock(&self.state);
            if with_depth {
                st.matched += 1;
            } else {
                st.unmatched += 1;
            }
        }
        gst::log!(
            CAT,
            imp = self,
            "colour {:?} {} depth",
            buffer.pts(),
            if with_depth { "with" } else { "without" }
        );

        let obj = self.obj();
        if obj.src_pad().segment().format() == gst::Format::Time {
            if let Some(end) = buffer
                .pts()
                .map(|p| p + buffer.duration().unwrap_or_default())
            {
                obj.set_position(end);
            }
        }
        obj.finish_buffer(buffer)
    }
}
