//! Whether a frame carries a usable picture: the photometric check that keeps junk out of the
//! keyframes.
//!
//! A black frame (a lens cap, a dropped exposure), a white or saturated one (a flash, the sun), or
//! a frame of noise (a broken link, an uninitialised buffer) differs from the reference in every
//! pixel, so the model reads it as all new and the gate used to keep it, make it the reference,
//! and keep the next real frame again. A textureless view (a blank wall, a grey card) carries a
//! picture but no geometry to match. [`assess`] tells them apart from the model's input picture,
//! in one pass over a 2x2-binned grey copy:
//!
//! | [`Quality`] | rule (grey 0–255, binned) | what the element does |
//! |---|---|---|
//! | `Dark` | nothing bright: 99.95 % of the pixels below 40 | never kept, never the reference (reason `junk`) |
//! | `Saturated` | nothing dark: 99 % of the pixels above 215 | never kept, never the reference (reason `junk`) |
//! | `Textureless` | standard deviation below 3 | utility 0: kept only as a stream's first frame (or by `max-gap`, `warmup`, a forced keyframe) |
//! | `Noise` | mean neighbour difference at least 0.7 of the standard deviation | never kept, never the reference (reason `junk`) |
//! | `Usable` | none of these | scored as usual |
//!
//! Percentiles rather than fractions: a small bright object on black (a lamp at night,
//! `videotestsrc pattern=ball`) is a picture down to a few bins of the model's picture: the ball
//! on every frame up to 1280x720, on 28 of 30 at 1920x1080 (with the 99th percentile, the rule
//! before, it was junk from 640x480 up). The margins, measured on every third real frame of
//! `../shared/data` (TUM fr1 rpy and desk, 7-Scenes, EuRoC, a laptop webcam with motion blur and
//! dark frames, phone frames of an orbit): the 99th percentile at least 125, the 1st at most 103,
//! a standard deviation of at least 13, a neighbour difference of at most 0.24 of it. White noise
//! gives about 1.1; sensor noise on a flat picture (sigma 1) a deviation of about 0.5.

/// A frame with fewer than [`DARK_SHARE`] of its bins (and fewer than 3) at or above this grey
/// level (0–255) is [`Quality::Dark`]: a few bright bins make a picture, a stray one does not.
pub const DARK_LEVEL: f32 = 40.0;
/// The share of the (binned) picture that must reach [`DARK_LEVEL`] for it not to be dark.
pub const DARK_SHARE: f32 = 0.0005;
/// A frame whose 1st percentile of grey (0–255) is above this is [`Quality::Saturated`].
pub const BRIGHT_P1: f32 = 215.0;
/// Standard deviation (grey levels) below which a view is [`Quality::Textureless`].
pub const FLAT_STD: f32 = 3.0;
/// Mean absolute neighbour difference over the standard deviation at or above which a frame is
/// [`Quality::Noise`] (no spatial structure).
pub const NOISE_RATIO: f32 = 0.7;

/// What [`assess`] found in a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Quality {
    /// A picture to score.
    #[default]
    Usable,
    /// (Nearly) all black.
    Dark,
    /// (Nearly) all white: saturated, a flash.
    Saturated,
    /// Structureless noise.
    Noise,
    /// A flat view: a picture without texture to match.
    Textureless,
    /// Flagged as damaged upstream (`GST_BUFFER_FLAG_CORRUPTED`: a decoder's concealment after
    /// lost or broken data) or as a gap filler (`GST_BUFFER_FLAG_GAP`): not a picture to trust.
    Corrupted,
}

impl Quality {
    pub const ALL: [Quality; 6] = [
        Quality::Usable,
        Quality::Dark,
        Quality::Saturated,
        Quality::Noise,
        Quality::Textureless,
        Quality::Corrupted,
    ];

    /// The string written into `LeanGateMeta`'s `quality` field.
    pub fn as_str(self) -> &'static str {
        match self {
            Quality::Usable => "usable",
            Quality::Dark => "dark",
            Quality::Saturated => "saturated",
            Quality::Noise => "noise",
            Quality::Textureless => "textureless",
            Quality::Corrupted => "corrupted",
        }
    }

    pub fn parse(s: &str) -> Option<Quality> {
        Quality::ALL.into_iter().find(|q| q.as_str() == s)
    }

    /// No usable picture: never kept, never the reference.
    pub fn is_junk(self) -> bool {
        matches!(
            self,
            Quality::Dark | Quality::Saturated | Quality::Noise | Quality::Corrupted
        )
    }
}

/// What [`measure`] finds in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measured {
    pub quality: Quality,
    /// [`sharpness`]'s measure (`None` for junk and pictures too small).
    pub sharpness: Option<f64>,
}

/// The quality of a grey picture (`w` x `h`, levels 0–255, row-major), e.g. the prior's
/// [`crate::geometry::grey_from_tensor`] of the model's input. A picture smaller than 4x4 is
/// [`Quality::Usable`] (nothing to tell).
pub fn assess(grey: &[f32], w: usize, h: usize) -> Quality {
    measure(grey, w, h, &mut Vec::new(), false).quality
}

/// [`assess`] and, `with_sharpness`, [`sharpness`]: two passes over the 2x2-binned picture and
/// one over the picture for the Laplacian (only when asked: the gate needs it only to wait for a
/// sharper frame); `bins` is scratch space kept between frames (no allocation once it has grown).
pub fn measure(
    grey: &[f32],
    w: usize,
    h: usize,
    bins: &mut Vec<f32>,
    with_sharpness: bool,
) -> Measured {
    let (bw, bh) = (w / 2, h / 2);
    let usable = Measured {
        quality: Quality::Usable,
        sharpness: None,
    };
    if bw < 2 || bh < 2 || grey.len() < w * h {
        return usable;
    }
    // Pass 1: 2x2 bins (the sensor's per-pixel noise halves, the picture's structure stays),
    // their sum, sum of squares and histogram.
    bins.clear();
    bins.resize(bw * bh, 0.0);
    let mut hist = [0u32; 256];
    let (mut sum, mut sq) = (0.0f64, 0.0f64);
    for (y, row) in bins.chunks_exact_mut(bw).enumerate() {
        let (r0, r1) = (
            &grey[2 * y * w..][..2 * bw],
            &grey[(2 * y + 1) * w..][..2 * bw],
        );
        let (mut rs, mut rq) = (0.0f32, 0.0f32);
        for ((o, a), b) in row
            .iter_mut()
            .zip(r0.chunks_exact(2))
            .zip(r1.chunks_exact(2))
        {
            let v = 0.25 * (a[0] + a[1] + b[0] + b[1]);
            *o = v;
            rs += v;
            rq += v * v;
            hist[v.clamp(0.0, 255.0) as usize] += 1;
        }
        sum += rs as f64;
        sq += rq as f64;
    }
    let n = bins.len() as f32;
    let mean = sum / n as f64;
    let std = (sq / n as f64 - mean * mean).max(0.0).sqrt() as f32;
    // The grey level below which a fraction `q` of the pixels lie.
    let percentile = |q: f32| {
        let want = ((q * n).ceil() as u32).max(1);
        let mut acc = 0u32;
        hist.iter()
            .position(|&c| {
                acc += c;
                acc >= want
            })
            .unwrap_or(255) as f32
    };
    let junk = |quality| Measured {
        quality,
        sharpness: None,
    };
    // Dark: fewer bins at or above DARK_LEVEL than 0.05 % of them, and than 3 (so that one
    // stray bin of a small picture does not count).
    let bright: u32 = hist[DARK_LEVEL as usize..].iter().sum();
    if (bright as f32) < (DARK_SHARE * n).max(3.0) {
        return junk(Quality::Dark);
    }
    if percentile(0.01) > BRIGHT_P1 {
        return junk(Quality::Saturated);
    }
    // Pass 2: neighbour differences of the bins (structure).
    let b = &bins[..];
    let mut diff = 0.0f64;
    for y in 0..bh {
        let row = &b[y * bw..][..bw];
        let mut d = 0.0f32;
        for x in 0..bw - 1 {
            d += (row[x + 1] - row[x]).abs();
        }
        if y + 1 < bh {
            let next = &b[(y + 1) * bw..][..bw];
            for (a, c) in row.iter().zip(next) {
                d += (a - c).abs();
            }
        }
        diff += d as f64;
    }
    let pairs = (bh * (bw - 1) + (bh - 1) * bw) as f64;
    let quality = if std < FLAT_STD {
        Quality::Textureless
    } else if (diff / pairs) as f32 >= NOISE_RATIO * std {
        return junk(Quality::Noise);
    } else {
        Quality::Usable
    };
    Measured {
        quality,
        sharpness: with_sharpness.then(|| laplacian_variance(grey, w, h)),
    }
}

/// Pass 3: the variance of the 4-neighbour Laplacian at full resolution (blur of a few pixels
/// averages away in the bins), rows accumulated in f32 so that the loop vectorises.
fn laplacian_variance(grey: &[f32], w: usize, h: usize) -> f64 {
    let (mut sum, mut sq) = (0.0f64, 0.0f64);
    for y in 1..h - 1 {
        let (up, row, down) = (
            &grey[(y - 1) * w..][..w],
            &grey[y * w..][..w],
            &grey[(y + 1) * w..][..w],
        );
        let (mut rs, mut rq) = (0.0f32, 0.0f32);
        for x in 1..w - 1 {
            let l = up[x] + down[x] + row[x - 1] + row[x + 1] - 4.0 * row[x];
            rs += l;
            rq += l * l;
        }
        sum += rs as f64;
        sq += rq as f64;
    }
    let n = ((w - 2) * (h - 2)) as f64;
    let mean = sum / n;
    (sq / n - mean * mean).max(0.0)
}

/// Sharpness of a grey picture (`w` x `h`, levels 0–255): the variance of its 4-neighbour
/// Laplacian, a usual focus measure. Motion blur and defocus lower it; it is
/// compared between neighbouring frames of one stream (the scene changes little between them),
/// never as an absolute. `None` for junk or a picture smaller than 4x4 ([`measure`]).
pub fn sharpness(grey: &[f32], w: usize, h: usize) -> Option<f64> {
    measure(grey, w, h, &mut Vec::new(), true).sharpness
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: usize = 96;
    const H: usize = 64;

    fn picture(f: impl Fn(usize, usize) -> f32) -> Vec<f32> {
        (0..W * H).map(|i| f(i % W, i / W)).collect()
    }

    /// A deterministic pseudo-random sequence in [0, 1).
    fn rng(seed: u32) -> impl FnMut() -> f32 {
        let mut x = seed.wrapping_mul(2_654_435_761).max(1);
        move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x >> 8) as f32 / (1u32 << 24) as f32
        }
    }

    #[test]
    fn tells_junk_from_pictures() {
        let scene = picture(|x, y| {
            let (u, v) = (x as f32, y as f32);
            120.0 + 60.0 * (u * 0.11).sin() * (v * 0.07).cos() + 30.0 * ((u + v) * 0.05).sin()
        });
        assert_eq!(assess(&scene, W, H), Quality::Usable);
        assert_eq!(assess(&picture(|_, _| 0.0), W, H), Quality::Dark);
        assert_eq!(assess(&picture(|_, _| 255.0), W, H), Quality::Saturated);
        // A lens cap: black with a little sensor noise; a flash: white with a few details.
        let mut r = rng(1);
        let cap: Vec<f32> = picture(|_, _| 0.0).iter().map(|_| 6.0 * r()).collect();
        assert_eq!(assess(&cap, W, H), Quality::Dark);
        let flash = picture(|x, y| 240.0 + ((x * 7 + y * 3) % 15) as f32);
        assert_eq!(assess(&flash, W, H), Quality::Saturated);
        // A small bright object on black (a lamp at night, videotestsrc's ball) is a picture.
        let ball = picture(|x, y| {
            let (dx, dy) = (x as f32 - 40.0, y as f32 - 30.0);
            if dx * dx + dy * dy < 36.0 {
                255.0
            } else {
                0.0
            }
        });
        assert_eq!(assess(&ball, W, H), Quality::Usable);
        // Down to a few bright bins (the ball at 1920x1080 in a 160x120 picture); one stray
        // bright pixel on black is still dark.
        let dot = picture(|x, y| {
            if (40..43).contains(&x) && (30..33).contains(&y) {
                255.0
            } else {
                0.0
            }
        });
        assert_eq!(assess(&dot, W, H), Quality::Usable);
        let hot = picture(|x, y| if (x, y) == (41, 31) { 255.0 } else { 0.0 });
        assert_eq!(assess(&hot, W, H), Quality::Dark);
        // Mid-grey with sensor noise (sigma about 1): a textureless view, not junk.
        let mut r = rng(2);
        let grey: Vec<f32> = (0..W * H).map(|_| 128.0 + 3.4 * (r() - 0.5)).collect();
        assert_eq!(assess(&grey, W, H), Quality::Textureless);
        assert!(!Quality::Textureless.is_junk());
        // A frame of noise (a broken link).
        let mut r = rng(3);
        let noise: Vec<f32> = (0..W * H).map(|_| 255.0 * r()).collect();
        assert_eq!(assess(&noise, W, H), Quality::Noise);
        // A dark but real scene (a dim room, half in shadow) is a picture.
        let dim = picture(|x, y| if x < W / 2 { 4.0 } else { 40.0 + (y as f32) });
        assert_eq!(assess(&dim, W, H), Quality::Usable);
        // Too small to tell.
        assert_eq!(assess(&[0.0; 2], 1, 2), Quality::Usable);
    }

    #[test]
    fn blur_lowers_sharpness() {
        let sharp = picture(|x, y| {
            if (x / 12 + y / 12) % 2 == 0 {
                40.0
            } else {
                200.0
            }
        });
        // A horizontal box blur of 5 pixels, as a fast pan leaves it.
        let blurred: Vec<f32> = (0..W * H)
            .map(|i| {
                let (x, y) = (i % W, i / W);
                (0..5)
                    .map(|d| sharp[y * W + (x + d).saturating_sub(2).min(W - 1)])
                    .sum::<f32>()
                    / 5.0
            })
            .collect();
        let (s, b) = (
            sharpness(&sharp, W, H).unwrap(),
            sharpness(&blurred, W, H).unwrap(),
        );
        assert!(b < 0.5 * s, "blurred {b} against sharp {s}");
        // A flat view has none; junk and tiny pictures have no measure.
        assert_eq!(sharpness(&picture(|_, _| 77.0), W, H), Some(0.0));
        assert_eq!(sharpness(&picture(|_, _| 0.0), W, H), None);
        assert_eq!(sharpness(&[1.0; 4], 2, 2), None);
    }

    #[test]
    fn names_round_trip() {
        for q in Quality::ALL {
            assert_eq!(Quality::parse(q.as_str()), Some(q));
        }
        assert_eq!(
            Quality::ALL.iter().filter(|q| q.is_junk()).count(),
            4,
            "dark, saturated, noise, corrupted"
        );
    }
}
