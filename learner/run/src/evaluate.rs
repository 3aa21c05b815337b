//! Greedy episodes of a checkpoint's policy, shared by `eval`, `plot` and `render`.
//!
//! The policy runs in plain Rust (the actors' [`MlpPolicy`]) over the checkpoint's weights,
//! so evaluation measures exactly what actors would do.

use std::path::{Path, PathBuf};

use crawler_env::observation::{stack_first, stack_next};
use crawler_env::policy::{MlpPolicy, PolicyError};
use crawler_env::{Crawler, EnvConfig, EpisodeSummary, OBS_DIM, PoseFrame, Randomization};

use crate::checkpoint::{self, CheckpointError, CheckpointMeta};
use crate::config::{ConfigError, TrainConfig};

/// The first seed of an evaluation: episode i uses `EVAL_SEED + i` (`eval`'s default, and
/// what the best-checkpoint keeper uses, so `eval` reproduces its numbers).
pub const EVAL_SEED: u64 = 1_000_000;
/// An episode slower than this (m/s) is stuck: the crawler barely moved.
pub const STUCK_SPEED: f32 = 0.05;

/// Whether an episode failed: it got stuck or its base turned over. The one definition that
/// `eval`'s `failed_episodes`, the best-checkpoint keeper and `pick` count.
pub fn episode_failed(speed: f32, flips: u32) -> bool {
    speed < STUCK_SPEED || flips > 0
}

#[derive(Debug, thiserror::Error)]
pub enum EvaluateError {
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("the checkpoint's weights do not fit its network: {0}")]
    Policy(#[from] PolicyError),
    #[error("{seconds} s is not a usable episode length at dt = {dt} s")]
    EpisodeLength { seconds: f32, dt: f32 },
    #[error("the policy chose no action")]
    NoAction,
    #[error(
        "the checkpoint's network takes {network} inputs, but its env (with the overrides) makes {env}: \
         env.observation_history must stay the one it was trained with"
    )]
    InputMismatch { network: usize, env: usize },
}

/// A checkpoint ready to act: its config (with overrides applied) and its greedy policy.
#[derive(Debug)]
pub struct LoadedPolicy {
    pub path: PathBuf,
    pub meta: CheckpointMeta,
    pub config: TrainConfig,
    pub policy: MlpPolicy,
}

/// Loads `path` (a `step-…` directory, or a directory of them: the newest) and applies
/// `overrides` (`KEY=VALUE`, e.g. `env.direction=backward`) to its stored config.
pub fn load_policy(path: &Path, overrides: &[String]) -> Result<LoadedPolicy, EvaluateError> {
    let loaded = checkpoint::load(path)?;
    let config = TrainConfig::from_json(&loaded.meta.config, "the checkpoint's config", overrides)?;
    let weights_path = loaded.path.join("weights.safetensors");
    let weights =
        std::fs::read(&weights_path).map_err(|source| EvaluateError::Io { path: weights_path.clone(), source })?;
    let policy = MlpPolicy::from_safetensors(&weights, &loaded.meta.network)?;
    let (network, env) = (loaded.meta.network.obs_dim, config.env.policy_input_dim());
    if network != env {
        return Err(EvaluateError::InputMismatch { network, env });
    }
    Ok(LoadedPolicy { path: loaded.path, meta: loaded.meta, config, policy })
}

/// The env of `config` set to run exactly `seconds` of simulated time on the nominal physics:
/// neither the progress rule nor a fall (`max_tilt_deg`) cuts an evaluation episode short, so
/// that falls are counted as flips and their cost shows in the speed, and the training's
/// physics randomisation is off (`eval --perturbed` states its own), so that a number means
/// the same robot whatever preset trained the policy.
pub fn evaluation_env(config: &EnvConfig, seconds: f32) -> Result<EnvConfig, EvaluateError> {
    let steps = (seconds / config.dt).round();
    if !(steps >= 1.0 && steps <= u32::MAX as f32) {
        return Err(EvaluateError::EpisodeLength { seconds, dt: config.dt });
    }
    let mut env = config.clone();
    env.max_episode_steps = steps as u32;
    env.min_episode_steps = steps as u32;
    env.max_tilt_deg = 180.0;
    env.randomization = Randomization::default();
    Ok(env)
}

/// One greedy (ε = 0) episode from the start pose drawn with `seed`; with `record`, every
/// physics step's pose.
pub fn greedy_episode(
    policy: &MlpPolicy,
    env: &EnvConfig,
    seed: u64,
    record: bool,
) -> Result<(EpisodeSummary, Vec<PoseFrame>), EvaluateError> {
    let mut crawler = Crawler::new(env.clone(), seed);
    crawler.set_recording(record);
    let mut frame = [0.0f32; OBS_DIM];
    // The policy's input: the last `observation_history` observations, newest first.
    let mut input = vec![0.0f32; env.policy_input_dim()];
    let mut previous = input.clone();
    let mut actions = Vec::with_capacity(1);
    crawler.observe(&mut frame);
    stack_first(&frame, &mut input);
    loop {
        policy.greedy_actions(&input, &mut actions)?;
        let action = *actions.first().ok_or(EvaluateError::NoAction)?;
        let outcome = crawler.step(action);
        if outcome.done() {
            let summary = crawler.episode_summary(Some(outcome));
            return Ok((summary, crawler.recorded_frames().to_vec()));
        }
        std::mem::swap(&mut input, &mut previous);
        crawler.observe(&mut frame);
        stack_next(&previous, &frame, &mut input);
    }
}
