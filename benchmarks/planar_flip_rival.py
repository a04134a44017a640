"""The planar-flip rival of the gates (issue 17), measured on its own.

    python benchmarks/planar_flip_rival.py [--cycles 2048]

The ground robots stand on a floor, so the overhead camera sees nearly coplanar points and
may sit in the mirror (flipped) pose of that plane: a second local minimum only the
perspective tells apart. The flip of a polished gate point `(P, O)` is
`jaxloc._model.mirrors.flip_start` (which the gates run only when a sighting is missing;
here it is run on every cycle, to measure what it would do on full data). It is
polished by `jaxloc._model.gates.MIRROR_STEPS` Gauss--Newton steps and evaluated once, and
judged by the mirror's rule (converged, more than `DISTINCT_MINIMUM` away, chi-square
within `AMBIGUITY_MARGIN`).

Prints (1) for missing-data cycle 1129 of `benchmarks/missing_data.py` (sequential, seed
0, probability 0.05; its closed form was `successful` with C 3.7 m off until the gates
looked for the flip, 750bcfb) the chi-square of
the gate point, of the polished flip and C's position; (2) on `--cycles` clean cycles of
the paper's scenario per strategy (`split(key(0), N)`), how many `successful` closed
forms the flip would make `ambiguous`.
"""

import argparse

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import jaxloc  # noqa: E402
import numpy as np  # noqa: E402
from jaxloc._model import gates  # noqa: E402
from jaxloc._model.measurements import cycle_data  # noqa: E402
from jaxloc._model.mirrors import flip_start  # noqa: E402


def gate_and_flip(scenario, obs):
    """The closed form's status, its gate point's chi-square and C, and the polished
    flip's chi-square (inf unless a distinct converged minimum) and C."""
    strategy = scenario.strategy
    closed = jaxloc.localize_cycle(obs, scenario.rig, throw=False)
    data = cycle_data(obs, scenario.rig)
    point = gates.gate_point(closed, data, strategy)
    P, O, r, _ = gates._polished(
        point.T_place, point.T_over, data, scenario.rig, strategy, True, gates.POLISH_STEPS
    )
    X, decrement = (P, flip_start(P, O)[0]), jnp.inf
    for i in range(gates.MIRROR_STEPS + 1):
        moved, r_flip, _, predicted, _ = gates._gauss_newton_step(X, data, scenario.rig, strategy)
        if i < gates.MIRROR_STEPS:
            X, decrement = moved, predicted
    chi2_flip = jnp.sum(r_flip**2)
    distinct = jnp.linalg.norm(X[1][4:] - O[4:]) > gates.DISTINCT_MINIMUM
    minimum = (decrement < gates.CONVERGED_DECREMENT) & jnp.isfinite(chi2_flip) & distinct
    return (closed.result._value, jnp.sum(r**2), O[4:], jnp.where(minimum, chi2_flip, jnp.inf),
            X[1][4:])  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=2048)
    args = parser.parse_args()
    scenario = jaxloc.Scenario.paper("sequential")
    k_sim, k_drop = jr.split(jr.fold_in(jr.key(0), 1129))
    truth, obs, _ = jaxloc.simulate_cycle(scenario, k_sim)
    obs = jaxloc.drop_sightings(obs, 0.05, key=k_drop)
    _, chi2, c, chi2_flip, c_flip = jax.jit(lambda o: gate_and_flip(scenario, o))(obs)
    print(f"missing-data cycle 1129: gate point chi2 {float(chi2):.2f}, C {np.round(c, 3)}; "
          f"polished flip chi2 {float(chi2_flip):.2f}, C {np.round(c_flip, 3)}; true C "
          f"{np.round(truth.poses.T_world_overhead.wxyz_xyz[4:], 3)}")  # fmt: skip
    for strategy in ("sequential", "concurrent"):
        scenario = jaxloc.Scenario.paper(strategy)

        def one(key, scenario=scenario):
            _, obs, visible = jaxloc.simulate_cycle(scenario, key)
            return visible, *gate_and_flip(scenario, obs)

        keys = jr.split(jr.key(0), args.cycles)
        visible, result, chi2, _, chi2_flip, _ = map(np.asarray, jax.jit(jax.vmap(one))(keys))
        ok = visible & (result == jaxloc.RESULTS.successful._value)
        ambiguous = ok & (chi2_flip - chi2 < gates.AMBIGUITY_MARGIN)
        print(f"{strategy}: {ok.sum()} successful clean closed forms, {ambiguous.sum()} the "
              f"flip would make ambiguous, {np.sum(ok & np.isfinite(chi2_flip))} with a "
              f"distinct flipped minimum")  # fmt: skip


if __name__ == "__main__":
    main()
