//! Experience replay: a fixed-capacity ring that stores each observation once.
//!
//! Each slot holds one observation and, where one starts there, the transition taken from it:
//! action, reward, end flags and a link to the slot holding the next observation. A stream's
//! next transition usually starts from the observation the previous one ended on, so it
//! reuses that slot: storage is about one observation per transition, not two. A slot is
//! written only at the ring's cursor, and a transition's next slot is always written after its
//! own, so while a transition's slot is intact, every slot its links reach is intact too.
//!
//! n-step returns are assembled at sample time by following links: they stop at termination
//! (no bootstrap), at truncation (bootstrap from the final observation) and at the newest
//! observation of a stream (a shorter bootstrap).

use crawler_proto::validate;
use std::collections::HashMap;

pub use crawler_run::config::{PrioritizedConfig, ReplayConfig};
use rand::Rng;
use serde::{Deserialize, Serialize};

pub use sampler::Sampler;

pub mod sampler;
pub mod sum_tree;

const HAS_TRANSITION: u8 = 1;
const TERMINATED: u8 = 2;
const TRUNCATED: u8 = 4;

/// Identifies the sequence of transitions of one crawler of one actor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct StreamId {
    pub actor: u32,
    pub env: u32,
}

/// What a replay read from a file may hold: what ingest validation lets into a live one.
#[derive(Debug, Clone)]
pub struct SnapshotBounds {
    /// `[low, high]` of each observation value.
    pub observation_range: Vec<[f32; 2]>,
    pub max_abs_reward: f32,
    pub num_actions: u32,
}

impl From<&crawler_proto::TransitionLimits> for SnapshotBounds {
    fn from(limits: &crawler_proto::TransitionLimits) -> Self {
        Self {
            observation_range: limits.observation_range.clone(),
            max_abs_reward: limits.max_abs_reward,
            num_actions: limits.num_actions,
        }
    }
}

/// One transition as it arrives.
#[derive(Debug, Clone, Copy)]
pub struct Transition<'a> {
    pub observation: &'a [f32],
    pub action: u8,
    pub reward: f32,
    pub next_observation: &'a [f32],
    pub terminated: bool,
    pub truncated: bool,
}

/// A sampled minibatch, in flat buffers ready to become tensors.
#[derive(Debug, Clone, Default)]
pub struct SampledBatch {
    pub observations: Vec<f32>,
    pub actions: Vec<i64>,
    /// Discounted sum of up to n rewards.
    pub returns: Vec<f32>,
    pub next_observations: Vec<f32>,
    /// γᵐ for an m-step return that bootstraps, 0 after termination.
    pub discounts: Vec<f32>,
    /// Importance-sampling weights, normalised by the batch's largest (prioritised only).
    pub weights: Vec<f32>,
    /// Where each sample came from, for priority updates.
    pub keys: Vec<SampleKey>,
}

/// A sampled slot and the write stamp it had, so a late priority update for a slot that has
/// since been overwritten is dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SampleKey {
    slot: u32,
    stamp: u64,
}

/// A stream's newest observation, still waiting for the transition that starts from it.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct Pending {
    slot: u32,
    stamp: u64,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReplayError {
    #[error("replay holds no transition to sample yet")]
    Empty,
    #[error("observation has {got} values; this replay stores {expected}")]
    Dimension { got: usize, expected: usize },
    #[error("replay.capacity = {0} is invalid: at least 2 slots are needed")]
    Capacity(usize),
    #[error("replay.n_step = {0} is invalid: an integer in 1..=100")]
    NStep(usize),
}

/// The replay buffer.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Replay {
    capacity: usize,
    n_step: usize,
    sampler: Sampler,
    obs_dim: usize,
    observations: Vec<f32>,
    actions: Vec<u8>,
    rewards: Vec<f32>,
    flags: Vec<u8>,
    next: Vec<u32>,
    /// Global write count at which each slot was last written.
    stamps: Vec<u64>,
    cursor: usize,
    writes: u64,
    filled: usize,
    transitions: usize,
    pending: HashMap<StreamId, Pending>,
    /// Transitions ever inserted.
    inserted: u64,
}

impl Replay {
    pub fn new(config: ReplayConfig, obs_dim: usize) -> Result<Self, ReplayError> {
        let capacity = config.capacity;
        if capacity < 2 || capacity > u32::MAX as usize {
            return Err(ReplayError::Capacity(capacity));
        }
        if !(1..=100).contains(&config.n_step) {
            return Err(ReplayError::NStep(config.n_step));
        }
        Ok(Self {
            capacity,
            n_step: config.n_step,
            sampler: Sampler::new(config.prioritized, capacity),
            obs_dim,
            observations: vec![0.0; capacity * obs_dim],
            actions: vec![0; capacity],
            rewards: vec![0.0; capacity],
            flags: vec![0; capacity],
            next: vec![0; capacity],
            stamps: vec![0; capacity],
            cursor: 0,
            writes: 0,
            filled: 0,
            transitions: 0,
            pending: HashMap::new(),
            inserted: 0,
        })
    }

    /// The config this replay was built with.
    pub fn config(&self) -> ReplayConfig {
        ReplayConfig { capacity: self.capacity, n_step: self.n_step, prioritized: self.sampler.prioritized_config() }
    }

    pub fn sampler(&self) -> &Sampler {
        &self.sampler
    }

    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Transitions that can be sampled.
    pub fn len(&self) -> usize {
        self.transitions
    }

    pub fn is_empty(&self) -> bool {
        self.transitions == 0
    }

    /// Whether every stored observation and reward is finite (an audit for tests and
    /// diagnostics: ingest validation should make this always true).
    pub fn all_finite(&self) -> bool {
        let slots = self.filled.min(self.capacity);
        self.observations[..slots * self.obs_dim].iter().all(|v| v.is_finite())
            && self.rewards[..slots].iter().all(|v| v.is_finite())
    }

    /// Transitions ever inserted.
    pub fn total_inserted(&self) -> u64 {
        self.inserted
    }

    /// Adds one transition of `stream`. O(1).
    pub fn insert(&mut self, stream: StreamId, t: &Transition<'_>) -> Result<(), ReplayError> {
        for obs in [t.observation, t.next_observation] {
            if obs.len() != self.obs_dim {
                return Err(ReplayError::Dimension { got: obs.len(), expected: self.obs_dim });
            }
        }
        let continued = self.pending.get(&stream).copied().filter(|p| {
            let slot = p.slot as usize;
            self.stamps[slot] == p.stamp && self.observation(slot) == t.observation
        });
        let start = match continued {
            Some(p) => p.slot as usize,
            None => self.write_observation(t.observation),
        };
        let start_stamp = self.stamps[start];
        let next = self.write_observation(t.next_observation);
        // With a tiny ring, writing `next` can overwrite `start` itself; then drop the transition.
        if self.stamps[start] != start_stamp {
            self.pending.remove(&stream);
            return Ok(());
        }
        self.actions[start] = t.action;
        self.rewards[start] = t.reward;
        self.next[start] = next as u32;
        self.flags[start] =
            HAS_TRANSITION | if t.terminated { TERMINATED } else { 0 } | if t.truncated { TRUNCATED } else { 0 };
        self.transitions += 1;
        self.inserted += 1;
        self.sampler.stored(start);
        if t.terminated || t.truncated {
            self.pending.remove(&stream);
        } else {
            self.pending.insert(stream, Pending { slot: next as u32, stamp: self.stamps[next] });
        }
        Ok(())
    }

    /// Checks a replay read from a file, field by field, as the wire's data is checked: the
    /// shape against this run's `config` and `obs_dim`, every index inside the ring, every
    /// count consistent with the flags, every stored value finite and inside `bounds`. A
    /// snapshot that passes samples as a replay filled by validated actors would. The error
    /// names the field.
    pub fn check_snapshot(
        &mut self,
        config: &ReplayConfig,
        obs_dim: usize,
        bounds: &SnapshotBounds,
    ) -> Result<(), String> {
        let capacity = self.capacity;
        if capacity != config.capacity || self.n_step != config.n_step || obs_dim != self.obs_dim {
            return Err(format!(
                "capacity {capacity}, n_step {}, obs_dim {}: this run has {}, {} and {obs_dim}",
                self.n_step, self.obs_dim, config.capacity, config.n_step
            ));
        }
        if self.sampler.prioritized_config() != config.prioritized {
            return Err("sampler differs from replay.prioritized".into());
        }
        let lengths = [
            ("observations", self.observations.len(), capacity * obs_dim),
            ("actions", self.actions.len(), capacity),
            ("rewards", self.rewards.len(), capacity),
            ("flags", self.flags.len(), capacity),
            ("next", self.next.len(), capacity),
            ("stamps", self.stamps.len(), capacity),
        ];
        if let Some((field, got, expected)) = lengths.iter().find(|(_, got, expected)| got != expected) {
            return Err(format!("{field} holds {got} values, a replay of {capacity} slots {expected}"));
        }
        if self.cursor >= capacity || self.filled > capacity {
            return Err(format!("cursor {} / filled {} outside {capacity} slots", self.cursor, self.filled));
        }
        let mut transitions = 0;
        for slot in 0..capacity {
            let flags = self.flags[slot];
            if flags & !(HAS_TRANSITION | TERMINATED | TRUNCATED) != 0 || self.stamps[slot] > self.writes {
                return Err(format!(
                    "slot {slot}: flags {flags:#x}, stamp {} of {} writes",
                    self.stamps[slot], self.writes
                ));
            }
            if slot >= self.filled {
                if flags != 0 {
                    return Err(format!("slot {slot}: never written, yet flags {flags:#x}"));
                }
                continue;
            }
            let observation = self.observation(slot);
            if let Err(outside) = validate::within_ranges("observation", observation, &bounds.observation_range) {
                return Err(format!("slot {slot}: {outside}"));
            }
            if flags & HAS_TRANSITION != 0 {
                transitions += 1;
                let (action, reward, next) = (self.actions[slot], self.rewards[slot], self.next[slot] as usize);
                let reward_ok = reward.is_finite() && reward.abs() <= bounds.max_abs_reward;
                if u32::from(action) >= bounds.num_actions || !reward_ok || next >= self.filled {
                    return Err(format!("slot {slot}: action {action}, reward {reward}, next slot {next}"));
                }
            }
        }
        if transitions != self.transitions {
            return Err(format!("transitions says {}, the flags hold {transitions}", self.transitions));
        }
        if let Some((stream, pending)) = self.pending.iter().find(|(_, p)| p.slot as usize >= capacity) {
            return Err(format!("stream {stream:?} continues from slot {}, outside the ring", pending.slot));
        }
        self.sampler.check_snapshot(capacity)
    }

    /// Forgets the unfinished episodes of every actor `keep` refuses (those that left): their
    /// next transitions will never come, and a table kept per stream would otherwise grow
    /// with every actor id ever seen.
    pub fn release_streams(&mut self, keep: impl Fn(u32) -> bool) {
        self.pending.retain(|stream, _| keep(stream.actor));
    }

    /// Streams with an unfinished episode.
    pub fn open_streams(&self) -> usize {
        self.pending.len()
    }

    fn observation(&self, slot: usize) -> &[f32] {
        &self.observations[slot * self.obs_dim..(slot + 1) * self.obs_dim]
    }

    /// Writes an observation at the cursor, dropping whatever transition the slot held.
    fn write_observation(&mut self, observation: &[f32]) -> usize {
        let slot = self.cursor;
        if self.flags[slot] & HAS_TRANSITION != 0 {
            self.transitions -= 1;
            self.sampler.removed(slot);
        }
        self.flags[slot] = 0;
        self.observations[slot * self.obs_dim..(slot + 1) * self.obs_dim].copy_from_slice(observation);
        self.writes += 1;
        self.stamps[slot] = self.writes;
        self.cursor = (self.cursor + 1) % self.capacity;
        self.filled = (self.filled + 1).min(self.capacity);
        slot
    }

    /// Samples `batch` transitions (uniformly, or by priority with weights for β `beta`)
    /// into `out`, computing n-step returns with discount `gamma`. O(batch · n) uniform,
    /// O(batch · (n + log capacity)) prioritised.
    pub fn sample(
        &self,
        batch: usize,
        gamma: f64,
        beta: f64,
        rng: &mut impl Rng,
        out: &mut SampledBatch,
    ) -> Result<(), ReplayError> {
        if self.transitions == 0 {
            return Err(ReplayError::Empty);
        }
        out.observations.clear();
        out.actions.clear();
        out.returns.clear();
        out.next_observations.clear();
        out.discounts.clear();
        out.weights.clear();
        out.keys.clear();
        match &self.sampler {
            Sampler::Prioritized(prioritized) => {
                let tree = &prioritized.tree;
                let total = tree.total();
                let segment = total / batch as f64;
                for i in 0..batch {
                    let mass = (i as f64 + rng.random::<f64>()) * segment;
                    let mut slot = tree.find(mass.min(total * (1.0 - 1e-12)));
                    if self.flags[slot] & HAS_TRANSITION == 0 {
                        // Only reachable through rounding at a segment's edge.
                        slot = self.uniform_slot(rng);
                    }
                    let probability = tree.get(slot) / total;
                    let weight = (self.transitions as f64 * probability).powf(-beta);
                    out.weights.push(weight as f32);
                    self.push_sample(slot, gamma, out);
                }
                let max = out.weights.iter().copied().fold(f32::MIN_POSITIVE, f32::max);
                for w in &mut out.weights {
                    *w /= max;
                }
            }
            Sampler::Uniform => {
                for _ in 0..batch {
                    let slot = self.uniform_slot(rng);
                    self.push_sample(slot, gamma, out);
                }
            }
        }
        Ok(())
    }

    /// A uniformly drawn slot that starts a transition (rejection sampling: most slots do).
    fn uniform_slot(&self, rng: &mut impl Rng) -> usize {
        loop {
            let slot = rng.random_range(0..self.filled);
            if self.flags[slot] & HAS_TRANSITION != 0 {
                return slot;
            }
        }
    }

    fn push_sample(&self, slot: usize, gamma: f64, out: &mut SampledBatch) {
        let (ret, discount, bootstrap_slot) = self.n_step_return(slot, gamma);
        out.observations.extend_from_slice(self.observation(slot));
        out.actions.push(i64::from(self.actions[slot]));
        out.returns.push(ret as f32);
        out.next_observations.extend_from_slice(self.observation(bootstrap_slot));
        out.discounts.push(discount as f32);
        out.keys.push(SampleKey { slot: slot as u32, stamp: self.stamps[slot] });
    }

    /// The n-step return from `slot`: (Σ γᵏ rₖ, discount for the bootstrap, bootstrap slot).
    pub(crate) fn n_step_return(&self, slot: usize, gamma: f64) -> (f64, f64, usize) {
        let mut ret = 0.0;
        let mut discount = 1.0;
        let mut current = slot;
        for step in 0..self.n_step {
            ret += discount * f64::from(self.rewards[current]);
            discount *= gamma;
            let flags = self.flags[current];
            let next = self.next[current] as usize;
            if flags & TERMINATED != 0 {
                return (ret, 0.0, next);
            }
            let chain_continues =
                step + 1 < self.n_step && flags & TRUNCATED == 0 && self.flags[next] & HAS_TRANSITION != 0;
            if !chain_continues {
                return (ret, discount, next);
            }
            current = next;
        }
        (ret, discount, current)
    }

    /// Sets priorities from the absolute TD errors of a sampled batch.
    pub fn update_priorities(&mut self, keys: &[SampleKey], td_errors: &[f32]) {
        for (key, &td) in keys.iter().zip(td_errors) {
            let slot = key.slot as usize;
            // Only the transition that was sampled: its slot may hold a newer one by now.
            if self.stamps[slot] == key.stamp && self.flags[slot] & HAS_TRANSITION != 0 {
                self.sampler.rescore(slot, td);
            }
        }
    }

    /// Bytes held by the buffer's arrays.
    pub fn memory_bytes(&self) -> usize {
        self.observations.capacity() * size_of::<f32>()
            + self.actions.capacity()
            + self.rewards.capacity() * size_of::<f32>()
            + self.flags.capacity()
            + self.next.capacity() * size_of::<u32>()
            + self.stamps.capacity() * size_of::<u64>()
            + self.sampler.memory_bytes()
    }

    /// The information a transition carries, stored once: one observation, the action, the
    /// reward and the end flags.
    pub fn raw_bytes_per_transition(&self) -> usize {
        self.obs_dim * size_of::<f32>() + size_of::<u8>() + size_of::<f32>() + size_of::<u8>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    const STREAM: StreamId = StreamId { actor: 0, env: 0 };

    /// Observations are [t] so each slot's content tells which step it is.
    fn push(replay: &mut Replay, stream: StreamId, t: f32, reward: f32, terminated: bool, truncated: bool) {
        let transition = Transition {
            observation: &[t],
            action: t as u8,
            reward,
            next_observation: &[t + 1.0],
            terminated,
            truncated,
        };
        replay.insert(stream, &transition).unwrap();
    }

    fn config(capacity: usize, n_step: usize) -> ReplayConfig {
        ReplayConfig { capacity, n_step, prioritized: None }
    }

    fn slot_of(replay: &Replay, t: f32) -> usize {
        (0..replay.filled).find(|&s| replay.observation(s) == [t] && replay.flags[s] & HAS_TRANSITION != 0).unwrap()
    }

    #[test]
    fn a_continuing_stream_stores_each_observation_once() {
        let mut replay = Replay::new(config(100, 1), 1).unwrap();
        for t in 0..10 {
            push(&mut replay, STREAM, t as f32, 1.0, false, false);
        }
        assert_eq!(replay.len(), 10);
        assert_eq!(replay.filled, 11, "10 transitions share 11 observations");
    }

    #[test]
    fn n_step_targets_stop_at_termination_and_bootstrap_at_truncation() {
        let gamma = 0.5;
        let mut replay = Replay::new(config(100, 3), 1).unwrap();
        // Episode A: t = 0, 1, 2 with rewards 1, 2, 4; terminates after t = 2.
        push(&mut replay, STREAM, 0.0, 1.0, false, false);
        push(&mut replay, STREAM, 1.0, 2.0, false, false);
        push(&mut replay, STREAM, 2.0, 4.0, true, false);
        // Episode B starts from a fresh observation 10: rewards 1, 1; truncated after t = 11.
        push(&mut replay, STREAM, 10.0, 1.0, false, false);
        push(&mut replay, STREAM, 11.0, 1.0, false, true);
        // Episode C: one step so far, still running.
        push(&mut replay, STREAM, 20.0, 3.0, false, false);

        let at = |t: f32| {
            let (ret, discount, next) = replay.n_step_return(slot_of(&replay, t), gamma);
            (ret, discount, replay.observation(next)[0])
        };
        // Full 3 steps, ending in termination: no bootstrap.
        assert_eq!(at(0.0), (1.0 + 0.5 * 2.0 + 0.25 * 4.0, 0.0, 3.0));
        // Two steps to termination.
        assert_eq!(at(1.0), (2.0 + 0.5 * 4.0, 0.0, 3.0));
        assert_eq!(at(2.0), (4.0, 0.0, 3.0));
        // The return does not run into the next episode; truncation bootstraps from the final
        // observation with γ².
        assert_eq!(at(10.0), (1.0 + 0.5 * 1.0, 0.25, 12.0));
        assert_eq!(at(11.0), (1.0, 0.5, 12.0));
        // The newest transition bootstraps from the newest observation after one step.
        assert_eq!(at(20.0), (3.0, 0.5, 21.0));
    }

    #[test]
    fn interleaved_streams_keep_their_own_chains() {
        let mut replay = Replay::new(config(100, 2), 1).unwrap();
        let other = StreamId { actor: 1, env: 0 };
        push(&mut replay, STREAM, 0.0, 1.0, false, false);
        push(&mut replay, other, 100.0, 10.0, false, false);
        push(&mut replay, STREAM, 1.0, 1.0, false, false);
        push(&mut replay, other, 101.0, 10.0, false, false);
        let (ret, discount, next) = replay.n_step_return(slot_of(&replay, 0.0), 0.9);
        assert_eq!((ret, discount, replay.observation(next)[0]), (1.0 + 0.9, 0.81, 2.0));
        let (ret, _, next) = replay.n_step_return(slot_of(&replay, 100.0), 0.9);
        assert_eq!((ret, replay.observation(next)[0]), (10.0 + 9.0, 102.0));
        assert_eq!(replay.filled, 6);
    }

    #[test]
    fn a_gap_in_a_stream_starts_a_new_chain() {
        let mut replay = Replay::new(config(100, 3), 1).unwrap();
        push(&mut replay, STREAM, 0.0, 1.0, false, false);
        // The transition from 1 was lost: the next one starts at 2, which does not match.
        push(&mut replay, STREAM, 2.0, 1.0, false, false);
        let (ret, discount, next) = replay.n_step_return(slot_of(&replay, 0.0), 0.5);
        assert_eq!((ret, discount, replay.observation(next)[0]), (1.0, 0.5, 1.0));
        assert_eq!(replay.filled, 4);
    }

    #[test]
    fn the_ring_wraps_and_drops_the_oldest_transitions() {
        let mut replay = Replay::new(config(8, 1), 1).unwrap();
        for t in 0..20 {
            push(&mut replay, STREAM, t as f32, t as f32, false, false);
        }
        // 21 observations written into 8 slots: the newest 8 are 13..=20, of which 13..=19
        // start transitions.
        assert_eq!(replay.filled, 8);
        assert_eq!(replay.len(), 7);
        let mut stored: Vec<f32> =
            (0..8).filter(|&s| replay.flags[s] & HAS_TRANSITION != 0).map(|s| replay.observation(s)[0]).collect();
        stored.sort_by(f32::total_cmp);
        assert_eq!(stored, [13.0, 14.0, 15.0, 16.0, 17.0, 18.0, 19.0]);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut batch = SampledBatch::default();
        replay.sample(64, 0.9, 0.0, &mut rng, &mut batch).unwrap();
        for (o, n) in batch.observations.iter().zip(&batch.next_observations) {
            assert!(*o >= 13.0 && *n == o + 1.0, "{o} -> {n}");
        }
        // A stream paused while the ring wrapped past its newest observation starts afresh.
        let mut replay = Replay::new(config(4, 1), 1).unwrap();
        push(&mut replay, STREAM, 0.0, 0.0, false, false);
        let other = StreamId { actor: 9, env: 9 };
        for t in 0..3 {
            push(&mut replay, other, 100.0 + t as f32, 0.0, false, false);
        }
        push(&mut replay, STREAM, 1.0, 0.0, false, false);
        let (_, _, next) = replay.n_step_return(slot_of(&replay, 1.0), 0.9);
        assert_eq!(replay.observation(next), [2.0]);
    }

    #[test]
    fn uniform_sampling_covers_transitions_evenly() {
        let mut replay = Replay::new(config(1000, 1), 1).unwrap();
        for t in 0..10 {
            push(&mut replay, STREAM, t as f32, 0.0, t == 9, false);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut batch = SampledBatch::default();
        let mut counts = [0usize; 10];
        for _ in 0..1000 {
            replay.sample(10, 0.9, 0.0, &mut rng, &mut batch).unwrap();
            for o in &batch.observations {
                counts[*o as usize] += 1;
            }
        }
        assert!(counts.iter().all(|&c| (800..1200).contains(&c)), "{counts:?}");
    }

    #[test]
    fn prioritized_sampling_follows_priorities_with_matching_weights() {
        let per = PrioritizedConfig { alpha: 1.0, beta_start: 1.0, beta_updates: 1, epsilon: 0.0 };
        let mut replay = Replay::new(ReplayConfig { capacity: 100, n_step: 1, prioritized: Some(per) }, 1).unwrap();
        for t in 0..4 {
            push(&mut replay, STREAM, t as f32, 0.0, false, false);
        }
        let keys: Vec<SampleKey> = (0..4)
            .map(|t| slot_of(&replay, t as f32))
            .map(|slot| SampleKey { slot: slot as u32, stamp: replay.stamps[slot] })
            .collect();
        // Priorities 1 : 2 : 3 : 4 (α = 1, ε = 0).
        replay.update_priorities(&keys, &[1.0, 2.0, 3.0, 4.0]);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut batch = SampledBatch::default();
        let mut counts = [0f64; 4];
        let draws = 40_000;
        for _ in 0..draws / 8 {
            replay.sample(8, 0.9, 1.0, &mut rng, &mut batch).unwrap();
            for (o, w) in batch.observations.iter().zip(&batch.weights) {
                counts[*o as usize] += 1.0;
                // w ∝ 1/(N·P(i)) = 10/(4·p_i), normalised by the batch's max: p_min/p_i.
                let expected_ratio = 1.0 / (*o + 1.0);
                let max_in_batch = batch.observations.iter().map(|&x| 1.0 / (x + 1.0)).fold(0.0, f32::max);
                assert!((w - expected_ratio / max_in_batch).abs() < 1e-5, "{w} for {o}");
            }
        }
        for (i, c) in counts.iter().enumerate() {
            let share = c / draws as f64;
            let expected = (i as f64 + 1.0) / 10.0;
            assert!((share - expected).abs() < 0.01, "transition {i}: {share} vs {expected}");
        }
        // A stale update for an overwritten slot is ignored.
        let stale = SampleKey { slot: keys[0].slot, stamp: keys[0].stamp + 1000 };
        replay.update_priorities(&[stale], &[100.0]);
        let Sampler::Prioritized(p) = &replay.sampler else { panic!("not prioritised") };
        assert_eq!(p.tree.get(keys[0].slot as usize), 1.0);
    }

    #[test]
    fn bad_input_is_rejected() {
        assert_eq!(Replay::new(config(1, 1), 4).unwrap_err(), ReplayError::Capacity(1));
        assert_eq!(Replay::new(config(10, 0), 4).unwrap_err(), ReplayError::NStep(0));
        let mut replay = Replay::new(config(10, 1), 2).unwrap();
        let mut batch = SampledBatch::default();
        assert_eq!(replay.sample(1, 0.9, 0.0, &mut ChaCha8Rng::seed_from_u64(0), &mut batch), Err(ReplayError::Empty));
        let t = Transition {
            observation: &[1.0],
            action: 0,
            reward: 0.0,
            next_observation: &[1.0, 2.0],
            terminated: false,
            truncated: false,
        };
        assert_eq!(replay.insert(STREAM, &t), Err(ReplayError::Dimension { got: 1, expected: 2 }));
    }
}
