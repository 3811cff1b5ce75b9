//! `labrig-station`: the operator station (declared in the library: [`labrig_station::StationNode`]).

fn main() -> std::process::ExitCode {
    keep_large_buffers_mapped();
    labrig_runtime::node_main::<labrig_station::StationNode>()
}

/// The station reads each new episode file whole to list it (a few MB, every few seconds over
/// a session). glibc serves a block that large with mmap at first, but raises its threshold to
/// the largest block freed, so the following ones come from the heap, between the list's small
/// long-lived entries, and are never given back: the station grew 2.3 MB an hour over a
/// one-hour soak while its live heap stayed flat (heaptrack: 8.4 MB at 1 minute, 8.9 at 20).
/// A fixed threshold keeps blocks of 256 KB and more mapped, and returned when freed.
#[allow(unsafe_code)]
fn keep_large_buffers_mapped() {
    // SAFETY: mallopt only sets one of glibc's allocator parameters; called first thing in
    // main, before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 256 * 1024);
    }
}
