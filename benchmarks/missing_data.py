"""Missing sightings: each mutual and overhead sighting missing independently (issue 20).

    python benchmarks/missing_data.py [--cycles 10000] [--probability 0.05] [--batch 500]
                                      [--strategy sequential concurrent] [--out FILE]

Each cycle (`jaxloc._study.robustness.missing_data_trial`): the paper's scenario (2 px
paper noise, 1% odometry), a simulated cycle, each sighting dropped with `--probability`
(`jaxloc.drop_sightings`: NaN and not visible), the closed form and the refinement
started from it (the study trial's `estimate_all`), and the Cramér–Rao bound of the
measurements present (missing sightings weighed 0) at the true poses. A cycle is
*observable* when that information is nonsingular (`observable` of the trial: no rotation
left free, e.g. by a robot's one bearing at a placement it holds for one step only) and
the bound passes the gates' observability test; *localized* when the refinement is
`successful`.
Reports per strategy: observable cycles, the share of them localized, the refined RMSE of
C's position against the bound's (efficiency = bound RMSE / RMSE over the localized
observable cycles; targets >= 95% localized and efficiency >= 0.95), and the `successful`
estimates (closed form or refined) that are wrong (position NEES above
`WRONG_POSE_NEES`) or sit on an unobservable cycle. Writes JSON.
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
from jaxloc._study.robustness import missing_data_trial, WRONG_POSE_NEES  # noqa: E402


@ft.partial(jax.jit, static_argnames="strategy")
def _batch(strategy, keys, probability):
    scenario = jaxloc.Scenario.paper(strategy)
    return jax.vmap(lambda k: missing_data_trial(scenario, k, probability))(keys)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=10_000, help="per strategy")
    parser.add_argument("--probability", type=float, default=0.05)
    parser.add_argument("--batch", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--strategy", nargs="+", default=["sequential", "concurrent"])
    parser.add_argument("--out", default="benchmarks/results/missing_data.json")
    args = parser.parse_args()
    report = {"cycles_per_strategy": args.cycles, "probability": args.probability}
    for strategy in args.strategy:
        t0 = time.perf_counter()
        parts = []
        for start in range(0, args.cycles, args.batch):
            idx = jnp.arange(start, start + args.batch)
            keys = jax.vmap(lambda i: jr.fold_in(jr.key(args.seed), i))(idx)
            out = jax.device_get(_batch(strategy, keys, args.probability))
            parts.append(out)
            done = min(start + args.batch, args.cycles)
            print(f"  {strategy}: {done}/{args.cycles} ({time.perf_counter() - t0:.0f} s)",
                  flush=True)  # fmt: skip
        r = {k: np.concatenate([p[k] for p in parts])[: args.cycles] for k in parts[0]}
        assert r["finite"].all(), "a pose is not finite"
        vis, obs_ = r["visible"], r["observable"]
        ok = r["refined"] == 0
        closed_ok = r["closed"] == 0
        base = vis & obs_
        loc = base & ok
        rmse = float(np.sqrt(r["sq_error_c"][loc].mean()))
        bound = float(np.sqrt(r["bound_c"][loc].mean()))
        wrong = {
            "closed": int(np.sum(vis & closed_ok & (r["closed_nees"] > WRONG_POSE_NEES))),
            "refined": int(np.sum(vis & ok & (r["refined_nees"] > WRONG_POSE_NEES))),
        }
        unobs = {
            "closed": int(np.sum(vis & ~obs_ & closed_ok)),
            "refined": int(np.sum(vis & ~obs_ & ok)),
        }
        row = {
            "cycles": int(args.cycles),
            "visible": int(vis.sum()),
            "with_missing": int(np.sum(vis & (r["missing"] > 0))),
            "observable": int(base.sum()),
            "localized": int(loc.sum()),
            "localized_share": float(loc.sum() / max(base.sum(), 1)),
            "closed_successful_share": float(np.sum(base & closed_ok) / max(base.sum(), 1)),
            "rmse_c_m": rmse,
            "bound_rmse_c_m": bound,
            "efficiency": bound / rmse,
            "successful_wrong": wrong,
            "successful_unobservable": unobs,
            "seconds": time.perf_counter() - t0,
        }
        report[strategy] = row
        print(strategy, dumps_json(row))
    with open(args.out, "w") as f:
        f.write(dumps_json(report))


if __name__ == "__main__":
    main()
