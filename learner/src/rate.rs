//! A samples-per-insert limiter, after Reverb's `SampleToInsertRatio`.
//!
//! Keeps the learner from overtraining on stale data when actors are slow, and from
//! bursting through a backlog after a restart. With `rate.limit_inserts` it limits the other
//! side too: [`RateLimiter::insert_headroom`] is how many more transitions the learner takes
//! before samples per insert would leave its band, which the learner hands out to actors as
//! insert credit (`service/credit.rs`). After the warm-up, sampling keeps
//! `samples_per_insert · inserted − sampled` at or above `−error_buffer` and the credit stops
//! once it reaches `error_buffer` (past it only what was already granted arrives), so the
//! data-to-update ratio a preset was tuned at holds on any machine, whichever side is slower.

pub use crawler_run::config::RateConfig;

/// Counts inserts and samples since this process started (or since [`RateLimiter::reset`]).
#[derive(Debug, Clone)]
pub struct RateLimiter {
    config: RateConfig,
    inserted: u64,
    sampled: u64,
    /// `inserted` at the moment the replay first held `warmup` transitions.
    baseline: Option<u64>,
}

impl RateLimiter {
    pub fn new(config: RateConfig) -> Self {
        Self { config, inserted: 0, sampled: 0, baseline: None }
    }

    pub fn config(&self) -> &RateConfig {
        &self.config
    }

    /// Starts the accounting afresh, for a learner resumed with `replay_len` transitions
    /// already stored: sampling may start at once if they cover the warm-up, but only at the
    /// configured ratio to new inserts, never in a burst.
    pub fn reset(&mut self, replay_len: usize) {
        self.inserted = 0;
        self.sampled = 0;
        self.baseline = (replay_len >= self.config.warmup).then_some(0);
    }

    /// Records `count` inserted transitions; `replay_len` is the replay's size afterwards.
    pub fn record_insert(&mut self, count: usize, replay_len: usize) {
        self.inserted += count as u64;
        if self.baseline.is_none() && replay_len >= self.config.warmup {
            self.baseline = Some(self.inserted);
        }
    }

    pub fn record_sample(&mut self, count: usize) {
        self.sampled += count as u64;
    }

    /// Whether `count` more transitions may be sampled now.
    pub fn can_sample(&self, count: usize) -> bool {
        let Some(baseline) = self.baseline else { return false };
        if self.config.samples_per_insert <= 0.0 {
            return true;
        }
        let budget = self.config.samples_per_insert * (self.inserted - baseline) as f64 + self.config.error_buffer;
        (self.sampled + count as u64) as f64 <= budget
    }

    /// Transitions the learner may still take, beyond `queued` ones received but not yet
    /// recorded, before inserting would put samples per insert above its band; before the
    /// warm-up is done, what it still needs plus the band. None when inserts are not limited.
    pub fn insert_headroom(&self, replay_len: usize, queued: u64) -> Option<u64> {
        let spi = self.config.samples_per_insert;
        if !self.config.limit_inserts || spi <= 0.0 {
            return None;
        }
        let band = self.config.error_buffer / spi;
        let room = match self.baseline {
            None => self.config.warmup.saturating_sub(replay_len) as f64 + band,
            Some(baseline) => {
                (self.config.error_buffer + self.sampled as f64) / spi - (self.inserted - baseline) as f64
            }
        };
        Some((room - queued as f64).max(0.0).floor() as u64)
    }

    /// Samples per insert realised since the warm-up (or the last reset); None before any
    /// insert counts.
    pub fn realised_samples_per_insert(&self) -> Option<f64> {
        let inserted = self.inserted - self.baseline?;
        (inserted > 0).then(|| self.sampled as f64 / inserted as f64)
    }

    pub fn warmed_up(&self) -> bool {
        self.baseline.is_some()
    }

    /// (inserted, sampled) since the last start or reset.
    pub fn counts(&self) -> (u64, u64) {
        (self.inserted, self.sampled)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limiter(spi: f64) -> RateLimiter {
        RateLimiter::new(RateConfig { samples_per_insert: spi, warmup: 100, error_buffer: 64.0, limit_inserts: true })
    }

    #[test]
    fn inserts_are_limited_to_the_band_once_warm() {
        let mut rate = limiter(8.0);
        // Before the warm-up: what it still needs plus the band (64 / 8 = 8 transitions).
        assert_eq!(rate.insert_headroom(0, 0), Some(108));
        assert_eq!(rate.insert_headroom(40, 30), Some(38));
        rate.record_insert(100, 100);
        // Warm, nothing sampled: 8 more transitions would use the whole band.
        assert_eq!(rate.insert_headroom(100, 0), Some(8));
        assert_eq!(rate.insert_headroom(100, 8), Some(0));
        rate.record_insert(8, 108);
        assert_eq!(rate.insert_headroom(108, 0), Some(0), "the band is used up: inserts wait");
        // Sampling frees room at the ratio: 32 samples, 4 transitions.
        assert!(rate.can_sample(32));
        rate.record_sample(32);
        assert_eq!(rate.insert_headroom(108, 0), Some(4));
        let off = RateLimiter::new(RateConfig { limit_inserts: false, ..*rate.config() });
        assert_eq!(off.insert_headroom(0, 0), None, "the sample-side mode hands out no credit");
    }

    #[test]
    fn with_both_sides_limited_a_slow_learner_keeps_the_ratio() {
        // Actors offer 64 transitions per turn, the learner samples 32 per turn: actors are 16
        // times faster than the ratio 8 needs. Inserts take only what the headroom allows.
        let mut rate = limiter(8.0);
        let mut replay = 0;
        for _ in 0..10_000 {
            let offered = 64;
            let taken = rate.insert_headroom(replay, 0).map_or(offered, |room| offered.min(room as usize));
            replay += taken;
            rate.record_insert(taken, replay);
            if rate.can_sample(32) {
                rate.record_sample(32);
            }
        }
        let realised = rate.realised_samples_per_insert().unwrap();
        assert!((realised - 8.0).abs() < 0.08, "{realised}");
        let mut sample_side = RateLimiter::new(RateConfig { limit_inserts: false, ..*rate.config() });
        let mut replay = 0;
        for _ in 0..10_000 {
            replay += 64;
            sample_side.record_insert(64, replay);
            if sample_side.can_sample(32) {
                sample_side.record_sample(32);
            }
        }
        let realised = sample_side.realised_samples_per_insert().unwrap();
        assert!(realised < 0.6, "the sample side alone lets the ratio fall to what the learner manages: {realised}");
    }

    #[test]
    fn nothing_is_sampled_before_warmup() {
        let mut rate = limiter(8.0);
        rate.record_insert(99, 99);
        assert!(!rate.can_sample(1));
        rate.record_insert(1, 100);
        assert!(rate.can_sample(32) && rate.can_sample(64) && !rate.can_sample(65));
    }

    #[test]
    fn samples_follow_inserts_at_the_ratio() {
        let mut rate = limiter(8.0);
        rate.record_insert(100, 100);
        let mut sampled = 0;
        for step in 0..1000 {
            rate.record_insert(4, 100 + 4 * step);
            while rate.can_sample(32) {
                rate.record_sample(32);
                sampled += 32;
            }
        }
        let ratio = sampled as f64 / 4000.0;
        assert!((ratio - 8.0).abs() < 0.05, "{ratio}");
    }

    #[test]
    fn a_resume_with_a_full_replay_allows_no_burst() {
        let mut rate = limiter(8.0);
        rate.record_insert(10_000, 10_000);
        rate.reset(10_000);
        assert!(rate.can_sample(64), "the error buffer lets training resume at once");
        rate.record_sample(64);
        assert!(!rate.can_sample(32), "but not past it until new data arrives");
        rate.record_insert(4, 10_004);
        assert!(rate.can_sample(32));
        let mut empty = limiter(8.0);
        empty.reset(0);
        assert!(!empty.can_sample(1), "a resume without replay warms up again");
    }
}
