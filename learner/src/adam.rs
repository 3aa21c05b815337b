//! Adam over one flat parameter buffer.
//!
//! The same arithmetic as `torch.optim.Adam` (no weight decay, no AMSGrad) in its fused and
//! foreach forms: m ← lerp(m, g, 1 − β1); v ← β2·v + (1 − β2)·g²;
//! θ ← θ − (lr / (1 − β1ᵗ)) · m / (√v / √(1 − β2ᵗ) + ε). Over a flat buffer it is a fixed
//! handful of tensor ops however many layers the network has.

use tch::{Kind, Tensor};

/// Adam's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamConfig {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self { lr: 1e-3, beta1: 0.9, beta2: 0.999, eps: 1e-8 }
    }
}

/// Adam's state for a flat buffer of `n` parameters.
#[derive(Debug)]
pub struct FlatAdam {
    pub config: AdamConfig,
    /// First-moment estimate.
    pub exp_avg: Tensor,
    /// Second-moment estimate.
    pub exp_avg_sq: Tensor,
    /// Steps taken.
    pub step: u64,
}

impl FlatAdam {
    pub fn new(num_params: i64, config: AdamConfig) -> Self {
        let zeros = || Tensor::zeros([num_params], (Kind::Float, tch::Device::Cpu));
        Self { config, exp_avg: zeros(), exp_avg_sq: zeros(), step: 0 }
    }

    /// Applies one step to `params` (a flat leaf tensor) given its flat gradient.
    pub fn step(&mut self, params: &mut Tensor, grad: &Tensor) {
        let AdamConfig { lr, beta1, beta2, eps } = self.config;
        self.step += 1;
        let t = self.step as i32;
        let bias_correction1 = 1.0 - beta1.powi(t);
        let bias_correction2_sqrt = (1.0 - beta2.powi(t)).sqrt();
        tch::no_grad(|| {
            let _ = self.exp_avg.lerp_(grad, 1.0 - beta1);
            let _ = self.exp_avg_sq.g_mul_scalar_(beta2);
            let _ = self.exp_avg_sq.addcmul_(grad, &(grad * (1.0 - beta2)));
            let denom = (self.exp_avg_sq.sqrt() / bias_correction2_sqrt) + eps;
            let _ = params.addcdiv_(&(&self.exp_avg * (-lr / bias_correction1)), &denom);
        });
    }
}
