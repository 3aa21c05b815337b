//! The learner process: an embedded zenoh router, ingest, the training thread, and weights.
//!
//! Data path: zenoh delivers transition batches to a callback that validates them and hands
//! them to the training thread through a bounded queue; when the queue is full the batch is
//! dropped and counted, so zenoh's receive path never waits on training (a reliably published
//! message that waits more than 5 s makes zenoh close the sender's link). The training thread
//! inserts, samples and updates; every `weights_every` updates it hands fresh weights to a
//! publisher that never blocks (congestion control Drop: a frozen actor cannot stall the
//! learner) and to a queryable that serves the latest weights to starting actors.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use crawler_proto::{self as proto, PROTOCOL_VERSION, SequenceTracker, TransitionLimits, keys};
use prost::Message;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use tch::Tensor;
use tracing::{debug, info, warn};
use zenoh::Wait;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;

use crawler_actor::env::observation;

use crate::checkpoint::{self, Checkpoint, CheckpointError, Progress};
use crate::config::TrainConfig;
use crate::dqn::{Batch, Dqn};
use crate::metrics::MetricsWriter;
use crate::rate::RateLimiter;
use crate::replay::{Replay, SampledBatch, StreamId, Transition};

#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error("zenoh: {context}: {message}")]
    Zenoh { context: String, message: String },
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("the run id is not usable: {0}")]
    RunId(#[source] proto::ProtoError),
    #[error("cannot create the run directory {path}: {source}")]
    RunDir { path: PathBuf, source: std::io::Error },
    #[error("the config cannot be written into checkpoints as JSON: {0}")]
    ConfigJson(#[from] serde_json::Error),
    #[error("cannot set up the replay buffer: {0}")]
    Replay(#[from] crate::replay::ReplayError),
    #[error("cannot open the run's metrics files: {0}")]
    Metrics(#[from] crate::metrics::MetricsError),
    #[error("cannot start the training thread: {0}")]
    TrainingThread(#[source] std::io::Error),
    #[error("the training thread panicked; the log above says where")]
    TrainingThreadPanicked,
}

fn zenoh_error(context: impl Into<String>) -> impl FnOnce(zenoh::Error) -> ServiceError {
    let context = context.into();
    move |e| ServiceError::Zenoh { context, message: e.to_string() }
}

/// What to run.
#[derive(Debug)]
pub struct ServiceOptions {
    pub config: TrainConfig,
    pub run_id: String,
    /// `runs_dir/run_id`: checkpoints and status live here.
    pub run_dir: PathBuf,
    /// A checkpoint to continue from (same run).
    pub resume: Option<Checkpoint>,
    /// A checkpoint of another run whose networks start this one (transfer).
    pub init_from: Option<Checkpoint>,
    /// How remote sessions are identified: by certificate under mutual TLS (which the
    /// overrides then configure), or not at all.
    pub identity: crate::access_control::Identity,
    /// Extra zenoh settings as (key, JSON5) pairs, applied last (TLS).
    pub zenoh_overrides: Vec<(String, String)>,
}

/// Per-actor view, from its transitions and status reports.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ActorView {
    pub transitions: u64,
    pub batches: u64,
    pub weights_version: u64,
    pub env_steps: u64,
    pub env_steps_per_second: f32,
    pub epsilon: f64,
    pub episodes: u64,
    /// Exponential moving average of episode speed (m/s), distance and return.
    pub speed_ema: f32,
    pub distance_ema: f32,
    pub return_ema: f32,
    pub gaps: u64,
}

/// Which kind of node a liveliness token announces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum NodeKind {
    Actor,
    Evaluator,
}

/// The nodes holding a liveliness token, at most `max` of them: only their messages are kept,
/// so every per-actor table is bounded by `max`.
#[derive(Debug, Default)]
struct LiveNodes {
    actors: BTreeSet<u32>,
    evaluators: BTreeSet<u32>,
    max: usize,
}

/// What became of a liveliness token.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Admission {
    Admitted,
    AlreadyLive,
    /// `max` nodes are live already: ignored.
    Full,
}

impl LiveNodes {
    fn set(&mut self, kind: NodeKind) -> &mut BTreeSet<u32> {
        match kind {
            NodeKind::Actor => &mut self.actors,
            NodeKind::Evaluator => &mut self.evaluators,
        }
    }

    fn get(&self, kind: NodeKind) -> &BTreeSet<u32> {
        match kind {
            NodeKind::Actor => &self.actors,
            NodeKind::Evaluator => &self.evaluators,
        }
    }

    fn holds(&self, kind: NodeKind, id: u32) -> bool {
        self.get(kind).contains(&id)
    }

    fn admit(&mut self, kind: NodeKind, id: u32) -> Admission {
        if self.holds(kind, id) {
            Admission::AlreadyLive
        } else if self.actors.len() + self.evaluators.len() >= self.max {
            Admission::Full
        } else {
            self.set(kind).insert(id);
            Admission::Admitted
        }
    }

    /// Whether the node was live.
    fn leave(&mut self, kind: NodeKind, id: u32) -> bool {
        self.set(kind).remove(&id)
    }
}

/// State shared between zenoh callbacks, the training thread and status reports.
#[derive(Debug, Default)]
struct Shared {
    actors: Mutex<BTreeMap<u32, ActorView>>,
    live: Mutex<LiveNodes>,
    /// Last sequence number per live actor (forgotten when it leaves).
    sequences: Mutex<SequenceTracker>,
    rejected: Mutex<BTreeMap<&'static str, u64>>,
    /// Liveliness tokens beyond `learner.max_actors`, ignored.
    ignored_tokens: AtomicU64,
    /// Actor ids that have metric tags of their own.
    tagged_actors: Mutex<BTreeSet<u32>>,
    latest_weights: Mutex<Vec<u8>>,
    dropped_batches: AtomicU64,
    skipped_updates: AtomicU64,
    evaluation: Mutex<Option<proto::EpisodeStats>>,
    /// Ids handed to `--id auto` actors, and when: reserved until the actor shows up.
    assigned: Mutex<BTreeMap<u32, Instant>>,
    /// Episodes not yet written to the metrics; bounded by [`MAX_PENDING_EPISODES`].
    pending_episodes: Mutex<Vec<proto::EpisodeStats>>,
}

impl Shared {
    fn new(max_actors: usize) -> Self {
        Self { live: Mutex::new(LiveNodes { max: max_actors, ..LiveNodes::default() }), ..Self::default() }
    }

    fn connected(&self) -> BTreeSet<u32> {
        lock(&self.live).actors.clone()
    }

    /// Whether actor `id` gets metric tags of its own (`actor/<id>/…`): the first
    /// `learner.max_actors` ids do, so that churn of ids cannot grow the tag set without bound.
    fn may_tag(&self, id: u32) -> bool {
        let max = lock(&self.live).max;
        let mut tagged = lock(&self.tagged_actors);
        tagged.contains(&id) || (tagged.len() < max && tagged.insert(id))
    }
}

/// Ids handed to `--id auto` actors that have not shown up yet, at most this many: the
/// oldest reservation gives way, so queries cannot push ids up without bound.
const MAX_PENDING_ASSIGNMENTS: usize = 16;

/// Episodes held for the metrics writer, which drains them every second. Beyond this (the
/// training thread stalled) new episodes are left out of the metrics, not queued.
const MAX_PENDING_EPISODES: usize = 10_000;

/// How often episodes and the training scalars reach the metrics files.
const METRICS_EVERY: Duration = Duration::from_secs(1);

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

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
    pub weights_version: u64,
    pub loss: f64,
    pub mean_q: f64,
    pub connected_actors: Vec<u32>,
    pub actors: BTreeMap<u32, ActorView>,
    /// Transitions per second received from each actor since the last status.
    pub ingest_per_second: BTreeMap<u32, f64>,
    pub rejected: BTreeMap<&'static str, u64>,
    pub dropped_batches: u64,
    /// Updates skipped because their loss or gradient was not finite.
    pub skipped_updates: u64,
    /// Liveliness tokens beyond `learner.max_actors`, ignored.
    pub ignored_tokens: u64,
    pub last_checkpoint: Option<String>,
    pub last_evaluation_speed: Option<f32>,
}

/// How a run ended.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub progress: Progress,
    pub last_checkpoint: Option<PathBuf>,
}

/// Opens the router, serves the run, trains until `stop` or a configured limit.
pub async fn run(options: ServiceOptions, stop: Arc<AtomicBool>) -> Result<Outcome, ServiceError> {
    let ServiceOptions { config, run_id, run_dir, resume, init_from, identity, zenoh_overrides } = options;
    keys::check_run_id(&run_id).map_err(ServiceError::RunId)?;
    std::fs::create_dir_all(&run_dir).map_err(|source| ServiceError::RunDir { path: run_dir.clone(), source })?;
    crate::set_torch_threads(config.learner.threads);
    crate::tune_allocator();

    let mut zenoh_config = zenoh::Config::default();
    let listen = crawler_actor::node::serde_json_list(&config.learner.listen);
    let max_actors = config.learner.max_actors;
    let base = [
        ("mode".to_string(), "\"router\"".to_string()),
        ("listen/endpoints".to_string(), listen),
        ("scouting/multicast/enabled".to_string(), "false".to_string()),
        // zenoh buffers up to 1 GiB of one incoming message by default; nothing legal is
        // larger than this.
        ("transport/link/rx/max_message_size".to_string(), proto::TRANSPORT_MAX_MESSAGE_BYTES.to_string()),
        // Sessions the router admits (actors, evaluators, observers, with room for
        // reconnections), so that per-session buffers stay bounded.
        ("transport/unicast/max_sessions".to_string(), (2 * max_actors + 16).to_string()),
        // A connection that never completes its handshake holds an accept slot this long
        // (zenoh's default is 10 s): idle connections delay real actors less.
        ("transport/unicast/accept_timeout".to_string(), "2000".to_string()),
        // The policy is always on: under TLS roles come by certificate, without it every
        // remote session is an actor (access_control.rs).
        ("access_control".to_string(), crate::access_control::policy(&run_id, identity).to_string()),
    ];
    for (key, value) in base.into_iter().chain(zenoh_overrides) {
        zenoh_config.insert_json5(&key, &value).map_err(zenoh_error(format!("setting {key} = {value}")))?;
    }
    let session = zenoh::open(zenoh_config).await.map_err(zenoh_error("opening the router"))?;

    info!(run = %run_id, listen = ?config.learner.listen, "learner router up");

    let shared = Arc::new(Shared::new(max_actors));
    let run_info = proto::RunInfo {
        protocol_version: PROTOCOL_VERSION,
        run_id: run_id.clone(),
        settings: Some((&config.actor_settings()).into()),
        assigned_actor_id: None,
    };
    let info_key = keys::info(&run_id);
    let reply_key = info_key.clone();
    let info_shared = Arc::clone(&shared);
    let _info_queryable = session
        .declare_queryable(&info_key)
        .callback(move |query| {
            let mut info = run_info.clone();
            if query.parameters().contains_key(keys::ASSIGN_PARAMETER) {
                info.assigned_actor_id = Some(assign_actor_id(&info_shared));
            }
            let _ = query.reply(&reply_key, info.encode_to_vec()).wait();
        })
        .await
        .map_err(zenoh_error("declaring the run-info queryable"))?;
    let weights_key = keys::weights(&run_id);
    let weights_shared = Arc::clone(&shared);
    let served_key = weights_key.clone();
    let _weights_queryable = session
        .declare_queryable(&weights_key)
        .callback(move |query| {
            let latest = lock(&weights_shared.latest_weights).clone();
            if !latest.is_empty() {
                let _ = query.reply(&served_key, latest).wait();
            }
        })
        .await
        .map_err(zenoh_error("declaring the weights queryable"))?;
    let weights_publisher = session
        .declare_publisher(&weights_key)
        .congestion_control(CongestionControl::Drop)
        .await
        .map_err(zenoh_error("declaring the weights publisher"))?;
    let _token = session
        .liveliness()
        .declare_token(keys::alive_learner(&run_id))
        .await
        .map_err(zenoh_error("declaring liveliness"))?;

    // Ingest: validate in the callback, queue (bounded) for the training thread.
    let (ingest_tx, ingest_rx) = sync_channel::<proto::TransitionBatch>(config.learner.ingest_queue);
    let limits = TransitionLimits {
        run_id: run_id.clone(),
        obs_dim: crawler_actor::env::OBS_DIM as u32,
        num_actions: config.env.num_actions() as u32,
        max_batch: proto::MAX_BATCH_TRANSITIONS,
        envs_per_actor: config.actor.envs_per_actor as u32,
        observation_range: observation::observation_range(config.env.max_torque),
        max_abs_reward: observation::max_abs_reward(config.env.action_repeat),
    };
    let _transitions = session
        .declare_subscriber(keys::all_transitions(&run_id))
        .callback(ingest_callback(limits, ingest_tx, Arc::clone(&shared)))
        .await
        .map_err(zenoh_error("subscribing to transitions"))?;
    let _stats = session
        .declare_subscriber(keys::all_stats(&run_id))
        .callback(validated(&shared, &run_id, proto::validate::episode_stats, record_episode))
        .await
        .map_err(zenoh_error("subscribing to stats"))?;
    let _status = session
        .declare_subscriber(keys::all_status(&run_id))
        .callback(validated(&shared, &run_id, proto::validate::actor_status, record_status))
        .await
        .map_err(zenoh_error("subscribing to status"))?;
    let _alive_actors = session
        .liveliness()
        .declare_subscriber(keys::all_alive_actors(&run_id))
        .history(true)
        .callback(liveliness_callback(Arc::clone(&shared), NodeKind::Actor))
        .await
        .map_err(zenoh_error("watching actor liveliness"))?;
    let _alive_evaluators = session
        .liveliness()
        .declare_subscriber(keys::all_alive_evaluators(&run_id))
        .history(true)
        .callback(liveliness_callback(Arc::clone(&shared), NodeKind::Evaluator))
        .await
        .map_err(zenoh_error("watching evaluator liveliness"))?;

    // Training runs on its own thread; weights come back through a channel to be published.
    let (weights_tx, mut weights_rx) = tokio::sync::mpsc::channel::<Vec<u8>>(2);
    let trainer = {
        let shared = Arc::clone(&shared);
        let stop = Arc::clone(&stop);
        let run_id = run_id.clone();
        std::thread::Builder::new()
            .name("training".into())
            .spawn(move || {
                let start = Start { resume, init_from };
                train(&config, &run_id, &run_dir, start, &ingest_rx, &weights_tx, &shared, &stop)
            })
            .map_err(ServiceError::TrainingThread)?
    };
    while let Some(bytes) = weights_rx.recv().await {
        if let Err(e) = weights_publisher.put(bytes).await {
            warn!("weights publish failed: {e}");
        }
    }
    let outcome = trainer.join().map_err(|_| ServiceError::TrainingThreadPanicked)??;

    // Tell every node of the run to exit; repeat briefly so late subscribers hear it too.
    let control = proto::Control {
        protocol_version: PROTOCOL_VERSION,
        run_id: run_id.clone(),
        command: proto::Command::Stop as i32,
    }
    .encode_to_vec();
    for _ in 0..5 {
        let _ = session.put(keys::control(&run_id), control.clone()).await;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let _ = session.close().await;
    Ok(outcome)
}

/// How long an id handed out stays reserved for an actor that has not yet connected.
const ASSIGNMENT_HOLD: Duration = Duration::from_secs(30);

/// The smallest id that no connected actor holds and that was not handed out recently.
fn assign_actor_id(shared: &Shared) -> u32 {
    let connected = shared.connected();
    let mut assigned = lock(&shared.assigned);
    assigned.retain(|id, at| at.elapsed() < ASSIGNMENT_HOLD && !connected.contains(id));
    while assigned.len() >= MAX_PENDING_ASSIGNMENTS {
        let Some(oldest) = assigned.iter().min_by_key(|(_, at)| **at).map(|(id, _)| *id) else { break };
        assigned.remove(&oldest);
    }
    let id = (0..).find(|id| !connected.contains(id) && !assigned.contains_key(id)).unwrap_or(u32::MAX);
    assigned.insert(id, Instant::now());
    info!(actor = id, "assigned an actor id");
    id
}

fn count_rejection(shared: &Shared, error: &proto::ProtoError) {
    let count = {
        let mut rejected = lock(&shared.rejected);
        let count = rejected.entry(error.kind()).or_default();
        *count += 1;
        *count
    };
    // Rate-limited: the first few of each kind, then every 1000th.
    if count <= 3 || count.is_multiple_of(1000) {
        warn!(kind = error.kind(), count, "rejected message: {error}");
    }
}

/// A message an actor or evaluator puts under its own id.
trait FromNode {
    fn node(&self) -> (NodeKind, u32);
}

impl FromNode for proto::EpisodeStats {
    fn node(&self) -> (NodeKind, u32) {
        (if self.evaluation { NodeKind::Evaluator } else { NodeKind::Actor }, self.actor_id)
    }
}

impl FromNode for proto::ActorStatus {
    fn node(&self) -> (NodeKind, u32) {
        (if self.evaluator { NodeKind::Evaluator } else { NodeKind::Actor }, self.actor_id)
    }
}

impl FromNode for proto::TransitionBatch {
    fn node(&self) -> (NodeKind, u32) {
        (NodeKind::Actor, self.actor_id)
    }
}

/// The checks every message from a node passes after decoding: it is put under its own id,
/// and that id holds a liveliness token. Returns the message when it passes.
fn from_live_sender<M: FromNode>(shared: &Shared, key: &str, message: M) -> Result<M, proto::ProtoError> {
    let (kind, id) = message.node();
    proto::validate::check_sender(key, id)?;
    if lock(&shared.live).holds(kind, id) { Ok(message) } else { Err(proto::ProtoError::NotLive { actor: id }) }
}

/// A subscriber callback that validates each message with `decode` and [`from_live_sender`] and
/// hands valid ones to `record`; rejections are counted and logged with rate limiting.
fn validated<M: FromNode + 'static>(
    shared: &Arc<Shared>,
    run_id: &str,
    decode: fn(&[u8], &str) -> Result<M, proto::ProtoError>,
    record: fn(&Shared, M),
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    let shared = Arc::clone(shared);
    let run_id = run_id.to_string();
    move |sample| {
        let checked = decode(&sample.payload().to_bytes(), &run_id)
            .and_then(|message| from_live_sender(&shared, sample.key_expr().as_str(), message));
        match checked {
            Ok(message) => record(&shared, message),
            Err(e) => count_rejection(&shared, &e),
        }
    }
}

/// Tracks liveliness tokens of one kind: up to `learner.max_actors` live nodes. A node that
/// leaves takes its sequence state with it; its view stays until a new node needs the room.
fn liveliness_callback(shared: Arc<Shared>, kind: NodeKind) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    move |sample| {
        let Some(id) = keys::trailing_id(sample.key_expr().as_str()) else { return };
        let mut live = lock(&shared.live);
        match sample.kind() {
            SampleKind::Put => match live.admit(kind, id) {
                Admission::AlreadyLive => {}
                Admission::Full => {
                    let ignored = shared.ignored_tokens.fetch_add(1, Ordering::Relaxed) + 1;
                    if ignored <= 3 || ignored.is_multiple_of(1000) {
                        warn!(
                            id,
                            max = live.max,
                            ignored,
                            "more live nodes than learner.max_actors: ignoring this one"
                        );
                    }
                }
                Admission::Admitted => {
                    info!(id, ?kind, "node connected");
                    // Views of actors that left stay for status.json until room is needed.
                    let live_actors = live.actors.clone();
                    let max = live.max;
                    drop(live);
                    let mut views = lock(&shared.actors);
                    if views.len() >= max {
                        views.retain(|id, _| live_actors.contains(id));
                    }
                }
            },
            SampleKind::Delete => {
                if live.leave(kind, id) {
                    info!(id, ?kind, "node left");
                    drop(live);
                    if kind == NodeKind::Actor {
                        lock(&shared.sequences).forget(id);
                    }
                }
            }
        }
    }
}

fn record_status(shared: &Shared, report: proto::ActorStatus) {
    if report.evaluator {
        return;
    }
    let mut actors = lock(&shared.actors);
    let view = actors.entry(report.actor_id).or_default();
    view.weights_version = report.weights_version;
    view.env_steps = report.env_steps;
    view.env_steps_per_second = report.env_steps_per_second;
    view.epsilon = report.epsilon;
}

fn record_episode(shared: &Shared, stats: proto::EpisodeStats) {
    {
        let mut pending = lock(&shared.pending_episodes);
        if pending.len() < MAX_PENDING_EPISODES {
            pending.push(stats.clone());
        }
    }
    if stats.evaluation {
        info!(speed = stats.speed, distance = stats.distance, weights = stats.weights_version, "evaluation episode");
        *lock(&shared.evaluation) = Some(stats);
        return;
    }
    let mut actors = lock(&shared.actors);
    let view = actors.entry(stats.actor_id).or_default();
    let alpha = if view.episodes == 0 { 1.0 } else { 0.1 };
    view.episodes += 1;
    view.speed_ema += alpha * (stats.speed - view.speed_ema);
    view.distance_ema += alpha * (stats.distance - view.distance_ema);
    view.return_ema += alpha * (stats.episode_return - view.return_ema);
    view.epsilon = stats.epsilon;
    debug!(actor = stats.actor_id, speed = stats.speed, distance = stats.distance, epsilon = stats.epsilon, "episode");
}

fn ingest_callback(
    limits: TransitionLimits,
    queue: SyncSender<proto::TransitionBatch>,
    shared: Arc<Shared>,
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    move |sample| {
        let batch = match proto::validate::transition_batch(&sample.payload().to_bytes(), &limits)
            .and_then(|batch| from_live_sender(&shared, sample.key_expr().as_str(), batch))
        {
            Ok(batch) => batch,
            Err(e) => return count_rejection(&shared, &e),
        };
        let check = lock(&shared.sequences).check(batch.actor_id, batch.incarnation, batch.sequence);
        match check {
            Err(e) => return count_rejection(&shared, &e),
            Ok(proto::validate::SequenceCheck::Gap { missing }) => {
                lock(&shared.actors).entry(batch.actor_id).or_default().gaps += missing;
            }
            Ok(_) => {}
        }
        match queue.try_send(batch) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                let dropped = shared.dropped_batches.fetch_add(1, Ordering::Relaxed) + 1;
                if dropped <= 3 || dropped.is_multiple_of(100) {
                    warn!(dropped, "ingest queue full: training is behind the actors; dropping a batch");
                }
            }
            Err(TrySendError::Disconnected(_)) => {}
        }
    }
}

/// Where training starts: fresh, resumed, or from another run's networks.
#[derive(Debug, Default)]
struct Start {
    resume: Option<Checkpoint>,
    init_from: Option<Checkpoint>,
}

/// The training loop. Returns when `stop` is set or a limit is reached, after a final
/// checkpoint.
#[allow(clippy::too_many_arguments)]
fn train(
    config: &TrainConfig,
    run_id: &str,
    run_dir: &Path,
    start: Start,
    ingest: &Receiver<proto::TransitionBatch>,
    weights_out: &tokio::sync::mpsc::Sender<Vec<u8>>,
    shared: &Shared,
    stop: &AtomicBool,
) -> Result<Outcome, ServiceError> {
    let checkpoint_dir = run_dir.join("checkpoints");
    let config_json = serde_json::to_value(config)?;
    let mut dqn = Dqn::new(config.dqn_config());
    let mut progress = Progress::default();
    let mut replay = None;
    if let Some(checkpoint) = &start.init_from {
        dqn.initialise_from(checkpoint)?;
        info!(from_run = %checkpoint.meta.run_id, "networks initialised from {}", checkpoint.path.display());
    }
    if let Some(checkpoint) = &start.resume {
        dqn.restore(checkpoint)?;
        progress = checkpoint.meta.progress.clone();
        replay = checkpoint::load_replay(checkpoint)?;
        info!(
            updates = progress.updates,
            weights_version = progress.weights_version,
            replay = replay.as_ref().map_or(0, Replay::len),
            "resumed from {}",
            checkpoint.path.display()
        );
    }
    // A new learner session: its weights order after anything an earlier process of this run
    // published (actors compare (session, version)), whatever it resumed with. Wall-clock
    // milliseconds also order it after a session that crashed before its first checkpoint.
    let now_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64);
    progress.learner_session = (progress.learner_session + 1).max(now_ms);
    let mut replay = match replay {
        Some(r) if r.config() == &config.replay => r,
        _ => Replay::new(config.replay.clone(), crawler_actor::env::OBS_DIM)?,
    };
    let mut rate = RateLimiter::new(config.rate);
    rate.reset(replay.len());
    let mut rng = ChaCha8Rng::seed_from_u64(config.dqn.seed ^ progress.updates);
    let mut sample = SampledBatch::default();
    let batch_size = config.dqn.batch_size;
    let session_start = Instant::now();
    let prior_seconds = progress.train_seconds;
    // Training time of the whole run: earlier sessions plus this one.
    let train_seconds = || prior_seconds + session_start.elapsed().as_secs_f64();
    let mut last_checkpoint: Option<PathBuf> = None;
    let mut last_loss = (f64::NAN, f64::NAN);
    let mut status_clock = Instant::now();
    let mut status_counts = (progress.updates, progress.env_steps);
    let mut actor_transitions: BTreeMap<u32, u64> = BTreeMap::new();
    let mut metrics = MetricsWriter::create(run_dir)?;
    let mut metrics_clock = Instant::now();
    let mut losses = LossAverage::default();

    // Every checkpoint, periodic or final, records the training time and ε at that moment.
    let save_checkpoint = |dqn: &Dqn, progress: &mut Progress, replay: Option<&Replay>| {
        progress.train_seconds = train_seconds();
        progress.epsilon = mean_epsilon(shared);
        if !progress.epsilon.is_finite() {
            progress.epsilon = 0.0;
        }
        checkpoint::save(&checkpoint_dir, dqn, run_id, progress, &config_json, replay, config.learner.keep_checkpoints)
    };
    let publish = |dqn: &Dqn, progress: &mut Progress| {
        if !dqn.online.all_finite() {
            warn!(updates = progress.updates, "the online network holds non-finite weights: not publishing them");
            return;
        }
        progress.weights_version += 1;
        let message = proto::Weights {
            protocol_version: PROTOCOL_VERSION,
            run_id: run_id.to_string(),
            version: progress.weights_version,
            learner_step: progress.updates,
            network: Some((&dqn.config.network).into()),
            safetensors: checkpoint::encode_weights(&dqn.online),
            learner_session: progress.learner_session,
        }
        .encode_to_vec();
        *lock(&shared.latest_weights) = message.clone();
        // Dropped when the publisher is busy: a newer version follows soon.
        let _ = weights_out.try_send(message);
    };
    publish(&dqn, &mut progress);

    let limits_reached = |progress: &Progress, elapsed: f64| {
        let l = &config.learner;
        (l.max_updates > 0 && progress.updates >= l.max_updates)
            || (l.max_seconds > 0.0 && elapsed >= l.max_seconds)
            || (l.max_env_steps > 0 && progress.env_steps >= l.max_env_steps)
    };
    while !stop.load(Ordering::SeqCst) && !limits_reached(&progress, session_start.elapsed().as_secs_f64()) {
        // Take what has arrived; wait briefly only when there is nothing to train on.
        let mut received = 0;
        let wait = if rate.can_sample(batch_size) { Duration::ZERO } else { Duration::from_millis(5) };
        let mut next = match ingest.recv_timeout(wait) {
            Ok(batch) => Some(batch),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        while let Some(batch) = next.take() {
            received += insert_batch(&mut replay, &batch, shared);
            progress.env_steps += batch.len() as u64;
            progress.physics_steps += batch.physics_steps;
            if received < 16 * batch_size.max(256) {
                next = ingest.try_recv().ok();
            }
        }
        rate.record_insert(received, replay.len());

        if rate.can_sample(batch_size) && replay.len() >= batch_size {
            let beta = config.replay.prioritized.map_or(0.0, |p| p.beta(progress.updates));
            if replay.sample(batch_size, config.dqn.gamma, beta, &mut rng, &mut sample).is_ok() {
                let stats = dqn.update(&to_batch(&sample, batch_size, config.replay.prioritized.is_some()));
                rate.record_sample(batch_size);
                if stats.applied {
                    replay.update_priorities(&sample.keys, &stats.td_errors);
                    progress.updates += 1;
                    last_loss = (stats.loss, stats.mean_q);
                    losses.add(stats.loss, stats.mean_q);
                    if progress.updates.is_multiple_of(config.learner.weights_every) {
                        publish(&dqn, &mut progress);
                    }
                    let every = config.learner.checkpoint_every;
                    if every > 0 && progress.updates.is_multiple_of(every) {
                        // A failed periodic checkpoint (disk full, say) is logged; training goes
                        // on and the older checkpoints stay. The final one's error is returned.
                        match save_checkpoint(&dqn, &mut progress, None) {
                            Ok(path) => last_checkpoint = Some(path),
                            Err(e) => warn!("periodic checkpoint failed: {e}"),
                        }
                    }
                } else {
                    // The weights were left as they were; status and metrics still go out below.
                    let skipped = shared.skipped_updates.fetch_add(1, Ordering::Relaxed) + 1;
                    if skipped <= 3 || skipped.is_multiple_of(1000) {
                        warn!(skipped, loss = stats.loss, grad_norm = stats.grad_norm, "skipped a non-finite update");
                    }
                }
            }
        }

        if metrics_clock.elapsed() >= METRICS_EVERY {
            flush_metrics(&mut metrics, shared, &mut losses, train_seconds(), progress.env_steps);
            metrics_clock = Instant::now();
        }

        if status_clock.elapsed().as_secs_f64() >= config.learner.status_every_s {
            let seconds = status_clock.elapsed().as_secs_f64();
            let actors = lock(&shared.actors).clone();
            actor_transitions.retain(|id, _| actors.contains_key(id));
            let ingest_per_second = actors
                .iter()
                .map(|(&id, view)| {
                    let before = actor_transitions.insert(id, view.transitions).unwrap_or(0);
                    (id, view.transitions.saturating_sub(before) as f64 / seconds)
                })
                .collect();
            let status = Status {
                run_id: run_id.to_string(),
                elapsed_s: train_seconds(),
                updates: progress.updates,
                updates_per_second: (progress.updates - status_counts.0) as f64 / seconds,
                env_steps: progress.env_steps,
                env_steps_per_second: (progress.env_steps - status_counts.1) as f64 / seconds,
                physics_steps: progress.physics_steps,
                replay_len: replay.len(),
                weights_version: progress.weights_version,
                loss: last_loss.0,
                mean_q: last_loss.1,
                connected_actors: shared.connected().into_iter().collect(),
                actors,
                ingest_per_second,
                rejected: lock(&shared.rejected).clone(),
                dropped_batches: shared.dropped_batches.load(Ordering::Relaxed),
                skipped_updates: shared.skipped_updates.load(Ordering::Relaxed),
                ignored_tokens: shared.ignored_tokens.load(Ordering::Relaxed),
                last_checkpoint: last_checkpoint.as_ref().map(|p| p.display().to_string()),
                last_evaluation_speed: lock(&shared.evaluation).as_ref().map(|e| e.speed),
            };
            report(&status, run_dir);
            if status.connected_actors.is_empty() && status.env_steps_per_second == 0.0 {
                warn!("no actor is connected and no transitions arrive: training waits for actors");
            }
            write_status_metrics(&mut metrics, &status, shared);
            status_clock = Instant::now();
            status_counts = (progress.updates, progress.env_steps);
        }
    }

    // What arrived since the last flush still reaches the metrics.
    flush_metrics(&mut metrics, shared, &mut losses, train_seconds(), progress.env_steps);

    let snapshot = config.learner.snapshot_replay.then_some(&replay);
    let path = save_checkpoint(&dqn, &mut progress, snapshot)?;
    info!(updates = progress.updates, env_steps = progress.env_steps, "final checkpoint {}", path.display());
    Ok(Outcome { progress, last_checkpoint: Some(path) })
}

/// TD loss and mean Q, averaged between metric writes.
#[derive(Debug, Default)]
struct LossAverage {
    loss: f64,
    mean_q: f64,
    count: u64,
}

impl LossAverage {
    fn add(&mut self, loss: f64, mean_q: f64) {
        self.loss += loss;
        self.mean_q += mean_q;
        self.count += 1;
    }
}

/// Writes pending episodes and the averaged loss, then flushes, so a reader (TensorBoard,
/// `plot`) sees everything up to now. Metrics are best effort: a failure is logged, and
/// training goes on.
fn flush_metrics(
    metrics: &mut MetricsWriter,
    shared: &Shared,
    losses: &mut LossAverage,
    train_seconds: f64,
    env_steps: u64,
) {
    write_episode_metrics(metrics, shared, train_seconds, env_steps);
    if losses.count > 0 {
        let n = losses.count as f64;
        let scalars = [("train/loss", losses.loss / n), ("train/mean_q", losses.mean_q / n)];
        if let Err(e) = metrics.write(train_seconds, env_steps, &scalars) {
            warn!("metrics: {e}");
        }
        *losses = LossAverage::default();
    }
    if let Err(e) = metrics.flush() {
        warn!("metrics: {e}");
    }
}

/// Every pending episode as scalars: `episode/*` for training actors (also per actor, with
/// its ε) and `eval/*` for evaluators.
fn write_episode_metrics(metrics: &mut MetricsWriter, shared: &Shared, train_seconds: f64, env_steps: u64) {
    let episodes = std::mem::take(&mut *lock(&shared.pending_episodes));
    for e in episodes {
        let group = if e.evaluation { "eval" } else { "episode" };
        let fields = [
            ("distance", f64::from(e.distance)),
            ("duration", f64::from(e.duration)),
            ("return", f64::from(e.episode_return)),
            ("return_position", f64::from(e.return_position)),
            ("return_upright", f64::from(e.return_upright)),
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

fn mean_epsilon(shared: &Shared) -> f64 {
    let actors = lock(&shared.actors);
    if actors.is_empty() { 0.0 } else { actors.values().map(|a| a.epsilon).sum::<f64>() / actors.len() as f64 }
}

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

/// Logs a status line and rewrites `status.json` atomically.
fn report(status: &Status, run_dir: &Path) {
    let per_actor: Vec<String> = status
        .actors
        .iter()
        .map(|(id, a)| {
            let rate = status.ingest_per_second.get(id).copied().unwrap_or(0.0);
            format!("#{id} {rate:.0}/s ε={:.4} v{} {:.2} m/s", a.epsilon, a.weights_version, a.speed_ema)
        })
        .collect();
    info!(
        "updates {} ({:.0}/s) | env steps {} ({:.0}/s) | replay {} | weights v{} | loss {:.4} | connected {:?} | {}",
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

/// Whether any endpoint listens on an address other than loopback.
pub fn listens_beyond_loopback(listen: &[String]) -> bool {
    listen.iter().any(|endpoint| !is_loopback_endpoint(endpoint))
}

/// `PROTOCOL/HOST:PORT` with HOST 127.x.y.z, localhost or [::1].
pub fn is_loopback_endpoint(endpoint: &str) -> bool {
    let address = endpoint.split_once('/').map_or(endpoint, |(_, a)| a);
    let address = address.split('#').next().unwrap_or(address);
    let host = address.rsplit_once(':').map_or(address, |(h, _)| h);
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost" || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn live_nodes_are_capped_and_leave_room_when_they_go() {
        let mut live = LiveNodes { max: 3, ..LiveNodes::default() };
        assert_eq!(live.admit(NodeKind::Actor, 0), Admission::Admitted);
        assert_eq!(live.admit(NodeKind::Actor, 0), Admission::AlreadyLive);
        assert_eq!(live.admit(NodeKind::Evaluator, 0), Admission::Admitted);
        assert_eq!(live.admit(NodeKind::Actor, 1), Admission::Admitted);
        assert_eq!(live.admit(NodeKind::Actor, 2), Admission::Full);
        assert!(!live.holds(NodeKind::Actor, 2));
        assert!(live.leave(NodeKind::Actor, 1));
        assert!(!live.leave(NodeKind::Actor, 1));
        assert_eq!(live.admit(NodeKind::Actor, 2), Admission::Admitted);
        assert!(live.holds(NodeKind::Evaluator, 0) && !live.holds(NodeKind::Evaluator, 2));
    }

    #[test]
    fn assignments_stay_small_under_a_flood_of_queries() {
        let shared = Shared::new(64);
        lock(&shared.live).actors.extend([0, 1]);
        let ids: Vec<u32> = (0..3000).map(|_| assign_actor_id(&shared)).collect();
        assert!(ids.iter().all(|&id| (2..2 + MAX_PENDING_ASSIGNMENTS as u32 + 1).contains(&id)), "{ids:?}");
        assert!(lock(&shared.assigned).len() <= MAX_PENDING_ASSIGNMENTS);
    }

    #[test]
    fn loopback_endpoints_are_told_apart() {
        for local in ["tcp/127.0.0.1:7447", "tcp/localhost:7447", "tcp/[::1]:7447", "tls/127.0.0.2:1"] {
            assert!(is_loopback_endpoint(local), "{local}");
        }
        for remote in ["tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/192.168.1.4:7447", "tcp/learner:7447"] {
            assert!(!is_loopback_endpoint(remote), "{remote}");
        }
    }
}
