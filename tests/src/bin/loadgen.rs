//! `loadgen`: many simulated actors in one process, for the scale bench
//! (`tests/benches/scale.rs`). Two modes:
//!
//! - `actors --connect ENDPOINT --run RUN --actors N [--first-id I] --rate T --seconds S`: N zenoh client
//!   sessions, each an actor as the learner sees one: a liveliness token under its id and a
//!   transitions publisher (reliable, congestion control *Block*, as real actors publish)
//!   putting valid, pre-encoded batches at T transitions/s (0: as fast as the link takes
//!   them) for S seconds. With `--credit` each waits for the learner's insert credit as a
//!   real actor does. Prints `{"actors", "batches", "transitions", "seconds"}` on stdout.
//! - `sink --listen ENDPOINT --seconds S`: a zenoh router with one subscriber on every run's
//!   transitions, counting what arrives: the transport alone, the anchor the learner's
//!   ingest is compared with. Prints `{"messages", "bytes", "seconds"}` on stdout once S
//!   seconds have passed since the first message.
//!
//! With `--tls-ca/--tls-cert/--tls-key` (before the mode) both ends speak mutual TLS: the
//! sink listens with its certificate, the actors connect with theirs (deploy/make-tls.sh).
//!
//! Batches are encoded once: the part that differs per message (sequence, id) is a second
//! protobuf encoding prepended to the shared body, which protobuf decoding merges (fields
//! may come in any order; the body's `count`, the last field, stays last).

use std::io::Write;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Parser, Subcommand};
use crawler_cli::{TlsArgs, TlsSide};
use crawler_proto::{self as proto, PROTOCOL_VERSION, keys};
use prost::Message;
use zenoh::qos::CongestionControl;

#[derive(Debug, Parser)]
struct Args {
    #[command(flatten)]
    tls: TlsArgs,
    #[command(subcommand)]
    mode: Mode,
}

#[derive(Debug, Subcommand)]
enum Mode {
    Actors {
        /// The learner's (or the sink's) endpoint, e.g. tcp/127.0.0.1:7447.
        #[arg(long)]
        connect: String,
        #[arg(long)]
        run: String,
        /// Simulated actors, ids FIRST_ID..FIRST_ID+N.
        #[arg(long)]
        actors: u32,
        #[arg(long, default_value_t = 0)]
        first_id: u32,
        /// Transitions per second each actor offers; 0: as fast as the link takes them.
        #[arg(long, default_value_t = 2000.0)]
        rate: f64,
        /// Transitions per batch (the default preset's 256).
        #[arg(long, default_value_t = 256)]
        batch: usize,
        /// Crawlers per actor the batches' env ids spread over (the run's envs_per_actor).
        #[arg(long, default_value_t = 8)]
        envs: u32,
        #[arg(long, default_value_t = 20.0)]
        seconds: f64,
        /// Wait for the learner's insert credit before each batch.
        #[arg(long)]
        credit: bool,
    },
    Sink {
        #[arg(long)]
        listen: String,
        #[arg(long, default_value_t = 20.0)]
        seconds: f64,
        /// Seconds the router stays up after the report, so that load generators still
        /// publishing never lose their peer mid-put.
        #[arg(long, default_value_t = 0.0)]
        linger: f64,
    },
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    // As the actor and learner do, before any thread exists.
    let endpoint = match &args.mode {
        Mode::Actors { connect, .. } => connect.clone(),
        Mode::Sink { listen, .. } => listen.clone(),
    };
    crawler_cli::serialize_tls_link_io(&[endpoint]);
    let tls = args.tls.files()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let report = runtime.block_on(async {
        match args.mode {
            Mode::Actors { connect, run, actors, first_id, rate, batch, envs, seconds, credit } => {
                let plan = Plan { run, rate, batch, envs, duration: Duration::from_secs_f64(seconds), credit };
                let overrides = tls.map(|t| t.zenoh_settings(TlsSide::Connect)).unwrap_or_default();
                actors_mode(&connect, &overrides, first_id..first_id.saturating_add(actors), plan).await
            }
            Mode::Sink { listen, seconds, linger } => {
                let overrides = tls.map(|t| t.zenoh_settings(TlsSide::Listen)).unwrap_or_default();
                let session = open_sink(&listen, &overrides).await?;
                let report = count(&session, Duration::from_secs_f64(seconds)).await?;
                print_line(&report)?;
                tokio::time::sleep(Duration::from_secs_f64(linger)).await;
                Ok(serde_json::Value::Null)
            }
        }
    })?;
    if !report.is_null() {
        print_line(&report)?;
    }
    Ok(())
}

fn print_line(report: &serde_json::Value) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{report}").and_then(|()| out.flush()).context("writing stdout")
}

fn err(context: &'static str) -> impl FnOnce(zenoh::Error) -> anyhow::Error {
    move |e| anyhow::anyhow!("{context}: {e}")
}

/// What every simulated actor does.
#[derive(Debug, Clone)]
struct Plan {
    run: String,
    rate: f64,
    batch: usize,
    envs: u32,
    duration: Duration,
    credit: bool,
}

async fn actors_mode(
    connect: &str,
    overrides: &[(String, String)],
    ids: std::ops::Range<u32>,
    plan: Plan,
) -> anyhow::Result<serde_json::Value> {
    let actors = ids.len();
    let body = Arc::new(batch_body(plan.batch, plan.envs));
    let batches = Arc::new(AtomicU64::new(0));
    // Every session first, then every actor at once: sessions opened while earlier actors
    // flood the link would open late and keep the whole run going past its end.
    let mut sessions = Vec::new();
    for id in ids {
        let config = crawler_actor::node::client_config(&[connect.to_string()], overrides)?;
        sessions.push((id, zenoh::open(config).await.map_err(err("opening a session"))?));
    }
    // One clock for all: the learner sees every token before the first batch, and a
    // generator that waits for a busy worker thread still stops on time.
    let start = Instant::now() + Duration::from_millis(500);
    let mut tasks = Vec::new();
    for (id, session) in sessions {
        let (plan, body, batches) = (plan.clone(), Arc::clone(&body), Arc::clone(&batches));
        tasks.push(tokio::spawn(async move { actor(session, id, plan, start, &body, &batches).await }));
    }
    for task in tasks {
        task.await.context("an actor task panicked")??;
    }
    let batches = batches.load(Ordering::Relaxed);
    Ok(serde_json::json!({
        "actors": actors,
        "batches": batches,
        "transitions": batches * plan.batch as u64,
        "seconds": start.elapsed().as_secs_f64(),
    }))
}

/// One simulated actor: a liveliness token, then from `start` on batches at the plan's rate.
async fn actor(
    session: zenoh::Session,
    id: u32,
    plan: Plan,
    start: Instant,
    body: &[u8],
    batches: &AtomicU64,
) -> anyhow::Result<()> {
    let _token =
        session.liveliness().declare_token(keys::alive_actor(&plan.run, id)).await.map_err(err("liveliness"))?;
    let incarnation = 1 + u64::from(id);
    let (credit_tx, credit_rx) = tokio::sync::watch::channel::<Option<proto::InsertCredit>>(None);
    let mut gate = crawler_actor::node::CreditGate::new(incarnation, credit_rx);
    let _credit = if plan.credit {
        let run = plan.run.clone();
        let subscriber = session
            .declare_subscriber(keys::credit(&plan.run, id))
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                if let Ok(credit) = proto::validate::insert_credit(&bytes, &run, sample.key_expr().as_str()) {
                    credit_tx.send_replace(Some(credit));
                }
            })
            .await
            .map_err(err("subscribing to credit"))?;
        Some(subscriber)
    } else {
        None
    };
    let publisher = session
        .declare_publisher(keys::transitions(&plan.run, id))
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(err("declaring the publisher"))?;
    tokio::time::sleep_until(start.into()).await;
    let interval = (plan.rate > 0.0).then(|| Duration::from_secs_f64(plan.batch as f64 / plan.rate));
    let mut sequence = 0u64;
    while start.elapsed() < plan.duration {
        // The actor's own credit gate: wait until it admits this batch.
        while plan.credit && !gate.admit(sequence) && start.elapsed() < plan.duration {
            let _ = tokio::time::timeout(Duration::from_millis(100), gate.changed()).await;
        }
        if start.elapsed() >= plan.duration {
            break;
        }
        let mut message = batch_head(&plan.run, id, incarnation, sequence);
        message.extend_from_slice(body);
        publisher.put(message).await.map_err(err("publishing"))?;
        batches.fetch_add(1, Ordering::Relaxed);
        sequence += 1;
        match interval {
            Some(interval) => tokio::time::sleep_until((start + interval.mul_f64(sequence as f64)).into()).await,
            // A put that finds room returns at once: let the other generators have the thread.
            None => tokio::task::yield_now().await,
        }
    }
    // Let the last batches leave before the session closes.
    tokio::time::sleep(Duration::from_millis(300)).await;
    session.close().await.map_err(err("closing"))?;
    Ok(())
}

/// Every field of a batch but its envelope and sequence, encoded once: what
/// `crawler_tests::valid_batch` holds, its env ids spread over `envs` crawlers.
fn batch_body(transitions: usize, envs: u32) -> Vec<u8> {
    let mut batch = crawler_tests::valid_batch("", 0, 0, transitions);
    batch.env_ids = (0..transitions as u32).map(|i| i % envs.max(1)).collect();
    batch.protocol_version = 0;
    batch.incarnation = 0;
    batch.encode_to_vec()
}

/// The per-message fields, encoded before the shared body.
fn batch_head(run: &str, id: u32, incarnation: u64, sequence: u64) -> Vec<u8> {
    proto::TransitionBatch {
        protocol_version: PROTOCOL_VERSION,
        run_id: run.to_string(),
        actor_id: id,
        sequence,
        incarnation,
        ..Default::default()
    }
    .encode_to_vec()
}

/// A router that load generators connect to.
async fn open_sink(listen: &str, overrides: &[(String, String)]) -> anyhow::Result<zenoh::Session> {
    let mut config = zenoh::Config::default();
    let settings = [
        ("mode", "\"router\"".to_string()),
        ("listen/endpoints", crawler_cli::zenoh_string_list(&[listen.to_string()])),
        ("scouting/multicast/enabled", "false".to_string()),
        ("transport/link/rx/max_message_size", proto::TRANSPORT_MAX_MESSAGE_BYTES.to_string()),
        ("transport/unicast/max_sessions", "1000".to_string()),
    ];
    let settings = settings.into_iter().map(|(k, v)| (k.to_string(), v)).chain(overrides.iter().cloned());
    for (key, value) in settings {
        config.insert_json5(&key, &value).map_err(|e| anyhow::anyhow!("setting {key}: {e}"))?;
    }
    zenoh::open(config).await.map_err(err("opening the router"))
}

/// Counts every transitions message of any run that reaches `session`, from the first one
/// on, for `duration`.
async fn count(session: &zenoh::Session, duration: Duration) -> anyhow::Result<serde_json::Value> {
    let counts = Arc::new((AtomicU64::new(0), AtomicU64::new(0)));
    let counter = Arc::clone(&counts);
    let _subscriber = session
        .declare_subscriber(format!("{}/*/transitions/*", keys::ROOT))
        .callback(move |sample| {
            counter.0.fetch_add(1, Ordering::Relaxed);
            counter.1.fetch_add(sample.payload().len() as u64, Ordering::Relaxed);
        })
        .await
        .map_err(err("subscribing"))?;
    while counts.0.load(Ordering::Relaxed) == 0 {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let first = (counts.0.load(Ordering::Relaxed), counts.1.load(Ordering::Relaxed));
    let start = Instant::now();
    tokio::time::sleep(duration).await;
    let seconds = start.elapsed().as_secs_f64();
    let (messages, bytes) = (counts.0.load(Ordering::Relaxed) - first.0, counts.1.load(Ordering::Relaxed) - first.1);
    Ok(serde_json::json!({ "messages": messages, "bytes": bytes, "seconds": seconds }))
}
