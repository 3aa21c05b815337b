//! Insert credit: the learner's hold on its actors, the insert side of rate limiting.
//!
//! zenoh's reliable transport pushes back only when a link's buffers are full, which says
//! nothing about how fast the learner learns. So the learner tells each actor, on
//! `crawler/<run>/credit/<id>`, which of its batches it may publish next
//! (`proto::InsertCredit`: an acknowledgement and a window, as in TCP), and actors wait for
//! it. With `rate.limit_inserts` the windows share out what the rate limiter still takes
//! (`RateLimiter::insert_headroom`) among the live actors, each at least one batch whenever
//! there is any room at all, so no actor starves; without it every window is `u32::MAX`, so
//! the mode can change on a resume without leaving actors waiting.
//!
//! The training thread writes an absolute limit into [`Shared`](super::edge::Shared): the
//! transitions admitted so far plus its headroom. A task of the learner process turns what
//! is left of it into credits every [`CREDIT_EVERY`] and publishes those that changed, and
//! every credit again after [`CREDIT_REFRESH`] (credits go out with congestion control
//! *Drop*, so a lost one is replaced). Because the limit is absolute, a stalled training
//! thread stops the credit once its headroom is used, rather than granting it again every
//! round. The edge refuses a batch past the window its process was granted (`over_credit`);
//! a process the learner has not heard of yet may introduce itself with one batch per
//! [`CREDIT_REFRESH`] and actor id, so that restarting under new incarnations gains nothing.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use crawler_proto::{self as proto, PROTOCOL_VERSION, SequenceTracker};

/// How often credits are worked out.
pub(super) const CREDIT_EVERY: Duration = Duration::from_millis(10);

/// An unchanged credit is sent again after this long; an actor id may introduce a new process
/// once in this long.
pub(super) const CREDIT_REFRESH: Duration = Duration::from_millis(250);

/// What the learner has granted: the credit each live actor was last sent, the largest
/// sequence limit granted to each actor process, against which the edge checks batches, and
/// when each id last introduced a process. Holds live actors only.
#[derive(Debug, Default)]
pub(super) struct CreditLedger {
    sent: BTreeMap<u32, (proto::InsertCredit, Instant)>,
    /// Actor id → (incarnation, first sequence not granted).
    granted: BTreeMap<u32, (u64, u64)>,
    introduced: BTreeMap<u32, Instant>,
}

impl CreditLedger {
    /// Whether a batch of `incarnation` numbered `sequence` lies within what was granted.
    /// A process that was granted nothing yet may introduce itself with one batch, when its
    /// id's credit has room and the id has not introduced another process in the last
    /// [`CREDIT_REFRESH`]: that batch is how the learner learns of it.
    pub(super) fn admit(&mut self, actor: u32, incarnation: u64, sequence: u64, now: Instant) -> bool {
        if let Some(&(granted_incarnation, limit)) = self.granted.get(&actor)
            && granted_incarnation == incarnation
        {
            return sequence < limit;
        }
        let room = self.sent.get(&actor).is_some_and(|(credit, _)| credit.window > 0);
        let recent = self.introduced.get(&actor).is_some_and(|at| now.duration_since(*at) < CREDIT_REFRESH);
        if room && !recent {
            self.introduced.insert(actor, now);
            true
        } else {
            false
        }
    }

    /// The credits due now: `room` transitions shared among the live actors in batches of
    /// `batch_transitions`, each window counted from what `sequences` says was accepted. A
    /// credit goes out when it changed or after [`CREDIT_REFRESH`]. Forgets actors that are
    /// no longer live.
    pub(super) fn due(
        &mut self,
        run_id: &str,
        room: u64,
        batch_transitions: u64,
        live: &BTreeSet<u32>,
        sequences: &SequenceTracker,
        now: Instant,
    ) -> Vec<proto::InsertCredit> {
        self.sent.retain(|id, _| live.contains(id));
        self.granted.retain(|id, _| live.contains(id));
        self.introduced.retain(|id, _| live.contains(id));
        let window = window(room, batch_transitions, live.len());
        let mut due = Vec::new();
        for &actor in live {
            let (incarnation, next_sequence) =
                sequences.last(actor).map_or((0, 0), |(inc, last)| (inc, last.saturating_add(1)));
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

/// Batches each of `actors` may have outstanding: `room` transitions shared out, rounded
/// up, so that every actor gets at least one batch whenever there is any room.
pub(super) fn window(room: u64, batch_transitions: u64, actors: usize) -> u32 {
    let share = (actors.max(1) as u64).saturating_mul(batch_transitions.max(1));
    u32::try_from(room.div_ceil(share)).unwrap_or(u32::MAX)
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
        // A process the learner has not heard from may introduce itself, once per refresh.
        assert!(ledger.admit(1, 55, 0, t0));
        assert!(!ledger.admit(1, 57, 0, t0), "a second new process of the same id waits");
        assert!(ledger.due("r", 1024, 256, &live, &sequences, t0).is_empty(), "nothing changed");
        sequences.check(1, 55, 0, t0).unwrap();
        let due = ledger.due("r", 1024, 256, &live, &sequences, t0);
        assert_eq!(due.len(), 1, "{due:?}");
        assert_eq!((due[0].actor_id, due[0].incarnation, due[0].next_sequence, due[0].window), (1, 55, 1, 2));
        assert!(ledger.admit(1, 55, 2, t0) && !ledger.admit(1, 55, 3, t0));
        // The window closes; what was granted stays granted, and no process introduces itself.
        let due = ledger.due("r", 0, 256, &live, &sequences, t0);
        assert!(due.iter().all(|c| c.window == 0));
        assert!(ledger.admit(1, 55, 2, t0) && !ledger.admit(1, 55, 3, t0));
        assert!(!ledger.admit(2, 9, 0, t0 + CREDIT_REFRESH), "no room, no introduction");
        // Unchanged credits go out again after the refresh.
        assert_eq!(ledger.due("r", 0, 256, &live, &sequences, t0 + CREDIT_REFRESH).len(), 2);
        // A new process of the same id starts from its own grant.
        sequences.check(1, 56, 0, t0 + proto::validate::INCARNATION_HANDOVER).unwrap();
        ledger.due("r", 256, 256, &live, &sequences, t0);
        assert!(ledger.admit(1, 56, 1, t0) && !ledger.admit(1, 56, 2, t0));
        // Without a limit, windows are as wide as the wire carries.
        assert_eq!(ledger.due("r", u64::MAX, 256, &live, &sequences, t0)[0].window, u32::MAX);
        // Actors that leave are forgotten.
        let only_two: BTreeSet<u32> = [2].into();
        ledger.due("r", 256, 256, &only_two, &sequences, t0);
        assert!(!ledger.sent.contains_key(&1) && !ledger.granted.contains_key(&1));
        assert!(!ledger.introduced.contains_key(&1));
    }
}
