//! Value parsers for the `leangate` command line: every numeric argument of every subcommand is
//! checked at parse time (a finite number, in its range), so a bad value is a usage error naming
//! the argument and the value (clap: `invalid value 'nan' for '--threshold <THRESHOLD>': expected a
//! number from 0 to 1`, exit status 2), never a panic, an abort or a silently accepted NaN.

use std::fmt::Display;
use std::ops::RangeInclusive;
use std::str::FromStr;

use crate::synth::{MAX_FRAMES, MAX_SIDE};

/// Largest `--working-width` of the teacher (wider depth maps are not subsampled anyway).
pub const MAX_WORKING_WIDTH: u32 = 8192;
/// Largest `leangate label --random` count (pairs are held in memory before scoring).
pub const MAX_RANDOM_PAIRS: usize = 10_000_000;
/// Picture sides `leangate geometry --size` accepts (the element's input limit).
pub const PICTURE_SIDES: RangeInclusive<u32> = 8..=4096;

/// A finite float in `range` (inclusive); `what` describes the range in the message.
fn float_in(s: &str, range: RangeInclusive<f64>, what: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(x) if x.is_finite() && range.contains(&x) => Ok(x),
        _ => Err(format!("expected {what}")),
    }
}

/// An integer in `range` (inclusive).
fn int_in<T>(s: &str, range: RangeInclusive<T>) -> Result<T, String>
where
    T: FromStr + PartialOrd + Display,
{
    match s.trim().parse::<T>() {
        Ok(x) if range.contains(&x) => Ok(x),
        _ => Err(format!(
            "expected an integer from {} to {}",
            range.start(),
            range.end()
        )),
    }
}

/// A finite number in [0, 1] (thresholds, noise levels).
pub fn unit_interval(s: &str) -> Result<f64, String> {
    float_in(s, 0.0..=1.0, "a number from 0 to 1")
}

/// A finite number > 0 (distances, rates).
pub fn finite_positive(s: &str) -> Result<f64, String> {
    float_in(s, f64::MIN_POSITIVE..=f64::MAX, "a finite number above 0")
}

/// A finite number >= 0 (offsets in seconds).
pub fn finite_non_negative(s: &str) -> Result<f64, String> {
    float_in(s, 0.0..=f64::MAX, "a finite number, 0 or more")
}

/// A count of at least 1.
pub fn nonzero(s: &str) -> Result<usize, String> {
    int_in(s, 1..=usize::MAX)
}

/// `leangate eval --phases`: 1 to 100 start frames per sequence.
pub fn phases(s: &str) -> Result<usize, String> {
    int_in(s, 1..=100)
}

/// A count of at least 1 that fits in a `u32`.
pub fn nonzero_u32(s: &str) -> Result<u32, String> {
    int_in(s, 1..=u32::MAX)
}

/// A side of a `leangate synth` frame: 2 to [`MAX_SIDE`] pixels.
pub fn synth_side(s: &str) -> Result<u32, String> {
    int_in(s, 2..=MAX_SIDE)
}

/// `leangate synth --frames`: 1 to [`MAX_FRAMES`].
pub fn synth_frames(s: &str) -> Result<usize, String> {
    int_in(s, 1..=MAX_FRAMES)
}

/// The teacher's working width: 1 to [`MAX_WORKING_WIDTH`] pixels.
pub fn working_width(s: &str) -> Result<u32, String> {
    int_in(s, 1..=MAX_WORKING_WIDTH)
}

/// `leangate label --random N`: 1 to [`MAX_RANDOM_PAIRS`].
pub fn random_pairs(s: &str) -> Result<usize, String> {
    int_in(s, 1..=MAX_RANDOM_PAIRS)
}

/// `WxH` (e.g. `160x120`), each side in [`PICTURE_SIDES`].
pub fn picture_size(s: &str) -> Result<(u32, u32), String> {
    let expected = || {
        format!(
            "expected WxH like 160x120, sides {} to {}",
            PICTURE_SIDES.start(),
            PICTURE_SIDES.end()
        )
    };
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(expected)?;
    let side = |v: &str| int_in(v, PICTURE_SIDES).map_err(|_| expected());
    Ok((side(w)?, side(h)?))
}

/// `PROPERTY=VALUE` for `leangate eval --set`: a property name and its value as text (checked
/// against the element when the eval starts).
pub fn property_setting(s: &str) -> Result<(String, String), String> {
    match s.split_once('=') {
        Some((k, v)) if !k.trim().is_empty() => Ok((k.trim().to_string(), v.to_string())),
        _ => Err(format!(
            "`{s}`: expected PROPERTY=VALUE, e.g. sharpness-lookback=0"
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floats_must_be_finite_and_in_range() {
        assert_eq!(unit_interval("0.5"), Ok(0.5));
        assert_eq!(unit_interval(" 1 "), Ok(1.0));
        assert_eq!(unit_interval("0"), Ok(0.0));
        for bad in [
            "nan",
            "NaN",
            "inf",
            "-inf",
            "2",
            "1.0000001",
            "-0.1",
            "",
            "abc",
        ] {
            let e = unit_interval(bad).unwrap_err();
            assert_eq!(e, "expected a number from 0 to 1");
        }
        assert_eq!(finite_positive("0.1"), Ok(0.1));
        for bad in ["0", "-1", "nan", "inf", "1e309"] {
            assert!(finite_positive(bad).is_err(), "{bad}");
        }
        assert_eq!(finite_non_negative("0"), Ok(0.0));
        assert!(finite_non_negative("-0.5").is_err());
        assert!(finite_non_negative("nan").is_err());
    }

    #[test]
    fn integers_must_be_in_range() {
        assert_eq!(nonzero("3"), Ok(3));
        assert!(nonzero("0").unwrap_err().contains("from 1 to"));
        assert!(nonzero("-1").is_err());
        assert!(nonzero("99999999999999999999999").is_err());
        assert_eq!(synth_side("640"), Ok(640));
        assert_eq!(synth_side("4096"), Ok(4096));
        let e = synth_side("100000").unwrap_err();
        assert!(e.contains("from 2 to 4096"), "{e}");
        assert!(working_width("0").is_err());
        assert!(random_pairs("10000000000000").is_err());
        assert_eq!(nonzero_u32("4096"), Ok(4096));
        assert!(nonzero_u32("0").is_err());
    }

    #[test]
    fn picture_sizes() {
        assert_eq!(picture_size("160x120"), Ok((160, 120)));
        assert_eq!(picture_size("64X48"), Ok((64, 48)));
        for bad in ["160", "4x120", "160x5000", "x", "ax b", "160x120x3"] {
            let e = picture_size(bad).unwrap_err();
            assert!(e.contains("expected WxH"), "{e}");
        }
    }
}
