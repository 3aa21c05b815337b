//! The project's side of `scripts/bench-anchors` (issue 17): the work that has an outside
//! anchor (MuJoCo, PyTorch, tch), one row at a time, as one JSON object per line on stdout.
//!
//! `cargo bench -p crawler-learner --bench anchors -- ROW` with ROW one of [`ROWS`]; the
//! script runs each row here and then its anchor, back to back, and prints the ratios.
//! Every row uses one thread. Workloads are defined here and mirrored, row by row, in
//! `scripts/anchors/anchors.py`; a change to one must be made to the other.
#![allow(clippy::print_stdout)]

mod support;

use std::time::{Duration, Instant};

use crawler_env::gait::SquareWaveGait;
use crawler_env::policy::{MlpPolicy, NetworkSpec};
use crawler_env::{Crawler, EnvConfig, OBS_DIM};
use crawler_learner::algo::dqn::{Batch, Dqn, DqnConfig, LossKind};
use crawler_learner::checkpoint::encode_weights;
use serde_json::json;
use tch::nn::{self, Module};
use tch::{Kind, Tensor};

/// The rows, in the order the script prints them.
const ROWS: &[&str] = &[
    "physics",
    "inference-b1",
    "inference-b8",
    "inference-b16",
    "update-study-b32",
    "update-study-b256",
    "update-default-b32",
    "update-default-b64",
    "update-default-b256",
];

/// The physics row: 10 episodes of 20 s of the square-wave gait that crawls in both engines,
/// from joint angles (0, 0), every physics step's touch sensors and observation computed
/// (MuJoCo computes its sensors on every step too), no inference.
const PHYSICS_EPISODES: u32 = 10;
const PHYSICS_STEPS: u32 = 10_000;

/// How long each timed loop runs.
const BUDGET: Duration = Duration::from_secs(3);

/// Calls per second of `f` over [`BUDGET`].
fn rate(f: impl FnMut()) -> f64 {
    support::rate(BUDGET, f)
}

fn physics() -> serde_json::Value {
    let config = EnvConfig {
        action_repeat: 1,
        max_episode_steps: PHYSICS_STEPS,
        min_progress_per_step: 0.0,
        ..EnvConfig::default()
    };
    let gait = SquareWaveGait::FORWARD;
    let mut crawler = Crawler::new(config.clone(), 0);
    let mut observation = [0.0f32; OBS_DIM];
    let mut distance = 0.0;
    let mut flips = 0;
    let start = Instant::now();
    for _ in 0..PHYSICS_EPISODES {
        crawler.reset_to([0.0, 0.0]);
        for step in 0..PHYSICS_STEPS {
            crawler.step_torques(gait.torques(step as f32 * config.dt));
            crawler.observe(&mut observation);
        }
        distance += crawler.distance();
        flips += crawler.episode_summary(None).flips;
    }
    let seconds = start.elapsed().as_secs_f64();
    let steps = f64::from(PHYSICS_EPISODES * PHYSICS_STEPS);
    let simulated = steps * f64::from(config.dt);
    json!({
        "row": "physics",
        "project": steps / seconds,
        "unit": "steps/s",
        "what": "rapier3d, one crawler",
        "speed": f64::from(distance) / simulated,
        "flips": flips,
    })
}

/// The network as a tch user writes it: `nn::seq` of `nn::linear`, `nn::layer_norm` and ReLU,
/// in PyTorch's layout, holding `weights` (`nn.Sequential` order and names). The inference
/// anchor, so it stays independent of how the learner lays out its own network.
fn tch_sequential(spec: &NetworkSpec, weights: &[f32]) -> (nn::VarStore, nn::Sequential) {
    let store = nn::VarStore::new(tch::Device::Cpu);
    let root = store.root();
    let mut sequential = nn::seq();
    let mut inputs = spec.obs_dim as i64;
    for (i, &width) in spec.hidden.iter().enumerate() {
        let index = spec.stride() * i;
        sequential = sequential.add(nn::linear(&root / index, inputs, width as i64, Default::default()));
        if spec.layer_norm {
            sequential = sequential.add(nn::layer_norm(&root / (index + 1), vec![width as i64], Default::default()));
        }
        sequential = sequential.add_fn(Tensor::relu);
        inputs = width as i64;
    }
    let last = spec.stride() * spec.hidden.len();
    sequential = sequential.add(nn::linear(&root / last, inputs, spec.num_actions as i64, Default::default()));
    let variables = store.variables();
    let mut offset = 0;
    tch::no_grad(|| {
        for info in spec.params() {
            let shape: Vec<i64> = info.shape.iter().map(|&d| d as i64).collect();
            let values = Tensor::from_slice(&weights[offset..offset + info.numel()]).view(shape.as_slice());
            offset += info.numel();
            let mut variable = variables[&info.name].shallow_clone();
            variable.copy_(&values);
        }
    });
    (store, sequential)
}

fn inference(batch: usize) -> serde_json::Value {
    tch::manual_seed(0);
    let spec = NetworkSpec::study();
    let dqn = Dqn::new(spec.clone(), DqnConfig::default());
    let policy = MlpPolicy::from_safetensors(&encode_weights(&dqn.online), &spec).unwrap_or_else(|e| panic!("{e}"));
    let (_store, sequential) = tch_sequential(&spec, &dqn.online.flat_values());
    let inputs: Vec<f32> = (0..batch * OBS_DIM).map(|i| ((i * 7919) % 13) as f32 * 0.1 - 0.6).collect();
    let tensor = Tensor::from_slice(&inputs).view([batch as i64, OBS_DIM as i64]);
    // Both compute the same function: a bench that timed different work would mislead.
    let ours = policy.q_values(&inputs).unwrap_or_else(|e| panic!("{e}"));
    let theirs: Vec<f32> =
        Vec::try_from(tch::no_grad(|| sequential.forward(&tensor)).flatten(0, -1)).unwrap_or_else(|e| panic!("{e}"));
    let max_diff = ours.iter().zip(&theirs).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(ours.len() == theirs.len() && max_diff < 1e-4, "the anchor computes another function: {max_diff}");
    let rust = rate(|| {
        let _ = std::hint::black_box(policy.q_values(&inputs));
    });
    let torch = rate(|| {
        let _ = std::hint::black_box(tch::no_grad(|| sequential.forward(&tensor)));
    });
    json!({
        "row": format!("inference-b{batch}"),
        "project": 1e6 / rust,
        "anchor": 1e6 / torch,
        "anchor_name": "tch 0.26 nn::seq (libtorch 2.13)",
        "unit": "µs",
        "what": "study network 40-512-256-128-25, plain Rust",
    })
}

fn update(row: &str, spec: NetworkSpec, config: DqnConfig) -> serde_json::Value {
    let batch = config.batch_size as i64;
    tch::manual_seed(1);
    let cpu = (Kind::Float, tch::Device::Cpu);
    let data = Batch {
        observations: Tensor::randn([batch, OBS_DIM as i64], cpu),
        actions: Tensor::randint(spec.num_actions as i64, [batch], (Kind::Int64, tch::Device::Cpu)),
        returns: Tensor::randn([batch], cpu),
        next_observations: Tensor::randn([batch, OBS_DIM as i64], cpu),
        discounts: Tensor::full([batch], config.gamma, cpu),
        weights: None,
    };
    let what = format!("{spec:?}, {config:?}");
    let mut dqn = Dqn::new(spec, config);
    let per_second = rate(|| {
        std::hint::black_box(dqn.update(&data));
    });
    json!({ "row": row, "project": per_second, "unit": "updates/s", "what": what })
}

/// configs/default.toml's `[dqn]` section at `batch_size`.
fn default_dqn(batch_size: usize) -> DqnConfig {
    DqnConfig { batch_size, loss: LossKind::Huber, max_grad_norm: Some(10.0), gamma: 0.98, ..DqnConfig::default() }
}

fn measure(row: &str) -> Option<serde_json::Value> {
    let study = || NetworkSpec::study();
    let default_net = NetworkSpec { obs_dim: OBS_DIM, hidden: vec![256, 256], num_actions: 25, layer_norm: true };
    Some(match row {
        "physics" => physics(),
        "inference-b1" => inference(1),
        "inference-b8" => inference(8),
        "inference-b16" => inference(16),
        "update-study-b32" => update(row, study(), DqnConfig { batch_size: 32, ..DqnConfig::default() }),
        "update-study-b256" => update(row, study(), DqnConfig { batch_size: 256, ..DqnConfig::default() }),
        // The default preset's network and loss; 64 is its batch size.
        "update-default-b32" => update(row, default_net, default_dqn(32)),
        "update-default-b64" => update(row, default_net, default_dqn(64)),
        "update-default-b256" => update(row, default_net, default_dqn(256)),
        _ => return None,
    })
}

fn main() {
    crawler_learner::tune_allocator();
    crawler_learner::set_torch_threads(1);
    // cargo bench passes `--bench`; every other argument is a row.
    let asked: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let rows: Vec<&str> = if asked.is_empty() { ROWS.to_vec() } else { asked.iter().map(String::as_str).collect() };
    for row in rows {
        match measure(row) {
            Some(result) => println!("{result}"),
            None => {
                eprintln!("anchors: unknown row `{row}`; the rows are {}", ROWS.join(", "));
                std::process::exit(2);
            }
        }
    }
}
