//! The crawler's state outside the step: the poses recorded for plots and animations, and its
//! state in MuJoCo's generalized coordinates (`qpos`, `qvel`), read and written for the
//! sim-to-sim replay.

use super::*;

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

pub(super) fn pose_frame(world: &PhysicsWorld, handles: &Handles, time: f32) -> PoseFrame {
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

impl Crawler {
    /// Starts (or stops) recording every body's pose at each physics step.
    pub fn set_recording(&mut self, enabled: bool) {
        self.recording = enabled.then(|| vec![self.pose_frame()]);
    }

    /// The frames recorded since recording started or the episode began.
    pub fn recorded_frames(&self) -> &[PoseFrame] {
        self.recording.as_deref().unwrap_or(&[])
    }

    pub(super) fn pose_frame(&self) -> PoseFrame {
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
