//! Keyframes worth keeping, with the embedded default gate on real frames of `tum_fr1_desk` (a
//! fast handheld sweep over office desks): junk never becomes a keyframe (black, white and noise
//! frames spliced in, a static textureless view), and a keep due on a blurred frame goes to a
//! sharper one (`sharpness-wait`, `sharpness-lookback`, and both: the sharpest around the due
//! frame). Skipped, saying so, when `../shared/data` is absent.

mod common;

use common::*;
use gst::prelude::*;
use gstleangate::{Quality, Reason};

const W: u32 = 640;
const H: u32 = 480;

/// `n` consecutive colour frames of tum_fr1_desk from `start` (`n` = 0: to the end), as RGB
/// bytes.
fn desk_frames(start: usize, n: usize) -> Option<Vec<Vec<u8>>> {
    let dir = shared_data("tum_fr1_desk/rgb")?;
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    files.sort();
    let end = if n == 0 { files.len() } else { start + n };
    Some(
        files[start..end]
            .iter()
            .map(|p| image::open(p).unwrap().into_rgb8().into_raw())
            .collect(),
    )
}

/// The default gate (annotate; the default's look-back of 3, which the harness would set to 0)
/// over `frames`, to EOS: each frame's (keep, reason, quality), and the element's `frames-junk`.
fn gate(frames: &[Vec<u8>], props: &str) -> (Vec<(bool, Reason, Quality)>, u64) {
    let mut h = harness(
        &format!("mode=annotate sharpness-lookback=3 {props}"),
        &rgb_caps(W, H),
    );
    let mut out = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        h.push(buffer(f.clone(), i as u64 * 33)).unwrap();
        out.extend(drain(&mut h));
    }
    assert!(h.push_event(gst::event::Eos::new()));
    out.extend(drain(&mut h));
    assert_eq!(out.len(), frames.len(), "every frame leaves once");
    let junk = h.element().unwrap().property::<u64>("frames-junk");
    let m = out
        .iter()
        .map(|b| {
            let m = meta(b);
            (m.keep, m.reason, m.quality)
        })
        .collect();
    (m, junk)
}

fn kept(v: &[(bool, Reason, Quality)]) -> Vec<usize> {
    (0..v.len()).filter(|&i| v[i].0).collect()
}

fn black() -> Vec<u8> {
    solid(W, H, [0, 0, 0])
}

/// 40 real frames with frame 20 black: the black frame is dropped as junk (it used to score 0.876,
/// be kept, become the reference, and have frame 21 kept again), and the real frames' keeps are
/// those of the same 40 frames without it, within one.
#[test]
fn a_black_frame_in_real_video_is_never_kept() {
    let Some(real) = desk_frames(100, 40) else {
        return;
    };
    let (clean, _) = gate(&real, "");
    let mut spliced = real.clone();
    spliced[20] = black();
    let (got, junk) = gate(&spliced, "");
    assert_eq!(
        (got[20].0, got[20].1, got[20].2),
        (false, Reason::Junk, Quality::Dark)
    );
    assert_eq!(junk, 1);
    let (a, b): (Vec<_>, Vec<_>) = (
        kept(&clean).into_iter().filter(|&i| i != 20).collect(),
        kept(&got),
    );
    assert!(
        a.len().abs_diff(b.len()) <= 1,
        "real keeps {b:?}, without the black frame {a:?}"
    );
    assert!(!b.contains(&21) || a.contains(&21), "frame 21 kept again");
    // With the check off, the black frame is what it was: kept as all new.
    let (off, junk) = gate(&spliced, "reject-junk=false");
    assert!(off[20].0 && junk == 0, "{:?}", off[20]);
}

/// Every 5th frame black (a flashing or dropping link): no dark frame kept (8 of the 16 keeps
/// were black before), and the real frames' keeps are those of the 32 real frames alone, within
/// one.
#[test]
fn a_flashing_stream_keeps_no_dark_frame() {
    let Some(real) = desk_frames(200, 40) else {
        return;
    };
    let spliced: Vec<Vec<u8>> = (0..40)
        .map(|i| if i % 5 == 2 { black() } else { real[i].clone() })
        .collect();
    let alone: Vec<Vec<u8>> = (0..40)
        .filter(|i| i % 5 != 2)
        .map(|i| real[i].clone())
        .collect();
    let (got, junk) = gate(&spliced, "");
    let (want, _) = gate(&alone, "");
    assert_eq!(junk, 8);
    for (i, g) in got.iter().enumerate() {
        if i % 5 == 2 {
            assert_eq!(*g, (false, Reason::Junk, Quality::Dark), "frame {i}");
        }
    }
    let (g, w) = (kept(&got).len(), kept(&want).len());
    assert!(
        g.abs_diff(w) <= 1,
        "{g} real keeps against {w} without the black frames"
    );
    // White (a flash) and noise frames are junk too.
    let mut x = 12345u32;
    let noise: Vec<u8> = (0..W * H * 3)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x >> 24) as u8
        })
        .collect();
    let mut other = real[..10].to_vec();
    other[4] = solid(W, H, [255, 255, 255]);
    other[7] = noise;
    let (got, junk) = gate(&other, "");
    assert_eq!((got[4].0, got[4].2), (false, Quality::Saturated));
    assert_eq!((got[7].0, got[7].2), (false, Quality::Noise));
    assert_eq!(junk, 2);
}

/// A static textureless view (mid-grey with sensor noise, sigma about 1): only its first frame is
/// kept (5 of 40 were: the prior lost its chain and the student alone read 0.34–0.50). A stream
/// that starts black keeps its first real frame as `first`.
#[test]
fn a_textureless_view_keeps_only_its_first_frame_and_junk_never_starts_a_stream() {
    common::init();
    let mut x = 7u32;
    let grey: Vec<Vec<u8>> = (0..40)
        .map(|_| {
            (0..W * H * 3)
                .map(|_| {
                    x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
                    // about +-2 levels, sigma about 1.2
                    (128 + ((x >> 16) % 5) as i32 - 2) as u8
                })
                .collect()
        })
        .collect();
    let (got, junk) = gate(&grey, "");
    assert_eq!(kept(&got), vec![0], "{got:?}");
    assert!(got.iter().all(|g| g.2 == Quality::Textureless));
    assert_eq!(junk, 0, "textureless is a view, not junk");
    let Some(real) = desk_frames(300, 6) else {
        return;
    };
    let mut capped = vec![black(), black()];
    capped.extend(real);
    let (got, _) = gate(&capped, "");
    assert_eq!(
        (got[0].0, got[1].0, got[2].0, got[2].1),
        (false, false, true, Reason::First)
    );
}

/// Sharpness measured apart from the element: the variance of the Laplacian of the whole frame's
/// grey at half size (320x240).
fn frame_sharpness(rgb: &[u8]) -> f64 {
    let (w, h) = (W as usize / 2, H as usize / 2);
    let g: Vec<f64> = (0..w * h)
        .map(|i| {
            let (x, y) = (2 * (i % w), 2 * (i / w));
            let mut v = 0.0;
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let p = 3 * ((y + dy) * W as usize + x + dx);
                v += 0.299 * rgb[p] as f64 + 0.587 * rgb[p + 1] as f64 + 0.114 * rgb[p + 2] as f64;
            }
            v / 4.0
        })
        .collect();
    let mut l = Vec::with_capacity(w * h);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let c = y * w + x;
            l.push(g[c - 1] + g[c + 1] + g[c - w] + g[c + w] - 4.0 * g[c]);
        }
    }
    let mean = l.iter().sum::<f64>() / l.len() as f64;
    l.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / l.len() as f64
}

/// The whole of tum_fr1_desk without a look-back (`sharpness-lookback=0`), the gate keeping at once
/// (`sharpness-wait=0`) and waiting up to two frames for a sharper one (`sharpness-wait=2`,
/// no buffering): the wait ends in a keep within two frames
/// every time, and fewer keyframes are less than half as sharp as a frame within three of them
/// (23 % before, 3 % now in the model card's measurement), with no more keyframes.
#[test]
fn a_keep_due_on_a_blurred_frame_goes_to_a_sharper_one() {
    let Some(frames) = desk_frames(0, 0) else {
        return;
    };
    let sharp: Vec<f64> = frames.iter().map(|f| frame_sharpness(f)).collect();
    let blurred_keeps = |v: &[(bool, Reason, Quality)]| {
        let n = v.len();
        let k = kept(v);
        let bad = k
            .iter()
            .filter(|&&i| {
                let best = sharp[i.saturating_sub(3)..(i + 4).min(n)]
                    .iter()
                    .fold(0.0f64, |a, &b| a.max(b));
                sharp[i] < 0.5 * best
            })
            .count();
        (bad, k.len())
    };
    let (at_once, _) = gate(&frames, "sharpness-lookback=0 sharpness-wait=0");
    let (waiting, _) = gate(&frames, "sharpness-lookback=0 sharpness-wait=2");
    assert!(at_once.iter().all(|g| g.1 != Reason::Deferred));
    let deferred: Vec<usize> = (0..waiting.len())
        .filter(|&i| waiting[i].1 == Reason::Deferred)
        .collect();
    assert!(!deferred.is_empty(), "nothing waited on a fast sweep");
    for &i in &deferred {
        assert!(
            waiting[i + 1..(i + 3).min(waiting.len())]
                .iter()
                .any(|g| g.0),
            "the keep deferred at frame {i} never came"
        );
    }
    let ((bad0, n0), (bad2, n2)) = (blurred_keeps(&at_once), blurred_keeps(&waiting));
    eprintln!("blurred keyframes: {bad0} of {n0} at once, {bad2} of {n2} waiting");
    assert!(bad2 * n0 < bad0 * n2, "{bad2}/{n2} against {bad0}/{n0}");
    assert!(n2 <= n0, "{n2} keyframes against {n0}");
}

/// Each buffer's keep flag.
fn keeps(v: &[gst::Buffer]) -> Vec<bool> {
    v.iter().map(|b| meta(b).keep).collect()
}

/// The kept frames' median sharpness as a fraction of the sharpest frame within three of each.
fn median_sharpness_ratio(keep: &[bool], sharp: &[f64]) -> f64 {
    let n = keep.len();
    let mut r: Vec<f64> = (0..n)
        .filter(|&i| keep[i])
        .map(|i| {
            let best = sharp[i.saturating_sub(3)..(i + 4).min(n)]
                .iter()
                .fold(0.0f64, |a, &b| a.max(b));
            sharp[i] / best
        })
        .collect();
    r.sort_by(|a, b| a.total_cmp(b));
    r[r.len() / 2]
}

/// `frames` through the element with `props`, 33 ms apart, then EOS: every buffer out, in order,
/// and the latency the element reported before EOS. `each(i, out)` sees what left the element
/// right after frame `i` went in.
fn through_gate(
    frames: &[Vec<u8>],
    props: &str,
    mut each: impl FnMut(usize, &[gst::Buffer]),
) -> (Vec<gst::Buffer>, Option<gst::ClockTime>) {
    let mut h = harness(props, &rgb_caps(W, H));
    let mut out = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        h.push(buffer(f.clone(), i as u64 * 33)).unwrap();
        let now = drain(&mut h);
        each(i, &now);
        out.extend(now);
    }
    let latency = h.query_latency();
    assert!(h.push_event(gst::event::Eos::new()));
    out.extend(drain(&mut h));
    (out, latency)
}

/// `sharpness-lookback=3` (with the default `sharpness-margin`: the element's default; the
/// harness sets 0 otherwise) on the first 300 frames of tum_fr1_desk, in annotate mode: every frame
/// leaves exactly once and in order, three frames after it came (the last three at EOS; a keep
/// used to let every held frame out at once, and the sink of a live pipeline, waiting for the
/// last of them, blocked the source for the whole look-back: late frames, kept ones among them,
/// were dropped), keeps due on blurred frames go back
/// to sharper ones (reason `sharper`, the due frame dropped), the kept frames' median sharpness
/// against their neighbours rises, and drop mode lets exactly the same frames through. The
/// latency query reports the three held frames.
#[test]
fn a_keep_due_on_a_blurred_frame_goes_back_to_a_sharper_recent_one() {
    let Some(frames) = desk_frames(0, 300) else {
        return;
    };
    let sharp: Vec<f64> = frames.iter().map(|f| frame_sharpness(f)).collect();
    let run = |props: &str| {
        let held = if props.contains("lookback=3") { 3 } else { 0 };
        let annotate = props.contains("annotate");
        through_gate(&frames, props, |i, now| {
            // Every frame leaves three frames later, neither sooner nor later: one frame in,
            // one out (annotate mode), as a live pipeline's sink expects them. In drop mode a
            // kept frame leaves then, alone.
            if annotate {
                assert_eq!(now.len(), usize::from(i >= held), "frame {i}");
            }
            if let Some(b) = now.first() {
                let due = i.checked_sub(held).map(|j| j as u64 * 33);
                assert_eq!(Some(b.pts().unwrap().mseconds()), due, "frame {i}");
            }
        })
    };
    let (at_once, _) = run("mode=annotate");
    let (back, latency) = run("mode=annotate sharpness-lookback=3");
    assert_eq!(back.len(), frames.len(), "every frame leaves once");
    let pts: Vec<u64> = back.iter().map(|b| b.pts().unwrap().mseconds()).collect();
    assert_eq!(
        pts,
        (0..frames.len() as u64).map(|i| i * 33).collect::<Vec<_>>()
    );
    assert!(
        latency.is_some_and(|l| l >= gst::ClockTime::from_mseconds(99)),
        "latency {latency:?}: three frames at 30/s are held"
    );
    let metas: Vec<_> = back.iter().map(meta).collect();
    let sharper: Vec<usize> = (0..metas.len())
        .filter(|&i| metas[i].reason == Reason::Sharper)
        .collect();
    assert!(!sharper.is_empty(), "no keep went back on a fast sweep");
    for &i in &sharper {
        assert!(metas[i].keep && metas[i].frames_since_keyframe == 0);
        // The frame the keep was due on is dropped within three frames after it, compared with
        // the new reference from then on.
        let due = (i + 1..(i + 4).min(metas.len()))
            .find(|&j| metas[j].keyframe_index == metas[i].keyframe_index && !metas[j].keep);
        assert!(due.is_some(), "keep at {i}: no due frame after it");
    }
    // In output order the keep count never goes down, and every frame's count of frames since
    // its keyframe is from the reference it names (a hostile probe found the frames between a
    // `sharper` keep and its due frame one keep behind, and the due frame counting from the new
    // keyframe while naming the old one).
    for (i, m) in metas.iter().enumerate() {
        if i > 0 {
            assert!(
                m.keyframe_index >= metas[i - 1].keyframe_index,
                "frame {i}: keyframe index {} after {}",
                m.keyframe_index,
                metas[i - 1].keyframe_index
            );
        }
        if let (false, Some(r)) = (m.keep, m.reference_pts) {
            let r = (r.mseconds() / 33) as usize;
            assert_eq!(m.frames_since_keyframe as usize, i - r, "frame {i}");
        }
    }
    let (k0, k3) = (keeps(&at_once), keeps(&back));
    let (m0, m3) = (
        median_sharpness_ratio(&k0, &sharp),
        median_sharpness_ratio(&k3, &sharp),
    );
    eprintln!("median kept sharpness / sharpest within 3: {m0:.2} at once, {m3:.2} going back");
    assert!(m3 > m0 + 0.05, "{m3:.2} against {m0:.2}");
    // Drop mode: the same frames, and only them.
    let (dropped, _) = run("sharpness-lookback=3");
    let kept_pts: Vec<u64> = (0..k3.len()).filter(|&i| k3[i]).map(|i| pts[i]).collect();
    let out_pts: Vec<u64> = dropped
        .iter()
        .map(|b| b.pts().unwrap().mseconds())
        .collect();
    assert_eq!(out_pts, kept_pts);
}

/// `sharpness-wait=2 sharpness-lookback=4` on the first 300 frames of tum_fr1_desk: a keep due
/// settles two frames later on the sharpest frame held, so every keep that waited lands within
/// two frames of the frame it was due on, before or after it; the kept frames are sharper than
/// keeping at once, every frame leaves once and in order, and drop mode lets the same frames
/// through.
#[test]
fn with_a_wait_and_a_lookback_a_keep_settles_on_the_sharpest_frame_around_the_due_one() {
    let Some(frames) = desk_frames(0, 300) else {
        return;
    };
    let sharp: Vec<f64> = frames.iter().map(|f| frame_sharpness(f)).collect();
    let run = |props: &str| through_gate(&frames, props, |_, _| {}).0;
    let settle = "sharpness-wait=2 sharpness-lookback=4";
    let at_once = run("mode=annotate");
    let settled = run(&format!("mode=annotate {settle}"));
    let pts: Vec<u64> = settled
        .iter()
        .map(|b| b.pts().unwrap().mseconds())
        .collect();
    assert_eq!(
        pts,
        (0..frames.len() as u64).map(|i| i * 33).collect::<Vec<_>>(),
        "every frame leaves once, in order"
    );
    let metas: Vec<_> = settled.iter().map(meta).collect();
    // Every keep that settles has its picture at hand: the reference is never lost.
    assert!(
        metas[1..].iter().all(|m| m.reason != Reason::First),
        "a keep settled on a frame the element no longer had"
    );
    let (mut waits, mut forward, mut back) = (0, 0, 0);
    let mut i = 0;
    while i < metas.len() {
        if metas[i].reason != Reason::Deferred {
            i += 1;
            continue;
        }
        // The frame the keep was due on, the first of a run of deferred frames. The keep that
        // settles it: a `sharper` keep before it that it counts already (in output order a frame
        // counts every keep that left before it), else the next keyframe.
        let due = i;
        let back_to = (due.saturating_sub(2)..due).find(|&j| {
            metas[j].reason == Reason::Sharper
                && metas[j].keyframe_index == metas[due].keyframe_index
        });
        let index = metas[due].keyframe_index + 1;
        let k = back_to
            .or_else(|| {
                (0..metas.len()).find(|&j| metas[j].keep && metas[j].keyframe_index == index)
            })
            .unwrap_or_else(|| panic!("the keep due on frame {due} never came"));
        assert!(
            k + 2 >= due && k <= due + 2,
            "the keep due on frame {due} went to frame {k}"
        );
        waits += 1;
        if k > due {
            forward += 1;
        } else if k < due {
            back += 1;
        }
        while i < metas.len() && metas[i].reason == Reason::Deferred {
            i += 1;
        }
    }
    eprintln!("{waits} keeps settled: {forward} on a later frame, {back} on an earlier one");
    assert!(forward > 0 && back > 0, "{forward} later, {back} earlier");
    let (k0, ks) = (keeps(&at_once), keeps(&settled));
    let (m0, ms) = (
        median_sharpness_ratio(&k0, &sharp),
        median_sharpness_ratio(&ks, &sharp),
    );
    eprintln!("median kept sharpness / sharpest within 3: {m0:.2} at once, {ms:.2} settled");
    assert!(ms > m0 + 0.05, "{ms:.2} against {m0:.2}");
    let kept_pts: Vec<u64> = (0..ks.len()).filter(|&i| ks[i]).map(|i| pts[i]).collect();
    let out_pts: Vec<u64> = run(settle)
        .iter()
        .map(|b| b.pts().unwrap().mseconds())
        .collect();
    assert_eq!(out_pts, kept_pts, "drop mode: the same frames");
}

/// Frames held for `sharpness-lookback` across what a stream does: new caps release them first
/// (in order, before the new-caps frames, which are held in turn), a flush discards them, the property going to 0 while
/// frames are held lets them out before the next frame. Nothing is lost or reordered otherwise.
#[test]
fn held_frames_survive_caps_changes_flushes_and_property_changes() {
    let Some(frames) = desk_frames(100, 20) else {
        return;
    };
    let mut h = harness("mode=annotate sharpness-lookback=5", &rgb_caps(W, H));
    // Upstream is asked for five more buffers than it would otherwise allocate.
    let caps: gst::Caps = rgb_caps(W, H).parse().unwrap();
    let mut q = gst::query::Allocation::new(Some(&caps), true);
    let sink = h.element().unwrap().static_pad("sink").unwrap();
    assert!(sink.query(&mut q));
    let pools: Vec<_> = q.allocation_pools().collect();
    assert!(
        pools.iter().any(|p| p.2 >= 5 && (p.3 == 0 || p.3 >= p.2)),
        "{pools:?}"
    );
    let pts = |v: &[gst::Buffer]| {
        v.iter()
            .map(|b| b.pts().unwrap().mseconds())
            .collect::<Vec<_>>()
    };
    for (i, f) in frames[..8].iter().enumerate() {
        h.push(buffer(f.clone(), i as u64 * 33)).unwrap();
    }
    let first = drain(&mut h);
    assert!(first.len() < 8, "nothing held: {:?}", pts(&first));
    // New caps: the held frames leave before the caps do, then the new frames follow.
    h.set_src_caps_str(&rgb_caps(W / 2, H / 2));
    let small = image::imageops::thumbnail(
        &image::RgbImage::from_raw(W, H, frames[8].clone()).unwrap(),
        W / 2,
        H / 2,
    )
    .into_raw();
    h.push(buffer(small, 8 * 33)).unwrap();
    let mut out = first;
    out.extend(drain(&mut h));
    // (the new-caps frame, a keep, is held like any other)
    assert_eq!(pts(&out), (0..8).map(|i| i * 33).collect::<Vec<_>>());
    // A flush discards what is held; the stream goes on.
    h.set_src_caps_str(&rgb_caps(W, H));
    for (i, f) in frames[9..14].iter().enumerate() {
        h.push(buffer(f.clone(), (9 + i as u64) * 33)).unwrap();
    }
    assert_eq!(pts(&drain(&mut h)), [8 * 33]);
    assert!(h.push_event(gst::event::FlushStart::new()));
    assert!(h.push_event(gst::event::FlushStop::new(true)));
    h.set_src_caps_str(&rgb_caps(W, H));
    h.push_event(gst::event::Segment::new(&gst::FormattedSegment::<
        gst::ClockTime,
    >::new()));
    drain(&mut h);
    for (i, f) in frames[14..18].iter().enumerate() {
        h.push(buffer(f.clone(), (14 + i as u64) * 33)).unwrap();
    }
    let mid = drain(&mut h);
    // The property to 0: the held frames leave before the next one, which leaves at once.
    h.element()
        .unwrap()
        .set_property("sharpness-lookback", 0u32);
    h.push(buffer(frames[18].clone(), 18 * 33)).unwrap();
    let mut tail = mid;
    tail.extend(drain(&mut h));
    assert_eq!(pts(&tail), (14..19).map(|i| i * 33).collect::<Vec<_>>());
}

/// `frame` blurred (a Gaussian of sigma 4).
fn blurred(frame: &[u8]) -> Vec<u8> {
    let img = image::RgbImage::from_raw(W, H, frame.to_vec()).unwrap();
    image::imageops::blur(&img, 4.0).into_raw()
}

/// Every keep the gate makes reaches the output when `sharpness-lookback` rises while frames are
/// held. A still view (a sharp frame A five times, then blurred three times) and a blurred view
/// far along the sweep (B), the look-back 3 and raised to 30 just before B: B's keep goes back to
/// the sharpest frame still held (an A at most three back), which leaves kept (`sharper`), B
/// dropped; the kept frames' indices run 1, 2 with none missing, as many as `frames-kept`. It used
/// to go back four frames, to an A that had already left as dropped: that keep was lost (counted,
/// the reference moved to a frame nobody received) and B dropped.
#[test]
fn a_keep_goes_back_only_to_a_frame_still_held_when_the_lookback_rises() {
    let Some(frames) = desk_frames(0, 0) else {
        return;
    };
    let (a, b) = (&frames[100], &frames[160]);
    let mut seq = vec![a.clone(); 5];
    seq.extend(std::iter::repeat_n(blurred(a), 3));
    seq.push(blurred(b));
    for (mode, lookback_first) in [("annotate", 3u32), ("drop", 3), ("annotate", 0)] {
        // Threshold 0.42: the still view's frames (utility 0.34 here) come within 0.1 of it,
        // so they are candidates to go back to.
        let mut h = harness(
            &format!("mode={mode} sharpness-lookback={lookback_first} threshold=0.42"),
            &rgb_caps(W, H),
        );
        let mut out = Vec::new();
        for (i, f) in seq.iter().enumerate() {
            if i == seq.len() - 1 {
                h.element()
                    .unwrap()
                    .set_property("sharpness-lookback", 30u32);
            }
            h.push(buffer(f.clone(), i as u64 * 33)).unwrap();
            out.extend(drain(&mut h));
        }
        assert!(h.push_event(gst::event::Eos::new()));
        out.extend(drain(&mut h));
        let metas: Vec<_> = out.iter().map(meta).collect();
        let kept: Vec<(u64, u64, Reason)> = out
            .iter()
            .zip(&metas)
            .filter(|(_, m)| m.keep)
            .map(|(b, m)| (b.pts().unwrap().mseconds() / 33, m.keyframe_index, m.reason))
            .collect();
        eprintln!("{mode} lookback {lookback_first} -> 30: kept {kept:?}");
        if mode == "annotate" {
            assert_eq!(out.len(), seq.len(), "every frame leaves once");
        }
        let counted = h.element().unwrap().property::<u64>("frames-kept");
        assert_eq!(
            kept.iter().map(|k| k.1).collect::<Vec<_>>(),
            (1..=counted).collect::<Vec<_>>(),
            "{mode}: a keep went missing: {kept:?}, {counted} counted"
        );
        assert_eq!(kept[0], (0, 1, Reason::First));
        if lookback_first > 0 {
            // B was due and blurred: its keep went back to a sharp A still held (5, 6 or 7 are
            // blurred, so 4 would be the one, but it left when the look-back was 3).
            assert_eq!(kept.len(), 2, "{kept:?}");
            assert_eq!(kept[1].2, Reason::Sharper, "{kept:?}");
            assert!((5..8).contains(&kept[1].0), "{kept:?}");
        }
    }
}

/// A forced keyframe, a reset and a gap while `sharpness-lookback` holds frames wait in line
/// behind them: no frame leaves sooner for them (one frame out for one in, annotate mode), each
/// leaves right after the frame it followed, and the forced keyframe and the reset still apply to
/// the next frame (reason `forced`, then `first`). They used to let every held frame out at once,
/// the sink of a live pipeline blocked on the last of them, and frames came late (two or three
/// dropped by the sink at each forced keyframe with `sharpness-lookback=30`).
#[test]
fn custom_events_and_gaps_wait_in_line_behind_held_frames() {
    let Some(frames) = desk_frames(100, 14) else {
        return;
    };
    let mut h = harness("mode=annotate sharpness-lookback=3", &rgb_caps(W, H));
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::<String>::new()));
    let log = seen.clone();
    let src = h.element().unwrap().static_pad("src").unwrap();
    src.add_probe(
        gst::PadProbeType::BUFFER | gst::PadProbeType::EVENT_DOWNSTREAM,
        move |_, info| {
            let item = match &info.data {
                Some(gst::PadProbeData::Buffer(b)) => {
                    let m = meta(b);
                    format!("{}:{}", b.pts().unwrap().mseconds() / 33, m.reason)
                }
                Some(gst::PadProbeData::Event(e)) => match e.view() {
                    gst::EventView::CustomDownstream(c) => {
                        c.structure().unwrap().name().to_string()
                    }
                    gst::EventView::CustomBoth(c) => c.structure().unwrap().name().to_string(),
                    gst::EventView::Gap(_) => "gap".into(),
                    gst::EventView::Tag(_) => "tag".into(),
                    _ => return gst::PadProbeReturn::Ok,
                },
                _ => return gst::PadProbeReturn::Ok,
            };
            log.lock().unwrap().push(item);
            gst::PadProbeReturn::Ok
        },
    );
    let custom = |name: &str| gst::event::CustomDownstream::new(gst::Structure::new_empty(name));
    let mut pushed = 0u64;
    let mut push = |h: &mut gst_check::Harness, i: usize| {
        h.push(buffer(frames[i].clone(), i as u64 * 33)).unwrap();
        pushed += 1;
        let out = drain(h).len();
        assert_eq!(out, usize::from(pushed > 3), "frame {i}");
    };
    for i in 0..6 {
        push(&mut h, i);
    }
    assert!(h.push_event(custom("leangate-force-keyframe")));
    push(&mut h, 6);
    push(&mut h, 7);
    // A tag (a parser's bitrate, a stream title) and a custom event for both directions wait in
    // line too: they used to let the held frames out and change which frames were kept.
    let mut tags = gst::TagList::new();
    tags.get_mut()
        .unwrap()
        .add::<gst::tags::Title>(&"a title", gst::TagMergeMode::Append);
    assert!(h.push_event(gst::event::Tag::new(tags)));
    push(&mut h, 8);
    assert!(
        h.push_event(gst::event::CustomBoth::new(gst::Structure::new_empty(
            "an-app-event"
        )))
    );
    push(&mut h, 9);
    assert!(h.push_event(custom("leangate-reset")));
    assert!(
        h.push_event(gst::event::Gap::builder(gst::ClockTime::from_mseconds(10 * 33 - 1)).build())
    );
    for i in 10..14 {
        push(&mut h, i);
    }
    assert!(h.push_event(gst::event::Eos::new()));
    drain(&mut h);
    let seen = seen.lock().unwrap().clone();
    eprintln!("{seen:?}");
    let at = |s: &str| {
        seen.iter()
            .position(|x| x == s)
            .unwrap_or_else(|| panic!("{s}: {seen:?}"))
    };
    // In order: each event right after the frame it followed; the forced and reset frames.
    assert_eq!(at("leangate-force-keyframe"), at("5:score") + 1, "{seen:?}");
    assert_eq!(
        at("6:forced"),
        at("leangate-force-keyframe") + 1,
        "{seen:?}"
    );
    assert_eq!(seen[at("tag") - 1].split(':').next(), Some("7"), "{seen:?}");
    assert_eq!(
        seen[at("an-app-event") - 1].split(':').next(),
        Some("8"),
        "{seen:?}"
    );
    let reset = at("leangate-reset");
    assert_eq!(seen[reset - 1].split(':').next(), Some("9"), "{seen:?}");
    assert_eq!(seen[reset + 1], "gap", "{seen:?}");
    assert_eq!(seen[reset + 2], "10:first", "{seen:?}");
    assert_eq!(seen.iter().filter(|s| s.contains(':')).count(), 14);
}

/// `sharpness-lookback` raised while playing: upstream is asked to allocate again (a
/// reconfigure event), so that a source with a bounded pool (a camera's, a hardware decoder's)
/// gets as many more buffers as the element now holds instead of stalling on them. Before, no
/// new allocation query came: the pool stayed sized for holding nothing.
#[test]
fn a_raised_lookback_while_playing_asks_upstream_to_allocate_again() {
    init();
    let pipeline = gst::parse::launch(
        "videotestsrc is-live=true ! video/x-raw,width=320,height=240,framerate=30/1 \
         ! leangate name=g mode=annotate ! fakesink sync=true",
    )
    .unwrap()
    .downcast::<gst::Pipeline>()
    .unwrap();
    let g = pipeline.by_name("g").unwrap();
    let queries = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let count = queries.clone();
    g.static_pad("sink")
        .unwrap()
        .add_probe(gst::PadProbeType::QUERY_DOWNSTREAM, move |_, info| {
            if let Some(gst::PadProbeData::Query(q)) = &info.data {
                if matches!(q.view(), gst::QueryView::Allocation(_)) {
                    count.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                }
            }
            gst::PadProbeReturn::Ok
        });
    let wait_for = |n: usize| {
        let t0 = std::time::Instant::now();
        while queries.load(std::sync::atomic::Ordering::SeqCst) < n {
            if t0.elapsed() > std::time::Duration::from_secs(10) {
                return false;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        true
    };
    pipeline.set_state(gst::State::Playing).unwrap();
    assert!(wait_for(1), "no allocation query at start");
    // Frames flow at the old setting...
    std::thread::sleep(std::time::Duration::from_millis(300));
    let before = queries.load(std::sync::atomic::Ordering::SeqCst);
    g.set_property("sharpness-lookback", 10u32);
    let asked = wait_for(before + 1);
    pipeline.set_state(gst::State::Null).unwrap();
    assert!(
        asked,
        "no new allocation query after sharpness-lookback 0 -> 10"
    );
}

/// `videotestsrc pattern=ball`, a small bright ball on black, is a picture (docs/element.md,
/// `reject-junk`): at 640x480 and 1280x720 no frame is junk (with the 99th percentile rule every
/// one was `dark` from 640x480 up, so `leangate-client --source videotestsrc` received nothing);
/// an all-black stream is still junk throughout.
#[test]
fn the_test_ball_on_black_is_a_picture_at_common_sizes() {
    let junk = |pattern: &str, w: u32, h: u32| {
        let msgs = common::run_pipeline(
            &format!(
                "videotestsrc pattern={pattern} num-buffers=20 ! video/x-raw,width={w},height={h} \
                 ! leangate mode=annotate ! fakesink"
            ),
            120,
        );
        assert_eq!(common::error_text(&msgs), None);
        let stats = common::element_message(&msgs, "leangate-stats");
        let last = gstleangate::StatsMessage::from_structure(stats.last().expect("stats")).unwrap();
        (last.frames_in, last.frames_junk)
    };
    assert_eq!(junk("ball", 640, 480), (20, 0));
    assert_eq!(junk("ball", 1280, 720), (20, 0));
    assert_eq!(junk("black", 640, 480), (20, 20));
}
