//! ε schedules.

use serde::{Deserialize, Serialize};

/// The study's schedule: ε starts at `start` and is multiplied by `factor` every `every`
/// steps, never going below `min`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EpsilonDecay {
    pub start: f64,
    pub factor: f64,
    pub every: u64,
    pub min: f64,
}

impl EpsilonDecay {
    /// The study's values: 0.01, × 0.9995 every 100 steps, down to 0.
    pub const STUDY: EpsilonDecay = EpsilonDecay { start: 0.01, factor: 0.9995, every: 100, min: 0.0 };

    /// ε after `steps` steps.
    pub fn at(&self, steps: u64) -> f64 {
        let decays = steps / self.every.max(1);
        let exponent = i32::try_from(decays).unwrap_or(i32::MAX);
        (self.start * self.factor.powi(exponent)).max(self.min)
    }
}

/// Ape-X's per-actor ladder: actor `index` of `count` explores with ε^(1 + α·index/(count−1)).
/// A single actor gets ε itself.
pub fn apex_epsilon(base: f64, alpha: f64, index: usize, count: usize) -> f64 {
    if count <= 1 {
        return base;
    }
    base.powf(1.0 + alpha * index as f64 / (count - 1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn study_decay_multiplies_every_hundred_steps() {
        let decay = EpsilonDecay::STUDY;
        assert_eq!(decay.at(0), 0.01);
        assert_eq!(decay.at(99), 0.01);
        assert!((decay.at(100) - 0.01 * 0.9995).abs() < 1e-15);
        assert!((decay.at(1_000) - 0.01 * 0.9995f64.powi(10)).abs() < 1e-15);
        let floored = EpsilonDecay { min: 0.005, ..decay };
        assert_eq!(floored.at(100_000_000), 0.005);
    }

    #[test]
    fn apex_ladder_spans_base_to_base_to_one_plus_alpha() {
        assert!((apex_epsilon(0.4, 7.0, 0, 8) - 0.4).abs() < 1e-12);
        assert!((apex_epsilon(0.4, 7.0, 7, 8) - 0.4f64.powi(8)).abs() < 1e-12);
        let ladder: Vec<f64> = (0..8).map(|i| apex_epsilon(0.4, 7.0, i, 8)).collect();
        assert!(ladder.windows(2).all(|w| w[0] > w[1]));
        assert_eq!(apex_epsilon(0.4, 7.0, 0, 1), 0.4);
    }
}
