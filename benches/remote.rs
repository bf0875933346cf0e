//! Remote scoring against local scoring: 1 and 8 client pipelines in one process against one
//! KServe V2 server on loopback (NVIDIA Triton through PyTriton, `scripts/v2_server.py`, CPU,
//! serving the shipped student), next to the same pipelines scoring locally on ONNX Runtime.
//!
//!     cargo bench --bench remote
//!
//! Each client: `videotestsrc pattern=ball num-buffers=F ! video/x-raw,format=RGB,320x240 !
//! leangate mode=annotate [server=URL] ! fakesink sync=false`, the default split student
//! (`leangate-s`: encoder on the server, head in the element; locally both in the element with
//! `threads=1`). Shown: aggregate frames/s over all clients (first buffer to last EOS), p50/p99
//! of the per-frame `inference-us` (preprocessing + scoring, the round trip included when
//! remote), the server round trip p50/p99 from `leangate-stats` (worst client), failed requests.
//!
//! Environment: LEANGATE_BENCH_FRAMES (frames per client, default 200), LEANGATE_BENCH_CLIENTS
//! (default "1,8"). The remote rows are skipped, saying why, when `.venv-triton` is absent.

#[path = "../tests/v2server/mod.rs"]
mod v2server;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use gst::prelude::*;
use gstleangate::{GateMeta, StatsMessage};

fn env_or<T: std::str::FromStr>(k: &str, d: T) -> T {
    std::env::var(k)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(d)
}

struct Row {
    clients: usize,
    backend: &'static str,
    fps: f64,
    p50_us: u64,
    p99_us: u64,
    server_p50_us: Option<u64>,
    server_p99_us: Option<u64>,
    failed: u64,
    frames: usize,
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    if sorted.is_empty() {
        return 0;
    }
    let rank = ((p / 100.0) * sorted.len() as f64).ceil().max(1.0) as usize;
    sorted[rank.min(sorted.len()) - 1]
}

/// Run `clients` pipelines at once; `server` None = local scoring.
fn run(clients: usize, frames: u32, server: Option<&str>) -> Row {
    let props = match server {
        Some(url) => format!("server={url} server-timeout=5000"),
        None => "threads=1".to_string(),
    };
    let samples = Arc::new(Mutex::new(Vec::<u64>::new()));
    let first = Arc::new(Mutex::new(None::<Instant>));
    let mut pipelines = Vec::new();
    for _ in 0..clients {
        let desc = format!(
            "videotestsrc pattern=ball num-buffers={frames} ! \
             video/x-raw,format=RGB,width=320,height=240,framerate=30/1 ! \
             leangate name=gate mode=annotate {props} ! fakesink sync=false"
        );
        let p = gst::parse::launch(&desc)
            .unwrap()
            .downcast::<gst::Pipeline>()
            .unwrap();
        let gate = p.by_name("gate").unwrap();
        let (samples, first) = (samples.clone(), first.clone());
        gate.static_pad("src")
            .unwrap()
            .add_probe(gst::PadProbeType::BUFFER, move |_, info| {
                if let Some(b) = info.buffer() {
                    first.lock().unwrap().get_or_insert_with(Instant::now);
                    if let Some(m) = GateMeta::read(b) {
                        if !m.utility.is_nan() {
                            samples.lock().unwrap().push(m.inference_us);
                        }
                    }
                }
                gst::PadProbeReturn::Ok
            });
        // Start (model load, server checks) before the clock runs: PAUSED prerolls.
        p.set_state(gst::State::Paused).unwrap();
        pipelines.push(p);
    }
    for p in &pipelines {
        let _ = p.state(gst::ClockTime::from_seconds(60));
    }
    *first.lock().unwrap() = None;
    samples.lock().unwrap().clear();
    for p in &pipelines {
        p.set_state(gst::State::Playing).unwrap();
    }
    let mut server_p50 = None;
    let mut server_p99 = None;
    let mut failed = 0;
    let deadline = Instant::now() + Duration::from_secs(600);
    for p in &pipelines {
        let bus = p.bus().unwrap();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            assert!(!left.is_zero(), "benchmark pipeline did not finish");
            let Some(msg) = bus.timed_pop(gst::ClockTime::from_mseconds(left.as_millis() as u64))
            else {
                continue;
            };
            match msg.view() {
                gst::MessageView::Eos(_) => break,
                gst::MessageView::Error(e) => panic!("{}", e.error()),
                gst::MessageView::Element(e) => {
                    let Some(s) = e.structure() else { continue };
                    let Ok(stats) = StatsMessage::from_structure(s) else {
                        continue;
                    };
                    if let Some(srv) = stats.server {
                        server_p50 = server_p50.max(Some(srv.latency_p50_us));
                        server_p99 = server_p99.max(Some(srv.latency_p99_us));
                        failed += srv.failed_requests;
                    }
                }
                _ => {}
            }
        }
    }
    let elapsed = first
        .lock()
        .unwrap()
        .map(|t| t.elapsed())
        .unwrap_or_default();
    for p in &pipelines {
        p.set_state(gst::State::Null).unwrap();
    }
    let mut s = samples.lock().unwrap().clone();
    s.sort_unstable();
    let total = clients * frames as usize;
    Row {
        clients,
        backend: if server.is_some() { "remote" } else { "local" },
        fps: total as f64 / elapsed.as_secs_f64().max(1e-9),
        p50_us: percentile(&s, 50.0),
        p99_us: percentile(&s, 99.0),
        server_p50_us: server_p50,
        server_p99_us: server_p99,
        failed,
        frames: total,
    }
}

fn main() {
    gst::init().unwrap();
    gstleangate::plugin_register_static().unwrap();
    let frames: u32 = env_or("LEANGATE_BENCH_FRAMES", 200);
    let clients: Vec<usize> = std::env::var("LEANGATE_BENCH_CLIENTS")
        .unwrap_or_else(|_| "1,8".into())
        .split(',')
        .filter_map(|c| c.trim().parse().ok())
        .collect();
    let server = match v2server::python() {
        Ok(_) => match v2server::V2Server::start(&v2server::student_models()[..1]) {
            Ok(s) => Some(s),
            Err(e) => {
                eprintln!("remote rows skipped: the V2 server did not start: {e}");
                None
            }
        },
        Err(why) => {
            eprintln!("remote rows skipped: {why}");
            None
        }
    };
    let mut rows = Vec::new();
    for &n in &clients {
        rows.push(run(n, frames, None));
        if let Some(s) = &server {
            rows.push(run(n, frames, Some(&s.url())));
        }
    }
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(0);
    println!(
        "\nremote scoring (leangate-s split: encoder on a PyTriton/Triton 2.51 CPU server on \
         127.0.0.1, head in the element) vs local ONNX Runtime (threads=1 per element); 320x240 \
         RGB, {frames} frames per client, {cores} CPU cores shared by clients and server\n"
    );
    println!(
        "{:>7}  {:<7} {:>8} {:>12} {:>10} {:>10} {:>14} {:>14} {:>7}",
        "clients",
        "backend",
        "frames",
        "frames/s",
        "p50 us",
        "p99 us",
        "server p50 us",
        "server p99 us",
        "failed"
    );
    for r in &rows {
        let opt = |v: Option<u64>| v.map(|v| v.to_string()).unwrap_or_else(|| "-".into());
        println!(
            "{:>7}  {:<7} {:>8} {:>12.1} {:>10} {:>10} {:>14} {:>14} {:>7}",
            r.clients,
            r.backend,
            r.frames,
            r.fps,
            r.p50_us,
            r.p99_us,
            opt(r.server_p50_us),
            opt(r.server_p99_us),
            r.failed
        );
    }
    drop(server);
}
