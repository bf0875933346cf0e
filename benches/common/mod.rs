//! What the pipeline benches share: run a pipeline to EOS, time one from the first buffer at its
//! `gate` element to EOS, and make textured test frames for the preprocessing figures (included
//! by path from `pipeline.rs` and `perf.rs`).
#![allow(dead_code)]

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use gst::prelude::*;
use gstleangate::PixelFormat;

/// Run a pipeline to EOS; panics on an error message.
pub fn run_to_eos(desc: &str, timeout: Duration) -> Vec<gst::Message> {
    let pipeline = gst::parse::launch(desc).unwrap_or_else(|e| panic!("`{desc}`: {e}"));
    let bus = pipeline.bus().unwrap();
    let _ = pipeline.set_state(gst::State::Playing);
    let mut msgs = Vec::new();
    let deadline = Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        assert!(!left.is_zero(), "`{desc}` did not finish in {timeout:?}");
        let Some(msg) = bus.timed_pop(gst::ClockTime::from_mseconds(left.as_millis() as u64))
        else {
            continue;
        };
        match msg.view() {
            gst::MessageView::Eos(_) => {
                msgs.push(msg);
                break;
            }
            gst::MessageView::Error(e) => {
                let _ = pipeline.set_state(gst::State::Null);
                panic!(
                    "`{desc}`: {} ({})",
                    e.error(),
                    e.debug().map(|d| d.to_string()).unwrap_or_default()
                );
            }
            _ => msgs.push(msg),
        }
    }
    pipeline.set_state(gst::State::Null).unwrap();
    msgs
}

pub struct RunResult {
    pub fps: f64,
    pub frames: u64,
    pub startup_ms: f64,
    pub keep_ratio: Option<f64>,
    pub inference_mean_us: Option<f64>,
    pub provider: Option<String>,
}

/// Run `desc` (which names the measured element `gate`) and time it from the first buffer at
/// the gate's sink pad to EOS.
pub fn measure(desc: &str) -> RunResult {
    let pipeline = gst::parse::launch(desc).unwrap_or_else(|e| panic!("`{desc}`: {e}"));
    let bin = pipeline.downcast_ref::<gst::Bin>().unwrap();
    let gate = bin.by_name("gate").expect("an element named gate");
    let count = Arc::new(AtomicU64::new(0));
    let first: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    {
        let (count, first) = (count.clone(), first.clone());
        gate.static_pad("sink")
            .unwrap()
            .add_probe(gst::PadProbeType::BUFFER, move |_, _| {
                if count.fetch_add(1, Ordering::Relaxed) == 0 {
                    *first.lock().unwrap() = Some(Instant::now());
                }
                gst::PadProbeReturn::Ok
            });
    }
    let bus = pipeline.bus().unwrap();
    let t0 = Instant::now();
    let _ = pipeline.set_state(gst::State::Playing);
    let mut stats = None;
    let end = loop {
        let msg = bus
            .timed_pop(gst::ClockTime::from_seconds(300))
            .unwrap_or_else(|| panic!("`{desc}` timed out"));
        match msg.view() {
            gst::MessageView::Eos(_) => break Instant::now(),
            gst::MessageView::Error(e) => panic!(
                "`{desc}`: {} ({})",
                e.error(),
                e.debug().map(|d| d.to_string()).unwrap_or_default()
            ),
            gst::MessageView::Element(e) => {
                if let Some(s) = e.structure().filter(|s| s.name() == "leangate-stats") {
                    stats = Some(s.to_owned());
                }
            }
            _ => {}
        }
    };
    pipeline.set_state(gst::State::Null).unwrap();
    let frames = count.load(Ordering::Relaxed);
    let first = first.lock().unwrap().expect("at least one buffer");
    let secs = end.duration_since(first).as_secs_f64();
    RunResult {
        fps: frames as f64 / secs,
        frames,
        startup_ms: first.duration_since(t0).as_secs_f64() * 1e3,
        keep_ratio: stats.as_ref().and_then(|s| s.get::<f64>("keep-ratio").ok()),
        inference_mean_us: stats
            .as_ref()
            .and_then(|s| s.get::<f64>("inference-mean-us").ok()),
        provider: stats
            .as_ref()
            .and_then(|s| s.get::<String>("execution-provider").ok()),
    }
}

/// A deterministic, textured plane of `len` bytes.
pub fn noise(len: usize, seed: u32) -> Vec<u8> {
    let mut x = 0x9E37_79B9u32 ^ seed;
    (0..len)
        .map(|i| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            ((i as u32 / 7) as u8).wrapping_add((x >> 24) as u8 / 4)
        })
        .collect()
}

/// Planes and strides of a tightly packed `w`x`h` frame of `format`, filled by [`noise`].
pub fn frame_planes(format: PixelFormat, w: usize, h: usize) -> (Vec<Vec<u8>>, [isize; 3]) {
    let mut strides = [0isize; 3];
    let mut planes = Vec::new();
    for (p, (row_bytes, rows)) in format.plane_sizes(w, h).into_iter().enumerate() {
        if rows > 0 {
            planes.push(noise(row_bytes * rows, p as u32 + 1));
            strides[p] = row_bytes as isize;
        }
    }
    (planes, strides)
}
