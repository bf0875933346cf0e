//! Issue 8, D1/D2: applications that touch `leangate` from a *synchronous* bus handler, as
//! applications do (adapt the threshold when a stats message arrives). Before the fix the element
//! posted its messages while holding its state lock, so these scenarios hung forever. Each one
//! runs Debian's /usr/bin/python3 (python3-gi) with the plugin built beside this test, under a
//! timeout: a hang fails the test instead of hanging CI.

#[path = "common/paths.rs"]
#[allow(dead_code)]
mod paths;

use std::io::Read;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const PYTHON: &str = "/usr/bin/python3";
const TIMEOUT: Duration = Duration::from_secs(60);

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn fixture(name: &str) -> String {
    repo()
        .join("tests/fixtures")
        .join(name)
        .display()
        .to_string()
}

fn python_ok() -> bool {
    let ok = Command::new(PYTHON)
        .args([
            "-c",
            "import gi; gi.require_version('Gst', '1.0'); from gi.repository import Gst",
        ])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        eprintln!("SKIPPED: {PYTHON} cannot import the GStreamer bindings (python3-gi)");
    }
    ok
}

/// Common prelude of every scenario: `run(desc, setup)` builds the pipeline, lets `setup(pipeline,
/// lg)` connect its handlers, plays to EOS (or error) and prints `EOS` / `ERROR ...`. The bus is
/// popped by this (main) thread; a hang shows as no output and the Rust side kills the child.
const PRELUDE: &str = r#"
import sys, threading, time
import gi
gi.require_version('Gst', '1.0')
from gi.repository import Gst
Gst.init(None)

def run(desc, setup):
    p = Gst.parse_launch(desc)
    lg = p.get_by_name('lg')
    bus = p.get_bus()
    bus.enable_sync_message_emission()
    extra = setup(p, lg, bus)
    p.set_state(Gst.State.PLAYING)
    counts = {}
    while True:
        m = bus.timed_pop_filtered(50 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR
                                   | Gst.MessageType.ELEMENT | Gst.MessageType.WARNING)
        if m is None:
            print('TIMEOUT', flush=True)
            sys.exit(3)
        if m.type == Gst.MessageType.ELEMENT:
            n = m.get_structure().get_name()
            counts[n] = counts.get(n, 0) + 1
            continue
        if m.type == Gst.MessageType.WARNING:
            counts['warning'] = counts.get('warning', 0) + 1
            continue
        if m.type == Gst.MessageType.ERROR:
            print('ERROR', m.parse_error(), flush=True)
            sys.exit(2)
        break
    p.set_state(Gst.State.NULL)
    if extra is not None:
        extra()
    print('EOS', ' '.join('%s=%d' % kv for kv in sorted(counts.items())), flush=True)
"#;

/// Run a scenario under the timeout; returns stdout. Panics (failing the test) on a hang.
fn scenario(body: &str) -> Option<String> {
    if !python_ok() {
        return None;
    }
    let plugins = paths::plugin_dir();
    let script = format!("{PRELUDE}\n{body}");
    let mut child = Command::new(PYTHON)
        .arg("-c")
        .arg(&script)
        .env("GST_PLUGIN_PATH", plugins.path())
        .env_remove("GST_PLUGIN_PATH_1_0")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn python3");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if start.elapsed() > TIMEOUT {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "the scenario hung (killed after {TIMEOUT:?}): a lock held while posting?\n{body}"
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut out = String::new();
    let mut err = String::new();
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert!(
        status.success() && out.contains("EOS"),
        "status {status}\nstdout:\n{out}\nstderr:\n{err}"
    );
    Some(out)
}

fn count(out: &str, key: &str) -> u64 {
    out.lines()
        .find(|l| l.starts_with("EOS"))
        .and_then(|l| {
            l.split_whitespace()
                .find_map(|kv| kv.strip_prefix(&format!("{key}=")))
        })
        .map(|v| v.parse().unwrap())
        .unwrap_or(0)
}

/// D1: a sync handler that sets a property on every `leangate-stats` message (interval and EOS).
#[test]
fn set_property_from_a_sync_handler_on_stats() {
    let body = format!(
        r#"
def setup(p, lg, bus):
    def on(bus, m):
        if m.get_structure() is not None and m.get_structure().get_name() == 'leangate-stats':
            lg.set_property('threshold', 0.7)
            lg.set_property('stats-interval', 1)
    bus.connect('sync-message::element', on)
run('videotestsrc num-buffers=10 pattern=ball ! video/x-raw,width=64,height=48 ! '
    'leangate name=lg model={} stats-interval=1 ! fakesink', setup)
"#,
        fixture("mad.onnx")
    );
    if let Some(out) = scenario(&body) {
        assert!(count(&out, "leangate-stats") >= 2, "{out}");
    }
}

/// D1: the same from the fail-open warning of a model that returns NaN.
#[test]
fn set_property_from_a_sync_handler_on_the_nan_warning() {
    let body = format!(
        r#"
def setup(p, lg, bus):
    def on(bus, m):
        lg.set_property('threshold', 0.7)
        lg.get_property('frames-in')
    bus.connect('sync-message::warning', on)
run('videotestsrc num-buffers=10 ! video/x-raw,width=32,height=32 ! '
    'leangate name=lg model={} ! fakesink', setup)
"#,
        fixture("nan.onnx")
    );
    if let Some(out) = scenario(&body) {
        assert!(count(&out, "warning") >= 1, "{out}");
    }
}

/// D2: a sync handler that only reads properties on every stats message, while another thread
/// sets `threshold` in a loop (the lock-order inversion).
#[test]
fn reader_in_sync_handler_and_setter_thread_do_not_deadlock() {
    let body = format!(
        r#"
stop = threading.Event()
def setup(p, lg, bus):
    def on(bus, m):
        if m.get_structure() is not None and m.get_structure().get_name() == 'leangate-stats':
            lg.get_property('threshold')
            lg.get_property('model')
            lg.get_property('frames-kept')
    bus.connect('sync-message::element', on)
    def setter():
        v = 0.0
        while not stop.is_set():
            v = (v + 0.01) % 1.0
            lg.set_property('threshold', v)
            lg.set_property('max-gap', int(v * 10))
    t = threading.Thread(target=setter, daemon=True)
    t.start()
    def done():
        stop.set()
        t.join(10)
        assert not t.is_alive()
    return done
run('videotestsrc num-buffers=300 pattern=ball ! video/x-raw,width=64,height=48 ! '
    'leangate name=lg model={} stats-interval=1 ! fakesink', setup)
"#,
        fixture("mad.onnx")
    );
    if let Some(out) = scenario(&body) {
        assert!(count(&out, "leangate-stats") >= 300, "{out}");
    }
}

#[test]
fn geometry_toggled_from_a_sync_handler_and_a_thread_while_streaming() {
    // The geometric prior's state lives under the state lock; switching it (and `screen`, which
    // uses it) from a bus handler (on the streaming thread) and from another thread at once must
    // neither deadlock nor fail.
    let body = format!(
        r#"
stop = threading.Event()
def setup(p, lg, bus):
    def on(bus, m):
        if m.get_structure() is not None and m.get_structure().get_name() == 'leangate-stats':
            lg.set_property('geometry', not lg.get_property('geometry'))
            lg.set_property('screen', not lg.get_property('screen'))
            lg.get_property('frames-screened')
    bus.connect('sync-message::element', on)
    def setter():
        while not stop.is_set():
            lg.set_property('geometry', True)
            lg.set_property('screen', False)
            lg.set_property('geometry', False)
            lg.set_property('screen', True)
    t = threading.Thread(target=setter, daemon=True)
    t.start()
    def done():
        stop.set()
        t.join(10)
        assert not t.is_alive()
    return done
run('videotestsrc num-buffers=300 pattern=ball ! video/x-raw,width=320,height=240 ! '
    'leangate name=lg model={} stats-interval=1 ! fakesink', setup)
"#,
        fixture("mad_geometry.onnx")
    );
    if let Some(out) = scenario(&body) {
        assert!(count(&out, "leangate-stats") >= 300, "{out}");
    }
}
