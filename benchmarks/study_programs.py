"""Size and cost of the study programs that `jaxloc table1` compiles.

    python benchmarks/study_programs.py            # trace, compile CPU, fusions per program
    python benchmarks/study_programs.py --run 5    # also the run time of 5 chunks
    python benchmarks/study_programs.py --ab-ynn   # also run time with / without YNNPACK

For each strategy of the paper's scenario (10,000 trials' chunk size, all three methods,
2 host CPU devices as `jaxloc table1` uses on this machine): the seconds to trace and
lower `jaxloc._study.engine._run_chunk`, the process CPU seconds of its XLA compile, and the
number of fused kernels in the compiled program (XLA:CPU compiles each with LLVM: the
compile time grows with their number). With `--run N`, the compiled program runs `N`
chunks of trials (seed 0, chunks 0 .. N-1) and the median seconds of all but the first
are printed; `--out FILE` writes every figure as JSON. With `--ab-ynn`, the same program
is compiled a second time with XLA:CPU's default YNNPACK library fusions on, and chunks
are run alternately with both programs (median of 4 chunks each), so the machine's drift
cancels.
"""

import argparse
import json
import os
import re
import resource
import subprocess
import time


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ab-ynn", action="store_true")
    parser.add_argument("--run", type=int, default=0, help="chunks to run and time")
    parser.add_argument("--out", help="write the figures to this JSON file")
    parser.add_argument("--devices", type=int, default=2)
    args = parser.parse_args()
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_force_host_platform_device_count={args.devices}"
    )
    import equinox as eqx
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import jaxloc._study.engine as mc
    from jaxloc import Scenario
    from jaxloc._core.compiler import CPU_OPTIONS
    from jaxloc._study.trial import METHODS

    chunk = mc.balanced_chunk_size(10_000)
    rows = []
    for strategy in ("sequential", "concurrent"):
        scenario = Scenario.paper(strategy)
        inputs = mc._chunk_inputs(scenario, 0, 0, chunk, METHODS)
        t0 = time.perf_counter()
        lowered = mc._run_chunk.lower(*inputs)
        t1, c0 = time.perf_counter(), _cpu()
        compiled = lowered.compile()
        c1 = _cpu()
        fusions = len(re.findall(r" fusion\(", compiled.compiled.as_text()))
        print(f"{strategy}: trace {t1 - t0:.1f} s, compile {c1 - c0:.1f} CPU-s, "
              f"{fusions} fusions (chunk {chunk}, {jax.device_count()} devices)", flush=True)
        row = dict(strategy=strategy, trace_s=round(t1 - t0, 2), compile_cpu_s=round(c1 - c0, 2),
                   fusions=fusions, chunk=chunk, devices=jax.device_count())
        if args.run:
            seconds = []
            for c in range(args.run):
                start = time.perf_counter()
                jax.block_until_ready(
                    compiled(*mc._chunk_inputs(scenario, 0, c * chunk, chunk, METHODS))
                )
                seconds.append(time.perf_counter() - start)
            row["chunk_s"] = [round(t, 3) for t in seconds]
            print(f"  run: {np.median(seconds[1:]):.2f} s per chunk of {chunk} (median of "
                  f"{args.run - 1}; {', '.join(f'{t:.2f}' for t in seconds)})", flush=True)
        rows.append(row)
        if not args.ab_ynn:
            continue
        ynn_on = dict(CPU_OPTIONS)
        del ynn_on["xla_cpu_experimental_ynn_fusion_type"]  # XLA's default: on
        with_ynn = eqx.filter_jit(mc._chunk_trials, compiler_options=ynn_on)
        times = {"without YNNPACK (jaxloc)": [], "with YNNPACK (XLA default)": []}
        programs = dict(zip(times, (mc._run_chunk, with_ynn)))
        for c in range(5):
            for name, program in programs.items():
                start = time.perf_counter()
                jax.block_until_ready(
                    program(*mc._chunk_inputs(scenario, 0, c * chunk, chunk, METHODS))
                )
                if c > 0:  # chunk 0 compiles the second program
                    times[name].append(time.perf_counter() - start)
        for name, ts in times.items():
            print(f"  {name}: {np.median(ts):.2f} s per chunk of {chunk} "
                  f"({', '.join(f'{t:.2f}' for t in ts)})", flush=True)
    if args.out:
        record = dict(
            commit=_commit(), load_average=os.getloadavg(), jax=jax.__version__, rows=rows
        )
        with open(args.out, "w") as f:
            json.dump(record, f, indent=1)


def _commit() -> str:
    """The commit of the jaxloc this script imported (which may be another checkout's, under
    `PYTHONPATH`), not of the script's own checkout."""
    import jaxloc

    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
            cwd=os.path.dirname(os.path.abspath(jaxloc.__file__)), check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


if __name__ == "__main__":
    main()
