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

mod reward;
mod sensors;
mod soft_constraints;
mod state;
mod world;

pub use reward::Reward;
pub use state::{GeneralizedState, InvalidStateError, PoseFrame};

use reward::{position_reward, upright_reward};
use sensors::hinge_angle;
use state::pose_frame;
use world::{Handles, build_world};

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

/// Draws the study's start pose: joint 1 uniform in its start range, joint 2 likewise, each
/// clamped into the joint's limits (the study's joint-2 range reaches below 0°).
fn draw_start_pose(config: &EnvConfig, rng: &mut ChaCha8Rng) -> [f32; 2] {
    let mut draw = |[low, high]: [f32; 2]| if high > low { rng.random_range(low..high) } else { low } * DEG;
    let q1 = draw(config.start_joint1_deg).clamp(JOINT1_RANGE[0], JOINT1_RANGE[1]);
    let q2 = draw(config.start_joint2_deg).clamp(JOINT2_RANGE[0], JOINT2_RANGE[1]);
    [q1, q2]
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
}

#[cfg(test)]
mod tests {
    use super::*;

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
