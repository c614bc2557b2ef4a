//! `hardware-agent cameras [ADDRESS]`: the GenICam cameras found, or the
//! one at an address, with what to name them by in `[camera.genicam]`.

use tweezer_vision::genicam::CameraInfo;

/// Lists what discovery finds, or describes the camera at `address`.
#[cfg(feature = "aravis")]
pub fn run(address: Option<&str>, json: bool) -> anyhow::Result<()> {
    use tweezer_vision::genicam::{describe, discover};
    let found = match address {
        Some(address) => vec![describe(address)?],
        None => discover(),
    };
    if found.is_empty() && !json {
        println!(
            "no GenICam camera found (GigE Vision cameras on another subnet, or on loopback, are reached by address: `hardware-agent cameras ADDRESS`)"
        );
    }
    for camera in &found {
        print(camera, json);
    }
    Ok(())
}

/// Refuses: this build has no GenICam support.
#[cfg(not(feature = "aravis"))]
pub fn run(_address: Option<&str>, _json: bool) -> anyhow::Result<()> {
    anyhow::bail!("{}", tweezer_vision::genicam::REBUILD_HINT)
}

#[cfg_attr(not(feature = "aravis"), allow(dead_code))]
fn print(camera: &CameraInfo, json: bool) {
    if json {
        println!("{}", serde_json::json!(camera));
    } else {
        println!(
            "{}  {} {}  serial {}  {} {}  formats {}",
            camera.id,
            camera.vendor,
            camera.model,
            camera.serial,
            camera.protocol,
            camera.address,
            camera.pixel_formats.join(",")
        );
    }
}
