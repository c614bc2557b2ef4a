//! Published snapshots: versions, the best by rolling return, pruning, and
//! restoring the store from its checkpointed state.

use burn::tensor::Device;
use tweezer_learner::snapshots::{Selector, Snapshots, SnapshotsError};
use tweezer_nets::{ARCHITECTURE, ActorConfig, EncoderConfig, SnapshotInfo, encode};

fn snapshot(version: u64) -> Vec<u8> {
    let actor = ActorConfig::new(EncoderConfig::new(16, 20)).init(&Device::flex());
    encode(
        &actor,
        &SnapshotInfo {
            architecture: ARCHITECTURE.into(),
            height: 16,
            width: 20,
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
