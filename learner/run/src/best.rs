//! The best checkpoint by greedy evaluation, kept beside the newest ones (as SB3's
//! `EvalCallback` keeps `best_model`).
//!
//! Why: DQN's greedy speed swings between checkpoints, and at fine control rates a policy can
//! collapse within a minute (EXPERIMENTS.md, `transfer-a`: 0.64 m/s at 823 s, stuck at 900 s).
//! The checkpoint to ship is the best one evaluated, not the last. Each periodic checkpoint is
//! copied aside, played for a few greedy episodes with `eval`'s seeds (on the nominal physics,
//! or `eval --perturbed`'s), and becomes `checkpoints/best` when it beats the best so far.
//! `eval runs/<run>/checkpoints/best [--perturbed]` reproduces its numbers (the same seeds).
//! Few nominal episodes can hide a gait that sticks or tumbles from other starts; perturbed
//! ones show it (EXPERIMENTS.md, `transfer-polyak-s1`).
//!
//! Ranking: a checkpoint whose episodes never flip the base and never get stuck beats any that
//! does; among equals, the higher mean speed wins. A fast gait that tumbles is not a gait.

use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tracing::{info, warn};

use crawler_env::Randomization;

use crate::evaluate::{
    EVAL_SEED, EvaluateError, LoadedPolicy, STUCK_SPEED, episode_failed, evaluation_env, greedy_episode, load_policy,
};

/// The directory under `checkpoints/` that holds the best checkpoint.
pub const BEST_DIR: &str = "best";
/// Where a candidate is copied while it is evaluated (never a `step-` name, so checkpoint
/// pruning and `latest` leave it alone).
const CANDIDATE_DIR: &str = ".best-candidate";
/// The replaced best while the new one is renamed into place.
const PREVIOUS_DIR: &str = ".best-previous";
/// The evaluation that made a checkpoint the best, inside its directory.
pub const EVALUATION_FILE: &str = "evaluation.json";

#[derive(Debug, thiserror::Error)]
pub enum BestError {
    #[error("{action} {path}: {source}")]
    Io { action: &'static str, path: PathBuf, source: std::io::Error },
    #[error("evaluating {path}: {source}")]
    Evaluate { path: PathBuf, source: EvaluateError },
    #[error("{path}: {source}")]
    Json { path: PathBuf, source: serde_json::Error },
}

fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> BestError {
    let path = path.to_path_buf();
    move |source| BestError::Io { action, path, source }
}

/// What a greedy evaluation of one checkpoint measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    /// The checkpoint's directory name (`step-…`).
    pub checkpoint: String,
    pub updates: u64,
    pub train_seconds: f64,
    pub episodes: u32,
    pub seconds: f32,
    /// Whether the episodes ran `eval --perturbed`'s physics.
    #[serde(default)]
    pub perturbed: bool,
    /// The perturbations they ran under (absent: nominal physics, or a record older than
    /// this field). `eval --perturbed`'s set has changed (it gained roll pushes: EXPERIMENTS.md,
    /// "Three more levers…"), so a resumed run compares against an old best only if it was
    /// measured under the same set.
    #[serde(default)]
    pub perturbations: Option<Randomization>,
    pub mean_speed: f64,
    pub min_speed: f64,
    pub flips: u32,
    pub stuck_episodes: u32,
    /// Episodes that flipped the base at least once or got stuck (absent in records older
    /// than this field: 0). A tumbling gait flips many times in one episode, so `flips` says
    /// how violently and this how often.
    #[serde(default)]
    pub failed_episodes: u32,
}

impl Evaluation {
    /// Whether no episode flipped the base or got stuck.
    pub fn clean(&self) -> bool {
        self.flips == 0 && self.stuck_episodes == 0
    }

    /// Whether this evaluation ranks above `other` (see the module's ranking).
    pub fn beats(&self, other: &Evaluation) -> bool {
        match (self.clean(), other.clean()) {
            (true, false) => true,
            (false, true) => false,
            _ => self.mean_speed > other.mean_speed,
        }
    }
}

/// How each checkpoint is evaluated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvaluationPlan {
    pub episodes: u32,
    pub seconds: f32,
    /// Run `eval --perturbed`'s physics (`Randomization::EVAL_PERTURBATIONS`) instead of the
    /// nominal one: a gait that survives them is likelier to survive another simulator.
    pub perturbed: bool,
}

impl EvaluationPlan {
    /// How the best-checkpoint thread evaluates checkpoints: `learner.best_*` of `config`.
    pub fn of(config: &crate::config::TrainConfig) -> Self {
        let l = &config.learner;
        Self { episodes: l.best_episodes, seconds: l.best_seconds, perturbed: l.best_perturbed }
    }

    /// The perturbations the plan's episodes run under; `None`: the nominal physics.
    pub fn perturbations(&self) -> Option<Randomization> {
        self.perturbed.then_some(Randomization::EVAL_PERTURBATIONS)
    }

    /// Whether `evaluation` was measured as this plan measures, so the two compare.
    fn measured(&self, evaluation: &Evaluation) -> bool {
        (evaluation.episodes, evaluation.seconds, evaluation.perturbed) == (self.episodes, self.seconds, self.perturbed)
            && evaluation.perturbations == self.perturbations()
    }
}

/// Greedy episodes of the checkpoint at `path` with `eval`'s seeds, as `plan` says.
pub fn evaluate_checkpoint(path: &Path, plan: EvaluationPlan) -> Result<Evaluation, EvaluateError> {
    evaluate_policy(&load_policy(path, &[])?, plan)
}

/// Greedy episodes of a loaded checkpoint with `eval`'s seeds, as `plan` says: for several
/// plans played on one checkpoint, read once.
pub fn evaluate_policy(loaded: &LoadedPolicy, plan: EvaluationPlan) -> Result<Evaluation, EvaluateError> {
    let EvaluationPlan { episodes, seconds, perturbed } = plan;
    let mut env = evaluation_env(&loaded.config.env, seconds)?;
    let perturbations = plan.perturbations();
    if let Some(perturbations) = &perturbations {
        env.randomization = perturbations.clone();
    }
    let mut speeds = Vec::with_capacity(episodes as usize);
    let (mut flips, mut stuck_episodes, mut failed_episodes) = (0, 0, 0);
    for i in 0..u64::from(episodes) {
        let (summary, _) = greedy_episode(&loaded.policy, &env, EVAL_SEED + i, false)?;
        speeds.push(f64::from(summary.speed));
        flips += summary.flips;
        stuck_episodes += u32::from(summary.speed < STUCK_SPEED);
        failed_episodes += u32::from(episode_failed(summary.speed, summary.flips));
    }
    let name = loaded.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    Ok(Evaluation {
        checkpoint: name,
        updates: loaded.meta.progress.updates,
        train_seconds: loaded.meta.progress.train_seconds,
        episodes,
        seconds,
        perturbed,
        perturbations,
        mean_speed: speeds.iter().sum::<f64>() / speeds.len().max(1) as f64,
        min_speed: speeds.iter().copied().fold(f64::INFINITY, f64::min),
        flips,
        stuck_episodes,
        failed_episodes,
    })
}

/// Keeps `checkpoints/best`: the best of the checkpoints it is shown.
#[derive(Debug)]
pub struct BestKeeper {
    checkpoints: PathBuf,
    plan: EvaluationPlan,
    best: Option<Evaluation>,
}

impl BestKeeper {
    /// A keeper for the run whose checkpoints live in `checkpoints`. A best checkpoint already
    /// there (a resumed run) is the one to beat.
    /// A best evaluated with another plan, or under another set of perturbations, is not
    /// comparable: it is replaced by the first candidate.
    /// A crash between `consider`'s two renames leaves the old best only as its copy
    /// `.best-previous`; that copy is put back as `checkpoints/best` here, so a restart finds
    /// the best it had rather than none.
    pub fn new(checkpoints: &Path, plan: EvaluationPlan) -> Self {
        let best_dir = checkpoints.join(BEST_DIR);
        let previous = checkpoints.join(PREVIOUS_DIR);
        if !best_dir.exists() && previous.exists() {
            match fs::rename(&previous, &best_dir) {
                Ok(()) => {
                    info!(best = %best_dir.display(), "restored the best checkpoint an interrupted swap left aside")
                }
                Err(e) => warn!(
                    "could not restore {} as {}: {e}; the run keeps a new best from its next checkpoint",
                    previous.display(),
                    best_dir.display()
                ),
            }
        }
        let record = best_dir.join(EVALUATION_FILE);
        let best = fs::read(&record)
            .ok()
            .and_then(|bytes| serde_json::from_slice::<Evaluation>(&bytes).ok())
            .filter(|e| plan.measured(e));
        Self { checkpoints: checkpoints.to_path_buf(), plan, best }
    }

    pub fn best(&self) -> Option<&Evaluation> {
        self.best.as_ref()
    }

    /// Copies the checkpoint at `path` aside (it may be pruned meanwhile), evaluates the copy
    /// and, if it beats the best so far, makes it `checkpoints/best`. Returns its evaluation
    /// and whether it became the best.
    pub fn consider(&mut self, path: &Path) -> Result<(Evaluation, bool), BestError> {
        let candidate = self.checkpoints.join(CANDIDATE_DIR);
        copy_checkpoint(path, &candidate)?;
        let mut evaluation = evaluate_checkpoint(&candidate, self.plan)
            .map_err(|source| BestError::Evaluate { path: path.to_path_buf(), source })?;
        if let Some(name) = path.file_name() {
            evaluation.checkpoint = name.to_string_lossy().into_owned();
        }
        let better = self.best.as_ref().is_none_or(|best| evaluation.beats(best));
        if better {
            let record = candidate.join(EVALUATION_FILE);
            let json = serde_json::to_vec_pretty(&evaluation)
                .map_err(|source| BestError::Json { path: record.clone(), source })?;
            fs::write(&record, json).map_err(io("write", &record))?;
            // The old best is moved aside, not deleted, until the new one is in place: a crash
            // in between leaves a best (or its copy, which `new` puts back) on disk, never none.
            let best = self.checkpoints.join(BEST_DIR);
            let previous = self.checkpoints.join(PREVIOUS_DIR);
            if previous.exists() {
                fs::remove_dir_all(&previous).map_err(io("remove", &previous))?;
            }
            if best.exists() {
                fs::rename(&best, &previous).map_err(io("rename", &best))?;
            }
            fs::rename(&candidate, &best).map_err(io("rename", &candidate))?;
            if previous.exists() {
                fs::remove_dir_all(&previous).map_err(io("remove", &previous))?;
            }
            self.best = Some(evaluation.clone());
        } else {
            fs::remove_dir_all(&candidate).map_err(io("remove", &candidate))?;
        }
        Ok((evaluation, better))
    }
}

/// Copies the files of checkpoint directory `from` into a fresh `to`.
fn copy_checkpoint(from: &Path, to: &Path) -> Result<(), BestError> {
    if to.exists() {
        fs::remove_dir_all(to).map_err(io("remove", to))?;
    }
    fs::create_dir_all(to).map_err(io("create", to))?;
    for entry in fs::read_dir(from).map_err(io("read", from))? {
        let entry = entry.map_err(io("read", from))?;
        if entry.file_type().map_err(io("read", from))?.is_file() {
            let target = to.join(entry.file_name());
            fs::copy(entry.path(), &target).map_err(io("copy", &entry.path()))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn evaluation(mean_speed: f64, flips: u32, stuck_episodes: u32) -> Evaluation {
        Evaluation {
            checkpoint: "step-000000000001".into(),
            updates: 1,
            train_seconds: 1.0,
            episodes: 5,
            seconds: 20.0,
            perturbed: false,
            perturbations: None,
            mean_speed,
            min_speed: 0.0,
            flips,
            stuck_episodes,
            failed_episodes: flips.max(stuck_episodes).min(5),
        }
    }

    #[test]
    fn a_clean_checkpoint_beats_a_faster_one_that_flips_or_sticks() {
        let clean = evaluation(0.4, 0, 0);
        assert!(clean.beats(&evaluation(0.9, 3, 0)));
        assert!(clean.beats(&evaluation(0.9, 0, 1)));
        assert!(!evaluation(0.9, 3, 0).beats(&clean));
        // Among equals the faster wins; a tie keeps the earlier best.
        assert!(evaluation(0.5, 0, 0).beats(&clean));
        assert!(!evaluation(0.3, 0, 0).beats(&clean));
        assert!(!evaluation(0.4, 0, 0).beats(&clean));
        assert!(evaluation(0.2, 1, 0).beats(&evaluation(0.1, 0, 2)));
    }

    #[test]
    fn a_best_left_aside_by_an_interrupted_swap_is_restored() {
        let checkpoints = tempfile::tempdir().unwrap();
        let plan = EvaluationPlan { episodes: 5, seconds: 20.0, perturbed: true };
        let recorded = Evaluation { perturbed: true, perturbations: plan.perturbations(), ..evaluation(0.5, 0, 0) };
        // The state after `best` was renamed aside and before the candidate took its place.
        let previous = checkpoints.path().join(PREVIOUS_DIR);
        fs::create_dir_all(&previous).unwrap();
        fs::write(previous.join(EVALUATION_FILE), serde_json::to_vec(&recorded).unwrap()).unwrap();
        let keeper = BestKeeper::new(checkpoints.path(), plan);
        assert_eq!(keeper.best(), Some(&recorded));
        assert!(checkpoints.path().join(BEST_DIR).join(EVALUATION_FILE).is_file());
        assert!(!previous.exists());
        // With a best in place, a leftover copy is not swapped in over it.
        fs::create_dir_all(&previous).unwrap();
        let older = Evaluation { mean_speed: 0.1, ..recorded.clone() };
        fs::write(previous.join(EVALUATION_FILE), serde_json::to_vec(&older).unwrap()).unwrap();
        assert_eq!(BestKeeper::new(checkpoints.path(), plan).best(), Some(&recorded));
    }

    #[test]
    fn a_resumed_run_keeps_an_old_best_only_if_it_was_measured_the_same_way() {
        let checkpoints = tempfile::tempdir().unwrap();
        let best = checkpoints.path().join(BEST_DIR);
        fs::create_dir_all(&best).unwrap();
        let plan = EvaluationPlan { episodes: 5, seconds: 20.0, perturbed: true };
        let kept_with = |recorded: &Evaluation| {
            fs::write(best.join(EVALUATION_FILE), serde_json::to_vec(recorded).unwrap()).unwrap();
            BestKeeper::new(checkpoints.path(), plan).best().cloned()
        };
        let same = Evaluation { perturbed: true, perturbations: plan.perturbations(), ..evaluation(0.5, 0, 0) };
        assert_eq!(kept_with(&same), Some(same.clone()));
        // Measured before eval --perturbed pushed: the record has no perturbation set.
        let older = Evaluation { perturbations: None, ..same.clone() };
        assert_eq!(kept_with(&older), None, "a best measured under other perturbations is not comparable");
        let other_set = Randomization { push_roll_rate: 0.0, ..Randomization::EVAL_PERTURBATIONS };
        assert_eq!(kept_with(&Evaluation { perturbations: Some(other_set), ..same.clone() }), None);
        assert_eq!(kept_with(&Evaluation { episodes: 10, ..same }), None, "nor one of another episode count");
        // A record written before the field existed still parses (as no perturbation set).
        let mut legacy = serde_json::to_value(&older).unwrap();
        legacy.as_object_mut().unwrap().remove("perturbations");
        let parsed: Evaluation = serde_json::from_value(legacy).unwrap();
        assert_eq!(parsed, older);
    }
}
