//! Memory allocator settings of the `sofipol` process.
//!
//! A night reduction allocates and frees buffers of 0.3-4 MB for every frame (cropped
//! frames, their variance and mask, sky medians, flats' rows). glibc's malloc serves blocks
//! above its mmap threshold (128 kB, raised dynamically up to 32 MB) with fresh `mmap`s
//! and gives them back on `free`, and trims the heap top above 128 kB: every new buffer
//! page-faults all its pages in again. On the 49-target bench night that was ~0.4 CPU-s of
//! kernel time (sys 0.55 s against 0.14 s with the settings below, ~12 % of the night's
//! CPU) for a peak RSS that moves by a few MB (104 -> 110 MB). Growing the heap 64 MB at a
//! time (`M_TOP_PAD`) rather than by what each request needs saves the repeated heap
//! extensions of the worker threads' arenas (each a system call that changes the address
//! space and flushes TLBs on the other core): -4 % CPU, -3 % wall on the bench night
//! (medians of 5, interleaved), peak RSS 146 -> 160 MB.

/// Keep freed memory in the process for reuse: blocks up to 32 MB come from the heap,
/// which grows by at least 64 MB at a time, and up to 256 MB of free heap top is kept.
/// Only on glibc (elsewhere a no-op). Call once, first thing in `main`, before threads
/// start. The one `unsafe` of the binary (the workspace denies unsafe code): a call into
/// glibc with constant arguments.
#[allow(unsafe_code)]
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes malloc's parameters; called before any thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
        libc::mallopt(libc::M_TOP_PAD, 64 << 20);
    }
}
