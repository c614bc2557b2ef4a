//! Checkpoint files: written whole, verified on reading, the newest valid
//! one found past newer files that are cut short or altered, the oldest
//! pruned.

use sha2::{Digest, Sha256};
use std::io;
use tweezer_learner::persistence::checkpoint::{CheckpointHeader, Checkpoints, read, read_header};
use tweezer_nets::Architecture;

fn header(updates: u64) -> CheckpointHeader {
    CheckpointHeader {
        updates,
        steps_inserted: updates * 2,
        sampler_state: 77,
        ..CheckpointHeader::new(Architecture::Paper {
            height: 16,
            width: 20,
        })
    }
}

#[test]
fn the_newest_whole_checkpoint_is_found_and_old_ones_pruned() {
    let dir = tempfile::tempdir().unwrap();
    let checkpoints = Checkpoints::open(dir.path(), 2).unwrap();
    let parts = |k: u8| vec![("a", vec![k; 1000]), ("b", vec![k + 1; 17])];
    for updates in [10, 20, 30] {
        checkpoints
            .write(header(updates), parts(updates as u8).into_iter().map(Ok))
            .unwrap();
    }
    let files = checkpoints.list().unwrap();
    assert_eq!(files.len(), 2, "kept the newest two: {files:?}");

    let loaded = read(&files[0]).unwrap();
    assert_eq!(loaded.header.updates, 30);
    assert_eq!(read_header(&files[0]).unwrap().updates, 30);
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

#[test]
fn a_part_that_cannot_be_made_fails_the_write_and_leaves_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let checkpoints = Checkpoints::open(dir.path(), 2).unwrap();
    let parts = [
        Ok(("a", vec![1u8; 100])),
        Err(io::Error::other(
            "the optimiser's record would not serialise",
        )),
    ];
    let error = checkpoints.write(header(10), parts).unwrap_err();
    assert!(error.to_string().contains("would not serialise"), "{error}");
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "{left:?}");
}

/// A checkpoint of the first format (the header before the parts) is
/// refused by name, never read as corrupt data, and resuming passes over it.
#[test]
fn checkpoints_of_the_first_format_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let mut header = header(40);
    header.parts = vec![("a".into(), 3), ("b".into(), 2)];
    let json = serde_json::to_vec(&header).unwrap();
    let mut bytes = b"TWZCKPT1".to_vec();
    bytes.extend((json.len() as u64).to_le_bytes());
    bytes.extend(&json);
    bytes.extend([1, 2, 3, 4, 5]);
    bytes.extend(Sha256::digest(&bytes));
    let path = dir.path().join("ckpt-000000000040-000000000080.twz");
    std::fs::write(&path, &bytes).unwrap();

    for error in [
        read(&path).unwrap_err().to_string(),
        read_header(&path).unwrap_err().to_string(),
    ] {
        assert!(
            error.contains("first format") && error.contains("start a new run"),
            "{error}"
        );
    }
    let (found, skipped) = Checkpoints::open(dir.path(), 2)
        .unwrap()
        .newest_valid()
        .unwrap();
    assert!(found.is_none());
    assert_eq!(skipped.len(), 1, "{skipped:?}");
}
