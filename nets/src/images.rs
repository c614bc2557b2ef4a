//! Observations → the image tensor a network takes, rendered by the shared
//! renderer straight into the buffer that becomes the tensor.

use burn::tensor::{Device, Tensor, TensorData};
use tweezer_gym::Renderer;

/// Renders each observation's sphere centres into one
/// `[batch, 1, height, width]` binary image tensor on `device`.
pub fn render_images<'a>(
    renderer: &Renderer,
    centres: impl ExactSizeIterator<Item = &'a [[f32; 2]]>,
    device: &Device,
) -> Tensor<4> {
    let n = centres.len();
    let p = renderer.pixels();
    let mut pixels = vec![0f32; n * p];
    for (slot, c) in pixels.chunks_exact_mut(p).zip(centres) {
        renderer
            .render(c, slot)
            .expect("each slot is one image of the renderer's size");
    }
    let shape = [n, 1, renderer.height(), renderer.width()];
    Tensor::from_data(TensorData::new(pixels, shape), device)
}
