//! `average`: the weight average of a run's newest checkpoints, as `checkpoints/average`.
//!
//! `average runs/<run>/checkpoints --last 20`. The learner writes it itself at the end of a
//! run whose config sets `learner.average_checkpoints`; this tool does the same for a run
//! that did not, or over another window. Its path goes to stdout, a summary to stderr; play
//! it with `eval runs/<run>/checkpoints/average` or `scripts/mujoco-check eval …/average`.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use crawler_run::average::average_newest;
use crawler_run::checkpoint;

#[derive(Debug, Parser)]
#[command(version, about = "Average the weights of a run's newest checkpoints into checkpoints/average")]
struct Args {
    /// A run's directory of checkpoints (`runs/<run>/checkpoints`).
    checkpoints: PathBuf,
    /// How many of the newest checkpoints to average (at least 2).
    #[arg(long, default_value_t = 20)]
    last: usize,
}

fn main() -> anyhow::Result<()> {
    crawler_cli::init_logging();
    let args = Args::parse();
    let path = average_newest(&args.checkpoints, args.last)
        .with_context(|| format!("averaging the newest {} checkpoints of {}", args.last, args.checkpoints.display()))?;
    let written = checkpoint::load(&path)?;
    let averaged = &written.meta.averaged_from;
    eprintln!(
        "{}: the weight average of {} checkpoints, {} … {}",
        path.display(),
        averaged.len(),
        averaged.first().map_or("", String::as_str),
        averaged.last().map_or("", String::as_str)
    );
    // The path is the tool's data: stdout, for scripts.
    let mut stdout = std::io::stdout().lock();
    writeln!(stdout, "{}", path.display())?;
    Ok(())
}
