//! A network partition between an actor and its learner: the actor streams
//! through a relay that goes silent (it drops every byte, and forgets the
//! connections it had), then forwards new connections again. The actor
//! must notice it lost the learner and stream again once the partition
//! ends, instead of waiting for ever on a connection that is gone.

use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tweezer_system_tests::{
    Running, TINY_ENV, binary, credentials, free_port, start_learner, status, wait_for_learner,
    write,
};

/// A TCP relay to `upstream` that a test can cut: while cut, it drops
/// every byte both ways; connections it had before a cut stay dropped
/// after it, as when a NAT or a firewall forgets them, and neither end
/// hears of the other closing.
struct Relay {
    cut: Arc<AtomicBool>,
    /// Bumped by every cut: connections of an older epoch are dead.
    epoch: Arc<AtomicU64>,
}

impl Relay {
    fn start(runtime: &tokio::runtime::Runtime, upstream: String) -> (Self, String) {
        let listener = runtime.block_on(TcpListener::bind("127.0.0.1:0")).unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let relay = Self {
            cut: Arc::default(),
            epoch: Arc::default(),
        };
        let (cut, epoch) = (relay.cut.clone(), relay.epoch.clone());
        runtime.spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                let (cut, epoch, upstream) = (cut.clone(), epoch.clone(), upstream.clone());
                tokio::spawn(async move {
                    let born = epoch.load(Ordering::SeqCst);
                    let live =
                        move || !cut.load(Ordering::SeqCst) && epoch.load(Ordering::SeqCst) == born;
                    if !live() {
                        // Accepted into the void.
                        let _held = client;
                        tokio::time::sleep(Duration::from_secs(600)).await;
                        return;
                    }
                    let Ok(server) = TcpStream::connect(&upstream).await else {
                        return;
                    };
                    let (client_read, client_write) = client.into_split();
                    let (server_read, server_write) = server.into_split();
                    let live = Arc::new(live);
                    tokio::join!(
                        pump(client_read, server_write, live.clone()),
                        pump(server_read, client_write, live),
                    );
                });
            }
        });
        (relay, addr)
    }

    fn set_cut(&self, cut: bool) {
        if cut {
            self.epoch.fetch_add(1, Ordering::SeqCst);
        }
        self.cut.store(cut, Ordering::SeqCst);
    }
}

/// Copies `from` to `to` while `live` says so, and drops what arrives
/// otherwise. A forgotten connection passes nothing on, its end either:
/// `to` is held open for as long as the relay runs.
async fn pump(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    live: Arc<impl Fn() -> bool>,
) {
    let mut buffer = vec![0u8; 64 << 10];
    loop {
        let n = match from.read(&mut buffer).await {
            Ok(0) | Err(_) if live() => return,
            Ok(0) | Err(_) => {
                tokio::time::sleep(Duration::from_secs(600)).await;
                drop(to);
                return;
            }
            Ok(n) => n,
        };
        if live() && to.write_all(&buffer[..n]).await.is_err() {
            return;
        }
    }
}

#[test]
fn an_actor_streams_again_after_a_silent_partition() {
    let dir = tempfile::tempdir().unwrap();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let learner_addr = format!("127.0.0.1:{}", free_port());
    let learner_config = write(
        &dir.path().join("learner.toml"),
        &format!(
            "{TINY_ENV}\n[learner]\nlisten = \"{learner_addr}\"\nuniform_steps = 300\n\
             [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n"
        ),
    );
    let (learner, _) = start_learner(&[
        "--config",
        &learner_config,
        "--run-dir",
        dir.path().join("run").to_str().unwrap(),
    ]);
    let learner = Running::new(learner);
    let (relay, relay_addr) = Relay::start(&runtime, learner_addr.clone());
    let actor_config = write(
        &dir.path().join("actor.toml"),
        &format!(
            "{TINY_ENV}\n[actor]\nlearner = \"{relay_addr}\"\nenvs = 4\nbatch_steps = 50\n\
             reconnect_initial_ms = 50\nreconnect_max_ms = 1000\n"
        ),
    );
    let log = dir.path().join("actor.log");
    let actor = Running::new(
        Command::new(binary("actor"))
            .args(["--config", &actor_config, "run"])
            .args(["--security", &credentials().file("actor")])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap(),
    );
    let limit = Duration::from_secs(120);
    wait_for_learner(&runtime, &learner_addr, "storing steps", limit, |s| {
        s.steps_inserted >= 500
    });

    relay.set_cut(true);
    std::thread::sleep(Duration::from_secs(12));
    relay.set_cut(false);
    let healed = Instant::now();
    let before = status(&runtime, &learner_addr).unwrap().steps_inserted;
    let resumed = wait_for_learner(
        &runtime,
        &learner_addr,
        "storing steps again after the partition",
        Duration::from_secs(45),
        |s| s.steps_inserted >= before + 500,
    );
    eprintln!(
        "steps flowed again {:.1} s after the partition ended ({} -> {})",
        healed.elapsed().as_secs_f64(),
        before,
        resumed.steps_inserted
    );
    drop(actor);
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("lost the learner"), "{text}");
    assert!(learner.stop().0.success());
}
