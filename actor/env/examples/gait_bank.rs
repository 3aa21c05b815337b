//! The gait bank: 60 open-loop square-wave gaits over periods, torque levels and phase lags,
//! each run for 20 s in this project's env from three fixed start poses. Prints one JSON line
//! per gait (the gait, its start poses, its mean speed, total flips and largest joint-limit
//! overshoot over them), the input
//! of `scripts/mujoco-check gaits`, which runs the same gaits on the study's MuJoCo model.
//! Several starts, because a gait that tumbles is chaotic: its speed from one start says
//! little.
//!
//! `cargo run --release -p crawler-env --example gait_bank [-- KEY=VALUE …]`: each argument
//! overrides one env setting (TOML values, e.g. `solver_iterations=50`), to measure a
//! candidate physics change on the whole bank. `--sort` prints the fastest first instead.
#![allow(clippy::print_stdout)]

use anyhow::Context;
use crawler_env::gait::SquareWaveGait;
use crawler_env::model::{JOINT1_RANGE, JOINT2_RANGE};
use crawler_env::observation::BASE_ANGVEL;
use crawler_env::{Crawler, EnvConfig, OBS_DIM};

const SECONDS: f32 = 20.0;
/// Joint angles of the start poses, in degrees: the middle and two corners of the study's
/// start ranges clamped into the limits (joint 1 in −45°…0°, joint 2 in 0°…22.5°).
const STARTS_DEG: [[f32; 2]; 3] = [[-22.5, 11.25], [-40.0, 2.0], [-5.0, 20.0]];

/// 4 periods × 5 torque patterns × 3 phase lags.
fn bank() -> Vec<SquareWaveGait> {
    let patterns: [([f32; 2], [f32; 2]); 5] = [
        ([-1.0, 1.0], [0.0, -1.0]), // the regression gait's levels
        ([-1.0, 1.0], [1.0, -1.0]), // full swings on both joints
        ([-0.5, 1.0], [0.0, -1.0]), // a gentler shoulder
        ([-1.0, 0.5], [0.0, -0.5]), // a gentler knee
        ([-0.5, 0.5], [0.5, -0.5]), // half torque everywhere
    ];
    let mut gaits = Vec::new();
    for period in [0.2f32, 0.3, 0.4, 0.6] {
        for (high, low) in patterns {
            for phase_lag in [0.0f32, 0.25, 0.5] {
                gaits.push(SquareWaveGait { period, high, low, phase_lag });
            }
        }
    }
    gaits
}

fn main() -> anyhow::Result<()> {
    let mut sort = false;
    let mut lines = Vec::new();
    for argument in std::env::args().skip(1) {
        if argument == "--sort" {
            sort = true;
        } else {
            lines.push(argument);
        }
    }
    // One TOML document, so that dotted keys of one table (physics.a, physics.b) merge.
    let overrides: toml::Table = toml::from_str(&lines.join("\n"))
        .with_context(|| format!("{lines:?} are not KEY=VALUE lines with TOML values"))?;
    let base: EnvConfig = overrides.try_into().context("env overrides")?;
    let config = EnvConfig { min_episode_steps: u32::MAX / 2, max_episode_steps: u32::MAX / 2 + 1, ..base };
    config.validate()?;
    let starts = STARTS_DEG.map(|pose| pose.map(f32::to_radians));
    let steps = (SECONDS / config.dt).round() as u32;
    let mut rows = Vec::new();
    for gait in bank() {
        let (mut distance, mut flips, mut overshoot, mut rocking) = (0.0, 0, 0.0f32, 0.0f64);
        let mut observation = [0.0; OBS_DIM];
        for start in starts {
            let mut crawler = Crawler::new(config.clone(), 1);
            crawler.reset_to(start);
            for s in 0..steps {
                crawler.step_torques(gait.torques(s as f32 * config.dt));
                let [q1, q2] = crawler.joint_angles();
                let beyond = [JOINT1_RANGE[0] - q1, q1 - JOINT1_RANGE[1], JOINT2_RANGE[0] - q2, q2 - JOINT2_RANGE[1]];
                overshoot = beyond.into_iter().fold(overshoot, f32::max);
                crawler.observe(&mut observation);
                let [wx, wy, _] = [0, 1, 2].map(|axis| f64::from(observation[BASE_ANGVEL.start + axis]));
                rocking += wx * wx + wy * wy;
            }
            // The env counts turn-overs (its base's top starting to face down) itself.
            flips += crawler.episode_summary(None).flips;
            distance += crawler.distance();
        }
        let speed = distance / (SECONDS * starts.len() as f32);
        let row = serde_json::json!({
            "gait": {"period": gait.period, "high": gait.high, "low": gait.low, "phase_lag": gait.phase_lag},
            "starts": starts,
            "seconds": SECONDS,
            "speed": speed,
            "flips": flips,
            "overshoot_deg": overshoot.to_degrees(),
            // Mean ωx² + ωy² of the base about its horizontal axes, (rad/s)²: what
            // `env.tilt_rate_penalty` charges per second and unit weight.
            "rocking": rocking / f64::from(steps * starts.len() as u32),
        });
        rows.push((speed, row));
    }
    if sort {
        rows.sort_by(|a, b| b.0.total_cmp(&a.0));
    }
    for (_, row) in rows {
        println!("{row}");
    }
    Ok(())
}
