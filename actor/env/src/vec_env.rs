//! K crawlers stepped together, writing into contiguous buffers.

use super::config::EnvConfig;
use super::crawler::{Crawler, EpisodeSummary, Reward};
use super::observation::{OBS_DIM, stack_first, stack_next};

/// K independent crawlers, each seeded on its own, with auto-reset.
///
/// After [`VecEnv::step`], `next_observations()` holds each crawler's observation after the
/// step: for a crawler whose episode just ended, that is the final observation, which belongs
/// in the transition. `observations()` holds what to act on next: the same values, or the first
/// observation of the new episode where one ended. Each crawler's values are the policy's
/// input, `EnvConfig::policy_input_dim`: its last `observation_history` observations, newest
/// first.
#[derive(Debug)]
pub struct VecEnv {
    crawlers: Vec<Crawler>,
    input_dim: usize,
    observations: Vec<f32>,
    next_observations: Vec<f32>,
    rewards: Vec<f32>,
    reward_parts: Vec<Reward>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
    finished: Vec<(usize, EpisodeSummary)>,
}

impl VecEnv {
    /// One crawler per seed. The config must be valid (see [`EnvConfig::validate`]).
    pub fn new(config: &EnvConfig, seeds: &[u64]) -> Self {
        let crawlers: Vec<Crawler> = seeds.iter().map(|&seed| Crawler::new(config.clone(), seed)).collect();
        let k = crawlers.len();
        let input_dim = config.policy_input_dim();
        let mut env = Self {
            crawlers,
            input_dim,
            observations: vec![0.0; k * input_dim],
            next_observations: vec![0.0; k * input_dim],
            rewards: vec![0.0; k],
            reward_parts: vec![Reward::default(); k],
            terminated: vec![false; k],
            truncated: vec![false; k],
            finished: Vec::with_capacity(k),
        };
        for (crawler, out) in env.crawlers.iter().zip(env.observations.chunks_exact_mut(input_dim)) {
            stack_first(&observe(crawler), out);
        }
        env.next_observations.copy_from_slice(&env.observations);
        env
    }

    pub fn len(&self) -> usize {
        self.crawlers.len()
    }

    pub fn is_empty(&self) -> bool {
        self.crawlers.is_empty()
    }

    /// Steps crawler i with `actions[i]`, resetting those whose episode ends. Returns the
    /// episodes that ended, by crawler index.
    ///
    /// # Panics
    /// If `actions.len()` differs from the number of crawlers: that is a caller bug.
    pub fn step(&mut self, actions: &[u32]) -> &[(usize, EpisodeSummary)] {
        assert_eq!(actions.len(), self.crawlers.len(), "one action per crawler");
        self.finished.clear();
        let buffers = self
            .crawlers
            .iter_mut()
            .zip(self.observations.chunks_exact_mut(self.input_dim))
            .zip(self.next_observations.chunks_exact_mut(self.input_dim))
            .enumerate();
        for (i, ((crawler, obs), next_obs)) in buffers {
            let outcome = crawler.step(actions[i]);
            stack_next(obs, &observe(crawler), next_obs);
            self.rewards[i] = outcome.reward.total();
            self.reward_parts[i] = outcome.reward;
            self.terminated[i] = outcome.terminated;
            self.truncated[i] = outcome.truncated;
            if outcome.done() {
                self.finished.push((i, crawler.episode_summary(Some(outcome))));
                crawler.reset();
                stack_first(&observe(crawler), obs);
            } else {
                obs.copy_from_slice(next_obs);
            }
        }
        &self.finished
    }

    /// Values in one crawler's slice of [`Self::observations`]: `EnvConfig::policy_input_dim`.
    pub fn input_dim(&self) -> usize {
        self.input_dim
    }

    /// K policy inputs to act on, crawler-major.
    pub fn observations(&self) -> &[f32] {
        &self.observations
    }

    /// K policy inputs right after the last step (final ones where an episode ended).
    pub fn next_observations(&self) -> &[f32] {
        &self.next_observations
    }

    pub fn rewards(&self) -> &[f32] {
        &self.rewards
    }

    pub fn reward_parts(&self) -> &[Reward] {
        &self.reward_parts
    }

    pub fn terminated(&self) -> &[bool] {
        &self.terminated
    }

    pub fn truncated(&self) -> &[bool] {
        &self.truncated
    }

    pub fn crawler(&self, i: usize) -> &Crawler {
        &self.crawlers[i]
    }

    pub fn crawler_mut(&mut self, i: usize) -> &mut Crawler {
        &mut self.crawlers[i]
    }
}

fn observe(crawler: &Crawler) -> [f32; OBS_DIM] {
    let mut frame = [0.0; OBS_DIM];
    crawler.observe(&mut frame);
    frame
}
