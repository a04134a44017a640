r"""A fixed-lag smoother over the last W cycles, and its bound (issue 21.3).

**Unknowns**, all in the first cycle's frame `W_0` (jaxlie right perturbations): the window
holds the start formation `F` of its oldest cycle (the body poses of C1, C2, C3), the
climbing robot's overhead camera `C_prev` of the cycle before it, and for each of its W
cycles the placements the cycle adds (sequential: C2, C3, C1 after their moves; concurrent:
C2, C3 after each move) and its overhead camera `C_k`. A cycle's start placements are the
previous cycle's end placements: the robots stand still between cycles, so the two cycles
share those unknowns.

**Measurements:** every cycle's whitened mutual pixels, overhead pixels and odometry
distances (the model of [`jaxloc.refine_cycle`][], `jaxloc._model.measurements`, evaluated
at the window's poses: it depends on relative poses only, so `W_0` serves as well as the
cycle's own frame); the climbing robot's odometry between consecutive cycles
(`log(Z^-1 B_{k-1}^-1 B_k)` per axis over its sigma, `B = C M^-1` its body; see
`jaxloc._track.scenario`); and the prior that summarizes every older cycle.

**Marginalization** (Schur complement): when a new cycle arrives and the window is full,
the oldest cycle leaves. Its factors (its measurements, the prior, and the odometry from
`C_prev` to its own camera) are linearized at the current estimate, `H = J^T J`,
`g = J^T r`; the poses they alone involve (`F`, `C_prev` and the cycle's placements that are
not at its end) are eliminated, `H_p = H_kk - H_ke H_ee^-1 H_ek`, `b_p = g_k - H_ke
H_ee^-1 g_e`, and the kept poses (the cycle's end formation, the next `F`, and its camera,
the next `C_prev`) carry the Gaussian prior `|R_p delta + e_p|^2` with `R_p^T R_p = H_p`,
`R_p^T e_p = b_p`, `delta = log(x_lin^-1 x)` per pose. The window stays W cycles long, so
the cost per cycle does not grow with the number of cycles.

**Gauge:** C1's pose at the start of the first cycle is `W_0`'s origin, exactly: it is held
at the identity while it is in the window (and, once marginalized, the prior carries it).

**Bound:** the Fisher information at the true poses, with the sightings the cameras make
there (as [`jaxloc.cycle_crlb`][]), marginalized the same way (exactly: at a fixed
linearization point the Schur complement is the marginal information). It does not
depend on W: [`bound_update`][] keeps a one-cycle window.

The least squares are [`levenberg_marquardt`][] (`jaxloc._core.least_squares`); the
linear algebra is `jaxloc._core.linalg`'s (LAPACK-free).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._core.least_squares import levenberg_marquardt, normal_equations
from .._core.linalg import cholesky, gram_dot, lower_inverse, spd_inverse
from .._core.poses import compose, identity_params, inverse, rplus, rplus_params
from .._core.results import RESULTS, status_code
from .._cycle.estimate import FitCheck
from .._cycle.layout import num_moves, num_placements, num_steps, placement_ids
from .._cycle.rig import Rig
from .._model.gates import chi2_limit, worst_measurement
from .._model.measurements import CycleData, residual_poses, whitened_with_jacobian
from .frames import adjoint, body_of_overhead


#: Predicted decrease of the whitened cost (chi-square units) below which a step of the
#: smoother's Levenberg--Marquardt counts as converged (as `jaxloc.refine_cycle`'s).
NEGLIGIBLE_DECREASE = 1e-4
#: Iteration cap of the smoother's Levenberg--Marquardt per cycle.
SMOOTHER_MAX_STEPS = 24


class WindowLayout:
    """Where every unknown and every residual of a W-cycle window sits (static).

    Poses: `0..2` the oldest cycle's start formation (C1, C2, C3), `3` `C_prev`, then per
    slot `j` its new placements (placement `3 + q` of the cycle at `4 + j * per_slot + q`)
    and its overhead camera (`4 + j * per_slot + new`). Residuals: per slot its cycle's
    (`rows_per_cycle`), then per slot the climbing robot's odometry into it (6), then the
    prior (24)."""

    def __init__(self, strategy: str, window: int):
        if not isinstance(window, int) or isinstance(window, bool) or window < 1:
            raise ValueError(f"`window` must be a positive int (cycles); got {window!r}.")
        self.strategy, self.window = strategy, window
        ids = placement_ids(strategy)
        self.placements = P = num_placements(strategy)
        self.new = P - 3
        self.per_slot = self.new + 1
        self.num_poses = 4 + window * self.per_slot
        # The cycle's residual rows, as `whitened` orders them (one home for that order).
        self.rows_per_cycle = residual_poses(strategy).shape[0]
        self.num_rows = window * (self.rows_per_cycle + 6) + 24
        cycle_map = np.zeros((window, P + 1), np.int64)
        end = np.zeros((window, 3), np.int64)
        for j in range(window):
            for p in range(P):
                if p >= 3:
                    cycle_map[j, p] = self.slot_pose(j, p - 3)
                else:
                    cycle_map[j, p] = p if j == 0 else end[j - 1, p]
            cycle_map[j, P] = self.slot_camera(j)
            end[j] = cycle_map[j, ids[-1]]
        self.cycle_map, self.end = cycle_map, end
        self.cameras = np.array([self.slot_camera(j) for j in range(window)])
        self.previous_camera = np.concatenate([[3], self.cameras[:-1]])
        # Marginalization of slot 0: kept (the next start formation and C_prev), eliminated.
        self.keep = np.concatenate([end[0], [self.slot_camera(0)]])
        involved = set(range(4)) | {self.slot_pose(0, q) for q in range(self.per_slot)}
        self.eliminate = np.array(sorted(involved - set(self.keep.tolist())))
        # After the shift, C1 of the start formation is still the gauge iff C1 never moves.
        self.gauge_stays = bool(end[0, 0] == 0)

    def slot_pose(self, j: int, q: int) -> int:
        return 4 + j * self.per_slot + q

    def slot_camera(self, j: int) -> int:
        return self.slot_pose(j, self.new)

    def slot_poses(self, j: int) -> np.ndarray:
        return np.arange(self.slot_pose(j, 0), self.slot_pose(j, 0) + self.per_slot)

    def rows(self, name: str, j: int = 0) -> np.ndarray:
        """Residual rows of slot `j`'s `"cycle"` or `"odometry"`, or the `"prior"`."""
        W, m = self.window, self.rows_per_cycle
        if name == "cycle":
            return np.arange(j * m, (j + 1) * m)
        if name == "odometry":
            return np.arange(W * m + 6 * j, W * m + 6 * j + 6)
        return np.arange(W * (m + 6), W * (m + 6) + 24)

    def columns(self, poses) -> np.ndarray:
        """Tangent columns of window poses."""
        return (6 * np.asarray(poses)[:, None] + np.arange(6)[None]).reshape(-1)


class SmootherState(eqx.Module):
    """The smoother between two cycles (see the module docstring).

    **Fields:** `poses` `(num_poses, 7)` (`W_0`, `wxyz_xyz`); `data` (each slot's
    [`CycleData`][], leading axis W); `climber`, `climber_sigma` (the climbing robot's
    odometry into each slot's cycle, `(W, 7)`, `(W, 6)`); `active` `(W,)` (slots holding a
    cycle); `previous_active` (`C_prev` exists: a cycle was marginalized); `prior_lin`
    `(4, 7)`, `prior_R` `(24, 24)`, `prior_e` `(24,)` (the marginalization prior on the
    start formation and `C_prev`), `prior_active`; `gauge` (the start formation's C1 is
    `W_0`'s origin); `count` (cycles added); `status` (int32: 0 while every cycle
    succeeded, else the first failure's code, kept for every later cycle).
    """

    poses: Float[Array, "n 7"]
    data: CycleData
    climber: Float[Array, "W 7"]
    climber_sigma: Float[Array, "W 6"]
    active: Bool[Array, " W"]
    previous_active: Bool[Array, ""]
    prior_lin: Float[Array, "4 7"]
    prior_R: Float[Array, "24 24"]
    prior_e: Float[Array, " 24"]
    prior_active: Bool[Array, ""]
    gauge: Bool[Array, ""]
    count: Int[Array, ""]
    status: Int[Array, ""]


class SmootherEstimate(eqx.Module):
    """The smoother's estimate of the newest cycle's end, in `W_0`.

    **Fields:** `poses` `(4, 7)`: end-of-cycle body poses of (C, C1, C2, C3);
    `covariance` `(24, 24)`: their joint right-perturbation covariance (the window's
    `(J^T J)^-1`, the prior included); `result` (a [`jaxloc.RESULTS`][]: the first failure
    of the run so far, or the gates' verdict on this cycle); `checks` ([`FitCheck`][] of
    the window); `num_steps`.
    """

    poses: Float[Array, "4 7"]
    covariance: Float[Array, "24 24"]
    result: RESULTS
    checks: FitCheck
    num_steps: Int[Array, ""]


def empty_data(layout: WindowLayout, dtype) -> CycleData:
    """Unused measurements (zero weights) for every slot."""
    steps, moves = num_steps(layout.strategy), num_moves(layout.strategy)
    W = layout.window
    z = lambda *shape: jnp.zeros((W,) + shape, dtype)  # noqa: E731
    return CycleData(z(steps, 3, 3, 2), z(steps, 3, 3), z(steps, 3, 2), z(steps, 3), z(moves),
                     z(moves))  # fmt: skip


def smoother_start(layout: WindowLayout, dtype) -> SmootherState:
    """The smoother before the first cycle."""
    W, n = layout.window, layout.num_poses
    ident = jnp.broadcast_to(identity_params(dtype), (n, 7))
    return SmootherState(
        poses=ident, data=empty_data(layout, dtype),
        climber=jnp.broadcast_to(identity_params(dtype), (W, 7)),
        climber_sigma=jnp.ones((W, 6), dtype), active=jnp.zeros(W, bool),
        previous_active=jnp.array(False), prior_lin=ident[:4],
        prior_R=jnp.zeros((24, 24), dtype), prior_e=jnp.zeros(24, dtype),
        prior_active=jnp.array(False), gauge=jnp.array(True),
        count=jnp.array(0, jnp.int32), status=jnp.array(0, jnp.int32),
    )  # fmt: skip


def climber_residual(
    O_a: Float[Array, "7"], O_b: Float[Array, "7"], Z, sigma, mount
) -> Float[Array, "6"]:
    """Whitened residual of the climbing robot's odometry `Z` between its overhead cameras
    `O_a` and `O_b`: `log(Z^-1 B_a^-1 B_b) / sigma`, `B = O M^-1`."""
    B_a, B_b = body_of_overhead(O_a, mount), body_of_overhead(O_b, mount)
    rel = compose(inverse(jaxlie.SE3(B_a)), jaxlie.SE3(B_b))
    return jaxlie.manifold.rminus(jaxlie.SE3(Z), rel).astype(O_a.dtype) / sigma


def _climber_model(O_a, O_b, Z, sigma, mount):
    """Residual and its Jacobian `(6, 2, 6)` w.r.t. right perturbations of `O_a`, `O_b`."""

    def f(d):
        return climber_residual(
            rplus(jaxlie.SE3(O_a), d[0]).wxyz_xyz, rplus(jaxlie.SE3(O_b), d[1]).wxyz_xyz,
            Z, sigma, mount,
        )  # fmt: skip

    zero = jnp.zeros((2, 6), O_a.dtype)
    return f(zero), jax.jacfwd(f)(zero)


def _prior_model(x: Float[Array, "4 7"], lin, R, e):
    """Residual `R delta + e` `(24,)`, `delta = log(lin^-1 x)` per pose, and its Jacobian
    `(24, 4, 6)` w.r.t. right perturbations of `x`."""

    def delta(xi, li):
        def f(d):
            return jaxlie.manifold.rminus(jaxlie.SE3(li), rplus(jaxlie.SE3(xi), d))

        zero = jnp.zeros(6, xi.dtype)
        return f(zero).astype(xi.dtype), jax.jacfwd(f)(zero).astype(xi.dtype)

    d, D = jax.vmap(delta)(x, lin)  # (4, 6), (4, 6, 6)
    r = R @ d.reshape(-1) + e
    J = jnp.einsum("rpi,pij->rpj", R.reshape(24, 4, 6), D)
    return r, J


def pinned(layout: WindowLayout, state: SmootherState) -> Bool[Array, " n"]:
    """Poses held fixed (no column): the gauge, a missing `C_prev`, empty slots."""
    head = jnp.stack([state.gauge, jnp.array(False), jnp.array(False), ~state.previous_active])
    slots = jnp.repeat(~state.active, layout.per_slot)
    return jnp.concatenate([head, slots])


def window_model(layout: WindowLayout, state: SmootherState, x, rig: Rig):
    """Whitened residuals `(num_rows,)` of the window at poses `x` `(num_poses, 7)` and
    their Jacobian `(num_rows, 6 num_poses)` w.r.t. right perturbations (zero columns
    for pinned poses, zero rows for unused factors)."""
    dtype = x.dtype
    W, n, P = layout.window, layout.num_poses, layout.placements
    strategy = layout.strategy
    mount = rig.mounts[0].astype(dtype)
    cmap = layout.cycle_map  # (W, P + 1), static

    # Every slot's cycle, as one vmap (traced once).
    T_place, T_over = x[cmap[:, :P]], x[cmap[:, P]]
    r_c, J_c = jax.vmap(lambda tp, to, d: whitened_with_jacobian(tp, to, d, rig, strategy))(
        T_place, T_over, state.data
    )  # (W, m), (W, m, P + 1, 6)
    onehot = jnp.asarray(cmap[:, :, None] == np.arange(n)[None, None], dtype)  # (W, P+1, n)
    J_c = jnp.sum(J_c[:, :, :, None, :] * onehot[:, None, :, :, None], axis=2)  # (W, m, n, 6)
    act = state.active.astype(dtype)
    r_c, J_c = r_c * act[:, None], J_c * act[:, None, None, None]

    # The climbing robot's odometry into every slot.
    prev, cams = layout.previous_camera, layout.cameras
    r_o, J_o = jax.vmap(lambda a, b, z, s: _climber_model(a, b, z, s, mount))(
        x[prev], x[cams], state.climber, state.climber_sigma
    )  # (W, 6), (W, 6, 2, 6)
    pick = jnp.asarray(
        np.stack([prev, cams], 1)[:, :, None] == np.arange(n)[None, None], dtype
    )  # (W, 2, n)
    J_o = jnp.sum(J_o[:, :, :, None, :] * pick[:, None, :, :, None], axis=2)  # (W, 6, n, 6)
    first = np.arange(W) == 0
    edge = (state.active & (~first | state.previous_active)).astype(dtype)
    r_o, J_o = r_o * edge[:, None], J_o * edge[:, None, None, None]

    # The prior on the start formation and C_prev.
    r_p, J_p = _prior_model(x[:4], state.prior_lin, state.prior_R, state.prior_e)
    J_p = jnp.concatenate([J_p, jnp.zeros((24, n - 4, 6), dtype)], axis=1)
    on = state.prior_active.astype(dtype)
    r_p, J_p = r_p * on, J_p * on

    r = jnp.concatenate([r_c.reshape(-1), r_o.reshape(-1), r_p])
    J = jnp.concatenate([J_c.reshape(-1, n, 6), J_o.reshape(-1, n, 6), J_p])
    free = (~pinned(layout, state)).astype(dtype)
    return r, (J * free[None, :, None]).reshape(r.shape[0], 6 * n)


def _schur(H, g, keep, eliminate, pinned_mask):
    """Marginal information and gradient of the `keep` columns: `H_kk - H_ke H_ee^-1
    H_ek`, `g_k - H_ke H_ee^-1 g_e` (pinned eliminated columns are zero: an identity
    block stands in for their information)."""
    He = H[eliminate][:, eliminate] + jnp.diag(pinned_mask[eliminate].astype(H.dtype))
    inv, ok = spd_inverse(He)
    Hke = H[keep][:, eliminate]
    return H[keep][:, keep] - Hke @ inv @ Hke.T, g[keep] - Hke @ inv @ g[eliminate], ok


def marginalize(layout: WindowLayout, state: SmootherState, rig: Rig) -> SmootherState:
    """Drop the oldest cycle: its factors become a prior on its end formation and its
    camera (linearized at the current poses), and every slot moves one place back."""
    dtype = state.poses.dtype
    r, J = window_model(layout, state, state.poses, rig)
    rows = np.concatenate([layout.rows("cycle", 0), layout.rows("odometry", 0),
                           layout.rows("prior")])  # fmt: skip
    Jd, rd = J[rows], r[rows]
    H, g = gram_dot(Jd), rd @ Jd
    mask = jnp.repeat(pinned(layout, state), 6)
    keep, elim = layout.columns(layout.keep), layout.columns(layout.eliminate)
    Hp, bp, ok = _schur(H, g, keep, elim, mask)
    # A kept pose that is pinned (the concurrent strategy's C1, the gauge) keeps a zero
    # column; an identity block makes the prior's square root exist.
    Hp = Hp + jnp.diag(mask[keep].astype(dtype))
    Hp = 0.5 * (Hp + Hp.T)
    L = cholesky(Hp)
    ok = ok & jnp.all(jnp.isfinite(L))
    L = jnp.where(ok, L, jnp.eye(24, dtype=dtype))
    e = lower_inverse(L) @ bp
    W = layout.window
    ident = identity_params(dtype)
    # Shift: the kept poses become the new start formation and C_prev.
    slots = state.poses[4:].reshape(W, layout.per_slot, 7)
    slots = jnp.concatenate([slots[1:], jnp.broadcast_to(ident, (1, layout.per_slot, 7))])
    poses = jnp.concatenate([state.poses[layout.keep], slots.reshape(-1, 7)])

    def shift(a, fill):
        return jnp.concatenate([a[1:], jnp.broadcast_to(fill, (1,) + a.shape[1:])])

    data = jax.tree.map(lambda a: shift(a, jnp.zeros((), a.dtype)), state.data)
    status = jnp.where((state.status == 0) & ~ok, status_code(RESULTS.unobservable), state.status)
    return SmootherState(
        poses=poses, data=data, climber=shift(state.climber, ident),
        climber_sigma=shift(state.climber_sigma, jnp.ones(6, dtype)),
        active=shift(state.active, False), previous_active=jnp.array(True),
        prior_lin=state.poses[layout.keep], prior_R=jnp.where(ok, L.T, 0.0),
        prior_e=jnp.where(ok, e, 0.0), prior_active=jnp.array(True),
        gauge=state.gauge & layout.gauge_stays, count=state.count, status=status,
    )  # fmt: skip


def _select(pred, a, b):
    return jax.tree.map(lambda u, v: jnp.where(pred, u, v), a, b)


def insert(
    layout: WindowLayout,
    state: SmootherState,
    data: CycleData,
    climber: Float[Array, "7"],
    climber_sigma: Float[Array, "6"],
    T_place: Float[Array, "P 7"],
    T_over: Float[Array, "7"],
    rig: Rig,
    *,
    in_world0: bool = False,
) -> tuple[SmootherState, Int[Array, ""]]:
    """Add a cycle: marginalize the oldest first if the window is full, then put the cycle
    in the next free slot with its start `T_place` `(P, 7)`, `T_over` (its frame `W_k`,
    mapped into `W_0` through the window's estimate of its start C1; or already in `W_0`
    with `in_world0`). The first cycle also sets the start formation. Returns the state
    and the slot used."""
    W = layout.window
    full = state.count >= W
    state = _select(full, marginalize(layout, state, rig), state)
    s = jnp.minimum(state.count, W - 1)
    dtype = state.poses.dtype
    if in_world0:
        frame = identity_params(dtype)
    else:
        frame = state.poses[jnp.asarray(layout.cycle_map[:, 0])[s]]
    to_w0 = jax.vmap(lambda T: compose(jaxlie.SE3(frame), jaxlie.SE3(T)).wxyz_xyz)
    new = to_w0(jnp.concatenate([T_place[3:], T_over[None]]))  # (per_slot, 7)
    idx = 4 + s * layout.per_slot + jnp.arange(layout.per_slot)
    poses = state.poses.at[idx].set(new)
    # The first cycle's start formation (its C1 is W_0's origin).
    first = state.count == 0
    start = to_w0(T_place[:3]).at[0].set(identity_params(dtype))
    poses = poses.at[:3].set(jnp.where(first, start, poses[:3]))
    state = eqx.tree_at(
        lambda t: (t.poses, t.data, t.climber, t.climber_sigma, t.active, t.count),
        state,
        (
            poses,
            jax.tree.map(lambda a, b: a.at[s].set(b), state.data, data),
            state.climber.at[s].set(climber),
            state.climber_sigma.at[s].set(climber_sigma),
            state.active.at[s].set(True),
            state.count + 1,
        ),
    )
    return state, s


def information(layout: WindowLayout, state: SmootherState, J) -> Float[Array, "N N"]:
    """`J^T J` of the window, with an identity block for every pinned pose."""
    mask = jnp.repeat(pinned(layout, state), 6).astype(J.dtype)
    return gram_dot(J) + jnp.diag(mask)


def newest_end(layout: WindowLayout, state: SmootherState, s, covariance, rig: Rig):
    """End-of-cycle body poses of (C, C1, C2, C3) of slot `s` `(4, 7)` and their joint
    covariance `(24, 24)` from the window's tangent covariance."""
    dtype = state.poses.dtype
    which = jnp.concatenate(
        [jnp.asarray(layout.cameras)[s][None], jnp.asarray(layout.end)[s]]
    )  # (4,) window poses: camera, C1, C2, C3
    cols = (6 * which[:, None] + jnp.arange(6)[None]).reshape(-1)
    cov = covariance[cols][:, cols]
    mount = rig.mounts[0].astype(dtype)
    A = jnp.eye(24, dtype=dtype).at[:6, :6].set(adjoint(mount))
    poses = state.poses[which]
    poses = poses.at[0].set(body_of_overhead(poses[0], mount))
    return poses, A @ cov @ A.T


def _gates(layout, state, r, J, covariance, covariance_ok, observable_cycle, noise_model):
    """Chi-square, observability and the test of each measurement against the rest
    ([`jaxloc._model.gates.worst_measurement`][]: every pixel sighting of the window, and
    every odometry distance, climbing-robot odometry row and prior row) of the window at
    its solution."""
    dtype = r.dtype
    chi2 = jnp.sum(r * r)
    act = state.active
    sightings = jnp.sum(jnp.where(act[:, None], (state.data.mutual_weight > 0).reshape(
        layout.window, -1), False)) + jnp.sum(
        jnp.where(act[:, None], (state.data.overhead_weight > 0).reshape(layout.window, -1),
                  False))  # fmt: skip
    odometry = jnp.sum(jnp.where(act[:, None], state.data.odometry_weight > 0, False))
    first = np.arange(layout.window) == 0
    edges = jnp.sum(act & (~first | state.previous_active))
    gaussian = odometry + 6 * edges + 24 * state.prior_active.astype(jnp.int32)
    unknowns = 6 * jnp.sum(~pinned(layout, state))
    dof = (2 * sightings + gaussian - unknowns).astype(jnp.int32)
    limit = chi2_limit(dof, sightings, gaussian, noise_model, dtype)
    observable = covariance_ok & observable_cycle & (dof > 0)
    # Rows reordered as the test takes them: every slot's pixel pairs, then single rows.
    m, moves = layout.rows_per_cycle, state.data.odometry.shape[-1]
    pairs = (m - moves) // 2
    cycle_rows = np.arange(layout.window)[:, None] * m
    pixel_rows = (cycle_rows + np.arange(2 * pairs)[None]).reshape(-1)
    single_rows = np.concatenate([(cycle_rows + 2 * pairs + np.arange(moves)[None]).reshape(-1),
                                  np.arange(layout.window * m, r.shape[0])])  # fmt: skip
    order = np.concatenate([pixel_rows, single_rows])
    worst = worst_measurement(r[order], J[order], jnp.where(covariance_ok, covariance, 0.0),
                              layout.window * pairs, sightings + gaussian, noise_model)  # fmt: skip
    return chi2, dof, limit, observable, worst


def solve_window(
    layout: WindowLayout,
    state: SmootherState,
    rig: Rig,
    *,
    max_steps: int = SMOOTHER_MAX_STEPS,
    rtol: float = 1e-6,
    atol: float = 1e-6,
):
    """Levenberg--Marquardt over the window from its current poses: `(state, r, J,
    num_steps, converged)` at the solution."""
    n = layout.num_poses
    free = (~pinned(layout, state)).astype(state.poses.dtype)

    def retract(x, delta):
        return jax.vmap(rplus_params)(x, delta.reshape(n, 6) * free[:, None])

    out = levenberg_marquardt(
        lambda x: normal_equations(*window_model(layout, state, x, rig), gram_dot),
        retract,
        lambda x: jnp.max(jnp.abs(x[:, 4:])),
        state.poses,
        num_unknowns=6 * n,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        # Below the kernel's 1e-3: a step rejected at the start (a converged start, whose
        # cost only rounding changes) then counts as the minimum within rounding.
        lam0=1e-4,
        decrease_tol=NEGLIGIBLE_DECREASE * (min(rtol, atol) / 1e-6) ** 2,
    )
    state = eqx.tree_at(lambda t: t.poses, state, out.x)
    r, J = window_model(layout, state, out.x, rig)
    return state, r, J, out.num_steps, out.converged


def smoother_update(
    layout: WindowLayout,
    state: SmootherState,
    data: CycleData,
    climber: Float[Array, "7"],
    climber_sigma: Float[Array, "6"],
    T_place: Float[Array, "P 7"],
    T_over: Float[Array, "7"],
    start_result: RESULTS,
    start_observable: Bool[Array, ""],
    rig: Rig,
) -> tuple[SmootherState, SmootherEstimate]:
    """One cycle of the fixed-lag smoother.

    **Arguments:** the `layout` and the `state`; the new cycle's whitened measurements
    `data` ([`jaxloc._model.measurements.cycle_data`][]); the climbing robot's odometry
    into it (`climber` `wxyz_xyz`, `climber_sigma` `(6,)`; ignored for the first cycle);
    a start for its poses in its own frame (`T_place` `(P, 7)`, `T_over` `(7,)`: e.g.
    [`jaxloc.refine_cycle`][]'s, with its `start_result` and its observability gate
    `start_observable`); the rig.

    **Returns:** the new state and a [`SmootherEstimate`][]. A failed start, a failed
    marginalization or a failed gate makes this cycle and every later one fail with that
    status (the run's chain of frames is broken).
    """
    state, s = insert(layout, state, data, climber, climber_sigma, T_place, T_over, rig)
    state, r, J, num_steps, converged = solve_window(layout, state, rig)
    covariance, cov_ok = spd_inverse(information(layout, state, J))
    chi2, dof, limit, observable, worst = _gates(layout, state, r, J, covariance, cov_ok,
                                                 start_observable, rig.noise_model)  # fmt: skip
    result = RESULTS.where(converged, RESULTS.successful, RESULTS.nonlinear_max_steps_reached)
    result = RESULTS.where(observable, result, RESULTS.unobservable)
    consistent = (chi2 <= limit) & (worst <= 1.0)
    result = RESULTS.where((result == RESULTS.successful) & ~consistent,
                           RESULTS.inconsistent_fit, result)  # fmt: skip
    result = RESULTS.where(start_result == RESULTS.successful, result, start_result)
    code = jnp.where(state.status == 0, status_code(result), state.status)
    state = eqx.tree_at(lambda t: t.status, state, code)
    result = RESULTS.where(code == 0, RESULTS.successful, result)
    result = _result_of_code(code, result)
    poses, cov = newest_end(layout, state, s, covariance, rig)
    nan = jnp.full((), jnp.nan, chi2.dtype)  # blunder_nees: not computed by the tracker
    checks = FitCheck(result, chi2, chi2, dof, limit, observable, worst, nan)
    return state, SmootherEstimate(poses, cov, result, checks, num_steps)


def _result_of_code(code, fallback: RESULTS) -> RESULTS:
    """The [`jaxloc.RESULTS`][] item of an int32 code (the run's first failure)."""
    out = fallback
    for item in RESULTS._name_to_item.values():
        out = RESULTS.where(code == status_code(item), item, out)
    return out


def bound_update(
    layout: WindowLayout,
    state: SmootherState,
    data: CycleData,
    climber: Float[Array, "7"],
    climber_sigma: Float[Array, "6"],
    T_place: Float[Array, "P 7"],
    T_over: Float[Array, "7"],
    rig: Rig,
) -> tuple[SmootherState, Float[Array, "4 7"], Float[Array, "24 24"]]:
    """One cycle of the smoother's bound: the new cycle at its true poses (in `W_0`) with
    the measurements its cameras make there (`data` as [`jaxloc._model.covariance.crlb_inputs`][]
    gives them) and the climbing robot's true motion with its odometry sigma. Returns the
    state and the true end poses (C, C1, C2, C3) with their joint bound `(24, 24)`
    (marginal over every earlier cycle). Use a one-cycle layout: the bound does not
    depend on the window."""
    state, s = insert(
        layout, state, data, climber, climber_sigma, T_place, T_over, rig, in_world0=True
    )
    _, J = window_model(layout, state, state.poses, rig)
    covariance, _ = spd_inverse(information(layout, state, J))
    poses, cov = newest_end(layout, state, s, covariance, rig)
    return state, poses, cov
