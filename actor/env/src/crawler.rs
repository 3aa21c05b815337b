//! One crawler in its own rapier3d world.
//!
//! Each crawler owns a separate physics world, so its trajectory depends on its seed and its
//! actions only, never on how many crawlers run beside it. The world is rebuilt at every reset,
//! so no solver warm-start state leaks from one episode into the next.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rapier3d::math::{Pose, Rotation, Vector};
use rapier3d::prelude::*;

use super::config::{EnvConfig, ShoulderPair};
use super::model::*;
use super::observation::{self as obs, OBS_DIM};
use super::randomization::EpisodePhysics;

/// The most one physics step's landing penalty may charge ([`Reward::base_impact`]): a
/// degenerate contact cannot swamp a whole episode's return.
const MAX_BASE_IMPACT_CHARGE: f32 = 5.0;

/// The most one physics step's joint-limit penalty may charge ([`Reward::joint_limit`]): as
/// much as a step's upright reward, so a limit slammed far past cannot swamp an episode.
const MAX_JOINT_LIMIT_CHARGE: f32 = 0.5;

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

/// What one decision step produced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOutcome {
    pub reward: Reward,
    /// The episode ended on its own terms (too little progress): do not bootstrap.
    pub terminated: bool,
    /// The episode hit its time limit: the state is not terminal, bootstrap from it.
    pub truncated: bool,
}

impl StepOutcome {
    pub fn done(&self) -> bool {
        self.terminated || self.truncated
    }
}

/// Statistics of a finished episode.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EpisodeSummary {
    /// Distance covered by the base in the rewarded direction, in metres.
    pub distance: f32,
    /// Simulated duration in seconds.
    pub duration: f32,
    /// Mean speed in the rewarded direction, in m/s.
    pub speed: f32,
    pub reward: Reward,
    /// Times the base turned over (its top started facing downwards).
    pub flips: u32,
    pub terminated: bool,
    pub truncated: bool,
    /// Physics steps taken.
    pub physics_steps: u32,
    /// The base's contact force above `base_impact_threshold`, integrated over the episode
    /// (N·s): how hard it landed, measured whether or not the reward charges it.
    pub base_impact_impulse: f32,
}

/// World poses of the bodies at one physics step, for plots and animations.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseFrame {
    /// Simulated time since the episode's start, in seconds.
    pub time: f32,
    /// Translation (x, y, z) and quaternion (w, x, y, z) of base, link 1 and link 2.
    pub base: [f32; 7],
    pub link1: [f32; 7],
    pub link2: [f32; 7],
    /// Centre of the tip cube.
    pub tip: [f32; 3],
    /// Joint angles in radians.
    pub joint_angles: [f32; 2],
}

/// A crawler's state in the study's MuJoCo generalized coordinates; see
/// [`Crawler::generalized_state`].
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct GeneralizedState {
    /// Base position (3), base quaternion w, x, y, z (4), joint angles (2).
    pub qpos: [f32; 9],
    /// Base linear velocity, world frame (3); base angular velocity, base frame (3); joint
    /// rates (2).
    pub qvel: [f32; 8],
}

/// Why [`Crawler::set_generalized_state`] refused a state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum InvalidStateError {
    #[error("state value {index} (qpos then qvel, 0-based) is not finite")]
    NotFinite { index: usize },
    #[error("the base quaternion (qpos[3..7]) is zero; give a unit quaternion w, x, y, z")]
    ZeroQuaternion,
}

#[derive(Debug, Clone, Copy)]
struct Handles {
    base: RigidBodyHandle,
    link1: RigidBodyHandle,
    link2: RigidBodyHandle,
    base_collider: ColliderHandle,
    link1_collider: ColliderHandle,
    tip_collider: ColliderHandle,
    /// The shoulder (base–link 1) and knee (link 1–link 2) hinges.
    joints: [ImpulseJointHandle; 2],
    /// The base–link 1 contact pair as a soft constraint: a joint that locks nothing, whose
    /// motor is the pair (`env.shoulder_pair = "soft_constraint"`; see
    /// [`Crawler::set_shoulder_pair`]). `None` under the viscous stand-in.
    shoulder_pair: Option<ImpulseJointHandle>,
}

/// Running totals of the current episode.
#[derive(Debug, Clone, Copy, Default)]
struct EpisodeState {
    physics_steps: u32,
    start_x: f32,
    reward: Reward,
    flips: u32,
    flipped: bool,
    base_impact_impulse: f32,
}

/// A single crawler: physics, observation, reward and episode logic.
pub struct Crawler {
    config: EnvConfig,
    rng: ChaCha8Rng,
    world: PhysicsWorld,
    handles: Handles,
    episode: EpisodeState,
    applied_torques: [f32; 2],
    touches: [f32; 17],
    /// Total normal force on the base's contacts in the last physics step, N.
    base_force: f32,
    recording: Option<Vec<PoseFrame>>,
    /// This episode's physics (the env's own unless randomised).
    physics: EpisodePhysics,
    /// Torques decided but not yet at the motors: `physics.latency_steps` of them.
    in_flight: std::collections::VecDeque<[f32; 2]>,
    /// Observation noise of the current decision (zeros without noise).
    noise: [f32; OBS_DIM],
}

impl std::fmt::Debug for Crawler {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Crawler")
            .field("config", &self.config)
            .field("physics_steps", &self.episode.physics_steps)
            .field("base_x", &self.base_x())
            .finish_non_exhaustive()
    }
}

impl Crawler {
    /// A crawler reset to a start pose drawn with `seed`. The config must be valid
    /// (see [`EnvConfig::validate`]).
    pub fn new(config: EnvConfig, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let [q1, q2] = draw_start_pose(&config, &mut rng);
        let physics = config.randomization.draw(config.joint_limit_timeconst, &mut rng);
        let (world, handles) = build_world(&config, &physics, q1, q2);
        let mut crawler = Self {
            config,
            rng,
            world,
            handles,
            episode: EpisodeState::default(),
            applied_torques: [0.0; 2],
            touches: [0.0; 17],
            base_force: 0.0,
            recording: None,
            physics,
            in_flight: std::collections::VecDeque::new(),
            noise: [0.0; OBS_DIM],
        };
        crawler.start_episode();
        crawler
    }

    pub fn config(&self) -> &EnvConfig {
        &self.config
    }

    /// Starts a new episode from a fresh start pose: all bodies at rest.
    pub fn reset(&mut self) {
        let pose = draw_start_pose(&self.config, &mut self.rng);
        self.reset_to(pose);
    }

    /// Starts a new episode from the given joint angles (radians), clamped into the limits,
    /// with the episode's physics drawn anew when the env randomises it.
    pub fn reset_to(&mut self, joint_angles: [f32; 2]) {
        let q1 = joint_angles[0].clamp(JOINT1_RANGE[0], JOINT1_RANGE[1]);
        let q2 = joint_angles[1].clamp(JOINT2_RANGE[0], JOINT2_RANGE[1]);
        self.physics = self.config.randomization.draw(self.config.joint_limit_timeconst, &mut self.rng);
        (self.world, self.handles) = build_world(&self.config, &self.physics, q1, q2);
        self.start_episode();
    }

    /// This episode's physics: the env's own, or what the randomisation drew.
    pub fn episode_physics(&self) -> &EpisodePhysics {
        &self.physics
    }

    fn start_episode(&mut self) {
        self.in_flight.clear();
        self.in_flight.extend(std::iter::repeat_n([0.0; 2], self.physics.latency_steps as usize));
        self.draw_observation_noise();
        self.applied_torques = [0.0; 2];
        self.touches = [0.0; 17];
        self.base_force = 0.0;
        self.episode = EpisodeState { start_x: self.base_x(), ..EpisodeState::default() };
        let first_frame = self.pose_frame();
        if let Some(frames) = &mut self.recording {
            frames.clear();
            frames.push(first_frame);
        }
    }

    /// Applies `action` for `action_repeat` physics steps. After a terminated or truncated
    /// step, call [`Self::reset`] before stepping again.
    pub fn step(&mut self, action: u32) -> StepOutcome {
        let torques = self.config.action_torques(action);
        self.step_torques(torques)
    }

    /// Like [`Self::step`], with torques given directly (each clamped to ±τmax).
    pub fn step_torques(&mut self, torques: [f32; 2]) -> StepOutcome {
        let max = self.config.max_torque;
        let torques = torques.map(|t| if t.is_finite() { t.clamp(-max, max) } else { 0.0 });
        let direction = self.config.direction.sign();
        let mut reward = Reward::default();
        let mut outcome = StepOutcome { reward, terminated: false, truncated: false };
        for _ in 0..self.config.action_repeat {
            let x_before = self.base_x();
            self.physics_step(torques);
            let dx = direction * (self.base_x() - x_before);
            reward += Reward {
                position: self.config.position_reward_weight * position_reward(dx),
                upright: upright_reward(self.base_rotation()),
                tilt_rate: self.tilt_rate_reward(),
                base_impact: self.base_impact_reward(),
                joint_limit: self.joint_limit_reward(),
            };
            if self.track_tilt() {
                outcome.terminated = true;
                break;
            }

            let steps = self.episode.physics_steps;
            if steps >= self.config.min_episode_steps {
                let progress_per_step = self.distance() / steps as f32;
                if progress_per_step < self.config.min_progress_per_step {
                    outcome.terminated = true;
                    break;
                }
            }
            if steps >= self.config.max_episode_steps {
                outcome.truncated = true;
                break;
            }
        }
        self.applied_torques = torques;
        self.draw_observation_noise();
        self.episode.reward += reward;
        outcome.reward = reward;
        outcome
    }

    /// One physics step with motor torques `torques`, applied as equal and opposite torques
    /// on each joint's parent and child about the hinge axis.
    fn physics_step(&mut self, decided: [f32; 2]) {
        // Latency: the motors get the torques decided `latency_steps` physics steps ago.
        let torques = if self.physics.latency_steps > 0 {
            self.in_flight.push_back(decided);
            self.in_flight.pop_front().unwrap_or(decided)
        } else {
            decided
        };
        let strength = self.physics.motor_strength;
        let (angles, rates) = (self.joint_angles(), self.joint_rates());
        let mut torques = [torques[0] * strength[0], torques[1] * strength[1]];
        // The MJCF's base–link 1 contact acts on the shoulder beside its motor.
        match self.config.shoulder_pair {
            ShoulderPair::Viscous => torques[0] -= SHOULDER_DAMPING * rates[0],
            ShoulderPair::SoftConstraint => self.set_shoulder_pair(angles[0], rates[0]),
        }
        let soft_limits =
            if self.physics.joint_limit_timeconst > 0.0 { self.soft_limit_targets(angles, rates) } else { [None; 2] };
        let bodies = &mut self.world.bodies;
        let axis1 = bodies[self.handles.base].rotation() * Vector::Y;
        let axis2 = bodies[self.handles.link1].rotation() * Vector::Y;
        let base_torque = -torques[0] * axis1;
        let link1_torque = torques[0] * axis1 - torques[1] * axis2;
        let link2_torque = torques[1] * axis2;
        for (handle, torque) in
            [(self.handles.base, base_torque), (self.handles.link1, link1_torque), (self.handles.link2, link2_torque)]
        {
            let body = &mut bodies[handle];
            body.reset_torques(false);
            body.add_torque(torque, true);
        }
        self.push_if_due();
        self.step_with_soft_limits(soft_limits);
        self.episode.physics_steps += 1;
        self.read_touch_sensors();
        if let Some(frames) = &mut self.recording {
            let frame = pose_frame(&self.world, &self.handles, self.episode.physics_steps as f32 * self.config.dt);
            frames.push(frame);
        }
    }

    /// Steps the world with the soft limits of the joints past one, keeping them unilateral
    /// as MuJoCo's are: a limit acts only where the joint, left free, would not already
    /// return into range at least as fast as the limit's reference drives it (MuJoCo's
    /// `a₀ < a_ref`). The step is first taken from a copy of the world with every limit off;
    /// a limit whose joint ends that step slower than its target rate is engaged and the step
    /// taken again from the copy. So the free acceleration is rapier's own, with gravity,
    /// contacts, the free base and the other joint, rather than an estimate (an estimate
    /// from the motor torques alone left 12 % of the shoulder's engaged steps pulling the
    /// joint towards its limit; EXPERIMENTS.md, "Soft limits that only push"). Steps with no
    /// joint past a limit pay for neither the copy nor the second step.
    fn step_with_soft_limits(&mut self, limits: [Option<SoftLimitTarget>; 2]) {
        if limits == [None; 2] {
            // A limit engaged at the last step must not drive its joint on at that step's
            // target rate now that the joint is back in range: if it did, a crawler left at
            // rest with the knee just past its limit would creep, both joints turning at a
            // steady 0.4-0.8 rad/s under zero torque (EXPERIMENTS.md, "Two faults in the soft
            // limits…").
            self.release_engaged_soft_limits();
            self.world.step();
            return;
        }
        // The copy keeps the motors as the last step left them, and with them the impulse
        // rapier warm-starts a limit from while it stays engaged.
        let before = WorldSnapshot::take(&self.world);
        self.set_soft_limits([None; 2]);
        self.world.step();
        let free_rates = self.joint_rates();
        let active = [0, 1].map(|index| {
            limits[index].filter(|limit| limit.inward * free_rates[index] < limit.inward * limit.target_rate)
        });
        if active == [None; 2] {
            return;
        }
        before.restore_into(&mut self.world);
        self.set_soft_limits(active);
        self.world.step();
    }

    /// Sets the soft-constraint pair's motor for this step from the shoulder's angle and rate:
    /// MuJoCo's soft constraint `Δq̇1 = dt·[(1 − d)·a₀ + d·a_ref]` with
    /// `a_ref = −B·q̇1`, solved as the soft limits are (a velocity motor targeting
    /// `q̇1 + dt·a_ref` with the compliance `d/((1 − d)·dt)`), with the motor's own d and B
    /// ([`SHOULDER_PAIR_IMPEDANCE`]). Unlike a limit it acts in both directions, so it needs
    /// no free step first.
    fn set_shoulder_pair(&mut self, shoulder_angle: f32, shoulder_rate: f32) {
        let Some(handle) = self.handles.shoulder_pair else { return };
        let dt = self.config.dt;
        let [constant, cosine] = SHOULDER_PAIR_IMPEDANCE;
        let damping = compliance_damping(constant + cosine * shoulder_angle.cos(), dt);
        let target_rate = shoulder_rate * (1.0 - dt * SHOULDER_PAIR_REFERENCE_RATE);
        if let Some(joint) = self.world.impulse_joints.get_mut(handle, false) {
            joint.data.set_motor(JointAxis::AngX, 0.0, target_rate, 0.0, damping);
        }
    }

    /// Releases whichever soft limit is still engaged. Joints are written only where one is,
    /// so that steps far from the limits leave the joint set (and rapier's joint assembly,
    /// cached against its edits) alone.
    fn release_engaged_soft_limits(&mut self) {
        for joint_handle in self.handles.joints {
            let engaged = self
                .world
                .impulse_joints
                .get(joint_handle)
                .is_some_and(|joint| joint.data.motor_axes.contains(JointAxesMask::ANG_X));
            if engaged && let Some(joint) = self.world.impulse_joints.get_mut(joint_handle, false) {
                release_soft_limit(&mut joint.data);
            }
        }
    }

    /// Engages each joint's soft limit as `limits` says and releases the others.
    fn set_soft_limits(&mut self, limits: [Option<SoftLimitTarget>; 2]) {
        for (limit, joint_handle) in limits.into_iter().zip(self.handles.joints) {
            let Some(joint) = self.world.impulse_joints.get_mut(joint_handle, false) else { continue };
            match limit {
                Some(limit) => {
                    joint.data.set_motor(JointAxis::AngX, 0.0, limit.target_rate, 0.0, limit.compliance_damping);
                }
                None => release_soft_limit(&mut joint.data),
            }
        }
    }

    /// Every `push_interval_s` of an episode, rolls the whole crawler about its base's x axis
    /// by a rate drawn from ±`push_roll_rate`, pivoting on the base's lower edge on the side it
    /// rolls towards, as a shove from the side tips a box: each body gets the same added
    /// angular velocity, and the linear velocity that rotation gives its centre of mass.
    fn push_if_due(&mut self) {
        let (interval, max_rate) = (self.physics.push_interval_s, self.physics.push_roll_rate);
        if interval <= 0.0 || max_rate <= 0.0 {
            return;
        }
        let every = ((interval / self.config.dt).round() as u32).max(1);
        let step = self.episode.physics_steps;
        if step == 0 || !step.is_multiple_of(every) {
            return;
        }
        let rate = self.rng.random_range(-max_rate..=max_rate);
        let base = &self.world.bodies[self.handles.base];
        // A positive roll about x lifts the +y side: the pivot is the −y lower edge.
        let edge = Vector::new(0.0, -BASE_HALF_EXTENT * rate.signum(), -BASE_HALF_EXTENT);
        let (pivot, spin) = (base.translation() + base.rotation() * edge, rate * (base.rotation() * Vector::X));
        for handle in [self.handles.base, self.handles.link1, self.handles.link2] {
            let body = &mut self.world.bodies[handle];
            let linvel = body.linvel() + spin.cross(body.center_of_mass() - pivot);
            let angvel = body.angvel() + spin;
            body.set_linvel(linvel, true);
            body.set_angvel(angvel, true);
        }
    }

    /// Soft joint limits, as MuJoCo computes them (its soft-constraint model with the default
    /// `solreflimit` and `solimplimit`). A joint past a limit by r (negative: beyond it) with
    /// rate v, measured into the range, has the reference acceleration
    /// `a_ref = −b·v − k·d·r` (k = 1/(d_max·τ)², b = 2/(d_max·τ), τ the time constant, d the
    /// impedance at r). MuJoCo's constraint force is `f = d·(a_ref − a₀)/A`, a₀ being the
    /// joint's acceleration without the limit and A its inverse inertia along the limit, so
    /// the joint accelerates at `d·a_ref + (1 − d)·a₀`. The limit only pushes into range, so
    /// it is off whenever a₀ already exceeds a_ref.
    ///
    /// rapier solves the same equation: a velocity motor on the hinge targeting `v + dt·a_ref`
    /// whose compliance is MuJoCo's regulariser, `(1 − d)/d · A` (an acceleration-based motor
    /// with damping `d/((1 − d)·dt)`), gives the impulse `d·dt·(a_ref − a₀)/A`, with A and a₀
    /// (gravity, contacts, the other joint, the free base) found by rapier's solver as
    /// MuJoCo's are. Whether the limit acts at all is decided by
    /// [`Crawler::step_with_soft_limits`].
    ///
    /// Returns each joint's limit where the joint is past one, `None` where it is within
    /// its range.
    fn soft_limit_targets(&self, angles: [f32; 2], rates: [f32; 2]) -> [Option<SoftLimitTarget>; 2] {
        let timeconst = self.physics.joint_limit_timeconst;
        let stiffness = 1.0 / (LIMIT_IMPEDANCE_MAX * timeconst).powi(2);
        let damping = 2.0 / (LIMIT_IMPEDANCE_MAX * timeconst);
        let dt = self.config.dt;
        [0, 1].map(|index| {
            let ([low, high], angle, rate) = ([JOINT1_RANGE, JOINT2_RANGE][index], angles[index], rates[index]);
            // Distance into the range from the nearer violated limit (negative past it), and
            // the direction into the range.
            let (distance, inward) = if angle < low {
                (angle - low, 1.0)
            } else if angle > high {
                (high - angle, -1.0)
            } else {
                return None;
            };
            let impedance = limit_impedance(distance.abs());
            let reference = -damping * inward * rate - stiffness * impedance * distance;
            Some(SoftLimitTarget {
                inward,
                target_rate: rate + dt * inward * reference,
                compliance_damping: compliance_damping(impedance, dt),
            })
        })
    }

    /// This physics step's penalty on the base's rocking (see [`Reward::tilt_rate`]).
    fn tilt_rate_reward(&self) -> f32 {
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
    fn base_impact_reward(&mut self) -> f32 {
        let impulse = self.config.dt * (self.base_force - self.config.base_impact_threshold).max(0.0);
        self.episode.base_impact_impulse += impulse;
        -(self.config.base_impact_penalty * impulse).min(MAX_BASE_IMPACT_CHARGE)
    }

    /// This physics step's penalty on the joints' excursions past their limits (see
    /// [`Reward::joint_limit`]).
    fn joint_limit_reward(&self) -> f32 {
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

    /// The total normal force on the base's contacts in the last physics step, in N.
    pub fn base_contact_force(&self) -> f32 {
        self.base_force
    }

    /// Counts a flip when the base turns upside down, and returns whether it tilts further
    /// from upright than `max_tilt_deg` allows: both read the one up axis of this step.
    fn track_tilt(&mut self) -> bool {
        let up = self.base_rotation() * Vector::Z;
        let flipped = up.z < 0.0;
        if flipped && !self.episode.flipped {
            self.episode.flips += 1;
        }
        self.episode.flipped = flipped;
        // cos(180°) = −1: an up axis never points further down than that, so 180 never fires.
        up.z < self.config.max_tilt_deg.to_radians().cos()
    }

    /// Reads the normal forces at the touch sites from the last contact solve, and the base's
    /// total contact force (every point, not only those at its corner sites).
    fn read_touch_sensors(&mut self) {
        self.touches = [0.0; 17];
        self.base_force = 0.0;
        let inv_dt = 1.0 / self.config.dt;
        let sites: [(ColliderHandle, usize, f32); 3] = [
            (self.handles.tip_collider, 0, TIP_HALF_EXTENT),
            (self.handles.link1_collider, 8, 0.0),
            (self.handles.base_collider, 9, BASE_HALF_EXTENT),
        ];
        for (collider, first_slot, half) in sites {
            for pair in self.world.narrow_phase.contact_pairs_with(collider) {
                let ours_is_first = pair.collider1 == collider;
                for manifold in pair.solver_manifolds() {
                    for point in &manifold.points {
                        let local = if ours_is_first { point.local_p1 } else { point.local_p2 };
                        let force = point.data.impulse.abs() * inv_dt;
                        if collider == self.handles.base_collider {
                            self.base_force += force;
                        }
                        if let Some(slot) = touch_slot(collider == self.handles.link1_collider, local, half) {
                            self.touches[first_slot + slot] += force;
                        }
                    }
                }
            }
        }
    }

    /// Writes the current observation (see [`super::observation`]) into `out`.
    pub fn observe(&self, out: &mut [f32; OBS_DIM]) {
        let bodies = &self.world.bodies;
        let base = &bodies[self.handles.base];
        let link1 = &bodies[self.handles.link1];
        let link2 = &bodies[self.handles.link2];
        let rotation = *base.rotation();
        out[obs::BASE_Z] = base.translation().z;
        out[obs::BASE_QUAT].copy_from_slice(&[rotation.w, rotation.x, rotation.y, rotation.z]);
        out[obs::JOINT_ANGLES].copy_from_slice(&self.joint_angles());
        out[obs::BASE_LINVEL].copy_from_slice(&base.linvel().to_array());
        out[obs::BASE_ANGVEL].copy_from_slice(&self.base_angvel_local().to_array());
        out[obs::JOINT_RATES].copy_from_slice(&self.joint_rates());
        out[obs::LINK1_ANGVEL].copy_from_slice(&link1.angvel().to_array());
        out[obs::LINK2_ANGVEL].copy_from_slice(&link2.angvel().to_array());
        out[obs::TIP_TOUCH.start..obs::PREV_ACTION.start].copy_from_slice(&self.touches);
        out[obs::PREV_ACTION].copy_from_slice(&self.applied_torques);
        if self.physics.observation_noise > 0.0 {
            for (value, noise) in out.iter_mut().zip(&self.noise) {
                *value += noise;
            }
            // Noise keeps values physical: a touch sensor reads no pull, a quaternion's
            // components stay within ±1, torques within ±τmax (the learner's validation holds
            // actors to all three).
            for value in &mut out[obs::TIP_TOUCH.start..obs::PREV_ACTION.start] {
                *value = value.max(0.0);
            }
            for value in &mut out[obs::BASE_QUAT] {
                *value = value.clamp(-1.0, 1.0);
            }
            let max = self.config.max_torque;
            for value in &mut out[obs::PREV_ACTION] {
                *value = value.clamp(-max, max);
            }
        }
    }

    /// New observation noise for the next decision: uniform, zero-mean, with the configured
    /// standard deviation (a uniform draw over ±σ·√3).
    fn draw_observation_noise(&mut self) {
        let sigma = self.physics.observation_noise;
        if sigma > 0.0 {
            let spread = sigma * 3.0f32.sqrt();
            for noise in &mut self.noise {
                *noise = self.rng.random_range(-spread..=spread);
            }
        }
    }

    /// Joint angles (q1, q2) in radians: each child's rotation about its hinge's +y.
    pub fn joint_angles(&self) -> [f32; 2] {
        let bodies = &self.world.bodies;
        let base = bodies[self.handles.base].rotation();
        let link1 = bodies[self.handles.link1].rotation();
        let link2 = bodies[self.handles.link2].rotation();
        [hinge_angle(base, link1), hinge_angle(link1, link2)]
    }

    /// Joint rates (q̇1, q̇2) in rad/s.
    pub fn joint_rates(&self) -> [f32; 2] {
        let bodies = &self.world.bodies;
        let base = &bodies[self.handles.base];
        let link1 = &bodies[self.handles.link1];
        let link2 = &bodies[self.handles.link2];
        let axis1 = base.rotation() * Vector::Y;
        let axis2 = link1.rotation() * Vector::Y;
        [(link1.angvel() - base.angvel()).dot(axis1), (link2.angvel() - link1.angvel()).dot(axis2)]
    }

    /// The base's world x position.
    pub fn base_x(&self) -> f32 {
        self.world.bodies[self.handles.base].translation().x
    }

    fn base_rotation(&self) -> Rotation {
        *self.world.bodies[self.handles.base].rotation()
    }

    /// Distance covered this episode in the rewarded direction.
    pub fn distance(&self) -> f32 {
        self.config.direction.sign() * (self.base_x() - self.episode.start_x)
    }

    /// Physics steps taken this episode.
    pub fn episode_physics_steps(&self) -> u32 {
        self.episode.physics_steps
    }

    /// Whether the base is currently upside down.
    pub fn is_flipped(&self) -> bool {
        self.episode.flipped
    }

    /// Statistics of the episode so far; `outcome` is the step that ended it, if any.
    pub fn episode_summary(&self, outcome: Option<StepOutcome>) -> EpisodeSummary {
        let duration = self.episode.physics_steps as f32 * self.config.dt;
        let distance = self.distance();
        EpisodeSummary {
            distance,
            duration,
            speed: if duration > 0.0 { distance / duration } else { 0.0 },
            reward: self.episode.reward,
            flips: self.episode.flips,
            terminated: outcome.is_some_and(|o| o.terminated),
            truncated: outcome.is_some_and(|o| o.truncated),
            physics_steps: self.episode.physics_steps,
            base_impact_impulse: self.episode.base_impact_impulse,
        }
    }

    /// Starts (or stops) recording every body's pose at each physics step.
    pub fn set_recording(&mut self, enabled: bool) {
        self.recording = enabled.then(|| vec![self.pose_frame()]);
    }

    /// The frames recorded since recording started or the episode began.
    pub fn recorded_frames(&self) -> &[PoseFrame] {
        self.recording.as_deref().unwrap_or(&[])
    }

    fn pose_frame(&self) -> PoseFrame {
        pose_frame(&self.world, &self.handles, self.episode.physics_steps as f32 * self.config.dt)
    }

    /// The crawler's state in the generalized coordinates of the study's MuJoCo model: `qpos`
    /// is the base's position, its quaternion (w, x, y, z) and the joint angles; `qvel` the
    /// base's linear velocity (world frame), its angular velocity (base frame) and the joint
    /// rates. The sim-to-sim state replay (`scripts/mujoco-check replay`) reads and writes
    /// both engines through it.
    pub fn generalized_state(&self) -> GeneralizedState {
        let base = &self.world.bodies[self.handles.base];
        let (t, r) = (base.translation(), *base.rotation());
        let [q1, q2] = self.joint_angles();
        let [r1, r2] = self.joint_rates();
        let v = base.linvel();
        let w = self.base_angvel_local();
        GeneralizedState {
            qpos: [t.x, t.y, t.z, r.w, r.x, r.y, r.z, q1, q2],
            qvel: [v.x, v.y, v.z, w.x, w.y, w.z, r1, r2],
        }
    }

    /// Puts every body where `state` says, moving with the velocities it gives, as MuJoCo's
    /// `qpos`/`qvel` would (see [`Self::generalized_state`]). The episode's counters keep
    /// running; contacts are found afresh at the next step. A non-finite value or a zero
    /// quaternion is refused and leaves the crawler as it was.
    pub fn set_generalized_state(&mut self, state: &GeneralizedState) -> Result<(), InvalidStateError> {
        if let Some(index) = state.qpos.iter().chain(&state.qvel).position(|v| !v.is_finite()) {
            return Err(InvalidStateError::NotFinite { index });
        }
        let [x, y, z, qw, qx, qy, qz, q1, q2] = state.qpos;
        let quaternion = Rotation::from_xyzw(qx, qy, qz, qw);
        if quaternion.length() < 1e-6 {
            return Err(InvalidStateError::ZeroQuaternion);
        }
        let base_rotation = quaternion.normalize();
        let [vx, vy, vz, wx, wy, wz, rate1, rate2] = state.qvel;
        let base_origin = Vector::new(x, y, z);
        let base_angvel = base_rotation * Vector::new(wx, wy, wz);
        // Both hinges turn about the base's y axis: the chain stays in one plane of the base.
        let axis = base_rotation * Vector::Y;
        let link1_rotation = base_rotation * Rotation::from_rotation_y(q1);
        let link2_rotation = link1_rotation * Rotation::from_rotation_y(q2);
        let link1_origin = base_origin + base_rotation * Vector::new(BASE_HALF_EXTENT, 0.0, 0.0);
        let link2_origin = link1_origin + link1_rotation * Vector::new(LINK1_LENGTH, 0.0, 0.0);
        let link1_angvel = base_angvel + rate1 * axis;
        let link2_angvel = link1_angvel + rate2 * axis;
        // Velocities of the hinge points, then of each body's centre of mass (rapier's linvel).
        let base_linvel = Vector::new(vx, vy, vz);
        let link1_origin_velocity = base_linvel + base_angvel.cross(link1_origin - base_origin);
        let link2_origin_velocity = link1_origin_velocity + link1_angvel.cross(link2_origin - link1_origin);
        let handles = self.handles;
        let bodies = &mut self.world.bodies;
        for (handle, origin, rotation, origin_velocity, angvel) in [
            (handles.base, base_origin, base_rotation, base_linvel, base_angvel),
            (handles.link1, link1_origin, link1_rotation, link1_origin_velocity, link1_angvel),
            (handles.link2, link2_origin, link2_rotation, link2_origin_velocity, link2_angvel),
        ] {
            let body = &mut bodies[handle];
            body.set_position(Pose::from_parts(origin, rotation), true);
            let centre_of_mass = body.center_of_mass();
            body.set_linvel(origin_velocity + angvel.cross(centre_of_mass - origin), true);
            body.set_angvel(angvel, true);
        }
        Ok(())
    }

    /// The base's angular velocity in its own frame (MuJoCo's free-joint `qvel[3..6]`).
    fn base_angvel_local(&self) -> Vector {
        let base = &self.world.bodies[self.handles.base];
        base.rotation().inverse() * base.angvel()
    }

    /// Holds the base fixed at height `z` above its resting height (diagnostics: the arm
    /// then hangs free of the floor). Undone by the next reset.
    pub fn hold_base_in_air(&mut self, z: f32) {
        let handles = self.handles;
        let lift = Vector::new(0.0, 0.0, z);
        for handle in [handles.base, handles.link1, handles.link2] {
            let body = &mut self.world.bodies[handle];
            let translation = body.translation() + lift;
            body.set_translation(translation, true);
        }
        self.world.bodies[handles.base].set_body_type(RigidBodyType::Fixed, true);
    }
}

/// MuJoCo's default `solimplimit` (0.9, 0.95, 0.001, 0.5, 2): the impedance d of a limit
/// constraint rises from 0.9 at the limit to 0.95 at 1 mm (here, radians) past it.
const LIMIT_IMPEDANCE_MIN: f32 = 0.9;
const LIMIT_IMPEDANCE_MAX: f32 = 0.95;
const LIMIT_IMPEDANCE_WIDTH: f32 = 0.001;

/// Turns a soft limit's motor off and forgets its impulse: rapier warm-starts a motor from
/// its last impulse, and a limit engaged again later must start from none, as MuJoCo's
/// constraint does when it becomes active.
fn release_soft_limit(joint: &mut GenericJoint) {
    joint.motor_axes.remove(JointAxesMask::ANG_X);
    joint.motors[JointAxis::AngX as usize].impulse = 0.0;
}

/// The damping of an acceleration-based rapier motor whose compliance is MuJoCo's regulariser
/// for a soft constraint of impedance `impedance` (0 < d < 1), `d/((1 − d)·dt)`: such a motor
/// moves its joint's rate by `dt·[(1 − d)·a₀ + d·a_ref]` as MuJoCo does
/// ([`Crawler::soft_limit_targets`] derives it). Used by the soft limits and the soft pair.
fn compliance_damping(impedance: f32, dt: f32) -> f32 {
    impedance / ((1.0 - impedance) * dt)
}

/// One step's soft limit on a joint past it ([`Crawler::soft_limit_targets`]).
#[derive(Debug, Clone, Copy, PartialEq)]
struct SoftLimitTarget {
    /// The direction into the joint's range: +1 past the lower limit, −1 past the upper.
    inward: f32,
    /// The joint rate the limit drives towards this step, `v + dt·a_ref`, rad/s.
    target_rate: f32,
    /// The motor damping that makes its compliance MuJoCo's regulariser.
    compliance_damping: f32,
}

/// The parts of a world one step changes, copied so that a step can be taken again
/// ([`Crawler::step_with_soft_limits`]). The island manager is part of it even though no
/// body sleeps: it links every touching contact pair into an island, and a step that
/// makes or breaks a contact changes those links (rapier's debug builds assert that they
/// match the narrow phase). The joints are written back one by one into the live set
/// rather than replaced by the copy, because rapier's solver caches its joint assembly
/// against the set's edit counter, which a replaced set would wind back onto a value the
/// cache has already seen (and the solver would keep the joints' motors of the discarded
/// step).
struct WorldSnapshot {
    bodies: RigidBodySet,
    colliders: ColliderSet,
    impulse_joints: ImpulseJointSet,
    narrow_phase: NarrowPhase,
    broad_phase: BroadPhaseBvh,
    islands: IslandManager,
}

impl WorldSnapshot {
    fn take(world: &PhysicsWorld) -> Self {
        Self {
            bodies: world.bodies.clone(),
            colliders: world.colliders.clone(),
            impulse_joints: world.impulse_joints.clone(),
            narrow_phase: world.narrow_phase.clone(),
            broad_phase: world.broad_phase.clone(),
            islands: world.islands.clone(),
        }
    }

    /// Puts the copy back, keeping it for another try.
    fn restore_into(&self, world: &mut PhysicsWorld) {
        world.bodies.clone_from(&self.bodies);
        world.colliders.clone_from(&self.colliders);
        world.narrow_phase.clone_from(&self.narrow_phase);
        world.broad_phase.clone_from(&self.broad_phase);
        world.islands.clone_from(&self.islands);
        for (handle, saved) in self.impulse_joints.iter() {
            if let Some(live) = world.impulse_joints.get_mut(handle, false) {
                live.data = saved.data;
                live.impulses = saved.impulses;
            }
        }
    }
}

/// MuJoCo's impedance at a violation `depth` ≥ 0 for the limits' `solimp`: a smooth step
/// (midpoint 0.5, power 2) from the minimum to the maximum over the width.
fn limit_impedance(depth: f32) -> f32 {
    let x = depth / LIMIT_IMPEDANCE_WIDTH;
    if x >= 1.0 {
        return LIMIT_IMPEDANCE_MAX;
    }
    let y = if x <= 0.5 { 2.0 * x * x } else { 1.0 - 2.0 * (1.0 - x) * (1.0 - x) };
    LIMIT_IMPEDANCE_MIN + y * (LIMIT_IMPEDANCE_MAX - LIMIT_IMPEDANCE_MIN)
}

/// Draws the study's start pose: joint 1 uniform in its start range, joint 2 likewise, each
/// clamped into the joint's limits (the study's joint-2 range reaches below 0°).
fn draw_start_pose(config: &EnvConfig, rng: &mut ChaCha8Rng) -> [f32; 2] {
    let mut draw = |[low, high]: [f32; 2]| if high > low { rng.random_range(low..high) } else { low } * DEG;
    let q1 = draw(config.start_joint1_deg).clamp(JOINT1_RANGE[0], JOINT1_RANGE[1]);
    let q2 = draw(config.start_joint2_deg).clamp(JOINT2_RANGE[0], JOINT2_RANGE[1]);
    [q1, q2]
}

fn position_reward(dx: f32) -> f32 {
    if dx > 0.0 { 0.5 * (1.0 - (-100.0 * dx).exp()) } else { 0.5 * (-1.0 + (-100.0 * dx.abs()).exp()) }
}

fn upright_reward(rotation: Rotation) -> f32 {
    // The y angle of xyz Euler angles: asin of −R[2][0] = asin(2(wy − xz)).
    let sin_pitch = (2.0 * (rotation.w * rotation.y - rotation.x * rotation.z)).clamp(-1.0, 1.0);
    0.5 * (1.0 - sin_pitch.asin().abs() / std::f32::consts::PI)
}

/// Rotation of `child` relative to `parent` about the parent's +y axis, in (−π, π].
fn hinge_angle(parent: &Rotation, child: &Rotation) -> f32 {
    let relative = parent.inverse() * *child;
    let angle = 2.0 * relative.y.atan2(relative.w);
    // q and −q are the same rotation; keep the angle in (−π, π].
    if angle > std::f32::consts::PI {
        angle - std::f32::consts::TAU
    } else if angle <= -std::f32::consts::PI {
        angle + std::f32::consts::TAU
    } else {
        angle
    }
}

/// Which touch site (0-based, within its body's group) a contact point at `local` (in the
/// collider's frame) falls in, if any.
fn touch_slot(is_knee: bool, local: Vector, half: f32) -> Option<usize> {
    if is_knee {
        // The knee site sits on link 1's axis at its far end: collider-local (L/2, 0, 0).
        let knee = Vector::new(LINK1_LENGTH / 2.0, 0.0, 0.0);
        return (local.distance(knee) <= TOUCH_SITE_RADIUS).then_some(0);
    }
    let index = obs::corner_index(local.to_array());
    let corner = Vector::from_array(obs::corner_position(index, half));
    (local.distance(corner) <= TOUCH_SITE_RADIUS).then_some(index)
}

fn pose_frame(world: &PhysicsWorld, handles: &Handles, time: f32) -> PoseFrame {
    let pose7 = |handle: RigidBodyHandle| {
        let body = &world.bodies[handle];
        let t = body.translation();
        let r = body.rotation();
        [t.x, t.y, t.z, r.w, r.x, r.y, r.z]
    };
    let link2 = &world.bodies[handles.link2];
    let tip = link2.position() * Vector::new(LINK2_LENGTH, 0.0, 0.0);
    let rot = |h: RigidBodyHandle| *world.bodies[h].rotation();
    PoseFrame {
        time,
        base: pose7(handles.base),
        link1: pose7(handles.link1),
        link2: pose7(handles.link2),
        tip: tip.to_array(),
        joint_angles: [
            hinge_angle(&rot(handles.base), &rot(handles.link1)),
            hinge_angle(&rot(handles.link1), &rot(handles.link2)),
        ],
    }
}

/// Builds the crawler's world with the base at rest and the joints at (q1, q2). If the arm
/// would reach into the floor, the whole crawler is lifted just clear of it.
///
/// Long on purpose: it follows the MJCF body by body (base, link 1, link 2, tip, floor, the two
/// hinges and their soft limits), so that each block can be read against the model file.
fn build_world(config: &EnvConfig, physics: &EpisodePhysics, q1: f32, q2: f32) -> (PhysicsWorld, Handles) {
    let integration_parameters = IntegrationParameters {
        dt: config.dt,
        num_solver_iterations: config.solver_iterations as usize,
        // length_unit is 1 (metres), so the normalized distance is the distance.
        normalized_prediction_distance: config.contact_prediction,
        // Every contact with the floor is one with a fixed body, and only those: the
        // randomised stiffness stands for how sharply the floor stops a landing.
        static_contact_softness: SpringCoefficients {
            natural_frequency: physics.floor_contact_hz,
            ..SpringCoefficients::contact_static_defaults()
        },
        ..IntegrationParameters::default()
    };
    let mut world =
        PhysicsWorld { gravity: Vector::new(0.0, 0.0, GRAVITY), integration_parameters, ..PhysicsWorld::default() };

    // MuJoCo combines two geoms' frictions by taking the larger. With `sliding_base`, every
    // pair takes the smaller instead and the floor gets the largest body friction, so each
    // body slides with its own coefficient.
    let (rule, floor_friction) = if config.sliding_base {
        (CoefficientCombineRule::Min, LINK_FRICTION.max(TIP_FRICTION))
    } else {
        (CoefficientCombineRule::Max, FLOOR_FRICTION)
    };
    // Randomised physics scales every friction alike, and each body's mass.
    let friction = |mu: f32| mu * physics.friction_scale;
    let [base_mass, link1_mass, link2_mass] = physics.mass_scale;

    let link1_rotation = Rotation::from_rotation_y(q1);
    let link2_rotation = Rotation::from_rotation_y(q1 + q2);
    let link1_origin = Vector::new(BASE_HALF_EXTENT, 0.0, 0.0);
    let link2_origin = link1_origin + link1_rotation * Vector::new(LINK1_LENGTH, 0.0, 0.0);
    let lift = start_lift(link1_origin, link1_rotation, link2_origin, link2_rotation);
    let up = Vector::new(0.0, 0.0, lift);

    let floor = world.bodies.insert(RigidBodyBuilder::fixed());
    let floor_collider = ColliderBuilder::new(SharedShape::halfspace(Vector::Z))
        .translation(Vector::new(0.0, 0.0, FLOOR_Z))
        .friction(friction(floor_friction))
        .friction_combine_rule(rule);
    world.colliders.insert_with_parent(floor_collider, floor, &mut world.bodies);

    let body = |pose: Pose| RigidBodyBuilder::dynamic().pose(pose).can_sleep(false);
    let base = world.bodies.insert(body(Pose::from_translation(up)));
    let link1 = world.bodies.insert(body(Pose::from_parts(link1_origin + up, link1_rotation)));
    let link2 = world.bodies.insert(body(Pose::from_parts(link2_origin + up, link2_rotation)));

    let base_collider = world.colliders.insert_with_parent(
        ColliderBuilder::cuboid(BASE_HALF_EXTENT, BASE_HALF_EXTENT, BASE_HALF_EXTENT)
            .mass(BASE_MASS * base_mass)
            .friction(friction(BASE_FRICTION))
            .friction_combine_rule(rule),
        base,
        &mut world.bodies,
    );
    let link1_collider = world.colliders.insert_with_parent(
        ColliderBuilder::capsule_x(LINK1_LENGTH / 2.0, LINK_RADIUS)
            .translation(Vector::new(LINK1_LENGTH / 2.0, 0.0, 0.0))
            .mass(LINK1_MASS * link1_mass)
            .friction(friction(LINK_FRICTION))
            .friction_combine_rule(rule),
        link1,
        &mut world.bodies,
    );
    world.colliders.insert_with_parent(
        ColliderBuilder::capsule_x(LINK2_LENGTH / 2.0, LINK_RADIUS)
            .translation(Vector::new(LINK2_LENGTH / 2.0, 0.0, 0.0))
            .mass(LINK2_MASS * link2_mass)
            .friction(friction(LINK_FRICTION))
            .friction_combine_rule(rule),
        link2,
        &mut world.bodies,
    );
    let tip_collider = world.colliders.insert_with_parent(
        ColliderBuilder::cuboid(TIP_HALF_EXTENT, TIP_HALF_EXTENT, TIP_HALF_EXTENT)
            .translation(Vector::new(LINK2_LENGTH, 0.0, 0.0))
            .mass(TIP_MASS * link2_mass)
            .friction(friction(TIP_FRICTION))
            .friction_combine_rule(rule),
        link2,
        &mut world.bodies,
    );

    // Jointed bodies never touch each other (MuJoCo excludes parent–child pairs); the base
    // still collides with link 2 and the tip, which share no joint with it.
    // Rigid limits are rapier's limit constraints; soft ones are motors set at each step
    // (`Crawler::step_with_soft_limits`).
    let hinge = |anchor: Vector, range: [f32; 2]| {
        let joint = RevoluteJointBuilder::new(Vector::Y)
            .local_anchor1(anchor)
            .local_anchor2(Vector::ZERO)
            .contacts_enabled(false)
            .motor_model(MotorModel::AccelerationBased)
            .motor_max_force(f32::MAX);
        if physics.joint_limit_timeconst > 0.0 { joint } else { joint.limits(range) }
    };
    let shoulder = world.impulse_joints.insert(base, link1, hinge(link1_origin, JOINT1_RANGE), true);
    let knee =
        world.impulse_joints.insert(link1, link2, hinge(Vector::new(LINK1_LENGTH, 0.0, 0.0), JOINT2_RANGE), true);
    // The base–link 1 pair as a soft constraint: a second joint on the shoulder's frames that
    // locks no axis, so its motor (set each step) is all it does. It is apart from the hinge
    // because the hinge's own motor is the shoulder's soft limit.
    let shoulder_pair = (config.shoulder_pair == ShoulderPair::SoftConstraint).then(|| {
        let pair = GenericJointBuilder::new(JointAxesMask::empty())
            .local_axis1(Vector::Y)
            .local_axis2(Vector::Y)
            .local_anchor1(link1_origin)
            .local_anchor2(Vector::ZERO)
            .contacts_enabled(false)
            .motor_model(JointAxis::AngX, MotorModel::AccelerationBased)
            .motor_max_force(JointAxis::AngX, f32::MAX);
        world.impulse_joints.insert(base, link1, pair, true)
    });

    let handles = Handles {
        base,
        link1,
        link2,
        base_collider,
        link1_collider,
        tip_collider,
        joints: [shoulder, knee],
        shoulder_pair,
    };
    (world, handles)
}

/// How far to lift a crawler posed with its base at rest so that no part is below the floor.
fn start_lift(link1_origin: Vector, link1_rotation: Rotation, link2_origin: Vector, link2_rotation: Rotation) -> f32 {
    let mut lowest = -BASE_HALF_EXTENT;
    let link1_end = link1_origin + link1_rotation * Vector::new(LINK1_LENGTH, 0.0, 0.0);
    lowest = lowest.min(link1_end.z - LINK_RADIUS);
    let link2_end = link2_origin + link2_rotation * Vector::new(LINK2_LENGTH, 0.0, 0.0);
    lowest = lowest.min(link2_end.z - LINK_RADIUS);
    for corner in 0..8 {
        let local =
            Vector::from_array(obs::corner_position(corner, TIP_HALF_EXTENT)) + Vector::new(LINK2_LENGTH, 0.0, 0.0);
        lowest = lowest.min((link2_origin + link2_rotation * local).z);
    }
    (FLOOR_Z - lowest).max(0.0)
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

    #[test]
    fn hinge_angle_is_signed_about_y() {
        let parent = Rotation::from_rotation_y(0.3);
        let child = Rotation::from_rotation_y(0.3 + 0.7);
        assert!((hinge_angle(&parent, &child) - 0.7).abs() < 1e-5);
        assert!((hinge_angle(&child, &parent) + 0.7).abs() < 1e-5);
    }

    /// A crawler whose base rests on the floor with the joints at `angles` (rad) and rates
    /// `rates` (rad/s), and no episode end.
    fn crawler_posed(angles: [f32; 2], rates: [f32; 2]) -> Crawler {
        let config = EnvConfig {
            action_repeat: 1,
            min_episode_steps: u32::MAX / 2,
            max_episode_steps: u32::MAX / 2 + 1,
            ..EnvConfig::default()
        };
        let mut crawler = Crawler::new(config, 5);
        let mut state = crawler.generalized_state();
        [state.qpos[7], state.qpos[8]] = angles;
        state.qvel = [0.0; 8];
        [state.qvel[6], state.qvel[7]] = rates;
        crawler.set_generalized_state(&state).expect("a finite state");
        crawler
    }

    #[test]
    fn a_soft_limit_brakes_a_joint_going_out_and_lets_a_returning_one_go() {
        // MuJoCo's limit force is unilateral: it stops a joint moving past its limit, and it
        // is zero for a joint that returns into range faster than the limit's reference
        // would drive it (here a_ref ≈ −800 rad/s² against a₀ of a few). A two-sided limit
        // would brake the returning joint by about dt·d·|a_ref| ≈ 1.5 rad/s in one step.
        let shoulder_rate_after_one_step = |rate: f32| {
            // Just past the shoulder's lower limit (the arm raised).
            let mut crawler = crawler_posed([JOINT1_RANGE[0] - 0.01, 0.5], [rate, 0.0]);
            crawler.step_torques([0.0, 0.0]);
            crawler.joint_rates()[0]
        };
        let returning = shoulder_rate_after_one_step(8.0);
        assert!((returning - 8.0).abs() < 0.3, "a joint returning at 8 rad/s came out at {returning}");
        let leaving = shoulder_rate_after_one_step(-8.0);
        assert!(leaving > -8.0 + 1.0, "a joint leaving its range at 8 rad/s kept {leaving}");
    }

    #[test]
    fn a_soft_limit_holds_a_joint_that_gravity_pulls_past_it() {
        // Link 2 hangs past the knee's lower limit with the motors off: gravity drives it
        // further out, so the limit stays engaged and pushes it back in at every step (the
        // free step alone would let it fall at about 0.07 rad/s per step).
        let mut crawler = crawler_posed([-30.0 * DEG, JOINT2_RANGE[0] - 0.01], [0.0; 2]);
        for step in 0..10 {
            crawler.step_torques([0.0, 0.0]);
            let knee_rate = crawler.joint_rates()[1];
            assert!(knee_rate > 0.0, "step {step}: the knee moves out at {knee_rate} rad/s");
        }
    }

    #[test]
    fn limit_impedance_rises_smoothly_from_its_minimum_to_its_maximum() {
        assert!((limit_impedance(0.0) - LIMIT_IMPEDANCE_MIN).abs() < 1e-6);
        assert!((limit_impedance(LIMIT_IMPEDANCE_WIDTH / 2.0) - 0.925).abs() < 1e-6);
        assert_eq!(limit_impedance(LIMIT_IMPEDANCE_WIDTH), LIMIT_IMPEDANCE_MAX);
        assert_eq!(limit_impedance(0.5), LIMIT_IMPEDANCE_MAX);
        let mut previous = 0.0;
        for i in 0..=100 {
            let d = limit_impedance(i as f32 * LIMIT_IMPEDANCE_WIDTH / 100.0);
            assert!(d >= previous, "not monotone at {i}");
            previous = d;
        }
    }

    #[test]
    fn start_pose_stays_inside_the_joint_limits() {
        let config = EnvConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..1000 {
            let [q1, q2] = draw_start_pose(&config, &mut rng);
            assert!((-45.0 * DEG..=0.0).contains(&q1));
            assert!((0.0..=22.5 * DEG).contains(&q2));
        }
    }
}
