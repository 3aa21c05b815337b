//! A run's configuration: a TOML preset (see `configs/`) plus `--set key=value` overrides.

use std::path::Path;

use crawler_env::EnvConfig;
use crawler_env::policy::NetworkSpec;
use crawler_env::settings::{ActorSettings, Exploration};
use serde::{Deserialize, Serialize};

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read { path: String, source: std::io::Error },
    #[error("config {origin} is not valid: {message}")]
    Parse { origin: String, message: String },
    #[error("override `{0}` is not KEY=VALUE (e.g. dqn.lr=1e-3)")]
    Override(String),
    #[error("{key} = {value} is invalid: {allowed}")]
    Invalid { key: String, value: String, allowed: String },
    #[error(transparent)]
    Actor(#[from] crawler_env::settings::SettingsError),
    #[error("{what} would need {needed_mib} MiB, more than this machine's {total_mib} MiB of memory: lower {key}")]
    TooLarge { what: &'static str, key: &'static str, needed_mib: u64, total_mib: u64 },
}

/// Hidden layers of the Q-network; its input and output sizes follow from the environment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NetworkSection {
    pub hidden: Vec<usize>,
    pub layer_norm: bool,
}

impl Default for NetworkSection {
    fn default() -> Self {
        Self { hidden: vec![512, 256, 128], layer_norm: true }
    }
}

/// The `[dqn]` section: the Double DQN update and its minibatches. The defaults are the study's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DqnConfig {
    /// Discount factor γ.
    pub gamma: f64,
    /// Adam's learning rate (at the start, where `lr_decay` is set).
    pub lr: f64,
    /// Anneal the learning rate linearly to a final value; a constant `lr` when absent.
    pub lr_decay: Option<LrDecay>,
    pub adam_eps: f64,
    /// Double DQN (the online net picks the next action, the target net values it);
    /// false gives vanilla DQN (the target net's max).
    pub double: bool,
    pub loss: LossKind,
    /// Clip the gradient's global L2 norm to this; none when absent.
    pub max_grad_norm: Option<f64>,
    pub target_update: TargetUpdate,
    /// Multiplies the (n-step) returns in the TD target: Q-values scale with it, so it moves
    /// them relative to the Huber loss's fixed threshold of 1 and to Adam's ε.
    pub reward_scale: f64,
    /// Transitions per gradient update.
    pub batch_size: usize,
    /// Seed of torch's RNG for the initial weights, and of replay sampling.
    pub seed: u64,
}

impl Default for DqnConfig {
    fn default() -> Self {
        Self {
            gamma: 0.99,
            lr: 5e-4,
            lr_decay: None,
            adam_eps: 1e-8,
            double: true,
            loss: LossKind::Mse,
            max_grad_norm: None,
            target_update: TargetUpdate::Hard { every: 25_000 },
            reward_scale: 1.0,
            batch_size: 32,
            seed: 0,
        }
    }
}

impl DqnConfig {
    /// Adam's learning rate for the update that follows `updates` done ones.
    pub fn learning_rate(&self, updates: u64) -> f64 {
        match self.lr_decay {
            None => self.lr,
            Some(LrDecay { final_lr, updates: over }) if updates >= over => final_lr,
            Some(LrDecay { final_lr, updates: over }) => {
                // The arm above took updates ≥ over, so over ≥ 1 here.
                let progress = updates as f64 / over as f64;
                self.lr + (final_lr - self.lr) * progress
            }
        }
    }
}

/// A linear learning-rate anneal (CleanRL's and SB3's schedules): from `lr` to `final_lr`
/// over the first `updates` gradient updates of this learner's optimiser, then constant. It
/// counts the updates of the run (a resumed run continues the schedule; `--init-from` starts
/// it afresh), not wall time, so a run's schedule is the same on a fast machine and a slow one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LrDecay {
    /// The learning rate once the anneal is over.
    pub final_lr: f64,
    /// Updates over which the rate falls.
    pub updates: u64,
}

/// How the TD error becomes a loss.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LossKind {
    /// Squared error, as in the study.
    Mse,
    /// Huber loss with δ = 1 (smooth L1).
    Huber,
}

/// How the target network follows the online one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum TargetUpdate {
    /// Copy the online weights every `every` updates.
    Hard { every: u64 },
    /// θ⁻ ← (1 − τ)·θ⁻ + τ·θ after every update.
    Polyak { tau: f64 },
}

/// Proportional prioritised replay (Schaul et al. 2016).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrioritizedConfig {
    /// Priority exponent α: 0 is uniform.
    pub alpha: f64,
    /// Importance-sampling exponent β at the start; it rises linearly to 1.
    pub beta_start: f64,
    /// Updates over which β reaches 1.
    pub beta_updates: u64,
    /// Added to |TD error| so no transition gets zero priority.
    pub epsilon: f64,
}

impl Default for PrioritizedConfig {
    fn default() -> Self {
        Self { alpha: 0.6, beta_start: 0.4, beta_updates: 100_000, epsilon: 1e-3 }
    }
}

impl PrioritizedConfig {
    /// β after `updates` gradient updates.
    pub fn beta(&self, updates: u64) -> f64 {
        let progress = (updates as f64 / self.beta_updates.max(1) as f64).min(1.0);
        self.beta_start + (1.0 - self.beta_start) * progress
    }
}

/// The `[replay]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayConfig {
    /// Slots (≈ transitions) held.
    pub capacity: usize,
    /// Steps summed into each return (1 is the study).
    pub n_step: usize,
    /// Prioritised sampling; uniform when absent.
    pub prioritized: Option<PrioritizedConfig>,
}

impl Default for ReplayConfig {
    fn default() -> Self {
        Self { capacity: 500_000, n_step: 1, prioritized: None }
    }
}

impl ReplayConfig {
    /// Bytes the replay buffer's arrays take at `config.capacity` (None: beyond u64 or beyond the
    /// u32 slot indices): one observation, action, reward, flags, link and stamp per slot,
    /// plus the sum tree for prioritised replay.
    pub fn bytes_needed(&self, obs_dim: usize) -> Option<u64> {
        let capacity = u64::try_from(self.capacity).ok().filter(|&c| c <= u64::from(u32::MAX))?;
        let per_slot = 4 * obs_dim as u64 + 1 + 4 + 1 + 4 + 8;
        let tree = if self.prioritized.is_some() { 2 * 8 * capacity } else { 0 };
        capacity.checked_mul(per_slot)?.checked_add(tree)
    }
}

/// The `[rate]` section: the samples-per-insert limiter (after Reverb's `SampleToInsertRatio`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RateConfig {
    /// Transitions sampled per transition inserted; 0 disables the limit.
    pub samples_per_insert: f64,
    /// Transitions the replay must hold before the first sample.
    pub warmup: usize,
    /// Slack, in sampled transitions, before sampling blocks (and, with `limit_inserts`,
    /// before inserting blocks).
    pub error_buffer: f64,
    /// Limit inserts too (Reverb's limiter on both sides): when the learner falls behind,
    /// actors wait for its insert credit, so samples per insert stays in its band whichever
    /// side is slower. Off: only sampling waits, and slow learning lets the ratio fall.
    #[serde(default = "RateConfig::default_limit_inserts")]
    pub limit_inserts: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ActorSection {
    pub envs_per_actor: usize,
    pub batch_transitions: usize,
    pub seed: u64,
    pub status_interval_s: f64,
}

impl Default for ActorSection {
    fn default() -> Self {
        let settings = ActorSettings::default();
        Self {
            envs_per_actor: settings.envs_per_actor,
            batch_transitions: settings.batch_transitions,
            seed: settings.seed,
            status_interval_s: settings.status_interval_s,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LearnerSection {
    /// libtorch intra-op threads.
    pub threads: usize,
    /// zenoh endpoints the embedded router listens on.
    pub listen: Vec<String>,
    /// Allow a plain-TCP listener on an address other than loopback (no authentication: any
    /// host that reaches the port acts as an actor). Mutual TLS needs no such opt-in.
    pub allow_plain_remote: bool,
    /// Live actors and evaluators the learner keeps track of; liveliness tokens beyond this
    /// are ignored, and so are their messages. Bounds every per-actor table.
    pub max_actors: usize,
    /// Publish weights every this many updates.
    pub weights_every: u64,
    /// Write a checkpoint every this many updates (0: only at the end).
    pub checkpoint_every: u64,
    pub keep_checkpoints: usize,
    /// At the end of a run, average the weights of this many newest checkpoints into
    /// `checkpoints/average` (`crate::average`; 0: off). At most `keep_checkpoints`.
    pub average_checkpoints: usize,
    /// Greedy episodes each periodic checkpoint is evaluated on, the best one being kept as
    /// `checkpoints/best` (`crate::best`; 0: off).
    pub best_episodes: u32,
    /// Simulated seconds per such episode.
    pub best_seconds: f32,
    /// Play them under `eval --perturbed`'s physics instead of the nominal one.
    pub best_perturbed: bool,
    /// Also snapshot the replay buffer in the final checkpoint.
    pub snapshot_replay: bool,
    /// Seconds between status lines.
    pub status_every_s: f64,
    /// Stop after this many updates / seconds / environment steps (0: no limit).
    pub max_updates: u64,
    pub max_seconds: f64,
    pub max_env_steps: u64,
    /// Transition batches queued between the network and the inserting thread before new
    /// ones are dropped.
    pub ingest_queue: usize,
    /// Directory that holds one directory per run.
    pub runs_dir: String,
}

impl Default for LearnerSection {
    fn default() -> Self {
        Self {
            threads: 1,
            listen: vec!["tcp/127.0.0.1:7447".into()],
            allow_plain_remote: false,
            max_actors: 64,
            weights_every: 50,
            checkpoint_every: 5_000,
            keep_checkpoints: 3,
            average_checkpoints: 0,
            best_episodes: 0,
            best_seconds: 20.0,
            best_perturbed: false,
            snapshot_replay: true,
            status_every_s: 5.0,
            max_updates: 0,
            max_seconds: 0.0,
            max_env_steps: 0,
            ingest_queue: 256,
            runs_dir: "runs".into(),
        }
    }
}

/// Everything a training run is configured by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    pub env: EnvConfig,
    pub network: NetworkSection,
    pub dqn: DqnConfig,
    pub replay: ReplayConfig,
    pub rate: RateConfig,
    pub exploration: Exploration,
    pub actor: ActorSection,
    pub learner: LearnerSection,
}

impl Default for RateConfig {
    fn default() -> Self {
        Self {
            samples_per_insert: 8.0,
            warmup: 10_000,
            error_buffer: 256.0,
            limit_inserts: Self::default_limit_inserts(),
        }
    }
}

impl RateConfig {
    /// Both sides limited by default: docs/PERFORMANCE.md, "Rate control", has the measurement.
    const fn default_limit_inserts() -> bool {
        true
    }
}

impl TrainConfig {
    /// Reads a TOML preset and applies `overrides` (`section.key=value`, value in TOML syntax;
    /// a bare word is taken as a string).
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ConfigError::Read { path: path.display().to_string(), source })?;
        Self::from_toml(&text, &path.display().to_string(), overrides)
    }

    pub fn from_toml(text: &str, origin: &str, overrides: &[String]) -> Result<Self, ConfigError> {
        let value: toml::Table = toml::from_str(text)
            .map_err(|e| ConfigError::Parse { origin: origin.to_string(), message: e.to_string() })?;
        Self::from_table(value, origin, overrides)
    }

    /// The config a checkpoint recorded (its `meta.json` `config`), with `overrides` applied.
    pub fn from_json(json: &serde_json::Value, origin: &str, overrides: &[String]) -> Result<Self, ConfigError> {
        let parse_error = |message: String| ConfigError::Parse { origin: origin.to_string(), message };
        // TOML has no null: an absent optional is how a preset says None.
        let table = toml::Table::try_from(without_nulls(json)).map_err(|e| parse_error(e.to_string()))?;
        Self::from_table(table, origin, overrides)
    }

    fn from_table(mut value: toml::Table, origin: &str, overrides: &[String]) -> Result<Self, ConfigError> {
        let parse_error = |message: String| ConfigError::Parse { origin: origin.to_string(), message };
        for assignment in overrides {
            let (key, raw) = assignment.split_once('=').ok_or_else(|| ConfigError::Override(assignment.clone()))?;
            let parsed = toml::from_str::<toml::Table>(&format!("v = {raw}"))
                .ok()
                .and_then(|mut t| t.remove("v"))
                .unwrap_or_else(|| toml::Value::String(raw.to_string()));
            set_path(&mut value, key.trim(), parsed).map_err(|_| ConfigError::Override(assignment.clone()))?;
        }
        check_finite(&value, "")?;
        let config: TrainConfig =
            toml::Value::Table(value).try_into().map_err(|e: toml::de::Error| parse_error(e.to_string()))?;
        config.validate()?;
        config.check_memory(crate::memory::total_bytes())?;
        Ok(config)
    }

    /// Refuses sizes this machine cannot hold, before anything starts: the replay buffer
    /// (`total` is the machine's memory in bytes; None: unknown, not checked).
    pub fn check_memory(&self, total: Option<u64>) -> Result<(), ConfigError> {
        let Some(total) = total else { return Ok(()) };
        let mib = |bytes: u64| bytes >> 20;
        let needed = self.replay.bytes_needed(self.env.policy_input_dim());
        if needed.is_none_or(|n| n > total) {
            return Err(ConfigError::TooLarge {
                what: "the replay buffer",
                key: "replay.capacity",
                needed_mib: needed.map_or(u64::MAX, mib),
                total_mib: mib(total),
            });
        }
        Ok(())
    }

    /// Checks every value against its allowed range; the error names the key.
    ///
    /// Long on purpose: one flat check per key, in the order of the presets' sections, so that
    /// a new knob's check has one obvious place and every message names its key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |key: &str, value: String, allowed: &str| ConfigError::Invalid {
            key: key.to_string(),
            value,
            allowed: allowed.to_string(),
        };
        self.env.validate().map_err(|e| invalid(&format!("env.{}", e.key), e.value, e.allowed))?;
        self.actor_settings().validate()?;
        let d = &self.dqn;
        if !(d.gamma > 0.0 && d.gamma <= 1.0) {
            return Err(invalid("dqn.gamma", d.gamma.to_string(), "a number in (0, 1]"));
        }
        if !(d.adam_eps.is_finite() && d.adam_eps > 0.0 && d.adam_eps < 1.0) {
            return Err(invalid("dqn.adam_eps", d.adam_eps.to_string(), "a number in (0, 1)"));
        }
        if !(d.lr.is_finite() && d.lr > 0.0 && d.lr < 1.0) {
            return Err(invalid("dqn.lr", d.lr.to_string(), "a number in (0, 1)"));
        }
        if let Some(LrDecay { final_lr, updates }) = d.lr_decay {
            if !(final_lr.is_finite() && final_lr > 0.0 && final_lr <= d.lr) {
                return Err(invalid("dqn.lr_decay.final_lr", final_lr.to_string(), "a number in (0, dqn.lr]"));
            }
            if updates == 0 {
                return Err(invalid("dqn.lr_decay.updates", "0".into(), "at least 1"));
            }
        }
        if !(1e-6..=1e6).contains(&d.reward_scale) {
            return Err(invalid("dqn.reward_scale", d.reward_scale.to_string(), "a number in [1e-6, 1e6]"));
        }
        if !(1..=8192).contains(&d.batch_size) {
            return Err(invalid("dqn.batch_size", d.batch_size.to_string(), "an integer in 1..=8192"));
        }
        if let Some(norm) = d.max_grad_norm
            && !(1e-6..=1e6).contains(&norm)
        {
            return Err(invalid("dqn.max_grad_norm", norm.to_string(), "a number in [1e-6, 1e6]"));
        }
        match d.target_update {
            TargetUpdate::Hard { every: 0 } => {
                return Err(invalid("dqn.target_update.every", "0".into(), "at least 1"));
            }
            TargetUpdate::Polyak { tau } if !(tau > 0.0 && tau <= 1.0) => {
                return Err(invalid("dqn.target_update.tau", tau.to_string(), "a number in (0, 1]"));
            }
            _ => {}
        }
        self.network_spec()
            .validate()
            .map_err(|e| invalid("network.hidden", format!("{:?}", self.network.hidden), &e.to_string()))?;
        if self.replay.capacity < 2 * d.batch_size {
            return Err(invalid("replay.capacity", self.replay.capacity.to_string(), "at least twice dqn.batch_size"));
        }
        if !(1..=100).contains(&self.replay.n_step) {
            return Err(invalid("replay.n_step", self.replay.n_step.to_string(), "an integer in 1..=100"));
        }
        if let Some(per) = self.replay.prioritized
            && !((0.0..=1.0).contains(&per.alpha)
                && (0.0..=1.0).contains(&per.beta_start)
                && (0.0..=1.0).contains(&per.epsilon)
                && per.beta_updates >= 1)
        {
            return Err(invalid(
                "replay.prioritized",
                format!("{per:?}"),
                "alpha, beta_start and epsilon in [0, 1], beta_updates ≥ 1",
            ));
        }
        let r = &self.rate;
        // Beyond 10 000 samples per insert the insert credit would round to nothing and the
        // actors wait for ever.
        if !(0.0..=10_000.0).contains(&r.samples_per_insert) {
            return Err(invalid(
                "rate.samples_per_insert",
                r.samples_per_insert.to_string(),
                "a number in [0, 10000] (0: no limit)",
            ));
        }
        if !(0.0..=1e12).contains(&r.error_buffer) {
            return Err(invalid("rate.error_buffer", r.error_buffer.to_string(), "samples in [0, 1e12]"));
        }
        if r.limit_inserts && r.samples_per_insert <= 0.0 {
            return Err(invalid(
                "rate.limit_inserts",
                "true".into(),
                "false when rate.samples_per_insert = 0 (no ratio to hold)",
            ));
        }
        // The band must hold a minibatch and a transition's worth of samples, or both sides
        // could wait for each other: sampling below `batch_size − error_buffer`, inserting
        // above `error_buffer − samples_per_insert`.
        if r.limit_inserts && r.error_buffer < d.batch_size as f64 + r.samples_per_insert {
            return Err(invalid(
                "rate.error_buffer",
                r.error_buffer.to_string(),
                "at least dqn.batch_size + rate.samples_per_insert when rate.limit_inserts is on",
            ));
        }
        if r.warmup < d.batch_size || r.warmup > self.replay.capacity {
            return Err(invalid("rate.warmup", r.warmup.to_string(), "between dqn.batch_size and replay.capacity"));
        }
        let l = &self.learner;
        if !(1..=64).contains(&l.threads) {
            return Err(invalid("learner.threads", l.threads.to_string(), "an integer in 1..=64"));
        }
        if l.listen.is_empty() {
            return Err(invalid(
                "learner.listen",
                "[]".into(),
                "at least one zenoh endpoint, e.g. \"tcp/127.0.0.1:7447\"",
            ));
        }
        // A century.
        if !(0.0..=3.2e9).contains(&l.max_seconds) {
            return Err(invalid(
                "learner.max_seconds",
                l.max_seconds.to_string(),
                "seconds in [0, 3.2e9] (0: no limit)",
            ));
        }
        if !(1..=4096).contains(&l.max_actors) {
            return Err(invalid("learner.max_actors", l.max_actors.to_string(), "an integer in 1..=4096"));
        }
        if !(1..=1_000_000).contains(&l.weights_every) {
            return Err(invalid("learner.weights_every", l.weights_every.to_string(), "an integer in 1..=1000000"));
        }
        if !(1..=1_000_000).contains(&l.keep_checkpoints) {
            return Err(invalid(
                "learner.keep_checkpoints",
                l.keep_checkpoints.to_string(),
                "an integer in 1..=1000000",
            ));
        }
        if l.average_checkpoints == 1 || l.average_checkpoints > l.keep_checkpoints {
            return Err(invalid(
                "learner.average_checkpoints",
                l.average_checkpoints.to_string(),
                "0 (off) or from 2 up to learner.keep_checkpoints (only kept checkpoints can be averaged)",
            ));
        }
        if l.average_checkpoints > 0 && l.checkpoint_every == 0 {
            return Err(invalid(
                "learner.average_checkpoints",
                l.average_checkpoints.to_string(),
                "0 when learner.checkpoint_every is 0 (it averages periodic checkpoints)",
            ));
        }
        if l.best_episodes > 1000 {
            return Err(invalid(
                "learner.best_episodes",
                l.best_episodes.to_string(),
                "an integer in 0..=1000 (0: off)",
            ));
        }
        if !(l.best_seconds.is_finite() && l.best_seconds > 0.0 && l.best_seconds <= 3600.0) {
            return Err(invalid("learner.best_seconds", l.best_seconds.to_string(), "seconds in (0, 3600]"));
        }
        if l.best_episodes > 0 && l.checkpoint_every == 0 {
            return Err(invalid(
                "learner.best_episodes",
                l.best_episodes.to_string(),
                "0 when learner.checkpoint_every is 0 (only periodic checkpoints are evaluated)",
            ));
        }
        if !(0.05..=3600.0).contains(&l.status_every_s) {
            return Err(invalid("learner.status_every_s", l.status_every_s.to_string(), "seconds in [0.05, 3600]"));
        }
        if !(1..=65_536).contains(&l.ingest_queue) {
            return Err(invalid("learner.ingest_queue", l.ingest_queue.to_string(), "an integer in 1..=65536"));
        }
        Ok(())
    }

    pub fn network_spec(&self) -> NetworkSpec {
        NetworkSpec {
            obs_dim: self.env.policy_input_dim(),
            hidden: self.network.hidden.clone(),
            num_actions: self.env.num_actions(),
            layer_norm: self.network.layer_norm,
        }
    }

    pub fn actor_settings(&self) -> ActorSettings {
        ActorSettings {
            env: self.env.clone(),
            envs_per_actor: self.actor.envs_per_actor,
            batch_transitions: self.actor.batch_transitions,
            exploration: self.exploration.clone(),
            seed: self.actor.seed,
            status_interval_s: self.actor.status_interval_s,
        }
    }
}

/// Refuses NaN and ±∞ anywhere in a config, naming the key: serde would take them as
/// numbers, and a NaN compares false with every bound a later check might use.
fn check_finite(value: &toml::Table, prefix: &str) -> Result<(), ConfigError> {
    fn walk(value: &toml::Value, key: &str) -> Result<(), ConfigError> {
        match value {
            toml::Value::Float(f) if !f.is_finite() => Err(ConfigError::Invalid {
                key: key.to_string(),
                value: f.to_string(),
                allowed: "a finite number (not NaN or ±inf)".into(),
            }),
            toml::Value::Table(table) => check_finite(table, key),
            toml::Value::Array(items) => {
                items.iter().enumerate().try_for_each(|(i, item)| walk(item, &format!("{key}[{i}]")))
            }
            _ => Ok(()),
        }
    }
    value.iter().try_for_each(|(k, v)| walk(v, &if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") }))
}

fn without_nulls(value: &serde_json::Value) -> serde_json::Value {
    match value {
        serde_json::Value::Object(map) => {
            map.iter().filter(|(_, v)| !v.is_null()).map(|(k, v)| (k.clone(), without_nulls(v))).collect()
        }
        serde_json::Value::Array(items) => items.iter().map(without_nulls).collect(),
        other => other.clone(),
    }
}

fn set_path(table: &mut toml::Table, path: &str, value: toml::Value) -> Result<(), ()> {
    let mut parts: Vec<&str> = path.split('.').collect();
    let last = parts.pop().filter(|p| !p.is_empty()).ok_or(())?;
    let mut current = table;
    for part in parts {
        let entry = current.entry(part.to_string()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
        current = entry.as_table_mut().ok_or(())?;
    }
    current.insert(last.to_string(), value);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_apply_and_bad_values_name_their_key() {
        let config = TrainConfig::from_toml(
            "[dqn]\nlr = 1e-3\n",
            "test",
            &["dqn.batch_size=64".into(), "env.direction=backward".into()],
        )
        .unwrap();
        assert_eq!(config.dqn.lr, 1e-3);
        assert_eq!(config.dqn.batch_size, 64);
        assert_eq!(config.env.direction, crawler_env::Direction::Backward);

        let err = TrainConfig::from_toml("", "test", &["dqn.lr=2".into()]).unwrap_err().to_string();
        assert!(err.contains("dqn.lr") && err.contains("(0, 1)"), "{err}");
        let err = TrainConfig::from_toml("", "test", &["env.action_levels=1".into()]).unwrap_err().to_string();
        assert!(err.contains("env.action_levels"), "{err}");
        // Batches too large for one message at this history: refused before a run starts
        // rather than every batch refused by the learner later.
        let overrides = ["actor.batch_transitions=4096".into(), "env.observation_history=8".into()];
        let err = TrainConfig::from_toml("", "test", &overrides).unwrap_err().to_string();
        assert!(err.contains("actor.batch_transitions") && err.contains("env.observation_history"), "{err}");
        let err = TrainConfig::from_toml("[dqn]\nlrr = 1\n", "test", &[]).unwrap_err().to_string();
        assert!(err.contains("lrr"), "{err}");
        assert!(matches!(TrainConfig::from_toml("", "t", &["nonsense".into()]), Err(ConfigError::Override(_))));
        // A config survives the JSON round trip a checkpoint gives it, None values included.
        let json = serde_json::to_value(&config).unwrap();
        assert_eq!(TrainConfig::from_json(&json, "test", &[]).unwrap(), config);
        let missing = TrainConfig::load(Path::new("/no/such/config.toml"), &[]).unwrap_err().to_string();
        assert!(missing.contains("/no/such/config.toml"), "{missing}");
    }

    /// The learning rate falls linearly from `lr` to `lr_decay.final_lr` over its updates,
    /// then stays; a decay that would raise the rate, or take no updates, is refused by name.
    #[test]
    fn a_learning_rate_decay_anneals_linearly_then_holds() {
        let overrides = ["dqn.lr=4e-4".into(), "dqn.lr_decay={ final_lr = 1e-4, updates = 1000 }".into()];
        let config = TrainConfig::from_toml("", "test", &overrides).unwrap();
        let rate = |updates| config.dqn.learning_rate(updates);
        assert!((rate(0) - 4e-4).abs() < 1e-12);
        assert!((rate(500) - 2.5e-4).abs() < 1e-12, "{}", rate(500));
        assert!((rate(1000) - 1e-4).abs() < 1e-12);
        assert!((rate(50_000) - 1e-4).abs() < 1e-12);
        assert_eq!(DqnConfig::default().learning_rate(123_456), DqnConfig::default().lr);

        for (decay, key) in [
            ("{ final_lr = 1e-3, updates = 1000 }", "dqn.lr_decay.final_lr"),
            ("{ final_lr = nan, updates = 1000 }", "dqn.lr_decay.final_lr"),
            ("{ final_lr = 0.0, updates = 1000 }", "dqn.lr_decay.final_lr"),
            ("{ final_lr = 1e-4, updates = 0 }", "dqn.lr_decay.updates"),
        ] {
            let overrides = ["dqn.lr=4e-4".into(), format!("dqn.lr_decay={decay}")];
            let err = TrainConfig::from_toml("", "test", &overrides).unwrap_err().to_string();
            assert!(err.contains(key), "{decay}: {err}");
        }
    }

    /// Every preset a user may pass loads and validates, and every knob in it says what it
    /// does: a line that sets a key carries a comment.
    #[test]
    fn every_preset_loads_and_comments_each_knob() {
        let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
        let mut presets: Vec<_> = std::fs::read_dir(&configs)
            .unwrap()
            .map(|entry| entry.unwrap().path())
            .filter(|path| path.extension().is_some_and(|e| e == "toml"))
            .collect();
        presets.sort();
        assert!(presets.len() >= 4, "presets found: {presets:?}");
        for preset in &presets {
            let config = TrainConfig::load(preset, &[]).unwrap_or_else(|e| panic!("{}: {e}", preset.display()));
            config.validate().unwrap_or_else(|e| panic!("{}: {e}", preset.display()));
            let text = std::fs::read_to_string(preset).unwrap();
            for (number, line) in text.lines().enumerate() {
                let code = line.split('#').next().unwrap_or("").trim();
                let sets_a_key = code.contains('=') && !code.starts_with('[');
                assert!(
                    !sets_a_key || line.contains('#'),
                    "{}:{}: `{code}` has no comment saying what it does",
                    preset.display(),
                    number + 1
                );
            }
        }
    }

    /// Only kept, periodic checkpoints can be averaged, and one checkpoint is no average.
    #[test]
    fn averaging_asks_for_two_to_keep_checkpoints_of_a_run_that_checkpoints() {
        let ok = ["learner.keep_checkpoints=20".into(), "learner.average_checkpoints=20".into()];
        assert_eq!(TrainConfig::from_toml("", "test", &ok).unwrap().learner.average_checkpoints, 20);
        for overrides in [
            vec!["learner.average_checkpoints=1"],
            vec!["learner.keep_checkpoints=3", "learner.average_checkpoints=4"],
            vec!["learner.keep_checkpoints=5", "learner.average_checkpoints=5", "learner.checkpoint_every=0"],
        ] {
            let overrides: Vec<String> = overrides.into_iter().map(String::from).collect();
            let err = TrainConfig::from_toml("", "test", &overrides).unwrap_err().to_string();
            assert!(err.contains("learner.average_checkpoints"), "{overrides:?}: {err}");
        }
    }

    #[test]
    fn nan_infinity_and_overflow_are_refused_with_the_key_named() {
        // `assignment` over the config `base` is refused, and the error names `key`.
        let refused = |base: &str, assignment: &str, key: &str| {
            let err = TrainConfig::from_toml(base, "test", &[assignment.into()]).unwrap_err().to_string();
            assert!(err.contains(key), "{assignment}: {err}");
        };
        for (assignment, key) in [
            ("dqn.adam_eps=nan", "dqn.adam_eps"),
            ("rate.error_buffer=nan", "rate.error_buffer"),
            ("learner.max_seconds=nan", "learner.max_seconds"),
            ("learner.max_seconds=inf", "learner.max_seconds"),
            ("env.max_torque=-inf", "env.max_torque"),
            ("env.start_joint1_deg=[0.0, nan]", "env.start_joint1_deg[1]"),
            ("exploration.base=nan", "exploration.base"),
            ("dqn.adam_eps=0.0", "dqn.adam_eps"),
            ("env.max_tilt_deg=0.0", "env.max_tilt_deg"),
            ("env.max_tilt_deg=nan", "env.max_tilt_deg"),
            ("env.contact_prediction=nan", "env.contact_prediction"),
            ("env.base_impact_threshold=-inf", "env.base_impact_threshold"),
            ("env.position_reward_weight=0.0", "env.position_reward_weight"),
            ("env.position_reward_weight=nan", "env.position_reward_weight"),
        ] {
            refused("", assignment, key);
        }
        // Keys of sections that have no defaults, over a whole section.
        let sections = "[replay]\ncapacity = 10000\nn_step = 1\n[rate]\nsamples_per_insert = 4.0\nwarmup = 1000\nerror_buffer = 512.0\n";
        assert!(TrainConfig::from_toml(sections, "test", &[]).is_ok());
        for (assignment, key) in [
            ("rate.samples_per_insert=1e30", "rate.samples_per_insert"),
            ("rate.error_buffer=1e30", "rate.error_buffer"),
            ("replay.prioritized={alpha=0.6, beta_start=0.4, beta_updates=0, epsilon=1e-3}", "replay.prioritized"),
            ("replay.prioritized={alpha=0.6, beta_start=0.4, beta_updates=10, epsilon=1e30}", "replay.prioritized"),
        ] {
            refused(sections, assignment, key);
        }
        // Finite but absurd: durations, rates and scales have ranges, refused by key.
        for (assignment, key) in [
            ("learner.status_every_s=1e-20", "learner.status_every_s"),
            ("learner.status_every_s=1e9", "learner.status_every_s"),
            ("learner.max_seconds=1e300", "learner.max_seconds"),
            ("dqn.reward_scale=1e-30", "dqn.reward_scale"),
            ("dqn.reward_scale=1e30", "dqn.reward_scale"),
            ("dqn.max_grad_norm=1e-30", "dqn.max_grad_norm"),
            ("learner.weights_every=1000000000", "learner.weights_every"),
            ("learner.keep_checkpoints=1000000000", "learner.keep_checkpoints"),
            ("actor.status_interval_s=1e-20", "actor.status_interval_s"),
            ("env.max_episode_steps=10", "env.max_episode_steps"),
            ("env.min_progress_per_step=1e30", "env.min_progress_per_step"),
            ("env.start_joint1_deg=[-1e30, 0.0]", "env.start_joint1_deg"),
        ] {
            refused("", assignment, key);
        }
        // Beyond i64, TOML itself refuses; beyond usize's useful range, the key is named.
        let err = TrainConfig::from_toml("", "test", &["replay.capacity=99999999999999999999".into()]).unwrap_err();
        assert!(err.to_string().contains("replay.capacity"), "{err}");
    }

    #[test]
    fn sizes_the_machine_cannot_hold_are_refused_before_anything_starts() {
        let config = TrainConfig::from_toml("[replay]\ncapacity = 4000000000\nn_step = 3\n", "test", &[]);
        // On a machine with less than ~700 GB the load itself refuses; check the arithmetic
        // against a stated memory too.
        let config = match config {
            Err(e) => {
                assert!(matches!(e, ConfigError::TooLarge { key: "replay.capacity", .. }), "{e}");
                return;
            }
            Ok(config) => config,
        };
        let err = config.check_memory(Some(24 << 30)).unwrap_err().to_string();
        assert!(err.contains("replay.capacity") && err.contains("MiB"), "{err}");
        let err = TrainConfig::from_toml("", "test", &["network.hidden=[65536, 65536]".into()]).unwrap_err();
        assert!(err.to_string().contains("network.hidden"), "{err}");
    }
}
