//! A foreign client: Python stubs generated from `proto/` by grpcio-tools
//! (installed from PyPI into a fresh virtual environment) call a real
//! learner's status and health with the real grpcio client over TLS with a
//! token; its Prometheus endpoint, the hardware agent's and an actor's are
//! parsed by the reference OpenMetrics parser.

use serde_json::Value;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use tweezer_system_tests::{
    TINY_ENV, binary, check, credentials, free_port, python_venv, start_agent, start_learner, stop,
    write,
};

#[test]
fn a_python_grpcio_client_reads_the_learner_over_tls_with_a_token() {
    let dir = tempfile::tempdir().unwrap();
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    let bin = python_venv(dir.path(), "requirements.txt");
    let python = bin.join("python");
    let stubs = dir.path().join("stubs");
    std::fs::create_dir_all(&stubs).unwrap();
    let proto = here.join("../proto");
    let mut protoc = vec![
        "-m".to_string(),
        "grpc_tools.protoc".into(),
        format!("-I{}", proto.display()),
        format!("--python_out={}", stubs.display()),
        format!("--grpc_python_out={}", stubs.display()),
    ];
    for name in ["common", "learner", "hardware_agent"] {
        protoc.push(
            proto
                .join(format!("tweezer/v1/{name}.proto"))
                .display()
                .to_string(),
        );
    }
    let protoc: Vec<&str> = protoc.iter().map(String::as_str).collect();
    check(&python, &protoc);

    let config = write(
        &dir.path().join("learner.toml"),
        &format!("{TINY_ENV}\n[learner]\nlisten = \"127.0.0.1:0\"\n"),
    );
    let metrics = format!("127.0.0.1:{}", free_port());
    let run_dir = dir.path().join("run");
    let (learner, addr) = start_learner(&[
        "--config",
        &config,
        "--run-dir",
        run_dir.to_str().unwrap(),
        "--metrics-listen",
        &metrics,
    ]);
    let ca = credentials().dir.join("ca.crt");
    let token = credentials().dir.join("read.token");
    let out = check(
        &python,
        &[
            here.join("python/learner_client.py").to_str().unwrap(),
            stubs.to_str().unwrap(),
            &addr,
            &metrics,
            ca.to_str().unwrap(),
            token.to_str().unwrap(),
        ],
    );
    let seen: Value = serde_json::from_str(out.trim()).unwrap();
    assert!(seen["buffer_capacity"].as_u64().unwrap() > 0, "{seen}");
    assert!(seen["latest_snapshot"].as_u64().unwrap() >= 1, "{seen}");
    assert_eq!(seen["without_token"], "UNAUTHENTICATED", "{seen}");
    assert_eq!(seen["health"], "SERVING", "{seen}");
    assert!(
        seen["content_type"]
            .as_str()
            .unwrap()
            .starts_with("application/openmetrics-text"),
        "{seen}"
    );
    // A scraper that does not ask for OpenMetrics gets the 0.0.4 text.
    assert!(
        seen["plain_content_type"]
            .as_str()
            .unwrap()
            .starts_with("text/plain; version=0.0.4"),
        "{seen}"
    );
    assert_eq!(seen["plain_families"]["tweezer_learner_updates"], "counter");
    assert_eq!(
        seen["plain_families"]["tweezer_learner_update_seconds"],
        "histogram"
    );
    let families = &seen["families"];
    let capacity = &families["tweezer_learner_buffer_capacity"];
    assert_eq!(capacity["type"], "gauge", "{seen}");
    assert_eq!(
        capacity["samples"]["tweezer_learner_buffer_capacity"].as_f64(),
        seen["buffer_capacity"].as_f64()
    );
    assert_eq!(
        families["tweezer_learner_steps_inserted"]["type"],
        "counter"
    );
    assert_eq!(
        families["tweezer_learner_update_seconds"]["type"], "histogram",
        "{seen}"
    );

    // The hardware agent's and an actor's endpoints, scraped the same way.
    let scrape = |addr: &str| -> Value {
        let out = check(
            &python,
            &[
                here.join("python/scrape.py").to_str().unwrap(),
                addr,
                ca.to_str().unwrap(),
                token.to_str().unwrap(),
            ],
        );
        serde_json::from_str(out.trim()).unwrap()
    };
    let agent_metrics = format!("127.0.0.1:{}", free_port());
    let (agent, _) = start_agent(&["--metrics-listen", &agent_metrics], None);
    let agent_seen = scrape(&agent_metrics);
    assert_eq!(agent_seen["without_token"], 401, "{agent_seen}");
    let families = &agent_seen["families"];
    assert_eq!(
        families["tweezer_agent_idle"]["samples"]["tweezer_agent_idle"],
        1.0
    );
    assert_eq!(
        families["tweezer_agent_step_latency_seconds"]["type"],
        "histogram"
    );
    assert!(stop(agent).0.success());

    let actor_metrics = format!("127.0.0.1:{}", free_port());
    let actor_config = write(
        &dir.path().join("actor.toml"),
        &format!(
            "{TINY_ENV}\n[actor]\nlearner = \"{addr}\"\nenvs = 2\nbatch_steps = 20\n\
             metrics_listen = \"{actor_metrics}\"\n"
        ),
    );
    // The actor serves with the service's certificate and streams with
    // its own token, given in the environment.
    let actor_token = std::fs::read_to_string(credentials().dir.join("actor.token")).unwrap();
    let actor = Command::new(binary("actor"))
        .args(["--config", &actor_config, "run"])
        .args(["--security", &credentials().file("server")])
        .env(tweezer_rpc::TOKEN_ENV, actor_token.trim())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    let acked = loop {
        let seen = scrape_when_up(&scrape, &actor_metrics, deadline);
        let acked = seen["families"]["tweezer_actor_steps_acked"]["samples"]
            ["tweezer_actor_steps_acked_total"]
            .as_f64()
            .unwrap_or(0.0);
        if acked > 0.0 || Instant::now() > deadline {
            break acked;
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    assert!(acked > 0.0, "the actor's metrics show acknowledged steps");
    assert!(stop(actor).0.success());
    assert!(stop(learner).0.success());
}

/// A scrape of `addr`, retried until the endpoint is up or `deadline`.
fn scrape_when_up(scrape: &dyn Fn(&str) -> Value, addr: &str, deadline: Instant) -> Value {
    loop {
        if std::net::TcpStream::connect(addr).is_ok() || Instant::now() > deadline {
            return scrape(addr);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}
