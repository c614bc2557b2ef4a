//! How the stages move the image, measured rather than typed in: each stage
//! is moved a few small known distances within the soft limits (read off
//! its encoder), and the free spheres' shift in the image between frames
//! gives the pixels per µm, which image axis the stage moves along, and its
//! sign. Moves that reverse the stage's direction show its backlash: the
//! motor turns through the play before the image moves.

use crate::config::AgentConfig;
use crate::instrument::Instrument;
use kdc101::ImageAxis;
use kdc101::apt::StopMode;
use serde::Serialize;
use std::time::{Duration, Instant};
use tweezer_vision::{Camera, Segmenter};

/// At least this many spheres must be matched across every move.
const MIN_MATCHED: usize = 3;
/// A sphere's own drift between two frames on the twin is at most 2 px per
/// axis; a match lies within this of the scene's shift, px.
const MATCH_TOLERANCE_PX: f64 = 6.0;
/// The largest share of a move's shift across its stage's image axis (a
/// camera turned by more than about 6° against the stages).
const MAX_CROSS_SHARE: f64 = 0.1;
/// The largest relative disagreement between two measures of px per µm.
const MAX_SCALE_DISAGREEMENT: f64 = 0.03;
/// Moves are commanded this often.
const MOVE_TICK: Duration = Duration::from_millis(50);
/// The speed of a calibration move, mm/s.
const MOVE_SPEED_MM_S: f64 = 0.05;
/// A move ends within this of its target, mm (it is then measured, not
/// assumed).
const MOVE_TOLERANCE_MM: f64 = 0.000_5;

/// Why the calibration was refused.
#[derive(Debug, thiserror::Error)]
#[error("calibration refused: {0}")]
pub struct CalibrationError(String);

fn refuse(reason: impl Into<String>) -> CalibrationError {
    CalibrationError(reason.into())
}

/// One measured move.
#[derive(Clone, Debug, Serialize)]
pub struct Move {
    /// The stage moved: 0 for X, 1 for Y.
    pub stage: usize,
    /// How far its motor turned, µm (its encoder).
    pub motor_um: f64,
    /// How far the scene moved in the image, px.
    pub shift_px: [f64; 2],
    /// Spheres matched across the move.
    pub matched: usize,
    /// Whether the move reversed the stage's direction (and so crossed its
    /// backlash).
    pub reversal: bool,
}

/// What `calibrate` found.
#[derive(Clone, Debug, Serialize)]
pub struct Measured {
    /// Camera pixels per µm.
    pub px_per_um: f64,
    /// The stage that moves the image along x.
    pub image_x: ImageAxis,
    /// Stage X's sign (`stages.x_sign`).
    pub x_sign: f64,
    /// Stage Y's sign.
    pub y_sign: f64,
    /// Each stage's backlash (X, Y), µm.
    pub backlash_um: [f64; 2],
    /// Root-mean-square gap between each move's measured shift and the
    /// one the calibration predicts, px (moves that cross the backlash
    /// aside).
    pub residual_px: f64,
    /// How far the image axes are turned against the stages, degrees.
    pub rotation_deg: f64,
    /// Every move.
    pub moves: Vec<Move>,
}

/// Free spheres in the current frame: detections away from the trapped
/// sphere at the frame's centre.
fn features(
    camera: &mut impl Camera,
    segmenter: &mut Segmenter,
    trap_search_px: f64,
) -> Result<Vec<[f64; 2]>, CalibrationError> {
    let frame = camera.grab().map_err(|e| refuse(format!("camera: {e}")))?;
    let centre = [frame.width() as f64 / 2.0, frame.height() as f64 / 2.0];
    Ok(segmenter
        .segment(&frame)
        .map_err(|e| refuse(format!("segmentation: {e}")))?
        .into_iter()
        .map(|d| d.centre)
        .filter(|c| (c[0] - centre[0]).hypot(c[1] - centre[1]) > trap_search_px)
        .collect())
}

/// The shift that carries most spheres of `before` onto one of `after`,
/// refined as the mean of their displacements; and how many matched.
pub fn scene_shift(before: &[[f64; 2]], after: &[[f64; 2]]) -> ([f64; 2], usize) {
    let matches = |shift: [f64; 2]| {
        before
            .iter()
            .filter_map(|a| {
                after
                    .iter()
                    .map(|b| [b[0] - a[0], b[1] - a[1]])
                    .filter(|v| (v[0] - shift[0]).hypot(v[1] - shift[1]) <= MATCH_TOLERANCE_PX)
                    .min_by(|u, v| {
                        let d = |w: &[f64; 2]| (w[0] - shift[0]).hypot(w[1] - shift[1]);
                        d(u).total_cmp(&d(v))
                    })
            })
            .collect::<Vec<_>>()
    };
    let best = before
        .iter()
        .flat_map(|a| after.iter().map(move |b| [b[0] - a[0], b[1] - a[1]]))
        .map(|candidate| (candidate, matches(candidate).len()))
        .max_by_key(|&(_, n)| n);
    let Some((candidate, _)) = best else {
        return ([0.0; 2], 0);
    };
    let matched = matches(candidate);
    let n = matched.len().max(1) as f64;
    let mean = [0, 1].map(|k| matched.iter().map(|v| v[k]).sum::<f64>() / n);
    (mean, matched.len())
}

/// Measures the calibration on `instrument`, whose stages were opened
/// without backlash compensation, with moves of `move_um`.
pub fn calibrate(
    instrument: &mut Instrument,
    config: &AgentConfig,
    move_um: f64,
) -> Result<Measured, CalibrationError> {
    if !(move_um.is_finite() && (1.0..=500.0).contains(&move_um)) {
        return Err(refuse(format!(
            "a move of {move_um} µm: choose one in [1, 500], larger than the backlash and small enough that spheres stay in view"
        )));
    }
    let trap_search_px = config.control.trap_search_px;
    let camera = instrument.rig().camera();
    camera.start().map_err(|e| refuse(format!("camera: {e}")))?;
    let mut segmenter = Segmenter::new(config.segmentation.clone(), camera.size())
        .map_err(|e| refuse(format!("segmentation: {e}")))?;
    let mut before = features(camera, &mut segmenter, trap_search_px)?;
    if before.len() < MIN_MATCHED {
        return Err(refuse(format!(
            "the scene has no features: {} free spheres in view, at least {MIN_MATCHED} needed (move to a region with free spheres, or check [segmentation] with `hardware-agent segment`)",
            before.len()
        )));
    }
    let step_mm = move_um / 1000.0;
    let mut moves = Vec::new();
    for stage in 0..2 {
        // Out and back, twice over: the first move takes up the play, the
        // first of each reversed pair crosses it.
        let now = instrument
            .rig()
            .stages()
            .position_mm()
            .map_err(|e| refuse(e.to_string()))?[stage];
        let room_up = config.stages.max_mm - now;
        let room_down = now - config.stages.min_mm;
        let out = if room_up >= 2.5 * step_mm {
            1.0
        } else if room_down >= 2.5 * step_mm {
            -1.0
        } else {
            return Err(refuse(format!(
                "stage {} at {now:.3} mm has no {:.0} µm of room inside its soft limits",
                ["X", "Y"][stage],
                2.5 * move_um
            )));
        };
        for (k, direction) in [out, out, -out, -out, out, out].into_iter().enumerate() {
            let motor_mm = move_stage(instrument, config, stage, direction * step_mm)?;
            let after = features(instrument.rig().camera(), &mut segmenter, trap_search_px)?;
            let (shift_px, matched) = scene_shift(&before, &after);
            if matched < MIN_MATCHED {
                return Err(refuse(format!(
                    "the shifts disagree: only {matched} spheres matched across a {move_um} µm move of stage {} (at least {MIN_MATCHED} needed: move to a region with more free spheres, or use a smaller --move-um)",
                    ["X", "Y"][stage]
                )));
            }
            if k > 0 {
                moves.push(Move {
                    stage,
                    motor_um: motor_mm * 1000.0,
                    shift_px,
                    matched,
                    reversal: k == 2 || k == 4,
                });
            }
            before = after;
        }
    }
    instrument.rig().camera().stop();
    fit(&moves)
}

/// Moves `stage` by `delta_mm` with velocity commands and waits until it
/// stands still; how far its motor truly turned, mm.
fn move_stage(
    instrument: &mut Instrument,
    config: &AgentConfig,
    stage: usize,
    delta_mm: f64,
) -> Result<f64, CalibrationError> {
    let stages = instrument.rig().stages();
    let read = |stages: &mut kdc101::StagePair<_>| {
        stages
            .position_mm()
            .map(|p| p[stage])
            .map_err(|e| refuse(e.to_string()))
    };
    let start = read(stages)?;
    let target = start + delta_mm;
    let speed = MOVE_SPEED_MM_S.min(config.stages.max_speed_mm_s);
    let bound = Instant::now() + Duration::from_secs_f64(3.0 * delta_mm.abs() / speed + 5.0);
    loop {
        let left = target - read(stages)?;
        if left.abs() <= MOVE_TOLERANCE_MM {
            break;
        }
        if Instant::now() > bound {
            let _ = stages.stop(StopMode::Immediate);
            return Err(refuse(format!(
                "stage {} did not reach {target:.4} mm in time",
                ["X", "Y"][stage]
            )));
        }
        // Slower as the target nears, to stop on it.
        let v = (left / (4.0 * MOVE_TICK.as_secs_f64())).clamp(-speed, speed);
        let mut mm_s = [0.0; 2];
        mm_s[stage] = v;
        stages
            .set_velocity_mm(mm_s)
            .map_err(|e| refuse(e.to_string()))?;
        std::thread::sleep(MOVE_TICK);
    }
    stages
        .stop(StopMode::Profiled)
        .map_err(|e| refuse(e.to_string()))?;
    // Still when two readings a tick apart agree.
    let mut last = read(stages)?;
    let settle = Instant::now() + Duration::from_secs(5);
    loop {
        std::thread::sleep(MOVE_TICK);
        let now = read(stages)?;
        if (now - last).abs() < 1e-5 {
            return Ok(now - start);
        }
        if Instant::now() > settle {
            return Err(refuse(format!(
                "stage {} did not settle",
                ["X", "Y"][stage]
            )));
        }
        last = now;
    }
}

/// The calibration the moves say, or why they disagree.
pub fn fit(moves: &[Move]) -> Result<Measured, CalibrationError> {
    let mut per_stage = Vec::new();
    for stage in 0..2 {
        let clean: Vec<&Move> = moves
            .iter()
            .filter(|m| m.stage == stage && !m.reversal)
            .collect();
        let name = ["X", "Y"][stage];
        // Shift per µm of motor travel, least squares through the origin.
        let travel: f64 = clean.iter().map(|m| m.motor_um * m.motor_um).sum();
        if clean.is_empty() || travel == 0.0 {
            return Err(refuse(format!("stage {name} did not move")));
        }
        let per_um = [0, 1].map(|k| {
            clean
                .iter()
                .map(|m| m.shift_px[k] * m.motor_um)
                .sum::<f64>()
                / travel
        });
        let axis = usize::from(per_um[1].abs() > per_um[0].abs());
        let (along, across) = (per_um[axis], per_um[1 - axis]);
        if across.abs() > MAX_CROSS_SHARE * along.abs() {
            return Err(refuse(format!(
                "stage {name} moves the image along ({:.3}, {:.3}) px/µm, {:.1}° off the image axes: turn the camera to the stages",
                per_um[0],
                per_um[1],
                across.atan2(along).to_degrees().abs()
            )));
        }
        for m in &clean {
            let scale = m.shift_px[axis] / m.motor_um;
            if (scale - along).abs() > MAX_SCALE_DISAGREEMENT * along.abs() {
                return Err(refuse(format!(
                    "the shifts disagree: a move of stage {name} by {:.2} µm shifted the image {:.1} px, {scale:.3} px/µm against {along:.3} over all its moves",
                    m.motor_um, m.shift_px[axis]
                )));
            }
        }
        per_stage.push((axis, along, across));
    }
    let [(x_axis, x_along, x_across), (y_axis, y_along, y_across)] = [per_stage[0], per_stage[1]];
    if x_axis == y_axis {
        return Err(refuse(format!(
            "both stages move the image along its {} axis",
            ["x", "y"][x_axis]
        )));
    }
    let (sx, sy) = (x_along.abs(), y_along.abs());
    if (sx - sy).abs() > MAX_SCALE_DISAGREEMENT * sx.max(sy) {
        return Err(refuse(format!(
            "the shifts disagree: stage X moves the image {sx:.3} px/µm, stage Y {sy:.3}"
        )));
    }
    let px_per_um = 0.5 * (sx + sy);
    // Features move against the trap: a stage whose forward motion moves
    // the image's features toward smaller coordinates has sign +1.
    let signs = [-x_along.signum(), -y_along.signum()];
    let axes = [x_axis, y_axis];
    let predicted = |m: &Move| {
        let mut shift = [0.0; 2];
        shift[axes[m.stage]] = -signs[m.stage] * px_per_um * m.motor_um;
        shift
    };
    let clean: Vec<&Move> = moves.iter().filter(|m| !m.reversal).collect();
    let residual_px = (clean
        .iter()
        .map(|m| {
            let p = predicted(m);
            (m.shift_px[0] - p[0]).powi(2) + (m.shift_px[1] - p[1]).powi(2)
        })
        .sum::<f64>()
        / clean.len() as f64)
        .sqrt();
    let backlash_um = [0, 1].map(|stage| {
        let reversals: Vec<f64> = moves
            .iter()
            .filter(|m| m.stage == stage && m.reversal)
            .map(|m| m.motor_um.abs() - m.shift_px[axes[stage]].abs() / px_per_um)
            .collect();
        (reversals.iter().sum::<f64>() / reversals.len().max(1) as f64).max(0.0)
    });
    let rotation_deg =
        0.5 * ((x_across / x_along).atan().to_degrees() - (y_across / y_along).atan().to_degrees());
    Ok(Measured {
        px_per_um,
        image_x: if x_axis == 0 {
            ImageAxis::X
        } else {
            ImageAxis::Y
        },
        x_sign: signs[0],
        y_sign: signs[1],
        backlash_um,
        residual_px,
        rotation_deg,
        moves: moves.to_vec(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scene_shift_follows_most_spheres_past_a_newcomer() {
        let before = [
            [100.0, 100.0],
            [300.0, 120.0],
            [220.0, 400.0],
            [50.0, 500.0],
        ];
        let after: Vec<[f64; 2]> = before
            .iter()
            .map(|p| [p[0] - 40.5, p[1] + 1.0])
            .chain([[600.0, 600.0]])
            .collect();
        let (shift, matched) = scene_shift(&before, &after);
        assert_eq!(matched, 4);
        assert!((shift[0] + 40.5).abs() < 1e-9 && (shift[1] - 1.0).abs() < 1e-9);
    }

    fn clean(stage: usize, motor_um: f64, shift_px: [f64; 2]) -> Move {
        Move {
            stage,
            motor_um,
            shift_px,
            matched: 5,
            reversal: false,
        }
    }

    #[test]
    fn a_fit_finds_the_axes_signs_scale_and_backlash() {
        // Stage X moves the image along y, features toward larger y when it
        // goes forward (sign -1); stage Y along x, toward smaller x (+1);
        // 8 µm of backlash on X.
        let moves = [
            clean(0, 20.0, [0.0, 200.0]),
            Move {
                reversal: true,
                ..clean(0, -20.0, [0.0, -120.0])
            },
            clean(0, -20.0, [0.0, -200.0]),
            clean(1, 20.0, [-200.0, 0.0]),
            clean(1, -20.0, [200.0, 0.0]),
        ];
        let m = fit(&moves).unwrap();
        assert_eq!(m.image_x, ImageAxis::Y);
        assert_eq!([m.x_sign, m.y_sign], [-1.0, 1.0]);
        assert!((m.px_per_um - 10.0).abs() < 1e-9);
        assert!((m.backlash_um[0] - 8.0).abs() < 1e-9);
        assert!(m.residual_px < 1e-9);
    }

    #[test]
    fn moves_that_disagree_are_refused() {
        let diagonal = [clean(0, 20.0, [200.0, 60.0]), clean(1, 20.0, [0.0, 200.0])];
        assert!(
            fit(&diagonal)
                .unwrap_err()
                .to_string()
                .contains("off the image axes")
        );
        let scales = [clean(0, 20.0, [200.0, 0.0]), clean(1, 20.0, [0.0, 230.0])];
        assert!(fit(&scales).unwrap_err().to_string().contains("disagree"));
        let same_axis = [clean(0, 20.0, [200.0, 0.0]), clean(1, 20.0, [200.0, 0.0])];
        assert!(
            fit(&same_axis)
                .unwrap_err()
                .to_string()
                .contains("both stages")
        );
    }
}
