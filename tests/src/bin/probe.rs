//! `probe`: a zenoh client for the security tests, connecting with whatever certificate it is
//! given. Its modes:
//!
//! - `listen KEY`: subscribes to KEY and prints one JSON line per sample that arrives on stdout
//!   (`{"key": …, "bytes": …, "weights_version": …, "command": …}`), flushed at once, until
//!   killed. What it prints is what the router let through.
//! - `forge --run RUN --id ID --seconds S`: behaves like an authenticated actor gone bad. It
//!   fetches the learner's genuine weights and, every 200 ms, puts them back on the weights
//!   key with version [`FORGED_VERSION`], puts a Stop on the control key and a run info on the
//!   info key (all outside an actor's rights), and a valid transition batch on its own
//!   transitions key (inside them). At the end it prints what it sent as JSON.
//! - `query KEY…`: asks each key once and prints `{"key": …, "replies": n, "forged": m}`, where
//!   `forged` counts replies carrying the marker the `as-another` attack serves.
//! - `attack KIND --run RUN --id ID --seconds S`: one of the attacks of an outsider (or of an
//!   insider with an actor certificate) on a running learner, for the attack suite in
//!   `tests/tests/it/security.rs`; see [`Attack`]. Prints what it did as JSON on stdout.

use std::io::Write;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Parser, Subcommand};
use crawler_cli::{TlsArgs, TlsSide};
use crawler_proto::{self as proto, PROTOCOL_VERSION, keys};
use crawler_tests::{FORGED_VERSION, valid_batch};
use prost::Message;
use zenoh::qos::CongestionControl;

#[derive(Debug, Parser)]
struct Args {
    /// The learner's endpoint, e.g. tls/localhost:7447.
    #[arg(long)]
    connect: String,
    #[command(flatten)]
    tls: TlsArgs,
    /// Extra zenoh settings, KEY=JSON5 (e.g. a CA but no client certificate).
    #[arg(long = "zenoh", value_delimiter = ';')]
    zenoh: Vec<String>,
    #[command(subcommand)]
    mode: Mode,
}

#[derive(Debug, Subcommand)]
enum Mode {
    Listen {
        /// Key expressions to subscribe to (one subscriber each).
        #[arg(required = true)]
        keys: Vec<String>,
    },
    Query {
        /// Keys to query, once each.
        #[arg(required = true)]
        keys: Vec<String>,
    },
    Forge {
        #[arg(long)]
        run: String,
        #[arg(long)]
        id: u32,
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
    },
    Attack {
        #[arg(value_enum)]
        kind: Attack,
        #[arg(long)]
        run: String,
        /// The actor id the attacker uses (attacks that need one hold its liveliness token).
        #[arg(long, default_value_t = 900)]
        id: u32,
        /// How long attacks that hold something (a queryable, a subscriber) hold it.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
        /// How many tokens `squat` declares.
        #[arg(long, default_value_t = 62)]
        count: u32,
        /// The actor `as-another` speaks for.
        #[arg(long, default_value_t = 1)]
        victim: u32,
    },
}

/// The attacks, each named after what it tries.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Attack {
    /// Put the genuine weights re-stamped with session and version u64::MAX.
    ForgedWeights,
    /// Put a Stop on the control key.
    Stop,
    /// Serve the run-info key with three action levels, and with empty settings.
    ForgedInfo,
    /// Status reports with ε = NaN and ε = 7, from a live id.
    NanEpsilon,
    /// Valid batches whose observations are finite but 3e38, from a live id.
    HugeObservations,
    /// Subscribe to every actor's transitions and never read.
    StalledSubscriber,
    /// 100 000 status reports and 20 000 batches under distinct actor and env ids.
    Flood,
    /// One 200 MiB put on a transitions key.
    HugeMessage,
    /// 50 liveliness tokens of made-up actors and 3 000 `assign` queries.
    Tokens,
    /// Batches and status put under another actor's key (id 0), and one's own key with
    /// another id in the payload.
    Impersonate,
    /// Liveliness tokens under other spellings of the live actors' ids 0 and 1 (`00`,
    /// `+1`, …), declared and then dropped.
    AliasTokens,
    /// Batches of one incarnation, then (once it has been quiet long enough) one of another,
    /// then more of the first again.
    ReplayIncarnation,
    /// `--count` made-up liveliness tokens held for `--seconds`, to take every free slot.
    Squat,
    /// Valid episode statistics and status reports from its own live id, as fast as the link
    /// takes them, for `--seconds`: more than its share of the metrics and status.
    Hog,
    /// Everything actor `--victim` does, from a session that is actor `--id`: its liveliness
    /// token, batches (of 3e38 observations) and status reports (ε NaN) under its keys, a
    /// subscription to its insert credit, and queryables on the run info and weights that
    /// answer [`FORGED_REPLY`]; beside them the same as itself (valid batches, its credit), the
    /// positive control. Reports the credits each subscription got, then holds it all for
    /// `--seconds`.
    AsAnother,
}

/// What the `as-another` attack's queryables answer.
const FORGED_REPLY: &[u8] = b"forged reply";

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    // As the actor does, before any thread exists.
    crawler_cli::serialize_tls_link_io(std::slice::from_ref(&args.connect));
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(run(args))
}

async fn run(args: Args) -> anyhow::Result<()> {
    let mut overrides = Vec::new();
    if let Some(tls) = args.tls.files()? {
        overrides.extend(tls.zenoh_settings(TlsSide::Connect));
    }
    overrides.extend(crawler_cli::zenoh_overrides(&args.zenoh)?);
    let config = crawler_actor::node::client_config(std::slice::from_ref(&args.connect), &overrides)?;
    let session = zenoh::open(config).await.map_err(|e| anyhow::anyhow!("opening a zenoh session: {e}"))?;
    match args.mode {
        Mode::Listen { keys } => listen(&session, &keys).await,
        Mode::Forge { run, id, seconds } => forge(&session, &run, id, Duration::from_secs_f64(seconds)).await,
        Mode::Query { keys } => query(&session, &keys).await,
        Mode::Attack { kind, run, id, seconds, count, victim } => {
            let target = Target { id, count, victim };
            let report = attack(&session, kind, &run, target, Duration::from_secs_f64(seconds)).await?;
            // Let the last messages leave before closing.
            tokio::time::sleep(Duration::from_millis(500)).await;
            session.close().await.map_err(|e| anyhow::anyhow!("closing: {e}"))?;
            writeln!(std::io::stdout(), "{report}").context("writing stdout")?;
            Ok(())
        }
    }
}

fn err(context: &str) -> impl FnOnce(zenoh::Error) -> anyhow::Error + '_ {
    move |e| anyhow::anyhow!("{context}: {e}")
}

async fn put(session: &zenoh::Session, key: &str, bytes: Vec<u8>) -> anyhow::Result<()> {
    session.put(key, bytes).congestion_control(CongestionControl::Block).await.map_err(err(key))
}

/// The learner's genuine weights (any session may query them).
async fn genuine_weights(session: &zenoh::Session, run: &str) -> anyhow::Result<proto::Weights> {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let replies = session.get(keys::weights(run)).timeout(Duration::from_secs(2)).await.map_err(err("query"))?;
        if let Ok(reply) = replies.recv_async().await
            && let Ok(sample) = reply.result()
        {
            return Ok(proto::validate::weights(&sample.payload().to_bytes(), run)?);
        }
        anyhow::ensure!(Instant::now() < deadline, "no weights from the learner within 30 s");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// A well-formed Stop for run `run`, as only the learner may send it.
fn stop_message(run: &str) -> Vec<u8> {
    proto::Control { protocol_version: PROTOCOL_VERSION, run_id: run.to_string(), command: proto::Command::Stop as i32 }
        .encode_to_vec()
}

fn status_report(run: &str, id: u32, epsilon: f64) -> Vec<u8> {
    proto::ActorStatus {
        protocol_version: PROTOCOL_VERSION,
        run_id: run.to_string(),
        actor_id: id,
        epsilon,
        num_envs: 2,
        ..Default::default()
    }
    .encode_to_vec()
}

/// Whom an attack uses: its own id, how many made-up ids, whose id it takes.
#[derive(Debug, Clone, Copy)]
struct Target {
    id: u32,
    count: u32,
    victim: u32,
}

async fn attack(
    session: &zenoh::Session,
    kind: Attack,
    run: &str,
    target: Target,
    hold: Duration,
) -> anyhow::Result<serde_json::Value> {
    let Target { id, count, victim } = target;
    let mut sent = 0u64;
    match kind {
        Attack::ForgedWeights => {
            let genuine = genuine_weights(session, run).await?;
            let forged = proto::Weights { version: u64::MAX, learner_session: u64::MAX, ..genuine };
            for _ in 0..15 {
                put(session, &keys::weights(run), forged.encode_to_vec()).await?;
                sent += 1;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
        Attack::Stop => {
            for _ in 0..15 {
                put(session, &keys::control(run), stop_message(run)).await?;
                sent += 1;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
        Attack::ForgedInfo => {
            let run_id = run.to_string();
            let replies = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
            let counter = std::sync::Arc::clone(&replies);
            let queryable = session
                .declare_queryable(keys::info(run))
                .callback(move |query| {
                    let mut settings = proto::ActorSettings::default();
                    let n = counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    // Every other reply: three action levels; else no settings at all.
                    if n.is_multiple_of(2) {
                        settings.env = Some(proto::EnvSettings { action_levels: 3, ..Default::default() });
                    }
                    let info = proto::RunInfo {
                        protocol_version: PROTOCOL_VERSION,
                        run_id: run_id.clone(),
                        settings: Some(settings),
                        assigned_actor_id: Some(0),
                    };
                    let _ = zenoh::Wait::wait(query.reply(query.key_expr().clone(), info.encode_to_vec()));
                })
                .await
                .map_err(err("declaring a queryable"))?;
            tokio::time::sleep(hold).await;
            sent = replies.load(std::sync::atomic::Ordering::Relaxed);
            drop(queryable);
        }
        Attack::NanEpsilon => {
            let _token = session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
            tokio::time::sleep(Duration::from_millis(500)).await;
            for epsilon in [f64::NAN, 7.0, f64::INFINITY] {
                for _ in 0..5 {
                    put(session, &keys::status(run, id), status_report(run, id, epsilon)).await?;
                    sent += 1;
                }
            }
        }
        Attack::HugeObservations => {
            let _token = session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
            tokio::time::sleep(Duration::from_millis(500)).await;
            for sequence in 1..=30 {
                let mut batch = valid_batch(run, id, sequence, 64);
                batch.observations.fill(3e38);
                batch.next_observations.fill(3e38);
                put(session, &keys::transitions(run, id), batch.encode_to_vec()).await?;
                sent += 1;
            }
        }
        Attack::StalledSubscriber => {
            // A subscriber whose queue nobody drains.
            let subscriber = session
                .declare_subscriber(keys::all_transitions(run))
                .with(zenoh::handlers::FifoChannel::new(1))
                .await
                .map_err(err("subscribing"))?;
            tokio::time::sleep(hold).await;
            sent = subscriber.len() as u64;
            drop(subscriber);
        }
        Attack::Flood => {
            for actor in 0..100_000u32 {
                let id = 10_000 + actor;
                let bytes = status_report(run, id, 0.1);
                session.put(keys::status(run, id), bytes).await.map_err(err("status"))?;
                sent += 1;
            }
            let _token = session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
            tokio::time::sleep(Duration::from_millis(500)).await;
            for sequence in 1..=20_000u64 {
                let actor = if sequence.is_multiple_of(2) { id } else { 200_000 + sequence as u32 };
                let mut batch = valid_batch(run, actor, sequence, 1);
                batch.env_ids = vec![sequence as u32];
                put(session, &keys::transitions(run, actor), batch.encode_to_vec()).await?;
                sent += 1;
            }
        }
        Attack::HugeMessage => {
            put(session, &keys::transitions(run, id), vec![7u8; 200 << 20]).await?;
            sent = 1;
        }
        Attack::AliasTokens => {
            let mut tokens = Vec::new();
            for alias in ["00", "01", "+0", "+1", "000", "001", "0000", "0001", "+00", "+01"] {
                let key = format!("{}/{run}/alive/actor/{alias}", keys::ROOT);
                tokens.push(session.liveliness().declare_token(key).await.map_err(err("token"))?);
                sent += 1;
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
            drop(tokens);
        }
        Attack::ReplayIncarnation => {
            let _token = session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
            // The learner's credit for this id names the incarnation it has taken: how the
            // attacker knows each one got in.
            let (credit_tx, mut credit_rx) = tokio::sync::watch::channel(0u64);
            let run_id = run.to_string();
            let _credit = session
                .declare_subscriber(keys::credit(run, id))
                .callback(move |sample| {
                    let bytes = sample.payload().to_bytes();
                    if let Ok(credit) = proto::validate::insert_credit(&bytes, &run_id, sample.key_expr().as_str()) {
                        credit_tx.send_replace(credit.incarnation);
                    }
                })
                .await
                .map_err(err("subscribing to credit"))?;
            tokio::time::sleep(Duration::from_millis(500)).await;
            let batch = |incarnation: u64, sequence: u64| {
                proto::TransitionBatch { incarnation, ..valid_batch(run, id, sequence, 8) }.encode_to_vec()
            };
            let mut sequence = 0;
            // Incarnation 11, then 12 once 11 has been quiet for the handover time: each
            // introduces itself until the learner's credit names it.
            for incarnation in [11, 12] {
                let taken = async {
                    loop {
                        sequence += 1;
                        put(session, &keys::transitions(run, id), batch(incarnation, sequence)).await?;
                        sent += 1;
                        let named = tokio::time::timeout(
                            Duration::from_millis(400),
                            credit_rx.wait_for(|taken| *taken == incarnation),
                        );
                        if matches!(named.await, Ok(Ok(_))) {
                            return anyhow::Ok(());
                        }
                    }
                };
                tokio::time::timeout(Duration::from_secs(30), taken)
                    .await
                    .with_context(|| format!("the learner never took incarnation {incarnation}"))??;
                tokio::time::sleep(proto::validate::INCARNATION_HANDOVER + Duration::from_millis(300)).await;
            }
            // Incarnation 11 again, sequences it never sent: refused as retired.
            for _ in 0..10 {
                sequence += 1;
                put(session, &keys::transitions(run, id), batch(11, sequence)).await?;
                sent += 1;
            }
            // Held until they have arrived: a token that left first would make them not live.
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        Attack::Squat => {
            let mut tokens = Vec::new();
            for fake in 0..count {
                let key = keys::alive_actor(run, 7_000 + fake);
                tokens.push(session.liveliness().declare_token(key).await.map_err(err("token"))?);
                sent += 1;
            }
            hold_and_report(kind, sent, hold).await?;
            drop(tokens);
        }
        Attack::Hog => {
            let _token = session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
            tokio::time::sleep(Duration::from_millis(500)).await;
            let episode = proto::EpisodeStats {
                protocol_version: PROTOCOL_VERSION,
                run_id: run.to_string(),
                actor_id: id,
                speed: 9.0,
                distance: 90.0,
                duration: 10.0,
                epsilon: 0.1,
                ..Default::default()
            }
            .encode_to_vec();
            let status = status_report(run, id, 0.1);
            let end = Instant::now() + hold;
            while Instant::now() < end {
                for _ in 0..100 {
                    put(session, &keys::stats(run, id), episode.clone()).await?;
                    put(session, &keys::status(run, id), status.clone()).await?;
                    sent += 2;
                }
            }
            // Held until they have arrived: a token that left first would make them not live.
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        Attack::Tokens => {
            let mut tokens = Vec::new();
            for fake in 0..50 {
                let key = keys::alive_actor(run, 5_000 + fake);
                tokens.push(session.liveliness().declare_token(key).await.map_err(err("token"))?);
            }
            let selector = format!("{}?{}", keys::info(run), keys::ASSIGN_PARAMETER);
            for _ in 0..3_000 {
                let replies = session.get(&selector).timeout(Duration::from_secs(2)).await.map_err(err("query"))?;
                while replies.recv_async().await.is_ok() {}
                sent += 1;
            }
            // Report now: the tokens stay while the test starts a genuine `--id auto` actor.
            hold_and_report(kind, sent, hold).await?;
            drop(tokens);
        }
        Attack::Impersonate => {
            let _token = session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
            tokio::time::sleep(Duration::from_millis(500)).await;
            for sequence in 1..=10 {
                // Under actor 0's key, in its name.
                let batch = valid_batch(run, 0, 1_000_000 + sequence, 8);
                put(session, &keys::transitions(run, 0), batch.encode_to_vec()).await?;
                // Under its own key, in actor 0's name.
                put(session, &keys::transitions(run, id), batch.encode_to_vec()).await?;
                put(session, &keys::status(run, id), status_report(run, 0, 0.1)).await?;
                sent += 3;
            }
        }
        Attack::AsAnother => {
            let _own_token =
                session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
            let _victim_token =
                session.liveliness().declare_token(keys::alive_actor(run, victim)).await.map_err(err("token"))?;
            let mut credits = Vec::new();
            let mut subscribers = Vec::new();
            for whose in [id, victim] {
                let counter = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
                let seen = std::sync::Arc::clone(&counter);
                let subscriber = session
                    .declare_subscriber(keys::credit(run, whose))
                    .callback(move |_| {
                        seen.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    })
                    .await
                    .map_err(err("subscribing to credit"))?;
                credits.push(counter);
                subscribers.push(subscriber);
            }
            let mut queryables = Vec::new();
            for key in [keys::info(run), keys::weights(run)] {
                let queryable = session
                    .declare_queryable(&key)
                    .callback(|query| {
                        let _ = zenoh::Wait::wait(query.reply(query.key_expr().clone(), FORGED_REPLY));
                    })
                    .await
                    .map_err(err("declaring a queryable"))?;
                queryables.push(queryable);
            }
            tokio::time::sleep(Duration::from_millis(500)).await;
            for sequence in 1..=10 {
                let mut poisoned = valid_batch(run, victim, 1_000_000 + sequence, 8);
                poisoned.incarnation = 99;
                poisoned.observations.fill(3e38);
                put(session, &keys::transitions(run, victim), poisoned.encode_to_vec()).await?;
                put(session, &keys::status(run, victim), status_report(run, victim, f64::NAN)).await?;
                // Its own batches, one per introduction interval, so the learner takes them.
                put(session, &keys::transitions(run, id), valid_batch(run, id, sequence, 8).encode_to_vec()).await?;
                sent += 3;
                tokio::time::sleep(Duration::from_millis(300)).await;
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
            let [own, others] = [0, 1].map(|i| credits[i].load(std::sync::atomic::Ordering::Relaxed));
            let credits = serde_json::json!({ "own_credits": own, "victim_credits": others });
            hold_and_report_with(kind, sent, credits, hold).await?;
            drop((queryables, subscribers));
        }
    }
    Ok(serde_json::json!({ "attack": format!("{kind:?}"), "sent": sent }))
}

async fn query(session: &zenoh::Session, keys: &[String]) -> anyhow::Result<()> {
    for key in keys {
        let replies = session.get(key).timeout(Duration::from_secs(3)).await.map_err(err("query"))?;
        let (mut count, mut forged) = (0u64, 0u64);
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                count += 1;
                forged += u64::from(sample.payload().to_bytes().as_ref() == FORGED_REPLY);
            }
        }
        let line = serde_json::json!({ "key": key, "replies": count, "forged": forged });
        writeln!(std::io::stdout(), "{line}").context("writing stdout")?;
    }
    Ok(())
}

/// Reports what an attack that holds something has sent, at once (the test acts while it
/// holds), then holds it for `hold`.
async fn hold_and_report(kind: Attack, sent: u64, hold: Duration) -> anyhow::Result<()> {
    hold_and_report_with(kind, sent, serde_json::json!({}), hold).await
}

/// [`hold_and_report`], with the fields of the JSON object `extra` in the report too.
async fn hold_and_report_with(kind: Attack, sent: u64, extra: serde_json::Value, hold: Duration) -> anyhow::Result<()> {
    let mut report = serde_json::json!({ "attack": format!("{kind:?}"), "sent": sent, "holding": true });
    if let (Some(report), serde_json::Value::Object(extra)) = (report.as_object_mut(), extra) {
        report.extend(extra);
    }
    let mut stdout = std::io::stdout().lock();
    writeln!(stdout, "{report}").context("writing stdout")?;
    stdout.flush().context("flushing stdout")?;
    drop(stdout);
    tokio::time::sleep(hold).await;
    Ok(())
}

async fn listen(session: &zenoh::Session, keys: &[String]) -> anyhow::Result<()> {
    // Unbounded, from zenoh's callbacks to the printing loop: a probe never holds the router up.
    let (tx, rx) = std::sync::mpsc::channel::<zenoh::sample::Sample>();
    let mut subscribers = Vec::new();
    for key in keys {
        let tx = tx.clone();
        let subscriber = session
            .declare_subscriber(key)
            .callback(move |sample| {
                let _ = tx.send(sample);
            })
            .await
            .map_err(|e| anyhow::anyhow!("subscribing to {key}: {e}"))?;
        subscribers.push(subscriber);
        eprintln!("probe: listening on {key}");
    }
    drop(tx);
    while let Ok(sample) = rx.recv() {
        let key = sample.key_expr().as_str().to_string();
        let bytes = sample.payload().to_bytes();
        let weights_version = key.ends_with("/weights").then(|| proto::Weights::decode(&bytes[..]).ok()).flatten();
        let command = key.ends_with("/control").then(|| proto::Control::decode(&bytes[..]).ok()).flatten();
        let line = serde_json::json!({
            "key": key,
            "bytes": bytes.len(),
            "weights_version": weights_version.map(|w| w.version),
            "command": command.map(|c| c.command),
        });
        let mut stdout = std::io::stdout().lock();
        writeln!(stdout, "{line}").context("writing stdout")?;
        stdout.flush().context("flushing stdout")?;
    }
    Ok(())
}

async fn forge(session: &zenoh::Session, run: &str, id: u32, duration: Duration) -> anyhow::Result<()> {
    // Like an actor, it holds its id's liveliness token (the learner keeps only live ids'
    // messages). The observer's is denied, as are its puts.
    let _token = session.liveliness().declare_token(keys::alive_actor(run, id)).await.map_err(err("token"))?;
    // Genuine weights to tamper with: an actor may query them.
    let genuine = genuine_weights(session, run).await?;
    let forged_weights = proto::Weights { version: FORGED_VERSION, ..genuine }.encode_to_vec();
    let stop = stop_message(run);
    let info = proto::RunInfo {
        protocol_version: PROTOCOL_VERSION,
        run_id: run.to_string(),
        settings: None,
        assigned_actor_id: None,
    }
    .encode_to_vec();
    let mut sent = serde_json::Map::new();
    let start = Instant::now();
    let mut sequence = 0u64;
    while start.elapsed() < duration {
        sequence += 1;
        let batch = proto::TransitionBatch { weights_version: genuine.version, ..valid_batch(run, id, sequence, 1) }
            .encode_to_vec();
        for (what, key, bytes) in [
            ("forged_weights", keys::weights(run), forged_weights.clone()),
            ("forged_stop", keys::control(run), stop.clone()),
            ("forged_info", keys::info(run), info.clone()),
            ("own_transitions", keys::transitions(run, id), batch),
        ] {
            session
                .put(&key, bytes)
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(|e| anyhow::anyhow!("put {key}: {e}"))?;
            let count = sent.entry(what).or_insert(serde_json::json!(0));
            *count = serde_json::json!(count.as_u64().unwrap_or(0) + 1);
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    session.close().await.map_err(|e| anyhow::anyhow!("closing: {e}"))?;
    writeln!(std::io::stdout(), "{}", serde_json::Value::Object(sent)).context("writing stdout")?;
    Ok(())
}
