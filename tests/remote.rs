//! Remote scoring (issue 10) against a real KServe V2 server on loopback: NVIDIA Triton
//! Inference Server through PyTriton, started by the tests (tests/v2server, scripts/v2_server.py)
//! and serving the shipped student `leangate-s` (pair, encoder and head). Skipped, with a
//! message, when `.venv-triton` is not installed (`scripts/setup.sh` installs it).
//!
//! - remote and local scoring give the same decisions on a clip, utilities within 1e-5, for the
//!   split model (encoder on the server, head here: one encoder request per scored frame,
//!   counted on the server) and the pair model;
//! - the server killed mid-stream: frames keep flowing (kept, reason `error`), a rate-limited
//!   warning names the server, and scoring resumes when it is back; a slow server times out
//!   and fails open the same way;
//! - start errors name the URL and what failed: unreachable, unknown model, wrong contract,
//!   unsupported scheme;
//! - a server that stops answering (a proxy turned black hole) does not hold up a pipeline
//!   stopping: the request in flight is interrupted, not waited out.
//!
//! Hostile servers (a scripted V2 server, tests/v2server/scripted.rs, with the fixture models;
//! these always run): credentials in the URL are sent but never shown; one in-flight bound per
//! server however its URL is spelled, the smallest when elements disagree; out-of-range
//! utilities and impossible feature shapes fail open; an answered error is not "unreachable";
//! a redirected inference is an error, never a GET.

mod common;
mod v2server;

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::*;
use gst::prelude::*;
use gstleangate::{Reason, StatsMessage};
use serde_json::json;
use v2server::scripted::{Reply, Scripted, Served};
use v2server::V2Server;

const W: u32 = 320;
const H: u32 = 240;

/// A pan over a textured strip at varying speed (pauses, slow and fast stretches): frames that
/// add nothing and frames that add a lot.
fn clip(n: usize) -> Vec<Vec<u8>> {
    let strip_w = 4000u32;
    let pix = |x: u32, y: u32| -> [u8; 3] {
        let h = |a: u32, b: u32, s: u32| {
            let v = (a / s).wrapping_mul(73_856_093) ^ (b / s).wrapping_mul(19_349_663);
            (v.wrapping_mul(2_654_435_761) >> 24) as u8
        };
        let r = h(x, y, 16) / 2 + h(x, y, 5) / 2;
        let g = h(x + 7, y, 32) / 2 + h(x, y + 3, 9) / 2;
        let b = ((x as f32 * 0.05).sin() * 60.0 + 128.0) as u8 / 2 + h(x, y, 48) / 2;
        [r, g, b]
    };
    let mut x0 = 0u32;
    (0..n)
        .map(|i| {
            let speed = match (i / 10) % 4 {
                0 => 0,
                1 => 3,
                2 => 12,
                _ => 40,
            };
            x0 = (x0 + speed).min(strip_w - W);
            let mut f = Vec::with_capacity((W * H * 3) as usize);
            for y in 0..H {
                for x in 0..W {
                    f.extend_from_slice(&pix(x0 + x, y));
                }
            }
            f
        })
        .collect()
}

/// Run `frames` through `leangate` (annotate mode, with `props`); every frame's metadata, and
/// the element.
fn gate(props: &str, frames: &[Vec<u8>]) -> (Vec<gstleangate::GateMeta>, gst::Element) {
    let mut h = harness(&format!("mode=annotate {props}"), &rgb_caps(W, H));
    let mut metas = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        h.push(buffer(f.clone(), i as u64 * 33)).unwrap();
        metas.extend(drain(&mut h).iter().map(meta));
    }
    let e = h.element().unwrap();
    (metas, e)
}

fn stats_now(e: &gst::Element, bus: &gst::Bus) -> StatsMessage {
    // An EOS makes the element post its stats.
    let sink = e.static_pad("sink").unwrap();
    let _ = sink.send_event(gst::event::Eos::new());
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline {
        if let Some(m) = bus.timed_pop(gst::ClockTime::from_mseconds(100)) {
            if let gst::MessageView::Element(el) = m.view() {
                if let Some(s) = el.structure() {
                    if s.name() == gstleangate::STATS_MESSAGE {
                        return StatsMessage::from_structure(s).unwrap();
                    }
                }
            }
        }
    }
    panic!("no leangate-stats after EOS");
}

fn compare(local: &[gstleangate::GateMeta], remote: &[gstleangate::GateMeta]) {
    assert_eq!(local.len(), remote.len());
    let mut worst = 0f64;
    for (i, (l, r)) in local.iter().zip(remote).enumerate() {
        assert_eq!(
            (l.keep, l.reason),
            (r.keep, r.reason),
            "frame {i}: local {l:?} remote {r:?}"
        );
        assert_ne!(r.reason, Reason::Error, "frame {i} failed remotely");
        if l.utility.is_nan() {
            assert!(r.utility.is_nan(), "frame {i}");
        } else {
            let d = (l.utility - r.utility).abs();
            worst = worst.max(d);
            assert!(
                d <= 1e-5,
                "frame {i}: local {} remote {}",
                l.utility,
                r.utility
            );
        }
    }
    let kept = remote.iter().filter(|m| m.keep).count();
    eprintln!(
        "{} frames, {kept} kept; largest |local - remote| utility difference {worst:.2e}",
        remote.len()
    );
    assert!(
        kept > 2 && kept < remote.len() - 2,
        "the clip must keep some and drop some"
    );
}

/// The scenarios that share one server (CPU is scarce: one server start, and one scenario at a
/// time so that the server-side request counts are theirs). The server is dropped, and so
/// stopped, at the end of the test, whatever happens.
/// The V2 server script loads Microsoft's onnxruntime wheel, which writes a device id and queued
/// usage events under `~/.cache/Microsoft` when it loads unless `ORT_DISABLE_TELEMETRY` is set
/// first: the script sets it, so in a fresh HOME it writes nothing there.
#[test]
fn the_v2_server_script_leaves_nothing_in_home_or_tmpdir() {
    let py = match v2server::python() {
        Ok(py) => py,
        Err(why) => {
            eprintln!("SKIPPED: {why}");
            return;
        }
    };
    let home = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(py)
        .arg(v2server::repo_root().join("scripts/v2_server.py"))
        .arg("--help")
        .env("HOME", home.path())
        .env_remove("ORT_DISABLE_TELEMETRY")
        .env_remove("XDG_CACHE_HOME")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let left = files_below(home.path());
    assert!(left.is_empty(), "left in HOME: {left:?}");

    // Served as the docs run it (no --workspace) and stopped with SIGTERM: nothing in HOME
    // (PyTriton's own default workspace is ~/.cache/pytriton, which it leaves behind) nor in
    // TMPDIR.
    let tmp = tempfile::tempdir().unwrap();
    let port = v2server::free_port();
    let mut child = std::process::Command::new(v2server::python().unwrap())
        .arg(v2server::repo_root().join("scripts/v2_server.py"))
        .arg(v2server::repo_root().join("models/leangate-s-head.onnx"))
        .args(["--http-port", &port.to_string()])
        .args(["--grpc-port", &v2server::free_port().to_string()])
        .args(["--metrics-port", &v2server::free_port().to_string()])
        .env("HOME", home.path())
        .env("TMPDIR", tmp.path())
        .env_remove("XDG_CACHE_HOME")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let url = format!("http://127.0.0.1:{port}/v2/models/leangate-s-head/ready");
    let t0 = Instant::now();
    let mut ready = false;
    while !ready && t0.elapsed() < Duration::from_secs(90) {
        std::thread::sleep(Duration::from_millis(200));
        ready = ureq::get(&url).call().is_ok();
        assert!(child.try_wait().unwrap().is_none(), "the server exited");
    }
    let running = files_below(tmp.path());
    std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    let status = child.wait().unwrap();
    assert!(ready, "not ready in 90 s");
    assert!(status.success(), "{status}");
    assert!(
        !running.is_empty(),
        "its workspace is in TMPDIR while it runs"
    );
    let left = files_below(home.path());
    assert!(left.is_empty(), "left in HOME: {left:?}");
    let left = files_below(tmp.path());
    assert!(left.is_empty(), "left in TMPDIR: {left:?}");
}

#[test]
fn against_the_student_on_a_v2_server() {
    let Some(server) = v2server::start_or_skip(&v2server::student_models()) else {
        return;
    };
    eprintln!("-- split model");
    split_model_remote_matches_local_with_one_encoder_request_per_frame(&server);
    eprintln!("-- pair model");
    pair_model_remote_matches_local(&server);
    eprintln!("-- start errors");
    unknown_model_and_wrong_contract_are_start_errors_naming_them(&server);
    eprintln!("-- hung requests");
    a_hung_request_is_interrupted_by_stopping(&server);
    let pgid = server.pgid().unwrap();
    drop(server);
    assert!(
        !v2server::group_alive(pgid, Duration::from_secs(5)),
        "the server left processes"
    );
}

fn split_model_remote_matches_local_with_one_encoder_request_per_frame(server: &V2Server) {
    let frames = clip(80);
    // The server runs the FP32 encoder, so the element runs the FP32 head here (precision auto
    // with a server): the local reference is the FP32 build.
    // The model scores every frame (`screen=false`): one encoder request per scored frame.
    let (local, _) = gate("precision=fp32 screen=false", &frames);
    let before = server.count("leangate-s-encoder");
    let head_before = server.count("leangate-s-head");
    init();
    let bus = gst::Bus::new();
    let e = element(&format!(
        "mode=annotate screen=false server={}",
        server.url()
    ));
    e.set_bus(Some(&bus));
    let mut h = gst_check::Harness::with_element(&e, Some("sink"), Some("src"));
    h.set_src_caps_str(&rgb_caps(W, H));
    h.play();
    let mut remote = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        h.push(buffer(f.clone(), i as u64 * 33)).unwrap();
        remote.extend(drain(&mut h).iter().map(meta));
    }
    compare(&local, &remote);
    // The start's dry run encodes a blank reference and a blank current frame; then the first
    // frame (the reference, not scored) is encoded once when the second is scored, and every
    // scored frame once: never two encoder runs for one scored frame.
    let served = server.count("leangate-s-encoder") - before;
    assert_eq!(
        served,
        2 + frames.len() as u64,
        "encoder requests on the server"
    );
    assert_eq!(
        server.count("leangate-s-head") - head_before,
        0,
        "the head runs in the element"
    );
    let s = stats_now(&e, &bus);
    let srv = s.server.expect("server fields in leangate-stats");
    assert_eq!(srv.server, server.url());
    assert_eq!(srv.server_model, "leangate-s-encoder");
    assert_eq!(srv.requests, frames.len() as u64);
    assert_eq!(srv.failed_requests, 0);
    assert!(srv.latency_p50_us > 0 && srv.latency_p99_us >= srv.latency_p50_us);
    assert_eq!(s.execution_provider, "remote");
    assert_eq!(s.model_precision, "fp32");
    eprintln!(
        "server latency p50 {} us, p99 {} us",
        srv.latency_p50_us, srv.latency_p99_us
    );
    // Screening on (the default): the frames the prior alone drops never reach the server, and
    // every decision is the same.
    let before = server.count("leangate-s-encoder");
    let (screened, e) = gate(&format!("server={}", server.url()), &frames);
    let n = e.property::<u64>("frames-screened");
    assert!(n > 0, "the clip has frames the prior drops alone");
    assert_eq!(
        server.count("leangate-s-encoder") - before,
        2 + frames.len() as u64 - n,
        "no request for a screened frame"
    );
    for (k, (a, b)) in screened.iter().zip(&local).enumerate() {
        assert_eq!((a.keep, a.reason), (b.keep, b.reason), "frame {k}");
    }
}

fn pair_model_remote_matches_local(server: &V2Server) {
    let model = v2server::repo_root().join("models/leangate-s.onnx");
    let frames = clip(60);
    let (local, _) = gate(&format!("model={} screen=false", model.display()), &frames);
    let before = server.count("leangate-s");
    let (remote, e) = gate(
        &format!(
            "model={} screen=false server={}",
            model.display(),
            server.url()
        ),
        &frames,
    );
    compare(&local, &remote);
    // One request per scored frame (all but the first), plus the start's dry run.
    assert_eq!(server.count("leangate-s") - before, frames.len() as u64);
    assert_eq!(e.property::<Option<String>>("server"), Some(server.url()));
}

/// A TCP proxy to the server on `upstream` that can turn into a black hole: it keeps accepting
/// connections and reading requests, but nothing reaches the server and nothing comes back (a
/// server that accepts the request and never answers).
struct BlackHole {
    port: u16,
    on: Arc<AtomicBool>,
}

impl BlackHole {
    fn start(upstream: u16) -> BlackHole {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let on = Arc::new(AtomicBool::new(false));
        let hole = on.clone();
        std::thread::spawn(move || {
            for client in listener.incoming() {
                let Ok(client) = client else { return };
                let Ok(server) = TcpStream::connect(("127.0.0.1", upstream)) else {
                    continue;
                };
                let (c, s) = (client.try_clone().unwrap(), server.try_clone().unwrap());
                let h = hole.clone();
                std::thread::spawn(move || pump(c, s, &h));
                let h = hole.clone();
                std::thread::spawn(move || pump(server, client, &h));
            }
        });
        BlackHole { port, on }
    }

    fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    fn set(&self, on: bool) {
        self.on.store(on, Ordering::SeqCst);
    }
}

/// Copy `from` to `to`, dropping the bytes while the hole is on.
fn pump(mut from: TcpStream, mut to: TcpStream, hole: &AtomicBool) {
    let mut buf = vec![0u8; 1 << 16];
    while let Ok(n) = from.read(&mut buf) {
        if n == 0 || (!hole.load(Ordering::SeqCst) && to.write_all(&buf[..n]).is_err()) {
            break;
        }
    }
    let _ = to.shutdown(std::net::Shutdown::Both);
}

/// Issue 22, item 3: with a request hanging (the server accepts it and never answers) and a
/// 60 s `server-timeout`, `set_state(NULL)` returns within seconds (before: after the whole
/// timeout), with no error or warning; and on the scorer itself, a cancel interrupts the request
/// (not counted as a server failure: no backoff), the requests that follow fail at once until
/// resumed, and scoring works again after.
fn a_hung_request_is_interrupted_by_stopping(server: &V2Server) {
    let hole = BlackHole::start(server.http_port);
    let frames = clip(6);
    init();
    let desc = format!(
        "appsrc name=src format=time caps={} ! leangate name=gate mode=annotate screen=false \
         sharpness-lookback=0 server={} server-timeout=60000 ! appsink name=out sync=false",
        rgb_caps(W, H),
        hole.url()
    );
    let pipeline = gst::parse::launch(&desc)
        .unwrap()
        .downcast::<gst::Pipeline>()
        .unwrap();
    let (src, sink) = app_ends(&pipeline);
    let gate = pipeline.by_name("gate").unwrap();
    pipeline.set_state(gst::State::Playing).unwrap();
    for (i, f) in frames[..3].iter().enumerate() {
        src.push_buffer(buffer(f.clone(), i as u64 * 33)).unwrap();
        let s = sink
            .try_pull_sample(gst::ClockTime::from_seconds(30))
            .expect("a frame through the healthy server");
        assert_ne!(meta(&s.buffer_owned().unwrap()).reason, Reason::Error);
    }
    hole.set(true);
    src.push_buffer(buffer(frames[3].clone(), 99)).unwrap();
    let t = Instant::now();
    while gate.property::<u64>("frames-in") < 4 {
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "the 4th frame arrives"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    // The frame's request is on its way to nowhere.
    std::thread::sleep(Duration::from_millis(300));
    assert!(sink.try_pull_sample(gst::ClockTime::ZERO).is_none());
    let t = Instant::now();
    pipeline.set_state(gst::State::Null).unwrap();
    let took = t.elapsed();
    eprintln!("set_state(NULL) with a request hanging: {took:?}");
    assert!(
        took < Duration::from_secs(5),
        "set_state(NULL) waited {took:?} for the hung request"
    );
    let bus = pipeline.bus().unwrap();
    while let Some(m) = bus.pop() {
        assert!(
            !matches!(
                m.view(),
                gst::MessageView::Error(_) | gst::MessageView::Warning(_)
            ),
            "an interrupted request is not a failure: {m:?}"
        );
    }

    // The scorer: cancel, resume.
    hole.set(false);
    let local = gstleangate::Scorer::load(
        &gstleangate::default_model(),
        &gstleangate::ScorerOptions {
            execution_provider: gstleangate::ExecutionProvider::Cpu,
            precision: gstleangate::Precision::Fp32,
            ..Default::default()
        },
    )
    .unwrap();
    let mut remote = gstleangate::RemoteScorer::connect(
        local,
        &gstleangate::RemoteOptions {
            url: hole.url(),
            model: None,
            timeout: Duration::from_secs(60),
            max_in_flight: 0,
        },
    )
    .unwrap();
    let len = remote.info().spec.len();
    let (a, b) = (vec![0.3f32; len], vec![0.6f32; len]);
    remote.score(&a, &b).unwrap();
    hole.set(true);
    let cancel = remote.canceller();
    let t = Instant::now();
    let r = std::thread::scope(|scope| {
        let h = scope.spawn(|| remote.score(&a, &b));
        std::thread::sleep(Duration::from_millis(300));
        cancel.cancel();
        h.join().unwrap()
    });
    assert!(
        matches!(r, Err(gstleangate::ScorerError::Interrupted)),
        "{r:?}"
    );
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    assert!(matches!(
        remote.score(&a, &b),
        Err(gstleangate::ScorerError::Interrupted)
    ));
    hole.set(false);
    cancel.resume();
    remote
        .score(&a, &b)
        .expect("scoring works again after resume");
    assert_eq!(remote.stats().failed_requests, 0, "{:?}", remote.stats());
}

fn error_of(props: &str) -> String {
    let msgs = run_pipeline(
        &format!(
            "videotestsrc num-buffers=3 ! video/x-raw,format=RGB,width=160,height=120 ! \
             leangate {props} ! fakesink"
        ),
        60,
    );
    error_text(&msgs).unwrap_or_else(|| panic!("no start error with {props}"))
}

#[test]
fn unreachable_server_is_a_start_error_naming_it() {
    // A port nobody listens on (no server needed).
    let url = format!("http://127.0.0.1:{}", v2server::free_port());
    let e = error_of(&format!("server={url} server-timeout=2000"));
    assert!(e.contains(&url) && e.contains("unreachable"), "{e}");
    let e = error_of("server=grpc://127.0.0.1:8001");
    assert!(
        e.contains("grpc://127.0.0.1:8001") && e.contains("gRPC"),
        "{e}"
    );
    let e = error_of("server=ftp://x");
    assert!(e.contains("ftp://x") && e.contains("http://"), "{e}");
}

fn unknown_model_and_wrong_contract_are_start_errors_naming_them(server: &V2Server) {
    let url = server.url();
    let e = error_of(&format!("server={url} server-model=no-such-model"));
    assert!(
        e.contains(&url) && e.contains("no-such-model") && e.contains("has no model"),
        "{e}"
    );
    // The default (split) student against the head: no `image` input.
    let e = error_of(&format!("server={url} server-model=leangate-s-head"));
    assert!(
        e.contains(&url) && e.contains("leangate-s-head") && e.contains("tensor contract"),
        "{e}"
    );
    assert!(e.contains("no input `image`"), "{e}");
    // The pair model against the encoder.
    let pair = v2server::repo_root().join("models/leangate-s.onnx");
    let e = error_of(&format!(
        "model={} server={url} server-model=leangate-s-encoder",
        pair.display()
    ));
    assert!(e.contains("no input `reference`"), "{e}");
}

#[test]
fn server_killed_mid_stream_fails_open_and_scoring_resumes() {
    let Some(mut server) = v2server::start_or_skip(&v2server::student_models()[..1]) else {
        return;
    };
    let frames = clip(40);
    init();
    let bus = gst::Bus::new();
    let e = element(&format!(
        "mode=annotate screen=false server={} server-timeout=500",
        server.url()
    ));
    e.set_bus(Some(&bus));
    let mut h = gst_check::Harness::with_element(&e, Some("sink"), Some("src"));
    h.set_src_caps_str(&rgb_caps(W, H));
    h.play();
    let mut pts = 0u64;
    let mut push = |h: &mut gst_check::Harness, f: &Vec<u8>| {
        let t0 = Instant::now();
        h.push(buffer(f.clone(), pts)).unwrap();
        pts += 33;
        let out = drain(h);
        assert_eq!(out.len(), 1, "annotate mode: every frame leaves");
        (meta(&out[0]), t0.elapsed())
    };
    // Healthy.
    for f in &frames[..20] {
        let (m, _) = push(&mut h, f);
        assert_ne!(m.reason, Reason::Error);
    }
    // Killed (as a crash): frames keep flowing, kept with reason `error`, none waits long.
    let pgid = server.pgid().unwrap();
    let backend_dirs = v2server::backend_tmp_dirs(pgid);
    assert_eq!(backend_dirs.len(), 2, "{backend_dirs:?}");
    server.kill();
    assert!(
        !v2server::group_alive(pgid, Duration::from_secs(5)),
        "the killed server left processes"
    );
    // Nor folders in /tmp (the Python backend's, which only a clean stop removes).
    for d in &backend_dirs {
        assert!(!d.exists(), "{} left behind", d.display());
    }
    let t_down = Instant::now();
    let mut failed = 0;
    while t_down.elapsed() < Duration::from_secs(2) {
        let (m, took) = push(&mut h, &frames[20 + failed % 20]);
        assert!(m.keep, "fail open");
        assert_eq!(m.reason, Reason::Error);
        assert!(
            took < Duration::from_millis(1500),
            "a frame waited {took:?}"
        );
        failed += 1;
        std::thread::sleep(Duration::from_millis(33));
    }
    assert!(
        failed > 10,
        "frames flowed while the server was down: {failed}"
    );
    // A warning on the bus names the server (rate-limited: one or two, not one per frame).
    let warnings: Vec<String> = bus_warnings(&bus);
    assert!(
        !warnings.is_empty() && warnings.len() <= 2,
        "{} warnings: {warnings:?}",
        warnings.len()
    );
    assert!(
        warnings[0].contains(&server.url()) && warnings[0].contains("fail open"),
        "{}",
        warnings[0]
    );
    // Back on the same port: scoring resumes within the backoff (at most 2 s after ready).
    server.spawn().expect("restart the server");
    let t_up = Instant::now();
    let mut resumed = None;
    let mut i = 0;
    while t_up.elapsed() < Duration::from_secs(10) {
        let (m, _) = push(&mut h, &frames[i % 40]);
        i += 1;
        if m.reason != Reason::Error {
            resumed = Some(t_up.elapsed());
            break;
        }
        std::thread::sleep(Duration::from_millis(33));
    }
    let resumed = resumed.expect("scoring resumed after the server came back");
    eprintln!("{failed} frames failed open while down; scoring resumed {resumed:?} after ready");
    for f in &frames[..10] {
        let (m, _) = push(&mut h, f);
        assert_ne!(m.reason, Reason::Error);
    }
    // Slow: every call now takes 800 ms against a 500 ms timeout: fail open again, quickly.
    server.set_delay_ms(800);
    let t_slow = Instant::now();
    let mut slow_failed = 0;
    while t_slow.elapsed() < Duration::from_secs(2) {
        let (m, took) = push(&mut h, &frames[slow_failed % 40]);
        assert!(m.keep && m.reason == Reason::Error, "{m:?}");
        assert!(
            took < Duration::from_millis(1500),
            "a frame waited {took:?}"
        );
        slow_failed += 1;
    }
    server.set_delay_ms(0);
    let t_fast = Instant::now();
    loop {
        let (m, _) = push(&mut h, &frames[3]);
        if m.reason != Reason::Error {
            break;
        }
        assert!(
            t_fast.elapsed() < Duration::from_secs(10),
            "scoring did not resume"
        );
        std::thread::sleep(Duration::from_millis(33));
    }
    let s = stats_now(&e, &bus).server.unwrap();
    assert!(s.failed_requests >= 2, "{s:?}");
    assert!(
        s.failed_requests < (failed + slow_failed) as u64,
        "backoff: not every failed frame is a request ({s:?}, {} frames failed)",
        failed + slow_failed
    );
    drop(h);
    let pgid = server.pgid().unwrap();
    drop(server);
    assert!(
        !v2server::group_alive(pgid, Duration::from_secs(5)),
        "the server left processes"
    );
}

#[test]
fn triton_repository_matches_the_models() {
    let py = v2server::repo_root().join(".venv/bin/python");
    if !py.exists() {
        eprintln!("SKIPPED: {} is absent (scripts/setup.sh)", py.display());
        return;
    }
    let out = std::process::Command::new(py)
        .arg(v2server::repo_root().join("models/triton/make_repo.py"))
        .arg("--check")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "models/triton is stale: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn server_properties_are_documented_and_refused_while_running() {
    init();
    let e = gst::ElementFactory::make("leangate").build().unwrap();
    for name in [
        "server",
        "server-model",
        "server-timeout",
        "server-max-in-flight",
    ] {
        let p = e
            .find_property(name)
            .unwrap_or_else(|| panic!("property {name} missing"));
        assert!(p.blurb().is_some_and(|b| b.len() > 20), "{name}");
    }
    assert_eq!(e.property::<Option<String>>("server"), None);
    assert_eq!(e.property::<u32>("server-timeout"), 1000);
    assert_eq!(e.property::<u32>("server-max-in-flight"), 16);
    // Local scoring (server unset): a running element refuses a new server.
    let mut h = harness("", &rgb_caps(W, H));
    h.push(buffer(texture(W, H, 1), 0)).unwrap();
    let el = h.element().unwrap();
    el.set_property("server", "http://127.0.0.1:1");
    assert_eq!(el.property::<Option<String>>("server"), None);
    let stats = el.property::<u64>("frames-in");
    assert_eq!(stats, 1);
}

// ---------------------------------------------------------------------------------------------
// Hostile servers (tests/v2server/scripted.rs: a real HTTP server on loopback answering as each
// test says), with the fixture models: no Triton needed, so these always run, in seconds.

/// `e` started in a harness for 64x48 RGB.
fn started(e: &gst::Element) -> gst_check::Harness {
    let mut h = gst_check::Harness::with_element(e, Some("sink"), Some("src"));
    h.set_src_caps_str(&rgb_caps(64, 48));
    h.play();
    h
}

/// Push `n` textured 64x48 frames (annotate mode), `gap` apart; every frame's metadata.
fn push_frames(h: &mut gst_check::Harness, n: usize, gap: Duration) -> Vec<gstleangate::GateMeta> {
    let mut metas = Vec::new();
    for i in 0..n {
        h.push(buffer(texture(64, 48, i as u32 % 7), i as u64 * 33))
            .expect("the element takes every frame");
        metas.extend(drain(h).iter().map(meta));
        std::thread::sleep(gap);
    }
    assert_eq!(metas.len(), n, "annotate mode: every frame leaves");
    metas
}

/// Every log line of the `leangate*` categories (down to DEBUG) from the first call on, for the
/// whole test process; the default stderr log goes, or DEBUG lines would flood it.
fn leangate_logs() -> Vec<String> {
    logs_at(None)
}

/// [`leangate_logs`], the WARNING lines alone (`Some(Warning)`) or all of them.
fn logs_at(level: Option<gst::DebugLevel>) -> Vec<String> {
    static LOGS: std::sync::Mutex<Vec<(gst::DebugLevel, String)>> =
        std::sync::Mutex::new(Vec::new());
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        init();
        gst::log::remove_default_log_function();
        gst::log::add_log_function(|cat, level, _, _, _, _, msg| {
            if cat.name().starts_with("leangate") {
                if let Some(m) = msg.get() {
                    LOGS.lock().unwrap().push((level, m.to_string()));
                }
            }
        });
        gst::log::set_active(true);
        gst::log::set_threshold_for_name("leangate*", gst::DebugLevel::Debug);
    });
    LOGS.lock()
        .unwrap()
        .iter()
        .filter(|(l, _)| level.is_none_or(|want| *l == want))
        .map(|(_, m)| m.clone())
        .collect()
}

#[test]
fn credentials_in_the_url_are_used_but_never_shown() {
    const SECRET: &str = "s3cret-pw";
    let _ = leangate_logs();
    let served = Served::mad();
    // "user:s3cret-pw" (percent-decoding: a unit test of src/remote/url.rs).
    let expected = "Basic dXNlcjpzM2NyZXQtcHc=";
    let server = Scripted::start(move |req, n| {
        if req.header("authorization") != Some(expected) {
            return Reply::json(401, &json!({"error": "who are you"}));
        }
        // The dry run and two frames, then the server fails.
        served.route(req, || match n {
            0..=2 => served.answer(0.9),
            _ => Reply::json(500, &json!({"error": "boom"})),
        })
    });
    let port = server.port();
    let url = format!("http://user:{SECRET}@127.0.0.1:{port}");
    let shown = format!("http://***@127.0.0.1:{port}");
    init();
    let bus = gst::Bus::new();
    let e = element(&format!(
        "mode=annotate model={} server={url}",
        fixture("mad.onnx")
    ));
    e.set_bus(Some(&bus));
    let mut h = started(&e);
    let metas = push_frames(&mut h, 6, Duration::ZERO);
    // The credentials were used: the server let the element in.
    assert_eq!(metas[1].reason, Reason::Score, "{:?}", metas[1]);
    assert!(metas[4..].iter().all(|m| m.reason == Reason::Error));
    assert!(server
        .seen()
        .iter()
        .all(|r| r.header("authorization") == Some(expected)));
    // Refused while running: the warning names what stays, without the password.
    e.set_property("server", "http://127.0.0.1:1");
    let warnings = bus_warnings(&bus);
    assert!(warnings.len() >= 2, "{warnings:?}");
    assert!(
        warnings
            .iter()
            .any(|w| w.contains(&shown) && w.contains("boom")),
        "{warnings:?}"
    );
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("it stays") && w.contains(&shown)),
        "{warnings:?}"
    );
    let stats = stats_now(&e, &bus).server.unwrap();
    assert_eq!(stats.server, shown);
    drop(h);
    // Start errors: unknown model, unreachable, refused URL.
    let free = v2server::free_port();
    let mut texts: Vec<String> = [
        format!(
            "model={} server={url} server-model=nope",
            fixture("mad.onnx")
        ),
        format!("server=http://user:{SECRET}@127.0.0.1:{free} server-timeout=2000"),
        format!("server=ftp://user:{SECRET}@127.0.0.1:{free}"),
    ]
    .iter()
    .map(|p| error_of(p))
    .collect();
    assert!(
        texts[0].contains(&shown) && texts[0].contains("nope"),
        "{}",
        texts[0]
    );
    assert!(
        texts[1].contains("***@127.0.0.1") && texts[1].contains("unreachable"),
        "{}",
        texts[1]
    );
    assert!(texts[2].contains("ftp://***@127.0.0.1"), "{}", texts[2]);
    texts.extend(warnings);
    // And the debug log: the property set, the start, the failures.
    let logs: Vec<String> = leangate_logs()
        .into_iter()
        .filter(|l| l.contains(&format!("127.0.0.1:{port}")) || l.contains(SECRET))
        .collect();
    assert!(
        logs.iter().any(|l| l.contains("scoring on server")),
        "the log saw the start: {logs:?}"
    );
    texts.extend(logs);
    for t in &texts {
        assert!(!t.contains(SECRET), "leaked: {t}");
    }
}

#[test]
fn one_in_flight_bound_per_server_however_its_url_is_spelled() {
    // Every inference takes 40 ms; the server counts how many it holds at once.
    let served = Served::mad();
    let server = Scripted::start(move |req, _| {
        served.route(req, || {
            std::thread::sleep(Duration::from_millis(40));
            served.answer(0.9)
        })
    });
    let p = server.port();
    // All elements started (each start's dry run counted), then the count restarts and every
    // element streams at once: the bound that applies is that of all of them.
    let run = |urls: Vec<(String, u32)>, server: &Scripted| {
        let barrier = std::sync::Arc::new(std::sync::Barrier::new(urls.len() + 1));
        let threads: Vec<_> = urls
            .into_iter()
            .map(|(url, bound)| {
                let barrier = barrier.clone();
                std::thread::spawn(move || {
                    let e = element(&format!(
                        "mode=annotate model={} server={url} server-max-in-flight={bound} \
                         server-timeout=10000",
                        fixture("mad.onnx")
                    ));
                    let mut h = started(&e);
                    barrier.wait();
                    barrier.wait();
                    let metas = push_frames(&mut h, 10, Duration::ZERO);
                    // No element stops (withdrawing its bound, which lets the others' rise)
                    // before every element has pushed its frames.
                    barrier.wait();
                    metas
                })
            })
            .collect();
        barrier.wait();
        server.reset_max_in_flight();
        barrier.wait();
        barrier.wait();
        for t in threads {
            let metas = t.join().unwrap();
            assert!(metas.iter().all(|m| m.reason != Reason::Error), "{metas:?}");
        }
    };
    // Four elements, four spellings of one server, a bound of 2.
    run(
        vec![
            (format!("http://127.0.0.1:{p}"), 2),
            (format!("http://localhost:{p}/"), 2),
            (format!("http://LOCALHOST:{p}"), 2),
            (format!("http://127.0.0.1:{p}/"), 2),
        ],
        &server,
    );
    assert_eq!(server.max_in_flight(), 2, "in flight at once, bound 2");
    // Elements that disagree: the smallest bound applies to all of them.
    let server2 = Scripted::start(move |req, _| {
        let served = Served::mad();
        served.route(req, || {
            std::thread::sleep(Duration::from_millis(40));
            served.answer(0.9)
        })
    });
    let p = server2.port();
    run(
        vec![
            (format!("http://127.0.0.1:{p}"), 1),
            (format!("http://localhost:{p}"), 4),
            (format!("http://127.0.0.1:{p}/"), 0),
        ],
        &server2,
    );
    assert_eq!(server2.max_in_flight(), 1, "the smallest bound, 1, for all");
}

#[test]
fn out_of_range_utilities_fail_open() {
    // Dry run fine, then a bad utility every other request (frames 1, 3, ...).
    let bad = [5.0f32, -3.0, 1e38, f32::INFINITY, -0.0001];
    let served = Served::mad();
    let server = Scripted::start(move |req, n| {
        served.route(req, || match n {
            n if n % 2 == 0 => served.answer(0.9),
            n => served.answer(bad[(n as usize / 2) % bad.len()]),
        })
    });
    init();
    let bus = gst::Bus::new();
    // Every due keep at once (the synthetic frames' sharpness varies; tests/keyframes.rs covers
    // the wait for a sharper one).
    let e = element(&format!(
        "mode=annotate model={} server={} sharpness-wait=0",
        fixture("mad.onnx"),
        server.url()
    ));
    e.set_bus(Some(&bus));
    // 150 ms apart: the backoff after a failure (100 ms) is over by the next frame.
    let metas = push_frames(
        &mut started(&e),
        1 + 2 * bad.len(),
        Duration::from_millis(150),
    );
    for (i, m) in metas.iter().enumerate().skip(1) {
        if i % 2 == 0 {
            assert_eq!(
                (m.keep, m.reason),
                (true, Reason::Score),
                "frame {i}: {m:?}"
            );
        } else {
            assert_eq!(
                (m.keep, m.reason),
                (true, Reason::Error),
                "frame {i}: {m:?}"
            );
            assert!(m.utility.is_nan(), "frame {i}: {m:?}");
        }
    }
    let w = bus_warnings(&bus);
    assert!(
        w.first()
            .is_some_and(|w| w.contains("`utility` 5 is not in [0, 1]")),
        "{w:?}"
    );
    // Out of range at the dry run: a start error.
    let server = Scripted::start(move |req, _| {
        let served = Served::mad();
        served.route(req, || served.answer(2.0))
    });
    let err = error_of(&format!(
        "model={} server={}",
        fixture("mad.onnx"),
        server.url()
    ));
    assert!(
        err.contains("dry run") && err.contains("not in [0, 1]"),
        "{err}"
    );
}

#[test]
fn impossible_feature_shapes_fail_open_before_onnx_runtime() {
    let _ = leangate_logs();
    // A split model: the dry run's two encodings fine, then every other answer a shape the
    // head cannot take: one whose element count overflows, one with an empty dimension, one of
    // the wrong rank, one with batch 2.
    let served = Served::split_encoder();
    let server = Scripted::start(move |req, n| {
        served.route(req, || match n {
            0..=1 => served.answer(0.0),
            n if n % 2 == 0 => served.answer(0.0),
            n => match (n / 2) % 4 {
                1 => Reply::tensor("features", &[1 << 32, 1 << 32, 1], &[]),
                2 => Reply::tensor("features", &[1, 3, 0, 16], &[]),
                3 => Reply::tensor("features", &[1, 768], &[0.0; 768]),
                _ => Reply::tensor("features", &[2, 3, 16, 8], &[0.0; 768]),
            },
        })
    });
    init();
    let bus = gst::Bus::new();
    let e = element(&format!(
        "mode=annotate model={} server={}",
        fixture("split_encoder.onnx"),
        server.url()
    ));
    e.set_bus(Some(&bus));
    let metas = push_frames(&mut started(&e), 12, Duration::from_millis(150));
    let errors = metas.iter().filter(|m| m.reason == Reason::Error).count();
    assert!(errors >= 4, "{metas:?}");
    assert!(metas.iter().all(|m| m.keep), "fail open: {metas:?}");
    // Each failure says what the shape was, and none comes from inside ONNX Runtime.
    let port = format!("127.0.0.1:{}", server.port());
    let logged: Vec<String> = leangate_logs()
        .into_iter()
        .filter(|l| l.contains(&port))
        .collect();
    for want in [
        "impossible shape",
        "[1, 3, 0, 16]",
        "[1, 768]",
        "[2, 3, 16, 8]",
    ] {
        assert!(
            logged.iter().any(|l| l.contains(want)),
            "{want}: {logged:?}"
        );
    }
    for l in logged.iter().chain(&bus_warnings(&bus)) {
        assert!(!l.contains("onnxruntime") && !l.contains(".cc"), "{l}");
    }
}

#[test]
fn server_errors_say_what_the_server_answered() {
    // The server answers the metadata with 500: it is not "unreachable".
    let server = Scripted::start(|req, _| {
        let served = Served::mad();
        served.route(req, || served.answer(0.9))
    });
    let broken = Scripted::start(|_, _| Reply::json(500, &json!({"error": "boom"})));
    let mad = fixture("mad.onnx");
    let e = error_of(&format!("model={mad} server={}", broken.url()));
    assert!(
        e.contains("answered the model metadata request")
            && e.contains("HTTP status 500 (Internal Server Error): boom")
            && !e.contains("unreachable"),
        "{e}"
    );
    // The URL as written.
    let e = error_of("server=http://");
    assert!(e.contains("`http://`") && e.contains("no host"), "{e}");
    let e = error_of("server=http://127.0.0.1:99999");
    assert!(
        e.contains("port 99999 is not a valid TCP port") && !e.contains("refused"),
        "{e}"
    );
    // Schemes are case-insensitive.
    let msgs = run_pipeline(
        &format!(
            "videotestsrc num-buffers=3 ! video/x-raw,format=RGB,width=64,height=48 ! \
             leangate model={mad} server=HTTP://127.0.0.1:{} ! fakesink",
            server.port()
        ),
        60,
    );
    assert_eq!(error_text(&msgs), None);
    drop(server);
}

#[test]
fn an_inference_redirect_is_an_error_not_a_get() {
    let served = Served::mad();
    let server = Scripted::start(move |req, n| {
        if req.method == "GET" && req.path.ends_with("/elsewhere") {
            // What following the redirect as a GET would find.
            return served.answer(0.9);
        }
        served.route(req, || match n {
            0 => served.answer(0.9),
            _ => Reply::redirect(302, "/v2/models/fixture-mad/elsewhere"),
        })
    });
    init();
    let bus = gst::Bus::new();
    let e = element(&format!(
        "mode=annotate model={} server={}",
        fixture("mad.onnx"),
        server.url()
    ));
    e.set_bus(Some(&bus));
    let metas = push_frames(&mut started(&e), 3, Duration::from_millis(150));
    assert!(
        metas[1..]
            .iter()
            .all(|m| m.keep && m.reason == Reason::Error),
        "{metas:?}"
    );
    let w = bus_warnings(&bus);
    assert!(
        w.first()
            .is_some_and(|w| w.contains("HTTP status 302 (Found)")
                && w.contains("`/v2/models/fixture-mad/elsewhere`")
                && w.contains("not followed")),
        "{w:?}"
    );
    assert!(
        !server.seen().iter().any(|r| r.path.ends_with("/elsewhere")),
        "the redirect was followed"
    );
}

/// What a hostile probe found (each fails without its fix): a password holding `/` sent the
/// secret to the host its user name named while every message showed the real host; a 401 read
/// as "no model"; a JSON answer of hundreds of MiB parsed whole (gigabytes of memory); unusable
/// answers not counted as failed requests; one WARNING log line per failed frame.
#[test]
fn hostile_servers_and_urls_found_by_a_probe() {
    let _ = leangate_logs();
    let mad = fixture("mad.onnx");
    // An unencoded `/` in the password: refused, nothing sent anywhere, the secret never shown.
    let decoy = Scripted::start(|_, _| Reply::json(500, &json!({"error": "never asked"})));
    let server = Scripted::start(|req, _| {
        let served = Served::mad();
        served.route(req, || served.answer(0.9))
    });
    for url in [
        format!("http://user:s3cret/PW@127.0.0.1:{}", server.port()),
        format!(
            "http://127.0.0.1:{}/tok3n@127.0.0.1:{}",
            decoy.port(),
            server.port()
        ),
    ] {
        let e = error_of(&format!("model={mad} server={url}"));
        assert!(
            e.contains("percent-encoded") && !e.contains("s3cret") && !e.contains("tok3n"),
            "{e}"
        );
    }
    assert!(decoy.seen().is_empty(), "{:?}", decoy.seen().len());
    assert!(server.seen().is_empty());

    // Credentials refused: said so, not "no model".
    let locked = Scripted::start(|_, _| Reply::json(401, &json!({"error": "unauthorized"})));
    let e = error_of(&format!("model={mad} server={}", locked.url()));
    assert!(
        e.contains("refused access") && !e.contains("has no model"),
        "{e}"
    );

    // After the dry run: a 9 MiB JSON answer, a utility out of range, then 500s.
    let served = Served::mad();
    let huge = json!({"outputs": [{"name": "utility", "datatype": "FP32", "shape": [1],
        "data": vec![0.0f32; 3_000_000]}]});
    let server = Scripted::start(move |req, n| {
        served.route(req, || match n {
            0 => served.answer(0.9),
            1 => Reply::json(200, &huge),
            2 => served.answer(7.0),
            _ => Reply::json(500, &json!({"error": "down"})),
        })
    });
    init();
    let bus = gst::Bus::new();
    let e = element(&format!(
        "mode=annotate model={mad} server={} sharpness-wait=0",
        server.url()
    ));
    e.set_bus(Some(&bus));
    let mut h = started(&e);
    // 150 ms apart for the first three (past the backoff), then 30 frames at once.
    let mut metas = push_frames(&mut h, 3, Duration::from_millis(150));
    metas.extend(push_frames(&mut h, 30, Duration::from_millis(2)));
    assert!(metas.iter().all(|m| m.keep), "fail open: {metas:?}");
    let port = format!("127.0.0.1:{}", server.port());
    let logged: Vec<String> = leangate_logs()
        .into_iter()
        .filter(|l| l.contains(&port))
        .collect();
    assert!(
        logged
            .iter()
            .any(|l| l.contains("more than the 8388608 allowed")),
        "{logged:?}"
    );
    let warned: Vec<String> = logs_at(Some(gst::DebugLevel::Warning))
        .into_iter()
        .filter(|l| l.contains(&port))
        .collect();
    assert!(warned.len() <= 2, "rate-limited like the bus: {warned:?}");
    let stats = stats_now(&e, &bus);
    let server_stats = stats.server.expect("server stats");
    // The huge answer, the bad utility, then 500s (as many as the backoff lets through): every
    // request failed, and is counted so.
    assert!(
        server_stats.requests >= 3 && server_stats.failed_requests == server_stats.requests,
        "{server_stats:?}"
    );
}
