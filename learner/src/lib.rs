//! The learner side of crawler: replay, the libtorch Double DQN and the learner process.
//!
//! Three layers, each its own module tree:
//! - the algorithm, [`algo`]: the Q-network on one flat buffer, fused Adam, the Double DQN
//!   update; [`replay`]: the ring that stores each observation once, n-step returns, its
//!   samplers (uniform, prioritised); [`rate`]: the samples-per-insert limiter; [`table`]:
//!   replay and the limiter under one lock, shared by the inserting and training threads;
//! - the process, [`service`]: the embedded zenoh router and its access control, the
//!   receive path (`service::edge`), the inserting thread (`service::inserter`), the training
//!   thread (`service::trainer`), status and
//!   metrics (`service::telemetry`);
//! - persistence, [`checkpoint`]: the DQN and replay glue over `crawler_run::checkpoint`.
//!
//! Everything about a run that needs no libtorch (its config, the checkpoint format, metrics
//! files, evaluation and plots) is the `crawler-run` crate.

pub mod algo;
pub mod checkpoint;
pub mod rate;
pub mod replay;
pub mod service;
pub mod table;

/// Sets libtorch's intra-op threads. Use 1 unless the learner owns the machine: with two
/// OpenMP threads, updates collapse from ~500/s to under 70/s as soon as anything else needs
/// a core.
pub fn set_torch_threads(threads: usize) {
    tch::set_num_threads(threads.max(1) as i32);
}
/// Keeps large freed blocks in glibc's heap instead of returning them to the OS at once.
///
/// Each DQN update allocates and frees several tensors of the network's size (760 KB for the
/// study's); above glibc's default 128 KiB threshold each one is a fresh `mmap`, and every
/// page of it faults in again. Raising the thresholds makes an update 1.5x faster (2.05 → 1.33
/// ms at batch 32 on one thread). Freed memory held back this way stays below 256 MiB.
/// Call once at start-up; a no-op off glibc.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[allow(unsafe_code)]
    // SAFETY: mallopt only sets glibc allocator parameters; it takes the allocator's own lock
    // and is sound to call from any thread at any time.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
    }
}
