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
//! Kept mapped, though, freed blocks become holes that a later block of
//! another size may not fit, and the process's peak then depends on where
//! the threads' interleaving happened to put each block: blub's job peaked
//! anywhere in 599–652 MiB with 445 MiB in use at most. So a job hands its
//! free pages back ([`release_freed_memory`]) where one working set ends
//! and a differently shaped one begins: after each band's system is solved
//! and after the erase (the encoding's pieces, decodings among them, reuse
//! each other's blocks, and a texture's erase runs beside the encoding of
//! the one before it, so there is no later point where one set ends). The peak
//! then follows the memory in use, which is what the budget can estimate:
//! over 12 runs each, blub 447–451 MiB, Fox 595–601 from 594–666,
//! WaterBottle 639–666 from 686–842, cube_gradient_1024 121–124 from
//! 143–162. The pages touched again are the price:
//! on WaterBottle (four 2048² textures) 535 000 faults instead of 175 000,
//! about 0.5 s more system time over 4.5 s of CPU; on Fox 0.16 s over 3.5.
//! A worker gives back what is left when it runs out of jobs.

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

/// Returns the heap's free pages to the system: between a job's stages, and
/// when a worker runs out of jobs.
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
