//! The training thread: it owns the DQN, samples from the replay table that the inserting
//! thread (`inserter.rs`) fills, learns, publishes weights and writes checkpoints.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Receiver;
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
use crate::replay::{Replay, SampledBatch};
use crate::table::{Table, TableState};

/// The longest the training thread waits for inserts before it looks at its stop flag,
/// limits and reports again.
const SAMPLE_WAIT: Duration = Duration::from_millis(5);

/// Where training starts: fresh, resumed, or from another run's networks.
#[derive(Debug, Default)]
pub(super) struct Start {
    pub resume: Option<Checkpoint>,
    pub init_from: Option<Checkpoint>,
}

/// What the training thread shares with the rest of the process.
#[derive(Debug, Clone, Copy)]
pub(super) struct Links<'a> {
    /// Encoded `Weights` messages for the publisher.
    pub weights_out: &'a tokio::sync::mpsc::Sender<Vec<u8>>,
    pub shared: &'a Shared,
    pub stop: &'a AtomicBool,
}

/// Trains until `stop` is set, a configured limit is reached or the receive path goes, then
/// writes the final checkpoint (with the replay when `learner.snapshot_replay`). The
/// inserting thread runs beside it for as long, taking validated batches from `ingest`.
pub(super) fn train(
    config: &TrainConfig,
    run_id: &str,
    run_dir: &Path,
    start: Start,
    ingest: Receiver<proto::TransitionBatch>,
    links: Links<'_>,
) -> Result<Outcome, ServiceError> {
    let mut trainer = Trainer::new(config, run_id, run_dir, start, links)?;
    let table = Arc::clone(&trainer.table);
    let (inserting_table, shared) = (&*table, links.shared);
    std::thread::scope(|scope| {
        // Closed on every way out, a panic's included, so that the inserting thread ends
        // and the scope can join it.
        let closing = CloseOnDrop(&table);
        let inserting = std::thread::Builder::new()
            .name("inserting".into())
            .spawn_scoped(scope, move || super::inserter::insert(inserting_table, &ingest, shared))
            .map_err(ServiceError::InsertingThread)?;
        trainer.publish();
        while !links.stop.load(Ordering::SeqCst) && !trainer.limit_reached() && !table.is_closed() {
            if let Some(stats) = trainer.learn_step() {
                trainer.after_update(&stats);
            }
            trainer.report();
        }
        drop(closing);
        inserting.join().map_err(|_| ServiceError::InsertingThreadPanicked)?;
        trainer.finish()
    })
}

/// Closes the table when dropped.
struct CloseOnDrop<'a>(&'a Table);

impl Drop for CloseOnDrop<'_> {
    fn drop(&mut self) {
        self.0.close();
    }
}

/// The training loop's state.
struct Trainer<'a> {
    config: &'a TrainConfig,
    run_id: &'a str,
    run_dir: &'a Path,
    links: Links<'a>,
    config_json: serde_json::Value,
    dqn: Dqn,
    /// Replay and the rate limiter, shared with the inserting thread.
    table: Arc<Table>,
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
        let table = Table::new(replay, RateLimiter::new(config.rate), progress.env_steps, progress.physics_steps);
        Ok(Self {
            config,
            run_id,
            run_dir,
            links,
            config_json: serde_json::to_value(config)?,
            rng: ChaCha8Rng::seed_from_u64(config.dqn.seed ^ progress.updates),
            telemetry: Telemetry::open(run_dir, &progress)?,
            dqn,
            table: Arc::new(table),
            sample: SampledBatch::default(),
            prior_seconds: progress.train_seconds,
            progress,
            session_start: Instant::now(),
            last_checkpoint: None,
            best: BestFeed::start(&run_dir.join("checkpoints"), crawler_run::best::EvaluationPlan::of(config))
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
            || (l.max_env_steps > 0 && self.table.env_steps() >= l.max_env_steps)
    }

    /// The table's counts of what the actors sent, into the progress a checkpoint records.
    fn count_env_steps(&mut self) {
        self.progress.env_steps = self.table.env_steps();
        self.progress.physics_steps = self.table.physics_steps();
    }

    /// The RL step: sample a minibatch (n-step returns, importance weights when
    /// prioritised), take one Double DQN gradient step on it, and re-score what was sampled.
    /// None when the rate limiter or the replay's size says to wait, and inserts did not
    /// change that within [`SAMPLE_WAIT`].
    fn learn_step(&mut self) -> Option<UpdateStats> {
        let (batch_size, gamma) = (self.config.dqn.batch_size, self.config.dqn.gamma);
        let beta = self.config.replay.prioritized.map_or(0.0, |p| p.beta(self.progress.updates));
        let weighted = {
            let mut table = self.table.ready_to_sample(batch_size, SAMPLE_WAIT)?;
            table.replay.sample(batch_size, gamma, beta, &mut self.rng, &mut self.sample).ok()?;
            table.rate.record_sample(batch_size);
            table.replay.sampler().is_weighted()
        };
        let stats = self.dqn.update(&to_batch(&self.sample, batch_size, weighted));
        if stats.applied {
            // Slots overwritten during the update keep their new priorities (stamps).
            self.table.lock().replay.update_priorities(&self.sample.keys, &stats.td_errors);
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
        self.telemetry.record_update(stats.loss, stats.mean_q, stats.learning_rate);
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
        self.count_env_steps();
        let epsilon = mean_epsilon(self.links.shared);
        self.progress.epsilon = if epsilon.is_finite() { epsilon } else { 0.0 };
        let dir = self.run_dir.join("checkpoints");
        let keep = self.config.learner.keep_checkpoints;
        // The replay is written under the table's lock: inserts wait for the snapshot.
        let table = with_replay.then(|| self.table.lock());
        let replay = table.as_ref().map(|table| &table.replay);
        checkpoint::save(&dir, &self.dqn, self.run_id, &self.progress, &self.config_json, replay, keep)
    }

    /// Tells the credit publisher how many admitted transitions the rate limiter takes in
    /// all, then writes status and metrics when they are due.
    fn report(&mut self) {
        self.count_env_steps();
        let (replay_len, replay_open_streams, samples_per_insert, insert_headroom) = {
            let table = self.table.lock();
            let headroom = share_insert_limit(&table, self.links.shared);
            (table.replay.len(), table.replay.open_streams(), table.rate.realised_samples_per_insert(), headroom)
        };
        let now = TrainingNow {
            progress: &self.progress,
            replay_len,
            replay_open_streams,
            train_seconds: self.train_seconds(),
            last_checkpoint: self.last_checkpoint.as_deref(),
            samples_per_insert,
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
        self.count_env_steps();
        let (seconds, env_steps) = (self.train_seconds(), self.progress.env_steps);
        self.telemetry.flush(self.links.shared, seconds, env_steps);
        let path = self.save_checkpoint(self.config.learner.snapshot_replay)?;
        info!(updates = self.progress.updates, env_steps, "final checkpoint {}", path.display());
        self.average_checkpoints();
        Ok(Outcome { progress: self.progress, last_checkpoint: Some(path) })
    }
}

/// Tells the credit publisher how many admitted transitions the rate limiter takes in all:
/// those admitted so far plus its headroom (`u64::MAX` when inserts are not limited). An
/// absolute count, so that a stalled training thread stops the credit once its headroom is
/// used rather than granting it again every round. Returns the headroom (None when inserts
/// are not limited).
fn share_insert_limit(table: &TableState, shared: &Shared) -> Option<u64> {
    // Admitted first: a batch admitted in between is then also counted as queued, which only
    // lowers the limit. The inserting thread counts a batch out of the queue only after the
    // rate limiter has it, which also only lowers it.
    let admitted = shared.admitted_transitions.load(Ordering::Relaxed);
    let queued = shared.queued_transitions.load(Ordering::Relaxed);
    let headroom = table.rate.insert_headroom(table.replay.len(), queued);
    let limit = headroom.map_or(u64::MAX, |headroom| admitted.saturating_add(headroom));
    shared.insert_limit.store(limit, Ordering::Relaxed);
    headroom
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
