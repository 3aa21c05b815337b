//! How long an actor takes to join a learner, with and without an attacker holding idle TCP
//! connections open to the learner's port (connections that never start zenoh's handshake
//! each hold an accept slot until `transport/unicast/accept_timeout`, 2 s here).
//! `cargo build --release --bins && cargo bench -p crawler-tests --bench join`
//!
//! Prints, from one run: the median and worst time from an actor's start to its first
//! weights, on a quiet port and under JOIN_BENCH_IDLE idle connections (default 200), and
//! their ratio. Timings live here, not in tests: the machines are shared and noisy.
//! `JOIN_BENCH_ZENOH=transport/unicast/accept_timeout=10000` passes a zenoh setting to the
//! learner (that one restores zenoh's default, for a before/after).
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::net::TcpStream;
use std::time::{Duration, Instant};

use crawler_tests::{Actor, Learner, free_port, u64_at};

const JOINS: u32 = 7;

/// Seconds from starting an actor process to its first weights, `JOINS` times.
fn join_times(port: u16, run: &str, log_dir: &std::path::Path) -> Vec<f64> {
    (0..JOINS)
        .map(|i| {
            let start = Instant::now();
            let mut actor = Actor::start(port, 100 + i, run, log_dir);
            actor.wait_for_log(Duration::from_secs(120), "first weights");
            start.elapsed().as_secs_f64()
        })
        .collect()
}

fn summary(times: &mut [f64]) -> (f64, f64) {
    times.sort_by(f64::total_cmp);
    (times[times.len() / 2], times[times.len() - 1])
}

fn main() {
    let idle: usize = std::env::var("JOIN_BENCH_IDLE").ok().and_then(|s| s.parse().ok()).unwrap_or(200);
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let zenoh = std::env::var("JOIN_BENCH_ZENOH").ok();
    let extra: Vec<&str> = zenoh.iter().flat_map(|z| ["--zenoh", z.as_str()]).collect();
    let mut learner = Learner::builder(dir.path(), "join").port(port).config("configs/smoke.toml").args(&extra).start();
    learner.wait_for(Duration::from_secs(60), "the learner's first status", |s| u64_at(s, "/weights_version") >= 1);

    let mut quiet = join_times(port, "join", dir.path());
    // The attacker: plain TCP connections that send nothing, reopened as the router drops them.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let holder = {
        let stop = std::sync::Arc::clone(&stop);
        std::thread::spawn(move || {
            let mut held: Vec<TcpStream> = Vec::new();
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                held.retain(|s| s.peer_addr().is_ok());
                while held.len() < idle {
                    match TcpStream::connect(("127.0.0.1", port)) {
                        Ok(stream) => held.push(stream),
                        Err(_) => break,
                    }
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        })
    };
    std::thread::sleep(Duration::from_secs(1));
    let mut attacked = join_times(port, "join", dir.path());
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    holder.join().unwrap();

    let (quiet_median, quiet_worst) = summary(&mut quiet);
    let (attacked_median, attacked_worst) = summary(&mut attacked);
    println!("join time, start of the actor process to its first weights ({JOINS} joins each):");
    println!("  quiet port:               median {quiet_median:.2} s, worst {quiet_worst:.2} s");
    println!("  {idle} idle connections:   median {attacked_median:.2} s, worst {attacked_worst:.2} s");
    println!(
        "  ratio (attacked / quiet): median {:.2}x, worst {:.2}x",
        attacked_median / quiet_median,
        attacked_worst / quiet_worst
    );
    assert!(learner.terminate(Duration::from_secs(60)).success());
}
