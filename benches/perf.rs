//! Performance, side by side in one run (issue 9): the cost of `leangate` in real pipelines
//! against `identity`, the ONNX Runtime threading settings, ffmpeg's `mpdecimate`, the frame →
//! tensor preprocessing per format (fast path vs the float reference), and many streams sharing
//! one session (batched) vs one session per stream.
//!
//!     cargo bench --bench perf                 # everything
//!     cargo bench --bench perf -- threads pre  # only the sections whose name contains a filter
//!
//! Sections: `threads`, `pipeline`, `mpdecimate`, `preprocess`, `streams`, `geometry`,
//! `scoring` (everything the element runs per frame, on real frames in memory). Environment:
//! LEANGATE_BENCH_REPS (repetitions, default 5; medians, A/B runs interleaved so that the load
//! of a shared machine hits both alike), LEANGATE_BENCH_FRAMES (frames per synthetic run,
//! default 200), and for `preprocess` LEANGATE_BENCH_FORMATS (e.g. `I420,Yuy2`) and
//! LEANGATE_BENCH_SIZES (e.g. `1920x1080>160x120`) to measure only some rows, and for `pipeline`
//! LEANGATE_BENCH_PIPELINES (parts of case names, e.g. `tum_fr1_desk,bear`). The model is the
//! embedded default student `leangate-s`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

#[path = "common/mod.rs"]
mod common;

use common::{frame_planes, measure, run_to_eos};
use gst::prelude::*;
use gstleangate::{PixelFormat, Preprocessor, RawFrame, ResizeMode, TensorSpec, YuvMatrix};

fn env_or<T: std::str::FromStr>(k: &str, d: T) -> T {
    std::env::var(k)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(d)
}

fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

fn has(factory: &str) -> bool {
    gst::ElementFactory::find(factory).is_some()
}

/// Frames/s of `desc` (which names the measured element `gate`), counted at the gate's sink pad
/// from the first buffer to EOS (start-up and model loading excluded).
fn fps(desc: &str) -> f64 {
    measure(desc).fps
}

/// Run each variant of `template` (GATE replaced) `reps` times, interleaved; median frames/s.
fn interleaved(template: &str, variants: &[(&str, String)], reps: usize) -> Vec<f64> {
    let descs: Vec<String> = variants
        .iter()
        .map(|(_, v)| template.replace("GATE", v))
        .collect();
    for d in &descs {
        fps(d); // warm-up: page cache, library loading
    }
    let mut all = vec![Vec::new(); descs.len()];
    for _ in 0..reps {
        for (i, d) in descs.iter().enumerate() {
            all[i].push(fps(d));
        }
    }
    all.iter().map(|v| median(v)).collect()
}

/// Encode `frames` of the `ball` test pattern at `w`x`h` into `dir` with the first available
/// encoder (H.264 preferred); None when there is none.
fn make_clip(dir: &Path, w: u32, h: u32, frames: u64) -> Option<(PathBuf, &'static str)> {
    let (enc, mux, ext, codec) = if has("x264enc") {
        ("x264enc speed-preset=veryfast", "mp4mux", "mp4", "h264")
    } else if has("openh264enc") {
        ("openh264enc", "mp4mux", "mp4", "h264")
    } else if has("avenc_mpeg4") {
        ("avenc_mpeg4 bitrate=8000000", "mp4mux", "mp4", "mpeg4")
    } else {
        return None;
    };
    let path = dir.join(format!("ball_{w}x{h}.{ext}"));
    run_to_eos(
        &format!(
            "videotestsrc pattern=ball num-buffers={frames} ! \
         video/x-raw,format=I420,width={w},height={h},framerate=30/1 ! {enc} ! {mux} ! \
         filesink location=\"{}\"",
            path.display()
        ),
        Duration::from_secs(600),
    );
    Some((path, codec))
}

/// tum_fr1_desk's 572 real frames (30 Hz) encoded by ffmpeg into `dir`: `name`.mkv with the
/// encoder arguments `codec` after scaling to `w`x`h`; None without ffmpeg, the encoder or the
/// sequence. The real-footage cases (H.264 at 640x480 and 1080p, 10-bit HEVC at 1080p).
fn desk_clip(dir: &Path, name: &str, w: u32, h: u32, codec: &[&str]) -> Option<PathBuf> {
    let rgb = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/tum_fr1_desk/rgb"
    ));
    // ffmpeg's glob needs the extension (a bare `*` matches nothing).
    let ext = std::fs::read_dir(&rgb)
        .ok()?
        .filter_map(|e| e.ok()?.path().extension()?.to_str().map(str::to_string))
        .next()?;
    let out = dir.join(format!("{name}.mkv"));
    let status = std::process::Command::new("ffmpeg")
        .args([
            "-v",
            "error",
            "-y",
            "-framerate",
            "30",
            "-pattern_type",
            "glob",
            "-i",
        ])
        .arg(rgb.join(format!("*.{ext}")))
        .args(["-vf", &format!("scale={w}:{h}")])
        .args(codec)
        .arg(&out)
        .status()
        .ok()?;
    (status.success() && out.exists()).then_some(out)
}

fn bear() -> Option<PathBuf> {
    let p = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/cotracker_clips/bear.mp4"
    ));
    p.exists().then_some(p)
}

// ---------------------------------------------------------------------------------------------

fn section_threads(reps: usize) {
    println!("\n## ONNX Runtime threading (default student, decoded H.264 bear.mp4 854x480, frames/s at the gate; median of {reps}, interleaved)");
    let Some(bear) = bear() else {
        println!("SKIPPED: ../shared/data/cotracker_clips/bear.mp4 absent");
        return;
    };
    let template = format!(
        "filesrc location=\"{}\" ! decodebin ! GATE ! fakesink sync=false",
        bear.display()
    );
    let lg = |extra: &str| format!("leangate name=gate threshold=0.3 {extra}");
    let variants = [
        ("identity (no gate)", "identity name=gate".to_string()),
        (
            "threads=2, spinning on (ONNX Runtime's own defaults)",
            lg("threads=2 ort-spinning=true"),
        ),
        (
            "threads=2, spinning off (before: threads=0 meant ORT's default, 2 here)",
            lg("threads=2"),
        ),
        (
            "threads=1, spinning off (now: the default, threads=0)",
            lg(""),
        ),
    ];
    let r = interleaved(&template, &variants, reps);
    println!("| configuration | frames/s | vs identity |");
    println!("|---|---|---|");
    for ((name, _), f) in variants.iter().zip(&r) {
        println!("| {name} | {f:.1} | {:.3} |", f / r[0]);
    }
}

fn section_pipeline(reps: usize, n: u64, tmp: &Path) {
    println!("\n## Pipelines: leangate (default student, defaults) vs identity, frames/s at the gate (median of {reps}, interleaved)");
    let mut cases: Vec<(String, String)> = Vec::new();
    for (w, h) in [(640u32, 480u32), (1920, 1080)] {
        for fmt in ["I420", "NV12"] {
            cases.push((
                format!("raw videotestsrc {fmt} {w}x{h}"),
                format!(
                    "videotestsrc pattern=ball num-buffers={n} ! \
                     video/x-raw,format={fmt},width={w},height={h},framerate=30/1 ! GATE ! \
                     fakesink sync=false"
                ),
            ));
        }
    }
    let encoder = if has("x264enc") || has("openh264enc") {
        None
    } else {
        Some("no H.264 encoder here (x264enc, openh264enc, avenc_h264 absent): the synthetic clips are MPEG-4 part 2")
    };
    for (w, h) in [(640u32, 480u32), (1920, 1080)] {
        match make_clip(tmp, w, h, n) {
            Some((clip, codec)) => cases.push((
                format!("decoded {codec} {w}x{h} (ball)"),
                format!(
                    "filesrc location=\"{}\" ! decodebin ! GATE ! fakesink sync=false",
                    clip.display()
                ),
            )),
            None => println!("SKIPPED: no encoder for the {w}x{h} decoded case"),
        }
    }
    for (name, w, h, codec) in [
        (
            "h264 640x480",
            640u32,
            480u32,
            &[
                "-c:v", "libx264", "-preset", "veryfast", "-pix_fmt", "yuv420p",
            ][..],
        ),
        (
            "h264 1920x1080",
            1920,
            1080,
            &[
                "-c:v", "libx264", "-preset", "veryfast", "-pix_fmt", "yuv420p",
            ][..],
        ),
        (
            "hevc 10-bit 1920x1080",
            1920,
            1080,
            &[
                "-c:v",
                "libx265",
                "-preset",
                "ultrafast",
                "-pix_fmt",
                "yuv420p10le",
                "-x265-params",
                "log-level=error",
            ][..],
        ),
    ] {
        let label = format!("decoded {name} tum_fr1_desk (real, 572 frames)");
        if !chosen_case(&label) {
            continue;
        }
        match desk_clip(tmp, &name.replace(' ', "_"), w, h, codec) {
            Some(clip) => cases.push((
                label,
                format!(
                    "filesrc location=\"{}\" ! decodebin ! GATE ! fakesink sync=false",
                    clip.display()
                ),
            )),
            None => {
                println!("SKIPPED: {label} (no ffmpeg, encoder or ../shared/data/tum_fr1_desk)")
            }
        }
    }
    if let Some(bear) = bear() {
        cases.push((
            "decoded h264 bear.mp4 854x480 (real)".into(),
            format!(
                "filesrc location=\"{}\" ! decodebin ! GATE ! fakesink sync=false",
                bear.display()
            ),
        ));
        cases.push((
            "decoded h264 bear.mp4 →1920x1080 (videoscale in both)".into(),
            format!(
                "filesrc location=\"{}\" ! decodebin ! videoscale ! \
                 video/x-raw,width=1920,height=1080 ! GATE ! fakesink sync=false",
                bear.display()
            ),
        ));
    }
    // The same decoded cases with a small queue before the gate (in both pipelines), as a
    // pipeline would run a gate in its own streaming thread: decoding and scoring overlap on two
    // cores. max-size-buffers=2 keeps the frames buffered before the first one is counted at most 2.
    let queued: Vec<(String, String)> = cases
        .iter()
        .filter(|(name, _)| name.starts_with("decoded"))
        .map(|(name, t)| {
            (
                format!("{name}, queue max-size-buffers=2 before the gate"),
                t.replace("! GATE", "! queue max-size-buffers=2 ! GATE"),
            )
        })
        .collect();
    cases.extend(queued);
    cases.retain(|(name, _)| chosen_case(name));
    if let Some(why) = encoder {
        println!("note: {why}");
    }
    // leangate with its default settings, and without the score step (`screen-step=0`: the
    // screening only where no score could change the decision) in the same interleaved runs.
    println!("| case | leangate fps | identity fps | leangate/identity wall time | the same with `screen-step=0` |");
    println!("|---|---|---|---|---|");
    for (case, template) in cases {
        let r = interleaved(
            &template,
            &[
                ("leangate", "leangate name=gate".to_string()),
                ("identity", "identity name=gate".to_string()),
                ("exact", "leangate name=gate screen-step=0".to_string()),
            ],
            reps,
        );
        println!(
            "| {case} | {:.1} | {:.1} | {:.3} | {:.3} |",
            r[0],
            r[1],
            r[1] / r[0],
            r[1] / r[2]
        );
    }
}

fn section_mpdecimate(reps: usize) {
    println!("\n## ffmpeg mpdecimate");
    let ok = std::process::Command::new("ffmpeg")
        .arg("-version")
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !ok {
        println!("SKIPPED: ffmpeg is not installed on this machine");
        return;
    }
    let Some(bear) = bear() else {
        println!("SKIPPED: bear.mp4 absent");
        return;
    };
    let run = |filter: bool| {
        let mut c = std::process::Command::new("ffmpeg");
        c.args(["-v", "error", "-nostdin", "-i"]).arg(&bear);
        if filter {
            c.args(["-vf", "mpdecimate"]);
        }
        c.args(["-f", "null", "-"]);
        let t = Instant::now();
        assert!(c.status().unwrap().success());
        t.elapsed().as_secs_f64()
    };
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for _ in 0..reps {
        a.push(run(true));
        b.push(run(false));
    }
    println!("| case | mpdecimate s | decode only s | ratio |");
    println!("|---|---|---|---|");
    println!(
        "| bear.mp4 | {:.3} | {:.3} | {:.3} |",
        median(&a),
        median(&b),
        median(&a) / median(&b)
    );
}

/// Median µs per frame of (fast `run`, reference `run_reference`), interleaved.
fn preprocess_us(format: PixelFormat, w: u32, h: u32, out: (u32, u32), reps: usize) -> (f64, f64) {
    let (planes, strides) = frame_planes(format, w as usize, h as usize);
    let mut p: [&[u8]; 3] = [&[], &[], &[]];
    for (i, plane) in planes.iter().enumerate() {
        p[i] = plane;
    }
    let frame = RawFrame {
        format,
        width: w,
        height: h,
        planes: p,
        strides,
    };
    let spec = TensorSpec {
        width: out.0,
        height: out.1,
        resize: ResizeMode::ShortSideCrop,
        mean: [0.485, 0.456, 0.406],
        std: [0.229, 0.224, 0.225],
    };
    let pre = Preprocessor::new(format, w, h, YuvMatrix::BT709, spec).unwrap();
    let mut out = vec![0f32; pre.spec().len()];
    let time = |fast: bool, iters: usize, out: &mut [f32]| {
        let t = Instant::now();
        for _ in 0..iters {
            if fast {
                pre.run(&frame, std::hint::black_box(&mut *out)).unwrap();
            } else {
                pre.run_reference(&frame, std::hint::black_box(&mut *out))
                    .unwrap();
            }
        }
        t.elapsed().as_secs_f64() * 1e6 / iters as f64
    };
    let once_fast = time(true, 3, &mut out);
    let once_ref = time(false, 2, &mut out);
    let it_fast = ((100_000.0 / once_fast) as usize).clamp(3, 5000);
    let it_ref = ((100_000.0 / once_ref) as usize).clamp(2, 5000);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for _ in 0..reps {
        a.push(time(true, it_fast, &mut out));
        b.push(time(false, it_ref, &mut out));
    }
    (median(&a), median(&b))
}

/// Output sizes: the embedded `leangate-s`'s input (what the element does per frame with the
/// default model), and a larger square input for bigger models.
const PREPROCESS_OUT: [(u32, u32); 2] = [(160, 120), (256, 256)];

/// `name` is in the comma-separated list in env `var` (case-insensitive), or `var` is unset.
/// Whether the pipeline case `name` is wanted: LEANGATE_BENCH_PIPELINES (comma-separated parts of
/// case names, e.g. `tum_fr1_desk,bear`) unset, or one of them in the name.
fn chosen_case(name: &str) -> bool {
    std::env::var("LEANGATE_BENCH_PIPELINES").map_or(true, |v| {
        v.split(',')
            .any(|x| !x.trim().is_empty() && name.contains(x.trim()))
    })
}

fn chosen(name: &str, var: &str) -> bool {
    std::env::var(var).map_or(true, |v| {
        v.split(',').any(|x| x.trim().eq_ignore_ascii_case(name))
    })
}

fn section_preprocess(reps: usize) {
    println!("\n## Preprocessing, short-side crop, one core, µs per frame (median of {reps}, interleaved): fast path (`run`) vs the previous float path (`run_reference`); 160x120 is the embedded model's input");
    println!("| format | size | → tensor | fast µs | float reference µs | speed-up |");
    println!("|---|---|---|---|---|---|");
    for (ow, oh) in PREPROCESS_OUT {
        for (w, h) in [(1920u32, 1080u32), (640, 480)] {
            // The 8-bit formats measured since the start, and one of each wider or packed
            // 4:2:2 layout the decoders added (the others share their code paths).
            for f in [
                PixelFormat::Rgb,
                PixelFormat::Rgbx,
                PixelFormat::Rgba,
                PixelFormat::Bgr,
                PixelFormat::Bgrx,
                PixelFormat::Bgra,
                PixelFormat::Gray8,
                PixelFormat::Nv12,
                PixelFormat::I420,
                PixelFormat::Yuy2,
                PixelFormat::I42010le,
                PixelFormat::P01010le,
                PixelFormat::Y42b,
                PixelFormat::I42210le,
                PixelFormat::Y444,
                PixelFormat::Y44410le,
                PixelFormat::Uyvy,
            ] {
                if !chosen(&format!("{f:?}"), "LEANGATE_BENCH_FORMATS")
                    || !chosen(&format!("{w}x{h}>{ow}x{oh}"), "LEANGATE_BENCH_SIZES")
                {
                    continue;
                }
                let (a, b) = preprocess_us(f, w, h, (ow, oh), reps);
                println!(
                    "| {f:?} | {w}x{h} | {ow}x{oh} | {a:.0} | {b:.0} | {:.1}x |",
                    b / a
                );
            }
        }
    }
}

/// The geometric prior's cost per frame at the embedded model's 160x120 input (one core): the
/// pyramid, the frame-to-frame homography (LK on the grid, then the RANSAC fit) and the raster
/// score of the chain, on a panning texture (every point tracks) and on real video (tum_fr1_desk's
/// first 300 frames as the student sees them; skipped without `../shared`).
fn section_geometry(reps: usize) {
    let (w, h) = (160usize, 120usize);
    let pan: Vec<Vec<f32>> = (0..100)
        .map(|k| {
            let dx = 1.5 * k as f32;
            let mut v = vec![0.0f32; w * h];
            for y in 0..h {
                for x in 0..w {
                    let (u, t) = (x as f32 + dx, y as f32);
                    v[y * w + x] = 128.0
                        + 50.0 * (u * 0.21).sin() * (t * 0.17).cos()
                        + 40.0 * ((u + t) * 0.09).sin()
                        + 30.0 * (u * 0.05 - t * 0.11).cos();
                }
            }
            v
        })
        .collect();
    println!("\n## geometric prior for a {w}x{h} model input, CPU time per frame (one thread, medians of {reps})");
    println!(
        "| frames | pyramid | LK on the grid | homography fit | raster score | tracker in all |"
    );
    println!("|---|---|---|---|---|---|");
    geometry_row("synthetic pan", &pan, w, h, reps);
    match real_greys(300) {
        Some((g, gw, gh)) => geometry_row("tum_fr1_desk (real)", &g, gw, gh, reps),
        None => println!("| tum_fr1_desk: SKIPPED (../shared absent) | | | | | |"),
    }
}

/// The first `n` frames of tum_fr1_desk as the embedded student's preprocessing sees them: RGB
/// images and the grey pictures of their input tensors (None without `../shared`).
fn real_frames(n: usize) -> Option<Vec<image::RgbImage>> {
    let dir = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/tum_fr1_desk/rgb"
    ));
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    files.sort();
    let frames: Vec<image::RgbImage> = files
        .iter()
        .take(n)
        .filter_map(|p| image::open(p).ok().map(|i| i.to_rgb8()))
        .collect();
    (!frames.is_empty()).then_some(frames)
}

/// The first `n` depth images of tum_fr1_desk (16-bit PNG, 5000 units per metre) as
/// `LeanGateDepthMeta` contents, beside [`real_frames`]' colour (one row per frame, same order).
fn real_depths(n: usize) -> Option<Vec<gstleangate::depth::DepthInput>> {
    let dir = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/tum_fr1_desk/depth"
    ));
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    files.sort();
    let depths: Vec<_> = files
        .iter()
        .take(n)
        .filter_map(|p| {
            let img = image::open(p).ok()?.to_luma16();
            let (w, h) = img.dimensions();
            let bytes: Vec<u8> = img.as_raw().iter().flat_map(|v| v.to_le_bytes()).collect();
            Some(gstleangate::depth::DepthInput {
                depth: gst::Buffer::from_mut_slice(bytes),
                format: gstleangate::depth::DepthFormat::Gray16Le,
                width: w,
                height: h,
                stride: 2 * w,
                scale: 5000.0,
                fx: 517.3,
                fy: 516.5,
                cx: 318.6,
                cy: 255.3,
            })
        })
        .collect();
    (!depths.is_empty()).then_some(depths)
}

fn real_greys(n: usize) -> Option<(Vec<Vec<f32>>, usize, usize)> {
    use gstleangate::{default_model, Scorer, ScorerOptions};
    let frames = real_frames(n)?;
    let (fw, fh) = frames[0].dimensions();
    let info = Scorer::load(&default_model(), &ScorerOptions::default())
        .ok()?
        .info()
        .clone();
    let pre = Preprocessor::new(
        PixelFormat::Rgb,
        fw,
        fh,
        YuvMatrix::BT709,
        info.spec.clone(),
    )
    .ok()?;
    let (w, h) = (info.spec.width as usize, info.spec.height as usize);
    let mut t = vec![0f32; info.spec.len()];
    let greys = frames
        .iter()
        .map(|f| {
            pre.run(&RawFrame::rgb(f.as_raw(), fw, fh), &mut t).unwrap();
            gstleangate::geometry::grey_from_tensor(&t, w, h, info.spec.mean, info.spec.std)
        })
        .collect();
    Some((greys, w, h))
}

/// CPU time of the calling thread, in seconds: what a stage costs, less sensitive than the wall
/// clock to the other load of a shared machine.
fn thread_cpu_s() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid timespec to fill; CLOCK_THREAD_CPUTIME_ID is always available on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// One row of the prior's table: CPU time per frame of each stage (medians of `reps`).
fn geometry_row(name: &str, frames: &[Vec<f32>], w: usize, h: usize, reps: usize) {
    use gstleangate::geometry::{
        fit_homography, grid, raster_tau, track_with, Pyramid, Tracker, GRID_X, GRID_Y, IDENTITY,
        LK_PRIOR,
    };
    let per_frame_us = |f: &mut dyn FnMut()| -> f64 {
        let mut v = Vec::new();
        for _ in 0..reps {
            let t0 = thread_cpu_s();
            f();
            v.push((thread_cpu_s() - t0) * 1e6 / frames.len() as f64);
        }
        median(&v)
    };
    let pyr: Vec<Pyramid> = frames
        .iter()
        .map(|g| Pyramid::for_prior(g.clone(), w, h))
        .collect();
    let t_pyr = per_frame_us(&mut || {
        for g in frames {
            std::hint::black_box(Pyramid::for_prior(g.clone(), w, h));
        }
    });
    let (pw, ph) = (pyr[0].width(), pyr[0].height());
    let pts = grid(pw, ph, GRID_X, GRID_Y);
    type Points = Vec<(f32, f32)>;
    let tracks: Vec<(Points, Points)> = (1..pyr.len())
        .map(|k| {
            pts.iter()
                .filter_map(|&p| track_with(&pyr[k - 1], &pyr[k], p, &LK_PRIOR).map(|q| (p, q)))
                .unzip()
        })
        .collect();
    let t_lk = per_frame_us(&mut || {
        for k in 1..pyr.len() {
            for &p in &pts {
                std::hint::black_box(track_with(&pyr[k - 1], &pyr[k], p, &LK_PRIOR));
            }
        }
    });
    let t_fit = per_frame_us(&mut || {
        for (s, d) in &tracks {
            std::hint::black_box(fit_homography(s, d));
        }
    });
    let mut hit = Vec::new();
    let t_raster = per_frame_us(&mut || {
        for _ in 0..frames.len() {
            std::hint::black_box(raster_tau(&IDENTITY, pw, ph, &mut hit));
        }
    });
    let t_all = per_frame_us(&mut || {
        let mut tr = Tracker::new();
        for (k, g) in frames.iter().enumerate() {
            tr.observe(Pyramid::for_prior(g.clone(), w, h));
            if k % 15 == 0 {
                tr.set_reference();
            }
            std::hint::black_box(tr.tau());
        }
    });
    println!(
        "| {name}, {} | {t_pyr:.0} µs | {t_lk:.0} µs | {t_fit:.0} µs | {t_raster:.0} µs | {t_all:.0} µs |",
        frames.len()
    );
}

/// Everything the element runs per frame, on real video in memory, one core: preprocessing of a
/// 640x480 RGB frame, the embedded student (its INT8 build, as on the CPU by default), the
/// geometric prior and the fusion ([`gstleangate::Utility`]), the gate. `model alone` is the
/// same with `geometry=false`. The frames are tum_fr1_desk's first 300 (decoded beforehand).
fn section_scoring(reps: usize) {
    use gstleangate::{
        default_model, Composed, Gate, GateConfig, Score, Scorer, ScorerOptions, Utility,
    };
    // Every configuration but the last runs the picture check, as the element does by default.
    println!("\n## The element's scoring per frame, one core (preprocessing 640x480 RGB, the embedded student, the prior, the gate): frames/s, median of {reps}, interleaved");
    let Some(frames) = real_frames(300) else {
        println!("SKIPPED: ../shared/data/tum_fr1_desk absent");
        return;
    };
    let (w, h) = frames[0].dimensions();
    let mut scorer = Scorer::load(&default_model(), &ScorerOptions::default()).unwrap();
    let info = scorer.info().clone();
    let pre =
        Preprocessor::new(PixelFormat::Rgb, w, h, YuvMatrix::BT709, info.spec.clone()).unwrap();
    let threshold = info.threshold.unwrap_or(0.5);
    // `check`: the picture check (`reject-junk`), as the element runs it by default.
    // `sharp`: the sharpness measure and the gate's look-back of 3 with its margin, as the
    // element runs them by default (`sharpness-lookback=3 sharpness-margin=0.05`). Not here: the
    // element's copy of each nearly-due held frame's model picture (230 KB; `cargo bench --bench
    // perf -- pipeline` has it).
    // Also where the time goes, stage by stage (seconds): preprocessing, the picture check + the
    // prior's tracking (`observe`), the composition (raster overlap, screening, the student when
    // it runs), the gate.
    // `step`: the model's leangate.score_step in the screening (`screen-step`, the default), or
    // none (`screen-step=0`).
    // `depth`: each frame's depth image beside it (`LeanGateDepthMeta`): the metric gate, the
    // model only where the pose fails.
    let depths = real_depths(frames.len());
    let mut run = |geometry: bool,
                   screen: bool,
                   check: bool,
                   step: bool,
                   sharp: bool,
                   depth: bool|
     -> (f64, f64, [f64; 4]) {
        let mut utility = Utility::new(info.geometry);
        utility.set_quality_check(check);
        utility.set_sharpness_measure(sharp);
        if !step {
            utility.set_score_step(None);
        }
        let mut gate = Gate::new(GateConfig {
            threshold,
            sharpness_lookback: if sharp { 3 } else { 0 },
            sharpness_margin: if sharp { 0.05 } else { 0.0 },
            ..Default::default()
        });
        let (mut reference, mut current) =
            (vec![0f32; info.spec.len()], vec![0f32; info.spec.len()]);
        let (t0, c0) = (Instant::now(), thread_cpu_s());
        let mut stages = [0f64; 4];
        for (k, f) in frames.iter().enumerate() {
            let s0 = Instant::now();
            pre.run(&RawFrame::rgb(f.as_raw(), w, h), &mut current)
                .unwrap();
            let s1 = Instant::now();
            let has_reference = gate.has_reference();
            utility.observe(Some((&current[..], &info.spec)), has_reference, geometry);
            if utility.quality().is_junk() {
                gate.decide(Score::Junk);
                continue;
            }
            if let (true, Some(d)) = (depth, depths.as_ref().and_then(|d| d.get(k))) {
                let frame = (&current[..], &info.spec);
                utility
                    .observe_depth(frame, Some(d), (w, h), has_reference)
                    .unwrap();
            }
            let s2 = Instant::now();
            let metric = utility.metric_tau().filter(|_| has_reference);
            let composed = (has_reference && metric.is_none()).then(|| {
                let model = || scorer.score(&reference, &current).map(f64::from);
                utility
                    .score_with(threshold, geometry, screen, model)
                    .unwrap()
            });
            let s3 = Instant::now();
            let score = match (metric, composed) {
                (Some(tau), _) => Score::Utility(tau),
                (None, c) => c.map_or(Score::NoReference, |c| Score::Utility(c.utility())),
            };
            if gate.decide_with(score, utility.sharpness()).keep {
                scorer.on_keep(matches!(composed, Some(Composed::Scored { .. })));
                std::mem::swap(&mut reference, &mut current);
                utility.on_keep();
            }
            let s4 = Instant::now();
            for (k, (a, b)) in [(s0, s1), (s1, s2), (s2, s3), (s3, s4)].iter().enumerate() {
                stages[k] += (*b - *a).as_secs_f64();
            }
        }
        let n = frames.len() as f64;
        (
            n / t0.elapsed().as_secs_f64(),
            n / (thread_cpu_s() - c0),
            stages.map(|t| t * 1e6 / n),
        )
    };
    let (mut alone, mut fused, mut exact, mut screened, mut unchecked, mut blunt) = (
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
    );
    let mut depthed = Vec::new();
    for _ in 0..reps {
        alone.push(run(false, false, true, true, true, false));
        fused.push(run(true, false, true, true, true, false));
        exact.push(run(true, true, true, false, true, false));
        screened.push(run(true, true, true, true, true, false));
        unchecked.push(run(true, true, false, true, true, false));
        blunt.push(run(true, true, true, true, false, false));
        if depths.is_some() {
            depthed.push(run(true, true, true, true, true, true));
        }
    }
    type Run = (f64, f64, [f64; 4]);
    let wall = |v: &[Run]| median(&v.iter().map(|x| x.0).collect::<Vec<_>>());
    let cpu = |v: &[Run]| median(&v.iter().map(|x| x.1).collect::<Vec<_>>());
    let (a, b, c, d) = (
        wall(&alone),
        wall(&fused),
        wall(&screened),
        wall(&unchecked),
    );
    let (ac, bc, cc, dc) = (cpu(&alone), cpu(&fused), cpu(&screened), cpu(&unchecked));
    let (e, ec) = (wall(&exact), cpu(&exact));
    let (f, fc) = (wall(&blunt), cpu(&blunt));
    println!(
        "model {} ({}), {} frames {w}x{h}, fusion: {}",
        info.name,
        info.precision,
        frames.len(),
        info.geometry
            .map_or("none".to_string(), |f| f.to_metadata())
    );
    println!("| configuration | frames/s (wall) | ms per frame (wall) | frames/s per CPU second of the thread |");
    println!("|---|---|---|---|");
    println!(
        "| model alone (`geometry=false`) | {a:.0} | {:.2} | {ac:.0} |",
        1e3 / a
    );
    println!(
        "| model + geometric prior (`screen=false`) | {b:.0} | {:.2} | {bc:.0} |",
        1e3 / b
    );
    println!(
        "| model + prior, screening only where no score could change the decision (`screen-step=0`) | {e:.0} | {:.2} | {ec:.0} |",
        1e3 / e
    );
    println!(
        "| model + prior, screening with the model's score step (the default) | {c:.0} | {:.2} | {cc:.0} |",
        1e3 / c
    );
    println!(
        "| the default without the picture check (`reject-junk=false`) | {d:.0} | {:.2} | {dc:.0} |",
        1e3 / d
    );
    println!(
        "| the default without the sharpness pass and look-back (`sharpness-lookback=0`) | {f:.0} | {:.2} | {fc:.0} |",
        1e3 / f
    );
    if !depthed.is_empty() {
        let (g, gc) = (wall(&depthed), cpu(&depthed));
        println!(
            "| the default with depth (RGB-D: `LeanGateDepthMeta`, the metric gate; the model where the pose fails) | {g:.0} | {:.2} | {gc:.0} |",
            1e3 / g
        );
        println!(
            "\nWith depth, per frame: {:.2}x the default's wall time, {:.2}x its CPU time",
            c / g,
            cc / gc
        );
    }
    println!("\n### Where the default's time goes per frame: microseconds, median of {reps}");
    println!("| stage | µs per frame |");
    println!("|---|---|");
    for (k, name) in [
        "preprocessing (640x480 RGB -> the model's tensor)",
        "picture check + prior tracking (grey, quality, sharpness, pyramid, LK, homography)",
        "composition (the prior's raster overlap, screening, the student when it runs)",
        "gate, keep bookkeeping",
    ]
    .iter()
    .enumerate()
    {
        let us = median(&screened.iter().map(|r| r.2[k]).collect::<Vec<_>>());
        println!("| {name} | {us:.0} |");
    }
}

fn main() {
    if let Some(arg) =
        std::env::args().find_map(|a| a.strip_prefix(streams::CHILD_FLAG).map(str::to_string))
    {
        gst::init().unwrap();
        gstleangate::plugin_register_static().expect("register the leangate plugin");
        streams::child(&arg);
        return;
    }
    let filter: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let wanted = |s: &str| filter.is_empty() || filter.iter().any(|f| s.contains(f.as_str()));
    gst::init().unwrap();
    gstleangate::plugin_register_static().expect("register the leangate plugin");
    let reps: usize = env_or("LEANGATE_BENCH_REPS", 5).max(1);
    let n: u64 = env_or("LEANGATE_BENCH_FRAMES", 200);
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    println!("# LeanGate perf bench: {cores} CPU cores, {reps} repetitions (medians), {n} frames per synthetic run, default student");
    let tmp = tempfile::tempdir().unwrap();
    if wanted("preprocess") {
        section_preprocess(reps);
    }
    if wanted("threads") {
        section_threads(reps);
    }
    if wanted("pipeline") {
        section_pipeline(reps, n, tmp.path());
    }
    if wanted("mpdecimate") {
        section_mpdecimate(reps);
    }
    if wanted("streams") {
        streams::section(reps);
    }
    if wanted("geometry") {
        section_geometry(reps);
    }
    if wanted("scoring") || wanted("stages") {
        section_scoring(reps);
    }
    let _ = Duration::ZERO;
}

mod streams {
    //! N pipelines of 640x480 in one process (a child process per configuration, so that its
    //! peak RSS is its own): aggregate frames/s through the gates, counted from the first buffer
    //! at any gate to the last EOS, and peak RSS.

    use super::*;

    pub const CHILD_FLAG: &str = "--streams-child=";

    /// (label, extra leangate properties)
    /// The first five run the element's default build (INT8 on the CPU); the last two the FP32
    /// build, for the INT8 / FP32 ratio in the same run.
    const CONFIGS: [(&str, &str); 7] = [
        ("separate sessions", "shared-session=false"),
        (
            "shared (default: a session per core)",
            "shared-session=true batch-size=1",
        ),
        (
            "shared, one session",
            "shared-session=true max-sessions=1 batch-size=1",
        ),
        (
            "shared, one session, batch-size=16",
            "shared-session=true max-sessions=1 batch-size=16",
        ),
        (
            "shared, a session per core, batch-size=4",
            "shared-session=true batch-size=4",
        ),
        (
            "FP32, separate sessions",
            "shared-session=false precision=fp32",
        ),
        (
            "FP32, shared (default)",
            "shared-session=true precision=fp32",
        ),
    ];
    /// CONFIGS[..DEFAULT_BUILD] run the default build.
    const DEFAULT_BUILD: usize = 5;

    fn rss_kib(key: &str) -> u64 {
        std::fs::read_to_string("/proc/self/status")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with(key))
                    .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
            })
            .unwrap_or(0)
    }

    /// In the child: run `n` pipelines with `props`, print "fps peak_rss_kib".
    pub fn child(arg: &str) {
        let mut it = arg.splitn(3, ',');
        let n: usize = it.next().unwrap().parse().unwrap();
        let frames: u64 = it.next().unwrap().parse().unwrap();
        let props = it.next().unwrap_or("");
        let count = Arc::new(AtomicU64::new(0));
        let first: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
        let pipelines: Vec<gst::Element> = (0..n)
            .map(|k| {
                let desc = format!(
                    "videotestsrc pattern=ball num-buffers={frames} ! \
                     video/x-raw,format=I420,width=640,height=480,framerate=30/1 ! \
                     leangate name=gate threshold=0.3 batch-timeout=2000 {props} ! \
                     fakesink sync=false"
                );
                let p = gst::parse::launch(&desc).unwrap();
                let gate = p
                    .downcast_ref::<gst::Bin>()
                    .unwrap()
                    .by_name("gate")
                    .unwrap();
                let src = p
                    .downcast_ref::<gst::Bin>()
                    .unwrap()
                    .iterate_sources()
                    .next()
                    .unwrap()
                    .unwrap();
                src.set_property_from_str("pattern", ["ball", "smpte", "snow", "pinwheel"][k % 4]);
                let (count, first) = (count.clone(), first.clone());
                gate.static_pad("sink").unwrap().add_probe(
                    gst::PadProbeType::BUFFER,
                    move |_, _| {
                        if count.fetch_add(1, Ordering::Relaxed) == 0 {
                            *first.lock().unwrap() = Some(Instant::now());
                        }
                        gst::PadProbeReturn::Ok
                    },
                );
                p
            })
            .collect();
        for p in &pipelines {
            p.set_state(gst::State::Playing).unwrap();
        }
        for p in &pipelines {
            let bus = p.bus().unwrap();
            for msg in bus.iter_timed(gst::ClockTime::from_seconds(600)) {
                match msg.view() {
                    gst::MessageView::Eos(_) => break,
                    gst::MessageView::Error(e) => panic!("{} ({:?})", e.error(), e.debug()),
                    _ => {}
                }
            }
        }
        let end = Instant::now();
        let hwm = rss_kib("VmHWM:");
        for p in &pipelines {
            p.set_state(gst::State::Null).unwrap();
        }
        let first = first.lock().unwrap().unwrap();
        let fps = count.load(Ordering::Relaxed) as f64 / end.duration_since(first).as_secs_f64();
        println!("RESULT {fps} {hwm}");
    }

    fn run_child(n: usize, frames: u64, props: &str) -> (f64, f64) {
        let out = std::process::Command::new(std::env::current_exe().unwrap())
            .arg(format!("{CHILD_FLAG}{n},{frames},{props}"))
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        let line = text
            .lines()
            .find(|l| l.starts_with("RESULT "))
            .unwrap_or_else(|| {
                panic!(
                    "child failed: {}\n{}",
                    text,
                    String::from_utf8_lossy(&out.stderr)
                )
            });
        let v: Vec<f64> = line
            .split_whitespace()
            .skip(1)
            .map(|x| x.parse().unwrap())
            .collect();
        (v[0], v[1])
    }

    /// Scorer only (no GStreamer): `k` threads each scoring `frames` tensors (a keep every 10th),
    /// aggregate scored frames/s.
    fn scorer_fps(k: usize, frames: usize, shared: bool, batch: usize, max_sessions: usize) -> f64 {
        use gstleangate::{ExecutionProvider, Scorer, ScorerOptions};
        let opts = ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            shared,
            batch_size: batch,
            batch_timeout: Duration::from_micros(2000),
            max_sessions,
            ..Default::default()
        };
        let mut scorers: Vec<Scorer> = (0..k)
            .map(|_| Scorer::load(&gstleangate::default_model(), &opts).unwrap())
            .collect();
        let len = scorers[0].info().spec.len();
        let pics: Vec<Vec<f32>> = (0..4)
            .map(|j| {
                (0..len)
                    .map(|i| (((i * (j + 3)) % 97) as f32) / 97.0)
                    .collect()
            })
            .collect();
        let t = Instant::now();
        std::thread::scope(|scope| {
            for s in scorers.iter_mut() {
                let pics = &pics;
                scope.spawn(move || {
                    for i in 1..=frames {
                        s.score(&pics[0], &pics[i % 4]).unwrap();
                        if i % 10 == 0 {
                            s.on_keep(false);
                        }
                    }
                });
            }
        });
        (k * frames) as f64 / t.elapsed().as_secs_f64()
    }

    pub fn section(reps: usize) {
        let reps = reps.min(3);
        println!("\n## Scorer only (no pipeline), default student, K threads scoring 100 frames each: aggregate scored frames/s (median of {reps}, interleaved)");
        println!("| threads K | separate sessions | shared (default: a session per core) | shared, one session | shared, one session, batch-size=K | shared default / separate | one session batched / separate |");
        println!("|---|---|---|---|---|---|---|");
        for k in [1usize, 4, 8] {
            let mut r = [Vec::new(), Vec::new(), Vec::new(), Vec::new()];
            for _ in 0..reps {
                r[0].push(scorer_fps(k, 100, false, 1, 0));
                r[1].push(scorer_fps(k, 100, true, 1, 0));
                r[2].push(scorer_fps(k, 100, true, 1, 1));
                r[3].push(scorer_fps(k, 100, true, k, 1));
            }
            let m: Vec<f64> = r.iter().map(|v| median(v)).collect();
            println!(
                "| {k} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {:.2} |",
                m[0],
                m[1],
                m[2],
                m[3],
                m[1] / m[0],
                m[3] / m[0]
            );
        }
        let frames: u64 = env_or("LEANGATE_BENCH_STREAM_FRAMES", 100);
        println!("\n## Many streams of 640x480 I420 (videotestsrc), one process, default student: aggregate frames/s through the gates and peak RSS (median of {reps}, configurations interleaved; {frames} frames per stream)");
        let counts = [1usize, 4, 8, 16];
        let mut res = vec![vec![(Vec::new(), Vec::new()); CONFIGS.len()]; counts.len()];
        for _ in 0..reps {
            for (ni, &n) in counts.iter().enumerate() {
                for (ci, (_, props)) in CONFIGS.iter().enumerate() {
                    let (fps, rss) = run_child(n, frames, props);
                    res[ni][ci].0.push(fps);
                    res[ni][ci].1.push(rss);
                }
            }
        }
        print!("| streams |");
        for (label, _) in CONFIGS {
            print!(" {label} fps | RSS MiB |");
        }
        println!(" best shared / separate fps | shared default / FP32 separate fps |");
        print!("|---|");
        for _ in CONFIGS {
            print!("---|---|");
        }
        println!("---|---|");
        let med: Vec<Vec<(f64, f64)>> = res
            .iter()
            .map(|r| r.iter().map(|(f, m)| (median(f), median(m))).collect())
            .collect();
        for (ni, &n) in counts.iter().enumerate() {
            print!("| {n} |");
            for (fps, rss) in &med[ni] {
                print!(" {fps:.1} | {:.1} |", rss / 1024.0);
            }
            let best = med[ni][1..DEFAULT_BUILD]
                .iter()
                .map(|x| x.0)
                .fold(0.0, f64::max);
            println!(
                " {:.2} | {:.2} |",
                best / med[ni][0].0,
                med[ni][1].0 / med[ni][DEFAULT_BUILD].0
            );
        }
        let (i1, i16) = (0, counts.len() - 1);
        print!("RSS per added stream (1 → 16), MiB:");
        for (ci, (label, _)) in CONFIGS.iter().enumerate() {
            print!(
                " {label} {:.2};",
                (med[i16][ci].1 - med[i1][ci].1) / 1024.0 / 15.0
            );
        }
        println!();
    }
}
