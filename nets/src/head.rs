//! The fully connected layers both networks put after the encoder.

use burn::config::Config;
use burn::module::Module;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

/// Two hidden layers with ReLU, then a linear output.
#[derive(Module, Debug)]
pub struct Head {
    fc1: Linear,
    fc2: Linear,
    out: Linear,
    /// LayerNorm before each hidden ReLU, when asked for.
    norms: Option<[LayerNorm; 2]>,
}

/// The head's shape.
#[derive(Config, Debug)]
pub struct HeadConfig {
    /// Width of the input: encoder features plus the appended vectors.
    pub inputs: usize,
    /// Width of the output.
    pub outputs: usize,
    /// Width of the two hidden layers.
    #[config(default = 64)]
    pub hidden: usize,
    /// Whether each hidden layer is normalised (LayerNorm) before its ReLU.
    #[config(default = false)]
    pub layer_norm: bool,
}

impl HeadConfig {
    /// A head with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> Head {
        Head {
            fc1: LinearConfig::new(self.inputs, self.hidden).init(device),
            fc2: LinearConfig::new(self.hidden, self.hidden).init(device),
            out: LinearConfig::new(self.hidden, self.outputs).init(device),
            norms: self
                .layer_norm
                .then(|| [0, 1].map(|_| LayerNormConfig::new(self.hidden).init(device))),
        }
    }
}

impl Head {
    /// # Shapes
    /// - `x`: `[batch, inputs]`
    /// - output: `[batch, outputs]`
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let norm = |k: usize, x: Tensor<2>| match &self.norms {
            Some(norms) => norms[k].forward(x),
            None => x,
        };
        let x = relu(norm(0, self.fc1.forward(x))); // [batch, hidden]
        let x = relu(norm(1, self.fc2.forward(x))); // [batch, hidden]
        self.out.forward(x) // [batch, outputs]
    }
}
