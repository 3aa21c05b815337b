//! The study's 40-value observation, index by index.
//!
//! | index  | value                                                         | frame |
//! |--------|---------------------------------------------------------------|-------|
//! | 0      | base height z (centre; 0 at rest on the floor)                | world |
//! | 1..5   | base orientation quaternion w, x, y, z                        | world |
//! | 5..7   | joint angles q1, q2 (rad)                                     | –     |
//! | 7..10  | base linear velocity vx, vy, vz                               | world |
//! | 10..13 | base angular velocity ωx, ωy, ωz                              | base  |
//! | 13..15 | joint rates q̇1, q̇2 (rad/s)                                    | –     |
//! | 15..18 | link 1 angular velocity                                       | world |
//! | 18..21 | link 2 angular velocity                                       | world |
//! | 21..29 | normal force (N) at the tip's corners 1–8                     | –     |
//! | 29     | normal force (N) at the knee site; always 0, as in the study  | –     |
//! | 30..38 | normal force (N) at the base's corners 1–8                    | –     |
//! | 38..40 | previous action as the two applied torques τ1, τ2 (N·m)       | –     |
//!
//! The frames are those the study's code produced (MuJoCo's `qvel` and `frameangvel`).
//! Corner k (1-based) of a box sits at local (sx, sy, sz) with sx = + when k > 4,
//! sy = + when (k − 1) mod 4 ≥ 2 and sz = + when k is even, as in the MJCF's site list.
//! Touch forces come from the contact solve of the last physics step, which MuJoCo too
//! computes before integrating. The knee's 2 mm site lies on the capsule's axis, 1 cm inside
//! its surface, so no contact ever reaches it; the value is kept for the layout's sake.
//!
//! A policy may see more than the current observation: with `env.observation_history` h its
//! input is h of these layouts, the current one first, then the one of each decision before
//! ([`stack_first`], [`stack_next`]).

use std::ops::Range;

/// Values in one observation.
pub const OBS_DIM: usize = 40;

/// Version of this layout; a checkpoint or peer with another version is incompatible.
pub const OBS_LAYOUT_VERSION: u32 = 1;

pub const BASE_Z: usize = 0;
pub const BASE_QUAT: Range<usize> = 1..5;
pub const JOINT_ANGLES: Range<usize> = 5..7;
pub const BASE_LINVEL: Range<usize> = 7..10;
pub const BASE_ANGVEL: Range<usize> = 10..13;
pub const JOINT_RATES: Range<usize> = 13..15;
pub const LINK1_ANGVEL: Range<usize> = 15..18;
pub const LINK2_ANGVEL: Range<usize> = 18..21;
pub const TIP_TOUCH: Range<usize> = 21..29;
pub const KNEE_TOUCH: usize = 29;
pub const BASE_TOUCH: Range<usize> = 30..38;
pub const PREV_ACTION: Range<usize> = 38..40;

/// Most observations a policy may see at once (`EnvConfig::observation_history`): 320 values.
pub const MAX_OBSERVATION_HISTORY: u32 = 8;

/// The policy's input at an episode's first decision: `frame`, the current observation, in
/// every slot of `out` (`h` × 40 values), since nothing came before it. Repeating the frame
/// rather than zero-filling keeps the input on states the crawler can be in: a crawler at rest
/// looks the same in every slot.
///
/// # Panics
/// If `out` is not a whole number of observations: a caller bug.
pub fn stack_first(frame: &[f32; OBS_DIM], out: &mut [f32]) {
    assert!(out.len().is_multiple_of(OBS_DIM), "the input holds whole observations");
    for slot in out.chunks_exact_mut(OBS_DIM) {
        slot.copy_from_slice(frame);
    }
}

/// The policy's input after a decision: `frame`, the new observation, then the newest h − 1
/// observations of `previous` (the input of the decision before), so slot j holds the
/// observation of j decisions ago. `previous` and `out` have the same length, h × 40.
///
/// # Panics
/// If the lengths differ or are not whole observations: a caller bug.
pub fn stack_next(previous: &[f32], frame: &[f32; OBS_DIM], out: &mut [f32]) {
    assert_eq!(previous.len(), out.len(), "inputs of one history length");
    assert!(out.len().is_multiple_of(OBS_DIM), "the input holds whole observations");
    let (newest, older) = out.split_at_mut(OBS_DIM);
    newest.copy_from_slice(frame);
    older.copy_from_slice(&previous[..previous.len() - OBS_DIM]);
}

/// The physical range of each observation value, with a wide margin: what validation of a
/// received transition accepts (`crawler_proto::TransitionLimits`). Far beyond what a
/// crawler reaches, yet small enough that no value can overflow the TD loss in f32.
///
/// | values            | range                 | why                                        |
/// |-------------------|-----------------------|--------------------------------------------|
/// | base height       | [−10, 100] m          | the crawler lives on a floor at 0          |
/// | quaternion        | [−1.01, 1.01]         | unit quaternion, with rounding             |
/// | joint angles      | [−2π, 2π] rad         | hinge angles are kept in (−π, π]           |
/// | linear velocity   | [−1000, 1000] m/s     |                                            |
/// | angular velocities, joint rates | [−10⁴, 10⁴] rad/s |                              |
/// | touch forces      | [0, 10⁶] N            | normal forces push, never pull             |
/// | previous torques  | ±1.01·τmax N·m        | the action's torques                       |
pub fn observation_range(max_torque: f32) -> Vec<[f32; 2]> {
    let mut ranges = vec![[0.0f32; 2]; OBS_DIM];
    let mut set = |range: Range<usize>, bounds: [f32; 2]| ranges[range].fill(bounds);
    let tau = std::f32::consts::TAU;
    set(BASE_Z..BASE_Z + 1, [-10.0, 100.0]);
    set(BASE_QUAT, [-1.01, 1.01]);
    set(JOINT_ANGLES, [-tau, tau]);
    set(BASE_LINVEL, [-1e3, 1e3]);
    for rates in [BASE_ANGVEL, JOINT_RATES, LINK1_ANGVEL, LINK2_ANGVEL] {
        set(rates, [-1e4, 1e4]);
    }
    for touch in [TIP_TOUCH, KNEE_TOUCH..KNEE_TOUCH + 1, BASE_TOUCH] {
        set(touch, [0.0, 1e6]);
    }
    let torque = 1.01 * max_torque;
    set(PREV_ACTION, [-torque, torque]);
    ranges
}

/// Index (0-based) of the box corner nearest to a point given in the box's own frame,
/// following the MJCF's corner numbering.
pub(crate) fn corner_index(local: [f32; 3]) -> usize {
    4 * usize::from(local[0] > 0.0) + 2 * usize::from(local[1] > 0.0) + usize::from(local[2] > 0.0)
}

/// The corner `index` (0-based) of a cube of half extent `half`, in the cube's frame.
pub(crate) fn corner_position(index: usize, half: f32) -> [f32; 3] {
    let sign = |bit: usize| if index & bit != 0 { half } else { -half };
    [sign(4), sign(2), sign(1)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_ranges_tile_the_observation() {
        let mut covered = [0u8; OBS_DIM];
        let ranges = [
            BASE_Z..BASE_Z + 1,
            BASE_QUAT,
            JOINT_ANGLES,
            BASE_LINVEL,
            BASE_ANGVEL,
            JOINT_RATES,
            LINK1_ANGVEL,
            LINK2_ANGVEL,
            TIP_TOUCH,
            KNEE_TOUCH..KNEE_TOUCH + 1,
            BASE_TOUCH,
            PREV_ACTION,
        ];
        for range in ranges {
            for i in range {
                covered[i] += 1;
            }
        }
        assert!(covered.iter().all(|&c| c == 1), "{covered:?}");
    }

    #[test]
    fn every_value_has_a_range() {
        let ranges = observation_range(1.0);
        assert_eq!(ranges.len(), OBS_DIM);
        assert!(ranges.iter().all(|[low, high]| low < high && low.is_finite() && high.is_finite()));
        assert_eq!(ranges[PREV_ACTION.start], [-1.01, 1.01]);
    }

    #[test]
    fn corner_numbering_matches_the_mjcf() {
        // MJCF: corner1 (-,-,-), corner2 (-,-,+), corner3 (-,+,-), corner5 (+,-,-), corner8 (+,+,+).
        assert_eq!(corner_position(0, 1.0), [-1.0, -1.0, -1.0]);
        assert_eq!(corner_position(1, 1.0), [-1.0, -1.0, 1.0]);
        assert_eq!(corner_position(2, 1.0), [-1.0, 1.0, -1.0]);
        assert_eq!(corner_position(4, 1.0), [1.0, -1.0, -1.0]);
        assert_eq!(corner_position(7, 1.0), [1.0, 1.0, 1.0]);
        for i in 0..8 {
            assert_eq!(corner_index(corner_position(i, 0.5)), i);
        }
    }
}
