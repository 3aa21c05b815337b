//! The crawler environment and what acts in it, as a library: the study's two-link crawling
//! robot in rapier3d, the plain-Rust Q-network that acts there ([`policy`]), and the settings
//! a learner sends to configure both ([`settings`]). The actor process (`crawler-actor`), the
//! learner, the tools and any binding depend on this crate; it runs no process and opens no
//! connection.
//!
//! [`Crawler`] is one robot in its own physics world; [`VecEnv`] steps K of them together.
//! [`observation`] documents the 40-value observation index by index.

mod config;
mod crawler;
mod error;
pub mod gait;
pub mod model;
pub mod observation;
pub mod policy;
pub mod randomization;
pub mod settings;
mod vec_env;

pub use config::{Direction, EnvConfig, ShoulderPair};
pub use crawler::{Crawler, EpisodeSummary, GeneralizedState, InvalidStateError, PoseFrame, Reward, StepOutcome};
pub use error::EnvConfigError;
pub use observation::{OBS_DIM, OBS_LAYOUT_VERSION};
pub use randomization::{EpisodePhysics, Randomization};
pub use vec_env::VecEnv;
