//! `pick`: the checkpoint to ship among a run's candidates, by how often each fails on the
//! nominal physics, then under `eval --perturbed`'s (`crawler_run::pick` says why).
//!
//! `pick runs/<run>/checkpoints/average runs/<run>/checkpoints runs/<run>/checkpoints/best`.
//! List the preferred candidate first: an exact tie keeps it. The chosen path goes to stdout
//! (for scripts), each candidate's numbers and a warning for a risky pick (or one that failed
//! on the nominal physics) to stderr, and with
//! `--record FILE` the whole selection as JSON to FILE.
//!
//! Exit status: 0 when a checkpoint was chosen, 3 (`RISKY_EXIT_CODE`) when it was chosen but
//! is a risk (it still fails in more than `RISKY_FAILURE_SHARE` of its episodes, which the
//! warning names; the path is printed all the same), 1 when none could be evaluated.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Parser;
use crawler_run::pick::{RISKY_EXIT_CODE, failure_share, pick};
use tracing::warn;

#[derive(Debug, Parser)]
#[command(
    version,
    about = "Pick the checkpoint that fails least on the nominal physics, then under perturbed physics, then crawls \
             fastest",
    after_help = "Exit status: 0 chosen; 3 chosen, but even it fails in more of its episodes than the risk line \
                  (a risk; the warning gives both shares); 1 none could be evaluated. The chosen path goes to \
                  stdout in both the first cases."
)]
struct Args {
    /// Checkpoint directories (step-…, average, best) or directories of them (the newest is
    /// taken); the preferred first.
    #[arg(required = true)]
    candidates: Vec<PathBuf>,
    /// Episodes per candidate on each physics; episode i uses `eval`'s seed + i, so
    /// `eval --episodes N` and `eval --perturbed --episodes N` reproduce each candidate's
    /// numbers.
    #[arg(long, default_value_t = 100)]
    episodes: u32,
    /// Simulated seconds per episode.
    #[arg(long, default_value_t = 20.0)]
    seconds: f32,
    /// Write the selection (every candidate's evaluation, the chosen one) as JSON here.
    #[arg(long)]
    record: Option<PathBuf>,
}

fn main() -> anyhow::Result<ExitCode> {
    crawler_cli::init_logging();
    let args = Args::parse();
    anyhow::ensure!(args.episodes > 0, "--episodes must be at least 1");
    let selection = pick(&args.candidates, args.episodes, args.seconds)?;
    for candidate in &selection.candidates {
        eprintln!("pick: {candidate}");
    }
    let chosen = selection.chosen();
    eprintln!("pick: the checkpoint to ship: {}", chosen.path.display());
    if let Some(nominal) = selection.chosen_nominal().filter(|nominal| nominal.failed_episodes > 0) {
        warn!(
            "even the pick failed (stuck or flipped) in {} of its {} episodes on the nominal physics, as every \
             candidate did: a gait to ship sticks in none; train longer or another seed",
            nominal.failed_episodes, nominal.episodes
        );
    }
    if let Some(evaluation) = selection.chosen_evaluation().filter(|_| selection.risky()) {
        warn!(
            "even the pick failed in {:.0} % of its perturbed episodes (above {:.0} %): runs like it tumbled on the \
             study's MuJoCo model (EXPERIMENTS.md, \"Picking the checkpoint to ship\"); play it there \
             (scripts/mujoco-check eval {}) or train another seed",
            100.0 * failure_share(evaluation),
            100.0 * selection.risky_failure_share,
            chosen.path.display()
        );
    }
    if let Some(record) = &args.record {
        let json = serde_json::to_vec_pretty(&selection)?;
        std::fs::write(record, json).with_context(|| format!("writing the selection to {}", record.display()))?;
    }
    let mut stdout = std::io::stdout().lock();
    writeln!(stdout, "{}", chosen.path.display())?;
    stdout.flush()?;
    Ok(if selection.risky() { ExitCode::from(RISKY_EXIT_CODE) } else { ExitCode::SUCCESS })
}
