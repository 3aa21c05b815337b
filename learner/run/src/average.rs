//! The weight average of a run's newest checkpoints, kept as `checkpoints/average`.
//!
//! Why: at the transfer preset's annealed learning rate DQN's greedy gait still changes from
//! one checkpoint to the next, and on the study's MuJoCo model checkpoints 5 000 updates apart
//! crawl anywhere from 0.35 to 0.6 m/s, some with flips (EXPERIMENTS.md, "A stiffer floor in the
//! randomisation" and "The committed recipe on three seeds…").
//! Any one checkpoint ships that noise. The mean of the last few checkpoints' weights (as
//! stochastic weight averaging does, and as translation models average their last
//! checkpoints; Nikishin et al. 2018 for RL) lies inside the region they wander in, and its
//! greedy policy crawled at or above their mean speed there, flip-free.
//!
//! The average is a checkpoint like any other (same files, same checks), so `eval`,
//! `render` and `scripts/mujoco-check` play it as they play `step-…` ones. It is never a
//! `step-` name, so pruning, `latest`, `--resume` and `--init-from` leave it alone; its
//! `meta.json` lists the checkpoints it averages (`averaged_from`).

use std::path::{Path, PathBuf};

use crate::checkpoint::{self, Checkpoint, CheckpointError, Snapshot};

/// The directory under `checkpoints/` that holds the average.
pub const AVERAGE_DIR: &str = "average";

#[derive(Debug, thiserror::Error)]
pub enum AverageError {
    #[error("averaging needs at least 2 checkpoints, asked for {0}")]
    TooFewAsked(usize),
    #[error(
        "{dir} holds {found} checkpoint(s), fewer than the {asked} to average; train longer, or keep more \
         (learner.keep_checkpoints ≥ learner.average_checkpoints)"
    )]
    TooFewFound { dir: PathBuf, found: usize, asked: usize },
    #[error("cannot average {path} with {newest}: {what} differs ({found} against {expected})")]
    Mismatch { path: PathBuf, newest: PathBuf, what: &'static str, found: String, expected: String },
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
}

/// Averages the online and target weights of the newest `count` checkpoints in `dir` into
/// `dir/average` (replaced whole) and returns its path. Adam's moments, the progress
/// counters and the config are the newest checkpoint's. Every checkpoint is read with its
/// checksums; all must come from the same run and have the same network.
pub fn average_newest(dir: &Path, count: usize) -> Result<PathBuf, AverageError> {
    if count < 2 {
        return Err(AverageError::TooFewAsked(count));
    }
    let listed = checkpoint::list(dir)?;
    if listed.len() < count {
        return Err(AverageError::TooFewFound { dir: dir.to_path_buf(), found: listed.len(), asked: count });
    }
    let chosen = &listed[listed.len() - count..];
    // The newest first: the others must match it.
    let newest = checkpoint::load(&chosen[count - 1])?;
    let mut online = vec![0.0f64; newest.online.len()];
    let mut target = vec![0.0f64; newest.target.len()];
    let mut names = Vec::with_capacity(count);
    for path in chosen {
        let loaded = if *path == newest.path { None } else { Some(checkpoint::load(path)?) };
        let each = loaded.as_ref().unwrap_or(&newest);
        check_same_run(each, &newest)?;
        accumulate(&mut online, &each.online);
        accumulate(&mut target, &each.target);
        names.push(path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default());
    }
    let mean = |sums: Vec<f64>| -> Vec<f32> { sums.into_iter().map(|sum| (sum / count as f64) as f32).collect() };
    let (online, target) = (mean(online), mean(target));
    let snapshot = Snapshot {
        network: &newest.meta.network,
        online: &online,
        target: &target,
        exp_avg: &newest.exp_avg,
        exp_avg_sq: &newest.exp_avg_sq,
        adam_step: newest.meta.adam_step,
        replay: None,
    };
    let meta = &newest.meta;
    Ok(checkpoint::write_named(dir, AVERAGE_DIR, &snapshot, &meta.run_id, &meta.progress, &meta.config, names)?)
}

/// Adds `values` into `sums` in f64, so that averaging 20 checkpoints loses no f32 precision.
fn accumulate(sums: &mut [f64], values: &[f32]) {
    for (sum, value) in sums.iter_mut().zip(values) {
        *sum += f64::from(*value);
    }
}

/// Weights of different runs or networks do not average into anything meaningful.
fn check_same_run(each: &Checkpoint, newest: &Checkpoint) -> Result<(), AverageError> {
    let mismatch = |what, found: String, expected: String| AverageError::Mismatch {
        path: each.path.clone(),
        newest: newest.path.clone(),
        what,
        found,
        expected,
    };
    if each.meta.run_id != newest.meta.run_id {
        return Err(mismatch("the run", each.meta.run_id.clone(), newest.meta.run_id.clone()));
    }
    if each.meta.network != newest.meta.network {
        return Err(mismatch("the network", format!("{:?}", each.meta.network), format!("{:?}", newest.meta.network)));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crawler_env::policy::NetworkSpec;

    fn spec() -> NetworkSpec {
        NetworkSpec { obs_dim: 40, hidden: vec![4], num_actions: 9, layer_norm: false }
    }

    /// A checkpoint of `run` at `updates` whose every online weight is `online` and every
    /// target weight `online + 1`.
    fn save(dir: &Path, run: &str, spec: &NetworkSpec, updates: u64, online: f32) -> PathBuf {
        let n = spec.num_params();
        let (online, target) = (vec![online; n], vec![online + 1.0; n]);
        let zeros = vec![0.0; n];
        let snapshot = Snapshot {
            network: spec,
            online: &online,
            target: &target,
            exp_avg: &zeros,
            exp_avg_sq: &zeros,
            adam_step: updates,
            replay: None,
        };
        let progress = checkpoint::Progress { updates, ..Default::default() };
        checkpoint::save(dir, &snapshot, run, &progress, &serde_json::json!({}), 100).expect("save")
    }

    #[test]
    fn the_average_is_the_mean_of_the_newest_checkpoints_and_loads_like_any_other() {
        let dir = tempfile::tempdir().expect("tempdir");
        for (updates, weight) in [(100, 50.0), (200, 1.0), (300, 2.0), (400, 6.0)] {
            save(dir.path(), "run", &spec(), updates, weight);
        }
        let path = average_newest(dir.path(), 3).expect("average");
        assert_eq!(path, dir.path().join(AVERAGE_DIR));
        let average = checkpoint::load(&path).expect("the average loads with its checksums");
        assert!(average.online.iter().all(|&w| w == 3.0), "mean of 1, 2, 6 (not the oldest, 50)");
        assert!(average.target.iter().all(|&w| w == 4.0));
        assert_eq!(average.meta.progress.updates, 400, "the newest's counters");
        assert_eq!(average.meta.averaged_from, ["step-000000000200", "step-000000000300", "step-000000000400"]);
        // Not a step- checkpoint: the newest is still the newest, and pruning keeps it.
        assert_eq!(checkpoint::latest(dir.path()).expect("latest"), dir.path().join("step-000000000400"));
        save(dir.path(), "run", &spec(), 500, 0.0);
        assert!(path.join("meta.json").is_file());
        // Averaging again replaces it.
        average_newest(dir.path(), 2).expect("average again");
        let again = checkpoint::load(&path).expect("load");
        assert!(again.online.iter().all(|&w| w == 3.0), "mean of 6 and 0");
    }

    #[test]
    fn too_few_checkpoints_or_mixed_networks_are_refused_by_name() {
        let dir = tempfile::tempdir().expect("tempdir");
        assert!(matches!(average_newest(dir.path(), 1), Err(AverageError::TooFewAsked(1))));
        save(dir.path(), "run", &spec(), 100, 1.0);
        let error = average_newest(dir.path(), 2).expect_err("one checkpoint");
        assert!(matches!(error, AverageError::TooFewFound { found: 1, asked: 2, .. }), "{error}");
        assert!(error.to_string().contains("learner.keep_checkpoints"), "{error}");
        let wider = NetworkSpec { hidden: vec![8], ..spec() };
        save(dir.path(), "run", &wider, 200, 1.0);
        let error = average_newest(dir.path(), 2).expect_err("two networks");
        assert!(matches!(error, AverageError::Mismatch { what: "the network", .. }), "{error}");
        save(dir.path(), "other-run", &wider, 300, 1.0);
        let error = average_newest(dir.path(), 2).expect_err("two runs");
        assert!(matches!(error, AverageError::Mismatch { what: "the run", .. }), "{error}");
        assert!(!dir.path().join(AVERAGE_DIR).exists(), "nothing written");
    }
}
