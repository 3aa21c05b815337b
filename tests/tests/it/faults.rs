//! Faults with real processes: actors and learners killed with SIGKILL, a process publishing
//! bad input while training runs, and a kill in the middle of a checkpoint write.

#![allow(clippy::unwrap_used)]

use std::process::Command;
use std::time::{Duration, Instant};

use crawler_learner::checkpoint;
use crawler_tests::{Actor, Learner, binary, free_port, log_field, signal, u64_at};

const SMOKE: &str = "configs/smoke.toml";

#[test]
fn an_actor_killed_with_sigkill_leaves_training_going_and_a_restart_gets_the_latest_weights() {
    let runs = tempfile::tempdir().unwrap();
    let port = free_port();
    let mut learner = Learner::builder(runs.path(), "kill-actor").port(port).config(SMOKE).start();
    let mut actors: Vec<Actor> = (0..2).map(|id| Actor::start(port, id, "kill-actor", runs.path())).collect();
    learner.wait_for(Duration::from_secs(120), "both actors training", |s| {
        (0..2).all(|id| u64_at(s, &format!("/actors/{id}/transitions")) > 0) && u64_at(s, "/updates") > 50
    });

    signal(actors[1].child.id(), "KILL");
    let _ = actors[1].child.wait();
    let status = learner.wait_for(Duration::from_secs(30), "the dead actor to leave", |s| {
        s["connected_actors"] == serde_json::json!([0])
    });
    let updates = u64_at(&status, "/updates");
    let transitions = u64_at(&status, "/actors/0/transitions");
    learner.wait_for(Duration::from_secs(60), "training to go on with one actor", |s| {
        u64_at(s, "/updates") > updates + 50 && u64_at(s, "/actors/0/transitions") > transitions
    });

    // The restarted actor asks the weights queryable at once instead of waiting for a publish:
    // it acts on weights at least as new as those published before it started. How long that
    // takes is the join bench's to measure (benches/join.rs), not a test's.
    let published = u64_at(&learner.status().unwrap(), "/weights_version");
    let restarted = Actor::start(port, 1, "kill-actor", runs.path());
    actors[1] = restarted;
    let line = actors[1].wait_for_log(Duration::from_secs(30), "first weights");
    let after_ms = log_field(&line, "after_ms").unwrap();
    let version = log_field(&line, "version").unwrap();
    eprintln!("restarted actor: first weights v{version} {after_ms} ms after joining (v{published} was published)");
    assert!(version >= published, "the restart got v{version}, older than the published v{published}");
    learner.wait_for(Duration::from_secs(30), "the restarted actor back in training", |s| {
        s["connected_actors"] == serde_json::json!([0, 1]) && u64_at(s, "/actors/1/transitions") > 0
    });
    assert!(actors[0].is_running());
}

#[test]
fn a_learner_killed_with_sigkill_resumes_the_run_and_running_actors_reconnect() {
    let runs = tempfile::tempdir().unwrap();
    let port = free_port();
    // No replay snapshot in periodic checkpoints: the resumed learner refills replay.
    let settings = ["--set", "learner.checkpoint_every=100", "--set", "rate.warmup=2000"];
    // Each save pauses before its rename: killed there, the learner has published 20 versions
    // past the checkpoint it will resume from, so the actors hold newer numbers than it.
    let pause = [("FAILPOINTS", "checkpoint-before-rename=sleep(400)")];
    let mut learner =
        Learner::builder(runs.path(), "kill-learner").port(port).config(SMOKE).args(&settings).env(&pause).start();
    let mut actors: Vec<Actor> = (0..2).map(|id| Actor::start(port, id, "kill-learner", runs.path())).collect();
    let checkpoints = runs.path().join("kill-learner/checkpoints");
    learner.wait_for(Duration::from_secs(120), "a few checkpoints", |s| u64_at(s, "/updates") >= 350);
    let start = Instant::now();
    while !std::fs::read_dir(&checkpoints)
        .unwrap()
        .flatten()
        .any(|e| e.file_name().to_string_lossy().contains(".partial-"))
    {
        assert!(start.elapsed() < Duration::from_secs(60), "no checkpoint write to interrupt");
        std::thread::sleep(Duration::from_millis(10));
    }
    signal(learner.child.id(), "KILL");
    let _ = learner.child.wait();
    let saved = checkpoint::load(&checkpoints).unwrap();
    assert!(saved.meta.progress.updates >= 300, "{:?}", saved.meta.progress);
    assert!(crate::replay_of(&saved).unwrap().is_none(), "periodic checkpoints hold no replay");
    let actor_steps: Vec<u64> = actors.iter().map(|a| last_status_steps(&a.log_text())).collect();

    // The actors outlive the learner and keep simulating.
    std::thread::sleep(Duration::from_secs(1));
    assert!(actors.iter_mut().all(Actor::is_running), "actors exited when the learner died");

    // The killed learner's last status.json must not pass for the new one's.
    std::fs::remove_file(runs.path().join("kill-learner/status.json")).unwrap();
    let restarted = Instant::now();
    // Resumed with other publishing settings, which the old version skip (computed from the
    // config) got wrong: versions are ordered by (learner session, version) now, so this
    // learner's publishes are newer than anything the killed one sent, whatever number they
    // carry. With weights_every 1 000 its numbers stay below the actors' for a while.
    let overrides = ["--set", "learner.weights_every=1000", "--set", "learner.checkpoint_every=1000"];
    let mut resumed = Learner::builder(runs.path(), "kill-learner").port(port).resume().args(&overrides).start();
    let status = resumed.wait_for(Duration::from_secs(60), "both actors reconnected and sending", |s| {
        s["connected_actors"] == serde_json::json!([0, 1])
            && (0..2).all(|id| u64_at(s, &format!("/actors/{id}/transitions")) > 0)
    });
    let reconnect = restarted.elapsed();
    eprintln!("actors reconnected and sending {:.1} s after the learner restarted", reconnect.as_secs_f64());

    // Counters continue from the checkpoint. The killed learner had published past the
    // checkpoint's version; the resumed one's only publish carries a lower number, and the
    // surviving actors take it.
    let progress = &saved.meta.progress;
    assert!(u64_at(&status, "/updates") >= progress.updates);
    assert!(u64_at(&status, "/env_steps") >= progress.env_steps);
    let resumed_version = progress.weights_version + 1;
    assert!(u64_at(&status, "/weights_version") >= resumed_version, "{status:#}");
    let held: Vec<u64> = actors.iter().map(|a| last_status_weights(&a.log_text())).collect();
    for (id, held) in held.iter().enumerate() {
        assert!(*held > resumed_version, "actor {id} held v{held}, not newer than v{resumed_version}");
    }
    let followed =
        resumed.wait_for(Duration::from_secs(60), "the surviving actors on the resumed learner's weights", |s| {
            (0..2).all(|id| {
                let version = u64_at(s, &format!("/actors/{id}/weights_version"));
                (resumed_version..held[id]).contains(&version) && version <= u64_at(s, "/weights_version")
            })
        });
    eprintln!("actors held {held:?}; they took the resumed learner's lower-numbered weights: {}", followed["actors"]);
    let trained = resumed.wait_for(Duration::from_secs(60), "training after the warm-up", |s| {
        u64_at(s, "/updates") > progress.updates + 20
    });
    let new_updates = u64_at(&trained, "/updates") - progress.updates;
    let new_inserts = u64_at(&trained, "/replay_len");
    assert!(new_inserts >= 2000, "updates started before the warm-up refilled: replay {new_inserts}");
    // samples_per_insert 4, batch 32, error buffer 128: updates ≤ (4·(inserted − warm-up) + 128)/32,
    // with a little slack for the transitions still pending their successor.
    let allowed = (4 * (new_inserts + 8 - 2000) + 128) / 32 + 1;
    assert!(new_updates <= allowed, "a burst of {new_updates} updates for {new_inserts} inserts (allowed {allowed})");

    // The same actor processes carried on: their step counters never went back.
    for (actor, before) in actors.iter_mut().zip(actor_steps) {
        assert!(actor.is_running());
        let now = last_status_steps(&actor.log_text());
        assert!(now > before, "actor steps {before} → {now}");
    }
    let exit = resumed.terminate(Duration::from_secs(60));
    assert!(exit.success());
    for actor in &mut actors {
        let _ = actor.child.wait();
    }
}

/// The weights version of an actor's newest status log line before any line of the resumed
/// learner's weights (the first status line whose version went down marks the switch).
fn last_status_weights(log: &str) -> u64 {
    let versions: Vec<u64> =
        log.lines().filter(|l| l.contains("actor status")).filter_map(|l| log_field(l, "weights")).collect();
    let switch = versions.windows(2).position(|w| w[1] < w[0]).map_or(versions.len(), |i| i + 1);
    versions[..switch].last().copied().unwrap_or(0)
}

/// The step count of an actor's newest status log line.
fn last_status_steps(log: &str) -> u64 {
    log.lines().rev().find(|l| l.contains("actor status")).and_then(|l| log_field(l, "steps")).unwrap_or(0)
}

#[test]
fn bad_input_is_refused_counted_and_kept_out_of_replay_while_training_goes_on() {
    let runs = tempfile::tempdir().unwrap();
    let port = free_port();
    let mut learner = Learner::builder(runs.path(), "garbage").port(port).config(SMOKE).actors(2).start();
    learner.wait_for(Duration::from_secs(120), "training", |s| u64_at(s, "/updates") > 50);

    let output = Command::new(binary("garbage"))
        .args(["--connect", &format!("tcp/127.0.0.1:{port}"), "--run", "garbage", "--id", "77", "--rounds", "5"])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let sent: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(sent["nan"], 5, "{sent}");

    // Every kind is counted under its reason.
    let expected = ["decode", "version", "run_id", "obs_dim", "non_finite", "action", "batch_size", "oversize"];
    let total = |s: &serde_json::Value| -> u64 {
        s["rejected"].as_object().map_or(0, |r| r.values().filter_map(serde_json::Value::as_u64).sum())
    };
    let status = learner.wait_for(Duration::from_secs(60), "all 65 bad messages counted", |s| total(s) >= 5 * 13);
    assert!(expected.iter().all(|kind| u64_at(&status, &format!("/rejected/{kind}")) > 0), "{status:#}");
    let rejected = &status["rejected"];
    // NaN and ∞ → non_finite, 2 a round; random and cut bytes fail to decode (or decode to
    // an empty message: wrong version) or miss their count.
    assert_eq!(u64_at(rejected, "/non_finite"), 10, "{rejected}");
    assert!(u64_at(rejected, "/version") >= 5, "{rejected}");
    // The 5 played-back batches are refused as replayed, or, when actor 77's insert credit
    // has run out by then, as over credit first: both keep them out, and which comes first
    // is a matter of timing.
    let played_back = u64_at(rejected, "/replayed") + u64_at(rejected, "/over_credit");
    assert_eq!(played_back, 5, "{rejected}");
    assert_eq!(total(&status), 5 * 13, "every bad message is counted once: {rejected}");
    // Only the one valid batch of actor 77 was accepted.
    assert_eq!(u64_at(&status, "/actors/77/transitions"), 8, "{status:#}");

    // Training went on, and the replay holds only finite, valid transitions.
    let updates = u64_at(&status, "/updates");
    learner.wait_for(Duration::from_secs(60), "more updates", |s| u64_at(s, "/updates") > updates + 50);
    assert!(learner.terminate(Duration::from_secs(60)).success());
    let saved = checkpoint::load(&runs.path().join("garbage/checkpoints")).unwrap();
    let replay = crate::replay_of(&saved).unwrap().unwrap();
    assert!(!replay.is_empty() && replay.all_finite());
}

#[test]
fn a_kill_during_a_checkpoint_write_keeps_the_previous_checkpoint_and_the_run_resumes() {
    let runs = tempfile::tempdir().unwrap();
    let port = free_port();
    let checkpoints = runs.path().join("torn/checkpoints");
    // Every save pauses 1.5 s between writing its files and renaming them into place.
    let pause = [("FAILPOINTS", "checkpoint-before-rename=sleep(1500)")];
    let mut learner = Learner::builder(runs.path(), "torn").port(port).config(SMOKE).actors(2).env(&pause).start();
    let start = Instant::now();
    let partial = loop {
        let entries: Vec<String> = std::fs::read_dir(&checkpoints)
            .map(|d| d.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect())
            .unwrap_or_default();
        let complete = entries.iter().filter(|n| !n.contains(".partial-")).count();
        if complete >= 1
            && let Some(partial) = entries.iter().find(|n| n.contains(".partial-"))
        {
            break partial.clone();
        }
        assert!(start.elapsed() < Duration::from_secs(120), "no checkpoint write to interrupt: {entries:?}");
        std::thread::sleep(Duration::from_millis(20));
    };
    // Kill the learner (its actors are its children: end them too) mid-write.
    let children = crawler_tests::children_of(learner.child.id());
    signal(learner.child.id(), "KILL");
    let _ = learner.child.wait();
    for child in children {
        signal(child, "KILL");
    }
    assert!(checkpoints.join(&partial).exists(), "the interrupted write left its partial directory");

    // The previous checkpoint is intact and is what loads.
    let saved = checkpoint::load(&checkpoints).unwrap();
    assert!(!saved.path.to_string_lossy().contains(".partial-"));
    assert!(saved.online.iter().all(|v| v.is_finite()));

    // The run resumes from it, and the partial directory is cleaned away.
    let mut resumed = Learner::builder(runs.path(), "torn").port(port).resume().actors(2).start();
    resumed.wait_for(Duration::from_secs(120), "training after the resume", |s| {
        u64_at(s, "/updates") > saved.meta.progress.updates
    });
    assert!(resumed.terminate(Duration::from_secs(60)).success());
    assert!(!checkpoints.join(&partial).exists(), "the partial directory was removed");
    let last = checkpoint::load(&checkpoints).unwrap();
    assert!(last.meta.progress.updates > saved.meta.progress.updates);
}
