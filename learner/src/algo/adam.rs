//! Adam over one flat parameter buffer, in a single fused pass.
//!
//! Per element, the arithmetic of `torch.optim.Adam(fused=True)` (no weight decay, no
//! AMSGrad), in f32:
//! m ← m + (1 − β1)·(g − m); v ← β2·v + (1 − β2)·g²;
//! θ ← θ − (lr / (1 − β1ᵗ)) · m / (√v / √(1 − β2ᵗ) + ε).
//!
//! Why not tensor ops: over a flat buffer Adam is ~9 tensor passes, each streaming the whole
//! network through memory (370 µs for the study's 190 k parameters). One fused loop in Rust
//! over the parameters in place (`tensor_memory`), reading each gradient part where autograd
//! left it and applying the clipping factor on the way, is one pass.

use tch::Tensor;

use super::network::Gradient;
use super::tensor_memory;

/// Adam's fixed settings. The learning rate is not one of them: it changes under
/// `dqn.lr_decay`, and its one owner is `DqnConfig::learning_rate`, which hands it to every
/// [`FlatAdam::step`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamConfig {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self { beta1: 0.9, beta2: 0.999, eps: 1e-8 }
    }
}

/// Adam's state for a flat buffer of parameters.
#[derive(Debug, Clone)]
pub struct FlatAdam {
    pub config: AdamConfig,
    /// First-moment estimate.
    pub exp_avg: Vec<f32>,
    /// Second-moment estimate.
    pub exp_avg_sq: Vec<f32>,
    /// Steps taken.
    pub step: u64,
}

impl FlatAdam {
    pub fn new(num_params: usize, config: AdamConfig) -> Self {
        let zeros = || vec![0.0f32; num_params];
        Self { config, exp_avg: zeros(), exp_avg_sq: zeros(), step: 0 }
    }

    /// Applies one step of learning rate `lr` to `params` (a flat f32 tensor) given its
    /// gradient times `grad_scale` (the clipping factor, 1 without clipping), in place: one
    /// pass over parameters, moments and gradient.
    ///
    /// # Panics
    /// If the lengths differ from the state's, or `params` is not a contiguous f32 CPU tensor:
    /// programming errors.
    pub fn step(&mut self, params: &mut Tensor, grad: &Gradient, lr: f64, grad_scale: f32) {
        let n = self.exp_avg.len();
        assert!(params.numel() == n && grad.numel() == n, "Adam state is for {n} parameters");
        // SAFETY: `params` is borrowed mutably for this call and no other handle to its
        // storage is used while the slice lives (the network's per-parameter views of it are
        // read only by forward passes, none of which run here).
        #[allow(unsafe_code)]
        let params = unsafe { tensor_memory::f32s_mut(params) };
        self.step += 1;
        let AdamConfig { beta1, beta2, eps } = self.config;
        // Past i32::MAX the bias corrections are 1 to the last bit; a wrapped exponent would
        // make them 0 and every step infinite.
        let t = i32::try_from(self.step).unwrap_or(i32::MAX);
        let step = AdamStep {
            step_size: (lr / (1.0 - beta1.powi(t))) as f32,
            bias_correction2_sqrt: (1.0 - beta2.powi(t)).sqrt() as f32,
            one_minus_beta1: (1.0 - beta1) as f32,
            beta2: beta2 as f32,
            one_minus_beta2: (1.0 - beta2) as f32,
            eps: eps as f32,
            grad_scale,
        };
        let mut offset = 0;
        grad.for_each_part(|g| {
            let range = offset..offset + g.len();
            offset = range.end;
            let (p, m, v) = (&mut params[range.clone()], &mut self.exp_avg[range.clone()], &mut self.exp_avg_sq[range]);
            adam_pass(p, m, v, g, &step);
        });
    }
}

/// One step's coefficients, in f32 as the fused kernel uses them.
#[derive(Debug, Clone, Copy)]
struct AdamStep {
    step_size: f32,
    bias_correction2_sqrt: f32,
    one_minus_beta1: f32,
    beta2: f32,
    one_minus_beta2: f32,
    eps: f32,
    /// The clipping factor the gradient is multiplied by.
    grad_scale: f32,
}

/// The fused Adam update of one stretch of parameters, compiled for each SIMD level and picked
/// at run time (sqrt and division vectorise only from SSE up; AVX-512 does 16 at a time).
#[multiversion::multiversion(targets = "simd")]
fn adam_pass(params: &mut [f32], exp_avg: &mut [f32], exp_avg_sq: &mut [f32], grad: &[f32], step: &AdamStep) {
    let lanes = params.iter_mut().zip(exp_avg.iter_mut()).zip(exp_avg_sq.iter_mut().zip(grad));
    for ((p, m), (v, &g)) in lanes {
        let g = g * step.grad_scale;
        *m += step.one_minus_beta1 * (g - *m);
        *v = step.beta2 * *v + step.one_minus_beta2 * g * g;
        let denom = v.sqrt() / step.bias_correction2_sqrt + step.eps;
        *p -= step.step_size * *m / denom;
    }
}
