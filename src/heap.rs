//! Heap settings for the processes that run the engine.
//!
//! An erase allocates and frees vectors of tens of megabytes many times:
//! work vectors, Galerkin rows, factors, images. glibc serves each of them
//! with a fresh `mmap` and returns it with `munmap`, so the kernel zeroes
//! every page again on its first touch; on Fox that was 15% of the erase's
//! CPU time. Served from the heap and kept mapped once freed, later vectors
//! reuse pages that are already there. The cost is that a process keeps its
//! high-water mark: a service's worker gives it back with
//! [`release_freed_memory`] when it runs out of jobs, not after each one
//! (back to back, jobs reuse each other's pages). With these settings
//! `cargo bench --bench service` (16 clients on blub and BoxTextured, two
//! workers) went from 174 to 188 jobs a minute, and the server's peak from
//! 1323 to 1050 MiB: one heap shared by all threads also fragments less.
//!
//! All threads share the one heap. Each of rayon's threads would otherwise get
//! an arena of its own, built from 64 MB mmap'd heaps that glibc unmaps as
//! soon as they empty, whatever the trim threshold, and serves larger blocks
//! with plain `mmap` even with mmap disabled: vectors made inside a
//! `rayon::join` came back as fresh pages on every use (17 munmaps in an erase
//! of Fox, 2 with one arena; erase 1257 → 1094 ms, median of six interleaved
//! runs). A first touch costs 0.4–1 µs a page on this kind of virtual machine.
//!
//! Kept mapped, freed blocks become holes that a later block of another
//! size may not fit, so a job's peak lies above the memory it has in use at
//! any one time, by as much as the threads' interleaving happens to leave:
//! over four runs each, Fox 641–653 MiB, WaterBottle 689–746,
//! blub_atlas_black 1044–1115. Handing the free pages back after each band's
//! solve and after the erase kept the peak at the memory in use (Fox
//! 596–603, WaterBottle 646–666), but every page touched again then cost a
//! fault, and on huge pages a whole 2 MiB page zeroed again: 280 000 faults
//! on Fox instead of 38 000, and 10% of the job's wall time (Fox 3.89 →
//! 3.37 s, WaterBottle 6.66 → 5.91 s, blub_atlas_dilated with mips 10.66
//! → 9.73 s, medians of interleaved runs). A farm feels the time, and the
//! budget's estimate (`cargo bench --bench erase -- budget`) still lies
//! above the peak of every erase-bound model. So a job keeps its pages, and
//! a worker gives back what is left when it runs out of jobs.

/// The process's allocator: the system's, with the pages of large blocks
/// backed by transparent huge pages where the kernel offers them on request
/// (`madvise` mode, as here).
///
/// A first touch of a 4 KiB page costs a fault of about a microsecond on
/// this kind of virtual machine, most of it bookkeeping rather than zeroing:
/// Fox's job took 280 000 of them, 11% of its CPU time. A 2 MiB page costs
/// one fault for 512 of them, and the solver's vectors, walked again and
/// again, then miss the TLB far less.
pub struct HugePageAlloc;

/// A transparent huge page on x86-64 and most arm64 kernels.
const HUGE_PAGE: usize = 2 << 20;

/// `p`, a block of `size` bytes (or null), with huge pages asked for under
/// the whole huge pages inside it: only those, so a block never shares one
/// with its neighbours, and none for a block smaller than one.
fn advise_huge(p: *mut u8, size: usize) -> *mut u8 {
    #[cfg(target_os = "linux")]
    if size >= HUGE_PAGE && !p.is_null() {
        let start = (p as usize).next_multiple_of(HUGE_PAGE);
        let end = (p as usize).saturating_add(size) / HUGE_PAGE * HUGE_PAGE;
        if end > start {
            // SAFETY: the range lies inside a block the allocator just
            // handed out; the advice changes only how its pages are backed.
            // A kernel without huge pages refuses it, which changes nothing.
            unsafe {
                libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = size;
    p
}

// SAFETY: every call is passed to `System` unchanged; the advice touches no
// byte of a block.
unsafe impl std::alloc::GlobalAlloc for HugePageAlloc {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: forwarded with the caller's guarantees.
        advise_huge(unsafe { std::alloc::System.alloc(layout) }, layout.size())
    }

    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: forwarded with the caller's guarantees.
        advise_huge(
            unsafe { std::alloc::System.alloc_zeroed(layout) },
            layout.size(),
        )
    }

    unsafe fn dealloc(&self, p: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: forwarded with the caller's guarantees.
        unsafe { std::alloc::System.dealloc(p, layout) }
    }

    unsafe fn realloc(&self, p: *mut u8, layout: std::alloc::Layout, size: usize) -> *mut u8 {
        // SAFETY: forwarded with the caller's guarantees.
        advise_huge(unsafe { std::alloc::System.realloc(p, layout, size) }, size)
    }
}

/// Serves large allocations from one heap for all threads and keeps freed
/// memory mapped.
/// Call once, first thing in `main`.
pub fn retain_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; it is called before
    // any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

/// Returns the heap's free pages to the system: when a worker runs out of
/// jobs (a job keeps its own, see the module docs).
pub fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim takes the allocator's own locks; any thread may call it.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// The process's resident memory in MiB (0 where /proc is not available),
/// for the solver's debug log: on a fresh process each new page costs a
/// fault, so memory is time.
pub fn resident_mb() -> u64 {
    status_kb("VmRSS:") >> 10
}

/// The process's peak resident memory so far in MiB (the kernel's
/// high-water mark; 0 where /proc is not available), for the stage logs.
pub fn peak_resident_mb() -> u64 {
    status_kb("VmHWM:") >> 10
}

/// A `kB` line of /proc/self/status.
fn status_kb(key: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix(key))?
                .trim()
                .trim_end_matches("kB")
                .trim()
                .parse()
                .ok()
        })
        .unwrap_or(0)
}

/// `n` copies of `value`, written by all of rayon's threads.
///
/// The first write to a fresh page costs a page fault (about a microsecond
/// here), so a large vector's first pass is mostly faults, and spread over
/// the threads they are taken side by side. It also keeps a vector's first
/// touch a write: `vec![0.0; n]` may leave its pages unmapped, a read then
/// maps the shared zero page, and the write after it costs a second fault
/// and a TLB flush on every core (the first V-cycle's Gauss–Seidel on a
/// fresh vector spent 5% of Fox's CPU time there).
pub fn filled<T: Copy + Send + Sync>(n: usize, value: T) -> Vec<T> {
    use rayon::prelude::*;
    let mut v = Vec::with_capacity(n);
    v.par_extend(rayon::iter::repeat_n(value, n));
    v
}

/// A copy of `src`, written by all of rayon's threads (see [`filled`]).
pub fn copied<T: Copy + Send + Sync>(src: &[T]) -> Vec<T> {
    use rayon::prelude::*;
    let mut v = Vec::with_capacity(src.len());
    v.par_extend(src.par_iter().copied());
    v
}
