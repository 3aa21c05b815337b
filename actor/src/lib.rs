//! The actor side of crawler: the rapier3d crawler environment ([`env`]) and acting with a
//! Q-network in plain Rust ([`policy`]). The environment knows nothing of networks or neural
//! nets; nothing here links libtorch.

pub mod env;
pub mod policy;
