//! Soak (issue 8): push `LEANGATE_SOAK_FRAMES` (default 1,000,000) small frames through
//! `leangate` with the fixture model `mad.onnx` (64x48 RGB, a mix of kept and dropped frames,
//! `stats-interval` set so that statistics are posted all along, property changes every 10,000
//! frames) and sample the process's resident memory. Not part of CI:
//!
//! ```sh
//! cargo bench --bench soak                          # or: LEANGATE_SOAK_FRAMES=200000 cargo bench --bench soak
//! ```
//!
//! Prints RSS every 100,000 frames and fails (exit 1) if RSS after warm-up (the first 100,000
//! frames) grows by more than 1 MiB, or if a frame is lost.
//!
//! `cargo bench --bench soak -- churn` (issue 22, item 4) instead creates and destroys elements:
//! `LEANGATE_CHURN_ROUNDS` (default 50) rounds of 50 pipelines `videotestsrc num-buffers=5 !
//! leangate batch-size=B ! fakesink` run together (the embedded student on the CPU, shared
//! sessions, batch sizes 1, 4, 7 and 10 mixed; `LEANGATE_CHURN_BATCH=1` for all at 1), and prints
//! RSS after each round; it fails (exit 1) if RSS grows by more than 24 MiB from round 20 to
//! the end (before the fix of issue 22: +250 MiB).

use std::time::Instant;

use gst::prelude::*;

const W: u32 = 64;
const H: u32 = 48;

fn rss_kib() -> u64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

fn texture(seed: u32) -> Vec<u8> {
    let mut v = Vec::with_capacity((W * H * 3) as usize);
    for y in 0..H {
        for x in 0..W {
            let a = (x * (3 + seed) + y * (7 + 2 * seed)) % 256;
            v.extend_from_slice(&[a as u8, ((x ^ y) * (seed + 1) % 256) as u8, (255 - a) as u8]);
        }
    }
    v
}

/// One round of `churn`: 50 elements with mixed batch sizes, created, run, destroyed.
fn churn_round(sizes: &[u32]) {
    let pipelines: Vec<gst::Element> = (0..50)
        .map(|i| {
            gst::parse::launch(&format!(
                "videotestsrc num-buffers=5 pattern={} ! video/x-raw,format=RGB,width=160,\
                 height=120 ! leangate execution-provider=cpu batch-size={} ! fakesink",
                i % 20,
                sizes[i % sizes.len()]
            ))
            .unwrap()
        })
        .collect();
    for p in &pipelines {
        p.set_state(gst::State::Playing).unwrap();
    }
    for p in &pipelines {
        let bus = p.bus().unwrap();
        let msg = bus.timed_pop_filtered(
            gst::ClockTime::from_seconds(60),
            &[gst::MessageType::Eos, gst::MessageType::Error],
        );
        match msg.as_ref().map(|m| m.view()) {
            Some(gst::MessageView::Eos(_)) => {}
            other => panic!("churn: a pipeline did not finish: {other:?}"),
        }
    }
    for p in &pipelines {
        p.set_state(gst::State::Null).unwrap();
    }
}

fn churn() {
    let rounds: usize = std::env::var("LEANGATE_CHURN_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(50);
    // `LEANGATE_CHURN_BATCH=1`: every element at batch size 1 (the control).
    let sizes: Vec<u32> = match std::env::var("LEANGATE_CHURN_BATCH") {
        Ok(b) => vec![b.parse().expect("LEANGATE_CHURN_BATCH: a batch size")],
        Err(_) => vec![1, 4, 7, 10],
    };
    println!(
        "churn: {rounds} rounds of 50 elements (batch sizes {sizes:?}), created, run, destroyed"
    );
    let t0 = Instant::now();
    let mut rss = Vec::new();
    for r in 0..rounds {
        churn_round(&sizes);
        rss.push(rss_kib());
        println!("  round {:>3}  RSS {:>7} KiB", r + 1, rss[r]);
    }
    let warm = rss[19.min(rounds - 1)];
    let end = *rss.last().unwrap();
    println!(
        "churn: RSS after round 1 {} KiB, round 20 {warm} KiB, round {rounds} {end} KiB ({:+} KiB \
         from round 20), {:.1} s",
        rss[0],
        end as i64 - warm as i64,
        t0.elapsed().as_secs_f64()
    );
    if end > warm + 24 * 1024 {
        println!("FAIL: RSS grew by more than 24 MiB after round 20");
        std::process::exit(1);
    }
}

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return; // `cargo test --benches` / `cargo bench -- --list`
    }
    if std::env::args().any(|a| a == "churn") {
        gst::init().unwrap();
        gstleangate::plugin_register_static().unwrap();
        churn();
        return;
    }
    let frames: u64 = std::env::var("LEANGATE_SOAK_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1_000_000);
    gst::init().unwrap();
    gstleangate::plugin_register_static().unwrap();
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/mad.onnx");
    let e = gst::ElementFactory::make("leangate")
        .property("model", model)
        .property("stats-interval", 10_000_000u64)
        .property("threshold", 0.05f64)
        .build()
        .unwrap();
    let bus = gst::Bus::new();
    e.set_bus(Some(&bus));
    let mut h = gst_check::Harness::with_element(&e, Some("sink"), Some("src"));
    h.set_src_caps_str(&format!(
        "video/x-raw,format=RGB,width={W},height={H},framerate=30/1"
    ));
    h.play();
    let pics: Vec<gst::Buffer> = (0..4)
        .map(|s| gst::Buffer::from_mut_slice(texture(s)))
        .collect();
    let t0 = Instant::now();
    let (mut out, mut stats, mut gaps) = (0u64, 0u64, 0u64);
    let mut samples = Vec::new();
    let mut warm = 0;
    println!("soak: {frames} frames of {W}x{H} RGB through leangate (mad.onnx)");
    for i in 0..frames {
        let mut b = pics[((i / 3) % 4) as usize].copy();
        {
            let b = b.get_mut().unwrap();
            b.set_pts(gst::ClockTime::from_nseconds(i * 33_333_333));
            b.set_duration(gst::ClockTime::from_nseconds(33_333_333));
        }
        h.push(b).expect("push");
        while let Some(b) = h.try_pull() {
            drop(b);
            out += 1;
        }
        while let Some(ev) = h.try_pull_event() {
            if ev.type_() == gst::EventType::Gap {
                gaps += 1;
            }
        }
        while let Some(m) = bus.pop() {
            if m.structure()
                .is_some_and(|s| s.name() == gstleangate::STATS_MESSAGE)
            {
                stats += 1;
            }
        }
        if i % 10_000 == 9_999 {
            e.set_property(
                "threshold",
                if i % 20_000 == 9_999 { 0.04f64 } else { 0.05 },
            );
        }
        if (i + 1) % 100_000 == 0 || i + 1 == frames {
            let rss = rss_kib();
            if i + 1 == 100_000 {
                warm = rss;
            }
            samples.push((i + 1, rss));
            println!(
                "  {:>8} frames  RSS {:>7} KiB  out {out}  gaps {gaps}  stats {stats}  {:.0} frames/s",
                i + 1,
                rss,
                (i + 1) as f64 / t0.elapsed().as_secs_f64()
            );
        }
    }
    let frames_in: u64 = e.property("frames-in");
    let kept: u64 = e.property("frames-kept");
    drop(h);
    let start = samples.first().map(|s| s.1).unwrap_or(0);
    let end = samples.last().map(|s| s.1).unwrap_or(0);
    println!(
        "soak: frames in {frames_in}, kept {kept}, out {out}, gap events {gaps}, stats messages \
         {stats}; RSS at 100k {warm} KiB, first sample {start} KiB, end {end} KiB ({:+} KiB after \
         warm-up), {:.1} s",
        end as i64 - warm as i64,
        t0.elapsed().as_secs_f64()
    );
    let mut ok = true;
    if frames_in != frames || out != kept || kept + gaps != frames {
        println!("FAIL: frames lost or duplicated");
        ok = false;
    }
    if warm > 0 && end > warm + 1024 {
        println!("FAIL: RSS grew by more than 1 MiB after warm-up");
        ok = false;
    }
    if !ok {
        std::process::exit(1);
    }
}
