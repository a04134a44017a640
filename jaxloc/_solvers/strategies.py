r"""The two moving strategies of the paper (Sec. III.B-C): a cycle's observations to poses.

Both strategies turn a [`jaxloc.CycleObservations`][] into a [`jaxloc.CycleEstimate`][]:
the poses of C1, C2, C3 at every step of the cycle and of the overhead camera, in the
cycle's world frame `W` (C1's body frame at the start), at metric scale.

- **Sequential** (4 steps): C2 moves, then C3, then C1. Each new formation is solved
  with respect to the robot that has moved the earliest (C3, then C1, then C2), and joined
  to the previous one through the two robots that did not move: their distance fixes the
  new formation's scale relative to the chain, and the reference robot's pose places it.
  One global scale remains, fitted to the three odometry distances in closed form
  (weighted least squares). Six distinct points for the overhead camera.
- **Concurrent** (3 steps): C1 stays, C2 and C3 move together twice. Every formation is
  solved in C1's frame, with its own scale. The three scales are fitted to the four
  odometry distances and the overhead camera's bearings: candidate scale ratios come
  from the odometry (for each move, the two robots' distances give a quadratic with up
  to two positive roots) and from the overhead camera (the ratios its seven bearings
  imply, from each P3P pose of the first formation); the candidate that fits the
  odometry and the bearings best together wins (a single local fit falls into wrong
  minima on the paper's own geometry). Seven distinct points for the overhead camera.
  The runner-up scale candidate and the overhead solver's runner-up pose are kept in
  the estimate's `stats` as starts for a multi-start refinement.
"""

import itertools as it

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from .._core.least_squares import _cholesky, _cholesky_solve
from .._core.numerics import adjugate3, safe_norm, safe_normalize
from .._core.results import raise_if_failed, RESULTS
from .._cycle.observations import (
    CycleObservations,
    CyclePoses,
    move_start_step,
    moving_robot,
)
from .mutual import _others, mutual_localization
from .overhead import solve_overhead_pose
from .p3p import p3p


class CycleEstimate(eqx.Module):
    """Estimated poses of one localization cycle.

    **Fields:**

    - `poses`: a [`jaxloc.CyclePoses`][]: every ground robot's body pose at every step,
      and the overhead camera's optical-frame pose, in the world frame `W` (C1's body frame
      at the start of the cycle), metres.
    - `scales`: metric scale applied to each step's formation (circumdiameter-1 units to
      metres), shape `(steps,)`; all equal for the sequential strategy.
    - `result`: a [`jaxloc.RESULTS`][] for the whole cycle.
    - `stats`: diagnostics: `"min_angle"` (rad, smallest triangle angle over the steps),
      `"odometry_rms"` (m, odometry residual after the scale fit), and the overhead
      solver's `"planarity"`, `"collinearity"`, `"num_valid_candidates"`,
      `"rms_angular_error"`. The concurrent strategy's `"robust"` estimate also carries
      the closed form's two other local minima, starts for [`jaxloc.refine_cycle`][]'s
      multi-start: `"alternative_scales"` `(2, steps)` (the runner-up scale candidate,
      and the winning scales again), `"alternative_T_world_overhead"` `(2, 7)` (the
      overhead pose for the runner-up scales, and the overhead solver's runner-up pose
      for the winning scales) and `"alternative_ok"` `(2,)`.
    """

    poses: CyclePoses
    scales: Float[Array, " steps"]
    result: RESULTS
    stats: dict[str, Array]


# For every (step, robot): index of the distinct physical point it occupies.
_POINT_ID = {
    "sequential": np.array([[0, 1, 2], [0, 3, 2], [0, 3, 4], [5, 3, 4]]),
    "concurrent": np.array([[0, 1, 2], [0, 3, 4], [0, 5, 6]]),
}
# Reference robot of each step's mutual localization.
_REFERENCE = {"sequential": (0, 2, 0, 1), "concurrent": (0, 0, 0)}


def overhead_point_ids(strategy: str) -> np.ndarray:
    """Distinct point index of each (step, robot) sighting, shape `(steps, 3)`."""
    return _POINT_ID[strategy]


def _compose(T_w_ref: jaxlie.SE3, scale, T_ref_body: jaxlie.SE3) -> jaxlie.SE3:
    """`T_w_ref @ T_ref_body`, with `T_ref_body`'s translations multiplied by `scale`."""

    def one(wxyz_xyz):
        T = jaxlie.SE3(wxyz_xyz)
        T = jaxlie.SE3.from_rotation_and_translation(T.rotation(), scale * T.translation())
        return (T_w_ref @ T).wxyz_xyz

    return jaxlie.SE3(jax.vmap(one)(T_ref_body.wxyz_xyz))


def _scale_translations(T: jaxlie.SE3, scale) -> jaxlie.SE3:
    return jaxlie.SE3(T.wxyz_xyz.at[..., 4:].multiply(scale))


def _pick(T: jaxlie.SE3, i: int) -> jaxlie.SE3:
    return jaxlie.SE3(T.wxyz_xyz[i])


def _distance(a: Float[Array, "3"], b: Float[Array, "3"]) -> Array:
    return safe_norm(a - b)


def _odometry_weights(obs: CycleObservations) -> Float[Array, " moves"]:
    """Inverse-variance weights, falling back to equal weights for zero sigmas."""
    sigma = obs.odometry_sigma
    floor = 1e-9 + 1e-6 * jnp.max(jnp.abs(obs.odometry))
    return 1.0 / jnp.maximum(sigma, floor) ** 2


def _mutual_steps(bearings: Float[Array, "steps 3 3 3"], refs: tuple[int, ...]):
    """[`jaxloc.mutual_localization`][] of every step, as one `vmap` (traced and compiled
    once, not once per step). Each step's robots are reordered so that its reference
    robot comes first, then put back: the poses are the same numbers in any order (each
    angle, side and rotation involves the same robots). Returns one
    [`jaxloc.MutualSolution`][] per step."""
    perms = np.array([(r, *_others(r)) for r in refs])
    steps = np.arange(len(refs))
    permuted = bearings[steps[:, None, None], perms[:, :, None], perms[:, None, :]]
    sols = jax.vmap(lambda b: mutual_localization(b, 0, throw=False))(permuted)
    T = sols.T_ref_body.wxyz_xyz[steps[:, None], np.argsort(perms, axis=1)]
    sols = eqx.tree_at(lambda sol: sol.T_ref_body, sols, jaxlie.SE3(T))
    return [jax.tree.map(lambda x: x[k], sols) for k in steps]


def _chain_sequential(obs: CycleObservations):
    """Poses of every step in step-0 units (circumdiameter of the first formation = 1)."""
    refs = _REFERENCE["sequential"]
    movers = moving_robot("sequential")
    sols = _mutual_steps(obs.mutual, refs)
    T = [sols[0].T_ref_body]
    for k in range(1, 4):
        ref, mover = refs[k], int(movers[k - 1])
        shared = 3 - ref - mover
        prev = T[k - 1]
        chain_dist = _distance(prev.translation()[ref], prev.translation()[shared])
        local_dist = _distance(
            sols[k].T_ref_body.translation()[ref], sols[k].T_ref_body.translation()[shared]
        )
        ratio = chain_dist / jnp.where(local_dist > 0, local_dist, 1.0)
        T.append(_compose(_pick(prev, ref), ratio, sols[k].T_ref_body))
    return T, sols


def _move_lengths(T: list[jaxlie.SE3], strategy: str) -> Float[Array, " moves"]:
    starts, movers = move_start_step(strategy), moving_robot(strategy)
    return jnp.stack(
        [
            _distance(T[int(a) + 1].translation()[int(r)], T[int(a)].translation()[int(r)])
            for a, r in zip(starts, movers)
        ]
    )


def _fit_sequential_scale(obs: CycleObservations, T: list[jaxlie.SE3]):
    lengths = _move_lengths(T, "sequential")
    w = _odometry_weights(obs)
    denom = jnp.sum(w * lengths**2)
    ok = denom > 1e-12 * jnp.sum(w * obs.odometry**2)
    scale = jnp.sum(w * obs.odometry * lengths) / jnp.where(ok, denom, 1.0)
    ok = ok & (scale > 0)
    scale = jnp.where(ok, scale, 1.0)
    rms = jnp.sqrt(jnp.mean((scale * lengths - obs.odometry) ** 2))
    return scale, ok, rms


def _ratio_candidates(p_before: Float[Array, "2 3"], p_after: Float[Array, "2 3"], d, w):
    r"""Candidate values of `s_after / s_before` from two robots' move distances.

    Robot j moved from `s_b p_j` to `s_a q_j` over distance `d_j`:
    `s_b^2 |p|^2 - 2 s_b s_a p.q + s_a^2 |q|^2 = d^2`. Dividing the two robots' equations
    by `d_j^2` and subtracting eliminates `s_b`, leaving a quadratic in `r = s_a / s_b`.
    Returns the two roots (NaN-free; invalid ones flagged) and the guess `r = 1`.
    """
    d2 = jnp.maximum(d**2, 1e-30)
    A = jnp.sum(p_before * p_before, axis=-1) / d2
    B = jnp.sum(p_before * p_after, axis=-1) / d2
    C = jnp.sum(p_after * p_after, axis=-1) / d2
    a, b, c = C[0] - C[1], -2.0 * (B[0] - B[1]), A[0] - A[1]
    disc = jnp.maximum(b * b - 4.0 * a * c, 0.0)
    sq = jnp.sqrt(disc)
    q = -0.5 * (b + jnp.where(b >= 0, sq, -sq))
    safe_a = jnp.where(jnp.abs(a) > 1e-300, a, 1.0)
    safe_q = jnp.where(jnp.abs(q) > 1e-300, q, 1.0)
    r1 = jnp.where(jnp.abs(a) > 1e-300, q / safe_a, -1.0)
    r2 = jnp.where(jnp.abs(q) > 1e-300, c / safe_q, -1.0)
    roots = jnp.stack([r1, r2, jnp.ones_like(r1)])
    valid = (roots > 0.05) & (roots < 20.0)
    return jnp.where(valid, roots, 1.0), valid


def _concurrent_cost_and_jac(s, P, d, w):
    """Weighted odometry residuals of the concurrent strategy and their Jacobian."""
    starts, movers = move_start_step("concurrent"), moving_robot("concurrent")

    def residuals(s):
        return jnp.stack(
            [
                jnp.sqrt(w[m]) * (_distance(s[a + 1] * P[a + 1, r], s[a] * P[a, r]) - d[m])
                for m, (a, r) in enumerate(zip(starts.tolist(), movers.tolist()))
            ]
        )

    return residuals(s), jax.jacfwd(residuals)(s)


def _solve3(A: Float[Array, "3 3"], b: Float[Array, "3"]) -> Float[Array, "3"]:
    """Solve a 3x3 system by the adjugate (no LAPACK call; A is a small SPD matrix)."""
    adj, det = adjugate3(A)
    safe = jnp.where(jnp.abs(det) > 1e-300, det, 1.0)
    return jnp.where(jnp.abs(det) > 1e-300, adj @ b / safe, 0.0)


def _overhead_candidates(obs: CycleObservations, P: Float[Array, "3 3 3"]):
    """The overhead camera's view of the concurrent cycle at unit first-formation scale.

    The first formation's three points (C1 at the origin, C2 and C3 at `P[0]`) fix the
    overhead camera up to that formation's scale by P3P, up to four solutions. Returns
    `(poses, valid, unit, bearings, seen)`: the P3P poses `T_cam_world` (`(4, 7)`), their
    validity, the seven distinct points at unit scales (`(7, 3)`), their mean overhead
    bearings and whether each was seen."""
    unit = jnp.stack([P[0, 0], P[0, 1], P[0, 2], P[1, 1], P[1, 2], P[2, 1], P[2, 2]])
    _, bearings, seen = _overhead_problem(obs, P)
    sol = p3p(unit[:3], bearings[:3])
    return sol.poses.wxyz_xyz, sol.valid & jnp.all(seen[:3]), unit, bearings, seen


# Nominal standard deviation (rad) of an overhead bearing, to weigh it against the
# odometry when choosing the concurrent strategy's scales (2 px at a 650 px focal length
# is 3 mrad; the paper's predicted points are worse).
_NOMINAL_BEARING_SIGMA = 3e-3
# Formation (step) of each of the concurrent strategy's seven distinct points.
_CONCURRENT_STEP_OF = np.array([0, 0, 0, 1, 1, 2, 2])
# Two concurrent scale candidates are distinct minima when some formation's scale
# differs by more than this (log ratio, ~10%); noise moves a scale by a few percent.
_DISTINCT_LOG_SCALE = 0.1


def _overhead_ratios(view) -> tuple[Float[Array, "4 7"], Float[Array, "4 3"]]:
    r"""The overhead camera's pose and the scale ratios `(1, s1/s0, s2/s0)` it sees, from
    each P3P pose of the first formation.

    Unknowns: the camera pose `T_cam_world` and the log-ratios of the later formations,
    whose points are `rho_k P_j`; started at the P3P pose and the ratios that put each
    formation's points closest to their bearings from it (linear least squares), then a
    few Gauss-Newton steps on the chordal bearing errors of all seven points. The overhead
    camera measures these ratios far better than the odometry's quadratics (differences
    of two noisy distance equations) on unfavourable moves. Returns `(poses, ratios)`,
    `(4, 7)` and `(4, 3)`; a failed start keeps ratios 1."""
    poses, valid, unit, bearings, seen = view
    dtype = unit.dtype

    def residuals(theta, T0):
        T = jaxlie.manifold.rplus(jaxlie.SE3(T0), theta[:6])
        rho = jnp.concatenate([jnp.ones(1, dtype), jnp.exp(theta[6:])])
        q = jax.vmap(T.apply)(unit * rho[_CONCURRENT_STEP_OF][:, None])
        return jnp.where(seen[:, None], safe_normalize(q) - bearings, 0.0).reshape(-1)

    def linear_ratios(T0):
        # With the camera fixed, formation k's moved points rho_k P_j lie on their
        # bearings: b_j x (rho_k R P_j + t) = 0, linear least squares in rho_k.
        T = jaxlie.SE3(T0)
        a = jnp.cross(bearings, jax.vmap(T.rotation().apply)(unit))
        c = jnp.cross(bearings, jnp.broadcast_to(T.translation(), unit.shape))
        num = jnp.where(seen, -jnp.sum(a * c, axis=-1), 0.0)
        den = jnp.where(seen, jnp.sum(a * a, axis=-1), 0.0)
        return jnp.stack([
            jnp.sum(num[_CONCURRENT_STEP_OF == k])
            / jnp.maximum(jnp.sum(den[_CONCURRENT_STEP_OF == k]), 1e-30)
            for k in (1, 2)
        ])

    def one(T0):
        def step(theta):
            r, J = residuals(theta, T0), jax.jacfwd(residuals)(theta, T0)
            # Element-wise products, no `dot`: tiny matrices under `vmap` (DESIGN §8).
            H = jnp.sum(J[:, :, None] * J[:, None, :], axis=0) + 1e-9 * jnp.eye(8, dtype=dtype)
            return theta - _cholesky_solve(_cholesky(H), jnp.sum(J * r[:, None], axis=0))

        rho0 = linear_ratios(T0)
        theta = jnp.concatenate([jnp.zeros(6, dtype), jnp.log(jnp.clip(rho0, 0.05, 20.0))])
        theta = jax.lax.fori_loop(0, 2, lambda _, theta: step(theta), theta)
        T = jaxlie.manifold.rplus(jaxlie.SE3(T0), theta[:6]).wxyz_xyz.astype(dtype)
        return T, jnp.concatenate([jnp.ones(1, dtype), jnp.exp(theta[6:])])

    T, rho = jax.vmap(one)(poses)
    ok = valid[:, None] & jnp.all(jnp.isfinite(T), axis=1, keepdims=True)
    ok = ok & jnp.isfinite(rho) & (rho > 0.05) & (rho < 20.0)
    return jnp.where(ok[:, :1], T, poses), jnp.where(ok, rho, 1.0)


def _overhead_misfit(view, rho):
    """Overhead-camera misfit of each candidate scale set, `(candidates,)`.

    The later formations' four points, placed with the candidate's scale ratios `rho`
    (`(candidates, 3)`, `rho[:, 0] = 1`), must project onto their bearings, seen from
    one of the camera poses in `view` (those of `_overhead_ratios`). Sum of squared
    chordal bearing errors (~ rad^2), best over the poses."""
    poses, valid, unit, bearings, seen = view

    def misfit(rho):
        X = unit * rho[_CONCURRENT_STEP_OF][:, None]

        def one(wxyz_xyz, valid):
            T = jaxlie.SE3(wxyz_xyz)
            q = jax.vmap(T.apply)(X)
            chord = jnp.sum((safe_normalize(q) - bearings) ** 2, axis=-1)
            front = jnp.all((jnp.sum(q * bearings, axis=-1) > 0) | ~seen)
            cost = jnp.sum(jnp.where(seen, chord, 0.0))
            return jnp.where(valid & front & jnp.isfinite(cost), cost, jnp.inf)

        return jnp.min(jax.vmap(one)(poses, valid))

    return jnp.where(jnp.any(valid), jax.vmap(misfit)(rho), 0.0)


def _fit_concurrent_scales(obs: CycleObservations, P: Float[Array, "3 3 3"]):
    """Scales `(s0, s1, s2)` of the three formations from the four odometry distances.

    Four distances fix three scales with one degree of freedom to spare, and the
    quadratic ratio equations often leave two branches that both fit the odometry
    within its noise (~4% of the paper's cycles); on unfavourable moves neither root is
    near the truth, and the odometry alone hardly constrains the ratios. Candidates: every
    combination of the quadratics' roots, and the ratios each P3P pose of the overhead
    camera implies; each starts a few Gauss-Newton steps on the odometry, and is also kept
    as is with only its overall scale fitted. The candidate that best fits the odometry
    and the overhead bearings together wins; the others' poses would be a wrong local
    minimum for any refinement. Returns `(scales, ok, odometry_rms, runner_up,
    runner_up_ok)`: `runner_up` is the best-scoring candidate whose scales differ from
    the winner's by more than `_DISTINCT_LOG_SCALE`, another start for a refinement."""
    d, w_abs = obs.odometry, _odometry_weights(obs)
    w = w_abs / jnp.max(w_abs)
    # moves: [C2 0->1, C3 0->1, C2 1->2, C3 1->2]
    r01, ok01 = _ratio_candidates(P[0, 1:], P[1, 1:], d[:2], w[:2])
    r12, ok12 = _ratio_candidates(P[1, 1:], P[2, 1:], d[2:], w[2:])
    combos = np.array(list(it.product(range(3), range(3))))
    view = _overhead_candidates(obs, P)
    poses_overhead, rho_overhead = _overhead_ratios(view)
    view = (poses_overhead, *view[1:])  # score every candidate from the refined poses
    rho = jnp.concatenate([
        jnp.stack(
            [jnp.ones(len(combos)), r01[combos[:, 0]], r01[combos[:, 0]] * r12[combos[:, 1]]],
            axis=1,
        ),
        rho_overhead,
    ])
    allowed = jnp.concatenate([ok01[combos[:, 0]] & ok12[combos[:, 1]], view[1]])
    starts, movers = move_start_step("concurrent"), moving_robot("concurrent")

    def init_and_refine(rho):
        q = jnp.stack(
            [
                _distance(rho[a + 1] * P[a + 1, r], rho[a] * P[a, r])
                for a, r in zip(starts.tolist(), movers.tolist())
            ]
        )
        s0 = jnp.sum(w * d * q) / jnp.maximum(jnp.sum(w * q * q), 1e-30)
        s = s0 * rho
        res, _ = _concurrent_cost_and_jac(s, P, d, w)
        fixed = (s, jnp.sum(res**2))

        def gauss_newton(_, s):
            res, J = _concurrent_cost_and_jac(s, P, d, w)
            step = _solve3(J.T @ J + 1e-12 * jnp.eye(3, dtype=s.dtype), -J.T @ res)
            s_new = s + step
            return jnp.where(jnp.all(s_new > 0), s_new, s)

        s = jax.lax.fori_loop(0, 6, gauss_newton, s)
        res, _ = _concurrent_cost_and_jac(s, P, d, w)
        return jnp.stack([fixed[0], s]), jnp.stack([fixed[1], jnp.sum(res**2)])

    s_all, cost = jax.vmap(init_and_refine)(rho)
    s_all, cost = s_all.reshape(-1, 3), cost.reshape(-1)
    allowed = jnp.repeat(allowed, 2) & jnp.all(s_all > 0, axis=1)
    cost = jnp.where(allowed & jnp.isfinite(cost), cost, jnp.inf)
    # Both kinds of evidence in one chi-square-like score: the odometry in units of its
    # sigma, the overhead bearings in units of a nominal angular sigma (the closed form
    # does not know the camera's noise; only the order of magnitude matters here).
    misfit = _overhead_misfit(view, s_all / s_all[:, :1])  # ratios to s0
    score = cost * jnp.max(w_abs) + misfit / _NOMINAL_BEARING_SIGMA**2
    score = jnp.where(jnp.any(jnp.isfinite(score)), score, cost)
    best = jnp.argmin(score)
    scales = s_all[best]
    ok = jnp.isfinite(cost[best]) & jnp.all(jnp.isfinite(scales))
    scales = jnp.where(ok, scales, 1.0)
    # The runner-up: the best-scoring candidate whose scales differ from the winner's by
    # more than `_DISTINCT_LOG_SCALE` (another local minimum for a refinement to try).
    gap = jnp.max(jnp.abs(jnp.log(jnp.abs(s_all) / scales[None])), axis=1)
    other_score = jnp.where(gap > _DISTINCT_LOG_SCALE, score, jnp.inf)
    other = jnp.argmin(other_score)
    runner_up_ok = ok & jnp.isfinite(other_score[other]) & jnp.all(jnp.isfinite(s_all[other]))
    runner_up = jnp.where(runner_up_ok, s_all[other], scales)
    lengths = jnp.stack(
        [
            _distance(scales[a + 1] * P[a + 1, r], scales[a] * P[a, r])
            for a, r in zip(starts.tolist(), movers.tolist())
        ]
    )
    rms = jnp.sqrt(jnp.mean((lengths - d) ** 2))
    return scales, ok, rms, runner_up, runner_up_ok


def _overhead_problem(obs: CycleObservations, positions: Float[Array, "steps 3 3"]):
    """Distinct world points and their mean overhead bearing (repeated sightings averaged)."""
    ids = _POINT_ID[obs.strategy]
    n_points = int(ids.max()) + 1
    first = {}
    for k in range(ids.shape[0]):
        for r in range(3):
            first.setdefault(int(ids[k, r]), (k, r))
    points = jnp.stack([positions[first[i]] for i in range(n_points)])
    vis = obs.overhead_visible
    bearings = jnp.where(vis[..., None], obs.overhead, 0.0)
    bearings = jnp.where(jnp.isfinite(bearings), bearings, jnp.nan)
    summed = jnp.stack(
        [sum(bearings[k, r] for k, r in zip(*np.nonzero(ids == i))) for i in range(n_points)]
    )
    seen = jnp.stack(
        [sum(vis[k, r] for k, r in zip(*np.nonzero(ids == i))) for i in range(n_points)]
    )
    mean_bearing = safe_normalize(summed)
    return points, mean_bearing, seen > 0


def localize_cycle(
    observations: CycleObservations,
    *,
    method: str = "robust",
    throw: bool = True,
) -> CycleEstimate:
    r"""All four robots' poses from one cycle's observations, at metric scale.

    The strategy is read from `observations.strategy`. Pure: `jit`, `vmap` and `grad`
    apply (batch observations with `jax.vmap(localize_cycle)`).

    **Arguments:**

    - `observations`: a [`jaxloc.CycleObservations`][] (bearings in body/camera frames
      and odometry), from the simulator, the image front end or a real robot.
    - `method`: the overhead camera's pose solver, `"robust"` (default: every point
      triplet through P3P, best candidate on all points; correct on a flat floor) or
      `"paper"` (the paper's 12-unknown linear system, Eq. 6; rank deficient on planar
      ground). See [`jaxloc.solve_overhead_pose`][].
    - `throw`: raise on failure if `True`; otherwise inspect `result`. Keyword only.

    **Returns:** a [`jaxloc.CycleEstimate`][] in the world frame `W` = C1's body frame at
    the start of the cycle.
    """
    (estimate,) = localize_cycle_methods(observations, (method,))
    return raise_if_failed(estimate, estimate.result, throw)


def localize_cycle_methods(
    observations: CycleObservations, methods: tuple[str, ...]
) -> list[CycleEstimate]:
    """[`jaxloc.localize_cycle`][] for several overhead-pose methods at once.

    The ground robots' chain and the scale fit are computed once and shared; only the
    overhead camera's solve differs. Never raises on traced values (`throw=False`).
    """
    strategy = observations.strategy
    if strategy == "sequential":
        T, sols = _chain_sequential(observations)
        scale, scale_ok, odo_rms = _fit_sequential_scale(observations, T)
        T = [_scale_translations(Tk, scale) for Tk in T]
        scales = jnp.full((4,), scale)
    else:
        sols = _mutual_steps(observations.mutual, _REFERENCE["concurrent"])
        P = jnp.stack([s.T_ref_body.translation() for s in sols])
        scales, scale_ok, odo_rms, runner_up, runner_up_ok = _fit_concurrent_scales(
            observations, P
        )
        T = [_scale_translations(s.T_ref_body, scales[k]) for k, s in enumerate(sols)]

    T_world_body = jaxlie.SE3(jnp.stack([Tk.wxyz_xyz for Tk in T]))
    positions = T_world_body.translation()
    points, bearings, mask = _overhead_problem(observations, positions)

    mutual_result = sols[0].result
    for s in sols[1:]:
        mutual_result = RESULTS.where(s.result == RESULTS.successful, mutual_result, s.result)
    odometry_ok = jnp.all(jnp.isfinite(observations.odometry)) & jnp.all(
        jnp.isfinite(observations.odometry_sigma)
    )
    estimates = []
    for method in methods:
        runner_up_stats = {}
        if strategy == "concurrent" and method == "robust":
            # The runner-up scales' poses too (one batched solve), for a refinement to
            # start from both (`jaxloc.refine_cycle`).
            alt_points, _, _ = _overhead_problem(observations, runner_up[:, None, None] * P)
            both = jax.vmap(
                lambda pts: solve_overhead_pose(
                    pts, bearings, mask, method=method, throw=False, runner_up=True
                )
            )(jnp.stack([points, alt_points]))
            pose_sol = jax.tree.map(lambda x: x[0], both)
            pose_sol.stats.pop("runner_up_pose")
            pose_sol.stats.pop("runner_up_ok")
            mirror = jaxlie.SE3(both.stats["runner_up_pose"][0]).inverse().wxyz_xyz
            runner_up_stats = {
                # The closed form's other local minima, for a refinement to start from
                # (`jaxloc.refine_cycle`): the runner-up scales with their own overhead
                # pose; the winning scales with the overhead solver's runner-up pose.
                "alternative_scales": jnp.stack([runner_up, scales]),
                "alternative_T_world_overhead": jnp.stack(
                    [jaxlie.SE3(both.pose.wxyz_xyz[1]).inverse().wxyz_xyz, mirror]
                ),
                "alternative_ok": jnp.stack([
                    runner_up_ok & (both.result == RESULTS.successful)[1],
                    both.stats["runner_up_ok"][0],
                ]),
            }
        else:
            pose_sol = solve_overhead_pose(points, bearings, mask, method=method, throw=False)
        T_world_overhead = pose_sol.pose.inverse()
        result = pose_sol.result
        result = RESULTS.where(scale_ok, result, RESULTS.scale_unobservable)
        result = RESULTS.where(mutual_result == RESULTS.successful, result, mutual_result)
        result = RESULTS.where(odometry_ok, result, RESULTS.nonfinite_observation)
        stats = dict(pose_sol.stats)
        stats["min_angle"] = jnp.min(jnp.stack([s.stats["min_angle"] for s in sols]))
        stats["odometry_rms"] = odo_rms
        stats.update(runner_up_stats)
        poses = CyclePoses(T_world_body, T_world_overhead)
        estimates.append(CycleEstimate(poses, scales, result, stats))
    return estimates
