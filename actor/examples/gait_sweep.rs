//! Sweeps open-loop square-wave gaits and prints the speed each reaches over 20 s.
//! `cargo run --release -p crawler-actor --example gait_sweep`
#![allow(clippy::print_stdout)]

use crawler_actor::env::gait::SquareWaveGait;
use crawler_actor::env::{Crawler, EnvConfig};

fn main() {
    let config =
        EnvConfig { min_episode_steps: u32::MAX / 2, max_episode_steps: u32::MAX / 2 + 1, ..EnvConfig::default() };
    let mut results = Vec::new();
    for period in [0.2f32, 0.3, 0.4, 0.5, 0.6] {
        for lag in [0.0f32, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875] {
            for (h1, l1) in [(-1.0f32, 1.0f32), (1.0, -1.0), (-1.0, 0.0), (0.0, -1.0), (-1.0, 0.5), (-0.5, 1.0)] {
                for (h2, l2) in [(1.0f32, -1.0f32), (1.0, 0.0), (1.0, 0.5), (0.5, -1.0)] {
                    let gait = SquareWaveGait { period, high: [h1, h2], low: [l1, l2], phase_lag: lag };
                    let mut crawler = Crawler::new(config.clone(), 1);
                    let steps = (20.0 / config.dt) as u32;
                    let mut flips = 0;
                    for s in 0..steps {
                        crawler.step_torques(gait.torques(s as f32 * config.dt));
                        flips += u32::from(crawler.is_flipped());
                    }
                    results.push((crawler.distance() / 20.0, flips, gait));
                }
            }
        }
    }
    results.sort_by(|a, b| b.0.total_cmp(&a.0));
    for (speed, flipped_steps, gait) in results.iter().take(15) {
        println!("{speed:.3} m/s flipped_steps={flipped_steps} {gait:?}");
    }
}
