//! Decoding and validation of everything received. Errors are typed and name the problem.

use std::collections::HashMap;

use prost::Message;

use crate::messages::*;
use crate::{MAX_MESSAGE_BYTES, PROTOCOL_VERSION};

/// Why a received message was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProtoError {
    #[error("message of {bytes} bytes exceeds the {max}-byte limit")]
    Oversize { bytes: usize, max: usize },
    #[error("undecodable {message}: {reason}")]
    Decode { message: &'static str, reason: String },
    #[error("protocol version {got}, this node speaks {expected}")]
    Version { got: u32, expected: u32 },
    #[error("message for run `{got}`, this node serves run `{expected}`")]
    RunId { got: String, expected: String },
    #[error("run id `{0}` is invalid: use 1-64 characters of A-Z a-z 0-9 _ -")]
    BadRunId(String),
    #[error("observation dimension {got}, the run uses {expected}")]
    ObsDim { got: u32, expected: u32 },
    #[error("batch of {got} transitions exceeds the limit of {max}")]
    BatchSize { got: usize, max: usize },
    #[error("field `{field}` has {got} values, expected {expected}")]
    Length { field: &'static str, got: usize, expected: usize },
    #[error("field `{field}` holds a NaN or infinite value at index {index}")]
    NonFinite { field: &'static str, index: usize },
    #[error("action {action} at index {index} is outside 0..{num_actions}")]
    Action { action: u32, index: usize, num_actions: u32 },
    #[error("sequence {got} from actor {actor} was already received (last {last})")]
    Replayed { actor: u32, got: u64, last: u64 },
    #[error("network spec is invalid: {0}")]
    Network(String),
}

impl ProtoError {
    /// A short stable name for metrics and rate-limited logs.
    pub fn kind(&self) -> &'static str {
        match self {
            ProtoError::Oversize { .. } => "oversize",
            ProtoError::Decode { .. } => "decode",
            ProtoError::Version { .. } => "version",
            ProtoError::RunId { .. } => "run_id",
            ProtoError::BadRunId(_) => "bad_run_id",
            ProtoError::ObsDim { .. } => "obs_dim",
            ProtoError::BatchSize { .. } => "batch_size",
            ProtoError::Length { .. } => "length",
            ProtoError::NonFinite { .. } => "non_finite",
            ProtoError::Action { .. } => "action",
            ProtoError::Replayed { .. } => "replayed",
            ProtoError::Network(_) => "network",
        }
    }
}

/// Decodes a message of type `M`, refusing anything over [`MAX_MESSAGE_BYTES`].
pub fn decode<M: Message + Default>(bytes: &[u8], message: &'static str) -> Result<M, ProtoError> {
    if bytes.len() > MAX_MESSAGE_BYTES {
        return Err(ProtoError::Oversize { bytes: bytes.len(), max: MAX_MESSAGE_BYTES });
    }
    M::decode(bytes).map_err(|e| ProtoError::Decode { message, reason: e.to_string() })
}

/// Checks the protocol version and run id every message carries.
pub fn check_envelope(version: u32, run_id: &str, expected_run: &str) -> Result<(), ProtoError> {
    if version != PROTOCOL_VERSION {
        return Err(ProtoError::Version { got: version, expected: PROTOCOL_VERSION });
    }
    if run_id != expected_run {
        return Err(ProtoError::RunId { got: run_id.to_string(), expected: expected_run.to_string() });
    }
    Ok(())
}

/// What a valid transition batch of this run looks like.
#[derive(Debug, Clone, PartialEq)]
pub struct TransitionLimits {
    pub run_id: String,
    pub obs_dim: u32,
    pub num_actions: u32,
    pub max_batch: usize,
}

fn finite(field: &'static str, values: &[f32]) -> Result<(), ProtoError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(ProtoError::NonFinite { field, index }),
        None => Ok(()),
    }
}

fn length(field: &'static str, got: usize, expected: usize) -> Result<(), ProtoError> {
    if got == expected { Ok(()) } else { Err(ProtoError::Length { field, got, expected }) }
}

/// Decodes and fully checks a transition batch: envelope, sizes, finiteness, action range.
/// Sequence numbers are checked separately by a [`SequenceTracker`].
pub fn transition_batch(bytes: &[u8], limits: &TransitionLimits) -> Result<TransitionBatch, ProtoError> {
    let batch: TransitionBatch = decode(bytes, "transition batch")?;
    check_envelope(batch.protocol_version, &batch.run_id, &limits.run_id)?;
    if batch.obs_dim != limits.obs_dim {
        return Err(ProtoError::ObsDim { got: batch.obs_dim, expected: limits.obs_dim });
    }
    let n = batch.actions.len();
    if n > limits.max_batch {
        return Err(ProtoError::BatchSize { got: n, max: limits.max_batch });
    }
    if n == 0 || batch.count as usize != n {
        return Err(ProtoError::Length { field: "actions (against count)", got: n, expected: batch.count as usize });
    }
    let obs_values = n * limits.obs_dim as usize;
    length("observations", batch.observations.len(), obs_values)?;
    length("next_observations", batch.next_observations.len(), obs_values)?;
    length("env_ids", batch.env_ids.len(), n)?;
    length("rewards", batch.rewards.len(), n)?;
    length("terminated", batch.terminated.len(), n)?;
    length("truncated", batch.truncated.len(), n)?;
    if !batch.priorities.is_empty() {
        length("priorities", batch.priorities.len(), n)?;
        finite("priorities", &batch.priorities)?;
    }
    finite("observations", &batch.observations)?;
    finite("next_observations", &batch.next_observations)?;
    finite("rewards", &batch.rewards)?;
    if let Some((index, &action)) = batch.actions.iter().enumerate().find(|(_, a)| **a >= limits.num_actions) {
        return Err(ProtoError::Action { action, index, num_actions: limits.num_actions });
    }
    Ok(batch)
}

/// Decodes and checks a weights message for run `run_id`.
pub fn weights(bytes: &[u8], run_id: &str) -> Result<Weights, ProtoError> {
    let weights: Weights = decode(bytes, "weights")?;
    check_envelope(weights.protocol_version, &weights.run_id, run_id)?;
    let spec = weights.network.as_ref().ok_or_else(|| ProtoError::Network("missing".into()))?;
    if spec.obs_dim == 0 || spec.num_actions == 0 || spec.hidden.contains(&0) {
        return Err(ProtoError::Network(format!("{spec:?} has a zero size")));
    }
    Ok(weights)
}

/// Decodes and checks an episode-stats message.
pub fn episode_stats(bytes: &[u8], run_id: &str) -> Result<EpisodeStats, ProtoError> {
    let stats: EpisodeStats = decode(bytes, "episode stats")?;
    check_envelope(stats.protocol_version, &stats.run_id, run_id)?;
    let values = [
        stats.episode_return,
        stats.return_position,
        stats.return_upright,
        stats.distance,
        stats.duration,
        stats.speed,
    ];
    finite("episode stats", &values)?;
    if !stats.epsilon.is_finite() {
        return Err(ProtoError::NonFinite { field: "epsilon", index: 0 });
    }
    Ok(stats)
}

/// Decodes and checks an actor-status message.
pub fn actor_status(bytes: &[u8], run_id: &str) -> Result<ActorStatus, ProtoError> {
    let status: ActorStatus = decode(bytes, "actor status")?;
    check_envelope(status.protocol_version, &status.run_id, run_id)?;
    Ok(status)
}

/// Decodes and checks a control message.
pub fn control(bytes: &[u8], run_id: &str) -> Result<Control, ProtoError> {
    let control: Control = decode(bytes, "control")?;
    check_envelope(control.protocol_version, &control.run_id, run_id)?;
    Ok(control)
}

/// Decodes and checks run info (any run: an actor may adopt the run it is offered).
pub fn run_info(bytes: &[u8]) -> Result<RunInfo, ProtoError> {
    let info: RunInfo = decode(bytes, "run info")?;
    if info.protocol_version != PROTOCOL_VERSION {
        return Err(ProtoError::Version { got: info.protocol_version, expected: PROTOCOL_VERSION });
    }
    crate::keys::check_run_id(&info.run_id)?;
    Ok(info)
}

/// What a sequence number says about a batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SequenceCheck {
    /// The next batch, as expected.
    InOrder,
    /// Accepted, but `missing` batches before it never arrived.
    Gap { missing: u64 },
    /// The first batch of a new actor process.
    NewIncarnation,
}

/// Tracks each actor's last sequence number per process incarnation: rejects replays, counts
/// gaps.
#[derive(Debug, Default, Clone)]
pub struct SequenceTracker {
    last: HashMap<u32, (u64, u64)>,
}

impl SequenceTracker {
    pub fn check(&mut self, actor: u32, incarnation: u64, sequence: u64) -> Result<SequenceCheck, ProtoError> {
        match self.last.get(&actor).copied() {
            Some((inc, last)) if inc == incarnation => {
                if sequence <= last {
                    return Err(ProtoError::Replayed { actor, got: sequence, last });
                }
                self.last.insert(actor, (incarnation, sequence));
                Ok(if sequence == last + 1 {
                    SequenceCheck::InOrder
                } else {
                    SequenceCheck::Gap { missing: sequence - last - 1 }
                })
            }
            _ => {
                self.last.insert(actor, (incarnation, sequence));
                Ok(SequenceCheck::NewIncarnation)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> TransitionLimits {
        TransitionLimits { run_id: "r".into(), obs_dim: 2, num_actions: 4, max_batch: 8 }
    }

    fn batch(n: usize) -> TransitionBatch {
        TransitionBatch {
            protocol_version: PROTOCOL_VERSION,
            run_id: "r".into(),
            actor_id: 1,
            sequence: 0,
            incarnation: 7,
            obs_dim: 2,
            env_ids: vec![0; n],
            observations: vec![0.5; 2 * n],
            next_observations: vec![0.25; 2 * n],
            actions: vec![3; n],
            rewards: vec![1.0; n],
            terminated: vec![false; n],
            truncated: vec![false; n],
            priorities: vec![],
            weights_version: 1,
            physics_steps: n as u64,
            count: n as u32,
        }
    }

    fn check(b: &TransitionBatch) -> Result<TransitionBatch, ProtoError> {
        transition_batch(&b.encode_to_vec(), &limits())
    }

    #[test]
    fn a_valid_batch_round_trips() {
        let b = batch(3);
        assert_eq!(check(&b).unwrap(), b);
    }

    #[test]
    fn every_kind_of_bad_batch_is_rejected_by_name() {
        let mut cases: Vec<(TransitionBatch, &str)> = Vec::new();
        let mut b = batch(2);
        b.protocol_version = 99;
        cases.push((b, "version"));
        let mut b = batch(2);
        b.run_id = "other".into();
        cases.push((b, "run_id"));
        let mut b = batch(2);
        b.obs_dim = 3;
        cases.push((b, "obs_dim"));
        cases.push((batch(9), "batch_size"));
        let mut b = batch(2);
        b.observations.pop();
        cases.push((b, "length"));
        let mut b = batch(2);
        b.terminated.push(true);
        cases.push((b, "length"));
        let mut b = batch(2);
        b.next_observations[3] = f32::NAN;
        cases.push((b, "non_finite"));
        let mut b = batch(2);
        b.rewards[1] = f32::INFINITY;
        cases.push((b, "non_finite"));
        let mut b = batch(2);
        b.actions[1] = 4;
        cases.push((b, "action"));
        let mut b = batch(2);
        b.priorities = vec![1.0];
        cases.push((b, "length"));
        for (b, kind) in cases {
            assert_eq!(check(&b).unwrap_err().kind(), kind, "{b:?}");
        }
        let garbage = transition_batch(&[0xff, 0xff, 0xff, 0x01, 0x02], &limits()).unwrap_err();
        assert_eq!(garbage.kind(), "decode");
        // A message cut short anywhere is rejected, never taken for a shorter valid one.
        let encoded = batch(3).encode_to_vec();
        for cut in 1..encoded.len() {
            assert!(transition_batch(&encoded[..encoded.len() - cut], &limits()).is_err(), "cut by {cut} bytes");
        }
        let mut empty = batch(0);
        empty.count = 0;
        assert_eq!(check(&empty).unwrap_err().kind(), "length");
        let mut miscounted = batch(2);
        miscounted.count = 3;
        assert_eq!(check(&miscounted).unwrap_err().kind(), "length");
        let huge = vec![0u8; MAX_MESSAGE_BYTES + 1];
        assert_eq!(transition_batch(&huge, &limits()).unwrap_err().kind(), "oversize");
    }

    #[test]
    fn replays_are_rejected_and_gaps_counted() {
        let mut tracker = SequenceTracker::default();
        assert_eq!(tracker.check(1, 7, 0), Ok(SequenceCheck::NewIncarnation));
        assert_eq!(tracker.check(1, 7, 1), Ok(SequenceCheck::InOrder));
        assert_eq!(tracker.check(1, 7, 4), Ok(SequenceCheck::Gap { missing: 2 }));
        assert_eq!(tracker.check(1, 7, 4).unwrap_err().kind(), "replayed");
        assert_eq!(tracker.check(1, 7, 2).unwrap_err().kind(), "replayed");
        // A restarted actor starts again at 0 under a new incarnation.
        assert_eq!(tracker.check(1, 8, 0), Ok(SequenceCheck::NewIncarnation));
        assert_eq!(tracker.check(2, 7, 0), Ok(SequenceCheck::NewIncarnation));
    }

    #[test]
    fn weights_need_a_usable_network() {
        let mut w = Weights {
            protocol_version: PROTOCOL_VERSION,
            run_id: "r".into(),
            version: 1,
            learner_step: 0,
            network: Some(NetworkSpec { obs_dim: 40, hidden: vec![8], num_actions: 25, layer_norm: true }),
            safetensors: vec![],
        };
        assert!(weights(&w.encode_to_vec(), "r").is_ok());
        assert_eq!(weights(&w.encode_to_vec(), "s").unwrap_err().kind(), "run_id");
        w.network = None;
        assert_eq!(weights(&w.encode_to_vec(), "r").unwrap_err().kind(), "network");
    }
}
