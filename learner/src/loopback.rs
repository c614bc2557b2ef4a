//! A learner service on a loopback port, and step batches to feed it: for
//! the ingest benchmark and the tests, over real sockets.

use crate::learner_state::LearnerState;
use crate::service::LearnerService;
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::net::TcpListener;
use tokio_stream::wrappers::TcpListenerStream;
use tweezer_config::ConfigError;
use tweezer_gym::{EnvConfig, RandomSteps};
use tweezer_proto::pb;

/// Serves `shared` on an ephemeral loopback port; returns its address.
pub async fn serve(shared: Arc<LearnerState>) -> std::io::Result<SocketAddr> {
    let listener = TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(LearnerService::new(shared).into_server())
            .serve_with_incoming(TcpListenerStream::new(listener)),
    );
    Ok(addr)
}

/// `count` batches of `size` consecutive random-policy steps from `envs`
/// environments, as actor `actor` would send them.
pub fn batches(
    env: &EnvConfig,
    actor: &str,
    envs: usize,
    count: usize,
    size: usize,
    seed: u64,
) -> Result<Vec<pb::StepBatch>, ConfigError> {
    let mut steps = RandomSteps::new(env, envs, seed)?.map(|r| tweezer_proto::step_to_wire(&r));
    Ok((0..count)
        .map(|sequence| pb::StepBatch {
            actor_id: actor.to_string(),
            session: seed.wrapping_add(1),
            sequence: sequence as u64,
            steps: steps.by_ref().take(size).collect(),
        })
        .collect())
}
