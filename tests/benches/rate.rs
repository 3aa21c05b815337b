//! Does samples per insert hold whichever side is slower? The real learner and actors, on
//! this machine, with each rate-control mode.
//! `cargo build --release --bins && cargo bench -p crawler-tests --bench rate`
//!
//! Each case is `PRESET:ACTORS:MODE:SECONDS` (MODE `both`: `rate.limit_inserts=true`,
//! `samples`: the sample side alone); `RATE_CASES` replaces the default list, which holds the
//! study preset with two actors for 10 minutes, and the default preset for 3 minutes with
//! one actor (the learner the fast side) and with four (the slow side) in both modes.
//! Printed per case, from the learner's last status: the configured and the realised samples
//! per insert (counted by the rate limiter from the warm-up on) and their ratio, updates/s,
//! env steps/s, and the actors' mean share of time spent waiting to hand over their data
//! (for insert credit, or a slow link).
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::time::{Duration, Instant};

use crawler_tests::{Learner, cpu_model, repo_root, u64_at};

const DEFAULT_CASES: &str = "study:2:both:600,default:1:both:180,\
                             default:4:both:180,default:4:samples:180";

struct Case {
    preset: String,
    actors: usize,
    limit_inserts: bool,
    seconds: u64,
}

fn parse(case: &str) -> Case {
    let parts: Vec<&str> = case.trim().split(':').collect();
    assert_eq!(parts.len(), 4, "a case is PRESET:ACTORS:MODE:SECONDS, not {case:?}");
    let limit_inserts = match parts[2] {
        "both" => true,
        "samples" => false,
        other => panic!("mode {other:?}: use `both` or `samples`"),
    };
    Case {
        preset: parts[0].to_string(),
        actors: parts[1].parse().unwrap(),
        limit_inserts,
        seconds: parts[3].parse().unwrap(),
    }
}

fn main() {
    let cases: Vec<Case> =
        std::env::var("RATE_CASES").unwrap_or_else(|_| DEFAULT_CASES.into()).split(',').map(parse).collect();
    println!("== rate control, {} cores, {}", std::thread::available_parallelism().map_or(0, |n| n.get()), cpu_model());
    println!(
        "{:>8} {:>6} {:>8} {:>6} {:>10} {:>9} {:>8} {:>9} {:>10} {:>10}",
        "preset", "actors", "mode", "s", "configured", "realised", "ratio", "updates/s", "env st/s", "waiting"
    );
    for case in cases {
        let config = format!("configs/{}.toml", case.preset);
        let configured = crawler_run::config::TrainConfig::load(&repo_root().join(&config), &[])
            .unwrap_or_else(|e| panic!("{config}: {e}"))
            .rate
            .samples_per_insert;
        let runs = tempfile::tempdir().unwrap();
        let limit = format!("rate.limit_inserts={}", case.limit_inserts);
        let mut learner = Learner::builder(runs.path(), "rate")
            .config(&config)
            .actors(case.actors)
            .args(&["--set", &limit, "--set", "learner.status_every_s=5.0"])
            .start();
        let start = Instant::now();
        learner.wait_for(Duration::from_secs(120), "training to start", |s| u64_at(s, "/updates") > 0);
        let first = learner.status().unwrap();
        std::thread::sleep(Duration::from_secs(case.seconds).saturating_sub(start.elapsed()));
        let last = learner.status().unwrap();
        learner.terminate(Duration::from_secs(120));
        let elapsed = last["elapsed_s"].as_f64().unwrap() - first["elapsed_s"].as_f64().unwrap();
        let rate = |pointer: &str| (u64_at(&last, pointer) - u64_at(&first, pointer)) as f64 / elapsed;
        let realised = last["samples_per_insert"].as_f64().unwrap_or(f64::NAN);
        let waits: Vec<f64> = last["actors"]
            .as_object()
            .map(|a| a.values().filter_map(|v| v["waiting_fraction"].as_f64()).collect())
            .unwrap_or_default();
        let wait = waits.iter().sum::<f64>() / waits.len().max(1) as f64;
        println!(
            "{:>8} {:>6} {:>8} {:>6} {:>10.2} {:>9.2} {:>8.3} {:>9.0} {:>10.0} {:>9.0}%",
            case.preset,
            case.actors,
            if case.limit_inserts { "both" } else { "samples" },
            case.seconds,
            configured,
            realised,
            realised / configured,
            rate("/updates"),
            rate("/env_steps"),
            100.0 * wait,
        );
    }
}
