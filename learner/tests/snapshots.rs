//! Published snapshots: versions, the best by rolling return, pruning, and
//! restoring the store from its checkpointed state.

use burn::tensor::Device;
use tweezer_learner::persistence::snapshots::{Selector, Snapshots, SnapshotsError};
use tweezer_nets::{ActorConfig, Architecture, EncoderConfig, SnapshotInfo, encode};

fn snapshot(version: u64) -> Vec<u8> {
    let actor = ActorConfig::new(EncoderConfig::new(16, 20)).init(&Device::flex());
    encode(
        &actor,
        &SnapshotInfo {
            architecture: Architecture::Paper {
                height: 16,
                width: 20,
            },
            version,
            training_step: version * 100,
        },
    )
}

#[test]
fn the_best_is_kept_while_older_versions_are_pruned() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Snapshots::create(dir.path(), 2).unwrap();
    assert!(matches!(
        store.get(Selector::Latest),
        Err(SnapshotsError::NotFound(_))
    ));
    let returns = [None, Some(5.0), Some(9.0), Some(3.0), Some(4.0), Some(8.0)];
    for (i, r) in returns.into_iter().enumerate() {
        let version = store.next_version();
        assert_eq!(version, i as u64 + 1);
        let (published, best) = store.publish(snapshot(version), r).unwrap();
        assert_eq!(published.info.version, version);
        assert_eq!(best, matches!(version, 2 | 3));
    }
    assert_eq!(store.latest_version(), 6);
    assert_eq!(store.best_version(), 3);
    assert_eq!(store.get(Selector::Best).unwrap().info.version, 3);
    assert_eq!(store.get(Selector::Version(5)).unwrap().info.version, 5);
    assert!(matches!(
        store.get(Selector::Version(2)),
        Err(SnapshotsError::NotFound(_))
    ));
    let mut files: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(
        files,
        [
            "best.safetensors",
            "v000003.safetensors",
            "v000005.safetensors",
            "v000006.safetensors"
        ]
    );

    assert_eq!(
        std::fs::read(dir.path().join("best.safetensors")).unwrap(),
        std::fs::read(store.path(3)).unwrap()
    );

    let state = store.state();
    let restored = Snapshots::restore(dir.path(), 2, &state).unwrap();
    assert_eq!(restored.latest_version(), 6);
    assert_eq!(restored.best_version(), 3);
    assert_eq!(restored.next_version(), 7);
    assert_eq!(
        restored.get(Selector::Latest).unwrap().sha256,
        store.get(Selector::Latest).unwrap().sha256
    );
}

/// The learner's own sequence: a checkpoint of the store, then more
/// snapshots than it keeps. The checkpoint's snapshots must survive, so
/// that it can be resumed after a SIGKILL; once no kept checkpoint needs
/// them they are pruned as usual. A checkpoint whose snapshots are gone is
/// passed over for an older one.
#[test]
fn snapshots_a_kept_checkpoint_needs_are_never_pruned() {
    use tweezer_learner::persistence::checkpoint::{CheckpointHeader, Checkpoints};
    let dir = tempfile::tempdir().unwrap();
    let snapshots_dir = dir.path().join("snapshots");
    let checkpoints = Checkpoints::open(&dir.path().join("checkpoints"), 3).unwrap();
    let mut store = Snapshots::create(&snapshots_dir, 2).unwrap();
    let publish = |store: &mut Snapshots| {
        let version = store.next_version();
        store.publish(snapshot(version), None).unwrap();
    };
    let checkpoint = |store: &mut Snapshots, updates: u64| {
        let header = CheckpointHeader {
            updates,
            snapshots: store.state(),
            ..CheckpointHeader::new(tweezer_nets::Architecture::Paper {
                height: 16,
                width: 20,
            })
        };
        checkpoints.write::<Vec<u8>>(header, []).unwrap();
        store.pin(checkpoints.needed_snapshots());
    };
    publish(&mut store);
    publish(&mut store);
    checkpoint(&mut store, 1);
    let at_checkpoint = store.state();
    assert_eq!(at_checkpoint.latest, Some(2));
    for _ in 0..4 {
        publish(&mut store);
    }
    // Versions 3 and 4 went; 2 stays for the checkpoint, 5 and 6 are kept.
    let on_disk = |v: u64| snapshots_dir.join(format!("v{v:06}.safetensors")).exists();
    assert_eq!(
        (1..=6).map(on_disk).collect::<Vec<_>>(),
        [false, true, false, false, true, true]
    );
    let restored = Snapshots::restore(&snapshots_dir, 2, &at_checkpoint).unwrap();
    assert_eq!(restored.latest_version(), 2);

    // Once three newer checkpoints are kept, version 2 is pruned as usual.
    for updates in 2..=4 {
        checkpoint(&mut store, updates);
    }
    publish(&mut store);
    assert!(!on_disk(2));

    // A checkpoint whose snapshots are gone is passed over for an older one.
    std::fs::remove_file(snapshots_dir.join("v000007.safetensors")).unwrap();
    checkpoint(&mut store, 5);
    let (usable, skipped) = checkpoints
        .newest_usable(|loaded| {
            Snapshots::restore(&snapshots_dir, 2, &loaded.header.snapshots)
                .map(drop)
                .map_err(|e| e.to_string())
        })
        .unwrap();
    assert_eq!(usable.unwrap().0.header.updates, 4);
    assert_eq!(skipped.len(), 1);
    assert!(skipped[0].to_string().contains("v000007"), "{}", skipped[0]);
}

#[test]
fn a_restored_store_never_gives_out_a_version_published_after_its_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Snapshots::create(dir.path(), 10).unwrap();
    for version in 1..=2 {
        store.publish(snapshot(version), None).unwrap();
    }
    // The checkpoint is taken at v2; v3 and v4 follow, then a crash.
    let state = store.state();
    for version in 3..=4 {
        store.publish(snapshot(version), None).unwrap();
    }
    let served = std::fs::read(store.path(4)).unwrap();
    drop(store);

    let mut store = Snapshots::restore(dir.path(), 10, &state).unwrap();
    assert_eq!(store.latest_version(), 2);
    assert_eq!(store.next_version(), 5, "3 and 4 already name weights");
    assert_eq!(store.get(Selector::Version(4)).unwrap().bytes, served);
    store.publish(snapshot(5), None).unwrap();
    assert_eq!(std::fs::read(store.path(4)).unwrap(), served);
    assert_eq!(store.state().kept, [1, 2, 3, 4, 5]);
    // A fresh store in a directory that holds snapshots numbers above them.
    assert_eq!(Snapshots::create(dir.path(), 10).unwrap().next_version(), 6);
}
