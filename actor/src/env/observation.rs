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
