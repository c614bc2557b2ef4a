//! `hardware-agent calibrate`: the calibration measured on the instrument
//! or the twin, printed, and written into a config file's `[stages]`.

use std::path::{Path, PathBuf};
use tweezer_hardware_agent::calibration::{Measured, calibrate};
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::instrument::Instrument;
use tweezer_process::init_logging;

/// The comment that says where `[stages]`'s calibration came from.
const NOTE: &str = "# Calibration measured by `hardware-agent calibrate`:";

/// What to calibrate, and where the result goes.
pub struct CalibrateArgs {
    /// The digital twin rather than the instrument.
    pub twin: bool,
    /// The twin's scene.
    pub seed: u64,
    /// Each move, µm.
    pub move_um: f64,
    /// The config file to write `[stages]` into.
    pub write: Option<PathBuf>,
    /// One JSON object instead of text.
    pub json: bool,
}

/// Measures, prints, and writes if asked.
pub fn run(config: &AgentConfig, args: &CalibrateArgs) -> anyhow::Result<()> {
    // The backlash is measured, so the driver must not take it up.
    let mut opened = config.clone();
    opened.stages.backlash_um = 0.0;
    init_logging(false);
    let mut instrument = Instrument::open(&opened, args.twin)?;
    super::stop_stages_on_signal(instrument.rig().stopper(), "the calibration")?;
    if args.twin {
        instrument.start_twin_episode(args.seed);
    }
    let measured = calibrate(&mut instrument, &opened, args.move_um)?;
    if args.json {
        println!("{}", serde_json::json!(measured));
    } else {
        println!(
            "px_per_um = {:.4}\nimage_x = \"{}\"\nx_sign = {}\ny_sign = {}\nbacklash: X {:.2} µm, Y {:.2} µm\nresidual {:.2} px over {} moves, image turned {:.2}° against the stages",
            measured.px_per_um,
            axis_name(&measured),
            measured.x_sign,
            measured.y_sign,
            measured.backlash_um[0],
            measured.backlash_um[1],
            measured.residual_px,
            measured.moves.len(),
            measured.rotation_deg
        );
    }
    if let Some(path) = &args.write {
        write_stages(path, &measured)?;
        if !args.json {
            println!("written to [stages] in {}", path.display());
        }
    }
    Ok(())
}

fn axis_name(measured: &Measured) -> &'static str {
    match measured.image_x {
        kdc101::ImageAxis::X => "x",
        kdc101::ImageAxis::Y => "y",
    }
}

/// Sets the calibration in `path`'s `[stages]` table (creating the file
/// or the table), keeping every other setting and comment.
fn write_stages(path: &Path, measured: &Measured) -> anyhow::Result<()> {
    tweezer_config::edit_toml(path, |doc| {
        let stages = doc
            .entry("stages")
            .or_insert_with(|| toml_edit::Item::Table(toml_edit::Table::new()))
            .as_table_mut()
            .ok_or("`stages` is not a table")?;
        let round = |v: f64, places: i32| (v * 10f64.powi(places)).round() / 10f64.powi(places);
        stages["px_per_um"] = toml_edit::value(round(measured.px_per_um, 4));
        stages["image_x"] = toml_edit::value(axis_name(measured));
        stages["x_sign"] = toml_edit::value(measured.x_sign);
        stages["y_sign"] = toml_edit::value(measured.y_sign);
        // One value serves both stages: the larger play is taken up.
        stages["backlash_um"] = toml_edit::value(round(
            measured.backlash_um[0].max(measured.backlash_um[1]),
            1,
        ));
        // The comments above the table stay, but for an older calibration's.
        let kept: String = stages
            .decor()
            .prefix()
            .and_then(|p| p.as_str())
            .unwrap_or("\n")
            .lines()
            .filter(|line| !line.starts_with(NOTE))
            .map(|line| format!("{line}\n"))
            .collect();
        stages.decor_mut().set_prefix(format!(
            "{kept}{NOTE} residual {:.2} px over {} moves; backlash X {:.2} µm, Y {:.2} µm.\n",
            measured.residual_px,
            measured.moves.len(),
            measured.backlash_um[0],
            measured.backlash_um[1]
        ));
        Ok(())
    })?;
    Ok(())
}
