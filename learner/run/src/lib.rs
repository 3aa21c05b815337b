//! A crawler run as files, and the tools that read them, all without libtorch.
//!
//! - [`config`]: the TOML presets and `--set` overrides, validated with the key named.
//! - [`checkpoint`]: the checkpoint format: safetensors weights with PyTorch names, optimiser
//!   state, an optional opaque replay snapshot, `meta.json` with sizes and CRC-32s; atomic.
//! - [`metrics`]: TensorBoard event files and `metrics.csv`, written and read.
//! - [`evaluate`]: a checkpoint as a plain-Rust policy, and greedy episodes of it.
//! - [`average`]: the weight average of a run's newest checkpoints, as `checkpoints/average`.
//! - [`best`]: the best checkpoint by greedy evaluation, kept as `checkpoints/best`.
//! - [`pick`]: the checkpoint to ship among a run's candidates, by perturbed evaluation.
//! - [`viz`]: learning-curve charts (PNG) and side views of the gait (GIF).
//! - [`memory`]: the machine's memory, so a replay it cannot hold is refused up front.
//!
//! The `eval`, `average`, `pick`, `plot` and `render` binaries are thin front ends over these. The learner
//! (`crawler-learner`) writes runs through this crate and adds only what needs libtorch.

pub mod average;
pub mod best;
pub mod checkpoint;
pub mod config;
pub mod evaluate;
pub mod memory;
pub mod metrics;
pub mod pick;
pub mod viz;
