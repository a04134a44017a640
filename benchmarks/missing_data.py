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
`WRONG_POSE_NEES`) or sit on an unobservable cycle; the statuses of the observable cycles
not localized (refined and closed form), and the `ambiguous` ones split by how close
their runner-up minimum fits (within `AMBIGUITY_MARGIN` or not) with how many of each
would be wrong if the best were reported. Writes JSON.
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
from jaxloc._model.gates import AMBIGUITY_MARGIN  # noqa: E402
from jaxloc._study.robustness import missing_data_trial, WRONG_POSE_NEES  # noqa: E402


@ft.partial(jax.jit, static_argnames="strategy")
def _batch(strategy, keys, probability):
    scenario = jaxloc.Scenario.paper(strategy)
    return jax.vmap(lambda k: missing_data_trial(scenario, k, probability))(keys)


def _ambiguous_split(r, base, names) -> dict:
    """The observable cycles the refinement calls `ambiguous`, by how much worse its
    runner-up minimum fits (`runner_up_chi2 - refined_chi2`): within `AMBIGUITY_MARGIN`
    (4, a likelihood ratio below e^2: two minima the data do not tell apart) or not (only
    within the wider `STAND_IN_MARGIN` of a stand-in search, or `ambiguous` by the gates'
    own rival minima); and of each, how many would be wrong (NEES above
    `WRONG_POSE_NEES`) if the best minimum were reported."""
    amb = base & (r["refined"] == {v: k for k, v in names.items()}["ambiguous"])
    gap = r["runner_up_chi2"] - r["refined_chi2"]
    wrong = r["refined_nees"] > WRONG_POSE_NEES
    close = amb & (gap < AMBIGUITY_MARGIN)
    wide = amb & (gap >= AMBIGUITY_MARGIN)
    return {
        "ambiguous": int(amb.sum()),
        "within_ambiguity_margin": int(close.sum()),
        "not_within_ambiguity_margin": int(wide.sum()),
        "best_wrong_within_ambiguity_margin": int(np.sum(close & wrong)),
        "best_wrong_not_within_ambiguity_margin": int(np.sum(wide & wrong)),
    }


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
    names = jaxloc.status_names()
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
            "not_localized_status": {
                names[int(c)]: int(n)
                for c, n in zip(*np.unique(r["refined"][base & ~ok], return_counts=True))
            },
            "not_localized_closed_status": {
                names[int(c)]: int(n)
                for c, n in zip(*np.unique(r["closed"][base & ~ok], return_counts=True))
            },
            "ambiguous_by_margin": _ambiguous_split(r, base, names),
            "seconds": time.perf_counter() - t0,
        }
        report[strategy] = row
        print(strategy, dumps_json(row))
    with open(args.out, "w") as f:
        f.write(dumps_json(report))


if __name__ == "__main__":
    main()
