//! Snapshots round-trip and refuse what does not fit.

use burn::tensor::{Device, Distribution, Tensor};
use tweezer_nets::{
    ARCHITECTURE, ActorConfig, EncoderConfig, SnapshotError, SnapshotInfo, decode, encode,
    file_sha256, read_info,
};

fn info(h: usize, w: usize) -> SnapshotInfo {
    SnapshotInfo {
        architecture: ARCHITECTURE.into(),
        height: h,
        width: w,
        version: 7,
        training_step: 1234,
    }
}

#[test]
fn round_trip_gives_the_same_policy() {
    let device = Device::flex();
    let actor = ActorConfig::new(EncoderConfig::new(64, 80)).init(&device);
    let bytes = encode(&actor, &info(64, 80));
    assert_eq!(read_info(&bytes).unwrap(), info(64, 80));
    let (loaded, meta) = decode(&bytes, 64, 80, &device).unwrap();
    assert_eq!(meta.version, 7);
    let image = Tensor::<4>::random([3, 1, 64, 80], Distribution::Bernoulli(0.1), &device);
    let vector = Tensor::<2>::random([3, 2], Distribution::Uniform(-1.0, 1.0), &device);
    let a: Vec<f32> = actor
        .forward(image.clone(), vector.clone())
        .into_data()
        .try_to_vec()
        .unwrap();
    let b: Vec<f32> = loaded
        .forward(image, vector)
        .into_data()
        .try_to_vec()
        .unwrap();
    assert_eq!(a, b);
    assert_eq!(file_sha256(&bytes), file_sha256(&bytes.clone()));
    assert_eq!(file_sha256(&bytes).len(), 64);
}

#[test]
fn mismatches_and_corruption_are_refused() {
    let device = Device::flex();
    let actor = ActorConfig::new(EncoderConfig::new(64, 80)).init(&device);
    let bytes = encode(&actor, &info(64, 80));

    let err = decode(&bytes, 128, 160, &device).unwrap_err();
    assert!(matches!(err, SnapshotError::Resolution { .. }), "{err}");
    assert!(err.to_string().contains("80x64"), "{err}");

    let other = encode(
        &actor,
        &SnapshotInfo {
            architecture: "someone-elses-net".into(),
            ..info(64, 80)
        },
    );
    let err = decode(&other, 64, 80, &device).unwrap_err();
    assert!(matches!(err, SnapshotError::Architecture { .. }), "{err}");

    // Flip one byte of the last weight.
    let mut corrupt = bytes.clone();
    let last = corrupt.len() - 3;
    corrupt[last] ^= 0x40;
    let err = decode(&corrupt, 64, 80, &device).unwrap_err();
    assert!(matches!(err, SnapshotError::Checksum { .. }), "{err}");

    let truncated = &bytes[..bytes.len() / 2];
    assert!(matches!(
        decode(truncated, 64, 80, &device),
        Err(SnapshotError::Format(_))
    ));
    assert!(matches!(
        decode(b"definitely not a snapshot", 64, 80, &device),
        Err(SnapshotError::Format(_))
    ));
}

#[test]
fn files_name_every_tensor_by_its_module_path() {
    let device = Device::flex();
    let actor = ActorConfig::new(EncoderConfig::new(64, 80)).init(&device);
    let bytes = encode(&actor, &info(64, 80));
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let mut names = file.names();
    names.sort();
    for expected in [
        "encoder.conv1.weight",
        "encoder.norm1.running_mean",
        "encoder.norm3.running_var",
        "encoder.fc.weight",
        "head.fc1.bias",
        "head.out.weight",
    ] {
        assert!(names.contains(&expected), "{expected} not in {names:?}");
    }
    assert_eq!(
        file.tensor("encoder.fc.weight").unwrap().shape(),
        [64 * 8 * 10, 512]
    );
}
