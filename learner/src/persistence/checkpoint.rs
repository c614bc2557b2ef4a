//! Checkpoints of the whole learner: networks, targets, optimiser states,
//! counters, sampler state, episode window, snapshot bookkeeping, actors'
//! sequence numbers, and the replay when configured.
//!
//! One file per checkpoint, `ckpt-<updates>-<steps>.twz`:
//!
//! ```text
//! "TWZCKPT2" | parts... | header (JSON) | header length (u64 LE) | SHA-256 of all before
//! ```
//!
//! The header, which names the parts and their lengths, comes last so that
//! each part is written as soon as it is serialised and dropped before the
//! next: a checkpoint never holds the whole state twice in memory.
//!
//! Files are written atomically ([`crate::persistence::durable_write::write_atomic`]);
//! a file that is truncated or corrupt fails its checksum and resuming
//! falls back to the previous one.

use crate::ingest::episodes::Episodes;
use crate::persistence::durable_write::{sync_dir, write_atomic};
use crate::persistence::snapshots::SnapshotsState;
use crate::replay::Source;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, BTreeSet};
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::ops::{Deref, Range};
use std::path::{Path, PathBuf};
use tweezer_nets::Architecture;

const MAGIC: &[u8; 8] = b"TWZCKPT2";
const EXTENSION: &str = "twz";

/// The learner's state besides the tensors.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CheckpointHeader {
    /// TD3 updates made.
    pub updates: u64,
    /// Transitions inserted since the run began.
    pub steps_inserted: u64,
    /// Replay sampler state ([`tweezer_gym::SplitMix64::state`]).
    pub sampler_state: u64,
    /// The networks trained.
    pub architecture: Architecture,
    /// Finished episodes and the rolling window.
    pub episodes: Episodes,
    /// Published snapshots.
    pub snapshots: SnapshotsState,
    /// Each actor session's last stored batch.
    pub sessions: Vec<SessionState>,
    /// Names and lengths of the binary parts, in file order.
    pub parts: Vec<(String, u64)>,
}

impl CheckpointHeader {
    /// The header of a run of `architecture` that has learned nothing yet:
    /// no update, no step, no episode, no snapshot, no part.
    pub fn new(architecture: Architecture) -> Self {
        Self {
            updates: 0,
            steps_inserted: 0,
            sampler_state: 0,
            architecture,
            episodes: Episodes::default(),
            snapshots: SnapshotsState::default(),
            sessions: Vec::new(),
            parts: Vec::new(),
        }
    }
}

/// What a checkpoint keeps of an actor session: enough to recognise its
/// resent batches after a restart.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SessionState {
    /// The actor's id.
    pub actor: String,
    /// Its session.
    pub session: u64,
    /// Its last stored batch.
    pub sequence: u64,
    /// The replay source its steps are stored under.
    pub source: Source,
}

/// A checkpoint that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// Reading or writing failed.
    #[error("checkpoint {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: io::Error,
    },
    /// The file is not a whole, valid checkpoint.
    #[error("checkpoint {path} is unusable: {reason}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// A checkpoint read back and verified.
#[derive(Debug)]
pub struct Loaded {
    /// Its file.
    pub path: PathBuf,
    /// The state besides the tensors.
    pub header: CheckpointHeader,
    bytes: Vec<u8>,
    parts: BTreeMap<String, Range<usize>>,
}

impl Loaded {
    /// The binary part `name`.
    pub fn part(&self, name: &str) -> Option<&[u8]> {
        self.parts.get(name).map(|r| &self.bytes[r.clone()])
    }
}

/// What a search for a usable checkpoint found: the newest one with what
/// the check made of it, if any, and why newer ones were skipped.
pub type Search<T> = (Option<(Loaded, T)>, Vec<CheckpointError>);

/// The checkpoint directory of a run.
#[derive(Clone, Debug)]
pub struct Checkpoints {
    dir: PathBuf,
    keep: usize,
}

impl Checkpoints {
    /// Checkpoints in `dir` (created if missing), keeping the newest `keep`.
    pub fn open(dir: &Path, keep: usize) -> Result<Self, CheckpointError> {
        std::fs::create_dir_all(dir).map_err(|source| CheckpointError::Io {
            path: dir.into(),
            source,
        })?;
        Ok(Self {
            dir: dir.into(),
            keep: keep.max(1),
        })
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Writes a checkpoint of `header` and `parts`, each part written as
    /// it comes and dropped before the next is made, then deletes the
    /// oldest beyond `keep`. Returns its path. An error from `parts` fails
    /// the write and leaves no file.
    pub fn write<'a, P: Deref<Target = [u8]>>(
        &self,
        mut header: CheckpointHeader,
        parts: impl IntoIterator<Item = io::Result<(&'a str, P)>>,
    ) -> Result<PathBuf, CheckpointError> {
        let path = self.dir.join(format!(
            "ckpt-{:012}-{:012}.{EXTENSION}",
            header.updates, header.steps_inserted
        ));
        let io_error = |source| CheckpointError::Io {
            path: path.clone(),
            source,
        };
        write_atomic(&path, |w: &mut dyn Write| {
            let mut hashing = Hashing {
                inner: w,
                hash: Sha256::new(),
            };
            hashing.write_all(MAGIC)?;
            header.parts.clear();
            for part in parts {
                let (name, bytes) = part?;
                hashing.write_all(&bytes)?;
                header.parts.push((name.to_string(), bytes.len() as u64));
            }
            let json = serde_json::to_vec(&header).map_err(io::Error::other)?;
            hashing.write_all(&json)?;
            hashing.write_all(&(json.len() as u64).to_le_bytes())?;
            let digest = hashing.hash.finalize();
            hashing.inner.write_all(&digest)
        })
        .map_err(io_error)?;
        self.prune(&path);
        Ok(path)
    }

    /// Checkpoint files, newest first.
    pub fn list(&self) -> Result<Vec<PathBuf>, CheckpointError> {
        let entries = std::fs::read_dir(&self.dir).map_err(|source| CheckpointError::Io {
            path: self.dir.clone(),
            source,
        })?;
        let mut files: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.extension().is_some_and(|e| e == EXTENSION)
                    && p.file_name()
                        .is_some_and(|n| n.to_string_lossy().starts_with("ckpt-"))
            })
            .collect();
        files.sort();
        files.reverse();
        Ok(files)
    }

    /// The newest checkpoint that reads back whole, with the reasons the
    /// newer ones were skipped; `None` when there is no usable one.
    pub fn newest_valid(&self) -> Result<(Option<Loaded>, Vec<CheckpointError>), CheckpointError> {
        let (usable, skipped) = self.newest_usable(|_| Ok(()))?;
        Ok((usable.map(|(loaded, ())| loaded), skipped))
    }

    /// The newest checkpoint that reads back whole and that `usable`
    /// accepts (everything else it needs is there), with what `usable`
    /// made of it and the reasons the newer ones were skipped; `None` when
    /// there is no usable one.
    pub fn newest_usable<T>(
        &self,
        mut usable: impl FnMut(&Loaded) -> Result<T, String>,
    ) -> Result<Search<T>, CheckpointError> {
        let mut skipped = Vec::new();
        for path in self.list()? {
            match read(&path) {
                Ok(loaded) => match usable(&loaded) {
                    Ok(made) => return Ok((Some((loaded, made)), skipped)),
                    Err(reason) => skipped.push(CheckpointError::Corrupt { path, reason }),
                },
                Err(e) => skipped.push(e),
            }
        }
        Ok((None, skipped))
    }

    /// The snapshot versions the kept checkpoints need on disk (each one's
    /// latest and best): pruning must spare them. Checkpoints whose header
    /// cannot be read need nothing.
    pub fn needed_snapshots(&self) -> BTreeSet<u64> {
        let files = self.list().unwrap_or_default();
        files
            .iter()
            .filter_map(|path| read_header(path).ok())
            .flat_map(|header| header.snapshots.needed())
            .collect()
    }

    fn prune(&self, newest: &Path) {
        let Ok(files) = self.list() else { return };
        let mut removed = false;
        for old in files.iter().skip(self.keep) {
            if old != newest {
                removed |= std::fs::remove_file(old).is_ok();
            }
        }
        if removed {
            let _ = sync_dir(&self.dir);
        }
    }
}

/// The longest header [`read_header`] reads.
const MAX_HEADER: u64 = 64 << 20;

/// Reads one checkpoint's header alone, without verifying the file (a
/// quick look; [`read`] verifies).
pub fn read_header(path: &Path) -> Result<CheckpointHeader, CheckpointError> {
    let corrupt = |reason: String| CheckpointError::Corrupt {
        path: path.into(),
        reason,
    };
    let io_error = |source| CheckpointError::Io {
        path: path.into(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io_error)?;
    let size = file.metadata().map_err(io_error)?.len();
    let mut magic = [0u8; 8];
    file.read_exact(&mut magic).map_err(io_error)?;
    let read_length = |file: &mut std::fs::File| {
        let mut length = [0u8; 8];
        file.read_exact(&mut length).map_err(io_error)?;
        let len = u64::from_le_bytes(length);
        if len > MAX_HEADER || len > size {
            return Err(corrupt(format!("a header of {len} bytes")));
        }
        Ok(len)
    };
    check_magic(&magic).map_err(corrupt)?;
    // The length sits before the digest at the end, the header before it.
    let length_at = size
        .checked_sub(32 + 8)
        .filter(|at| *at >= 8)
        .ok_or_else(|| corrupt("cut short".into()))?;
    file.seek(SeekFrom::Start(length_at)).map_err(io_error)?;
    let len = read_length(&mut file)?;
    let header_at = length_at
        .checked_sub(len)
        .filter(|at| *at >= 8)
        .ok_or_else(|| corrupt("header length beyond the file".into()))?;
    file.seek(SeekFrom::Start(header_at)).map_err(io_error)?;
    let mut json = vec![0; len as usize];
    file.read_exact(&mut json).map_err(io_error)?;
    serde_json::from_slice(&json).map_err(|e| corrupt(format!("header: {e}")))
}

/// Reads and verifies one checkpoint file.
pub fn read(path: &Path) -> Result<Loaded, CheckpointError> {
    let corrupt = |reason: String| CheckpointError::Corrupt {
        path: path.into(),
        reason,
    };
    let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io {
        path: path.into(),
        source,
    })?;
    check_magic(bytes.get(..MAGIC.len()).unwrap_or(&bytes)).map_err(corrupt)?;
    if bytes.len() < MAGIC.len() + 8 + 32 {
        return Err(corrupt("cut short".into()));
    }
    let (body, digest) = bytes.split_at(bytes.len() - 32);
    if Sha256::digest(body).as_slice() != digest {
        return Err(corrupt(
            "checksum mismatch: the file was cut short or altered".into(),
        ));
    }
    let length = |at: usize| u64::from_le_bytes(body[at..at + 8].try_into().expect("8 bytes"));
    // The parts lie between the magic and the header.
    let end = body.len() - 8;
    let start = end
        .checked_sub(length(end) as usize)
        .filter(|start| *start >= 8)
        .ok_or_else(|| corrupt("header length beyond the file".into()))?;
    let (json, parts_end) = (&body[start..end], start);
    let header: CheckpointHeader =
        serde_json::from_slice(json).map_err(|e| corrupt(format!("header: {e}")))?;
    let mut parts = BTreeMap::new();
    let mut at = MAGIC.len();
    for (name, len) in &header.parts {
        let end = at.saturating_add(*len as usize);
        if end > parts_end {
            return Err(corrupt(format!("part `{name}` runs past the end")));
        }
        parts.insert(name.clone(), at..end);
        at = end;
    }
    if at != parts_end {
        return Err(corrupt("bytes after the last part".into()));
    }
    Ok(Loaded {
        path: path.into(),
        header,
        bytes,
        parts,
    })
}

/// Refuses a file that does not start as a checkpoint of this format.
fn check_magic(magic: &[u8]) -> Result<(), String> {
    match magic {
        m if m == MAGIC => Ok(()),
        b"TWZCKPT1" => Err(
            "a checkpoint of the first format, which this learner does not read: start a new run"
                .into(),
        ),
        _ => Err("not a checkpoint file".into()),
    }
}

/// A writer that hashes what passes through it.
struct Hashing<'a> {
    inner: &'a mut dyn Write,
    hash: Sha256,
}

impl Write for Hashing<'_> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hash.update(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}
