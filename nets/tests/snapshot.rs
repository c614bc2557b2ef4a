//! Snapshots of either architecture round-trip, carry their
//! hyper-parameters, and refuse what does not fit, saying what differs.

use burn::tensor::{Device, Distribution, Tensor};
use std::collections::HashMap;
use tweezer_gym::{EnvConfig, ImageConfig, Observation, Policy, Renderer};
use tweezer_nets::{
    ActionJoin, Architecture, Frame, NetworkPolicy, Networks, PaperNetworks, Pooling, SetNetworks,
    SetShape, SnapshotError, SnapshotInfo, SphereInputs, critic_search, decode, encode,
    encode_with_critics, file_sha256, read_info, without_critics,
};

fn env(width: u32, height: u32) -> EnvConfig {
    EnvConfig {
        image: ImageConfig { width, height },
        ..EnvConfig::default()
    }
}

fn paper(width: u32, height: u32) -> PaperNetworks {
    PaperNetworks::new(Renderer::for_config(&env(width, height)).unwrap())
}

fn set(shape: SetShape) -> SetNetworks {
    SetNetworks::new(shape, shape.fov_px)
}

fn info(architecture: Architecture) -> SnapshotInfo {
    SnapshotInfo {
        architecture,
        version: 7,
        training_step: 1234,
    }
}

fn snapshot<N: Networks>(networks: &N, device: &Device) -> (N::Actor, Vec<u8>) {
    let actor = networks.actor(device);
    let bytes = encode(&actor, &info(networks.architecture()));
    (actor, bytes)
}

/// The same file with metadata `key` set to `value` (checksum untouched).
fn with_metadata(bytes: &[u8], key: &str, value: &str) -> Vec<u8> {
    edit_metadata(bytes, |metadata| {
        metadata.insert(key.into(), value.into());
    })
}

fn without_metadata(bytes: &[u8], key: &str) -> Vec<u8> {
    edit_metadata(bytes, |metadata| {
        assert!(metadata.remove(key).is_some(), "{key} is recorded");
    })
}

fn edit_metadata(bytes: &[u8], edit: impl FnOnce(&mut HashMap<String, String>)) -> Vec<u8> {
    let file = safetensors::SafeTensors::deserialize(bytes).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes).unwrap();
    let mut metadata: HashMap<String, String> = header.metadata().clone().unwrap();
    edit(&mut metadata);
    safetensors::serialize(file.tensors(), Some(metadata)).unwrap()
}

fn observations() -> Vec<Observation> {
    vec![
        Observation {
            centres: vec![[600.0, 500.0], [700.0, 560.0], [10.0, 1000.0]],
            vector: [0.6, -0.8],
            ..Observation::default()
        },
        Observation {
            vector: [-0.1, 0.3],
            ..Observation::default()
        },
    ]
}

fn actions(policy: &mut NetworkPolicy) -> Vec<[f32; 2]> {
    let obs = observations();
    let refs: Vec<&Observation> = obs.iter().collect();
    let mut out = vec![tweezer_gym::Action::ZERO; refs.len()];
    policy.act(&refs, &mut out);
    out.iter().map(|a| a.components()).collect()
}

#[test]
fn a_paper_snapshot_round_trips_to_the_same_policy() {
    let device = Device::flex();
    let networks = paper(80, 64);
    let (actor, bytes) = snapshot(&networks, &device);
    let expected = info(Architecture::Paper {
        height: 64,
        width: 80,
    });
    assert_eq!(read_info(&bytes).unwrap(), expected);
    let decoded = decode(&bytes, &networks, &device).unwrap();
    assert_eq!(decoded.info, expected);
    assert!(decoded.critics.is_none());
    let loaded = decoded.actor;
    let image = Tensor::<4>::random([3, 1, 64, 80], Distribution::Bernoulli(0.1), &device);
    let vector = Tensor::<2>::random([3, 2], Distribution::Uniform(-1.0, 1.0), &device);
    let out = |a: &tweezer_nets::Actor| -> Vec<f32> {
        a.forward(image.clone(), vector.clone())
            .into_data()
            .try_to_vec()
            .unwrap()
    };
    assert_eq!(out(&actor), out(&loaded));
    assert_eq!(file_sha256(&bytes).len(), 64);
}

#[test]
fn a_set_snapshot_round_trips_with_its_hyper_parameters() {
    let device = Device::flex();
    let shape = SetShape {
        sphere_hidden: 24,
        head_hidden: 40,
        pooling: Pooling::Max,
        max_spheres: 9,
        fov_px: [1280, 1024],
        inputs: SphereInputs::Motion,
        action_join: ActionJoin::PerSphere,
        critic_layer_norm: true,
        frame: Frame::Goal,
        motion_unit_px: 15.0,
    };
    let networks = set(shape);
    let (actor, bytes) = snapshot(&networks, &device);
    assert_eq!(read_info(&bytes).unwrap(), info(Architecture::Set(shape)));
    let mut direct = NetworkPolicy::new(networks.clone(), actor, device.clone());
    // Loading needs nothing but the file and the environment it acts in.
    let (mut loaded, meta) = NetworkPolicy::from_snapshot(&bytes, &env(7, 5), &device).unwrap();
    assert_eq!(meta.architecture, Architecture::Set(shape));
    assert_eq!(actions(&mut direct), actions(&mut loaded));
}

/// Each observation's smaller critic value of `action`.
fn value(
    networks: &SetNetworks,
    critics: &[tweezer_nets::SetCritic; 2],
    observations: &[&Observation],
    action: &[[f32; 2]],
    device: &Device,
) -> Vec<f32> {
    let n = observations.len();
    let input = networks.input(
        observations.iter().map(|o| tweezer_nets::Scene::of(o)),
        device,
    );
    let vectors: Vec<f32> = observations.iter().flat_map(|o| o.vector).collect();
    let tensor =
        |v: Vec<f32>| Tensor::<2>::from_data(burn::tensor::TensorData::new(v, [n, 2]), device);
    let (vector, action) = (
        tensor(vectors),
        tensor(action.iter().flatten().copied().collect()),
    );
    let [q1, q2] = critics.each_ref().map(|c| {
        let q = SetNetworks::value(
            c,
            SetNetworks::features(c, input.clone()),
            vector.clone(),
            action.clone(),
        );
        q.into_data().try_to_vec::<f32>().unwrap()
    });
    q1.iter().zip(&q2).map(|(a, b)| a.min(*b)).collect()
}

#[test]
fn a_snapshot_with_the_critics_lets_them_check_the_actor() {
    let device = Device::flex();
    let networks = set(SetShape::new([1280, 1024]));
    let actor = networks.actor(&device);
    let critics = [networks.critic(&device), networks.critic(&device)];
    // A scale small enough that untrained critics clear the margin.
    let scale = 1e-6;
    let bytes = encode_with_critics(&actor, &critics, scale, &info(networks.architecture()));
    let decoded = decode(&bytes, &networks, &device).unwrap();
    let loaded = decoded.critics.expect("the critics travel with the actor");
    assert_eq!(decoded.critic_reward_scale, Some(scale));

    let obs = observations();
    let refs: Vec<&Observation> = obs.iter().collect();
    let mut alone = NetworkPolicy::new(networks.clone(), actor, device.clone());
    let own = actions(&mut alone);
    // The critics come back as they went.
    for k in 0..2 {
        let q = |c: &[tweezer_nets::SetCritic; 2]| {
            value(
                &networks,
                &[c[k].clone(), c[k].clone()],
                &refs,
                &own,
                &device,
            )
        };
        assert_eq!(q(&critics), q(&loaded));
    }

    let (mut checked, _) =
        NetworkPolicy::from_snapshot(&bytes, &EnvConfig::default(), &device).unwrap();
    assert!(checked.has_critics());
    let chosen = actions(&mut checked);
    let margin = critic_search::margin(Some(scale));
    assert!(margin > 0.0);
    assert_eq!(
        chosen,
        critic_search::choose(&networks, &critics, margin, &refs, &own, &device)
    );
    // The choice is among the candidates around the actor's action, and
    // the critics value it at least as highly as the actor's own.
    for (i, action) in chosen.iter().enumerate() {
        assert!(critic_search::candidates(own[i]).contains(action));
    }
    let (mine, theirs) = (
        value(&networks, &critics, &refs, &own, &device),
        value(&networks, &critics, &refs, &chosen, &device),
    );
    assert!(
        mine.iter().zip(&theirs).all(|(m, t)| t >= m),
        "{mine:?} {theirs:?}"
    );
    // Untrained critics disagree with an untrained actor somewhere.
    assert_ne!(chosen, own);

    // A candidate replaces the actor's action only where the critics
    // value it more than the margin above it.
    let choose =
        |margin: f32| critic_search::choose(&networks, &critics, margin, &refs, &own, &device);
    let free = choose(0.0);
    let gains: Vec<f32> = value(&networks, &critics, &refs, &free, &device)
        .iter()
        .zip(&mine)
        .map(|(f, m)| f - m)
        .collect();
    let (i, gain) = gains
        .iter()
        .copied()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap();
    assert!(gain > 0.0 && free[i] != own[i], "{gains:?}");
    assert_eq!(choose(0.5 * gain)[i], free[i]);
    assert_eq!(choose(gain), own, "nothing beats the actor by the margin");

    // Without them, the actor acts alone, as it did before loading.
    let alone = checked.actor_alone();
    assert!(!alone.has_critics());
    assert_eq!(actions(&mut { alone }), own);

    // A scale the critics' values cannot be in is refused, by name.
    for bad in ["-0.1", "0", "NaN", "inf", "a tenth"] {
        let err = decode(
            &with_metadata(&bytes, "critic_reward_scale", bad),
            &networks,
            &device,
        )
        .unwrap_err();
        assert_eq!(
            err,
            SnapshotError::Metadata {
                field: "critic_reward_scale"
            },
            "{bad}"
        );
    }
    // A snapshot from before the scale was recorded is checked without a
    // margin, as it was measured.
    assert_eq!(critic_search::margin(None), 0.0);

    // Stripped of its critics, the file is its actor alone, verified.
    let stripped = without_critics(&bytes).unwrap();
    let (mut stripped, meta) =
        NetworkPolicy::from_snapshot(&stripped, &EnvConfig::default(), &device).unwrap();
    assert!(!stripped.has_critics());
    assert_eq!(meta, info(networks.architecture()));
    assert_eq!(actions(&mut stripped), own);

    // A critic's weight altered is refused like the actor's.
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let weight = file.tensor("critic2.head.out.weight").unwrap().data();
    let at = weight.as_ptr() as usize - bytes.as_ptr() as usize;
    let mut corrupt = bytes.clone();
    corrupt[at + 1] ^= 0x40;
    let err = decode(&corrupt, &networks, &device).unwrap_err();
    assert!(matches!(err, SnapshotError::Checksum { .. }), "{err}");
    let err = without_critics(&corrupt).unwrap_err();
    assert!(matches!(err, SnapshotError::Checksum { .. }), "{err}");
}

#[test]
fn mismatched_architectures_are_refused_naming_what_differs() {
    let device = Device::flex();
    let (_, cnn) = snapshot(&paper(80, 64), &device);
    let err = decode(&cnn, &paper(160, 128), &device).unwrap_err();
    assert!(matches!(err, SnapshotError::Mismatch { .. }), "{err}");
    let text = err.to_string();
    assert!(
        text.contains("height 64 vs 128") && text.contains("width 80 vs 160"),
        "{text}"
    );
    // An actor rendering another resolution refuses the file.
    let err = NetworkPolicy::from_snapshot(&cnn, &env(40, 32), &device).unwrap_err();
    assert!(err.to_string().contains("width 80 vs 40"), "{err}");

    let shape = SetShape::new([1280, 1024]);
    let (_, sets) = snapshot(&set(shape), &device);
    let wider = SetShape {
        sphere_hidden: 128,
        pooling: Pooling::Mean,
        ..shape
    };
    let err = decode(&sets, &set(wider), &device).unwrap_err().to_string();
    assert!(
        err.contains("sphere_hidden 64 vs 128") && err.contains("pooling max_mean vs mean"),
        "{err}"
    );
    let differences = err.rsplit("): ").next().unwrap();
    assert_eq!(
        differences,
        "sphere_hidden 64 vs 128, pooling max_mean vs mean"
    );
    // A network that reads motion refuses one trained on positions alone.
    let moving = SetShape {
        inputs: SphereInputs::Motion,
        ..shape
    };
    let err = decode(&sets, &set(moving), &device)
        .unwrap_err()
        .to_string();
    assert!(err.ends_with("inputs positions vs motion"), "{err}");
    // One acting in the goal frame refuses one trained in the stage's.
    let turned = SetShape {
        frame: Frame::Goal,
        ..shape
    };
    let err = decode(&sets, &set(turned), &device)
        .unwrap_err()
        .to_string();
    assert!(err.ends_with("frame stage vs goal"), "{err}");
    // One trained among faster spheres reads their motion in another unit.
    let fast = SetShape {
        motion_unit_px: 15.0,
        ..shape
    };
    let err = decode(&sets, &set(fast), &device).unwrap_err().to_string();
    assert!(err.ends_with("motion_unit_px 2 vs 15"), "{err}");
    let err = decode(&sets, &paper(80, 64), &device)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("tweezer-set-actor-v1 vs tweezer-paper-actor-v1"),
        "{err}"
    );
}

#[test]
fn bad_metadata_and_corruption_are_refused() {
    let device = Device::flex();
    let networks = set(SetShape::new([1280, 1024]));
    let (_, bytes) = snapshot(&networks, &device);
    let load = |b: &[u8]| NetworkPolicy::from_snapshot(b, &EnvConfig::default(), &device);

    let other = with_metadata(&bytes, "architecture", "someone-elses-net");
    let err = load(&other).unwrap_err().to_string();
    assert!(
        err.contains("unknown architecture `someone-elses-net`"),
        "{err}"
    );
    // A hostile size is refused before anything is allocated.
    let huge = with_metadata(&bytes, "sphere_hidden", "4000000000");
    let err = load(&huge).unwrap_err().to_string();
    assert!(err.contains("sphere_hidden"), "{err}");
    let err = load(&with_metadata(&bytes, "pooling", "attention"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("`pooling`"), "{err}");
    for unit in ["0", "-2", "NaN", "fast"] {
        let err = load(&with_metadata(&bytes, "motion_unit_px", unit))
            .unwrap_err()
            .to_string();
        assert!(err.contains("`motion_unit_px`"), "{unit}: {err}");
    }
    // A file from before the unit was recorded reads the spec's speed.
    let (_, older) = load(&without_metadata(&bytes, "motion_unit_px")).unwrap();
    assert_eq!(older.architecture, networks.architecture());
    // Images the paper network's convolutions cannot take.
    let (_, paper_bytes) = snapshot(&paper(80, 64), &device);
    let tiny = with_metadata(&with_metadata(&paper_bytes, "height", "4"), "width", "5");
    let err = load(&tiny).unwrap_err().to_string();
    assert!(err.contains("too small for the paper network"), "{err}");
    // Metadata that agrees with itself but not with the weights.
    let err = load(&with_metadata(&bytes, "head_hidden", "32"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("shape"), "{err}");

    // Flip one byte of the last weight.
    let mut corrupt = bytes.clone();
    let last = corrupt.len() - 3;
    corrupt[last] ^= 0x40;
    let err = decode(&corrupt, &networks, &device).unwrap_err();
    assert!(matches!(err, SnapshotError::Checksum { .. }), "{err}");

    let truncated = &bytes[..bytes.len() / 2];
    assert!(matches!(
        decode(truncated, &networks, &device),
        Err(SnapshotError::Format(_))
    ));
    assert!(matches!(
        decode(b"definitely not a snapshot", &networks, &device),
        Err(SnapshotError::Format(_))
    ));
}

#[test]
fn files_name_every_tensor_by_its_module_path() {
    let device = Device::flex();
    let (_, bytes) = snapshot(&paper(80, 64), &device);
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let names = file.names();
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
    let (_, bytes) = snapshot(&set(SetShape::new([1280, 1024])), &device);
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let mut names = file.names();
    names.sort();
    assert_eq!(
        names,
        [
            "encoder.fc1.bias",
            "encoder.fc1.weight",
            "encoder.fc2.bias",
            "encoder.fc2.weight",
            "head.fc1.bias",
            "head.fc1.weight",
            "head.fc2.bias",
            "head.fc2.weight",
            "head.out.bias",
            "head.out.weight",
        ]
    );
    assert_eq!(file.tensor("head.fc1.weight").unwrap().shape(), [130, 64]);
}
