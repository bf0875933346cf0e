//! The GPU check (issue 35): `scripts/gpu-check.sh`, the one command a session with a lent GPU
//! machine runs, and the tests it runs there.
//!
//! - Without a GPU (here, CI) the script must end at once with exit status 2, one line saying
//!   "no GPU", and a figures file saying so: never hang, never build anything.
//! - On a GPU, with the GPU ONNX Runtime (`LEANGATE_EXPECT_CUDA=1`, which the script sets): the
//!   CUDA provider loads, scores the embedded student as the CPU does, and runs in a pipeline;
//!   TensorRT likewise when `LEANGATE_EXPECT_TENSORRT=1` (the script sets it when TensorRT's
//!   libraries are there). Elsewhere these tests print SKIPPED and pass.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use gstleangate::{ExecutionProvider, Precision, Scorer, ScorerOptions};

#[test]
fn without_a_gpu_the_check_exits_2_at_once_saying_so() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let figures = dir.path().join("figures.md");
    let (out, err) = (dir.path().join("stdout"), dir.path().join("stderr"));
    let mut cmd = Command::new("bash");
    cmd.arg(root.join("scripts/gpu-check.sh"))
        .arg(&figures)
        .current_dir(dir.path())
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap());
    // On a machine with a GPU (the check runs this test there too), ask a nvidia-smi that is
    // not there; elsewhere the one on PATH, as a user's run would (none here).
    let gpu = Command::new("nvidia-smi")
        .arg("-L")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if gpu {
        cmd.env("LEANGATE_NVIDIA_SMI", "/nonexistent/nvidia-smi");
    } else {
        cmd.env_remove("LEANGATE_NVIDIA_SMI");
    }
    let t = Instant::now();
    let mut child = cmd.spawn().unwrap();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("scripts/gpu-check.sh still running after 60 s without a GPU");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let elapsed = t.elapsed();
    let stderr = std::fs::read_to_string(&err).unwrap();
    let stdout = std::fs::read_to_string(&out).unwrap();
    assert_eq!(status.code(), Some(2), "{stdout}{stderr}");
    assert!(elapsed < Duration::from_secs(20), "took {elapsed:?}");
    assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    assert!(
        stderr.starts_with("gpu-check: no GPU: ") && stderr.contains("nvidia-smi"),
        "{stderr}"
    );
    assert!(stdout.is_empty(), "{stdout}");
    let text = std::fs::read_to_string(&figures).expect("the figures file is written");
    assert!(
        text.contains("- GPU: no GPU (") && text.contains("nvidia-smi"),
        "{text}"
    );
    assert!(
        text.contains("| gpu | skip | ")
            && text.contains("| no GPU: ")
            && text.contains("nothing was measured"),
        "{text}"
    );
    assert!(
        !text.contains("| build |"),
        "nothing runs without a GPU: {text}"
    );
    // The raw log beside it (the figures file names it).
    let log = dir.path().join("figures.log");
    assert!(log.is_file() && text.contains(&log.display().to_string()));
}

fn expects(var: &str) -> bool {
    if std::env::var_os(var).is_some() {
        return true;
    }
    eprintln!("SKIPPED: {var} is not set (no GPU expected here; scripts/gpu-check.sh sets it)");
    false
}

fn load(ep: ExecutionProvider, precision: Precision) -> Scorer {
    Scorer::load(
        &gstleangate::default_model(),
        &ScorerOptions {
            execution_provider: ep,
            precision,
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{} does not load: {e}", ep.as_str()))
}

/// Utilities of 30 frames of textures (a keep every 5th).
fn utilities(s: &mut Scorer) -> Vec<f32> {
    let spec = s.info().spec.clone();
    let (w, h) = (spec.width as usize, spec.height as usize);
    let pics: Vec<Vec<f32>> = (0..6)
        .map(|k| {
            (0..3 * w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f32, ((i / w) % h) as f32);
                    0.5 + 0.4 * ((x + 3.0 * k as f32) * 0.21).sin() * ((y - k as f32) * 0.13).cos()
                })
                .collect()
        })
        .collect();
    let mut reference = 0;
    (1..=30)
        .map(|i| {
            let u = s.score(&pics[reference], &pics[i % 6]).unwrap();
            if i % 5 == 0 {
                s.on_keep(true);
                reference = i % 6;
            }
            u
        })
        .collect()
}

/// FP32 within 0.02 of the CPU's utilities (TF32 convolutions on the GPU); INT8 within 0.05
/// (the GPU's 8-bit kernels may round differently from the CPU's).
fn agrees_with_the_cpu(ep: ExecutionProvider) {
    for (precision, tolerance) in [(Precision::Fp32, 0.02), (Precision::Int8, 0.05)] {
        let mut gpu = load(ep, precision);
        assert_eq!(gpu.provider(), ep.as_str());
        let a = utilities(&mut load(ExecutionProvider::Cpu, precision));
        let b = utilities(&mut gpu);
        let diff = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        eprintln!("{} {}: max |du| {diff}", ep.as_str(), precision.as_str());
        assert!(
            diff < tolerance,
            "{} {} differs from the CPU by {diff}: {a:?} vs {b:?}",
            ep.as_str(),
            precision.as_str()
        );
    }
}

#[test]
fn cuda_scores_the_embedded_student_as_the_cpu_does() {
    if expects("LEANGATE_EXPECT_CUDA") {
        agrees_with_the_cpu(ExecutionProvider::Cuda);
    }
}

#[test]
fn tensorrt_scores_the_embedded_student_as_the_cpu_does() {
    if expects("LEANGATE_EXPECT_TENSORRT") {
        agrees_with_the_cpu(ExecutionProvider::TensorRt);
    }
}

#[test]
fn auto_chooses_a_gpu_provider() {
    if expects("LEANGATE_EXPECT_CUDA") {
        let s = load(ExecutionProvider::Auto, Precision::Auto);
        let want = if std::env::var_os("LEANGATE_EXPECT_TENSORRT").is_some() {
            "tensorrt"
        } else {
            "cuda"
        };
        assert_eq!(s.provider(), want, "warnings: {:?}", s.warnings);
        assert_eq!(s.info().precision, "fp32", "FP32 on GPU providers");
    }
}

#[test]
fn the_element_runs_on_cuda() {
    if !expects("LEANGATE_EXPECT_CUDA") {
        return;
    }
    let msgs = common::run_pipeline(
        "videotestsrc num-buffers=40 pattern=ball ! video/x-raw,width=640,height=480,framerate=30/1 ! \
         leangate execution-provider=cuda stats-interval=300000000 ! fakesink",
        60,
    );
    assert!(
        common::error_text(&msgs).is_none(),
        "{:?}",
        common::error_text(&msgs)
    );
    let stats: Vec<gstleangate::StatsMessage> = common::element_message(&msgs, "leangate-stats")
        .into_iter()
        .map(|s| gstleangate::StatsMessage::from_structure(s).unwrap())
        .collect();
    let last = stats.last().expect("leangate-stats messages");
    assert_eq!(last.execution_provider, "cuda", "{last:?}");
}
