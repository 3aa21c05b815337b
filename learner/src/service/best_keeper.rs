//! The best-checkpoint thread: it plays each periodic checkpoint greedily beside training and
//! keeps the best as `checkpoints/best` (`crawler_run::best`).
//!
//! Why a thread of its own: an evaluation takes seconds of simulation, and the training loop
//! must never wait for it. Checkpoints offered while one is being evaluated are skipped, so it
//! costs at most one core's share and never queues up.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{SyncSender, TrySendError, sync_channel};
use std::thread::JoinHandle;

use crawler_run::best::{BestKeeper, EvaluationPlan};
use tracing::{info, warn};

/// The handle the training loop offers checkpoints to.
#[derive(Debug)]
pub(super) struct BestFeed {
    offers: Option<SyncSender<PathBuf>>,
    thread: Option<JoinHandle<()>>,
}

impl BestFeed {
    /// A feed for the checkpoints in `checkpoints`; a plan of 0 episodes makes it a no-op.
    pub fn start(checkpoints: &Path, plan: EvaluationPlan) -> std::io::Result<Self> {
        if plan.episodes == 0 {
            return Ok(Self { offers: None, thread: None });
        }
        let mut keeper = BestKeeper::new(checkpoints, plan);
        let (offers, checkpoints_in) = sync_channel::<PathBuf>(1);
        let thread = std::thread::Builder::new().name("best-checkpoint".into()).spawn(move || {
            for path in checkpoints_in {
                match keeper.consider(&path) {
                    Ok((e, true)) => info!(
                        checkpoint = %e.checkpoint, speed = e.mean_speed, min_speed = e.min_speed, flips = e.flips,
                        stuck = e.stuck_episodes, "new best checkpoint by greedy evaluation"
                    ),
                    Ok((e, false)) => info!(
                        checkpoint = %e.checkpoint, speed = e.mean_speed, flips = e.flips, stuck = e.stuck_episodes,
                        best_speed = keeper.best().map(|b| b.mean_speed), "evaluated; the best stays"
                    ),
                    // A pruned or unreadable checkpoint is skipped; the best so far stays.
                    Err(e) => warn!("best checkpoint: {e}"),
                }
            }
        })?;
        Ok(Self { offers: Some(offers), thread: Some(thread) })
    }

    /// Offers a fresh periodic checkpoint; skipped when the previous one is still being
    /// evaluated.
    pub fn offer(&self, checkpoint: &Path) {
        if let Some(offers) = &self.offers {
            match offers.try_send(checkpoint.to_path_buf()) {
                Ok(()) | Err(TrySendError::Full(_)) => {}
                Err(TrySendError::Disconnected(_)) => warn!("the best-checkpoint thread has stopped"),
            }
        }
    }
}

impl Drop for BestFeed {
    /// Lets an evaluation in progress finish (seconds at most), so `best` is never left
    /// half-written.
    fn drop(&mut self) {
        self.offers = None;
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            warn!("the best-checkpoint thread panicked");
        }
    }
}
