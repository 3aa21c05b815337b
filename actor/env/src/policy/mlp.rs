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
    #[error("{found} parameter values given; the network spec needs {expected}")]
    ParameterCount { found: usize, expected: usize },
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
        for y in output.chunks_exact_mut(self.outputs) {
            y.copy_from_slice(&self.bias);
        }
        if batch == 1 {
            // One row: nothing to block for, the weights are streamed once either way, and
            // after a ReLU about half the inputs are zero, whose rows this skips.
            add_row_combination(input, &self.weight_t, output);
        } else {
            self.add_product(input, batch, output);
        }
        let norm = self.norm.as_ref().map(|(scale, shift)| (scale.as_slice(), shift.as_slice()));
        normalize_and_activate(output, self.outputs, norm, self.relu);
    }

    /// `Y += X·Wᵀ` for `batch` observations.
    fn add_product(&self, x: &[f32], batch: usize, y: &mut [f32]) {
        add_matmul(x, batch, self.inputs, self.outputs, &self.weight_t, WeightLayout::InputsByOutputs, y);
    }
}

/// How a Linear layer's weights lie in memory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightLayout {
    /// Wᵀ, `inputs × outputs`, row-major: the actors' own copy and the learner's buffers. The
    /// kernels read it as it lies; the other layout they must repack at every call, which at
    /// batch 32 made a 512→256 product 2.7× slower.
    InputsByOutputs,
    /// PyTorch's `weight`, `outputs × inputs`, row-major: safetensors files and the wire.
    OutputsByInputs,
}

/// `Y += X·Wᵀ` with X `batch × inputs` and Y `batch × outputs` (row-major): the `gemm` crate's
/// register-blocked kernels, dispatched at run time to the CPU's SIMD (SSE, AVX2+FMA,
/// AVX-512). Either weight layout is read in place, through its strides.
fn add_matmul(x: &[f32], batch: usize, inputs: usize, outputs: usize, w: &[f32], layout: WeightLayout, y: &mut [f32]) {
    assert!(
        x.len() == batch * inputs && y.len() == batch * outputs && w.len() == inputs * outputs,
        "matrix shapes are checked when the layers are built"
    );
    // Wᵀ's element (i, o) is at i·row_stride + o·column_stride.
    let (w_row_stride, w_column_stride) = match layout {
        WeightLayout::InputsByOutputs => (outputs as isize, 1),
        WeightLayout::OutputsByInputs => (1, inputs as isize),
    };
    // SAFETY: the three pointers come from slices whose lengths were just checked to hold
    // exactly the matrices the sizes and strides describe (X batch × inputs and Y batch ×
    // outputs row-major, Wᵀ inputs × outputs in either layout, every index in bounds); `y` is
    // borrowed mutably, so nothing else aliases it while gemm writes, and gemm runs on this
    // thread only (Parallelism::None) and returns before the borrows end.
    #[allow(unsafe_code)]
    unsafe {
        gemm::gemm(
            batch,
            outputs,
            inputs,
            y.as_mut_ptr(),
            1,
            outputs as isize,
            true,
            x.as_ptr(),
            1,
            inputs as isize,
            w.as_ptr(),
            w_column_stride,
            w_row_stride,
            1.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// Q-values, `batch × num_actions`, of the network `spec` whose parameters lie end to end in
/// `params` in `nn.Sequential` order ([`NetworkSpec::params`]), each weight matrix in
/// `layout`, for the observations laid end to end in `observations`. The learner's no-grad
/// forward passes (the TD target's) run here, over its parameter buffer in place, with the
/// actors' kernels.
pub fn q_values_of_params(
    spec: &NetworkSpec,
    params: &[f32],
    layout: WeightLayout,
    observations: &[f32],
) -> Result<Vec<f32>, PolicyError> {
    let obs_dim = spec.obs_dim;
    if !observations.len().is_multiple_of(obs_dim) {
        return Err(PolicyError::InputSize { len: observations.len(), obs_dim });
    }
    let expected = spec.num_params();
    if params.len() != expected {
        return Err(PolicyError::ParameterCount { found: params.len(), expected });
    }
    let batch = observations.len() / obs_dim;
    let mut rest = params;
    let mut take = |n: usize| {
        let (head, tail) = rest.split_at(n);
        rest = tail;
        head
    };
    let mut current = observations.to_vec();
    let mut next = Vec::new();
    let mut inputs = obs_dim;
    let widths = spec.hidden.iter().map(|&w| (w, true)).chain(std::iter::once((spec.num_actions, false)));
    for (outputs, hidden) in widths {
        let (weight, bias) = (take(outputs * inputs), take(outputs));
        let norm = (hidden && spec.layer_norm).then(|| (take(outputs), take(outputs)));
        next.clear();
        next.resize(batch * outputs, 0.0);
        for y in next.chunks_exact_mut(outputs) {
            y.copy_from_slice(bias);
        }
        add_matmul(&current, batch, inputs, outputs, weight, layout, &mut next);
        normalize_and_activate(&mut next, outputs, norm, hidden);
        std::mem::swap(&mut current, &mut next);
        inputs = outputs;
    }
    Ok(current)
}

/// `y += Σᵢ x[i]·Wᵀ[i]` (the rows of `weight_t`, each `y.len()` long), skipping zero inputs:
/// axpys, compiled for each SIMD level and picked at run time.
#[multiversion::multiversion(targets = "simd")]
fn add_row_combination(x: &[f32], weight_t: &[f32], y: &mut [f32]) {
    for (&a, w) in x.iter().zip(weight_t.chunks_exact(y.len())) {
        if a != 0.0 {
            for (o, &wo) in y.iter_mut().zip(w) {
                *o += a * wo;
            }
        }
    }
}

/// LayerNorm (where the layer has one) and ReLU (where it has one) on each `width`-value row,
/// compiled for each SIMD level and picked at run time.
#[multiversion::multiversion(targets = "simd")]
fn normalize_and_activate(output: &mut [f32], width: usize, norm: Option<(&[f32], &[f32])>, relu: bool) {
    for y in output.chunks_exact_mut(width) {
        if let Some((scale, shift)) = norm {
            layer_norm(y, scale, shift);
        }
        if relu {
            for v in y.iter_mut() {
                *v = v.max(0.0);
            }
        }
    }
}

/// A row-major `rows × cols` matrix transposed (`cols × rows`, row-major): from one
/// [`WeightLayout`] to the other.
pub fn transpose(matrix: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    let mut out = vec![0.0; matrix.len()];
    for r in 0..rows {
        for c in 0..cols {
            out[c * rows + r] = matrix[r * cols + c];
        }
    }
    out
}

/// PyTorch's LayerNorm (biased variance) over one sample's values, in f32 as PyTorch computes
/// it. The sums run over [`LANES`] interleaved partial sums, a fixed order the compiler can keep
/// in SIMD registers (one running sum would forbid that), and two passes (mean, then the
/// centred squares) keep the variance accurate.
#[inline(always)]
fn layer_norm(values: &mut [f32], scale: &[f32], shift: &[f32]) {
    let n = values.len() as f32;
    let mean = lane_sum(values, |v| v) / n;
    let var = lane_sum(values, |v| (v - mean) * (v - mean)) / n;
    let inv_std = 1.0 / (var + LAYER_NORM_EPS).sqrt();
    for ((v, g), b) in values.iter_mut().zip(scale).zip(shift) {
        *v = (*v - mean) * inv_std * g + b;
    }
}

/// Partial sums kept side by side in [`lane_sum`].
const LANES: usize = 16;

#[inline(always)]
fn lane_sum(values: &[f32], f: impl Fn(f32) -> f32) -> f32 {
    let mut lanes = [0.0f32; LANES];
    let mut chunks = values.chunks_exact(LANES);
    for chunk in &mut chunks {
        for (lane, &v) in lanes.iter_mut().zip(chunk) {
            *lane += f(v);
        }
    }
    let tail: f32 = chunks.remainder().iter().map(|&v| f(v)).sum();
    lanes.iter().sum::<f32>() + tail
}

/// The index of the largest value (ties go to the lowest index, as PyTorch's `argmax`).
pub fn argmax(values: &[f32]) -> u32 {
    let mut best = 0;
    for (i, v) in values.iter().enumerate() {
        if *v > values[best] {
            best = i;
        }
    }
    best as u32
}
