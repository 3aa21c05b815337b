//! A samples-per-insert limiter, after Reverb's `SampleToInsertRatio`.
//!
//! Keeps the learner from overtraining on stale data when actors are slow, and from
//! bursting through a backlog after a restart.

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
        RateLimiter::new(RateConfig { samples_per_insert: spi, warmup: 100, error_buffer: 64.0 })
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
