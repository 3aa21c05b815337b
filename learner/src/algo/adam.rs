//! Adam over one flat parameter buffer, in a single fused pass.
//!
//! Per element, the arithmetic of `torch.optim.Adam(fused=True)` (no weight decay, no
//! AMSGrad), in f32:
//! m ← m + (1 − β1)·(g − m); v ← β2·v + (1 − β2)·g²;
//! θ ← θ − (lr / (1 − β1ᵗ)) · m / (√v / √(1 − β2ᵗ) + ε).
//!
//! Why not tensor ops: over a flat buffer Adam is ~9 tensor passes, each streaming the whole
//! network through memory (370 µs for the study's 190 k parameters). One fused loop in Rust,
//! plus copying the gradient out and the parameters back in, is about 3x cheaper.

use tch::Tensor;

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
    params: Vec<f32>,
    grad: Vec<f32>,
}

impl FlatAdam {
    pub fn new(num_params: usize, config: AdamConfig) -> Self {
        let zeros = || vec![0.0f32; num_params];
        Self { config, exp_avg: zeros(), exp_avg_sq: zeros(), step: 0, params: zeros(), grad: zeros() }
    }

    /// Applies one step to `params` (a flat f32 tensor) given its flat gradient.
    ///
    /// # Panics
    /// If the tensors' lengths differ from the state's: a programming error.
    pub fn step(&mut self, params: &mut Tensor, grad: &Tensor) {
        let n = self.exp_avg.len();
        assert!(params.numel() == n && grad.numel() == n, "Adam state is for {n} parameters");
        grad.copy_data(&mut self.grad, n);
        params.copy_data(&mut self.params, n);
        self.step += 1;
        let AdamConfig { lr, beta1, beta2, eps } = self.config;
        let t = self.step as i32;
        let step_size = (lr / (1.0 - beta1.powi(t))) as f32;
        let bias_correction2_sqrt = (1.0 - beta2.powi(t)).sqrt() as f32;
        let (one_minus_beta1, beta2, one_minus_beta2, eps) =
            ((1.0 - beta1) as f32, beta2 as f32, (1.0 - beta2) as f32, eps as f32);
        let update = |p: &mut f32, m: &mut f32, v: &mut f32, g: f32| {
            *m += one_minus_beta1 * (g - *m);
            *v = beta2 * *v + one_minus_beta2 * g * g;
            let denom = v.sqrt() / bias_correction2_sqrt + eps;
            *p -= step_size * *m / denom;
        };
        // Fixed-size blocks let the compiler keep the loop in SIMD registers.
        const BLOCK: usize = 16;
        let blocks = self.params.chunks_exact_mut(BLOCK).zip(self.exp_avg.chunks_exact_mut(BLOCK));
        for ((p, m), (v, g)) in blocks.zip(self.exp_avg_sq.chunks_exact_mut(BLOCK).zip(self.grad.chunks_exact(BLOCK))) {
            for i in 0..BLOCK {
                update(&mut p[i], &mut m[i], &mut v[i], g[i]);
            }
        }
        let done = n / BLOCK * BLOCK;
        for i in done..n {
            update(&mut self.params[i], &mut self.exp_avg[i], &mut self.exp_avg_sq[i], self.grad[i]);
        }
        tch::no_grad(|| params.copy_(&Tensor::from_slice(&self.params)));
    }
}
