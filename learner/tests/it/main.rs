//! The learner's integration tests, one binary (libtorch links once): the Q-network against
//! tch's own layers, checkpoints of a trained DQN, and DQN solving a chain MDP.

mod chain_mdp;
mod checkpoint;
mod network;
