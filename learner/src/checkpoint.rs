//! The DQN and replay side of checkpoints; the format itself (files, checksums, atomic
//! renames) is [`crawler_run::checkpoint`], which links no libtorch.

use std::io::{BufReader, Write};
use std::path::{Path, PathBuf};

pub use crawler_run::checkpoint::{
    CHECKPOINT_FORMAT, Checkpoint, CheckpointError, CheckpointMeta, FileDigest, FileWriter, MAX_COUNTER, Progress,
    Snapshot, corrupt, latest, list, load,
};

use crate::algo::dqn::Dqn;
use crate::algo::network::{ParameterCountError, QNetwork};
use crate::replay::{Replay, ReplayConfig, SnapshotBounds};
use crawler_run::config::TrainConfig;

/// The network's weights as safetensors bytes named as PyTorch's `state_dict` (what the
/// learner broadcasts and what `weights.safetensors` holds).
pub fn encode_weights(network: &QNetwork) -> Vec<u8> {
    crawler_run::checkpoint::encode_weights(network.spec(), &network.flat_values())
}

/// Writes a checkpoint of `dqn` (and `replay`, when given) under `dir` and keeps the newest
/// `keep` of them.
pub fn save(
    dir: &Path,
    dqn: &Dqn,
    run_id: &str,
    progress: &Progress,
    config: &serde_json::Value,
    replay: Option<&Replay>,
    keep: usize,
) -> Result<PathBuf, CheckpointError> {
    let write_replay = |mut writer: &mut dyn Write| match replay {
        Some(replay) => bincode::serde::encode_into_std_write(replay, &mut writer, bincode::config::standard())
            .map(drop)
            .map_err(std::io::Error::other),
        None => Ok(()),
    };
    let (online, target) = (dqn.online.flat_values(), dqn.target.flat_values());
    // Adam's moments lie like the parameter buffer; checkpoints hold PyTorch's layout.
    let exp_avg = dqn.online.to_torch_order(&dqn.optimizer.exp_avg);
    let exp_avg_sq = dqn.online.to_torch_order(&dqn.optimizer.exp_avg_sq);
    let snapshot = Snapshot {
        network: &dqn.network,
        online: &online,
        target: &target,
        exp_avg: &exp_avg,
        exp_avg_sq: &exp_avg_sq,
        adam_step: dqn.optimizer.step,
        replay: replay.is_some().then_some(&write_replay as FileWriter<'_>),
    };
    crawler_run::checkpoint::save(dir, &snapshot, run_id, progress, config, keep)
}

/// What a resumed run's replay must be: its configuration, its observation width, and the
/// values ingest would have let in.
#[derive(Debug, Clone, Copy)]
pub struct ReplayExpectation<'a> {
    pub config: &'a ReplayConfig,
    pub obs_dim: usize,
    pub bounds: &'a SnapshotBounds,
}

impl ReplayExpectation<'_> {
    /// The most bytes such a replay's snapshot takes: per slot its observation, the
    /// transition's fields at their widest varints and two sum-tree nodes, plus one pending
    /// stream per slot at most.
    fn most_bytes(&self) -> u64 {
        let per_slot = self.obs_dim as u64 * 4 + 128;
        (self.config.capacity as u64).saturating_mul(per_slot).saturating_add(1 << 20)
    }
}

/// Reads the replay snapshot of a checkpoint, if it has one and it was taken with `expected`'s
/// configuration (None otherwise: the run then starts an empty replay), and checks every
/// record in it as ingest checks the wire's.
pub fn load_replay(
    checkpoint: &Checkpoint,
    expected: &ReplayExpectation<'_>,
) -> Result<Option<Replay>, CheckpointError> {
    let Some((path, bytes)) = crawler_run::checkpoint::replay_bytes(checkpoint, expected.most_bytes())? else {
        return Ok(None);
    };
    let reader = BufReader::new(bytes.as_slice());
    let mut replay: Replay = bincode::serde::decode_from_std_read(&mut { reader }, bincode::config::standard())
        .map_err(|e| CheckpointError::ReplayLayout { path: path.clone(), reason: e.to_string() })?;
    if replay.config() != *expected.config || replay.obs_dim() != expected.obs_dim {
        return Ok(None);
    }
    replay
        .check_snapshot(expected.config, expected.obs_dim, expected.bounds)
        .map_err(|reason| CheckpointError::ReplayContent { path, reason })?;
    Ok(Some(replay))
}

/// [`load_replay`] for a run of `config`: the replay it configures, the values its ingest
/// lets in.
pub fn load_replay_for(checkpoint: &Checkpoint, config: &TrainConfig) -> Result<Option<Replay>, CheckpointError> {
    let bounds = SnapshotBounds::from(&crate::service::transition_limits(config, &checkpoint.meta.run_id));
    let expected =
        ReplayExpectation { config: &config.replay, obs_dim: config.env.policy_input_dim(), bounds: &bounds };
    load_replay(checkpoint, &expected)
}

impl Dqn {
    /// Copies the online and target networks of `checkpoint` (another run's, for transfer);
    /// the optimiser and the update count stay fresh. The network spec must match.
    pub fn initialise_from(&mut self, checkpoint: &Checkpoint) -> Result<(), CheckpointError> {
        self.check_network(checkpoint)?;
        let bad = |e: ParameterCountError| corrupt(&checkpoint.path, e);
        self.online.load_flat(&checkpoint.online).map_err(bad)?;
        self.target.load_flat(&checkpoint.target).map_err(bad)?;
        Ok(())
    }

    fn check_network(&self, checkpoint: &Checkpoint) -> Result<(), CheckpointError> {
        if checkpoint.meta.network != self.network {
            return Err(CheckpointError::Mismatch {
                path: checkpoint.path.clone(),
                what: "network",
                found: format!("{:?}", checkpoint.meta.network),
                expected: format!("{:?}", self.network),
            });
        }
        Ok(())
    }

    /// Restores weights, target and optimiser state from `checkpoint`. The network spec must
    /// match this learner's.
    pub fn restore(&mut self, checkpoint: &Checkpoint) -> Result<(), CheckpointError> {
        self.initialise_from(checkpoint)?;
        // The loader checked both moments' lengths against the network.
        self.optimizer.exp_avg = self.online.from_torch_order(&checkpoint.exp_avg);
        self.optimizer.exp_avg_sq = self.online.from_torch_order(&checkpoint.exp_avg_sq);
        self.optimizer.step = checkpoint.meta.adam_step;
        self.updates = checkpoint.meta.progress.updates;
        Ok(())
    }
}
