//! The shape of the Q-network, shared by the learner (tch) and actors (plain Rust).

use serde::{Deserialize, Serialize};

/// An MLP `obs_dim → hidden[0] → … → num_actions`, with LayerNorm (optional) and ReLU after
/// each hidden layer.
///
/// Parameter names follow a PyTorch `nn.Sequential` of the same layers, so its `state_dict`
/// loads them as they are: hidden layer i is `Linear` at index s·i, `LayerNorm` at s·i + 1 and
/// `ReLU` after it, with stride s = 3 (2 without LayerNorm); the output `Linear` comes last.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkSpec {
    pub obs_dim: usize,
    pub hidden: Vec<usize>,
    pub num_actions: usize,
    #[serde(default = "yes")]
    pub layer_norm: bool,
}

fn yes() -> bool {
    true
}

impl From<&NetworkSpec> for crawler_proto::NetworkSpec {
    fn from(spec: &NetworkSpec) -> Self {
        let narrow = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        crawler_proto::NetworkSpec {
            obs_dim: narrow(spec.obs_dim),
            hidden: spec.hidden.iter().map(|&h| narrow(h)).collect(),
            num_actions: narrow(spec.num_actions),
            layer_norm: spec.layer_norm,
        }
    }
}

impl From<&crawler_proto::NetworkSpec> for NetworkSpec {
    fn from(wire: &crawler_proto::NetworkSpec) -> Self {
        NetworkSpec {
            obs_dim: wire.obs_dim as usize,
            hidden: wire.hidden.iter().map(|&h| h as usize).collect(),
            num_actions: wire.num_actions as usize,
            layer_norm: wire.layer_norm,
        }
    }
}

/// One parameter tensor of the network: its `nn.Sequential` name and shape.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParamInfo {
    pub name: String,
    pub shape: Vec<usize>,
}

impl ParamInfo {
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
}

impl NetworkSpec {
    /// The study's network: 40 → 512 → 256 → 128 → 25.
    pub fn study() -> Self {
        Self { obs_dim: 40, hidden: vec![512, 256, 128], num_actions: 25, layer_norm: true }
    }

    /// Modules per hidden layer in the `nn.Sequential` (Linear, LayerNorm where present,
    /// ReLU): hidden layer `i`'s Linear is module `stride · i`.
    pub fn stride(&self) -> usize {
        if self.layer_norm { 3 } else { 2 }
    }

    /// Every parameter, in `nn.Sequential` order.
    pub fn params(&self) -> Vec<ParamInfo> {
        let mut params = Vec::new();
        let mut inputs = self.obs_dim;
        let linear = |params: &mut Vec<ParamInfo>, index: usize, inputs: usize, outputs: usize| {
            params.push(ParamInfo { name: format!("{index}.weight"), shape: vec![outputs, inputs] });
            params.push(ParamInfo { name: format!("{index}.bias"), shape: vec![outputs] });
        };
        for (i, &width) in self.hidden.iter().enumerate() {
            let index = self.stride() * i;
            linear(&mut params, index, inputs, width);
            if self.layer_norm {
                params.push(ParamInfo { name: format!("{}.weight", index + 1), shape: vec![width] });
                params.push(ParamInfo { name: format!("{}.bias", index + 1), shape: vec![width] });
            }
            inputs = width;
        }
        linear(&mut params, self.stride() * self.hidden.len(), inputs, self.num_actions);
        params
    }

    /// Total number of scalar parameters.
    pub fn num_params(&self) -> usize {
        self.params().iter().map(ParamInfo::numel).sum()
    }

    /// Checks that every size is usable.
    pub fn validate(&self) -> Result<(), SpecError> {
        if self.obs_dim == 0 || self.num_actions == 0 {
            return Err(SpecError::Empty { obs_dim: self.obs_dim, num_actions: self.num_actions });
        }
        if self.hidden.iter().any(|&w| w == 0 || w > MAX_HIDDEN_WIDTH) {
            return Err(SpecError::HiddenWidth(self.hidden.clone()));
        }
        // The same limits as the wire's: weights must fit in one message, so no declared shape
        // (a config, a checkpoint's meta.json) makes anyone allocate more.
        let wire = crawler_proto::NetworkSpec::from(self);
        crawler_proto::validate::network_spec(&wire).map_err(SpecError::Wire)
    }
}

/// Widest hidden layer a spec may declare.
const MAX_HIDDEN_WIDTH: usize = 65_536;

/// A network shape no one should build.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpecError {
    #[error("obs_dim ({obs_dim}) and num_actions ({num_actions}) must be positive")]
    Empty { obs_dim: usize, num_actions: usize },
    #[error("hidden widths {0:?} must each be in 1..={MAX_HIDDEN_WIDTH}")]
    HiddenWidth(Vec<usize>),
    #[error("the network does not fit the wire protocol's limits: {0}")]
    Wire(#[source] crawler_proto::ProtoError),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn study_network_names_match_nn_sequential() {
        let names: Vec<String> = NetworkSpec::study().params().into_iter().map(|p| p.name).collect();
        let expected = [
            "0.weight", "0.bias", "1.weight", "1.bias", "3.weight", "3.bias", "4.weight", "4.bias", "6.weight",
            "6.bias", "7.weight", "7.bias", "9.weight", "9.bias",
        ];
        assert_eq!(names, expected);
        assert_eq!(
            NetworkSpec::study().num_params(),
            40 * 512 + 512 * 3 + 512 * 256 + 256 * 3 + 256 * 128 + 128 * 3 + 128 * 25 + 25
        );
    }
}
