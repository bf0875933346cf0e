use std::path::Path;
use std::time::Instant;

use image::RgbImage;
use nalgebra::{Isometry3, Vector3};

use super::materials::Pattern;
use super::motion::generate_path;
use super::render::render_frame;
use super::*;
use crate::dataset::{RgbFormat, Sequence};
use crate::teacher::{score_pair, DepthView, TeacherConfig};

fn small_cfg(motion: MotionProfile, frames: usize) -> SynthConfig {
    SynthConfig {
        seed: 7,
        frames,
        width: 64,
        height: 48,
        motion,
        ..Default::default()
    }
}

#[test]
fn profile_names_round_trip() {
    for p in MotionProfile::ALL {
        assert_eq!(p.name().parse::<MotionProfile>().unwrap(), p);
    }
    assert!("fly".parse::<MotionProfile>().is_err());
}

#[test]
fn render_is_deterministic() {
    let cfg = SynthConfig {
        blur: true,
        lighting_changes: true,
        ..small_cfg(MotionProfile::Shaky, 12)
    };
    let scene = Scene::new(cfg.seed);
    let (samples, _) = generate_path(&scene, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
    let a = render_frame(&cfg, &scene, &samples, 5);
    let scene2 = Scene::new(cfg.seed);
    let (samples2, _) = generate_path(&scene2, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
    let b = render_frame(&cfg, &scene2, &samples2, 5);
    assert_eq!(a.0.as_raw(), b.0.as_raw());
    assert_eq!(a.1, b.1);
    let other = Scene::new(cfg.seed + 1);
    assert_ne!(other.room, scene.room);
}

#[test]
fn camera_stays_in_region_and_depth_is_valid() {
    for p in MotionProfile::ALL {
        let cfg = small_cfg(p, 240);
        let scene = Scene::new(cfg.seed);
        let (poses, segs) = camera_path(&cfg, &scene);
        assert_eq!(poses.len(), 240);
        assert!(!segs.is_empty());
        let (lo, hi) = scene.camera_region;
        for pose in &poses {
            let t = pose.translation.vector;
            for a in 0..3 {
                assert!(t[a] > lo[a] - 0.1 && t[a] < hi[a] + 0.1, "{p}: {t:?}");
            }
        }
        let intr = cfg.intrinsics();
        let (_, d) = scene.render(&poses[100], &intr, cfg.width, cfg.height);
        assert!(d.data.iter().all(|&z| z > 0.05 && z < 15.0), "{p}");
    }
}

/// The per-row box culling must not change the result: compare with an exhaustive f64
/// ray cast against the room and every box.
#[test]
fn culled_render_matches_brute_force() {
    let cfg = SynthConfig {
        width: 80,
        height: 60,
        ..small_cfg(MotionProfile::Shaky, 120)
    };
    let scene = Scene::new(5);
    let (poses, _) = camera_path(&cfg, &scene);
    let k = cfg.intrinsics();
    let mut box_hits = 0;
    for pose in poses.iter().step_by(10) {
        let (_, d) = scene.render(pose, &k, cfg.width, cfg.height);
        for v in 0..cfg.height {
            for u in 0..cfg.width {
                let dc = Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
                let dw = pose.rotation * dc;
                let o = pose.translation.vector;
                let mut best = f64::INFINITY;
                for a in 0..3 {
                    let wall = if dw[a] > 0.0 { scene.room[a] } else { 0.0 };
                    best = best.min((wall - o[a]) / dw[a]);
                }
                let room_t = best;
                for b in &scene.boxes {
                    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
                    for a in 0..3 {
                        let (mut ta, mut tb) = (
                            (b.lo[a] as f64 - o[a]) / dw[a],
                            (b.hi[a] as f64 - o[a]) / dw[a],
                        );
                        if ta > tb {
                            std::mem::swap(&mut ta, &mut tb);
                        }
                        t0 = t0.max(ta);
                        t1 = t1.min(tb);
                    }
                    if t0 <= t1 && t0 > 0.0 {
                        best = best.min(t0);
                    }
                }
                if best < room_t {
                    box_hits += 1;
                }
                let got = d.data[(v * cfg.width + u) as usize] as f64;
                assert!(
                    (got - best).abs() < 1e-3 * best,
                    "({u},{v}): {got} vs {best}"
                );
            }
        }
    }
    assert!(
        box_hits > 1000,
        "scene should show furniture ({box_hits} pixels)"
    );
}

#[test]
fn motion_profiles_have_expected_speeds() {
    let speed = |p: MotionProfile| {
        let cfg = small_cfg(p, 150);
        let scene = Scene::new(3);
        let (poses, _) = camera_path(&cfg, &scene);
        let rot: f64 = poses
            .windows(2)
            .map(|w| (w[0].inverse() * w[1]).rotation.angle())
            .sum();
        rot.to_degrees() / 5.0 // deg/s over 5 s
    };
    let st = speed(MotionProfile::Static);
    let pan = speed(MotionProfile::Pan);
    let rot = speed(MotionProfile::Rotate);
    assert!(st < 2.0, "static {st} deg/s");
    assert!(pan > 10.0 && pan < 40.0, "pan {pan} deg/s");
    assert!(rot > pan, "rotate {rot} vs pan {pan}");
}

#[test]
fn depth_is_consistent_with_poses() {
    let cfg = SynthConfig {
        width: 160,
        height: 120,
        ..small_cfg(MotionProfile::Walk, 30)
    };
    let scene = Scene::new(11);
    let (poses, _) = camera_path(&cfg, &scene);
    let intr = cfg.intrinsics();
    let tc = TeacherConfig::default();
    let view = |p: &Isometry3<f64>| {
        let (_, d) = scene.render(p, &intr, cfg.width, cfg.height);
        DepthView::new(&d, &intr, &tc).unwrap()
    };
    let v0 = view(&poses[0]);
    let same = score_pair(&v0, &poses[0], &view(&poses[0]), &poses[0], 0.1);
    assert_eq!(same.tau, 0.0);
    // a tiny motion: 5 mm sideways
    let tiny = poses[0] * Isometry3::translation(0.005, 0.0, 0.0);
    let s = score_pair(&view(&tiny), &tiny, &v0, &poses[0], 0.1);
    assert!(s.tau < 0.05, "tiny motion tau {}", s.tau);
    // a few frames of walking: still mostly overlapping, and not trivially so
    let s = score_pair(&view(&poses[5]), &poses[5], &v0, &poses[0], 0.1);
    assert!(s.tau > 0.0 && s.tau < 0.5, "walk tau {:?}", s);
}

#[test]
fn written_sequence_loads_back() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = SynthConfig {
        rgb_format: RgbFormat::Jpeg(90),
        lighting_changes: true,
        ..small_cfg(MotionProfile::Mixed, 6)
    };
    let out = dir.path().join("synth");
    let sum = render_sequence(&cfg, &out).unwrap();
    assert_eq!(sum.frames, 6);
    let seq = Sequence::open(&out).unwrap();
    assert_eq!(seq.len(), 6);
    assert!(seq.has_ground_truth());
    assert_eq!(seq.intrinsics, Some(cfg.intrinsics()));
    assert_eq!(seq.load_rgb(3).unwrap().dimensions(), (64, 48));
    let d = seq.load_depth_m(3).unwrap();
    assert!(d.data.iter().all(|&z| z > 0.0));
    assert!(out.join("synth.json").is_file());
    let teacher = crate::teacher::Teacher::from_sequence(&seq, &TeacherConfig::default()).unwrap();
    assert_eq!(teacher.score(2, 2).tau, 0.0);
}

#[test]
fn image_textures_are_used() {
    let dir = tempfile::tempdir().unwrap();
    let tex = dir.path().join("tex");
    std::fs::create_dir(&tex).unwrap();
    // a pure red texture: some surfaces must come out red-dominant
    RgbImage::from_pixel(16, 16, image::Rgb([255, 0, 0]))
        .save(tex.join("red.png"))
        .unwrap();
    let cfg = SynthConfig {
        textures: Some(tex.clone()),
        noise: 0.0,
        ..small_cfg(MotionProfile::Rotate, 3)
    };
    let textures = load_textures(&tex).unwrap();
    let scene = Scene::with_textures(cfg.seed, &textures);
    assert!(scene
        .materials
        .iter()
        .any(|m| matches!(m.pattern, Pattern::Image(0))));
    let out = dir.path().join("seq");
    render_sequence(&cfg, &out).unwrap();
    assert_eq!(Sequence::open(&out).unwrap().len(), 3);
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    assert!(load_textures(&empty).is_err());
}

#[test]
fn bad_config_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = SynthConfig {
        frames: 0,
        ..Default::default()
    };
    assert!(render_sequence(&cfg, dir.path()).is_err());
    let cfg = SynthConfig {
        textures: Some(dir.path().join("nope")),
        ..small_cfg(MotionProfile::Static, 2)
    };
    assert!(render_sequence(&cfg, &dir.path().join("o")).is_err());
}

/// Writes a visual sample, not a test: `LEANGATE_SYNTH_SAMPLE=/tmp/x cargo test synth_sample -- --ignored`.
#[test]
#[ignore]
fn synth_sample() {
    let Ok(out) = std::env::var("LEANGATE_SYNTH_SAMPLE") else {
        eprintln!("set LEANGATE_SYNTH_SAMPLE to an output directory");
        return;
    };
    let cfg = SynthConfig {
        frames: 90,
        seed: std::env::var("LEANGATE_SYNTH_SEED")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(1),
        blur: true,
        lighting_changes: true,
        ..Default::default()
    };
    let sum = render_sequence(&cfg, Path::new(&out)).unwrap();
    eprintln!("{:?}", sum.segments);
}

/// Timing helper, not a test: `cargo test --release synth_speed -- --ignored --nocapture`.
#[test]
#[ignore]
fn synth_speed() {
    let cfg = SynthConfig {
        frames: 60,
        ..Default::default()
    };
    let scene = Scene::new(cfg.seed);
    let (samples, _) = generate_path(&scene, cfg.motion, cfg.fps, cfg.frames, cfg.seed);
    let t0 = Instant::now();
    for i in 0..cfg.frames {
        let _ = render_frame(&cfg, &scene, &samples, i);
    }
    let r = cfg.frames as f64 / t0.elapsed().as_secs_f64();
    let dir = tempfile::tempdir().unwrap();
    let sum = render_sequence(&cfg, &dir.path().join("s")).unwrap();
    eprintln!(
        "render only: {r:.1} frames/s at 640x480; render_sequence: render {:.1} fps, with writing {:.1} fps",
        sum.render_fps(),
        sum.total_fps()
    );
}
