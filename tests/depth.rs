//! Depth beside the colour (issue 52): `leangate` reads a `LeanGateDepthMeta` on each colour
//! buffer and gates with the metric gate (the teacher's S with the pose fitted from the frames);
//! without it, or when the pose fails, the frame is gated colour-only, and its LeanGateMeta says
//! which (`depth`).
//!
//! The scene: a textured plane 2 m in front of a 160x120 camera (fx = fy = 130) that moves
//! sideways 4 cm a frame, so the teacher's utility grows by 0.04 * 130 / 2 / 160 = 0.01625 a
//! frame (the part of the view that has left) and reaches 0.5 near frame 31.

mod common;

use common::*;
use gst::prelude::*;
use gstleangate::depth::{DepthFormat, DepthInput};
use gstleangate::DepthUse;

const W: u32 = 160;
const H: u32 = 120;
const F: f64 = 130.0;
const Z: f64 = 2.0;
const STEP_M: f64 = 0.04;

/// The plane's texture under pixel (x, y) with the camera moved `shift` metres.
fn grey_at(x: u32, y: u32, shift: f64) -> u8 {
    let wx = (x as f64 - 79.5) / F * Z + shift;
    let wy = (y as f64 - 59.5) / F * Z;
    let v = (wx * 9.0).sin() * (wy * 7.0).cos() + (wx * 3.1 + wy * 4.3).sin();
    (128.0 + 60.0 * v) as u8
}

fn colour(shift: f64) -> Vec<u8> {
    (0..W * H)
        .flat_map(|i| {
            let g = grey_at(i % W, i / W, shift);
            [g, g, g]
        })
        .collect()
}

/// The plane's depth at `w` x `h` (GRAY16_LE millimetres), intrinsics of the colour frame.
fn depth(w: u32, h: u32) -> DepthInput {
    let mm = (Z * 1000.0) as u16;
    let data: Vec<u8> = (0..w * h).flat_map(|_| mm.to_le_bytes()).collect();
    DepthInput {
        depth: gst::Buffer::from_mut_slice(data),
        format: DepthFormat::Gray16Le,
        width: w,
        height: h,
        stride: 2 * w,
        scale: 1000.0,
        fx: F,
        fy: F,
        cx: 79.5,
        cy: 59.5,
    }
}

fn rgbd_harness(props: &str) -> (gst_check::Harness, gst::Bus) {
    let h = harness(
        &format!(
            "mode=annotate model={} sharpness-lookback=0 {props}",
            fixture("mad_geometry.onnx")
        ),
        &rgb_caps(W, H),
    );
    let bus = gst::Bus::new();
    h.element().unwrap().set_bus(Some(&bus));
    (h, bus)
}

/// Push frame `k` of the move, with `d` attached when given.
fn push(h: &mut gst_check::Harness, k: u64, d: Option<&DepthInput>) {
    let mut b = buffer(colour(STEP_M * k as f64), k * 33);
    if let Some(d) = d {
        d.attach(b.get_mut().unwrap()).unwrap();
    }
    h.push(b).unwrap();
}

#[test]
fn depth_gives_the_teachers_utility_and_the_keep_where_it_falls_due() {
    let (mut h, _bus) = rgbd_harness("threshold=0.5");
    let d = depth(W, H);
    let mut metas = Vec::new();
    for k in 0..40 {
        push(&mut h, k, Some(&d));
        metas.extend(drain(&mut h).iter().map(meta));
    }
    assert_eq!(metas.len(), 40);
    let kept: Vec<usize> = (0..40).filter(|&k| metas[k].keep).collect();
    assert_eq!(kept[0], 0);
    // The second keep comes where the view has moved half its width: frame 31 or so.
    assert!((29..=33).contains(&kept[1]), "kept {kept:?}");
    for (k, m) in metas.iter().enumerate().take(kept[1]).skip(1) {
        assert_eq!(m.depth, DepthUse::Used, "frame {k}: {m:?}");
        let expected = 0.01625 * k as f64;
        assert!(
            (m.utility - expected).abs() < 0.04,
            "frame {k}: utility {} against {expected}",
            m.utility
        );
    }
    assert_eq!(metas[0].depth, DepthUse::Used);
}

#[test]
fn depth_of_another_size_is_resampled_onto_the_model_grid() {
    let (mut h, _bus) = rgbd_harness("threshold=0.5");
    let d = depth(80, 60);
    let mut metas = Vec::new();
    for k in 0..12 {
        push(&mut h, k, Some(&d));
        metas.extend(drain(&mut h).iter().map(meta));
    }
    let m = &metas[10];
    assert_eq!(m.depth, DepthUse::Used, "{m:?}");
    assert!((m.utility - 0.1625).abs() < 0.04, "{m:?}");
}

#[test]
fn frames_without_depth_are_gated_colour_only_and_say_so() {
    let (mut h, _bus) = rgbd_harness("threshold=0.5");
    let d = depth(W, H);
    let mut metas = Vec::new();
    for k in 0..8 {
        push(&mut h, k, (k % 3 != 2).then_some(&d));
        metas.extend(drain(&mut h).iter().map(meta));
    }
    assert_eq!(metas.len(), 8, "no frame lost");
    for (k, m) in metas.iter().enumerate() {
        let want = if k % 3 == 2 {
            DepthUse::Missing
        } else {
            DepthUse::Used
        };
        assert_eq!(m.depth, want, "frame {k}: {m:?}");
    }
    // A stream without depth says `none`.
    let (mut h, _bus) = rgbd_harness("");
    push(&mut h, 0, None);
    push(&mut h, 1, None);
    let m: Vec<_> = drain(&mut h).iter().map(meta).collect();
    assert!(m.iter().all(|m| m.depth == DepthUse::None), "{m:?}");
}

#[test]
fn malformed_depth_warns_once_and_the_frames_are_gated_colour_only() {
    let (mut h, bus) = rgbd_harness("threshold=0.5");
    for k in 0..5 {
        let mut b = buffer(colour(STEP_M * k as f64), k * 33);
        {
            let bm = b.get_mut().unwrap();
            // Attach with a good stride, then break it in the structure as a careless app would.
            depth(W, H).attach(bm).unwrap();
            let mut m = gst::meta::CustomMeta::from_mut_buffer(bm, "LeanGateDepthMeta").unwrap();
            // Below a row of 160 GRAY16_LE pixels.
            m.mut_structure().set("stride", 10u32);
        }
        h.push(b).unwrap();
    }
    let m: Vec<_> = drain(&mut h).iter().map(meta).collect();
    assert_eq!(m.len(), 5, "no frame lost");
    assert!(m.iter().all(|m| m.depth != DepthUse::Used), "{m:?}");
    let warnings = bus_warnings(&bus);
    assert_eq!(warnings.len(), 1, "rate-limited: {warnings:?}");
    assert!(
        warnings[0].contains("depth ignored") && warnings[0].contains("stride 10"),
        "{warnings:?}"
    );
}

/// The documented gst-launch line (docs/element.md, *Depth: `leangatedepthmux`*) on real RGB-D
/// frames: 7-Scenes colour JPEGs and depth PNGs through `leangatedepthmux` into `leangate`. Every
/// frame leaves with its verdict; after the first, each is gated with depth (a pose fitted).
#[test]
fn real_rgbd_frames_through_the_depth_mux_are_gated_with_depth() {
    let Some(dir) = shared_data("7scenes_redkitchen_dev") else {
        return;
    };
    let d = dir.display();
    let desc = format!(
        "multifilesrc location={d}/rgb/%06d.jpg caps=image/jpeg,framerate=30/1 ! jpegdec ! \
         videoconvert ! m.sink \
         multifilesrc location={d}/depth/%06d.png caps=image/png,framerate=30/1 ! pngdec ! \
         videoconvert ! m.depth \
         leangatedepthmux name=m depth-scale=1000 intrinsics=585,585,320,240 ! \
         leangate mode=annotate ! appsink name=sink sync=false"
    );
    init();
    let pipeline = gst::parse::launch(&desc).unwrap();
    let bin = pipeline.clone().downcast::<gst::Bin>().unwrap();
    let sink = bin
        .by_name("sink")
        .unwrap()
        .downcast::<gst_app::AppSink>()
        .unwrap();
    let metas = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let m2 = metas.clone();
    sink.set_callbacks(
        gst_app::AppSinkCallbacks::builder()
            .new_sample(move |s| {
                let sample = s.pull_sample().map_err(|_| gst::FlowError::Eos)?;
                m2.lock()
                    .unwrap()
                    .push(meta(sample.buffer_owned().as_ref().unwrap()));
                Ok(gst::FlowSuccess::Ok)
            })
            .build(),
    );
    let msgs = run_to_end(&pipeline, &desc, 120);
    assert!(error_text(&msgs).is_none(), "{:?}", error_text(&msgs));
    let metas = metas.lock().unwrap();
    assert_eq!(metas.len(), 60, "every frame leaves");
    let used = metas.iter().filter(|m| m.depth == DepthUse::Used).count();
    assert!(used >= 58, "{used} of 60 gated with depth: {metas:?}");
    // The 7-Scenes clip moves little: the oracle keeps its first frame only, and so does this.
    assert!(metas.iter().filter(|m| m.keep).count() <= 2, "{metas:?}");
}

/// Depth with no reading anywhere (all NaN in GRAY32F, as a sensor gives in the dark or too
/// close): no corner can be lifted, so no pose; every frame is gated colour-only and says so.
#[test]
fn depth_without_readings_is_gated_colour_only() {
    let (mut h, bus) = rgbd_harness("threshold=0.5");
    let nan: Vec<u8> = (0..W * H).flat_map(|_| f32::NAN.to_le_bytes()).collect();
    let d = DepthInput {
        depth: gst::Buffer::from_mut_slice(nan),
        format: DepthFormat::Gray32F,
        width: W,
        height: H,
        stride: 4 * W,
        scale: 1.0,
        fx: F,
        fy: F,
        cx: 79.5,
        cy: 59.5,
    };
    for k in 0..6 {
        push(&mut h, k, Some(&d));
    }
    let m: Vec<_> = drain(&mut h).iter().map(meta).collect();
    assert_eq!(m.len(), 6);
    assert!(m[1..].iter().all(|m| m.depth == DepthUse::Lost), "{m:?}");
    assert!(
        m[1..].iter().all(|m| m.utility.is_finite()),
        "the colour-only utility: {m:?}"
    );
    assert!(bus_warnings(&bus).is_empty());
}
