//! Transition batches: decoding and validation never panic, and whatever is accepted is
//! internally consistent; the sequence tracker takes any order of (incarnation, sequence).
#![no_main]

use crawler_proto::{SequenceTracker, TransitionLimits, validate};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let limits = TransitionLimits {
        run_id: "fuzz".into(),
        obs_dim: 40,
        num_actions: 25,
        max_batch: 4096,
        envs_per_actor: 8,
        observation_range: vec![[-1e4, 1e4]; 40],
        max_abs_reward: 10.0,
    };
    if let Ok(batch) = validate::transition_batch(data, &limits) {
        let n = batch.actions.len();
        assert!(n > 0 && n <= limits.max_batch && batch.count as usize == n);
        assert_eq!(batch.observations.len(), n * 40);
        assert_eq!(batch.next_observations.len(), n * 40);
        assert!(batch.observations.iter().chain(&batch.next_observations).chain(&batch.rewards).all(|v| v.is_finite()));
        assert!(batch.actions.iter().all(|&a| a < 25));
        let mut tracker = SequenceTracker::default();
        let _ = tracker.check(batch.actor_id, batch.incarnation, batch.sequence);
        assert!(tracker.check(batch.actor_id, batch.incarnation, batch.sequence).is_err(), "a replay passed");
    }
});
