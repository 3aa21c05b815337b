//! The actor process's library: the zenoh client that joins a learner's run, acts in
//! [`crawler_env`]'s crawlers with the weights the learner broadcasts, and publishes
//! transitions within its insert credit ([`node`]). The env, the policy and the settings are
//! `crawler-env`'s; the binary (`src/bin/actor.rs`) parses flags and runs [`node::run`].
//! Nothing here links libtorch.

pub mod node;
