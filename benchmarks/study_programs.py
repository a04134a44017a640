"""Size and cost of the study programs that `jaxloc table1` compiles.

    python benchmarks/study_programs.py            # trace, compile CPU, fusions per program
    python benchmarks/study_programs.py --ab-ynn   # also run time with / without YNNPACK

For each strategy of the paper's scenario (10,000 trials' chunk size, all three methods,
2 host CPU devices as `jaxloc table1` uses on this machine): the seconds to trace and
lower `jaxloc._study.engine._run_chunk`, the process CPU seconds of its XLA compile, and the
number of fused kernels in the compiled program (XLA:CPU compiles each with LLVM: the
compile time grows with their number). With `--ab-ynn`, the same program is compiled a
second time with XLA:CPU's default YNNPACK library fusions on, and chunks are run
alternately with both programs (median of 4 chunks each), so the machine's drift cancels.
"""

import argparse
import os
import re
import resource
import time


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ab-ynn", action="store_true")
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


if __name__ == "__main__":
    main()
