//! The `Learner` gRPC service: actors stream steps in and get
//! acknowledgements; clients fetch snapshots in chunks; operators read
//! status. Wire types stop here: the rest of the learner sees domain types.

use crate::ingest::batch::{Ack, ActorBatch, Refusal};
use crate::ingest::limiter::limiter_state_name;
use crate::ingest::sessions::ActorSummary;
use crate::ingest::status::LearnerStatus;
use crate::persistence::snapshots::{Published, Selector, SnapshotsError};
use crate::state::LearnerState;
use std::pin::Pin;
use std::sync::Arc;
use tokio_stream::Stream;
use tonic::{Code, Request, Response, Status, Streaming};
use tweezer_proto::pb;
use tweezer_proto::pb::learner_server::{Learner, LearnerServer};

/// Largest `data` of one snapshot chunk, 64 KiB: also about what a
/// GetSnapshot stream whose client reads nothing holds (the chunk waiting
/// for its flow-control window), so that the streams a connection may open
/// ([`tweezer_rpc::MAX_CONCURRENT_STREAMS`]) hold a few MiB at most.
pub const CHUNK_BYTES: usize = 64 << 10;

/// The `Learner` service over the shared state.
#[derive(Debug, Clone)]
pub struct LearnerService {
    shared: Arc<LearnerState>,
    max_message_bytes: usize,
}

impl LearnerService {
    /// The service for `shared`, decoding step batches of up to gRPC's
    /// default 4 MiB.
    pub fn new(shared: Arc<LearnerState>) -> Self {
        Self {
            shared,
            max_message_bytes: tweezer_proto::DEFAULT_MAX_MESSAGE_BYTES,
        }
    }

    /// Decodes step batches of up to `bytes` (and tells actors so).
    pub fn with_max_message_bytes(mut self, bytes: usize) -> Self {
        self.max_message_bytes = bytes;
        self
    }

    /// The gRPC server of this service, with its message limit.
    pub fn into_server(self) -> LearnerServer<Self> {
        let limit = self.max_message_bytes;
        LearnerServer::new(self).max_decoding_message_size(limit)
    }
}

type AckStream = Pin<Box<dyn Stream<Item = Result<pb::StepAck, Status>> + Send>>;
type ChunkStream = Pin<Box<dyn Stream<Item = Result<pb::SnapshotChunk, Status>> + Send>>;

fn selector(request: &pb::SnapshotRequest) -> Result<Selector, Status> {
    use pb::snapshot_request::Selector as Wire;
    match request.selector {
        Some(Wire::Tag(tag)) => match pb::SnapshotTag::try_from(tag) {
            Ok(pb::SnapshotTag::Latest) => Ok(Selector::Latest),
            Ok(pb::SnapshotTag::Best) => Ok(Selector::Best),
            _ => Err(Status::invalid_argument(format!(
                "selector.tag: {tag} is not LATEST or BEST"
            ))),
        },
        Some(Wire::Version(v)) => Ok(Selector::Version(v)),
        None => Err(Status::invalid_argument(
            "selector: missing (a tag or a version)",
        )),
    }
}

impl From<SnapshotsError> for Status {
    fn from(e: SnapshotsError) -> Self {
        match e {
            SnapshotsError::NotFound(m) => Status::not_found(m),
            other => Status::internal(other.to_string()),
        }
    }
}

#[tonic::async_trait]
impl Learner for LearnerService {
    type StreamStepsStream = AckStream;
    type GetSnapshotStream = ChunkStream;

    async fn stream_steps(
        &self,
        request: Request<Streaming<pb::StepBatch>>,
    ) -> Result<Response<AckStream>, Status> {
        let token = request
            .extensions()
            .get::<tweezer_rpc::Caller>()
            .map(|caller| caller.name.clone());
        let mut inbound = request.into_inner();
        let shared = self.shared.clone();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            shared.stream_opened();
            let mut session = None;
            loop {
                let batch = tokio::select! {
                    message = inbound.message() => match message {
                        Ok(Some(batch)) => batch,
                        Ok(None) => break,
                        Err(status) => {
                            if let Some(refusal) = unreadable_batch(&status) {
                                shared.count_malformed();
                                tracing::warn!(
                                    actor = session.as_ref().map_or("(not yet known)", |(id, _): &(String, u64)| id.as_str()),
                                    code = ?refusal.code(),
                                    message = refusal.message(),
                                    "refused an unreadable step batch"
                                );
                                let _ = tx.send(Err(refusal)).await;
                            } else {
                                tracing::debug!(%status, "an actor's stream ended uncleanly");
                            }
                            break;
                        }
                    },
                    () = shared.stopped() => {
                        let _ = tx.send(Err(Status::unavailable("the learner is shutting down"))).await;
                        break;
                    }
                };
                let (s, t, token) = (shared.clone(), tx.clone(), token.clone());
                let arrived = std::time::Instant::now();
                let mut bound = session.clone();
                let result = tokio::task::spawn_blocking(move || {
                    let ack = match batch_from_wire(&batch, s.bounds()) {
                        Ok(batch) => s
                            .accept(batch, &mut bound, token.as_deref(), || t.is_closed())
                            .map(ack_to_wire)
                            .map_err(refusal_to_status),
                        Err(status) => {
                            s.count_malformed();
                            Err(status)
                        }
                    };
                    (ack, bound)
                })
                .await;
                shared
                    .timings()
                    .batch_seconds
                    .observe(arrived.elapsed().as_secs_f64());
                let Ok((ack, bound)) = result else {
                    let _ = tx
                        .send(Err(Status::internal("batch handling failed")))
                        .await;
                    break;
                };
                session = bound;
                let refused = ack.is_err();
                if tx.send(ack).await.is_err() || refused {
                    break;
                }
            }
            shared.stream_closed(session.as_ref());
        });
        let mut response =
            Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx)) as AckStream);
        response.metadata_mut().insert(
            tweezer_proto::MAX_MESSAGE_HEADER,
            self.max_message_bytes.into(),
        );
        Ok(response)
    }

    async fn get_snapshot(
        &self,
        request: Request<pb::SnapshotRequest>,
    ) -> Result<Response<ChunkStream>, Status> {
        let selector = selector(request.get_ref())?;
        let shared = self.shared.clone();
        let published = tokio::task::spawn_blocking(move || match shared.snapshots() {
            Some(snapshots) => snapshots.get(selector).map_err(Status::from),
            None => Err(Status::not_found(
                "this learner publishes no snapshots (it is not training)",
            )),
        })
        .await
        .map_err(|e| Status::internal(e.to_string()))??;
        let info = info_to_wire(&published);
        let chunks = (0..published.bytes.len().div_ceil(CHUNK_BYTES).max(1)).map(move |i| {
            let start = i * CHUNK_BYTES;
            let end = (start + CHUNK_BYTES).min(published.bytes.len());
            Ok(pb::SnapshotChunk {
                info: (i == 0).then(|| info.clone()),
                offset: start as u64,
                data: published.bytes[start..end].to_vec(),
            })
        });
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }

    async fn list_snapshots(
        &self,
        _request: Request<pb::ListSnapshotsRequest>,
    ) -> Result<Response<pb::SnapshotList>, Status> {
        let shared = self.shared.clone();
        let list = tokio::task::spawn_blocking(move || {
            let missing =
                || Status::not_found("this learner publishes no snapshots (it is not training)");
            let (kept, latest, best) = {
                let store = shared.snapshots().ok_or_else(missing)?;
                (
                    store.state().kept,
                    store.latest_version(),
                    store.best_version(),
                )
            };
            let mut snapshots = Vec::with_capacity(kept.len());
            for version in kept {
                let store = shared.snapshots().ok_or_else(missing)?;
                match store.get(Selector::Version(version)) {
                    Ok(published) => snapshots.push(info_to_wire(&published)),
                    // Pruned since the list was taken.
                    Err(SnapshotsError::NotFound(_)) => {}
                    Err(e) => return Err(Status::from(e)),
                }
            }
            Ok(pb::SnapshotList {
                snapshots,
                latest,
                best,
            })
        })
        .await
        .map_err(|e| Status::internal(e.to_string()))??;
        Ok(Response::new(list))
    }

    async fn get_status(
        &self,
        _request: Request<pb::LearnerStatusRequest>,
    ) -> Result<Response<pb::LearnerStatus>, Status> {
        Ok(Response::new(status_to_wire(self.shared.status())))
    }

    async fn pause_learning(
        &self,
        _request: Request<pb::PauseLearningRequest>,
    ) -> Result<Response<pb::LearnerStatus>, Status> {
        self.training_only()?;
        self.shared.set_paused(true);
        tracing::info!("learning paused by an operator");
        Ok(Response::new(status_to_wire(self.shared.status())))
    }

    async fn resume_learning(
        &self,
        _request: Request<pb::ResumeLearningRequest>,
    ) -> Result<Response<pb::LearnerStatus>, Status> {
        self.training_only()?;
        self.shared.set_paused(false);
        tracing::info!("learning resumed by an operator");
        Ok(Response::new(status_to_wire(self.shared.status())))
    }

    async fn checkpoint(
        &self,
        _request: Request<pb::CheckpointRequest>,
    ) -> Result<Response<pb::CheckpointReply>, Status> {
        self.training_only()?;
        let mut written = self.shared.request_checkpoint();
        tokio::time::timeout(CHECKPOINT_WAIT, written.changed())
            .await
            .map_err(|_| Status::deadline_exceeded("no checkpoint was written within two minutes"))?
            .map_err(|_| Status::unavailable("the learner is shutting down"))?;
        let outcome = written.borrow().clone();
        match outcome {
            Some(Ok(path)) => Ok(Response::new(pb::CheckpointReply {
                path: path.display().to_string(),
            })),
            Some(Err(reason)) => Err(Status::resource_exhausted(format!(
                "the checkpoint could not be written: {reason}. The learner goes on training and retries; the last good checkpoint is kept"
            ))),
            None => Err(Status::internal(
                "the trainer answered without a checkpoint",
            )),
        }
    }
}

/// How long Checkpoint waits for the trainer.
const CHECKPOINT_WAIT: std::time::Duration = std::time::Duration::from_secs(120);

impl LearnerService {
    /// Refuses calls that need a trainer on a learner without one.
    fn training_only(&self) -> Result<(), Status> {
        if self.shared.snapshots().is_none() {
            return Err(Status::failed_precondition(
                "this learner does not train (it only ingests)",
            ));
        }
        Ok(())
    }
}

/// The answer to an error reading an actor's stream when it is the batch
/// that cannot be read (not protobuf, or larger than the learner takes);
/// `None` when the stream itself broke (the actor went away).
fn unreadable_batch(status: &Status) -> Option<Status> {
    match status.code() {
        // tonic's decoder answers INTERNAL for bytes that are not a
        // StepBatch.
        Code::Internal => Some(Status::invalid_argument(format!(
            "the message is not a StepBatch: {}",
            status.message()
        ))),
        Code::OutOfRange | Code::ResourceExhausted => Some(Status::resource_exhausted(format!(
            "the StepBatch is larger than this learner takes: {}",
            status.message()
        ))),
        _ => None,
    }
}

/// An actor's batch from the wire, every field checked.
fn batch_from_wire(
    batch: &pb::StepBatch,
    bounds: &tweezer_gym::StepBounds,
) -> Result<ActorBatch, Status> {
    let (actor, sequence, steps) =
        tweezer_proto::step_batch_from_wire(batch, bounds, tweezer_proto::MAX_BATCH_STEPS)?;
    Ok(ActorBatch {
        actor,
        session: batch.session,
        sequence,
        steps,
    })
}

/// An acknowledgement on the wire.
fn ack_to_wire(ack: Ack) -> pb::StepAck {
    pb::StepAck {
        sequence: ack.sequence,
        snapshot_version: ack.snapshot_version,
        explore_uniformly: ack.explore_uniformly,
    }
}

/// A refused batch's gRPC status.
fn refusal_to_status(refusal: Refusal) -> Status {
    match refusal {
        Refusal::Malformed(reason) => Status::invalid_argument(reason),
        Refusal::NotYours(reason) => Status::permission_denied(reason),
        // Transient: sessions are forgotten as they go idle.
        Refusal::TooManySessions => Status::unavailable(refusal.to_string()),
        Refusal::Closed => Status::cancelled(refusal.to_string()),
        Refusal::ShuttingDown => Status::unavailable(refusal.to_string()),
    }
}

/// The learner's status on the wire.
fn status_to_wire(s: LearnerStatus) -> pb::LearnerStatus {
    pb::LearnerStatus {
        steps_inserted: s.steps_inserted,
        updates: s.training.updates,
        buffer_size: s.buffer_size as u64,
        buffer_capacity: s.buffer_capacity as u64,
        insert_rate: s.training.insert_rate,
        sample_rate: s.training.sample_rate,
        limiter_state: limiter_state_name(s.limiter).into(),
        connected_actors: s.connected_actors,
        rolling_return: s.rolling.mean_return,
        success_rate: s.rolling.success_rate,
        latest_snapshot: s.latest_snapshot,
        best_snapshot: s.best_snapshot,
        critic_loss: s.training.critic_loss,
        actor_loss: s.training.actor_loss,
        mean_q: s.training.mean_q,
        episodes: s.episodes,
        malformed_batches: s.malformed_batches,
        duplicate_batches: s.duplicate_batches,
        explore_uniformly: s.explore_uniformly,
        paused: s.paused,
        actors: s.actors.into_iter().map(actor_to_wire).collect(),
        diverged_updates: s.training.diverged_updates,
        known_actors: s.known_actors as u64,
    }
}

/// An actor's summary on the wire.
fn actor_to_wire(actor: ActorSummary) -> pb::ActorStatus {
    pb::ActorStatus {
        id: actor.id,
        session: actor.session,
        token: actor.token.unwrap_or_default(),
        streams: actor.streams,
        steps: actor.steps,
        episodes: actor.episodes,
        idle_seconds: actor.idle_seconds,
        last_sequence: actor.last_sequence,
    }
}

/// A published snapshot's metadata on the wire.
fn info_to_wire(published: &Published) -> pb::SnapshotInfo {
    let image = published.info.architecture.image();
    pb::SnapshotInfo {
        version: published.info.version,
        training_step: published.info.training_step,
        size_bytes: published.bytes.len() as u64,
        sha256: published.sha256.clone(),
        architecture: published.info.architecture.name().to_string(),
        image_width: image.map_or(0, |(_, w)| w as u32),
        image_height: image.map_or(0, |(h, _)| h as u32),
        network: published.info.architecture.to_string(),
    }
}
