//! The learning algorithm on libtorch: the Q-network on one flat parameter buffer, fused Adam
//! over it, and the Double DQN update.

pub mod adam;
pub mod dqn;
pub mod network;
pub(crate) mod tensor_memory;
