//! Segmentation of twin frames, whose true sphere centres are known, and of
//! the same frames replayed from PNG and TIFF files.

use tweezer_gym::{EnvConfig, SplitMix64};
use tweezer_hardware_agent::twin::{OpticsConfig, detection_quality, episode_scene};
use tweezer_vision::{Camera, CameraError, ReplayCamera, read_frame, write_frame};
use tweezer_vision::{SegmentConfig, SegmentError, Segmenter};

/// Spheres on a jittered grid, 150 px apart: none touches another (debris
/// may lie over one).
fn separated_scene(seed: u64) -> Vec<[f64; 2]> {
    let mut rng = SplitMix64::new(seed);
    let mut spheres = Vec::new();
    for i in 0..6 {
        for j in 0..8 {
            spheres.push([
                100.0 + 150.0 * j as f64 + rng.uniform(-20.0, 20.0),
                100.0 + 150.0 * i as f64 + rng.uniform(-20.0, 20.0),
            ]);
        }
    }
    spheres
}

#[test]
fn separate_spheres_are_found_within_a_third_of_a_pixel_at_any_focus_and_noise() {
    let scenes: Vec<_> = (0..4).map(separated_scene).collect();
    for focus in [-0.8, -0.3, 0.0, 0.3, 0.8] {
        for noise in [1.0, 3.0] {
            let optics = OpticsConfig {
                focus,
                read_noise: noise,
                full_well_electrons: 10_000.0 / (noise * noise),
                ..OpticsConfig::default()
            };
            let q = detection_quality(&optics, &SegmentConfig::default(), &scenes, 7).unwrap();
            assert_eq!(q.spheres, 4 * 48);
            assert!(
                q.recall >= 0.99 && q.precision >= 0.98 && q.isolated_mean_error_px < 0.33,
                "focus {focus}, noise ×{noise}: {q:?}"
            );
        }
    }
}

#[test]
fn the_spheres_of_virtual_episodes_are_found() {
    let config = EnvConfig::default();
    let scenes: Vec<_> = (0..12)
        .map(|seed| episode_scene(&config, seed, 5))
        .collect();
    let q = detection_quality(
        &OpticsConfig::default(),
        &SegmentConfig::default(),
        &scenes,
        3,
    )
    .unwrap();
    // Touching and overlapping spheres (about one in twelve at the spec's
    // density) are split less well than separate ones are found.
    assert!(q.spheres > 100, "{q:?}");
    assert!(q.recall >= 0.9 && q.precision >= 0.95, "{q:?}");
    assert!(q.isolated_mean_error_px < 0.33, "{q:?}");
}

#[test]
fn a_frame_replayed_from_png_or_tiff_is_segmented_as_the_original() {
    let dir = tempfile::tempdir().unwrap();
    let optics = OpticsConfig::default();
    let scene = separated_scene(1);
    let frame = optics.render(&scene, &[], 1);
    let mut segmenter = Segmenter::new(SegmentConfig::default(), optics.size_px).unwrap();
    let original = segmenter.segment(&frame).unwrap();
    assert_eq!(original.len(), scene.len());

    // The same frame at 16 bits: every value scaled by 257.
    let deep = tweezer_vision::GrayFrame::new(
        frame.width(),
        frame.height(),
        u16::MAX,
        frame.pixels().iter().map(|&p| p * 257).collect(),
    )
    .unwrap();
    write_frame(&dir.path().join("a.png"), &frame).unwrap();
    write_frame(&dir.path().join("b.png"), &deep).unwrap();
    write_frame(&dir.path().join("c.tif"), &deep).unwrap();
    std::fs::write(dir.path().join("notes.txt"), "not a frame").unwrap();
    assert_eq!(read_frame(&dir.path().join("a.png")).unwrap(), frame);
    assert_eq!(read_frame(&dir.path().join("c.tif")).unwrap(), deep);

    let mut camera = ReplayCamera::open(dir.path(), false).unwrap();
    assert_eq!((camera.len(), camera.size()), (3, [1280, 1024]));
    for _ in 0..3 {
        let replayed = segmenter.segment(&camera.grab().unwrap()).unwrap();
        assert_eq!(replayed.len(), original.len());
        for (a, b) in replayed.iter().zip(&original) {
            let d = (a.centre[0] - b.centre[0]).hypot(a.centre[1] - b.centre[1]);
            assert!(d < 0.05, "{a:?} vs {b:?}");
        }
    }
    assert!(matches!(camera.grab(), Err(CameraError::Exhausted(_))));
    let mut looping = ReplayCamera::open(dir.path(), true).unwrap();
    for _ in 0..4 {
        looping.grab().unwrap();
    }
}

#[test]
fn bad_files_and_frames_of_the_wrong_size_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let small = OpticsConfig {
        size_px: [640, 512],
        ..OpticsConfig::default()
    };
    write_frame(
        &dir.path().join("1.png"),
        &OpticsConfig::default().render(&[], &[], 1),
    )
    .unwrap();
    write_frame(&dir.path().join("2.png"), &small.render(&[], &[], 1)).unwrap();
    std::fs::write(dir.path().join("3.png"), b"\x89PNG but not really").unwrap();
    let mut camera = ReplayCamera::open(dir.path(), false).unwrap();
    camera.grab().unwrap();
    let error = camera.grab().unwrap_err().to_string();
    assert!(
        error.contains("2.png") && error.contains("[640, 512]"),
        "{error}"
    );
    let error = camera.grab().unwrap_err().to_string();
    assert!(error.contains("3.png"), "{error}");

    let empty = tempfile::tempdir().unwrap();
    let error = ReplayCamera::open(empty.path(), false)
        .unwrap_err()
        .to_string();
    assert!(error.contains("no .png"), "{error}");

    let mut segmenter = Segmenter::new(SegmentConfig::default(), [1280, 1024]).unwrap();
    assert!(matches!(
        segmenter.segment(&small.render(&[], &[], 1)),
        Err(SegmentError::Size { .. })
    ));
    let bad = SegmentConfig {
        max_area_px: 10.0,
        ..SegmentConfig::default()
    };
    let error = Segmenter::new(bad, [1280, 1024]).unwrap_err().to_string();
    assert!(error.contains("max_area_px"), "{error}");
}

#[test]
fn the_segment_command_prints_one_json_line_per_file_and_names_a_bad_one() {
    let dir = tempfile::tempdir().unwrap();
    let optics = OpticsConfig::default();
    let scene = separated_scene(2);
    let good = dir.path().join("frame.png");
    write_frame(&good, &optics.render(&scene, &[], 2)).unwrap();
    let bad = dir.path().join("broken.tif");
    std::fs::write(&bad, b"II*\0 truncated").unwrap();
    let out = tweezer_system_tests::output_of(
        std::process::Command::new(env!("CARGO_BIN_EXE_hardware-agent"))
            .arg("segment")
            .arg(&good)
            .arg(&bad)
            .arg("--json"),
    );
    assert!(!out.status.success());
    let stdout = String::from_utf8(out.stdout).unwrap();
    let line: serde_json::Value = serde_json::from_str(stdout.lines().next().unwrap()).unwrap();
    assert_eq!(line["file"], good.display().to_string());
    let centres = line["centres"].as_array().unwrap();
    assert_eq!(centres.len(), scene.len());
    for c in centres {
        let (x, y) = (c[0].as_f64().unwrap(), c[1].as_f64().unwrap());
        assert!(
            scene.iter().any(|s| (s[0] - x).hypot(s[1] - y) < 1.0),
            "{c}"
        );
    }
    assert_eq!(stdout.lines().count(), 1);
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(stderr.contains("broken.tif"), "{stderr}");
}
