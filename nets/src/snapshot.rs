//! Policy snapshots: the actor's weights (BatchNorm statistics included) in
//! a safetensors file, which any safetensors reader opens, with metadata
//! naming the architecture and its hyper-parameters, the version and
//! training step, and a SHA-256 of the weights that loading verifies.
//! The learner adds its two critics under [`CRITIC_PREFIXES`], so that a
//! policy can check the actor's action against them
//! ([`crate::critic_search`]).

use crate::architecture::{Architecture, ArchitectureError};
use crate::networks::Networks;
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor, TensorData};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, HashMap};

/// What a snapshot says about itself.
#[derive(Clone, Debug, PartialEq)]
pub struct SnapshotInfo {
    /// Network architecture and hyper-parameters.
    pub architecture: Architecture,
    /// Snapshot version (increases with every snapshot of a run).
    pub version: u64,
    /// Learner updates made when it was taken.
    pub training_step: u64,
}

/// A snapshot that cannot be used.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum SnapshotError {
    /// Not a readable safetensors file.
    #[error("not a safetensors snapshot: {0}")]
    Format(String),
    /// A metadata field is missing or malformed.
    #[error("snapshot metadata `{field}` is missing or malformed")]
    Metadata {
        /// The field.
        field: &'static str,
    },
    /// The architecture it names cannot be built.
    #[error("snapshot metadata: {0}")]
    Architecture(#[from] ArchitectureError),
    /// The network is not the one this process can use.
    #[error("snapshot holds {found}, this process needs {expected}: {differences}")]
    Mismatch {
        /// What we can load.
        expected: String,
        /// What the file holds.
        found: String,
        /// What differs, field by field.
        differences: String,
    },
    /// The weights do not match their checksum.
    #[error("snapshot weights fail their checksum (expected {expected}, computed {computed})")]
    Checksum {
        /// Stored.
        expected: String,
        /// Computed.
        computed: String,
    },
    /// A tensor the network needs is missing or has the wrong shape or type.
    #[error("snapshot tensor `{name}`: {reason}")]
    Tensor {
        /// Its name.
        name: String,
        /// What is wrong.
        reason: String,
    },
}

impl SnapshotError {
    /// The refusal of a `found` network where `expected` is needed.
    pub fn mismatch(expected: &Architecture, found: &Architecture) -> Self {
        Self::Mismatch {
            expected: expected.to_string(),
            found: found.to_string(),
            differences: found.differences(expected).join(", "),
        }
    }
}

/// Where a snapshot keeps the learner's two critics: their tensors' names
/// start with these (`critic1.head.out.weight`).
pub const CRITIC_PREFIXES: [&str; 2] = ["critic1", "critic2"];

/// Float tensors by name: shape and data.
type Tensors = BTreeMap<String, (Vec<usize>, Vec<f32>)>;

/// Every float tensor of a module by its path (`encoder.conv1.weight`).
#[derive(Default)]
struct Named {
    path: Vec<String>,
    tensors: Tensors,
}

impl ModuleVisitor for Named {
    fn enter_module(&mut self, name: &str, _container: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let tensor = param.val();
        let shape = tensor.dims().to_vec();
        let data = tensor
            .into_data()
            .convert::<f32>()
            .try_to_vec::<f32>()
            .expect("converted to f32");
        self.tensors.insert(self.path.join("."), (shape, data));
    }
}

fn digest(tensors: &Tensors) -> String {
    let mut hash = Sha256::new();
    for (name, (shape, data)) in tensors {
        hash.update(name.as_bytes());
        for d in shape {
            hash.update((*d as u64).to_le_bytes());
        }
        for v in data {
            hash.update(v.to_le_bytes());
        }
    }
    hash.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// Writes `actor` and `info` as safetensors bytes.
pub fn encode<M: Module>(actor: &M, info: &SnapshotInfo) -> Vec<u8> {
    serialise(named::<M, M>(actor, &[]), info, HashMap::new())
}

/// Writes `actor`, the learner's two `critics`, the `reward_scale` their
/// values are in (rewards times it) and `info` as safetensors bytes.
pub fn encode_with_critics<M: Module, C: Module>(
    actor: &M,
    critics: &[C; 2],
    reward_scale: f64,
    info: &SnapshotInfo,
) -> Vec<u8> {
    let mut metadata = HashMap::new();
    metadata.insert(REWARD_SCALE.to_string(), reward_scale.to_string());
    serialise(named(actor, critics), info, metadata)
}

/// The metadata field with the scale of the critics' values.
const REWARD_SCALE: &str = "critic_reward_scale";

/// Every tensor of `actor` by its path, and of each of `critics` by its
/// path under its prefix in [`CRITIC_PREFIXES`].
fn named<M: Module, C: Module>(actor: &M, critics: &[C]) -> Named {
    let mut named = Named::default();
    actor.visit(&mut named);
    for (critic, prefix) in critics.iter().zip(CRITIC_PREFIXES) {
        named.path = vec![prefix.to_string()];
        critic.visit(&mut named);
    }
    named.path.clear();
    named
}

/// The file of `named`'s tensors, with `info` and `metadata` in its header.
fn serialise(named: Named, info: &SnapshotInfo, mut metadata: HashMap<String, String>) -> Vec<u8> {
    metadata.insert("format".to_string(), "tweezer-snapshot".to_string());
    metadata.insert(
        "architecture".to_string(),
        info.architecture.name().to_string(),
    );
    for (name, value) in info.architecture.fields() {
        metadata.insert(name.to_string(), value);
    }
    metadata.insert("version".to_string(), info.version.to_string());
    metadata.insert("training_step".to_string(), info.training_step.to_string());
    metadata.insert("weights_sha256".to_string(), digest(&named.tensors));
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = named
        .tensors
        .iter()
        .map(|(name, (shape, data))| {
            let raw = data.iter().flat_map(|v| v.to_le_bytes()).collect();
            (name.clone(), shape.clone(), raw)
        })
        .collect();
    let views = bytes.iter().map(|(name, shape, raw)| {
        let view = TensorView::new(Dtype::F32, shape.clone(), raw).expect("shape matches data");
        (name.as_str(), view)
    });
    safetensors::serialize(views, Some(metadata)).expect("f32 tensors serialise")
}

fn field<T: std::str::FromStr>(
    metadata: &HashMap<String, String>,
    field: &'static str,
) -> Result<T, SnapshotError> {
    metadata
        .get(field)
        .and_then(|v| v.parse().ok())
        .ok_or(SnapshotError::Metadata { field })
}

/// The snapshot's metadata table, checked to be ours.
fn metadata(bytes: &[u8]) -> Result<HashMap<String, String>, SnapshotError> {
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| SnapshotError::Format(e.to_string()))?;
    let metadata = header.metadata().clone().unwrap_or_default();
    if metadata.get("format").map(String::as_str) != Some("tweezer-snapshot") {
        return Err(SnapshotError::Metadata { field: "format" });
    }
    Ok(metadata)
}

fn info_of(metadata: &HashMap<String, String>) -> Result<SnapshotInfo, SnapshotError> {
    let name: String = field(metadata, "architecture")?;
    Ok(SnapshotInfo {
        architecture: Architecture::from_fields(&name, |k| metadata.get(k).map(String::as_str))?,
        version: field(metadata, "version")?,
        training_step: field(metadata, "training_step")?,
    })
}

/// Reads a snapshot's metadata without loading its weights.
pub fn read_info(bytes: &[u8]) -> Result<SnapshotInfo, SnapshotError> {
    info_of(&metadata(bytes)?)
}

/// Replaces each parameter by the file's tensor of the same path, noting
/// the first problem.
struct Load<'a> {
    path: Vec<String>,
    tensors: &'a Tensors,
    device: Device,
    loaded: usize,
    error: Option<SnapshotError>,
}

impl ModuleMapper for Load<'_> {
    fn enter_module(&mut self, name: &str, _container: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container: &str) {
        self.path.pop();
    }

    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let name = self.path.join(".");
        let (id, tensor, mapper) = param.consume();
        let wanted = tensor.dims().to_vec();
        let fail = |reason: String| SnapshotError::Tensor {
            name: name.clone(),
            reason,
        };
        let replacement = match self.tensors.get(&name) {
            None => Err(fail("missing".into())),
            Some((shape, _)) if *shape != wanted => Err(fail(format!(
                "shape {shape:?}, the network needs {wanted:?}"
            ))),
            Some((shape, data)) => Ok(Tensor::<D>::from_data(
                TensorData::new(data.clone(), shape.clone()),
                &self.device,
            )),
        };
        let tensor = match replacement {
            Ok(t) => {
                self.loaded += 1;
                t
            }
            Err(e) => {
                self.error.get_or_insert(e);
                tensor
            }
        };
        Param::from_mapped_value(id, tensor, mapper)
    }
}

/// A snapshot loaded: the actor, the learner's critics where the file
/// holds them, and what the file says about itself.
pub struct Decoded<N: Networks> {
    /// The policy network.
    pub actor: N::Actor,
    /// The learner's two critics, when the snapshot carries them.
    pub critics: Option<[N::Critic; 2]>,
    /// The scale of the critics' values (rewards times it), where the
    /// snapshot records it: those from before 2026-11-29 do not.
    pub critic_reward_scale: Option<f64>,
    /// Architecture, version and training step.
    pub info: SnapshotInfo,
}

impl<N: Networks> std::fmt::Debug for Decoded<N> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Decoded")
            .field("info", &self.info)
            .field("critics", &self.critics.is_some())
            .field("critic_reward_scale", &self.critic_reward_scale)
            .finish_non_exhaustive()
    }
}

/// Loads a snapshot of the architecture `networks` builds onto `device`,
/// refusing any other architecture or hyper-parameters and corrupted
/// weights.
pub fn decode<N: Networks>(
    bytes: &[u8],
    networks: &N,
    device: &Device,
) -> Result<Decoded<N>, SnapshotError> {
    let metadata = metadata(bytes)?;
    let info = info_of(&metadata)?;
    let expected = networks.architecture();
    if info.architecture != expected {
        return Err(SnapshotError::mismatch(&expected, &info.architecture));
    }
    let tensors = verified_tensors(bytes, &metadata)?;
    let has_critics = tensors.keys().any(|name| of_critic(name));
    let mut loaded = 0;
    let actor = load(networks.actor(device), &[], &tensors, device, &mut loaded)?;
    let critics = if has_critics {
        let [q1, q2] = CRITIC_PREFIXES.map(|prefix| {
            load(
                networks.critic(device),
                &[prefix],
                &tensors,
                device,
                &mut loaded,
            )
        });
        Some([q1?, q2?])
    } else {
        None
    };
    if loaded != tensors.len() {
        let known = named(&actor, critics.as_ref().map_or(&[][..], |c| &c[..]));
        let extra = tensors
            .keys()
            .find(|k| !known.tensors.contains_key(*k))
            .cloned()
            .unwrap_or_default();
        return Err(SnapshotError::Tensor {
            name: extra,
            reason: "not part of the network".into(),
        });
    }
    let critic_reward_scale = if metadata.contains_key(REWARD_SCALE) {
        let scale: f64 = field(&metadata, REWARD_SCALE)?;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(SnapshotError::Metadata {
                field: REWARD_SCALE,
            });
        }
        Some(scale)
    } else {
        None
    };
    Ok(Decoded {
        actor,
        critics,
        critic_reward_scale,
        info,
    })
}

/// The snapshot `bytes`, verified, without the learner's critics: its
/// actor alone, with the checksum of what remains.
pub fn without_critics(bytes: &[u8]) -> Result<Vec<u8>, SnapshotError> {
    let metadata = metadata(bytes)?;
    let info = info_of(&metadata)?;
    let tensors = verified_tensors(bytes, &metadata)?
        .into_iter()
        .filter(|(name, _)| !of_critic(name))
        .collect();
    let named = Named {
        path: Vec::new(),
        tensors,
    };
    Ok(serialise(named, &info, HashMap::new()))
}

/// Whether tensor `name` is one of the critics'.
fn of_critic(name: &str) -> bool {
    let module = name.split('.').next();
    CRITIC_PREFIXES.iter().any(|p| module == Some(*p))
}

/// Every tensor of the file by name, once their checksum is verified.
fn verified_tensors(
    bytes: &[u8],
    metadata: &HashMap<String, String>,
) -> Result<Tensors, SnapshotError> {
    let file = SafeTensors::deserialize(bytes).map_err(|e| SnapshotError::Format(e.to_string()))?;
    let mut tensors = BTreeMap::new();
    for (name, view) in file.tensors() {
        if view.dtype() != Dtype::F32 {
            return Err(SnapshotError::Tensor {
                name,
                reason: format!("dtype {:?}, expected F32", view.dtype()),
            });
        }
        let data = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        tensors.insert(name, (view.shape().to_vec(), data));
    }
    let expected: String = field(metadata, "weights_sha256")?;
    let computed = digest(&tensors);
    if computed != expected {
        return Err(SnapshotError::Checksum { expected, computed });
    }
    Ok(tensors)
}

/// `fresh` with each parameter replaced by the tensor of the same path
/// under `prefix`; counts the tensors used into `loaded`.
fn load<M: Module>(
    fresh: M,
    prefix: &[&str],
    tensors: &Tensors,
    device: &Device,
    loaded: &mut usize,
) -> Result<M, SnapshotError> {
    let mut load = Load {
        path: prefix.iter().map(|p| p.to_string()).collect(),
        tensors,
        device: device.clone(),
        loaded: 0,
        error: None,
    };
    let module = fresh.map(&mut load);
    *loaded += load.loaded;
    match load.error {
        Some(e) => Err(e),
        None => Ok(module),
    }
}

/// SHA-256 of a whole snapshot file, lowercase hex (what the learner
/// announces when it serves the file).
pub fn file_sha256(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}
