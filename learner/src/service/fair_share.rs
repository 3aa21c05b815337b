//! Fair shares: no single sender takes more than its share of what the learner holds for all
//! of them.
//!
//! Two bounded buffers are split evenly among the live senders: the ingest queue (batches
//! waiting for the inserting thread) and the episodes waiting for the metrics writer. A
//! sender that holds its share of a buffer has its further messages dropped, while everyone
//! else still finds room. Status reports overwrite their sender's view, so what bounds them
//! is a rate: each sender's reports pass a token bucket sized from the configured status
//! interval. Log lines a message causes pass a budget per event and sender. What is dropped
//! is counted per sender (`over_share` in status.json) and in all (`rejected.over_share`).
//!
//! Every table here holds live senders only (the edge checks liveliness first, and a sender
//! that leaves is forgotten), so all of it is bounded by `learner.max_actors`.
//! The token bucket is written here rather than taken from a rate-limiting crate because its
//! state must live in these per-sender tables and leave with the sender.

use std::collections::{BTreeMap, HashMap};
use std::time::Instant;

use serde::Serialize;

use super::edge::NodeKind;

/// A message's sender.
pub(super) type Sender = (NodeKind, u32);

/// What one sender had dropped for going over its share.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct OverShare {
    /// Transition batches beyond its share of the ingest queue.
    pub batches: u64,
    /// Episode statistics beyond its share of the metrics' pending episodes.
    pub episodes: u64,
    /// Status reports beyond its rate.
    pub statuses: u64,
    /// Log lines left out beyond its budget.
    pub log_lines: u64,
}

/// A sender's token bucket: `rate` tokens a second, at most `burst` saved.
#[derive(Debug, Clone, Copy)]
struct TokenBucket {
    tokens: f64,
    at: Instant,
}

impl TokenBucket {
    fn full(burst: f64, now: Instant) -> Self {
        Self { tokens: burst, at: now }
    }

    fn take(&mut self, rate: f64, burst: f64, now: Instant) -> bool {
        let elapsed = now.saturating_duration_since(self.at).as_secs_f64();
        self.tokens = (self.tokens + elapsed * rate).min(burst);
        self.at = now;
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

/// How fast each sender may report status, and how many log lines of one event it may cause.
#[derive(Debug, Clone, Copy)]
pub(super) struct Budgets {
    /// Status reports a second per sender: a few times the configured interval's rate, so
    /// that a late report and its successor both pass.
    pub status_rate: f64,
    pub status_burst: f64,
    /// Log lines a second per event and sender.
    pub log_rate: f64,
    pub log_burst: f64,
}

impl Default for Budgets {
    /// The budgets of the actors' default status interval.
    fn default() -> Self {
        Self::for_status_interval(2.0)
    }
}

impl Budgets {
    /// Budgets for actors that report status every `status_interval_s`.
    pub fn for_status_interval(status_interval_s: f64) -> Self {
        Self { status_rate: 4.0 / status_interval_s.max(1e-3), status_burst: 8.0, log_rate: 1.0, log_burst: 10.0 }
    }
}

/// The share of `capacity` each of `senders` live senders may hold: an even split, at least
/// one.
pub(super) fn share(capacity: usize, senders: usize) -> usize {
    (capacity / senders.max(1)).max(1)
}

/// Takes one of `share` places for `sender` in `held`; false when it holds them all.
fn take_place(held: &mut HashMap<Sender, usize>, sender: Sender, share: usize) -> bool {
    let places = held.entry(sender).or_default();
    let free = *places < share;
    if free {
        *places += 1;
    }
    free
}

/// Per-sender holdings, buckets and drop counts.
#[derive(Debug, Default)]
pub(super) struct FairShares {
    budgets: Budgets,
    queued_batches: HashMap<Sender, usize>,
    pending_episodes: HashMap<Sender, usize>,
    status: HashMap<Sender, TokenBucket>,
    log_lines: HashMap<(Sender, &'static str), TokenBucket>,
    /// Log lines of events no sender owns (tokens coming and going, id assignments): one
    /// budget per event for everyone, ten times a sender's.
    unattributed_log_lines: HashMap<&'static str, TokenBucket>,
    over: BTreeMap<Sender, OverShare>,
    over_total: u64,
}

impl FairShares {
    pub fn new(budgets: Budgets) -> Self {
        Self { budgets, ..Self::default() }
    }

    fn count_over(&mut self, sender: Sender, which: impl FnOnce(&mut OverShare) -> &mut u64) {
        *which(self.over.entry(sender).or_default()) += 1;
        self.over_total += 1;
    }

    /// Takes a place in the ingest queue of `capacity` batches for `actor`, one of `actors`
    /// live actors; false (and counted) when it holds its share already.
    pub fn enter_queue(&mut self, actor: u32, capacity: usize, actors: usize) -> bool {
        let sender = (NodeKind::Actor, actor);
        let taken = take_place(&mut self.queued_batches, sender, share(capacity, actors));
        if !taken {
            self.count_over(sender, |o| &mut o.batches);
        }
        taken
    }

    /// Gives `actor`'s place in the ingest queue back (its batch was inserted, or the queue
    /// turned it away).
    pub fn leave_queue(&mut self, actor: u32) {
        if let Some(held) = self.queued_batches.get_mut(&(NodeKind::Actor, actor)) {
            *held = held.saturating_sub(1);
        }
    }

    /// Takes a place among `capacity` pending episodes for `sender`, one of `senders` live
    /// senders; false (and counted) when it holds its share already.
    pub fn enter_pending_episodes(&mut self, sender: Sender, capacity: usize, senders: usize) -> bool {
        let taken = take_place(&mut self.pending_episodes, sender, share(capacity, senders));
        if !taken {
            self.count_over(sender, |o| &mut o.episodes);
        }
        taken
    }

    /// The metrics writer took every pending episode.
    pub fn pending_episodes_written(&mut self) {
        self.pending_episodes.clear();
    }

    /// Whether `sender`'s status report passes its rate; counted when it does not.
    pub fn status_passes(&mut self, sender: Sender, now: Instant) -> bool {
        let Budgets { status_rate, status_burst, .. } = self.budgets;
        let bucket = self.status.entry(sender).or_insert_with(|| TokenBucket::full(status_burst, now));
        let passes = bucket.take(status_rate, status_burst, now);
        if !passes {
            self.count_over(sender, |o| &mut o.statuses);
        }
        passes
    }

    /// Whether a log line of `event` caused by `sender` is written; counted when it is not.
    pub fn log_line_passes(&mut self, sender: Sender, event: &'static str, now: Instant) -> bool {
        let Budgets { log_rate, log_burst, .. } = self.budgets;
        let bucket = self.log_lines.entry((sender, event)).or_insert_with(|| TokenBucket::full(log_burst, now));
        let passes = bucket.take(log_rate, log_burst, now);
        if !passes {
            self.count_over(sender, |o| &mut o.log_lines);
        }
        passes
    }

    /// Whether a log line of `event`, which no sender owns, is written; counted in all when
    /// it is not.
    pub fn unattributed_log_line_passes(&mut self, event: &'static str, now: Instant) -> bool {
        let (rate, burst) = (10.0 * self.budgets.log_rate, 10.0 * self.budgets.log_burst);
        let bucket = self.unattributed_log_lines.entry(event).or_insert_with(|| TokenBucket::full(burst, now));
        let passes = bucket.take(rate, burst, now);
        if !passes {
            self.over_total += 1;
        }
        passes
    }

    /// Drops everything about a sender that left.
    pub fn forget(&mut self, sender: Sender) {
        self.queued_batches.remove(&sender);
        self.pending_episodes.remove(&sender);
        self.status.remove(&sender);
        self.log_lines.retain(|(who, _), _| *who != sender);
        self.over.remove(&sender);
    }

    /// What each live sender had dropped, by name (`actor-3`, `evaluator-1000`), for
    /// status.json; senders that dropped nothing are left out.
    pub fn over_share(&self) -> BTreeMap<String, OverShare> {
        self.over
            .iter()
            .map(|((kind, id), over)| {
                let kind = match kind {
                    NodeKind::Actor => "actor",
                    NodeKind::Evaluator => "evaluator",
                };
                (format!("{kind}-{id}"), *over)
            })
            .collect()
    }

    /// Messages and log lines dropped for going over a share, in all.
    pub fn over_total(&self) -> u64 {
        self.over_total
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    const ACTOR: fn(u32) -> Sender = |id| (NodeKind::Actor, id);

    #[test]
    fn a_flooding_actor_fills_its_share_of_the_queue_and_no_more() {
        let mut shares = FairShares::new(Budgets::for_status_interval(2.0));
        // 256 places, 4 live actors: 64 each.
        let taken = (0..1_000).filter(|_| shares.enter_queue(7, 256, 4)).count();
        assert_eq!(taken, 64);
        assert!((0..3).all(|actor| (0..64).all(|_| shares.enter_queue(actor, 256, 4))));
        assert_eq!(shares.over_share()["actor-7"].batches, 1_000 - 64);
        assert!(!shares.over_share().contains_key("actor-0"));
        // An inserted batch frees a place for its own sender only.
        shares.leave_queue(0);
        assert!(!shares.enter_queue(7, 256, 4));
        assert!(shares.enter_queue(0, 256, 4));
        assert_eq!(share(5, 0), 5);
        assert_eq!(share(5, 10), 1, "every live sender has a place");
    }

    #[test]
    fn pending_episodes_are_shared_until_the_writer_takes_them() {
        let mut shares = FairShares::new(Budgets::for_status_interval(2.0));
        let evaluator = (NodeKind::Evaluator, 1000);
        assert_eq!((0..100).filter(|_| shares.enter_pending_episodes(ACTOR(1), 20, 2)).count(), 10);
        assert_eq!((0..5).filter(|_| shares.enter_pending_episodes(evaluator, 20, 2)).count(), 5);
        shares.pending_episodes_written();
        assert!(shares.enter_pending_episodes(ACTOR(1), 20, 2));
        assert_eq!(shares.over_share()["actor-1"].episodes, 90);
        assert_eq!(shares.over_total(), 90);
    }

    #[test]
    fn statuses_pass_at_their_rate_and_a_sender_that_leaves_is_forgotten() {
        let mut shares = FairShares::new(Budgets::for_status_interval(1.0));
        let start = Instant::now();
        // A burst of 8, then 4 a second.
        assert_eq!((0..100).filter(|_| shares.status_passes(ACTOR(2), start)).count(), 8);
        let later = start + Duration::from_millis(1_000);
        assert_eq!((0..100).filter(|_| shares.status_passes(ACTOR(2), later)).count(), 4);
        // Another sender's bucket is its own.
        assert!(shares.status_passes(ACTOR(3), later));
        assert_eq!(shares.over_share()["actor-2"].statuses, 188);
        shares.forget(ACTOR(2));
        assert!(!shares.over_share().contains_key("actor-2"));
        assert!(shares.status_passes(ACTOR(2), later), "a sender that comes back starts afresh");
    }

    #[test]
    fn log_lines_have_a_budget_per_event_and_sender() {
        let mut shares = FairShares::new(Budgets::for_status_interval(1.0));
        let now = Instant::now();
        assert_eq!((0..50).filter(|_| shares.log_line_passes(ACTOR(4), "evaluation", now)).count(), 10);
        assert!(shares.log_line_passes(ACTOR(4), "other", now));
        assert!(shares.log_line_passes(ACTOR(5), "evaluation", now));
        assert_eq!(shares.over_share()["actor-4"].log_lines, 40);
    }
}
