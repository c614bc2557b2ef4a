//! The convolutional trunk both networks share in shape (not in weights).

use crate::cpu_kernels::{self, batch_norm_relu_inference, batch_norm_relu_training};
use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, Linear, LinearConfig, PaddingConfig2d};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

/// Three convolutions with BatchNorm and ReLU, then a 512-wide linear layer.
#[derive(Module, Debug)]
pub struct Encoder {
    conv1: Conv2d,
    norm1: BatchNorm,
    conv2: Conv2d,
    norm2: BatchNorm,
    conv3: Conv2d,
    norm3: BatchNorm,
    fc: Linear,
}

/// The encoder's shape.
#[derive(Config, Debug)]
pub struct EncoderConfig {
    /// Input image height in pixels.
    pub height: usize,
    /// Input image width in pixels.
    pub width: usize,
    /// Width of the linear layer after the convolutions.
    #[config(default = 512)]
    pub features: usize,
}

/// The convolutions as (input channels, output channels, kernel, stride,
/// padding), in order.
const CONVOLUTIONS: [(usize, usize, usize, usize, usize); 3] =
    [(1, 32, 8, 4, 2), (32, 64, 4, 2, 1), (64, 64, 3, 1, 1)];

/// Feature-map side after the convolutions of an input `side` pixels long,
/// or `None` where a kernel is longer than its padded input.
fn conv_side(side: usize) -> Option<usize> {
    CONVOLUTIONS
        .iter()
        .try_fold(side, |size, &(_, _, kernel, stride, padding)| {
            (size + 2 * padding)
                .checked_sub(kernel)
                .map(|room| room / stride + 1)
        })
}

/// The shortest image side the convolutions take (8 pixels: the second
/// kernel needs two columns of the first's output).
pub fn min_image_side() -> usize {
    (1..)
        .find(|&side| conv_side(side).is_some())
        .expect("a side fits")
}

impl EncoderConfig {
    /// Feature-map size after the three convolutions: (channels, height,
    /// width); a side shorter than the convolutions take (8 pixels, see
    /// `min_image_side`) counts as 0.
    pub fn conv_output(&self) -> [usize; 3] {
        let side = |s| conv_side(s).unwrap_or(0);
        [CONVOLUTIONS[2].1, side(self.height), side(self.width)]
    }

    /// Length of the flattened feature map: 81,920 at 256 x 320.
    pub fn flatten_size(&self) -> usize {
        self.conv_output().iter().product()
    }

    /// An encoder with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> Encoder {
        let conv = |layer: usize| {
            let (inputs, outputs, kernel, stride, pad) = CONVOLUTIONS[layer];
            Conv2dConfig::new([inputs, outputs], [kernel, kernel])
                .with_stride([stride, stride])
                .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
                .init(device)
        };
        let norm = |layer: usize| BatchNormConfig::new(CONVOLUTIONS[layer].1).init(device);
        Encoder {
            conv1: conv(0),
            norm1: norm(0),
            conv2: conv(1),
            norm2: norm(1),
            conv3: conv(2),
            norm3: norm(2),
            fc: LinearConfig::new(self.flatten_size(), self.features).init(device),
        }
    }
}

impl Encoder {
    /// Encodes binary images.
    ///
    /// # Shapes
    /// - `image`: `[batch, 1, height, width]`
    /// - output: `[batch, features]`
    pub fn forward(&self, image: Tensor<4>) -> Tensor<2> {
        let x = norm_relu(&self.norm1, conv(&self.conv1, image)); // [batch, 32, h/4, w/4]
        let x = norm_relu(&self.norm2, conv(&self.conv2, x)); // [batch, 64, h/8, w/8]
        let x = norm_relu(&self.norm3, conv(&self.conv3, x)); // [batch, 64, h/8, w/8]
        relu(linear(&self.fc, x.flatten::<2>(1, 3))) // [batch, features]
    }
}

/// `layer` applied to `x`: on the CPU with its weight gradient computed
/// in one pass ([`cpu_kernels::linear`]), elsewhere by Burn.
fn linear(layer: &Linear, x: Tensor<2>) -> Tensor<2> {
    match &layer.bias {
        Some(bias) if cpu_kernels::is_cpu_backend(&x.device()) => {
            cpu_kernels::linear(x, layer.weight.val(), bias.val())
        }
        _ => layer.forward(x),
    }
}

/// `layer` applied to `x`: on the CPU as one matrix product over the batch
/// ([`cpu_kernels::conv2d`]), elsewhere by Burn.
fn conv(layer: &Conv2d, x: Tensor<4>) -> Tensor<4> {
    match (&layer.bias, &layer.padding) {
        (Some(bias), PaddingConfig2d::Explicit(p, _, _, _))
            if cpu_kernels::is_cpu_backend(&x.device()) =>
        {
            cpu_kernels::conv2d(x, layer.weight.val(), bias.val(), layer.stride[0], *p)
        }
        _ => layer.forward(x),
    }
}

/// ReLU of `layer` applied to `x`: on the CPU in a few passes over `x`
/// ([`batch_norm_relu_training`], [`batch_norm_relu_inference`]),
/// elsewhere by Burn.
fn norm_relu(layer: &BatchNorm, x: Tensor<4>) -> Tensor<4> {
    let device = x.device();
    match (cpu_kernels::is_cpu_backend(&device), device.is_autodiff()) {
        (true, false) => batch_norm_relu_inference(layer, x),
        (true, true) if layer.training.is_enabled() => batch_norm_relu_training(layer, x),
        _ => relu(layer.forward(x)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_sizes_follow_from_the_layers() {
        let paper = EncoderConfig::new(256, 320);
        assert_eq!(paper.conv_output(), [64, 32, 40]);
        assert_eq!(paper.flatten_size(), 81_920);
        assert_eq!(EncoderConfig::new(64, 80).conv_output(), [64, 8, 10]);
        assert_eq!(EncoderConfig::new(128, 160).flatten_size(), 64 * 16 * 20);
        assert_eq!(EncoderConfig::new(8, 10).conv_output(), [64, 1, 1]);
        assert_eq!(min_image_side(), 8);
        // 7 pixels: the first map is one column, the second kernel's 4
        // overhang its 3 padded ones.
        assert_eq!(EncoderConfig::new(7, 10).conv_output(), [64, 0, 1]);
    }
}
