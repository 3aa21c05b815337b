//! How the replay draws transitions: the seam for sampling schemes.
//!
//! The replay's storage (slots, links, n-step returns) is the same for every scheme; a
//! [`Sampler`] owns what a scheme adds (for prioritised replay, the sum tree of priorities)
//! and is told of every transition stored, overwritten and re-scored. It is built from the
//! config once, so the config and the sampling state cannot disagree.

use serde::{Deserialize, Serialize};

use super::PrioritizedConfig;
use super::sum_tree::SumTree;

/// The sampling scheme of a replay and its state.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub enum Sampler {
    /// Every stored transition equally likely (the study).
    Uniform,
    /// Proportional to priority (Schaul et al. 2016), with importance-sampling weights.
    Prioritized(Prioritized),
}

/// Proportional prioritised sampling: priorities (|TD error| + ε)^α in a sum tree.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Prioritized {
    pub(super) config: PrioritizedConfig,
    pub(super) tree: SumTree,
    /// New transitions get the largest priority seen, so each is sampled soon at least once.
    max_priority: f64,
}

impl Sampler {
    /// The scheme `prioritized` asks for, over `capacity` slots.
    pub fn new(prioritized: Option<PrioritizedConfig>, capacity: usize) -> Self {
        match prioritized {
            None => Self::Uniform,
            Some(config) => Self::Prioritized(Prioritized { config, tree: SumTree::new(capacity), max_priority: 1.0 }),
        }
    }

    /// The config this sampler was built from (`replay.prioritized`).
    pub fn prioritized_config(&self) -> Option<PrioritizedConfig> {
        match self {
            Self::Uniform => None,
            Self::Prioritized(p) => Some(p.config),
        }
    }

    /// Whether samples carry importance weights.
    pub fn is_weighted(&self) -> bool {
        matches!(self, Self::Prioritized(_))
    }

    /// A transition now starts at `slot`.
    pub(super) fn stored(&mut self, slot: usize) {
        if let Self::Prioritized(p) = self {
            p.tree.set(slot, p.max_priority);
        }
    }

    /// The transition at `slot` was overwritten.
    pub(super) fn removed(&mut self, slot: usize) {
        if let Self::Prioritized(p) = self {
            p.tree.set(slot, 0.0);
        }
    }

    /// The transition at `slot` was trained on with TD error `td`.
    pub(super) fn rescore(&mut self, slot: usize, td: f32) {
        if let Self::Prioritized(p) = self {
            let td = if td.is_finite() { f64::from(td.abs()) } else { p.max_priority };
            let priority = (td + p.config.epsilon).powf(p.config.alpha);
            p.tree.set(slot, priority);
            p.max_priority = p.max_priority.max(priority);
        }
    }

    /// Checks a sampler read from a file (see [`SumTree::check_snapshot`]).
    pub(super) fn check_snapshot(&mut self, capacity: usize) -> Result<(), String> {
        match self {
            Self::Uniform => Ok(()),
            Self::Prioritized(p) => {
                if !(p.max_priority.is_finite() && p.max_priority > 0.0) {
                    return Err(format!("sampler max_priority {}", p.max_priority));
                }
                p.tree.check_snapshot(capacity)
            }
        }
    }

    pub(super) fn memory_bytes(&self) -> usize {
        match self {
            Self::Uniform => 0,
            Self::Prioritized(p) => p.tree.memory_bytes(),
        }
    }
}
