//! The gRPC wire schema of Tweezer RL and the conversions between wire and
//! domain types.
//!
//! `pb` holds the types generated from `proto/tweezer/v1/*.proto` (the public
//! contract, readable by any gRPC stack). Nothing below a service's edge
//! should use them: convert with the functions here, which validate every
//! field and name the one that is wrong.

mod convert;
mod snapshot_download;

pub use convert::{
    MAX_ACTOR_ID, MAX_BATCH_STEPS, WireError, action_from_wire, action_to_wire, check_actor_id,
    observation_from_wire, observation_to_wire, outcome_to_wire, step_batch_from_wire,
    step_from_wire, step_to_wire,
};
pub use snapshot_download::{DownloadError, download_snapshot};

/// The response header of `StreamSteps` that gives the largest `StepBatch`
/// the learner decodes, in bytes.
pub const MAX_MESSAGE_HEADER: &str = "tweezer-max-message-bytes";

/// The largest message a gRPC peer takes unless it says otherwise (4 MiB).
pub const DEFAULT_MAX_MESSAGE_BYTES: usize = 4 << 20;

/// The encoded `FileDescriptorSet` of every proto file, for gRPC server
/// reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/tweezer_descriptor.bin"));

/// Types and service stubs generated from the proto files.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod pb {
    tonic::include_proto!("tweezer.v1");
}
