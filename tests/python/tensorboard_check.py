"""Reads a run directory's TensorBoard event files with TensorBoard's own
reader and compares every scalar with metrics.jsonl
(tests/tests/tensorboard.rs):

  tensorboard_check.py run RUN_DIR     one run: JSON with the tags, the lines
                                       and scalars compared, and mismatches
  tensorboard_check.py logdir LOGDIR   what `tensorboard --logdir LOGDIR`
                                       lists: JSON {run: [tags]}"""

import json
import sys

from tensorboard.backend.event_processing import event_accumulator, event_multiplexer

SKIP = {"kind", "time_s", "updates"}


def scalars(path):
    acc = event_accumulator.EventAccumulator(path, size_guidance={event_accumulator.SCALARS: 0})
    acc.Reload()
    return {tag: acc.Scalars(tag) for tag in acc.Tags()["scalars"]}


def expected(run_dir):
    """Per tag, the (step or None, value) pairs metrics.jsonl implies."""
    out = {}
    lines = 0
    for text in open(f"{run_dir}/metrics.jsonl"):
        line = json.loads(text)
        lines += 1
        step = line.get("updates")
        for name, value in line.items():
            if name in SKIP or isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            out.setdefault(f"{line['kind']}/{name}", []).append((step, float(value)))
    return out, lines


def close(a, b):
    return abs(a - b) <= 1e-6 * max(1.0, abs(b))


def run(run_dir):
    got = scalars(run_dir)
    want, lines = expected(run_dir)
    mismatches = []
    compared = 0
    for tag, pairs in want.items():
        events = got.get(tag, [])
        if len(events) != len(pairs):
            mismatches.append(f"{tag}: {len(events)} scalars, metrics.jsonl has {len(pairs)}")
            continue
        for event, (step, value) in zip(events, pairs):
            compared += 1
            if (step is not None and event.step != step) or not close(event.value, value):
                mismatches.append(f"{tag}: step {event.step} value {event.value}, expected {step} {value}")
                break
    print(json.dumps({
        "tags": sorted(got),
        "lines": lines,
        "compared": compared,
        "mismatches": mismatches[:20],
    }))


def logdir(path):
    mux = event_multiplexer.EventMultiplexer(size_guidance={event_accumulator.SCALARS: 0})
    mux.AddRunsFromDirectory(path)
    mux.Reload()
    print(json.dumps({name: sorted(tags["scalars"]) for name, tags in mux.Runs().items()}))


if __name__ == "__main__":
    {"run": run, "logdir": logdir}[sys.argv[1]](sys.argv[2])
