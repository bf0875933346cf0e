//! Issue 8, D4: the element's own memory must not grow with the number of frames. Before the fix
//! the inference-time statistics kept every sample (8 bytes a frame) and every stats message
//! copied them all. A counting global allocator (Rust allocations only: the plugin's own) measures
//! the live bytes after warm-up and at the end of a long run.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicI64, Ordering};

use common::*;
use gst::prelude::*;

struct Counting;

static LIVE: AtomicI64 = AtomicI64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        LIVE.fetch_add(l.size() as i64, Ordering::Relaxed);
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        LIVE.fetch_sub(l.size() as i64, Ordering::Relaxed);
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        LIVE.fetch_add(new as i64 - l.size() as i64, Ordering::Relaxed);
        unsafe { System.realloc(p, l, new) }
    }
}

#[global_allocator]
static A: Counting = Counting;

#[test]
fn live_memory_is_flat_over_a_long_run() {
    let (w, h) = (16u32, 12u32);
    let mut hs = harness(
        &format!(
            "model={} stats-interval=1 threshold=0.05",
            fixture("mad.onnx")
        ),
        &rgb_caps(w, h),
    );
    let bus = gst::Bus::new();
    hs.element().unwrap().set_bus(Some(&bus));
    let pics: Vec<Vec<u8>> = (0..3).map(|k| texture(w, h, k)).collect();
    let mut run = |from: u64, to: u64| {
        for i in from..to {
            hs.push(buffer(pics[((i / 2) % 3) as usize].clone(), i))
                .unwrap();
            while hs.try_pull().is_some() {}
            while hs.try_pull_event().is_some() {}
            while bus.pop().is_some() {}
        }
    };
    run(0, 5_000);
    let warm = LIVE.load(Ordering::Relaxed);
    run(5_000, 45_000);
    let end = LIVE.load(Ordering::Relaxed);
    assert!(
        end - warm < 64 * 1024,
        "live Rust heap grew by {} bytes over 40,000 frames (warm {warm}, end {end})",
        end - warm
    );
}
