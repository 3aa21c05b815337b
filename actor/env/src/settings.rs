//! What an actor needs to know about its run. The learner serves it in
//! [`crawler_proto::RunInfo`] as the proto message [`crawler_proto::ActorSettings`], so
//! actors on other machines need no config file; the conversions are below.

use crawler_proto as proto;
use serde::{Deserialize, Serialize};

use crate::policy::{EpsilonDecay, apex_epsilon};
use crate::{Direction, EnvConfig, Randomization, ShoulderPair};

/// Why run settings received from a learner are unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SettingsError {
    #[error("the run info carries no {0} settings")]
    Missing(&'static str),
    #[error("field `{field}` = {value} does not fit: {allowed}")]
    Field { field: &'static str, value: String, allowed: &'static str },
    #[error(transparent)]
    Env(#[from] crate::EnvConfigError),
    #[error("exploration {exploration:?} is invalid: {allowed}")]
    Exploration { exploration: Exploration, allowed: &'static str },
    #[error(
        "actor.batch_transitions = {transitions} with env.observation_history = {history} makes \
         messages of up to {bytes} bytes, over the protocol's limit of {max} bytes, and the \
         learner refuses such batches. Set actor.batch_transitions to at most {fits}"
    )]
    BatchTooLarge { transitions: usize, history: u32, bytes: usize, max: usize, fits: usize },
}

/// How actors explore.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum Exploration {
    /// Ape-X: actor i of `actors` uses ε = base^(1 + alpha·i/(actors − 1)), fixed.
    Ladder { base: f64, alpha: f64, actors: usize },
    /// The study: ε starts at `start`, × `factor` every `every` decisions, floored at `min`.
    Decay { start: f64, factor: f64, every: u64, min: f64 },
}

impl Default for Exploration {
    fn default() -> Self {
        Exploration::Ladder { base: 0.4, alpha: 7.0, actors: 8 }
    }
}

impl Exploration {
    /// ε of actor `actor` after it took `steps` decisions (per crawler).
    pub fn epsilon(&self, actor: u32, steps: u64) -> f64 {
        match *self {
            Exploration::Ladder { base, alpha, actors } => {
                let index = (actor as usize).min(actors.saturating_sub(1));
                apex_epsilon(base, alpha, index, actors)
            }
            Exploration::Decay { start, factor, every, min } => EpsilonDecay { start, factor, every, min }.at(steps),
        }
    }

    /// Checks the schedule's parameters.
    pub fn validate(&self) -> Result<(), SettingsError> {
        let (ok, allowed) = match *self {
            Exploration::Ladder { base, alpha, actors } => (
                (0.0..=1.0).contains(&base) && alpha.is_finite() && alpha >= 0.0 && actors > 0,
                "a ladder needs base in [0, 1], alpha ≥ 0 and actors ≥ 1",
            ),
            Exploration::Decay { start, factor, every, min } => (
                [start, factor, min].iter().all(|v| (0.0..=1.0).contains(v)) && every > 0,
                "a decay needs start, factor and min in [0, 1] and every ≥ 1",
            ),
        };
        if ok { Ok(()) } else { Err(SettingsError::Exploration { exploration: self.clone(), allowed }) }
    }
}

/// An actor's settings, fixed for the run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ActorSettings {
    pub env: EnvConfig,
    /// Crawlers each actor steps together.
    pub envs_per_actor: usize,
    /// Transitions per published batch.
    pub batch_transitions: usize,
    pub exploration: Exploration,
    /// Base seed; actor i's crawler k uses seed `seed + 1000·i + k`.
    pub seed: u64,
    /// Seconds between status reports.
    pub status_interval_s: f64,
}

impl Default for ActorSettings {
    fn default() -> Self {
        Self {
            env: EnvConfig::default(),
            envs_per_actor: 8,
            batch_transitions: 256,
            exploration: Exploration::default(),
            seed: 0,
            status_interval_s: 2.0,
        }
    }
}

impl ActorSettings {
    /// Transitions in each batch an actor publishes: whole steps of all its crawlers, the
    /// first that reach `batch_transitions`. The learner's insert credit counts in these.
    pub fn transitions_per_batch(&self) -> usize {
        let envs = self.envs_per_actor.max(1);
        self.batch_transitions.div_ceil(envs) * envs
    }

    /// Checks every setting; the error names the field.
    pub fn validate(&self) -> Result<(), SettingsError> {
        self.env.validate()?;
        self.exploration.validate()?;
        let field = |field: &'static str, value: &dyn std::fmt::Display, allowed: &'static str| SettingsError::Field {
            field,
            value: value.to_string(),
            allowed,
        };
        if !(1..=1024).contains(&self.envs_per_actor) {
            return Err(field("actor.envs_per_actor", &self.envs_per_actor, "an integer in 1..=1024"));
        }
        if !(1..=4096).contains(&self.batch_transitions) {
            return Err(field("actor.batch_transitions", &self.batch_transitions, "an integer in 1..=4096"));
        }
        // A status report per 50 ms at most, one per hour at least: anything shorter floods the
        // learner's log and metrics, anything longer leaves status.json stale.
        if !(0.05..=3600.0).contains(&self.status_interval_s) {
            return Err(field("actor.status_interval_s", &self.status_interval_s, "seconds in [0.05, 3600]"));
        }
        // A batch carries two inputs of 40·h values per transition, so which batch sizes fit in
        // one message depends on the history.
        let input_dim = self.env.policy_input_dim();
        let largest_batch = |transitions: usize| proto::TransitionBatch::largest_encoded_len(transitions, input_dim);
        let bytes = largest_batch(self.batch_transitions);
        if bytes > proto::MAX_MESSAGE_BYTES {
            return Err(SettingsError::BatchTooLarge {
                transitions: self.batch_transitions,
                history: self.env.observation_history,
                bytes,
                max: proto::MAX_MESSAGE_BYTES,
                fits: (1..self.batch_transitions)
                    .rev()
                    .find(|&n| largest_batch(n) <= proto::MAX_MESSAGE_BYTES)
                    .unwrap_or(1),
            });
        }
        Ok(())
    }

    /// Seeds of actor `actor`'s crawlers.
    pub fn seeds(&self, actor: u32) -> Vec<u64> {
        (0..self.envs_per_actor as u64).map(|k| self.seed + 1000 * u64::from(actor) + k).collect()
    }
}

fn pair(values: &[f32], field: &'static str) -> Result<[f32; 2], SettingsError> {
    <[f32; 2]>::try_from(values).map_err(|_| SettingsError::Field {
        field,
        // Quoted in part: the list came from the network and may be long.
        value: proto::validate::quoted_prefix(&format!("{values:?}")),
        allowed: "exactly two values [low, high]",
    })
}

impl From<&EnvConfig> for proto::EnvSettings {
    fn from(env: &EnvConfig) -> Self {
        let direction = match env.direction {
            Direction::Forward => proto::Direction::Forward,
            Direction::Backward => proto::Direction::Backward,
        };
        proto::EnvSettings {
            action_levels: env.action_levels,
            action_repeat: env.action_repeat,
            direction: direction as i32,
            shoulder_pair: match env.shoulder_pair {
                ShoulderPair::SoftConstraint => proto::ShoulderPair::SoftConstraint,
                ShoulderPair::Viscous => proto::ShoulderPair::Viscous,
            } as i32,
            max_torque: env.max_torque,
            dt: env.dt,
            min_episode_steps: env.min_episode_steps,
            max_episode_steps: env.max_episode_steps,
            min_progress_per_step: env.min_progress_per_step,
            sliding_base: env.sliding_base,
            solver_iterations: env.solver_iterations,
            contact_prediction: env.contact_prediction,
            start_joint1_deg: env.start_joint1_deg.to_vec(),
            start_joint2_deg: env.start_joint2_deg.to_vec(),
            joint_limit_timeconst: env.joint_limit_timeconst,
            max_tilt_deg: env.max_tilt_deg,
            tilt_rate_penalty: env.tilt_rate_penalty,
            base_impact_penalty: env.base_impact_penalty,
            joint_limit_penalty: env.joint_limit_penalty,
            base_impact_threshold: env.base_impact_threshold,
            position_reward_weight: env.position_reward_weight,
            observation_history: env.observation_history,
            randomization: env.randomization.is_active().then(|| {
                let r = &env.randomization;
                proto::RandomizationSettings {
                    friction_scale: r.friction_scale.to_vec(),
                    mass_scale: r.mass_scale.to_vec(),
                    motor_strength: r.motor_strength.to_vec(),
                    joint_limit_timeconst: r.joint_limit_timeconst.to_vec(),
                    latency_steps: r.latency_steps.to_vec(),
                    observation_noise: r.observation_noise,
                    push_interval_s: r.push_interval_s,
                    push_roll_rate: r.push_roll_rate,
                    floor_contact_hz: r.floor_contact_hz.to_vec(),
                }
            }),
        }
    }
}

impl TryFrom<&proto::RandomizationSettings> for Randomization {
    type Error = SettingsError;

    fn try_from(r: &proto::RandomizationSettings) -> Result<Self, SettingsError> {
        // Ranges are checked with the whole env by `EnvConfig::validate`.
        let latency: [u32; 2] = r.latency_steps.as_slice().try_into().map_err(|_| SettingsError::Field {
            field: "env.randomization.latency_steps",
            value: proto::validate::quoted_prefix(&format!("{:?}", r.latency_steps)),
            allowed: "exactly two values [low, high]",
        })?;
        Ok(Randomization {
            friction_scale: pair(&r.friction_scale, "env.randomization.friction_scale")?,
            mass_scale: pair(&r.mass_scale, "env.randomization.mass_scale")?,
            motor_strength: pair(&r.motor_strength, "env.randomization.motor_strength")?,
            joint_limit_timeconst: pair(&r.joint_limit_timeconst, "env.randomization.joint_limit_timeconst")?,
            latency_steps: latency,
            observation_noise: r.observation_noise,
            push_interval_s: r.push_interval_s,
            push_roll_rate: r.push_roll_rate,
            floor_contact_hz: pair(&r.floor_contact_hz, "env.randomization.floor_contact_hz")?,
        })
    }
}

/// The wire enum `T` that `value` encodes, or an error naming `field` and its `allowed` values.
fn wire_enum<T: TryFrom<i32>>(value: i32, field: &'static str, allowed: &'static str) -> Result<T, SettingsError> {
    T::try_from(value).map_err(|_| SettingsError::Field { field, value: value.to_string(), allowed })
}

impl TryFrom<&proto::EnvSettings> for EnvConfig {
    type Error = SettingsError;

    fn try_from(env: &proto::EnvSettings) -> Result<Self, SettingsError> {
        let direction = match wire_enum(env.direction, "env.direction", "0 (forward) or 1 (backward)")? {
            proto::Direction::Forward => Direction::Forward,
            proto::Direction::Backward => Direction::Backward,
        };
        let shoulder_pair =
            match wire_enum(env.shoulder_pair, "env.shoulder_pair", "0 (soft_constraint) or 1 (viscous)")? {
                proto::ShoulderPair::SoftConstraint => ShoulderPair::SoftConstraint,
                proto::ShoulderPair::Viscous => ShoulderPair::Viscous,
            };
        let config = EnvConfig {
            action_levels: env.action_levels,
            shoulder_pair,
            action_repeat: env.action_repeat,
            direction,
            max_torque: env.max_torque,
            dt: env.dt,
            min_episode_steps: env.min_episode_steps,
            max_episode_steps: env.max_episode_steps,
            min_progress_per_step: env.min_progress_per_step,
            sliding_base: env.sliding_base,
            solver_iterations: env.solver_iterations,
            contact_prediction: env.contact_prediction,
            start_joint1_deg: pair(&env.start_joint1_deg, "env.start_joint1_deg")?,
            start_joint2_deg: pair(&env.start_joint2_deg, "env.start_joint2_deg")?,
            joint_limit_timeconst: env.joint_limit_timeconst,
            max_tilt_deg: env.max_tilt_deg,
            tilt_rate_penalty: env.tilt_rate_penalty,
            base_impact_penalty: env.base_impact_penalty,
            joint_limit_penalty: env.joint_limit_penalty,
            base_impact_threshold: env.base_impact_threshold,
            position_reward_weight: env.position_reward_weight,
            observation_history: env.observation_history,
            randomization: env.randomization.as_ref().map(Randomization::try_from).transpose()?.unwrap_or_default(),
        };
        config.validate()?;
        Ok(config)
    }
}

impl From<&ActorSettings> for proto::ActorSettings {
    fn from(settings: &ActorSettings) -> Self {
        let exploration = match settings.exploration {
            Exploration::Ladder { base, alpha, actors } => proto::Exploration::Ladder(proto::EpsilonLadder {
                base,
                alpha,
                actors: u32::try_from(actors).unwrap_or(u32::MAX),
            }),
            Exploration::Decay { start, factor, every, min } => {
                proto::Exploration::Decay(proto::EpsilonDecay { start, factor, every, min })
            }
        };
        proto::ActorSettings {
            env: Some((&settings.env).into()),
            // Validated to at most 1 024 and 4 096.
            envs_per_actor: u32::try_from(settings.envs_per_actor).unwrap_or(u32::MAX),
            batch_transitions: u32::try_from(settings.batch_transitions).unwrap_or(u32::MAX),
            exploration: Some(exploration),
            seed: settings.seed,
            status_interval_s: settings.status_interval_s,
        }
    }
}

impl TryFrom<&proto::ActorSettings> for ActorSettings {
    type Error = SettingsError;

    /// Converts and validates: whatever a learner (or an impostor) sends, the result is
    /// usable or an error that names the field.
    fn try_from(wire: &proto::ActorSettings) -> Result<Self, SettingsError> {
        let env = wire.env.as_ref().ok_or(SettingsError::Missing("environment"))?;
        let exploration = match wire.exploration.as_ref().ok_or(SettingsError::Missing("exploration"))? {
            proto::Exploration::Ladder(l) => {
                Exploration::Ladder { base: l.base, alpha: l.alpha, actors: l.actors as usize }
            }
            proto::Exploration::Decay(d) => {
                Exploration::Decay { start: d.start, factor: d.factor, every: d.every, min: d.min }
            }
        };
        let settings = ActorSettings {
            env: EnvConfig::try_from(env)?,
            envs_per_actor: wire.envs_per_actor as usize,
            batch_transitions: wire.batch_transitions as usize,
            exploration,
            seed: wire.seed,
            status_interval_s: wire.status_interval_s,
        };
        settings.validate()?;
        Ok(settings)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_survive_the_wire() {
        let mut settings = ActorSettings::default();
        settings.env.direction = Direction::Backward;
        settings.env.action_repeat = 10;
        settings.env.max_tilt_deg = 60.0;
        settings.env.tilt_rate_penalty = 0.02;
        settings.env.joint_limit_penalty = 500.0;
        settings.env.position_reward_weight = 3.0;
        settings.env.observation_history = 4;
        settings.env.contact_prediction = 0.004;
        settings.env.joint_limit_timeconst = 0.03;
        settings.env.shoulder_pair = ShoulderPair::Viscous;
        settings.env.randomization.latency_steps = [0, 2];
        settings.env.randomization.push_interval_s = 1.5;
        settings.env.randomization.push_roll_rate = 4.0;
        settings.env.randomization.floor_contact_hz = [60.0, 2000.0];
        settings.exploration = Exploration::Decay { start: 1.0, factor: 0.99, every: 100, min: 0.05 };
        let wire = proto::ActorSettings::from(&settings);
        assert_eq!(ActorSettings::try_from(&wire), Ok(settings.clone()));
        let ladder = ActorSettings::default();
        assert_eq!(ActorSettings::try_from(&proto::ActorSettings::from(&ladder)), Ok(ladder));
    }

    /// A batch holds two inputs of 40·h values per transition: with a long history the largest
    /// batch sizes no longer fit in one message, and settings that would make the learner
    /// refuse every batch are refused up front, on either side of the wire, naming both keys
    /// and the size that fits.
    #[test]
    fn a_batch_that_cannot_fit_in_one_message_is_refused_with_the_size_that_fits() {
        let mut settings = ActorSettings { batch_transitions: 4096, ..ActorSettings::default() };
        assert_eq!(settings.validate(), Ok(()), "4096 transitions of 40 values fit");
        settings.env.observation_history = 8;
        let Err(SettingsError::BatchTooLarge { transitions, history, bytes, max, fits }) = settings.validate() else {
            panic!("4096 transitions of 320 values accepted");
        };
        assert_eq!((transitions, history, max), (4096, 8, proto::MAX_MESSAGE_BYTES));
        assert!(bytes > max && fits < 4096, "{bytes} bytes, {fits} fit");
        let dim = settings.env.policy_input_dim();
        assert!(proto::TransitionBatch::largest_encoded_len(fits, dim) <= max);
        assert!(proto::TransitionBatch::largest_encoded_len(fits + 1, dim) > max);
        let message = settings.validate().unwrap_err().to_string();
        for named in ["actor.batch_transitions", "env.observation_history", &format!("at most {fits}")] {
            assert!(message.contains(named), "{named} not in: {message}");
        }
        let wire = proto::ActorSettings::from(&settings);
        assert!(matches!(ActorSettings::try_from(&wire), Err(SettingsError::BatchTooLarge { .. })));
        settings.batch_transitions = fits;
        assert_eq!(settings.validate(), Ok(()));
    }

    #[test]
    fn malformed_settings_are_named() {
        let good = proto::ActorSettings::from(&ActorSettings::default());
        let mut empty = good.clone();
        empty.env = None;
        assert_eq!(ActorSettings::try_from(&empty), Err(SettingsError::Missing("environment")));
        let mut bad_pair = good.clone();
        if let Some(env) = bad_pair.env.as_mut() {
            env.start_joint1_deg = vec![1.0];
        }
        assert!(matches!(ActorSettings::try_from(&bad_pair), Err(SettingsError::Field { .. })));
        // A field the sender left out reads as 0: a tilt limit of 0° is refused, not obeyed.
        let mut no_tilt = good.clone();
        if let Some(env) = no_tilt.env.as_mut() {
            env.max_tilt_deg = 0.0;
        }
        let error = ActorSettings::try_from(&no_tilt).unwrap_err().to_string();
        assert!(error.contains("max_tilt_deg"), "{error}");
        // Enum values the protocol does not define are refused by name, not read as a default.
        for (field, set) in [
            ("env.direction", (|env: &mut proto::EnvSettings| env.direction = 7) as fn(&mut proto::EnvSettings)),
            ("env.shoulder_pair", |env: &mut proto::EnvSettings| env.shoulder_pair = -1),
        ] {
            let mut unknown = good.clone();
            if let Some(env) = unknown.env.as_mut() {
                set(env);
            }
            let error = ActorSettings::try_from(&unknown).unwrap_err().to_string();
            assert!(error.contains(field), "{error}");
        }
        let mut nan = good.clone();
        nan.status_interval_s = f64::NAN;
        assert!(ActorSettings::try_from(&nan).is_err());
        // Batches are whole steps of every crawler.
        let batches = |batch_transitions, envs_per_actor| {
            ActorSettings { batch_transitions, envs_per_actor, ..ActorSettings::default() }.transitions_per_batch()
        };
        assert_eq!((batches(256, 8), batches(100, 8), batches(1, 3)), (256, 104, 3));
        // A finite but absurd interval would flood the learner with status reports.
        let mut tiny = good.clone();
        tiny.status_interval_s = 1e-20;
        let error = ActorSettings::try_from(&tiny).unwrap_err().to_string();
        assert!(error.contains("actor.status_interval_s"), "{error}");
        let mut no_envs = good;
        no_envs.envs_per_actor = 0;
        assert!(ActorSettings::try_from(&no_envs).is_err());
    }
}

#[cfg(test)]
mod wire_tests {
    use super::*;
    use prost::Message;

    #[test]
    fn settings_survive_encoding() {
        let wire = proto::ActorSettings::from(&ActorSettings::default());
        let bytes = wire.encode_to_vec();
        let back = proto::ActorSettings::decode(bytes.as_slice()).unwrap();
        assert_eq!(back, wire);
        let info = proto::RunInfo {
            protocol_version: proto::PROTOCOL_VERSION,
            run_id: "r".into(),
            settings: Some(wire),
            assigned_actor_id: None,
        };
        let decoded = proto::validate::run_info(&info.encode_to_vec()).unwrap();
        assert_eq!(decoded, info);
        let env = EnvConfig::try_from(decoded.settings.as_ref().and_then(|s| s.env.as_ref()).unwrap()).unwrap();
        assert_eq!(env, EnvConfig::default(), "the env, joint limits included, survives the wire");
        let randomized = EnvConfig { randomization: Randomization::EVAL_PERTURBATIONS, ..EnvConfig::default() };
        let back = EnvConfig::try_from(&proto::EnvSettings::from(&randomized)).unwrap();
        assert_eq!(back, randomized, "the randomisation survives the wire");
    }
}
