//! The learner's HTTP/2 edge, spoken to directly rather than through a
//! gRPC client: a connection that makes the server reset stream after
//! stream ("MadeYouReset", CVE-2025-8671) is closed with GOAWAY, and
//! GetSnapshot streams whose reader never opens its window are bounded
//! per connection, and so is the memory they hold.

use bytes::Bytes;
use prost::Message;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::Duration;
use tweezer_proto::pb;
use tweezer_system_tests::{
    Running, TINY_ENV, credentials, learner_status, start_learner_with, write,
};

/// A plaintext learner (so that the test writes HTTP/2 frames itself) on
/// the tiny environment.
fn start_plain_learner(dir: &Path) -> (Running, String) {
    let config = write(
        &dir.join("learner.toml"),
        &format!("{TINY_ENV}\n[learner]\nlisten = \"127.0.0.1:0\"\n"),
    );
    let (child, addr) = start_learner_with(
        &credentials().file("server-plain"),
        &config,
        &dir.join("run"),
        Some(&dir.join("learner.log")),
    );
    (Running::new(child), addr)
}

/// One HTTP/2 frame.
fn frame(kind: u8, flags: u8, stream: u32, payload: &[u8]) -> Vec<u8> {
    let length = (payload.len() as u32).to_be_bytes();
    let mut frame = vec![length[1], length[2], length[3], kind, flags];
    frame.extend_from_slice(&stream.to_be_bytes());
    frame.extend_from_slice(payload);
    frame
}

const HEADERS: u8 = 0x1;
const RST_STREAM: u8 = 0x3;
const SETTINGS: u8 = 0x4;
const GOAWAY: u8 = 0x7;
const WINDOW_UPDATE: u8 = 0x8;
const END_HEADERS: u8 = 0x4;
const ACK: u8 = 0x1;
const ENHANCE_YOUR_CALM: u32 = 0xb;

/// A header block of HPACK literals (not indexed, no Huffman coding), each
/// name and value shorter than 127 bytes.
fn header_block(fields: &[(&str, &str)]) -> Vec<u8> {
    let mut block = Vec::new();
    for (name, value) in fields {
        block.push(0x00);
        block.push(name.len() as u8);
        block.extend_from_slice(name.as_bytes());
        block.push(value.len() as u8);
        block.extend_from_slice(value.as_bytes());
    }
    block
}

/// What the server sent on a raw connection: resets, and the GOAWAY's
/// error code if one came.
#[derive(Default)]
struct Heard {
    resets: usize,
    goaway: Option<u32>,
}

/// Reads frames until the connection ends or a GOAWAY comes, answering
/// the server's SETTINGS.
fn listen(mut reader: TcpStream, writer: Arc<Mutex<TcpStream>>) -> Heard {
    let mut heard = Heard::default();
    let mut head = [0u8; 9];
    while reader.read_exact(&mut head).is_ok() {
        let length = u32::from_be_bytes([0, head[0], head[1], head[2]]) as usize;
        let mut payload = vec![0u8; length];
        if reader.read_exact(&mut payload).is_err() {
            break;
        }
        match head[3] {
            SETTINGS if head[4] & ACK == 0 => {
                let _ = writer
                    .lock()
                    .unwrap()
                    .write_all(&frame(SETTINGS, ACK, 0, &[]));
            }
            RST_STREAM => heard.resets += 1,
            GOAWAY => {
                heard.goaway = Some(u32::from_be_bytes(payload[4..8].try_into().unwrap()));
                break;
            }
            _ => {}
        }
    }
    heard
}

#[test]
fn a_connection_that_makes_the_server_reset_streams_is_closed_with_goaway() {
    let dir = tempfile::tempdir().unwrap();
    let (learner, addr) = start_plain_learner(dir.path());
    let stream = TcpStream::connect(&addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let writer = Arc::new(Mutex::new(stream.try_clone().unwrap()));
    let reader = {
        let writer = writer.clone();
        std::thread::spawn(move || listen(stream, writer))
    };
    let mut hello = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    hello.extend(frame(SETTINGS, 0, 0, &[]));
    writer.lock().unwrap().write_all(&hello).unwrap();

    // Each stream opens with a request, then gets a WINDOW_UPDATE that
    // overflows its window: a stream error the server answers with its
    // own RST_STREAM. 4,000 of them, unless the server stops it first.
    let block = header_block(&[
        (":method", "POST"),
        (":scheme", "http"),
        (":path", "/tweezer.v1.Learner/GetStatus"),
        (":authority", "learner"),
        ("content-type", "application/grpc"),
        ("te", "trailers"),
    ]);
    let mut sent = 0;
    'sending: for batch in 0..80u32 {
        let mut bytes = Vec::new();
        for i in 0..50u32 {
            let id = 2 * (batch * 50 + i) + 1;
            bytes.extend(frame(HEADERS, END_HEADERS, id, &block));
            bytes.extend(frame(WINDOW_UPDATE, 0, id, &0x7fff_ffffu32.to_be_bytes()));
        }
        if writer.lock().unwrap().write_all(&bytes).is_err() {
            break 'sending;
        }
        sent += 50;
        if reader.is_finished() {
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let _ = writer.lock().unwrap().shutdown(std::net::Shutdown::Write);
    let heard = reader.join().unwrap();
    eprintln!(
        "sent {sent} streams; the server reset {} and sent GOAWAY {:?}",
        heard.resets, heard.goaway
    );
    assert_eq!(
        heard.goaway,
        Some(ENHANCE_YOUR_CALM),
        "no GOAWAY after {sent} streams the server had to reset ({} resets)",
        heard.resets
    );
    assert!(heard.resets <= tweezer_rpc::MAX_LOCAL_ERROR_RESETS + 50);

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime
        .block_on(learner_status(&addr, "read-plain"))
        .expect("other clients are served");
    let (status, _) = learner.stop();
    assert!(status.success());
}

/// The resident memory of process `pid`, bytes.
fn resident_bytes(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    let kib: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kib * 1024
}

/// A gRPC message: the uncompressed flag, the length, the bytes.
fn grpc_message(message: &impl Message) -> Bytes {
    let body = message.encode_to_vec();
    let mut framed = vec![0u8];
    framed.extend_from_slice(&(body.len() as u32).to_be_bytes());
    framed.extend(body);
    Bytes::from(framed)
}

#[test]
fn snapshot_streams_nobody_reads_are_bounded_per_connection() {
    let dir = tempfile::tempdir().unwrap();
    let (learner, addr) = start_plain_learner(dir.path());
    let token = std::fs::read_to_string(credentials().dir.join("read.token")).unwrap();
    let pid = learner.child().id();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let size = runtime.block_on(async {
        let status = learner_status(&addr, "read-plain").await.unwrap();
        assert!(status.latest_snapshot > 0, "a first snapshot is published");
        status.latest_snapshot
    });
    assert!(size > 0);
    let before = resident_bytes(pid);

    const CONNECTIONS: usize = 4;
    const REQUESTS: usize = 150;
    let accepted = Arc::new(AtomicUsize::new(0));
    let (hold_tx, hold_rx) = mpsc::channel();
    runtime.block_on(async {
        for _ in 0..CONNECTIONS {
            let tcp = tokio::net::TcpStream::connect(&addr).await.unwrap();
            let (client, connection) = h2::client::Builder::new()
                .initial_window_size(1)
                .handshake::<_, Bytes>(tcp)
                .await
                .unwrap();
            tokio::spawn(connection);
            for _ in 0..REQUESTS {
                let ready = tokio::time::timeout(Duration::from_secs(2), client.clone().ready());
                let Ok(Ok(mut client)) = ready.await else {
                    break;
                };
                let request =
                    http::Request::post(format!("http://{addr}/tweezer.v1.Learner/GetSnapshot"))
                        .header("content-type", "application/grpc")
                        .header("te", "trailers")
                        .header("authorization", format!("Bearer {}", token.trim()))
                        .body(())
                        .unwrap();
                let Ok((response, mut send)) = client.send_request(request, false) else {
                    break;
                };
                let latest = pb::SnapshotRequest {
                    selector: Some(pb::snapshot_request::Selector::Tag(
                        pb::SnapshotTag::Latest as i32,
                    )),
                };
                let _ = send.send_data(grpc_message(&latest), true);
                let (accepted, hold) = (accepted.clone(), hold_tx.clone());
                tokio::spawn(async move {
                    if let Ok(response) = response.await {
                        accepted.fetch_add(1, Ordering::SeqCst);
                        // Held, never read: its window stays at one byte.
                        let _ = hold.send((response, send));
                    }
                });
            }
        }
        tokio::time::sleep(Duration::from_secs(2)).await;
    });
    let accepted = accepted.load(Ordering::SeqCst);
    let grown = resident_bytes(pid).saturating_sub(before);
    eprintln!(
        "{accepted} unread GetSnapshot streams on {CONNECTIONS} connections; the learner grew by {:.1} MiB",
        grown as f64 / (1 << 20) as f64
    );
    let per_connection = tweezer_rpc::MAX_CONCURRENT_STREAMS as usize;
    assert!(
        accepted <= CONNECTIONS * per_connection,
        "{accepted} streams accepted on {CONNECTIONS} connections: no per-connection bound"
    );
    assert!(
        grown < 64 << 20,
        "the learner grew by {grown} bytes for {accepted} unread streams"
    );
    drop(hold_rx);
    let (status, _) = learner.stop();
    assert!(status.success());
}
