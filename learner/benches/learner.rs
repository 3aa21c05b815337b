//! Learner-core throughput: DQN updates, Adam's share, replay and inference.
//! `cargo bench -p crawler-learner --bench learner`
#![allow(clippy::print_stdout)]

mod support;

use std::time::{Duration, Instant};

use crawler_env::policy::{MlpPolicy, NetworkSpec};
use crawler_learner::algo::adam::{AdamConfig, FlatAdam};
use crawler_learner::algo::dqn::{Batch, Dqn, DqnConfig};
use crawler_learner::algo::network::Gradient;
use crawler_learner::checkpoint::encode_weights;
use crawler_learner::replay::{Replay, ReplayConfig, SampledBatch, StreamId, Transition};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use support::rate;
use tch::nn::OptimizerConfig;
use tch::{Kind, Tensor, nn};

const OBS: usize = 40;

fn random_batch(batch: i64) -> Batch {
    let cpu = (Kind::Float, tch::Device::Cpu);
    Batch {
        observations: Tensor::randn([batch, OBS as i64], cpu),
        actions: Tensor::randint(25, [batch], (Kind::Int64, tch::Device::Cpu)),
        returns: Tensor::randn([batch], cpu),
        next_observations: Tensor::randn([batch, OBS as i64], cpu),
        discounts: Tensor::full([batch], 0.99, cpu),
        weights: None,
    }
}

/// Microseconds per step of libtorch's per-parameter Adam over the study's network, with
/// gradients in place (what the flat fused Adam replaces).
fn per_parameter_adam_step_us(spec: &NetworkSpec, budget: Duration) -> f64 {
    let vs = nn::VarStore::new(tch::Device::Cpu);
    let params: Vec<Tensor> = spec
        .params()
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let shape: Vec<i64> = p.shape.iter().map(|&d| d as i64).collect();
            vs.root().var(&format!("p{i}"), &shape, nn::Init::Uniform { lo: -0.05, up: 0.05 })
        })
        .collect();
    let mut adam = nn::Adam::default().build(&vs, 5e-4).unwrap_or_else(|e| panic!("{e}"));
    let loss: Tensor = params.iter().map(|p| p.square().sum(Kind::Float)).fold(Tensor::from(0.0f32), |a, b| a + b);
    loss.backward();
    1e6 / rate(budget, || adam.step())
}

/// Microseconds per step of the flat fused Adam over the study's network.
fn flat_adam_step_us(budget: Duration) -> f64 {
    let dqn = Dqn::new(NetworkSpec::study(), DqnConfig::default());
    let mut params = dqn.online.flat().copy();
    let grad = Gradient::from_parts(vec![Tensor::randn([params.numel() as i64], (Kind::Float, tch::Device::Cpu))]);
    let mut adam = FlatAdam::new(params.numel(), AdamConfig::default());
    1e6 / rate(budget, || adam.step(&mut params, &grad, 1e-3, 1.0))
}

fn main() {
    let budget = Duration::from_millis(3000);
    let spec = NetworkSpec::study();
    crawler_learner::tune_allocator();
    let mut update_us_batch32 = f64::NAN;

    println!("== DQN updates/s, study network 40-512-256-128-25 (Double DQN, MSE)");
    for threads in [1usize, 2] {
        crawler_learner::set_torch_threads(threads);
        for batch in [32i64, 256] {
            let mut dqn = Dqn::new(NetworkSpec::study(), DqnConfig::default());
            let data = random_batch(batch);
            let flat = rate(budget, || {
                dqn.update(&data);
            });
            println!("threads={threads} batch={batch:<3}  {flat:>6.0} updates/s  ({:>6.0} µs each)", 1e6 / flat);
            if threads == 1 && batch == 32 {
                update_us_batch32 = 1e6 / flat;
            }
        }
    }
    let flat_adam = flat_adam_step_us(budget);
    let torch_adam = per_parameter_adam_step_us(&spec, budget);
    println!(
        "Adam step, one thread: flat fused {flat_adam:.0} µs vs libtorch per-parameter {torch_adam:.0} µs ({:.2}x faster)",
        torch_adam / flat_adam
    );
    println!(
        "Adam's share of a batch-32 update: {:.0}% with the flat fused Adam; {:.0}% if libtorch's were swapped in",
        100.0 * flat_adam / update_us_batch32,
        100.0 * torch_adam / (update_us_batch32 - flat_adam + torch_adam)
    );
    crawler_learner::set_torch_threads(1);

    println!("== replay (capacity 500 000, 40-value observations, episodes of 1 000 steps)");
    let mut replay = Replay::new(ReplayConfig::default(), OBS).unwrap_or_else(|e| panic!("{e}"));
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    // Four interleaved streams, each continuing from its own last observation.
    const STREAMS: usize = 4;
    let mut last: Vec<Vec<f32>> = vec![vec![0.0f32; OBS]; STREAMS];
    let mut next = vec![0.0f32; OBS];
    let mut t = 0u64;
    let mut insert = |replay: &mut Replay| {
        let stream = (t % STREAMS as u64) as usize;
        next.iter_mut().for_each(|v| *v = rng.random());
        let terminated = (t / STREAMS as u64) % 1000 == 999;
        let transition = Transition {
            observation: &last[stream],
            action: 3,
            reward: 0.5,
            next_observation: &next,
            terminated,
            truncated: false,
        };
        let id = StreamId { actor: stream as u32, env: 0 };
        replay.insert(id, &transition).unwrap_or_else(|e| panic!("{e}"));
        std::mem::swap(&mut last[stream], &mut next);
        if terminated {
            last[stream].iter_mut().for_each(|v| *v = rng.random());
        }
        t += 1;
    };
    let fill = 600_000;
    let start = Instant::now();
    for _ in 0..fill {
        insert(&mut replay);
    }
    let insert_rate = fill as f64 / start.elapsed().as_secs_f64();
    println!("insert: {insert_rate:>12.0} transitions/s");
    let mut out = SampledBatch::default();
    let mut sample_rng = ChaCha8Rng::seed_from_u64(1);
    for batch in [32usize, 256] {
        let per_second = rate(budget, || {
            replay.sample(batch, 0.99, 0.4, &mut sample_rng, &mut out).unwrap_or_else(|e| panic!("{e}"));
        });
        println!("sample batch={batch:<3}: {:>9.0} transitions/s", per_second * batch as f64);
    }
    let per_transition = replay.memory_bytes() as f64 / replay.len() as f64;
    let raw = replay.raw_bytes_per_transition() as f64;
    let naive = (2 * OBS * 4 + 1 + 4 + 1) as f64;
    println!(
        "memory: {per_transition:.1} bytes per stored transition; raw {raw} ({:.3}x raw; storing s and s' would be {naive})",
        per_transition / raw
    );

    println!("== inference, study network: plain Rust vs tch");
    tch::manual_seed(0);
    let dqn = Dqn::new(NetworkSpec::study(), DqnConfig::default());
    let policy = MlpPolicy::from_safetensors(&encode_weights(&dqn.online), &spec).unwrap_or_else(|e| panic!("{e}"));
    for batch in [1usize, 16] {
        let inputs: Vec<f32> = (0..batch * OBS).map(|i| (i % 7) as f32 * 0.3).collect();
        let tensor = Tensor::from_slice(&inputs).view([batch as i64, OBS as i64]);
        let rust = rate(budget, || {
            let _ = policy.q_values(&inputs);
        });
        let torch = rate(budget, || {
            let _ = dqn.q_values(&tensor);
        });
        println!(
            "batch={batch:<2}  plain Rust {:>8.1} µs   tch {:>8.1} µs   (plain Rust / tch time {:.2})",
            1e6 / rust,
            1e6 / torch,
            torch / rust
        );
    }
}
