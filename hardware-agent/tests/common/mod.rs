//! A rig on the twin's stages around a live camera, for the tests of
//! camera sources whose frames do not come from the twin.

use kdc101::StagePair;
use serialport::TTYPort;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tweezer_gym::EnvConfig;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::{ControlConfig, Rig};
use tweezer_hardware_agent::overlay::Overlay;
use tweezer_hardware_agent::twin::TwinStages;
use tweezer_vision::{Camera, Segmenter};

/// The agent's defaults without free spheres in the (unused) virtual
/// sample, a loop at 10 Hz with a wide deadline margin (a loaded test
/// machine must not end an episode early), and `lost_trap_frames`.
pub fn agent_config(lost_trap_frames: u32) -> (AgentConfig, ControlConfig) {
    let config = AgentConfig {
        env: EnvConfig {
            min_free_spheres: 0,
            max_free_spheres: 0,
            ..EnvConfig::default()
        },
        ..AgentConfig::default()
    };
    let control = ControlConfig {
        rate_hz: 10.0,
        deadline_margin_ms: 2000.0,
        lost_trap_frames,
        ..config.control.clone()
    };
    (config, control)
}

/// `camera` and the twin's simulated stages in a rig, and the stages.
pub fn twin_rig<C: Camera>(
    camera: C,
    config: &AgentConfig,
    control: ControlConfig,
) -> (Rig<C, TTYPort>, Arc<TwinStages>) {
    let twin = Arc::new(TwinStages::spawn(&config.twin).unwrap());
    let (stages, _) =
        StagePair::<TTYPort>::open_paths(twin.ports(), &config.stages, control.command_interval())
            .unwrap();
    let segmenter = Segmenter::new(config.segmentation.clone(), camera.size()).unwrap();
    let overlay = Overlay::new(
        &Default::default(),
        config.stages.px_per_um,
        config.env.sphere_radius_px(),
    )
    .unwrap();
    let rig = Rig::new(
        camera,
        stages,
        segmenter,
        config.env.clone(),
        control,
        overlay,
    )
    .unwrap();
    (rig, twin)
}

/// Whether both of the twin's stages stand still within two seconds (the
/// simulated controllers take the stop from their serial ports).
pub fn still(twin: &TwinStages) -> bool {
    let deadline = Instant::now() + Duration::from_secs(2);
    loop {
        let speeds = twin
            .stages()
            .each_ref()
            .map(|stage| stage.controller().speed_mm_s());
        if speeds == [0.0; 2] {
            return true;
        }
        if Instant::now() > deadline {
            eprintln!("the stages still move at {speeds:?} mm/s");
            return false;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}
