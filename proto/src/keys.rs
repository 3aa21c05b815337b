//! zenoh key expressions. Everything of run `<run>` lives under `crawler/<run>/`.
//!
//! | key                               | who puts        | what                      |
//! |-----------------------------------|-----------------|---------------------------|
//! | `crawler/<run>/transitions/<id>`  | actor `<id>`    | [`crate::TransitionBatch`]|
//! | `crawler/<run>/stats/<id>`        | actor/evaluator | [`crate::EpisodeStats`]   |
//! | `crawler/<run>/status/<id>`       | actor/evaluator | [`crate::ActorStatus`]    |
//! | `crawler/<run>/weights`           | learner only    | [`crate::Weights`] (also a queryable) |
//! | `crawler/<run>/info`              | learner (queryable) | [`crate::RunInfo`]    |
//! | `crawler/<run>/control`           | learner only    | [`crate::Control`]        |
//! | `crawler/<run>/credit/<id>`       | learner only    | [`crate::InsertCredit`] for actor `<id>` |
//! | `crawler/<run>/alive/actor/<id>`  | liveliness token of actor `<id>` |          |
//! | `crawler/<run>/alive/evaluator/<id>` | liveliness token of evaluator `<id>` |      |
//! | `crawler/<run>/alive/learner`     | liveliness token of the learner  |          |

use crate::error::ProtoError;

pub const ROOT: &str = "crawler";

/// Longest run id, in bytes (all its characters are ASCII).
pub const MAX_RUN_ID_BYTES: usize = 64;

/// Checks a run id: 1–64 characters of `[A-Za-z0-9_-]`, so it is one key-expression chunk.
pub fn check_run_id(run: &str) -> Result<(), ProtoError> {
    let ok = !run.is_empty()
        && run.len() <= MAX_RUN_ID_BYTES
        && run.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if ok { Ok(()) } else { Err(ProtoError::BadRunId(crate::error::quoted_prefix(run))) }
}

pub fn transitions(run: &str, actor: u32) -> String {
    format!("{ROOT}/{run}/transitions/{actor}")
}

pub fn all_transitions(run: &str) -> String {
    format!("{ROOT}/{run}/transitions/*")
}

pub fn stats(run: &str, actor: u32) -> String {
    format!("{ROOT}/{run}/stats/{actor}")
}

pub fn all_stats(run: &str) -> String {
    format!("{ROOT}/{run}/stats/*")
}

pub fn status(run: &str, actor: u32) -> String {
    format!("{ROOT}/{run}/status/{actor}")
}

pub fn all_status(run: &str) -> String {
    format!("{ROOT}/{run}/status/*")
}

pub fn weights(run: &str) -> String {
    format!("{ROOT}/{run}/weights")
}

/// Weights of any run: what an actor that was not told its run asks for.
pub fn any_weights() -> String {
    format!("{ROOT}/*/weights")
}

pub fn info(run: &str) -> String {
    format!("{ROOT}/{run}/info")
}

/// The selector parameter with which an actor asks the run-info queryable for an id.
pub const ASSIGN_PARAMETER: &str = "assign";

pub fn control(run: &str) -> String {
    format!("{ROOT}/{run}/control")
}

pub fn credit(run: &str, actor: u32) -> String {
    format!("{ROOT}/{run}/credit/{actor}")
}

pub fn all_credits(run: &str) -> String {
    format!("{ROOT}/{run}/credit/*")
}

pub fn alive_actor(run: &str, actor: u32) -> String {
    format!("{ROOT}/{run}/alive/actor/{actor}")
}

pub fn all_alive_actors(run: &str) -> String {
    format!("{ROOT}/{run}/alive/actor/*")
}

pub fn alive_evaluator(run: &str, evaluator: u32) -> String {
    format!("{ROOT}/{run}/alive/evaluator/{evaluator}")
}

pub fn all_alive_evaluators(run: &str) -> String {
    format!("{ROOT}/{run}/alive/evaluator/*")
}

pub fn alive_learner(run: &str) -> String {
    format!("{ROOT}/{run}/alive/learner")
}

/// The run id in a key under `crawler/<run>/…`.
pub fn run_of(key: &str) -> Option<&str> {
    let mut parts = key.split('/');
    (parts.next() == Some(ROOT)).then(|| parts.next()).flatten()
}

/// The trailing numeric id of a key such as `crawler/<run>/alive/actor/<id>`, in its one
/// spelling: decimal, no sign, no leading zero. `03` or `+3` would otherwise name actor 3 too,
/// and a token declared and dropped under such an alias would take actor 3 off the books.
pub fn trailing_id(key: &str) -> Result<u32, ProtoError> {
    let text = key.rsplit('/').next().unwrap_or(key);
    canonical_id(text).ok_or_else(|| ProtoError::NonCanonicalId { key: crate::error::quoted_prefix(key) })
}

/// `text` as a node id if it is that id's one spelling (decimal, no sign, no leading zero),
/// as in keys and in certificate names ([`crate::identity`]).
pub fn canonical_id(text: &str) -> Option<u32> {
    text.parse::<u32>().ok().filter(|id| id.to_string() == text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_nest_under_the_run() {
        assert_eq!(transitions("r1", 3), "crawler/r1/transitions/3");
        assert_eq!(run_of("crawler/r1/weights"), Some("r1"));
        assert_eq!(run_of("other/r1/weights"), None);
        assert_eq!(trailing_id(&alive_actor("r1", 12)), Ok(12));
        assert_eq!(trailing_id("crawler/r1/alive/actor/0"), Ok(0));
        for alias in ["012", "+12", "00", "1_2", " 12", "12 ", "", "4294967296", "-0", "x"] {
            let key = format!("crawler/r1/alive/actor/{alias}");
            assert_eq!(
                trailing_id(&key).map_err(|e| e.kind()),
                Err("non_canonical_id"),
                "{alias:?} must not name an actor"
            );
        }
        assert!(check_run_id("2026-11-22_run-1").is_ok());
        for bad in ["", "a/b", "a*", "x".repeat(65).as_str(), "ünïcode"] {
            assert!(check_run_id(bad).is_err(), "{bad}");
        }
    }
}
