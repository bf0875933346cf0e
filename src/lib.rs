//! LeanGate: geometric-utility frame gating for monocular SLAM, as a GStreamer plugin.

pub mod dataset;
pub mod synth;
pub mod teacher;
