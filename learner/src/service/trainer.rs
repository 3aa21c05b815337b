//! The training thread: it owns the DQN, replay and the rate limiter (no lock guards them),
//! drains the ingest queue into replay, learns, publishes weights and writes checkpoints.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use crawler_proto::{self as proto, PROTOCOL_VERSION};
use crawler_run::config::TrainConfig;
use prost::Message;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use tracing::{info, warn};

use super::best_keeper::BestFeed;
use super::edge::{Shared, lock, mean_epsilon};
use super::telemetry::{Telemetry, TrainingNow};
use super::{Outcome, ServiceError};
use crate::algo::dqn::{Batch, Dqn, UpdateStats};
use crate::checkpoint::{self, Checkpoint, CheckpointError, Progress};
use crate::rate::RateLimiter;
use crate::replay::{Replay, SampledBatch, StreamId, Transition};

/// Where training starts: fresh, resumed, or from another run's networks.
#[derive(Debug, Default)]
pub(super) struct Start {
    pub resume: Option<Checkpoint>,
    pub init_from: Option<Checkpoint>,
}

/// What the training thread shares with the rest of the process.
#[derive(Debug, Clone, Copy)]
pub(super) struct Links<'a> {
    /// Validated transition batches from the edge.
    pub ingest: &'a Receiver<proto::TransitionBatch>,
    /// Encoded `Weights` messages for the publisher.
    pub weights_out: &'a tokio::sync::mpsc::Sender<Vec<u8>>,
    pub shared: &'a Shared,
    pub stop: &'a AtomicBool,
}

/// Trains until `stop` is set or a configured limit is reached, then writes the final
/// checkpoint (with the replay when `learner.snapshot_replay`).
pub(super) fn train(
    config: &TrainConfig,
    run_id: &str,
    run_dir: &Path,
    start: Start,
    links: Links<'_>,
) -> Result<Outcome, ServiceError> {
    let mut trainer = Trainer::new(config, run_id, run_dir, start, links)?;
    trainer.publish();
    while !links.stop.load(Ordering::SeqCst) && !trainer.limit_reached() {
        if !trainer.ingest() {
            break;
        }
        if let Some(stats) = trainer.learn_step() {
            trainer.after_update(&stats);
        }
        let headroom = trainer.share_insert_limit();
        trainer.report(headroom);
    }
    trainer.finish()
}

/// The training loop's state.
struct Trainer<'a> {
    config: &'a TrainConfig,
    run_id: &'a str,
    run_dir: &'a Path,
    links: Links<'a>,
    config_json: serde_json::Value,
    dqn: Dqn,
    replay: Replay,
    rate: RateLimiter,
    rng: ChaCha8Rng,
    sample: SampledBatch,
    progress: Progress,
    session_start: Instant,
    /// Training seconds of the run's earlier sessions.
    prior_seconds: f64,
    last_checkpoint: Option<PathBuf>,
    telemetry: Telemetry,
    /// Periodic checkpoints go here to be evaluated for `checkpoints/best`.
    best: BestFeed,
}

impl<'a> Trainer<'a> {
    fn new(
        config: &'a TrainConfig,
        run_id: &'a str,
        run_dir: &'a Path,
        start: Start,
        links: Links<'a>,
    ) -> Result<Self, ServiceError> {
        let mut dqn = Dqn::new(config.network_spec(), config.dqn.clone());
        let mut progress = Progress::default();
        let mut replay = None;
        if let Some(checkpoint) = &start.init_from {
            dqn.initialise_from(checkpoint)?;
            info!(from_run = %checkpoint.meta.run_id, "networks initialised from {}", checkpoint.path.display());
        }
        if let Some(checkpoint) = &start.resume {
            dqn.restore(checkpoint)?;
            progress = checkpoint.meta.progress.clone();
            // The file's size and CRC are checked first, so a snapshot that passes them but
            // does not decode was written by an older replay layout, and one whose records
            // fail their checks was written by no learner: either way the run resumes with an
            // empty replay (as when the replay config changed) rather than not at all.
            replay = match checkpoint::load_replay_for(checkpoint, config) {
                Ok(replay) => replay,
                Err(
                    CheckpointError::ReplayLayout { path, reason } | CheckpointError::ReplayContent { path, reason },
                ) => {
                    warn!(
                        "the replay snapshot {} is not usable ({reason}); resuming with an empty replay",
                        path.display()
                    );
                    None
                }
                Err(e) => return Err(e.into()),
            };
            info!(
                updates = progress.updates,
                weights_version = progress.weights_version,
                replay = replay.as_ref().map_or(0, Replay::len),
                "resumed from {}",
                checkpoint.path.display()
            );
        }
        // A new learner session: its weights order after anything an earlier process of this
        // run published (actors compare (session, version)), whatever it resumed with.
        // Wall-clock milliseconds also order it after a session that crashed before its first
        // checkpoint.
        let now_ms =
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64);
        progress.learner_session = progress.learner_session.saturating_add(1).max(now_ms);
        let replay = match replay {
            Some(r) if r.config() == config.replay && r.obs_dim() == config.env.policy_input_dim() => r,
            _ => Replay::new(config.replay.clone(), config.env.policy_input_dim())?,
        };
        let mut rate = RateLimiter::new(config.rate);
        rate.reset(replay.len());
        Ok(Self {
            config,
            run_id,
            run_dir,
            links,
            config_json: serde_json::to_value(config)?,
            rng: ChaCha8Rng::seed_from_u64(config.dqn.seed ^ progress.updates),
            telemetry: Telemetry::open(run_dir, &progress)?,
            dqn,
            replay,
            rate,
            sample: SampledBatch::default(),
            prior_seconds: progress.train_seconds,
            progress,
            session_start: Instant::now(),
            last_checkpoint: None,
            best: BestFeed::start(&run_dir.join("checkpoints"), config.best_evaluation())
                .map_err(ServiceError::BestThread)?,
        })
    }

    /// Training time of the whole run: earlier sessions plus this one.
    fn train_seconds(&self) -> f64 {
        self.prior_seconds + self.session_start.elapsed().as_secs_f64()
    }

    fn limit_reached(&self) -> bool {
        let l = &self.config.learner;
        let elapsed = self.session_start.elapsed().as_secs_f64();
        (l.max_updates > 0 && self.progress.updates >= l.max_updates)
            || (l.max_seconds > 0.0 && elapsed >= l.max_seconds)
            || (l.max_env_steps > 0 && self.progress.env_steps >= l.max_env_steps)
    }

    /// Moves what has arrived into replay, waiting briefly only when there is nothing to
    /// train on. False once the edge has gone (the process is shutting down).
    fn ingest(&mut self) -> bool {
        let batch_size = self.config.dqn.batch_size;
        let wait = if self.rate.can_sample(batch_size) { Duration::ZERO } else { Duration::from_millis(5) };
        let mut next = match self.links.ingest.recv_timeout(wait) {
            Ok(batch) => Some(batch),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => return false,
        };
        // At most one queue's worth per turn, so that arrivals cannot starve learning, and a
        // whole one, so that inserts keep up with any flood the queue admitted.
        let mut drained = 0;
        let mut received = 0;
        while let Some(batch) = next.take() {
            self.links.shared.queued_transitions.fetch_sub(batch.len() as u64, Ordering::Relaxed);
            received += insert_batch(&mut self.replay, &batch, self.links.shared);
            self.progress.env_steps += batch.len() as u64;
            self.progress.physics_steps += batch.physics_steps;
            drained += 1;
            if drained < self.config.learner.ingest_queue {
                next = self.links.ingest.try_recv().ok();
            }
        }
        self.rate.record_insert(received, self.replay.len());
        let departed = std::mem::take(&mut *lock(&self.links.shared.departed));
        if !departed.is_empty() {
            // Everyone not live goes, including actors whose last batches arrived after they
            // had already been released.
            let live = self.links.shared.connected();
            self.replay.release_streams(|actor| live.contains(&actor));
        }
        true
    }

    /// Tells the credit publisher how many admitted transitions the rate limiter takes in
    /// all: those admitted so far plus its headroom (`u64::MAX` when inserts are not
    /// limited). An absolute count, so that a stalled training thread stops the credit once
    /// its headroom is used rather than granting it again every round. Returns the headroom
    /// (None when inserts are not limited).
    fn share_insert_limit(&self) -> Option<u64> {
        let shared = self.links.shared;
        // Admitted first: a batch admitted in between is then also counted as queued, which
        // only lowers the limit.
        let admitted = shared.admitted_transitions.load(Ordering::Relaxed);
        let queued = shared.queued_transitions.load(Ordering::Relaxed);
        let headroom = self.rate.insert_headroom(self.replay.len(), queued);
        let limit = headroom.map_or(u64::MAX, |headroom| admitted.saturating_add(headroom));
        shared.insert_limit.store(limit, Ordering::Relaxed);
        headroom
    }

    /// The RL step: sample a minibatch (n-step returns, importance weights when
    /// prioritised), take one Double DQN gradient step on it, and re-score what was sampled.
    /// None when the rate limiter or the replay's size says to wait.
    fn learn_step(&mut self) -> Option<UpdateStats> {
        let (batch_size, gamma) = (self.config.dqn.batch_size, self.config.dqn.gamma);
        if !self.rate.can_sample(batch_size) || self.replay.len() < batch_size {
            return None;
        }
        let beta = self.config.replay.prioritized.map_or(0.0, |p| p.beta(self.progress.updates));
        self.replay.sample(batch_size, gamma, beta, &mut self.rng, &mut self.sample).ok()?;
        let stats = self.dqn.update(&to_batch(&self.sample, batch_size, self.replay.sampler().is_weighted()));
        self.rate.record_sample(batch_size);
        if stats.applied {
            self.replay.update_priorities(&self.sample.keys, &stats.td_errors);
        }
        Some(stats)
    }

    /// Counts an update, and publishes and checkpoints when they are due. A skipped
    /// (non-finite) update left the weights as they were; it is counted and logged.
    fn after_update(&mut self, stats: &UpdateStats) {
        if !stats.applied {
            let skipped = self.links.shared.skipped_updates.fetch_add(1, Ordering::Relaxed) + 1;
            if skipped <= 3 || skipped.is_multiple_of(1000) {
                warn!(skipped, loss = stats.loss, grad_norm = stats.grad_norm, "skipped a non-finite update");
            }
            return;
        }
        self.progress.updates += 1;
        self.telemetry.record_update(stats.loss, stats.mean_q, self.dqn.optimizer.config.lr);
        if self.progress.updates.is_multiple_of(self.config.learner.weights_every) {
            self.publish();
        }
        let every = self.config.learner.checkpoint_every;
        if every > 0 && self.progress.updates.is_multiple_of(every) {
            // A failed periodic checkpoint (disk full, say) is logged; training goes on and the
            // older checkpoints stay. The final one's error is returned.
            match self.save_checkpoint(false) {
                Ok(path) => {
                    self.best.offer(&path);
                    self.last_checkpoint = Some(path);
                }
                Err(e) => warn!("periodic checkpoint failed: {e}"),
            }
        }
    }

    /// Hands the online network to the publisher and the weights queryable as a new version;
    /// never non-finite weights.
    fn publish(&mut self) {
        let dqn = &self.dqn;
        if !dqn.online.all_finite() {
            warn!(updates = self.progress.updates, "the online network holds non-finite weights: not publishing them");
            return;
        }
        self.progress.weights_version += 1;
        let message = proto::Weights {
            protocol_version: PROTOCOL_VERSION,
            run_id: self.run_id.to_string(),
            version: self.progress.weights_version,
            learner_step: self.progress.updates,
            network: Some((&dqn.network).into()),
            safetensors: checkpoint::encode_weights(&dqn.online),
            learner_session: self.progress.learner_session,
        }
        .encode_to_vec();
        *lock(&self.links.shared.latest_weights) = message.clone();
        // Dropped when the publisher is busy: a newer version follows soon.
        let _ = self.links.weights_out.try_send(message);
    }

    /// Every checkpoint, periodic or final, records the training time and ε at that moment.
    fn save_checkpoint(&mut self, with_replay: bool) -> Result<PathBuf, CheckpointError> {
        self.progress.train_seconds = self.train_seconds();
        let epsilon = mean_epsilon(self.links.shared);
        self.progress.epsilon = if epsilon.is_finite() { epsilon } else { 0.0 };
        let replay = with_replay.then_some(&self.replay);
        let dir = self.run_dir.join("checkpoints");
        let keep = self.config.learner.keep_checkpoints;
        checkpoint::save(&dir, &self.dqn, self.run_id, &self.progress, &self.config_json, replay, keep)
    }

    /// Status and metrics, when they are due; `insert_headroom` as `share_insert_limit` just
    /// worked it out.
    fn report(&mut self, insert_headroom: Option<u64>) {
        let now = TrainingNow {
            progress: &self.progress,
            replay_len: self.replay.len(),
            replay_open_streams: self.replay.open_streams(),
            train_seconds: self.train_seconds(),
            last_checkpoint: self.last_checkpoint.as_deref(),
            samples_per_insert: self.rate.realised_samples_per_insert(),
            insert_headroom,
        };
        let every = self.config.learner.status_every_s;
        self.telemetry.tick(now, every, self.run_id, self.run_dir, self.links.shared);
    }

    /// `checkpoints/average`, when the config asks for it. A run whose average fails (too
    /// few checkpoints yet, say) still ends well: its checkpoints are all there, and the
    /// `average` tool can write it later.
    fn average_checkpoints(&self) {
        let count = self.config.learner.average_checkpoints;
        if count == 0 {
            return;
        }
        let dir = self.run_dir.join("checkpoints");
        match crawler_run::average::average_newest(&dir, count) {
            Ok(path) => info!(checkpoints = count, "weight average of the newest checkpoints: {}", path.display()),
            Err(error) => warn!(
                "no weight average of the newest checkpoints: {error}; once there are enough, run `average {} --last {count}`",
                dir.display()
            ),
        }
    }

    /// The last metrics and the final checkpoint.
    fn finish(mut self) -> Result<Outcome, ServiceError> {
        // What arrived since the last flush still reaches the metrics.
        let (seconds, env_steps) = (self.train_seconds(), self.progress.env_steps);
        self.telemetry.flush(self.links.shared, seconds, env_steps);
        let path = self.save_checkpoint(self.config.learner.snapshot_replay)?;
        info!(updates = self.progress.updates, env_steps, "final checkpoint {}", path.display());
        self.average_checkpoints();
        Ok(Outcome { progress: self.progress, last_checkpoint: Some(path) })
    }
}

/// Stores a validated batch; counts it in its actor's view.
fn insert_batch(replay: &mut Replay, batch: &proto::TransitionBatch, shared: &Shared) -> usize {
    let dim = batch.obs_dim as usize;
    let mut inserted = 0;
    for i in 0..batch.len() {
        let transition = Transition {
            observation: &batch.observations[i * dim..(i + 1) * dim],
            // Validated against the action count, which is at most 15² = 225.
            action: u8::try_from(batch.actions[i]).unwrap_or(u8::MAX),
            reward: batch.rewards[i],
            next_observation: &batch.next_observations[i * dim..(i + 1) * dim],
            terminated: batch.terminated[i],
            truncated: batch.truncated[i],
        };
        let stream = StreamId { actor: batch.actor_id, env: batch.env_ids[i] };
        if replay.insert(stream, &transition).is_ok() {
            inserted += 1;
        }
    }
    let mut actors = lock(&shared.actors);
    let view = actors.entry(batch.actor_id).or_default();
    view.transitions += inserted as u64;
    view.batches += 1;
    inserted
}

/// A sampled minibatch as tensors (`batch` rows).
fn to_batch(sample: &SampledBatch, batch: usize, weighted: bool) -> Batch {
    let rows = batch as i64;
    let dim = (sample.observations.len() / batch.max(1)) as i64;
    Batch {
        observations: Tensor::from_slice(&sample.observations).view([rows, dim]),
        actions: Tensor::from_slice(&sample.actions),
        returns: Tensor::from_slice(&sample.returns),
        next_observations: Tensor::from_slice(&sample.next_observations).view([rows, dim]),
        discounts: Tensor::from_slice(&sample.discounts),
        weights: weighted.then(|| Tensor::from_slice(&sample.weights)),
    }
}
