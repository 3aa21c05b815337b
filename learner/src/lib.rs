//! The learner side of crawler: replay, the libtorch Double DQN, checkpoints and metrics.
