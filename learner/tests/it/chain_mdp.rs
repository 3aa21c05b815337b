//! Learning end to end in-process: DQN with replay converges to Q* on a chain MDP.

#![allow(clippy::unwrap_used)] // Tests: a panic is a failure with a message.

use crawler_env::policy::NetworkSpec;
use crawler_learner::algo::dqn::{Batch, Dqn, DqnConfig, TargetUpdate};
use crawler_learner::replay::{Replay, ReplayConfig, SampledBatch, StreamId, Transition};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;

/// States 0..N−1 in a row, one-hot observed. Action 1 moves right, action 0 left (or stays at
/// 0). Reaching state N−1 pays 1 and ends the episode; every other step pays 0.
const N: usize = 6;
const GAMMA: f64 = 0.9;

fn one_hot(state: usize) -> Vec<f32> {
    let mut v = vec![0.0; N];
    v[state] = 1.0;
    v
}

fn step(state: usize, action: u8) -> (usize, f32, bool) {
    let next = if action == 1 { state + 1 } else { state.saturating_sub(1) };
    if next == N - 1 { (next, 1.0, true) } else { (next, 0.0, false) }
}

/// Q*(s, right) = γ^(N−2−s); Q*(s, left) = γ · V*(max(s−1, 0)), V*(s) = γ^(N−2−s).
fn q_star(state: usize, action: u8) -> f64 {
    let value = |s: usize| GAMMA.powi((N - 2 - s) as i32);
    if action == 1 { value(state) } else { GAMMA * value(state.saturating_sub(1)) }
}

fn to_batch(sample: &SampledBatch, batch: usize) -> Batch {
    Batch {
        observations: Tensor::from_slice(&sample.observations).view([batch as i64, N as i64]),
        actions: Tensor::from_slice(&sample.actions),
        returns: Tensor::from_slice(&sample.returns),
        next_observations: Tensor::from_slice(&sample.next_observations).view([batch as i64, N as i64]),
        discounts: Tensor::from_slice(&sample.discounts),
        weights: None,
    }
}

#[test]
fn dqn_converges_to_q_star_on_a_chain() {
    crawler_learner::set_torch_threads(1);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut replay = Replay::new(ReplayConfig { capacity: 20_000, n_step: 1, prioritized: None }, N).unwrap();
    let stream = StreamId { actor: 0, env: 0 };
    let mut state = 0;
    for _ in 0..10_000 {
        let action = rng.random_range(0..2u8);
        let (next, reward, terminated) = step(state, action);
        let (obs, next_obs) = (one_hot(state), one_hot(next));
        let transition =
            Transition { observation: &obs, action, reward, next_observation: &next_obs, terminated, truncated: false };
        replay.insert(stream, &transition).unwrap();
        state = if terminated { 0 } else { next };
    }

    let network = NetworkSpec { obs_dim: N, hidden: vec![32], num_actions: 2, layer_norm: true };
    let config =
        DqnConfig { gamma: GAMMA, lr: 3e-3, target_update: TargetUpdate::Hard { every: 100 }, ..DqnConfig::default() };
    let mut dqn = Dqn::new(network, config);
    let mut sample = SampledBatch::default();
    for _ in 0..4_000 {
        replay.sample(64, GAMMA, 0.0, &mut rng, &mut sample).unwrap();
        dqn.update(&to_batch(&sample, 64));
    }

    let states: Vec<f32> = (0..N - 1).flat_map(one_hot).collect();
    let q = dqn.q_values(&Tensor::from_slice(&states).view([(N - 1) as i64, N as i64]));
    let q: Vec<f32> = Vec::try_from(q.flatten(0, -1)).unwrap();
    for s in 0..N - 1 {
        for a in 0..2u8 {
            let got = f64::from(q[s * 2 + a as usize]);
            let want = q_star(s, a);
            assert!((got - want).abs() < 0.05, "Q({s}, {a}) = {got:.4}, Q* = {want:.4}");
        }
    }
}
