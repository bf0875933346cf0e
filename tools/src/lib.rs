//! LeanGate's tools, beside the plugin crate: everything that needs ground truth or renders data.
//!
//! - [`args`]: the command line's value parsers (every numeric argument checked at parse time);
//! - [`dataset`]: RGB-D sequences in the TUM layout (and plain image folders and video files);
//! - [`teacher`]: the exact geometric keyframe score (MASt3R-SLAM's `S = min(f_m, f_u)`) from depth
//!   and poses — the oracle that labels training pairs and judges every gate;
//! - [`synth`]: procedural RGB-D indoor scenes with human-like camera paths;
//! - [`geometry`]: the element's geometric prior on labelled pairs (for fitting its fusion);
//! - [`eval`]: runs the real element and the baselines over a sequence and judges them;
//! - [`output`]: the files they write, whole or not at all.
//!
//! The `leangate` binary (`synth`, `label`, `eval`) is the command-line face of these modules.
//! The gate, scorer, preprocessing and meta come from the plugin crate (`gstleangate`), so the
//! tools judge exactly the code the element runs.

pub mod args;
pub mod dataset;
pub mod eval;
pub mod geometry;
pub mod output;
pub mod synth;
pub mod teacher;
