#!/usr/bin/env bash
# Runs a cargo command that builds Burn's cuda backend with the LLVM it
# links taken from PyPI instead of GitHub:
#
#   deploy/cuda/with-llvm.sh cargo build --release --locked -p tweezer-learner --features cuda
#
# Burn's CUDA runtime (cubecl-cuda) compiles kernels to PTX with LLVM 23.1,
# linked statically, and the build script of tracel-llvm-bundler would
# download that LLVM from GitHub. Here it comes from the pinned
# deploy/cuda/llvm-requirements.txt, installed into a virtual environment
# ($LLVM_VENV, default ~/.cache/tweezer-rl/llvm-venv) and laid out where the
# bundler finds an installed bundle (under $XDG_DATA_HOME, set for the
# command alone). Linux on x86-64. No CUDA toolkit is needed to build, and
# the learner needs only NVIDIA's driver to run.
set -euo pipefail
if (($# == 0)); then
    echo "usage: $0 COMMAND [ARGS...] (a cargo command building --features cuda)" >&2
    exit 2
fi
root="$(cd "$(dirname "$0")/../.." && pwd)"

venv="${LLVM_VENV:-$HOME/.cache/tweezer-rl/llvm-venv}"
requirements="$root/deploy/cuda/llvm-requirements.txt"
if ! cmp -s "$requirements" "$venv/llvm-requirements.txt" 2>/dev/null; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet -r "$requirements"
    cp "$requirements" "$venv/llvm-requirements.txt"
fi
sdk="$("$venv/bin/python" -c 'import mlc_llvm_static as m; print(m.get_prefix())')"

# The bundle directory the locked tracel-llvm-bundler expects, and the LLVM
# release it was made for.
bundler="$(grep -A1 '^name = "tracel-llvm-bundler"$' "$root/Cargo.lock" | sed -n 's/^version = "\(.*\)"$/\1/p')"
if [[ -z "$bundler" ]]; then
    echo "Cargo.lock has no tracel-llvm-bundler: is the cuda feature's dependency tree still the same?" >&2
    exit 1
fi
wanted="${bundler%%-*}" have="$("$sdk/bin/llvm-config" --version)"
if [[ "${wanted%.*}" != "${have%.*}" ]]; then
    echo "Cargo.lock's tracel-llvm-bundler $bundler wants LLVM $wanted; deploy/cuda/llvm-requirements.txt pins LLVM $have: pin a $wanted SDK" >&2
    exit 1
fi

data="$venv/xdg-data"
bundle="$data/tracel/tracel-llvm-$bundler"
mkdir -p "$bundle"
for part in bin include lib; do
    ln -sfn "$sdk/$part" "$bundle/$part"
done
touch "$bundle/.tracel-llvm-installed"

XDG_DATA_HOME="$data" exec "$@"
