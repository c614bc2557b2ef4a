//! Checkpoint files: written whole, verified on reading, the newest valid
//! one found past newer files that are cut short or altered, the oldest
//! pruned.

use tweezer_learner::checkpoint::{CheckpointHeader, Checkpoints, read};

fn header(updates: u64) -> CheckpointHeader {
    CheckpointHeader {
        updates,
        steps_inserted: updates * 2,
        sampler_state: 77,
        resolution: [16, 20],
        ..CheckpointHeader::default()
    }
}

#[test]
fn the_newest_whole_checkpoint_is_found_and_old_ones_pruned() {
    let dir = tempfile::tempdir().unwrap();
    let checkpoints = Checkpoints::open(dir.path(), 2).unwrap();
    let parts = |k: u8| vec![("a", vec![k; 1000]), ("b", vec![k + 1; 17])];
    for updates in [10, 20, 30] {
        checkpoints
            .write(header(updates), &parts(updates as u8))
            .unwrap();
    }
    let files = checkpoints.list().unwrap();
    assert_eq!(files.len(), 2, "kept the newest two: {files:?}");

    let loaded = read(&files[0]).unwrap();
    assert_eq!(loaded.header.updates, 30);
    assert_eq!(loaded.header.sampler_state, 77);
    assert_eq!(loaded.part("a").unwrap(), &[30u8; 1000][..]);
    assert_eq!(loaded.part("b").unwrap(), &[31u8; 17][..]);
    assert!(loaded.part("c").is_none());

    // Cut the newest short, and flip one byte of a copy named newer still.
    let bytes = std::fs::read(&files[0]).unwrap();
    std::fs::write(&files[0], &bytes[..bytes.len() - 100]).unwrap();
    let mut flipped = bytes.clone();
    flipped[200] ^= 1;
    std::fs::write(
        dir.path().join("ckpt-000000000099-000000000000.twz"),
        flipped,
    )
    .unwrap();

    let (found, skipped) = checkpoints.newest_valid().unwrap();
    assert_eq!(found.unwrap().header.updates, 20);
    assert_eq!(skipped.len(), 2);
    for error in skipped {
        assert!(error.to_string().contains("checksum mismatch"), "{error}");
    }
    assert!(read(&dir.path().join("missing.twz")).is_err());
}
