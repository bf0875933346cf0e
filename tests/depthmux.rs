//! `leangatedepthmux`: depth frames matched to colour frames by time and attached as
//! `LeanGateDepthMeta`, in real pipelines (multifilesrc/pngdec on the shared 7-Scenes frames, appsrc
//! for the timing cases).

mod common;

use std::time::{Duration, Instant};

use gst::prelude::*;
use gstleangate::depth::{DepthFormat, DepthInput};

const MS: u64 = 1_000_000;

fn rgb_caps(w: u32, h: u32, fps: i32) -> gst::Caps {
    common::init();
    gst::Caps::builder("video/x-raw")
        .field("format", "RGB")
        .field("width", w as i32)
        .field("height", h as i32)
        .field("framerate", gst::Fraction::new(fps, 1))
        .build()
}

fn depth_caps(format: &str, w: u32, h: u32, fps: i32) -> gst::Caps {
    common::init();
    gst::Caps::builder("video/x-raw")
        .field("format", format)
        .field("width", w as i32)
        .field("height", h as i32)
        .field("framerate", gst::Fraction::new(fps, 1))
        .build()
}

fn timed(data: Vec<u8>, pts_ns: u64, dur_ns: u64) -> gst::Buffer {
    let mut b = gst::Buffer::from_mut_slice(data);
    {
        let b = b.get_mut().unwrap();
        b.set_pts(gst::ClockTime::from_nseconds(pts_ns));
        b.set_duration(gst::ClockTime::from_nseconds(dur_ns));
    }
    b
}

/// A GRAY16_LE picture of `v` everywhere, rows padded to 4 bytes as GStreamer lays them out.
fn gray16(w: u32, h: u32, v: u16) -> Vec<u8> {
    let stride = (w as usize * 2).div_ceil(4) * 4;
    let mut out = vec![0u8; stride * h as usize];
    for y in 0..h as usize {
        for x in 0..w as usize {
            out[y * stride + 2 * x..][..2].copy_from_slice(&v.to_le_bytes());
        }
    }
    out
}

fn gray32f(w: u32, h: u32, v: f32) -> Vec<u8> {
    (0..w * h).flat_map(|_| v.to_le_bytes()).collect()
}

/// The first depth sample of the meta's depth picture.
fn first_depth_value(d: &DepthInput) -> f64 {
    let map = d.depth.map_readable().unwrap();
    match d.format {
        DepthFormat::Gray16Le => u16::from_le_bytes([map[0], map[1]]) as f64,
        DepthFormat::Gray32F => f32::from_le_bytes([map[0], map[1], map[2], map[3]]) as f64,
    }
}

fn depth_of(b: &gst::BufferRef) -> Option<DepthInput> {
    DepthInput::read(b).map(|r| r.expect("a well-formed LeanGateDepthMeta"))
}

struct Mux {
    pipeline: gst::Pipeline,
    colour: gst_app::AppSrc,
    depth: gst_app::AppSrc,
    out: gst_app::AppSink,
}

/// A failed assertion stops the pipeline too (disposing a playing pipeline is a CRITICAL, which
/// would abort the whole test binary).
impl Drop for Mux {
    fn drop(&mut self) {
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}

/// `appsrc name=colour ! m.sink  appsrc name=depth ! m.depth  leangatedepthmux name=m <props>
/// ! appsink name=out`, playing.
fn mux(props: &str, colour_caps: &gst::Caps, depth_caps: &gst::Caps, live: bool) -> Mux {
    common::init();
    let src = if live {
        "format=time is-live=true do-timestamp=true min-latency=0"
    } else {
        "format=time"
    };
    let desc = format!(
        "appsrc name=colour {src} ! m.sink appsrc name=depth {src} ! m.depth \
         leangatedepthmux name=m {props} ! appsink name=out sync=false"
    );
    let pipeline = gst::parse::launch(&desc)
        .unwrap()
        .downcast::<gst::Pipeline>()
        .unwrap();
    let app = |name: &str| {
        pipeline
            .by_name(name)
            .unwrap()
            .downcast::<gst_app::AppSrc>()
            .unwrap()
    };
    let (colour, depth) = (app("colour"), app("depth"));
    colour.set_caps(Some(colour_caps));
    depth.set_caps(Some(depth_caps));
    let out = pipeline
        .by_name("out")
        .unwrap()
        .downcast::<gst_app::AppSink>()
        .unwrap();
    pipeline.set_state(gst::State::Playing).unwrap();
    Mux {
        pipeline,
        colour,
        depth,
        out,
    }
}

/// [`mux`] with 8x8 RGB colour and 4x4 depth of `depth_format` at `fps`, the intrinsics of an
/// 8x8 camera.
fn small_mux(depth_format: &str, fps: i32, live: bool) -> Mux {
    mux(
        "intrinsics=500,500,3.5,3.5",
        &rgb_caps(8, 8, fps),
        &depth_caps(depth_format, 4, 4, fps),
        live,
    )
}

/// Push frames `frames` of a 25 fps stream (40 ms each): colour textures on `m.colour`, or
/// 4x4 GRAY16_LE depth of value 7 on `m.depth`.
fn push_colour(m: &Mux, frames: std::ops::Range<u64>) {
    for i in frames {
        m.colour
            .push_buffer(timed(common::texture(8, 8, 1), 40 * MS * i, 40 * MS))
            .unwrap();
    }
}

fn push_depth(m: &Mux, frames: std::ops::Range<u64>) {
    for i in frames {
        m.depth
            .push_buffer(timed(gray16(4, 4, 7), 40 * MS * i, 40 * MS))
            .unwrap();
    }
}

/// The run posted exactly one warning, and it says `what`.
fn one_warning(msgs: &[gst::Message], what: &str) {
    let warnings = common::warning_texts(msgs);
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(warnings[0].contains(what), "{warnings:?}");
}

/// Everything the appsink gets until EOS or an error (bounded: a hang fails the test), and the
/// bus messages; the pipeline is then stopped.
fn collect(
    pipeline: &gst::Pipeline,
    out: &gst_app::AppSink,
    timeout: Duration,
) -> (Vec<gst::Sample>, Vec<gst::Message>) {
    let bus = pipeline.bus().unwrap();
    let deadline = Instant::now() + timeout;
    let (mut samples, mut msgs) = (Vec::new(), Vec::new());
    'run: loop {
        assert!(
            Instant::now() < deadline,
            "no EOS in {timeout:?} ({} samples)",
            samples.len()
        );
        while let Some(s) = out.try_pull_sample(gst::ClockTime::from_mseconds(20)) {
            samples.push(s);
        }
        while let Some(m) = bus.pop() {
            let error = matches!(m.view(), gst::MessageView::Error(_));
            msgs.push(m);
            if error {
                break 'run;
            }
        }
        if out.is_eos() {
            break;
        }
    }
    pipeline.set_state(gst::State::Null).unwrap();
    msgs.extend(std::iter::from_fn(|| bus.pop()));
    (samples, msgs)
}

fn pts_ms(s: &gst::Sample) -> u64 {
    s.buffer().unwrap().pts().unwrap().nseconds() / MS
}

/// The CI line: 7-Scenes colour JPEGs and depth PNGs through multifilesrc. pngdec gives 16-bit
/// PNGs as GRAY16_BE (checked here), so a `videoconvert` turns them into the GRAY16_LE the depth
/// pad takes, exactly (every value compared with the PNG decoded by the `image` crate).
#[test]
fn ci_line_on_7scenes_attaches_the_depth_png_of_each_frame() {
    let Some(seq) = common::shared_data("7scenes_redkitchen_dev") else {
        return;
    };
    common::init();
    let rgb = seq.join("rgb/%06d.jpg");
    let depth = seq.join("depth/%06d.png");

    // What pngdec makes of a 16-bit PNG.
    let probe = gst::parse::launch(&format!(
        "multifilesrc location={} num-buffers=1 caps=image/png,framerate=30/1 ! pngdec ! \
         appsink name=out",
        depth.display()
    ))
    .unwrap()
    .downcast::<gst::Pipeline>()
    .unwrap();
    let out = probe
        .by_name("out")
        .unwrap()
        .downcast::<gst_app::AppSink>()
        .unwrap();
    probe.set_state(gst::State::Playing).unwrap();
    let (s, _) = collect(&probe, &out, Duration::from_secs(20));
    let fmt = s[0]
        .caps()
        .unwrap()
        .structure(0)
        .unwrap()
        .get::<String>("format");
    assert!(
        matches!(fmt.as_deref(), Ok("GRAY16_BE") | Ok("GRAY16_LE")),
        "{fmt:?}"
    );

    let desc = format!(
        "multifilesrc location={} caps=image/jpeg,framerate=30/1 ! jpegdec ! videoconvert ! m.sink \
         multifilesrc location={} caps=image/png,framerate=30/1 ! pngdec ! videoconvert ! m.depth \
         leangatedepthmux name=m depth-scale=1000 intrinsics=585,585,320,240 ! appsink name=out \
         sync=false",
        rgb.display(),
        depth.display()
    );
    let pipeline = gst::parse::launch(&desc)
        .unwrap()
        .downcast::<gst::Pipeline>()
        .unwrap();
    let out = pipeline
        .by_name("out")
        .unwrap()
        .downcast::<gst_app::AppSink>()
        .unwrap();
    pipeline.set_state(gst::State::Playing).unwrap();
    let (samples, msgs) = collect(&pipeline, &out, Duration::from_secs(60));
    assert_eq!(common::error_text(&msgs), None);
    assert!(common::warning_texts(&msgs).is_empty(), "{msgs:?}");
    assert_eq!(samples.len(), 60);

    for (i, s) in samples.iter().enumerate() {
        let b = s.buffer().unwrap();
        let pts = b.pts().unwrap().nseconds();
        assert!(
            pts.abs_diff(i as u64 * 1_000_000_000 / 30) <= 1000,
            "frame {i} at {pts}"
        );
        let d = depth_of(b).unwrap_or_else(|| panic!("frame {i} has no depth"));
        assert_eq!(
            d.depth.pts(),
            b.pts(),
            "frame {i}: the depth of the same instant"
        );
        assert_eq!(
            (d.format, d.width, d.height, d.stride),
            (DepthFormat::Gray16Le, 640, 480, 1280)
        );
        assert_eq!(
            (d.scale, d.fx, d.fy, d.cx, d.cy),
            (1000.0, 585.0, 585.0, 320.0, 240.0)
        );
        // The PNG of the same index, decoded here: every 7th pixel of each frame, all of three.
        let png = image::open(seq.join(format!("depth/{i:06}.png")))
            .unwrap()
            .into_luma16();
        assert_eq!(png.dimensions(), (640, 480));
        let map = d.depth.map_readable().unwrap();
        let step = if [0, 29, 59].contains(&i) { 1 } else { 7 };
        let mut nonzero = 0;
        for (k, p) in png.as_raw().iter().enumerate().step_by(step) {
            let got = u16::from_le_bytes([map[2 * k], map[2 * k + 1]]);
            assert_eq!(got, *p, "frame {i} pixel {k}");
            nonzero += (got > 0) as usize;
        }
        assert!(nonzero > 1000, "frame {i}: real depth, not zeros");
    }
}

/// Depth missing for some colour frames, an off-time stray, two candidates for one frame (the
/// nearest wins), two unreadable depth buffers (one warning): every colour frame comes out, in
/// order, unchanged, with the right depth or none.
#[test]
fn gaps_in_depth_leave_those_frames_without_depth() {
    let (w, h) = (8, 8);
    let m = mux(
        "intrinsics=500,500,3.5,3.5 max-skew=10000000",
        &rgb_caps(w, h, 25),
        &depth_caps("GRAY16_LE", 4, 4, 25),
        false,
    );
    let frame = |i: u64| 40 * MS * i;
    let mut depth: Vec<(u64, Vec<u8>)> = Vec::new();
    for i in 0..12u64 {
        match i {
            2 | 5 | 6 => {}
            1 => depth.push((frame(1) - 7 * MS, gray16(4, 4, 2))),
            3 => depth.push((frame(3) + 9 * MS, gray16(4, 4, 4))),
            8 => {
                depth.push((frame(8) - 9 * MS, gray16(4, 4, 100)));
                depth.push((frame(8) + 4 * MS, gray16(4, 4, 9)));
            }
            9 | 10 => depth.push((frame(i), vec![0u8; 5])),
            _ => depth.push((frame(i), gray16(4, 4, i as u16 + 1))),
        }
        if i == 5 {
            // Between colour 5 and 6, more than the skew from both.
            depth.push((frame(5) + 20 * MS, gray16(4, 4, 200)));
        }
    }
    for (pts, data) in depth {
        m.depth.push_buffer(timed(data, pts, 40 * MS)).unwrap();
    }
    m.depth.end_of_stream().unwrap();
    let mut sent = Vec::new();
    for i in 0..12u64 {
        let mut b = timed(common::texture(w, h, i as u32), frame(i), 40 * MS);
        if i % 2 == 1 {
            b.get_mut().unwrap().set_flags(gst::BufferFlags::DELTA_UNIT);
        }
        sent.push(b.clone());
        m.colour.push_buffer(b).unwrap();
    }
    m.colour.end_of_stream().unwrap();
    let (samples, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(20));
    assert_eq!(common::error_text(&msgs), None);
    assert_eq!(samples.len(), 12);
    for (i, (s, sent)) in samples.iter().zip(&sent).enumerate() {
        let b = s.buffer().unwrap();
        assert_eq!(b.pts(), sent.pts(), "in order");
        assert_eq!(b.duration(), sent.duration());
        assert_eq!(b.flags().contains(gst::BufferFlags::DELTA_UNIT), i % 2 == 1);
        assert_eq!(
            b.map_readable().unwrap().as_slice(),
            sent.map_readable().unwrap().as_slice(),
            "frame {i}: the colour passes unchanged"
        );
        let want = match i {
            2 | 5 | 6 | 9 | 10 => None,
            _ => Some(i as f64 + 1.0),
        };
        assert_eq!(
            depth_of(b).as_ref().map(first_depth_value),
            want,
            "frame {i}"
        );
    }
    one_warning(&msgs, "without depth");
}

/// An application that lacks a frame's depth sends a GAP event at its time on the depth pad (as
/// the Python client's `FrameGate` does): that colour frame leaves without depth at once, without
/// waiting for a later depth frame or the depth pad's EOS (the last frame here has none).
#[test]
fn a_gap_event_lets_the_colour_frame_go_without_depth_at_once() {
    let m = small_mux("GRAY16_LE", 25, false);
    let with_depth = |i: u64| (2..6).contains(&i) || (16..19).contains(&i);
    for i in 0..20u64 {
        m.colour
            .push_buffer(timed(common::texture(8, 8, 1), 40 * MS * i, 40 * MS))
            .unwrap();
        if with_depth(i) {
            m.depth
                .push_buffer(timed(gray16(4, 4, i as u16), 40 * MS * i, 40 * MS))
                .unwrap();
        } else {
            let gap = gst::event::Gap::builder(gst::ClockTime::from_nseconds(40 * MS * i)).build();
            assert!(m.depth.send_event(gap));
        }
    }
    // Every frame comes out before either pad ends.
    let mut got = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(20);
    while got.len() < 20 && Instant::now() < deadline {
        if let Some(s) = m.out.try_pull_sample(gst::ClockTime::from_mseconds(20)) {
            let d = depth_of(s.buffer().unwrap())
                .as_ref()
                .map(first_depth_value);
            got.push((pts_ms(&s), d));
        }
    }
    let want: Vec<(u64, Option<f64>)> = (0..20)
        .map(|i| (40 * i, with_depth(i).then_some(i as f64)))
        .collect();
    assert_eq!(got, want);
    m.colour.end_of_stream().unwrap();
    m.depth.end_of_stream().unwrap();
    let (rest, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(20));
    assert_eq!(common::error_text(&msgs), None);
    assert!(rest.is_empty());
}

#[test]
fn depth_ending_first_does_not_stall_colour() {
    let m = small_mux("GRAY16_LE", 25, false);
    push_depth(&m, 0..3);
    m.depth.end_of_stream().unwrap();
    push_colour(&m, 0..10);
    m.colour.end_of_stream().unwrap();
    let (samples, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(20));
    assert_eq!(common::error_text(&msgs), None);
    let got: Vec<(u64, bool)> = samples
        .iter()
        .map(|s| (pts_ms(s), depth_of(s.buffer().unwrap()).is_some()))
        .collect();
    let want: Vec<(u64, bool)> = (0..10).map(|i| (40 * i, i < 3)).collect();
    assert_eq!(got, want);
}

#[test]
fn colour_ending_first_ends_the_output() {
    let m = small_mux("GRAY16_LE", 25, false);
    push_colour(&m, 0..4);
    m.colour.end_of_stream().unwrap();
    // Depth goes on (and never ends).
    push_depth(&m, 0..30);
    let (samples, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(20));
    assert_eq!(common::error_text(&msgs), None);
    assert_eq!(
        samples.iter().map(pts_ms).collect::<Vec<_>>(),
        [0, 40, 80, 120]
    );
    assert!(samples
        .iter()
        .all(|s| depth_of(s.buffer().unwrap()).is_some()));
}

/// Colour buffers without a timestamp cannot be matched: they pass without depth, said once.
#[test]
fn untimed_colour_passes_without_depth() {
    let m = small_mux("GRAY16_LE", 25, false);
    for i in 0..3u64 {
        m.depth
            .push_buffer(timed(gray16(4, 4, 7), 40 * MS * i, 40 * MS))
            .unwrap();
        m.colour
            .push_buffer(gst::Buffer::from_mut_slice(common::texture(8, 8, i as u32)))
            .unwrap();
    }
    m.depth.end_of_stream().unwrap();
    m.colour.end_of_stream().unwrap();
    let (samples, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(20));
    assert_eq!(common::error_text(&msgs), None);
    assert_eq!(samples.len(), 3);
    assert!(samples
        .iter()
        .all(|s| depth_of(s.buffer().unwrap()).is_none()));
    one_warning(&msgs, "without a timestamp");
}

/// Live: a depth source that never delivers does not hold the colour stream (the aggregator's
/// deadline passes each frame on without depth).
#[test]
fn live_colour_flows_when_depth_never_comes() {
    let m = small_mux("GRAY16_LE", 50, true);
    // do-timestamp stamps with the clock: wait until the live sources are playing.
    let deadline = Instant::now() + Duration::from_secs(5);
    while m.colour.current_state() != gst::State::Playing {
        assert!(Instant::now() < deadline, "the live pipeline does not play");
        std::thread::sleep(Duration::from_millis(5));
    }
    for _ in 0..8 {
        let mut b = gst::Buffer::from_mut_slice(common::texture(8, 8, 2));
        b.get_mut()
            .unwrap()
            .set_duration(gst::ClockTime::from_mseconds(20));
        m.colour.push_buffer(b).unwrap();
        std::thread::sleep(Duration::from_millis(20));
    }
    // All eight come out before the colour stream even ends.
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut samples = Vec::new();
    while samples.len() < 8 && Instant::now() < deadline {
        if let Some(s) = m.out.try_pull_sample(gst::ClockTime::from_mseconds(50)) {
            samples.push(s);
        }
    }
    assert_eq!(
        samples.len(),
        8,
        "colour frames held back by a silent depth pad"
    );
    assert!(samples
        .iter()
        .all(|s| depth_of(s.buffer().unwrap()).is_none()));
    m.colour.end_of_stream().unwrap();
    let (rest, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(10));
    assert_eq!(common::error_text(&msgs), None);
    assert!(rest.is_empty());
}

/// A flushing seek goes through to both branches (the aggregator's own handling) and matching
/// starts again from the new position.
#[test]
fn flushing_seek_passes_through() {
    common::init();
    let pipeline = gst::parse::launch(
        "videotestsrc ! video/x-raw,width=8,height=8,framerate=25/1 ! m.sink \
         videotestsrc ! video/x-raw,format=GRAY16_LE,width=4,height=4,framerate=25/1 ! m.depth \
         leangatedepthmux name=m intrinsics=500,500,3.5,3.5 ! appsink name=out sync=false \
         max-buffers=2",
    )
    .unwrap()
    .downcast::<gst::Pipeline>()
    .unwrap();
    struct Stop(gst::Pipeline);
    impl Drop for Stop {
        fn drop(&mut self) {
            let _ = self.0.set_state(gst::State::Null);
        }
    }
    let stop = Stop(pipeline.clone());
    let out = pipeline
        .by_name("out")
        .unwrap()
        .downcast::<gst_app::AppSink>()
        .unwrap();
    pipeline.set_state(gst::State::Playing).unwrap();
    let pull = || {
        out.try_pull_sample(gst::ClockTime::from_seconds(10))
            .expect("a sample in 10 s")
    };
    let before: Vec<u64> = (0..5).map(|_| pts_ms(&pull())).collect();
    assert_eq!(before, [0, 40, 80, 120, 160]);
    pipeline
        .seek_simple(
            gst::SeekFlags::FLUSH | gst::SeekFlags::ACCURATE,
            gst::ClockTime::from_seconds(2),
        )
        .unwrap();
    let mut s = pull();
    let deadline = Instant::now() + Duration::from_secs(10);
    while pts_ms(&s) < 2000 {
        assert!(
            Instant::now() < deadline,
            "no frame from the seek's position"
        );
        s = pull();
    }
    let mut after = vec![pts_ms(&s)];
    assert!(depth_of(s.buffer().unwrap()).is_some());
    for _ in 0..4 {
        let s = pull();
        assert!(depth_of(s.buffer().unwrap()).is_some());
        after.push(pts_ms(&s));
    }
    assert_eq!(after, [2000, 2040, 2080, 2120, 2160]);
    drop(stop);
}

const TEST_SRCS: &str = "videotestsrc num-buffers=2 ! video/x-raw,width=8,height=8 ! m.sink \
     videotestsrc num-buffers=2 ! video/x-raw,format=GRAY16_LE,width=8,height=8 ! m.depth";

#[test]
fn start_needs_intrinsics_and_a_valid_depth_scale() {
    common::init();
    let run = |props: &str| {
        let msgs = common::run_pipeline(
            &format!("{TEST_SRCS} leangatedepthmux name=m {props} ! fakesink"),
            20,
        );
        common::error_text(&msgs)
    };
    let e = run("").expect("no intrinsics: an error");
    assert!(e.contains("intrinsics"), "{e}");
    let e = run("intrinsics=585,abc,320,240").expect("bad intrinsics: an error");
    assert!(e.contains("585,abc,320,240"), "{e}");
    let e = run("intrinsics=-585,585,320,240").expect("negative focal length: an error");
    assert!(e.contains("-585,585,320,240"), "{e}");
    // (NaN never reaches the element: GLib refuses it for any double property, with a warning.)
    for scale in ["0", "-1000", "inf", "-inf"] {
        let e = run(&format!("intrinsics=585,585,320,240 depth-scale={scale}"))
            .unwrap_or_else(|| panic!("depth-scale={scale}: an error"));
        assert!(e.contains("depth-scale"), "{e}");
    }
    assert_eq!(run("intrinsics=585,585,320,240 depth-scale=5000"), None);

    // Refused in place: the property keeps its value, until a valid one clears the refusal.
    let e = gst::ElementFactory::make("leangatedepthmux")
        .build()
        .unwrap();
    e.set_property("depth-scale", 0.0f64);
    assert_eq!(e.property::<f64>("depth-scale"), 1000.0);
    e.set_property("depth-scale", f64::INFINITY);
    assert_eq!(e.property::<f64>("depth-scale"), 1000.0);
    e.set_property("depth-scale", 5000.0f64);
    assert_eq!(e.property::<f64>("depth-scale"), 5000.0);
}

/// A depth format outside the template is refused at negotiation: an error, not a hang.
#[test]
fn depth_format_outside_the_template_is_refused() {
    let m = small_mux("GRAY8", 25, false);
    m.depth
        .push_buffer(timed(vec![0u8; 16], 0, 40 * MS))
        .unwrap();
    m.colour
        .push_buffer(timed(common::texture(8, 8, 1), 0, 40 * MS))
        .unwrap();
    m.colour.end_of_stream().unwrap();
    m.depth.end_of_stream().unwrap();
    let (_, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(20));
    let e = common::error_text(&msgs).expect("GRAY8 depth: an error");
    assert!(e.contains("negotiat"), "{e}");
}

/// Caps changes on both pads: the depth size and format follow the depth caps, the src caps the
/// colour caps.
#[test]
fn caps_changes_are_followed() {
    let m = mux(
        "intrinsics=500,500,3.5,3.5 depth-scale=5000",
        &rgb_caps(8, 8, 25),
        &depth_caps("GRAY16_LE", 4, 4, 25),
        false,
    );
    let push = |src: &gst_app::AppSrc, caps: gst::Caps, data: Vec<u8>, i: u64| {
        let sample = gst::Sample::builder()
            .buffer(&timed(data, 40 * MS * i, 40 * MS))
            .caps(&caps)
            .build();
        src.push_sample(&sample).unwrap();
    };
    for i in 0..8u64 {
        let (caps, data) = match i {
            0..3 => (depth_caps("GRAY16_LE", 4, 4, 25), gray16(4, 4, 1)),
            3..6 => (depth_caps("GRAY16_LE", 8, 6, 25), gray16(8, 6, 2)),
            _ => (depth_caps("GRAY32F", 2, 2, 25), gray32f(2, 2, 1.5)),
        };
        push(&m.depth, caps, data, i);
    }
    m.depth.end_of_stream().unwrap();
    for i in 0..8u64 {
        let side = if i < 5 { 8 } else { 16 };
        push(
            &m.colour,
            rgb_caps(side, side, 25),
            common::texture(side, side, i as u32),
            i,
        );
    }
    m.colour.end_of_stream().unwrap();
    let (samples, msgs) = collect(&m.pipeline, &m.out, Duration::from_secs(20));
    assert_eq!(common::error_text(&msgs), None);
    assert_eq!(samples.len(), 8);
    for (i, s) in samples.iter().enumerate() {
        let width = s.caps().unwrap().structure(0).unwrap().get::<i32>("width");
        assert_eq!(width, Ok(if i < 5 { 8 } else { 16 }), "frame {i}");
        let d = depth_of(s.buffer().unwrap()).unwrap();
        let got = (
            d.format,
            d.width,
            d.height,
            d.stride,
            d.scale,
            first_depth_value(&d),
        );
        let want = match i {
            0..3 => (DepthFormat::Gray16Le, 4, 4, 8, 5000.0, 1.0),
            3..6 => (DepthFormat::Gray16Le, 8, 6, 16, 5000.0, 2.0),
            _ => (DepthFormat::Gray32F, 2, 2, 8, 1.0, 1.5),
        };
        assert_eq!(got, want, "frame {i}");
    }
}

/// Every property has a blurb, in the element and in `gst-inspect-1.0`.
#[test]
fn gst_inspect_documents_every_property() {
    common::init();
    let e = gst::ElementFactory::make("leangatedepthmux")
        .build()
        .unwrap();
    let ours = ["depth-scale", "intrinsics", "max-skew"];
    for p in ours {
        let spec = e.find_property(p).unwrap_or_else(|| panic!("no {p}"));
        assert!(spec.blurb().is_some_and(|b| b.len() > 40), "{p}");
    }
    // The cdylib built with this test binary (target/<profile>/deps), alone in a folder.
    let exe = std::env::current_exe().unwrap();
    let deps = exe.parent().unwrap();
    let lib = [deps.to_path_buf(), deps.parent().unwrap().to_path_buf()]
        .iter()
        .map(|d| d.join("libgstleangate.so"))
        .find(|p| p.exists())
        .expect("libgstleangate.so built beside the tests");
    let plugins = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink(&lib, plugins.path().join("libgstleangate.so")).unwrap();
    let out = std::process::Command::new("gst-inspect-1.0")
        .arg("leangatedepthmux")
        .env("GST_PLUGIN_PATH", plugins.path())
        .env("GST_REGISTRY", plugins.path().join("registry.bin"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for (p, says) in [
        ("depth-scale", "units per metre"),
        ("intrinsics", "fx,fy,cx,cy"),
        ("max-skew", "running times"),
    ] {
        assert!(text.contains(&format!("  {p} ")), "{p} not in gst-inspect");
        assert!(text.contains(says), "{says} not in gst-inspect");
    }
}
