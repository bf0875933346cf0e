//! The element's geometric prior ([`gstleangate::geometry`]) on pairs of a sequence, computed
//! exactly as the element computes it: each colour frame goes through the element's
//! preprocessing to the model's input size, becomes a grey pyramid, consecutive frames give a
//! homography, and a pair (current `i`, reference `j`) chains those of `j → j+1 → … → i` in the
//! element's order (a [`Chain`], as the element's tracker keeps) before it is scored. `training/fuse.py` fits the model's
//! `leangate.geometry` fusion on these numbers.

use gstleangate::geometry::{frame_homography, Chain, Mat3, Pyramid};
use gstleangate::{PixelFormat, Preprocessor, RawFrame, ResizeMode, TensorSpec, YuvMatrix};

use crate::dataset::Sequence;

/// Grey picture of frame `i` at `w` x `h` as the element's tracker sees it.
fn grey(seq: &Sequence, i: usize, w: u32, h: u32, resize: ResizeMode) -> Result<Vec<f32>, String> {
    let rgb = seq.load_rgb(i).map_err(|e| format!("frame {i}: {e}"))?;
    let spec = TensorSpec {
        width: w,
        height: h,
        resize,
        mean: [0.0; 3],
        std: [1.0 / 255.0; 3],
    };
    let pre = Preprocessor::new(
        PixelFormat::Rgb,
        rgb.width(),
        rgb.height(),
        YuvMatrix::BT601,
        spec,
    )
    .map_err(|e| format!("frame {i}: {e}"))?;
    let mut t = vec![0.0f32; pre.spec().len()];
    let frame = RawFrame::rgb(rgb.as_raw(), rgb.width(), rgb.height());
    pre.run(&frame, &mut t)
        .map_err(|e| format!("frame {i}: {e}"))?;
    Ok(gstleangate::geometry::grey_from_tensor(
        &t,
        w as usize,
        h as usize,
        [0.0; 3],
        [1.0 / 255.0; 3],
    ))
}

/// `(tau_geo, f_m, f_u)` of one pair.
pub type PairGeometry = (f64, f64, f64);

/// `(tau_geo, f_m, f_u)` of each pair `(current i, reference j)`, `j < i`; None where the chain
/// is lost. Frames are read once, in order.
pub fn pair_geometry(
    seq: &Sequence,
    pairs: &[(usize, usize)],
    w: u32,
    h: u32,
    resize: ResizeMode,
) -> Result<Vec<Option<PairGeometry>>, String> {
    let Some(last) = pairs.iter().map(|p| p.0).max() else {
        return Ok(Vec::new());
    };
    let first = pairs.iter().map(|p| p.1).min().unwrap_or(0);
    // steps[k - first] = homography k → k+1
    let mut steps: Vec<Option<Mat3>> = Vec::with_capacity(last - first);
    let mut prev = Pyramid::for_prior(grey(seq, first, w, h, resize)?, w as usize, h as usize);
    let (pw, ph) = (prev.width(), prev.height());
    for k in first + 1..=last {
        let cur = Pyramid::for_prior(grey(seq, k, w, h, resize)?, w as usize, h as usize);
        steps.push(frame_homography(&prev, &cur));
        prev = cur;
    }
    let mut chain = Chain::default();
    Ok(pairs
        .iter()
        .map(|&(i, j)| {
            chain.start();
            for s in &steps[j - first..i - first] {
                chain.push(*s);
            }
            chain.score(pw, ph)
        })
        .collect())
}
