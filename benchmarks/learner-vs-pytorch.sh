#!/usr/bin/env bash
# The learner's TD3 update next to PyTorch's, in one run on this machine:
# `learner bench` and benchmarks/pytorch/td3_update.py alternate, at 40 x 32
# and 320 x 256, batch 32; prints the medians and their ratio, and each
# process's peak resident memory.
#
#   benchmarks/learner-vs-pytorch.sh [--reps N] [--updates N] [--device D]
#       [--replay-capacity N] [--timeout S] [--json]
#
# The learner's replay holds 20,000 transitions unless --replay-capacity
# says otherwise (the paper's 1,050,000 for the memory goal); PyTorch's
# process holds none.
# --device wgpu or cuda runs ours on that learner.device and PyTorch on CUDA.
# Each process may run --timeout seconds (default 1200) before it is
# killed and the run ends with its error output.
# PyTorch comes from the pinned benchmarks/pytorch/requirements.txt, into a
# virtual environment made on first use ($BENCH_VENV, default
# ~/.cache/tweezer-rl/bench-venv). The learner is $LEARNER, default the
# release build (with the device's feature), built if missing.
set -euo pipefail
cd "$(dirname "$0")/.."

venv="${BENCH_VENV:-$HOME/.cache/tweezer-rl/bench-venv}"
if [[ ! -x "$venv/bin/python" ]] || ! "$venv/bin/python" -c 'import torch' 2>/dev/null; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet -r benchmarks/pytorch/requirements.txt
fi

learner="${LEARNER:-}"
if [[ -z "$learner" ]]; then
    features=() prev=
    for arg in "$@"; do
        [[ $prev == --device && $arg != cpu ]] && features=(--features "$arg")
        prev=$arg
    done
    target="${CARGO_TARGET_DIR:-target}"
    cargo build --release --locked -p tweezer-learner "${features[@]}" >&2
    learner="$target/release/learner"
fi

exec "$venv/bin/python" benchmarks/pytorch/compare.py --learner "$learner" "$@"
