//! The heap counter (`visnav_daemon::heap::CountingAlloc`, the `visnav` binary's global
//! allocator) follows allocations and frees, including growth by `realloc`, and keeps the peak.

#[global_allocator]
static ALLOC: visnav_daemon::heap::CountingAlloc = visnav_daemon::heap::CountingAlloc;

use visnav_daemon::heap::{heap_in_use_bytes, heap_peak_bytes, reset_heap_peak};

#[test]
fn the_heap_counter_follows_allocations_and_frees() {
    // Other test threads allocate too: compare with a margin far below the 64 MB moved here.
    const MB64: usize = 64 << 20;
    let before = heap_in_use_bytes().expect("installed");
    let mut v: Vec<u8> = Vec::with_capacity(MB64 / 2);
    v.resize(MB64 / 2, 1);
    v.reserve_exact(MB64); // realloc to 96 MB
    let grown = heap_in_use_bytes().expect("installed");
    assert!(
        grown >= before + MB64 + MB64 / 2 - (4 << 20),
        "{before} -> {grown}"
    );
    drop(v);
    let after = heap_in_use_bytes().expect("installed");
    assert!(
        after < before + (4 << 20),
        "{before} -> {after} after the free"
    );
    // The peak saw the 96 MB (and the 32 MB block beside it during the realloc), freed or not.
    let peak = heap_peak_bytes().expect("installed");
    assert!(
        peak >= before + MB64 + MB64 / 2,
        "peak {peak}, before {before}"
    );
    reset_heap_peak();
    let reset = heap_peak_bytes().expect("installed");
    assert!(reset < before + (4 << 20), "peak {reset} after the reset");
}
