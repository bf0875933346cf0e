//! Throughput of the tools' library: the synthetic renderer (target: about 50 frames/s at 640x480
//! on a 2-core machine) and the geometric teacher (target: thousands of pairs/s at 160 px).
//! Run: `cargo bench --bench tools`. Prints figures; asserts nothing (speed is not a test).

use std::time::Instant;

use leangate_tools::synth::{self, MotionProfile, Scene, SensorConfig, SynthConfig};
use leangate_tools::teacher::{self, DepthView, DepthViewExt, Teacher, TeacherConfig};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn main() {
    let cfg = SynthConfig {
        seed: 3,
        frames: 60,
        motion: MotionProfile::Mixed,
        ..Default::default()
    };
    let scene = Scene::new(cfg.seed);
    let (poses, _) = synth::camera_path(&cfg, &scene);
    let intr = cfg.intrinsics();
    println!(
        "synth render, 640x480, {} frames per run, 3 runs",
        poses.len()
    );
    let mut fps = Vec::new();
    let mut last = Vec::new();
    for _ in 0..3 {
        let t = Instant::now();
        last = poses
            .iter()
            .map(|p| scene.render(p, &intr, 640, 480))
            .collect::<Vec<_>>();
        fps.push(poses.len() as f64 / t.elapsed().as_secs_f64());
    }
    println!(
        "  render only:            {:8.1} frames/s (median)",
        median(fps)
    );

    let dir = std::env::temp_dir().join(format!("leangate-bench-{}", std::process::id()));
    let t = Instant::now();
    let summary = synth::render_sequence(&cfg, &dir).expect("render_sequence");
    println!(
        "  render + PNG write:     {:8.1} frames/s ({} frames in {:.2} s)",
        summary.total_fps(),
        summary.frames,
        t.elapsed().as_secs_f64()
    );

    for (name, sensor) in [
        ("rolling", "rolling"),
        ("blur", "blur"),
        ("realistic (all, JPEG)", "realistic"),
    ] {
        let real = SynthConfig {
            sensor: sensor.parse::<SensorConfig>().expect("sensor names"),
            ..cfg.clone()
        };
        let d = dir.join(sensor);
        let s = synth::render_sequence(&real, &d).expect("render_sequence");
        println!(
            "  --sensor {name:<22} {:6.1} frames/s render, {:.1} with writing",
            s.render_fps(),
            s.total_fps()
        );
    }

    let tcfg = TeacherConfig::default();
    let views: Vec<DepthView> = last
        .iter()
        .map(|(_, d)| DepthView::new(d, &intr, &tcfg).unwrap())
        .collect();
    let teacher = Teacher::from_views(views, poses.clone(), tcfg.max_dist_m).unwrap();
    let pairs = teacher::pairs_within(teacher.len(), 30);
    let mut rates = Vec::new();
    for _ in 0..3 {
        let t = Instant::now();
        let s = teacher.score_pairs(&pairs);
        assert_eq!(s.len(), pairs.len());
        rates.push(pairs.len() as f64 / t.elapsed().as_secs_f64());
    }
    println!(
        "teacher, {}x{} working resolution, {} pairs per run: {:.0} pairs/s (median of 3, all cores)",
        teacher.view(0).unwrap().width,
        teacher.view(0).unwrap().height,
        pairs.len(),
        median(rates)
    );
    let _ = std::fs::remove_dir_all(&dir);
}
