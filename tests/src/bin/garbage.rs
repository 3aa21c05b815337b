//! `garbage`: publishes every kind of bad input a learner must refuse, as a client of its
//! router, for the fault-tolerance tests. Each round sends, on the transitions topic of actor
//! `--id`: random bytes, a truncated valid batch, a wrong protocol version, another run's id,
//! a wrong observation size, NaN and ∞ values, an action out of range, a batch over the size
//! limit, a message over the byte limit, and a replayed sequence number; plus garbage on the
//! stats and status topics. One valid batch goes first (the one the replays repeat), so
//! exactly its 8 transitions may reach replay. Prints what it sent, per kind, as JSON on
//! stdout.

use std::collections::BTreeMap;

use anyhow::Context;
use clap::Parser;
use crawler_proto::{self as proto, keys};
use crawler_tests::valid_batch;
use prost::Message;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use zenoh::qos::CongestionControl;

#[derive(Debug, Parser)]
struct Args {
    /// The learner's endpoint, e.g. tcp/127.0.0.1:7447.
    #[arg(long)]
    connect: String,
    #[arg(long)]
    run: String,
    /// The actor id whose topics are used.
    #[arg(long, default_value_t = 77)]
    id: u32,
    #[arg(long, default_value_t = 5)]
    rounds: u32,
}

#[tokio::main(flavor = "multi_thread", worker_threads = 1)]
async fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    let config = crawler_actor::node::client_config(std::slice::from_ref(&args.connect), &[])?;
    let session = zenoh::open(config).await.map_err(|e| anyhow::anyhow!("opening a zenoh session: {e}"))?;
    // The learner keeps messages of live nodes only: hold the id's liveliness token, as an
    // actor does, so the bad messages are judged on their content.
    let _token = session
        .liveliness()
        .declare_token(keys::alive_actor(&args.run, args.id))
        .await
        .map_err(|e| anyhow::anyhow!("declaring liveliness: {e}"))?;
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    let transitions = keys::transitions(&args.run, args.id);
    let mut rng = ChaCha8Rng::seed_from_u64(u64::from(args.id));
    let mut sent: BTreeMap<&str, u32> = BTreeMap::new();
    // One valid batch first, whose sequence number every round then replays.
    const VALID_SEQUENCE: u64 = 1_000_000;
    let valid = valid_batch(&args.run, args.id, VALID_SEQUENCE, 8).encode_to_vec();
    // Block rather than drop when the link is busy (the 16 MiB message fills it), so that
    // every bad message reaches the learner and the test can count them exactly.
    let block = CongestionControl::Block;
    session
        .put(&transitions, valid.clone())
        .congestion_control(block)
        .await
        .map_err(|e| anyhow::anyhow!("put valid: {e}"))?;
    sent.insert("valid", 1);
    // Until the learner's next credit round has granted this incarnation (they come every
    // 10 ms): a replay is then refused as a replay, not as a batch past its credit.
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    let mut sequence = 0u64;
    for _ in 0..args.rounds {
        let mut next = |f: &mut dyn FnMut(&mut proto::TransitionBatch)| {
            sequence += 1;
            let mut batch = valid_batch(&args.run, args.id, sequence, 8);
            f(&mut batch);
            batch.encode_to_vec()
        };
        let garbage: Vec<u8> = (0..rng.random_range(1..512)).map(|_| rng.random()).collect();
        let whole = next(&mut |_| {});
        let truncated = whole[..whole.len() - rng.random_range(1..whole.len() / 2)].to_vec();
        let mut messages: Vec<(&str, Vec<u8>)> = vec![
            ("garbage", garbage),
            ("truncated", truncated),
            ("version", next(&mut |b| b.protocol_version = 99)),
            ("run_id", next(&mut |b| b.run_id = "another-run".into())),
            ("obs_dim", next(&mut |b| b.obs_dim = 39)),
            ("nan", next(&mut |b| b.observations[3] = f32::NAN)),
            ("infinity", next(&mut |b| b.rewards[2] = f32::INFINITY)),
            ("action", next(&mut |b| b.actions[0] = 10_000)),
        ];
        sequence += 1;
        messages.push(("batch_size", valid_batch(&args.run, args.id, sequence, 5000).encode_to_vec()));
        messages.push(("oversize", vec![0u8; proto::MAX_MESSAGE_BYTES + 1]));
        // A sequence number this incarnation has already used.
        messages.push(("replayed", valid.clone()));
        for (kind, bytes) in messages {
            session
                .put(&transitions, bytes)
                .congestion_control(block)
                .await
                .map_err(|e| anyhow::anyhow!("put {kind}: {e}"))?;
            *sent.entry(kind).or_default() += 1;
        }
        let stats_garbage: Vec<u8> = (0..64).map(|_| rng.random()).collect();
        session
            .put(keys::stats(&args.run, args.id), stats_garbage.clone())
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        session
            .put(keys::status(&args.run, args.id), stats_garbage)
            .congestion_control(block)
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        *sent.entry("stats_and_status").or_default() += 2;
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    // Let the last messages leave before closing.
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    session.close().await.map_err(|e| anyhow::anyhow!("closing: {e}"))?;
    let json = serde_json::to_string(&sent).context("encoding the report")?;
    #[allow(clippy::print_stdout)]
    {
        println!("{json}");
    }
    Ok(())
}
