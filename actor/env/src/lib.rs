//! The crawler environment: the study's two-link crawling robot in rapier3d.
//!
//! [`Crawler`] is one robot in its own physics world; [`VecEnv`] steps K of them together.
//! [`observation`] documents the 40-value observation index by index.

mod config;
mod crawler;
pub mod gait;
pub mod model;
pub mod observation;
pub mod randomization;
mod vec_env;

pub use config::{Direction, EnvConfig, EnvConfigError, ShoulderPair};
pub use crawler::{Crawler, EpisodeSummary, GeneralizedState, InvalidStateError, PoseFrame, Reward, StepOutcome};
pub use observation::{OBS_DIM, OBS_LAYOUT_VERSION};
pub use randomization::{EpisodePhysics, Randomization};
pub use vec_env::VecEnv;
