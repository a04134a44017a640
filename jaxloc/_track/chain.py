r"""Chaining cycles into the first cycle's frame, with first-order covariance (issue 21.2).

Every cycle is estimated alone, in its own world frame `W_k` (C1's body frame at the start
of cycle `k`, the paper's choice). Cycle `k + 1` starts where cycle `k` ended, so its frame
is C1's end-of-cycle pose in cycle `k`'s estimate, `T_{W_k W_{k+1}} = A_k`, and the frame of
cycle `k` in the first cycle's is the product `F_k = A_0 A_1 ... A_{k-1}`. A pose `X` of cycle
`k` is `F_k X` in `W_0`.

Covariance (right perturbations, `jaxloc._track.frames`): with `F_hat = F exp(xi)` and
`X_hat = X exp(delta)` from independent cycles,
`F_hat X_hat = F X exp(Ad(X^-1) xi + delta)`, so
`cov = Ad(X^-1) cov(xi) Ad(X^-1)^T + cov(delta)`; the next frame is cycle `k`'s C1 chained
the same way. With each cycle's own covariance this is the chained estimate's covariance;
with each cycle's Cramér–Rao bound at the true poses it is the *chained bound*: the error
an efficient per-cycle estimator chained this way would have, to first order.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Bool, Float

from .._core.poses import compose, identity_params, inverse
from .._core.results import RESULTS
from .._cycle.estimate import CycleEstimate
from .._cycle.rig import Rig
from .._study.trial import final_poses
from .frames import end_covariance, transport


class ChainState(eqx.Module):
    """The chain after some cycles: the next cycle's frame in `W_0` and its covariance.

    **Fields:** `frame` (`wxyz_xyz`, `T_{W_0 W_k}`), `covariance` `(6, 6)` (its right
    perturbation), `ok` (every cycle so far was successful).
    """

    frame: Float[Array, "7"]
    covariance: Float[Array, "6 6"]
    ok: Bool[Array, ""]


def chain_start(dtype) -> ChainState:
    """The chain before the first cycle: `W_0` itself, exactly known."""
    return ChainState(identity_params(dtype), jnp.zeros((6, 6), dtype), jnp.array(True))


def chain_step(
    state: ChainState,
    end_poses: Float[Array, "4 7"],
    end_covariance: Float[Array, "24 24"],
    ok: Bool[Array, ""],
) -> tuple[ChainState, Float[Array, "4 7"], Float[Array, "4 6 6"]]:
    """Chain one cycle.

    **Arguments:** the chain `state`; the cycle's end-of-cycle body poses of (C, C1, C2,
    C3) in its own frame `W_k` (`wxyz_xyz`, `(4, 7)`) and their joint right-perturbation
    covariance `(24, 24)` ([`jaxloc._track.frames.end_covariance`][]); whether the cycle's
    estimate is usable.

    **Returns:** `(state, poses, covariances)`: the chain for the next cycle, the four
    poses in `W_0` and their covariances `(4, 6, 6)` (right perturbations; the frame's
    error carried in). The next frame is C1's chained pose.
    """
    def one(X, cov):
        T = compose(jaxlie.SE3(state.frame), jaxlie.SE3(X)).wxyz_xyz
        return T, transport(inverse(jaxlie.SE3(X)).wxyz_xyz, state.covariance) + cov

    blocks = jnp.stack([end_covariance[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(4)])
    poses, covs = jax.vmap(one)(end_poses, blocks)
    return ChainState(poses[1], covs[1], state.ok & ok), poses, covs


def cycle_end(estimate: CycleEstimate, rig: Rig, strategy: str):
    """A cycle estimate's end-of-cycle body poses of (C, C1, C2, C3) in its frame `(4, 7)`
    and their joint covariance `(24, 24)` (from `estimate.covariance.tangent`)."""
    poses = final_poses(estimate.poses, rig).wxyz_xyz
    cov = end_covariance(estimate.covariance.tangent, strategy, rig.mounts[0])
    return poses, cov


def chain_estimates(
    estimates: CycleEstimate, rig: Rig, strategy: str
) -> tuple[Float[Array, "K 4 7"], Float[Array, "K 4 6 6"], Bool[Array, " K"]]:
    """Chain K cycle estimates (a [`jaxloc.CycleEstimate`][] with a leading axis K, e.g.
    `jax.vmap(refine_cycle)` of K cycles' observations) into the first cycle's frame.

    **Returns:** `(poses, covariances, ok)`: each cycle's end-of-cycle body poses of (C,
    C1, C2, C3) in `W_0` `(K, 4, 7)`, their right-perturbation covariances
    `(K, 4, 6, 6)` ([`jaxloc._track.frames.pose_covariances`][] gives world-frame
    position covariances), and whether every cycle up to `k` was successful `(K,)`: a
    failed cycle breaks the chain for every later one.
    """
    dtype = estimates.poses.T_world_overhead.wxyz_xyz.dtype

    def step(state, est):
        end, cov = cycle_end(est, rig, strategy)
        state, poses, covs = chain_step(state, end, cov, est.result == RESULTS.successful)
        return state, (poses, covs, state.ok)

    _, out = jax.lax.scan(step, chain_start(dtype), estimates)
    return out
