//! The segmenter on frames drawn here: microspheres as a bright-field
//! microscope shows them (a dark ring, its centre lighter or darker with
//! focus) over an uneven background with noise, at known centres.

use tweezer_vision::{Detection, GrayFrame, SegmentConfig, SegmentError, Segmenter};

const SIZE: [usize; 2] = [640, 480];

/// A sphere's look: a dark ring of radius 24 px and a centre spot lighter
/// (`centre` > 0) or darker than the background.
#[derive(Clone, Copy)]
struct Look {
    ring_depth: f64,
    centre: f64,
}

const LIGHT_CENTRE: Look = Look {
    ring_depth: 0.3,
    centre: 0.2,
};

/// Splitmix64: a noise source of the test's own.
struct Noise(u64);

impl Noise {
    fn unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A standard normal draw (Box–Muller).
    fn normal(&mut self) -> f64 {
        let (u, v) = (self.unit().max(1e-12), self.unit());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// An 8-bit frame: background about 140 with a gentle gradient, the
/// spheres at `centres`, extra `relief(x, y)` (0: none), noise of σ 2.
fn frame(centres: &[[f64; 2]], look: Look, relief: impl Fn(f64, f64) -> f64) -> GrayFrame {
    let [w, h] = SIZE;
    let mut noise = Noise(7);
    let mut pixels = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            let mut m = relief(px, py);
            for c in centres {
                let r = (px - c[0]).hypot(py - c[1]);
                let ring = (r - 24.0) / 3.0;
                let spot = r / 6.5;
                m += -look.ring_depth * (-0.5 * ring * ring).exp()
                    + look.centre * (-0.5 * spot * spot).exp();
            }
            let background = 140.0 * (1.0 + 0.1 * (px / w as f64 - 0.5));
            let level = background * (1.0 + m) + 2.0 * noise.normal();
            pixels.push(level.round().clamp(0.0, 255.0) as u16);
        }
    }
    GrayFrame::new(w, h, 255, pixels).unwrap()
}

fn segment(frame: &GrayFrame) -> Vec<Detection> {
    let mut segmenter = Segmenter::new(SegmentConfig::default(), SIZE).unwrap();
    segmenter.segment(frame).unwrap()
}

/// The detection nearest `truth`, and how far it is.
fn nearest(found: &[Detection], truth: [f64; 2]) -> (Detection, f64) {
    (found.iter())
        .map(|d| (*d, (d.centre[0] - truth[0]).hypot(d.centre[1] - truth[1])))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("a detection")
}

/// Six spheres, 150 px or more apart, at fractional positions.
fn separated() -> Vec<[f64; 2]> {
    let mut centres = Vec::new();
    for (i, y) in [120.3, 330.8].into_iter().enumerate() {
        for (j, x) in [110.6, 300.2, 505.45].into_iter().enumerate() {
            centres.push([x + 1.7 * j as f64, y + 0.9 * i as f64]);
        }
    }
    centres
}

#[test]
fn separate_spheres_are_found_within_half_a_pixel_light_or_dark_centred() {
    let dark_centre = Look {
        ring_depth: 0.3,
        centre: -0.2,
    };
    for look in [LIGHT_CENTRE, dark_centre] {
        let truth = separated();
        let found = segment(&frame(&truth, look, |_, _| 0.0));
        assert_eq!(found.len(), truth.len(), "{found:?}");
        for t in &truth {
            let (d, error) = nearest(&found, *t);
            assert!(error < 0.5, "sphere at {t:?} found at {:?}", d.centre);
            assert!(!d.clipped, "{d:?}");
            assert!(d.circularity >= 0.8, "{d:?}");
        }
    }
}

#[test]
fn a_blank_frame_and_a_streak_of_debris_hold_no_sphere() {
    assert_eq!(segment(&frame(&[], LIGHT_CENTRE, |_, _| 0.0)), []);
    // A dark streak 200 px long and 14 px wide: as dark as a ring, far
    // from round.
    let streak = |x: f64, y: f64| {
        if (200.0..400.0).contains(&x) && (233.0..247.0).contains(&y) {
            -0.3
        } else {
            0.0
        }
    };
    assert_eq!(segment(&frame(&[], LIGHT_CENTRE, streak)), []);
}

#[test]
fn two_touching_spheres_are_split_into_two() {
    let truth = [[300.0, 240.0], [352.0, 246.0]];
    let found = segment(&frame(&truth, LIGHT_CENTRE, |_, _| 0.0));
    assert_eq!(found.len(), 2, "{found:?}");
    for t in truth {
        let (d, error) = nearest(&found, t);
        assert!(error < 3.0, "sphere at {t:?} found at {:?}", d.centre);
    }
}

#[test]
fn a_sphere_cut_by_the_frame_edge_is_kept_and_marked() {
    let truth = [[12.0, 240.0], [320.0, 240.0]];
    let found = segment(&frame(&truth, LIGHT_CENTRE, |_, _| 0.0));
    assert_eq!(found.len(), 2, "{found:?}");
    let (edge, _) = nearest(&found, truth[0]);
    assert!(edge.clipped, "{edge:?}");
    let (inside, error) = nearest(&found, truth[1]);
    assert!(!inside.clipped && error < 0.5, "{inside:?}");
}

#[test]
fn a_frame_of_another_size_is_refused_naming_both_sizes() {
    let mut segmenter = Segmenter::new(SegmentConfig::default(), [320, 240]).unwrap();
    let error = segmenter
        .segment(&frame(&[], LIGHT_CENTRE, |_, _| 0.0))
        .unwrap_err();
    assert_eq!(
        error,
        SegmentError::Size {
            got: [640, 480],
            want: [320, 240]
        }
    );
    assert!(error.to_string().contains("[640, 480]"), "{error}");
}

#[test]
fn bad_settings_are_refused_by_name() {
    let bad = SegmentConfig {
        min_circularity: 1.5,
        ..SegmentConfig::default()
    };
    let error = Segmenter::new(bad, SIZE).unwrap_err();
    assert!(
        matches!(error, SegmentError::Config { field, .. } if field == "min_circularity"),
        "{error:?}"
    );
    assert!(
        error
            .to_string()
            .starts_with("segmentation.min_circularity")
    );
}
