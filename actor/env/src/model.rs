//! The study's physical model, transcribed from its MuJoCo file (`crawling_robot.xml`).
//!
//! Frames follow the MJCF: z is up, the crawler moves along x, both hinges turn about y.
//! The base's centre sits at the origin at rest and the floor is the plane z = −0.05.
//! A positive joint angle turns the child about +y, which points its +x end downwards.

/// Half extent of the cubic base (a 10 cm box).
pub const BASE_HALF_EXTENT: f32 = 0.05;
pub const BASE_MASS: f32 = 0.5;
/// The base's own friction. MuJoCo takes the larger of two geoms' frictions, so against the
/// floor (0.5) the base really has 0.5; see [`super::EnvConfig::sliding_base`].
pub const BASE_FRICTION: f32 = 1e-4;

/// Link 1: a capsule along its body's +x, hinged at the centre of the base's +x face.
pub const LINK1_LENGTH: f32 = 0.20;
pub const LINK1_MASS: f32 = 0.2;
/// Link 2: a capsule along its body's +x, hinged at link 1's far end.
pub const LINK2_LENGTH: f32 = 0.24;
pub const LINK2_MASS: f32 = 0.1;
pub const LINK_RADIUS: f32 = 0.01;
/// MJCF's default friction, which the capsules keep.
pub const LINK_FRICTION: f32 = 1.0;

/// The tip: a 2 cm cube fixed at link 2's far end. It grips the floor.
pub const TIP_HALF_EXTENT: f32 = 0.01;
pub const TIP_MASS: f32 = 0.1;
pub const TIP_FRICTION: f32 = 0.99;

/// Viscous damping at the shoulder, N·m·s/rad, for `env.shoulder_pair = "viscous"`. The MJCF
/// declares a contact pair between the base and link 1, whose capsule starts at the hinge and
/// so overlaps the base by its radius at every angle. Along the hinge that contact can only
/// rub. A least-squares fit of MuJoCo's shoulder acceleration over rates alone found a torque
/// against the shoulder's rate, −0.0069·q̇1 (400 random states, R² = 0.9997; `EXPERIMENTS.md`,
/// "State replay"); fitted against one MuJoCo step with and without the pair, the pair also
/// takes a tenth of every acceleration, which this term leaves whole (see
/// [`SHOULDER_PAIR_IMPEDANCE`]).
pub const SHOULDER_DAMPING: f32 = 0.0069;

/// The base–link 1 pair as MuJoCo solves it (`env.shoulder_pair = "soft_constraint"`): a soft
/// constraint on the shoulder's rate, under which one step changes the rate by
/// `dt·[(1 − d)·a₀ + d·a_ref]`, with a₀ the acceleration without the pair, `a_ref = −B·q̇1`
/// and the impedance `d = 0.054 + 0.064·cos q1`, B ≈ 104 /s (`scripts/mujoco-check pair`,
/// R² = 0.9965 over 400 random airborne states; EXPERIMENTS.md, "Two faults in the soft
/// limits…").
///
/// This engine solves it as a velocity motor on a second base–link 1 joint. rapier spreads a
/// motor over its substeps as a damper, so the same effect per step takes the motor's own
/// values, fitted against the same MuJoCo steps on 300 other states: the impedance is
/// `a + b·cos q1` with these [a, b] (twice MuJoCo's) and the reference rate
/// [`SHOULDER_PAIR_REFERENCE_RATE`]. The fit holds for the study's 2 ms step and rapier's
/// 4 solver iterations (the presets' values); with others, rerun `scripts/mujoco-check pair`
/// with them as overrides before trusting it.
pub const SHOULDER_PAIR_IMPEDANCE: [f32; 2] = [0.110, 0.123];

/// B′ in /s: the soft pair's motor targets `q̇1·(1 − dt·B′)` (see [`SHOULDER_PAIR_IMPEDANCE`]).
pub const SHOULDER_PAIR_REFERENCE_RATE: f32 = 65.0;

pub const FLOOR_Z: f32 = -0.05;
pub const FLOOR_FRICTION: f32 = 0.5;

/// Joint ranges in radians: joint 1 is −80°…80°, joint 2 is 0°…150°.
pub const JOINT1_RANGE: [f32; 2] = [-80.0 * DEG, 80.0 * DEG];
pub const JOINT2_RANGE: [f32; 2] = [0.0, 150.0 * DEG];

/// Radius of MuJoCo's touch-sensor sites; a contact counts for a site when its point lies
/// within it.
pub const TOUCH_SITE_RADIUS: f32 = 0.002;

pub const GRAVITY: f32 = -9.81;

pub const DEG: f32 = std::f32::consts::PI / 180.0;
