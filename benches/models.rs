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
//!
//! `cargo bench --bench models -- providers` runs instead the embedded student on each execution
//! provider of LEANGATE_BENCH_EPS (default `cpu,cuda,tensorrt`), FP32 and INT8 builds, scorer only:
//! load time, the largest utility difference from the CPU provider (same build, same frames),
//! frames/s of one stream (batch 1), and of K streams (LEANGATE_BENCH_STREAMS, default `8,32`) on
//! one shared session, unbatched and with `batch-size` K. LEANGATE_BENCH_FRAMES (default 200),
//! LEANGATE_BENCH_REPS (default 3, medians). A provider that cannot load is a row saying why. One
//! `CHECK provider=.. build=.. status=ok|failed ..` line per row for scripts
//! (scripts/gpu-check.sh).

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
    if std::env::args().skip(1).any(|a| a == "providers") {
        providers::section();
        return;
    }
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

mod providers {
    //! The embedded student on each execution provider (see the header).

    use std::time::{Duration, Instant};

    use gstleangate::{ExecutionProvider, Precision, Scorer, ScorerOptions};

    fn env_or<T: std::str::FromStr>(k: &str, d: T) -> T {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    }

    fn list(k: &str, d: &str) -> Vec<String> {
        std::env::var(k)
            .unwrap_or_else(|_| d.to_string())
            .split(',')
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
            .collect()
    }

    fn options(ep: ExecutionProvider, precision: Precision, batch: usize) -> ScorerOptions {
        ScorerOptions {
            execution_provider: ep,
            precision,
            shared: batch > 0,
            max_sessions: 1,
            batch_size: batch,
            batch_timeout: Duration::from_millis(2),
            ..Default::default()
        }
    }

    /// One line, at most 600 characters (for tables and CHECK lines).
    fn one_line(e: impl std::fmt::Display) -> String {
        let s = e
            .to_string()
            .split_whitespace()
            .collect::<Vec<_>>()
            .join(" ");
        s.chars().take(600).collect::<String>().replace('|', "/")
    }

    fn pics(n: usize) -> Vec<Vec<f32>> {
        (0..8)
            .map(|k| {
                (0..n)
                    .map(|i| (((i * (k + 3)) % 97) as f32) / 97.0)
                    .collect()
            })
            .collect()
    }

    /// Utilities of `frames` frames, a keep every 5th.
    fn utilities(s: &mut Scorer, frames: usize) -> Result<Vec<f32>, String> {
        let pics = pics(s.info().spec.len());
        let mut out = Vec::new();
        let mut reference = 0;
        for i in 1..=frames {
            out.push(
                s.score(&pics[reference], &pics[i % pics.len()])
                    .map_err(one_line)?,
            );
            if i % 5 == 0 {
                s.on_keep(true);
                reference = i % pics.len();
            }
        }
        Ok(out)
    }

    /// Aggregate frames/s of `k` threads, each scoring `frames` frames (a keep every 10th) on
    /// its own scorer of `opts`, after an untimed warm-up (engine builds, first kernels).
    fn streams_fps(k: usize, frames: usize, opts: &ScorerOptions) -> Result<f64, String> {
        let mut scorers = (0..k)
            .map(|_| Scorer::load(&gstleangate::default_model(), opts).map_err(one_line))
            .collect::<Result<Vec<_>, _>>()?;
        let pics = pics(scorers[0].info().spec.len());
        let run = |scorers: &mut [Scorer], frames: usize| -> Result<f64, String> {
            let t = Instant::now();
            std::thread::scope(|scope| {
                let handles: Vec<_> = scorers
                    .iter_mut()
                    .map(|s| {
                        let pics = &pics;
                        scope.spawn(move || -> Result<(), String> {
                            for i in 1..=frames {
                                s.score(&pics[0], &pics[i % pics.len()]).map_err(one_line)?;
                                if i % 10 == 0 {
                                    s.on_keep(true);
                                }
                            }
                            s.idle();
                            Ok(())
                        })
                    })
                    .collect();
                handles
                    .into_iter()
                    .try_for_each(|h| h.join().expect("scoring thread"))
            })?;
            Ok((scorers.len() * frames) as f64 / t.elapsed().as_secs_f64())
        };
        run(&mut scorers, frames.min(20))?;
        run(&mut scorers, frames)
    }

    fn median(mut v: Vec<f64>) -> f64 {
        v.sort_by(|a, b| a.total_cmp(b));
        v[v.len() / 2]
    }

    pub fn section() {
        let eps: Vec<ExecutionProvider> = list("LEANGATE_BENCH_EPS", "cpu,cuda,tensorrt")
            .iter()
            .map(|e| {
                ExecutionProvider::parse(e).unwrap_or_else(|| {
                    panic!("LEANGATE_BENCH_EPS: `{e}` is not one of auto, cpu, cuda, tensorrt")
                })
            })
            .collect();
        let ks: Vec<usize> = list("LEANGATE_BENCH_STREAMS", "8,32")
            .iter()
            .map(|k| k.parse().expect("LEANGATE_BENCH_STREAMS: stream counts"))
            .collect();
        let frames: usize = env_or("LEANGATE_BENCH_FRAMES", 200).max(10);
        let reps: usize = env_or("LEANGATE_BENCH_REPS", 3).max(1);
        println!(
            "## Execution providers: embedded student `{}`, scorer only, {frames} frames per \
             stream, medians of {reps}",
            gstleangate::DEFAULT_MODEL_NAME
        );
        print!("| provider | build | load s | max abs diff vs CPU | 1 stream frames/s |");
        for k in &ks {
            print!(" {k} streams, batch 1 | {k} streams, batch-size={k} |");
        }
        println!();
        println!("|---|---|---|---|---|{}", "---|---|".repeat(ks.len()));
        let builds = [("fp32", Precision::Fp32), ("int8", Precision::Int8)];
        // The CPU provider's utilities for the same frames: what the others must match.
        let cpus: Vec<Result<Vec<f32>, String>> = builds
            .iter()
            .map(|&(_, precision)| {
                Scorer::load(
                    &gstleangate::default_model(),
                    &options(ExecutionProvider::Cpu, precision, 0),
                )
                .map_err(one_line)
                .and_then(|mut s| utilities(&mut s, 40))
            })
            .collect();
        // Provider by provider, in the order given (a slow one last does not hold up the others).
        for &ep in &eps {
            for (&(build, precision), cpu) in builds.iter().zip(&cpus) {
                let name = ep.as_str();
                let t = Instant::now();
                let loaded =
                    Scorer::load(&gstleangate::default_model(), &options(ep, precision, 0));
                let load_s = t.elapsed().as_secs_f64();
                let mut s = match loaded {
                    Ok(s) => s,
                    Err(e) => {
                        let e = one_line(e);
                        println!("| {name} | {build} | {load_s:.2} | failed to load: {e} |");
                        println!("CHECK provider={name} build={build} status=failed reason={e}");
                        continue;
                    }
                };
                let diff = match (&cpu, utilities(&mut s, 40)) {
                    (Ok(a), Ok(b)) => Ok(a
                        .iter()
                        .zip(&b)
                        .map(|(x, y)| (x - y).abs())
                        .fold(0.0f32, f32::max)),
                    (Err(e), _) => Err(format!("CPU reference: {e}")),
                    (_, Err(e)) => Err(e),
                };
                let diff = match diff {
                    Ok(d) => d,
                    Err(e) => {
                        println!("| {name} | {build} | {load_s:.2} | scoring failed: {e} |");
                        println!("CHECK provider={name} build={build} status=failed reason={e}");
                        continue;
                    }
                };
                let one: Result<Vec<f64>, String> = (0..reps)
                    .map(|_| {
                        let t = Instant::now();
                        utilities(&mut s, frames).map(|_| frames as f64 / t.elapsed().as_secs_f64())
                    })
                    .collect();
                drop(s);
                let mut failed = Vec::new();
                let one = match one {
                    Ok(v) => median(v),
                    Err(e) => {
                        failed.push(format!("1 stream: {e}"));
                        f64::NAN
                    }
                };
                print!("| {name} | {build} | {load_s:.2} | {diff:.5} | {one:.1} |");
                for &k in &ks {
                    for batch in [1, k] {
                        let fps: Result<Vec<f64>, String> = (0..reps)
                            .map(|_| streams_fps(k, frames / 2, &options(ep, precision, batch)))
                            .collect();
                        match fps {
                            Ok(v) => print!(" {:.1} |", median(v)),
                            Err(e) => {
                                print!(" failed |");
                                failed.push(format!("{k} streams batch {batch}: {e}"));
                            }
                        }
                    }
                }
                println!();
                if failed.is_empty() {
                    println!(
                        "CHECK provider={name} build={build} status=ok max_abs_diff={diff:.6} \
                         fps={one:.1} load_s={load_s:.2}"
                    );
                } else {
                    println!(
                        "CHECK provider={name} build={build} status=failed max_abs_diff={diff:.6} \
                         reason={}",
                        failed.join("; ")
                    );
                }
            }
        }
    }
}
