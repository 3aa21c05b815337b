//! Learning speed: trains the default preset and evaluates it greedily as it goes.
//! `cargo build --release --bins && cargo bench -p crawler-tests --bench learning_speed`
//!
//! Environment: `MINUTES` of training (default 20), `SEED` (default 0), `CONFIG` (default
//! configs/default.toml), `EVAL_EVERY_S` (default 30), `SET` (extra `KEY=VALUE` settings,
//! separated by `;`, e.g. `env.direction="backward"`), `INIT_FROM` (a checkpoint to start
//! from: transfer), `RUNS_DIR` and `RUN` (keep the run there, with its metrics and an
//! `evaluations.json`; by default it lives in a temporary directory), `ACTORS` (local actor
//! processes, default 2; an Ape-X ladder's `exploration.actors` should match, via `SET`).
//! About every `EVAL_EVERY_S` seconds the newest checkpoint is run for 10 greedy episodes of
//! 20 s (`eval`). Prints each evaluation (with its slowest episode and the episodes stuck
//! below 0.05 m/s: a mean hides them), the wall time of training to the first evaluation
//! ≥ 0.5 m/s, the speed at 20 and 60 minutes, and the env steps and updates done. Evaluation
//! shares the machine with training, as a user's would.
//!
//! `MUJOCO=1` also plays checkpoints on the study's own MuJoCo model after training
//! (`scripts/mujoco-check eval`, 10 greedy episodes of 20 s), one every `MUJOCO_EVERY_S`
//! seconds of training (default 120) and the last, and prints the time to the first that
//! crawls ≥ 0.5 m/s there without a flip: the transfer column of EXPERIMENTS.md.
#![allow(clippy::print_stdout, clippy::unwrap_used)]

use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use crawler_tests::{Learner, binary, env_or};

#[derive(serde::Serialize)]
struct Evaluation {
    train_seconds: f64,
    updates: u64,
    env_steps: u64,
    physics_steps: u64,
    speed: f64,
    speed_std: f64,
    min_speed: f64,
    stuck_episodes: u64,
    flips: u64,
    checkpoint: PathBuf,
    /// The same checkpoint on the study's MuJoCo model (`MUJOCO=1`), as
    /// `scripts/mujoco-check eval` summarises it.
    mujoco: Option<serde_json::Value>,
}

fn evaluate(checkpoint: &PathBuf) -> Option<Evaluation> {
    let output = Command::new(binary("eval")).arg(checkpoint).output().ok()?;
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).ok()?;
    Some(Evaluation {
        train_seconds: report["train_seconds"].as_f64()?,
        updates: report["updates"].as_u64()?,
        env_steps: report["env_steps"].as_u64()?,
        physics_steps: report["physics_steps"].as_u64()?,
        speed: report["speed"]["mean"].as_f64()?,
        speed_std: report["speed"]["std"].as_f64()?,
        min_speed: report["min_speed"].as_f64()?,
        stuck_episodes: report["stuck_episodes"].as_u64()?,
        flips: report["flips"].as_u64()?,
        checkpoint: checkpoint.clone(),
        mujoco: None,
    })
}

/// The summary of `scripts/mujoco-check eval` on `checkpoint`; on failure, why.
fn evaluate_in_mujoco(checkpoint: &PathBuf) -> Result<serde_json::Value, String> {
    let script = crawler_tests::repo_root().join("scripts/mujoco-check");
    let output = Command::new(script).arg("eval").arg(checkpoint).output().map_err(|e| e.to_string())?;
    if !output.status.success() {
        return Err(String::from_utf8_lossy(&output.stderr).into_owned());
    }
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).map_err(|e| e.to_string())?;
    Ok(report["summary"].clone())
}

/// Plays every `every_s` seconds' checkpoint and the last in MuJoCo, printing each.
fn cross_check_in_mujoco(evaluations: &mut [Evaluation], every_s: f64) {
    println!("on the study's MuJoCo model (scripts/mujoco-check eval):");
    println!("{:>8} {:>16} {:>9} {:>6} {:>6}", "train s", "speed m/s", "min", "stuck", "flips");
    let last = evaluations.len().saturating_sub(1);
    let mut last_checked = -f64::INFINITY;
    for (index, evaluation) in evaluations.iter_mut().enumerate() {
        if evaluation.train_seconds - last_checked < every_s && index != last {
            continue;
        }
        last_checked = evaluation.train_seconds;
        match evaluate_in_mujoco(&evaluation.checkpoint) {
            Ok(summary) => {
                let number = |key: &str| summary[key].as_f64().unwrap_or(f64::NAN);
                println!(
                    "{:>8.0} {:>9.3} ± {:.3} {:>9.3} {:>6} {:>6}",
                    evaluation.train_seconds,
                    number("mean_speed"),
                    number("std_speed"),
                    number("min_speed"),
                    number("stuck_episodes"),
                    number("flips")
                );
                evaluation.mujoco = Some(summary);
            }
            Err(why) => {
                eprintln!("MuJoCo evaluation of {} failed: {why}", evaluation.checkpoint.display());
                return;
            }
        }
    }
    let crawls = |e: &&Evaluation| {
        e.mujoco
            .as_ref()
            .is_some_and(|m| m["mean_speed"].as_f64().is_some_and(|v| v >= 0.5) && m["flips"].as_u64() == Some(0))
    };
    match evaluations.iter().find(crawls) {
        Some(e) => println!("first MuJoCo evaluation >= 0.5 m/s without a flip: {:.0} s of training", e.train_seconds),
        None => println!("no MuJoCo evaluation reached 0.5 m/s without a flip"),
    }
}

fn main() {
    let minutes: f64 = env_or("MINUTES", 20.0);
    let seed: u64 = env_or("SEED", 0);
    let config: String = env_or("CONFIG", "configs/default.toml".to_string());
    let eval_every: f64 = env_or("EVAL_EVERY_S", 30.0);
    let actors: usize = env_or("ACTORS", 2);
    let temporary = tempfile::tempdir().unwrap();
    let runs_dir: PathBuf = std::env::var_os("RUNS_DIR").map_or_else(|| temporary.path().to_path_buf(), PathBuf::from);
    let run: String = env_or("RUN", "speed".to_string());
    let set: String = env_or("SET", String::new());
    let settings = [
        format!("learner.max_seconds={}", minutes * 60.0),
        "learner.checkpoint_every=2000".into(),
        "learner.keep_checkpoints=1000000".into(),
        "learner.snapshot_replay=false".into(),
        format!("dqn.seed={seed}"),
        format!("actor.seed={}", seed * 100_000),
    ];
    let settings: Vec<String> =
        settings.into_iter().chain(set.split(';').map(str::trim).filter(|s| !s.is_empty()).map(String::from)).collect();
    let mut extra = Vec::new();
    for setting in &settings {
        extra.extend(["--set", setting.as_str()]);
    }
    let init_from = std::env::var("INIT_FROM").ok();
    if let Some(path) = &init_from {
        extra.extend(["--init-from", path.as_str()]);
    }
    let mut learner = Learner::builder(&runs_dir, &run).config(&config).actors(actors).args(&extra).start();
    let checkpoints = runs_dir.join(&run).join("checkpoints");
    println!(
        "config {config}, seed {seed}, {minutes} min, {actors} actors, settings {settings:?}, init from {init_from:?}"
    );
    println!(
        "{:>8} {:>10} {:>12} {:>14} {:>16} {:>6} {:>6} {:>6}",
        "train s", "updates", "env steps", "physics steps", "speed m/s", "min", "stuck", "flips"
    );
    let mut evaluations: Vec<Evaluation> = Vec::new();
    let mut last_evaluated = -f64::INFINITY;
    loop {
        let exit = learner.child.try_wait().ok().flatten();
        let finished = exit.is_some();
        let newest = crawler_learner::checkpoint::list(&checkpoints).ok().and_then(|mut l| l.pop());
        if let Some(path) = newest
            && let Some(evaluation) = evaluate(&path)
            && (evaluation.train_seconds - last_evaluated >= eval_every || finished)
            && evaluations.last().is_none_or(|e| e.updates != evaluation.updates)
        {
            println!(
                "{:>8.0} {:>10} {:>12} {:>14} {:>9.3} ± {:.3} {:>6.3} {:>6} {:>6}",
                evaluation.train_seconds,
                evaluation.updates,
                evaluation.env_steps,
                evaluation.physics_steps,
                evaluation.speed,
                evaluation.speed_std,
                evaluation.min_speed,
                evaluation.stuck_episodes,
                evaluation.flips
            );
            last_evaluated = evaluation.train_seconds;
            evaluations.push(evaluation);
        }
        if let Some(status) = exit {
            if !status.success() && evaluations.is_empty() {
                eprintln!("the learner exited with {status} before any evaluation: its log says why");
                std::process::exit(1);
            }
            break;
        }
        std::thread::sleep(Duration::from_secs(2));
    }
    if env_or("MUJOCO", 0) == 1 {
        cross_check_in_mujoco(&mut evaluations, env_or("MUJOCO_EVERY_S", 120.0));
    }
    let first = evaluations.iter().find(|e| e.speed >= 0.5);
    match first {
        Some(e) => println!(
            "first evaluation >= 0.5 m/s: {:.0} s of training ({:.3} m/s, {} physics steps)",
            e.train_seconds, e.speed, e.physics_steps
        ),
        None => println!("no evaluation reached 0.5 m/s"),
    }
    for mark in [20.0, 60.0] {
        match evaluations.iter().rev().find(|e| e.train_seconds <= mark * 60.0 + 1.0) {
            Some(e) if minutes >= mark => {
                println!(
                    "speed at {mark} min: {:.3} ± {:.3} m/s (min {:.3}, {} stuck), {} flips",
                    e.speed, e.speed_std, e.min_speed, e.stuck_episodes, e.flips
                )
            }
            _ => println!("speed at {mark} min: not reached (run with MINUTES={mark})"),
        }
    }
    let record = serde_json::json!({ "config": config, "seed": seed, "minutes": minutes, "settings": settings,
        "init_from": init_from, "evaluations": evaluations });
    std::fs::write(runs_dir.join(&run).join("evaluations.json"), serde_json::to_vec_pretty(&record).unwrap()).unwrap();
    if let Some(e) = evaluations.last() {
        println!(
            "done: {} env steps, {} physics steps, {} updates in {:.0} s",
            e.env_steps, e.physics_steps, e.updates, e.train_seconds
        );
    }
}
