//! What the learner's benches share (`mod support;`; a folder, so cargo does not take it
//! for a bench of its own).

use std::time::{Duration, Instant};

/// Runs `f` repeatedly for about `budget` after one warm-up call; returns calls per second.
pub fn rate(budget: Duration, mut f: impl FnMut()) -> f64 {
    f();
    let start = Instant::now();
    let mut calls = 0u64;
    while start.elapsed() < budget {
        f();
        calls += 1;
    }
    calls as f64 / start.elapsed().as_secs_f64()
}
