//! Throughput of `leangate` in real pipelines, side by side with `identity` (the cost of the
//! pipeline without the gate), and the per-format cost of the frame → tensor preprocessing.
//!
//!     cargo bench --bench pipeline
//!
//! Environment: LEANGATE_BENCH_REPS (repetitions per figure, default 5; the median is shown),
//! LEANGATE_BENCH_FRAMES (frames per synthetic run, default 300), LEANGATE_MODEL (default
//! tests/fixtures/mad.onnx), LEANGATE_BENCH_THRESHOLD (default 0.05).
//!
//! Cases:
//! - file: `filesrc location=CLIP ! decodebin ! leangate ! fakesink sync=false` vs `identity`,
//!   on a 640x480 clip of the `ball` test pattern encoded at start-up in a temporary directory
//!   (the first available of x264enc, openh264enc, avenc_mpeg4, jpegenc/MJPEG-in-AVI), and, when
//!   ../shared/data is present, cotracker_clips/bear.mp4 (real content, H.264 854x480) with
//!   `videoscale ! video/x-raw,width=640,height=480` in both pipelines.
//! - raw: `videotestsrc ! video/x-raw,format=F,width=640,height=480 ! leangate ! fakesink` vs
//!   `identity`, for F = I420, NV12, RGB (no decoding: the gate's cost is most visible).
//! - preprocess: `gstleangate::Preprocessor` alone, 640x480 RGB/NV12/I420 → 64x64
//!   and 256x256 tensors, microseconds per frame.
//!
//! Frames per second are counted at the gate's (or identity's) sink pad, from the first buffer to
//! EOS, so the model loading at start-up is not included (it is shown separately).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[path = "common/mod.rs"]
mod common;

use common::{frame_planes, measure, run_to_eos};
use gstleangate::{PixelFormat, Preprocessor, RawFrame, ResizeMode, TensorSpec, YuvMatrix};

const W: u32 = 640;
const H: u32 = 480;

fn env_or<T: std::str::FromStr>(k: &str, d: T) -> T {
    std::env::var(k)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(d)
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

fn has(factory: &str) -> bool {
    gst::ElementFactory::find(factory).is_some()
}

/// Encode `src` (a description producing raw video) into a 640x480 file in `dir`.
fn make_clip(dir: &Path, name: &str, src: &str) -> Option<PathBuf> {
    let (enc, mux, ext) = if has("x264enc") {
        (
            "x264enc speed-preset=veryfast tune=zerolatency",
            "mp4mux",
            "mp4",
        )
    } else if has("openh264enc") {
        ("openh264enc", "mp4mux", "mp4")
    } else if has("avenc_mpeg4") {
        ("avenc_mpeg4 bitrate=4000000", "mp4mux", "mp4")
    } else if has("jpegenc") {
        ("jpegenc quality=90", "avimux", "avi")
    } else {
        eprintln!("SKIPPED: no video encoder (x264enc, openh264enc, avenc_mpeg4, jpegenc) for the file case");
        return None;
    };
    let path = dir.join(format!("{name}.{ext}"));
    let desc = format!(
        "{src} ! videoconvert ! videoscale ! video/x-raw,format=I420,width={W},height={H},pixel-aspect-ratio=1/1 ! {enc} ! \
         {mux} ! filesink location=\"{}\"",
        path.display()
    );
    run_to_eos(&desc, Duration::from_secs(300));
    let codec = enc.split_whitespace().next().unwrap();
    eprintln!("made {} ({codec})", path.display());
    Some(path)
}

struct Row {
    case: String,
    leangate_fps: f64,
    identity_fps: f64,
    frames: u64,
    keep_ratio: f64,
    inference_us: f64,
    startup_ms: f64,
    provider: String,
}

/// Alternate leangate and identity runs (so that load changes hit both alike); medians.
fn compare(case: &str, template: &str, leangate: &str, reps: usize) -> Row {
    let lg_desc = template.replace("GATE", leangate);
    let id_desc = template.replace("GATE", "identity name=gate");
    // One untimed run of each: page cache, ONNX Runtime library loading, decoder setup.
    measure(&lg_desc);
    measure(&id_desc);
    let (mut lg, mut id, mut inf, mut start) = (vec![], vec![], vec![], vec![]);
    let (mut frames, mut keep, mut provider) = (0, f64::NAN, String::new());
    for _ in 0..reps {
        let r = measure(&lg_desc);
        lg.push(r.fps);
        inf.push(r.inference_mean_us.unwrap_or(f64::NAN));
        start.push(r.startup_ms);
        frames = r.frames;
        keep = r.keep_ratio.unwrap_or(f64::NAN);
        provider = r.provider.unwrap_or_default();
        let r = measure(&id_desc);
        assert_eq!(r.frames, frames, "both pipelines see the same frames");
        id.push(r.fps);
    }
    let row = Row {
        case: case.to_string(),
        leangate_fps: median(&mut lg),
        identity_fps: median(&mut id),
        frames,
        keep_ratio: keep,
        inference_us: median(&mut inf),
        startup_ms: median(&mut start),
        provider,
    };
    eprintln!(
        "  {case}: leangate {:.0} fps, identity {:.0} fps",
        row.leangate_fps, row.identity_fps
    );
    row
}

/// Median microseconds per frame of `Preprocessor::run`.
fn preprocess_us(format: PixelFormat, size: u32, reps: usize) -> f64 {
    let (w, h) = (W as usize, H as usize);
    let (planes, strides) = frame_planes(format, w, h);
    let mut p: [&[u8]; 3] = [&[], &[], &[]];
    for (i, plane) in planes.iter().enumerate() {
        p[i] = plane;
    }
    let frame = RawFrame {
        format,
        width: W,
        height: H,
        planes: p,
        strides,
    };
    let spec = TensorSpec {
        width: size,
        height: size,
        resize: ResizeMode::ShortSideCrop,
        mean: [0.485, 0.456, 0.406],
        std: [0.229, 0.224, 0.225],
    };
    let pre = Preprocessor::new(format, W, H, YuvMatrix::BT601, spec).unwrap();
    let mut out = vec![0f32; pre.spec().len()];
    for _ in 0..10 {
        pre.run(&frame, &mut out).unwrap();
    }
    // About 0.2 s per repetition.
    let t = Instant::now();
    pre.run(&frame, &mut out).unwrap();
    let once = t.elapsed().as_secs_f64().max(1e-6);
    let iters = ((0.2 / once) as usize).clamp(5, 20_000);
    let mut per = Vec::with_capacity(reps);
    for _ in 0..reps {
        let t = Instant::now();
        for _ in 0..iters {
            pre.run(&frame, std::hint::black_box(&mut out)).unwrap();
        }
        per.push(t.elapsed().as_secs_f64() * 1e6 / iters as f64);
    }
    assert!(out.iter().all(|v| v.is_finite()));
    median(&mut per)
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo bench --bench pipeline -- raw` filters the cases.
    let filter: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let wanted = |case: &str| filter.is_empty() || filter.iter().any(|f| case.contains(f.as_str()));

    gst::init().unwrap();
    gstleangate::plugin_register_static().expect("register the leangate plugin");
    let reps: usize = env_or("LEANGATE_BENCH_REPS", 5).max(1);
    let n: u64 = env_or("LEANGATE_BENCH_FRAMES", 300);
    let threshold: f64 = env_or("LEANGATE_BENCH_THRESHOLD", 0.05);
    let model = std::env::var("LEANGATE_MODEL").unwrap_or_else(|_| {
        concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/mad.onnx").to_string()
    });
    let leangate = format!("leangate name=gate model=\"{model}\" threshold={threshold}");
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    eprintln!("LeanGate pipeline benchmark: {reps} repetitions (median), {n} frames per synthetic run, model {model}, threshold {threshold}, {cores} CPU cores");

    let tmp = tempfile::tempdir().unwrap();
    let mut rows = Vec::new();

    if wanted("file") {
        let mut clips = Vec::new();
        if let Some(p) = make_clip(
            tmp.path(),
            "ball",
            &format!("videotestsrc pattern=ball num-buffers={n} ! video/x-raw,width={W},height={H},framerate=30/1"),
        ) {
            clips.push(("file ball 640x480", p));
        }
        let bear = PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../shared/data/cotracker_clips/bear.mp4"
        ));
        let mut templates: Vec<(String, String)> = clips
            .into_iter()
            .map(|(case, clip)| {
                let codec = clip.extension().unwrap().to_string_lossy().into_owned();
                (
                    format!("{case} ({codec})"),
                    format!(
                        "filesrc location=\"{}\" ! decodebin ! GATE ! fakesink sync=false",
                        clip.display()
                    ),
                )
            })
            .collect();
        if bear.exists() {
            // Real content, H.264 as shipped, scaled to 640x480 in both pipelines (re-encoding
            // it is not needed; the scaling is part of both the measured pipelines' cost).
            templates.push((
                "file bear.mp4 h264 →640x480".to_string(),
                format!(
                    "filesrc location=\"{}\" ! decodebin ! videoscale ! \
                     video/x-raw,width={W},height={H},pixel-aspect-ratio=1/1 ! GATE ! \
                     fakesink sync=false",
                    bear.display()
                ),
            ));
        } else {
            eprintln!("SKIPPED: {} absent (real-content clip)", bear.display());
        }
        for (case, template) in templates {
            rows.push(compare(&case, &template, &leangate, reps));
        }
    }
    if wanted("raw") {
        for fmt in ["I420", "NV12", "RGB"] {
            let template = format!(
                "videotestsrc pattern=ball num-buffers={n} ! video/x-raw,format={fmt},width={W},height={H},framerate=30/1 ! GATE ! fakesink sync=false"
            );
            rows.push(compare(
                &format!("raw {fmt} 640x480"),
                &template,
                &leangate,
                reps,
            ));
        }
    }

    let mut pre_rows = Vec::new();
    if wanted("preprocess") {
        for fmt in [PixelFormat::Rgb, PixelFormat::Nv12, PixelFormat::I420] {
            let a = preprocess_us(fmt, 64, reps);
            let b = preprocess_us(fmt, 256, reps);
            pre_rows.push((fmt, a, b));
        }
    }

    println!();
    if !rows.is_empty() {
        println!("Pipeline throughput (frames/s, median of {reps}; counted at the gate's sink pad, first buffer to EOS)");
        println!(
            "| {:<34} | {:>6} | {:>13} | {:>13} | {:>8} | {:>10} | {:>12} | {:>10} | {:>8} |",
            "case",
            "frames",
            "leangate fps",
            "identity fps",
            "ratio",
            "keep ratio",
            "inference µs",
            "startup ms",
            "provider"
        );
        println!(
            "|{:-<36}|{:-<8}|{:-<15}|{:-<15}|{:-<10}|{:-<12}|{:-<14}|{:-<12}|{:-<10}|",
            "", "", "", "", "", "", "", "", ""
        );
        for r in &rows {
            println!(
                "| {:<34} | {:>6} | {:>13.1} | {:>13.1} | {:>8.3} | {:>10.3} | {:>12.0} | {:>10.1} | {:>8} |",
                r.case,
                r.frames,
                r.leangate_fps,
                r.identity_fps,
                r.leangate_fps / r.identity_fps,
                r.keep_ratio,
                r.inference_us,
                r.startup_ms,
                r.provider
            );
        }
        println!("ratio = leangate fps / identity fps; inference µs = the element's mean preprocessing + scoring time per scored frame (leangate-stats); startup = PLAYING to first buffer at the gate (model loading included)");
        println!();
    }
    if !pre_rows.is_empty() {
        println!(
            "Preprocessing 640x480 → tensor (Preprocessor::run, µs per frame, median of {reps})"
        );
        println!(
            "| {:<6} | {:>9} | {:>11} |",
            "format", "→ 64x64", "→ 256x256"
        );
        println!("|{:-<8}|{:-<11}|{:-<13}|", "", "", "");
        for (fmt, a, b) in &pre_rows {
            println!("| {:<6} | {:>9.1} | {:>11.1} |", format!("{fmt:?}"), a, b);
        }
    }
}
