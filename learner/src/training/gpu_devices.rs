//! Opening the GPU devices of `learner.device` (features `cuda` and `wgpu`):
//! once per process, tried with one small tensor, and a clear error where
//! the machine cannot run them, instead of Burn's panics at the first
//! tensor.

use burn::tensor::{Device, Tensor};
use std::panic::{AssertUnwindSafe, PanicHookInfo};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use tweezer_config::ConfigError;

/// The first CUDA GPU, or an error saying why this machine cannot use it.
/// Burn opens CUDA on a device thread of its own, and where the driver
/// (`libcuda.so`) or a GPU is missing it panics there, then in the caller on
/// the closed channel; the error carries the first of those panics.
#[cfg(feature = "cuda")]
pub fn cuda() -> Result<Device, ConfigError> {
    static DEVICE: OnceLock<Result<Device, String>> = OnceLock::new();
    let opened = DEVICE.get_or_init(|| {
        one_stream();
        tried(Device::cuda(0))
    });
    opened.clone().map_err(|why| ConfigError::Invalid {
        field: "learner.device".into(),
        reason: format!(
            "`cuda` cannot open the first CUDA GPU ({why}); install NVIDIA's driver (it brings libcuda.so.1; no CUDA toolkit is needed) on a machine with an NVIDIA GPU, check that the GPU is visible (`nvidia-smi`, CUDA_VISIBLE_DEVICES), or choose `wgpu` or `flex`"
        ),
    })
}

/// The wgpu device on the first of [`WGPU_APIS`] with an adapter that
/// works, or an error naming what each API answered. Burn's own choice
/// would fall back to OpenGL, where Mesa's drivers lack the subgroup
/// operations of Burn's matrix kernels (a batch-1 inference then panicked),
/// and a machine without any driver panics at the first tensor instead.
#[cfg(feature = "wgpu")]
pub fn wgpu() -> Result<Device, ConfigError> {
    static DEVICE: OnceLock<Result<Device, String>> = OnceLock::new();
    let opened = DEVICE.get_or_init(|| {
        one_stream();
        let mut answers = Vec::new();
        for &api in WGPU_APIS {
            let opened = Device::wgpu_options().graphics_api(api).init();
            match opened.map_err(|e| e.to_string()).and_then(tried) {
                Ok(device) => return Ok(device),
                Err(why) => answers.push(format!("{api:?}: {why}")),
            }
        }
        Err(answers.join("; "))
    });
    opened.clone().map_err(|answers| ConfigError::Invalid {
        field: "learner.device".into(),
        reason: format!(
            "`wgpu` found no adapter it can use ({answers}); install the GPU's Vulkan driver and the Vulkan loader (NVIDIA's driver also needs libglvnd's libraries: Debian's libvulkan1, libglvnd0, libglx0 and libegl1), or Mesa's software driver (Debian's mesa-vulkan-drivers), or choose `flex`"
        ),
    })
}

/// The graphics APIs the wgpu device may come up on, best first.
#[cfg(feature = "wgpu")]
const WGPU_APIS: &[burn::tensor::wgpu::WgpuBackend] = {
    use burn::tensor::wgpu::WgpuBackend::{Dx12, Metal, Vulkan};
    if cfg!(target_os = "macos") {
        &[Metal]
    } else if cfg!(windows) {
        &[Vulkan, Dx12]
    } else {
        &[Vulkan]
    }
};

/// Puts the work of every thread on one stream of Burn's GPU runtimes,
/// before the first kernel. By default each thread gets its own, and a TD3
/// step on another thread than the one its tensors came from (the learner
/// builds its networks on one thread and trains on another) came out wrong
/// in fresh processes on wgpu: 4 of 4, against 0 of 4 on one stream.
fn one_stream() {
    use cubecl_environment::stream::{StreamPolicy, set_policy};
    set_policy(StreamPolicy::Single);
}

/// `device`, once a tensor made on it has come back to the host; or what
/// panicked on the way.
fn tried(device: Device) -> Result<Device, String> {
    first_panic_of(|| Tensor::<1>::zeros([1], &device).into_data())?;
    Ok(device)
}

/// What `f` returns, or the message of the first panic on any thread while
/// it ran (the caller's own panic is often only a consequence, a closed
/// channel). Those panics are not printed: the error reports them. Meant
/// for opening a device at start-up, while nothing else should panic.
fn first_panic_of<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    // The hook is the process's: one caller at a time.
    static HOOKED: Mutex<()> = Mutex::new(());
    let _hooked = HOOKED.lock().unwrap_or_else(PoisonError::into_inner);
    let first = Arc::new(Mutex::new(None::<String>));
    let seen = Arc::clone(&first);
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let mut seen = seen.lock().unwrap_or_else(PoisonError::into_inner);
        seen.get_or_insert_with(|| panic_message(info));
    }));
    let outcome = std::panic::catch_unwind(AssertUnwindSafe(f));
    std::panic::set_hook(previous);
    outcome.map_err(|_| {
        let mut first = first.lock().unwrap_or_else(PoisonError::into_inner);
        first.take().unwrap_or_else(|| NO_MESSAGE.into())
    })
}

/// What a panic whose payload is not text reports.
const NO_MESSAGE: &str = "a panic without a message";

/// A panic's message, with the thread it happened on.
fn panic_message(info: &PanicHookInfo) -> String {
    let payload = info.payload();
    let message = payload
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or(NO_MESSAGE);
    let thread = std::thread::current();
    format!(
        "thread `{}` panicked: {message}",
        thread.name().unwrap_or("unnamed")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_on_another_thread_is_reported_rather_than_the_callers() {
        let outcome = first_panic_of(|| {
            let runner = std::thread::Builder::new()
                .name("device runner".into())
                .spawn(|| -> u32 { panic!("no driver library") })
                .expect("a thread");
            // As Burn's caller does when its device thread has gone.
            runner.join().expect("the runner's answer")
        });
        assert_eq!(
            outcome,
            Err("thread `device runner` panicked: no driver library".into())
        );
    }

    #[test]
    fn a_value_passes_and_a_later_panic_is_caught_again() {
        assert_eq!(first_panic_of(|| 7), Ok(7));
        let outcome = first_panic_of(|| -> u32 { panic!("{} GPUs", 0) });
        assert!(
            outcome
                .as_ref()
                .is_err_and(|why| why.ends_with("panicked: 0 GPUs")),
            "{outcome:?}"
        );
    }

    #[test]
    fn a_device_that_works_is_handed_back() {
        assert!(tried(Device::flex()).is_ok());
    }
}
