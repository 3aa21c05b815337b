//! How many actors one learner takes: a training learner fed by N simulated actors.
//! `cargo build --release --bins && cargo bench -p crawler-tests --bench scale`
//!
//! For each N (`SCALE_ACTORS`, default 1,4,16,64,256), in one run on this machine:
//! 1. the anchor: `loadgen sink`, a bare zenoh router with one subscriber, fed by
//!    `loadgen actors` (N sessions, each with a liveliness token, publishing valid pre-encoded
//!    batches of the default preset's size at `SCALE_RATE` transitions/s each, reliable and
//!    blocking as real actors publish): what the transport alone carries;
//! 2. the learner: the default preset's learner, training, fed by the same load. Inserts are
//!    not limited and sampling takes what comes (`rate.limit_inserts=false`,
//!    `rate.samples_per_insert=0`), so the table shows the ingest path's ceiling, not the
//!    rate limiter's choice.
//!
//! Per N: transitions/s offered, carried by zenoh alone, received, validated and inserted by
//! the learner, batches dropped (ingest queue full) and rejected, updates/s, the learner's
//! CPU (cores) and resident memory at the start and end of the window, and the ratio of
//! inserted to zenoh's own throughput. `SCALE_SECONDS` (default 20) is each window.
//! `SCALE_TLS=1` adds zenoh's throughput over mutual TLS beside plain TCP (the transport
//! cost of TLS on ingest; deploy/README.md, "A cluster").
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::process::{Command, Stdio};
use std::time::Duration;

use crawler_tests::{Learner, binary, cpu_model, cpu_seconds, env_or, free_port, rss_mib, u64_at};

const CONFIG: &str = "configs/default.toml";
const RUN: &str = "scale";

/// The default preset's batch: its transitions and the crawlers they come from.
fn batch_shape() -> (usize, u32) {
    let config = crawler_run::config::TrainConfig::load(&crawler_tests::repo_root().join(CONFIG), &[])
        .unwrap_or_else(|e| panic!("{CONFIG}: {e}"));
    let settings = config.actor_settings();
    (settings.transitions_per_batch(), settings.envs_per_actor as u32)
}

/// Mutual-TLS flags for `loadgen`: the sink as the learner, the actors as actor 0.
#[derive(Debug, Clone)]
struct Tls {
    dir: std::path::PathBuf,
}

impl Tls {
    fn flags(&self, who: &str) -> Vec<String> {
        let file = |ext: &str| self.dir.join(format!("{who}.{ext}")).display().to_string();
        vec![
            format!("--tls-ca={}", self.dir.join("ca.pem").display()),
            format!("--tls-cert={}", file("pem")),
            format!("--tls-key={}", file("key")),
        ]
    }
}

/// `loadgen actors` against `endpoint` for `seconds`; its JSON report once it is done.
fn offer(endpoint: &str, tls: Option<&Tls>, actors: u32, rate: f64, seconds: f64) -> std::process::Child {
    let (batch, envs) = batch_shape();
    Command::new(binary("loadgen"))
        .args(tls.map(|t| t.flags("actor-0")).unwrap_or_default())
        .args(["actors", "--connect", endpoint, "--run", RUN])
        .args(["--actors", &actors.to_string(), "--rate", &rate.to_string()])
        .args(["--batch", &batch.to_string(), "--envs", &envs.to_string(), "--seconds", &seconds.to_string()])
        .env("RUST_LOG", "warn,zenoh=error")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap()
}

fn report(child: std::process::Child) -> serde_json::Value {
    let output = child.wait_with_output().unwrap();
    assert!(output.status.success(), "loadgen failed: {}", output.status);
    serde_json::from_slice(&output.stdout).unwrap()
}

/// Transitions/s zenoh alone carries from `actors` load generators to one subscriber, over
/// plain TCP or mutual TLS.
fn anchor(tls: Option<&Tls>, actors: u32, rate: f64, seconds: f64) -> f64 {
    let endpoint = match tls {
        Some(_) => format!("tls/localhost:{}", free_port()),
        None => format!("tcp/127.0.0.1:{}", free_port()),
    };
    let sink = Command::new(binary("loadgen"))
        .args(tls.map(|t| t.flags("learner")).unwrap_or_default())
        .args(["sink", "--listen", &endpoint, "--seconds", &seconds.to_string()])
        // Up until the generators are done: a peer that vanishes mid-put stalls them.
        .args(["--linger", &(seconds + 10.0).to_string()])
        .env("RUST_LOG", "warn,zenoh=error")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    // The generators run past the sink's window: it counts from its first message on.
    let load = offer(&endpoint, tls, actors, rate, seconds + 5.0 + f64::from(actors) * 0.02);
    let mut sink = sink;
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(sink.stdout.take().unwrap()), &mut line).unwrap();
    let sink_report: serde_json::Value = serde_json::from_str(&line).unwrap();
    let _ = report(load);
    let _ = sink.kill();
    let _ = sink.wait();
    let sink = sink_report;
    let (batch, _) = batch_shape();
    sink["messages"].as_f64().unwrap() * batch as f64 / sink["seconds"].as_f64().unwrap()
}

struct Row {
    actors: u32,
    offered: f64,
    zenoh: f64,
    received: f64,
    validated: f64,
    inserted: f64,
    dropped: u64,
    rejected: u64,
    updates: f64,
    cpu: f64,
    rss: (f64, f64),
    connected: usize,
}

fn learner_row(actors: u32, rate: f64, seconds: f64, zenoh: f64) -> Row {
    let runs = tempfile::tempdir().unwrap();
    let max_actors = format!("learner.max_actors={}", actors + 8);
    let args = [
        "--set",
        "learner.status_every_s=1.0",
        "--set",
        &max_actors,
        "--set",
        "rate.limit_inserts=false",
        "--set",
        "rate.samples_per_insert=0.0",
        "--set",
        "learner.checkpoint_every=0",
    ];
    let mut learner = Learner::builder(runs.path(), RUN).config(CONFIG).args(&args).start();
    learner.wait_for(Duration::from_secs(60), "the learner's first status", |_| true);
    let endpoint = format!("tcp/127.0.0.1:{}", learner.port);
    let load = offer(&endpoint, None, actors, rate, seconds + 15.0 + f64::from(actors) * 0.05);
    let pid = learner.child.id();
    let all_connected = |s: &serde_json::Value| s["connected_actors"].as_array().map_or(0, Vec::len) >= actors as usize;
    let first = learner.wait_for(Duration::from_secs(120), "every simulated actor connected and sending", |s| {
        all_connected(s) && u64_at(s, "/env_steps") > 0
    });
    let (cpu0, rss0) = (cpu_seconds(pid), rss_mib(pid).unwrap_or(f64::NAN));
    std::thread::sleep(Duration::from_secs_f64(seconds));
    let last = learner.status().unwrap();
    let (cpu1, rss1) = (cpu_seconds(pid), rss_mib(pid).unwrap_or(f64::NAN));
    let elapsed = last["elapsed_s"].as_f64().unwrap() - first["elapsed_s"].as_f64().unwrap();
    let (batch, _) = batch_shape();
    let delta = |pointer: &str| u64_at(&last, pointer).saturating_sub(u64_at(&first, pointer));
    let rejected = |s: &serde_json::Value| {
        s["rejected"].as_object().map_or(0, |m| m.values().filter_map(serde_json::Value::as_u64).sum::<u64>())
    };
    let inserted = delta("/env_steps") as f64 / elapsed;
    let dropped = delta("/dropped_batches");
    let rejected = rejected(&last).saturating_sub(rejected(&first));
    let validated = inserted + (dropped * batch as u64) as f64 / elapsed;
    let row = Row {
        actors,
        offered: f64::from(actors) * rate,
        zenoh,
        received: validated + (rejected * batch as u64) as f64 / elapsed,
        validated,
        inserted,
        dropped,
        rejected,
        updates: delta("/updates") as f64 / elapsed,
        cpu: (cpu1 - cpu0) / elapsed,
        rss: (rss0, rss1),
        connected: last["connected_actors"].as_array().map_or(0, Vec::len),
    };
    // The generators finish first: a learner that left would stall their puts.
    let _ = report(load);
    learner.terminate(Duration::from_secs(60));
    row
}

fn main() {
    let counts: Vec<u32> = std::env::var("SCALE_ACTORS")
        .unwrap_or_else(|_| "1,4,16,64,256".into())
        .split(',')
        .filter_map(|n| n.trim().parse().ok())
        .collect();
    let rate: f64 = env_or("SCALE_RATE", 2000.0);
    let seconds: f64 = env_or("SCALE_SECONDS", 20.0);
    let (batch, _) = batch_shape();
    println!(
        "== scale: {CONFIG}, batches of {batch} transitions, {rate} transitions/s offered per actor, {seconds} s windows"
    );
    println!("== {} cores, {}", std::thread::available_parallelism().map_or(0, |n| n.get()), cpu_model());
    println!(
        "{:>6} {:>10} {:>10} {:>10} {:>10} {:>10} {:>8} {:>8} {:>9} {:>6} {:>17} {:>9} {:>10}",
        "actors",
        "offered/s",
        "zenoh/s",
        "received",
        "validated",
        "inserted",
        "dropped",
        "rejected",
        "updates/s",
        "cpu",
        "learner RSS MiB",
        "connected",
        "ins/zenoh"
    );
    let material = tempfile::tempdir().unwrap();
    let tls = (env_or("SCALE_TLS", 0) == 1)
        .then(|| Tls { dir: crawler_tests::make_tls(&material.path().join("tls"), "localhost", 1) });
    let mut tls_rows = Vec::new();
    for actors in counts {
        let zenoh = anchor(None, actors, rate, seconds);
        if let Some(tls) = &tls {
            tls_rows.push((actors, zenoh, anchor(Some(tls), actors, rate, seconds)));
        }
        let row = learner_row(actors, rate, seconds, zenoh);
        println!(
            "{:>6} {:>10.0} {:>10.0} {:>10.0} {:>10.0} {:>10.0} {:>8} {:>8} {:>9.0} {:>6.2} {:>7.0} → {:>7.0} {:>9} {:>10.2}",
            row.actors,
            row.offered,
            row.zenoh,
            row.received,
            row.validated,
            row.inserted,
            row.dropped,
            row.rejected,
            row.updates,
            row.cpu,
            row.rss.0,
            row.rss.1,
            row.connected,
            row.inserted / row.zenoh
        );
    }
    if !tls_rows.is_empty() {
        println!("== zenoh alone, plain TCP against mutual TLS (transitions/s)");
        println!("{:>6} {:>10} {:>10} {:>9}", "actors", "tcp", "tls", "tls/tcp");
        for (actors, tcp, tls) in tls_rows {
            println!("{actors:>6} {tcp:>10.0} {tls:>10.0} {:>9.2}", tls / tcp);
        }
    }
}
