r"""Tracking one run: every cycle's estimate, chained, smoothed, and one-step updates
([`jaxloc.track_cycles`][]).

For each cycle `k`, in order (one `lax.scan` over the cycles):

1. the cycle alone: the closed form and the joint refinement
   ([`jaxloc.localize_cycle`][], [`jaxloc.refine_cycle`][]), in its own frame `W_k`;
2. chaining it into `W_0` (`jaxloc._track.chain`);
3. one-step localization of the climbing robot from the cycle's first formation
   (`jaxloc._track.one_step`), before the cycle's moves: its prior is the smoother's
   estimate of the previous cycle's end propagated by the climbing robot's odometry (with
   the end formation's perimeter), or, for the first cycle, the height prior;
4. the fixed-lag smoother (`jaxloc._track.smoother`), started from the cycle's
   refinement mapped into `W_0` through its own estimate of the cycle's start.

A failed cycle breaks the chain and the smoother for every later cycle (their status
stays the first failure's); a one-step update whose prior came from a failed smoother
fails with it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._core.compiler import jit
from .._core.results import RESULTS, status_code
from .._cycle.rig import Rig
from .._model.covariance import estimate_placements
from .._model.measurements import cycle_data
from .._refine.cycle import refine_cycle
from .._solvers.localize import localize_cycle_methods
from .._study.trial import REFINE_MAX_STEPS
from .chain import chain_start, chain_step, cycle_end
from .one_step import (
    localize_one_step,
    one_step_prior_from,
    OneStepEstimate,
    OneStepPrior,
    Snapshot,
)
from .simulate import TrackObservations
from .smoother import smoother_start, smoother_update, WindowLayout


#: Cycles of the fixed-lag smoother's window by default.
DEFAULT_WINDOW = 2


class TrackEstimates(eqx.Module):
    """Every estimate of a tracked run (leading axis K, the cycles).

    **Fields:**

    - `cycle_status` `(K,)`: each cycle's own refined estimate's status (int32, gates
      included; 0 = successful).
    - `chain_poses` `(K, 4, 7)`, `chain_covariance` `(K, 4, 6, 6)`, `chain_status` `(K,)`:
      the chained end-of-cycle body poses of (C, C1, C2, C3) in `W_0`, their
      right-perturbation covariances, and the chain's status (the first failure's code).
    - `smoother_poses`, `smoother_covariance` `(K, 24, 24)` (joint), `smoother_status`: the
      fixed-lag smoother's.
    - `one_step`: the one-step estimates ([`OneStepEstimate`][], in each cycle's frame
      `W_k`), `one_step_status` `(K,)` and the priors they used, `one_step_prior`.
    """

    cycle_status: Int[Array, " K"]
    chain_poses: Float[Array, "K 4 7"]
    chain_covariance: Float[Array, "K 4 6 6"]
    chain_status: Int[Array, " K"]
    smoother_poses: Float[Array, "K 4 7"]
    smoother_covariance: Float[Array, "K 24 24"]
    smoother_status: Int[Array, " K"]
    one_step: OneStepEstimate
    one_step_status: Int[Array, " K"]
    one_step_prior: OneStepPrior


def _first_failure(previous, code):
    return jnp.where(previous == 0, code, previous)


@jit(inline=True)
def track_cycles(
    observations: TrackObservations, rig: Rig, *, window: int = DEFAULT_WINDOW
) -> TrackEstimates:
    r"""Track the team over K cycles: each cycle alone, chained, one-step updates of the
    climbing robot, and the fixed-lag smoother (see the module docstring).

    **Arguments:**

    - `observations`: a [`jaxloc.TrackObservations`][] (K cycles, the climbing robot's
      odometry between them, the first cycle's height prior).
    - `rig`: the team's [`jaxloc.Rig`][].
    - `window`: the smoother's window, in cycles (static). Keyword only.

    **Returns:** a [`TrackEstimates`][]. Pure, for one run: `jit` and `vmap` apply; the cost
    per cycle does not depend on K.
    """
    cycles = observations.cycles
    strategy = cycles.strategy
    layout = WindowLayout(strategy, window)
    dtype = cycles.mutual.dtype
    n_cycles = cycles.mutual.shape[0]
    zero = jnp.array(0, jnp.int32)

    def one_cycle(carry, inputs):
        chain, smoother, prev_end, prev_cov, chain_code = carry
        obs, climber, climber_sigma, k = inputs
        # 1. The cycle alone.
        (closed,) = localize_cycle_methods(obs, rig, ("robust",))
        est = refine_cycle(obs, rig, closed, max_steps=REFINE_MAX_STEPS, throw=False)
        code = status_code(est.result)
        ok = est.result == RESULTS.successful
        # 2. Chaining.
        end, end_cov = cycle_end(est, rig, strategy)
        chain, chain_poses, chain_cov = chain_step(chain, end, end_cov, ok)
        chain_code = _first_failure(chain_code, code)
        # 3. One-step localization from the cycle's first formation.
        propagated = one_step_prior_from(prev_end, prev_cov, climber, climber_sigma)
        first = OneStepPrior.height_prior(
            observations.height, observations.height_sigma, observations.tilt_sigma, dtype
        )
        prior = jax.tree.map(lambda a, b: jnp.where(k == 0, a, b), first, propagated)
        one = localize_one_step(Snapshot.of(obs, 0), rig, prior, throw=False)
        one_code = jnp.where((k == 0) | (smoother.status == 0), status_code(one.result),
                             smoother.status)  # fmt: skip
        # 4. The smoother, started from the cycle's refinement.
        T_place, T_over = estimate_placements(est.poses, strategy)
        smoother, smoothed = smoother_update(
            layout, smoother, cycle_data(obs, rig), climber, climber_sigma, T_place, T_over,
            est.result, est.checks.observable, rig,
        )  # fmt: skip
        out = (code, chain_poses, chain_cov, chain_code, smoothed.poses, smoothed.covariance,
               smoother.status, one, one_code, prior)  # fmt: skip
        return (chain, smoother, smoothed.poses, smoothed.covariance, chain_code), out

    ident = jnp.zeros((4, 7), dtype).at[:, 0].set(1.0)
    init = (chain_start(dtype), smoother_start(layout, dtype), ident,
            jnp.eye(24, dtype=dtype), zero)  # fmt: skip
    inputs = (cycles, observations.climber_odometry, observations.climber_odometry_sigma,
              jnp.arange(n_cycles))  # fmt: skip
    _, out = jax.lax.scan(one_cycle, init, inputs)
    return TrackEstimates(*out)
