//! MuJoCo's soft constraints in rapier: the joint limits, kept unilateral by stepping again
//! from a copy of the world when the free step would leave a joint past its limit's
//! reference, and the base–link 1 contact pair as a soft constraint on the shoulder's rate.
//! Both use MuJoCo's impedance and regulariser (`solimp`, `solref`) as rapier motors.

use super::*;

/// MuJoCo's default `solimplimit` (0.9, 0.95, 0.001, 0.5, 2): the impedance d of a limit
/// constraint rises from 0.9 at the limit to 0.95 at 1 mm (here, radians) past it.
pub(super) const LIMIT_IMPEDANCE_MIN: f32 = 0.9;
pub(super) const LIMIT_IMPEDANCE_MAX: f32 = 0.95;
pub(super) const LIMIT_IMPEDANCE_WIDTH: f32 = 0.001;

/// Turns a soft limit's motor off and forgets its impulse: rapier warm-starts a motor from
/// its last impulse, and a limit engaged again later must start from none, as MuJoCo's
/// constraint does when it becomes active.
pub(super) fn release_soft_limit(joint: &mut GenericJoint) {
    joint.motor_axes.remove(JointAxesMask::ANG_X);
    joint.motors[JointAxis::AngX as usize].impulse = 0.0;
}

/// The damping of an acceleration-based rapier motor whose compliance is MuJoCo's regulariser
/// for a soft constraint of impedance `impedance` (0 < d < 1), `d/((1 − d)·dt)`: such a motor
/// moves its joint's rate by `dt·[(1 − d)·a₀ + d·a_ref]` as MuJoCo does
/// ([`Crawler::soft_limit_targets`] derives it). Used by the soft limits and the soft pair.
pub(super) fn compliance_damping(impedance: f32, dt: f32) -> f32 {
    impedance / ((1.0 - impedance) * dt)
}

/// One step's soft limit on a joint past it ([`Crawler::soft_limit_targets`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct SoftLimitTarget {
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
pub(super) fn limit_impedance(depth: f32) -> f32 {
    let x = depth / LIMIT_IMPEDANCE_WIDTH;
    if x >= 1.0 {
        return LIMIT_IMPEDANCE_MAX;
    }
    let y = if x <= 0.5 { 2.0 * x * x } else { 1.0 - 2.0 * (1.0 - x) * (1.0 - x) };
    LIMIT_IMPEDANCE_MIN + y * (LIMIT_IMPEDANCE_MAX - LIMIT_IMPEDANCE_MIN)
}

impl Crawler {
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
    pub(super) fn step_with_soft_limits(&mut self, limits: [Option<SoftLimitTarget>; 2]) {
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
    pub(super) fn set_shoulder_pair(&mut self, shoulder_angle: f32, shoulder_rate: f32) {
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
    pub(super) fn release_engaged_soft_limits(&mut self) {
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
    pub(super) fn set_soft_limits(&mut self, limits: [Option<SoftLimitTarget>; 2]) {
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
    pub(super) fn soft_limit_targets(&self, angles: [f32; 2], rates: [f32; 2]) -> [Option<SoftLimitTarget>; 2] {
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
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
