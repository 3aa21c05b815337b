//! The Q-network's forward pass in plain Rust, over the learner's safetensors weights.

use safetensors::{Dtype, SafeTensors};

use super::spec::NetworkSpec;

/// Why weights could not be loaded or used.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error("weights are not a valid safetensors file: {0}")]
    Format(#[from] safetensors::SafeTensorError),
    #[error("network spec is invalid: {0}")]
    Spec(String),
    #[error("weights lack tensor `{0}` that the network spec requires")]
    Missing(String),
    #[error("tensor `{name}` has dtype {dtype} and shape {shape:?}; expected F32 with shape {expected:?}")]
    Mismatch { name: String, dtype: String, shape: Vec<usize>, expected: Vec<usize> },
    #[error("tensor `{0}` holds a NaN or infinite value")]
    NonFinite(String),
    #[error("input holds {len} values, not a whole number of {obs_dim}-value observations")]
    InputSize { len: usize, obs_dim: usize },
}

#[derive(Debug, Clone)]
struct Dense {
    inputs: usize,
    outputs: usize,
    /// Row-major `outputs × inputs`, as PyTorch stores a Linear's weight.
    weight: Vec<f32>,
    bias: Vec<f32>,
    /// LayerNorm's scale and shift, where the layer has one.
    norm: Option<(Vec<f32>, Vec<f32>)>,
    relu: bool,
}

/// PyTorch's default LayerNorm epsilon.
const LAYER_NORM_EPS: f32 = 1e-5;

/// A Q-network evaluated in plain Rust.
#[derive(Debug, Clone)]
pub struct MlpPolicy {
    spec: NetworkSpec,
    layers: Vec<Dense>,
}

impl MlpPolicy {
    /// Loads weights named as [`NetworkSpec::params`] lists them.
    pub fn from_safetensors(bytes: &[u8], spec: &NetworkSpec) -> Result<Self, PolicyError> {
        spec.validate().map_err(PolicyError::Spec)?;
        let tensors = SafeTensors::deserialize(bytes)?;
        let mut values = spec.params().into_iter().map(|info| {
            let view = tensors.tensor(&info.name).map_err(|_| PolicyError::Missing(info.name.clone()))?;
            if view.dtype() != Dtype::F32 || view.shape() != info.shape.as_slice() {
                return Err(PolicyError::Mismatch {
                    name: info.name,
                    dtype: format!("{:?}", view.dtype()),
                    shape: view.shape().to_vec(),
                    expected: info.shape,
                });
            }
            let data: Vec<f32> =
                view.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
            if data.iter().any(|v| !v.is_finite()) {
                return Err(PolicyError::NonFinite(info.name));
            }
            Ok(data)
        });
        let mut next = || values.next().unwrap_or_else(|| Err(PolicyError::Spec("too few parameters".into())));
        let mut layers = Vec::new();
        let mut inputs = spec.obs_dim;
        for &width in &spec.hidden {
            let (weight, bias) = (next()?, next()?);
            let norm = if spec.layer_norm { Some((next()?, next()?)) } else { None };
            layers.push(Dense { inputs, outputs: width, weight, bias, norm, relu: true });
            inputs = width;
        }
        let (weight, bias) = (next()?, next()?);
        layers.push(Dense { inputs, outputs: spec.num_actions, weight, bias, norm: None, relu: false });
        Ok(Self { spec: spec.clone(), layers })
    }

    pub fn spec(&self) -> &NetworkSpec {
        &self.spec
    }

    /// Q-values for a batch of observations laid end to end; returns `batch × num_actions`
    /// values, sample-major.
    pub fn q_values(&self, observations: &[f32]) -> Result<Vec<f32>, PolicyError> {
        let obs_dim = self.spec.obs_dim;
        if observations.len() % obs_dim != 0 {
            return Err(PolicyError::InputSize { len: observations.len(), obs_dim });
        }
        let batch = observations.len() / obs_dim;
        let mut current = observations.to_vec();
        let mut next = Vec::new();
        for layer in &self.layers {
            layer.forward(&current, batch, &mut next);
            std::mem::swap(&mut current, &mut next);
        }
        Ok(current)
    }

    /// The greedy action of each observation in the batch (ties go to the lowest index, as
    /// `argmax` does in PyTorch).
    pub fn greedy_actions(&self, observations: &[f32], actions: &mut Vec<u32>) -> Result<(), PolicyError> {
        let q = self.q_values(observations)?;
        actions.clear();
        actions.extend(q.chunks_exact(self.spec.num_actions).map(argmax));
        Ok(())
    }
}

impl Dense {
    fn forward(&self, input: &[f32], batch: usize, output: &mut Vec<f32>) {
        output.clear();
        output.resize(batch * self.outputs, 0.0);
        for (x, y) in input.chunks_exact(self.inputs).zip(output.chunks_exact_mut(self.outputs)) {
            for ((yo, row), b) in y.iter_mut().zip(self.weight.chunks_exact(self.inputs)).zip(&self.bias) {
                *yo = dot(row, x) + b;
            }
            if let Some((scale, shift)) = &self.norm {
                layer_norm(y, scale, shift);
            }
            if self.relu {
                for v in y.iter_mut() {
                    *v = v.max(0.0);
                }
            }
        }
    }
}

/// Dot product with eight independent partial sums, which the compiler turns into SIMD.
fn dot(a: &[f32], b: &[f32]) -> f32 {
    const LANES: usize = 8;
    let mut partial = [0.0f32; LANES];
    let (a_chunks, b_chunks) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f32 = a_chunks.remainder().iter().zip(b_chunks.remainder()).map(|(x, y)| x * y).sum();
    for (ca, cb) in a_chunks.zip(b_chunks) {
        for lane in 0..LANES {
            partial[lane] += ca[lane] * cb[lane];
        }
    }
    partial.iter().sum::<f32>() + tail
}

fn layer_norm(values: &mut [f32], scale: &[f32], shift: &[f32]) {
    let n = values.len() as f64;
    let mean = values.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    let var = values.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n;
    let inv_std = 1.0 / (var + f64::from(LAYER_NORM_EPS)).sqrt();
    for ((v, g), b) in values.iter_mut().zip(scale).zip(shift) {
        *v = ((f64::from(*v) - mean) * inv_std) as f32 * g + b;
    }
}

fn argmax(values: &[f32]) -> u32 {
    let mut best = 0;
    for (i, v) in values.iter().enumerate() {
        if *v > values[best] {
            best = i;
        }
    }
    best as u32
}
