"""The concurrent strategy's closed form (paper Sec. III.B): three formations, three scales.

C1 stays; C2 and C3 move together twice (3 steps). Every formation is solved in C1's
frame, with its own scale. The three scales are fitted to the four odometry distances and
the overhead camera's bearings: candidate scale ratios come from the odometry (for each
move, the two robots' distances give a quadratic with up to two positive roots) and from
the overhead camera (the ratios its seven bearings imply, from each P3P pose of the first
formation); the candidate that fits the odometry and the bearings best together wins (a
single local fit falls into wrong minima on the paper's own geometry). The runner-up
scale candidate is kept as a start for a multi-start refinement.
"""

import functools as ft
import itertools as it

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from .._core.least_squares import gauss_newton
from .._core.numerics import safe_norm, safe_normalize
from .._core.poses import apply, rplus
from .._cycle.layout import move_start_step, moving_robot, reference_robots
from .._cycle.observations import CycleObservations
from .._cycle.sightings import matvec
from .mutual import cycle_bearings, mutual_steps
from .overhead_points import overhead_problem
from .p3p import p3p
from .sequential import odometry_weights, scale_translations


def _distance(a: Float[Array, "3"], b: Float[Array, "3"]) -> Array:
    return safe_norm(a - b)


def _gauss_newton(model, x0, *, steps: int, lam: float, retract=None):
    """`steps` Gauss--Newton steps (no convergence test) with a fixed tiny damping `lam`
    that regularizes directions no residual touches (reverse-differentiable)."""
    if retract is None:
        retract = lambda x, delta: x + delta  # noqa: E731
    return gauss_newton(model, retract, x0, steps=steps, lam=lam)


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

def _move_lengths(s: Float[Array, "3"], P: Float[Array, "3 3 3"]) -> Float[Array, "4"]:
    """Length (m) of each of the concurrent strategy's four moves, in move order, with the
    formations `P` (step, robot, xyz; unit scale) scaled by `s` (one scale per step)."""
    starts, movers = move_start_step("concurrent"), moving_robot("concurrent")
    return jnp.stack(
        [
            _distance(s[a + 1] * P[a + 1, r], s[a] * P[a, r])
            for a, r in zip(starts.tolist(), movers.tolist())
        ]
    )


def _concurrent_cost_and_jac(s, P, d, w):
    """Weighted odometry residuals of the concurrent strategy `(4,)` and their Jacobian
    `(4, 3)` with respect to the scales `s`."""

    def residuals(s):
        return jnp.sqrt(w) * (_move_lengths(s, P) - d)

    return residuals(s), jax.jacfwd(residuals)(s)


def _overhead_candidates(obs: CycleObservations, P: Float[Array, "3 3 3"]):
    """The overhead camera's view of the concurrent cycle at unit first-formation scale.

    The first formation's three points (C1 at the origin, C2 and C3 at `P[0]`) fix the
    overhead camera up to that formation's scale by P3P, up to four solutions. Returns
    `(poses, valid, unit, bearings, seen)`: the P3P poses `T_cam_world` (`(4, 7)`), their
    validity, the seven distinct points at unit scales (`(7, 3)`), their mean overhead
    bearings and whether each was seen."""
    unit = jnp.stack([P[0, 0], P[0, 1], P[0, 2], P[1, 1], P[1, 2], P[2, 1], P[2, 2]])
    _, bearings, seen = overhead_problem(obs, P)
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
        T = rplus(jaxlie.SE3(T0), theta[:6])
        rho = jnp.concatenate([jnp.ones(1, dtype), jnp.exp(theta[6:])])
        q = jax.vmap(ft.partial(apply, T))(unit * rho[_CONCURRENT_STEP_OF][:, None])
        return jnp.where(seen[:, None], safe_normalize(q) - bearings, 0.0).reshape(-1)

    def linear_ratios(T0):
        # With the camera fixed, formation k's moved points rho_k P_j lie on their
        # bearings: b_j x (rho_k R P_j + t) = 0, linear least squares in rho_k.
        T = jaxlie.SE3(T0)
        a = jnp.cross(bearings, matvec(T.rotation().as_matrix()[None], unit))
        c = jnp.cross(bearings, jnp.broadcast_to(T.translation(), unit.shape))
        num = jnp.where(seen, -jnp.sum(a * c, axis=-1), 0.0)
        den = jnp.where(seen, jnp.sum(a * a, axis=-1), 0.0)
        return jnp.stack([
            jnp.sum(num[_CONCURRENT_STEP_OF == k])
            / jnp.maximum(jnp.sum(den[_CONCURRENT_STEP_OF == k]), 1e-30)
            for k in (1, 2)
        ])

    def one(T0):
        rho0 = linear_ratios(T0)
        theta = jnp.concatenate([jnp.zeros(6, dtype), jnp.log(jnp.clip(rho0, 0.05, 20.0))])
        theta = _gauss_newton(
            lambda theta: (residuals(theta, T0), jax.jacfwd(residuals)(theta, T0)),
            theta, steps=2, lam=1e-9,
        )
        T = rplus(jaxlie.SE3(T0), theta[:6]).wxyz_xyz
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
            q = jax.vmap(ft.partial(apply, T))(X)
            chord = jnp.sum((safe_normalize(q) - bearings) ** 2, axis=-1)
            front = jnp.all((jnp.sum(q * bearings, axis=-1) > 0) | ~seen)
            cost = jnp.sum(jnp.where(seen, chord, 0.0))
            return jnp.where(valid & front & jnp.isfinite(cost), cost, jnp.inf)

        return jnp.min(jax.vmap(one)(poses, valid))

    return jnp.where(jnp.any(valid), jax.vmap(misfit)(rho), 0.0)

def _scale_ratio_candidates(obs: CycleObservations, P: Float[Array, "3 3 3"], d, w):
    """Candidate scale ratios `(1, s1/s0, s2/s0)` `(13, 3)` and which are allowed `(13,)`:
    the 9 combinations of the odometry quadratics' roots, then the 4 the overhead camera
    sees from each P3P pose; and the overhead `view` with its refined poses."""
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
    return rho, allowed, view


def _fit_candidate(rho: Float[Array, "3"], P, d, w):
    """Two scale sets `(2, 3)` from the ratios `rho` and their odometry costs `(2,)`: the
    overall scale fitted by linear least squares, then 6 Gauss--Newton steps on all three
    scales (a step that makes a scale non-positive is refused)."""
    q = _move_lengths(rho, P)
    s0 = jnp.sum(w * d * q) / jnp.maximum(jnp.sum(w * q * q), 1e-30)
    s = s0 * rho
    res, _ = _concurrent_cost_and_jac(s, P, d, w)
    fixed = (s, jnp.sum(res**2))
    s = _gauss_newton(
        lambda s: _concurrent_cost_and_jac(s, P, d, w), s, steps=6,
        lam=1e-12, retract=lambda s, step: jnp.where(jnp.all(s + step > 0), s + step, s),
    )  # fmt: skip
    res, _ = _concurrent_cost_and_jac(s, P, d, w)
    return jnp.stack([fixed[0], s]), jnp.stack([fixed[1], jnp.sum(res**2)])


def _best_and_runner_up(s_all: Float[Array, "k 3"], score, cost):
    """The lowest-`score` scale set and the best-scoring one whose scales differ from it
    by more than `_DISTINCT_LOG_SCALE` (another local minimum for a refinement to try).
    Returns `(scales, ok, runner_up, runner_up_ok)`; failures fall back to ones / the
    winner."""
    best = jnp.argmin(score)
    scales = s_all[best]
    ok = jnp.isfinite(cost[best]) & jnp.all(jnp.isfinite(scales))
    scales = jnp.where(ok, scales, 1.0)
    gap = jnp.max(jnp.abs(jnp.log(jnp.abs(s_all) / scales[None])), axis=1)
    other_score = jnp.where(gap > _DISTINCT_LOG_SCALE, score, jnp.inf)
    other = jnp.argmin(other_score)
    runner_up_ok = ok & jnp.isfinite(other_score[other]) & jnp.all(jnp.isfinite(s_all[other]))
    runner_up = jnp.where(runner_up_ok, s_all[other], scales)
    return scales, ok, runner_up, runner_up_ok


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
    d, w_abs = obs.odometry, odometry_weights(obs)
    w = w_abs / jnp.max(w_abs)
    rho, allowed, view = _scale_ratio_candidates(obs, P, d, w)
    s_all, cost = jax.vmap(ft.partial(_fit_candidate, P=P, d=d, w=w))(rho)
    s_all, cost = s_all.reshape(-1, 3), cost.reshape(-1)
    allowed = jnp.repeat(allowed, 2) & jnp.all(s_all > 0, axis=1)
    cost = jnp.where(allowed & jnp.isfinite(cost), cost, jnp.inf)
    # Both kinds of evidence in one chi-square-like score: the odometry in units of its
    # sigma, the overhead bearings in units of a nominal angular sigma (the closed form
    # does not know the camera's noise; only the order of magnitude matters here).
    misfit = _overhead_misfit(view, s_all / s_all[:, :1])  # ratios to s0
    score = cost * jnp.max(w_abs) + misfit / _NOMINAL_BEARING_SIGMA**2
    score = jnp.where(jnp.any(jnp.isfinite(score)), score, cost)
    scales, ok, runner_up, runner_up_ok = _best_and_runner_up(s_all, score, cost)
    rms = jnp.sqrt(jnp.mean((_move_lengths(scales, P) - d) ** 2))
    return scales, ok, rms, runner_up, runner_up_ok


def concurrent_formations(observations: CycleObservations, bearings=None):
    """The concurrent closed form: `(T_world_body, scales, scale_ok, odometry_rms,
    runner_up_scales, runner_up_ok, mutual_solutions)`, the first a `jaxlie.SE3` of batch
    `(3, 3)` at metric scale in `W` (C1's frame), `scales` `(3,)` one per formation.
    `bearings`: the mutual bearings as [`cycle_bearings`][] fills them, if the caller has
    them already."""
    if bearings is None:
        bearings = cycle_bearings(observations)[0]
    sols = mutual_steps(bearings, reference_robots("concurrent"))
    P = jnp.stack([s.T_ref_body.translation() for s in sols])
    scales, ok, rms, runner_up, runner_up_ok = _fit_concurrent_scales(observations, P)
    T = jnp.stack([scale_translations(s.T_ref_body, c).wxyz_xyz for s, c in zip(sols, scales)])
    return jaxlie.SE3(T), scales, ok, rms, runner_up, runner_up_ok, sols


def runner_up_positions(runner_up, sols) -> Float[Array, "steps 3 3"]:
    """Every robot's position at every step with the runner-up scales."""
    P = jnp.stack([s.T_ref_body.translation() for s in sols])
    return runner_up[:, None, None] * P
