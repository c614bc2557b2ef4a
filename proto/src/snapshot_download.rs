//! Downloading a policy snapshot from a learner: the chunks of one
//! `GetSnapshot` call assembled in order, checked against the size and
//! SHA-256 its first chunk announces.

use crate::pb;
use crate::pb::learner_client::LearnerClient;
use sha2::{Digest, Sha256};
use tonic::codegen::{Body, Bytes, StdError};

/// Most bytes a snapshot may announce (a paper-size actor is ~170 MB).
const MAX_SNAPSHOT_BYTES: u64 = 2 << 30;

/// A download that failed.
#[derive(Debug, thiserror::Error)]
pub enum DownloadError {
    /// The learner answered with an error (NOT_FOUND before the first
    /// snapshot, for one).
    #[error("learner refused the snapshot: {}: {}", .0.code(), .0.message())]
    Status(#[from] tonic::Status),
    /// The chunks do not make up the file they announced.
    #[error("snapshot download is inconsistent: {0}")]
    Inconsistent(String),
}

/// Downloads the snapshot `selector` names; returns its info and bytes.
pub async fn download_snapshot<T>(
    client: &mut LearnerClient<T>,
    selector: pb::snapshot_request::Selector,
) -> Result<(pb::SnapshotInfo, Vec<u8>), DownloadError>
where
    T: tonic::client::GrpcService<tonic::body::Body>,
    T::Error: Into<StdError>,
    T::ResponseBody: Body<Data = Bytes> + Send + 'static,
    <T::ResponseBody as Body>::Error: Into<StdError> + Send,
{
    let bad = |m: String| DownloadError::Inconsistent(m);
    let mut chunks = client
        .get_snapshot(pb::SnapshotRequest {
            selector: Some(selector),
        })
        .await?
        .into_inner();
    let first = chunks
        .message()
        .await?
        .ok_or_else(|| bad("no chunk arrived".into()))?;
    let info = first
        .info
        .clone()
        .ok_or_else(|| bad("the first chunk carries no info".into()))?;
    if info.size_bytes > MAX_SNAPSHOT_BYTES {
        return Err(bad(format!(
            "announced size {} is too large",
            info.size_bytes
        )));
    }
    let mut bytes = Vec::with_capacity(info.size_bytes as usize);
    let mut chunk = Some(first);
    while let Some(c) = chunk {
        if c.offset != bytes.len() as u64 {
            return Err(bad(format!(
                "chunk at offset {} where {} was expected",
                c.offset,
                bytes.len()
            )));
        }
        if bytes.len() as u64 + c.data.len() as u64 > info.size_bytes {
            return Err(bad(format!(
                "more than the {} bytes announced",
                info.size_bytes
            )));
        }
        bytes.extend_from_slice(&c.data);
        chunk = chunks.message().await?;
    }
    if bytes.len() as u64 != info.size_bytes {
        return Err(bad(format!(
            "{} bytes arrived, {} were announced",
            bytes.len(),
            info.size_bytes
        )));
    }
    let digest: String = Sha256::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    if digest != info.sha256 {
        return Err(bad(format!(
            "SHA-256 {digest} does not match the announced {}",
            info.sha256
        )));
    }
    Ok((info, bytes))
}
