"""How many Levenberg--Marquardt steps the joint refinement takes, per cycle.

    python benchmarks/refine_steps.py [--cycles 2048] [--seed 3]

Paper scenario, both strategies, default noise: `localize_cycle` then `refine_cycle`
(`max_steps` as the studies use) under one `jit(vmap)`; prints the percentiles of
`stats["num_steps"]` and the fraction of cycles beyond 8 and 12 steps. A batch's
`while_loop` runs as long as its slowest cycle: this bounds what compacting the
unconverged cycles of a batch could save (the mean over the mean of the batch maxima).
"""

import argparse

import jax
import jax.random as jr
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--batch", type=int, default=32, help="lax.map step of the studies")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    import jaxloc
    from jaxloc._study.trial import REFINE_MAX_STEPS

    for strategy in ("sequential", "concurrent"):
        scenario = jaxloc.Scenario.paper(strategy)
        rig = scenario.rig

        def steps(key, scenario=scenario, rig=rig):
            _, obs, _ = jaxloc.simulate_cycle(scenario, key)
            closed = jaxloc.localize_cycle(obs, rig, throw=False)
            refined = jaxloc.refine_cycle(
                obs, rig, closed, throw=False, max_steps=REFINE_MAX_STEPS
            )
            return refined.stats["num_steps"]

        n = np.asarray(jax.jit(jax.vmap(steps))(jr.split(jr.key(args.seed), args.cycles)))
        p50, p90, p99 = np.percentile(n, [50, 90, 99])
        batches = n[: n.size // args.batch * args.batch].reshape(-1, args.batch)
        waste = batches.max(axis=1).mean() / n.mean()
        print(f"{strategy}: {args.cycles} cycles, steps median {p50:.0f} p90 {p90:.0f} "
              f"p99 {p99:.0f} max {n.max()}, mean {n.mean():.2f}; > 8: {(n > 8).mean():.2%}, "
              f"> 12: {(n > 12).mean():.2%}; batches of {args.batch} run "
              f"{waste:.2f}x the mean steps (the most compaction could save)")


if __name__ == "__main__":
    main()
