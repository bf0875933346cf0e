//! The `leangatedepthmux` element: puts a depth stream beside a colour stream, the GStreamer way.
//!
//! An aggregator with two always sink pads, `sink` (colour, any raw video) and `depth`
//! (GRAY16_LE or GRAY32F), and one src pad that carries the colour stream unchanged but for a
//! [`crate::depth`] `LeanGateDepthMeta` on each colour buffer that a depth frame matched (nearest
//! running time within `max-skew`). `leangate` downstream then gates with depth; a colour frame
//! that no depth frame matched passes without the meta and is gated colour-only.

use gst::glib;
use gst::prelude::*;

mod imp;

glib::wrapper! {
    pub struct DepthMux(ObjectSubclass<imp::DepthMux>)
        @extends gst_base::Aggregator, gst::Element, gst::Object;
}

pub fn register(plugin: &gst::Plugin) -> Result<(), glib::BoolError> {
    gst::Element::register(
        Some(plugin),
        "leangatedepthmux",
        gst::Rank::NONE,
        DepthMux::static_type(),
    )
}
