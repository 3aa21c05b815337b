//! Settings of one crawler environment. Every field has the study's value as its default.

use serde::{Deserialize, Serialize};

use super::error::EnvConfigError;
use super::observation::{MAX_OBSERVATION_HISTORY, OBS_DIM};
use super::randomization::Randomization;

/// Largest `env.position_reward_weight`: ten times the study's. It keeps a physics step's
/// reward, and so an episode's return, inside the bounds the protocol enforces
/// (`crawler_proto::validate::report_limits::MAX_ABS_RETURN`).
pub const MAX_POSITION_REWARD_WEIGHT: f32 = 10.0;

/// Largest `env.base_impact_penalty`, per N·s of base impulse over the threshold. The charge
/// a physics step can take is capped on its own (`MAX_BASE_IMPACT_CHARGE`, `crawler/reward.rs`), so
/// this bound is not what keeps returns inside the protocol's limits; it only refuses weights
/// far beyond any measured (EXPERIMENTS.md: 5–17).
pub const MAX_BASE_IMPACT_PENALTY: f32 = 50.0;

/// Largest `env.joint_limit_penalty`, per rad·s past the limits. As with the landing penalty
/// a physics step's charge is capped on its own (`MAX_JOINT_LIMIT_CHARGE`, `crawler/reward.rs`); this
/// only refuses weights that would charge any touch of a limit the whole cap.
pub const MAX_JOINT_LIMIT_PENALTY: f32 = 10_000.0;

/// Which way along x the crawler is rewarded for moving.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    #[default]
    Forward,
    Backward,
}

impl Direction {
    /// +1 for forward, −1 for backward: the factor applied to x displacements.
    pub fn sign(self) -> f32 {
        match self {
            Direction::Forward => 1.0,
            Direction::Backward => -1.0,
        }
    }
}

/// How the MJCF's contact pair between the base and link 1 acts on the shoulder. Link 1's
/// capsule starts at the hinge, inside the base, so the pair is in contact at every angle and
/// can only rub along the hinge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ShoulderPair {
    /// As MuJoCo solves it: a soft constraint on the shoulder's rate, which takes a tenth of
    /// every shoulder acceleration, the motor's included (`model::SHOULDER_PAIR_IMPEDANCE`).
    #[default]
    SoftConstraint,
    /// A viscous torque against the shoulder's rate (`model::SHOULDER_DAMPING`), fitted over
    /// rates alone: it leaves the motor's own acceleration whole, where the study's model takes
    /// a tenth of it (EXPERIMENTS.md, "The shoulder pair as MuJoCo's soft constraint…"). Kept
    /// to replay the physics of runs trained with it.
    Viscous,
}

/// Settings of the crawler environment. The defaults reproduce the study.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EnvConfig {
    /// Torque levels per joint, n; the action space has n² actions.
    pub action_levels: u32,
    /// Physics steps each decision is held for. 1 is the study (a decision every 2 ms).
    pub action_repeat: u32,
    /// Rewarded direction of travel.
    pub direction: Direction,
    /// Motor torque limit τmax in N·m; levels are spread evenly over [−τmax, τmax].
    pub max_torque: f32,
    /// Physics time step in seconds.
    pub dt: f32,
    /// Physics steps before the progress check may end an episode (2 s in the study).
    pub min_episode_steps: u32,
    /// Physics steps after which an episode is truncated (200 s in the study).
    pub max_episode_steps: u32,
    /// After the minimum duration, an episode terminates once the distance covered per
    /// physics step, averaged over the episode, falls below this (metres; 0.1 mm in the study).
    pub min_progress_per_step: f32,
    /// false: frictions combine by maximum, as MuJoCo does, so the base has the floor's 0.5.
    /// true: every body keeps its own friction, so the base truly slides (μ = 1e-4).
    pub sliding_base: bool,
    /// rapier's solver iterations per step.
    pub solver_iterations: u32,
    /// How close, in metres, two shapes must come before rapier makes a contact between them
    /// (its `prediction_distance`). rapier's own default, 0.02 m, makes speculative contacts:
    /// a landing is felt a step before the shapes touch. The study's MuJoCo model makes a
    /// contact only once shapes penetrate (geom margin 0), so 0 is the faithful value: it
    /// halves the one-step error of `scripts/mujoco-check replay` from airborne states
    /// (EXPERIMENTS.md, "Speculative contacts, a roll lever that failed…").
    pub contact_prediction: f32,
    /// Range in degrees from which joint 1's start angle is drawn uniformly.
    pub start_joint1_deg: [f32; 2],
    /// Range in degrees from which joint 2's start angle is drawn uniformly; the draw is
    /// clamped into joint 2's limits (0°…150°).
    pub start_joint2_deg: [f32; 2],
    /// Joint limits: 0 makes them rigid (rapier's limit constraints). A positive value makes
    /// them soft as MuJoCo's are, with this time constant (seconds) in MuJoCo's own
    /// soft-constraint formula, unilateral as MuJoCo's (`Crawler::soft_limit_targets`,
    /// `Crawler::step_with_soft_limits`); 0.02 s is MuJoCo's default `solreflimit`, which the
    /// study's model keeps. Rigid limits are what let open-loop gaits
    /// and learned policies crawl here while they tumble on the study's model.
    pub joint_limit_timeconst: f32,
    /// How the study's base–link 1 contact pair acts on the shoulder: `soft_constraint` as
    /// MuJoCo solves it, `viscous` as a damper fitted over rates alone (see [`ShoulderPair`]).
    pub shoulder_pair: ShoulderPair,
    /// An episode terminates once the base tilts further than this from upright, in degrees
    /// (the angle between its up axis and the world's). 180 never terminates: the study. A
    /// smaller value ends episodes on a fall, as legged_gym does, so that a policy loses all
    /// future reward by tipping over and learns a margin from it; a gait that only stays up
    /// in one simulator's physics is what fails to transfer (EXPERIMENTS.md, "Fidelity").
    pub max_tilt_deg: f32,
    /// Weight k of the position reward (1: the study's reward). Each physics step earns
    /// k·0.5·(1 − e^(−100·dx)) for its progress dx. At the study's weight the upright term
    /// dominates a step's reward (0.5 against 0.048 at 0.5 m/s), and pitching the base by 20°
    /// costs as much as 0.6 m/s of speed earns; a larger k makes the policy trade pitch and
    /// safety margins for speed at a higher rate.
    pub position_reward_weight: f32,
    /// Weight w of a penalty on the base's rocking (0: the study's reward, none). Each physics
    /// step adds −w·dt·(ωx² + ωy²), ω being the base's angular velocity about its own two
    /// horizontal axes in rad/s (legged_gym's `ang_vel_xy` term), at most 0.5 in magnitude, so
    /// a second of rocking at ω costs w·ω². Gaits that jolt the base about its edges are the
    /// ones that crawl here and tumble on the study's model (EXPERIMENTS.md, "Fidelity").
    pub tilt_rate_penalty: f32,
    /// Weight w of a penalty on the joints' excursions past their limits (0: the study's
    /// reward, none). Each physics step adds −w·dt·Σ overshoot, the sum over both joints of
    /// how far each is past its limit in rad (legged_gym's `dof_pos_limits` term), at most 0.5
    /// in magnitude: a second spent 0.01 rad past a limit costs 0.01·w. The joint limits are
    /// soft on the study's model, and from states past a limit this engine moves the base
    /// further than MuJoCo does; a gait that leans on them carries over worse (EXPERIMENTS.md,
    /// "Every checkpoint of a run on the study's model…").
    pub joint_limit_penalty: f32,
    /// Weight w of a penalty on hard landings of the base (0: the study's reward, none). Each
    /// physics step adds −w·dt·max(0, F − `base_impact_threshold`), F being the total normal
    /// force the base's contacts carried in that step, in N, at most 5 in magnitude (ten steps'
    /// upright reward: a landing must cost more than one step's reward to be avoided): so a
    /// landing costs w per N·s of impulse above what the threshold lets through. On the
    /// study's model the gaits that tumble land the base hard on an edge (130–490 N), and a
    /// millimetre of asymmetry in MuJoCo's contact solution then rolls it onto a side
    /// (EXPERIMENTS.md, "Speculative contacts, a roll lever that failed…").
    pub base_impact_penalty: f32,
    /// The base's contact force, in N, that [`Self::base_impact_penalty`] lets through
    /// without a charge: resting on the floor carries the crawler's weight, about 9 N.
    pub base_impact_threshold: f32,
    /// How many decisions' observations the policy sees at once, newest first (1: the study's
    /// 40 values). With h > 1 each decision's input is the current observation followed by
    /// the h − 1 before it (`observation::stack_next`), as RMA-style adaptation does: from how
    /// the state moved under the last torques a policy can tell a soft floor or a weak motor
    /// from the nominal ones, and act for the physics it is in rather than for all of them.
    pub observation_history: u32,
    /// Per-episode physics randomisation (off by default).
    pub randomization: Randomization,
}

impl Default for EnvConfig {
    fn default() -> Self {
        Self {
            action_levels: 5,
            action_repeat: 1,
            direction: Direction::Forward,
            max_torque: 1.0,
            dt: 0.002,
            min_episode_steps: 1_000,
            max_episode_steps: 100_000,
            min_progress_per_step: 1e-4,
            sliding_base: false,
            solver_iterations: 4,
            contact_prediction: 0.0,
            start_joint1_deg: [-45.0, 0.0],
            start_joint2_deg: [-22.5, 22.5],
            joint_limit_timeconst: 0.02,
            shoulder_pair: ShoulderPair::default(),
            max_tilt_deg: 180.0,
            position_reward_weight: 1.0,
            tilt_rate_penalty: 0.0,
            joint_limit_penalty: 0.0,
            base_impact_penalty: 0.0,
            base_impact_threshold: 50.0,
            observation_history: 1,
            randomization: Randomization::default(),
        }
    }
}

impl EnvConfig {
    /// Number of discrete actions, n².
    pub fn num_actions(&self) -> usize {
        (self.action_levels as usize).pow(2)
    }

    /// Values in the policy's input per decision: the 40-value observation times
    /// [`Self::observation_history`].
    pub fn policy_input_dim(&self) -> usize {
        OBS_DIM * self.observation_history as usize
    }

    /// Checks every field against its allowed range.
    pub fn validate(&self) -> Result<(), EnvConfigError> {
        fn check(
            ok: bool,
            key: &'static str,
            value: impl ToString,
            allowed: &'static str,
        ) -> Result<(), EnvConfigError> {
            if ok { Ok(()) } else { Err(EnvConfigError { key, value: value.to_string(), allowed }) }
        }
        let levels = self.action_levels;
        check((2..=15).contains(&levels), "action_levels", levels, "an integer in 2..=15")?;
        let repeat = self.action_repeat;
        check((1..=500).contains(&repeat), "action_repeat", repeat, "an integer in 1..=500")?;
        let torque = self.max_torque;
        check(torque.is_finite() && torque > 0.0 && torque <= 100.0, "max_torque", torque, "a number in (0, 100] N·m")?;
        let dt = self.dt;
        check(dt.is_finite() && (1e-4..=0.02).contains(&dt), "dt", dt, "a number of seconds in [0.0001, 0.02]")?;
        // Any u32 step count works: the tools that play one endless episode (the gait bank,
        // the state replay) set both to about u32::MAX / 2.
        check(self.min_episode_steps >= 1, "min_episode_steps", self.min_episode_steps, "at least 1")?;
        check(
            self.max_episode_steps >= self.min_episode_steps,
            "max_episode_steps",
            self.max_episode_steps,
            "at least min_episode_steps",
        )?;
        let progress = self.min_progress_per_step;
        check(
            progress.is_finite() && (0.0..=0.01).contains(&progress),
            "min_progress_per_step",
            progress,
            "metres in [0, 0.01] per physics step (0: never ends an episode)",
        )?;
        let iters = self.solver_iterations;
        check((1..=100).contains(&iters), "solver_iterations", iters, "an integer in 1..=100")?;
        let prediction = self.contact_prediction;
        check(
            prediction.is_finite() && (0.0..=0.05).contains(&prediction),
            "contact_prediction",
            prediction,
            "a distance in [0, 0.05] m; 0: contacts from penetration on, as MuJoCo's",
        )?;
        let timeconst = self.joint_limit_timeconst;
        check(
            timeconst.is_finite() && (timeconst == 0.0 || (0.001..=1.0).contains(&timeconst)),
            "joint_limit_timeconst",
            timeconst,
            "0 (rigid limits) or a time constant in [0.001, 1] s",
        )?;
        let tilt = self.max_tilt_deg;
        check(
            tilt.is_finite() && tilt > 0.0 && tilt <= 180.0,
            "max_tilt_deg",
            tilt,
            "an angle in (0, 180] degrees; 180 never terminates",
        )?;
        let weight = self.position_reward_weight;
        check(
            weight.is_finite() && weight > 0.0 && weight <= MAX_POSITION_REWARD_WEIGHT,
            "position_reward_weight",
            weight,
            "a weight in (0, 10] (1: the study's reward)",
        )?;
        let penalty = self.tilt_rate_penalty;
        check(
            penalty.is_finite() && (0.0..=10.0).contains(&penalty),
            "tilt_rate_penalty",
            penalty,
            "a weight in [0, 10] (0: no penalty, the study's reward)",
        )?;
        let penalty = self.joint_limit_penalty;
        check(
            penalty.is_finite() && (0.0..=MAX_JOINT_LIMIT_PENALTY).contains(&penalty),
            "joint_limit_penalty",
            penalty,
            "a weight in [0, 10000] per rad·s (0: no penalty, the study's reward)",
        )?;
        let penalty = self.base_impact_penalty;
        check(
            penalty.is_finite() && (0.0..=MAX_BASE_IMPACT_PENALTY).contains(&penalty),
            "base_impact_penalty",
            penalty,
            "a weight in [0, 50] per N·s (0: no penalty, the study's reward)",
        )?;
        let threshold = self.base_impact_threshold;
        check(
            threshold.is_finite() && (0.0..=10_000.0).contains(&threshold),
            "base_impact_threshold",
            threshold,
            "a force in [0, 10000] N",
        )?;
        let history = self.observation_history;
        check(
            (1..=MAX_OBSERVATION_HISTORY).contains(&history),
            "observation_history",
            history,
            "an integer in 1..=8 (1: the study's 40-value observation)",
        )?;
        self.randomization.validate()?;
        for (key, range) in [("start_joint1_deg", self.start_joint1_deg), ("start_joint2_deg", self.start_joint2_deg)] {
            check(
                range.iter().all(|v| v.is_finite() && (-180.0..=180.0).contains(v)) && range[0] <= range[1],
                key,
                format!("{range:?}"),
                "[low, high] with -180 ≤ low ≤ high ≤ 180, in degrees",
            )?;
        }
        Ok(())
    }

    /// The torque of level `level` of `action_levels`, evenly spaced in [−τmax, τmax].
    pub fn torque_of_level(&self, level: u32) -> f32 {
        let span = (self.action_levels - 1).max(1) as f32;
        -self.max_torque + 2.0 * self.max_torque * level as f32 / span
    }

    /// Joint torques (τ1, τ2) of action `action`: joint 1 takes level `action / n`,
    /// joint 2 level `action % n`.
    pub fn action_torques(&self, action: u32) -> [f32; 2] {
        let n = self.action_levels;
        [self.torque_of_level(action / n), self.torque_of_level(action % n)]
    }
}
