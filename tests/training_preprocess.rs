//! The training pipeline's Python preprocessing (`training/preprocess.py`, which makes every
//! training, calibration and evaluation tensor) against the element's own (`Preprocessor`):
//! short-side-crop with area averaging (and bilinear when upscaling) must agree to 1/255 on the
//! same RGB picture, at integer and non-integer scales. Runs `.venv/bin/python` (numpy is all the
//! resampling needs); skips with a message when that venv is absent.

use std::path::{Path, PathBuf};
use std::process::Command;

use gstleangate::{PixelFormat, Preprocessor, RawFrame, ResizeMode, TensorSpec, YuvMatrix};

const OUT_W: u32 = 160;
const OUT_H: u32 = 120;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn python() -> Option<PathBuf> {
    let p = repo().join(".venv/bin/python");
    p.exists().then_some(p)
}

/// A deterministic picture with smooth gradients, sharp edges and pixel-level noise, so that tap
/// weights and crop offsets both matter.
fn picture(w: u32, h: u32, seed: u32) -> Vec<u8> {
    let mut v = Vec::with_capacity((w * h * 3) as usize);
    let mut s = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
    for y in 0..h {
        for x in 0..w {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            let noise = (s % 64) as f32;
            let fx = x as f32 / w as f32;
            let fy = y as f32 / h as f32;
            let checker = if ((x / 7) + (y / 5)) % 2 == 0 {
                90.0
            } else {
                0.0
            };
            let r = 160.0 * fx + noise;
            let g = 120.0 * fy + checker;
            let b = 255.0 * (0.5 + 0.5 * (fx * 23.0 + fy * 17.0).sin()) * 0.7 + noise * 0.5;
            v.push(r.clamp(0.0, 255.0) as u8);
            v.push(g.clamp(0.0, 255.0) as u8);
            v.push(b.clamp(0.0, 255.0) as u8);
        }
    }
    v
}

/// The element's tensor in [0, 1] (mean 0, std 1), CHW.
fn element_tensor(rgb: &[u8], w: u32, h: u32) -> Vec<f32> {
    let spec = TensorSpec {
        width: OUT_W,
        height: OUT_H,
        resize: ResizeMode::ShortSideCrop,
        mean: [0.0; 3],
        std: [1.0; 3],
    };
    let pre = Preprocessor::new(PixelFormat::Rgb, w, h, YuvMatrix::BT601, spec).unwrap();
    let frame = RawFrame::rgb(rgb, w, h);
    let mut out = vec![0f32; (3 * OUT_W * OUT_H) as usize];
    pre.run(&frame, &mut out).unwrap();
    out
}

/// training.preprocess.resize_array on the same bytes: uint8 HWC.
fn python_tensor(py: &Path, dir: &Path, rgb: &[u8], w: u32, h: u32) -> Vec<u8> {
    let src = dir.join(format!("in_{w}x{h}.rgb"));
    let dst = dir.join(format!("out_{w}x{h}.rgb"));
    std::fs::write(&src, rgb).unwrap();
    let script = "import sys\n\
                  import numpy as np\n\
                  from training.preprocess import resize_array\n\
                  w, h, ow, oh = (int(a) for a in sys.argv[3:7])\n\
                  img = np.fromfile(sys.argv[1], np.uint8).reshape(h, w, 3)\n\
                  out = resize_array(img, ow, oh, 'short-side-crop')\n\
                  assert out.shape == (oh, ow, 3) and out.dtype == np.uint8, (out.shape, out.dtype)\n\
                  out.tofile(sys.argv[2])\n";
    let o = Command::new(py)
        .current_dir(repo())
        .arg("-c")
        .arg(script)
        .arg(&src)
        .arg(&dst)
        .args([w, h, OUT_W, OUT_H].map(|v| v.to_string()))
        .output()
        .expect("run the venv's python");
    assert!(
        o.status.success(),
        "python preprocessing failed for {w}x{h}:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let out = std::fs::read(&dst).unwrap();
    assert_eq!(out.len(), (3 * OUT_W * OUT_H) as usize);
    out
}

#[test]
fn python_preprocessing_matches_the_element() {
    let Some(py) = python() else {
        eprintln!(
            "SKIPPED: {} is absent (make setup creates it)",
            repo().join(".venv/bin/python").display()
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // 640x480: scale 4 (TUM, 7-Scenes); 368x480: portrait, non-integer scale, vertical crop
    // (a cotracker clip); 1280x720: 16:9, horizontal crop (webcam); 752x480: EuRoC; 333x197:
    // odd non-integer scale with fractional crop offsets; 100x90: upscaling (bilinear taps).
    for (k, &(w, h)) in [
        (640, 480),
        (368, 480),
        (1280, 720),
        (752, 480),
        (333, 197),
        (100, 90),
    ]
    .iter()
    .enumerate()
    {
        let rgb = picture(w, h, k as u32 + 1);
        let ours = element_tensor(&rgb, w, h);
        let theirs = python_tensor(&py, dir.path(), &rgb, w, h);
        let plane = (OUT_W * OUT_H) as usize;
        let mut worst = (0f32, 0usize);
        for c in 0..3 {
            for i in 0..plane {
                let e = ours[c * plane + i];
                let p = theirs[i * 3 + c] as f32 / 255.0;
                let d = (e - p).abs();
                if d > worst.0 {
                    worst = (d, c * plane + i);
                }
            }
        }
        assert!(
            worst.0 <= 1.0 / 255.0,
            "{w}x{h}: python and element differ by {:.5} (> 1/255) at tensor index {}",
            worst.0,
            worst.1
        );
        eprintln!("{w}x{h}: max |python - element| = {:.5}", worst.0);
    }
}
