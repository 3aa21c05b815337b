//! The Double DQN update: TD targets, loss, Adam and target-network upkeep.

use crawler_actor::policy::NetworkSpec;
pub use crawler_run::config::{DqnConfig, LossKind, TargetUpdate};
use tch::{Kind, Reduction, Tensor};

use super::adam::{AdamConfig, FlatAdam};
use super::network::QNetwork;
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
        let adam = AdamConfig { lr: config.lr, eps: config.adam_eps, ..AdamConfig::default() };
        let optimizer = FlatAdam::new(online.flat().numel(), adam);
        Self { network, config, online, target, optimizer, updates: 0 }
    }

    /// The TD target scale · r + discount · Q⁻(s', a*) with a* chosen by the online net
    /// (Double) or the target net (vanilla).
    pub fn td_targets(&self, batch: &Batch) -> Tensor {
        tch::no_grad(|| {
            let next_target_q = self.target.forward(&batch.next_observations);
            let bootstrap = if self.config.double {
                let best = self.online.forward(&batch.next_observations).argmax(1, true);
                next_target_q.gather(1, &best, false).squeeze_dim(1)
            } else {
                next_target_q.max_dim(1, false).0
            };
            let discounted = &batch.discounts * bootstrap;
            if self.config.reward_scale == 1.0 {
                discounted + &batch.returns
            } else {
                discounted + &batch.returns * self.config.reward_scale
            }
        })
    }

    /// One gradient step on `batch`; updates the target network as configured.
    pub fn update(&mut self, batch: &Batch) -> UpdateStats {
        let targets = self.td_targets(batch);
        let q = self.online.forward(&batch.observations).gather(1, &batch.actions.unsqueeze(1), false).squeeze_dim(1);
        let elementwise = match self.config.loss {
            LossKind::Mse => q.mse_loss(&targets, Reduction::None),
            LossKind::Huber => q.huber_loss(&targets, Reduction::None, 1.0),
        };
        let loss = match &batch.weights {
            Some(w) => (elementwise * w).mean(Kind::Float),
            None => elementwise.mean(Kind::Float),
        };
        let grad = self.online.gradient(&loss);
        let grad_norm = grad.l2_norm();
        let loss_value = loss.double_value(&[]);
        if !(loss_value.is_finite() && grad_norm.is_finite() && grad_norm < MAX_APPLIED_GRAD_NORM) {
            // One bad batch must not poison the weights: skip the step, report it.
            return UpdateStats {
                applied: false,
                loss: loss_value,
                mean_q: f64::NAN,
                td_errors: Vec::new(),
                grad_norm,
            };
        }
        // Clipping as torch.nn.utils.clip_grad_norm_ does it, folded into Adam's pass.
        let grad_scale = match self.config.max_grad_norm {
            Some(max) if grad_norm > max => (max / (grad_norm + 1e-6)) as f32,
            _ => 1.0,
        };
        self.optimizer.step(self.online.flat_mut(), &grad, grad_scale);
        self.updates += 1;
        match self.config.target_update {
            TargetUpdate::Hard { every } => {
                if self.updates.is_multiple_of(every.max(1)) {
                    self.target.copy_from(&self.online);
                }
            }
            TargetUpdate::Polyak { tau } => self.target.polyak_from(&self.online, tau),
        }
        let (mean_q, td_errors) = td_summary(&q.detach().contiguous(), &targets.contiguous());
        UpdateStats { applied: true, loss: loss_value, mean_q, td_errors, grad_norm }
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
