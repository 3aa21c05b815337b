//! What an actor needs to know about its run. The learner serves it as JSON in
//! [`crawler_proto::RunInfo`], so actors on other machines need no config file.

use serde::{Deserialize, Serialize};

use crate::env::EnvConfig;
use crate::policy::{EpsilonDecay, apex_epsilon};

/// How actors explore.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum Exploration {
    /// Ape-X: actor i of `actors` uses ε = base^(1 + alpha·i/(actors − 1)), fixed.
    Ladder { base: f64, alpha: f64, actors: usize },
    /// The study: ε starts at `start`, × `factor` every `every` decisions, floored at `min`.
    Decay { start: f64, factor: f64, every: u64, min: f64 },
}

impl Default for Exploration {
    fn default() -> Self {
        Exploration::Ladder { base: 0.4, alpha: 7.0, actors: 8 }
    }
}

impl Exploration {
    /// ε of actor `actor` after it took `steps` decisions (per crawler).
    pub fn epsilon(&self, actor: u32, steps: u64) -> f64 {
        match *self {
            Exploration::Ladder { base, alpha, actors } => {
                let index = (actor as usize).min(actors.saturating_sub(1));
                apex_epsilon(base, alpha, index, actors)
            }
            Exploration::Decay { start, factor, every, min } => EpsilonDecay { start, factor, every, min }.at(steps),
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        match *self {
            Exploration::Ladder { base, alpha, actors } => {
                if !(0.0..=1.0).contains(&base) || !alpha.is_finite() || alpha < 0.0 || actors == 0 {
                    return Err(format!(
                        "exploration ladder base = {base}, alpha = {alpha}, actors = {actors}: need base in [0, 1], alpha ≥ 0, actors ≥ 1"
                    ));
                }
            }
            Exploration::Decay { start, factor, every, min } => {
                let ok = (0.0..=1.0).contains(&start)
                    && (0.0..=1.0).contains(&factor)
                    && (0.0..=1.0).contains(&min)
                    && every > 0;
                if !ok {
                    return Err(format!(
                        "exploration decay start = {start}, factor = {factor}, every = {every}, min = {min}: need start, factor, min in [0, 1] and every ≥ 1"
                    ));
                }
            }
        }
        Ok(())
    }
}

/// An actor's settings, fixed for the run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ActorSettings {
    pub env: EnvConfig,
    /// Crawlers each actor steps together.
    pub envs_per_actor: usize,
    /// Transitions per published batch.
    pub batch_transitions: usize,
    pub exploration: Exploration,
    /// Base seed; actor i's crawler k uses seed `seed + 1000·i + k`.
    pub seed: u64,
    /// Seconds between status reports.
    pub status_interval_s: f64,
}

impl Default for ActorSettings {
    fn default() -> Self {
        Self {
            env: EnvConfig::default(),
            envs_per_actor: 8,
            batch_transitions: 256,
            exploration: Exploration::default(),
            seed: 0,
            status_interval_s: 2.0,
        }
    }
}

impl ActorSettings {
    pub fn validate(&self) -> Result<(), String> {
        self.env.validate().map_err(|e| e.to_string())?;
        self.exploration.validate()?;
        if !(1..=1024).contains(&self.envs_per_actor) {
            return Err(format!("actor.envs_per_actor = {} is invalid: an integer in 1..=1024", self.envs_per_actor));
        }
        if !(1..=4096).contains(&self.batch_transitions) {
            return Err(format!(
                "actor.batch_transitions = {} is invalid: an integer in 1..=4096",
                self.batch_transitions
            ));
        }
        if !(self.status_interval_s.is_finite() && self.status_interval_s > 0.0) {
            return Err(format!("actor.status_interval_s = {} is invalid: a positive number", self.status_interval_s));
        }
        Ok(())
    }

    /// Seeds of actor `actor`'s crawlers.
    pub fn seeds(&self, actor: u32) -> Vec<u64> {
        (0..self.envs_per_actor as u64).map(|k| self.seed + 1000 * u64::from(actor) + k).collect()
    }
}
