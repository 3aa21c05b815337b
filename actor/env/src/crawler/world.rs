//! Building a crawler's rapier world from the study's MJCF, body by body.

use super::*;

#[derive(Debug, Clone, Copy)]
pub(super) struct Handles {
    pub(super) base: RigidBodyHandle,
    pub(super) link1: RigidBodyHandle,
    pub(super) link2: RigidBodyHandle,
    pub(super) base_collider: ColliderHandle,
    pub(super) link1_collider: ColliderHandle,
    pub(super) tip_collider: ColliderHandle,
    /// The shoulder (base–link 1) and knee (link 1–link 2) hinges.
    pub(super) joints: [ImpulseJointHandle; 2],
    /// The base–link 1 contact pair as a soft constraint: a joint that locks nothing, whose
    /// motor is the pair (`env.shoulder_pair = "soft_constraint"`; see
    /// [`Crawler::set_shoulder_pair`]). `None` under the viscous stand-in.
    pub(super) shoulder_pair: Option<ImpulseJointHandle>,
}

/// Builds the crawler's world with the base at rest and the joints at (q1, q2). If the arm
/// would reach into the floor, the whole crawler is lifted just clear of it.
///
/// Long on purpose: it follows the MJCF body by body (base, link 1, link 2, tip, floor, the two
/// hinges and their soft limits), so that each block can be read against the model file.
pub(super) fn build_world(config: &EnvConfig, physics: &EpisodePhysics, q1: f32, q2: f32) -> (PhysicsWorld, Handles) {
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
pub(super) fn start_lift(
    link1_origin: Vector,
    link1_rotation: Rotation,
    link2_origin: Vector,
    link2_rotation: Rotation,
) -> f32 {
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
