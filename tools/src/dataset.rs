//! Sequence I/O in the TUM RGB-D layout, shared by every LeanGate tool.
//!
//! # Layout
//!
//! A sequence is a directory holding:
//!
//! * `rgb.txt`: one `timestamp path` line per colour frame (path relative to the directory);
//! * `depth.txt` (optional): one `timestamp path` line per depth frame, 16-bit single-channel PNGs;
//!   a pixel value divided by `depth_scale` gives metres, 0 means "no reading" (and so does 65535,
//!   the marker Microsoft 7-Scenes writes for it: 13 m or more at every usual scale);
//! * `groundtruth.txt` (optional; `groundtruth_tum.txt` is accepted as a fallback name): one
//!   `t tx ty tz qx qy qz qw` line per pose, **camera-to-world**, camera frame as in OpenCV/TUM
//!   (x right, y down, z forward);
//! * `intrinsics.txt` (optional): one non-comment line `fx fy cx cy depth_scale` (pixels, pixel
//!   centres at integer coordinates; depth units per metre, e.g. 1000 for millimetres, 5000 for
//!   the TUM benchmark).
//!
//! Lines whose first non-blank character is `#`, and blank lines, are ignored everywhere.
//!
//! A directory without `rgb.txt` is also accepted for gating without ground truth: the images
//! (`*.png`, `*.jpg`, `*.jpeg`) in its `rgb/` sub-directory, or else in the directory itself, sorted
//! by name, become the frames, with timestamps `index / 30` s.
//!
//! # Association
//!
//! As TUM's `associate.py` (without its one-to-one constraint): each colour frame takes the
//! depth frame and the pose with the nearest timestamp, if within [`OpenOptions::max_difference`]
//! (20 ms by default). With [`OpenOptions::drop_unmatched`] (the default) a colour frame that
//! lacks a depth match while `depth.txt` exists, or lacks a pose while a ground-truth file
//! exists, is dropped, so that every kept frame is complete. With `drop_unmatched = false` every
//! colour frame is kept and the missing parts are `None` (useful to gate a whole clip whose
//! ground truth covers only part of it).

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use image::{ImageBuffer, Luma, RgbImage};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

/// The list files a sequence directory may hold (see the module documentation).
pub const LIST_FILES: [&str; 5] = [
    "rgb.txt",
    "depth.txt",
    "groundtruth.txt",
    "groundtruth_tum.txt",
    "intrinsics.txt",
];

/// Pinhole intrinsics of the depth (and, in synthetic data, colour) camera, plus the depth scale.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (pixel centres at integer coordinates).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Depth PNG units per metre (PNG value / depth_scale = metres).
    pub depth_scale: f64,
}

/// One associated frame of a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Timestamp of the colour image, seconds.
    pub timestamp: f64,
    /// Absolute path of the colour image.
    pub rgb: PathBuf,
    /// Absolute path of the associated depth image, if any.
    pub depth: Option<PathBuf>,
    /// Associated camera-to-world pose, if any.
    pub pose: Option<Isometry3<f64>>,
}

/// A depth map in metres, row-major; `0.0` marks pixels without a reading.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` depths in metres, row-major; 0.0 = invalid.
    pub data: Vec<f32>,
}

impl DepthImage {
    /// A depth image filled with zeros (no valid pixel).
    pub fn new(width: u32, height: u32) -> Self {
        DepthImage {
            width,
            height,
            data: vec![0.0; width as usize * height as usize],
        }
    }

    /// Depth at pixel `(u, v)`; `None` outside the image.
    pub fn get(&self, u: u32, v: u32) -> Option<f32> {
        if u < self.width && v < self.height {
            self.data
                .get(v as usize * self.width as usize + u as usize)
                .copied()
        } else {
            None
        }
    }
}

/// Errors of sequence reading and writing; messages name the file (and line) at fault.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// An I/O error on `path`.
    #[error("`{}`: {source}", path.display())]
    Io {
        /// File or directory concerned.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// A malformed line in a text file (`line` is 1-based).
    #[error("`{}` line {line}: {message}", path.display())]
    Parse {
        /// File concerned.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What was wrong.
        message: String,
    },
    /// A required file or directory does not exist.
    #[error("`{}`: missing {what}", path.display())]
    Missing {
        /// Expected path.
        path: PathBuf,
        /// What it should have been.
        what: String,
    },
    /// An image could not be decoded or encoded.
    #[error("`{}`: {source}", path.display())]
    Image {
        /// Image file concerned.
        path: PathBuf,
        /// Underlying error.
        source: image::ImageError,
    },
    /// Content that parsed but is inconsistent (bad sizes, counts, values).
    #[error("`{}`: {message}", path.display())]
    Invalid {
        /// File or directory concerned.
        path: PathBuf,
        /// What was wrong.
        message: String,
    },
    /// A frame index past the end of the sequence.
    #[error("frame index {index} out of range (sequence has {len} frames)")]
    IndexOutOfRange {
        /// Requested index.
        index: usize,
        /// Number of frames.
        len: usize,
    },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Options of [`Sequence::open_with`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpenOptions {
    /// Largest timestamp difference (seconds) for associating depth and poses to colour frames.
    pub max_difference: f64,
    /// Drop colour frames lacking a depth frame (when `depth.txt` exists) or a pose (when a
    /// ground-truth file exists). Otherwise keep them with `None`.
    pub drop_unmatched: bool,
}

impl Default for OpenOptions {
    fn default() -> Self {
        OpenOptions {
            max_difference: 0.02,
            drop_unmatched: true,
        }
    }
}

/// An RGB(-D) sequence with optional ground truth.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// The sequence directory.
    pub root: PathBuf,
    /// Associated frames, in timestamp order.
    pub frames: Vec<Frame>,
    /// Intrinsics from `intrinsics.txt`, if present.
    pub intrinsics: Option<Intrinsics>,
}

/// Reads the non-comment lines of a text file as `(1-based line number, trimmed line)`.
fn read_lines(path: &Path) -> Result<Vec<(usize, String)>, DatasetError> {
    let text = fs::read_to_string(path).map_err(io_err(path))?;
    // A UTF-8 byte-order mark (some Windows editors write one) is not part of the first line.
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    Ok(text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
        .map(|(i, l)| (i, l.to_string()))
        .collect())
}

fn parse_numbers(
    path: &Path,
    line_no: usize,
    line: &str,
    expected: usize,
    what: &str,
) -> Result<Vec<f64>, DatasetError> {
    let toks: Vec<&str> = line.split_whitespace().collect();
    if toks.len() != expected {
        return Err(DatasetError::Parse {
            path: path.to_path_buf(),
            line: line_no,
            message: format!("expected {expected} numbers `{what}`, got {}", toks.len()),
        });
    }
    toks.iter()
        .map(|t| {
            t.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| DatasetError::Parse {
                    path: path.to_path_buf(),
                    line: line_no,
                    message: format!("`{t}` is not a finite number (expected `{what}`)"),
                })
        })
        .collect()
}

/// Parses a `timestamp path` list (`rgb.txt`, `depth.txt`); paths are made absolute.
///
/// `shared`: whether a row may repeat. In a one-row-per-frame `depth.txt` two colour frames may
/// share their nearest depth image, so an identical row (same timestamp, same file) is read once;
/// two *different* files at one timestamp are refused there too. In `rgb.txt` every row is a
/// frame, and two frames at one time are refused.
fn read_file_list(
    path: &Path,
    root: &Path,
    shared: bool,
) -> Result<Vec<(f64, PathBuf)>, DatasetError> {
    let mut out = Vec::new();
    for (no, line) in read_lines(path)? {
        let mut it = line.splitn(2, char::is_whitespace);
        let ts = it.next().unwrap_or("");
        let file = it.next().map(str::trim).unwrap_or("");
        if file.is_empty() {
            return Err(DatasetError::Parse {
                path: path.to_path_buf(),
                line: no,
                message: "expected `timestamp filename`".into(),
            });
        }
        let t = ts
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| DatasetError::Parse {
                path: path.to_path_buf(),
                line: no,
                message: format!("timestamp `{ts}` is not a finite number"),
            })?;
        out.push((t, root.join(file), no));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.2.cmp(&b.2)));
    if shared {
        // The same file however its path is spelled (`depth/../depth/x.png`, absolute).
        let same = |a: &Path, b: &Path| {
            a == b || matches!((fs::canonicalize(a), fs::canonicalize(b)), (Ok(x), Ok(y)) if x == y)
        };
        out.dedup_by(|b, a| a.0 == b.0 && same(&a.1, &b.1));
    }
    // Two rows at one time would be associated with the same depth and pose, and their order
    // would be the file's, not time's: refused, naming both lines.
    if let Some(w) = out.windows(2).find(|w| w[0].0 == w[1].0) {
        let (a, b) = (w[0].2.min(w[1].2), w[0].2.max(w[1].2));
        let message = if shared {
            format!(
                "timestamp {} names another file on line {a} (`{}` and `{}`)",
                w[0].0,
                w[0].1.display(),
                w[1].1.display()
            )
        } else {
            format!("timestamp {} is also on line {a}", w[0].0)
        };
        return Err(DatasetError::Parse {
            path: path.to_path_buf(),
            line: b,
            message,
        });
    }
    Ok(out.into_iter().map(|(t, p, _)| (t, p)).collect())
}

/// Parses a TUM trajectory (`t tx ty tz qx qy qz qw`, camera-to-world), sorted by time.
pub fn read_trajectory(path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, DatasetError> {
    let mut out = Vec::new();
    for (no, line) in read_lines(path)? {
        let n = parse_numbers(path, no, &line, 8, "t tx ty tz qx qy qz qw")?;
        let q = Quaternion::new(n[7], n[4], n[5], n[6]);
        let norm = q.norm();
        if norm.is_nan() || norm <= 1e-6 {
            return Err(DatasetError::Parse {
                path: path.to_path_buf(),
                line: no,
                message: "quaternion has zero norm".into(),
            });
        }
        let rot = UnitQuaternion::from_quaternion(q);
        out.push((
            n[0],
            Isometry3::from_parts(Translation3::new(n[1], n[2], n[3]), rot),
        ));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(out)
}

/// Parses `intrinsics.txt`: the first non-comment line, `fx fy cx cy depth_scale`.
pub fn read_intrinsics(path: &Path) -> Result<Intrinsics, DatasetError> {
    let lines = read_lines(path)?;
    let (no, line) = lines.first().ok_or_else(|| DatasetError::Invalid {
        path: path.to_path_buf(),
        message: "no `fx fy cx cy depth_scale` line".into(),
    })?;
    let n = parse_numbers(path, *no, line, 5, "fx fy cx cy depth_scale")?;
    if n[0] <= 0.0 || n[1] <= 0.0 || n[4] <= 0.0 {
        return Err(DatasetError::Parse {
            path: path.to_path_buf(),
            line: *no,
            message: "fx, fy and depth_scale must be positive".into(),
        });
    }
    // Depth is value / depth_scale in f32: a scale whose inverse is not a normal f32 turns
    // every reading into infinity or zero (no reading).
    if !(1.0 / n[4] as f32).is_normal() {
        return Err(DatasetError::Parse {
            path: path.to_path_buf(),
            line: *no,
            message: format!("depth_scale {:e} is out of range (units per metre)", n[4]),
        });
    }
    Ok(Intrinsics {
        fx: n[0],
        fy: n[1],
        cx: n[2],
        cy: n[3],
        depth_scale: n[4],
    })
}

/// Index of the entry of `list` (sorted by time) nearest to `t`, if within `max_diff`.
fn nearest<T>(list: &[(f64, T)], t: f64, max_diff: f64) -> Option<usize> {
    if list.is_empty() {
        return None;
    }
    let pos = list.partition_point(|(lt, _)| *lt < t);
    let mut best: Option<(usize, f64)> = None;
    for idx in [pos.wrapping_sub(1), pos] {
        if let Some((lt, _)) = list.get(idx) {
            let d = (lt - t).abs();
            if best.is_none_or(|(_, bd)| d < bd) {
                best = Some((idx, d));
            }
        }
    }
    best.filter(|(_, d)| *d <= max_diff).map(|(i, _)| i)
}

fn is_image_file(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .map(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
        .unwrap_or(false)
}

/// Sorted image files (`png`, `jpg`, `jpeg`) directly inside `dir`.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let mut files: Vec<PathBuf> = fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && is_image_file(p))
        .collect();
    files.sort();
    Ok(files)
}

impl Sequence {
    /// Opens a sequence directory with the default [`OpenOptions`] (20 ms, drop unmatched).
    pub fn open(path: &Path) -> Result<Sequence, DatasetError> {
        Self::open_with(path, &OpenOptions::default())
    }

    /// Opens a sequence directory; see the module documentation for layout and association.
    pub fn open_with(path: &Path, opts: &OpenOptions) -> Result<Sequence, DatasetError> {
        let root = path.to_path_buf();
        if !root.is_dir() {
            return Err(DatasetError::Missing {
                path: root,
                what: "sequence directory".into(),
            });
        }
        let rgb_txt = root.join("rgb.txt");
        let rgb_list: Vec<(f64, PathBuf)> = if rgb_txt.is_file() {
            read_file_list(&rgb_txt, &root, false)?
        } else {
            let sub = root.join("rgb");
            let dir = if sub.is_dir() { sub } else { root.clone() };
            let files = list_images(&dir)?;
            if files.is_empty() {
                return Err(DatasetError::Missing {
                    path: rgb_txt,
                    what: "rgb.txt (and no png/jpg images in the directory or its rgb/)".into(),
                });
            }
            files
                .into_iter()
                .enumerate()
                .map(|(i, p)| (i as f64 / 30.0, p))
                .collect()
        };
        if rgb_list.is_empty() {
            return Err(DatasetError::Invalid {
                path: rgb_txt,
                message: "no frames listed".into(),
            });
        }

        let depth_txt = root.join("depth.txt");
        let depth_list = if depth_txt.is_file() {
            Some(read_file_list(&depth_txt, &root, true)?)
        } else {
            None
        };
        let gt_path = ["groundtruth.txt", "groundtruth_tum.txt"]
            .iter()
            .map(|n| root.join(n))
            .find(|p| p.is_file());
        let poses = match &gt_path {
            Some(p) => Some(read_trajectory(p)?),
            None => None,
        };
        let intr_path = root.join("intrinsics.txt");
        let intrinsics = if intr_path.is_file() {
            Some(read_intrinsics(&intr_path)?)
        } else {
            None
        };

        let mut frames = Vec::with_capacity(rgb_list.len());
        for (t, rgb) in rgb_list {
            let depth = depth_list
                .as_ref()
                .and_then(|l| nearest(l, t, opts.max_difference).map(|i| l[i].1.clone()));
            let pose = poses
                .as_ref()
                .and_then(|l| nearest(l, t, opts.max_difference).map(|i| l[i].1));
            if opts.drop_unmatched
                && ((depth_list.is_some() && depth.is_none())
                    || (poses.is_some() && pose.is_none()))
            {
                continue;
            }
            frames.push(Frame {
                timestamp: t,
                rgb,
                depth,
                pose,
            });
        }
        if frames.is_empty() {
            return Err(DatasetError::Invalid {
                path: root,
                message: format!(
                    "no colour frame could be associated with depth/poses within {} ms",
                    opts.max_difference * 1000.0
                ),
            });
        }
        Ok(Sequence {
            root,
            frames,
            intrinsics,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the sequence has no frame.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// True when intrinsics exist and every frame has a depth image and a pose.
    pub fn has_ground_truth(&self) -> bool {
        self.intrinsics.is_some()
            && !self.frames.is_empty()
            && self
                .frames
                .iter()
                .all(|f| f.depth.is_some() && f.pose.is_some())
    }

    /// Frames the teacher can judge: with a depth image and a pose, when intrinsics exist.
    pub fn judged_frames(&self) -> usize {
        match self.intrinsics {
            Some(_) => self
                .frames
                .iter()
                .filter(|f| f.depth.is_some() && f.pose.is_some())
                .count(),
            None => 0,
        }
    }

    /// Timestamps of all frames.
    pub fn timestamps(&self) -> Vec<f64> {
        self.frames.iter().map(|f| f.timestamp).collect()
    }

    fn frame(&self, i: usize) -> Result<&Frame, DatasetError> {
        self.frames.get(i).ok_or(DatasetError::IndexOutOfRange {
            index: i,
            len: self.frames.len(),
        })
    }

    /// Loads colour frame `i` as 8-bit RGB (grayscale images are expanded).
    pub fn load_rgb(&self, i: usize) -> Result<RgbImage, DatasetError> {
        let path = &self.frame(i)?.rgb;
        let bytes = fs::read(path).map_err(io_err(path))?;
        let reader = image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(io_err(path))?;
        // The JPEG decoder fills a cut-off file with grey instead of failing: a file that
        // ends before its end-of-image marker is refused here.
        if reader.format() == Some(image::ImageFormat::Jpeg) && !jpeg_is_complete(&bytes) {
            return Err(DatasetError::Invalid {
                path: path.to_path_buf(),
                message: "the JPEG ends before its end-of-image marker (a truncated file?)".into(),
            });
        }
        let img = reader.decode().map_err(|source| image_err(path, source))?;
        Ok(img.into_rgb8())
    }

    /// Loads depth frame `i` in metres (0.0 = no reading), using `depth_scale`.
    pub fn load_depth_m(&self, i: usize) -> Result<DepthImage, DatasetError> {
        let frame = self.frame(i)?;
        let path = frame.depth.as_ref().ok_or_else(|| DatasetError::Missing {
            path: self.root.join("depth.txt"),
            what: format!("depth frame for colour frame {i} ({})", frame.rgb.display()),
        })?;
        let intr = self.intrinsics.ok_or_else(|| DatasetError::Missing {
            path: self.root.join("intrinsics.txt"),
            what: "intrinsics (needed for depth_scale)".into(),
        })?;
        read_depth_png(path, intr.depth_scale)
    }
}

/// Whether a JPEG file holds its end-of-image marker (FF D9) near its end: some writers pad the
/// file after it, a truncated file never has it there (inside the compressed data FF is always
/// followed by 00 or a restart marker, FF D0-D7).
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    let tail = &bytes[bytes.len().saturating_sub(1024)..];
    tail.windows(2).any(|w| w == [0xFF, 0xD9])
}

fn image_err(path: &Path, source: image::ImageError) -> DatasetError {
    match source {
        image::ImageError::IoError(e) => DatasetError::Io {
            path: path.to_path_buf(),
            source: e,
        },
        source => DatasetError::Image {
            path: path.to_path_buf(),
            source,
        },
    }
}

/// The 16-bit value some datasets (Microsoft 7-Scenes) write for "no reading", besides 0.
pub const NO_READING_MAX: u16 = u16::MAX;

/// Reads a 16-bit single-channel depth PNG and converts it to metres (value / `depth_scale`);
/// 0 and [`NO_READING_MAX`] are "no reading" (0.0).
pub fn read_depth_png(path: &Path, depth_scale: f64) -> Result<DepthImage, DatasetError> {
    let img = image::open(path).map_err(|source| image_err(path, source))?;
    let img = match img {
        image::DynamicImage::ImageLuma16(b) => b,
        other => {
            return Err(DatasetError::Invalid {
                path: path.to_path_buf(),
                message: format!(
                    "expected a 16-bit single-channel depth image, got {:?}",
                    other.color()
                ),
            })
        }
    };
    let inv = (1.0 / depth_scale) as f32;
    let (width, height) = img.dimensions();
    let data = img
        .into_raw()
        .into_iter()
        .map(|v| {
            if v == NO_READING_MAX {
                0.0
            } else {
                v as f32 * inv
            }
        })
        .collect();
    Ok(DepthImage {
        width,
        height,
        data,
    })
}

/// Writes a depth map (metres) as a 16-bit PNG with `value = round(metres * depth_scale)`;
/// invalid, non-finite, non-positive or out-of-range (65535 units or more: [`NO_READING_MAX`] reads
/// back as no reading) depths become 0.
pub fn write_depth_png(
    path: &Path,
    depth: &DepthImage,
    depth_scale: f64,
) -> Result<(), DatasetError> {
    let n = depth.width as usize * depth.height as usize;
    if depth.data.len() != n {
        return Err(DatasetError::Invalid {
            path: path.to_path_buf(),
            message: format!(
                "depth image has {} values for {}x{}",
                depth.data.len(),
                depth.width,
                depth.height
            ),
        });
    }
    let raw: Vec<u16> = depth
        .data
        .iter()
        .map(|&d| {
            let v = (d as f64 * depth_scale).round();
            if v.is_finite() && v > 0.0 && v < NO_READING_MAX as f64 {
                v as u16
            } else {
                0
            }
        })
        .collect();
    let buf: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_raw(depth.width, depth.height, raw).ok_or_else(|| {
            DatasetError::Invalid {
                path: path.to_path_buf(),
                message: "bad depth buffer size".into(),
            }
        })?;
    let file = fs::File::create(path).map_err(io_err(path))?;
    let enc = image::codecs::png::PngEncoder::new_with_quality(
        BufWriter::new(file),
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Adaptive,
    );
    buf.write_with_encoder(enc)
        .map_err(|source| image_err(path, source))
}

/// Encoding of colour frames written by [`SequenceWriter`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RgbFormat {
    /// Lossless PNG (fast compression).
    #[default]
    Png,
    /// JPEG with the given quality (1-100).
    Jpeg(u8),
}

fn write_rgb(path: &Path, rgb: &RgbImage, format: RgbFormat) -> Result<(), DatasetError> {
    let file = fs::File::create(path).map_err(io_err(path))?;
    let w = BufWriter::new(file);
    let res = match format {
        RgbFormat::Png => rgb.write_with_encoder(image::codecs::png::PngEncoder::new_with_quality(
            w,
            image::codecs::png::CompressionType::Fast,
            image::codecs::png::FilterType::Adaptive,
        )),
        RgbFormat::Jpeg(q) => rgb.write_with_encoder(
            image::codecs::jpeg::JpegEncoder::new_with_quality(w, q.clamp(1, 100)),
        ),
    };
    res.map_err(|source| image_err(path, source))
}

struct Record {
    index: usize,
    timestamp: f64,
    rgb: String,
    depth: Option<String>,
    pose: Option<Isometry3<f64>>,
}

/// Writes a sequence in the TUM layout read by [`Sequence::open`].
///
/// Frames are written with [`SequenceWriter::write_frame`], which takes `&self` and may be
/// called from several threads at once (images are encoded in the calling thread); the text
/// files (`rgb.txt`, `depth.txt`, `groundtruth.txt`, `intrinsics.txt`) are written by
/// [`SequenceWriter::finish`], sorted by frame index.
pub struct SequenceWriter {
    root: PathBuf,
    intrinsics: Intrinsics,
    rgb_format: RgbFormat,
    records: Mutex<Vec<Record>>,
    header: String,
}

impl SequenceWriter {
    /// Creates `root` (and `root/rgb`, `root/depth`) for writing.
    pub fn create(
        root: &Path,
        intrinsics: Intrinsics,
        rgb_format: RgbFormat,
    ) -> Result<SequenceWriter, DatasetError> {
        for dir in [root.to_path_buf(), root.join("rgb"), root.join("depth")] {
            fs::create_dir_all(&dir).map_err(io_err(&dir))?;
        }
        Ok(SequenceWriter {
            root: root.to_path_buf(),
            intrinsics,
            rgb_format,
            records: Mutex::new(Vec::new()),
            header: String::new(),
        })
    }

    /// A comment line (without `#`) written at the top of every text file, e.g. provenance.
    pub fn set_header(&mut self, header: &str) {
        self.header = header.replace('\n', " ");
    }

    /// The output directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Writes frame `index` (file names `rgb/{index:06}.png|jpg`, `depth/{index:06}.png`).
    pub fn write_frame(
        &self,
        index: usize,
        timestamp: f64,
        rgb: &RgbImage,
        depth: Option<&DepthImage>,
        pose: Option<&Isometry3<f64>>,
    ) -> Result<(), DatasetError> {
        let ext = match self.rgb_format {
            RgbFormat::Png => "png",
            RgbFormat::Jpeg(_) => "jpg",
        };
        let rgb_rel = format!("rgb/{index:06}.{ext}");
        write_rgb(&self.root.join(&rgb_rel), rgb, self.rgb_format)?;
        let depth_rel = match depth {
            Some(d) => {
                let rel = format!("depth/{index:06}.png");
                write_depth_png(&self.root.join(&rel), d, self.intrinsics.depth_scale)?;
                Some(rel)
            }
            None => None,
        };
        let rec = Record {
            index,
            timestamp,
            rgb: rgb_rel,
            depth: depth_rel,
            pose: pose.copied(),
        };
        self.records
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(rec);
        Ok(())
    }

    /// Writes the text files and returns the sequence directory.
    pub fn finish(self) -> Result<PathBuf, DatasetError> {
        let mut recs = self.records.into_inner().unwrap_or_else(|e| e.into_inner());
        recs.sort_by_key(|r| r.index);
        let head = if self.header.is_empty() {
            String::new()
        } else {
            format!("# {}\n", self.header)
        };
        let mut rgb = format!("{head}# timestamp filename\n");
        let mut depth = format!("{head}# timestamp filename (16-bit PNG, depth_scale units per metre, 0 = no reading)\n");
        let mut gt = format!("{head}# timestamp tx ty tz qx qy qz qw (camera-to-world)\n");
        let (mut any_depth, mut any_pose) = (false, false);
        for r in &recs {
            rgb.push_str(&format!("{:.6} {}\n", r.timestamp, r.rgb));
            if let Some(d) = &r.depth {
                any_depth = true;
                depth.push_str(&format!("{:.6} {}\n", r.timestamp, d));
            }
            if let Some(p) = &r.pose {
                any_pose = true;
                gt.push_str(&format!("{:.6} {}\n", r.timestamp, format_pose(p)));
            }
        }
        let i = &self.intrinsics;
        let intr = format!(
            "{head}# fx fy cx cy depth_scale (depth units per metre)\n{} {} {} {} {}\n",
            i.fx, i.fy, i.cx, i.cy, i.depth_scale
        );
        let mut files = vec![("rgb.txt", rgb), ("intrinsics.txt", intr)];
        if any_depth {
            files.push(("depth.txt", depth));
        }
        if any_pose {
            files.push(("groundtruth.txt", gt));
        }
        for (name, text) in files {
            let p = self.root.join(name);
            fs::write(&p, text).map_err(io_err(&p))?;
        }
        Ok(self.root)
    }
}

/// Formats a pose as TUM `tx ty tz qx qy qz qw`.
pub fn format_pose(p: &Isometry3<f64>) -> String {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    format!(
        "{:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
        t.x, t.y, t.z, q.i, q.j, q.k, q.w
    )
}

/// One frame for [`write_sequence_files`]: `(timestamp, rgb, depth, camera-to-world pose)`.
pub type FrameData = (f64, RgbImage, Option<DepthImage>, Option<Isometry3<f64>>);

/// Convenience: writes a whole sequence at once (see [`SequenceWriter`]); frames are
/// `(timestamp, rgb, depth, pose)`.
pub fn write_sequence_files(
    root: &Path,
    intrinsics: Intrinsics,
    rgb_format: RgbFormat,
    frames: &[FrameData],
) -> Result<PathBuf, DatasetError> {
    let w = SequenceWriter::create(root, intrinsics, rgb_format)?;
    for (i, (t, rgb, d, p)) in frames.iter().enumerate() {
        w.write_frame(i, *t, rgb, d.as_ref(), p.as_ref())?;
    }
    w.finish()
}

/// Writes a trajectory in TUM format (`t tx ty tz qx qy qz qw`).
pub fn write_trajectory(path: &Path, poses: &[(f64, Isometry3<f64>)]) -> Result<(), DatasetError> {
    let file = fs::File::create(path).map_err(io_err(path))?;
    let mut w = BufWriter::new(file);
    let mut go = || -> std::io::Result<()> {
        writeln!(w, "# timestamp tx ty tz qx qy qz qw (camera-to-world)")?;
        for (t, p) in poses {
            writeln!(w, "{t:.6} {}", format_pose(p))?;
        }
        w.flush()
    };
    go().map_err(io_err(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    const REDKITCHEN: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/7scenes_redkitchen_dev"
    );
    const EUROC: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/euroc_v101_static"
    );

    fn present(p: &str) -> bool {
        if Path::new(p).is_dir() {
            true
        } else {
            eprintln!("skipping: real data `{p}` absent");
            false
        }
    }

    #[test]
    fn redkitchen_loads() {
        if !present(REDKITCHEN) {
            return;
        }
        let seq = Sequence::open(Path::new(REDKITCHEN)).unwrap();
        assert_eq!(seq.len(), 60);
        assert!(seq.has_ground_truth());
        let intr = seq.intrinsics.unwrap();
        assert_eq!(intr.depth_scale, 1000.0);
        let d = seq.load_depth_m(0).unwrap();
        assert_eq!((d.width, d.height), (640, 480));
        let valid: Vec<f32> = d.data.iter().copied().filter(|&x| x > 0.0).collect();
        assert!(valid.len() > 640 * 480 / 2);
        assert!(valid.iter().all(|&x| x > 0.2 && x < 10.0));
        let rgb = seq.load_rgb(59).unwrap();
        assert_eq!(rgb.dimensions(), (640, 480));
        assert!(matches!(
            seq.load_rgb(60),
            Err(DatasetError::IndexOutOfRange { .. })
        ));
    }

    #[test]
    fn euroc_rgb_and_partial_gt() {
        if !present(EUROC) {
            return;
        }
        let all = Sequence::open_with(
            Path::new(EUROC),
            &OpenOptions {
                drop_unmatched: false,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(all.len(), 95);
        assert!(!all.has_ground_truth());
        assert_eq!(all.frames.iter().filter(|f| f.pose.is_some()).count(), 74);
        let gt = Sequence::open(Path::new(EUROC)).unwrap();
        assert_eq!(gt.len(), 74);
        assert!(gt.frames.iter().all(|f| f.pose.is_some()));
        assert!(!gt.has_ground_truth()); // no depth
        let img = gt.load_rgb(0).unwrap();
        assert_eq!(img.dimensions(), (752, 480));
        assert!(gt.load_depth_m(0).is_err());
    }

    #[test]
    fn zero_and_the_7scenes_marker_are_no_reading() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.png");
        let raw: Vec<u16> = vec![0, 1000, 65535, 65534];
        ImageBuffer::<Luma<u16>, Vec<u16>>::from_raw(4, 1, raw)
            .unwrap()
            .save(&path)
            .unwrap();
        let d = read_depth_png(&path, 1000.0).unwrap();
        assert_eq!(d.data, vec![0.0, 1.0, 0.0, 65534.0 * (1.0f32 / 1000.0)]);
        // Writing never produces the marker for a real depth: 65.535 m at scale 1000 is out of
        // range and written as 0.
        let out = dir.path().join("w.png");
        let far = DepthImage {
            width: 2,
            height: 1,
            data: vec![65.535, 65.534],
        };
        write_depth_png(&out, &far, 1000.0).unwrap();
        let back = read_depth_png(&out, 1000.0).unwrap().data;
        assert_eq!(back, vec![0.0, 65534.0 * (1.0f32 / 1000.0)]);
    }

    #[test]
    fn image_folder_without_lists() {
        let dir = tempfile::tempdir().unwrap();
        let rgb = dir.path().join("rgb");
        fs::create_dir(&rgb).unwrap();
        for name in ["b.png", "a.png", "c.jpg"] {
            RgbImage::new(8, 6).save(rgb.join(name)).unwrap();
        }
        fs::write(rgb.join("notes.txt"), "not an image").unwrap();
        let seq = Sequence::open(dir.path()).unwrap();
        assert_eq!(seq.len(), 3);
        assert!(seq.frames[0].rgb.ends_with("a.png"));
        assert!((seq.frames[2].timestamp - 2.0 / 30.0).abs() < 1e-12);
        assert!(!seq.has_ground_truth());
        assert_eq!(seq.load_rgb(1).unwrap().dimensions(), (8, 6));
        // the folder itself also works
        assert_eq!(Sequence::open(&rgb).unwrap().len(), 3);

        let webcam = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../shared/data/webcam_classroom"
        );
        if present(webcam) {
            assert_eq!(Sequence::open(Path::new(webcam)).unwrap().len(), 220);
        }
    }

    #[test]
    fn bad_intrinsics_and_depth_format() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("rgb.txt"), "0.0 a.png\n").unwrap();
        fs::write(dir.path().join("intrinsics.txt"), "# c\n500 500 320\n").unwrap();
        let err = Sequence::open(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("intrinsics.txt` line 2: expected 5 numbers"),
            "{err}"
        );
        fs::write(dir.path().join("intrinsics.txt"), "500 500 320 240 abc\n").unwrap();
        let err = Sequence::open(dir.path()).unwrap_err().to_string();
        assert!(err.contains("`abc` is not a finite number"), "{err}");
        // an 8-bit image where a 16-bit depth PNG is expected
        let p = dir.path().join("d8.png");
        image::GrayImage::new(4, 4).save(&p).unwrap();
        let err = read_depth_png(&p, 1000.0).unwrap_err().to_string();
        assert!(err.contains("16-bit"), "{err}");
        assert!(read_depth_png(&dir.path().join("none.png"), 1000.0).is_err());
    }

    #[test]
    fn unmatched_frames_dropped_or_kept() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(
            dir.path().join("rgb.txt"),
            "0.00 a.png\n0.10 b.png\n0.20 c.png\n",
        )
        .unwrap();
        fs::write(dir.path().join("depth.txt"), "0.005 da.png\n0.19 dc.png\n").unwrap();
        let seq = Sequence::open(dir.path()).unwrap();
        assert_eq!(seq.timestamps(), vec![0.0, 0.2]);
        assert!(seq.frames[1].depth.as_ref().unwrap().ends_with("dc.png"));
        let all = Sequence::open_with(
            dir.path(),
            &OpenOptions {
                drop_unmatched: false,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(all.len(), 3);
        assert!(all.frames[1].depth.is_none());
    }

    #[test]
    fn bad_groundtruth_line_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("rgb.txt"), "# c\n0.0 rgb/a.png\n").unwrap();
        fs::write(
            dir.path().join("groundtruth.txt"),
            "# c\n0.0 0 0 0 0 0 0 1\n0.1 1 2 3 4\n",
        )
        .unwrap();
        let err = Sequence::open(dir.path()).unwrap_err().to_string();
        assert!(err.contains("groundtruth.txt` line 3"), "{err}");
        assert!(err.contains("expected 8 numbers"), "{err}");
        assert!(err.contains("got 5"), "{err}");
    }

    #[test]
    fn missing_directory_and_rgb() {
        let err = Sequence::open(Path::new("/nonexistent/leangate")).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/leangate"));
        let dir = tempfile::tempdir().unwrap();
        let err = Sequence::open(dir.path()).unwrap_err().to_string();
        assert!(err.contains("rgb.txt"), "{err}");
    }

    #[test]
    fn association_nearest_within_tolerance() {
        let list = vec![(0.0, 'a'), (0.033, 'b'), (0.066, 'c')];
        assert_eq!(nearest(&list, 0.030, 0.02), Some(1));
        assert_eq!(nearest(&list, 0.050, 0.02), Some(2));
        assert_eq!(nearest(&list, 0.2, 0.02), None);
        assert_eq!(nearest(&list, -0.01, 0.02), Some(0));
    }

    #[test]
    fn write_and_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let intr = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 15.5,
            cy: 11.5,
            depth_scale: 1000.0,
        };
        let mut frames = Vec::new();
        for i in 0..3 {
            let rgb = RgbImage::from_fn(32, 24, |x, y| image::Rgb([x as u8, y as u8, i as u8]));
            let mut d = DepthImage::new(32, 24);
            for (k, v) in d.data.iter_mut().enumerate() {
                *v = if k % 7 == 0 {
                    0.0
                } else {
                    1.0 + k as f32 * 0.001
                };
            }
            let pose = Isometry3::new(
                nalgebra::Vector3::new(i as f64, 0.5, -0.25),
                nalgebra::Vector3::new(0.1, 0.2 * i as f64, 0.3),
            );
            frames.push((i as f64 / 30.0, rgb, Some(d), Some(pose)));
        }
        let root = dir.path().join("seq");
        write_sequence_files(&root, intr, RgbFormat::Png, &frames).unwrap();
        let seq = Sequence::open(&root).unwrap();
        assert_eq!(seq.len(), 3);
        assert!(seq.has_ground_truth());
        assert_eq!(seq.intrinsics, Some(intr));
        for (i, frame) in frames.iter().enumerate() {
            assert_eq!(seq.load_rgb(i).unwrap(), frame.1);
            let d = seq.load_depth_m(i).unwrap();
            let orig = frame.2.as_ref().unwrap();
            for (a, b) in d.data.iter().zip(&orig.data) {
                assert!((a - b).abs() < 0.0006, "{a} {b}");
            }
            let p = seq.frames[i].pose.unwrap();
            let q = frame.3.unwrap();
            assert!((p.inverse() * q).translation.vector.norm() < 1e-6);
            assert!((p.inverse() * q).rotation.angle() < 1e-6);
        }
    }
}
