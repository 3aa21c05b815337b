//! `plot`: PNG figures of one or more runs.
//!
//! `plot runs/<run> [runs/<other> …] --out <dir>` writes
//! - `learning_curves.png`: episode speed of each actor against env steps (each actor explores
//!   with its own ε, so the near-greedy one shows what the policy does), greedy evaluation
//!   episodes where an evaluator ran, and the distance and duration of all training episodes
//!   (the study's Figs. 2, 3 and 5); raw points light, smoothed with a time-weighted EMA;
//!   several runs share one plot (backward from scratch vs. transferred);
//! - `training.png`: TD loss, mean Q, env steps/s and updates/s against training time;
//! - `joint_angles.png`: both joint angles over the first 4 s of a greedy episode of the
//!   first run's newest checkpoint (the study's Fig. 4).
//!
//! The paths written go to stdout, one per line.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use crawler_run::evaluate::{evaluation_env, greedy_episode, load_policy};
use crawler_run::metrics::{Scalar, read_csv};
use crawler_run::viz::charts::{self, Mark, Panel, SERIES_COLOURS, Series, time_weighted_ema};
use tracing::{info, warn};

#[derive(Debug, Parser)]
#[command(version, about = "Plot learning curves, training health and joint angles of runs")]
struct Args {
    /// Run directories (each holds metrics.csv and checkpoints/).
    #[arg(required = true)]
    runs: Vec<PathBuf>,
    /// A legend label per run (default: the run directory's name).
    #[arg(long = "label")]
    labels: Vec<String>,
    /// Where to write the PNGs (default: <first run>/plots).
    #[arg(long)]
    out: Option<PathBuf>,
    /// The EMA's time constant as a fraction of the x range.
    #[arg(long, default_value_t = 0.02)]
    smoothing: f64,
    /// The checkpoint for the joint-angle figure (default: the first run's newest).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Seed of the joint-angle episode's start pose.
    #[arg(long, default_value_t = 1_000_000)]
    seed: u64,
    /// Seconds of the joint-angle figure.
    #[arg(long, default_value_t = 4.0)]
    seconds: f32,
}

struct Run {
    label: String,
    scalars: Vec<Scalar>,
}

impl Run {
    fn points(&self, tag: &str, x: impl Fn(&Scalar) -> f64) -> Vec<(f64, f64)> {
        self.scalars.iter().filter(|s| s.tag == tag).map(|s| (x(s), s.value)).collect()
    }

    /// The ids of actors with per-actor tags (`actor/<id>/speed`), ascending.
    fn actor_ids(&self) -> Vec<u32> {
        let mut ids: Vec<u32> = self
            .scalars
            .iter()
            .filter_map(|s| s.tag.strip_prefix("actor/")?.strip_suffix("/speed")?.parse().ok())
            .collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }

    fn last(&self, tag: &str) -> Option<f64> {
        self.scalars.iter().rev().find(|s| s.tag == tag).map(|s| s.value)
    }
}

const WIDTH: u32 = 1000;
const PANEL_HEIGHT: u32 = 320;

/// One curve of a panel: `points` raw (light dots, when smoothing) and smoothed (bold).
struct Curve {
    label: String,
    points: Vec<(f64, f64)>,
}

/// A panel of curves, smoothed with a time constant of `smoothing` × the x span, or drawn
/// as lines when `smoothing` is None. Raw points go under every smoothed line.
fn panel(title: &str, x_label: &str, curves: Vec<Curve>, smoothing: Option<f64>) -> Panel {
    let mut raw = Vec::new();
    let mut lines = Vec::new();
    for (i, curve) in curves.into_iter().enumerate() {
        let (colour, light) = SERIES_COLOURS[i % SERIES_COLOURS.len()];
        match smoothing {
            Some(fraction) => {
                let span = curve.points.last().map_or(1.0, |l| l.0) - curve.points.first().map_or(0.0, |f| f.0);
                let smoothed = time_weighted_ema(&curve.points, (span * fraction).max(1e-9));
                raw.push(Series { label: String::new(), colour: light, mark: Mark::Dots, points: curve.points });
                lines.push(Series { label: curve.label, colour, mark: Mark::Line(3), points: smoothed });
            }
            None => lines.push(Series { label: curve.label, colour, mark: Mark::Line(2), points: curve.points }),
        }
    }
    raw.extend(lines);
    Panel { title: title.into(), x_label: x_label.into(), y_label: title.into(), series: raw, y_range: None }
}

/// One curve per run for `tag`; runs without it are left out.
fn per_run(runs: &[Run], tag: &str, x: impl Fn(&Scalar) -> f64 + Copy) -> Vec<Curve> {
    runs.iter()
        .map(|run| Curve { label: run.label.clone(), points: run.points(tag, x) })
        .filter(|curve| !curve.points.is_empty())
        .collect()
}

/// One curve per actor of every run, labelled with the actor's last ε.
fn per_actor(runs: &[Run], x: impl Fn(&Scalar) -> f64 + Copy) -> Vec<Curve> {
    let mut curves = Vec::new();
    for run in runs {
        for id in run.actor_ids() {
            let epsilon = run
                .last(&format!("actor/{id}/epsilon"))
                .map_or(String::new(), |e| format!(", ε = {}", epsilon_label(e)));
            let prefix = if runs.len() > 1 { format!("{} · ", run.label) } else { String::new() };
            curves.push(Curve {
                label: format!("{prefix}actor {id}{epsilon}"),
                points: run.points(&format!("actor/{id}/speed"), x),
            });
        }
    }
    curves
}

/// ε as people read it: two decimals, or one significant digit below 0.01 (the ε ladder's
/// last actor explores with 0.0007, which two decimals would show as 0).
fn epsilon_label(epsilon: f64) -> String {
    if epsilon == 0.0 || epsilon >= 0.01 { format!("{epsilon:.2}") } else { format!("{epsilon:.0e}") }
}

fn write(panels: &[Panel], height: u32, path: &Path) -> anyhow::Result<()> {
    charts::write_png(path, WIDTH, height, panels).with_context(|| format!("writing {}", path.display()))?;
    #[allow(clippy::print_stdout)]
    {
        println!("{}", path.display());
    }
    Ok(())
}

fn joint_angles(checkpoint: &Path, seed: u64, seconds: f32) -> anyhow::Result<Panel> {
    let loaded = load_policy(checkpoint, &[])?;
    let env = evaluation_env(&loaded.config.env, seconds)?;
    let (summary, frames) = greedy_episode(&loaded.policy, &env, seed, true)?;
    info!(checkpoint = %loaded.path.display(), speed = summary.speed, "joint-angle episode");
    let series = |index: usize, label: &str, colour| Series {
        label: label.into(),
        colour,
        mark: Mark::Line(2),
        points: frames.iter().map(|f| (f64::from(f.time), f64::from(f.joint_angles[index]).to_degrees())).collect(),
    };
    Ok(Panel {
        title: format!("Joint angles, first {seconds} s of a greedy episode (seed {seed}, {:.2} m/s)", summary.speed),
        x_label: "time (s)".into(),
        y_label: "angle (deg)".into(),
        series: vec![
            series(0, "joint 1 (shoulder)", SERIES_COLOURS[0].0),
            series(1, "joint 2 (knee)", SERIES_COLOURS[1].0),
        ],
        y_range: Some((-90.0, 160.0)),
    })
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    anyhow::ensure!(
        args.labels.is_empty() || args.labels.len() == args.runs.len(),
        "{} --label given for {} runs: give one per run or none",
        args.labels.len(),
        args.runs.len()
    );
    anyhow::ensure!(
        args.smoothing > 0.0 && args.smoothing < 1.0,
        "--smoothing must be in (0, 1), got {}",
        args.smoothing
    );
    let mut runs = Vec::new();
    for (i, dir) in args.runs.iter().enumerate() {
        let csv = dir.join("metrics.csv");
        let scalars = read_csv(&csv).with_context(|| {
            format!("reading {} (is {} a run directory of a learner with metrics?)", csv.display(), dir.display())
        })?;
        let label = args.labels.get(i).cloned().unwrap_or_else(|| {
            dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into_owned())
        });
        runs.push(Run { label, scalars });
    }
    let out = args.out.clone().unwrap_or_else(|| args.runs[0].join("plots"));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;

    let env_steps = |s: &Scalar| s.env_steps as f64;
    let steps = "env steps (decisions)";
    let smoothing = Some(args.smoothing);
    let mut curves = vec![panel("episode speed per actor (m/s)", steps, per_actor(&runs, env_steps), smoothing)];
    let greedy = per_run(&runs, "eval/speed", env_steps);
    if !greedy.is_empty() {
        curves.push(panel("greedy evaluation speed (m/s)", steps, greedy, smoothing));
    }
    for (tag, title) in [
        ("episode/distance", "episode distance (m), all actors"),
        ("episode/duration", "episode duration (s), all actors"),
    ] {
        curves.push(panel(title, steps, per_run(&runs, tag, env_steps), smoothing));
    }
    write(&curves, PANEL_HEIGHT, &out.join("learning_curves.png"))?;

    let minutes = |s: &Scalar| s.train_seconds / 60.0;
    let time = "training time (min)";
    let training: Vec<Panel> = [
        ("train/loss", "TD loss"),
        ("train/mean_q", "mean Q"),
        ("throughput/env_steps_per_s", "env steps/s"),
        ("throughput/updates_per_s", "updates/s"),
    ]
    .into_iter()
    .map(|(tag, title)| panel(title, time, per_run(&runs, tag, minutes), None))
    .collect();
    write(&training, PANEL_HEIGHT, &out.join("training.png"))?;

    let checkpoint = args.checkpoint.clone().unwrap_or_else(|| args.runs[0].join("checkpoints"));
    match joint_angles(&checkpoint, args.seed, args.seconds) {
        Ok(panel) => write(&[panel], 420, &out.join("joint_angles.png"))?,
        Err(e) if args.checkpoint.is_some() => return Err(e),
        Err(e) => warn!("no joint-angle figure: {e:#}"),
    }
    Ok(())
}
