//! The actor process: a zenoh client that simulates crawlers and feeds the learner.
//!
//! Two halves: an async half (zenoh I/O, status, signals) and a simulation thread that steps
//! K crawlers with batched plain-Rust inference. They meet at three points, each bounded:
//! - the latest weights, in a `watch` channel: the simulation swaps them in between steps;
//! - outgoing messages, in a bounded channel: when the link is slow, or the learner's insert
//!   credit (`proto::InsertCredit`) does not yet admit the next batch, the simulation waits
//!   (back-pressure) instead of queueing without limit;
//! - a stop flag.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crawler_proto::{self as proto, PROTOCOL_VERSION, keys};
use prost::Message;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tokio::sync::{mpsc, watch};
use tracing::{debug, info, warn};
use zenoh::qos::CongestionControl;

use crawler_env::policy::{MlpPolicy, NetworkSpec, PolicyError};
use crawler_env::settings::ActorSettings;
use crawler_env::{EpisodeSummary, VecEnv};

/// How to run an actor.
#[derive(Debug, Clone)]
pub struct ActorOptions {
    /// zenoh endpoints of the learner, e.g. `tcp/127.0.0.1:7447`.
    pub connect: Vec<String>,
    /// This actor's id; `None`: ask the learner for a free one (`--id auto`).
    pub id: Option<u32>,
    /// The run to join; when absent, the first run a learner offers.
    pub run: Option<String>,
    /// ε = 0 and only evaluation stats are published.
    pub evaluator: bool,
    /// Extra zenoh settings as JSON5 `key=value` pairs (TLS, auth), applied last.
    pub zenoh_overrides: Vec<(String, String)>,
    /// Stop after this many decisions per crawler (none: run until told to stop).
    pub max_steps: Option<u64>,
    /// A file touched at every status report (container health checks).
    pub heartbeat: Option<std::path::PathBuf>,
}

#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("zenoh: {context}: {message}")]
    Zenoh { context: String, message: String },
    #[error("the run id is not usable: {0}")]
    RunId(#[source] proto::ProtoError),
    #[error("the learner assigned no actor id: pass --id N")]
    NoActorId,
    #[error("stopped before a learner answered")]
    StoppedBeforeLearnerAnswered,
    #[error("cannot start the simulation thread: {0}")]
    SimulationThread(#[source] std::io::Error),
    #[error("the simulation thread panicked; the log above says where")]
    SimulationPanicked,
    #[error("weights rejected: {0}")]
    WeightsRejected(#[source] proto::ProtoError),
    #[error("weights carry no network spec")]
    WeightsWithoutNetwork,
    #[error("weights of a {found_obs}→{found_actions} network do not fit this environment's {obs}→{actions}")]
    WeightsShape { found_obs: usize, found_actions: usize, obs: usize, actions: usize },
    #[error("weights unusable: {0}")]
    Policy(#[from] PolicyError),
}

fn zenoh_error(context: impl Into<String>) -> impl FnOnce(zenoh::Error) -> NodeError {
    let context = context.into();
    move |e| NodeError::Zenoh { context, message: e.to_string() }
}

/// A client config that waits for the learner forever and retries quickly.
pub fn client_config(connect: &[String], overrides: &[(String, String)]) -> Result<zenoh::Config, NodeError> {
    let mut config = zenoh::Config::default();
    let endpoints = crawler_cli::zenoh_string_list(connect);
    let settings = [
        ("mode", "\"client\"".to_string()),
        ("connect/endpoints", endpoints),
        ("connect/timeout_ms", "-1".to_string()),
        ("connect/exit_on_failure", "false".to_string()),
        ("connect/retry", "{ period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2 }".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
        // Nothing larger than the protocol's largest message is buffered (zenoh's default is 1 GiB).
        ("transport/link/rx/max_message_size", proto::TRANSPORT_MAX_MESSAGE_BYTES.to_string()),
    ];
    for (key, value) in settings.iter().map(|(k, v)| (k.to_string(), v.clone())).chain(overrides.iter().cloned()) {
        config.insert_json5(&key, &value).map_err(zenoh_error(format!("setting {key} = {value}")))?;
    }
    Ok(config)
}

/// Weights the simulation can act with.
#[derive(Debug)]
struct PublishedPolicy {
    /// The learner process that published these; see [`PublishedPolicy::order`].
    session: u64,
    version: u64,
    policy: MlpPolicy,
}

impl PublishedPolicy {
    /// (learner session, version): the order in which weights supersede one another.
    fn order(&self) -> (u64, u64) {
        (self.session, self.version)
    }
}

enum Outgoing {
    Batch(proto::TransitionBatch),
    Stats(proto::EpisodeStats),
}

/// Counters shared between the simulation and status reports.
#[derive(Debug, Default)]
struct Counters {
    env_steps: AtomicU64,
    physics_steps: AtomicU64,
    weights_version: AtomicU64,
    epsilon_bits: AtomicU64,
    /// Nanoseconds the simulation spent waiting to hand over a message.
    waiting_nanos: AtomicU64,
}

/// Hands `message` to the publisher, counting the time the simulation waits for room (the
/// learner's insert credit, or a slow link); false once the publisher has gone.
fn hand_over(out: &mpsc::Sender<Outgoing>, message: Outgoing, counters: &Counters) -> bool {
    let message = match out.try_send(message) {
        Ok(()) => return true,
        Err(mpsc::error::TrySendError::Closed(_)) => return false,
        Err(mpsc::error::TrySendError::Full(message)) => message,
    };
    let start = Instant::now();
    let sent = out.blocking_send(message).is_ok();
    counters.waiting_nanos.fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
    sent
}

/// Runs an actor until the learner says stop, `stop` is set, or `max_steps` is reached.
pub async fn run(mut options: ActorOptions, stop: Arc<AtomicBool>) -> Result<(), NodeError> {
    let Some(session) = connect(&options, &stop).await? else {
        info!("stopped before reaching a learner");
        return Ok(());
    };
    let (run_id, settings, assigned) =
        fetch_run_info(&session, options.run.as_deref(), options.id.is_none(), &stop).await?;
    let id = options.id.or(assigned).ok_or(NodeError::NoActorId)?;
    options.id = Some(id);
    info!(run = %run_id, id, envs = settings.envs_per_actor, evaluator = options.evaluator, "joined run");

    let (weights, policy_rx) = WeightsFeed::new(&run_id, settings.env.policy_input_dim(), settings.env.num_actions());
    // Evaluators publish no transitions, so they need no credit.
    let (credit_tx, credit_rx) = watch::channel(None);
    let _credit =
        if options.evaluator { None } else { Some(subscribe_credit(&session, &run_id, id, credit_tx).await?) };
    let _subscriptions = subscribe(&session, &run_id, &weights, &stop, id, options.evaluator).await?;
    weights.wait_for_first(&session, &policy_rx, &stop).await;
    let publishers = Publishers::declare(&session, &run_id, id).await?;
    // Distinct per process: start time mixed with the process id.
    let started = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64);
    let incarnation = (started ^ (u64::from(std::process::id()) << 40)).max(1);
    let gate = (!options.evaluator).then(|| CreditGate::new(incarnation, credit_rx));

    let counters = Arc::new(Counters::default());
    let (out_tx, out_rx) = mpsc::channel::<Outgoing>(8);
    let simulation = {
        let (stop, counters, settings) = (Arc::clone(&stop), Arc::clone(&counters), settings.clone());
        let (run_id, options) = (run_id.clone(), options.clone());
        std::thread::Builder::new()
            .name("simulation".into())
            .spawn(move || simulate(&options, &run_id, &settings, incarnation, policy_rx, &out_tx, &stop, &counters))
            .map_err(NodeError::SimulationThread)?
    };
    let reporter = StatusReporter { run_id: &run_id, id, settings: &settings, options: &options, counters: &counters };
    publishers.forward(out_rx, gate, reporter, &stop).await;
    let result = simulation.join();
    info!("actor {id} stopped");
    let _ = session.close().await;
    result.map_err(|_| NodeError::SimulationPanicked)
}

/// Opens the session to the learner; None when `stop` came first.
async fn connect(options: &ActorOptions, stop: &AtomicBool) -> Result<Option<zenoh::Session>, NodeError> {
    let config = client_config(&options.connect, &options.zenoh_overrides)?;
    info!(endpoints = ?options.connect, id = ?options.id, "connecting to the learner");
    // With connect/timeout_ms = -1, opening waits for the learner forever, and its future
    // blocks the thread that polls it; open on a blocking thread so a signal can end the wait.
    let opening = tokio::task::spawn_blocking(move || zenoh::Wait::wait(zenoh::open(config)));
    tokio::select! {
        session = opening => Ok(Some(session
            .map_err(|e| NodeError::Zenoh { context: "opening the session".into(), message: e.to_string() })?
            .map_err(zenoh_error("opening the session"))?)),
        () = stopped(stop) => Ok(None),
    }
}

/// Where weights from the learner (published or queried) are checked and, when newer than
/// what the simulation holds, handed to it.
#[derive(Debug, Clone)]
struct WeightsFeed {
    run_id: String,
    /// The shape this env needs (input and action counts; hidden layers come with the weights).
    expected: NetworkSpec,
    policy_tx: Arc<watch::Sender<Option<Arc<PublishedPolicy>>>>,
}

impl WeightsFeed {
    fn new(
        run_id: &str,
        input_dim: usize,
        num_actions: usize,
    ) -> (Self, watch::Receiver<Option<Arc<PublishedPolicy>>>) {
        let expected = NetworkSpec { obs_dim: input_dim, hidden: vec![], num_actions, layer_norm: true };
        let (policy_tx, policy_rx) = watch::channel::<Option<Arc<PublishedPolicy>>>(None);
        (Self { run_id: run_id.to_string(), expected, policy_tx: Arc::new(policy_tx) }, policy_rx)
    }

    /// Takes `bytes` if they are valid weights newer (by learner session, then version) than
    /// the current ones; anything else is logged and ignored.
    fn accept(&self, bytes: &[u8]) {
        match load_weights(bytes, &self.run_id, &self.expected) {
            Ok(loaded) => {
                let newer = self.policy_tx.borrow().as_ref().is_none_or(|p| loaded.order() > p.order());
                if newer {
                    debug!(session = loaded.session, version = loaded.version, "new weights");
                    self.policy_tx.send_replace(Some(Arc::new(loaded)));
                }
            }
            Err(e) => warn!("ignoring weights: {e}"),
        }
    }

    /// A starting actor asks for the latest weights rather than waiting for the next publish.
    async fn wait_for_first(
        &self,
        session: &zenoh::Session,
        policy_rx: &watch::Receiver<Option<Arc<PublishedPolicy>>>,
        stop: &AtomicBool,
    ) {
        let joined = Instant::now();
        let mut waited = Instant::now();
        while policy_rx.borrow().is_none() && !stop.load(Ordering::SeqCst) {
            if let Ok(replies) = session.get(keys::weights(&self.run_id)).timeout(Duration::from_secs(2)).await {
                while let Ok(reply) = replies.recv_async().await {
                    if let Ok(sample) = reply.result() {
                        self.accept(&sample.payload().to_bytes());
                    }
                }
            }
            if policy_rx.borrow().is_none() {
                if waited.elapsed() > Duration::from_secs(10) {
                    info!("still waiting for the learner's weights");
                    waited = Instant::now();
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
        if let Some(policy) = policy_rx.borrow().as_ref() {
            info!(version = policy.version, after_ms = joined.elapsed().as_millis() as u64, "first weights");
        }
    }
}

/// What an actor declared to listen with; dropping it undeclares them.
#[derive(Debug)]
struct Subscriptions {
    _weights: zenoh::pubsub::Subscriber<()>,
    _control: zenoh::pubsub::Subscriber<()>,
    _token: zenoh::liveliness::LivelinessToken,
}

/// Subscribes to weights and to the learner's stop, and declares this node's liveliness
/// token (the learner keeps the messages of live nodes only).
async fn subscribe(
    session: &zenoh::Session,
    run_id: &str,
    weights: &WeightsFeed,
    stop: &Arc<AtomicBool>,
    id: u32,
    evaluator: bool,
) -> Result<Subscriptions, NodeError> {
    let feed = weights.clone();
    let weights = session
        .declare_subscriber(keys::weights(run_id))
        .callback(move |sample| feed.accept(&sample.payload().to_bytes()))
        .await
        .map_err(zenoh_error("subscribing to weights"))?;
    let (control_stop, control_run) = (Arc::clone(stop), run_id.to_string());
    let control = session
        .declare_subscriber(keys::control(run_id))
        .callback(move |sample| {
            if let Ok(control) = proto::validate::control(&sample.payload().to_bytes(), &control_run)
                && control.command == proto::Command::Stop as i32
            {
                info!("learner says stop");
                control_stop.store(true, Ordering::SeqCst);
            }
        })
        .await
        .map_err(zenoh_error("subscribing to control"))?;
    let token_key = if evaluator { keys::alive_evaluator(run_id, id) } else { keys::alive_actor(run_id, id) };
    let token = session.liveliness().declare_token(token_key).await.map_err(zenoh_error("declaring liveliness"))?;
    Ok(Subscriptions { _weights: weights, _control: control, _token: token })
}

/// Follows this actor's insert credit (`crawler/<run>/credit/<id>`): each valid one replaces
/// the last in `credit_tx`.
async fn subscribe_credit(
    session: &zenoh::Session,
    run_id: &str,
    id: u32,
    credit_tx: watch::Sender<Option<proto::InsertCredit>>,
) -> Result<zenoh::pubsub::Subscriber<()>, NodeError> {
    let run = run_id.to_string();
    session
        .declare_subscriber(keys::credit(run_id, id))
        .callback(move |sample| {
            match proto::validate::insert_credit(&sample.payload().to_bytes(), &run, sample.key_expr().as_str()) {
                Ok(credit) => {
                    credit_tx.send_replace(Some(credit));
                }
                Err(e) => debug!("ignoring insert credit: {e}"),
            }
        })
        .await
        .map_err(zenoh_error("subscribing to insert credit"))
}

/// Whether the learner's insert credit admits this process's next batch (`proto::InsertCredit`).
#[derive(Debug)]
pub struct CreditGate {
    incarnation: u64,
    credit_rx: watch::Receiver<Option<proto::InsertCredit>>,
    /// Batches a credit for another incarnation still admits: one per such credit received,
    /// so that a learner that has not heard of this process yet learns of it.
    introductions: u32,
}

impl CreditGate {
    /// A gate for actor process `incarnation`, fed the credits that arrive by `credit_rx`.
    pub fn new(incarnation: u64, credit_rx: watch::Receiver<Option<proto::InsertCredit>>) -> Self {
        Self { incarnation, credit_rx, introductions: 0 }
    }

    /// Takes in a credit that arrived since the last look.
    fn refresh(&mut self) {
        if self.credit_rx.has_changed().unwrap_or(false) {
            let introduces = self
                .credit_rx
                .borrow_and_update()
                .as_ref()
                .is_some_and(|credit| credit.incarnation != self.incarnation && credit.window > 0);
            self.introductions = u32::from(introduces);
        }
    }

    /// Whether batch `sequence` may go now; consumes an introduction when it is one.
    pub fn admit(&mut self, sequence: u64) -> bool {
        self.refresh();
        let credit = self.credit_rx.borrow();
        match credit.as_ref() {
            Some(credit) if credit.incarnation == self.incarnation => credit.admits(self.incarnation, sequence),
            Some(_) if self.introductions > 0 => {
                drop(credit);
                self.introductions -= 1;
                true
            }
            _ => false,
        }
    }

    /// Resolves when a new credit arrives (never, once the learner's session is gone).
    pub async fn changed(&mut self) {
        if self.credit_rx.changed().await.is_err() {
            std::future::pending::<()>().await;
        }
        // Seen by `refresh` in the next `admit`.
        self.credit_rx.mark_changed();
    }
}

/// How long a batch waits for insert credit before the actor says so in its log.
const CREDIT_QUIET: Duration = Duration::from_secs(10);

/// Resolves when the gate sees a new credit; never without a gate.
async fn credit_changed(gate: Option<&mut CreditGate>) {
    match gate {
        Some(gate) => gate.changed().await,
        None => std::future::pending().await,
    }
}

/// The actor's three publishers: transitions block when the link is busy (back-pressure on
/// the simulation), stats and status are dropped instead.
#[derive(Debug)]
struct Publishers {
    transitions: zenoh::pubsub::Publisher<'static>,
    stats: zenoh::pubsub::Publisher<'static>,
    status: zenoh::pubsub::Publisher<'static>,
}

impl Publishers {
    async fn declare(session: &zenoh::Session, run_id: &str, id: u32) -> Result<Self, NodeError> {
        let declare = |key: String, congestion: CongestionControl, what: &'static str| async move {
            session
                .declare_publisher(key)
                .congestion_control(congestion)
                .await
                .map_err(zenoh_error(format!("declaring the {what} publisher")))
        };
        Ok(Self {
            transitions: declare(keys::transitions(run_id, id), CongestionControl::Block, "transitions").await?,
            stats: declare(keys::stats(run_id, id), CongestionControl::Drop, "stats").await?,
            status: declare(keys::status(run_id, id), CongestionControl::Drop, "status").await?,
        })
    }

    /// Publishes what the simulation sends until it ends, and a status report every
    /// `status_interval_s`. With a credit gate, a batch the learner's credit does not admit
    /// yet waits for one that does, and so does everything behind it (the simulation then
    /// waits too, once the channel is full); `stop` ends such a wait.
    async fn forward(
        &self,
        mut out_rx: mpsc::Receiver<Outgoing>,
        mut gate: Option<CreditGate>,
        mut reporter: StatusReporter<'_>,
        stop: &AtomicBool,
    ) {
        let mut ticker = tokio::time::interval(Duration::from_secs_f64(reporter.settings.status_interval_s));
        let mut last = (0u64, reporter.counters.waiting_nanos.load(Ordering::Relaxed), Instant::now());
        let mut waiting: Option<proto::TransitionBatch> = None;
        let mut announced = Instant::now();
        loop {
            tokio::select! {
                message = out_rx.recv(), if waiting.is_none() => {
                    let Some(message) = message else { break };
                    match message {
                        Outgoing::Batch(batch) => {
                            if gate.as_mut().is_none_or(|gate| gate.admit(batch.sequence)) {
                                self.publish(&self.transitions, batch.encode_to_vec()).await;
                            } else {
                                waiting = Some(batch);
                                announced = Instant::now();
                            }
                        }
                        Outgoing::Stats(episode) => self.publish(&self.stats, episode.encode_to_vec()).await,
                    }
                }
                () = credit_changed(gate.as_mut()), if waiting.is_some() => {
                    if let (Some(gate), Some(batch)) = (gate.as_mut(), waiting.as_ref())
                        && gate.admit(batch.sequence)
                        && let Some(batch) = waiting.take()
                    {
                        self.publish(&self.transitions, batch.encode_to_vec()).await;
                    }
                }
                _ = ticker.tick() => {
                    let report = reporter.report(&mut last);
                    let _ = self.status.put(report.encode_to_vec()).await;
                    if waiting.is_some() && announced.elapsed() > CREDIT_QUIET {
                        info!(
                            "no insert credit from the learner for {} s: it is busy, or holds learner.max_actors \
                             actors already (its status.json counts ignored_tokens)",
                            CREDIT_QUIET.as_secs()
                        );
                        announced = Instant::now();
                    }
                }
                () = stopped(stop), if waiting.is_some() => break,
            }
        }
    }

    async fn publish(&self, publisher: &zenoh::pubsub::Publisher<'static>, bytes: Vec<u8>) {
        if let Err(e) = publisher.put(bytes).await {
            warn!("publish failed: {e}");
        }
    }
}

/// Builds the periodic status report from the simulation's counters.
#[derive(Debug)]
struct StatusReporter<'a> {
    run_id: &'a str,
    id: u32,
    settings: &'a ActorSettings,
    options: &'a ActorOptions,
    counters: &'a Counters,
}

impl StatusReporter<'_> {
    /// The report since `last` (steps, nanoseconds waited, time), which it advances;
    /// touches the heartbeat file.
    fn report(&mut self, last: &mut (u64, u64, Instant)) -> proto::ActorStatus {
        let counters = self.counters;
        let steps = counters.env_steps.load(Ordering::Relaxed);
        let waited = counters.waiting_nanos.load(Ordering::Relaxed);
        let seconds = last.2.elapsed().as_secs_f64().max(1e-9);
        let rate = (steps - last.0) as f64 / seconds;
        let waiting_fraction = ((waited - last.1) as f64 * 1e-9 / seconds).clamp(0.0, 1.0) as f32;
        *last = (steps, waited, Instant::now());
        let report = proto::ActorStatus {
            protocol_version: PROTOCOL_VERSION,
            run_id: self.run_id.to_string(),
            actor_id: self.id,
            weights_version: counters.weights_version.load(Ordering::Relaxed),
            env_steps: steps,
            physics_steps: counters.physics_steps.load(Ordering::Relaxed),
            env_steps_per_second: rate as f32,
            epsilon: f64::from_bits(counters.epsilon_bits.load(Ordering::Relaxed)),
            num_envs: self.settings.envs_per_actor as u32,
            evaluator: self.options.evaluator,
            waiting_fraction,
        };
        if let Some(path) = &self.options.heartbeat
            && let Err(e) = std::fs::write(path, steps.to_string())
        {
            warn!("heartbeat {}: {e}", path.display());
        }
        info!(
            steps,
            steps_per_s = format!("{rate:.0}"),
            weights = report.weights_version,
            epsilon = format!("{:.4}", report.epsilon),
            waiting = format!("{:.2}", report.waiting_fraction),
            "actor status"
        );
        report
    }
}

/// Resolves once `stop` is set.
async fn stopped(stop: &AtomicBool) {
    while !stop.load(Ordering::SeqCst) {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Asks learners for their run info until one answers (or `stop` is set).
async fn fetch_run_info(
    session: &zenoh::Session,
    run: Option<&str>,
    assign: bool,
    stop: &AtomicBool,
) -> Result<(String, ActorSettings, Option<u32>), NodeError> {
    let key = match run {
        Some(run) => {
            keys::check_run_id(run).map_err(NodeError::RunId)?;
            keys::info(run)
        }
        None => keys::info("*"),
    };
    let key = if assign { format!("{key}?{}", keys::ASSIGN_PARAMETER) } else { key };
    let mut announced = false;
    while !stop.load(Ordering::SeqCst) {
        if let Ok(replies) = session.get(&key).timeout(Duration::from_secs(2)).await {
            while let Ok(reply) = replies.recv_async().await {
                let Ok(sample) = reply.result() else { continue };
                // A malformed reply is skipped, never fatal: the next query may reach the
                // genuine learner.
                let info = match proto::validate::run_info(&sample.payload().to_bytes()) {
                    Ok(info) => info,
                    Err(e) => {
                        warn!("ignoring run info: {e}");
                        continue;
                    }
                };
                let settings = match info.settings.as_ref().map(ActorSettings::try_from) {
                    Some(Ok(settings)) => settings,
                    Some(Err(e)) => {
                        warn!(run = %info.run_id, "ignoring run info with unusable settings: {e}");
                        continue;
                    }
                    None => continue,
                };
                if assign && info.assigned_actor_id.is_none() {
                    warn!("the learner assigned no id; asking again");
                    continue;
                }
                return Ok((info.run_id, settings, info.assigned_actor_id));
            }
        }
        if !announced {
            info!(key, "waiting for a learner");
            announced = true;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    Err(NodeError::StoppedBeforeLearnerAnswered)
}

fn load_weights(bytes: &[u8], run_id: &str, expected: &NetworkSpec) -> Result<PublishedPolicy, NodeError> {
    let weights = proto::validate::weights(bytes, run_id).map_err(NodeError::WeightsRejected)?;
    // Validation guarantees a network spec within the protocol's size limits.
    let spec = weights.network.as_ref().map(NetworkSpec::from).ok_or(NodeError::WeightsWithoutNetwork)?;
    if spec.obs_dim != expected.obs_dim || spec.num_actions != expected.num_actions {
        return Err(NodeError::WeightsShape {
            found_obs: spec.obs_dim,
            found_actions: spec.num_actions,
            obs: expected.obs_dim,
            actions: expected.num_actions,
        });
    }
    let policy = MlpPolicy::from_safetensors(&weights.safetensors, &spec)?;
    Ok(PublishedPolicy { session: weights.learner_session, version: weights.version, policy })
}

/// The simulation loop: act, step, batch transitions, report episodes.
#[allow(clippy::too_many_arguments)]
fn simulate(
    options: &ActorOptions,
    run_id: &str,
    settings: &ActorSettings,
    incarnation: u64,
    mut policy_rx: watch::Receiver<Option<Arc<PublishedPolicy>>>,
    out: &mpsc::Sender<Outgoing>,
    stop: &AtomicBool,
    counters: &Counters,
) {
    let Some(mut policy) = policy_rx.borrow_and_update().clone() else { return };
    // `run` resolved an automatic id before starting the simulation.
    let id = options.id.unwrap_or_default();
    let mut env = VecEnv::new(&settings.env, &settings.seeds(id));
    let k = env.len();
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed ^ (0x9E37_79B9 * (u64::from(id) + 1)));
    let num_actions = settings.env.num_actions() as u32;
    let repeat = u64::from(settings.env.action_repeat);
    let input_dim = env.input_dim();
    let mut batch = new_batch(run_id, id, incarnation, input_dim);
    let mut greedy = Vec::with_capacity(k);
    let mut actions = vec![0u32; k];
    let mut observations = vec![0.0f32; k * input_dim];
    let mut steps_per_env = 0u64;
    while !stop.load(Ordering::SeqCst) && options.max_steps.is_none_or(|max| steps_per_env < max) {
        if policy_rx.has_changed().unwrap_or(false)
            && let Some(latest) = policy_rx.borrow_and_update().clone()
        {
            policy = latest;
        }
        counters.weights_version.store(policy.version, Ordering::Relaxed);
        let epsilon = if options.evaluator { 0.0 } else { settings.exploration.epsilon(id, steps_per_env) };
        counters.epsilon_bits.store(epsilon.to_bits(), Ordering::Relaxed);
        observations.copy_from_slice(env.observations());
        if policy.policy.greedy_actions(&observations, &mut greedy).is_err() {
            warn!("weights do not fit the observations; stopping");
            return;
        }
        for (action, &best) in actions.iter_mut().zip(&greedy) {
            *action = if rng.random::<f64>() < epsilon { rng.random_range(0..num_actions) } else { best };
        }
        let finished: Vec<_> = env.step(&actions).to_vec();
        steps_per_env += 1;
        counters.env_steps.fetch_add(k as u64, Ordering::Relaxed);
        // An episode can end part-way through a held action; counting whole decisions
        // overstates physics steps by less than one decision per episode.
        let physics = k as u64 * repeat;
        counters.physics_steps.fetch_add(physics, Ordering::Relaxed);

        if !options.evaluator {
            append_transitions(&mut batch, &env, &observations, &actions);
            batch.physics_steps += physics;
            if batch.len() >= settings.transitions_per_batch() {
                batch.weights_version = policy.version;
                batch.count = batch.len() as u32;
                let full = std::mem::replace(&mut batch, new_batch(run_id, id, incarnation, input_dim));
                batch.sequence = full.sequence + 1;
                if !hand_over(out, Outgoing::Batch(full), counters) {
                    return;
                }
            }
        }
        for (_, summary) in finished {
            let stats = EpisodeStatsSource {
                run_id,
                id,
                epsilon,
                evaluation: options.evaluator,
                weights_version: policy.version,
            }
            .stats(&summary);
            if !hand_over(out, Outgoing::Stats(stats), counters) {
                return;
            }
        }
    }
}

/// Appends the step just taken by every crawler of `env` to `batch`.
fn append_transitions(batch: &mut proto::TransitionBatch, env: &VecEnv, observations: &[f32], actions: &[u32]) {
    let next = env.next_observations();
    let dim = env.input_dim();
    for i in 0..env.len() {
        batch.env_ids.push(i as u32);
        batch.observations.extend_from_slice(&observations[i * dim..(i + 1) * dim]);
        batch.next_observations.extend_from_slice(&next[i * dim..(i + 1) * dim]);
        batch.actions.push(actions[i]);
        batch.rewards.push(env.rewards()[i]);
        batch.terminated.push(env.terminated()[i]);
        batch.truncated.push(env.truncated()[i]);
    }
}

/// Who an episode's stats come from, and with what policy.
struct EpisodeStatsSource<'a> {
    run_id: &'a str,
    id: u32,
    epsilon: f64,
    evaluation: bool,
    weights_version: u64,
}

impl EpisodeStatsSource<'_> {
    fn stats(&self, summary: &EpisodeSummary) -> proto::EpisodeStats {
        proto::EpisodeStats {
            protocol_version: PROTOCOL_VERSION,
            run_id: self.run_id.to_string(),
            actor_id: self.id,
            epsilon: self.epsilon,
            episode_return: summary.reward.total(),
            return_position: summary.reward.position,
            return_upright: summary.reward.upright,
            return_tilt_rate: summary.reward.tilt_rate,
            return_base_impact: summary.reward.base_impact,
            return_joint_limit: summary.reward.joint_limit,
            distance: summary.distance,
            duration: summary.duration,
            speed: summary.speed,
            flips: summary.flips,
            terminated: summary.terminated,
            truncated: summary.truncated,
            evaluation: self.evaluation,
            weights_version: self.weights_version,
        }
    }
}

fn new_batch(run_id: &str, actor: u32, incarnation: u64, input_dim: usize) -> proto::TransitionBatch {
    proto::TransitionBatch {
        protocol_version: PROTOCOL_VERSION,
        run_id: run_id.to_string(),
        actor_id: actor,
        incarnation,
        obs_dim: input_dim as u32,
        ..Default::default()
    }
}
