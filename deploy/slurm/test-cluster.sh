#!/usr/bin/env bash
# Runs deploy/slurm/train.sbatch on a real Slurm: installs Debian's
# slurm-wlm and munge if missing, starts a single-machine cluster on
# loopback (munged, slurmctld, and two slurmd as virtual nodes, since a
# heterogeneous job needs two), submits the job with a tiny config, requeues
# it once it has checkpointed, and checks that it trained, checkpointed,
# resumed after the requeue and stopped with a final checkpoint; while the
# requeued job runs, Prometheus (Debian's package) scrapes the targets the
# job registered, with deploy/prometheus/slurm.yml, and every one must be
# up. Stops only the daemons it started. Needs root.
#
#   deploy/slurm/test-cluster.sh BIN_DIR     # the learner, actor and tweezer binaries
set -euo pipefail

bin="$(realpath "${1:?usage: test-cluster.sh BIN_DIR}")"
if [[ "$(id -u)" != 0 ]]; then
    echo "test-cluster.sh needs root: it installs packages and runs the Slurm and munge daemons" >&2
    exit 1
fi
here="$(cd "$(dirname "$0")" && pwd)"
work="$(mktemp -d /tmp/tweezer-slurm-XXXXXX)"
chmod 755 "$work" # munged, running as munge, keeps its socket and log inside
started=$(date +%s)
say() { echo "[slurm test $(( $(date +%s) - started ))s] $*"; }

if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
    say "installing slurm-wlm and munge"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
fi
if ! command -v prometheus >/dev/null || ! command -v promtool >/dev/null; then
    say "installing prometheus"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends prometheus >/dev/null
fi

pids=()
started_pid() { # a daemon's pid, once its pid file is written
    for _ in $(seq 100); do
        if [[ -s "$1" ]]; then
            pids+=("$(cat "$1")")
            return 0
        fi
        sleep 0.1
    done
    say "no pid file $1"
    exit 1
}
job=""
cleanup() {
    # The job's steps outlive the daemons: end the job first.
    if [[ -n "$job" ]]; then
        scancel "$job" 2>/dev/null || true
        for _ in $(seq 60); do
            [[ -z "$(squeue -h -j "$job" 2>/dev/null)" ]] && break
            sleep 0.5
        done
    fi
    for pid in "${pids[@]}"; do
        kill "$pid" 2>/dev/null || true
    done
    # The daemons write into $work until they are gone: wait for them (10 s
    # at most) before removing it. Cleanup never decides the test's result.
    for _ in $(seq 100); do
        alive=0
        for pid in "${pids[@]}"; do
            kill -0 "$pid" 2>/dev/null && alive=1
        done
        [[ "$alive" == 0 ]] && break
        sleep 0.1
    done
    if [[ "${KEEP:-}" != 1 ]]; then
        rm -rf "$work" 2>/dev/null || say "could not remove $work entirely"
    fi
}
trap cleanup EXIT

# munge: no systemd here; its key comes with the package.
if [[ ! -s /etc/munge/munge.key ]]; then
    mungekey --create --keyfile /etc/munge/munge.key
    chown munge:munge /etc/munge/munge.key
fi
mkdir -p "$work/munge"
chown munge:munge "$work/munge"
runuser -u munge -- munged --socket="$work/munge/munge.socket" \
    --pid-file="$work/munge/munged.pid" --log-file="$work/munge/munged.log" \
    --seed-file="$work/munge/munged.seed"
started_pid "$work/munge/munged.pid"

ctld_port=$((20000 + RANDOM % 20000))
conf="$work/slurm.conf"
mkdir -p "$work/state" "$work/spool/node1" "$work/spool/node2"
cat > "$conf" <<EOF
ClusterName=tweezer-test
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort=$ctld_port
AuthType=auth/munge
AuthInfo=socket=$work/munge/munge.socket
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool/%n
SlurmctldPidFile=$work/slurmctld.pid
SlurmdPidFile=$work/slurmd-%n.pid
SlurmctldLogFile=$work/slurmctld.log
SlurmdLogFile=$work/slurmd-%n.log
SlurmdParameters=config_overrides
ReturnToService=2
MpiDefault=none
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
SchedulerParameters=bf_interval=1,sched_interval=1
KillWait=60
NodeName=node1 NodeHostname=localhost NodeAddr=127.0.0.1 Port=$((ctld_port + 1)) CPUs=4 RealMemory=32000 State=UNKNOWN
NodeName=node2 NodeHostname=localhost NodeAddr=127.0.0.1 Port=$((ctld_port + 2)) CPUs=4 RealMemory=32000 State=UNKNOWN
PartitionName=test Nodes=node1,node2 Default=YES MaxTime=INFINITE State=UP
EOF
export SLURM_CONF="$conf"
slurmctld -f "$conf"
started_pid "$work/slurmctld.pid"
for node in node1 node2; do
    slurmd -f "$conf" -N "$node"
    started_pid "$work/slurmd-$node.pid"
done
for _ in $(seq 30); do
    [[ "$(sinfo -h -o '%t' | sort -u)" == "idle" ]] && break
    sleep 1
done
sinfo
say "cluster up"

# Credentials, as an operator makes them.
sec="$work/security"
mkdir -p "$sec"
"$bin/tweezer" cert ca --out "$sec" --days 2 >/dev/null
"$bin/tweezer" cert issue --ca "$sec" --name learner --host 127.0.0.1 --host localhost --out "$sec" --days 2 >/dev/null
"$bin/tweezer" token new --role actor --name actors --tokens "$sec/tokens" --out "$sec/actor.token" >/dev/null
"$bin/tweezer" token new --role read --name test --tokens "$sec/tokens" --out "$sec/read.token" >/dev/null
printf 'cert = "learner.crt"\nkey = "learner.key"\ntokens = "tokens"\n' > "$sec/learner.toml"
# The actors serve metrics too: a certificate (this one names the loopback
# address every virtual node shares) and the tokens a scraper's is checked
# against.
printf 'ca = "ca.crt"\ntoken_file = "actor.token"\ncert = "learner.crt"\nkey = "learner.key"\ntokens = "tokens"\n' \
    > "$sec/actor.toml"
printf 'ca = "ca.crt"\n' > "$sec/probe.toml"

env_table="$(cat "$here/../tiny-env.toml")"
cat > "$work/learner.toml" <<EOF
$env_table
[learner]
uniform_steps = 500
[learner.limiter]
min_size = 200
updates_per_insert = 0.25
[learner.snapshots]
every_updates = 50
[learner.checkpoints]
every_seconds = 5
EOF
cat > "$work/actor.toml" <<EOF
$env_table
[actor]
envs = 4
batch_steps = 50
reconnect_initial_ms = 100
reconnect_max_ms = 1000
EOF

run="$work/run"
job=$(TWEEZER_BIN="$bin" TWEEZER_RUN="$run" TWEEZER_CONFIG="$work/learner.toml" \
    TWEEZER_ACTOR_CONFIG="$work/actor.toml" TWEEZER_SECURITY_DIR="$sec" \
    TWEEZER_PORT=$((ctld_port + 3)) TWEEZER_METRICS_PORT=$((ctld_port + 4)) TWEEZER_SECONDS=45 \
    sbatch --parsable --output="$work/job.out" "$here/train.sbatch")
job="${job%%;*}"
say "submitted job $job"

wait_for() { # what, seconds, condition...
    local what="$1" seconds="$2"
    shift 2
    for _ in $(seq "$seconds"); do
        if "$@"; then return 0; fi
        sleep 1
    done
    say "timed out waiting for $what"
    cat "$work/job.out" >&2 || true
    tail -20 "$work/slurmctld.log" >&2 || true
    exit 1
}
checkpoints() { ls "$run/checkpoints" 2>/dev/null | grep -c '\.twz$' || true; }
has_checkpoints() { [[ "$(checkpoints)" -ge 2 ]]; }
wait_for "the first checkpoints" 180 has_checkpoints
say "requeueing job $job"
scontrol requeue "$job"
resumed() { grep -q '"resuming"' "$work/job.out" 2>/dev/null; }
# A requeued job waits out the scheduler's restart delay (about two minutes).
wait_for "the requeued job to resume" 300 resumed
say "resumed"

# Prometheus with the shipped scrape config, its globs pointed at this run:
# the learner and both actors registered themselves and are up.
prom="$work/prometheus"
mkdir -p "$prom"
cp "$sec/ca.crt" "$sec/read.token" "$prom/"
sed -e "s|/shared/tweezer/prometheus|$run/prometheus|" -e 's/scrape_interval: 15s/scrape_interval: 1s/' \
    "$here/../prometheus/slurm.yml" > "$prom/prometheus.yml"
promtool check config "$prom/prometheus.yml" >/dev/null
prom_port=$((ctld_port + 10))
prometheus --config.file="$prom/prometheus.yml" --storage.tsdb.path="$prom/data" \
    --web.listen-address="127.0.0.1:$prom_port" > "$prom/prometheus.log" 2>&1 &
pids+=($!)
up_targets() { # how many targets Prometheus scraped successfully, by job
    curl -sf --max-time 2 "http://127.0.0.1:$prom_port/api/v1/query?query=up" \
        | python3 -c 'import json, sys
r = json.load(sys.stdin)["data"]["result"]
print(" ".join(sorted(s["metric"]["job"] + "=" + s["value"][1] for s in r)))' 2>/dev/null || true
}
all_up() { [[ "$(up_targets)" == "tweezer-actor=1 tweezer-actor=1 tweezer-learner=1" ]]; }
up_within() { for _ in $(seq "$1"); do all_up && return 0; sleep 1; done; return 1; }
if ! up_within 60; then
    say "Prometheus did not find the learner and both actors up: $(up_targets)"
    ls "$run/prometheus"
    tail -20 "$prom/prometheus.log"
    cat "$work/job.out" >&2 || true
    tail -20 "$work/slurmctld.log" >&2 || true
    exit 1
fi
say "Prometheus scrapes the learner and both actors through file_sd: all up"
gone() { [[ -z "$(squeue -h -j "$job" 2>/dev/null)" ]]; }
wait_for "the job to end" 300 gone

out="$work/job.out"
grep -q '(restart 1)' "$out" || { say "no restart in the job's output"; cat "$out"; exit 1; }
updates=$(grep -c '"kind":"update"' "$run/metrics.jsonl" || true)
[[ "$updates" -ge 3 ]] || { say "only $updates update lines in metrics.jsonl"; cat "$out"; exit 1; }
acked=$(grep -ho '"steps_acked":[0-9]*' "$out" | cut -d: -f2 | sort -n | tail -1)
[[ "${acked:-0}" -gt 0 ]] || { say "no actor report with acknowledged steps"; cat "$out"; exit 1; }
finals=$(grep -c 'stopping: finishing the update in flight' "$out" || true)
written=$(grep -c '"checkpoint written"' "$out" || true)
[[ "$finals" -ge 1 && "$written" -ge 1 ]] || { say "no final checkpoint"; cat "$out"; exit 1; }
say "passed: $(checkpoints) checkpoints kept, $updates metric lines of updates, actors acknowledged up to $acked steps, resumed after requeue"
