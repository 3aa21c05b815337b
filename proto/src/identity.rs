//! Who a certificate speaks for. Under mutual TLS each actor and evaluator holds a
//! certificate whose subject common name (CN) names its role and its id, and the learner's
//! router lets that certificate put, subscribe and declare tokens only under that id's keys
//! ([`crate::keys`]). `deploy/make-tls.sh` issues these names; the actor reads its own with
//! `--id auto`; the learner's access-control policy lists them.
//!
//! | CN                          | who                    | ids                              |
//! |-----------------------------|------------------------|----------------------------------|
//! | `crawler-actor-<id>`        | actor `<id>`           | [`CERTIFIED_ACTOR_IDS`]          |
//! | `crawler-evaluator-<id>`    | evaluator `<id>`       | [`CERTIFIED_EVALUATOR_IDS`]      |
//! | `crawler-observer`          | read-only monitors     | none                             |
//!
//! Actors and evaluators share the id space of the `stats/<id>` and `status/<id>` keys, so
//! their certified ids never overlap: an evaluator's certificate can never speak for an actor.
//! The ranges are fixed (not a learner setting) because a certificate outlives any one run's
//! configuration. Ids are written in their one canonical decimal form, as on the wire.

use std::ops::Range;

/// Ids an actor certificate may name: `crawler-actor-0` … `crawler-actor-999`.
pub const CERTIFIED_ACTOR_IDS: Range<u32> = 0..1000;
/// Ids an evaluator certificate may name: `crawler-evaluator-1000` … `crawler-evaluator-1999`.
pub const CERTIFIED_EVALUATOR_IDS: Range<u32> = 1000..2000;
// An evaluator's certificate must never name an actor's id (they share `stats/<id>`).
const _: () = assert!(CERTIFIED_ACTOR_IDS.end <= CERTIFIED_EVALUATOR_IDS.start);

const ACTOR_PREFIX: &str = "crawler-actor-";
const EVALUATOR_PREFIX: &str = "crawler-evaluator-";
/// The CN of read-only monitor certificates (dashboards, the security tests' probe).
pub const OBSERVER_COMMON_NAME: &str = "crawler-observer";

/// The role and id a certificate's common name grants.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Certified {
    Actor(u32),
    Evaluator(u32),
    Observer,
}

impl Certified {
    /// The common name that grants this identity.
    pub fn common_name(self) -> String {
        match self {
            Self::Actor(id) => format!("{ACTOR_PREFIX}{id}"),
            Self::Evaluator(id) => format!("{EVALUATOR_PREFIX}{id}"),
            Self::Observer => OBSERVER_COMMON_NAME.to_string(),
        }
    }

    /// What common name `cn` grants, or why it grants nothing.
    pub fn from_common_name(cn: &str) -> Result<Self, IdentityError> {
        if cn == OBSERVER_COMMON_NAME {
            return Ok(Self::Observer);
        }
        let (text, range, make): (&str, Range<u32>, fn(u32) -> Self) = if let Some(text) = cn.strip_prefix(ACTOR_PREFIX)
        {
            (text, CERTIFIED_ACTOR_IDS, Self::Actor)
        } else if let Some(text) = cn.strip_prefix(EVALUATOR_PREFIX) {
            (text, CERTIFIED_EVALUATOR_IDS, Self::Evaluator)
        } else {
            return Err(IdentityError::UnknownRole { cn: crate::error::quoted_prefix(cn) });
        };
        match crate::keys::canonical_id(text) {
            Some(id) if range.contains(&id) => Ok(make(id)),
            _ => Err(IdentityError::BadId {
                cn: crate::error::quoted_prefix(cn),
                first: range.start,
                last: range.end - 1,
            }),
        }
    }
}

/// A common name that grants no identity.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IdentityError {
    #[error(
        "certificate common name {cn:?} names no role: expected crawler-actor-<id>, crawler-evaluator-<id> or \
         crawler-observer (deploy/make-tls.sh issues them)"
    )]
    UnknownRole { cn: String },
    #[error("certificate common name {cn:?} has no valid id: expected a canonical decimal in {first}..={last}")]
    BadId { cn: String, first: u32, last: u32 },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_only_canonical_ids_in_range_are_granted() {
        for identity in [
            Certified::Actor(0),
            Certified::Actor(999),
            Certified::Evaluator(1000),
            Certified::Evaluator(1999),
            Certified::Observer,
        ] {
            assert_eq!(Certified::from_common_name(&identity.common_name()), Ok(identity));
        }
        for bad in [
            "crawler-actor-01",
            "crawler-actor-+1",
            "crawler-actor-1000",
            "crawler-actor-",
            "crawler-evaluator-999",
            "crawler-evaluator-2000",
            "crawler-evaluator-01000",
        ] {
            assert!(matches!(Certified::from_common_name(bad), Err(IdentityError::BadId { .. })), "{bad}");
        }
        for bad in ["crawler-actor", "crawler CA", "localhost", "", "crawler-observer-1"] {
            assert!(matches!(Certified::from_common_name(bad), Err(IdentityError::UnknownRole { .. })), "{bad}");
        }
    }
}
