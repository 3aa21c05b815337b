//! An open-loop square-wave gait: the physics regression check and the benchmark's workload.

/// Each joint's torque flips between `high` and `low` every half period; joint 2 lags joint 1
/// by `phase_lag` of a period.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SquareWaveGait {
    pub period: f32,
    /// Torques (τ1, τ2) during the first half of joint i's cycle.
    pub high: [f32; 2],
    /// Torques (τ1, τ2) during the second half.
    pub low: [f32; 2],
    /// Fraction of a period by which joint 2's wave lags joint 1's.
    pub phase_lag: f32,
}

impl SquareWaveGait {
    /// A gait that crawls forward, upright, in this engine and on the study's MuJoCo model
    /// alike (0.24 and 0.12 m/s over the gait bank's three starts, no flips in either:
    /// `scripts/mujoco-check gaits`). A half-strength knee keeps the base down.
    pub const FORWARD: SquareWaveGait =
        SquareWaveGait { period: 0.3, high: [-1.0, 0.5], low: [0.0, -0.5], phase_lag: 0.0 };

    /// The gait this engine let crawl at 0.73 m/s while it had rigid joint limits, and which
    /// tumbles on the study's MuJoCo model (about 100 flips in 20 s) and here (from some
    /// starts): the canary of the forgiving physics issue 18 fixed.
    pub const TUMBLES_IN_MUJOCO: SquareWaveGait =
        SquareWaveGait { period: 0.3, high: [-1.0, 1.0], low: [0.0, -1.0], phase_lag: 0.0 };

    /// Torques (τ1, τ2) at time `t` seconds.
    pub fn torques(&self, t: f32) -> [f32; 2] {
        let first_half = |phase: f32| (t / self.period - phase).rem_euclid(1.0) < 0.5;
        let joint = |j: usize, phase: f32| {
            if first_half(phase) { self.high[j] } else { self.low[j] }
        };
        [joint(0, 0.0), joint(1, self.phase_lag)]
    }
}
