//! Heap accounting: [`CountingAlloc`] wraps the system allocator and counts the bytes the
//! process holds on its heap (what was allocated and not yet freed, as requested: the
//! allocator's own overhead and fragmentation are not in it, the resident set size has them).
//! The `visnav` binary installs it as the global allocator; [`heap_in_use_bytes`] reads the
//! count (`None` where it is not installed, e.g. in a library's tests). It costs one relaxed
//! atomic add per allocation. The soak scenario reports the daemons' heap growth with it
//! (docs/closed-loop.md), and `visnav_heap_bytes` exports it.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

static IN_USE: AtomicUsize = AtomicUsize::new(0);
/// The largest `IN_USE` since the start or the last [`reset_heap_peak`].
static PEAK: AtomicUsize = AtomicUsize::new(0);

/// Adds `size` to the count and raises the peak.
fn add(size: usize) {
    let now = IN_USE.fetch_add(size, Ordering::Relaxed).wrapping_add(size);
    PEAK.fetch_max(now, Ordering::Relaxed);
}
static INSTALLED: AtomicBool = AtomicBool::new(false);

/// The system allocator, counting the bytes in use (see the module doc).
pub struct CountingAlloc;

// SAFETY: every call is forwarded to `System` with the caller's arguments unchanged; the
// counter is bookkeeping only.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded (the caller upholds `alloc`'s contract).
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            INSTALLED.store(true, Ordering::Relaxed);
            add(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            INSTALLED.store(true, Ordering::Relaxed);
            add(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded (`ptr` came from this allocator with `layout`).
        unsafe { System.dealloc(ptr, layout) };
        IN_USE.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            // The old block is freed and a new one of `new_size` held.
            add(new_size);
            IN_USE.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        p
    }
}

/// The most bytes held on the heap at once since the start or the last [`reset_heap_peak`]
/// (a `realloc` counts both blocks for an instant), when [`CountingAlloc`] is installed: what the
/// resident set must at least have held, freed or not.
pub fn heap_peak_bytes() -> Option<usize> {
    INSTALLED
        .load(Ordering::Relaxed)
        .then(|| PEAK.load(Ordering::Relaxed))
}

/// Starts a new peak at the bytes in use now.
pub fn reset_heap_peak() {
    PEAK.store(IN_USE.load(Ordering::Relaxed), Ordering::Relaxed);
}

/// Bytes on the heap now, when [`CountingAlloc`] is the global allocator.
pub fn heap_in_use_bytes() -> Option<usize> {
    INSTALLED
        .load(Ordering::Relaxed)
        .then(|| IN_USE.load(Ordering::Relaxed))
}
