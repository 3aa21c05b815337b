//! What the training thread reports: `status.json` and its log line every
//! `learner.status_every_s`, and the metrics files (TensorBoard, CSV) every second.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use crawler_run::metrics::{MetricsError, MetricsWriter};
use serde::Serialize;
use tracing::{info, warn};

use super::edge::{ActorView, Shared, lock};
use super::fair_share::OverShare;

/// How often episodes and the training scalars reach the metrics files.
const METRICS_EVERY: Duration = Duration::from_secs(1);

/// The status file written every `status_every_s`, for people and tests.
#[derive(Debug, Clone, Serialize)]
pub struct Status {
    pub run_id: String,
    pub elapsed_s: f64,
    pub updates: u64,
    pub updates_per_second: f64,
    pub env_steps: u64,
    pub env_steps_per_second: f64,
    pub physics_steps: u64,
    pub replay_len: usize,
    /// Actor crawlers with an episode open in replay (bounded by the live actors).
    pub replay_open_streams: usize,
    pub weights_version: u64,
    pub loss: f64,
    pub mean_q: f64,
    pub connected_actors: Vec<u32>,
    pub actors: BTreeMap<u32, ActorView>,
    /// Transitions per second received from each actor since the last status.
    pub ingest_per_second: BTreeMap<u32, f64>,
    pub rejected: BTreeMap<&'static str, u64>,
    /// What each live sender had dropped for going over its fair share (senders that
    /// dropped nothing are left out); `rejected.over_share` counts them all.
    pub over_share: BTreeMap<String, OverShare>,
    pub dropped_batches: u64,
    /// Updates skipped because their loss or gradient was not finite.
    pub skipped_updates: u64,
    /// Liveliness tokens beyond `learner.max_actors`, ignored.
    pub ignored_tokens: u64,
    /// Samples per insert realised since the warm-up (the rate limiter's own count).
    pub samples_per_insert: Option<f64>,
    /// Transitions the learner takes before inserts wait (`rate.limit_inserts`; absent when
    /// only sampling is limited).
    pub insert_headroom: Option<u64>,
    pub last_checkpoint: Option<String>,
    pub last_evaluation_speed: Option<f32>,
}

/// The training loop's figures at one moment, as telemetry reads them.
#[derive(Debug, Clone, Copy)]
pub(super) struct TrainingNow<'a> {
    pub progress: &'a crate::checkpoint::Progress,
    pub replay_len: usize,
    pub replay_open_streams: usize,
    pub train_seconds: f64,
    pub last_checkpoint: Option<&'a Path>,
    pub samples_per_insert: Option<f64>,
    pub insert_headroom: Option<u64>,
}

/// The training thread's reporting state: clocks, counters since the last report, and the
/// metrics files.
#[derive(Debug)]
pub(super) struct Telemetry {
    metrics: MetricsWriter,
    metrics_clock: Instant,
    losses: LossAverage,
    last_loss: (f64, f64),
    status_clock: Instant,
    /// (updates, env steps) at the last status.
    status_counts: (u64, u64),
    /// Transitions each actor had sent at the last status.
    actor_transitions: BTreeMap<u32, u64>,
}

impl Telemetry {
    pub(super) fn open(run_dir: &Path, progress: &crate::checkpoint::Progress) -> Result<Self, MetricsError> {
        Ok(Self {
            metrics: MetricsWriter::create(run_dir)?,
            metrics_clock: Instant::now(),
            losses: LossAverage::default(),
            last_loss: (f64::NAN, f64::NAN),
            status_clock: Instant::now(),
            status_counts: (progress.updates, progress.env_steps),
            actor_transitions: BTreeMap::new(),
        })
    }

    /// Records an applied update's loss and mean Q, and the learning rate it was made with.
    pub(super) fn record_update(&mut self, loss: f64, mean_q: f64, learning_rate: f64) {
        self.last_loss = (loss, mean_q);
        self.losses.add(loss, mean_q);
        self.losses.learning_rate = learning_rate;
    }

    /// Called on every turn of the training loop: writes metrics and status when due.
    pub(super) fn tick(
        &mut self,
        now: TrainingNow<'_>,
        status_every_s: f64,
        run_id: &str,
        run_dir: &Path,
        shared: &Shared,
    ) {
        if self.metrics_clock.elapsed() >= METRICS_EVERY {
            self.flush(shared, now.train_seconds, now.progress.env_steps);
            self.metrics_clock = Instant::now();
        }
        if self.status_clock.elapsed().as_secs_f64() >= status_every_s {
            let status = self.status(now, run_id, shared);
            report(&status, run_dir);
            if status.connected_actors.is_empty() && status.env_steps_per_second == 0.0 {
                warn!("no actor is connected and no transitions arrive: training waits for actors");
            }
            write_status_metrics(&mut self.metrics, &status, shared);
            self.status_clock = Instant::now();
            self.status_counts = (now.progress.updates, now.progress.env_steps);
        }
    }

    fn status(&mut self, now: TrainingNow<'_>, run_id: &str, shared: &Shared) -> Status {
        let seconds = self.status_clock.elapsed().as_secs_f64();
        let actors = lock(&shared.actors).clone();
        self.actor_transitions.retain(|id, _| actors.contains_key(id));
        let ingest_per_second = actors
            .iter()
            .map(|(&id, view)| {
                let before = self.actor_transitions.insert(id, view.transitions).unwrap_or(0);
                (id, view.transitions.saturating_sub(before) as f64 / seconds)
            })
            .collect();
        let progress = now.progress;
        let (over_share, over_total) = {
            let shares = lock(&shared.shares);
            (shares.over_share(), shares.over_total())
        };
        let mut rejected = lock(&shared.rejected).clone();
        if over_total > 0 {
            rejected.insert("over_share", over_total);
        }
        Status {
            run_id: run_id.to_string(),
            elapsed_s: now.train_seconds,
            updates: progress.updates,
            updates_per_second: (progress.updates - self.status_counts.0) as f64 / seconds,
            env_steps: progress.env_steps,
            env_steps_per_second: (progress.env_steps - self.status_counts.1) as f64 / seconds,
            physics_steps: progress.physics_steps,
            replay_len: now.replay_len,
            replay_open_streams: now.replay_open_streams,
            weights_version: progress.weights_version,
            loss: self.last_loss.0,
            mean_q: self.last_loss.1,
            connected_actors: shared.connected().into_iter().collect(),
            actors,
            ingest_per_second,
            rejected,
            over_share,
            dropped_batches: shared.dropped_batches.load(Ordering::Relaxed),
            skipped_updates: shared.skipped_updates.load(Ordering::Relaxed),
            ignored_tokens: shared.ignored_tokens.load(Ordering::Relaxed),
            samples_per_insert: now.samples_per_insert,
            insert_headroom: now.insert_headroom,
            last_checkpoint: now.last_checkpoint.map(|p| p.display().to_string()),
            last_evaluation_speed: lock(&shared.evaluation).as_ref().map(|e| e.speed),
        }
    }

    /// Writes pending episodes and the averaged loss, then flushes, so a reader
    /// (TensorBoard, `plot`) sees everything up to now. Metrics are best effort: a failure is
    /// logged, and training goes on.
    pub(super) fn flush(&mut self, shared: &Shared, train_seconds: f64, env_steps: u64) {
        let metrics = &mut self.metrics;
        write_episode_metrics(metrics, shared, train_seconds, env_steps);
        let losses = std::mem::take(&mut self.losses);
        if losses.count > 0 {
            let n = losses.count as f64;
            let scalars = [
                ("train/loss", losses.loss / n),
                ("train/mean_q", losses.mean_q / n),
                ("train/learning_rate", losses.learning_rate),
            ];
            if let Err(e) = metrics.write(train_seconds, env_steps, &scalars) {
                warn!("metrics: {e}");
            }
        }
        if let Err(e) = metrics.flush() {
            warn!("metrics: {e}");
        }
    }
}

/// TD loss and mean Q, averaged between metric writes, and the latest update's learning rate
/// (it changes under `dqn.lr_decay`).
#[derive(Debug, Default)]
struct LossAverage {
    loss: f64,
    mean_q: f64,
    learning_rate: f64,
    count: u64,
}

impl LossAverage {
    fn add(&mut self, loss: f64, mean_q: f64) {
        self.loss += loss;
        self.mean_q += mean_q;
        self.count += 1;
    }
}

/// Every pending episode as scalars: `episode/*` for training actors (also per actor, with
/// its ε) and `eval/*` for evaluators.
fn write_episode_metrics(metrics: &mut MetricsWriter, shared: &Shared, train_seconds: f64, env_steps: u64) {
    let episodes = std::mem::take(&mut *lock(&shared.pending_episodes));
    lock(&shared.shares).pending_episodes_written();
    for e in episodes {
        let group = if e.evaluation { "eval" } else { "episode" };
        let fields = [
            ("distance", f64::from(e.distance)),
            ("duration", f64::from(e.duration)),
            ("return", f64::from(e.episode_return)),
            ("return_position", f64::from(e.return_position)),
            ("return_upright", f64::from(e.return_upright)),
            ("return_tilt_rate", f64::from(e.return_tilt_rate)),
            ("return_base_impact", f64::from(e.return_base_impact)),
            ("return_joint_limit", f64::from(e.return_joint_limit)),
            ("speed", f64::from(e.speed)),
            ("flips", f64::from(e.flips)),
        ];
        let mut tags: Vec<(String, f64)> = fields.iter().map(|(name, v)| (format!("{group}/{name}"), *v)).collect();
        if !e.evaluation && shared.may_tag(e.actor_id) {
            tags.push((format!("actor/{}/speed", e.actor_id), f64::from(e.speed)));
            tags.push((format!("actor/{}/epsilon", e.actor_id), e.epsilon));
        }
        let scalars: Vec<(&str, f64)> = tags.iter().map(|(t, v)| (t.as_str(), *v)).collect();
        if let Err(error) = metrics.write(train_seconds, env_steps, &scalars) {
            warn!("metrics: {error}");
            return;
        }
    }
}

/// The status report's throughput and health figures as scalars.
fn write_status_metrics(metrics: &mut MetricsWriter, status: &Status, shared: &Shared) {
    let mut scalars = vec![
        ("throughput/env_steps_per_s", status.env_steps_per_second),
        ("throughput/updates_per_s", status.updates_per_second),
        ("replay/size", status.replay_len as f64),
        ("weights/version", status.weights_version as f64),
        ("actors/connected", status.connected_actors.len() as f64),
        ("ingest/dropped_batches", status.dropped_batches as f64),
        ("ingest/rejected", status.rejected.values().sum::<u64>() as f64),
        ("progress/physics_steps", status.physics_steps as f64),
        ("progress/updates", status.updates as f64),
    ];
    if let Some(ratio) = status.samples_per_insert {
        scalars.push(("rate/samples_per_insert", ratio));
    }
    let waits: Vec<(String, f64)> = status
        .actors
        .iter()
        .filter(|(id, _)| shared.may_tag(**id))
        .map(|(id, view)| (format!("actor/{id}/waiting"), f64::from(view.waiting_fraction)))
        .collect();
    scalars.extend(waits.iter().map(|(t, v)| (t.as_str(), *v)));
    let ingest: Vec<(String, f64)> = status
        .ingest_per_second
        .iter()
        .filter(|(id, _)| shared.may_tag(**id))
        .map(|(id, rate)| (format!("actor/{id}/ingest_per_s"), *rate))
        .collect();
    scalars.extend(ingest.iter().map(|(t, v)| (t.as_str(), *v)));
    if let Err(e) = metrics.write(status.elapsed_s, status.env_steps, &scalars).and_then(|()| metrics.flush()) {
        warn!("metrics: {e}");
    }
}

/// Logs a status line and rewrites `status.json` atomically.
fn report(status: &Status, run_dir: &Path) {
    let per_actor: Vec<String> = status
        .actors
        .iter()
        .map(|(id, a)| {
            let rate = status.ingest_per_second.get(id).copied().unwrap_or(0.0);
            let wait = if a.waiting_fraction >= 0.005 {
                format!(" waits {:.0}%", 100.0 * a.waiting_fraction)
            } else {
                String::new()
            };
            format!("#{id} {rate:.0}/s ε={:.4} v{} {:.2} m/s{wait}", a.epsilon, a.weights_version, a.speed_ema)
        })
        .collect();
    let ratio = status.samples_per_insert.map_or_else(|| "-".to_string(), |r| format!("{r:.2}"));
    info!(
        "updates {} ({:.0}/s) | env steps {} ({:.0}/s) | samples/insert {ratio} | replay {} | weights v{} | loss {:.4} | connected {:?} | {}",
        status.updates,
        status.updates_per_second,
        status.env_steps,
        status.env_steps_per_second,
        status.replay_len,
        status.weights_version,
        status.loss,
        status.connected_actors,
        per_actor.join(" | ")
    );
    let path = run_dir.join("status.json");
    let temp = run_dir.join("status.json.tmp");
    if let Ok(json) = serde_json::to_vec_pretty(status)
        && std::fs::write(&temp, json).is_ok()
    {
        let _ = std::fs::rename(&temp, &path);
    }
}
