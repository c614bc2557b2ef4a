"""Runs `learner bench` and td3_update.py in alternation and prints the
median update times and their ratio (ours / PyTorch's) per resolution, and
each process's peak resident memory (ours holding a replay of
`--replay-capacity` transitions, PyTorch none). `--device wgpu` or `cuda`
runs ours on that `learner.device` and PyTorch on CUDA."""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
RESOLUTIONS = [(40, 32), (320, 256)]


def measured(command, timeout):
    """Runs `command` to its end, for at most `timeout` seconds: its JSON
    output, with its peak resident memory in MB (the kernel's count for the
    process, read when it is reaped) under "peak_rss_mb". A command that
    fails or outlives its time ends the benchmark with its error output."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        process = subprocess.Popen(command, stdout=out, stderr=err)
        deadline = time.monotonic() + timeout
        pid, status, usage = os.wait4(process.pid, os.WNOHANG)
        while not pid and time.monotonic() < deadline:
            time.sleep(0.05)
            pid, status, usage = os.wait4(process.pid, os.WNOHANG)
        failure = None
        if not pid:
            process.kill()
            _, status, usage = os.wait4(process.pid, 0)
            failure = f"did not finish within {timeout:g} s (--timeout) and was killed"
        # Reaped here: Popen must not wait for it again.
        process.returncode = os.waitstatus_to_exitcode(status)
        if failure is None and process.returncode != 0:
            failure = f"failed ({process.returncode})"
        if failure:
            err.seek(0)
            sys.exit(f"{' '.join(command)} {failure}:\n"
                     f"{err.read().decode(errors='replace')}")
        out.seek(0)
        result = json.loads(out.read())
    # ru_maxrss is in KiB on Linux.
    result["peak_rss_mb"] = usage.ru_maxrss * 1024 / 1e6
    return result


def learner_bench(learner, device, width, height, updates, batch_size, replay, config_dir,
                  timeout):
    config = os.path.join(config_dir, f"{width}x{height}.toml")
    with open(config, "w") as f:
        f.write(f"[env.image]\nwidth = {width}\nheight = {height}\n")
        if device != "cpu":
            f.write(f"[learner]\ndevice = \"{device}\"\n")
    return measured(
        [learner, "--config", config, "bench", "--json", "--updates", str(updates),
         "--batch-size", str(batch_size), "--replay-capacity", str(replay)], timeout)


def pytorch_bench(device, width, height, updates, batch_size, threads, timeout):
    return measured(
        [sys.executable, os.path.join(HERE, "td3_update.py"), "--width", str(width),
         "--height", str(height), "--updates", str(updates), "--batch-size", str(batch_size),
         "--threads", str(threads), "--device", "cpu" if device == "cpu" else "cuda"],
        timeout)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--learner", required=True)
    parser.add_argument("--reps", type=int, default=3, help="runs of each side per resolution")
    parser.add_argument("--updates", type=int, default=0,
                        help="updates timed per run (default: 40 at 40 x 32, 6 at 320 x 256)")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--threads", type=int, default=os.cpu_count(),
                        help="PyTorch's threads (the learner uses every core)")
    parser.add_argument("--device", choices=["cpu", "wgpu", "cuda"], default="cpu",
                        help="ours on flex, wgpu or cuda; PyTorch on the CPU or CUDA")
    parser.add_argument("--replay-capacity", type=int, default=20000,
                        help="transitions in the learner's replay (the paper's: 1050000)")
    parser.add_argument("--timeout", type=float, default=1200,
                        help="seconds each benchmark process may run before it is killed")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    results = []
    with tempfile.TemporaryDirectory() as config_dir:
        for width, height in RESOLUTIONS:
            updates = args.updates or (40 if width * height <= 64 * 64 else 6)
            ours, theirs, device, peer = [], [], None, None
            ours_mb, theirs_mb = [], []
            for _ in range(args.reps):
                bench = learner_bench(args.learner, args.device, width, height, updates,
                                      args.batch_size, args.replay_capacity, config_dir,
                                      args.timeout)
                ours.append(bench["update_ms_mean"])
                ours_mb.append(bench["peak_rss_mb"])
                device = bench.get("device", "flex")
                torch = pytorch_bench(args.device, width, height, updates, args.batch_size,
                                      args.threads, args.timeout)
                theirs.append(torch["update_ms_mean"])
                theirs_mb.append(torch["peak_rss_mb"])
                peer = f"{torch['peer']} on {torch['device']}"
            ours_ms, theirs_ms = statistics.median(ours), statistics.median(theirs)
            results.append({
                "resolution": [width, height],
                "batch_size": args.batch_size,
                "device": device,
                "peer": peer,
                "update_ms_median": ours_ms,
                "peer_update_ms_median": theirs_ms,
                "ratio": ours_ms / theirs_ms,
                "update_ms_runs": ours,
                "peer_update_ms_runs": theirs,
                "replay_capacity": args.replay_capacity,
                "peak_rss_mb_median": statistics.median(ours_mb),
                "peer_peak_rss_mb_median": statistics.median(theirs_mb),
            })

    if args.json:
        print(json.dumps(results))
        return
    print(f"{'resolution':<12}{'learner ms':>12}{'PyTorch ms':>12}{'ratio':>8}"
          f"{'learner MB':>12}{'PyTorch MB':>12}  runs")
    for r in results:
        w, h = r["resolution"]
        print(f"{f'{w} x {h}':<12}{r['update_ms_median']:>12.1f}"
              f"{r['peer_update_ms_median']:>12.1f}{r['ratio']:>8.2f}"
              f"{r['peak_rss_mb_median']:>12.0f}{r['peer_peak_rss_mb_median']:>12.0f}"
              f"  {len(r['update_ms_runs'])}")
    print(f"(medians; batch {args.batch_size}; {results[0]['peer']}; learner on "
          f"{results[0]['device']} with a replay of {args.replay_capacity:,} transitions; "
          f"MB: peak resident memory)")


if __name__ == "__main__":
    main()
