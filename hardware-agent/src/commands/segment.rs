//! `hardware-agent segment FILES`: the centres segmentation finds in each.

use anyhow::bail;
use std::collections::HashMap;
use std::path::PathBuf;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_vision::Segmenter;
use tweezer_vision::read_frame;

/// Segments every file and prints its centres; a file that cannot be read
/// or segmented is reported and the rest still run.
pub fn run(config: &AgentConfig, files: &[PathBuf], json: bool) -> anyhow::Result<()> {
    let mut segmenters: HashMap<[usize; 2], Segmenter> = HashMap::new();
    let mut failed = 0;
    for file in files {
        let result = read_frame(file)
            .map_err(anyhow::Error::from)
            .and_then(|frame| {
                let size = [frame.width(), frame.height()];
                let segmenter = match segmenters.entry(size) {
                    std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                    std::collections::hash_map::Entry::Vacant(e) => {
                        e.insert(Segmenter::new(config.segmentation.clone(), size)?)
                    }
                };
                Ok(segmenter.segment(&frame)?)
            });
        match result {
            Ok(found) => {
                let centres: Vec<[f64; 2]> = found
                    .iter()
                    .map(|d| d.centre.map(|v| (v * 100.0).round() / 100.0))
                    .collect();
                if json {
                    let line =
                        serde_json::json!({"file": file.display().to_string(), "centres": centres});
                    println!("{line}");
                } else {
                    let list: Vec<String> = centres
                        .iter()
                        .map(|c| format!("({:.2}, {:.2})", c[0], c[1]))
                        .collect();
                    println!(
                        "{}: {} spheres {}",
                        file.display(),
                        centres.len(),
                        list.join(" ")
                    );
                }
            }
            Err(e) => {
                failed += 1;
                eprintln!("error: {}: {e:#}", file.display());
            }
        }
    }
    if failed > 0 {
        bail!("{failed} of {} files could not be segmented", files.len());
    }
    Ok(())
}
