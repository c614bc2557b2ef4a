#!/usr/bin/env bash
# Checks the metrics every service exposes against Prometheus' own tools:
# installs Debian's prometheus package (for promtool) if missing, starts a
# learner, an actor and a hardware agent on its twin over TLS with tokens,
# scrapes each /metrics as a scraper that does not ask for OpenMetrics
# would, and runs `promtool check metrics` on each; then checks that every
# metric the Grafana dashboard (deploy/grafana/tweezer-rl.json) queries is
# exposed by a live service, and that the Kubernetes scrape config
# (kubernetes.yml) passes `promtool check config`. Stops only the processes
# it started.
#
#   deploy/prometheus/check-metrics.sh BIN_DIR   # learner, actor, hardware-agent, tweezer
set -euo pipefail

bin="$(realpath "${1:?usage: check-metrics.sh BIN_DIR}")"
here="$(cd "$(dirname "$0")" && pwd)"
dashboard="$here/../grafana/tweezer-rl.json"
work="$(mktemp -d /tmp/tweezer-metrics-XXXXXX)"
started=$(date +%s)
say() { echo "[metrics check $(( $(date +%s) - started ))s] $*"; }

if ! command -v promtool >/dev/null; then
    if [[ "$(id -u)" != 0 ]]; then
        echo "check-metrics.sh needs promtool (Debian: apt-get install prometheus) or root to install it" >&2
        exit 1
    fi
    say "installing prometheus (for promtool)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends prometheus >/dev/null
fi

pids=()
cleanup() {
    for pid in "${pids[@]}"; do
        kill "$pid" 2>/dev/null || true
    done
    wait 2>/dev/null || true
    rm -rf "$work"
}
trap cleanup EXIT

cd "$work"
"$bin/tweezer" cert ca --out . --days 1 >/dev/null
"$bin/tweezer" cert issue --ca . --name server --host 127.0.0.1 --host localhost --out . --days 1 >/dev/null
for role in read actor; do
    "$bin/tweezer" token new --role "$role" --name "$role" --tokens tokens --out "$role.token" >/dev/null
done
printf 'cert = "server.crt"\nkey = "server.key"\nca = "ca.crt"\ntokens = "tokens"\ntoken_file = "actor.token"\n' > server.toml
port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
learner_metrics="127.0.0.1:$(port)"
agent_metrics="127.0.0.1:$(port)"
actor_metrics="127.0.0.1:$(port)"
env="$(cat "$here/../tiny-env.toml")"
printf '%s\n[learner]\nlisten = "127.0.0.1:0"\nmetrics_listen = "%s"\n' "$env" "$learner_metrics" > learner.toml

"$bin/learner" serve --security server.toml --config learner.toml --run-dir run > learner.out 2> learner.log &
pids+=($!)
"$bin/hardware-agent" serve --twin --greedy --listen 127.0.0.1:0 --security server.toml \
    --metrics-listen "$agent_metrics" > agent.out 2> agent.log &
pids+=($!)
for _ in $(seq 300); do
    [[ -s learner.out ]] && break
    sleep 0.1
done
learner="$(awk '{print $4}' learner.out)"
[[ -n "$learner" ]] || { say "the learner did not start"; cat learner.log; exit 1; }
printf '%s\n[actor]\nlearner = "%s"\nenvs = 2\nbatch_steps = 20\nmetrics_listen = "%s"\n' \
    "$env" "$learner" "$actor_metrics" > actor.toml
"$bin/actor" --config actor.toml run --security server.toml > actor.out 2> actor.log &
pids+=($!)

scrape() { # ADDR FILE: the metrics at ADDR, as a plain scraper asks
    curl -sf --max-time 5 --cacert ca.crt -H "authorization: Bearer $(cat read.token)" \
        "https://$1/metrics" -o "$2"
}
all=""
for service in learner:"$learner_metrics" agent:"$agent_metrics" actor:"$actor_metrics"; do
    name="${service%%:*}"
    addr="${service#*:}"
    for _ in $(seq 600); do
        scrape "$addr" "$name.metrics" && break
        sleep 0.1
    done
    [[ -s "$name.metrics" ]] || { say "no metrics from the $name at $addr"; cat "$name.log"; exit 1; }
    promtool check metrics < "$name.metrics" || { say "promtool rejects the $name's metrics"; exit 1; }
    say "promtool check metrics: the $name's $(grep -c '^# TYPE' "$name.metrics") families pass"
    all+="$(cat "$name.metrics")"$'\n'
done

missing=0
for metric in $(grep -o 'tweezer_[a-z_]*' "$dashboard" | sort -u); do
    if ! grep -q "^$metric[ {]" <<<"$all"; then
        say "the dashboard queries $metric, which no service exposes"
        missing=1
    fi
done
[[ "$missing" == 0 ]] || exit 1
say "passed: every metric the dashboard queries is exposed ($(grep -o 'tweezer_[a-z_]*' "$dashboard" | sort -u | wc -l) names)"

# The Kubernetes scrape config, with this check's CA and read token where
# it expects them (the Slurm one runs live in deploy/slurm/test-cluster.sh).
mkdir -p k8s/tweezer
cp "$here/kubernetes.yml" k8s/
cp ca.crt read.token k8s/tweezer/
promtool check config k8s/kubernetes.yml >/dev/null || { promtool check config k8s/kubernetes.yml; exit 1; }
say "passed: promtool check config deploy/prometheus/kubernetes.yml"
