//! Acting: the Q-network's forward pass in plain Rust and ε-greedy exploration.
//!
//! Actors link no libtorch. They load the learner's safetensors weights into [`MlpPolicy`],
//! whose forward pass a parity test in the learner crate pins to the tch one.

mod exploration;
mod mlp;
mod spec;
pub use spec::ParamInfo;

pub use exploration::{EpsilonDecay, apex_epsilon};
pub use mlp::{MlpPolicy, PolicyError, WeightLayout, argmax, q_values_of_params, transpose};
pub use spec::{NetworkSpec, SpecError};
