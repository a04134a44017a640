"""Issue 17.1, evidence for the next observability gate: the smallest eigenvalue of the
Fisher information's Jacobi-scaled (unit-diagonal) form, from the whitened Jacobian as it is
("jacobi") and with every row first scaled to unit norm ("row-equilibrated", each
measurement counted once whatever its noise), placement 0 (the gauge) left out.

    python benchmarks/observability_rows.py [--clean 4096]

The gates use the row-equilibrated form since 8f08208 (`jaxloc._model.gates.
nonsingular_information`). `--clean N` also prints its smallest eigenvalue over N refined
cycles of the paper's scenario per strategy (seeds `split(key(0), N)`), the margin of clean
data above the gates' floor of 1e-10: at 8f08208, N = 4096, smallest 4.0e-5 (sequential)
and 1.6e-5 (concurrent), 1 % quantile 1.5e-4 / 1.6e-4, median 2.9e-4 / 2.7e-4.

Cases: a noiseless cycle (pixel_sigma 0: pixels weighed at the 1e-6 px floor, the scale
fixed by 1 % odometry), complete and with one mutual bearing missing (observable); and
cycles 28, 29 of tests/test_robust.py's outlier batch after a Huber refinement rejected
C2's step-0 sighting of C3 (a rotation left free: singular), cycle 0 as a control. At
f9301c7: jacobi 8.7e-15 / 9.4e-15 (noiseless), -5e-17 / 9e-17 (free), 1.4e-4 (control);
row-equilibrated 3.4e-4 / 3.4e-4, -1.6e-16 / 7.1e-16, 2.0e-4: only the row-equilibrated
form separates "observable at disparate noise levels" from "a direction nothing touches".
"""

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np


jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import jaxloc  # noqa: E402
import test_robust  # noqa: E402
from jaxloc._core.linalg import row_equilibrated_gram  # noqa: E402
from jaxloc._model.gates import gate_point  # noqa: E402
from jaxloc._model.measurements import (  # noqa: E402
    cycle_data,
    unknowns_jacobian,
    whitened_blocks,
    whitened_with_jacobian,
)
from jaxloc._refine.cycle import refined_data  # noqa: E402


def smallest_scaled_eigenvalues(estimate, strategy, rig, data) -> tuple[float, float]:
    """(Jacobi-scaled, row-equilibrated then Jacobi-scaled) smallest eigenvalue of the
    information at `estimate` on `data`, placement 0 (the gauge) left out."""
    point = gate_point(estimate, data, strategy)
    _, J = whitened_with_jacobian(point.T_place, point.T_over, data, rig, strategy)
    J = np.asarray(J).reshape(J.shape[0], -1)[:, 6:]
    norms = np.linalg.norm(J, axis=1)
    rows = J[norms > 0] / norms[norms > 0, None]
    out = []
    for M in (J, rows):
        H = M.T @ M
        d = 1 / np.sqrt(np.diag(H))
        out.append(float(np.linalg.eigvalsh(H * d[:, None] * d[None, :])[0]))
    return out[0], out[1]


def report(name, values) -> None:
    print(f"{name}: jacobi {values[0]:.3g}, row-equilibrated {values[1]:.3g}")


def clean_distribution(strategy: str, n: int) -> None:
    """Smallest row-equilibrated, Jacobi-scaled eigenvalue of the information at `n`
    refined clean cycles of the paper's scenario (those that kept every robot in view)."""
    scenario = jaxloc.Scenario.paper(strategy)

    def one(key):
        _, obs, visible = jaxloc.simulate_cycle(scenario, key)
        est = jaxloc.localize_cycle(obs, scenario.rig, throw=False)
        refined = jaxloc.refine_cycle(obs, scenario.rig, est, throw=False)
        data = cycle_data(obs, scenario.rig)
        point = gate_point(refined, data, strategy)
        _, B = whitened_blocks(point.T_place, point.T_over, data, scenario.rig, strategy)
        G = row_equilibrated_gram(unknowns_jacobian(B, strategy))
        d = 1 / jnp.sqrt(jnp.diag(G))
        return visible, jnp.linalg.eigvalsh(G * d[:, None] * d[None, :])[0]

    visible, smallest = map(np.asarray, jax.jit(jax.vmap(one))(jr.split(jr.key(0), n)))
    e = smallest[visible]
    print(f"clean {strategy} ({visible.sum()} cycles): smallest {e.min():.3g}, "
          f"1% quantile {np.quantile(e, 0.01):.3g}, median {np.median(e):.3g}")


def main() -> None:
    scenario = jaxloc.Scenario.paper("sequential", pixel_sigma=0.0)
    _, obs, _ = jax.jit(jaxloc.simulate_cycle)(scenario, jr.key(3))
    missing = obs.mutual.at[1, 1, 2].set(jnp.nan)
    for name, mutual in (("noiseless complete", obs.mutual), ("noiseless missing", missing)):
        o = jaxloc.CycleObservations(mutual, obs.overhead, obs.odometry, obs.odometry_sigma,
                                     "sequential")  # fmt: skip
        est = jaxloc.localize_cycle(o, scenario.rig, throw=False)
        data = cycle_data(o, scenario.rig)
        report(name, smallest_scaled_eigenvalues(est, o.strategy, scenario.rig, data))
    T = test_robust
    keys = jr.split(jr.key(11), T.BATCH)
    for i in (28, 29, 0):
        k_sim, k_pick, k_out = jr.split(keys[i], 3)  # as test_robust._batch draws them
        _, o, _ = jaxloc.simulate_cycle(T.SCENARIO, k_sim)
        m, ov = T._sighting_mask(o, k_pick)
        bad = jaxloc.add_outliers(o, T.RIG, m, ov, key=k_out)
        est = jaxloc.localize_cycle(bad, T.RIG, throw=False)
        robust = jaxloc.refine_cycle(bad, T.RIG, est, loss="huber", throw=False)
        data = refined_data(cycle_data(bad, T.RIG), robust)
        report(f"robust cycle {i}", smallest_scaled_eigenvalues(robust, bad.strategy, T.RIG, data))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clean", type=int, default=0, metavar="N")
    args = parser.parse_args()
    main()
    for strategy in ("sequential", "concurrent") if args.clean else ():
        clean_distribution(strategy, args.clean)
