//! Issue 8 (reliability): one test per defect (each failed before its fix), and the reliability
//! suite that stays in CI: concurrent pipelines identical to solo runs, property and event storms
//! during streaming, randomised frame layouts against the tightly packed result (proptest), and
//! flush-seek storms.

mod common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use common::pack::{pack_rgb, raw_frame};
use common::*;
use gst::prelude::*;
use gstleangate::{PixelFormat, Preprocessor, Reason, ResizeMode, TensorSpec, YuvMatrix};
use proptest::prelude::*;

const W: u32 = 64;
const H: u32 = 48;

// ---------------------------------------------------------------------------------------------
// D3, D5, D6, D8: models refused at start (or, with external data, accepted)

#[test]
fn broken_models_are_refused_at_start_naming_model_and_problem() {
    let cases: &[(&str, &[&str])] = &[
        // D3: would abort the process allocating 120 GB.
        ("huge_input.onnx", &["100000x100000", "too large"]),
        // D5
        ("batch2.onnx", &["batch dimension of 2"]),
        ("h_fixed.onnx", &["only one side", "leangate.input_size"]),
        // A fixed side of 0 was read as a dynamic one (a hostile probe).
        ("h_zero.onnx", &["fixes its input's H to 0"]),
        (
            "split_mismatch_encoder.onnx",
            &["split_head_8.onnx", "dry run"],
        ),
        ("mean_nan.onnx", &["leangate.mean", "finite"]),
        ("mean_inf.onnx", &["leangate.mean", "finite"]),
        ("std_tiny.onnx", &["leangate.std", "magnitude"]),
        ("threshold_5.onnx", &["leangate.threshold = 5", "[0, 1]"]),
        ("threshold_neg.onnx", &["leangate.threshold = -3", "[0, 1]"]),
        (
            "geometry_bad.onnx",
            &["leangate.geometry", "four finite numbers"],
        ),
        (
            "score_max_bad.onnx",
            &["leangate.score_max = 1.5", "(0, 1]"],
        ),
        (
            "score_step_bad.onnx",
            &["leangate.score_step = 0", "(0, 1]"],
        ),
        (
            "nan_always.onnx",
            &["dry run on a blank frame", "not finite"],
        ),
        // D8: the head must live in the encoder's folder.
        ("head_dotdot.onnx", &["leangate.head", "no `..`"]),
        ("head_absolute.onnx", &["leangate.head", "no absolute path"]),
    ];
    for (file, wants) in cases {
        let msgs = run_pipeline(
            &format!(
                "videotestsrc num-buffers=3 ! video/x-raw,width=32,height=32 ! leangate model={} ! fakesink",
                fixture(file)
            ),
            30,
        );
        let e = error_text(&msgs).unwrap_or_else(|| panic!("{file} must be refused at start"));
        assert!(e.contains(file), "{file}: the error names the model: {e}");
        for w in *wants {
            assert!(e.contains(w), "{file}: expected {w:?} in: {e}");
        }
        assert!(
            element_message(&msgs, "leangate-stats").is_empty(),
            "{file}: no frame was gated"
        );
    }
}

#[test]
fn a_model_path_that_is_not_a_regular_file_is_refused_at_start_without_reading_it() {
    // Opening a FIFO blocks until something writes to it: the element used to hang at start,
    // beyond the reach of a state change. A device is no model either.
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("model.onnx");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .expect("mkfifo runs");
    assert!(made.success());
    for path in [fifo.display().to_string(), "/dev/zero".to_string()] {
        let msgs = run_pipeline(
            &format!(
                "videotestsrc num-buffers=3 ! video/x-raw,width=32,height=32 ! leangate model=\"{path}\" ! fakesink"
            ),
            30,
        );
        let e = error_text(&msgs).unwrap_or_else(|| panic!("{path} must be refused at start"));
        assert!(e.contains(&path), "the error names the path: {e}");
        assert!(e.contains("not a regular file"), "{path}: {e}");
    }
}

#[test]
fn head_symlink_out_of_the_folder_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let inner = dir.path().join("model");
    std::fs::create_dir(&inner).unwrap();
    std::fs::copy(
        fixture("split_encoder.onnx"),
        inner.join("split_encoder.onnx"),
    )
    .unwrap();
    std::fs::copy(fixture("split_head.onnx"), dir.path().join("outside.onnx")).unwrap();
    std::os::unix::fs::symlink(
        dir.path().join("outside.onnx"),
        inner.join("split_head.onnx"),
    )
    .unwrap();
    let msgs = run_pipeline(
        &format!(
            "videotestsrc num-buffers=3 ! leangate model={} ! fakesink",
            inner.join("split_encoder.onnx").display()
        ),
        30,
    );
    let e = error_text(&msgs).expect("refused");
    assert!(e.contains("outside the encoder's folder"), "{e}");
    // The same head as a plain file beside the encoder loads.
    std::fs::remove_file(inner.join("split_head.onnx")).unwrap();
    std::fs::copy(fixture("split_head.onnx"), inner.join("split_head.onnx")).unwrap();
    let msgs = run_pipeline(
        &format!(
            "videotestsrc num-buffers=3 ! leangate model={} ! fakesink",
            inner.join("split_encoder.onnx").display()
        ),
        30,
    );
    assert!(error_text(&msgs).is_none(), "{:?}", error_text(&msgs));
}

#[test]
fn external_data_resolves_next_to_the_model() {
    // The working directory (the crate) is not the model's folder.
    assert!(!std::env::current_dir()
        .unwrap()
        .join("ext_data.onnx.data")
        .exists());
    let msgs = run_pipeline(
        &format!(
            "videotestsrc num-buffers=5 pattern=ball ! video/x-raw,width=64,height=48 ! \
             leangate model={} mode=annotate ! fakesink",
            fixture("ext_data.onnx")
        ),
        30,
    );
    assert!(error_text(&msgs).is_none(), "{:?}", error_text(&msgs));
    let stats = element_message(&msgs, "leangate-stats");
    let s = stats.last().unwrap();
    assert_eq!(s.get::<&str>("model").unwrap(), "fixture-ext-data");
    assert_eq!(s.get::<u64>("frames-in").unwrap(), 5);
}

#[test]
fn model_metadata_threshold_in_range_still_applies() {
    let mut h = harness(
        &format!("model={}", fixture("mad_meta.onnx")),
        &rgb_caps(W, H),
    );
    h.push(buffer(solid(W, H, [0, 0, 0]), 0)).unwrap();
    drain(&mut h);
    let e = h.element().unwrap();
    // The gate uses 0.3 from the metadata: a 0.35 step is kept.
    let v = (0.35f64 * 255.0).round() as u8;
    h.push(buffer(solid(W, H, [v, v, v]), 33)).unwrap();
    assert_eq!(drain(&mut h).len(), 1);
    assert_eq!(e.property::<f64>("threshold"), -1.0);
}

// ---------------------------------------------------------------------------------------------
// D7: bottom-up frames (negative VideoMeta strides)

/// A buffer holding `planes` (tightly packed rows, `strides`) laid out with the given per-plane
/// row padding, direction (`flip`: bottom-up, negative stride), gaps between planes and leading
/// offset, described by a VideoMeta.
#[derive(Debug, Clone, Copy, Default)]
struct Layout {
    /// Row padding per plane.
    pads: [usize; 3],
    /// Bottom-up planes (negative stride).
    flip: [bool; 3],
    /// Bytes before each plane.
    gaps: [usize; 3],
    /// Bytes before everything.
    lead: usize,
}

fn laid_out(
    format: PixelFormat,
    (w, h): (u32, u32),
    planes: &[Vec<u8>],
    strides: &[usize],
    layout: Layout,
) -> gst::Buffer {
    let Layout {
        pads,
        flip,
        gaps,
        lead,
    } = layout;
    let mut data = vec![0xA5u8; lead];
    let mut offsets = Vec::new();
    let mut vstrides = Vec::new();
    for (p, (plane, &s)) in planes.iter().zip(strides).enumerate() {
        let rows = plane.len() / s;
        let row_bytes = s; // tightly packed input: stride == row bytes
        let ns = row_bytes + pads[p];
        data.extend(std::iter::repeat_n(0x5Au8, gaps[p]));
        let base = data.len();
        data.extend(std::iter::repeat_n(0xEEu8, ns * rows));
        for y in 0..rows {
            let dst = if flip[p] { rows - 1 - y } else { y };
            data[base + dst * ns..base + dst * ns + row_bytes]
                .copy_from_slice(&plane[y * s..(y + 1) * s]);
        }
        if flip[p] {
            offsets.push(base + (rows - 1) * ns);
            vstrides.push(-(ns as i32));
        } else {
            offsets.push(base);
            vstrides.push(ns as i32);
        }
    }
    data.extend(std::iter::repeat_n(0x11u8, 7));
    let mut b = gst::Buffer::from_mut_slice(data);
    gst_video::VideoMeta::add_full(
        b.get_mut().unwrap(),
        gst_video::VideoFrameFlags::empty(),
        format.to_video_format(),
        w,
        h,
        &offsets,
        &vstrides,
    )
    .unwrap();
    b
}

fn info(format: PixelFormat, w: u32, h: u32) -> gst_video::VideoInfo {
    gst_video::VideoInfo::builder(format.to_video_format(), w, h)
        .fps(gst::Fraction::new(30, 1))
        .build()
        .unwrap()
}

#[test]
fn bottom_up_frames_score_like_top_down_in_the_element() {
    let pic = texture(W, H, 3);
    let (planes, strides) = pack_rgb(&pic, W, H, PixelFormat::Rgb, 0);
    let mut hs = harness(
        &format!(
            "model={} mode=annotate reject-junk=false",
            fixture("mad.onnx")
        ),
        &rgb_caps(W, H),
    );
    hs.push(buffer(solid(W, H, [0, 0, 0]), 0)).unwrap();
    let mut up = laid_out(
        PixelFormat::Rgb,
        (W, H),
        &planes,
        &strides,
        Layout {
            flip: [true; 3],
            ..Layout::default()
        },
    );
    up.get_mut()
        .unwrap()
        .set_pts(gst::ClockTime::from_mseconds(33));
    hs.push(up).unwrap();
    hs.push(buffer(solid(W, H, [0, 0, 0]), 66)).unwrap();
    hs.push(buffer(pic.clone(), 99)).unwrap();
    let out = drain(&mut hs);
    assert_eq!(out.len(), 4);
    let (m1, m3) = (meta(&out[1]), meta(&out[3]));
    assert_ne!(m1.reason, Reason::Error, "the bottom-up frame is readable");
    assert!(m1.utility > 0.1, "{}", m1.utility);
    assert!(
        (m1.utility - m3.utility).abs() < 1e-6,
        "{} vs {}",
        m1.utility,
        m3.utility
    );
}

#[test]
fn hostile_video_meta_is_an_unreadable_frame_not_a_crash() {
    let p = Preprocessor::new(
        PixelFormat::Rgb,
        W,
        H,
        YuvMatrix::BT601,
        TensorSpec {
            width: 16,
            height: 16,
            resize: ResizeMode::Stretch,
            mean: [0.0; 3],
            std: [1.0; 3],
        },
    )
    .unwrap();
    init();
    let vi = info(PixelFormat::Rgb, W, H);
    let mut out = vec![0.0; 3 * 16 * 16];
    let size = (W * H * 3) as usize;
    for (offset, stride) in [
        (0usize, -(3 * W as i32)), // bottom-up but offset at the start: rows before 0
        (size, 3 * W as i32),      // offset past the end
        (0, i32::MIN),             // wraps in unsigned arithmetic
        (usize::MAX - 10, 3 * W as i32), // offset overflow
        (0, 3 * W as i32 - 1),     // stride smaller than a row
        (0, i32::MAX),
    ] {
        let mut b = gst::Buffer::from_mut_slice(vec![0u8; size]);
        gst_video::VideoMeta::add_full(
            b.get_mut().unwrap(),
            gst_video::VideoFrameFlags::empty(),
            gst_video::VideoFormat::Rgb,
            W,
            H,
            &[offset],
            &[stride],
        )
        .unwrap();
        let e = p.run_buffer(&b, &vi, &mut out).unwrap_err();
        assert!(
            !e.to_string().contains("need 18446744073709"),
            "no wrapped size: {e}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// D8: OOB events, threshold values, model while playing, stats on backwards PTS

#[test]
fn oob_custom_events_are_handled_like_in_band_ones() {
    let mut h = harness(&format!("model={}", fixture("mad.onnx")), &rgb_caps(W, H));
    let pic = texture(W, H, 4);
    h.push(buffer(pic.clone(), 0)).unwrap();
    h.push(buffer(pic.clone(), 33)).unwrap();
    assert_eq!(drain(&mut h).len(), 1);
    let s = || gst::Structure::new_empty(gstleangate::FORCE_KEYFRAME_EVENT);
    // Downstream, out of band.
    h.push_event(gst::event::CustomDownstreamOob::new(s()));
    h.push(buffer(pic.clone(), 66)).unwrap();
    let out = drain(&mut h);
    assert_eq!(out.len(), 1, "forced by the OOB downstream event");
    assert_eq!(meta(&out[0]).reason, Reason::Forced);
    // Upstream, out of band (CustomBothOob travels both ways).
    // (Whether upstream of leangate handles it does not matter.)
    let _ = h.push_upstream_event(gst::event::CustomBothOob::new(s()));
    h.push(buffer(pic.clone(), 99)).unwrap();
    let out = drain(&mut h);
    assert_eq!(out.len(), 1, "forced by the OOB upstream event");
    assert_eq!(meta(&out[0]).reason, Reason::Forced);
    // Reset, downstream out of band.
    h.push_event(gst::event::CustomDownstreamOob::new(
        gst::Structure::new_empty(gstleangate::RESET_EVENT),
    ));
    h.push(buffer(pic.clone(), 132)).unwrap();
    let out = drain(&mut h);
    assert_eq!(meta(&out[0]).reason, Reason::First);
}

#[test]
fn negative_threshold_other_than_minus_one_is_refused() {
    let e = element(&format!("model={}", fixture("mad.onnx")));
    e.set_property("threshold", 0.4f64);
    e.set_property("threshold", -0.5f64);
    assert_eq!(e.property::<f64>("threshold"), 0.4, "refused, unchanged");
    e.set_property("threshold", -1.0f64);
    assert_eq!(e.property::<f64>("threshold"), -1.0);
    let pspec = e.find_property("threshold").unwrap();
    let blurb = pspec.blurb().unwrap();
    assert!(blurb.contains("-1") && blurb.contains("[0, 1]"), "{blurb}");

    // And -0.5 does not act like -1 in a running element: the gate keeps 0.4.
    let mut h = harness(
        &format!("model={} threshold=0.4", fixture("mad_meta.onnx")),
        &rgb_caps(W, H),
    );
    h.element().unwrap().set_property("threshold", -0.5f64);
    h.push(buffer(solid(W, H, [0, 0, 0]), 0)).unwrap();
    let v = (0.35f64 * 255.0).round() as u8;
    h.push(buffer(solid(W, H, [v, v, v]), 33)).unwrap();
    assert_eq!(
        drain(&mut h).len(),
        1,
        "0.35 < 0.4: dropped (the model says 0.3)"
    );
}

#[test]
fn a_value_refused_before_the_element_has_a_bus_is_reported_when_it_starts() {
    // gst-launch sets properties before it builds the pipeline: the refusal's warning has no bus
    // then, so it goes out when the element starts, once.
    init();
    let desc = format!(
        "videotestsrc num-buffers=3 ! leangate model={} threshold=-0.5 screen-step=-0.3 ! \
         fakesink",
        fixture("mad.onnx")
    );
    let pipeline = gst::parse::launch(&desc).unwrap();
    let msgs = run_to_end(&pipeline, &desc, 20);
    assert_eq!(error_text(&msgs), None);
    let warnings = warning_texts(&msgs);
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings[0].contains("threshold -0.5 refused"),
        "{warnings:?}"
    );
    assert!(
        warnings[1].contains("screen-step -0.3 refused"),
        "{warnings:?}"
    );
    // Started again: nothing left to report.
    let again = warning_texts(run_to_end(&pipeline, &desc, 20));
    assert_eq!(again.len(), 0);
}

#[test]
fn model_change_while_running_is_refused_and_the_property_stays() {
    let first = fixture("mad.onnx");
    let mut h = harness(&format!("model={first}"), &rgb_caps(W, H));
    let bus = gst::Bus::new();
    let e = h.element().unwrap();
    e.set_bus(Some(&bus));
    h.push(buffer(texture(W, H, 1), 0)).unwrap();
    e.set_property("model", fixture("mad_meta.onnx"));
    e.set_property(
        "execution-provider",
        gstleangate::ExecutionProviderChoice::Cpu,
    );
    e.set_property("precision", gstleangate::PrecisionChoice::Fp32);
    assert_eq!(
        e.property::<String>("model"),
        first,
        "still the model in use"
    );
    assert_eq!(
        e.property::<gstleangate::ExecutionProviderChoice>("execution-provider"),
        gstleangate::ExecutionProviderChoice::Auto
    );
    assert_eq!(
        e.property::<gstleangate::PrecisionChoice>("precision"),
        gstleangate::PrecisionChoice::Auto
    );
    let warnings: Vec<String> = bus_warnings(&bus);
    assert_eq!(warnings.len(), 3, "{warnings:?}");
    assert!(warnings[0].contains("`model` cannot change while the element runs"));
    assert!(warnings[2].contains("`precision` cannot change while the element runs"));
    // The value that stays, as a user writes it (not glib's Debug form of a GValue).
    assert!(warnings[2].ends_with("it stays auto"), "{}", warnings[2]);
    assert!(warnings[1].ends_with("it stays auto"), "{}", warnings[1]);
    assert!(
        warnings[0].ends_with(&format!("it stays {first}")),
        "{}",
        warnings[0]
    );
    h.push(buffer(texture(W, H, 2), 33)).unwrap();
    drain(&mut h);
    assert_eq!(
        e.property::<u64>("frames-in"),
        2,
        "still gating with the first model"
    );
    // Stopped, the change is accepted.
    drop(h);
    e.set_property("model", fixture("mad_meta.onnx"));
    assert_eq!(e.property::<String>("model"), fixture("mad_meta.onnx"));
}

#[test]
fn stats_keep_coming_when_pts_goes_backwards_without_a_flush() {
    let mut h = harness(
        &format!("model={} stats-interval=100000000", fixture("mad.onnx")),
        &rgb_caps(W, H),
    );
    let bus = gst::Bus::new();
    h.element().unwrap().set_bus(Some(&bus));
    let pic = texture(W, H, 1);
    // 1 s of stream, then the source loops back to 0 without a flush, for another second.
    for i in 0..30u64 {
        h.push(buffer(pic.clone(), i * 33)).unwrap();
    }
    let before = std::iter::from_fn(|| bus.pop()).count();
    assert!(before >= 6, "{before}");
    for i in 0..30u64 {
        h.push(buffer(pic.clone(), i * 33)).unwrap();
    }
    let after: Vec<gst::Message> = std::iter::from_fn(|| bus.pop()).collect();
    assert!(
        after.len() >= 6,
        "stats after PTS went back: {} messages",
        after.len()
    );
    let s = gstleangate::StatsMessage::from_structure(after.last().unwrap().structure().unwrap())
        .unwrap();
    assert!(
        s.interval_frames_in >= 3 && s.interval_frames_in <= 4,
        "{s:?}"
    );
}

// ---------------------------------------------------------------------------------------------
// D4: bounded statistics, with run and interval percentiles

/// The `leangate-stats` messages (every 0.3 s of stream time) of 40 frames of `videotestsrc
/// pattern` at `w`x`h` through `model`; asserts the run had no error and at least 4 messages.
fn interval_stats(model: &str, pattern: &str, w: u32, h: u32) -> Vec<gstleangate::StatsMessage> {
    let msgs = run_pipeline(
        &format!(
            "videotestsrc num-buffers=40 pattern={pattern} ! video/x-raw,width={w},height={h},framerate=30/1 ! \
             leangate model={} stats-interval=300000000 ! fakesink",
            fixture(model)
        ),
        30,
    );
    assert!(error_text(&msgs).is_none());
    let stats: Vec<gstleangate::StatsMessage> = element_message(&msgs, "leangate-stats")
        .into_iter()
        .map(|s| gstleangate::StatsMessage::from_structure(s).unwrap())
        .collect();
    assert!(stats.len() >= 4);
    stats
}

#[test]
fn screened_frames_are_counted_per_interval_and_over_the_run() {
    // mad_geometry's fusion has no student weight: every frame the prior follows is screened.
    let stats = interval_stats("mad_geometry.onnx", "pinwheel", 160, 120);
    let last = stats.last().unwrap();
    assert!(
        last.frames_screened > 0 && last.frames_screened < last.frames_in,
        "{last:?}"
    );
    assert_eq!(
        stats
            .iter()
            .map(|s| s.interval_frames_screened)
            .sum::<u64>(),
        last.frames_screened,
        "the intervals partition the screened frames"
    );
    assert!(stats
        .iter()
        .all(|s| s.interval_frames_screened <= s.interval_frames_in));
}

#[test]
fn stats_carry_run_and_interval_percentiles() {
    let stats = interval_stats("mad.onnx", "ball", 64, 48);
    let last = stats.last().unwrap();
    assert_eq!(
        stats.iter().map(|s| s.interval_frames_in).sum::<u64>(),
        last.frames_in,
        "the intervals partition the run"
    );
    assert_eq!(
        stats.iter().map(|s| s.interval_frames_kept).sum::<u64>(),
        last.frames_kept
    );
    assert!(last.inference_p50_us > 0 && last.inference_p50_us <= last.inference_p99_us);
    assert!(last.interval_inference_p50_us <= last.interval_inference_p99_us);
}

// ---------------------------------------------------------------------------------------------
// GAP events for dropped spans

#[test]
fn drop_mode_sends_gap_events_for_dropped_spans() {
    let mut h = harness(&format!("model={}", fixture("mad.onnx")), &rgb_caps(W, H));
    let pic = texture(W, H, 1);
    for i in 0..5u64 {
        h.push(buffer(pic.clone(), i * 33)).unwrap();
    }
    assert_eq!(drain(&mut h).len(), 1);
    let mut gaps = Vec::new();
    while let Some(ev) = h.try_pull_event() {
        if let gst::EventView::Gap(g) = ev.view() {
            gaps.push(g.get());
        }
    }
    let want: Vec<_> = (1..5u64)
        .map(|i| {
            (
                gst::ClockTime::from_mseconds(i * 33),
                Some(gst::ClockTime::from_mseconds(33)),
            )
        })
        .collect();
    assert_eq!(gaps, want);
}

/// Issue 22, item 14: a dropped buffer without PTS is announced at its DTS (as GstBaseSink
/// times such a buffer); one with neither timestamp has no span to announce, so it sends no GAP
/// (docs/element.md, Gating), and is still counted (`frames-in` - `frames-kept`).
#[test]
fn dropped_buffers_without_pts_gap_at_their_dts_or_not_at_all() {
    let mut h = harness(&format!("model={}", fixture("mad.onnx")), &rgb_caps(W, H));
    let pic = texture(W, H, 1);
    let stamped = |i: u64, dts: bool| {
        let mut b = buffer(pic.clone(), 0);
        let m = b.get_mut().unwrap();
        m.set_pts(gst::ClockTime::NONE);
        m.set_dts(dts.then(|| gst::ClockTime::from_mseconds(i * 33)));
        b
    };
    for i in 0..5u64 {
        h.push(stamped(i, true)).unwrap();
    }
    for i in 5..9u64 {
        h.push(stamped(i, false)).unwrap();
    }
    assert_eq!(
        drain(&mut h).len(),
        1,
        "a static picture: only the first is kept"
    );
    let mut gaps = Vec::new();
    while let Some(ev) = h.try_pull_event() {
        if let gst::EventView::Gap(g) = ev.view() {
            gaps.push(g.get().0);
        }
    }
    let want: Vec<_> = (1..5u64)
        .map(|i| gst::ClockTime::from_mseconds(i * 33))
        .collect();
    assert_eq!(
        gaps, want,
        "a GAP at each dropped buffer's DTS, none without timestamps"
    );
    let e = h.element().unwrap();
    let (frames_in, kept) = (
        e.property::<u64>("frames-in"),
        e.property::<u64>("frames-kept"),
    );
    assert_eq!((frames_in, kept), (9, 1));
}

/// A compositor mixing a gated branch (a static picture: everything but the first frame dropped)
/// with a moving branch must not stall waiting for frames that will never come. The gated branch's
/// source stays open (no EOS), as a camera does: without GAP events the compositor waits on that
/// pad after the first frame and produces nothing more. With the default look-back of 3, the
/// last 3 frames stay held (they leave when the next ones come): 3 fewer mixed frames, no stall.
#[test]
fn compositor_does_not_stall_on_a_gated_branch() {
    for lookback in [0u64, 3] {
        compositor_on_a_gated_branch(lookback);
    }
}

fn compositor_on_a_gated_branch(lookback: u64) {
    init();
    let desc = format!(
        "compositor name=mix ! video/x-raw,width=64,height=48 ! appsink name=out sync=false \
         appsrc name=src format=time caps={} ! leangate model={} sharpness-lookback={lookback} ! \
         queue ! mix.sink_0 \
         videotestsrc num-buffers=60 pattern=ball ! video/x-raw,width=32,height=24,framerate=30/1 ! \
         queue ! mix.sink_1",
        rgb_caps(W, H),
        fixture("mad.onnx")
    );
    let pipeline = gst::parse::launch(&desc)
        .unwrap()
        .downcast::<gst::Pipeline>()
        .unwrap();
    let bin = pipeline.upcast_ref::<gst::Bin>();
    let (src, sink) = app_ends(bin);
    pipeline.set_state(gst::State::Playing).unwrap();
    let pic = texture(W, H, 5);
    for i in 0..60u64 {
        let mut b = buffer(pic.clone(), 0);
        {
            let b = b.get_mut().unwrap();
            b.set_pts(gst::ClockTime::from_nseconds(i * 33_333_333));
            b.set_duration(gst::ClockTime::from_nseconds(33_333_333));
        }
        src.push_buffer(b).unwrap();
    }
    // No EOS on the gated branch.
    let want = 59 - lookback as usize;
    let mut pts = Vec::new();
    while let Some(s) = sink.try_pull_sample(gst::ClockTime::from_seconds(5)) {
        pts.push(s.buffer().unwrap().pts().unwrap());
        if pts.len() == want {
            break;
        }
    }
    pipeline.set_state(gst::State::Null).unwrap();
    assert!(
        pts.len() >= want,
        "look-back {lookback}: the compositor produced {} frames: it stalled on the gated branch",
        pts.len()
    );
    assert!(pts.windows(2).all(|w| w[1] > w[0]));
}

// ---------------------------------------------------------------------------------------------
// The suite: concurrency, storms, randomised layouts, flush seeks

/// Run a deterministic annotate-mode pipeline and return (reason, utility bits, keep) per frame.
fn annotate_run(seed: u32, frames: u64) -> Vec<(String, u64, bool, u64)> {
    annotate_run_with(
        seed,
        frames,
        &format!("model={} threshold=0.2", fixture("mad.onnx")),
    )
}

/// [`annotate_run`] with other `leangate` properties (model, threshold, sessions).
fn annotate_run_with(seed: u32, frames: u64, props: &str) -> Vec<(String, u64, bool, u64)> {
    init();
    let desc = format!(
        "appsrc name=src format=time caps={} ! leangate {props} mode=annotate max-gap=7 ! \
         appsink name=out sync=false",
        rgb_caps(W, H),
    );
    let pipeline = gst::parse::launch(&desc)
        .unwrap()
        .downcast::<gst::Pipeline>()
        .unwrap();
    let (src, sink) = app_ends(&pipeline);
    pipeline.set_state(gst::State::Playing).unwrap();
    let pics: Vec<Vec<u8>> = (0..5).map(|k| texture(W, H, seed * 7 + k)).collect();
    let feeder = std::thread::spawn(move || {
        for i in 0..frames {
            let k = ((i * 7 + i / 3) % 5) as usize;
            src.push_buffer(buffer(pics[k].clone(), i * 33)).unwrap();
        }
        src.end_of_stream().unwrap();
    });
    let mut out = Vec::new();
    while let Some(s) = sink.try_pull_sample(gst::ClockTime::from_seconds(30)) {
        let m = meta(&s.buffer_owned().unwrap());
        out.push((
            m.reason.as_str().to_string(),
            m.utility.to_bits(),
            m.keep,
            m.keyframe_index,
        ));
    }
    feeder.join().unwrap();
    pipeline.set_state(gst::State::Null).unwrap();
    out
}

#[test]
fn eight_concurrent_pipelines_are_identical_to_solo_runs() {
    let frames = 60;
    let solo: Vec<_> = (0..8).map(|s| annotate_run(s, frames)).collect();
    for s in &solo {
        assert_eq!(s.len() as u64, frames);
    }
    let handles: Vec<_> = (0..8)
        .map(|s| std::thread::spawn(move || annotate_run(s, frames)))
        .collect();
    for (s, h) in handles.into_iter().enumerate() {
        assert_eq!(h.join().unwrap(), solo[s], "pipeline {s}");
    }
}

/// Elements sharing one session of the default student, their frames batched, decide as
/// elements with a session each, with the same utilities (within 1e-5).
#[test]
fn shared_batched_elements_match_separate_sessions() {
    let frames = 40;
    let separate = "execution-provider=cpu shared-session=false";
    let batched =
        "execution-provider=cpu shared-session=true max-sessions=1 batch-size=4 batch-timeout=20000";
    let solo: Vec<_> = (0..4)
        .map(|s| annotate_run_with(s, frames, separate))
        .collect();
    let handles: Vec<_> = (0..4)
        .map(|s| std::thread::spawn(move || annotate_run_with(s, frames, batched)))
        .collect();
    for (s, h) in handles.into_iter().enumerate() {
        let got = h.join().unwrap();
        assert_eq!(got.len(), solo[s].len(), "pipeline {s}");
        for (i, (a, b)) in solo[s].iter().zip(&got).enumerate() {
            assert_eq!((&a.0, a.2, a.3), (&b.0, b.2, b.3), "pipeline {s} frame {i}");
            let (ua, ub) = (f64::from_bits(a.1), f64::from_bits(b.1));
            assert!(
                (ua.is_nan() && ub.is_nan()) || (ua - ub).abs() <= 1e-5,
                "pipeline {s} frame {i}: {ua} vs {ub}"
            );
        }
    }
}

/// Issue 22, item 2: four elements batch on one session (`batch-size=4`, a one-second
/// `batch-timeout`); after 10 frames one of them stops streaming: EOS, PAUSED, or its sink stops
/// pulling. The other three then gate their 40 frames far faster than one frame per timeout
/// (30 s before the fix, when the idle element still counted as a batch member).
#[test]
fn an_element_that_stops_streaming_does_not_slow_its_batch_down() {
    init();
    for how in ["eos", "paused", "not pulled"] {
        let (_dir, model) = student_copy();
        let desc = format!(
            "appsrc name=src format=time caps={} ! leangate model={} execution-provider=cpu \
             max-sessions=1 batch-size=4 batch-timeout=1000000 mode=annotate \
             sharpness-lookback=0 ! appsink name=out sync=false max-buffers=1",
            rgb_caps(W, H),
            model.display()
        );
        let pipelines: Vec<gst::Pipeline> = (0..4)
            .map(|_| {
                gst::parse::launch(&desc)
                    .unwrap()
                    .downcast::<gst::Pipeline>()
                    .unwrap()
            })
            .collect();
        for p in &pipelines {
            p.set_state(gst::State::Playing).unwrap();
        }
        let t0 = std::time::Instant::now();
        let handles: Vec<_> = pipelines
            .iter()
            .enumerate()
            .map(|(k, p)| {
                let (src, sink) = app_ends(p);
                let p = p.clone();
                std::thread::spawn(move || {
                    let stopper = k == 0;
                    let frames = if stopper && how == "eos" { 10 } else { 40 };
                    let pics: Vec<Vec<u8>> =
                        (0..5).map(|i| texture(W, H, k as u32 * 5 + i)).collect();
                    for i in 0..frames {
                        src.push_buffer(buffer(pics[(i % 5) as usize].clone(), i * 33))
                            .unwrap();
                    }
                    if frames == 10 {
                        src.end_of_stream().unwrap();
                    }
                    let mut pulled = 0;
                    while pulled < frames {
                        if stopper && pulled == 10 {
                            if how == "paused" {
                                p.set_state(gst::State::Paused).unwrap();
                            }
                            break;
                        }
                        sink.try_pull_sample(gst::ClockTime::from_seconds(60))
                            .expect("a frame");
                        pulled += 1;
                    }
                    t0.elapsed()
                })
            })
            .collect();
        let took: Vec<_> = handles.into_iter().map(|h| h.join().unwrap()).collect();
        for p in &pipelines {
            p.set_state(gst::State::Null).unwrap();
        }
        eprintln!("{how}: {took:?}");
        for t in &took[1..] {
            assert!(
                *t < std::time::Duration::from_secs(10),
                "{how}: 40 frames took {t:?} (one per batch timeout after the 10th: 30 s)"
            );
        }
    }
}

/// Elements of both builds of the embedded student in one process, sharing and batching: each
/// element gets its own build's sessions (the registry never hands an FP32 element an INT8
/// session or batches the two together), so every run matches a solo, unshared run of the same
/// build to 1e-5, and the two builds do score differently.
#[test]
fn fp32_and_int8_elements_in_one_process_keep_their_own_build() {
    let frames = 30;
    let shared = "execution-provider=cpu shared-session=true max-sessions=1 batch-size=4 \
                  batch-timeout=20000";
    let builds = ["fp32", "int8", "fp32", "int8"];
    let solo: Vec<_> = builds
        .iter()
        .enumerate()
        .map(|(s, b)| {
            annotate_run_with(
                s as u32 / 2,
                frames,
                &format!("execution-provider=cpu shared-session=false precision={b}"),
            )
        })
        .collect();
    let handles: Vec<_> = builds
        .iter()
        .enumerate()
        .map(|(s, b)| {
            let props = format!("{shared} precision={b}");
            std::thread::spawn(move || annotate_run_with(s as u32 / 2, frames, &props))
        })
        .collect();
    for (s, h) in handles.into_iter().enumerate() {
        let got = h.join().unwrap();
        assert_eq!(got.len(), solo[s].len(), "pipeline {s}");
        for (i, (a, b)) in solo[s].iter().zip(&got).enumerate() {
            let (ua, ub) = (f64::from_bits(a.1), f64::from_bits(b.1));
            assert!(
                (ua.is_nan() && ub.is_nan()) || (ua - ub).abs() <= 1e-5,
                "pipeline {s} ({}) frame {i}: {ua} vs {ub}",
                builds[s]
            );
        }
    }
    // Same frames (seed 0), FP32 against INT8: close, not identical.
    let differ = solo[0]
        .iter()
        .zip(&solo[1])
        .filter(|(a, b)| a.1 != b.1)
        .count();
    assert!(differ > 0, "the INT8 build scores differently from FP32");
}

#[test]
fn property_and_event_storms_during_streaming() {
    init();
    let frames = 400u64;
    let desc = format!(
        "appsrc name=src format=time caps={} ! leangate name=lg model={} stats-interval=1 ! \
         appsink name=out sync=false",
        rgb_caps(32, 24),
        fixture("mad.onnx")
    );
    let pipeline = gst::parse::launch(&desc)
        .unwrap()
        .downcast::<gst::Pipeline>()
        .unwrap();
    let lg = pipeline.by_name("lg").unwrap();
    let (src, sink) = app_ends(&pipeline);
    // A sync handler that reads properties on every message (the D2 pattern, in Rust).
    let lg2 = lg.clone();
    pipeline.bus().unwrap().set_sync_handler(move |_, _| {
        let _ = lg2.property::<f64>("threshold");
        let _ = lg2.property::<u64>("frames-in");
        gst::BusSyncReply::Drop
    });
    pipeline.set_state(gst::State::Playing).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    // Rounds of changes done so far: the feeder waits for some mid-stream, so the storm really
    // overlaps streaming even when a loaded machine schedules it late.
    let rounds = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let storm = {
        let (lg, stop, rounds) = (lg.clone(), stop.clone(), rounds.clone());
        std::thread::spawn(move || {
            let mut n = 0u64;
            while !stop.load(Ordering::Relaxed) {
                let t = (n % 100) as f64 / 100.0;
                lg.set_property("threshold", if n.is_multiple_of(17) { -1.0 } else { t });
                lg.set_property("max-gap", (n % 5) as u32);
                lg.set_property("warmup", (n % 3) as u32);
                lg.set_property(
                    "mode",
                    if n.is_multiple_of(2) {
                        gstleangate::GateMode::Annotate
                    } else {
                        gstleangate::GateMode::Drop
                    },
                );
                lg.set_property("stats-interval", n % 4);
                lg.set_property("model", fixture("mad_meta.onnx")); // refused: running
                let name = if n.is_multiple_of(2) {
                    gstleangate::FORCE_KEYFRAME_EVENT
                } else {
                    gstleangate::RESET_EVENT
                };
                let s = gst::Structure::new_empty(name);
                let ev = match n % 3 {
                    0 => gst::event::CustomDownstreamOob::new(s),
                    1 => gst::event::CustomBoth::new(s),
                    _ => gst::event::CustomBothOob::new(s),
                };
                lg.static_pad("sink").unwrap().send_event(ev);
                let _ = lg
                    .static_pad("src")
                    .unwrap()
                    .send_event(gst::event::CustomUpstream::new(gst::Structure::new_empty(
                        gstleangate::FORCE_KEYFRAME_EVENT,
                    )));
                n += 1;
                rounds.store(n, Ordering::Relaxed);
            }
            n
        })
    };
    let pics: Vec<Vec<u8>> = (0..3).map(|k| texture(32, 24, k)).collect();
    let feeder = std::thread::spawn(move || {
        for i in 0..frames {
            if i == frames / 2 {
                let t0 = std::time::Instant::now();
                while rounds.load(Ordering::Relaxed) < 12 && t0.elapsed().as_secs() < 30 {
                    std::thread::sleep(std::time::Duration::from_millis(1));
                }
            }
            src.push_buffer(buffer(pics[(i % 3) as usize].clone(), i * 33))
                .unwrap();
        }
        src.end_of_stream().unwrap();
    });
    let mut out = 0u64;
    while sink
        .try_pull_sample(gst::ClockTime::from_seconds(30))
        .is_some()
    {
        out += 1;
    }
    stop.store(true, Ordering::Relaxed);
    let changes = storm.join().unwrap();
    feeder.join().unwrap();
    assert!(sink.is_eos(), "reached EOS");
    assert_eq!(lg.property::<u64>("frames-in"), frames);
    let kept = lg.property::<u64>("frames-kept");
    assert!(out >= kept && out <= frames, "out {out}, kept {kept}");
    assert_eq!(lg.property::<String>("model"), fixture("mad.onnx"));
    assert!(changes > 10, "{changes} rounds of changes");
    pipeline.set_state(gst::State::Null).unwrap();
}

#[test]
fn flush_seek_storm() {
    init();
    let desc = format!(
        "videotestsrc pattern=ball is-live=false ! video/x-raw,width=64,height=48,framerate=30/1 ! \
         leangate name=lg model={} stats-interval=50000000 ! fakesink name=sink sync=false",
        fixture("mad.onnx")
    );
    let pipeline = gst::parse::launch(&desc).unwrap();
    let bus = pipeline.bus().unwrap();
    pipeline.set_state(gst::State::Paused).unwrap();
    pipeline.state(gst::ClockTime::from_seconds(10)).0.unwrap();
    pipeline.set_state(gst::State::Playing).unwrap();
    for i in 0..40u64 {
        let pos = gst::ClockTime::from_mseconds((i * 137) % 3000);
        pipeline
            .seek_simple(gst::SeekFlags::FLUSH | gst::SeekFlags::ACCURATE, pos)
            .unwrap();
        if i % 8 == 0 {
            pipeline.state(gst::ClockTime::from_seconds(10)).0.unwrap();
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    // Finally play a bounded segment to its end.
    pipeline.state(gst::ClockTime::from_seconds(10)).0.unwrap();
    pipeline
        .seek(
            1.0,
            gst::SeekFlags::FLUSH,
            gst::SeekType::Set,
            gst::ClockTime::ZERO,
            gst::SeekType::Set,
            gst::ClockTime::from_seconds(1),
        )
        .unwrap();
    let mut eos = false;
    while let Some(m) = bus.timed_pop(gst::ClockTime::from_seconds(30)) {
        match m.view() {
            gst::MessageView::Error(e) => panic!("error: {}", e.error()),
            gst::MessageView::Eos(_) => {
                eos = true;
                break;
            }
            _ => {}
        }
    }
    assert!(eos, "EOS after the storm");
    let lg = pipeline
        .downcast_ref::<gst::Bin>()
        .unwrap()
        .by_name("lg")
        .unwrap();
    assert!(lg.property::<u64>("frames-in") >= 30);
    pipeline.set_state(gst::State::Null).unwrap();
}

/// Tightly packed planes of `format` as a RawFrame.
fn packed_tensor(format: PixelFormat, w: u32, h: u32, pic: &[u8], p: &Preprocessor) -> Vec<f32> {
    let (planes, strides) = pack_rgb(pic, w, h, format, 0);
    let frame = raw_frame(format, w, h, &planes, &strides);
    let mut out = vec![0.0; p.spec().len()];
    p.run(&frame, &mut out).unwrap();
    out
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, failure_persistence: None, ..ProptestConfig::default() })]

    /// Any layout a producer may describe with a VideoMeta (row padding, bottom-up planes, gaps
    /// between planes, a leading offset) reads exactly like the tightly packed frame.
    #[test]
    fn random_layouts_read_like_tightly_packed(
        fi in 0usize..PixelFormat::ALL.len(),
        w in 1u32..41,
        h in 1u32..31,
        pads in proptest::array::uniform3(0usize..13),
        flip in proptest::array::uniform3(any::<bool>()),
        gaps in proptest::array::uniform3(0usize..17),
        lead in 0usize..29,
        seed in 0u32..50,
        crop in any::<bool>(),
    ) {
        init();
        let format = PixelFormat::ALL[fi];
        let pic = texture(w, h, seed);
        let spec = TensorSpec {
            width: 12,
            height: 9,
            resize: if crop { ResizeMode::ShortSideCrop } else { ResizeMode::Stretch },
            mean: [0.1, 0.2, 0.3],
            std: [0.5, 0.6, 0.7],
        };
        let p = Preprocessor::new(format, w, h, YuvMatrix::BT601, spec).unwrap();
        let want = packed_tensor(format, w, h, &pic, &p);
        let (planes, strides) = pack_rgb(&pic, w, h, format, 0);
        let b = laid_out(format, (w, h), &planes, &strides, Layout { pads, flip, gaps, lead });
        let mut got = vec![0.0; p.spec().len()];
        p.run_buffer(&b, &info(format, w, h), &mut got).unwrap();
        prop_assert_eq!(got, want);
    }
}

#[test]
fn a_flood_of_feedback_from_another_thread_neither_hangs_nor_floods_the_bus() {
    // A consumer thread sends leangate-feedback as fast as it can (half of the reports invalid)
    // while 300 frames stream; a synchronous bus handler reads feedback-offset and sets
    // feedback-rate. The run ends, every frame is gated, the offset stays within its bounds,
    // and the invalid reports give rate-limited warnings, not one per report.
    init();
    let desc = format!(
        "videotestsrc num-buffers=300 pattern=ball ! video/x-raw,width=160,height=120 ! \
         leangate name=gate model={} ! fakesink name=out sync=false",
        fixture("mad_geometry.onnx")
    );
    let pipeline = gst::parse::launch(&desc)
        .unwrap()
        .downcast::<gst::Pipeline>()
        .unwrap();
    let gate = pipeline.by_name("gate").unwrap();
    let sink = pipeline.by_name("out").unwrap();
    let bus = pipeline.bus().unwrap();
    let (warnings, seen) = (
        Arc::new(std::sync::Mutex::new(0usize)),
        Arc::new(std::sync::Mutex::new(Vec::<f64>::new())),
    );
    {
        let (warnings, seen, gate) = (warnings.clone(), seen.clone(), gate.clone());
        bus.set_sync_handler(move |_, msg| {
            if let gst::MessageView::Warning(_) = msg.view() {
                *warnings.lock().unwrap() += 1;
            }
            seen.lock()
                .unwrap()
                .push(gate.property::<f64>("feedback-offset"));
            gate.set_property("feedback-rate", 0.5);
            gst::BusSyncReply::Pass
        });
    }
    pipeline.set_state(gst::State::Playing).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let flood = {
        let (stop, sink) = (stop.clone(), sink.clone());
        std::thread::spawn(move || {
            let mut n = 0u64;
            while !stop.load(Ordering::Relaxed) {
                let tau = if n.is_multiple_of(2) { 0.9 } else { 5.0 };
                let s = gst::Structure::builder(gstleangate::FEEDBACK_EVENT)
                    .field("tau", tau)
                    .build();
                sink.send_event(gst::event::CustomUpstream::new(s));
                n += 1;
            }
            n
        })
    };
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    let mut ended = false;
    while std::time::Instant::now() < deadline {
        if let Some(msg) = bus.timed_pop(gst::ClockTime::from_mseconds(100)) {
            match msg.view() {
                gst::MessageView::Eos(_) => {
                    ended = true;
                    break;
                }
                gst::MessageView::Error(e) => panic!("{}", e.error()),
                _ => {}
            }
        }
    }
    stop.store(true, Ordering::Relaxed);
    let sent = flood.join().unwrap();
    let offset = gate.property::<f64>("feedback-offset");
    let frames = gate.property::<u64>("frames-in");
    pipeline.set_state(gst::State::Null).unwrap();
    assert!(ended, "no EOS within 60 s ({sent} reports sent)");
    assert_eq!(frames, 300);
    assert!(sent > 300, "the flood outran the frames: {sent}");
    assert!((0.0..=0.3).contains(&offset), "{offset}");
    assert!(offset > 0.0, "the valid reports (tau 0.9) raised it");
    let w = *warnings.lock().unwrap();
    assert!((1..=5).contains(&w), "rate-limited warnings, got {w}");
    assert!(seen.lock().unwrap().iter().all(|o| (0.0..=0.3).contains(o)));
}

#[test]
fn caps_the_preprocessing_cannot_take_are_an_error_naming_why() {
    // Wider than the preprocessing takes: before, only upstream's "not-negotiated" reached the
    // bus, and the reason stayed in the debug log.
    let msgs = run_pipeline(
        "videotestsrc num-buffers=2 ! video/x-raw,format=GRAY8,width=32769,height=2 ! leangate ! fakesink",
        30,
    );
    let e = error_text(&msgs).expect("an error");
    assert!(
        e.contains("32769x2") && e.contains("too large") && e.contains("at most 32768"),
        "{e}"
    );
}

/// Stopping the element, or a flushing seek, ends a local model run in flight instead of waiting
/// for it (found by a hostile probe: set_state(NULL) waited as long as the model ran, for ever
/// with a model that loops on real frames, and took 6.8 s with one taking 5.6 s a frame). The
/// fixture `forever.onnx` loops about for ever on any real frame: the pipeline must still stop,
/// and a stop is no failure (no warning or error on the bus).
#[test]
fn stopping_ends_a_model_run_in_flight() {
    common::init();
    let desc = format!(
        "videotestsrc ! video/x-raw,width=64,height=48 ! leangate name=g model={} ! fakesink",
        fixture("forever.onnx")
    );
    for flush_first in [false, true] {
        let pipeline = gst::parse::launch(&desc).unwrap();
        let gate = pipeline
            .downcast_ref::<gst::Bin>()
            .unwrap()
            .by_name("g")
            .unwrap();
        pipeline.set_state(gst::State::Playing).unwrap();
        // The second frame is scored against the first (kept as `first`): its run loops.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
        while gate.property::<u64>("frames-in") < 2 {
            assert!(std::time::Instant::now() < deadline, "no second frame");
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
        let (tx, rx) = std::sync::mpsc::channel();
        let p = pipeline.clone();
        std::thread::spawn(move || {
            if flush_first {
                // A flushing seek interrupts the run; the frames after it loop again.
                let _ = p.seek_simple(gst::SeekFlags::FLUSH, gst::ClockTime::ZERO);
            }
            let _ = p.set_state(gst::State::Null);
            let _ = tx.send(());
        });
        assert!(
            rx.recv_timeout(std::time::Duration::from_secs(20)).is_ok(),
            "the pipeline did not stop while the model ran (flush first: {flush_first})"
        );
        let bus = pipeline.bus().unwrap();
        let msgs: Vec<_> = std::iter::from_fn(|| bus.pop()).collect();
        assert!(error_text(&msgs).is_none(), "{:?}", error_text(&msgs));
        assert!(
            warning_texts(&msgs).is_empty(),
            "{:?}",
            warning_texts(&msgs)
        );
    }
}
