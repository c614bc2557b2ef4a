//! `tweezer learner ...`.

use crate::LearnerCommand;
use crate::connect::{call_error, channel};
use crate::fields;
use anyhow::{Context, anyhow};
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_proto::pb::snapshot_request::Selector;
use tweezer_proto::{DownloadError, download_snapshot, pb};

/// Runs a learner command against the learner at `address`.
pub async fn run(address: &str, command: LearnerCommand, json: bool) -> anyhow::Result<()> {
    let mut client = LearnerClient::new(channel(address, "learner", "--learner").await?)
        .max_decoding_message_size(64 << 20);
    match command {
        LearnerCommand::Status { watch } => {
            crate::watch::repeat(watch, json, || {
                let mut client = client.clone();
                async move {
                    let status = client
                        .get_status(pb::LearnerStatusRequest {})
                        .await
                        .map_err(|e| call_error("GetStatus", e))?
                        .into_inner();
                    Ok(fields::learner(&status))
                }
            })
            .await
        }
        LearnerCommand::Download { snapshot, out } => {
            let selector = match snapshot.as_str() {
                "best" => Selector::Tag(pb::SnapshotTag::Best.into()),
                "latest" => Selector::Tag(pb::SnapshotTag::Latest.into()),
                v => Selector::Version(v.parse().map_err(|_| {
                    anyhow!("snapshot {v:?}: give \"best\", \"latest\" or a version number")
                })?),
            };
            let (info, bytes) =
                download_snapshot(&mut client, selector)
                    .await
                    .map_err(|e| match e {
                        DownloadError::Status(s) => call_error("GetSnapshot", s),
                        other => anyhow!(other),
                    })?;
            std::fs::write(&out, &bytes)
                .with_context(|| format!("cannot write {}", out.display()))?;
            let fields = vec![
                ("file", serde_json::json!(out.display().to_string())),
                ("version", serde_json::json!(info.version)),
                ("training_step", serde_json::json!(info.training_step)),
                ("size_bytes", serde_json::json!(info.size_bytes)),
                ("sha256", serde_json::json!(info.sha256)),
                ("architecture", serde_json::json!(info.architecture)),
                (
                    "image",
                    serde_json::json!([info.image_width, info.image_height]),
                ),
            ];
            fields::print(&fields, json);
            Ok(())
        }
    }
}
