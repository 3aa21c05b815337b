//! Per-episode physics randomisation: training for robustness to what the port gets wrong.
//!
//! A policy trained in one simulator exploits its exact physics; the study's MuJoCo model
//! differs from this port in ways the gait bank measures but no single setting removes
//! (EXPERIMENTS.md, "Fidelity"). Drawing the physics anew for each episode, as legged_gym and
//! humanoid-gym do before their sim-to-sim checks, makes those differences look like the
//! variation the policy must already cope with. Every range is drawn uniformly; the defaults
//! draw nothing, so an unrandomised env is bit-for-bit what it was.

use rand::Rng;
use rand::distr::uniform::SampleUniform;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::error::EnvConfigError;

/// Ranges, each `[low, high]`, drawn once per episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Randomization {
    /// Multiplies every friction coefficient (floor, base, links, tip).
    pub friction_scale: [f32; 2],
    /// Multiplies each body's mass (base, link 1, link 2 with the tip), drawn per body.
    pub mass_scale: [f32; 2],
    /// Multiplies each motor's torque, drawn per motor.
    pub motor_strength: [f32; 2],
    /// The joint limits' time constant in seconds (see `EnvConfig::joint_limit_timeconst`);
    /// `[0, 0]` keeps the env's own setting.
    pub joint_limit_timeconst: [f32; 2],
    /// Physics steps between a decision and its torques reaching the motors, drawn per
    /// episode from `[low, high]` (integers).
    pub latency_steps: [u32; 2],
    /// Standard deviation of zero-mean noise added to each observed value, relative to a
    /// unit per value (uniform noise of that spread). Drawn anew for every decision.
    pub observation_noise: f32,
    /// Seconds between pushes that roll the whole crawler about its base's own x axis, as
    /// legged_gym's `push_robots` (0: never). On the study's model the fast gaits fail by
    /// rolling onto a side; this engine rolls the symmetric crawler far less (the tumbling
    /// square wave: 0.3–5° of side tilt after 1 s here, 38° there), so without pushes a
    /// policy seldom meets a roll (EXPERIMENTS.md, "State replay" and "Speculative
    /// contacts…").
    pub push_interval_s: f32,
    /// Largest roll rate a push adds, rad/s; each push draws uniformly from ±this.
    pub push_roll_rate: f32,
    /// Natural frequency of the floor's contacts in Hz (rapier's `static_contact_softness`);
    /// `[0, 0]` keeps rapier's own (60 Hz). From the same states the study's model lands the
    /// base in sharper pulses, 2.2× this engine's landing impulse at 60 Hz, and stiffer
    /// contacts close most of that gap but move the trajectory elsewhere (EXPERIMENTS.md,
    /// "The landing force in both engines…"), so no single value is faithful: a policy
    /// trained over a range must cope with both kinds of landing.
    pub floor_contact_hz: [f32; 2],
}

impl Default for Randomization {
    fn default() -> Self {
        Self {
            friction_scale: [1.0, 1.0],
            mass_scale: [1.0, 1.0],
            motor_strength: [1.0, 1.0],
            joint_limit_timeconst: [0.0, 0.0],
            latency_steps: [0, 0],
            observation_noise: 0.0,
            push_interval_s: 0.0,
            push_roll_rate: 0.0,
            floor_contact_hz: [0.0, 0.0],
        }
    }
}

impl Randomization {
    /// The perturbations `eval --perturbed` reports speed under: ±30 % friction, ±20 % masses,
    /// motors at 80–100 %, limits from twice as stiff to twice as soft as MuJoCo's, up to
    /// 4 ms of latency, and a sideways push of up to 2.5 rad/s of roll every second. The pushes
    /// are there because a gait that survives everything else here can still roll onto its
    /// side on the study's model (EXPERIMENTS.md, "State replay"); the transfer preset's best
    /// checkpoint is chosen under these, so they must show that failure. They are half the
    /// transfer preset's training pushes: at 5 rad/s every checkpoint of a run flipped here,
    /// those that crawl upright on the study's model included, so nothing could be chosen.
    pub const EVAL_PERTURBATIONS: Randomization = Randomization {
        friction_scale: [0.7, 1.3],
        mass_scale: [0.8, 1.2],
        motor_strength: [0.8, 1.0],
        joint_limit_timeconst: [0.01, 0.04],
        latency_steps: [0, 2],
        observation_noise: 0.0,
        push_interval_s: 1.0,
        push_roll_rate: 2.5,
        floor_contact_hz: [0.0, 0.0],
    };

    /// Whether any range draws something other than the env's nominal physics.
    pub fn is_active(&self) -> bool {
        *self != Randomization::default()
    }

    /// Checks every range; the error names the key and what it allows.
    pub fn validate(&self) -> Result<(), EnvConfigError> {
        fn error(key: &'static str, value: String, allowed: &'static str) -> Result<(), EnvConfigError> {
            Err(EnvConfigError { key, value, allowed })
        }
        let scale = |key: &'static str, [low, high]: [f32; 2], max: f32| {
            if low.is_finite() && high.is_finite() && 0.0 < low && low <= high && high <= max {
                Ok(())
            } else {
                error(
                    key,
                    format!("{:?}", [low, high]),
                    "[low, high] with 0 < low ≤ high ≤ the key's maximum (10; motors 2)",
                )
            }
        };
        scale("randomization.friction_scale", self.friction_scale, 10.0)?;
        scale("randomization.mass_scale", self.mass_scale, 10.0)?;
        scale("randomization.motor_strength", self.motor_strength, 2.0)?;
        // A range that may also be [0, 0], "keep the env's own value".
        let own_or_within = |key: &'static str, [low, high]: [f32; 2], [min, max]: [f32; 2], allowed: &'static str| {
            let ok = |v: f32| v.is_finite() && (min..=max).contains(&v);
            if (low == 0.0 && high == 0.0) || (ok(low) && ok(high) && low <= high) {
                Ok(())
            } else {
                error(key, format!("{:?}", [low, high]), allowed)
            }
        };
        own_or_within(
            "randomization.joint_limit_timeconst",
            self.joint_limit_timeconst,
            [0.001, 1.0],
            "[0, 0] (the env's own) or [low, high] within [0.001, 1] s",
        )?;
        let [low, high] = self.latency_steps;
        if !(low <= high && high <= 50) {
            return error(
                "randomization.latency_steps",
                format!("{:?}", [low, high]),
                "[low, high] with low ≤ high ≤ 50",
            );
        }
        let noise = self.observation_noise;
        if !(noise.is_finite() && (0.0..=1.0).contains(&noise)) {
            return error("randomization.observation_noise", noise.to_string(), "a number in [0, 1]");
        }
        let interval = self.push_interval_s;
        if !(interval.is_finite() && (interval == 0.0 || (0.01..=1000.0).contains(&interval))) {
            return error("randomization.push_interval_s", interval.to_string(), "0 (no pushes) or [0.01, 1000] s");
        }
        let rate = self.push_roll_rate;
        if !(rate.is_finite() && (0.0..=50.0).contains(&rate)) {
            return error("randomization.push_roll_rate", rate.to_string(), "a number in [0, 50] rad/s");
        }
        own_or_within(
            "randomization.floor_contact_hz",
            self.floor_contact_hz,
            [1.0, MAX_FLOOR_CONTACT_HZ],
            "[0, 0] (rapier's own) or [low, high] within [1, 100000] Hz",
        )?;
        Ok(())
    }

    /// One episode's physics. Draws nothing when the randomisation is off, and nothing for a
    /// range left at its "keep the env's own" value, so adding a range leaves the draws of
    /// configurations without it as they were.
    pub fn draw(&self, nominal_timeconst: f32, rng: &mut ChaCha8Rng) -> EpisodePhysics {
        if !self.is_active() {
            return EpisodePhysics::nominal(nominal_timeconst);
        }
        fn uniform<T: SampleUniform + PartialOrd + Copy>(rng: &mut ChaCha8Rng, [low, high]: [T; 2]) -> T {
            if high > low { rng.random_range(low..=high) } else { low }
        }
        // [0, 0] keeps the env's own value and draws nothing.
        let own_or_uniform = |rng: &mut ChaCha8Rng, own: f32, range: [f32; 2]| {
            if range == [0.0, 0.0] { own } else { uniform(rng, range) }
        };
        // The order of the draws is part of a seed's meaning: a new range is drawn last.
        let friction_scale = uniform(rng, self.friction_scale);
        let mass_scale = [uniform(rng, self.mass_scale), uniform(rng, self.mass_scale), uniform(rng, self.mass_scale)];
        let motor_strength = [uniform(rng, self.motor_strength), uniform(rng, self.motor_strength)];
        let joint_limit_timeconst = own_or_uniform(rng, nominal_timeconst, self.joint_limit_timeconst);
        let latency_steps = uniform(rng, self.latency_steps);
        let floor_contact_hz = own_or_uniform(rng, EpisodePhysics::NOMINAL_FLOOR_CONTACT_HZ, self.floor_contact_hz);
        EpisodePhysics {
            friction_scale,
            mass_scale,
            motor_strength,
            joint_limit_timeconst,
            latency_steps,
            observation_noise: self.observation_noise,
            push_interval_s: self.push_interval_s,
            push_roll_rate: self.push_roll_rate,
            floor_contact_hz,
        }
    }
}

/// The physics of one episode, as drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpisodePhysics {
    pub friction_scale: f32,
    /// Base, link 1, link 2 (with the tip).
    pub mass_scale: [f32; 3],
    pub motor_strength: [f32; 2],
    pub joint_limit_timeconst: f32,
    pub latency_steps: u32,
    pub observation_noise: f32,
    /// Seconds between roll pushes (0: none) and their largest roll rate, rad/s.
    pub push_interval_s: f32,
    pub push_roll_rate: f32,
    /// Natural frequency of the floor's contacts, Hz.
    pub floor_contact_hz: f32,
}

impl EpisodePhysics {
    /// rapier's own stiffness for contacts with a fixed body (the floor), which this env keeps
    /// unless randomised: 60 Hz (`SpringCoefficients::contact_static_defaults`, which
    /// `nominal_floor_contact_hz_is_rapiers_default` holds to it).
    pub const NOMINAL_FLOOR_CONTACT_HZ: f32 = 60.0;

    /// The env's own physics: no scaling, no latency, no noise, no pushes.
    pub fn nominal(joint_limit_timeconst: f32) -> Self {
        Self {
            friction_scale: 1.0,
            mass_scale: [1.0; 3],
            motor_strength: [1.0; 2],
            joint_limit_timeconst,
            latency_steps: 0,
            observation_noise: 0.0,
            push_interval_s: 0.0,
            push_roll_rate: 0.0,
            floor_contact_hz: Self::NOMINAL_FLOOR_CONTACT_HZ,
        }
    }
}

/// Stiffest floor contact a randomisation may draw, Hz: 10 kHz already lands the base with
/// 0.91× MuJoCo's impulse (EXPERIMENTS.md, "The landing force in both engines…"); beyond
/// 100 kHz the spring is far stiffer than one 2 ms step can resolve.
pub const MAX_FLOOR_CONTACT_HZ: f32 = 100_000.0;

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn the_default_draws_nothing_and_ranges_are_respected() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let before = rng.clone();
        assert_eq!(Randomization::default().draw(0.05, &mut rng), EpisodePhysics::nominal(0.05));
        assert_eq!(rng, before, "an inactive randomisation consumes no random numbers");

        let ranges = Randomization::EVAL_PERTURBATIONS;
        ranges.validate().unwrap();
        for _ in 0..200 {
            let physics = ranges.draw(0.05, &mut rng);
            assert!((0.7..=1.3).contains(&physics.friction_scale));
            assert!(physics.mass_scale.iter().all(|m| (0.8..=1.2).contains(m)));
            assert!(physics.motor_strength.iter().all(|m| (0.8..=1.0).contains(m)));
            assert!((0.01..=0.04).contains(&physics.joint_limit_timeconst));
            assert!(physics.latency_steps <= 2);
            assert_eq!(physics.floor_contact_hz, EpisodePhysics::NOMINAL_FLOOR_CONTACT_HZ);
        }

        let stiffer = Randomization { floor_contact_hz: [60.0, 2000.0], ..ranges };
        stiffer.validate().unwrap();
        let drawn: Vec<f32> = (0..200).map(|_| stiffer.draw(0.05, &mut rng).floor_contact_hz).collect();
        assert!(drawn.iter().all(|hz| (60.0..=2000.0).contains(hz)));
        assert!(drawn.iter().any(|&hz| hz > 1000.0) && drawn.iter().any(|&hz| hz < 1000.0), "{drawn:?}");

        // The floor's stiffness is drawn after everything else, so the same seed draws the
        // same other physics with or without it: runs of configurations written before the
        // range existed replay as they were.
        let (mut a, mut b) = (ChaCha8Rng::seed_from_u64(7), ChaCha8Rng::seed_from_u64(7));
        let with_floor = stiffer.draw(0.05, &mut a);
        let without = ranges.draw(0.05, &mut b);
        assert_ne!(with_floor.floor_contact_hz, without.floor_contact_hz);
        assert_eq!(EpisodePhysics { floor_contact_hz: without.floor_contact_hz, ..with_floor }, without);
    }

    #[test]
    fn nominal_floor_contact_hz_is_rapiers_default() {
        let rapier = rapier3d::dynamics::SpringCoefficients::<f32>::contact_static_defaults();
        assert_eq!(EpisodePhysics::NOMINAL_FLOOR_CONTACT_HZ, rapier.natural_frequency);
    }

    #[test]
    fn bad_ranges_are_named() {
        let bad = Randomization { mass_scale: [1.2, 0.8], ..Randomization::default() };
        assert_eq!(bad.validate().unwrap_err().key, "randomization.mass_scale");
        let bad = Randomization { observation_noise: f32::NAN, ..Randomization::default() };
        assert_eq!(bad.validate().unwrap_err().key, "randomization.observation_noise");
        let bad = Randomization { latency_steps: [0, 500], ..Randomization::default() };
        assert_eq!(bad.validate().unwrap_err().key, "randomization.latency_steps");
        let bad = Randomization { push_interval_s: 0.001, ..Randomization::default() };
        assert_eq!(bad.validate().unwrap_err().key, "randomization.push_interval_s");
        let bad = Randomization { push_roll_rate: f32::INFINITY, ..Randomization::default() };
        assert_eq!(bad.validate().unwrap_err().key, "randomization.push_roll_rate");
        for hz in [[0.0, 60.0], [2000.0, 60.0], [60.0, f32::NAN], [60.0, 1e6]] {
            let bad = Randomization { floor_contact_hz: hz, ..Randomization::default() };
            assert_eq!(bad.validate().unwrap_err().key, "randomization.floor_contact_hz", "{hz:?}");
        }
    }
}
