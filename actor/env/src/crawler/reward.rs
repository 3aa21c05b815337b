//! The reward, term by term: the study's position and upright terms, and the penalties the
//! presets may add (the base's rocking, its hard landings, the joints' excursions past their
//! limits), each summed over the physics steps a decision is held for.

use super::*;

/// The most one physics step's landing penalty may charge ([`Reward::base_impact`]): a
/// degenerate contact cannot swamp a whole episode's return.
pub(super) const MAX_BASE_IMPACT_CHARGE: f32 = 5.0;

/// The most one physics step's joint-limit penalty may charge ([`Reward::joint_limit`]): as
/// much as a step's upright reward, so a limit slammed far past cannot swamp an episode.
pub(super) const MAX_JOINT_LIMIT_CHARGE: f32 = 0.5;

/// The reward of one decision step, by component. Both are sums over the physics steps the
/// decision was held for, so their scale per second does not depend on the action repeat.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Reward {
    /// `k·0.5·(1 − e^(−100·dx))` for dx > 0, else `k·0.5·(−1 + e^(−100·|dx|))`, with dx the
    /// base's x displacement in the rewarded direction and k the env's
    /// `position_reward_weight` (1, the study's, by default).
    pub position: f32,
    /// `0.5·(1 − |pitch|/π)`, pitch being the base's rotation about y (xyz Euler angles).
    pub upright: f32,
    /// `−min(w·dt·(ωx² + ωy²), 0.5)` with w the env's `tilt_rate_penalty` (0 by default): the
    /// base's rocking about its horizontal axes.
    pub tilt_rate: f32,
    /// `−min(w·dt·max(0, F − F₀), 5)` with w the env's `base_impact_penalty` (0 by default),
    /// F the base's contact force and F₀ `base_impact_threshold`: hard landings of the base.
    pub base_impact: f32,
    /// `−min(w·dt·Σ overshoot, 0.5)` with w the env's `joint_limit_penalty` (0 by default) and
    /// the sum over both joints of how far each is past its limit, in rad (legged_gym's
    /// `dof_pos_limits` term): gaits that lean on the limits.
    pub joint_limit: f32,
}

impl Reward {
    pub fn total(&self) -> f32 {
        self.position + self.upright + self.tilt_rate + self.base_impact + self.joint_limit
    }

    /// The largest |total| one decision can earn under `config`, which the learner uses to
    /// reject out-of-range rewards from the network. Each physics step earns a position reward
    /// in (−0.5·k, 0.5·k) (k the env's `position_reward_weight`), an upright reward in
    /// [0, 0.5] and a tilt-rate charge in [−0.5, 0], so at most 0.5·k + 0.5 in magnitude, plus
    /// a landing charge of at most [`MAX_BASE_IMPACT_CHARGE`] where the env charges landings
    /// and a joint-limit charge of at most [`MAX_JOINT_LIMIT_CHARGE`] where it charges those;
    /// the margin covers rounding.
    pub fn max_abs_total(config: &EnvConfig) -> f32 {
        let landing = if config.base_impact_penalty > 0.0 { MAX_BASE_IMPACT_CHARGE } else { 0.0 };
        let limits = if config.joint_limit_penalty > 0.0 { MAX_JOINT_LIMIT_CHARGE } else { 0.0 };
        let per_step = 0.5 * config.position_reward_weight + 0.5 + landing + limits;
        1.01 * per_step * config.action_repeat as f32
    }
}

/// Sums term by term: a decision's reward over its physics steps, an episode's over its
/// decisions. Listing every field here (no `..`) makes a new term a compile error until it
/// is summed too.
impl std::ops::AddAssign for Reward {
    fn add_assign(&mut self, step: Reward) {
        let Reward { position, upright, tilt_rate, base_impact, joint_limit } = step;
        self.position += position;
        self.upright += upright;
        self.tilt_rate += tilt_rate;
        self.base_impact += base_impact;
        self.joint_limit += joint_limit;
    }
}

pub(super) fn position_reward(dx: f32) -> f32 {
    if dx > 0.0 { 0.5 * (1.0 - (-100.0 * dx).exp()) } else { 0.5 * (-1.0 + (-100.0 * dx.abs()).exp()) }
}

pub(super) fn upright_reward(rotation: Rotation) -> f32 {
    // The y angle of xyz Euler angles: asin of −R[2][0] = asin(2(wy − xz)).
    let sin_pitch = (2.0 * (rotation.w * rotation.y - rotation.x * rotation.z)).clamp(-1.0, 1.0);
    0.5 * (1.0 - sin_pitch.asin().abs() / std::f32::consts::PI)
}

impl Crawler {
    /// This physics step's penalty on the base's rocking (see [`Reward::tilt_rate`]).
    pub(super) fn tilt_rate_reward(&self) -> f32 {
        let weight = self.config.tilt_rate_penalty;
        if weight == 0.0 {
            return 0.0;
        }
        let local = self.base_angvel_local();
        -(weight * self.config.dt * (local.x * local.x + local.y * local.y)).min(0.5)
    }

    /// This physics step's penalty on a hard landing of the base (see [`Reward::base_impact`]).
    /// It also adds the step's excess impulse to the episode's total, which is measured with
    /// or without a charge.
    pub(super) fn base_impact_reward(&mut self) -> f32 {
        let impulse = self.config.dt * (self.base_force - self.config.base_impact_threshold).max(0.0);
        self.episode.base_impact_impulse += impulse;
        -(self.config.base_impact_penalty * impulse).min(MAX_BASE_IMPACT_CHARGE)
    }

    /// This physics step's penalty on the joints' excursions past their limits (see
    /// [`Reward::joint_limit`]).
    pub(super) fn joint_limit_reward(&self) -> f32 {
        let weight = self.config.joint_limit_penalty;
        if weight == 0.0 {
            return 0.0;
        }
        let overshoot: f32 = self
            .joint_angles()
            .into_iter()
            .zip([JOINT1_RANGE, JOINT2_RANGE])
            .map(|(angle, [low, high])| (low - angle).max(angle - high).max(0.0))
            .sum();
        -(weight * self.config.dt * overshoot).min(MAX_JOINT_LIMIT_CHARGE)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn position_reward_is_odd_and_saturates() {
        assert_eq!(position_reward(0.0), 0.0);
        assert!((position_reward(0.001) + position_reward(-0.001)).abs() < 1e-7);
        assert!(position_reward(1.0) > 0.499);
        assert!(position_reward(-1.0) < -0.499);
    }

    #[test]
    fn upright_reward_is_half_when_level_and_falls_with_pitch() {
        assert!((upright_reward(Rotation::IDENTITY) - 0.5).abs() < 1e-6);
        let tilted = upright_reward(Rotation::from_rotation_y(0.5));
        assert!((tilted - 0.5 * (1.0 - 0.5 / std::f32::consts::PI)).abs() < 1e-5, "{tilted}");
    }
}
