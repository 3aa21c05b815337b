//! The Q-network's forward pass in plain Rust, over the learner's safetensors weights.

use safetensors::{Dtype, SafeTensors};

use super::spec::{NetworkSpec, SpecError};

/// Why weights could not be loaded or used.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error("weights are not a valid safetensors file: {0}")]
    Format(#[from] safetensors::SafeTensorError),
    #[error("network spec is invalid: {0}")]
    Spec(#[from] SpecError),
    #[error("the weights end before parameter {index} of the {expected} the network spec lists")]
    TooFewParameters { index: usize, expected: usize },
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
    /// Row-major `inputs × outputs`: PyTorch's Linear weight, transposed.
    weight_t: Vec<f32>,
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
        spec.validate()?;
        let tensors = SafeTensors::deserialize(bytes)?;
        let params = spec.params();
        let expected = params.len();
        let mut values = params.into_iter().map(|info| {
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
        let mut index = 0;
        let mut next = || {
            index += 1;
            values.next().unwrap_or(Err(PolicyError::TooFewParameters { index: index - 1, expected }))
        };
        let mut layers = Vec::new();
        let mut inputs = spec.obs_dim;
        for &width in &spec.hidden {
            let (weight, bias) = (next()?, next()?);
            let norm = if spec.layer_norm { Some((next()?, next()?)) } else { None };
            let weight_t = transpose(&weight, width, inputs);
            layers.push(Dense { inputs, outputs: width, weight_t, bias, norm, relu: true });
            inputs = width;
        }
        let (weight, bias) = (next()?, next()?);
        let weight_t = transpose(&weight, spec.num_actions, inputs);
        layers.push(Dense { inputs, outputs: spec.num_actions, weight_t, bias, norm: None, relu: false });
        Ok(Self { spec: spec.clone(), layers })
    }

    pub fn spec(&self) -> &NetworkSpec {
        &self.spec
    }

    /// Q-values for a batch of observations laid end to end; returns `batch × num_actions`
    /// values, sample-major.
    pub fn q_values(&self, observations: &[f32]) -> Result<Vec<f32>, PolicyError> {
        let obs_dim = self.spec.obs_dim;
        if !observations.len().is_multiple_of(obs_dim) {
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
        // y = b + Σᵢ xᵢ·Wᵀ[i]: each step adds a contiguous weight row to the outputs (an axpy,
        // which vectorises without reordering any sum), and four samples share each pass over
        // the weights, which are most of the memory traffic.
        let mut x_blocks = input.chunks_exact(4 * self.inputs);
        let mut y_blocks = output.chunks_exact_mut(4 * self.outputs);
        for (x, y) in (&mut x_blocks).zip(&mut y_blocks) {
            let (y01, y23) = y.split_at_mut(2 * self.outputs);
            let (y0, y1) = y01.split_at_mut(self.outputs);
            let (y2, y3) = y23.split_at_mut(self.outputs);
            for yk in [&mut *y0, &mut *y1, &mut *y2, &mut *y3] {
                yk.copy_from_slice(&self.bias);
            }
            for (i, w) in self.weight_t.chunks_exact(self.outputs).enumerate() {
                let a = [x[i], x[self.inputs + i], x[2 * self.inputs + i], x[3 * self.inputs + i]];
                let lanes = y0.iter_mut().zip(y1.iter_mut()).zip(y2.iter_mut().zip(y3.iter_mut())).zip(w);
                for (((o0, o1), (o2, o3)), &wo) in lanes {
                    *o0 += a[0] * wo;
                    *o1 += a[1] * wo;
                    *o2 += a[2] * wo;
                    *o3 += a[3] * wo;
                }
            }
        }
        let rest = x_blocks.remainder().chunks_exact(self.inputs);
        for (x, y) in rest.zip(y_blocks.into_remainder().chunks_exact_mut(self.outputs)) {
            y.copy_from_slice(&self.bias);
            for (&a, w) in x.iter().zip(self.weight_t.chunks_exact(self.outputs)) {
                // After a ReLU about half the inputs are zero: skip their rows.
                if a != 0.0 {
                    for (o, &wo) in y.iter_mut().zip(w) {
                        *o += a * wo;
                    }
                }
            }
        }
        for y in output.chunks_exact_mut(self.outputs) {
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

/// A row-major `rows × cols` matrix transposed.
fn transpose(matrix: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    let mut out = vec![0.0; matrix.len()];
    for r in 0..rows {
        for c in 0..cols {
            out[c * rows + r] = matrix[r * cols + c];
        }
    }
    out
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
