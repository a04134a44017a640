r"""First-order covariance and Cramér–Rao lower bound of a localization cycle (DESIGN §5, §9).

Both use the measurement model and the parametrization of [`jaxloc.refine_cycle`][]:
every distinct robot placement's body pose and the overhead camera's optical-frame pose,
each `T exp(delta)` with `delta = (v, omega)` (jaxlie right perturbation), gauge fixed by
C1's start pose (the world frame `W`, exactly known). With `J` the Jacobian of the
sigma-whitened residuals (mutual pixels, overhead pixels, odometry),
the Fisher information is $F = J^\top \Sigma^{-1} J$ and the bound is $F^{-1}$:

- [`jaxloc.cycle_covariance`][]: $F^{-1}$ at an estimate (e.g. the refined one), with
  the measurements that were actually made: the estimate's first-order covariance.
- [`jaxloc.cycle_crlb`][]: $F^{-1}$ at the true poses, with the sightings the cameras
  make there (`in_view`): the Cramér–Rao bound of any unbiased estimator under Gaussian
  pixel noise of the scenario's per-axis sigma.

Per camera (C, C1, C2, C3 at the end of the cycle) the position block (m^2, in `W`, the
camera centre for C; propagated from the tangent with `jax.jacfwd`, since jaxlie's
tangent translation is not the world position) and the rotation block (rad^2, the
tangent rotation; its trace is that of the geodesic rotation error's second moment) are
reported separately, never summed.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._core.least_squares import _cholesky
from .._cycle.observations import CycleObservations, CyclePoses
from .._sim.scenario import Scenario
from .._solvers.strategies import CycleEstimate
from .cycle import _estimate_placements
from .model import (
    _first_occurrence,
    _odometry_weight,
    _predict,
    _SIGMA_FLOOR_PX,
    _unpack,
    _visible_masks,
    cycle_data,
    cycle_jacobian,
    CycleData,
    pixel_sigma_per_axis,
    placement_ids,
)


class CycleCovariance(eqx.Module):
    """Covariance (or Cramér–Rao bound) of one cycle's estimates.

    **Fields:**

    - `tangent`: covariance of the stacked tangent parameters, shape `(n, n)` with
        `n = 6 (placements - 1) + 6`: placements 1, 2, ... (see
        [`jaxloc.placement_ids`][]; placement 0, C1's start pose, is the gauge) then the
        overhead camera, each `(v, omega)` of `T exp(delta)`.
    - `position`: world-frame position covariance (m^2) of (C, C1, C2, C3) at the end of
        the cycle, shape `(4, 3, 3)`; for C the camera centre. C1's is zero when C1 never
        moved (concurrent strategy: its pose is the world frame).
    - `rotation`: covariance of the rotation tangent `omega` (rad^2) of the same four
        poses, shape `(4, 3, 3)` (C: its optical frame; the body frame's is the same
        up to a fixed rotation, same trace).
    - `ok`: whether the information matrix was positive definite (all entries are 0
        otherwise).
    """

    tangent: Float[Array, "n n"]
    position: Float[Array, "4 3 3"]
    rotation: Float[Array, "4 3 3"]
    ok: Bool[Array, ""]


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


def _lower_inverse(L: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """`L^-1` of a lower-triangular `L` by forward substitution (no LAPACK)."""
    n = L.shape[0]
    eye = jnp.eye(n, dtype=L.dtype)

    def body(i, Y):
        return Y.at[i].set((eye[i] - L[i] @ Y) / L[i, i])  # rows >= i of Y are still zero

    return jax.lax.fori_loop(0, n, body, jnp.zeros_like(L))


def _spd_inverse(F: Float[Array, "n n"]):
    """Inverse of an SPD matrix via a Jacobi-scaled Cholesky; `(inverse, ok)`, 0 if not PD."""
    dg = jnp.diag(F)
    good = dg > 0
    d = jnp.where(good, 1.0 / jnp.sqrt(jnp.where(good, dg, 1.0)), 0.0)
    Fn = F * d[:, None] * d[None, :]
    Fn = jnp.where(jnp.all(good), Fn, jnp.eye(F.shape[0], dtype=F.dtype))
    L = _cholesky(Fn)
    ok = jnp.all(good) & jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diag(L) > 0)
    L = jnp.where(ok, L, jnp.eye(F.shape[0], dtype=F.dtype))
    Y = _lower_inverse(L)
    inv = Y.T @ Y  # F_n^-1 = L^-T L^-1
    inv = d[:, None] * inv * d[None, :]
    inv = 0.5 * (inv + inv.T)
    ok = ok & jnp.all(jnp.isfinite(inv))
    return jnp.where(ok, inv, 0.0), ok


def _covariance_at(T_place, T_over, data: CycleData, scenario: Scenario, strategy: str):
    J = cycle_jacobian(T_place, T_over, data, scenario, strategy)
    cov, ok = _spd_inverse(J.T @ J)
    ids = placement_ids(strategy)

    def positions(theta):
        P, O = _unpack(theta, T_place, T_over)
        return jnp.concatenate([O[None, 4:], P[ids[-1], 4:]])

    G = jax.jacfwd(positions)(jnp.zeros(cov.shape[0], cov.dtype))  # (4, 3, n)
    S = jnp.asarray(_final_selection(strategy), cov.dtype)
    return CycleCovariance(
        tangent=cov,
        position=jnp.einsum("cin,nm,cjm->cij", G, cov, G),
        rotation=jnp.einsum("cin,nm,cjm->cij", S, cov, S),
        ok=ok,
    )


def _covariance_inputs(observations: CycleObservations, scenario: Scenario, estimate):
    """`(T_place, T_over, data)` of [`jaxloc.cycle_covariance`][]."""
    strategy = observations.strategy
    data = cycle_data(observations, scenario)
    T_place, T_over = _estimate_placements(estimate, strategy)
    T_place = T_place.at[0].set(jnp.zeros(7, T_place.dtype).at[0].set(1.0))
    return T_place, T_over, data


def _crlb_inputs(scenario: Scenario, truth, strategy: str):
    """`(T_place, T_over, data)` of [`jaxloc.cycle_crlb`][]: exact measurements, the
    sightings the cameras make at the truth, the scenario's sigmas."""
    poses = truth if isinstance(truth, CyclePoses) else truth.poses
    ks, rs = _first_occurrence(strategy)
    T_place = poses.T_world_body.wxyz_xyz[ks, rs]
    T_over = poses.T_world_overhead.wxyz_xyz
    dtype = T_place.dtype
    mutual, overhead, lengths = _predict(T_place, T_over, scenario, strategy)
    m_vis, o_vis = _visible_masks(T_place, T_over, scenario, strategy)
    s_px = jnp.maximum(pixel_sigma_per_axis(scenario).astype(dtype), _SIGMA_FLOOR_PX)
    rel = scenario.odometry_sigma_rel.astype(dtype)
    data = CycleData(
        mutual_pixels=mutual,
        mutual_weight=jnp.where(m_vis, 1.0 / s_px, 0.0),
        overhead_pixels=overhead,
        overhead_weight=jnp.where(o_vis, 1.0 / s_px, 0.0),
        odometry=lengths,
        odometry_weight=_odometry_weight(lengths, rel * lengths),
    )
    return T_place, T_over, data


def cycle_covariance(
    observations: CycleObservations, scenario: Scenario, estimate: CycleEstimate
) -> CycleCovariance:
    r"""First-order covariance of a cycle's estimate, $(J^\top \Sigma^{-1} J)^{-1}$ at it.

    **Arguments:**

    - `observations`: the [`jaxloc.CycleObservations`][] the estimate came from (which
        pixels were measured, odometry sigmas).
    - `scenario`: the [`jaxloc.Scenario`][] (cameras, `pixel_sigma`, `noise_model`).
    - `estimate`: a [`jaxloc.CycleEstimate`][], normally [`jaxloc.refine_cycle`][]'s (the
        formula is the ML estimator's covariance; at a closed-form estimate it is only
        the linearization there). A stationary robot's pose is read at its first step.

    **Returns:** a [`jaxloc.CycleCovariance`][]. Pure; `jit`/`vmap` apply.
    """
    inputs = _covariance_inputs(observations, scenario, estimate)
    return _covariance_at(*inputs, scenario, observations.strategy)


def cycle_crlb(scenario: Scenario, truth, strategy: str | None = None) -> CycleCovariance:
    r"""Cramér–Rao lower bound of a cycle: $(J^\top \Sigma^{-1} J)^{-1}$ at the true poses.

    Residual model, parametrization and gauge of [`jaxloc.refine_cycle`][]. Measurements
    included: every mutual sighting and overhead sighting inside the camera's view
    (`in_view` at the truth, as the simulator decides), with per-axis pixel sigma
    [`jaxloc.pixel_sigma_per_axis`][]`(scenario)` (a zero sigma is floored at 1e-6 px),
    and every odometry distance with sigma `odometry_sigma_rel` times the true distance.
    For the paper's noise model (not Gaussian) this is the bound for Gaussian noise of the
    same covariance, which is also the first-order covariance of the least-squares
    estimator under either model.

    **Arguments:**

    - `scenario`: a [`jaxloc.Scenario`][].
    - `truth`: a [`jaxloc.CycleTruth`][] or [`jaxloc.CyclePoses`][] (true poses in `W`).
    - `strategy`: `"sequential"` or `"concurrent"`; default `scenario.strategy`.

    **Returns:** a [`jaxloc.CycleCovariance`][]; see [`jaxloc.crlb_rmse`][] for predicted
    RMSEs. Pure and differentiable in the scenario and the poses (formation design).
    """
    strategy = scenario.strategy if strategy is None else strategy
    return _covariance_at(*_crlb_inputs(scenario, truth, strategy), scenario, strategy)


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

