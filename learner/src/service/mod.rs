//! The learner process: an embedded zenoh router, ingest, the training thread, and weights.
//!
//! - [`edge`]: every zenoh callback (validation, liveliness, run info, the weights
//!   queryable), touching only small shared tables;
//! - [`inserter`]: the inserting thread, which moves validated batches into the replay table;
//! - [`trainer`]: the training thread, which owns the DQN and samples from the table;
//! - [`credit`]: insert credit, the rate limiter's hold on the actors (`rate.limit_inserts`);
//! - [`telemetry`]: `status.json`, the status line and the metrics files;
//! - [`access_control`]: the router's zenoh access-control policy, always on.
//!
//! Data path: zenoh delivers transition batches to a callback that validates them and hands
//! them to the inserting thread through a bounded queue; when the queue is full the batch is
//! dropped and counted, so zenoh's receive path never waits on training (a reliably published
//! message that waits more than 5 s makes zenoh close the sender's link). The inserting thread
//! writes into the replay table (`crate::table`: replay and rate limiter under one lock) while
//! the training thread samples from it and updates; every `weights_every` updates it hands fresh weights to a
//! publisher that never blocks (congestion control Drop: a frozen actor cannot stall the
//! learner) and to a queryable that serves the latest weights to starting actors.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::sync_channel;
use std::time::Duration;

use crawler_proto::{self as proto, PROTOCOL_VERSION, keys};
use crawler_run::config::TrainConfig;
use prost::Message;
use tracing::{info, warn};
use zenoh::qos::CongestionControl;

use crate::checkpoint::{Checkpoint, CheckpointError, Progress};

pub mod access_control;
mod best_keeper;
mod credit;
mod edge;
mod fair_share;
mod inserter;
mod telemetry;
mod trainer;

pub use edge::{ActorView, transition_limits};
pub use fair_share::OverShare;
pub use telemetry::Status;

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
    Metrics(#[from] crawler_run::metrics::MetricsError),
    #[error("cannot start the training thread: {0}")]
    TrainingThread(#[source] std::io::Error),
    #[error("the training thread panicked; the log above says where")]
    TrainingThreadPanicked,
    #[error("cannot start the inserting thread: {0}")]
    InsertingThread(#[source] std::io::Error),
    #[error("the inserting thread panicked; the log above says where")]
    InsertingThreadPanicked,
    #[error("cannot start the best-checkpoint thread: {0}")]
    BestThread(#[source] std::io::Error),
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
    pub identity: access_control::Identity,
    /// Extra zenoh settings as (key, JSON5) pairs, applied last (TLS).
    pub zenoh_overrides: Vec<(String, String)>,
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
    let session = open_router(&config, &run_id, identity, zenoh_overrides).await?;
    info!(run = %run_id, listen = ?config.learner.listen, "learner router up");

    let budgets = fair_share::Budgets::for_status_interval(config.actor.status_interval_s);
    let shared = Arc::new(edge::Shared::new(config.learner.max_actors, budgets));
    let (ingest_tx, ingest_rx) = sync_channel::<proto::TransitionBatch>(config.learner.ingest_queue);
    // Held to the end: dropping it undeclares the run's queryables and subscriptions.
    let _edge = edge::serve(&session, &config, &run_id, &shared, ingest_tx).await?;
    let weights_publisher = session
        .declare_publisher(keys::weights(&run_id))
        .congestion_control(CongestionControl::Drop)
        .await
        .map_err(zenoh_error("declaring the weights publisher"))?;

    // Aborted when `run` returns, on every path, and before the session closes.
    let credits = AbortOnDrop(tokio::spawn(publish_credits(
        session.clone(),
        run_id.clone(),
        Arc::clone(&shared),
        config.actor_settings().transitions_per_batch() as u64,
    )));
    // Training runs on its own thread; weights come back through a channel to be published.
    let (weights_tx, mut weights_rx) = tokio::sync::mpsc::channel::<Vec<u8>>(2);
    let trainer = {
        let (shared, stop, run_id) = (Arc::clone(&shared), Arc::clone(&stop), run_id.clone());
        std::thread::Builder::new()
            .name("training".into())
            .spawn(move || {
                let links = trainer::Links { weights_out: &weights_tx, shared: &shared, stop: &stop };
                trainer::train(&config, &run_id, &run_dir, trainer::Start { resume, init_from }, ingest_rx, links)
            })
            .map_err(ServiceError::TrainingThread)?
    };
    while let Some(bytes) = weights_rx.recv().await {
        if let Err(e) = weights_publisher.put(bytes).await {
            warn!("weights publish failed: {e}");
        }
    }
    let outcome = trainer.join().map_err(|_| ServiceError::TrainingThreadPanicked)??;
    drop(credits);
    broadcast_stop(&session, &run_id).await;
    let _ = session.close().await;
    Ok(outcome)
}

/// A task aborted when this is dropped.
#[derive(Debug)]
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Hands out insert credit every [`credit::CREDIT_EVERY`] until aborted: what is left of the
/// training thread's insert limit, shared among the live actors (`credit.rs`).
async fn publish_credits(session: zenoh::Session, run_id: String, shared: Arc<edge::Shared>, batch: u64) {
    use std::sync::atomic::Ordering;
    let mut ticker = tokio::time::interval(credit::CREDIT_EVERY);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        ticker.tick().await;
        let live = shared.connected();
        let sequences = edge::lock(&shared.sequences).clone();
        let limit = shared.insert_limit.load(Ordering::Relaxed);
        let room = limit.saturating_sub(shared.admitted_transitions.load(Ordering::Relaxed));
        let due = edge::lock(&shared.credits).due(&run_id, room, batch, &live, &sequences, std::time::Instant::now());
        for credit in due {
            let key = keys::credit(&run_id, credit.actor_id);
            // Dropped rather than queued behind a slow link: the next refresh replaces it.
            let put = session.put(key, credit.encode_to_vec()).congestion_control(CongestionControl::Drop);
            if let Err(e) = put.await {
                warn!("insert credit publish failed: {e}");
            }
        }
    }
}

/// The embedded router: listening where the config says, bounded, with the access-control
/// policy always on; `overrides` (TLS) go last.
async fn open_router(
    config: &TrainConfig,
    run_id: &str,
    identity: access_control::Identity,
    overrides: Vec<(String, String)>,
) -> Result<zenoh::Session, ServiceError> {
    let mut zenoh_config = zenoh::Config::default();
    let listen = crawler_cli::zenoh_string_list(&config.learner.listen);
    let base = [
        ("mode".to_string(), "\"router\"".to_string()),
        ("listen/endpoints".to_string(), listen),
        ("scouting/multicast/enabled".to_string(), "false".to_string()),
        // zenoh buffers up to 1 GiB of one incoming message by default; nothing legal is
        // larger than this.
        ("transport/link/rx/max_message_size".to_string(), proto::TRANSPORT_MAX_MESSAGE_BYTES.to_string()),
        // Sessions the router admits (actors, evaluators, observers, with room for
        // reconnections), so that per-session buffers stay bounded.
        ("transport/unicast/max_sessions".to_string(), (2 * config.learner.max_actors + 16).to_string()),
        // A connection that never completes its handshake holds an accept slot this long
        // (zenoh's default is 10 s): idle connections delay real actors less.
        ("transport/unicast/accept_timeout".to_string(), "2000".to_string()),
        // The policy is always on: under TLS roles come by certificate, without it every
        // remote session is an actor (access_control.rs).
        ("access_control".to_string(), access_control::policy(run_id, identity).to_string()),
    ];
    for (key, value) in base.into_iter().chain(overrides) {
        zenoh_config.insert_json5(&key, &value).map_err(zenoh_error(format!("setting {key} = {value}")))?;
    }
    zenoh::open(zenoh_config).await.map_err(zenoh_error("opening the router"))
}

/// Tells every node of the run to exit; repeated briefly so late subscribers hear it too.
async fn broadcast_stop(session: &zenoh::Session, run_id: &str) {
    let control = proto::Control {
        protocol_version: PROTOCOL_VERSION,
        run_id: run_id.to_string(),
        command: proto::Command::Stop as i32,
    }
    .encode_to_vec();
    for _ in 0..5 {
        let _ = session.put(keys::control(run_id), control.clone()).await;
        tokio::time::sleep(Duration::from_millis(100)).await;
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
    fn loopback_endpoints_are_told_apart() {
        for local in ["tcp/127.0.0.1:7447", "tcp/localhost:7447", "tcp/[::1]:7447", "tls/127.0.0.2:1"] {
            assert!(is_loopback_endpoint(local), "{local}");
        }
        for remote in ["tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/192.168.1.4:7447", "tcp/learner:7447"] {
            assert!(!is_loopback_endpoint(remote), "{remote}");
        }
    }
}
