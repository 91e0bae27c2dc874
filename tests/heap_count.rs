//! The heap counter (`visnav_daemon::heap::CountingAlloc`, the `visnav` binary's global
//! allocator) follows allocations and frees, including growth by `realloc`.

#[global_allocator]
static ALLOC: visnav_daemon::heap::CountingAlloc = visnav_daemon::heap::CountingAlloc;

use visnav_daemon::heap::heap_in_use_bytes;

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
}
