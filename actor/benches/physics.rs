//! Physics throughput on one core along a moving gait, for 1 crawler and for K = 16.
//! `cargo bench -p crawler-actor --bench physics`
//!
//! Target (issue 2): at least 60 000 physics steps/s per core. Prints the ratio to it.
#![allow(clippy::print_stdout)]

use std::time::Instant;

use crawler_actor::env::gait::SquareWaveGait;
use crawler_actor::env::{EnvConfig, VecEnv};

const TARGET_STEPS_PER_SECOND: f64 = 60_000.0;

/// Steps K crawlers through `physics_steps` steps each of the square-wave gait, using
/// actions (the gait's torques are levels of the 5-level grid) and auto-reset.
fn measure(k: usize, physics_steps: u32) -> f64 {
    let config = EnvConfig::default();
    let seeds: Vec<u64> = (0..k as u64).collect();
    let mut env = VecEnv::new(&config, &seeds);
    let gait = SquareWaveGait::FORWARD;
    let level = |torque: f32| ((torque + 1.0) * 2.0).round() as u32;
    let start = Instant::now();
    for step in 0..physics_steps {
        let [t1, t2] = gait.torques(step as f32 * config.dt);
        let action = level(t1) * config.action_levels + level(t2);
        let actions = vec![action; k];
        env.step(&actions);
    }
    let elapsed = start.elapsed().as_secs_f64();
    (k as f64 * f64::from(physics_steps)) / elapsed
}

fn main() {
    let steps = 50_000;
    measure(1, steps / 10); // warm-up
    for k in [1usize, 16] {
        let per_crawler = if k == 1 { steps } else { steps / 8 };
        let rate = measure(k, per_crawler);
        println!(
            "physics K={k:<2}  {rate:>9.0} steps/s on one core  ({:.2}x the 60k target)",
            rate / TARGET_STEPS_PER_SECOND
        );
    }
}
