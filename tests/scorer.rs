//! The scorer on its own (no pipeline): real ONNX Runtime on the fixture models.

mod common;

use common::fixture;
use gstleangate::{ExecutionProvider, ModelSource, Precision, Scorer, ScorerError, ScorerOptions};
use gstleangate::{PixelFormat, Preprocessor, RawFrame, ResizeMode, YuvMatrix};

fn load(name: &str) -> Result<Scorer, ScorerError> {
    Scorer::load(
        &ModelSource::File(fixture(name).into()),
        &ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            ..Default::default()
        },
    )
}

fn constant(len: usize, v: f32) -> Vec<f32> {
    vec![v; len]
}

#[test]
fn pair_model_scores_and_reads_metadata() {
    let mut s = load("mad.onnx").unwrap();
    let info = s.info().clone();
    assert_eq!((info.spec.width, info.spec.height), (64, 64));
    assert_eq!(info.spec.resize, ResizeMode::Stretch);
    assert_eq!(info.name, "fixture-mad");
    assert_eq!(info.threshold, None);
    assert!(!s.is_split());
    let n = info.spec.len();
    let u = s.score(&constant(n, 0.25), &constant(n, 0.75)).unwrap();
    assert!((u - 0.5).abs() < 1e-6);
    assert_eq!(s.provider(), "cpu");

    let m = load("mad_meta.onnx").unwrap();
    let i = m.info();
    assert_eq!(
        (i.spec.width, i.spec.height, i.threshold),
        (48, 32, Some(0.3))
    );
    assert_eq!(i.spec.resize, ResizeMode::ShortSideCrop);

    let f = load("mad_fixed.onnx").unwrap();
    assert_eq!(
        (f.info().spec.width, f.info().spec.height),
        (48, 32),
        "size from the graph"
    );

    let mut two = load("mad_2d.onnx").unwrap();
    let n = two.info().spec.len();
    assert!((two.score(&constant(n, 0.0), &constant(n, 0.2)).unwrap() - 0.2).abs() < 1e-6);
}

#[test]
fn wrong_tensor_length_is_an_error_not_a_crash() {
    let mut s = load("mad.onnx").unwrap();
    let e = s.score(&[0.0; 10], &[0.0; 10]).unwrap_err();
    assert!(e.to_string().contains("does not match [1,3,64,64]"), "{e}");
}

#[test]
fn nan_output_is_an_inference_error() {
    let mut s = load("nan.onnx").unwrap();
    let n = s.info().spec.len();
    let e = s.score(&constant(n, 0.0), &constant(n, 1.0)).unwrap_err();
    assert!(
        matches!(e, ScorerError::Inference(_)) && e.to_string().contains("not finite"),
        "{e}"
    );
}

#[test]
fn split_model_matches_pair_and_caches_the_reference_features() {
    let mut pair = load("mad.onnx").unwrap();
    let mut split = load("split_encoder.onnx").unwrap();
    assert!(split.is_split());
    assert_eq!(split.info().name, "fixture-split");
    let n = split.info().spec.len();
    let frames: Vec<Vec<f32>> = (0..5).map(|k| constant(n, 0.1 * k as f32)).collect();
    // Gate by hand: keep frames 0, 2, 3; the split model must encode each frame once, plus the
    // reference once at the start (it was kept without being scored).
    let keep = [true, false, true, true, false];
    let mut reference = 0;
    let mut scored_frames = 0;
    for i in 1..5 {
        let a = pair.score(&frames[reference], &frames[i]).unwrap();
        let b = split.score(&frames[reference], &frames[i]).unwrap();
        assert!((a - b).abs() < 1e-6, "frame {i}: pair {a} vs split {b}");
        scored_frames += 1;
        if keep[i] {
            split.on_keep(true);
            reference = i;
        }
    }
    assert_eq!(split.encoder_runs(), scored_frames + 1);
    // After a reset the reference is encoded again.
    split.reset_reference();
    split.score(&frames[0], &frames[1]).unwrap();
    assert_eq!(split.encoder_runs(), scored_frames + 3);
}

#[test]
fn split_head_alone_or_missing_is_rejected() {
    let e = load("split_head.onnx").unwrap_err().to_string();
    // The contract it states covers split models too (it described only pair models).
    assert!(
        e.contains("head of a split model") && e.contains("or a split model (an encoder"),
        "{e}"
    );
    let dir = tempfile::tempdir().unwrap();
    let enc = dir.path().join("split_encoder.onnx");
    std::fs::copy(fixture("split_encoder.onnx"), &enc).unwrap();
    let e = Scorer::load(&ModelSource::File(enc), &ScorerOptions::default())
        .unwrap_err()
        .to_string();
    // Named as the head the encoder's metadata names (a hostile probe found it reported as a
    // plain unreadable model file).
    assert!(
        e.contains("split_head.onnx") && e.contains("No such file") && e.contains("leangate.head"),
        "{e}"
    );
}

#[test]
fn auto_provider_falls_back_to_cpu_with_reasons() {
    let s = Scorer::load(
        &ModelSource::File(fixture("mad.onnx").into()),
        &ScorerOptions::default(),
    )
    .unwrap();
    if s.provider() != "cpu" {
        eprintln!(
            "SKIPPED: a GPU provider ({}) is available here",
            s.provider()
        );
        return;
    }
    assert_eq!(s.warnings.len(), 2, "{:?}", s.warnings);
    assert!(s.warnings[0].contains("tensorrt") && s.warnings[1].contains("cuda"));
}

#[test]
fn embedded_default_is_a_split_model_with_its_metadata() {
    let mut s = Scorer::load(
        &gstleangate::default_model(),
        &ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            ..Default::default()
        },
    )
    .unwrap();
    assert!(s.is_split());
    assert_eq!(s.info().name, gstleangate::DEFAULT_MODEL_NAME);
    // Calibrated to the teacher's units: the default threshold is the paper's tau_keep 0.5, and
    // the model says how and on what the calibration was fitted.
    assert_eq!(s.info().threshold, Some(0.5));
    let cal = s
        .info()
        .calibration
        .clone()
        .expect("the default student carries leangate.calibration");
    assert!(cal.contains("tum_fr1_rpy"), "{cal}");
    // Fused with the geometric prior by default (training/fuse.py, fitted across the two real
    // sequences): increasing in the prior and in the student, no quadratic term.
    let f = s
        .info()
        .geometry
        .expect("the default student carries leangate.geometry");
    assert!(f.w[1] > 0.0 && f.w[3] > 0.0 && f.w[2] == 0.0, "{f:?}");
    assert!((0.0..0.3).contains(&f.fuse(0.0, Some(0.0))), "{f:?}");
    assert!(f.fuse(1.0, Some(1.0)) > 0.9, "{f:?}");
    // The pair form of the same network carries the same calibration.
    let pair = Scorer::load(
        &ModelSource::File(
            std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/leangate-s.onnx"),
        ),
        &ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(pair.info().threshold, Some(0.5));
    assert_eq!(pair.info().calibration.as_deref(), Some(cal.as_str()));
    let t = 0.5;
    // On real pictures: a frame against itself is not novel; two unrelated places are.
    let (Some(kitchen), Some(classroom)) = (
        common::shared_data("7scenes_redkitchen_dev/rgb/000000.jpg"),
        common::shared_data("webcam_classroom/rgb"),
    ) else {
        return;
    };
    let first_classroom = std::fs::read_dir(&classroom)
        .unwrap()
        .map(|e| e.unwrap().path())
        .min()
        .unwrap();
    let spec = s.info().spec.clone();
    let tensor = |path: &std::path::Path| picture_tensor(path, &spec);
    let a = tensor(&kitchen);
    let b = tensor(&first_classroom);
    let same = s.score(&a, &a).unwrap() as f64;
    let other = s.score(&a, &b).unwrap() as f64;
    assert!(
        same < t && other >= t,
        "same place {same}, another place {other}, threshold {t}"
    );
}

#[test]
fn the_embedded_students_scores_stay_within_the_score_max_it_promises() {
    // The screening bound relies on leangate.score_max: no score of either build exceeds it, on
    // the most different pictures there are (black, white, noise, stripes, and real frames when
    // ../shared is there), and it is the calibration's top knot, rounded up.
    for precision in [Precision::Fp32, Precision::Int8] {
        let mut s = Scorer::load(
            &gstleangate::default_model(),
            &ScorerOptions {
                execution_provider: ExecutionProvider::Cpu,
                precision,
                ..Default::default()
            },
        )
        .unwrap();
        let max = s
            .info()
            .score_max
            .expect("the embedded student carries leangate.score_max");
        assert_eq!(s.info().geometry.unwrap().s_max, max);
        let cal = s.info().calibration.clone().unwrap();
        let top: f64 = cal
            .split_whitespace()
            .find_map(|k| k.strip_prefix("1:"))
            .and_then(|v| v.trim_end_matches(',').parse().ok())
            .unwrap_or_else(|| panic!("no top knot in {cal}"));
        assert!(
            top <= max && max < top + 1e-3,
            "top knot {top}, score_max {max}"
        );
        let spec = s.info().spec.clone();
        let n = spec.len();
        let mut x = 0x9e37_79b9u32;
        let mut noise = || {
            (0..n)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    (x >> 8) as f32 / (1 << 24) as f32 * 5.0 - 2.5
                })
                .collect::<Vec<f32>>()
        };
        let mut pics = vec![
            vec![-2.5f32; n],
            vec![2.5f32; n],
            (0..n)
                .map(|j| if j / 7 % 2 == 0 { -2.5 } else { 2.5 })
                .collect(),
            noise(),
            noise(),
        ];
        if let Some(dir) = common::shared_data("tum_fr1_rpy/rgb") {
            let mut files: Vec<_> = std::fs::read_dir(dir)
                .unwrap()
                .map(|e| e.unwrap().path())
                .collect();
            files.sort();
            for f in files.iter().step_by(60) {
                pics.push(picture_tensor(f, &spec));
            }
        }
        let mut highest = f64::MIN;
        for a in &pics {
            for b in &pics {
                highest = highest.max(s.score(a, b).unwrap() as f64);
                s.on_keep(false);
            }
        }
        assert!(
            highest <= max,
            "{precision:?}: score {highest} > score_max {max}"
        );
        assert!(
            highest > 0.5,
            "{precision:?}: the pictures reach high scores ({highest})"
        );
    }
}

/// Stream `k`'s frames: smooth pictures that drift, with a jump every 9 frames (so that some
/// frames are kept and the reference moves).
fn stream_frames(len: usize, k: usize, n: usize) -> Vec<Vec<f32>> {
    (0..n)
        .map(|i| {
            let phase = (i / 9) as f32 * 1.7 + k as f32 * 0.61 + (i % 9) as f32 * 0.03;
            (0..len)
                .map(|j| {
                    let x = (j % 256) as f32 / 256.0;
                    let y = (j / 256 % 256) as f32 / 256.0;
                    0.5 + 0.4 * ((x * 7.0 + phase).sin() * (y * 5.0 - phase).cos())
                })
                .collect()
        })
        .collect()
}

/// Score a stream with a simple gate (keep when utility >= 0.42, the new frame then being the
/// reference); (utility, keep) per frame.
fn gate_stream(s: &mut Scorer, frames: &[Vec<f32>]) -> Vec<(f32, bool)> {
    let mut reference = 0;
    let mut out = Vec::new();
    for i in 1..frames.len() {
        let u = s.score(&frames[reference], &frames[i]).unwrap();
        let keep = u >= 0.42;
        if keep {
            s.on_keep(true);
            reference = i;
        }
        out.push((u, keep));
    }
    out
}

/// Shared sessions and batched encoder runs give the same decisions and utilities (within
/// 1e-5) as one unshared, unbatched session per stream, on the same frames; with a session cap
/// of 2, four streams spread over exactly two sessions, two streams each.
#[test]
fn shared_and_batched_scoring_matches_separate_sessions() {
    let opts = |shared: bool, batch_size: usize, max_sessions: usize| ScorerOptions {
        execution_provider: ExecutionProvider::Cpu,
        shared,
        batch_size,
        batch_timeout: std::time::Duration::from_millis(200),
        max_sessions,
        ..Default::default()
    };
    let streams = 4;
    let n = 28;
    let len = {
        let s = Scorer::load(&gstleangate::default_model(), &opts(false, 1, 0)).unwrap();
        s.info().spec.len()
    };
    let frames: Vec<Vec<Vec<f32>>> = (0..streams).map(|k| stream_frames(len, k, n)).collect();

    // Separate sessions, one stream after the other.
    let separate: Vec<Vec<(f32, bool)>> = frames
        .iter()
        .map(|f| {
            let mut s = Scorer::load(&gstleangate::default_model(), &opts(false, 1, 0)).unwrap();
            gate_stream(&mut s, f)
        })
        .collect();

    for (batch, cap) in [(1usize, 1usize), (4, 1), (1, 2), (4, 2)] {
        let mut scorers: Vec<Scorer> = (0..streams)
            .map(|_| Scorer::load(&gstleangate::default_model(), &opts(true, batch, cap)).unwrap())
            .collect();
        // How many scorers each distinct session serves.
        let mut groups = std::collections::BTreeMap::<usize, usize>::new();
        for (i, s) in scorers.iter().enumerate() {
            let first = (0..=i)
                .find(|&j| scorers[j].shares_session_with(s))
                .unwrap();
            *groups.entry(first).or_default() += 1;
            assert_eq!(s.is_batching(), batch > 1);
        }
        let groups: Vec<usize> = groups.into_values().collect();
        assert_eq!(
            groups,
            vec![streams / cap; cap],
            "batch {batch}, cap {cap}: scorers per session"
        );
        let before = scorers[0].batch_counts();
        let results: Vec<Vec<(f32, bool)>> = std::thread::scope(|scope| {
            let handles: Vec<_> = scorers
                .iter_mut()
                .zip(&frames)
                .map(|(s, f)| scope.spawn(move || gate_stream(s, f)))
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let (batches, batched_frames) = scorers[0].batch_counts();
        if batch > 1 {
            assert!(
                batched_frames - before.1 > batches - before.0,
                "some runs held several frames: {batches} batches, {batched_frames} frames"
            );
        }
        for (k, (a, b)) in separate.iter().zip(&results).enumerate() {
            assert_eq!(a.len(), b.len());
            for (i, ((ua, ka), (ub, kb))) in a.iter().zip(b).enumerate() {
                assert_eq!(
                    ka, kb,
                    "batch {batch} cap {cap} stream {k} frame {i}: decisions differ"
                );
                assert!(
                    (ua - ub).abs() <= 1e-5,
                    "batch {batch} cap {cap} stream {k} frame {i}: {ua} vs {ub}"
                );
            }
            assert!(
                a.iter().any(|x| x.1) && a.iter().any(|x| !x.1),
                "keeps and drops: {a:?}"
            );
        }
    }
    // A scorer with sharing off gets its own session.
    let a = Scorer::load(&gstleangate::default_model(), &opts(true, 1, 1)).unwrap();
    let b = Scorer::load(&gstleangate::default_model(), &opts(false, 1, 1)).unwrap();
    assert!(!a.shares_session_with(&b));
}

/// The default session cap: one session per core on the CPU provider (each session scores one
/// frame at a time), one on GPU providers.
#[test]
fn default_session_cap_is_one_per_core_on_cpu() {
    let cores = std::thread::available_parallelism().unwrap().get();
    assert_eq!(gstleangate::default_max_sessions("cpu", 1), cores);
    assert_eq!(
        gstleangate::default_max_sessions("cpu", 2),
        (cores / 2).max(1)
    );
    assert_eq!(gstleangate::default_max_sessions("cuda", 1), 1);
    assert_eq!(gstleangate::default_max_sessions("tensorrt", 1), 1);
    // Streams beyond the cap join existing sessions; below it each gets its own.
    let opts = ScorerOptions {
        execution_provider: ExecutionProvider::Cpu,
        shared: true,
        // A key no other test of this binary uses.
        threads: 5,
        ..Default::default()
    };
    let cap = opts.effective_max_sessions("cpu");
    let scorers: Vec<Scorer> = (0..cap + 2)
        .map(|_| Scorer::load(&gstleangate::default_model(), &opts).unwrap())
        .collect();
    let distinct = (0..scorers.len())
        .filter(|&i| {
            !scorers[..i]
                .iter()
                .any(|o| o.shares_session_with(&scorers[i]))
        })
        .count();
    assert_eq!(distinct, cap);
}

/// Batching adds no latency to a stream that is alone on its session: with a one-second
/// `batch_timeout`, five frames take far less than a second.
#[test]
fn a_single_batching_stream_never_waits() {
    let opts = ScorerOptions {
        execution_provider: ExecutionProvider::Cpu,
        shared: true,
        batch_size: 8,
        batch_timeout: std::time::Duration::from_secs(1),
        // A key no other test of this binary uses: a session of its own.
        threads: 3,
        ..Default::default()
    };
    let mut s = Scorer::load(&gstleangate::default_model(), &opts).unwrap();
    assert!(s.is_batching());
    let len = s.info().spec.len();
    let frames = stream_frames(len, 7, 6);
    let t = std::time::Instant::now();
    for f in &frames[1..] {
        s.score(&frames[0], f).unwrap();
    }
    assert!(
        t.elapsed() < std::time::Duration::from_millis(900),
        "{:?} for five frames",
        t.elapsed()
    );
}

/// Issue 22, item 2: a stream that stops must not slow the others down to one frame per
/// `batch_timeout`. Four scorers batch on one session (batch 4, a one-second timeout); one stops
/// after 10 frames, either silently (a sink that stopped pulling: only the timeout tells) or
/// saying so (`idle`, as the element does at EOS, PAUSED or a flush). The other three then score
/// 40 frames each far faster than 30 x 1 s (before the fix: one frame per second each), still in
/// batches.
#[test]
fn a_stream_that_stops_does_not_hold_back_the_others_batches() {
    for says_so in [false, true] {
        // A copy of the student: a session of its own.
        let (_dir, encoder) = common::student_copy();
        let source = ModelSource::File(encoder);
        let opts = ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            shared: true,
            max_sessions: 1,
            batch_size: 4,
            batch_timeout: std::time::Duration::from_secs(1),
            ..Default::default()
        };
        let mut scorers: Vec<Scorer> = (0..4)
            .map(|_| Scorer::load(&source, &opts).unwrap())
            .collect();
        assert!(scorers.iter().all(|s| s.is_batching()));
        assert_eq!(scorers[0].batch_members(), (4, 0), "none streams yet");
        let len = scorers[0].info().spec.len();
        let frames: Vec<Vec<Vec<f32>>> = (0..4).map(|k| stream_frames(len, k, 41)).collect();
        let t0 = std::time::Instant::now();
        let took: Vec<std::time::Duration> = std::thread::scope(|scope| {
            let handles: Vec<_> = scorers
                .iter_mut()
                .zip(&frames)
                .enumerate()
                .map(|(k, (s, f))| {
                    scope.spawn(move || {
                        if k == 0 {
                            gate_stream(s, &f[..11]);
                            if says_so {
                                s.idle();
                            }
                        } else {
                            gate_stream(s, f);
                        }
                        t0.elapsed()
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let (batches, batched) = scorers[0].batch_counts();
        eprintln!(
            "stopper says so: {says_so}; finished after {took:?}; {batches} batches of {batched} \
             frames"
        );
        for t in &took[1..] {
            assert!(
                *t < std::time::Duration::from_secs(10),
                "stopper says so: {says_so}: 40 frames took {t:?} (one per batch timeout: 30 s)"
            );
        }
        assert!(batched > batches, "frames were still batched");
        let (members, streaming) = scorers[0].batch_members();
        assert_eq!(members, 4);
        if says_so {
            assert!(
                streaming <= 3,
                "the stopped stream does not count: {streaming}"
            );
        }
        drop(scorers.remove(0));
        assert_eq!(scorers[0].batch_members().0, 3, "a dropped scorer leaves");
    }
}

/// When another session of a shared model cannot be created, a new scorer shares an existing
/// one and says so in its warnings, instead of failing to start. The second load is made to
/// fail by corrupting the split model's head file after the first load, keeping its size and
/// modification time (the registry knows a model by its files' sizes and times, so the second
/// scorer still looks for a session of the same model).
#[test]
fn a_failed_extra_session_falls_back_to_sharing_one_that_works() {
    let (dir, encoder) = common::student_copy();
    let source = ModelSource::File(encoder);
    let opts = ScorerOptions {
        execution_provider: ExecutionProvider::Cpu,
        shared: true,
        max_sessions: 2,
        ..Default::default()
    };
    let mut first = Scorer::load(&source, &opts).unwrap();
    assert!(first.warnings.is_empty(), "{:?}", first.warnings);
    let head = dir.path().join("leangate-s-head.onnx");
    let (len, modified) = {
        let md = std::fs::metadata(&head).unwrap();
        (md.len() as usize, md.modified().unwrap())
    };
    let mut garbage = b"not an onnx model".repeat(len / 17 + 1);
    garbage.truncate(len);
    std::fs::write(&head, garbage).unwrap();
    std::fs::File::options()
        .write(true)
        .open(&head)
        .unwrap()
        .set_modified(modified)
        .unwrap();
    // With sharing off the broken head is a plain start error...
    let err = Scorer::load(
        &source,
        &ScorerOptions {
            shared: false,
            ..opts.clone()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("head"), "{err}");
    // ...with sharing on, below the cap, the new scorer shares the session that works.
    let mut second = Scorer::load(&source, &opts).unwrap();
    assert!(second.shares_session_with(&first));
    assert_eq!(second.warnings.len(), 1, "{:?}", second.warnings);
    assert!(
        second.warnings[0].contains("could not be created, sharing an existing one"),
        "{:?}",
        second.warnings
    );
    let len = first.info().spec.len();
    let (a, b) = (stream_frames(len, 0, 2), stream_frames(len, 1, 2));
    let ua = first.score(&a[0], &a[1]).unwrap();
    let ub = second.score(&a[0], &a[1]).unwrap();
    assert_eq!(ua, ub);
    assert!(second.score(&b[0], &b[1]).unwrap().is_finite());
    // With no working session left, the broken model is an error again.
    drop((first, second));
    assert!(Scorer::load(&source, &opts).is_err());
}

/// The embedded student's calibration (its knots, as `leangate.calibration` states them) covers
/// the raw range 0..1 and is strictly increasing: every threshold inside its range makes a
/// different cut of the network's ranking (a flat segment would make neighbouring thresholds
/// keep the same frames).
#[test]
fn embedded_calibration_is_strictly_increasing() {
    let s = Scorer::load(
        &gstleangate::default_model(),
        &ScorerOptions {
            execution_provider: ExecutionProvider::Cpu,
            ..Default::default()
        },
    )
    .unwrap();
    let cal = s.info().calibration.clone().unwrap();
    let knots: Vec<(f64, f64)> = cal
        .split("raw->calibrated ")
        .nth(1)
        .unwrap_or_else(|| panic!("no knots in {cal:?}"))
        .split([' ', ','])
        .map_while(|tok| {
            let (r, c) = tok.split_once(':')?;
            Some((r.parse().ok()?, c.parse().ok()?))
        })
        .collect();
    assert!(knots.len() >= 3, "{cal}");
    assert_eq!(knots.first().unwrap().0, 0.0, "{cal}");
    assert_eq!(knots.last().unwrap().0, 1.0, "{cal}");
    for w in knots.windows(2) {
        assert!(w[1].0 > w[0].0, "raw knots increase: {cal}");
        assert!(
            w[1].1 > w[0].1,
            "calibrated values strictly increase: {cal}"
        );
    }
}

/// A picture file as the model's input tensor (the element's preprocessing).
fn picture_tensor(path: &std::path::Path, spec: &gstleangate::TensorSpec) -> Vec<f32> {
    let img = image::open(path).unwrap().to_rgb8();
    let (w, h) = img.dimensions();
    let pre = Preprocessor::new(PixelFormat::Rgb, w, h, YuvMatrix::BT601, spec.clone()).unwrap();
    let raw = RawFrame::rgb(img.as_raw(), w, h);
    let mut t = vec![0.0; spec.len()];
    pre.run(&raw, &mut t).unwrap();
    t
}

/// The embedded student has an INT8 build: `precision` auto runs it on the CPU, fp32 runs the
/// FP32 build (the same network as `models/leangate-s.onnx`, to 1e-5), and the two builds never
/// share a session. On real 7-Scenes pairs (every frame against its next 24) the INT8 utilities
/// stay within 0.05 of the FP32 ones, 0.01 on average (quantization measured 0.017 / 0.002).
#[test]
fn embedded_student_runs_its_int8_build_on_the_cpu_unless_fp32_is_asked() {
    use gstleangate::Precision;
    let opts = |precision: Precision| ScorerOptions {
        execution_provider: ExecutionProvider::Cpu,
        precision,
        ..Default::default()
    };
    let mut int8 = Scorer::load(&gstleangate::default_model(), &opts(Precision::Auto)).unwrap();
    let explicit = Scorer::load(&gstleangate::default_model(), &opts(Precision::Int8)).unwrap();
    let mut fp32 = Scorer::load(&gstleangate::default_model(), &opts(Precision::Fp32)).unwrap();
    assert_eq!(int8.info().precision, "int8");
    assert_eq!(explicit.info().precision, "int8");
    assert_eq!(fp32.info().precision, "fp32");
    assert!(int8.warnings.is_empty(), "{:?}", int8.warnings);
    // Same model, same threshold and calibration text; different sessions.
    assert_eq!(int8.info().name, fp32.info().name);
    assert_eq!(int8.info().threshold, Some(0.5));
    assert_eq!(int8.info().calibration, fp32.info().calibration);
    assert!(!int8.shares_session_with(&fp32));
    assert!(!explicit.shares_session_with(&fp32));
    // A model file runs as it is: precision does not apply, and says so.
    let pair_path =
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/leangate-s.onnx");
    let mut pair = Scorer::load(&ModelSource::File(pair_path), &opts(Precision::Int8)).unwrap();
    assert_eq!(pair.info().precision, "fp32");
    assert!(
        pair.warnings
            .iter()
            .any(|w| w.contains("precision `int8` applies to the embedded student only")),
        "{:?}",
        pair.warnings
    );

    let Some(dir) = common::shared_data("7scenes_redkitchen_dev/rgb") else {
        return;
    };
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    let spec = fp32.info().spec.clone();
    let frames: Vec<Vec<f32>> = files.iter().map(|f| picture_tensor(f, &spec)).collect();
    let (mut sum, mut max, mut n) = (0.0f64, 0.0f64, 0usize);
    for i in 0..frames.len() {
        for j in i + 1..frames.len().min(i + 25) {
            let u = |s: &mut Scorer| {
                s.reset_reference();
                s.score(&frames[i], &frames[j]).unwrap() as f64
            };
            let (a, b, p) = (u(&mut int8), u(&mut fp32), u(&mut pair));
            assert!(
                (b - p).abs() < 1e-5,
                "pair {i}->{j}: fp32 build {b}, pair model {p}"
            );
            let d = (a - b).abs();
            sum += d;
            max = max.max(d);
            n += 1;
        }
    }
    let mean = sum / n as f64;
    assert!(n > 1000, "{n} pairs");
    assert!(
        max <= 0.05 && mean <= 0.01,
        "int8 vs fp32 over {n} pairs: mean {mean:.4}, max {max:.4}"
    );
}

/// What a model reads besides its own file is part of what it is (found by a hostile probe): a
/// split model whose head was replaced while an element ran on it was shared by the next element
/// with the old head still loaded. `files_read` names the head and external tensor data, and a
/// scorer loaded after one of them changed gets a session of its own.
#[test]
fn a_replaced_head_or_external_data_file_is_a_new_model_for_sharing() {
    let dir = tempfile::tempdir().unwrap();
    for f in [
        "split_encoder.onnx",
        "split_head.onnx",
        "ext_data.onnx",
        "ext_data.onnx.data",
    ] {
        std::fs::copy(fixture(f), dir.path().join(f)).unwrap();
    }
    let canon = |f: &str| dir.path().join(f).canonicalize().unwrap();
    let enc = dir.path().join("split_encoder.onnx");
    assert_eq!(
        gstleangate::files_read(&enc),
        vec![canon("split_encoder.onnx"), canon("split_head.onnx")]
    );
    let ext = dir.path().join("ext_data.onnx");
    assert_eq!(
        gstleangate::files_read(&ext),
        vec![canon("ext_data.onnx"), canon("ext_data.onnx.data")]
    );
    let opts = ScorerOptions {
        execution_provider: ExecutionProvider::Cpu,
        shared: true,
        max_sessions: 1,
        ..Default::default()
    };
    for (model, read) in [(&enc, "split_head.onnx"), (&ext, "ext_data.onnx.data")] {
        let a = Scorer::load(&ModelSource::File(model.clone()), &opts).unwrap();
        let b = Scorer::load(&ModelSource::File(model.clone()), &opts).unwrap();
        assert!(
            a.shares_session_with(&b),
            "{read}: the same files are shared"
        );
        // The same bytes written again: a new modification time, as a replaced file has.
        let path = dir.path().join(read);
        let bytes = std::fs::read(&path).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        std::fs::remove_file(&path).unwrap();
        std::fs::write(&path, bytes).unwrap();
        let c = Scorer::load(&ModelSource::File(model.clone()), &opts).unwrap();
        assert!(
            !c.shares_session_with(&a),
            "{read} replaced: the next scorer must load it afresh"
        );
    }
}

/// An encoder that declares a dynamic batch is run in batches with `batch-size`: one that cannot
/// take a batch is refused at load (found by a hostile probe: it passed the dry run of one frame,
/// then every batched frame failed and was kept).
#[test]
fn an_encoder_that_declares_a_batch_but_cannot_take_one_is_refused() {
    let e = load("split_batch_one_encoder.onnx")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("dynamic batch") && e.contains("batch of 2") && e.contains("shape [1"),
        "{e}"
    );
    // The same encoder computing per frame loads.
    load("split_encoder.onnx").unwrap();
}

/// One model's load does not hold up another's (found by a hostile probe: the registry of shared
/// sessions stayed locked while a model loaded, so an element starting with a slow model, or one
/// whose start never ended, held up every other element's start in the process). Streams of the
/// same model still wait for its one load.
#[test]
fn a_slow_model_load_does_not_hold_up_another_models_load() {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    let opts = ScorerOptions {
        execution_provider: ExecutionProvider::Cpu,
        shared: true,
        ..Default::default()
    };
    let slow_done = Arc::new(AtomicBool::new(false));
    let slow = {
        let (opts, done) = (opts.clone(), slow_done.clone());
        std::thread::spawn(move || {
            let s = Scorer::load(&ModelSource::File(fixture("slow.onnx").into()), &opts);
            done.store(true, Ordering::SeqCst);
            s.map(|_| ())
        })
    };
    // The slow model's start (its dry run: three 1600x1600 products) has begun.
    std::thread::sleep(std::time::Duration::from_millis(100));
    Scorer::load(&ModelSource::File(fixture("mad.onnx").into()), &opts).unwrap();
    let other_first = !slow_done.load(Ordering::SeqCst);
    slow.join().unwrap().unwrap();
    assert!(
        other_first,
        "mad.onnx loaded only after slow.onnx: the registry was held through the slow load"
    );
}
