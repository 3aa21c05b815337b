//! Checkpoints: round trip, atomicity, retention and corruption.

#![allow(clippy::unwrap_used)] // Tests: a panic is a failure with a message.

use std::fs;

use crawler_env::policy::NetworkSpec;
use crawler_learner::algo::dqn::{Batch, Dqn, DqnConfig};
use crawler_learner::checkpoint::{self, CheckpointError, Progress, ReplayExpectation};
use crawler_learner::replay::{Replay, ReplayConfig, SampledBatch, SnapshotBounds, StreamId, Transition};
use rand::SeedableRng;
use tch::{Kind, Tensor};

fn network() -> NetworkSpec {
    NetworkSpec { obs_dim: 40, hidden: vec![64, 32], num_actions: 25, layer_norm: true }
}

fn config(seed: u64) -> DqnConfig {
    DqnConfig { seed, ..DqnConfig::default() }
}

fn trained(seed: u64) -> Dqn {
    let mut dqn = Dqn::new(network(), config(seed));
    for _ in 0..3 {
        let batch = Batch {
            observations: Tensor::randn([16, 40], (Kind::Float, tch::Device::Cpu)),
            actions: Tensor::randint(25, [16], (Kind::Int64, tch::Device::Cpu)),
            returns: Tensor::ones([16], (Kind::Float, tch::Device::Cpu)),
            next_observations: Tensor::randn([16, 40], (Kind::Float, tch::Device::Cpu)),
            discounts: Tensor::full([16], 0.99, (Kind::Float, tch::Device::Cpu)),
            weights: None,
        };
        dqn.update(&batch);
    }
    dqn
}

fn progress(updates: u64) -> Progress {
    Progress { updates, env_steps: 10 * updates, weights_version: updates / 2, epsilon: 0.25, ..Progress::default() }
}

/// What ingest lets into a replay of 40-value observations: values within ±1000, rewards
/// within ±100, 25 actions.
fn bounds() -> SnapshotBounds {
    SnapshotBounds { observation_range: vec![[-1e3, 1e3]; 40], max_abs_reward: 100.0, num_actions: 25 }
}

fn load_replay(loaded: &checkpoint::Checkpoint, config: &ReplayConfig) -> Result<Option<Replay>, CheckpointError> {
    checkpoint::load_replay(loaded, &ReplayExpectation { config, obs_dim: 40, bounds: &bounds() })
}

fn bits(t: &Tensor) -> Vec<u32> {
    Vec::<f32>::try_from(t.flatten(0, -1)).unwrap().into_iter().map(f32::to_bits).collect()
}

#[test]
fn a_round_trip_gives_bit_identical_q_values_and_state() {
    let dir = tempfile::tempdir().unwrap();
    let dqn = trained(1);
    let run_config = serde_json::json!({ "lr": 5e-4 });
    let path = checkpoint::save(dir.path(), &dqn, "run-a", &progress(3), &run_config, None, 3).unwrap();
    assert!(path.ends_with("step-000000000003"));

    let loaded = checkpoint::load(dir.path()).unwrap();
    assert_eq!(loaded.meta.run_id, "run-a");
    assert_eq!(loaded.meta.progress, progress(3));
    assert_eq!(loaded.meta.config, run_config);
    let mut restored = Dqn::new(network(), config(99));
    restored.restore(&loaded).unwrap();

    let inputs = Tensor::randn([8, 40], (Kind::Float, tch::Device::Cpu));
    assert_eq!(bits(&dqn.q_values(&inputs)), bits(&restored.q_values(&inputs)));
    assert_eq!(bits(&dqn.target.flat().detach()), bits(&restored.target.flat().detach()));
    assert_eq!(dqn.optimizer.exp_avg_sq, restored.optimizer.exp_avg_sq);
    assert_eq!(dqn.optimizer.exp_avg, restored.optimizer.exp_avg);
    assert_eq!((restored.optimizer.step, restored.updates), (3, 3));

    // The weights load into a PyTorch-style name table as well.
    let weights = fs::read(path.join("weights.safetensors")).unwrap();
    let tensors = safetensors::SafeTensors::deserialize(&weights).unwrap();
    let mut names: Vec<String> = tensors.names().into_iter().map(str::to_string).collect();
    names.sort();
    assert_eq!(
        names,
        ["0.bias", "0.weight", "1.bias", "1.weight", "3.bias", "3.weight", "4.bias", "4.weight", "6.bias", "6.weight"]
    );
}

#[test]
fn corrupt_or_truncated_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let path =
        checkpoint::save(dir.path(), &trained(2), "run", &progress(1), &serde_json::Value::Null, None, 3).unwrap();
    let weights = path.join("weights.safetensors");
    let original = fs::read(&weights).unwrap();

    let mut flipped = original.clone();
    let middle = flipped.len() / 2;
    flipped[middle] ^= 0x40;
    fs::write(&weights, &flipped).unwrap();
    let err = checkpoint::load(&path).unwrap_err();
    assert!(matches!(err, CheckpointError::Corrupt { .. }));
    let message = err.to_string();
    assert!(message.contains("weights.safetensors") && message.contains("CRC-32"), "{message}");

    fs::write(&weights, &original[..original.len() - 10]).unwrap();
    let message = checkpoint::load(&path).unwrap_err().to_string();
    assert!(message.contains("weights.safetensors") && message.contains("truncated"), "{message}");

    fs::write(&weights, &original).unwrap();
    assert!(checkpoint::load(&path).is_ok());
    fs::write(path.join("meta.json"), b"{ not json").unwrap();
    let message = checkpoint::load(&path).unwrap_err().to_string();
    assert!(message.contains("meta.json"), "{message}");
}

#[test]
fn a_checkpoint_of_another_network_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    checkpoint::save(dir.path(), &trained(3), "run", &progress(1), &serde_json::Value::Null, None, 3).unwrap();
    let loaded = checkpoint::load(dir.path()).unwrap();
    let other = NetworkSpec { hidden: vec![64, 16], ..network() };
    let err = Dqn::new(other, config(0)).restore(&loaded).unwrap_err().to_string();
    assert!(err.contains("network") && err.contains("16"), "{err}");
}

#[test]
fn only_the_newest_are_kept_and_partial_writes_are_ignored() {
    let dir = tempfile::tempdir().unwrap();
    let dqn = trained(4);
    for updates in 1..=5 {
        checkpoint::save(dir.path(), &dqn, "run", &progress(updates), &serde_json::Value::Null, None, 2).unwrap();
    }
    let names: Vec<String> = checkpoint::list(dir.path())
        .unwrap()
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["step-000000000004", "step-000000000005"]);
    // A crash mid-write leaves a partial directory: it is never taken for a checkpoint.
    let partial = dir.path().join("step-000000000009.partial-1");
    fs::create_dir(&partial).unwrap();
    fs::write(partial.join("weights.safetensors"), b"half").unwrap();
    assert!(checkpoint::latest(dir.path()).unwrap().ends_with("step-000000000005"));
    assert_eq!(checkpoint::load(dir.path()).unwrap().meta.progress.updates, 5);
    // The next save clears it away.
    checkpoint::save(dir.path(), &dqn, "run", &progress(6), &serde_json::Value::Null, None, 2).unwrap();
    assert!(!partial.exists());
    let empty = tempfile::tempdir().unwrap();
    assert!(matches!(checkpoint::load(empty.path()), Err(CheckpointError::NotFound(_))));
}

#[test]
fn a_reader_of_a_live_learners_directory_gets_the_newest_checkpoint_while_older_ones_are_pruned() {
    // `eval runs/<run>/checkpoints` beside a learner that saves and prunes (keep 1 here, the
    // harshest setting): the checkpoint listed as newest is often removed mid-read. Every
    // read must still load a whole checkpoint, never fail on a file pruned under it.
    let dir = tempfile::tempdir().unwrap();
    let dqn = trained(5);
    checkpoint::save(dir.path(), &dqn, "run", &progress(1), &serde_json::Value::Null, None, 1).unwrap();
    let saves = 120;
    let saving = std::sync::atomic::AtomicBool::new(true);
    let (loads, newest_seen) = std::thread::scope(|scope| {
        let reader = scope.spawn(|| {
            let (mut loads, mut newest_seen) = (0_u64, 0_u64);
            while saving.load(std::sync::atomic::Ordering::Relaxed) || loads == 0 {
                let loaded = checkpoint::load(dir.path()).unwrap_or_else(|e| panic!("load {loads}: {e}"));
                assert!(loaded.meta.progress.updates >= newest_seen, "went back in time");
                newest_seen = loaded.meta.progress.updates;
                loads += 1;
            }
            (loads, newest_seen)
        });
        for updates in 2..=saves {
            checkpoint::save(dir.path(), &dqn, "run", &progress(updates), &serde_json::Value::Null, None, 1).unwrap();
        }
        saving.store(false, std::sync::atomic::Ordering::Relaxed);
        reader.join().unwrap()
    });
    assert!(loads >= 1 && newest_seen >= 1, "{loads} loads, newest {newest_seen}");
    assert_eq!(checkpoint::list(dir.path()).unwrap().len(), 1);
}

#[test]
fn the_replay_snapshot_round_trips() {
    let mut replay = Replay::new(ReplayConfig { capacity: 64, n_step: 3, prioritized: None }, 40).unwrap();
    for t in 0..100 {
        let obs = vec![t as f32; 40];
        let next = vec![t as f32 + 1.0; 40];
        let transition = Transition {
            observation: &obs,
            action: (t % 25) as u8,
            reward: t as f32,
            next_observation: &next,
            terminated: t % 30 == 29,
            truncated: false,
        };
        replay.insert(StreamId { actor: 0, env: 0 }, &transition).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    checkpoint::save(dir.path(), &trained(5), "run", &progress(1), &serde_json::Value::Null, Some(&replay), 1).unwrap();
    let loaded = checkpoint::load(dir.path()).unwrap();
    let restored = load_replay(&loaded, &replay.config()).unwrap().unwrap();
    assert_eq!(restored.len(), replay.len());
    let draw = |r: &Replay| {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let mut out = SampledBatch::default();
        r.sample(32, 0.9, 0.0, &mut rng, &mut out).unwrap();
        (out.observations, out.returns, out.discounts, out.next_observations)
    };
    assert_eq!(draw(&restored), draw(&replay));
    // A snapshot cut short is detected.
    let snapshot = loaded.path.join("replay.bin");
    let bytes = fs::read(&snapshot).unwrap();
    fs::write(&snapshot, &bytes[..bytes.len() / 2]).unwrap();
    let message = load_replay(&loaded, &replay.config()).unwrap_err().to_string();
    assert!(message.contains("replay.bin"), "{message}");
}

fn batch_with(value: f64) -> Batch {
    Batch {
        observations: Tensor::full([16, 40], value, (Kind::Float, tch::Device::Cpu)),
        actions: Tensor::zeros([16], (Kind::Int64, tch::Device::Cpu)),
        returns: Tensor::full([16], value, (Kind::Float, tch::Device::Cpu)),
        next_observations: Tensor::full([16, 40], value, (Kind::Float, tch::Device::Cpu)),
        discounts: Tensor::full([16], 0.99, (Kind::Float, tch::Device::Cpu)),
        weights: None,
    }
}

#[test]
fn a_non_finite_update_is_skipped_and_leaves_every_weight_as_it_was() {
    let mut dqn = trained(4);
    let (online, target, step) = (bits(dqn.online.flat()), bits(dqn.target.flat()), dqn.optimizer.step);
    // Finite inputs near f32::MAX overflow the loss: the update must not happen.
    for value in [3e38, f64::NAN, f64::INFINITY] {
        let stats = dqn.update(&batch_with(value));
        assert!(!stats.applied, "an update with inputs {value} was applied: {stats:?}");
    }
    assert_eq!(bits(dqn.online.flat()), online);
    assert_eq!(bits(dqn.target.flat()), target);
    assert_eq!(dqn.optimizer.step, step);
    assert!(dqn.online.all_finite());
    // A sane batch still trains.
    assert!(dqn.update(&batch_with(0.5)).applied);
    assert_ne!(bits(dqn.online.flat()), online);
}

#[test]
fn non_finite_weights_are_never_saved_and_older_checkpoints_stay() {
    let dir = tempfile::tempdir().unwrap();
    let mut dqn = trained(5);
    let config = serde_json::json!({});
    checkpoint::save(dir.path(), &dqn, "run-n", &progress(1), &config, None, 1).unwrap();
    let _ = dqn.online.flat_mut().get(0).fill_(f64::NAN);
    let error = checkpoint::save(dir.path(), &dqn, "run-n", &progress(2), &config, None, 1).unwrap_err();
    assert!(matches!(error, CheckpointError::NonFinite(_, "online")), "{error}");
    // keep = 1, yet the good checkpoint was not pruned for the refused one.
    let kept = checkpoint::list(dir.path()).unwrap();
    assert_eq!(kept.len(), 1);
    assert_eq!(checkpoint::load(dir.path()).unwrap().meta.progress.updates, 1);
}

#[test]
fn a_meta_json_declaring_an_enormous_network_is_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let path =
        checkpoint::save(dir.path(), &trained(6), "run-h", &progress(1), &serde_json::json!({}), None, 1).unwrap();
    let meta_path = path.join("meta.json");
    let mut meta: serde_json::Value = serde_json::from_slice(&fs::read(&meta_path).unwrap()).unwrap();
    meta["network"]["hidden"] = serde_json::json!(vec![65_536; 1000]);
    fs::write(&meta_path, serde_json::to_vec(&meta).unwrap()).unwrap();
    let error = checkpoint::load(&path).unwrap_err().to_string();
    assert!(error.contains("meta.json") && error.contains("hidden layers"), "{error}");
}

/// A replay snapshot whose file is intact (size and CRC as recorded) but that is not this
/// version's replay layout is told apart from a damaged file, so a resumed run can go on
/// with an empty replay instead of refusing to start.
#[test]
fn an_intact_snapshot_of_another_replay_layout_is_named_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let replay = Replay::new(ReplayConfig { capacity: 8, n_step: 1, prioritized: None }, 40).unwrap();
    let path =
        checkpoint::save(dir.path(), &trained(7), "run", &progress(1), &serde_json::Value::Null, Some(&replay), 1)
            .unwrap();
    // Rewrite replay.bin with bytes of no replay layout, and record their size and CRC.
    let foreign = vec![0xFFu8; 64];
    fs::write(path.join("replay.bin"), &foreign).unwrap();
    let meta_path = path.join("meta.json");
    let mut meta: serde_json::Value = serde_json::from_slice(&fs::read(&meta_path).unwrap()).unwrap();
    meta["files"]["replay.bin"] = serde_json::json!({ "bytes": foreign.len(), "crc32": crc32fast::hash(&foreign) });
    fs::write(&meta_path, serde_json::to_vec(&meta).unwrap()).unwrap();
    let loaded = checkpoint::load(&path).unwrap();
    match load_replay(&loaded, &replay.config()) {
        Err(CheckpointError::ReplayLayout { path, .. }) => assert!(path.ends_with("replay.bin"), "{}", path.display()),
        other => panic!("expected a replay-layout error, got {other:?}"),
    }
}

/// Rewrites one field of a checkpoint's `meta.json`.
fn edit_meta(path: &std::path::Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let meta_path = path.join("meta.json");
    let mut meta: serde_json::Value = serde_json::from_slice(&fs::read(&meta_path).unwrap()).unwrap();
    edit(&mut meta);
    fs::write(&meta_path, serde_json::to_vec(&meta).unwrap()).unwrap();
}

#[test]
fn counters_beyond_what_a_run_reaches_are_refused_by_file_and_field() {
    for (field, pointer, value) in [
        ("adam_step", "/adam_step", serde_json::json!(u64::MAX)),
        ("progress.updates", "/progress/updates", serde_json::json!(1u64 << 60)),
        ("progress.weights_version", "/progress/weights_version", serde_json::json!(u64::MAX)),
        ("progress.learner_session", "/progress/learner_session", serde_json::json!(u64::MAX)),
        ("progress.epsilon", "/progress/epsilon", serde_json::json!(-0.5)),
        ("progress.train_seconds", "/progress/train_seconds", serde_json::json!(1e300)),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let path =
            checkpoint::save(dir.path(), &trained(8), "run", &progress(1), &serde_json::json!({}), None, 1).unwrap();
        edit_meta(&path, |meta| *meta.pointer_mut(pointer).unwrap() = value.clone());
        let error = checkpoint::load(&path).unwrap_err().to_string();
        assert!(error.contains("meta.json") && error.contains(field), "{field}: {error}");
    }
}

/// Adam's step past 2³¹ once wrapped its bias correction to zero, and every update after a
/// resume was skipped as non-finite: a step count anywhere in range still trains.
#[test]
fn a_resume_at_a_step_count_past_i32_keeps_training_finite() {
    let dir = tempfile::tempdir().unwrap();
    let path = checkpoint::save(dir.path(), &trained(9), "run", &progress(1), &serde_json::json!({}), None, 1).unwrap();
    for step in [(1u64 << 32) - 1, 1 << 32, checkpoint::MAX_COUNTER] {
        edit_meta(&path, |meta| meta["adam_step"] = serde_json::json!(step));
        let mut dqn = Dqn::new(network(), config(1));
        dqn.restore(&checkpoint::load(&path).unwrap()).unwrap();
        for _ in 0..3 {
            assert!(dqn.update(&batch_with(0.5)).applied, "adam step {step}");
        }
        assert!(dqn.online.all_finite(), "adam step {step}");
    }
}

#[test]
fn files_that_are_devices_or_larger_than_their_network_are_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let path =
        checkpoint::save(dir.path(), &trained(10), "run", &progress(1), &serde_json::json!({}), None, 1).unwrap();
    // An entry far larger than the network's values.
    edit_meta(&path, |meta| meta["files"]["weights.safetensors"]["bytes"] = serde_json::json!(8u64 << 30));
    let error = checkpoint::load(&path).unwrap_err().to_string();
    assert!(error.contains("meta.json") && error.contains("files.weights.safetensors.bytes"), "{error}");
    // A weights file that links to an endless device, its entry left as it was.
    let dir = tempfile::tempdir().unwrap();
    let path =
        checkpoint::save(dir.path(), &trained(10), "run", &progress(1), &serde_json::json!({}), None, 1).unwrap();
    fs::remove_file(path.join("target.safetensors")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", path.join("target.safetensors")).unwrap();
    let started = std::time::Instant::now();
    let error = checkpoint::load(&path).unwrap_err().to_string();
    assert!(error.contains("target.safetensors") && error.contains("not a regular file"), "{error}");
    assert!(started.elapsed() < std::time::Duration::from_secs(5), "read the device before refusing it");
    // A meta.json that is a device.
    fs::remove_file(path.join("meta.json")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", path.join("meta.json")).unwrap();
    let error = checkpoint::load(&path).unwrap_err().to_string();
    assert!(error.contains("meta.json") && error.contains("not a regular file"), "{error}");
}

/// A replay snapshot whose checksum holds but whose records no validated actor could have
/// sent (here an observation of 3e38, written straight into the ring) is refused by record,
/// and a snapshot whose entry claims more bytes than this run's replay takes is not read.
#[test]
fn a_replay_snapshot_is_checked_record_by_record() {
    let config = ReplayConfig { capacity: 16, n_step: 1, prioritized: None };
    let mut replay = Replay::new(config.clone(), 40).unwrap();
    let (obs, next) = (vec![0.5f32; 40], vec![0.25f32; 40]);
    let mut huge = next.clone();
    huge[7] = 3e38;
    for (i, next) in [&next, &huge].into_iter().enumerate() {
        let transition = Transition {
            observation: &obs,
            action: 1,
            reward: 0.5,
            next_observation: next,
            terminated: true,
            truncated: false,
        };
        replay.insert(StreamId { actor: 0, env: i as u32 }, &transition).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let path =
        checkpoint::save(dir.path(), &trained(11), "run", &progress(1), &serde_json::json!({}), Some(&replay), 1)
            .unwrap();
    let loaded = checkpoint::load(&path).unwrap();
    match load_replay(&loaded, &config) {
        Err(CheckpointError::ReplayContent { path, reason }) => {
            assert!(path.ends_with("replay.bin"), "{}", path.display());
            assert!(
                reason.contains("slot 3") && reason.contains("`observation` holds") && reason.contains("at index 7"),
                "{reason}"
            );
        }
        other => panic!("expected the snapshot refused, got {other:?}"),
    }
    // A replay of another size is not this run's: not read, and no error.
    let other = ReplayConfig { capacity: 32, ..config.clone() };
    assert!(load_replay(&loaded, &other).unwrap().is_none());
    // An entry claiming more than a 16-slot replay takes.
    edit_meta(&path, |meta| meta["files"]["replay.bin"]["bytes"] = serde_json::json!(1u64 << 40));
    let loaded = checkpoint::load(&path).unwrap();
    match load_replay(&loaded, &config) {
        Err(CheckpointError::ReplayContent { reason, .. }) => assert!(reason.contains("more than"), "{reason}"),
        other => panic!("expected the oversized snapshot refused, got {other:?}"),
    }
}
