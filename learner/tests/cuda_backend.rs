//! The learner on Burn's CUDA backend: the checks of every GPU backend
//! ([`gpu`]), and a machine where CUDA opens no GPU. Built with the `cuda`
//! feature only, which needs LLVM 23.1 (`deploy/cuda/with-llvm.sh cargo
//! test --workspace --locked --features tweezer-learner/cuda --test
//! cuda_backend`); on a machine without NVIDIA's driver or GPU all but the
//! last skip, unless `TWEEZER_REQUIRE_CUDA=1`.
#![cfg(feature = "cuda")]

mod agreement;
mod gpu;

use gpu::Gpu;
use tweezer_learner::config::DeviceChoice;

const CUDA: Gpu = Gpu {
    choice: DeviceChoice::Cuda,
    require: "TWEEZER_REQUIRE_CUDA",
};

gpu::gpu_checks!(CUDA);

/// Where CUDA sees no GPU (none visible to the process here; on a machine
/// without NVIDIA's driver, no driver either), `learner bench` on cuda
/// fails with an error naming the config field, instead of Burn's panics
/// on its device thread and then in the caller.
#[test]
fn no_visible_gpu_is_a_config_error() {
    gpu::a_device_that_does_not_open_is_a_config_error(
        &CUDA,
        &[("CUDA_VISIBLE_DEVICES", "")],
        "cannot open the first CUDA GPU",
    );
}
