//! Published policy snapshots: every `every_updates` updates the actor's
//! weights become a new version, written to the run directory and kept in
//! memory for serving. `best` is the snapshot published at the highest
//! rolling return (the model the paper took to the microscope); it is kept on
//! disk, also as `best.safetensors`, whatever the pruning of older versions.

use crate::persistence::durable_write::{link_atomic, write_bytes_atomic};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeSet, VecDeque};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tweezer_nets::{SnapshotInfo, file_sha256, read_info};

/// The best snapshot's second name in the snapshots directory.
pub const BEST_FILE: &str = "best.safetensors";

/// A snapshot ready to serve.
#[derive(Debug)]
pub struct Published {
    /// Its metadata.
    pub info: SnapshotInfo,
    /// The safetensors file.
    pub bytes: Vec<u8>,
    /// SHA-256 of `bytes`, lowercase hex.
    pub sha256: String,
}

impl Published {
    fn new(bytes: Vec<u8>) -> Result<Self, SnapshotsError> {
        let info = read_info(&bytes).map_err(|e| SnapshotsError::Corrupt(e.to_string()))?;
        Ok(Self {
            sha256: file_sha256(&bytes),
            info,
            bytes,
        })
    }
}

/// Which snapshot a client asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Selector {
    /// The newest.
    Latest,
    /// The one published at the highest rolling return.
    Best,
    /// An exact version.
    Version(u64),
}

/// A snapshot that cannot be had.
#[derive(Debug, thiserror::Error)]
pub enum SnapshotsError {
    /// None published yet, or that version is no longer kept.
    #[error("{0}")]
    NotFound(String),
    /// A file could not be written or read.
    #[error("snapshot file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: io::Error,
    },
    /// A kept file is not a snapshot.
    #[error("snapshot file is corrupt: {0}")]
    Corrupt(String),
}

/// What a checkpoint keeps of the store: enough to find the files again.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SnapshotsState {
    /// Versions on disk, oldest first.
    pub kept: Vec<u64>,
    /// The newest version.
    pub latest: Option<u64>,
    /// The best version and the rolling return it was published at.
    pub best: Option<(u64, f64)>,
}

impl SnapshotsState {
    /// The versions a learner restored from this state reads back: its
    /// latest and its best.
    pub fn needed(&self) -> impl Iterator<Item = u64> + use<> {
        self.latest.into_iter().chain(self.best.map(|(v, _)| v))
    }
}

/// The run's snapshots.
#[derive(Debug)]
pub struct Snapshots {
    dir: PathBuf,
    keep: usize,
    kept: VecDeque<u64>,
    /// The highest version written or found on disk: a version number
    /// names one set of weights for ever, so numbering goes on above it.
    highest: u64,
    latest: Option<Arc<Published>>,
    best: Option<(Arc<Published>, f64)>,
    /// Versions that kept checkpoints need: never pruned.
    pinned: BTreeSet<u64>,
}

impl Snapshots {
    /// An empty store writing into `dir` (created if missing), keeping the
    /// newest `keep` files besides the best.
    pub fn create(dir: &Path, keep: usize) -> Result<Self, SnapshotsError> {
        std::fs::create_dir_all(dir).map_err(|source| SnapshotsError::Io {
            path: dir.into(),
            source,
        })?;
        let mut store = Self {
            dir: dir.into(),
            keep,
            kept: VecDeque::new(),
            highest: 0,
            latest: None,
            best: None,
            pinned: BTreeSet::new(),
        };
        store.highest = store.on_disk()?.last().copied().unwrap_or(0);
        Ok(store)
    }

    /// The store as a checkpoint left it, its latest and best files read
    /// back from `dir`. Versions published after that checkpoint (before
    /// a crash) stay served and are pruned in their turn: clients may
    /// hold them, and their numbers are not given out again.
    pub fn restore(
        dir: &Path,
        keep: usize,
        state: &SnapshotsState,
    ) -> Result<Self, SnapshotsError> {
        let mut store = Self::create(dir, keep)?;
        store.kept = state.kept.iter().copied().collect();
        let latest = state.latest.unwrap_or(0);
        let later = store.on_disk()?.into_iter().filter(|&v| v > latest);
        store.kept.extend(later);
        store.latest = state.latest.map(|v| store.read(v)).transpose()?;
        store.best = state
            .best
            .map(|(v, r)| store.read(v).map(|p| (p, r)))
            .transpose()?;
        Ok(store)
    }

    /// The state a checkpoint needs.
    pub fn state(&self) -> SnapshotsState {
        SnapshotsState {
            kept: self.kept.iter().copied().collect(),
            latest: self.latest.as_ref().map(|p| p.info.version),
            best: self.best.as_ref().map(|(p, r)| (p.info.version, *r)),
        }
    }

    /// The version the next snapshot gets.
    pub fn next_version(&self) -> u64 {
        let latest = self.latest.as_ref().map_or(0, |p| p.info.version);
        latest.max(self.highest) + 1
    }

    /// The path of version `version`.
    pub fn path(&self, version: u64) -> PathBuf {
        self.dir.join(format!("v{version:06}.safetensors"))
    }

    /// The versions whose files are in the directory, lowest first.
    fn on_disk(&self) -> Result<Vec<u64>, SnapshotsError> {
        let entries = std::fs::read_dir(&self.dir).map_err(|source| SnapshotsError::Io {
            path: self.dir.clone(),
            source,
        })?;
        let mut versions: Vec<u64> = entries
            .filter_map(|entry| {
                let name = entry.ok()?.file_name();
                let version = name
                    .to_str()?
                    .strip_prefix('v')?
                    .strip_suffix(".safetensors")?;
                let version: u64 = version.parse().ok()?;
                // Only the names `path` gives.
                (self.path(version).file_name() == Some(name.as_os_str())).then_some(version)
            })
            .collect();
        versions.sort_unstable();
        Ok(versions)
    }

    fn read(&self, version: u64) -> Result<Arc<Published>, SnapshotsError> {
        let path = self.path(version);
        let bytes = std::fs::read(&path).map_err(|source| SnapshotsError::Io {
            path: path.clone(),
            source,
        })?;
        let published = Published::new(bytes)?;
        if published.info.version != version {
            return Err(SnapshotsError::Corrupt(format!(
                "{} holds version {}",
                path.display(),
                published.info.version
            )));
        }
        Ok(Arc::new(published))
    }

    fn write(&self, path: &Path, bytes: &[u8]) -> Result<(), SnapshotsError> {
        write_bytes_atomic(path, bytes).map_err(|source| SnapshotsError::Io {
            path: path.into(),
            source,
        })
    }

    /// Publishes `bytes` (an encoded snapshot of version
    /// [`Self::next_version`]); it becomes `best` when `rolling_return` beats
    /// the best so far. Returns the published snapshot and whether it is the
    /// new best.
    pub fn publish(
        &mut self,
        bytes: Vec<u8>,
        rolling_return: Option<f64>,
    ) -> Result<(Arc<Published>, bool), SnapshotsError> {
        let published = Arc::new(Published::new(bytes)?);
        let version = published.info.version;
        self.write(&self.path(version), &published.bytes)?;
        self.highest = self.highest.max(version);
        self.kept.push_back(version);
        self.latest = Some(published.clone());
        let is_best =
            rolling_return.is_some_and(|r| self.best.as_ref().is_none_or(|(_, best)| r >= *best));
        if let Some(r) = rolling_return.filter(|_| is_best) {
            // A second name for the file just written, not a second copy.
            let best = self.dir.join(BEST_FILE);
            if link_atomic(&self.path(version), &best).is_err() {
                self.write(&best, &published.bytes)?;
            }
            self.best = Some((published.clone(), r));
        }
        self.prune();
        Ok((published, is_best))
    }

    /// Spares `versions` (those the kept checkpoints need) from pruning
    /// from now on, instead of the ones pinned before.
    pub fn pin(&mut self, versions: BTreeSet<u64>) {
        self.pinned = versions;
    }

    /// Deletes the oldest files beyond `keep`, never the best's nor a
    /// pinned one.
    fn prune(&mut self) {
        let best = self.best.as_ref().map(|(p, _)| p.info.version);
        let prunable = |v: u64| Some(v) != best && !self.pinned.contains(&v);
        let count = |kept: &VecDeque<u64>| kept.iter().filter(|&&v| prunable(v)).count();
        while count(&self.kept) > self.keep {
            let Some(position) = self.kept.iter().position(|&v| prunable(v)) else {
                break;
            };
            if let Some(version) = self.kept.remove(position) {
                let _ = std::fs::remove_file(self.path(version));
            }
        }
    }

    /// The snapshot `selector` names.
    pub fn get(&self, selector: Selector) -> Result<Arc<Published>, SnapshotsError> {
        let none = || SnapshotsError::NotFound("no policy snapshot has been published yet".into());
        match selector {
            Selector::Latest => self.latest.clone().ok_or_else(none),
            Selector::Best => match &self.best {
                Some((p, _)) => Ok(p.clone()),
                None if self.latest.is_some() => Err(SnapshotsError::NotFound(
                    "no snapshot has a best yet: none was published after an episode finished"
                        .into(),
                )),
                None => Err(none()),
            },
            Selector::Version(v) => {
                for p in self.latest.iter().chain(self.best.iter().map(|(p, _)| p)) {
                    if p.info.version == v {
                        return Ok(p.clone());
                    }
                }
                if !self.kept.contains(&v) {
                    return Err(SnapshotsError::NotFound(format!(
                        "snapshot version {v} is not kept (kept: {:?})",
                        self.kept
                    )));
                }
                self.read(v)
            }
        }
    }

    /// The latest version, or 0 before the first.
    pub fn latest_version(&self) -> u64 {
        self.latest.as_ref().map_or(0, |p| p.info.version)
    }

    /// The best version, or 0 before there is one.
    pub fn best_version(&self) -> u64 {
        self.best.as_ref().map_or(0, |(p, _)| p.info.version)
    }
}
