//! `eval`: greedy episodes (ε = 0) of a checkpoint, with fixed seeds.
//!
//! `eval runs/<run>/checkpoints` (newest) or `eval runs/<run>/checkpoints/step-…`.
//! Per-episode results and mean ± std go to stdout as JSON; a summary goes to stderr.
//! Episodes last `--seconds` of simulated time; the progress rule does not cut them short.
//! A mean hides the starts a policy never gets going from, so the report also counts stuck
//! episodes (slower than [`STUCK_SPEED`]) and gives the slowest episode's speed.

use std::path::PathBuf;

use clap::Parser;
use crawler_run::config::TrainConfig;
use crawler_run::evaluate::{EVAL_SEED, STUCK_SPEED, episode_failed, evaluation_env, greedy_episode, load_policy};
use serde::Serialize;
use tracing::info;

#[derive(Debug, Parser)]
#[command(version, about = "Evaluate a checkpoint greedily: speed in m/s, distance, return, flips")]
struct Args {
    /// A checkpoint directory (step-…) or a directory of them (the newest is taken).
    checkpoint: PathBuf,
    /// Episodes to run; episode i uses seed `seed + i`.
    #[arg(long, default_value_t = 10)]
    episodes: u64,
    /// Simulated seconds per episode.
    #[arg(long, default_value_t = 20.0)]
    seconds: f32,
    #[arg(long, default_value_t = EVAL_SEED)]
    seed: u64,
    /// Evaluate under perturbed physics, drawn per episode: ±30 % friction, ±20 % masses,
    /// motors at 80–100 %, joint limits from twice as stiff (0.01 s) to twice as soft (0.04 s)
    /// as MuJoCo's, 0–4 ms of latency, a roll push of up to 2.5 rad/s every second
    /// (`Randomization::EVAL_PERTURBATIONS`; the report lists them).
    #[arg(long)]
    perturbed: bool,
    /// Override an env setting of the checkpoint's config, e.g. --set env.direction=backward.
    /// `env.randomization.*` keys state the evaluation's physics instead, on top of the nominal
    /// physics (or --perturbed's), e.g. --set 'env.randomization.floor_contact_hz=[2000,2000]'
    /// (the training's randomisation never applies to an evaluation; the report lists them).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
}

#[derive(Debug, Serialize)]
struct Episode {
    seed: u64,
    speed: f32,
    distance: f32,
    duration: f32,
    episode_return: f32,
    return_position: f32,
    return_upright: f32,
    return_tilt_rate: f32,
    return_base_impact: f32,
    return_joint_limit: f32,
    /// The base's contact force above `env.base_impact_threshold`, integrated (N·s).
    base_impact_impulse: f32,
    flips: u32,
}

#[derive(Debug, Serialize)]
struct MeanStd {
    mean: f64,
    std: f64,
}

fn mean_std(values: impl Iterator<Item = f64> + Clone) -> MeanStd {
    let n = values.clone().count().max(1) as f64;
    let mean = values.clone().sum::<f64>() / n;
    let var = values.map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    MeanStd { mean, std: var.sqrt() }
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    // An evaluation never inherits the training's randomisation, so `env.randomization.*`
    // overrides cannot go to the checkpoint's config, where they would vanish without a word:
    // they are applied to the evaluation's own physics instead.
    let (physics_overrides, config_overrides): (Vec<String>, Vec<String>) =
        args.overrides.iter().cloned().partition(|assignment| assignment.trim_start().starts_with("env.randomization"));
    let loaded = load_policy(&args.checkpoint, &config_overrides)?;
    let mut env = evaluation_env(&loaded.config.env, args.seconds)?;
    if args.perturbed {
        env.randomization = crawler_env::Randomization::EVAL_PERTURBATIONS;
    }
    if !physics_overrides.is_empty() {
        let mut stated = loaded.config.clone();
        stated.env.randomization = env.randomization.clone();
        let stated = TrainConfig::from_json(&serde_json::to_value(&stated)?, "eval's physics", &physics_overrides)?;
        env.randomization = stated.env.randomization;
    }
    info!(checkpoint = %loaded.path.display(), updates = loaded.meta.progress.updates, "evaluating");

    let mut episodes = Vec::new();
    for i in 0..args.episodes {
        let seed = args.seed + i;
        let (summary, _) = greedy_episode(&loaded.policy, &env, seed, false)?;
        episodes.push(Episode {
            seed,
            speed: summary.speed,
            distance: summary.distance,
            duration: summary.duration,
            episode_return: summary.reward.total(),
            return_position: summary.reward.position,
            return_upright: summary.reward.upright,
            return_tilt_rate: summary.reward.tilt_rate,
            return_base_impact: summary.reward.base_impact,
            return_joint_limit: summary.reward.joint_limit,
            base_impact_impulse: summary.base_impact_impulse,
            flips: summary.flips,
        });
    }
    let speed = mean_std(episodes.iter().map(|e| f64::from(e.speed)));
    let distance = mean_std(episodes.iter().map(|e| f64::from(e.distance)));
    let episode_return = mean_std(episodes.iter().map(|e| f64::from(e.episode_return)));
    let impact = mean_std(episodes.iter().map(|e| f64::from(e.base_impact_impulse)));
    let flips: u32 = episodes.iter().map(|e| e.flips).sum();
    let min_speed = episodes.iter().map(|e| e.speed).fold(f32::INFINITY, f32::min);
    let stuck = episodes.iter().filter(|e| e.speed < STUCK_SPEED).count();
    // An episode that flipped or got stuck (or both) counts once: `pick` ranks candidates by this count.
    let failed = episodes.iter().filter(|e| episode_failed(e.speed, e.flips)).count();
    eprintln!(
        "{}: speed {:.3} ± {:.3} m/s (min {min_speed:.3}, {stuck} stuck below {STUCK_SPEED} m/s, {failed} failed: stuck or flipped), distance {:.2} ± {:.2} m, return {:.1} ± {:.1}, base landings {:.2} N·s over {} N, flips {flips} over {} episodes of {} s on {} physics",
        loaded.path.display(),
        speed.mean,
        speed.std,
        distance.mean,
        distance.std,
        episode_return.mean,
        episode_return.std,
        impact.mean,
        env.base_impact_threshold,
        episodes.len(),
        args.seconds,
        if env.randomization.is_active() { "perturbed (the report lists how)" } else { "the nominal" }
    );
    let report = serde_json::json!({
        "checkpoint": loaded.path,
        "updates": loaded.meta.progress.updates,
        "env_steps": loaded.meta.progress.env_steps,
        "physics_steps": loaded.meta.progress.physics_steps,
        "train_seconds": loaded.meta.progress.train_seconds,
        "network": loaded.meta.network,
        "action_repeat": env.action_repeat,
        "direction": env.direction,
        "seconds": args.seconds,
        "perturbations": env.randomization.is_active().then_some(&env.randomization),
        "episodes": episodes,
        "speed": speed,
        "min_speed": min_speed,
        "stuck_episodes": stuck,
        "stuck_below_speed": STUCK_SPEED,
        "failed_episodes": failed,
        "distance": distance,
        "return": episode_return,
        "flips": flips,
        "base_impact_impulse": impact,
        "base_impact_threshold": env.base_impact_threshold,
    });
    let mut stdout = std::io::stdout().lock();
    serde_json::to_writer_pretty(&mut stdout, &report)?;
    std::io::Write::write_all(&mut stdout, b"\n")?;
    Ok(())
}
