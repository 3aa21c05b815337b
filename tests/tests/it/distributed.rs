//! A learner and two actors, as real processes on loopback.

#![allow(clippy::unwrap_used)]

use std::process::Command;
use std::time::Duration;

use crawler_tests::{Learner, binary, repo_root, u64_at};

#[test]
fn a_learner_trains_on_two_actors_and_checkpoints() {
    let runs = tempfile::tempdir().unwrap();
    let mut learner = Learner::builder(runs.path(), "itest").actors(2).start();

    let status = learner.wait_for(Duration::from_secs(180), "both actors' transitions in replay", |s| {
        let both = |pointer: &str, min: u64| (0..2).all(|id| u64_at(s, &format!("/actors/{id}/{pointer}")) >= min);
        both("transitions", 1) && both("weights_version", 3) && s["last_checkpoint"].is_string()
    });
    // The liveliness view lists both actors; weights reached them; training is sane.
    assert_eq!(status["connected_actors"], serde_json::json!([0, 1]), "{status:#}");
    assert!(status["loss"].as_f64().is_some_and(f64::is_finite), "loss {:?}", status["loss"]);
    assert!(u64_at(&status, "/updates") > 0 && u64_at(&status, "/replay_len") > 0);
    assert!(u64_at(&status, "/weights_version") >= 3);

    let exit = learner.terminate(Duration::from_secs(60));
    assert!(exit.success(), "learner exit after SIGTERM: {exit}");
    // SIGTERM leaves a final checkpoint that loads, with finite weights and the replay.
    let checkpoint = crawler_learner::checkpoint::load(&runs.path().join("itest/checkpoints")).unwrap();
    assert!(checkpoint.meta.progress.updates >= u64_at(&status, "/updates"));
    assert!(checkpoint.online.iter().all(|v| v.is_finite()));
    let replay = crate::replay_of(&checkpoint).unwrap().unwrap();
    assert!(replay.len() as u64 >= u64_at(&status, "/replay_len"));

    // `eval` of that checkpoint: JSON on stdout, the same for the same seeds.
    let eval = || {
        let output = Command::new(binary("eval"))
            .arg(runs.path().join("itest/checkpoints"))
            .args(["--episodes", "3", "--seconds", "2", "--seed", "5"])
            .output()
            .unwrap();
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        serde_json::from_slice::<serde_json::Value>(&output.stdout).unwrap()
    };
    let first = eval();
    assert_eq!(first, eval(), "eval is deterministic for fixed seeds");
    assert_eq!(first["episodes"].as_array().unwrap().len(), 3);
    assert!(first["speed"]["mean"].as_f64().unwrap().is_finite());
    // The failures a mean hides: the slowest episode and how many barely moved.
    let speeds: Vec<f64> = first["episodes"].as_array().unwrap().iter().map(|e| e["speed"].as_f64().unwrap()).collect();
    let slowest = speeds.iter().copied().fold(f64::INFINITY, f64::min);
    assert!((first["min_speed"].as_f64().unwrap() - slowest).abs() < 1e-6, "{first:#}");
    let stuck = speeds.iter().filter(|&&v| v < first["stuck_below_speed"].as_f64().unwrap()).count() as u64;
    assert_eq!(first["stuck_episodes"].as_u64(), Some(stuck), "{first:#}");
    let failed = first["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .zip(&speeds)
        .filter(|(e, v)| **v < first["stuck_below_speed"].as_f64().unwrap() || e["flips"].as_u64() != Some(0))
        .count() as u64;
    assert_eq!(first["failed_episodes"].as_u64(), Some(failed), "{first:#}");
    assert!((first["episodes"][0]["duration"].as_f64().unwrap() - 2.0).abs() < 1e-3);
}

#[test]
fn bad_configs_are_refused_with_the_key_or_path_named() {
    let run = |args: &[&str]| {
        let output = Command::new(binary("learner")).current_dir(repo_root()).args(args).output().unwrap();
        assert!(!output.status.success(), "{args:?} should fail");
        String::from_utf8_lossy(&output.stderr).into_owned()
    };
    let message = run(&["--config", "configs/no-such-preset.toml", "--actors", "0"]);
    assert!(message.contains("configs/no-such-preset.toml"), "{message}");
    let message = run(&["--config", "configs/smoke.toml", "--set", "dqn.lr=5", "--actors", "0"]);
    assert!(message.contains("dqn.lr") && message.contains("(0, 1)"), "{message}");
    let message = run(&["--config", "configs/smoke.toml", "--set", "env.action_repeat=0", "--actors", "0"]);
    assert!(message.contains("env.action_repeat"), "{message}");
    let message = run(&["--config", "configs/smoke.toml", "--set", "dqn.reward_scale=0", "--actors", "0"]);
    assert!(message.contains("dqn.reward_scale") && message.contains("[1e-6, 1e6]"), "{message}");
    // A run id that is no key-expression chunk (or a path) is refused before any actor starts.
    let message = run(&["--config", "configs/smoke.toml", "--run", "lever-0.1", "--actors", "2"]);
    assert!(message.contains("`lever-0.1`") && message.contains("A-Z a-z 0-9 _ -"), "{message}");
    assert!(!message.contains("started local actors"), "{message}");
    // NaN anywhere, by key; a replay this machine cannot hold, before any actor starts.
    for key in ["dqn.adam_eps", "rate.error_buffer", "learner.max_seconds"] {
        let message = run(&["--config", "configs/smoke.toml", "--set", &format!("{key}=nan"), "--actors", "0"]);
        assert!(message.contains(key) && message.contains("finite"), "{message}");
    }
    let message = run(&["--config", "configs/smoke.toml", "--set", "replay.capacity=4000000000", "--actors", "2"]);
    assert!(message.contains("replay.capacity") && message.contains("MiB"), "{message}");
    assert!(!message.contains("started local actors"), "{message}");
    // Plain TCP beyond loopback needs an explicit opt-in, and the refusal says why.
    let listen = "learner.listen=[\"tcp/0.0.0.0:7447\"]";
    let message = run(&["--config", "configs/smoke.toml", "--set", listen, "--actors", "0"]);
    assert!(message.contains("--allow-plain-remote") && message.contains("unauthenticated"), "{message}");
}

#[test]
fn a_resumed_run_continues_its_counters_weights_version_and_replay() {
    let runs = tempfile::tempdir().unwrap();
    let mut first =
        Learner::builder(runs.path(), "resumed").actors(2).args(&["--set", "learner.max_updates=150"]).start();
    let exit = first.wait_for_exit(Duration::from_secs(180));
    assert!(exit.success(), "first session: {exit}");
    let checkpoints = runs.path().join("resumed/checkpoints");
    let before = crawler_learner::checkpoint::load(&checkpoints).unwrap();
    let replay_before = crate::replay_of(&before).unwrap().unwrap().len();
    assert_eq!(before.meta.progress.updates, 150);

    // `--resume` takes the run's own config; the overrides here only move the goal post.
    let mut second =
        Learner::builder(runs.path(), "resumed").resume().actors(2).args(&["--set", "learner.max_updates=300"]).start();
    let exit = second.wait_for_exit(Duration::from_secs(180));
    assert!(exit.success(), "resumed session: {exit}");
    let after = crawler_learner::checkpoint::load(&checkpoints).unwrap();
    let (p0, p1) = (&before.meta.progress, &after.meta.progress);
    assert_eq!(p1.updates, 300, "updates continue from 150 to the new limit");
    assert!(p1.env_steps > p0.env_steps && p1.physics_steps > p0.physics_steps, "{p0:?} → {p1:?}");
    assert!(p1.weights_version > p0.weights_version, "weights versions continue: {p0:?} → {p1:?}");
    assert!(p1.train_seconds > p0.train_seconds);
    assert_eq!(after.meta.run_id, "resumed");
    let replay_after = crate::replay_of(&after).unwrap().unwrap().len();
    assert!(replay_after > replay_before, "the replay was restored and grew: {replay_before} → {replay_after}");
}

#[test]
fn an_actor_waiting_for_an_absent_learner_exits_on_sigterm() {
    let port = crawler_tests::free_port();
    let mut actor = Command::new(binary("actor"))
        .args(["--connect", &format!("tcp/127.0.0.1:{port}"), "--id", "0"])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    assert!(actor.try_wait().unwrap().is_none(), "it waits for the learner");
    crawler_tests::signal(actor.id(), "TERM");
    let start = std::time::Instant::now();
    let status = loop {
        if let Some(status) = actor.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > Duration::from_secs(5) {
            let _ = actor.kill();
            panic!("the actor ignored SIGTERM while connecting");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "{status}");
}

/// Samples per insert, as the learner's status reports it, once both actors have reported
/// and the learner has made `updates` updates.
fn realised_ratio(limit_inserts: bool, updates: u64) -> (f64, serde_json::Value) {
    let runs = tempfile::tempdir().unwrap();
    let limit = format!("rate.limit_inserts={limit_inserts}");
    // 64 samples per insert: two updates of 32 per transition, more than the learner can
    // make at the rate two actors produce, so the learner is the slow side.
    let mut learner = Learner::builder(runs.path(), "ratio")
        .actors(2)
        .args(&["--set", "rate.samples_per_insert=64.0", "--set", "rate.error_buffer=128.0", "--set", &limit])
        .start();
    let status = learner.wait_for(Duration::from_secs(180), "updates with both actors reporting", |s| {
        u64_at(s, "/updates") >= updates && (0..2).all(|id| u64_at(s, &format!("/actors/{id}/env_steps")) > 0)
    });
    let exit = learner.terminate(Duration::from_secs(60));
    assert!(exit.success(), "learner exit after SIGTERM: {exit}");
    (status["samples_per_insert"].as_f64().unwrap(), status)
}

#[test]
fn limited_inserts_hold_samples_per_insert_when_the_learner_is_the_slow_side() {
    let (ratio, status) = realised_ratio(true, 6000);
    assert!((ratio - 64.0).abs() <= 6.4, "realised samples per insert {ratio}, configured 64: {status:#}");
    // The actors were held back, and said so; none sent past its credit.
    let waits: Vec<f64> =
        (0..2).map(|id| status["actors"][id.to_string()]["waiting_fraction"].as_f64().unwrap()).collect();
    assert!(waits.iter().all(|&w| w > 0.2), "credit waits {waits:?}: {status:#}");
    assert_eq!(status["rejected"].get("over_credit"), None, "{status:#}");
    assert!(status["insert_headroom"].is_u64(), "{status:#}");
    // With the sample side alone, the same actors push the ratio far below the setting.
    let (ratio, status) = realised_ratio(false, 6000);
    assert!(ratio < 32.0, "realised {ratio} without the insert limit: {status:#}");
    assert!(status["insert_headroom"].is_null(), "{status:#}");
}

#[test]
fn an_actor_that_ignores_its_insert_credit_is_refused_past_it() {
    let runs = tempfile::tempdir().unwrap();
    // One genuine actor, and the learner the slow side (64 samples per insert).
    let mut learner = Learner::builder(runs.path(), "greedy")
        .actors(1)
        .args(&["--set", "rate.samples_per_insert=64.0", "--set", "rate.error_buffer=128.0"])
        .start();
    learner.wait_for(Duration::from_secs(120), "training", |s| u64_at(s, "/updates") > 100);
    // A simulated actor (id 5) that publishes as fast as the link takes, credit or not.
    let endpoint = format!("tcp/127.0.0.1:{}", learner.port);
    let output = Command::new(binary("loadgen"))
        .args(["actors", "--connect", &endpoint, "--run", "greedy", "--actors", "1", "--first-id", "5", "--rate", "0"])
        .args(["--batch", "64", "--envs", "2", "--seconds", "4"])
        .env("RUST_LOG", "warn,zenoh=error")
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let offered: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let status = learner.wait_for(Duration::from_secs(30), "the flood counted", |s| {
        u64_at(s, "/rejected/over_credit") > 0 && u64_at(s, "/updates") > 2000
    });
    // Nearly everything it sent past its window was refused, and the ratio held.
    let refused = u64_at(&status, "/rejected/over_credit");
    assert!(refused * 2 > u64_at(&offered, "/batches"), "refused {refused} of {offered}: {status:#}");
    let ratio = status["samples_per_insert"].as_f64().unwrap();
    assert!((ratio - 64.0).abs() <= 6.4, "realised samples per insert {ratio}: {status:#}");
    let exit = learner.terminate(Duration::from_secs(60));
    assert!(exit.success(), "{exit}");
}
