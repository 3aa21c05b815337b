//! Property tests of the transition-batch decoder: valid batches round-trip, no input, random
//! or a mutated valid message, makes it panic or accept something inconsistent, and the
//! hand-written encoding agrees with prost's derived one for the same schema on every input.

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

/// `TransitionBatch`'s schema, derived by prost: the reference its hand-written encoding is
/// held to. Named alike, so that the two name fields alike in their errors.
mod derived {
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TransitionBatch {
        #[prost(uint32, tag = "1")]
        pub protocol_version: u32,
        #[prost(string, tag = "2")]
        pub run_id: String,
        #[prost(uint32, tag = "3")]
        pub actor_id: u32,
        #[prost(uint64, tag = "4")]
        pub sequence: u64,
        #[prost(uint64, tag = "5")]
        pub incarnation: u64,
        #[prost(uint32, tag = "6")]
        pub obs_dim: u32,
        #[prost(uint32, repeated, tag = "7")]
        pub env_ids: Vec<u32>,
        #[prost(float, repeated, tag = "8")]
        pub observations: Vec<f32>,
        #[prost(float, repeated, tag = "9")]
        pub next_observations: Vec<f32>,
        #[prost(uint32, repeated, tag = "10")]
        pub actions: Vec<u32>,
        #[prost(float, repeated, tag = "11")]
        pub rewards: Vec<f32>,
        #[prost(bool, repeated, tag = "12")]
        pub terminated: Vec<bool>,
        #[prost(bool, repeated, tag = "13")]
        pub truncated: Vec<bool>,
        #[prost(float, repeated, tag = "14")]
        pub priorities: Vec<f32>,
        #[prost(uint64, tag = "15")]
        pub weights_version: u64,
        #[prost(uint64, tag = "16")]
        pub physics_steps: u64,
        #[prost(uint32, tag = "17")]
        pub count: u32,
    }
}

impl From<derived::TransitionBatch> for TransitionBatch {
    fn from(d: derived::TransitionBatch) -> Self {
        TransitionBatch {
            protocol_version: d.protocol_version,
            run_id: d.run_id,
            actor_id: d.actor_id,
            sequence: d.sequence,
            incarnation: d.incarnation,
            obs_dim: d.obs_dim,
            env_ids: d.env_ids,
            observations: d.observations,
            next_observations: d.next_observations,
            actions: d.actions,
            rewards: d.rewards,
            terminated: d.terminated,
            truncated: d.truncated,
            priorities: d.priorities,
            weights_version: d.weights_version,
            physics_steps: d.physics_steps,
            count: d.count,
        }
    }
}

/// Floats compared by their bits, so that NaNs from random bytes compare equal to themselves.
fn bits(batch: &TransitionBatch) -> Vec<u32> {
    batch
        .observations
        .iter()
        .chain(&batch.next_observations)
        .chain(&batch.rewards)
        .chain(&batch.priorities)
        .map(|v| v.to_bits())
        .collect()
}

fn same(a: &TransitionBatch, b: &TransitionBatch) -> bool {
    let strip = |batch: &TransitionBatch| TransitionBatch {
        observations: vec![],
        next_observations: vec![],
        rewards: vec![],
        priorities: vec![],
        ..batch.clone()
    };
    strip(a) == strip(b)
        && bits(a) == bits(b)
        && [a.observations.len(), a.next_observations.len(), a.rewards.len(), a.priorities.len()]
            == [b.observations.len(), b.next_observations.len(), b.rewards.len(), b.priorities.len()]
}

/// Decodes `bytes` both ways, and from a buffer split in two at `split` (as a message that
/// arrived in fragments is), and checks that all three agree: the same error or the same batch.
fn decoders_agree(bytes: &[u8], split: usize) -> Result<(), TestCaseError> {
    let derived = derived::TransitionBatch::decode(bytes).map(TransitionBatch::from);
    let written = TransitionBatch::decode(bytes);
    let split = split.min(bytes.len());
    let fragmented = TransitionBatch::decode(prost::bytes::Buf::chain(&bytes[..split], &bytes[split..]));
    for other in [&written, &fragmented] {
        match (&derived, other) {
            (Ok(a), Ok(b)) => prop_assert!(same(a, b), "{a:?} != {b:?}"),
            (Err(a), Err(b)) => prop_assert_eq!(a.to_string(), b.to_string()),
            (a, b) => prop_assert!(false, "derived {a:?}, hand-written {b:?}"),
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2_000))]

    #[test]
    fn the_hand_written_encoding_is_prosts(batch in valid_batch(), split in any::<prop::sample::Index>()) {
        let derived = derived::TransitionBatch::decode(batch.encode_to_vec().as_slice()).unwrap();
        prop_assert_eq!(derived.encode_to_vec(), batch.encode_to_vec());
        prop_assert_eq!(derived.encoded_len(), batch.encoded_len());
        let bytes = batch.encode_to_vec();
        decoders_agree(&bytes, split.index(bytes.len() + 1))?;
    }

    #[test]
    fn the_decoders_agree_on_mutated_and_random_input(
        batch in valid_batch(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8),
        noise in prop::collection::vec(any::<u8>(), 0..512),
        split in any::<prop::sample::Index>(),
    ) {
        let mut bytes = batch.encode_to_vec();
        for (index, value) in flips {
            let i = index.index(bytes.len());
            bytes[i] ^= value;
        }
        decoders_agree(&bytes, split.index(bytes.len() + 1))?;
        decoders_agree(&noise, split.index(noise.len() + 1))?;
    }

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

/// Floats sent unpacked (one fixed32 per value, which protobuf parsers must accept), and a
/// packed field split in two, decode as prost's derive decodes them.
#[test]
fn unpacked_and_repeated_float_fields_decode_as_prost_does() {
    let key_fixed32 = (8 << 3) | 5;
    let key_packed = (8 << 3) | 2;
    let mut bytes = vec![key_fixed32];
    bytes.extend(1.5f32.to_le_bytes());
    bytes.push(key_packed);
    bytes.push(8);
    bytes.extend(2.5f32.to_le_bytes());
    bytes.extend(3.5f32.to_le_bytes());
    bytes.push(key_fixed32);
    bytes.extend((-4.0f32).to_le_bytes());
    let decoded = TransitionBatch::decode(bytes.as_slice()).unwrap();
    assert_eq!(decoded.observations, [1.5, 2.5, 3.5, -4.0]);
    for split in 0..=bytes.len() {
        decoders_agree(&bytes, split).unwrap();
    }
    // A packed length that is not a whole number of floats is refused, as prost refuses it.
    let ragged = [key_packed, 3, 0, 0, 0];
    assert!(TransitionBatch::decode(ragged.as_slice()).is_err());
    decoders_agree(&ragged, 2).unwrap();
}
