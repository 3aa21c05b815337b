//! The contract between actors and the learner: what crosses the wire.
