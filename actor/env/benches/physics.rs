//! Physics throughput on one core along a moving gait, for 1 crawler and for K = 16.
//! `cargo bench -p crawler-env --bench physics`
//!
//! Target (issue 2): at least 60 000 physics steps/s per core. Prints the ratio to it, and
//! what the default soft-constraint shoulder pair (`env.shoulder_pair`, a second joint with a
//! motor set every step) costs against the viscous stand-in, measured alternately in one run.
#![allow(clippy::print_stdout)]

use std::time::Instant;

use crawler_env::gait::SquareWaveGait;
use crawler_env::{EnvConfig, ShoulderPair, VecEnv};

const TARGET_STEPS_PER_SECOND: f64 = 60_000.0;

/// Steps K crawlers through `physics_steps` steps each of the square-wave gait, using
/// actions (the gait's torques are levels of the 5-level grid) and auto-reset.
fn measure(k: usize, physics_steps: u32, shoulder_pair: ShoulderPair) -> f64 {
    let config = EnvConfig { shoulder_pair, ..EnvConfig::default() };
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
    measure(1, steps / 10, ShoulderPair::default()); // warm-up
    for k in [1usize, 16] {
        let per_crawler = if k == 1 { steps } else { steps / 8 };
        let rate = measure(k, per_crawler, ShoulderPair::default());
        println!(
            "physics K={k:<2}  {rate:>9.0} steps/s on one core  ({:.2}x the 60k target)",
            rate / TARGET_STEPS_PER_SECOND
        );
    }
    // Alternating rounds, so that a machine's drift in speed falls on both alike.
    let (mut soft, mut viscous) = (0.0, 0.0);
    for _ in 0..3 {
        soft += measure(1, steps / 2, ShoulderPair::SoftConstraint);
        viscous += measure(1, steps / 2, ShoulderPair::Viscous);
    }
    println!(
        "shoulder pair K=1  soft constraint {:>9.0}, viscous {:>9.0} steps/s  ({:.2}x)",
        soft / 3.0,
        viscous / 3.0,
        soft / viscous
    );
}
