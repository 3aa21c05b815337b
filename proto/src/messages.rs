//! Wire messages (protobuf, via prost). Field numbers are part of the protocol: never reuse one.

/// Transitions from one actor, for the learner's replay.
///
/// Transition i observed `observations[i·obs_dim .. (i+1)·obs_dim]` in crawler `env_ids[i]`,
/// took `actions[i]`, got `rewards[i]` and reached `next_observations[i·obs_dim ..]`.
///
/// Its `prost::Message` implementation is written out in `transition_codec.rs`, so that packed
/// floats decode in one pass; each field's comment gives its tag and protobuf type, and a test
/// holds the encoding equal, byte for byte, to prost's derived one for the same schema.
#[derive(Clone, PartialEq, Default, Debug)]
pub struct TransitionBatch {
    /// 1, `uint32`.
    pub protocol_version: u32,
    /// 2, `string`.
    pub run_id: String,
    /// 3, `uint32`.
    pub actor_id: u32,
    /// 4, `uint64`. Increases by one per batch from each actor process; restarts at 0 with
    /// the process.
    pub sequence: u64,
    /// 5, `uint64`. A fresh random value per actor process, so a restarted actor's sequence is
    /// not taken for a replay of the old one's.
    pub incarnation: u64,
    /// 6, `uint32`.
    pub obs_dim: u32,
    /// 7, `repeated uint32` (packed).
    pub env_ids: Vec<u32>,
    /// 8, `repeated float` (packed).
    pub observations: Vec<f32>,
    /// 9, `repeated float` (packed).
    pub next_observations: Vec<f32>,
    /// 10, `repeated uint32` (packed).
    pub actions: Vec<u32>,
    /// 11, `repeated float` (packed).
    pub rewards: Vec<f32>,
    /// 12, `repeated bool` (packed).
    pub terminated: Vec<bool>,
    /// 13, `repeated bool` (packed).
    pub truncated: Vec<bool>,
    /// 14, `repeated float` (packed). Initial priorities for prioritised replay; empty for none.
    pub priorities: Vec<f32>,
    /// 15, `uint64`. Version of the weights that chose these actions.
    pub weights_version: u64,
    /// 16, `uint64`. Physics steps these transitions took (decisions × action repeat).
    pub physics_steps: u64,
    /// 17, `uint32`. The number of transitions. Encoded last, so a message cut short anywhere
    /// lacks it and fails validation (protobuf itself cannot tell a truncated message from a
    /// short one).
    pub count: u32,
}

impl TransitionBatch {
    pub fn len(&self) -> usize {
        self.actions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }

    /// The most bytes a batch of `transitions` transitions of `obs_dim` values each can take
    /// encoded: every varint at its widest, priorities present, the longest run id. A sender
    /// checks its settings against [`crate::MAX_MESSAGE_BYTES`] with it before a run starts;
    /// otherwise the receiver would refuse every batch it sent. Computed from the fields'
    /// wire types, because encoding a worst-case batch would allocate it; a test holds it
    /// equal to prost's own `encoded_len` of one.
    pub fn largest_encoded_len(transitions: usize, obs_dim: usize) -> usize {
        use prost::encoding::{encoded_len_varint, key_len};
        const VARINT32: usize = 5;
        const VARINT64: usize = 10;
        const FLOAT: usize = 4;
        const BOOL: usize = 1;
        let single = |tag: u32, bytes: usize| key_len(tag) + bytes;
        let length_delimited =
            |tag: u32, bytes: usize| (key_len(tag) + encoded_len_varint(bytes as u64)).saturating_add(bytes);
        // prost writes no packed field that holds no values.
        let packed = |tag: u32, bytes: usize| if bytes == 0 { 0 } else { length_delimited(tag, bytes) };
        let observation_bytes = transitions.saturating_mul(obs_dim).saturating_mul(FLOAT);
        [
            single(1, VARINT32),
            length_delimited(2, crate::keys::MAX_RUN_ID_BYTES),
            single(3, VARINT32),
            single(4, VARINT64),
            single(5, VARINT64),
            single(6, VARINT32),
            packed(7, transitions.saturating_mul(VARINT32)),
            packed(8, observation_bytes),
            packed(9, observation_bytes),
            packed(10, transitions.saturating_mul(VARINT32)),
            packed(11, transitions.saturating_mul(FLOAT)),
            packed(12, transitions.saturating_mul(BOOL)),
            packed(13, transitions.saturating_mul(BOOL)),
            packed(14, transitions.saturating_mul(FLOAT)),
            single(15, VARINT64),
            single(16, VARINT64),
            single(17, VARINT32),
        ]
        .iter()
        .fold(0usize, |total, bytes| total.saturating_add(*bytes))
    }
}

/// The Q-network's shape.
#[derive(Clone, PartialEq, Eq, prost::Message)]
pub struct NetworkSpec {
    #[prost(uint32, tag = "1")]
    pub obs_dim: u32,
    #[prost(uint32, repeated, tag = "2")]
    pub hidden: Vec<u32>,
    #[prost(uint32, tag = "3")]
    pub num_actions: u32,
    #[prost(bool, tag = "4")]
    pub layer_norm: bool,
}

/// Fresh weights from the learner.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Weights {
    #[prost(uint32, tag = "1")]
    pub protocol_version: u32,
    #[prost(string, tag = "2")]
    pub run_id: String,
    /// Increases with every publish, across learner restarts of the same run.
    #[prost(uint64, tag = "3")]
    pub version: u64,
    /// Gradient updates behind these weights.
    #[prost(uint64, tag = "4")]
    pub learner_step: u64,
    #[prost(message, optional, tag = "5")]
    pub network: Option<NetworkSpec>,
    /// The online network as a safetensors file, named like a PyTorch `nn.Sequential`.
    #[prost(bytes = "vec", tag = "6")]
    pub safetensors: Vec<u8>,
    /// Which learner process of the run published these: 0 for the first, one more with
    /// every resume. Weights are ordered by (`learner_session`, `version`), so a resumed
    /// learner's first publish is newer than anything its crashed predecessor sent, whatever
    /// settings it resumed with.
    #[prost(uint64, tag = "7")]
    pub learner_session: u64,
}

impl Weights {
    /// The order in which weights supersede one another.
    pub fn order(&self) -> (u64, u64) {
        (self.learner_session, self.version)
    }
}

/// What an actor needs to know about the run it joins; served by the learner.
#[derive(Clone, PartialEq, prost::Message)]
pub struct RunInfo {
    #[prost(uint32, tag = "1")]
    pub protocol_version: u32,
    #[prost(string, tag = "2")]
    pub run_id: String,
    /// The actors' settings: environment, exploration, batching.
    #[prost(message, optional, tag = "5")]
    pub settings: Option<ActorSettings>,
    /// For a query with the parameter `assign`: an actor id that no connected actor holds and
    /// that was not handed out in the last 30 s (actors started with `--id auto`).
    #[prost(uint32, optional, tag = "4")]
    pub assigned_actor_id: Option<u32>,
}

// Tag 3 of RunInfo (the settings as JSON, protocol 1) is retired: never reuse it.

/// The crawler environment's settings (the actor crate's `EnvConfig`, field for field).
#[derive(Clone, PartialEq, prost::Message)]
pub struct EnvSettings {
    #[prost(uint32, tag = "1")]
    pub action_levels: u32,
    #[prost(uint32, tag = "2")]
    pub action_repeat: u32,
    #[prost(enumeration = "Direction", tag = "3")]
    pub direction: i32,
    #[prost(float, tag = "4")]
    pub max_torque: f32,
    #[prost(float, tag = "5")]
    pub dt: f32,
    #[prost(uint32, tag = "6")]
    pub min_episode_steps: u32,
    #[prost(uint32, tag = "7")]
    pub max_episode_steps: u32,
    #[prost(float, tag = "8")]
    pub min_progress_per_step: f32,
    #[prost(bool, tag = "9")]
    pub sliding_base: bool,
    #[prost(uint32, tag = "10")]
    pub solver_iterations: u32,
    /// [low, high] in degrees.
    #[prost(float, repeated, tag = "11")]
    pub start_joint1_deg: Vec<f32>,
    #[prost(float, repeated, tag = "12")]
    pub start_joint2_deg: Vec<f32>,
    /// 0: rigid joint limits; > 0: soft ones with this time constant in seconds.
    #[prost(float, tag = "13")]
    pub joint_limit_timeconst: f32,
    /// Per-episode physics randomisation; absent: none.
    #[prost(message, optional, tag = "14")]
    pub randomization: Option<RandomizationSettings>,
    /// Tilt from upright, in degrees, past which an episode terminates; 180: never.
    #[prost(float, tag = "15")]
    pub max_tilt_deg: f32,
    /// Weight of the penalty on the base's rocking; 0: none (the study's reward).
    #[prost(float, tag = "16")]
    pub tilt_rate_penalty: f32,
    /// Distance in metres within which shapes get a contact; 0: from penetration on.
    #[prost(float, tag = "17")]
    pub contact_prediction: f32,
    /// Weight of the penalty on the base's hard landings, per N·s; 0: none (the study's reward).
    #[prost(float, tag = "18")]
    pub base_impact_penalty: f32,
    /// The base's contact force, in N, that the landing penalty lets through.
    #[prost(float, tag = "19")]
    pub base_impact_threshold: f32,
    /// Weight of the position reward; 1: the study's reward.
    #[prost(float, tag = "20")]
    pub position_reward_weight: f32,
    /// Observations the policy sees per decision, newest first; 1: the study's 40 values.
    #[prost(uint32, tag = "21")]
    pub observation_history: u32,
    /// Weight of the penalty on the joints' excursions past their limits, per rad·s; 0: none
    /// (the study's reward).
    #[prost(float, tag = "22")]
    pub joint_limit_penalty: f32,
    /// How the base–link 1 contact pair acts on the shoulder.
    #[prost(enumeration = "ShoulderPair", tag = "23")]
    pub shoulder_pair: i32,
}

/// Ranges drawn once per episode (`crawler_env::Randomization` documents each); every
/// `[low, high]` pair is two values.
#[derive(Clone, PartialEq, prost::Message)]
pub struct RandomizationSettings {
    #[prost(float, repeated, tag = "1")]
    pub friction_scale: Vec<f32>,
    #[prost(float, repeated, tag = "2")]
    pub mass_scale: Vec<f32>,
    #[prost(float, repeated, tag = "3")]
    pub motor_strength: Vec<f32>,
    #[prost(float, repeated, tag = "4")]
    pub joint_limit_timeconst: Vec<f32>,
    #[prost(uint32, repeated, tag = "5")]
    pub latency_steps: Vec<u32>,
    #[prost(float, tag = "6")]
    pub observation_noise: f32,
    #[prost(float, tag = "7")]
    pub push_interval_s: f32,
    #[prost(float, tag = "8")]
    pub push_roll_rate: f32,
    #[prost(float, repeated, tag = "9")]
    pub floor_contact_hz: Vec<f32>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum Direction {
    Forward = 0,
    Backward = 1,
}

/// How the base–link 1 contact pair acts on the shoulder (`crawler_env::ShoulderPair`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum ShoulderPair {
    SoftConstraint = 0,
    Viscous = 1,
}

/// Ape-X's fixed per-actor ε: actor i of `actors` uses base^(1 + alpha·i/(actors − 1)).
#[derive(Clone, PartialEq, prost::Message)]
pub struct EpsilonLadder {
    #[prost(double, tag = "1")]
    pub base: f64,
    #[prost(double, tag = "2")]
    pub alpha: f64,
    #[prost(uint32, tag = "3")]
    pub actors: u32,
}

/// The study's decaying ε: `start`, × `factor` every `every` decisions, floored at `min`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct EpsilonDecay {
    #[prost(double, tag = "1")]
    pub start: f64,
    #[prost(double, tag = "2")]
    pub factor: f64,
    #[prost(uint64, tag = "3")]
    pub every: u64,
    #[prost(double, tag = "4")]
    pub min: f64,
}

/// How actors explore; the tags are [`ActorSettings`]' field numbers.
#[derive(Clone, PartialEq, prost::Oneof)]
pub enum Exploration {
    #[prost(message, tag = "4")]
    Ladder(EpsilonLadder),
    #[prost(message, tag = "5")]
    Decay(EpsilonDecay),
}

/// What every actor of a run is told by the learner (the actor crate's `ActorSettings`).
#[derive(Clone, PartialEq, prost::Message)]
pub struct ActorSettings {
    #[prost(message, optional, tag = "1")]
    pub env: Option<EnvSettings>,
    #[prost(uint32, tag = "2")]
    pub envs_per_actor: u32,
    #[prost(uint32, tag = "3")]
    pub batch_transitions: u32,
    #[prost(oneof = "Exploration", tags = "4, 5")]
    pub exploration: Option<Exploration>,
    #[prost(uint64, tag = "6")]
    pub seed: u64,
    #[prost(double, tag = "7")]
    pub status_interval_s: f64,
}

/// One finished episode.
#[derive(Clone, PartialEq, prost::Message)]
pub struct EpisodeStats {
    #[prost(uint32, tag = "1")]
    pub protocol_version: u32,
    #[prost(string, tag = "2")]
    pub run_id: String,
    #[prost(uint32, tag = "3")]
    pub actor_id: u32,
    #[prost(double, tag = "4")]
    pub epsilon: f64,
    #[prost(float, tag = "5")]
    pub episode_return: f32,
    #[prost(float, tag = "6")]
    pub return_position: f32,
    #[prost(float, tag = "7")]
    pub return_upright: f32,
    /// The rocking penalty's part of the return (≤ 0; 0 where the env has none).
    #[prost(float, tag = "16")]
    pub return_tilt_rate: f32,
    /// The landing penalty's part of the return (≤ 0; 0 where the env has none).
    #[prost(float, tag = "17")]
    pub return_base_impact: f32,
    /// The joint-limit penalty's part of the return (≤ 0; 0 where the env has none).
    #[prost(float, tag = "18")]
    pub return_joint_limit: f32,
    /// Metres in the rewarded direction.
    #[prost(float, tag = "8")]
    pub distance: f32,
    /// Seconds of simulated time.
    #[prost(float, tag = "9")]
    pub duration: f32,
    /// m/s in the rewarded direction.
    #[prost(float, tag = "10")]
    pub speed: f32,
    #[prost(uint32, tag = "11")]
    pub flips: u32,
    #[prost(bool, tag = "12")]
    pub terminated: bool,
    #[prost(bool, tag = "13")]
    pub truncated: bool,
    /// From an evaluator (ε = 0), not a training actor.
    #[prost(bool, tag = "14")]
    pub evaluation: bool,
    #[prost(uint64, tag = "15")]
    pub weights_version: u64,
}

/// An actor's periodic report.
#[derive(Clone, PartialEq, prost::Message)]
pub struct ActorStatus {
    #[prost(uint32, tag = "1")]
    pub protocol_version: u32,
    #[prost(string, tag = "2")]
    pub run_id: String,
    #[prost(uint32, tag = "3")]
    pub actor_id: u32,
    #[prost(uint64, tag = "4")]
    pub weights_version: u64,
    /// Decisions taken since the process started, over all its crawlers.
    #[prost(uint64, tag = "5")]
    pub env_steps: u64,
    #[prost(uint64, tag = "6")]
    pub physics_steps: u64,
    #[prost(float, tag = "7")]
    pub env_steps_per_second: f32,
    #[prost(double, tag = "8")]
    pub epsilon: f64,
    #[prost(uint32, tag = "9")]
    pub num_envs: u32,
    #[prost(bool, tag = "10")]
    pub evaluator: bool,
    /// Share of the time since the previous report the simulation spent waiting to hand
    /// over a message: for the learner's insert credit, or for a slow link.
    #[prost(float, tag = "11")]
    pub waiting_fraction: f32,
}

/// The learner's grant to one actor: which transition batches it may publish next. Actors
/// publish a transition batch only within their credit; a learner that does not limit
/// inserts grants a window of `u32::MAX`.
///
/// Flow control as in TCP: an acknowledgement and a window. The learner has received the
/// batches of actor process `incarnation` up to `next_sequence` (exclusive) and admits
/// `window` more, so that one may publish sequence `s` while `s < next_sequence + window`.
/// A credit for another incarnation (the learner has not yet heard from this process)
/// admits one batch per credit received, which introduces the process to the learner.
#[derive(Clone, PartialEq, prost::Message)]
pub struct InsertCredit {
    #[prost(uint32, tag = "1")]
    pub protocol_version: u32,
    #[prost(string, tag = "2")]
    pub run_id: String,
    #[prost(uint32, tag = "3")]
    pub actor_id: u32,
    /// The actor process the learner last received from under this id; 0 for none.
    #[prost(uint64, tag = "4")]
    pub incarnation: u64,
    /// The sequence number the learner expects next from that process.
    #[prost(uint64, tag = "5")]
    pub next_sequence: u64,
    /// Batches admitted from `next_sequence` on.
    #[prost(uint32, tag = "6")]
    pub window: u32,
}

impl InsertCredit {
    /// Whether `incarnation` may publish batch `sequence` under this credit (the credit
    /// of another incarnation is handled by the caller: one batch per credit).
    pub fn admits(&self, incarnation: u64, sequence: u64) -> bool {
        self.incarnation == incarnation && sequence < self.next_sequence.saturating_add(u64::from(self.window))
    }
}

/// A command from the learner to every node of the run.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Control {
    #[prost(uint32, tag = "1")]
    pub protocol_version: u32,
    #[prost(string, tag = "2")]
    pub run_id: String,
    #[prost(enumeration = "Command", tag = "3")]
    pub command: i32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum Command {
    Unspecified = 0,
    /// The run is over: exit cleanly.
    Stop = 1,
}
