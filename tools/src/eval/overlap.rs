//! The `overlap` baseline: keep a frame when the view overlap since the last keep, measured from
//! the images alone, falls below a threshold — the classical tracked-overlap keyframe rule (as in
//! ORB-SLAM's "fewer than x % of the reference's points still tracked"), here in the teacher's own
//! terms.
//!
//! Method (README): the element's geometric prior ([`gstleangate::geometry`]) on the grey
//! 160x120 thumbnails every policy sees: frame-to-frame homographies from sparse pyramidal
//! Lucas-Kanade on an 8x6 grid of the thumbnail halved to 80x60 (RANSAC), chained from the last kept frame and scored like the
//! teacher scores a pair (`tau_geo = 1 - min(f_m, f_u)` of the nearest-pixel warp). A frame is kept
//! when `tau_geo` reaches the threshold, or when the chain is lost (the view has changed); it then
//! becomes the new reference. Depth is not used, so parallax and the teacher's 3-D check are
//! invisible to it.

use gstleangate::geometry::{frame_homography, prior_size, Chain, Mat3, Pyramid};

use super::{Trace, THUMB_H, THUMB_W};

/// Frame-to-frame homographies (`steps[k]`: frame k → k+1; None where tracking failed), computed
/// once and shared by every threshold tried.
pub fn steps(thumbs: &[Vec<u8>]) -> Vec<Option<Mat3>> {
    let (w, h) = (THUMB_W as usize, THUMB_H as usize);
    let pyr: Vec<Pyramid> = thumbs
        .iter()
        .map(|t| Pyramid::for_prior(t.iter().map(|&g| g as f32).collect(), w, h))
        .collect();
    pyr.windows(2)
        .map(|w| frame_homography(&w[0], &w[1]))
        .collect()
}

/// The overlap gate at `threshold` (in tau_geo). The trace carries no utility: tau_geo is not
/// calibrated to the teacher, so it is not judged for MAE/RMSE.
pub fn overlap_gate(steps: &[Option<Mat3>], threshold: f64) -> Trace {
    let n = steps.len() + 1;
    let (w, h) = prior_size(THUMB_W as usize, THUMB_H as usize);
    let mut keep = Vec::with_capacity(n);
    let mut chain = Chain::default();
    for i in 0..n {
        let k = i == 0 || {
            chain.push(steps[i - 1]);
            // A lost chain keeps: the view has changed.
            chain.score(w, h).is_none_or(|(tau, _, _)| tau >= threshold)
        };
        if k {
            chain.start();
        }
        keep.push(k);
    }
    Trace {
        utility: vec![None; n],
        keep,
    }
}

/// The overlap gate with its threshold chosen so the kept count is as close as possible to
/// `target`. Returns the trace and the threshold.
pub fn overlap_for_budget(steps: &[Option<Mat3>], target: usize) -> (Trace, f64) {
    super::baselines::fit_budget(target, (1e-3, 1.0), 24, |t| overlap_gate(steps, t))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::motion::tests::texture;
    use gstleangate::geometry::IDENTITY;

    #[test]
    fn keeps_when_the_view_has_moved_by_the_threshold() {
        // 2 thumbnail px per frame: tau_geo grows by 2/160 a frame, so at 0.25 a keep every 20.
        let thumbs: Vec<Vec<u8>> = (0..61).map(|k| texture(2.0 * k as f32, 0.0)).collect();
        let st = steps(&thumbs);
        assert!(st.iter().all(|s| s.is_some()), "a textured pan tracks");
        let t = overlap_gate(&st, 0.25);
        let kept: Vec<usize> = (0..t.keep.len()).filter(|&i| t.keep[i]).collect();
        assert_eq!(kept, vec![0, 20, 40, 60]);
        let still: Vec<Option<Mat3>> = vec![Some(IDENTITY); 30];
        assert_eq!(overlap_gate(&still, 0.1).kept(), 1);
        // A lost chain keeps (the view has changed) and restarts from there.
        let mut lost = still.clone();
        lost[10] = None;
        let t = overlap_gate(&lost, 0.1);
        assert_eq!(t.kept(), 2);
        assert!(t.keep[11]);
        let (b, th) = overlap_for_budget(&st, 7);
        assert_eq!(b.kept(), 7, "threshold {th}");
    }
}
