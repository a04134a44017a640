r"""First-order covariance and Cramér–Rao lower bound of a localization cycle (DESIGN §5, §9).

Both use the measurement model and the parametrization of [`jaxloc.refine_cycle`][]:
every distinct robot placement's body pose and the overhead camera's optical-frame pose,
each `T exp(delta)` with `delta = (v, omega)` (jaxlie right perturbation), gauge fixed by
C1's start pose (the world frame `W`, exactly known). With `J` the Jacobian of the
sigma-whitened residuals (mutual pixels, overhead pixels, odometry), the Fisher
information is $F = J^\top J$ and the bound is $F^{-1}$:

- [`jaxloc.cycle_covariance`][]: $F^{-1}$ at an estimate (e.g. the refined one), with
  the measurements that were actually made: the estimate's first-order covariance.
- [`jaxloc.cycle_crlb`][]: $F^{-1}$ at the true poses, with the sightings the cameras
  make there (`in_view`): the Cramér–Rao bound of any unbiased estimator under Gaussian
  pixel noise of the rig's per-axis sigma.

Per camera (C, C1, C2, C3 at the end of the cycle) the position block (m^2, in `W`, the
camera centre for C; propagated from the tangent with `jax.jacfwd`, since jaxlie's
tangent translation is not the world position) and the rotation block (rad^2, the
tangent rotation; its trace is that of the geodesic rotation error's second moment) are
reported separately, never summed.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._core.compiler import jit
from .._core.linalg import spd_inverse
from .._cycle.estimate import CycleCovariance, CycleEstimate
from .._cycle.layout import first_sighting, num_steps, placement_ids
from .._cycle.observations import CycleObservations, CyclePoses
from .._cycle.rig import Rig
from .measurements import (
    cycle_data,
    CycleData,
    normal_equations,
    odometry_weight,
    pixel_weights,
    predict,
    unpack,
    visible,
)


def strategy_of(poses: CyclePoses) -> str:
    """The strategy of a cycle's poses, from its number of steps."""
    steps = poses.T_world_body.wxyz_xyz.shape[-3]
    return {num_steps(s): s for s in ("sequential", "concurrent")}[steps]


def _final_selection(strategy: str) -> np.ndarray:
    """Rows of the tangent picking the rotation of (C, C1, C2, C3) at the end, `(4, 3, n)`."""
    ids = placement_ids(strategy)
    n = 6 * (int(ids.max()) + 1)
    S = np.zeros((4, 3, n))
    S[0, :, n - 3 :] = np.eye(3)
    for r in range(3):
        p = int(ids[-1, r])
        if p > 0:
            S[r + 1, :, 6 * (p - 1) + 3 : 6 * (p - 1) + 6] = np.eye(3)
    return S


def covariance_from_information(
    information: Float[Array, "n n"], T_place, T_over, strategy: str
) -> CycleCovariance:
    """The [`jaxloc.CycleCovariance`][] of the tangent with this information matrix, at
    placements `T_place` `(placements, 7)` and overhead camera `T_over` `(7,)`."""
    cov, ok = spd_inverse(information)
    return covariance_of_tangent(cov, ok, T_place, T_over, strategy)


def _final_positions(T_place, T_over, strategy: str):
    """The end-of-cycle positions of (C, C1, C2, C3) as a function of the tangent."""
    ids = placement_ids(strategy)

    def positions(theta):
        P, O = unpack(theta, T_place, T_over)
        return jnp.concatenate([O[None, 4:], P[ids[-1], 4:]])

    return positions


def final_position_jacobian(T_place, T_over, strategy: str) -> Float[Array, "4 3 n"]:
    """`(4, 3, n)`: the derivative of the end-of-cycle (C, C1, C2, C3) positions (m, in
    `W`) with respect to the tangent of the placements `(T_place, T_over)`."""
    positions = _final_positions(T_place, T_over, strategy)
    n = 6 * T_place.shape[0]  # placement 0 is the gauge; the overhead camera adds 6
    return jax.jacfwd(positions)(jnp.zeros(n, T_place.dtype))


def covariance_of_tangent(
    tangent: Float[Array, "n n"], ok, T_place, T_over, strategy: str, position_jacobian=None
) -> CycleCovariance:
    """The [`jaxloc.CycleCovariance`][] of a tangent covariance `(n, n)`: its position
    (through the poses, by [`final_position_jacobian`][], or the one given) and rotation
    blocks of the four end-of-cycle poses."""
    G = position_jacobian
    if G is None:
        G = final_position_jacobian(T_place, T_over, strategy)
    S = jnp.asarray(_final_selection(strategy), tangent.dtype)
    return CycleCovariance(
        tangent=tangent,
        position=jnp.einsum("cin,nm,cjm->cij", G, tangent, G),
        rotation=jnp.einsum("cin,nm,cjm->cij", S, tangent, S),
        ok=ok,
    )


def final_offsets(
    offset: Float[Array, " n"], T_place, T_over, strategy: str
) -> tuple[Float[Array, "4 3"], Float[Array, "4 3"]]:
    """The change of the end-of-cycle (C, C1, C2, C3) positions (m, in `W`) and tangent
    rotations (rad) when the tangent moves by `offset`, to first order."""
    zero = jnp.zeros_like(offset)
    _, dp = jax.jvp(_final_positions(T_place, T_over, strategy), (zero,), (offset,))
    dr = jnp.einsum("cin,n->ci", jnp.asarray(_final_selection(strategy), offset.dtype), offset)
    return dp, dr


def with_offset(
    covariance: CycleCovariance,
    offset: Float[Array, " n"],
    position_offset: Float[Array, "4 3"],
    rotation_offset: Float[Array, "4 3"],
) -> CycleCovariance:
    """`covariance` plus the outer products of an estimate's known offsets from the
    estimator whose covariance is given (tangent `(n,)`; end-of-cycle positions and
    rotations `(4, 3)`): the estimate's second moment about the truth."""

    def outer(d):
        return d[..., :, None] * d[..., None, :]

    return CycleCovariance(
        tangent=covariance.tangent + outer(offset),
        position=covariance.position + outer(position_offset),
        rotation=covariance.rotation + outer(rotation_offset),
        ok=covariance.ok,
    )


def covariance_at(T_place, T_over, data: CycleData, rig: Rig, strategy: str) -> CycleCovariance:
    """$(J^\\top J)^{-1}$ of the whitened measurements `data` at the given poses."""
    H = normal_equations(T_place, T_over, data, rig, strategy).H
    return covariance_from_information(H, T_place, T_over, strategy)


def estimate_placements(poses: CyclePoses, strategy: str):
    """`(T_place (placements, 7), T_over (7,))`: each placement's pose where it first
    occurs, and the overhead camera's, with the gauge (placement 0) set to the identity."""
    ks, rs = first_sighting(strategy)
    T_place = poses.T_world_body.wxyz_xyz[ks, rs]
    T_place = T_place.at[0].set(jnp.zeros(7, T_place.dtype).at[0].set(1.0))
    return T_place, poses.T_world_overhead.wxyz_xyz


def crlb_inputs(
    rig: Rig, truth: CyclePoses, odometry_sigma_rel, strategy: str, present=(None, None)
):
    """`(T_place, T_over, data)` of [`jaxloc.cycle_crlb`][]: exact measurements, the
    sightings the cameras make at the truth (and, if given, marked in `present`, the
    masks `(mutual (steps, 3, 3), overhead (steps, 3))`), the rig's sigmas."""
    T_place, T_over = estimate_placements(truth, strategy)
    dtype = T_place.dtype
    mutual, overhead, lengths = predict(T_place, T_over, rig, strategy)
    m_vis, o_vis = visible(T_place, T_over, rig, strategy)
    m_present, o_present = present
    if m_present is not None:
        m_vis = m_vis & m_present
    if o_present is not None:
        o_vis = o_vis & o_present
    w_px = pixel_weights(rig, dtype)
    rel = jnp.asarray(odometry_sigma_rel, dtype)
    data = CycleData(
        mutual_pixels=mutual,
        mutual_weight=jnp.where(m_vis, w_px[None, 1:, None], 0.0),
        overhead_pixels=overhead,
        overhead_weight=jnp.where(o_vis, w_px[0], 0.0),
        odometry=lengths,
        odometry_weight=odometry_weight(lengths, rel * lengths),
    )
    return T_place, T_over, data


@jit(inline=True)
def cycle_covariance(
    observations: CycleObservations, rig: Rig, estimate: CycleEstimate
) -> CycleCovariance:
    r"""First-order covariance of a cycle's estimate, $(J^\top \Sigma^{-1} J)^{-1}$ at it.

    **Arguments:**

    - `observations`: the [`jaxloc.CycleObservations`][] the estimate came from (which
        sightings were made, odometry sigmas).
    - `rig`: the team's [`jaxloc.Rig`][] (cameras, mounts, markers, pixel noise).
    - `estimate`: a [`jaxloc.CycleEstimate`][], normally [`jaxloc.refine_cycle`][]'s (the
        formula is the ML estimator's covariance; at a closed-form estimate it is only
        the linearization there). A stationary robot's pose is read at its first step.

    **Returns:** a [`jaxloc.CycleCovariance`][]. Pure; `jit`/`vmap` apply. (Every
    estimate also carries the covariance its observability gate computed, as
    `estimate.covariance`.)
    """
    strategy = observations.strategy
    T_place, T_over = estimate_placements(estimate.poses, strategy)
    return covariance_at(T_place, T_over, cycle_data(observations, rig), rig, strategy)


def cycle_crlb(
    rig: Rig,
    truth: CyclePoses,
    *,
    odometry_sigma_rel: float | Array,
    strategy: str | None = None,
    mutual_visible: Bool[ArrayLike, "steps 3 3"] | None = None,
    overhead_visible: Bool[ArrayLike, "steps 3"] | None = None,
) -> CycleCovariance:
    r"""Cramér–Rao lower bound of a cycle: $(J^\top \Sigma^{-1} J)^{-1}$ at the true poses.

    Residual model, parametrization and gauge of [`jaxloc.refine_cycle`][]. Measurements
    included: every mutual sighting and overhead sighting inside the camera's view
    (`in_view` at the truth, as the simulator decides), with the rig's per-axis pixel
    sigma ([`jaxloc.Rig.sigma_per_axis`][]; a zero sigma is weighed as 1e-6 px), and every
    odometry distance with sigma `odometry_sigma_rel` times the true distance. For the
    paper's noise model (not Gaussian) this is the bound for Gaussian noise of the same
    covariance, which is also the first-order covariance of the least-squares estimator
    under either model.

    **Arguments:**

    - `rig`: the team's [`jaxloc.Rig`][] (a scenario's is `scenario.rig`).
    - `truth`: the true poses in `W`, a [`jaxloc.CyclePoses`][] (a simulated cycle's
        `truth.poses`).
    - `odometry_sigma_rel`: relative standard deviation of each move's measured distance
        (keyword only; a scenario's `odometry_sigma_rel`).
    - `strategy`: `"sequential"` or `"concurrent"`; default: from the number of steps.
    - `mutual_visible`, `overhead_visible`: optional masks `(steps, 3, 3)` and
        `(steps, 3)` of the sightings actually made (e.g. a cycle's
        `observations.mutual_visible`): the bound of the measurements present, missing
        sightings weighed 0. Default: every sighting in view.

    **Returns:** a [`jaxloc.CycleCovariance`][]; see [`jaxloc.crlb_rmse`][] for predicted
    RMSEs. Pure and differentiable in the rig and the poses (formation design).
    """
    strategy = strategy_of(truth) if strategy is None else strategy
    present = tuple(
        None if m is None else jnp.asarray(m, bool) for m in (mutual_visible, overhead_visible)
    )
    return _crlb(rig, truth, jnp.asarray(odometry_sigma_rel), strategy, present)


@jit(inline=True)
def _crlb(rig: Rig, truth: CyclePoses, odometry_sigma_rel, strategy: str, present):
    # Compiled once per shape and strategy for eager callers; inlined into a caller's trace.
    inputs = crlb_inputs(rig, truth, odometry_sigma_rel, strategy, present)
    return covariance_at(*inputs, rig, strategy)


def crlb_rmse(covariance: CycleCovariance) -> tuple[Float[Array, "4"], Float[Array, "4"]]:
    """Predicted RMSEs from a [`jaxloc.CycleCovariance`][].

    **Returns:** `(position, rotation)`, each shape `(4,)` for (C, C1, C2, C3):
    `sqrt(trace)` of the 3x3 position block (m) and of the rotation block (rad).
    """

    def root_trace(P):
        t = jnp.trace(P, axis1=-2, axis2=-1)
        ok = t > 0
        return jnp.where(ok, jnp.sqrt(jnp.where(ok, t, 1.0)), 0.0)

    return root_trace(covariance.position), root_trace(covariance.rotation)
