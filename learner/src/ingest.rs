//! The edge where actors' steps enter: the `Learner` gRPC service's
//! `StreamSteps` and `GetStatus`. Batches are validated whole before any
//! step touches the replay; a malformed batch is refused with
//! INVALID_ARGUMENT, counted, and ends that stream.

use crate::limiter::SharedLimiter;
use crate::replay::{Replay, Source};
use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};
use tweezer_gym::ObservationBounds;
use tweezer_proto::pb;
use tweezer_proto::pb::learner_server::Learner;

/// Most steps one batch may carry.
pub const MAX_BATCH_STEPS: usize = 4096;

/// What the service shares with the learner's other threads.
#[derive(Debug)]
pub struct Ingest {
    replay: Mutex<Replay>,
    /// `None` while learning is paused: inserts are not rate limited.
    limiter: Option<SharedLimiter>,
    bounds: ObservationBounds,
    sources: Mutex<HashMap<String, Source>>,
    connected: AtomicU32,
    malformed: AtomicU64,
    snapshot_version: AtomicU64,
    explore_uniformly: AtomicBool,
}

impl Ingest {
    /// Ingestion into `replay`, rate limited by `limiter` when given.
    pub fn new(replay: Replay, limiter: Option<SharedLimiter>, bounds: ObservationBounds) -> Self {
        Self {
            replay: Mutex::new(replay),
            limiter,
            bounds,
            sources: Mutex::new(HashMap::new()),
            connected: AtomicU32::new(0),
            malformed: AtomicU64::new(0),
            snapshot_version: AtomicU64::new(0),
            explore_uniformly: AtomicBool::new(true),
        }
    }

    /// The replay.
    pub fn replay(&self) -> MutexGuard<'_, Replay> {
        self.replay.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Batches refused as malformed.
    pub fn malformed(&self) -> u64 {
        self.malformed.load(Ordering::Relaxed)
    }

    fn source(&self, actor: &str) -> Source {
        let mut sources = self.sources.lock().unwrap_or_else(|p| p.into_inner());
        let next = sources.len() as Source;
        *sources.entry(actor.to_string()).or_insert(next)
    }

    /// Validates and stores one batch, waiting for the rate limiter.
    fn accept(&self, batch: &pb::StepBatch) -> Result<pb::StepAck, Status> {
        let (actor, sequence, steps) =
            tweezer_proto::step_batch_from_wire(batch, &self.bounds, MAX_BATCH_STEPS).inspect_err(
                |_| {
                    self.malformed.fetch_add(1, Ordering::Relaxed);
                },
            )?;
        let source = self.source(&actor);
        if let Some(limiter) = &self.limiter {
            while !limiter.wait_to_insert(steps.len() as u64, Duration::from_millis(200)) {}
        }
        let len = {
            let mut replay = self.replay();
            for step in &steps {
                replay
                    .insert(source, step)
                    .map_err(|e| Status::invalid_argument(e.to_string()))?;
            }
            replay.len()
        };
        if let Some(limiter) = &self.limiter {
            limiter.replay_len(len);
        }
        Ok(pb::StepAck {
            sequence,
            snapshot_version: self.snapshot_version.load(Ordering::Relaxed),
            explore_uniformly: self.explore_uniformly.load(Ordering::Relaxed),
        })
    }
}

/// The `Learner` service over shared ingestion state.
#[derive(Debug, Clone)]
pub struct LearnerService {
    ingest: Arc<Ingest>,
}

impl LearnerService {
    /// The service for `ingest`.
    pub fn new(ingest: Arc<Ingest>) -> Self {
        Self { ingest }
    }
}

type AckStream = Pin<Box<dyn Stream<Item = Result<pb::StepAck, Status>> + Send>>;
type ChunkStream = Pin<Box<dyn Stream<Item = Result<pb::SnapshotChunk, Status>> + Send>>;

#[tonic::async_trait]
impl Learner for LearnerService {
    type StreamStepsStream = AckStream;
    type GetSnapshotStream = ChunkStream;

    async fn stream_steps(
        &self,
        request: Request<Streaming<pb::StepBatch>>,
    ) -> Result<Response<AckStream>, Status> {
        let mut inbound = request.into_inner();
        let ingest = self.ingest.clone();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            ingest.connected.fetch_add(1, Ordering::Relaxed);
            while let Ok(Some(batch)) = inbound.message().await {
                let shared = ingest.clone();
                let ack = tokio::task::spawn_blocking(move || shared.accept(&batch))
                    .await
                    .unwrap_or_else(|e| Err(Status::internal(e.to_string())));
                let refused = ack.is_err();
                if tx.send(ack).await.is_err() || refused {
                    break;
                }
            }
            ingest.connected.fetch_sub(1, Ordering::Relaxed);
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }

    async fn get_snapshot(
        &self,
        _request: Request<pb::SnapshotRequest>,
    ) -> Result<Response<ChunkStream>, Status> {
        Err(Status::not_found(
            "no policy snapshot has been published: this learner does not train yet",
        ))
    }

    async fn get_status(
        &self,
        _request: Request<pb::LearnerStatusRequest>,
    ) -> Result<Response<pb::LearnerStatus>, Status> {
        let i = &self.ingest;
        let (len, capacity, inserted) = {
            let replay = i.replay();
            (replay.len(), replay.capacity(), replay.inserted())
        };
        let limiter_state = match &i.limiter {
            Some(l) => format!("{:?}", l.snapshot().1),
            None => "learning paused".into(),
        };
        Ok(Response::new(pb::LearnerStatus {
            steps_inserted: inserted,
            buffer_size: len as u64,
            buffer_capacity: capacity as u64,
            limiter_state,
            connected_actors: i.connected.load(Ordering::Relaxed),
            ..pb::LearnerStatus::default()
        }))
    }
}
