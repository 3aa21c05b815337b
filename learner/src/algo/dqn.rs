//! The Double DQN update: TD targets, loss, Adam and target-network upkeep.

use crawler_env::policy::{NetworkSpec, argmax, q_values_of_params};
pub use crawler_run::config::{DqnConfig, LossKind, LrDecay, TargetUpdate};
use tch::{Kind, Reduction, Tensor};

use super::adam::{AdamConfig, FlatAdam};
use super::network::{BUFFER_LAYOUT, QNetwork};
use super::tensor_memory;

/// One sampled minibatch, already as tensors. `discount` is γⁿ for an n-step transition that
/// bootstraps and 0 for one that ended in termination.
#[derive(Debug)]
pub struct Batch {
    pub observations: Tensor,
    pub actions: Tensor,
    pub returns: Tensor,
    pub next_observations: Tensor,
    pub discounts: Tensor,
    /// Importance-sampling weights (prioritised replay), or None for uniform.
    pub weights: Option<Tensor>,
}

/// Gradient norms at or above this are refused like non-finite ones: squared into Adam's
/// second moment they would overflow f32 (its largest value is 3.4e38).
pub const MAX_APPLIED_GRAD_NORM: f64 = 1e18;

/// What one update measured.
#[derive(Debug, Clone, PartialEq)]
pub struct UpdateStats {
    /// False when the loss or the gradient was not finite (or too large to apply): the
    /// weights, the optimiser and the target network were left as they were.
    pub applied: bool,
    pub loss: f64,
    pub mean_q: f64,
    /// |TD error| per sample, for priority updates.
    pub td_errors: Vec<f32>,
    pub grad_norm: f64,
    /// The learning rate of this update (`DqnConfig::learning_rate` at its count), applied
    /// or not.
    pub learning_rate: f64,
}

/// Online and target Q-networks with their optimiser.
#[derive(Debug)]
pub struct Dqn {
    /// The Q-network's shape (online and target alike).
    pub network: NetworkSpec,
    pub config: DqnConfig,
    pub online: QNetwork,
    pub target: QNetwork,
    pub optimizer: FlatAdam,
    /// Gradient updates done.
    pub updates: u64,
}

impl Dqn {
    pub fn new(network: NetworkSpec, config: DqnConfig) -> Self {
        tch::manual_seed(config.seed as i64);
        let online = QNetwork::new(&network, true);
        let mut target = QNetwork::new(&network, false);
        target.copy_from(&online);
        let adam = AdamConfig { eps: config.adam_eps, ..AdamConfig::default() };
        let optimizer = FlatAdam::new(online.flat().numel(), adam);
        Self { network, config, online, target, optimizer, updates: 0 }
    }

    /// The TD target scale · r + discount · Q⁻(s', a*) with a* chosen by the online net
    /// (Double) or the target net (vanilla).
    ///
    /// Why not libtorch: these forward passes need no gradient, so they run in the actors'
    /// plain-Rust MLP over the parameter buffers in place (`gemm` kernels at the CPU's own SIMD
    /// width, no autograd bookkeeping, no per-op dispatch): a fifth of an update's GEMM work
    /// and some thirty tensor ops become two calls. `learner/tests/it/network.rs` pins them
    /// to libtorch's forward pass.
    pub fn td_targets(&self, batch: &Batch) -> Tensor {
        let plain = tensor_memory::plain_f32;
        let (next, returns, discounts) =
            (plain(&batch.next_observations), plain(&batch.returns), plain(&batch.discounts));
        // SAFETY: every tensor read here is either this batch's own (copies made just above,
        // or the batch's tensors, which nothing writes during an update) or a network's flat
        // buffer, which only `FlatAdam::step` and the target updates write, and neither runs
        // while these slices live.
        #[allow(unsafe_code)]
        let (next, returns, discounts, online, target) = unsafe {
            (
                tensor_memory::f32s(&next),
                tensor_memory::f32s(&returns),
                tensor_memory::f32s(&discounts),
                tensor_memory::f32s(self.online.flat()),
                tensor_memory::f32s(self.target.flat()),
            )
        };
        let forward = |params: &[f32]| {
            q_values_of_params(&self.network, params, BUFFER_LAYOUT, next)
                .expect("replay batches hold observations of the network's size and the buffers fit its spec")
        };
        let actions = self.network.num_actions;
        let target_q = forward(target);
        let bootstrap: Vec<f32> = if self.config.double {
            let online_q = forward(online);
            let best = online_q.chunks_exact(actions).map(argmax);
            target_q.chunks_exact(actions).zip(best).map(|(q, a)| q[a as usize]).collect()
        } else {
            target_q.chunks_exact(actions).map(|q| q.iter().copied().fold(f32::NEG_INFINITY, f32::max)).collect()
        };
        let scale = self.config.reward_scale as f32;
        let targets: Vec<f32> =
            returns.iter().zip(discounts).zip(&bootstrap).map(|((&r, &d), &b)| r * scale + d * b).collect();
        Tensor::from_slice(&targets)
    }

    /// One gradient step on `batch`; updates the target network as configured.
    pub fn update(&mut self, batch: &Batch) -> UpdateStats {
        let targets = self.td_targets(batch);
        let q = self.online.forward(&batch.observations).gather(1, &batch.actions.unsqueeze(1), false).squeeze_dim(1);
        // Per sample only where importance weights scale the samples; else reduced in the op.
        let reduction = if batch.weights.is_some() { Reduction::None } else { Reduction::Mean };
        let loss = match self.config.loss {
            LossKind::Mse => q.mse_loss(&targets, reduction),
            LossKind::Huber => q.huber_loss(&targets, reduction, 1.0),
        };
        let loss = match &batch.weights {
            Some(w) => (loss * w).mean(Kind::Float),
            None => loss,
        };
        let grad = self.online.gradient(&loss);
        let grad_norm = grad.l2_norm();
        let loss_value = loss.double_value(&[]);
        let learning_rate = self.config.learning_rate(self.updates);
        if !(loss_value.is_finite() && grad_norm.is_finite() && grad_norm < MAX_APPLIED_GRAD_NORM) {
            // One bad batch must not poison the weights: skip the step, report it.
            return UpdateStats {
                applied: false,
                loss: loss_value,
                mean_q: f64::NAN,
                td_errors: Vec::new(),
                grad_norm,
                learning_rate,
            };
        }
        // Clipping as torch.nn.utils.clip_grad_norm_ does it, folded into Adam's pass.
        let grad_scale = match self.config.max_grad_norm {
            Some(max) if grad_norm > max => (max / (grad_norm + 1e-6)) as f32,
            _ => 1.0,
        };
        self.optimizer.step(self.online.flat_mut(), &grad, learning_rate, grad_scale);
        self.updates += 1;
        match self.config.target_update {
            TargetUpdate::Hard { every } => {
                if self.updates.is_multiple_of(every.max(1)) {
                    self.target.copy_from(&self.online);
                }
            }
            TargetUpdate::Polyak { tau } => self.target.polyak_from(&self.online, tau),
        }
        let (mean_q, td_errors) = td_summary(&tensor_memory::plain_f32(&q), &tensor_memory::plain_f32(&targets));
        UpdateStats { applied: true, loss: loss_value, mean_q, td_errors, grad_norm, learning_rate }
    }

    /// Q-values of the online network for `batch × obs_dim` observations.
    pub fn q_values(&self, observations: &Tensor) -> Tensor {
        tch::no_grad(|| self.online.forward(observations))
    }
}

/// The batch's mean Q and each sample's |TD error|, in one pass over the two vectors (as
/// tensor ops it would be four ops and a copy).
fn td_summary(q: &Tensor, targets: &Tensor) -> (f64, Vec<f32>) {
    // SAFETY: `q` and `targets` are this update's own results; nothing writes them while the
    // slices live.
    #[allow(unsafe_code)]
    let (q, targets) = unsafe { (tensor_memory::f32s(q), tensor_memory::f32s(targets)) };
    let mean_q = q.iter().map(|&v| f64::from(v)).sum::<f64>() / q.len().max(1) as f64;
    (mean_q, q.iter().zip(targets).map(|(a, b)| (a - b).abs()).collect())
}
