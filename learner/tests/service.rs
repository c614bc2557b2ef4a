//! Actors' steps over real gRPC on loopback: acknowledgements, status,
//! malformed batches refused without touching the replay, many streams.

use std::net::SocketAddr;
use std::sync::Arc;
use tokio::net::TcpListener;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::Code;
use tweezer_gym::{EnvConfig, StepBounds};
use tweezer_learner::bench::random_batches as batches;
use tweezer_learner::ingest::service::LearnerService;
use tweezer_learner::replay::{Replay, ReplayConfig};
use tweezer_learner::state::LearnerState;
use tweezer_proto::pb;
use tweezer_proto::pb::learner_client::LearnerClient;

fn ingest() -> Arc<LearnerState> {
    let replay = Replay::new(ReplayConfig {
        capacity: 100_000,
        ..ReplayConfig::default()
    });
    Arc::new(LearnerState::new(
        replay,
        None,
        StepBounds::for_config(&EnvConfig::default()),
    ))
}

/// Serves `shared` on an ephemeral loopback port; returns its address.
async fn serve(shared: Arc<LearnerState>) -> std::io::Result<SocketAddr> {
    let listener = TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(LearnerService::new(shared).into_server())
            .serve_with_incoming(TcpListenerStream::new(listener)),
    );
    Ok(addr)
}

type Client = LearnerClient<tonic::transport::Channel>;
type Sender = tokio::sync::mpsc::Sender<pb::StepBatch>;

/// A learner on loopback and a client connected to it.
async fn connected() -> (Arc<LearnerState>, Client) {
    let ingest = ingest();
    let addr = serve(ingest.clone()).await.unwrap();
    let client = LearnerClient::connect(format!("http://{addr}"))
        .await
        .unwrap();
    (ingest, client)
}

/// Opens a `StreamSteps` call fed through a channel.
async fn open(client: &mut Client) -> (Sender, tonic::Streaming<pb::StepAck>) {
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let acks = client
        .stream_steps(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    (tx, acks)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batches_are_acknowledged_in_order_and_counted() {
    let (_ingest, mut client) = connected().await;
    let sent = batches(&EnvConfig::default(), "actor-a", 4, 10, 32, 1).unwrap();
    let (tx, mut acks) = open(&mut client).await;
    for batch in sent {
        let sequence = batch.sequence;
        tx.send(batch).await.unwrap();
        let ack = acks.message().await.unwrap().unwrap();
        assert_eq!(ack.sequence, sequence);
        assert!(ack.explore_uniformly);
    }
    let status = client
        .get_status(pb::LearnerStatusRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(status.connected_actors, 1);
    // 320 steps from 4 environments: all but each environment's last are
    // complete transitions (episode ends complete at once).
    assert!(
        status.buffer_size >= 316 && status.buffer_size <= 320,
        "{status:?}"
    );
    assert_eq!(status.steps_inserted, 320);
    assert_eq!(status.buffer_capacity, 100_000);
    drop(tx);
    assert!(
        acks.message().await.unwrap().is_none(),
        "the stream ends with the actor's"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_batches_are_refused_and_never_touch_the_replay() {
    let (ingest, mut client) = connected().await;
    let good = batches(&EnvConfig::default(), "actor-b", 2, 3, 16, 2).unwrap();
    let mut cases = Vec::new();
    let mut nan = good[1].clone();
    nan.steps[5].reward = f32::NAN;
    cases.push((nan, "steps[5].reward"));
    let mut odd = good[1].clone();
    odd.steps[0].observation.as_mut().unwrap().centres.push(1.0);
    cases.push((odd, "steps[0].observation.centres"));
    let mut fast = good[1].clone();
    fast.steps[3].action.as_mut().unwrap().x = 1.5;
    cases.push((fast, "steps[3].action"));
    let mut anonymous = good[1].clone();
    anonymous.actor_id.clear();
    cases.push((anonymous, "actor_id"));
    let mut spaced = good[1].clone();
    spaced.actor_id = "actor b".into();
    cases.push((spaced, "actor_id"));
    let mut stranger = good[1].clone();
    stranger.actor_id = "actor-c".into();
    cases.push((stranger, "on a stream opened by `actor-b`"));

    for (i, (bad, field)) in cases.into_iter().enumerate() {
        let (tx, mut acks) = open(&mut client).await;
        let before = ingest.replay().inserted();
        tx.send(good[0].clone()).await.unwrap();
        acks.message().await.unwrap().unwrap();
        let after_good = ingest.replay().inserted();
        tx.send(bad).await.unwrap();
        let status = acks.message().await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(status.message().contains(field), "{}", status.message());
        assert_eq!(
            ingest.replay().inserted(),
            after_good,
            "the replay was touched"
        );
        assert!(after_good >= before);
        assert_eq!(ingest.malformed(), i as u64 + 1);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn eight_concurrent_streams_all_land() {
    let ingest = ingest();
    let addr = serve(ingest.clone()).await.unwrap();
    let tasks: Vec<_> = (0..8)
        .map(|k| {
            tokio::spawn(async move {
                let mut client = LearnerClient::connect(format!("http://{addr}"))
                    .await
                    .unwrap();
                let sent =
                    batches(&EnvConfig::default(), &format!("actor-{k}"), 2, 20, 25, k).unwrap();
                let n = sent.len();
                let stream = tokio_stream::iter(sent);
                let mut acks = client.stream_steps(stream).await.unwrap().into_inner();
                let mut count = 0;
                while let Some(ack) = acks.message().await.unwrap() {
                    assert_eq!(ack.sequence, count);
                    count += 1;
                }
                assert_eq!(count as usize, n);
            })
        })
        .collect();
    for t in tasks {
        t.await.unwrap();
    }
    // 8 actors x 500 steps, minus at most one pending step per environment.
    let len = ingest.replay().len();
    assert!((3_984..=4_000).contains(&len), "{len}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_batch_resent_after_a_reconnect_is_acknowledged_not_stored_again() {
    let (ingest, mut client) = connected().await;
    let sent = batches(&EnvConfig::default(), "actor-d", 2, 3, 10, 4).unwrap();
    let (tx, mut acks) = open(&mut client).await;
    for batch in &sent[..2] {
        tx.send(batch.clone()).await.unwrap();
        acks.message().await.unwrap().unwrap();
    }
    drop((tx, acks));
    let stored = ingest.steps_inserted();
    assert_eq!(stored, 20);

    // The actor reconnects and resends batch 1, which it never saw acked.
    let (tx, mut acks) = open(&mut client).await;
    for batch in &sent[1..] {
        tx.send(batch.clone()).await.unwrap();
        let ack = acks.message().await.unwrap().unwrap();
        assert_eq!(ack.sequence, batch.sequence);
    }
    assert_eq!(ingest.duplicates(), 1);
    assert_eq!(
        ingest.steps_inserted(),
        30,
        "batch 2 stored, batch 1 not twice"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_producer_held_by_back_pressure_is_released_when_its_actor_goes() {
    use tweezer_learner::ingest::limiter::{Limiter, LimiterConfig};
    // Learning starts at 10 transitions and may owe at most 5 updates; no
    // learner runs, so the second batch must wait.
    let limiter = Limiter::new(LimiterConfig {
        min_size: 10,
        slack: 5.0,
        ..LimiterConfig::default()
    });
    let shared = Arc::new(LearnerState::new(
        Replay::new(ReplayConfig::default()),
        Some(limiter),
        StepBounds::for_config(&EnvConfig::default()),
    ));
    let addr = serve(shared.clone()).await.unwrap();
    let mut client = LearnerClient::connect(format!("http://{addr}"))
        .await
        .unwrap();
    let sent = batches(&EnvConfig::default(), "actor-e", 1, 3, 20, 5).unwrap();
    let (tx, mut acks) = open(&mut client).await;
    tx.send(sent[0].clone()).await.unwrap();
    acks.message().await.unwrap().unwrap();
    tx.send(sent[1].clone()).await.unwrap();
    let waited = tokio::time::timeout(std::time::Duration::from_millis(500), acks.message()).await;
    assert!(waited.is_err(), "the second batch is held back");
    assert_eq!(shared.connected(), 1);

    drop((tx, acks, client));
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    while shared.connected() > 0 {
        assert!(
            std::time::Instant::now() < deadline,
            "the held producer never gave up"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_eq!(shared.steps_inserted(), 20, "the held batch was not stored");
}

/// Sends each message's bytes as they are: what a client that does not
/// speak protobuf, or sends more than a learner takes, puts on the wire.
#[derive(Clone, Copy, Default)]
struct RawBytes;

struct RawEncoder;

impl tonic::codec::Encoder for RawEncoder {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn encode(
        &mut self,
        item: Vec<u8>,
        dst: &mut tonic::codec::EncodeBuf<'_>,
    ) -> Result<(), tonic::Status> {
        bytes::BufMut::put_slice(dst, &item);
        Ok(())
    }
}

impl tonic::codec::Codec for RawBytes {
    type Encode = Vec<u8>;
    type Decode = pb::StepAck;
    type Encoder = RawEncoder;
    type Decoder =
        <tonic_prost::ProstCodec<pb::StepBatch, pb::StepAck> as tonic::codec::Codec>::Decoder;

    fn encoder(&mut self) -> RawEncoder {
        RawEncoder
    }

    fn decoder(&mut self) -> Self::Decoder {
        tonic::codec::Codec::decoder(
            &mut tonic_prost::ProstCodec::<pb::StepBatch, pb::StepAck>::default(),
        )
    }
}

/// Opens `StreamSteps` on `client`'s learner and sends `message` as raw
/// bytes; the first answer.
async fn raw_stream_steps(addr: std::net::SocketAddr, message: Vec<u8>) -> tonic::Status {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.unwrap();
    let path = http::uri::PathAndQuery::from_static("/tweezer.v1.Learner/StreamSteps");
    let request = tonic::Request::new(tokio_stream::iter(vec![message]));
    let mut answers = grpc
        .streaming(request, path, RawBytes)
        .await
        .unwrap()
        .into_inner();
    match answers.message().await {
        Err(status) => status,
        Ok(answer) => panic!("the learner answered {answer:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unreadable_batches_are_refused_with_their_status_and_counted() {
    let ingest = ingest();
    let addr = serve(ingest.clone()).await.unwrap();

    // Eight bytes that are not protobuf.
    let status = raw_stream_steps(addr, vec![0xff; 8]).await;
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("not a StepBatch"), "{status:?}");
    assert_eq!(ingest.malformed(), 1);

    // More than gRPC's default 4 MiB in one message.
    let status = raw_stream_steps(addr, vec![0; 5 << 20]).await;
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("larger than"), "{status:?}");
    assert_eq!(ingest.malformed(), 2);

    // Nothing reached the replay, and a good batch still goes in.
    assert_eq!(ingest.replay().len(), 0);
    let mut client = LearnerClient::connect(format!("http://{addr}"))
        .await
        .unwrap();
    let (tx, mut acks) = open(&mut client).await;
    let batch = batches(&EnvConfig::default(), "actor-a", 1, 1, 8, 1).unwrap();
    tx.send(batch[0].clone()).await.unwrap();
    assert_eq!(acks.message().await.unwrap().unwrap().sequence, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reward_no_environment_can_give_is_refused_naming_the_range() {
    let (ingest, mut client) = connected().await;
    let mut batch = batches(&EnvConfig::default(), "actor-r", 1, 1, 16, 7).unwrap()[0].clone();
    batch.steps[3].reward = 1e30;
    let (tx, mut acks) = open(&mut client).await;
    tx.send(batch).await.unwrap();
    let status = acks.message().await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(
        status.message().contains("steps[3].reward") && status.message().contains("outside ["),
        "{}",
        status.message()
    );
    assert_eq!((ingest.malformed(), ingest.steps_inserted()), (1, 0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_session_can_silence_another_and_a_restarted_actor_counts_afresh() {
    let (ingest, mut client) = connected().await;
    let sent = batches(&EnvConfig::default(), "victim", 1, 4, 8, 9).unwrap();
    let send = |client: &mut Client, batch: pb::StepBatch| {
        let mut client = client.clone();
        async move {
            let (tx, mut acks) = open(&mut client).await;
            tx.send(batch).await.unwrap();
            acks.message().await.unwrap().unwrap()
        }
    };
    // Another client claims the victim's id with the largest sequence, in
    // its own session.
    let mut poison = sent[0].clone();
    poison.session = 666;
    poison.sequence = u64::MAX;
    send(&mut client, poison).await;
    assert_eq!(ingest.steps_inserted(), 8);

    // The victim's batches are all stored.
    for batch in &sent[..2] {
        send(&mut client, batch.clone()).await;
    }
    assert_eq!((ingest.steps_inserted(), ingest.duplicates()), (24, 0));

    // Restarted (a new session) with a clock that stepped back: sequences
    // start low again, and are stored.
    let mut restarted = sent[2].clone();
    restarted.session = 4242;
    restarted.sequence = 0;
    send(&mut client, restarted).await;
    assert_eq!((ingest.steps_inserted(), ingest.duplicates()), (32, 0));

    // Within a session, a resent batch is still recognised.
    send(&mut client, sent[1].clone()).await;
    assert_eq!((ingest.steps_inserted(), ingest.duplicates()), (32, 1));
}

#[test]
fn a_session_stays_with_the_token_that_opened_it() {
    use tweezer_learner::ingest::batch::{ActorBatch, Refusal};
    let ingest = ingest();
    let steps = tweezer_gym::RandomSteps::new(&EnvConfig::default(), 1, 3)
        .unwrap()
        .take(4)
        .collect::<Vec<_>>();
    let batch = |session, sequence| ActorBatch {
        actor: "lab-pc".into(),
        session,
        sequence,
        steps: steps.clone(),
    };
    let accept = |batch, token| ingest.accept(batch, &mut None, Some(token), || false);
    accept(batch(7, 1), "actor-a").unwrap();
    let refused = accept(batch(7, 2), "actor-b").unwrap_err();
    assert!(
        matches!(&refused, Refusal::NotYours(m) if m.contains("`actor-a`")),
        "{refused:?}"
    );
    accept(batch(7, 2), "actor-a").unwrap();
    accept(batch(8, 1), "actor-b").unwrap();
    // Session 0 remembers nothing, so any token may use it.
    accept(batch(0, 1), "actor-a").unwrap();
    accept(batch(0, 1), "actor-b").unwrap();
    assert_eq!(ingest.steps_inserted(), 20);
    let tokens: Vec<_> = (ingest.status().actors.into_iter())
        .map(|a| (a.session, a.token))
        .collect();
    assert!(tokens.contains(&(7, Some("actor-a".into()))), "{tokens:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thousands_of_actor_ids_leave_the_registry_bounded_and_the_status_small() {
    use tonic_prost::prost::Message;
    use tweezer_learner::ingest::batch::ActorBatch;
    use tweezer_learner::ingest::sessions::{MAX_SESSIONS, STATUS_ACTORS};
    let (ingest, mut client) = connected().await;
    let step = tweezer_gym::RandomSteps::new(&EnvConfig::default(), 1, 3)
        .unwrap()
        .next()
        .unwrap();
    let n = 30_000;
    let state = ingest.clone();
    tokio::task::spawn_blocking(move || {
        for k in 0..n {
            let batch = ActorBatch {
                actor: format!("actor-{k:05}-with-a-long-pod-name-for-good-measure"),
                session: k + 1,
                sequence: 1,
                steps: vec![step.clone()],
            };
            let mut stream = None;
            state.stream_opened();
            state.accept(batch, &mut stream, None, || false).unwrap();
            state.stream_closed(stream.as_ref());
        }
    })
    .await
    .unwrap();
    let status = client
        .get_status(pb::LearnerStatusRequest {})
        .await
        .unwrap()
        .into_inner();
    let known = status.known_actors as usize;
    assert!(
        (MAX_SESSIONS * 9 / 10..=MAX_SESSIONS).contains(&known),
        "{known}"
    );
    assert_eq!(status.actors.len(), STATUS_ACTORS);
    assert!(
        status.encoded_len() < 64 << 10,
        "{} bytes",
        status.encoded_len()
    );
    // The newest are kept; the oldest were forgotten.
    assert!(
        status.actors.iter().all(|a| a.session > n - known as u64),
        "{:?}",
        status.actors.first()
    );
    assert_eq!(ingest.steps_inserted(), n);
}
