//! The contract between crawler actors and the learner: what crosses the wire.
//!
//! - [`messages`]: the prost messages, each carrying [`PROTOCOL_VERSION`] and the run id.
//! - [`keys`]: the zenoh key expressions, all under `crawler/<run>/…`.
//! - [`identity`]: the certificate common names that say whose keys a session may use.
//! - [`validate`]: checks of everything received, with typed errors; nothing here panics on
//!   input from the network.
//!
//! Architecture invariant: only types from this crate cross the wire, and every message a
//! node receives goes through [`validate`] before anything else looks at it.

mod error;
pub mod identity;
pub mod keys;
pub mod messages;
mod transition_codec;
pub mod validate;

pub use error::ProtoError;
pub use messages::*;
pub use validate::{SequenceTracker, TransitionLimits};

/// Version of the wire protocol. Bumped with any incompatible change to a message or key.
/// 2: run settings as a proto message (was JSON); weights ordered by learner session.
/// 3: the env settings carry the joint limits' softness (`EnvSettings.joint_limit_timeconst`)
///    and the physics randomisation; an older actor, which would silently simulate other
///    physics, is refused.
/// 4: the env settings carry the tilt that ends an episode (`EnvSettings.max_tilt_deg`); an
///    older actor would read it as absent and never end an episode on a fall.
/// 5: the env settings carry the rocking penalty (`EnvSettings.tilt_rate_penalty`) and episode
///    stats its part of the return; an older actor would train on another reward.
/// 6: the physics randomisation carries roll pushes (`RandomizationSettings.push_interval_s`,
///    `push_roll_rate`), and the joint limits follow MuJoCo's formula; an older actor would
///    simulate other physics.
/// 7: the env settings carry the contact prediction distance
///    (`EnvSettings.contact_prediction`), whose default changed from rapier's 0.02 m to 0; an
///    older actor would simulate other physics.
/// 8: the env settings carry the penalty on the base's hard landings
///    (`EnvSettings.base_impact_penalty`, `base_impact_threshold`) and episode stats its part
///    of the return; an older actor would train on another reward.
/// 9: the env settings carry the position reward's weight (`EnvSettings.position_reward_weight`);
///    an older actor would train on the study's weight whatever the learner's config says.
/// 10: the physics randomisation carries the floor contacts' stiffness
///    (`RandomizationSettings.floor_contact_hz`); an older actor would simulate other physics.
/// 11: the env settings carry how many decisions' observations the policy sees
///    (`EnvSettings.observation_history`); an older actor would send 40-value observations to
///    a learner whose network takes more.
/// 12: the env settings carry the penalty on the joints' excursions past their limits
///    (`EnvSettings.joint_limit_penalty`) and episode stats its part of the return
///    (`EpisodeStats.return_joint_limit`); an older actor would train on another reward.
/// 13: the env settings carry how the base–link 1 contact pair acts on the shoulder
///    (`EnvSettings.shoulder_pair`); an older actor would simulate the viscous stand-in
///    whatever the learner's config says.
/// 14: actors publish transitions only within the learner's insert credit (`InsertCredit` on
///    `crawler/<run>/credit/<id>`) and report the time they waited
///    (`ActorStatus.waiting_fraction`); an older actor would ignore the learner's limit.
pub const PROTOCOL_VERSION: u32 = 14;

/// Largest encoded message a node accepts, in bytes. The largest legal messages: the weights
/// of a network of [`MAX_NETWORK_PARAMETERS`] (about 3.6 MB; the study's network is 780 kB)
/// and a batch of transitions of 40·h values for a policy that sees h observations: 4096 of
/// 40 values take about 1.4 MB, but not every batch size fits at every h, so senders check
/// theirs with [`TransitionBatch::largest_encoded_len`].
pub const MAX_MESSAGE_BYTES: usize = 4 << 20;

/// What zenoh itself buffers of one incoming message before dropping it
/// (`transport/link/rx/max_message_size`, 1 GiB by default). Twice [`MAX_MESSAGE_BYTES`]: a
/// message a little over the protocol's limit still reaches validation, where it is named and
/// counted, while a huge one is dropped by zenoh before it costs more than this in memory.
pub const TRANSPORT_MAX_MESSAGE_BYTES: usize = 2 * MAX_MESSAGE_BYTES;

/// Most transitions in one batch.
pub const MAX_BATCH_TRANSITIONS: usize = 4096;

/// Most scalar parameters a Q-network may have: its weights must fit in one message.
pub const MAX_NETWORK_PARAMETERS: usize = 900_000;

/// Most hidden layers a Q-network may have.
pub const MAX_HIDDEN_LAYERS: usize = 16;
