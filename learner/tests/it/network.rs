//! The Q-network: plain-Rust inference parity, Adam parity, and the TD targets.

#![allow(clippy::unwrap_used)] // Tests: a panic is a failure with a message.

use crawler_env::policy::{MlpPolicy, NetworkSpec};
use crawler_learner::algo::adam::{AdamConfig, FlatAdam};
use crawler_learner::algo::dqn::{Batch, Dqn, DqnConfig, LossKind, TargetUpdate};
use crawler_learner::algo::network::QNetwork;
use crawler_learner::checkpoint::encode_weights;
use tch::{Kind, Tensor, nn, nn::OptimizerConfig};

fn small() -> NetworkSpec {
    NetworkSpec { obs_dim: 40, hidden: vec![64, 32], num_actions: 25, layer_norm: true }
}

#[test]
fn plain_rust_inference_matches_the_tch_forward_pass() {
    let specs = [
        NetworkSpec::study(),
        small(),
        NetworkSpec { obs_dim: 40, hidden: vec![48], num_actions: 9, layer_norm: false },
    ];
    for (seed, spec) in specs.iter().enumerate() {
        tch::manual_seed(seed as i64);
        let network = QNetwork::new(spec, true);
        let policy = MlpPolicy::from_safetensors(&encode_weights(&network), spec).unwrap();
        for batch in [1i64, 5, 16] {
            // Observation-like inputs: mostly O(1), some large (touch forces reach tens of N).
            let inputs = Tensor::randn([batch, spec.obs_dim as i64], (Kind::Float, tch::Device::Cpu)) * 5.0;
            let expected: Vec<f32> = Vec::try_from(tch::no_grad(|| network.forward(&inputs)).flatten(0, -1)).unwrap();
            let values: Vec<f32> = Vec::try_from(inputs.flatten(0, -1)).unwrap();
            let got = policy.q_values(&values).unwrap();
            assert_eq!(got.len(), expected.len());
            let max_diff = got.iter().zip(&expected).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
            assert!(max_diff <= 1e-5, "{spec:?} batch {batch}: max |diff| {max_diff}");
            let mut actions = Vec::new();
            policy.greedy_actions(&values, &mut actions).unwrap();
            let tch_actions: Vec<i64> =
                Vec::try_from(tch::no_grad(|| network.forward(&inputs)).argmax(1, false)).unwrap();
            assert_eq!(actions.iter().map(|&a| i64::from(a)).collect::<Vec<_>>(), tch_actions);
        }
    }
}

#[test]
fn policy_loading_names_what_is_wrong() {
    let network = QNetwork::new(&small(), false);
    let bytes = encode_weights(&network);
    let other = NetworkSpec { hidden: vec![64, 16], ..small() };
    let err = MlpPolicy::from_safetensors(&bytes, &other).unwrap_err().to_string();
    assert!(err.contains("3.weight") && err.contains("[16, 64]"), "{err}");
    let err = MlpPolicy::from_safetensors(&bytes[..bytes.len() / 2], &small()).unwrap_err().to_string();
    assert!(err.contains("safetensors"), "{err}");
    assert!(MlpPolicy::from_safetensors(&bytes, &small()).unwrap().q_values(&[0.0; 39]).is_err());
}

#[test]
fn flat_adam_matches_libtorch_adam() {
    let spec = small();
    tch::manual_seed(7);
    let mut ours = QNetwork::new(&spec, true);
    // The reference: libtorch's Adam over the same parameters, one tensor each, in PyTorch's
    // layout (ours keeps each weight transposed).
    let vs = nn::VarStore::new(tch::Device::Cpu);
    for (i, p) in ours.params().iter().enumerate() {
        let p = if p.dim() == 2 { p.t_copy() } else { p.shallow_clone() };
        let _ = vs.root().var_copy(&format!("p{i}"), &p);
    }
    let reference_params = vs.trainable_variables();
    let lr = 1e-3;
    let mut adam = FlatAdam::new(ours.flat().numel(), AdamConfig::default());
    let mut torch_adam = nn::Adam::default().build(&vs, lr).unwrap();
    for step in 0..25 {
        let inputs = Tensor::randn([32, 40], (Kind::Float, tch::Device::Cpu));
        let targets = Tensor::randn([32, 25], (Kind::Float, tch::Device::Cpu));
        let loss = ours.forward(&inputs).mse_loss(&targets, tch::Reduction::Mean);
        let grad = ours.gradient(&loss);
        adam.step(ours.flat_mut(), &grad, lr, 1.0);
        let reference_loss = forward_with(&spec, &reference_params, &inputs).mse_loss(&targets, tch::Reduction::Mean);
        torch_adam.backward_step(&reference_loss);
        let reference_flat =
            Tensor::cat(&reference_params.iter().map(|p| p.detach().view([-1])).collect::<Vec<_>>(), 0);
        let diff = (Tensor::from_slice(&ours.flat_values()) - reference_flat).abs().max().double_value(&[]);
        assert!(diff < 1e-6, "step {step}: parameters differ by {diff}");
    }
}

/// The MLP forward pass over a list of separate parameter tensors (LayerNorm variant).
fn forward_with(spec: &NetworkSpec, params: &[Tensor], x: &Tensor) -> Tensor {
    let mut x = x.shallow_clone();
    let mut i = 0;
    for &width in &spec.hidden {
        x = x.linear(&params[i], Some(&params[i + 1]));
        x = x.layer_norm([width as i64], Some(&params[i + 2]), Some(&params[i + 3]), 1e-5, false).relu();
        i += 4;
    }
    x.linear(&params[i], Some(&params[i + 1]))
}

/// A linear network (no hidden layer): Q(s) = W s + b, with W and b set by hand.
fn linear_dqn(double: bool, online: &[f32], target: &[f32]) -> Dqn {
    let spec = NetworkSpec { obs_dim: 2, hidden: vec![], num_actions: 3, layer_norm: false };
    let config = DqnConfig {
        gamma: 0.9,
        double,
        target_update: TargetUpdate::Hard { every: 1_000_000 },
        ..DqnConfig::default()
    };
    let mut dqn = Dqn::new(spec, config);
    dqn.online.load_flat(online).unwrap();
    dqn.target.load_flat(target).unwrap();
    dqn
}

#[test]
fn double_and_vanilla_targets_match_a_hand_computed_example() {
    // Rows of W then b. At s' = (1, 2): online Q = (1, 2, 1.5), so the online net picks
    // action 1; target Q = (5, 2, 3), whose own max is action 0.
    let online = [1.0, 0.0, 0.0, 1.0, 0.5, 0.5, 0.0, 0.0, 0.0];
    let target = [5.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0];
    let batch = Batch {
        observations: Tensor::from_slice(&[0.0f32, 0.0, 0.0, 0.0]).view([2, 2]),
        actions: Tensor::from_slice(&[0i64, 0]),
        returns: Tensor::from_slice(&[1.0f32, 1.0]),
        next_observations: Tensor::from_slice(&[1.0f32, 2.0, 1.0, 2.0]).view([2, 2]),
        discounts: Tensor::from_slice(&[0.9f32, 0.0]),
        weights: None,
    };
    let targets = |double, reward_scale| {
        let mut dqn = linear_dqn(double, &online, &target);
        dqn.config.reward_scale = reward_scale;
        Vec::<f32>::try_from(dqn.td_targets(&batch)).unwrap()
    };
    // Double: 1 + 0.9 · Q⁻(s', 1) = 1 + 0.9 · 2; vanilla: 1 + 0.9 · max Q⁻(s') = 1 + 0.9 · 5.
    // The second sample terminated: its target is its reward alone.
    let double = targets(true, 1.0);
    let vanilla = targets(false, 1.0);
    assert!((double[0] - 2.8).abs() < 1e-6 && (double[1] - 1.0).abs() < 1e-6, "{double:?}");
    assert!((vanilla[0] - 5.5).abs() < 1e-6 && (vanilla[1] - 1.0).abs() < 1e-6, "{vanilla:?}");
    // A reward scale multiplies the returns only, not the bootstrapped value: 0.5 + 0.9 · 2.
    let scaled = targets(true, 0.5);
    assert!((scaled[0] - 2.3).abs() < 1e-6 && (scaled[1] - 0.5).abs() < 1e-6, "{scaled:?}");
}

#[test]
fn an_update_reduces_the_loss_and_hard_target_updates_copy_on_schedule() {
    for loss in [LossKind::Mse, LossKind::Huber] {
        let config = DqnConfig {
            lr: 1e-3,
            loss,
            max_grad_norm: Some(10.0),
            target_update: TargetUpdate::Hard { every: 5 },
            ..DqnConfig::default()
        };
        let mut dqn = Dqn::new(small(), config);
        let batch = Batch {
            observations: Tensor::randn([32, 40], (Kind::Float, tch::Device::Cpu)),
            actions: Tensor::randint(25, [32], (Kind::Int64, tch::Device::Cpu)),
            returns: Tensor::ones([32], (Kind::Float, tch::Device::Cpu)),
            next_observations: Tensor::randn([32, 40], (Kind::Float, tch::Device::Cpu)),
            discounts: Tensor::zeros([32], (Kind::Float, tch::Device::Cpu)),
            weights: Some(Tensor::ones([32], (Kind::Float, tch::Device::Cpu))),
        };
        let first = dqn.update(&batch);
        assert!(first.loss.is_finite() && first.td_errors.len() == 32);
        let target_before: Tensor = dqn.target.flat().copy();
        for _ in 0..3 {
            dqn.update(&batch);
        }
        assert!(dqn.target.flat().equal(&target_before), "no copy before update 5");
        let last = dqn.update(&batch);
        assert!(dqn.target.flat().equal(&dqn.online.flat().detach()), "copied at update 5");
        assert!(last.loss < first.loss, "{loss:?}: {} -> {}", first.loss, last.loss);
    }
}

/// Under `dqn.lr_decay` the optimiser steps with the annealed rate: after the decay's one
/// update, a step moves the weights about 100× less than the same step at the constant rate.
#[test]
fn a_learning_rate_decay_shrinks_the_optimiser_steps() {
    use crawler_learner::algo::dqn::LrDecay;
    let batch = || Batch {
        observations: Tensor::randn([32, 40], (Kind::Float, tch::Device::Cpu)),
        actions: Tensor::randint(25, [32], (Kind::Int64, tch::Device::Cpu)),
        returns: Tensor::ones([32], (Kind::Float, tch::Device::Cpu)),
        next_observations: Tensor::randn([32, 40], (Kind::Float, tch::Device::Cpu)),
        discounts: Tensor::zeros([32], (Kind::Float, tch::Device::Cpu)),
        weights: None,
    };
    tch::manual_seed(7);
    let batches = [batch(), batch()];
    let second_step = |lr_decay| {
        let config = DqnConfig { lr: 1e-3, lr_decay, ..DqnConfig::default() };
        let mut dqn = Dqn::new(small(), config);
        dqn.update(&batches[0]);
        let before: Tensor = dqn.online.flat().copy();
        let stats = dqn.update(&batches[1]);
        let moved = (dqn.online.flat().detach() - before).abs().max().double_value(&[]);
        (moved, stats.learning_rate)
    };
    let (constant, constant_lr) = second_step(None);
    let (decayed, decayed_lr) = second_step(Some(LrDecay { final_lr: 1e-5, updates: 1 }));
    assert!((constant_lr - 1e-3).abs() < 1e-12, "{constant_lr}");
    assert!((decayed_lr - 1e-5).abs() < 1e-12, "{decayed_lr}");
    assert!(constant > 1e-4, "a constant-rate step moved the weights by at most {constant}");
    assert!(decayed < 0.05 * constant, "decayed step {decayed} against constant {constant}");
}
