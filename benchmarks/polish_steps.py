"""How many Gauss--Newton polish steps the closed forms' gates need.

    python benchmarks/polish_steps.py [--cycles 2048] [--seed 7]

The gates of a closed-form estimate look at its maximum-likelihood optimum nearby,
`jaxloc._model.gates.POLISH_STEPS` Gauss--Newton steps away (four). For the paper
scenario (both strategies, default noise), `localize_cycle` ("robust" and "paper") is run
with 4, 2 and 1 steps on the same cycles; printed: how many statuses differ from the
4-step ones, and the largest relative change of the fit statistic (`checks.chi2_min`) and
of the position covariance's trace among the cycles both call successful.
"""

import argparse

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    import jaxloc
    import jaxloc._model.gates as gates

    n = args.cycles
    for strategy in ("sequential", "concurrent"):
        scenario = jaxloc.Scenario.paper(strategy)
        rig = scenario.rig
        simulate = jax.vmap(lambda k, s=scenario: jaxloc.simulate_cycle(s, k)[1])
        obs = jax.jit(simulate)(jr.split(jr.key(args.seed), n))
        runs = {}
        for steps in (4, 2, 1):
            gates.POLISH_STEPS = steps  # read when the gates are traced
            for method in ("robust", "paper"):
                e = jax.jit(jax.vmap(
                    lambda o, m=method: jaxloc.localize_cycle(o, rig, method=m, throw=False)
                ))(obs)  # fmt: skip
                runs[steps, method] = (
                    np.asarray(e.result._value), np.asarray(e.checks.chi2_min),
                    np.asarray(jnp.trace(e.covariance.position, axis1=-2, axis2=-1)),
                )  # fmt: skip
        for steps in (2, 1):
            for method in ("robust", "paper"):
                (r4, c4, p4), (r, c, p) = runs[4, method], runs[steps, method]
                both = (r4 == 0) & (r == 0)
                dchi = np.max(np.abs(c[both] - c4[both]) / np.maximum(c4[both], 1.0))
                dcov = np.max(np.abs(p[both] - p4[both]) / p4[both])
                print(f"{strategy} {method}: {steps} steps against 4: statuses differ in "
                      f"{int(np.sum(r != r4))} of {n} cycles; largest relative change of "
                      f"chi2_min {dchi:.2e}, of the position covariance {dcov:.2e}")  # fmt: skip


if __name__ == "__main__":
    main()
