//! A setting outside its range. Its own module, below [`crate::config`] and
//! [`crate::randomization`], which both validate through it without depending on each other.

/// A setting outside its allowed range. The message names the key and the range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("env.{key} = {value} is invalid: {allowed}")]
pub struct EnvConfigError {
    pub key: &'static str,
    pub value: String,
    pub allowed: &'static str,
}
