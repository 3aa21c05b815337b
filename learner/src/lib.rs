//! The learner side of crawler: replay, the libtorch Double DQN, checkpoints and metrics.
//!
//! - [`network`]: the Q-network, every parameter a view into one flat buffer.
//! - [`adam`]: Adam over that buffer, the arithmetic of `torch.optim.Adam`.
//! - [`dqn`]: TD targets (Double or vanilla), loss, target-network upkeep.
//! - [`replay`]: the ring buffer (each observation stored once), n-step returns, PER.
//! - [`rate`]: the samples-per-insert limiter.

pub mod adam;
pub mod checkpoint;
pub mod dqn;
pub mod network;

/// Sets libtorch's intra-op threads. Use 1 unless the learner owns the machine: with two
/// OpenMP threads, updates collapse from ~500/s to under 70/s as soon as anything else needs
/// a core.
pub fn set_torch_threads(threads: usize) {
    tch::set_num_threads(threads.max(1) as i32);
}
pub mod rate;
pub mod replay;
pub mod sum_tree;
