"""Peak memory of a streamed Monte Carlo study (`jaxloc.stream_study`) against its size.

    python benchmarks/stream_memory.py --trials 10000000 [--methods robust] [--out DIR]

Runs one study of the paper's sequential scenario in bounded memory and samples the
process's resident set size (VmRSS) every second; prints and writes (as JSON, with the
command) the peak RSS, the RSS after the first chunk, and trials/s. With `--out DIR` the
chunks also go to disk and an interrupted run resumes where it stopped.
"""

import argparse
import json
import os
import resource
import sys
import threading
import time

import jaxloc


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10_000_000)
    ap.add_argument("--methods", default="robust")
    ap.add_argument("--chunk-size", type=int, default=4096)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="stream chunks to DIR too (resumable)")
    ap.add_argument("--json", default=os.path.join(os.path.dirname(__file__), "results",
                                                   "stream_memory.json"))
    args = ap.parse_args()
    methods = tuple(args.methods.split(","))
    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    t0 = time.perf_counter()

    def sample():
        while not stop.is_set():
            samples.append((time.perf_counter() - t0, _rss_mb()))
            stop.wait(1.0)

    threading.Thread(target=sample, daemon=True).start()
    summary = jaxloc.stream_study(
        jaxloc.Scenario.paper("sequential"),
        args.trials,
        seed=args.seed,
        chunk_size=args.chunk_size,
        methods=methods,
        out_dir=args.out,
        progress=sys.stderr.isatty(),
    )
    elapsed = time.perf_counter() - t0
    stop.set()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    report = {
        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
        "trials": args.trials,
        "methods": list(methods),
        "chunk_size": args.chunk_size,
        "seconds": elapsed,
        "trials_per_second_including_compile": args.trials / elapsed,
        "peak_rss_mb": peak,
        "rss_mb_samples_every_second": samples[:: max(1, len(samples) // 200)],
        "n_ok": {m: summary["methods"][m]["n_ok"] for m in methods},
        "overhead_position_rmse_m": {
            m: summary["methods"][m]["cameras"]["C"]["position_m"]["rmse"] for m in methods
        },
    }
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(report, f, indent=2)
    print(f"{args.trials} trials ({','.join(methods)}), chunk {args.chunk_size}: "
          f"{elapsed:.0f} s, peak RSS {peak:.0f} MB; wrote {args.json}")


if __name__ == "__main__":
    main()
