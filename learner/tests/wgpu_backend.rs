//! The learner on Burn's wgpu backend (the learner's tests build it with
//! the `wgpu` feature; CI runs them on Mesa's software Vulkan driver,
//! lavapipe): the checks of every GPU backend ([`gpu`]), and a machine
//! without a Vulkan driver.
#![cfg(feature = "wgpu")]

mod agreement;
mod gpu;

use gpu::Gpu;
use tweezer_learner::config::DeviceChoice;

/// `.ci/run` sets `TWEEZER_REQUIRE_WGPU=1`.
const WGPU: Gpu = Gpu {
    choice: DeviceChoice::Wgpu,
    require: "TWEEZER_REQUIRE_WGPU",
};

gpu::gpu_checks!(WGPU);

/// Where the Vulkan loader finds no driver, `learner bench` on wgpu fails
/// with an error naming the config field, instead of panicking or falling
/// back to OpenGL (whatever this machine has).
#[test]
fn no_vulkan_driver_is_a_config_error() {
    // The Vulkan loader reads its drivers from the files these name only:
    // here, a file that does not exist.
    let dir = tempfile::tempdir().unwrap();
    let none = dir.path().join("none.json");
    let none = none.to_str().unwrap();
    gpu::a_device_that_does_not_open_is_a_config_error(
        &WGPU,
        &[("VK_ICD_FILENAMES", none), ("VK_DRIVER_FILES", none)],
        "no adapter",
    );
}
