//! Sim-to-sim state replay: puts this project's crawler into states recorded in another
//! simulator and plays the same torques from each, so that two engines can be compared step
//! by step along one trajectory instead of only by where whole episodes end.
//!
//! Reads JSON lines on stdin, each `{"qpos": [9], "qvel": [8], "torques": [[τ1, τ2], …]}` in
//! the study's MuJoCo generalized coordinates (`Crawler::generalized_state` documents them).
//! For each line it rebuilds the world (fresh contacts, no warm start), sets the state, applies
//! the torques one physics step each and prints one JSON line, `{"states": [{"qpos", "qvel"},
//! …]}`, the state after every step. `scripts/mujoco-check replay` drives it.
//!
//! `cargo run --release -p crawler-env --example state_replay [-- KEY=VALUE …]`: each argument
//! overrides one env setting (TOML values), as for the gait bank.
#![allow(clippy::print_stdout)]

use std::io::BufRead;

use anyhow::Context;
use crawler_env::{Crawler, EnvConfig, GeneralizedState};

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Query {
    qpos: [f32; 9],
    qvel: [f32; 8],
    torques: Vec<[f32; 2]>,
}

fn main() -> anyhow::Result<()> {
    let lines: Vec<String> = std::env::args().skip(1).collect();
    let overrides: toml::Table = toml::from_str(&lines.join("\n"))
        .with_context(|| format!("{lines:?} are not KEY=VALUE lines with TOML values"))?;
    let base: EnvConfig = overrides.try_into().context("env overrides")?;
    // One physics step per torque pair, and no episode end: the replay decides the length.
    let config =
        EnvConfig { action_repeat: 1, min_episode_steps: u32::MAX / 2, max_episode_steps: u32::MAX / 2 + 1, ..base };
    config.validate()?;
    let mut crawler = Crawler::new(config, 1);
    for (number, line) in std::io::stdin().lock().lines().enumerate() {
        let line = line.context("reading stdin")?;
        if line.trim().is_empty() {
            continue;
        }
        let query: Query =
            serde_json::from_str(&line).with_context(|| format!("line {}: not a replay query", number + 1))?;
        let state = GeneralizedState { qpos: query.qpos, qvel: query.qvel };
        crawler.reset_to([query.qpos[7], query.qpos[8]]);
        crawler.set_generalized_state(&state).with_context(|| format!("line {}", number + 1))?;
        let mut states = Vec::with_capacity(query.torques.len());
        for torques in query.torques {
            crawler.step_torques(torques);
            let GeneralizedState { qpos, qvel } = crawler.generalized_state();
            states.push(serde_json::json!({
                "qpos": qpos,
                "qvel": qvel,
                "base_force": crawler.base_contact_force(),
            }));
        }
        println!("{}", serde_json::json!({ "states": states }));
    }
    Ok(())
}
