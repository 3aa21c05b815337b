//! The learner side of crawler: replay, the libtorch Double DQN, checkpoints and metrics.
//!
//! - [`network`]: the Q-network, every parameter a view into one flat buffer.
//! - [`adam`]: Adam over that buffer, the arithmetic of `torch.optim.Adam`.
//! - [`dqn`]: TD targets (Double or vanilla), loss, target-network upkeep.
//! - [`replay`]: the ring buffer (each observation stored once), n-step returns, PER.
//! - [`rate`]: the samples-per-insert limiter.
//! - [`checkpoint`]: atomic, checksummed checkpoints; [`config`]: the TOML presets.
//! - [`service`]: the learner process (router, ingest, training thread, weights).
//! - [`access_control`]: the router's zenoh ACL for runs served over mutual TLS.
//! - [`metrics`]: TensorBoard event files and `metrics.csv`.
//! - [`evaluate`], [`viz`]: greedy episodes, plots and the gait animation.

pub mod access_control;
pub mod adam;
pub mod checkpoint;
pub mod config;
pub mod dqn;
pub mod evaluate;
pub mod memory;
pub mod metrics;
pub mod network;

/// Sets libtorch's intra-op threads. Use 1 unless the learner owns the machine: with two
/// OpenMP threads, updates collapse from ~500/s to under 70/s as soon as anything else needs
/// a core.
pub fn set_torch_threads(threads: usize) {
    tch::set_num_threads(threads.max(1) as i32);
}
pub mod rate;
pub mod replay;
pub mod service;
pub mod sum_tree;
pub mod viz;

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
