//! The actor side of crawler: the rapier3d crawler environment ([`env`]), acting with a
//! Q-network in plain Rust ([`policy`]), and the zenoh client that feeds the learner
//! ([`node`]). Nothing here links libtorch.

pub mod env;
pub mod node;
pub mod policy;
pub mod settings;
