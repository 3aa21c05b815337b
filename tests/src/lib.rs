//! Integration tests live in `tests/tests/`; they start the real `learner` and `actor`
//! binaries (built by `cargo test --workspace`) on loopback.
