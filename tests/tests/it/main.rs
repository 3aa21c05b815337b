//! Integration tests that run the real binaries on loopback, one test binary for all of
//! them (libtorch links once):
//! - [`distributed`]: training, resume, actors joining and leaving;
//! - [`faults`]: SIGKILL of actors and learners, a kill inside a checkpoint write, garbage;
//! - [`outputs`]: metrics files, plots, the GIF, eval, transfer, the MuJoCo cross-check;
//! - [`security`]: mutual TLS and the access-control policy under attack;
//! - [`docker`]: the compose deployments, and [`swarm`]: the Swarm stack (`#[ignore]`d;
//!   scripts/test runs them where an engine answers, with `-- --ignored docker:: swarm::`).

mod distributed;
mod docker;
mod faults;
mod outputs;
mod security;
mod swarm;

/// The replay snapshot of a checkpoint a learner of this workspace wrote, checked against the
/// run's own config.
pub(crate) fn replay_of(
    checkpoint: &crawler_learner::checkpoint::Checkpoint,
) -> Result<Option<crawler_learner::replay::Replay>, crawler_learner::checkpoint::CheckpointError> {
    let config = crawler_run::config::TrainConfig::from_json(&checkpoint.meta.config, "the checkpoint's config", &[])
        .map_err(|e| crawler_learner::checkpoint::corrupt(&checkpoint.path, e))?;
    crawler_learner::checkpoint::load_replay_for(checkpoint, &config)
}
