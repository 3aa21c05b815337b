//! Decoding and validation of everything received. Errors are typed and name the problem.

use std::collections::HashMap;

use prost::Message;

pub use crate::error::{MAX_QUOTED_CHARS, ProtoError, quoted_prefix};
use crate::messages::*;
use crate::{MAX_MESSAGE_BYTES, PROTOCOL_VERSION};

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
        return Err(ProtoError::RunId { got: quoted_prefix(run_id), expected: expected_run.to_string() });
    }
    Ok(())
}

/// Checks that the actor id in a message's key (`crawler/<run>/<kind>/<id>`) is the one in
/// its payload, so one actor cannot speak for another.
pub fn check_sender(key: &str, payload_actor: u32) -> Result<(), ProtoError> {
    if crate::keys::trailing_id(key)? == payload_actor {
        Ok(())
    } else {
        Err(ProtoError::KeyMismatch { key: quoted_prefix(key), payload: payload_actor })
    }
}

/// What a valid transition batch of this run looks like.
#[derive(Debug, Clone, PartialEq)]
pub struct TransitionLimits {
    pub run_id: String,
    pub obs_dim: u32,
    pub num_actions: u32,
    pub max_batch: usize,
    /// Crawlers per actor: every env id is below this.
    pub envs_per_actor: u32,
    /// The inclusive physical range `[low, high]` of each observation value, `obs_dim`
    /// entries (the environment documents them, with a margin).
    pub observation_range: Vec<[f32; 2]>,
    /// The largest |reward| one decision can earn.
    pub max_abs_reward: f32,
}

/// Largest priority a batch may propose for prioritised replay.
pub const MAX_PRIORITY: f32 = 1e6;

/// Every value inside `[low, high]`.
fn within(field: &'static str, values: &[f32], low: f32, high: f32) -> Result<(), ProtoError> {
    within_ranges(field, values, &[[low, high]])
}

/// Value i inside range `i mod ranges.len()` (one range per observation index); no ranges:
/// no bound. Public so that data read back from a file (a replay snapshot) is held to the
/// same bounds as data from the wire.
pub fn within_ranges(field: &'static str, values: &[f32], ranges: &[[f32; 2]]) -> Result<(), ProtoError> {
    if ranges.is_empty() {
        return Ok(());
    }
    // The common case first, as one branch-free pass per row of `ranges.len()` values that
    // the compiler vectorises (this check is the ingest path's largest cost of our own under
    // a flood, docs/PERFORMANCE.md "Scale"); NaN fails both comparisons. Only a batch that
    // fails is walked again to name the first value out of range.
    let inside = values.chunks(ranges.len()).all(|row| {
        row.iter().zip(ranges).fold(true, |ok, (value, [low, high])| ok & (*value >= *low) & (*value <= *high))
    });
    if inside {
        return Ok(());
    }
    for (index, (value, [low, high])) in values.iter().zip(ranges.iter().cycle()).enumerate() {
        if !(*low..=*high).contains(value) {
            return Err(ProtoError::OutOfRange {
                field,
                index,
                value: f64::from(*value),
                low: f64::from(*low),
                high: f64::from(*high),
            });
        }
    }
    Ok(())
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
        within("priorities", &batch.priorities, 0.0, MAX_PRIORITY)?;
    }
    finite("observations", &batch.observations)?;
    finite("next_observations", &batch.next_observations)?;
    finite("rewards", &batch.rewards)?;
    if let Some((index, &action)) = batch.actions.iter().enumerate().find(|(_, a)| **a >= limits.num_actions) {
        return Err(ProtoError::Action { action, index, num_actions: limits.num_actions });
    }
    if let Some((index, &env)) = batch.env_ids.iter().enumerate().find(|(_, e)| **e >= limits.envs_per_actor) {
        return Err(ProtoError::EnvId { env, index, envs_per_actor: limits.envs_per_actor });
    }
    // Finite is not enough: values near f32::MAX square to infinity in the loss.
    within_ranges("observations", &batch.observations, &limits.observation_range)?;
    within_ranges("next_observations", &batch.next_observations, &limits.observation_range)?;
    within("rewards", &batch.rewards, -limits.max_abs_reward, limits.max_abs_reward)?;
    Ok(batch)
}

/// Decodes and checks a weights message for run `run_id`.
pub fn weights(bytes: &[u8], run_id: &str) -> Result<Weights, ProtoError> {
    let weights: Weights = decode(bytes, "weights")?;
    check_envelope(weights.protocol_version, &weights.run_id, run_id)?;
    let spec = weights.network.as_ref().ok_or_else(|| ProtoError::Network("missing".into()))?;
    network_spec(spec)?;
    Ok(weights)
}

/// Scalar parameters of an MLP `obs_dim → hidden… → num_actions` (with LayerNorm's two
/// vectors per hidden layer when `layer_norm`), or None when the count overflows.
pub fn parameter_count(obs_dim: u64, hidden: &[u64], num_actions: u64, layer_norm: bool) -> Option<u64> {
    let mut total = 0u64;
    let mut inputs = obs_dim;
    for &width in hidden.iter().chain(std::iter::once(&num_actions)) {
        let linear = inputs.checked_mul(width)?.checked_add(width)?;
        total = total.checked_add(linear)?;
        inputs = width;
    }
    if layer_norm {
        for &width in hidden {
            total = total.checked_add(width.checked_mul(2)?)?;
        }
    }
    Some(total)
}

/// Checks a network's shape: positive sizes, at most [`crate::MAX_HIDDEN_LAYERS`] hidden
/// layers and [`crate::MAX_NETWORK_PARAMETERS`] parameters, so that no declared shape can
/// make a node allocate more than a message can carry.
pub fn network_spec(spec: &NetworkSpec) -> Result<(), ProtoError> {
    if spec.obs_dim == 0 || spec.num_actions == 0 || spec.hidden.contains(&0) {
        return Err(ProtoError::Network(format!("{spec:?} has a zero size")));
    }
    if spec.hidden.len() > crate::MAX_HIDDEN_LAYERS {
        return Err(ProtoError::Network(format!(
            "{} hidden layers, at most {} allowed",
            spec.hidden.len(),
            crate::MAX_HIDDEN_LAYERS
        )));
    }
    let hidden: Vec<u64> = spec.hidden.iter().map(|&h| u64::from(h)).collect();
    let count = parameter_count(u64::from(spec.obs_dim), &hidden, u64::from(spec.num_actions), spec.layer_norm);
    match count {
        Some(count) if count <= crate::MAX_NETWORK_PARAMETERS as u64 => Ok(()),
        _ => Err(ProtoError::Network(format!(
            "{} parameters, at most {} allowed",
            count.map_or_else(|| "more than 2^64".to_string(), |c| c.to_string()),
            crate::MAX_NETWORK_PARAMETERS
        ))),
    }
}

/// Physical limits of the numbers in episode stats and status reports: far beyond anything a
/// crawler does, tight enough that no value can overflow a sum or a moving average.
pub mod report_limits {
    /// m/s: the crawler's best gait is about 1 m/s.
    pub const MAX_ABS_SPEED: f32 = 100.0;
    /// m in one episode.
    pub const MAX_ABS_DISTANCE: f32 = 1e5;
    /// s of simulated time in one episode (the longest is 500 × 100 000 × 0.02 s).
    pub const MAX_DURATION: f32 = 1e6;
    /// |return| of one episode: at most 11 per physics step (5.5 with the largest position
    /// reward weight, 10, plus a landing charge of at most 5 and a joint-limit charge of at
    /// most 0.5), so at most 5.5e8 over the longest episode.
    pub const MAX_ABS_RETURN: f32 = 1e9;
    /// Decisions per second one actor can report.
    pub const MAX_STEPS_PER_SECOND: f32 = 1e8;
    /// Crawlers per actor.
    pub const MAX_ENVS: u32 = 1024;
}

fn probability(field: &'static str, value: f64) -> Result<(), ProtoError> {
    if (0.0..=1.0).contains(&value) {
        Ok(())
    } else if value.is_finite() {
        Err(ProtoError::OutOfRange { field, index: 0, value, low: 0.0, high: 1.0 })
    } else {
        Err(ProtoError::NonFinite { field, index: 0 })
    }
}

/// Decodes and checks an episode-stats message.
pub fn episode_stats(bytes: &[u8], run_id: &str) -> Result<EpisodeStats, ProtoError> {
    let stats: EpisodeStats = decode(bytes, "episode stats")?;
    check_envelope(stats.protocol_version, &stats.run_id, run_id)?;
    let values = [
        stats.episode_return,
        stats.return_position,
        stats.return_upright,
        stats.return_tilt_rate,
        stats.return_base_impact,
        stats.return_joint_limit,
        stats.distance,
        stats.duration,
        stats.speed,
    ];
    finite("episode stats", &values)?;
    probability("epsilon", stats.epsilon)?;
    use report_limits::*;
    let returns = [
        stats.episode_return,
        stats.return_position,
        stats.return_upright,
        stats.return_tilt_rate,
        stats.return_base_impact,
        stats.return_joint_limit,
    ];
    within("episode returns", &returns, -MAX_ABS_RETURN, MAX_ABS_RETURN)?;
    within("distance", &[stats.distance], -MAX_ABS_DISTANCE, MAX_ABS_DISTANCE)?;
    within("duration", &[stats.duration], 0.0, MAX_DURATION)?;
    within("speed", &[stats.speed], -MAX_ABS_SPEED, MAX_ABS_SPEED)?;
    Ok(stats)
}

/// Decodes and checks an actor-status message.
pub fn actor_status(bytes: &[u8], run_id: &str) -> Result<ActorStatus, ProtoError> {
    let status: ActorStatus = decode(bytes, "actor status")?;
    check_envelope(status.protocol_version, &status.run_id, run_id)?;
    probability("epsilon", status.epsilon)?;
    use report_limits::*;
    finite("env_steps_per_second", &[status.env_steps_per_second])?;
    within("env_steps_per_second", &[status.env_steps_per_second], 0.0, MAX_STEPS_PER_SECOND)?;
    probability("waiting_fraction", f64::from(status.waiting_fraction))?;
    if status.num_envs > MAX_ENVS {
        return Err(ProtoError::OutOfRange {
            field: "num_envs",
            index: 0,
            value: f64::from(status.num_envs),
            low: 0.0,
            high: f64::from(MAX_ENVS),
        });
    }
    Ok(status)
}

/// Decodes and checks an insert credit received on `key` (`crawler/<run>/credit/<id>`): of
/// this run, and for the actor the key names.
pub fn insert_credit(bytes: &[u8], run_id: &str, key: &str) -> Result<InsertCredit, ProtoError> {
    let credit: InsertCredit = decode(bytes, "insert credit")?;
    check_envelope(credit.protocol_version, &credit.run_id, run_id)?;
    check_sender(key, credit.actor_id)?;
    Ok(credit)
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
    if info.settings.as_ref().is_none_or(|s| s.env.is_none() || s.exploration.is_none()) {
        return Err(ProtoError::MissingSettings);
    }
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

/// Incarnations remembered as retired, across all actors: enough for every actor of a large
/// run to restart many times, small enough to bound the table.
pub const RETIRED_INCARNATIONS: usize = 4096;

/// How long an actor's incarnation must have sent nothing before a new one takes its id over:
/// longer than any pause of a working actor, shorter than a process restart.
pub const INCARNATION_HANDOVER: std::time::Duration = std::time::Duration::from_secs(2);

/// Tracks each actor's last sequence number per process incarnation: rejects replays, counts
/// gaps. A new incarnation takes over a live id only once the current one has been silent for
/// [`INCARNATION_HANDOVER`] (a restarted process), so a sender that announces itself under a
/// working actor's id takes nothing over. An incarnation that was replaced, or whose actor
/// left, is retired and refused from then on, so recorded batches of an earlier process cannot
/// be played back.
#[derive(Debug, Default, Clone)]
pub struct SequenceTracker {
    last: HashMap<u32, Last>,
    retired: std::collections::HashSet<(u32, u64)>,
    retired_order: std::collections::VecDeque<(u32, u64)>,
}

/// An actor's current incarnation, its last accepted sequence number and when it came.
#[derive(Debug, Clone, Copy)]
struct Last {
    incarnation: u64,
    sequence: u64,
    at: std::time::Instant,
}

impl SequenceTracker {
    /// Forgets an actor that left, so the tracker holds only live actors; its incarnation
    /// is retired.
    pub fn forget(&mut self, actor: u32) {
        if let Some(last) = self.last.remove(&actor) {
            self.retire(actor, last.incarnation);
        }
    }

    fn retire(&mut self, actor: u32, incarnation: u64) {
        if self.retired.insert((actor, incarnation)) {
            self.retired_order.push_back((actor, incarnation));
            if self.retired_order.len() > RETIRED_INCARNATIONS
                && let Some(oldest) = self.retired_order.pop_front()
            {
                self.retired.remove(&oldest);
            }
        }
    }

    /// The process incarnation and last accepted sequence number of `actor`, if any.
    pub fn last(&self, actor: u32) -> Option<(u64, u64)> {
        self.last.get(&actor).map(|last| (last.incarnation, last.sequence))
    }

    /// Actors tracked.
    pub fn len(&self) -> usize {
        self.last.len()
    }

    pub fn is_empty(&self) -> bool {
        self.last.is_empty()
    }

    /// Incarnations remembered as retired (at most [`RETIRED_INCARNATIONS`]).
    pub fn retired(&self) -> usize {
        self.retired.len()
    }

    /// Refuses an incarnation that was retired.
    pub fn refuse_retired(&self, actor: u32, incarnation: u64) -> Result<(), ProtoError> {
        if self.retired.contains(&(actor, incarnation)) {
            Err(ProtoError::RetiredIncarnation { actor, incarnation })
        } else {
            Ok(())
        }
    }

    /// Checks batch `sequence` of `incarnation` from `actor`, arriving at `now`, and records it
    /// when it is taken.
    pub fn check(
        &mut self,
        actor: u32,
        incarnation: u64,
        sequence: u64,
        now: std::time::Instant,
    ) -> Result<SequenceCheck, ProtoError> {
        self.refuse_retired(actor, incarnation)?;
        let taken = Last { incarnation, sequence, at: now };
        match self.last.get(&actor).copied() {
            Some(last) if last.incarnation == incarnation => {
                if sequence <= last.sequence {
                    return Err(ProtoError::Replayed { actor, got: sequence, last: last.sequence });
                }
                self.last.insert(actor, taken);
                Ok(if sequence == last.sequence + 1 {
                    SequenceCheck::InOrder
                } else {
                    SequenceCheck::Gap { missing: sequence - last.sequence - 1 }
                })
            }
            Some(last) => {
                if now.saturating_duration_since(last.at) < INCARNATION_HANDOVER {
                    return Err(ProtoError::IncarnationBusy { actor, incarnation });
                }
                self.retire(actor, last.incarnation);
                self.last.insert(actor, taken);
                Ok(SequenceCheck::NewIncarnation)
            }
            None => {
                self.last.insert(actor, taken);
                Ok(SequenceCheck::NewIncarnation)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> TransitionLimits {
        TransitionLimits {
            run_id: "r".into(),
            obs_dim: 2,
            num_actions: 4,
            max_batch: 8,
            envs_per_actor: 2,
            observation_range: vec![[-1.0, 1.0], [0.0, 10.0]],
            max_abs_reward: 10.0,
        }
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
        // Finite but outside the physical ranges: the values that overflow a loss.
        let mut b = batch(2);
        b.observations[1] = 3e38;
        cases.push((b, "out_of_range"));
        let mut b = batch(2);
        b.next_observations[0] = -1.5;
        cases.push((b, "out_of_range"));
        let mut b = batch(2);
        b.rewards[0] = -11.0;
        cases.push((b, "out_of_range"));
        let mut b = batch(2);
        b.priorities = vec![1.0, -1.0];
        cases.push((b, "out_of_range"));
        let mut b = batch(2);
        b.env_ids[1] = 2;
        cases.push((b, "env_id"));
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
        let t0 = std::time::Instant::now();
        assert_eq!(tracker.check(1, 7, 0, t0), Ok(SequenceCheck::NewIncarnation));
        assert_eq!(tracker.check(1, 7, 1, t0), Ok(SequenceCheck::InOrder));
        assert_eq!(tracker.check(1, 7, 4, t0), Ok(SequenceCheck::Gap { missing: 2 }));
        assert_eq!(tracker.check(1, 7, 4, t0).unwrap_err().kind(), "replayed");
        assert_eq!(tracker.check(1, 7, 2, t0).unwrap_err().kind(), "replayed");
        // A restarted actor starts again at 0 under a new incarnation, once the old one is quiet.
        assert_eq!(tracker.check(1, 8, 0, t0).unwrap_err().kind(), "incarnation_busy");
        assert_eq!(tracker.check(1, 8, 0, t0 + INCARNATION_HANDOVER), Ok(SequenceCheck::NewIncarnation));
        assert_eq!(tracker.check(2, 7, 0, t0), Ok(SequenceCheck::NewIncarnation));
    }

    #[test]
    fn a_replaced_or_departed_incarnation_never_comes_back() {
        let mut tracker = SequenceTracker::default();
        let t0 = std::time::Instant::now();
        let later = t0 + INCARNATION_HANDOVER;
        assert!(tracker.check(1, 7, 5, t0).is_ok());
        // Incarnation 9 takes actor 1 over after 7 went quiet; 7's batches played back then
        // are refused, whatever their sequence.
        assert_eq!(tracker.check(1, 9, 0, later), Ok(SequenceCheck::NewIncarnation));
        for sequence in [0, 3, 6, 1000] {
            assert_eq!(tracker.check(1, 7, sequence, later).unwrap_err().kind(), "retired_incarnation");
        }
        // An actor that leaves retires its incarnation too.
        tracker.forget(1);
        assert_eq!(tracker.check(1, 9, 1, later).unwrap_err().kind(), "retired_incarnation");
        assert_eq!(tracker.check(1, 11, 0, later), Ok(SequenceCheck::NewIncarnation));
        // The retired set is bounded: the oldest are forgotten first.
        let mut at = later;
        for incarnation in 100..100 + RETIRED_INCARNATIONS as u64 + 10 {
            at += INCARNATION_HANDOVER;
            tracker.check(2, incarnation, 0, at).unwrap();
        }
        assert_eq!(tracker.retired(), RETIRED_INCARNATIONS);
        assert!(tracker.refuse_retired(1, 7).is_ok(), "the oldest retirement was forgotten");
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
            learner_session: 0,
        };
        assert!(weights(&w.encode_to_vec(), "r").is_ok());
        assert_eq!(weights(&w.encode_to_vec(), "s").unwrap_err().kind(), "run_id");
        // Shapes that would need more memory than a message can carry.
        for hidden in [vec![65_536; 1000], vec![4096, 4096], vec![u32::MAX; 3], vec![1; 17]] {
            w.network = Some(NetworkSpec { obs_dim: 40, hidden: hidden.clone(), num_actions: 25, layer_norm: true });
            let error = weights(&w.encode_to_vec(), "r").unwrap_err();
            assert_eq!(error.kind(), "network", "{hidden:?}");
        }
        w.network = None;
        assert_eq!(weights(&w.encode_to_vec(), "r").unwrap_err().kind(), "network");
    }

    #[test]
    fn parameter_count_matches_the_study_network_and_never_overflows() {
        let study = 40 * 512 + 512 * 3 + 512 * 256 + 256 * 3 + 256 * 128 + 128 * 3 + 128 * 25 + 25;
        assert_eq!(parameter_count(40, &[512, 256, 128], 25, true), Some(study));
        assert_eq!(parameter_count(40, &[u64::MAX, 2], 25, true), None);
    }

    #[test]
    fn reports_with_impossible_numbers_are_rejected_by_name() {
        let status = |epsilon: f64, rate: f32| ActorStatus {
            protocol_version: PROTOCOL_VERSION,
            run_id: "r".into(),
            actor_id: 1,
            epsilon,
            env_steps_per_second: rate,
            num_envs: 8,
            ..Default::default()
        };
        assert!(actor_status(&status(0.4, 100.0).encode_to_vec(), "r").is_ok());
        assert_eq!(actor_status(&status(f64::NAN, 1.0).encode_to_vec(), "r").unwrap_err().kind(), "non_finite");
        assert_eq!(actor_status(&status(1.5, 1.0).encode_to_vec(), "r").unwrap_err().kind(), "out_of_range");
        assert_eq!(actor_status(&status(0.1, -1.0).encode_to_vec(), "r").unwrap_err().kind(), "out_of_range");
        let episode = |speed: f32, epsilon: f64| EpisodeStats {
            protocol_version: PROTOCOL_VERSION,
            run_id: "r".into(),
            speed,
            epsilon,
            duration: 20.0,
            ..Default::default()
        };
        assert!(episode_stats(&episode(0.9, 0.0).encode_to_vec(), "r").is_ok());
        assert_eq!(episode_stats(&episode(3e38, 0.0).encode_to_vec(), "r").unwrap_err().kind(), "out_of_range");
        assert_eq!(episode_stats(&episode(0.5, f64::NAN).encode_to_vec(), "r").unwrap_err().kind(), "non_finite");
        // Each part of the return is checked, the joint-limit charge's too.
        let limit_charge = |value: f32| EpisodeStats { return_joint_limit: value, ..episode(0.5, 0.0) };
        assert!(episode_stats(&limit_charge(-12.0).encode_to_vec(), "r").is_ok());
        assert_eq!(episode_stats(&limit_charge(f32::NAN).encode_to_vec(), "r").unwrap_err().kind(), "non_finite");
        assert_eq!(episode_stats(&limit_charge(-3e9).encode_to_vec(), "r").unwrap_err().kind(), "out_of_range");
    }

    #[test]
    fn errors_quote_at_most_a_prefix_of_what_arrived() {
        let huge = "x".repeat(1 << 20);
        let error = check_envelope(PROTOCOL_VERSION, &huge, "r").unwrap_err().to_string();
        assert!(error.len() < 200, "{} bytes", error.len());
        let error = crate::keys::check_run_id(&huge).unwrap_err().to_string();
        assert!(error.len() < 200, "{} bytes", error.len());
    }

    #[test]
    fn a_node_speaks_only_for_its_own_id() {
        assert!(check_sender("crawler/r/transitions/3", 3).is_ok());
        assert_eq!(check_sender("crawler/r/transitions/3", 4).unwrap_err().kind(), "key_mismatch");
        assert_eq!(check_sender("crawler/r/transitions/x", 0).unwrap_err().kind(), "non_canonical_id");
        assert_eq!(check_sender("crawler/r/transitions/03", 3).unwrap_err().kind(), "non_canonical_id");
    }

    #[test]
    fn run_info_without_settings_is_refused() {
        let info = RunInfo { protocol_version: PROTOCOL_VERSION, run_id: "r".into(), ..Default::default() };
        assert_eq!(run_info(&info.encode_to_vec()).unwrap_err().kind(), "missing_settings");
    }

    #[test]
    fn an_insert_credit_is_for_its_run_and_the_actor_its_key_names() {
        let credit = InsertCredit {
            protocol_version: PROTOCOL_VERSION,
            run_id: "r".into(),
            actor_id: 2,
            incarnation: 77,
            next_sequence: 10,
            window: 3,
        };
        let bytes = credit.encode_to_vec();
        assert_eq!(insert_credit(&bytes, "r", "crawler/r/credit/2").unwrap(), credit);
        assert_eq!(insert_credit(&bytes, "r", "crawler/r/credit/3").unwrap_err().kind(), "key_mismatch");
        assert_eq!(insert_credit(&bytes, "other", "crawler/r/credit/2").unwrap_err().kind(), "run_id");
        assert_eq!(insert_credit(&bytes[..bytes.len() - 1], "r", "crawler/r/credit/2").unwrap_err().kind(), "decode");
        // The window counts from the acknowledged sequence, for that process only.
        assert!(credit.admits(77, 12) && !credit.admits(77, 13) && !credit.admits(78, 10));
        let closed = InsertCredit { window: 0, ..credit.clone() };
        assert!(!closed.admits(77, 10));
        let huge = InsertCredit { next_sequence: u64::MAX, window: u32::MAX, ..credit };
        assert!(huge.admits(77, u64::MAX - 1), "no overflow at the top of the range");
    }
}
