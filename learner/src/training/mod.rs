//! Learning from the replay: TD3 on minibatches, the loop that paces it
//! with the rate limiter and publishes and checkpoints, and the guard that
//! rolls back a diverged update. Its CPU kernels, Adam included, are
//! `tweezer_nets::cpu_kernels`.

pub mod divergence;
#[cfg(any(feature = "cuda", feature = "wgpu"))]
pub mod gpu_devices;
pub mod minibatch;
pub mod mirror;
pub mod module_updates;
pub mod passes;
pub mod td3;
pub mod trainer;
