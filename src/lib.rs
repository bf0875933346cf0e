//! LeanGate: geometric-utility frame gating for monocular SLAM, as a GStreamer plugin.
