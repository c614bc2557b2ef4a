//! `tweezer learner ...`.

use crate::LearnerCommand;
use crate::connect::{call_error, channel};
use crate::fields;
use crate::watch::Trend;
use anyhow::{Context, anyhow};
use std::path::Path;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_proto::pb::snapshot_request::Selector;
use tweezer_proto::{DownloadError, download_snapshot, pb};
use tweezer_rpc::AuthChannel;

/// The learner's status.
async fn status(client: &mut LearnerClient<AuthChannel>) -> anyhow::Result<pb::LearnerStatus> {
    tweezer_rpc::learner_status(client)
        .await
        .map_err(|e| call_error("GetStatus", e))
}

/// Runs a learner command against the learner at `address`, connecting as
/// the security file `security` says.
pub async fn run(
    security: Option<&Path>,
    address: &str,
    command: LearnerCommand,
    json: bool,
) -> anyhow::Result<()> {
    let mut client = LearnerClient::new(channel(security, address, "learner", "--learner").await?)
        .max_decoding_message_size(64 << 20);
    match command {
        LearnerCommand::Status { watch } => {
            let trends = [
                Trend::Value("rolling_return"),
                Trend::Value("success_rate"),
                Trend::PerSecond("updates"),
                Trend::PerSecond("steps_inserted"),
            ];
            crate::watch::repeat(watch, json, &trends, || {
                let mut client = client.clone();
                async move { Ok(fields::learner(&status(&mut client).await?)) }
            })
            .await
        }
        LearnerCommand::Pause => {
            let status = client
                .pause_learning(pb::PauseLearningRequest {})
                .await
                .map_err(|e| call_error("PauseLearning", e))?
                .into_inner();
            fields::print(&fields::learner(&status), json);
            Ok(())
        }
        LearnerCommand::Resume => {
            let status = client
                .resume_learning(pb::ResumeLearningRequest {})
                .await
                .map_err(|e| call_error("ResumeLearning", e))?
                .into_inner();
            fields::print(&fields::learner(&status), json);
            Ok(())
        }
        LearnerCommand::Checkpoint => {
            let reply = client
                .checkpoint(pb::CheckpointRequest {})
                .await
                .map_err(|e| call_error("Checkpoint", e))?
                .into_inner();
            fields::print(&vec![("checkpoint", serde_json::json!(reply.path))], json);
            Ok(())
        }
        LearnerCommand::Actors => {
            let status = status(&mut client).await?;
            if status.actors.is_empty() && !json {
                println!("no actor has sent steps to this learner since it started");
            }
            for (k, actor) in status.actors.iter().enumerate() {
                if k > 0 && !json {
                    println!();
                }
                fields::print(&fields::actor(actor), json);
            }
            Ok(())
        }
        LearnerCommand::Snapshots => {
            let list = client
                .list_snapshots(pb::ListSnapshotsRequest {})
                .await
                .map_err(|e| call_error("ListSnapshots", e))?
                .into_inner();
            for (k, info) in list.snapshots.iter().enumerate() {
                if k > 0 && !json {
                    println!();
                }
                let tags: Vec<&str> = [("latest", list.latest), ("best", list.best)]
                    .into_iter()
                    .filter(|&(_, v)| v == info.version)
                    .map(|(tag, _)| tag)
                    .collect();
                let mut row = fields::snapshot(info);
                row.push(("tags", serde_json::json!(tags.join(","))));
                fields::print(&row, json);
            }
            Ok(())
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
            let mut row = vec![("file", serde_json::json!(out.display().to_string()))];
            row.extend(fields::snapshot(&info));
            fields::print(&row, json);
            Ok(())
        }
    }
}
