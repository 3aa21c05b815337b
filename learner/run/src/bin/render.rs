//! `render`: an animated GIF of one greedy episode of a checkpoint, in side view.
//!
//! `render runs/<run>/checkpoints --out gait.gif` draws the base, both links and the tip, a
//! ground grid, the start line, a distance marker and a time stamp. The file's path, frame
//! count and the episode's speed go to stdout as JSON.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use crawler_run::evaluate::{evaluation_env, greedy_episode, load_policy};
use crawler_run::viz::{Canvas, Colour, GifWriter, SideView, frame_stride};
use tracing::info;

#[derive(Debug, Parser)]
#[command(version, about = "Render a greedy episode of a checkpoint as an animated GIF (side view)")]
struct Args {
    /// A checkpoint directory (step-…) or a directory of them (the newest is taken).
    checkpoint: PathBuf,
    /// The GIF to write.
    #[arg(long, default_value = "gait.gif")]
    out: PathBuf,
    /// Simulated seconds to show.
    #[arg(long, default_value_t = 8.0)]
    seconds: f32,
    /// Seed of the start pose (eval's first episode uses 1000000 too).
    #[arg(long, default_value_t = 1_000_000)]
    seed: u64,
    /// Frames per second of simulated time (and of playback). GIF delays are whole
    /// hundredths of a second, so 25, 50 or 100 play back exactly.
    #[arg(long, default_value_t = 25, value_parser = clap::value_parser!(u32).range(1..=100))]
    fps: u32,
    #[arg(long, default_value_t = 640, value_parser = clap::value_parser!(u16).range(160..))]
    width: u16,
    #[arg(long, default_value_t = 360, value_parser = clap::value_parser!(u16).range(120..))]
    height: u16,
    /// Override a setting of the checkpoint's config, e.g. --set env.direction=backward.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    let loaded = load_policy(&args.checkpoint, &args.overrides)?;
    let env = evaluation_env(&loaded.config.env, args.seconds)?;
    info!(checkpoint = %loaded.path.display(), seconds = args.seconds, "rendering");
    let (summary, frames) = greedy_episode(&loaded.policy, &env, args.seed, true)?;
    let stride = frame_stride(env.dt, args.fps);
    let delay = (100.0 / f64::from(args.fps)).round() as u16;
    let direction = match env.direction {
        crawler_env::Direction::Forward => 1.0,
        crawler_env::Direction::Backward => -1.0,
    };
    let start_x = frames.first().map_or(0.0, |f| f.base[0]);
    let view =
        SideView { width: u32::from(args.width), height: u32::from(args.height), scale: f64::from(args.height) * 1.6 };
    let file = std::fs::File::create(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut gif = GifWriter::new(std::io::BufWriter::new(file), args.width, args.height, delay)?;
    let mut canvas = Canvas::new(view.width, view.height, Colour::White);
    for frame in frames.iter().step_by(stride) {
        view.draw(&mut canvas, frame, start_x, direction);
        gif.add(&canvas)?;
    }
    let count = gif.frames();
    drop(gif);
    eprintln!(
        "{}: {count} frames at {} fps, {:.2} m in {:.1} s ({:.3} m/s, {} flips)",
        args.out.display(),
        args.fps,
        summary.distance,
        summary.duration,
        summary.speed,
        summary.flips
    );
    let report = serde_json::json!({
        "gif": args.out,
        "frames": count,
        "fps": args.fps,
        "width": args.width,
        "height": args.height,
        "speed": summary.speed,
        "distance": summary.distance,
        "flips": summary.flips,
        "checkpoint": loaded.path,
    });
    let mut stdout = std::io::stdout().lock();
    serde_json::to_writer_pretty(&mut stdout, &report)?;
    std::io::Write::write_all(&mut stdout, b"\n")?;
    Ok(())
}
