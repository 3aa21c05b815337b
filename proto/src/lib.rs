//! The contract between crawler actors and the learner: what crosses the wire.
//!
//! - [`messages`]: the prost messages, each carrying [`PROTOCOL_VERSION`] and the run id.
//! - [`keys`]: the zenoh key expressions, all under `crawler/<run>/…`.
//! - [`validate`]: checks of everything received, with typed errors; nothing here panics on
//!   input from the network.
//!
//! Architecture invariant: only types from this crate cross the wire, and every message a
//! node receives goes through [`validate`] before anything else looks at it.

pub mod keys;
pub mod messages;
pub mod validate;

pub use messages::*;
pub use validate::{ProtoError, SequenceTracker, TransitionLimits};

/// Version of the wire protocol. Bumped with any incompatible change to a message or key.
pub const PROTOCOL_VERSION: u32 = 1;

/// Largest encoded message a node accepts, in bytes. A transition batch of 1 024 transitions of
/// 40 values is about 340 kB; a weights message of the study's network about 780 kB.
pub const MAX_MESSAGE_BYTES: usize = 16 << 20;
