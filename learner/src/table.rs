//! Replay and its rate limiter behind one lock, after Reverb's `Table`: the inserting thread
//! writes into it while the training thread samples from it.
//!
//! The lock is held for one batch's inserts, one minibatch's sampling or one priority
//! update, never across a gradient step: inserting never waits for the network and sampling
//! never waits for a flood to be inserted. A training thread that may not sample yet (the
//! warm-up, or samples per insert at its bound) sleeps on a condition variable that every
//! insert wakes.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Condvar, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use crate::rate::RateLimiter;
use crate::replay::Replay;

/// What the lock guards.
#[derive(Debug)]
pub struct TableState {
    pub replay: Replay,
    pub rate: RateLimiter,
}

impl TableState {
    /// Whether a minibatch of `count` may be sampled now: the rate limiter allows it and
    /// the replay holds that many transitions.
    pub fn can_sample(&self, count: usize) -> bool {
        self.rate.can_sample(count) && self.replay.len() >= count
    }
}

/// The shared replay table.
#[derive(Debug)]
pub struct Table {
    state: Mutex<TableState>,
    inserted: Condvar,
    /// Transitions received (whether or not replay kept them) and the physics steps they
    /// took, counted from the run's start: budgets in env steps read these without the lock.
    env_steps: AtomicU64,
    physics_steps: AtomicU64,
    /// Set when no more inserts come (the receive path has gone).
    closed: AtomicBool,
}

impl Table {
    /// A table over `replay`, whose rate limiter starts counting from `replay`'s size (a
    /// resumed replay may be sampled at once, at the configured ratio to new inserts only).
    /// `env_steps` and `physics_steps` continue the run's counts.
    pub fn new(replay: Replay, mut rate: RateLimiter, env_steps: u64, physics_steps: u64) -> Self {
        rate.reset(replay.len());
        Self {
            state: Mutex::new(TableState { replay, rate }),
            inserted: Condvar::new(),
            env_steps: AtomicU64::new(env_steps),
            physics_steps: AtomicU64::new(physics_steps),
            closed: AtomicBool::new(false),
        }
    }

    /// The state, for reading or for a checkpoint. A thread that panicked while holding the
    /// lock left the replay whole or one transition short (every insert is one ring write),
    /// so a poisoned lock is taken as it is.
    pub fn lock(&self) -> MutexGuard<'_, TableState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Runs `insert` on the replay (it returns how many transitions replay kept), records
    /// them with the rate limiter, counts `env_steps` received and their `physics_steps`, and
    /// wakes a training thread that waits to sample. Returns what replay kept.
    pub fn insert(&self, env_steps: u64, physics_steps: u64, insert: impl FnOnce(&mut Replay) -> usize) -> usize {
        let kept = {
            let mut state = self.lock();
            let kept = insert(&mut state.replay);
            let len = state.replay.len();
            state.rate.record_insert(kept, len);
            kept
        };
        self.env_steps.fetch_add(env_steps, Ordering::Relaxed);
        self.physics_steps.fetch_add(physics_steps, Ordering::Relaxed);
        self.inserted.notify_one();
        kept
    }

    /// The state once a minibatch of `count` may be sampled, waiting at most `timeout` for
    /// inserts to allow it; None if they did not.
    pub fn ready_to_sample(&self, count: usize, timeout: Duration) -> Option<MutexGuard<'_, TableState>> {
        let state = self.lock();
        if state.can_sample(count) {
            return Some(state);
        }
        let (state, _) = self
            .inserted
            .wait_timeout_while(state, timeout, |state| !state.can_sample(count) && !self.is_closed())
            .unwrap_or_else(PoisonError::into_inner);
        state.can_sample(count).then_some(state)
    }

    /// Transitions received since the run started.
    pub fn env_steps(&self) -> u64 {
        self.env_steps.load(Ordering::Relaxed)
    }

    /// Physics steps of the transitions received since the run started.
    pub fn physics_steps(&self) -> u64 {
        self.physics_steps.load(Ordering::Relaxed)
    }

    /// No more inserts come; a waiting training thread wakes.
    pub fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        self.inserted.notify_all();
    }

    pub fn is_closed(&self) -> bool {
        self.closed.load(Ordering::SeqCst)
    }
}

#[cfg(test)]
mod tests {
    use std::time::Instant;

    use super::*;
    use crate::rate::RateConfig;
    use crate::replay::{StreamId, Transition};
    use crawler_run::config::ReplayConfig;

    fn table(warmup: usize, samples_per_insert: f64, error_buffer: f64) -> Table {
        let replay = Replay::new(ReplayConfig { capacity: 64, n_step: 1, prioritized: None }, 2).unwrap();
        let rate = RateLimiter::new(RateConfig { samples_per_insert, warmup, error_buffer, limit_inserts: false });
        Table::new(replay, rate, 10, 20)
    }

    fn insert(table: &Table, count: usize) {
        table.insert(count as u64, 2 * count as u64, |replay| {
            for i in 0..count {
                let (a, b) = ([i as f32, 0.0], [i as f32 + 1.0, 0.0]);
                let t = Transition {
                    observation: &a,
                    action: 0,
                    reward: 1.0,
                    next_observation: &b,
                    terminated: false,
                    truncated: false,
                };
                replay.insert(StreamId { actor: 0, env: 0 }, &t).unwrap();
            }
            count
        });
    }

    #[test]
    fn sampling_waits_for_the_warm_up_and_an_insert_from_another_thread_ends_the_wait() {
        // Sampling starts with the warm-up, within the error buffer.
        let table = table(4, 1.0, 2.0);
        let start = Instant::now();
        assert!(table.ready_to_sample(2, Duration::from_millis(20)).is_none());
        assert!(start.elapsed() >= Duration::from_millis(20), "it waited its timeout");
        std::thread::scope(|scope| {
            scope.spawn(|| {
                std::thread::sleep(Duration::from_millis(50));
                insert(&table, 4);
            });
            // Woken by the insert, long before the timeout.
            let state = table.ready_to_sample(2, Duration::from_secs(30));
            assert!(state.is_some_and(|s| s.replay.len() == 4));
        });
        assert!(start.elapsed() < Duration::from_secs(20));
        assert_eq!((table.env_steps(), table.physics_steps()), (14, 28), "counted on from the run's counts");
    }

    #[test]
    fn the_rate_limiter_bounds_sampling_through_the_table() {
        let table = table(2, 1.0, 0.0);
        insert(&table, 2);
        assert!(table.ready_to_sample(1, Duration::ZERO).is_none(), "no slack: the warm-up alone allows nothing");
        insert(&table, 2);
        // Two inserts since the warm-up: two samples of one allowed.
        for _ in 0..2 {
            let mut state = table.ready_to_sample(1, Duration::ZERO).unwrap();
            state.rate.record_sample(1);
        }
        assert!(table.ready_to_sample(1, Duration::ZERO).is_none());
    }

    #[test]
    fn closing_wakes_a_waiting_sampler() {
        let table = table(1_000, 1.0, 0.0);
        let start = Instant::now();
        std::thread::scope(|scope| {
            scope.spawn(|| {
                std::thread::sleep(Duration::from_millis(50));
                table.close();
            });
            assert!(table.ready_to_sample(1, Duration::from_secs(30)).is_none());
        });
        assert!(start.elapsed() < Duration::from_secs(20));
    }
}
