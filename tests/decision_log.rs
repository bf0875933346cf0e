//! The decision log (`GST_DEBUG=leangate:7`): every frame's line, and a keep that went back to a
//! held frame logged again when it is made, including one settled when the held frames are let
//! go (issue 53, 4). In a binary of its own: it raises the element's debug level for the process.

mod common;

use common::*;
use std::sync::{Arc, Mutex};

#[test]
fn a_keep_settled_at_the_end_of_the_stream_is_logged_with_gstreamer_times() {
    init();
    let lines = Arc::new(Mutex::new(Vec::<String>::new()));
    let sink = lines.clone();
    let log = gst::log::add_log_function(move |cat, _level, _file, _fn, _line, obj, msg| {
        if cat.name() != "leangate" || !obj.is_some_and(|o| o.to_string().contains("logtest")) {
            return;
        }
        if let Some(m) = msg.get() {
            sink.lock().unwrap().push(m.to_string());
        }
    });
    gst::log::set_active(true);
    gst::log::set_threshold_for_name("leangate", gst::DebugLevel::Trace);
    let mut h = red_harness("mode=annotate name=logtest");
    // Frame 5 is due but blurred, its keep owed when the stream ends: it settles on frame 5.
    push_red(&mut h, 0, &NEARLY_DUE_THEN_BLURRED_DUE);
    h.push_event(gst::event::Eos::new());
    let out = drain(&mut h);
    gst::log::remove_log_function(log);
    assert!(out.last().is_some_and(|b| meta(b).keep));
    let lines = lines.lock().unwrap().clone();
    let keeps: Vec<_> = lines.iter().filter(|l| l.contains(" keep ")).collect();
    // One line per frame as it is decided, then the settled keep's.
    assert_eq!(keeps.len(), 7, "{keeps:#?}");
    assert!(
        keeps[5].starts_with("pts 0:00:00.165000000 utility 0.52"),
        "{}",
        keeps[5]
    );
    assert!(keeps[5].contains("keep false (deferred"), "{}", keeps[5]);
    assert!(
        keeps[6].starts_with("pts 0:00:00.165000000 keep true (sharper: settled"),
        "{}",
        keeps[6]
    );
    assert!(
        lines.iter().all(|l| !l.contains("Some(")),
        "times as GStreamer prints them: {lines:#?}"
    );
}
