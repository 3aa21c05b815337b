//! `plot`: PNG figures of one or more runs.
//!
//! `plot runs/<run> [runs/<other> …] --out <dir>` writes
//! - `learning_curves.png`: episode distance, duration and speed against env steps, raw
//!   (light dots) and smoothed with a time-weighted EMA (as the study's Figs. 2, 3 and 5); one
//!   colour per run, so two runs (backward from scratch vs. transferred) share one plot;
//! - `training.png`: TD loss, mean Q, env steps/s and updates/s against training time;
//! - `joint_angles.png`: both joint angles over the first 4 s of a greedy episode of the
//!   first run's newest checkpoint (the study's Fig. 4).
//!
//! The paths written go to stdout, one per line.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use crawler_learner::evaluate::{evaluation_env, greedy_episode, load_policy};
use crawler_learner::metrics::{Scalar, read_csv};
use crawler_learner::viz::{Area, Canvas, Chart, Colour, SERIES, Series, time_weighted_ema};
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
}

const WIDTH: u32 = 960;

/// Charts stacked vertically, one tag each; raw points light, the EMA bold.
fn stacked(
    runs: &[Run],
    panels: &[(&str, &str)],
    x_label: &str,
    x: impl Fn(&Scalar) -> f64 + Copy,
    smoothing: Option<f64>,
) -> Canvas {
    let panel_height = 300;
    let mut canvas = Canvas::new(WIDTH, panel_height * panels.len() as u32, Colour::White);
    for (i, (tag, title)) in panels.iter().enumerate() {
        let mut chart = Chart {
            title: (*title).to_string(),
            x_label: x_label.into(),
            y_label: (*title).to_string(),
            ..Chart::default()
        };
        for (r, run) in runs.iter().enumerate() {
            let (colour, light) = SERIES[r % SERIES.len()];
            let points = run.points(tag, x);
            match smoothing {
                Some(fraction) => {
                    let span = points.last().map_or(1.0, |l| l.0) - points.first().map_or(0.0, |f| f.0);
                    let smoothed = time_weighted_ema(&points, (span * fraction).max(1e-9));
                    chart.series.push(Series { label: String::new(), colour: light, width: 0.0, points });
                    chart.series.push(Series { label: run.label.clone(), colour, width: 2.5, points: smoothed });
                }
                None => chart.series.push(Series { label: run.label.clone(), colour, width: 2.0, points }),
            }
        }
        // Raw points first, every run's smoothed curve on top.
        chart.series.sort_by_key(|s| !s.label.is_empty());
        let area = Area { x: 0, y: (i as u32 * panel_height) as i32, width: WIDTH as i32, height: panel_height as i32 };
        chart.draw(&mut canvas, area);
    }
    canvas
}

fn write(canvas: &Canvas, path: &Path) -> anyhow::Result<()> {
    canvas.write_png(path).with_context(|| format!("writing {}", path.display()))?;
    #[allow(clippy::print_stdout)]
    {
        println!("{}", path.display());
    }
    Ok(())
}

fn joint_angles(checkpoint: &Path, seed: u64, seconds: f32) -> anyhow::Result<Canvas> {
    let loaded = load_policy(checkpoint, &[])?;
    let env = evaluation_env(&loaded.config.env, seconds)?;
    let (summary, frames) = greedy_episode(&loaded.policy, &env, seed, true)?;
    info!(checkpoint = %loaded.path.display(), speed = summary.speed, "joint-angle episode");
    let series = |index: usize, label: &str, colour: Colour| Series {
        label: label.into(),
        colour,
        width: 2.0,
        points: frames.iter().map(|f| (f64::from(f.time), f64::from(f.joint_angles[index]).to_degrees())).collect(),
    };
    let chart = Chart {
        title: format!("Joint angles, first {seconds} s of a greedy episode (seed {seed}, {:.2} m/s)", summary.speed),
        x_label: "time (s)".into(),
        y_label: "angle (deg)".into(),
        series: vec![series(0, "joint 1 (shoulder)", Colour::Blue), series(1, "joint 2 (knee)", Colour::Orange)],
        y_range: Some((-90.0, 160.0)),
    };
    let mut canvas = Canvas::new(WIDTH, 400, Colour::White);
    chart.draw(&mut canvas, Area { x: 0, y: 0, width: WIDTH as i32, height: 400 });
    Ok(canvas)
}

fn main() -> anyhow::Result<()> {
    crawler_actor::cli::init_logging();
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
    let curves = stacked(
        &runs,
        &[
            ("episode/distance", "episode distance (m)"),
            ("episode/duration", "episode duration (s)"),
            ("episode/speed", "episode speed (m/s)"),
        ],
        "env steps (decisions)",
        env_steps,
        Some(args.smoothing),
    );
    write(&curves, &out.join("learning_curves.png"))?;

    let minutes = |s: &Scalar| s.train_seconds / 60.0;
    let training = stacked(
        &runs,
        &[
            ("train/loss", "TD loss"),
            ("train/mean_q", "mean Q"),
            ("throughput/env_steps_per_s", "env steps/s"),
            ("throughput/updates_per_s", "updates/s"),
        ],
        "training time (min)",
        minutes,
        None,
    );
    write(&training, &out.join("training.png"))?;

    let checkpoint = args.checkpoint.clone().unwrap_or_else(|| args.runs[0].join("checkpoints"));
    match joint_angles(&checkpoint, args.seed, args.seconds) {
        Ok(canvas) => write(&canvas, &out.join("joint_angles.png"))?,
        Err(e) if args.checkpoint.is_some() => return Err(e),
        Err(e) => warn!("no joint-angle figure: {e:#}"),
    }
    Ok(())
}
