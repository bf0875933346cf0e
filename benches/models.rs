//! The default student in its forms, side by side in one run: the pair model
//! (`models/leangate-s.onnx`: both images through the encoder for every scored frame) against the
//! split model embedded in the plugin (encoder once per frame, the reference keyframe's features
//! cached until the next keep), in its FP32 build and its INT8 build (`precision`; INT8 is what
//! the element runs on the CPU by default).
//!
//!     cargo bench --bench models
//!
//! 1. Scorer only: frames/s over a stream where a fraction of the frames is kept.
//! 2. In a real pipeline: `videotestsrc ! 640x480 ! leangate [model=pair] ! fakesink`.
//!
//! Prints figures and the split/pair ratio; asserts nothing (speed is not a test).

use std::time::Instant;

use gst::prelude::*;
use gstleangate::{ExecutionProvider, ModelSource, Precision, Scorer, ScorerOptions};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn scorer(source: ModelSource, precision: Precision) -> Scorer {
    Scorer::load(
        &source,
        &ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            precision,
            ..Default::default()
        },
    )
    .expect("load model")
}

/// Frames/s scoring `frames` frames, keeping every `keep_every`-th.
fn scorer_fps(s: &mut Scorer, frames: usize, keep_every: usize) -> f64 {
    let n = s.info().spec.len();
    let pics: Vec<Vec<f32>> = (0..8)
        .map(|k| {
            (0..n)
                .map(|i| (((i * (k + 3)) % 97) as f32) / 97.0)
                .collect()
        })
        .collect();
    let mut reference = pics[0].clone();
    let t = Instant::now();
    for i in 1..=frames {
        let cur = &pics[i % pics.len()];
        s.score(&reference, cur).expect("score");
        if i % keep_every == 0 {
            s.on_keep(true);
            reference = cur.clone();
        }
    }
    frames as f64 / t.elapsed().as_secs_f64()
}

fn pipeline_fps(model_prop: &str, frames: u32) -> f64 {
    let desc = format!(
        "videotestsrc num-buffers={frames} pattern=ball ! video/x-raw,format=I420,width=640,height=480,framerate=30/1 ! \
         leangate {model_prop} ! fakesink sync=false"
    );
    let p = gst::parse::launch(&desc).expect("pipeline");
    let bus = p.bus().unwrap();
    let t = Instant::now();
    p.set_state(gst::State::Playing).expect("play");
    for msg in bus.iter_timed(gst::ClockTime::NONE) {
        match msg.view() {
            gst::MessageView::Eos(_) => break,
            gst::MessageView::Error(e) => panic!("{}", e.error()),
            _ => {}
        }
    }
    let fps = frames as f64 / t.elapsed().as_secs_f64();
    p.set_state(gst::State::Null).unwrap();
    fps
}

fn main() {
    gst::init().unwrap();
    gstleangate::plugin_register_static().unwrap();
    let pair_path = concat!(env!("CARGO_MANIFEST_DIR"), "/models/leangate-s.onnx");
    let mut pair = scorer(ModelSource::File(pair_path.into()), Precision::Auto);
    let mut fp32 = scorer(gstleangate::default_model(), Precision::Fp32);
    let mut int8 = scorer(gstleangate::default_model(), Precision::Int8);
    let reps = 5;
    println!("leangate-s: pair (FP32) vs split (embedded) FP32 vs split INT8, CPU, frames/s, median of {reps}, interleaved");
    println!("| case | pair | split FP32 | split INT8 | split FP32 / pair | INT8 / FP32 |");
    println!("|---|---|---|---|---|---|");
    let row = |case: &str, a: Vec<f64>, b: Vec<f64>, c: Vec<f64>| {
        let (a, b, c) = (median(a), median(b), median(c));
        println!(
            "| {case} | {a:.1} | {b:.1} | {c:.1} | {:.2} | {:.2} |",
            b / a,
            c / b
        );
    };
    for keep_every in [10usize, 2] {
        let (mut a, mut b, mut c) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..reps {
            a.push(scorer_fps(&mut pair, 200, keep_every));
            b.push(scorer_fps(&mut fp32, 200, keep_every));
            c.push(scorer_fps(&mut int8, 200, keep_every));
        }
        row(&format!("scorer only, 1 keep in {keep_every}"), a, b, c);
    }
    let (mut a, mut b, mut c) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..reps {
        a.push(pipeline_fps(&format!("model={pair_path}"), 150));
        b.push(pipeline_fps("precision=fp32", 150));
        c.push(pipeline_fps("", 150));
    }
    row("pipeline 640x480 I420 (videotestsrc ball)", a, b, c);
}
