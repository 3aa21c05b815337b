//! Insert credit: the learner's half of rate limiting on the insert side (`rate.limit_inserts`).
//!
//! zenoh's reliable transport pushes back only when a link's buffers are full, which says
//! nothing about how fast the learner learns. So the learner tells each actor, on
//! `crawler/<run>/credit/<id>`, which of its batches it may publish next
//! (`proto::InsertCredit`: an acknowledgement and a window, as in TCP), and actors wait for
//! it. The windows share out the rate limiter's insert headroom
//! (`RateLimiter::insert_headroom`) among the live actors, each at least one batch whenever
//! there is any headroom at all, so no actor starves and the overshoot past the band is at
//! most one batch per actor.
//!
//! The training thread writes the headroom into [`Shared`]; a task of the learner process
//! turns it into credits every [`CREDIT_EVERY`] and publishes those that changed, and every
//! credit again after [`CREDIT_REFRESH`] (credits go out with congestion control *Drop*, so a
//! lost one is replaced). The edge refuses a batch past the window it was granted
//! (`over_credit`), so an actor that ignores its credit cannot push the ratio down.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use crawler_proto::{self as proto, PROTOCOL_VERSION, SequenceTracker};

/// How often credits are worked out.
pub(super) const CREDIT_EVERY: Duration = Duration::from_millis(10);

/// An unchanged credit is sent again after this long.
pub(super) const CREDIT_REFRESH: Duration = Duration::from_millis(250);

/// What the learner has granted: the credit each live actor was last sent, and the largest
/// sequence limit granted to each actor process, against which the edge checks batches.
/// Holds live actors only.
#[derive(Debug, Default)]
pub(super) struct CreditLedger {
    sent: BTreeMap<u32, (proto::InsertCredit, Instant)>,
    /// Actor id → (incarnation, first sequence not granted).
    granted: BTreeMap<u32, (u64, u64)>,
}

impl CreditLedger {
    /// Whether a batch of `incarnation` numbered `sequence` lies within what was granted. A
    /// process the learner has granted nothing yet (its first batch) is admitted: that batch
    /// is how the learner learns of it.
    pub(super) fn admits(&self, actor: u32, incarnation: u64, sequence: u64) -> bool {
        match self.granted.get(&actor) {
            Some(&(granted_incarnation, limit)) if granted_incarnation == incarnation => sequence < limit,
            _ => true,
        }
    }

    /// The credits due now: each live actor's share of `headroom` transitions, in batches of
    /// `batch_transitions`, from what `sequences` says was accepted. A credit goes out when it
    /// changed or after [`CREDIT_REFRESH`]. Forgets actors that are no longer live.
    pub(super) fn due(
        &mut self,
        run_id: &str,
        headroom: u64,
        batch_transitions: u64,
        live: &BTreeSet<u32>,
        sequences: &SequenceTracker,
        now: Instant,
    ) -> Vec<proto::InsertCredit> {
        self.sent.retain(|id, _| live.contains(id));
        self.granted.retain(|id, _| live.contains(id));
        let window = window(headroom, batch_transitions, live.len());
        let mut due = Vec::new();
        for &actor in live {
            let (incarnation, next_sequence) = sequences.last(actor).map_or((0, 0), |(inc, last)| (inc, last + 1));
            let credit = proto::InsertCredit {
                protocol_version: PROTOCOL_VERSION,
                run_id: run_id.to_string(),
                actor_id: actor,
                incarnation,
                next_sequence,
                window,
            };
            if incarnation != 0 {
                let limit = next_sequence.saturating_add(u64::from(window));
                let entry = self.granted.entry(actor).or_insert((incarnation, limit));
                // Grants only grow within a process: a window that shrank leaves in flight
                // what the larger one allowed.
                *entry = if entry.0 == incarnation { (incarnation, entry.1.max(limit)) } else { (incarnation, limit) };
            }
            let fresh = self
                .sent
                .get(&actor)
                .is_some_and(|(last, at)| *last == credit && now.duration_since(*at) < CREDIT_REFRESH);
            if !fresh {
                self.sent.insert(actor, (credit.clone(), now));
                due.push(credit);
            }
        }
        due
    }
}

/// Batches each of `actors` may have outstanding: `headroom` transitions shared out, rounded
/// up, so that every actor gets at least one batch whenever there is any headroom.
pub(super) fn window(headroom: u64, batch_transitions: u64, actors: usize) -> u32 {
    let share = (actors.max(1) as u64).saturating_mul(batch_transitions.max(1));
    u32::try_from(headroom.div_ceil(share)).unwrap_or(u32::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headroom_is_shared_out_rounded_up() {
        assert_eq!(window(0, 256, 4), 0, "no headroom, no credit");
        assert_eq!(window(1, 256, 4), 1, "any headroom gives each actor a batch");
        assert_eq!(window(1024, 256, 4), 1);
        assert_eq!(window(1025, 256, 4), 2);
        assert_eq!(window(u64::MAX, 1, 1), u32::MAX);
        assert_eq!(window(512, 0, 0), 512, "degenerate sizes count as one");
    }

    #[test]
    fn credits_follow_what_was_accepted_and_go_out_when_they_change() {
        let mut ledger = CreditLedger::default();
        let mut sequences = SequenceTracker::default();
        let live: BTreeSet<u32> = [1, 2].into();
        let t0 = Instant::now();
        let due = ledger.due("r", 1024, 256, &live, &sequences, t0);
        assert_eq!(due.len(), 2);
        assert!(due.iter().all(|c| c.incarnation == 0 && c.window == 2), "{due:?}");
        // A process the learner has not heard from may introduce itself.
        assert!(ledger.admits(1, 55, 0));
        assert!(ledger.due("r", 1024, 256, &live, &sequences, t0).is_empty(), "nothing changed");
        sequences.check(1, 55, 0).unwrap();
        let due = ledger.due("r", 1024, 256, &live, &sequences, t0);
        assert_eq!(due.len(), 1, "{due:?}");
        assert_eq!((due[0].actor_id, due[0].incarnation, due[0].next_sequence, due[0].window), (1, 55, 1, 2));
        assert!(ledger.admits(1, 55, 2) && !ledger.admits(1, 55, 3));
        // The window closes; what was granted stays granted.
        let due = ledger.due("r", 0, 256, &live, &sequences, t0);
        assert!(due.iter().all(|c| c.window == 0));
        assert!(ledger.admits(1, 55, 2) && !ledger.admits(1, 55, 3));
        // Unchanged credits go out again after the refresh.
        assert_eq!(ledger.due("r", 0, 256, &live, &sequences, t0 + CREDIT_REFRESH).len(), 2);
        // A new process of the same id starts from its own grant.
        sequences.check(1, 56, 0).unwrap();
        ledger.due("r", 256, 256, &live, &sequences, t0);
        assert!(ledger.admits(1, 56, 1) && !ledger.admits(1, 56, 2));
        // Actors that leave are forgotten.
        let only_two: BTreeSet<u32> = [2].into();
        ledger.due("r", 256, 256, &only_two, &sequences, t0);
        assert!(!ledger.sent.contains_key(&1) && !ledger.granted.contains_key(&1));
    }
}
