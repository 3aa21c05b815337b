//! The inserting thread: it moves validated batches from the ingest queue into the replay
//! table while the training thread learns, and releases the replay streams of actors that
//! left. Inserting on its own thread means a flood is inserted as fast as the receive path
//! validates it, instead of a queue's worth between two gradient steps.

use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::Duration;

use crawler_proto as proto;

use super::edge::{Shared, lock};
use crate::replay::{Replay, StreamId, Transition};
use crate::table::Table;

/// How long the thread waits for a batch before it looks whether the table has closed.
const POLL: Duration = Duration::from_millis(20);

/// Inserts until the table closes (training ended) or the queue's sender goes (the receive
/// path has gone; the table is then closed, which ends training).
pub(super) fn insert(table: &Table, ingest: &Receiver<proto::TransitionBatch>, shared: &Shared) {
    while !table.is_closed() {
        match ingest.recv_timeout(POLL) {
            Ok(batch) => {
                let kept = table.insert(batch.len() as u64, batch.physics_steps, |replay| insert_batch(replay, &batch));
                // Out of the queue only once the rate limiter has counted it, so that the
                // insert limit never counts a batch in neither place.
                shared.queued_transitions.fetch_sub(batch.len() as u64, Ordering::Relaxed);
                lock(&shared.shares).leave_queue(batch.actor_id);
                let mut actors = lock(&shared.actors);
                let view = actors.entry(batch.actor_id).or_default();
                view.transitions += kept as u64;
                view.batches += 1;
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => table.close(),
        }
        let departed = std::mem::take(&mut *lock(&shared.departed));
        if !departed.is_empty() {
            // Everyone not live goes, including actors whose last batches arrived after they
            // had already been released.
            let live = shared.connected();
            table.lock().replay.release_streams(|actor| live.contains(&actor));
        }
    }
}

/// Stores a validated batch; returns how many transitions replay kept.
fn insert_batch(replay: &mut Replay, batch: &proto::TransitionBatch) -> usize {
    let dim = batch.obs_dim as usize;
    let mut kept = 0;
    for i in 0..batch.len() {
        let transition = Transition {
            observation: &batch.observations[i * dim..(i + 1) * dim],
            // Validated against the action count, which is at most 15² = 225.
            action: u8::try_from(batch.actions[i]).unwrap_or(u8::MAX),
            reward: batch.rewards[i],
            next_observation: &batch.next_observations[i * dim..(i + 1) * dim],
            terminated: batch.terminated[i],
            truncated: batch.truncated[i],
        };
        let stream = StreamId { actor: batch.actor_id, env: batch.env_ids[i] };
        if replay.insert(stream, &transition).is_ok() {
            kept += 1;
        }
    }
    kept
}
