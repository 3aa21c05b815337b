//! `probe`: a zenoh client for the security tests, connecting with whatever certificate it is
//! given. Two modes:
//!
//! - `listen KEY`: subscribes to KEY and prints one JSON line per sample that arrives on stdout
//!   (`{"key": …, "bytes": …, "weights_version": …, "command": …}`), flushed at once, until
//!   killed. What it prints is what the router let through.
//! - `forge --run RUN --id ID --seconds S`: behaves like an authenticated actor gone bad. It
//!   fetches the learner's genuine weights and, every 200 ms, puts them back on the weights
//!   key with version [`FORGED_VERSION`], puts a Stop on the control key and a run info on the
//!   info key (all outside an actor's rights), and a valid transition batch on its own
//!   transitions key (inside them). At the end it prints what it sent as JSON.

use std::io::Write;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Parser, Subcommand};
use crawler_actor::cli::{TlsArgs, TlsSide};
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
        key: String,
    },
    Forge {
        #[arg(long)]
        run: String,
        #[arg(long)]
        id: u32,
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
    },
}

#[tokio::main(flavor = "multi_thread", worker_threads = 1)]
async fn main() -> anyhow::Result<()> {
    crawler_actor::cli::init_logging();
    let args = Args::parse();
    let mut overrides = Vec::new();
    if let Some(tls) = args.tls.files().map_err(anyhow::Error::msg)? {
        overrides.extend(tls.zenoh_settings(TlsSide::Connect));
    }
    overrides.extend(crawler_actor::cli::zenoh_overrides(&args.zenoh).map_err(anyhow::Error::msg)?);
    let config = crawler_actor::node::client_config(std::slice::from_ref(&args.connect), &overrides)?;
    let session = zenoh::open(config).await.map_err(|e| anyhow::anyhow!("opening a zenoh session: {e}"))?;
    match args.mode {
        Mode::Listen { key } => listen(&session, &key).await,
        Mode::Forge { run, id, seconds } => forge(&session, &run, id, Duration::from_secs_f64(seconds)).await,
    }
}

async fn listen(session: &zenoh::Session, key: &str) -> anyhow::Result<()> {
    let subscriber = session.declare_subscriber(key).await.map_err(|e| anyhow::anyhow!("subscribing to {key}: {e}"))?;
    eprintln!("probe: listening on {key}");
    while let Ok(sample) = subscriber.recv_async().await {
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
    // Genuine weights to tamper with: an actor may query them.
    let deadline = Instant::now() + Duration::from_secs(30);
    let genuine = loop {
        let replies = session
            .get(keys::weights(run))
            .timeout(Duration::from_secs(2))
            .await
            .map_err(|e| anyhow::anyhow!("querying weights: {e}"))?;
        if let Ok(reply) = replies.recv_async().await
            && let Ok(sample) = reply.result()
        {
            break proto::validate::weights(&sample.payload().to_bytes(), run)?;
        }
        anyhow::ensure!(Instant::now() < deadline, "no weights from the learner within 30 s");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let forged_weights = proto::Weights { version: FORGED_VERSION, ..genuine }.encode_to_vec();
    let stop = proto::Control {
        protocol_version: PROTOCOL_VERSION,
        run_id: run.to_string(),
        command: proto::Command::Stop as i32,
    }
    .encode_to_vec();
    let info = proto::RunInfo {
        protocol_version: PROTOCOL_VERSION,
        run_id: run.to_string(),
        actor_settings_json: "{}".into(),
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
