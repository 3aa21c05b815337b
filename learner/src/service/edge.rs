//! The learner's network edge: every zenoh callback, apart from training.
//!
//! Callbacks validate what arrives (`proto::validate`, the sender's id against the key and a
//! live token), count what they reject, and touch only [`Shared`]: small tables behind
//! short-lived mutexes. Transition batches go to the inserting thread through a bounded queue
//! with `try_send`, so nothing here ever waits for replay or training.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use crawler_env::observation;
use crawler_proto::{self as proto, PROTOCOL_VERSION, SequenceTracker, TransitionLimits, keys};
use crawler_run::config::TrainConfig;
use prost::Message;
use serde::Serialize;
use tracing::{debug, info, warn};
use zenoh::Wait;
use zenoh::sample::SampleKind;

use super::credit::CreditLedger;
use super::fair_share::{Budgets, FairShares};
use super::{ServiceError, zenoh_error};

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
    /// Share of its last status interval the actor's simulation waited to hand over a
    /// message (for insert credit, or for a slow link).
    pub waiting_fraction: f32,
}

/// Which kind of node a liveliness token announces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub(super) enum NodeKind {
    Actor,
    Evaluator,
}

/// The nodes holding a liveliness token, at most `max` of them: only their messages are kept,
/// so every per-actor table is bounded by `max`. Tokens that arrive while every slot is taken
/// wait, in arrival order and at most `max` of them, and take the slots that come free: a
/// token event is never sent twice, so a node turned away and forgotten would stay out.
#[derive(Debug, Default)]
pub(super) struct LiveNodes {
    pub(super) actors: BTreeSet<u32>,
    evaluators: BTreeSet<u32>,
    waiting: VecDeque<(NodeKind, u32)>,
    pub(super) max: usize,
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
            if self.waiting.len() < self.max && !self.waiting.contains(&(kind, id)) {
                self.waiting.push_back((kind, id));
            }
            Admission::Full
        } else {
            self.set(kind).insert(id);
            Admission::Admitted
        }
    }

    /// Takes a node's token off the books. Returns whether it was live, and the waiting node
    /// that took its slot, if any.
    fn leave(&mut self, kind: NodeKind, id: u32) -> (bool, Option<(NodeKind, u32)>) {
        self.waiting.retain(|&waiting| waiting != (kind, id));
        if !self.set(kind).remove(&id) {
            return (false, None);
        }
        let promoted = self.waiting.pop_front();
        if let Some((kind, id)) = promoted {
            self.set(kind).insert(id);
        }
        (true, promoted)
    }
}

/// State shared between zenoh callbacks, the inserting and training threads and status reports.
#[derive(Debug, Default)]
pub(super) struct Shared {
    pub(super) actors: Mutex<BTreeMap<u32, ActorView>>,
    pub(super) live: Mutex<LiveNodes>,
    /// Last sequence number per live actor (forgotten when it leaves).
    pub(super) sequences: Mutex<SequenceTracker>,
    pub(super) rejected: Mutex<BTreeMap<&'static str, u64>>,
    /// Liveliness tokens beyond `learner.max_actors`, ignored.
    pub(super) ignored_tokens: AtomicU64,
    /// Actors that left since the inserting thread last looked: it releases their replay
    /// streams.
    pub(super) departed: Mutex<Vec<u32>>,
    /// Actor ids that have metric tags of their own.
    pub(super) tagged_actors: Mutex<BTreeSet<u32>>,
    pub(super) latest_weights: Mutex<Vec<u8>>,
    pub(super) dropped_batches: AtomicU64,
    pub(super) skipped_updates: AtomicU64,
    pub(super) evaluation: Mutex<Option<proto::EpisodeStats>>,
    /// Ids handed to `--id auto` actors, and when: reserved until the actor shows up.
    pub(super) assigned: Mutex<BTreeMap<u32, Instant>>,
    /// Episodes not yet written to the metrics; bounded by [`MAX_PENDING_EPISODES`].
    pub(super) pending_episodes: Mutex<Vec<proto::EpisodeStats>>,
    /// Transitions in the ingest queue, not yet in replay.
    pub(super) queued_transitions: AtomicU64,
    /// Transitions ever put in the ingest queue (they may since have been inserted).
    pub(super) admitted_transitions: AtomicU64,
    /// How many admitted transitions the learner takes in all, as the training thread last
    /// worked it out from the rate limiter: `admitted_transitions` then, plus the headroom
    /// (`credit.rs`). `u64::MAX` when inserts are not limited; 0 until training starts.
    pub(super) insert_limit: AtomicU64,
    /// Insert credit granted to each live actor.
    pub(super) credits: Mutex<CreditLedger>,
    /// Each live sender's share of the ingest queue, the pending episodes, status reports
    /// and log lines.
    pub(super) shares: Mutex<FairShares>,
}

impl Shared {
    pub(super) fn new(max_actors: usize, budgets: Budgets) -> Self {
        Self {
            live: Mutex::new(LiveNodes { max: max_actors, ..LiveNodes::default() }),
            shares: Mutex::new(FairShares::new(budgets)),
            ..Self::default()
        }
    }

    /// Live actors and evaluators, in all.
    fn live_senders(&self) -> usize {
        let live = lock(&self.live);
        live.actors.len() + live.evaluators.len()
    }

    pub(super) fn connected(&self) -> BTreeSet<u32> {
        lock(&self.live).actors.clone()
    }

    /// Whether actor `id` gets metric tags of its own (`actor/<id>/…`): the first
    /// `learner.max_actors` ids do, so that churn of ids cannot grow the tag set without bound.
    pub(super) fn may_tag(&self, id: u32) -> bool {
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

pub(super) fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// What the edge declared on the router; dropping it undeclares everything.
#[derive(Debug)]
pub(super) struct Edge {
    _queryables: [zenoh::query::Queryable<()>; 2],
    _subscribers: [zenoh::pubsub::Subscriber<()>; 3],
    _liveliness: [zenoh::pubsub::Subscriber<()>; 2],
    _token: zenoh::liveliness::LivelinessToken,
}

/// Declares the run's queryables (run info, latest weights), its subscribers (transitions
/// into `ingest`, episode stats, actor status), the liveliness watches, and the learner's
/// own liveliness token.
pub(super) async fn serve(
    session: &zenoh::Session,
    config: &TrainConfig,
    run_id: &str,
    shared: &Arc<Shared>,
    ingest: SyncSender<proto::TransitionBatch>,
) -> Result<Edge, ServiceError> {
    let run_info = proto::RunInfo {
        protocol_version: PROTOCOL_VERSION,
        run_id: run_id.to_string(),
        settings: Some((&config.actor_settings()).into()),
        assigned_actor_id: None,
    };
    let info_key = keys::info(run_id);
    let reply_key = info_key.clone();
    let info_shared = Arc::clone(shared);
    let info = session
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
    let weights_key = keys::weights(run_id);
    let weights_shared = Arc::clone(shared);
    let served_key = weights_key.clone();
    let weights = session
        .declare_queryable(&weights_key)
        .callback(move |query| {
            let latest = lock(&weights_shared.latest_weights).clone();
            if !latest.is_empty() {
                let _ = query.reply(&served_key, latest).wait();
            }
        })
        .await
        .map_err(zenoh_error("declaring the weights queryable"))?;
    let limits = transition_limits(config, run_id);
    let transitions = session
        .declare_subscriber(keys::all_transitions(run_id))
        .callback(ingest_callback(
            limits,
            config.rate.limit_inserts,
            config.learner.ingest_queue,
            ingest,
            Arc::clone(shared),
        ))
        .await
        .map_err(zenoh_error("subscribing to transitions"))?;
    let stats = session
        .declare_subscriber(keys::all_stats(run_id))
        .callback(validated(shared, run_id, proto::validate::episode_stats, record_episode))
        .await
        .map_err(zenoh_error("subscribing to stats"))?;
    let status = session
        .declare_subscriber(keys::all_status(run_id))
        .callback(validated(shared, run_id, proto::validate::actor_status, record_status))
        .await
        .map_err(zenoh_error("subscribing to status"))?;
    let actors = watch_liveliness(session, keys::all_alive_actors(run_id), shared, NodeKind::Actor).await?;
    let evaluators = watch_liveliness(session, keys::all_alive_evaluators(run_id), shared, NodeKind::Evaluator).await?;
    let token = session
        .liveliness()
        .declare_token(keys::alive_learner(run_id))
        .await
        .map_err(zenoh_error("declaring liveliness"))?;
    Ok(Edge {
        _queryables: [info, weights],
        _subscribers: [transitions, stats, status],
        _liveliness: [actors, evaluators],
        _token: token,
    })
}

/// Follows the liveliness tokens of one kind of node under `key`, those already there too.
async fn watch_liveliness(
    session: &zenoh::Session,
    key: String,
    shared: &Arc<Shared>,
    kind: NodeKind,
) -> Result<zenoh::pubsub::Subscriber<()>, ServiceError> {
    session
        .liveliness()
        .declare_subscriber(key)
        .history(true)
        .callback(liveliness_callback(Arc::clone(shared), kind))
        .await
        .map_err(zenoh_error("watching liveliness"))
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
    drop(assigned);
    if lock(&shared.shares).unattributed_log_line_passes("assigned an actor id", Instant::now()) {
        info!(actor = id, "assigned an actor id");
    }
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
        let id = match keys::trailing_id(sample.key_expr().as_str()) {
            Ok(id) => id,
            // Counted, and never allowed near a live node's books.
            Err(e) => return count_rejection(&shared, &e),
        };
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
                            "more live nodes than learner.max_actors: this one waits for a free slot"
                        );
                    }
                }
                Admission::Admitted => {
                    drop(live);
                    connected(&shared, kind, id);
                }
            },
            SampleKind::Delete => {
                let (was_live, promoted) = live.leave(kind, id);
                drop(live);
                lock(&shared.shares).forget((kind, id));
                if was_live && lock(&shared.shares).unattributed_log_line_passes("node left", Instant::now()) {
                    info!(id, ?kind, "node left");
                    if kind == NodeKind::Actor {
                        lock(&shared.sequences).forget(id);
                        lock(&shared.departed).push(id);
                    }
                }
                if let Some((kind, id)) = promoted {
                    connected(&shared, kind, id);
                }
            }
        }
    }
}

/// Logs a node that took a slot, and makes room among the views of actors that left.
fn connected(shared: &Shared, kind: NodeKind, id: u32) {
    if lock(&shared.shares).unattributed_log_line_passes("node connected", Instant::now()) {
        info!(id, ?kind, "node connected");
    }
    // Views of actors that left stay for status.json until room is needed.
    let (live_actors, max) = {
        let live = lock(&shared.live);
        (live.actors.clone(), live.max)
    };
    let mut views = lock(&shared.actors);
    if views.len() >= max {
        views.retain(|id, _| live_actors.contains(id));
    }
}

fn record_status(shared: &Shared, report: proto::ActorStatus) {
    if !lock(&shared.shares).status_passes(report.node(), Instant::now()) || report.evaluator {
        return;
    }
    let mut actors = lock(&shared.actors);
    let view = actors.entry(report.actor_id).or_default();
    view.weights_version = report.weights_version;
    view.env_steps = report.env_steps;
    view.env_steps_per_second = report.env_steps_per_second;
    view.epsilon = report.epsilon;
    view.waiting_fraction = report.waiting_fraction;
}

fn record_episode(shared: &Shared, stats: proto::EpisodeStats) {
    let sender = stats.node();
    let senders = shared.live_senders();
    if !lock(&shared.shares).enter_pending_episodes(sender, MAX_PENDING_EPISODES, senders) {
        return;
    }
    {
        let mut pending = lock(&shared.pending_episodes);
        if pending.len() < MAX_PENDING_EPISODES {
            pending.push(stats.clone());
        }
    }
    if stats.evaluation {
        if lock(&shared.shares).log_line_passes(sender, "evaluation episode", Instant::now()) {
            info!(
                speed = stats.speed,
                distance = stats.distance,
                weights = stats.weights_version,
                "evaluation episode"
            );
        }
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

/// What a valid transition batch of this run holds.
pub fn transition_limits(config: &TrainConfig, run_id: &str) -> TransitionLimits {
    TransitionLimits {
        run_id: run_id.to_string(),
        obs_dim: config.env.policy_input_dim() as u32,
        num_actions: config.env.num_actions() as u32,
        max_batch: proto::MAX_BATCH_TRANSITIONS,
        envs_per_actor: config.actor.envs_per_actor as u32,
        // One observation's ranges for each slot of the history.
        observation_range: observation::observation_range(config.env.max_torque)
            .repeat(config.env.observation_history as usize),
        max_abs_reward: crawler_env::Reward::max_abs_total(&config.env),
    }
}

/// Validates a transition batch, checks it against the actor's insert credit (when
/// `limit_inserts`) and its sequence, and queues it for the inserting thread.
fn ingest_callback(
    limits: TransitionLimits,
    limit_inserts: bool,
    capacity: usize,
    queue: SyncSender<proto::TransitionBatch>,
    shared: Arc<Shared>,
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    move |sample| {
        let batch = match proto::validate::transition_batch(&sample.payload().to_bytes(), &limits)
            .and_then(|batch| from_live_sender(&shared, sample.key_expr().as_str(), batch))
            .and_then(|batch| {
                // Before the credit check, so that a played-back batch cannot use up the
                // introduction a restarted actor needs.
                lock(&shared.sequences).refuse_retired(batch.actor_id, batch.incarnation)?;
                Ok(batch)
            }) {
            Ok(batch) => batch,
            Err(e) => return count_rejection(&shared, &e),
        };
        // Before the sequence check, so that a refused batch does not advance the
        // acknowledgement its actor's next credit counts from.
        if limit_inserts
            && !lock(&shared.credits).admit(batch.actor_id, batch.incarnation, batch.sequence, Instant::now())
        {
            let error = proto::ProtoError::OverCredit { actor: batch.actor_id, sequence: batch.sequence };
            return count_rejection(&shared, &error);
        }
        let check = lock(&shared.sequences).check(batch.actor_id, batch.incarnation, batch.sequence, Instant::now());
        match check {
            Err(e) => return count_rejection(&shared, &e),
            Ok(proto::validate::SequenceCheck::Gap { missing }) => {
                lock(&shared.actors).entry(batch.actor_id).or_default().gaps += missing;
            }
            Ok(_) => {}
        }
        // A sender that holds its share of the queue cannot take the others' room.
        let actor = batch.actor_id;
        let actors = lock(&shared.live).actors.len();
        if !lock(&shared.shares).enter_queue(actor, capacity, actors) {
            return;
        }
        // Counted before the send, so that the inserting thread never takes out more than
        // went in.
        let transitions = batch.len() as u64;
        shared.queued_transitions.fetch_add(transitions, Ordering::Relaxed);
        match queue.try_send(batch) {
            Ok(()) => {
                shared.admitted_transitions.fetch_add(transitions, Ordering::Relaxed);
            }
            Err(TrySendError::Full(_)) => {
                lock(&shared.shares).leave_queue(actor);
                shared.queued_transitions.fetch_sub(transitions, Ordering::Relaxed);
                let dropped = shared.dropped_batches.fetch_add(1, Ordering::Relaxed) + 1;
                if dropped <= 3 || dropped.is_multiple_of(100) {
                    warn!(dropped, "ingest queue full: training is behind the actors; dropping a batch");
                }
            }
            Err(TrySendError::Disconnected(_)) => {
                lock(&shared.shares).leave_queue(actor);
                shared.queued_transitions.fetch_sub(transitions, Ordering::Relaxed);
            }
        }
    }
}

/// The mean ε the live actors reported last (0 with none).
pub(super) fn mean_epsilon(shared: &Shared) -> f64 {
    let actors = lock(&shared.actors);
    if actors.is_empty() { 0.0 } else { actors.values().map(|a| a.epsilon).sum::<f64>() / actors.len() as f64 }
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
        assert_eq!(live.leave(NodeKind::Actor, 1), (true, Some((NodeKind::Actor, 2))));
        assert_eq!(live.leave(NodeKind::Actor, 1), (false, None));
        assert!(live.holds(NodeKind::Actor, 2), "the node that waited takes the free slot");
        assert!(live.holds(NodeKind::Evaluator, 0) && !live.holds(NodeKind::Evaluator, 2));
    }

    #[test]
    fn waiting_nodes_are_bounded_and_a_waiter_that_leaves_takes_no_slot() {
        let mut live = LiveNodes { max: 2, ..LiveNodes::default() };
        for id in 0..2 {
            assert_eq!(live.admit(NodeKind::Actor, id), Admission::Admitted);
        }
        for id in 10..1000 {
            assert_eq!(live.admit(NodeKind::Actor, id), Admission::Full);
        }
        assert_eq!(live.waiting.len(), 2, "squatters cannot queue without bound");
        assert_eq!(live.leave(NodeKind::Actor, 10), (false, None));
        assert_eq!(live.leave(NodeKind::Actor, 0), (true, Some((NodeKind::Actor, 11))));
        assert_eq!(live.leave(NodeKind::Actor, 1), (true, None));
        assert_eq!(live.admit(NodeKind::Actor, 5), Admission::Admitted);
    }

    #[test]
    fn assignments_stay_small_under_a_flood_of_queries() {
        let shared = Shared::new(64, Budgets::default());
        lock(&shared.live).actors.extend([0, 1]);
        let ids: Vec<u32> = (0..3000).map(|_| assign_actor_id(&shared)).collect();
        assert!(ids.iter().all(|&id| (2..2 + MAX_PENDING_ASSIGNMENTS as u32 + 1).contains(&id)), "{ids:?}");
        assert!(lock(&shared.assigned).len() <= MAX_PENDING_ASSIGNMENTS);
    }
}
