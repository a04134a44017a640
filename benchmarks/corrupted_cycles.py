"""10^5 seeded corrupted cycles: does any `successful` estimate contradict its covariance?

    python benchmarks/corrupted_cycles.py [--cycles 100000] [--batch 2048] [--out FILE]

Each cycle: a random formation of the paper's scenario (triangle, headings, the climbing
robot's place), a simulated cycle with 2 px paper noise, one defect of `jaxloc.DEFECTS`
(round robin over the defects), the closed form (`jaxloc.localize_cycle`) and the
refinement (`jaxloc.refine_cycle`); half the cycles sequential, half concurrent. Counts,
per defect and stage, the successful estimates and those whose position NEES (under the
estimate's own covariance) exceeds the 99.99% chi-square quantile (`NEES>q`: the
first-order covariance is optimistic in the tails of random near-degenerate formations,
so clean cycles have some) and those that are wrong (`wrong`: NEES above
`WRONG_POSE_NEES`, an error ten times the claimed standard deviation): the gates'
promise is that defects add none. Of the wrong ones, `warned` counts those whose own
`checks.blunder_nees` exceeds `WRONG_POSE_NEES` too (the estimate said that an undetected
blunder in one measurement could move a position by more than ten of its standard
deviations), and `warned_all` counts every successful estimate that says so. Prints a
table and writes JSON (strict, NaN as null).
"""

import argparse
import functools as ft
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import jaxloc  # noqa: E402
import numpy as np  # noqa: E402
from jaxloc._core.files import dumps_json  # noqa: E402
from jaxloc._study.robustness import corrupted_trial, NEES_LIMIT, WRONG_POSE_NEES  # noqa: E402


@ft.partial(jax.jit, static_argnames="strategy")
def _batch(strategy, keys, defects):
    base = jaxloc.Scenario.paper(strategy)
    return jax.vmap(lambda k, d: corrupted_trial(base, k, d))(keys, defects)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=100_000)
    parser.add_argument("--batch", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/results/corrupted_cycles.json")
    args = parser.parse_args()
    n_defects = len(jaxloc.DEFECTS)
    counts = {}
    t0 = time.perf_counter()
    done = 0
    for strategy in ("sequential", "concurrent"):
        n = args.cycles // 2
        for start in range(0, n, args.batch):
            idx = np.arange(start, min(start + args.batch, n))
            pad = args.batch - idx.size
            idx_full = np.concatenate([idx, np.full(pad, idx[-1])]) if pad else idx
            keys = jax.vmap(lambda i: jr.fold_in(jr.key(args.seed), i))(
                jnp.asarray(idx_full) + (0 if strategy == "sequential" else 10**9)
            )
            defects = jnp.asarray(idx_full % n_defects)
            out = jax.tree.map(np.asarray, _batch(strategy, keys, defects))
            out = jax.tree.map(lambda x: x[: idx.size], out)
            for d in range(n_defects):
                sel = (idx % n_defects == d) & out["visible"]
                for stage in ("closed", "refined"):
                    key = (strategy, jaxloc.DEFECTS[d], stage)
                    c = counts.setdefault(key, [0, 0, 0, 0, 0, 0])
                    ok = sel & (out[stage] == 0)
                    c[0] += int(sel.sum())
                    c[1] += int(ok.sum())
                    nees = np.max(out[f"{stage}_nees"], axis=1)
                    c[2] += int((ok & (nees > NEES_LIMIT)).sum())
                    wrong = ok & (nees > WRONG_POSE_NEES)
                    c[3] += int(wrong.sum())
                    warned = out[f"{stage}_blunder"] > WRONG_POSE_NEES
                    c[4] += int((wrong & warned).sum())
                    c[5] += int((ok & warned).sum())
            done += idx.size
            rate = done / (time.perf_counter() - t0)
            print(f"{strategy}: {done} cycles, {rate:.0f} cycles/s", flush=True)
    rows = [
        {"strategy": s, "defect": d, "stage": st, "visible": c[0], "successful": c[1],
         "nees_above_99.99%": c[2], "wrong": c[3], "warned": c[4], "warned_all": c[5]}
        for (s, d, st), c in counts.items()
    ]  # fmt: skip
    print(f"\n{'strategy':<11}{'defect':<19}{'stage':<9}{'visible':>8}{'successful':>11}"
          f"{'NEES>q':>8}{'wrong':>7}{'warned':>8}{'warned_all':>11}")  # fmt: skip
    for r in rows:
        print(f"{r['strategy']:<11}{r['defect']:<19}{r['stage']:<9}{r['visible']:>8}"
              f"{r['successful']:>11}{r['nees_above_99.99%']:>8}{r['wrong']:>7}"
              f"{r['warned']:>8}{r['warned_all']:>11}")  # fmt: skip
    total = sum(r["successful"] for r in rows)
    bad = sum(r["nees_above_99.99%"] for r in rows)
    wrong = sum(r["wrong"] for r in rows)
    warned = sum(r["warned"] for r in rows)
    warned_all = sum(r["warned_all"] for r in rows)
    print(f"\n{total} successful estimates, {bad} with a position NEES above the 99.99% "
          f"quantile ({NEES_LIMIT}), {wrong} wrong (NEES above {WRONG_POSE_NEES}), {warned} "
          f"of them warned by their blunder_nees (> {WRONG_POSE_NEES}; {warned_all} "
          f"successful estimates warned in all); {time.perf_counter() - t0:.0f} s")  # fmt: skip
    with open(args.out, "w") as f:
        f.write(dumps_json({"command": "python benchmarks/corrupted_cycles.py", "args":
                            vars(args), "rows": rows, "successful": total,
                            "nees_above_quantile": bad, "wrong": wrong, "warned": warned,
                            "warned_all": warned_all}))  # fmt: skip


if __name__ == "__main__":
    main()
