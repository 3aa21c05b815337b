//! Property tests of the transition-batch decoder: valid batches round-trip, and no input,
//! random or a mutated valid message, makes it panic or accept something inconsistent.

#![allow(clippy::unwrap_used)]

use crawler_proto::validate::transition_batch;
use crawler_proto::{PROTOCOL_VERSION, TransitionBatch, TransitionLimits};
use proptest::prelude::*;
use prost::Message;

const OBS_DIM: u32 = 4;

fn limits() -> TransitionLimits {
    TransitionLimits {
        run_id: "run".into(),
        obs_dim: OBS_DIM,
        num_actions: 25,
        max_batch: 64,
        envs_per_actor: 8,
        observation_range: vec![[-1e3, 1e3]; OBS_DIM as usize],
        max_abs_reward: 10.0,
    }
}

fn valid_batch() -> impl Strategy<Value = TransitionBatch> {
    (1usize..32, any::<u64>(), any::<u64>()).prop_flat_map(|(n, sequence, incarnation)| {
        let values = n * OBS_DIM as usize;
        (
            prop::collection::vec(-1e3f32..1e3, values),
            prop::collection::vec(-1e3f32..1e3, values),
            prop::collection::vec(0u32..25, n),
            prop::collection::vec(-10f32..10.0, n),
            prop::collection::vec(any::<bool>(), n),
            prop::collection::vec(any::<bool>(), n),
            prop::collection::vec(0u32..8, n),
        )
            .prop_map(
                move |(observations, next_observations, actions, rewards, terminated, truncated, env_ids)| {
                    TransitionBatch {
                        protocol_version: PROTOCOL_VERSION,
                        run_id: "run".into(),
                        actor_id: 3,
                        sequence,
                        incarnation,
                        obs_dim: OBS_DIM,
                        env_ids,
                        observations,
                        next_observations,
                        actions,
                        rewards,
                        terminated,
                        truncated,
                        priorities: vec![],
                        weights_version: 7,
                        physics_steps: n as u64 * 10,
                        count: n as u32,
                    }
                },
            )
    })
}

/// What validation promises about anything it accepts.
fn consistent(batch: &TransitionBatch) -> bool {
    let n = batch.actions.len();
    let values = n * OBS_DIM as usize;
    n > 0
        && batch.count as usize == n
        && batch.observations.len() == values
        && batch.next_observations.len() == values
        && [batch.env_ids.len(), batch.rewards.len(), batch.terminated.len(), batch.truncated.len()]
            .iter()
            .all(|&l| l == n)
        && batch.observations.iter().chain(&batch.next_observations).chain(&batch.rewards).all(|v| v.is_finite())
        && batch.actions.iter().all(|&a| a < 25)
        && batch.env_ids.iter().all(|&e| e < 8)
        && batch.observations.iter().chain(&batch.next_observations).all(|v| v.abs() <= 1e3)
        && batch.rewards.iter().all(|r| r.abs() <= 10.0)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2_000))]

    #[test]
    fn valid_batches_round_trip(batch in valid_batch()) {
        let decoded = transition_batch(&batch.encode_to_vec(), &limits()).unwrap();
        prop_assert_eq!(decoded, batch);
    }

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..4096)) {
        if let Ok(batch) = transition_batch(&bytes, &limits()) {
            prop_assert!(consistent(&batch));
        }
    }

    #[test]
    fn mutated_messages_are_rejected_or_still_consistent(
        batch in valid_batch(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
    ) {
        let mut bytes = batch.encode_to_vec();
        for (index, value) in flips {
            let i = index.index(bytes.len());
            bytes[i] ^= value;
        }
        if let Ok(decoded) = transition_batch(&bytes, &limits()) {
            prop_assert!(consistent(&decoded), "{decoded:?}");
        }
    }
}

/// A batch whose every field is as wide as the wire allows.
fn widest_batch(transitions: usize, obs_dim: usize) -> TransitionBatch {
    TransitionBatch {
        protocol_version: u32::MAX,
        run_id: "r".repeat(crawler_proto::keys::MAX_RUN_ID_BYTES),
        actor_id: u32::MAX,
        sequence: u64::MAX,
        incarnation: u64::MAX,
        obs_dim: u32::MAX,
        env_ids: vec![u32::MAX; transitions],
        observations: vec![f32::MAX; transitions * obs_dim],
        next_observations: vec![f32::MAX; transitions * obs_dim],
        actions: vec![u32::MAX; transitions],
        rewards: vec![f32::MAX; transitions],
        terminated: vec![true; transitions],
        truncated: vec![true; transitions],
        priorities: vec![f32::MAX; transitions],
        weights_version: u64::MAX,
        physics_steps: u64::MAX,
        count: u32::MAX,
    }
}

/// The bound senders check their settings with is exactly what prost encodes for the widest
/// batch, across the sizes where length prefixes change width.
#[test]
fn the_largest_batch_bound_is_what_prost_encodes_for_the_widest_batch() {
    for transitions in [1, 2, 25, 26, 255, 256, 4096] {
        for obs_dim in [1, 40, 120, 320] {
            let widest = widest_batch(transitions, obs_dim);
            assert_eq!(
                TransitionBatch::largest_encoded_len(transitions, obs_dim),
                widest.encoded_len(),
                "{transitions} transitions of {obs_dim} values"
            );
        }
    }
    // The presets' batches (256 transitions of 40 values) are far inside the message limit;
    // the protocol's largest batch of eight stacked observations is not.
    assert!(TransitionBatch::largest_encoded_len(256, 40) < crawler_proto::MAX_MESSAGE_BYTES / 10);
    let stacked = TransitionBatch::largest_encoded_len(crawler_proto::MAX_BATCH_TRANSITIONS, 8 * 40);
    assert!(stacked > crawler_proto::MAX_MESSAGE_BYTES, "{stacked}");
    // Sizes no batch could have saturate instead of overflowing.
    assert_eq!(TransitionBatch::largest_encoded_len(usize::MAX, 320), usize::MAX);
    assert_eq!(TransitionBatch::largest_encoded_len(usize::MAX / 2, 0), usize::MAX);
}
