//! Why a received message was refused, and how an error quotes what it received. Its own
//! module, below [`crate::keys`], [`crate::identity`] and [`crate::validate`], so each of them
//! reports through it without depending on another.

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
    #[error("field `{field}` holds {value} at index {index}, outside its physical range [{low}, {high}]")]
    OutOfRange { field: &'static str, index: usize, value: f64, low: f64, high: f64 },
    #[error("env id {env} at index {index} is outside 0..{envs_per_actor} (the run's crawlers per actor)")]
    EnvId { env: u32, index: usize, envs_per_actor: u32 },
    #[error("message on key `{key}` claims actor {payload}: a node may only put under its own id")]
    KeyMismatch { key: String, payload: u32 },
    #[error("actor {actor} holds no liveliness token in this run: its messages are not kept")]
    NotLive { actor: u32 },
    #[error("run info carries no actor settings")]
    MissingSettings,
    #[error("batch {sequence} from actor {actor} lies past the insert credit the learner granted it")]
    OverCredit { actor: u32, sequence: u64 },
    #[error("incarnation {incarnation} of actor {actor} was replaced or left: its batches are not taken again")]
    RetiredIncarnation { actor: u32, incarnation: u64 },
    #[error(
        "incarnation {incarnation} claims actor {actor} while another incarnation of it is sending: a new process takes an id over once the old one has been silent for 2 s"
    )]
    IncarnationBusy { actor: u32, incarnation: u64 },
    #[error("key `{key}` does not end in a node id written in decimal without sign or leading zeros")]
    NonCanonicalId { key: String },
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
            ProtoError::OutOfRange { .. } => "out_of_range",
            ProtoError::EnvId { .. } => "env_id",
            ProtoError::KeyMismatch { .. } => "key_mismatch",
            ProtoError::NotLive { .. } => "not_live",
            ProtoError::MissingSettings => "missing_settings",
            ProtoError::OverCredit { .. } => "over_credit",
            ProtoError::NonCanonicalId { .. } => "non_canonical_id",
            ProtoError::RetiredIncarnation { .. } => "retired_incarnation",
            ProtoError::IncarnationBusy { .. } => "incarnation_busy",
        }
    }
}

/// Longest piece of a received string an error quotes: errors reach logs, and a run id
/// from the network may be megabytes long.
pub const MAX_QUOTED_CHARS: usize = 80;

/// The first [`MAX_QUOTED_CHARS`] characters of `text`, with `…` when it was longer.
pub fn quoted_prefix(text: &str) -> String {
    let mut prefix: String = text.chars().take(MAX_QUOTED_CHARS).collect();
    if prefix.len() < text.len() {
        prefix.push('…');
    }
    prefix
}
