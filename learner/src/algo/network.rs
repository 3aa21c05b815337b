//! The Q-network on libtorch, with every parameter in one contiguous buffer.
//!
//! Why one buffer: the optimiser, target copies and Polyak averaging then each become a
//! handful of tensor ops over the whole network instead of one set per parameter tensor.
//!
//! Autograd sees one leaf tensor per parameter, each sharing its storage with a slice of the
//! buffer, so in-place updates of the buffer are the parameters' updates. (Differentiating
//! views of the buffer instead would make every view's backward materialise a full-size
//! gradient: 3x slower for the study's network.)
//!
//! Architecture invariant: each weight matrix lies in the buffer transposed, `inputs ×
//! outputs` ([`WeightLayout::InputsByOutputs`], the actors' layout), and the forward pass is
//! `b + x·Wᵀ` (`addmm`). The TD target's no-grad passes read the buffer in place with the
//! `gemm` kernels, which take this layout as it lies but must repack PyTorch's `outputs ×
//! inputs` at every call (2.7× slower for a 512→256 layer at batch 32). Everything that leaves
//! or enters the learner (weights on the wire, checkpoints, Adam's moments in them) is in
//! PyTorch's layout: [`QNetwork::to_torch_order`] and [`QNetwork::from_torch_order`] are the
//! only crossings.

use crawler_env::policy::{NetworkSpec, ParamInfo, WeightLayout, transpose};
use tch::{Kind, Tensor};

/// A gradient, one tensor per parameter in slot order: laid end to end they match the flat
/// buffer. Kept in parts because joining them would copy the whole network once more.
#[derive(Debug)]
pub struct Gradient {
    parts: Vec<Tensor>,
}

impl Gradient {
    /// The parts as contiguous f32 tensors (autograd's usually are; others are copied).
    pub fn from_parts(parts: Vec<Tensor>) -> Self {
        let parts = parts.iter().map(super::tensor_memory::plain_f32).collect();
        Self { parts }
    }

    /// Values in all the parts.
    pub fn numel(&self) -> usize {
        self.parts.iter().map(Tensor::numel).sum()
    }

    /// Each part's values, in slot order.
    pub fn for_each_part(&self, mut f: impl FnMut(&[f32])) {
        for part in &self.parts {
            // SAFETY: the parts are this gradient's own tensors: autograd's results, which
            // nothing else holds, or copies made in `from_parts`; nothing writes them while
            // `f` reads, since `f` cannot reach them through `&self`'s shared borrow.
            #[allow(unsafe_code)]
            f(unsafe { super::tensor_memory::f32s(part) });
        }
    }

    /// The L2 norm over all parts (∞ if it overflows f32, as libtorch's norm would).
    pub fn l2_norm(&self) -> f64 {
        let mut sum = 0.0f64;
        self.for_each_part(|values| sum += f64::from(sum_of_squares(values)));
        sum.sqrt()
    }
}

/// Σ v², over 16 interleaved partial sums: a fixed order the compiler keeps in SIMD registers,
/// compiled for each SIMD level and picked at run time.
#[multiversion::multiversion(targets = "simd")]
fn sum_of_squares(values: &[f32]) -> f32 {
    const LANES: usize = 16;
    let mut lanes = [0.0f32; LANES];
    let mut chunks = values.chunks_exact(LANES);
    for chunk in &mut chunks {
        for (lane, &v) in lanes.iter_mut().zip(chunk) {
            *lane += v * v;
        }
    }
    lanes.iter().sum::<f32>() + chunks.remainder().iter().map(|v| v * v).sum::<f32>()
}

/// Parameters that do not fit the network they are meant for.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{found} parameter values ({kind}) given; the network needs {expected} f32")]
pub struct ParameterCountError {
    pub found: usize,
    pub kind: String,
    pub expected: usize,
}

/// Parameter `info` lives at `offset..offset + info.numel()` of the flat buffer; a weight
/// matrix (`info.shape` is PyTorch's `[outputs, inputs]`) lies there transposed.
#[derive(Debug, Clone)]
pub struct ParamSlot {
    pub info: ParamInfo,
    pub offset: usize,
}

impl ParamSlot {
    /// `[outputs, inputs]` for a weight matrix, None for a vector.
    fn matrix(&self) -> Option<[usize; 2]> {
        match self.info.shape.as_slice() {
            &[outputs, inputs] => Some([outputs, inputs]),
            _ => None,
        }
    }

    /// The shape of the slot's tensor in the buffer: a weight matrix transposed.
    fn stored_shape(&self) -> Vec<i64> {
        match self.matrix() {
            Some([outputs, inputs]) => vec![inputs as i64, outputs as i64],
            None => self.info.shape.iter().map(|&d| d as i64).collect(),
        }
    }
}

/// The layout of a learner's flat buffers (parameters, gradients, Adam's moments).
pub const BUFFER_LAYOUT: WeightLayout = WeightLayout::InputsByOutputs;

/// An MLP Q-network whose parameters are views into one flat f32 tensor.
#[derive(Debug)]
pub struct QNetwork {
    spec: NetworkSpec,
    slots: Vec<ParamSlot>,
    /// All parameters, concatenated in `nn.Sequential` order. Never requires grad itself.
    flat: Tensor,
    /// One tensor per parameter, each sharing storage with its slice of `flat`.
    params: Vec<Tensor>,
}

/// PyTorch's default LayerNorm epsilon.
const LAYER_NORM_EPS: f64 = 1e-5;

impl QNetwork {
    /// A network initialised as PyTorch initialises `nn.Linear` (uniform in ±1/√fan_in for
    /// weight and bias) and `nn.LayerNorm` (scale 1, shift 0), from torch's global RNG.
    pub fn new(spec: &NetworkSpec, requires_grad: bool) -> Self {
        let slots = slots_of(spec);
        let total = slots.iter().map(|s| s.info.numel()).sum::<usize>() as i64;
        // Drawn in PyTorch's order and layout, so a seed gives PyTorch's initial weights.
        let torch_order = Tensor::zeros([total], (Kind::Float, tch::Device::Cpu));
        tch::no_grad(|| {
            let mut fan_in = spec.obs_dim;
            for slot in &slots {
                let mut view = torch_order.narrow(0, slot.offset as i64, slot.info.numel() as i64);
                let is_norm = spec.layer_norm && slot.info.shape.len() == 1 && is_layer_norm(spec, &slot.info.name);
                if is_norm {
                    if slot.info.name.ends_with("weight") {
                        let _ = view.fill_(1.0);
                    }
                } else {
                    if slot.info.shape.len() == 2 {
                        fan_in = slot.info.shape[1];
                    }
                    let bound = 1.0 / (fan_in as f64).sqrt();
                    let _ = view.uniform_(-bound, bound);
                }
            }
        });
        // A contiguous f32 CPU tensor always converts.
        let torch_values = Vec::<f32>::try_from(&torch_order).unwrap_or_default();
        let flat = Tensor::from_slice(&reorder(&slots, &torch_values, Direction::FromTorch));
        let params = param_views(&flat, &slots, requires_grad);
        Self { spec: spec.clone(), slots, flat, params }
    }

    /// Values of a flat buffer laid out like this network's (parameters, a gradient, Adam's
    /// moments), in PyTorch's order and layout: each weight `outputs × inputs`.
    pub fn to_torch_order(&self, values: &[f32]) -> Vec<f32> {
        reorder(&self.slots, values, Direction::ToTorch)
    }

    /// The inverse of [`Self::to_torch_order`].
    pub fn from_torch_order(&self, values: &[f32]) -> Vec<f32> {
        reorder(&self.slots, values, Direction::FromTorch)
    }

    pub fn spec(&self) -> &NetworkSpec {
        &self.spec
    }

    pub fn slots(&self) -> &[ParamSlot] {
        &self.slots
    }

    /// The flat parameter buffer, in [`BUFFER_LAYOUT`].
    pub fn flat(&self) -> &Tensor {
        &self.flat
    }

    pub fn flat_mut(&mut self) -> &mut Tensor {
        &mut self.flat
    }

    /// Whether every parameter is finite: weights are published and saved only then.
    pub fn all_finite(&self) -> bool {
        tch::no_grad(|| self.flat.isfinite().all().int64_value(&[]) != 0)
    }

    /// The per-parameter tensors autograd differentiates, in `nn.Sequential` order; weight
    /// matrices transposed (`inputs × outputs`).
    pub fn params(&self) -> &[Tensor] {
        &self.params
    }

    /// The gradient of `loss` with respect to every parameter.
    pub fn gradient(&self, loss: &Tensor) -> Gradient {
        let parts = Tensor::run_backward(&[loss], &self.params, false, false);
        Gradient::from_parts(parts)
    }

    fn param(&self, index: usize) -> Tensor {
        self.params[index].shallow_clone()
    }

    /// Q-values, `batch × num_actions`, for observations `batch × obs_dim`.
    pub fn forward(&self, observations: &Tensor) -> Tensor {
        let mut x = observations.shallow_clone();
        let mut index = 0;
        for &width in &self.spec.hidden {
            let (weight, bias) = (self.param(index), self.param(index + 1));
            index += 2;
            x = bias.addmm(&x, &weight);
            if self.spec.layer_norm {
                let (scale, shift) = (self.param(index), self.param(index + 1));
                index += 2;
                x = x.layer_norm([width as i64], Some(&scale), Some(&shift), LAYER_NORM_EPS, false);
            }
            x = x.relu();
        }
        self.param(index + 1).addmm(&x, &self.param(index))
    }

    /// Copies another network's parameters into this one (a hard target update).
    pub fn copy_from(&mut self, other: &QNetwork) {
        tch::no_grad(|| self.flat.copy_(&other.flat));
    }

    /// θ ← (1 − τ)·θ + τ·θ_other (a Polyak target update).
    pub fn polyak_from(&mut self, other: &QNetwork, tau: f64) {
        tch::no_grad(|| {
            let _ = self.flat.lerp_(&other.flat, tau);
        });
    }

    /// Every parameter's values, flat, in `nn.Sequential` order (the spec's) and PyTorch's
    /// layout: what the wire and checkpoints carry.
    pub fn flat_values(&self) -> Vec<f32> {
        // A contiguous f32 CPU tensor always converts.
        self.to_torch_order(&Vec::<f32>::try_from(&self.flat.detach()).unwrap_or_default())
    }

    /// Overwrites all parameters from a flat vector in slot order and PyTorch's layout.
    pub fn load_flat(&mut self, values: &[f32]) -> Result<(), ParameterCountError> {
        let expected = self.flat.numel();
        if values.len() != expected {
            return Err(ParameterCountError { found: values.len(), kind: "f32".into(), expected });
        }
        let values = self.from_torch_order(values);
        tch::no_grad(|| self.flat.copy_(&Tensor::from_slice(&values)));
        Ok(())
    }
}

/// Which way [`reorder`] converts.
#[derive(Debug, Clone, Copy)]
enum Direction {
    ToTorch,
    FromTorch,
}

/// `values` (one value per parameter, in slot order) with each weight matrix transposed
/// between PyTorch's layout and the buffer's; vectors are copied as they are.
fn reorder(slots: &[ParamSlot], values: &[f32], direction: Direction) -> Vec<f32> {
    let mut out = Vec::with_capacity(values.len());
    for slot in slots {
        let Some(part) = values.get(slot.offset..slot.offset + slot.info.numel()) else { break };
        match (slot.matrix(), direction) {
            (Some([outputs, inputs]), Direction::FromTorch) => out.extend(transpose(part, outputs, inputs)),
            (Some([outputs, inputs]), Direction::ToTorch) => out.extend(transpose(part, inputs, outputs)),
            (None, _) => out.extend_from_slice(part),
        }
    }
    out
}

/// Leaf tensors over `flat`'s storage, one per slot.
fn param_views(flat: &Tensor, slots: &[ParamSlot], requires_grad: bool) -> Vec<Tensor> {
    slots
        .iter()
        .map(|slot| {
            let shape = slot.stored_shape();
            let view = flat.narrow(0, slot.offset as i64, slot.info.numel() as i64).view(shape.as_slice());
            view.detach().set_requires_grad(requires_grad)
        })
        .collect()
}

fn is_layer_norm(spec: &NetworkSpec, name: &str) -> bool {
    let index: usize = name.split('.').next().and_then(|i| i.parse().ok()).unwrap_or(0);
    spec.layer_norm && index % 3 == 1 && index / 3 < spec.hidden.len()
}

fn slots_of(spec: &NetworkSpec) -> Vec<ParamSlot> {
    let mut offset = 0;
    spec.params()
        .into_iter()
        .map(|info| {
            let slot = ParamSlot { offset, info };
            offset += slot.info.numel();
            slot
        })
        .collect()
}
