//! The whole system on one machine: a learner and two actors with the default preset.
//! `cargo build --release --bins && cargo bench -p crawler-tests --bench system`
//!
//! Prints, from one run: what the actors produce against what the learner ingests
//! (transitions/s), end-to-end env and physics steps/s and updates/s, and the resident
//! memory of the learner and of each actor over time, with the growth from the moment the
//! replay filled up to the end. The soak: `SYSTEM_BENCH_SECONDS=1800`.
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::time::{Duration, Instant};

use crawler_tests::{Learner, children_of, rss_mib, u64_at};

const CONFIG: &str = "configs/default.toml";

fn main() {
    let seconds: u64 = std::env::var("SYSTEM_BENCH_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(90);
    let runs = tempfile::tempdir().unwrap();
    let extra = ["--set", "learner.status_every_s=5.0"];
    let capacity = crawler_run::config::TrainConfig::load(&crawler_tests::repo_root().join(CONFIG), &[])
        .unwrap_or_else(|e| panic!("{CONFIG}: {e}"))
        .replay
        .capacity;
    let mut learner = Learner::builder(runs.path(), "bench").config(CONFIG).actors(2).args(&extra).start();
    learner.wait_for(Duration::from_secs(60), "training to start", |s| u64_at(s, "/updates") > 0);
    let first = learner.status().unwrap();
    let start = Instant::now();
    println!(
        "{:>6} {:>10} {:>10} {:>10} {:>12} {:>12} {:>10}",
        "t (s)", "learner", "actor 0", "actor 1", "updates/s", "ingest/s", "replay"
    );
    // (learner, actors) RSS when the replay first reported its full capacity, and the latest.
    let mut at_full: Option<(f64, Vec<f64>)> = None;
    let mut latest: (f64, Vec<f64>) = (f64::NAN, Vec::new());
    while start.elapsed() < Duration::from_secs(seconds) {
        std::thread::sleep(Duration::from_secs(10));
        let pid = learner.child.id();
        let actors: Vec<f64> = children_of(pid).into_iter().filter_map(rss_mib).collect();
        let status = learner.status().unwrap();
        let actor_rss: Vec<String> = actors.iter().map(|r| format!("{r:>7.1} MiB")).collect();
        let learner_rss = rss_mib(pid).unwrap_or(f64::NAN);
        let replay_len = u64_at(&status, "/replay_len");
        println!(
            "{:>6} {:>6.1} MiB {} {:>12.0} {:>12.0} {:>10}",
            start.elapsed().as_secs(),
            learner_rss,
            actor_rss.join(" "),
            status["updates_per_second"].as_f64().unwrap_or(f64::NAN),
            status["env_steps_per_second"].as_f64().unwrap_or(f64::NAN),
            replay_len,
        );
        // Full: the ring's slots are all used. Each episode's last observation holds a slot
        // without being a transition, so the sampleable count stays a little below capacity.
        if at_full.is_none() && replay_len as f64 >= 0.99 * capacity as f64 {
            at_full = Some((learner_rss, actors.clone()));
        }
        latest = (learner_rss, actors);
    }
    let last = learner.status().unwrap();
    let elapsed = last["elapsed_s"].as_f64().unwrap() - first["elapsed_s"].as_f64().unwrap();
    let delta = |pointer: &str| (u64_at(&last, pointer) - u64_at(&first, pointer)) as f64 / elapsed;
    let ingested = delta("/env_steps");
    let produced: f64 =
        (0..2).map(|id| last["actors"][id.to_string()]["env_steps_per_second"].as_f64().unwrap_or(0.0)).sum();
    println!("== over {elapsed:.0} s");
    println!(
        "actors produce {produced:.0} transitions/s; the learner ingests {ingested:.0}/s ({:.2}x)",
        ingested / produced
    );
    println!(
        "end to end: {ingested:.0} env steps/s, {:.0} physics steps/s, {:.0} updates/s",
        delta("/physics_steps"),
        delta("/updates")
    );
    println!("dropped batches: {}, rejected: {}", last["dropped_batches"], last["rejected"]);
    match at_full {
        Some((learner_full, actors_full)) => {
            println!(
                "RSS learner: {learner_full:.1} MiB when replay filled, {:.1} MiB at the end ({:.3}x)",
                latest.0,
                latest.0 / learner_full
            );
            for (i, (full, end)) in actors_full.iter().zip(&latest.1).enumerate() {
                println!(
                    "RSS actor {i}: {full:.1} MiB when replay filled, {end:.1} MiB at the end ({:.3}x)",
                    end / full
                );
            }
        }
        None => println!("the replay did not fill during the run: no growth figure"),
    }
    learner.terminate(Duration::from_secs(60));
}
