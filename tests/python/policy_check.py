"""Checks the Python policy package (python/tweezer_policy) against the Rust
policy (tests/tests/python_policy.rs):

  policy_check.py observations OUT.jsonl --fov W H --seed S --count N
      writes N observations: centres drawn over the field of view and just
      beyond its edges (0 to 40 of them, some sets empty), each with a
      displacement (a fifth of them new to the view), target vectors of
      every length up to 1
  policy_check.py compare SNAPSHOT OBS.jsonl RUST.jsonl --fov W H
      loads the snapshot with the package, computes its actions for the
      observations with NumPy (and PyTorch where it is installed) and
      prints the largest difference from the Rust actions as JSON"""

import argparse
import json
import sys

import numpy as np

import tweezer_policy


def observations(args):
    rng = np.random.default_rng(args.seed)
    w, h = args.fov
    margin = 26.0
    with open(args.out, "w") as out:
        for k in range(args.count):
            n = 0 if k % 7 == 0 else int(rng.integers(1, 41))
            centres = rng.uniform([-margin, -margin], [w + margin, h + margin], size=(n, 2))
            angle, length = rng.uniform(0, 2 * np.pi), rng.uniform(0, 1)
            vector = [length * np.cos(angle), length * np.sin(angle)]
            moves = rng.uniform(-2.8, 2.8, size=(n, 2))
            new = rng.uniform(size=n) < 0.2
            line = {
                "centres": [[float(np.float32(x)), float(np.float32(y))] for x, y in centres],
                "displacements": [
                    None if fresh else [float(np.float32(x)), float(np.float32(y))]
                    for (x, y), fresh in zip(moves, new)
                ],
                "vector": [float(np.float32(v)) for v in vector],
            }
            out.write(json.dumps(line) + "\n")


def compare(args):
    lines = [json.loads(line) for line in open(args.observations)]
    centres = [np.asarray(o["centres"], dtype=np.float32).reshape(-1, 2) for o in lines]
    displacements = [o["displacements"] for o in lines]
    vectors = np.asarray([o["vector"] for o in lines], dtype=np.float32)
    rust = np.asarray([json.loads(line)["action"] for line in open(args.rust)], dtype=np.float32)
    report = {}
    backends = ["numpy"]
    try:
        import torch  # noqa: F401

        backends.append("torch")
    except ImportError:
        report["torch"] = "not installed"
    for backend in backends:
        policy = tweezer_policy.load(args.snapshot, fov_px=tuple(args.fov), backend=backend)
        actions = np.clip(policy.act(centres, vectors, displacements), -1.0, 1.0)
        if actions.shape != rust.shape:
            sys.exit(f"{backend}: {actions.shape} actions, Rust gave {rust.shape}")
        report[backend] = float(np.abs(actions - rust).max())
    snapshot = tweezer_policy.read(args.snapshot)
    report["architecture"] = snapshot.architecture
    report["inputs"] = snapshot.fields.get("inputs")
    report["frame"] = snapshot.fields.get("frame")
    report["motion_unit_px"] = snapshot.fields.get("motion_unit_px")
    report["version"] = snapshot.version
    report["actions"] = len(rust)
    report["unsaturated"] = int((np.abs(rust) < 0.99).sum())
    print(json.dumps(report))


def main():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command", required=True)
    o = sub.add_parser("observations")
    o.add_argument("out")
    o.add_argument("--fov", type=int, nargs=2, required=True)
    o.add_argument("--seed", type=int, default=0)
    o.add_argument("--count", type=int, default=200)
    c = sub.add_parser("compare")
    c.add_argument("snapshot")
    c.add_argument("observations")
    c.add_argument("rust")
    c.add_argument("--fov", type=int, nargs=2, required=True)
    args = parser.parse_args()
    {"observations": observations, "compare": compare}[args.command](args)


if __name__ == "__main__":
    main()
