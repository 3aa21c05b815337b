//! What the crawler senses: the touch sites, the base's contact force, the joint angles read
//! off the bodies, and the 40-value observation ([`crate::observation`] documents it index by
//! index) with its per-decision noise.

use super::*;

/// Rotation of `child` relative to `parent` about the parent's +y axis, in (−π, π].
pub(super) fn hinge_angle(parent: &Rotation, child: &Rotation) -> f32 {
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
pub(super) fn touch_slot(is_knee: bool, local: Vector, half: f32) -> Option<usize> {
    if is_knee {
        // The knee site sits on link 1's axis at its far end: collider-local (L/2, 0, 0).
        let knee = Vector::new(LINK1_LENGTH / 2.0, 0.0, 0.0);
        return (local.distance(knee) <= TOUCH_SITE_RADIUS).then_some(0);
    }
    let index = obs::corner_index(local.to_array());
    let corner = Vector::from_array(obs::corner_position(index, half));
    (local.distance(corner) <= TOUCH_SITE_RADIUS).then_some(index)
}

impl Crawler {
    /// The total normal force on the base's contacts in the last physics step, in N.
    pub fn base_contact_force(&self) -> f32 {
        self.base_force
    }

    /// Reads the normal forces at the touch sites from the last contact solve, and the base's
    /// total contact force (every point, not only those at its corner sites).
    pub(super) fn read_touch_sensors(&mut self) {
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
    pub(super) fn draw_observation_noise(&mut self) {
        let sigma = self.physics.observation_noise;
        if sigma > 0.0 {
            let spread = sigma * 3.0f32.sqrt();
            for noise in &mut self.noise {
                *noise = self.rng.random_range(-spread..=spread);
            }
        }
    }

    /// The base's angular velocity in its own frame (MuJoCo's free-joint `qvel[3..6]`).
    pub(super) fn base_angvel_local(&self) -> Vector {
        let base = &self.world.bodies[self.handles.base];
        base.rotation().inverse() * base.angvel()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hinge_angle_is_signed_about_y() {
        let parent = Rotation::from_rotation_y(0.3);
        let child = Rotation::from_rotation_y(0.3 + 0.7);
        assert!((hinge_angle(&parent, &child) - 0.7).abs() < 1e-5);
        assert!((hinge_angle(&child, &parent) + 0.7).abs() < 1e-5);
    }
}
