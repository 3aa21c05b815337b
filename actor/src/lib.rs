//! The actor side of crawler: the rapier3d crawler environment and (later) the policy and
//! zenoh loop. The environment in [`env`] knows nothing of networks or neural nets.

pub mod env;
