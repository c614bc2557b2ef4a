//! Where the agent's policy comes from: a learner over gRPC (its best,
//! latest or a pinned snapshot), a snapshot file, or a baseline that needs no
//! training (greedy, or the planner: a fallback on the instrument).
//! Every snapshot is verified before use: its checksum, architecture and
//! image resolution must match what this agent renders.

use burn::tensor::Device;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tweezer_config::{ConfigError, in_range};
use tweezer_gym::{Baseline, EnvConfig, Policy};
use tweezer_nets::{LoadError, NetworkPolicy, SnapshotInfo, file_sha256};
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_proto::pb::snapshot_request::Selector;
use tweezer_proto::{download_snapshot, pb};
use tweezer_rpc::{ClientSecurity, Security};

/// What kind of source.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PolicyKind {
    /// A learner's snapshot over gRPC.
    Learner,
    /// A snapshot file.
    File,
    /// Straight at the target, blind to spheres (needs no training).
    Greedy,
    /// The receding-horizon planner on the same observation (needs no
    /// training).
    Planner,
}

/// The `[policy]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PolicyConfig {
    /// Where the policy comes from.
    pub source: PolicyKind,
    /// The learner's gRPC address (source = "learner"): `host:port`, or a
    /// URL whose scheme matches the security file.
    pub learner: String,
    /// Which of its snapshots: "best", "latest" or a version number.
    pub snapshot: String,
    /// Follow `snapshot` ("best" or "latest"): between episodes, load each
    /// newer snapshot the learner publishes under it.
    pub follow: bool,
    /// The snapshot file (source = "file").
    pub file: PathBuf,
    /// Longest wait for the learner, s.
    pub timeout_s: f64,
}

impl Default for PolicyConfig {
    fn default() -> Self {
        Self {
            source: PolicyKind::Learner,
            learner: "127.0.0.1:50051".into(),
            snapshot: "best".into(),
            follow: false,
            file: PathBuf::from("snapshot.safetensors"),
            timeout_s: 30.0,
        }
    }
}

/// A learner's snapshot, by tag or version.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SnapshotChoice {
    /// The one with the best rolling return.
    Best,
    /// The newest.
    Latest,
    /// This version.
    Version(u64),
}

impl std::fmt::Display for SnapshotChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Best => f.write_str("best"),
            Self::Latest => f.write_str("latest"),
            Self::Version(v) => write!(f, "v{v}"),
        }
    }
}

impl SnapshotChoice {
    /// Parses "best", "latest" or a version number.
    pub fn parse(text: &str) -> Result<Self, String> {
        match text {
            "best" => Ok(Self::Best),
            "latest" => Ok(Self::Latest),
            v => v.parse().map(Self::Version).map_err(|_| {
                format!("policy.snapshot = {v:?}: \"best\", \"latest\" or a version number")
            }),
        }
    }

    fn selector(self) -> Selector {
        match self {
            Self::Best => Selector::Tag(pb::SnapshotTag::Best.into()),
            Self::Latest => Selector::Tag(pb::SnapshotTag::Latest.into()),
            Self::Version(v) => Selector::Version(v),
        }
    }
}

impl PolicyConfig {
    /// The policy the table names.
    pub fn choice(&self) -> Result<PolicyChoice, PolicyError> {
        self.validate()
            .map_err(|e| PolicyError::Config(e.in_table("policy").to_string()))?;
        let snapshot = || SnapshotChoice::parse(&self.snapshot).map_err(PolicyError::Config);
        Ok(match self.source {
            PolicyKind::Greedy => PolicyChoice::Baseline(Baseline::Greedy),
            PolicyKind::Planner => PolicyChoice::Baseline(Baseline::Planner),
            PolicyKind::File => PolicyChoice::File(self.file.clone()),
            PolicyKind::Learner if self.follow => PolicyChoice::Follow(snapshot()?),
            PolicyKind::Learner => PolicyChoice::Learner(snapshot()?),
        })
    }

    /// Checks the fields the source uses.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let snapshot = SnapshotChoice::parse(&self.snapshot)
            .map_err(|e| ConfigError::invalid("snapshot", e))?;
        if self.follow
            && (self.source != PolicyKind::Learner
                || matches!(snapshot, SnapshotChoice::Version(_)))
        {
            return Err(ConfigError::invalid(
                "follow",
                format!(
                    "needs source = \"learner\" and snapshot = \"best\" or \"latest\" (source = {:?}, snapshot = {:?})",
                    self.source, self.snapshot
                ),
            ));
        }
        in_range("timeout_s", self.timeout_s, 0.1, 3600.0)?;
        if self.source == PolicyKind::Learner
            && self.learner.parse::<tonic::transport::Uri>().is_err()
        {
            return Err(ConfigError::invalid(
                "learner",
                format!("{:?} is not a URI", self.learner),
            ));
        }
        Ok(())
    }
}

/// A policy to load, as an operator names it.
#[derive(Clone, Debug, PartialEq)]
pub enum PolicyChoice {
    /// A snapshot of the configured learner.
    Learner(SnapshotChoice),
    /// The configured learner's best or latest snapshot now, and each newer
    /// one it publishes under that tag, between episodes.
    Follow(SnapshotChoice),
    /// A snapshot file.
    File(PathBuf),
    /// A baseline that needs no training.
    Baseline(Baseline),
}

/// A policy the agent can drive with, and what it is.
pub struct LoadedPolicy {
    /// The policy.
    pub policy: Box<dyn Policy + Send>,
    /// Snapshot version (0 for a baseline).
    pub version: u64,
    /// Where it came from, for status and records.
    pub description: String,
}

impl std::fmt::Debug for LoadedPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LoadedPolicy")
            .field("version", &self.version)
            .field("description", &self.description)
            .finish_non_exhaustive()
    }
}

/// Why no policy could be loaded.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    /// A bad `[policy]` table or `[env]` image settings.
    #[error("{0}")]
    Config(String),
    /// The learner could not be reached or refused.
    #[error(
        "cannot fetch the {choice} snapshot from the learner at {address} (the agent's `policy.learner`): {reason}"
    )]
    Learner {
        /// Its address.
        address: String,
        /// Which snapshot.
        choice: SnapshotChoice,
        /// Why.
        reason: String,
    },
    /// The snapshot failed verification or could not be read.
    #[error("refusing the policy: {0}")]
    Refused(String),
}

impl LoadedPolicy {
    /// A baseline, for observations of `env`.
    pub fn baseline(baseline: Baseline, env: &EnvConfig) -> Self {
        Self {
            policy: baseline.policy(env),
            version: 0,
            description: format!("{} baseline", baseline.name()),
        }
    }

    /// Loads the policy `config` names, for observations of `env`; a
    /// learner's snapshot is fetched as `security` says.
    pub fn load(
        config: &PolicyConfig,
        env: &EnvConfig,
        security: Option<&Security>,
    ) -> Result<Self, PolicyError> {
        Self::choose(&config.choice()?, config, env, security)
    }

    /// Loads `choice`, a learner's snapshot from the learner `config` names
    /// (connecting as `security` says).
    pub fn choose(
        choice: &PolicyChoice,
        config: &PolicyConfig,
        env: &EnvConfig,
        security: Option<&Security>,
    ) -> Result<Self, PolicyError> {
        match choice {
            PolicyChoice::Follow(SnapshotChoice::Version(v)) => Err(PolicyError::Config(format!(
                "only \"best\" or \"latest\" can be followed, not version {v}"
            ))),
            PolicyChoice::Follow(tag) => {
                Self::choose(&PolicyChoice::Learner(*tag), config, env, security)
            }
            PolicyChoice::Baseline(baseline) => Ok(Self::baseline(*baseline, env)),
            PolicyChoice::File(path) => {
                Self::from_file_within(path, env, Duration::from_secs_f64(config.timeout_s))
            }
            PolicyChoice::Learner(snapshot) => {
                let timeout = Duration::from_secs_f64(config.timeout_s);
                let security = security.ok_or_else(|| {
                    PolicyError::Config(
                        "a learner's snapshot needs a security file (--security or TWEEZER_SECURITY) with the learner's CA and a read token".into(),
                    )
                })?;
                Self::from_learner(&config.learner, *snapshot, timeout, env, security)
            }
        }
    }

    /// Loads and verifies a snapshot file.
    pub fn from_file(path: &Path, env: &EnvConfig) -> Result<Self, PolicyError> {
        Self::from_file_within(path, env, Duration::from_secs(60))
    }

    /// Loads and verifies a snapshot file that must be read within
    /// `timeout`: only a regular file is read (a FIFO or a device could
    /// block for ever), on a helper thread that is abandoned if a stalled
    /// file system keeps it past the bound.
    pub fn from_file_within(
        path: &Path,
        env: &EnvConfig,
        timeout: Duration,
    ) -> Result<Self, PolicyError> {
        let refuse = |why: String| {
            PolicyError::Refused(format!("cannot read snapshot {}: {why}", path.display()))
        };
        let metadata = std::fs::metadata(path).map_err(|e| refuse(e.to_string()))?;
        if !metadata.is_file() {
            return Err(refuse("not a regular file".into()));
        }
        let (tx, rx) = std::sync::mpsc::channel();
        let owned = path.to_path_buf();
        std::thread::Builder::new()
            .name("policy-file".into())
            .spawn(move || {
                let _ = tx.send(std::fs::read(owned));
            })
            .map_err(|e| refuse(e.to_string()))?;
        let bytes = match rx.recv_timeout(timeout) {
            Ok(read) => read.map_err(|e| refuse(e.to_string()))?,
            Err(_) => {
                return Err(refuse(format!(
                    "not read within {:.1} s (policy.timeout_s)",
                    timeout.as_secs_f64()
                )));
            }
        };
        Self::from_bytes(&bytes, env, &format!("file {}", path.display()))
    }

    /// The snapshot the learner `config` names publishes under `tag` when
    /// it is newer than `version`: downloaded, verified and loaded; `None`
    /// when there is none newer. One bound, `policy.timeout_s`, for all of
    /// it.
    pub fn newer(
        config: &PolicyConfig,
        tag: SnapshotChoice,
        version: u64,
        env: &EnvConfig,
        security: &Security,
    ) -> Result<Option<Self>, PolicyError> {
        let address = config.learner.as_str();
        let timeout = Duration::from_secs_f64(config.timeout_s);
        let fail = |reason: String| PolicyError::Learner {
            address: address.into(),
            choice: tag,
            reason,
        };
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| fail(e.to_string()))?;
        let ask = async {
            let channel = ClientSecurity::load(security)
                .map_err(|e| fail(e.to_string()))?
                .connect_bounded(address, timeout)
                .await
                .map_err(|e| fail(e.to_string()))?;
            tweezer_rpc::learner_status(&mut LearnerClient::new(channel))
                .await
                .map_err(|e| fail(e.to_string()))
        };
        let status = runtime
            .block_on(async { tokio::time::timeout(timeout, ask).await })
            .map_err(|_| {
                fail(format!(
                    "no status within {:.1} s (policy.timeout_s)",
                    timeout.as_secs_f64()
                ))
            })??;
        let published = match tag {
            SnapshotChoice::Best => status.best_snapshot,
            _ => status.latest_snapshot,
        };
        if published <= version {
            return Ok(None);
        }
        Self::from_learner(
            address,
            SnapshotChoice::Version(published),
            timeout,
            env,
            security,
        )
        .map(Some)
    }

    /// Downloads, verifies and loads a learner's snapshot.
    fn from_learner(
        address: &str,
        choice: SnapshotChoice,
        timeout: Duration,
        env: &EnvConfig,
        security: &Security,
    ) -> Result<Self, PolicyError> {
        let fail = |reason: String| PolicyError::Learner {
            address: address.into(),
            choice,
            reason,
        };
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| fail(e.to_string()))?;
        // One bound for all of it: the TCP connect, the TLS handshake and
        // the download (a learner that accepts and never answers must not
        // hold the agent in LOADING).
        let fetch = async {
            let channel = ClientSecurity::load(security)
                .map_err(|e| fail(e.to_string()))?
                .connect_bounded(address, timeout)
                .await
                .map_err(|e| fail(e.to_string()))?;
            let mut client = LearnerClient::new(channel).max_decoding_message_size(64 << 20);
            download_snapshot(&mut client, choice.selector())
                .await
                .map_err(|e| fail(e.to_string()))
        };
        let (info, bytes) = runtime
            .block_on(async { tokio::time::timeout(timeout, fetch).await })
            .map_err(|_| {
                fail(format!(
                    "no snapshot within {:.1} s (policy.timeout_s: connect, TLS handshake and download together)",
                    timeout.as_secs_f64()
                ))
            })??;
        Self::from_bytes(
            &bytes,
            env,
            &format!("learner {address} snapshot v{}", info.version),
        )
    }

    fn from_bytes(bytes: &[u8], env: &EnvConfig, origin: &str) -> Result<Self, PolicyError> {
        let (policy, info): (NetworkPolicy, SnapshotInfo) =
            NetworkPolicy::from_snapshot(bytes, env, &Device::flex()).map_err(|e| match e {
                LoadError::Config(e) => PolicyError::Config(e.to_string()),
                LoadError::Snapshot(e) => PolicyError::Refused(format!("{origin}: {e}")),
            })?;
        Ok(Self {
            policy: Box::new(policy),
            version: info.version,
            description: format!(
                "{origin} ({}, v{}, step {}, sha256 {})",
                info.architecture.name(),
                info.version,
                info.training_step,
                &file_sha256(bytes)[..12]
            ),
        })
    }
}
