//! The renderer against `docs/spec.md` §2's pixel rule, evaluated pixel by
//! pixel.

use tweezer_gym::{
    Action, Env, EnvConfig, Frame, ImageConfig, Outcome, Policy, Renderer, SizeMismatch,
    SplitMix64, UniformRandom,
};

/// The rule of `docs/spec.md` §2, pixel by pixel: on iff the pixel centre is
/// within `radius` of some centre (the trapped sphere at the FOV centre
/// included).
fn reference(fov: [u32; 2], image: ImageConfig, radius: f64, centres: &[[f32; 2]]) -> Vec<u8> {
    let s = f64::from(fov[0]) / f64::from(image.width);
    let mut discs: Vec<[f64; 2]> = vec![[f64::from(fov[0]) / 2.0, f64::from(fov[1]) / 2.0]];
    discs.extend(centres.iter().map(|c| [f64::from(c[0]), f64::from(c[1])]));
    let mut out = Vec::new();
    for i in 0..image.height {
        for j in 0..image.width {
            let (px, py) = (s * (f64::from(j) + 0.5), s * (f64::from(i) + 0.5));
            let lit = discs
                .iter()
                .any(|c| (px - c[0]) * (px - c[0]) + (py - c[1]) * (py - c[1]) <= radius * radius);
            out.push(u8::from(lit));
        }
    }
    out
}

const FOV: [u32; 2] = [1280, 1024];
const RESOLUTIONS: [(u32, u32); 5] = [(320, 256), (80, 64), (160, 128), (1280, 1024), (100, 80)];

fn renderer(width: u32, height: u32) -> Renderer {
    Renderer::new(FOV, ImageConfig { width, height }, 27.0).unwrap()
}

fn random_centres(rng: &mut SplitMix64, n: usize) -> Vec<[f32; 2]> {
    (0..n)
        .map(|_| {
            [
                rng.uniform(-27.0, 1307.0) as f32,
                rng.uniform(-27.0, 1051.0) as f32,
            ]
        })
        .collect()
}

#[test]
fn matches_the_pixel_rule_at_every_resolution() {
    let mut rng = SplitMix64::new(17);
    for (w, h) in RESOLUTIONS {
        let r = renderer(w, h);
        let image = ImageConfig {
            width: w,
            height: h,
        };
        for _ in 0..6 {
            let centres = random_centres(&mut rng, 40);
            let mut out = vec![7u8; r.pixels()];
            r.render(&centres, &mut out).unwrap();
            assert_eq!(out, reference(FOV, image, 27.0, &centres), "{w}x{h}");
        }
    }
}

#[test]
fn large_discs_match_the_pixel_rule() {
    // Wide discs take the renderer's general path (no dx² table).
    let mut rng = SplitMix64::new(23);
    for (w, h, radius) in [(1280, 1024, 90.0), (320, 256, 150.0), (160, 128, 300.0)] {
        let image = ImageConfig {
            width: w,
            height: h,
        };
        let r = Renderer::new(FOV, image, radius).unwrap();
        let centres = random_centres(&mut rng, 5);
        let mut out = vec![0u8; r.pixels()];
        r.render(&centres, &mut out).unwrap();
        assert_eq!(
            out,
            reference(FOV, image, radius, &centres),
            "{w}x{h} r={radius}"
        );
    }
}

#[test]
fn boundary_pixels_are_inclusive() {
    // At 320 x 256 (s = 4), pixel centres lie at 2 + 4k. A sphere at
    // (3, 2) is exactly 27 px from pixel (7, 0)'s centre (30, 2).
    let r = renderer(320, 256).without_trap();
    let lit = |x: f32| {
        let mut out = vec![0u8; r.pixels()];
        r.render(&[[x, 2.0]], &mut out).unwrap();
        out[7]
    };
    assert_eq!(lit(3.0), 1, "exactly at the radius");
    assert_eq!(lit(3.5), 1, "inside");
    assert_eq!(lit(2.5), 0, "outside");
    assert_eq!(lit(3.0 - f32::EPSILON * 4.0), 0, "just outside");
}

#[test]
fn discs_cut_by_the_fov_edge_and_the_trap() {
    let r = renderer(320, 256);
    let image = ImageConfig::default();
    let centres = [
        [-20.0, 500.0],
        [1300.0, 3.0],
        [640.0, -26.5],
        [1279.9, 1023.9],
        [0.0, 0.0],
        [-27.0, -27.0],
    ];
    let mut out = vec![0u8; r.pixels()];
    r.render(&centres, &mut out).unwrap();
    assert_eq!(out, reference(FOV, image, 27.0, &centres));
    // The trapped sphere alone: a disc at the image centre.
    r.render(&[], &mut out).unwrap();
    assert_eq!(out, reference(FOV, image, 27.0, &[]));
    assert_eq!(out[128 * 320 + 160], 1);
    // About the disc's area: π · 27² / 4² ≈ 143 pixels.
    let lit: u32 = out.iter().map(|&p| u32::from(p)).sum();
    assert!((130..=160).contains(&lit), "{lit}");
}

#[test]
fn u8_and_f32_agree() {
    let r = renderer(160, 128);
    let centres = random_centres(&mut SplitMix64::new(3), 30);
    let mut a = vec![0u8; r.pixels()];
    let mut b = vec![0.5f32; r.pixels()];
    r.render(&centres, &mut a).unwrap();
    r.render(&centres, &mut b).unwrap();
    assert!(a.iter().zip(&b).all(|(&a, &b)| f32::from(a) == b));
}

#[test]
fn a_batch_is_filled_in_place() {
    let r = renderer(80, 64);
    let mut rng = SplitMix64::new(5);
    let batch: Vec<Vec<[f32; 2]>> = (0..4).map(|_| random_centres(&mut rng, 12)).collect();
    let mut tensor = vec![0f32; 4 * r.pixels()];
    for (obs, slot) in batch.iter().zip(tensor.chunks_exact_mut(r.pixels())) {
        r.render(obs, slot).unwrap();
    }
    for (obs, slot) in batch.iter().zip(tensor.chunks_exact(r.pixels())) {
        let expected = reference(
            FOV,
            ImageConfig {
                width: 80,
                height: 64,
            },
            27.0,
            obs,
        );
        assert!(expected.iter().zip(slot).all(|(&a, &b)| f32::from(a) == b));
    }
}

#[test]
fn wrong_output_sizes_are_refused() {
    let r = renderer(320, 256);
    let mut out = vec![0u8; 100];
    assert_eq!(
        r.render(&[], &mut out),
        Err(SizeMismatch {
            got: 100,
            expected: 81920,
            width: 320,
            height: 256
        })
    );
}

#[test]
fn resolutions_with_non_square_pixels_are_refused() {
    assert!(
        Renderer::new(
            FOV,
            ImageConfig {
                width: 320,
                height: 200
            },
            27.0
        )
        .is_err()
    );
    assert!(
        Renderer::new(
            FOV,
            ImageConfig {
                width: 320,
                height: 256
            },
            0.0
        )
        .is_err()
    );
}

#[test]
fn incremental_frames_equal_full_renders_over_an_episode() {
    for (w, h) in [(320, 256), (80, 64)] {
        let config = EnvConfig {
            image: ImageConfig {
                width: w,
                height: h,
            },
            ..EnvConfig::default()
        };
        let r = Renderer::for_config(&config).unwrap();
        let mut frame = Frame::<u8>::new(&r);
        let mut full = vec![0u8; r.pixels()];
        let mut env = Env::new(config.clone()).unwrap();
        let mut policy = UniformRandom::new(2);
        let mut action = [Action::ZERO];
        for seed in 0..3 {
            env.reset(seed);
            while env.outcome() == Outcome::Running && env.steps() < 300 {
                frame.update(&r, &env.observation().centres).unwrap();
                r.render(&env.observation().centres, &mut full).unwrap();
                assert_eq!(frame.pixels(), &full[..]);
                policy.act(&[env.observation()], &mut action);
                env.step(action[0]).unwrap();
            }
        }
    }
}
