r"""The measurement model of a localization cycle and its Jacobian (DESIGN §5).

Shared by the joint refinement ([`jaxloc.refine_cycle`][]), the covariance and the
Cramér–Rao bound ([`jaxloc.cycle_covariance`][], [`jaxloc.cycle_crlb`][]) and the closed
forms' goodness-of-fit and observability gates. Unknowns: the pose `T_world_body` of
every distinct robot placement (see [`jaxloc.placement_ids`][]) and the overhead camera's
optical-frame pose `T_world_overhead`, all `wxyz_xyz`. Measurements: every mutual
sighting in pixels of the observing camera, every overhead pixel, every odometry
distance, each whitened by its standard deviation. Cameras, mounts, markers and pixel
noise come from a [`jaxloc.Rig`][], and every sighting goes through the one projection
path of `jaxloc._cycle.sightings`.

The Jacobian is assembled by the chain rule, not by differentiating the whole model:
a sighting depends on two poses only (jaxlie's right perturbation `T exp(delta)`,
`delta = (v, omega)`; see `jaxloc._cycle.sightings`), and only the camera projection is
differentiated, by each model's closed-form `project_with_jacobian`. About 20x cheaper
than `jax.jacfwd` over the ~40 stacked tangent directions.
"""


import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float

from .._core.least_squares import NormalEquations
from .._core.linalg import gram_dot
from .._core.numerics import safe_norm
from .._core.poses import quaternion_matrix, rplus
from .._core.robust import RobustLoss
from .._cycle.layout import move_start_step, moving_robot, placement_ids
from .._cycle.observations import CycleObservations, ODOMETRY_SIGMA_FLOOR
from .._cycle.rig import ground_cameras_apply, PIXEL_SIGMA_FLOOR, Rig
from .._cycle.sightings import (
    camera_pose_jacobian,
    in_body,
    matmul,
    matvec,
    matvec_t,
    mutual_points,
    observer_jacobian,
    target_jacobian,
)


def rotations(T: Float[Array, "*b 7"]) -> Float[Array, "*b 3 3"]:
    """Rotation matrices of `wxyz_xyz` poses, any leading shape."""
    return quaternion_matrix(T[..., :4])


class Geometry(eqx.Module):
    """Every sighting of a cycle at given poses, in camera frames, with what its
    Jacobian needs (all arrays; built by [`geometry`][]).

    **Fields:** `R_body (steps, 3, 3, 3)`, `p_body (steps, 3, 3)` (the ground robots at
    every step); `mutual_cam (steps, 3, 3, 3)`: robot `j`'s marker in robot `i`'s camera
    frame `[k, i, j]` (diagonal a dummy); `mutual_body`: the same in robot `i`'s body
    frame; `R_over (3, 3)`, `p_over (3,)`: the overhead camera; `over_cam (steps, 3, 3)`:
    every marker in its frame; `markers (3, 3)`, `mount_R (3, 3, 3)`: the ground
    robots' markers and camera mounts; `markers_world (steps, 3, 3)`: every marker in
    `W`.
    """

    R_body: Float[Array, "steps 3 3 3"]
    p_body: Float[Array, "steps 3 3"]
    mutual_cam: Float[Array, "steps 3 3 3"]
    mutual_body: Float[Array, "steps 3 3 3"]
    R_over: Float[Array, "3 3"]
    p_over: Float[Array, "3"]
    over_cam: Float[Array, "steps 3 3"]
    markers: Float[Array, "3 3"]
    mount_R: Float[Array, "3 3 3"]
    markers_world: Float[Array, "steps 3 3"]


def geometry(T_place, T_over, rig: Rig, strategy: str) -> Geometry:
    """The sightings of a cycle whose placements are at `T_place` `(placements, 7)` and
    whose overhead camera's optical frame is at `T_over` `(7,)` (`wxyz_xyz`, world `W`)."""
    ids = placement_ids(strategy)
    T_body = T_place[ids]  # (steps, 3, 7)
    R, p = rotations(T_body), T_body[..., 4:]
    dtype = T_place.dtype
    mount_R = rig.mount_rotations()[1:].astype(dtype)
    mount_t = rig.mount_translations()[1:].astype(dtype)
    markers = rig.markers[1:].astype(dtype)
    mutual_cam, mutual_body = mutual_points(R, p, mount_R, mount_t, markers)
    R_over, p_over = rotations(T_over), T_over[4:]
    x = matvec(R, markers) + p  # (steps, 3, 3): markers in W
    over_cam = in_body(R_over, p_over, x)
    return Geometry(
        R, p, mutual_cam, mutual_body, R_over, p_over, over_cam, markers, mount_R, x
    )


def _by_observer(x):
    """`(steps, 3, ...)` -> `(3, steps, ...)`: the observer axis first, for
    `ground_cameras_apply`."""
    return jnp.swapaxes(x, 0, 1)


def _from_observer(x):
    return jnp.swapaxes(x, 0, 1)


def predict(T_place, T_over, rig: Rig, strategy: str):
    """Noise-free measurements of a cycle at the given poses.

    **Returns:** `(mutual (steps, 3, 3, 2) px, overhead (steps, 3, 2) px, lengths (moves,)
    m)`: every mutual sighting in the observer's image (diagonal a finite dummy), every
    overhead sighting in the overhead camera's image, and each move's straight-line
    length between the mover's body origins.
    """
    g = geometry(T_place, T_over, rig, strategy)
    mutual = _from_observer(
        ground_cameras_apply(rig, lambda cam, x: cam.project(x), _by_observer(g.mutual_cam))
    )
    overhead = rig.overhead.project(g.over_cam)
    return mutual, overhead, move_lengths(g.p_body, strategy)


def move_lengths(p_body: Float[Array, "steps 3 3"], strategy: str) -> Float[Array, " moves"]:
    """Straight-line length of each move between the mover's body origins (m)."""
    starts, movers = move_start_step(strategy), moving_robot(strategy)
    return safe_norm(p_body[starts + 1, movers] - p_body[starts, movers])


def visible(
    T_place, T_over, rig: Rig, strategy: str
) -> tuple[Bool[Array, "steps 3 3"], Bool[Array, "steps 3"]]:
    """Which sightings the cameras make at the given poses (`in_view`, as the simulator
    decides): `(mutual (steps, 3, 3), overhead (steps, 3))`, diagonal False."""
    g = geometry(T_place, T_over, rig, strategy)
    mutual = _from_observer(
        ground_cameras_apply(rig, lambda cam, x: cam.in_view(x), _by_observer(g.mutual_cam))
    )
    return mutual & ~np.eye(3, dtype=bool)[None], rig.overhead.in_view(g.over_cam)


class CycleData(eqx.Module):
    """Measurements of a cycle with their whitening weights (1 / sigma; 0 = unused).

    **Fields:** `mutual_pixels` `(steps, 3, 3, 2)` px, `mutual_weight` `(steps, 3, 3)`
    1/px, `overhead_pixels` `(steps, 3, 2)` px, `overhead_weight` `(steps, 3)` 1/px,
    `odometry` `(moves,)` m, `odometry_weight` `(moves,)` 1/m. Unused entries hold 0.
    """

    mutual_pixels: Float[Array, "steps 3 3 2"]
    mutual_weight: Float[Array, "steps 3 3"]
    overhead_pixels: Float[Array, "steps 3 2"]
    overhead_weight: Float[Array, "steps 3"]
    odometry: Float[Array, " moves"]
    odometry_weight: Float[Array, " moves"]

    @property
    def num_sightings(self) -> Array:
        """Number of pixel sightings used (each two residuals)."""
        return jnp.sum(self.mutual_weight > 0) + jnp.sum(self.overhead_weight > 0)

    @property
    def num_odometry(self) -> Array:
        """Number of odometry distances used."""
        return jnp.sum(self.odometry_weight > 0)


def pixel_weights(rig: Rig, dtype) -> Float[Array, "4"]:
    """`1 / sigma` per camera (C, C1, C2, C3) of each pixel coordinate (1/px)."""
    sigma = jnp.maximum(rig.sigma_per_axis().astype(dtype), PIXEL_SIGMA_FLOOR)
    return 1.0 / sigma


def odometry_weight(distance, sigma):
    """`1 / sigma` of each odometry distance, sigma floored at `ODOMETRY_SIGMA_FLOOR`
    times the cycle's longest move (exact odometry of a noise-free simulation)."""
    floor = 1e-9 + ODOMETRY_SIGMA_FLOOR * jnp.max(jnp.abs(distance))
    return 1.0 / jnp.maximum(sigma, floor)


def _pixels_from_bearings(observations: CycleObservations, rig: Rig):
    """Pixels of the sightings that carry a bearing but no pixel (observations built from
    bearings alone): each bearing projected through its camera, so that the refinement
    weighs every sighting in its camera's image either way."""
    dtype = observations.mutual.dtype
    mount_R = rig.mount_rotations()[1:].astype(dtype)
    b_cam = matvec_t(mount_R[None, :, None], observations.mutual)  # body -> camera frame
    mutual = _from_observer(
        ground_cameras_apply(rig, lambda cam, x: cam.project(x), _by_observer(b_cam))
    )
    return mutual, rig.overhead.project(observations.overhead)


def cycle_data(observations: CycleObservations, rig: Rig) -> CycleData:
    """Whitened measurement set of a cycle. A sighting is used when its pixel is finite,
    or, failing that, its bearing (projected through its camera); non-finite pixels and
    bearings, sightings marked not visible and the diagonal are missing data, left out.
    Pixel sigma per camera and axis from the rig; odometry sigma from the observations."""
    dtype = observations.mutual_pixels.dtype
    w_px = pixel_weights(rig, dtype)
    from_bearings = _pixels_from_bearings(observations, rig)
    off_diagonal = ~np.eye(3, dtype=bool)[None]

    def choose(pixels, bearings, derived, mask):
        pixel_ok = jnp.all(jnp.isfinite(pixels), axis=-1)
        bearing_ok = jnp.all(jnp.isfinite(bearings), axis=-1) & jnp.all(jnp.isfinite(derived), -1)
        uv = jnp.where(pixel_ok[..., None], pixels, derived)
        ok = mask & (pixel_ok | bearing_ok)
        return jnp.where(ok[..., None], uv, 0.0), ok

    mp, m_ok = choose(
        observations.mutual_pixels, observations.mutual, from_bearings[0],
        off_diagonal & observations.mutual_visible,
    )  # fmt: skip
    op, o_ok = choose(
        observations.overhead_pixels, observations.overhead, from_bearings[1],
        observations.overhead_visible,
    )  # fmt: skip
    d, sigma = observations.odometry, observations.odometry_sigma
    d_ok = jnp.isfinite(d) & jnp.isfinite(sigma) & (d > 0) & (sigma >= 0)
    d = jnp.where(d_ok, d, 0.0)
    return CycleData(
        mutual_pixels=mp,
        mutual_weight=jnp.where(m_ok, w_px[None, 1:, None], 0.0),
        overhead_pixels=op,
        overhead_weight=jnp.where(o_ok, w_px[0], 0.0),
        odometry=d,
        odometry_weight=jnp.where(d_ok, odometry_weight(d, jnp.where(d_ok, sigma, 0.0)), 0.0),
    )


def unpack(theta, T0_place, T0_over):
    """Poses from the tangent vector: placements 1, 2, ... then the overhead camera, each
    `T0 exp(delta)`; placement 0 (C1 at the start) is the identity (the gauge)."""
    n = T0_place.shape[0]
    d = theta[:-6].reshape(n - 1, 6)
    moved = jax.vmap(lambda t, dd: rplus(jaxlie.SE3(t), dd).wxyz_xyz)(
        T0_place[1:], d
    )
    first = jnp.zeros((1, 7), T0_place.dtype).at[0, 0].set(1.0)
    T_place = jnp.concatenate([first, moved.astype(T0_place.dtype)])
    T_over = rplus(jaxlie.SE3(T0_over), theta[-6:]).wxyz_xyz
    return T_place, T_over.astype(T0_over.dtype)


def pack(T_place, T_over, T0_place, T0_over):
    """The inverse of [`unpack`][]: the tangent vector `theta` `(6 n,)` with `T =
    T0 exp(delta)` per pose (placements 1, 2, ... then the overhead camera; placement 0
    is the gauge and has no coordinates). A chart: valid while each rotation from `T0`
    is below pi."""
    rminus = jaxlie.manifold.rminus
    d = jax.vmap(lambda t0, t: rminus(jaxlie.SE3(t0), jaxlie.SE3(t)))(T0_place[1:], T_place[1:])
    d_over = rminus(jaxlie.SE3(T0_over), jaxlie.SE3(T_over))
    return jnp.concatenate([d.reshape(-1), d_over]).astype(T0_place.dtype)


#: The ordered pairs (observer, target) of mutual sightings, grouped by observer.
OBSERVER = np.array([0, 0, 1, 1, 2, 2])
TARGET = np.array([1, 2, 0, 2, 0, 1])


def residual_poses(strategy: str) -> np.ndarray:
    """The two poses each whitened residual depends on, `(m, 2)` int, in the row order of
    [`whitened`][]: pose `p < placements` is a placement, `placements` the overhead
    camera. Rows: mutual sightings `(steps, 6 pairs, 2)` as (observer, target), overhead
    sightings `(steps, 3, 2)` as (robot, camera), odometry `(moves,)` as (end, start)."""
    ids = placement_ids(strategy)
    n = int(ids.max()) + 1
    mutual = np.stack([ids[:, OBSERVER], ids[:, TARGET]], -1)  # (steps, 6, 2)
    mutual = np.repeat(mutual[:, :, None], 2, axis=2).reshape(-1, 2)
    overhead = np.stack([ids, np.full_like(ids, n)], -1)
    overhead = np.repeat(overhead[:, :, None], 2, axis=2).reshape(-1, 2)
    starts, movers = move_start_step(strategy), moving_robot(strategy)
    odometry = np.stack([ids[starts + 1, movers], ids[starts, movers]], -1)
    return np.concatenate([mutual, overhead, odometry]).astype(np.int32)


def whitened(T_place, T_over, data: CycleData, rig: Rig, strategy: str):
    """Whitened residuals `(m,)`: mutual pixels (the six ordered pairs of each step),
    overhead pixels, odometry (the rows of [`residual_poses`][])."""
    mutual, overhead, lengths = predict(T_place, T_over, rig, strategy)
    pair = (slice(None), OBSERVER, TARGET)
    r_m = data.mutual_weight[pair][..., None] * (mutual[pair] - data.mutual_pixels[pair])
    r_o = data.overhead_weight[..., None] * (overhead - data.overhead_pixels)
    r_d = data.odometry_weight * (lengths - data.odometry)
    return jnp.concatenate([r_m.reshape(-1), r_o.reshape(-1), r_d])


def sighting_squares(
    r: Float[Array, " m"], steps: int
) -> tuple[Float[Array, "steps 6"], Float[Array, "steps 3"]]:
    """Squared whitened norm of each pixel sighting (its two rows of [`whitened`][]):
    `(mutual (steps, 6 ordered pairs OBSERVER, TARGET), overhead (steps, 3))`; 0 for an
    unused sighting."""
    n_m, n_o = 12 * steps, 6 * steps
    s_m = jnp.sum(r[:n_m].reshape(steps, 6, 2) ** 2, axis=-1)
    s_o = jnp.sum(r[n_m : n_m + n_o].reshape(steps, 3, 2) ** 2, axis=-1)
    return s_m, s_o


def robust_weights(r: Float[Array, " m"], steps: int, loss: RobustLoss):
    """The robust cost `sum rho(s_i) + odometry^2` of whitened residuals `r` and the
    square root of each row's weight `rho'(s_i)` (1 for the odometry rows, which stay
    plain least squares)."""
    s_m, s_o = sighting_squares(r, steps)
    s = jnp.concatenate([s_m.reshape(-1), s_o.reshape(-1)])
    n = s.shape[0]
    cost = jnp.sum(loss.rho(s)) + jnp.sum(r[2 * n :] ** 2)
    w = jnp.repeat(jnp.sqrt(loss.weight(s)), 2)
    return cost, jnp.concatenate([w, jnp.ones(r.shape[0] - 2 * n, r.dtype)])


def whitened_cost(T_place, T_over, data: CycleData, rig: Rig, strategy: str,
                  loss: RobustLoss | None = None):  # fmt: skip
    """The cost the refinement minimises: `r^T r` of [`whitened`][], or with a robust
    `loss` `sum rho(s_i)` over the pixel sightings plus the odometry's squares."""
    r = whitened(T_place, T_over, data, rig, strategy)
    if loss is None:
        return jnp.sum(r * r)
    return robust_weights(r, data.mutual_pixels.shape[0], loss)[0]


def without(data: CycleData, mutual: Bool[Array, "steps 3 3"],
            overhead: Bool[Array, "steps 3"]) -> CycleData:  # fmt: skip
    """`data` with the sightings marked in `mutual` and `overhead` left out (weight 0,
    as missing data: they count in no sum and no degree of freedom)."""
    weights = (
        jnp.where(mutual, 0.0, data.mutual_weight),
        jnp.where(overhead, 0.0, data.overhead_weight),
    )
    return eqx.tree_at(lambda d: (d.mutual_weight, d.overhead_weight), data, weights)


def whitened_blocks(
    T_place: Float[Array, "placements 7"],
    T_over: Float[Array, "7"],
    data: CycleData,
    rig: Rig,
    strategy: str,
) -> tuple[Float[Array, " m"], Float[Array, "m 2 6"]]:
    """Whitened residuals and their Jacobian as two blocks per row.

    **Returns:** `(r, B)`: `r` as [`whitened`][] `(m,)`; `B[row, k]` `(6,)` the derivative
    of the row with respect to the right perturbation `delta = (v, omega)` of pose
    `residual_poses(strategy)[row, k]` (`T exp(delta)`). Every residual depends on two
    poses only, so this is the whole Jacobian.
    """
    dtype = T_place.dtype
    g = geometry(T_place, T_over, rig, strategy)
    R = g.R_body
    steps = R.shape[0]
    pair = (slice(None), OBSERVER, TARGET)
    # Mutual sightings, grouped by observer for its camera: (steps, 3 observers, 2, ...).
    by_observer = g.mutual_cam[pair].reshape(steps, 3, 2, 3)
    uv, Jp = ground_cameras_apply(
        rig, lambda cam, x: cam.project_with_jacobian(x), _by_observer(by_observer)
    )
    mutual = _from_observer(uv).reshape(steps, 6, 2)
    Jp = _from_observer(Jp).reshape(steps, 6, 2, 3)
    mount_R = g.mount_R[OBSERVER][None]
    observer = matmul(Jp, observer_jacobian(mount_R, g.mutual_body[pair]))
    Rt = jnp.swapaxes(R, -1, -2)
    A = matmul(jnp.swapaxes(mount_R, -1, -2), matmul(Rt[:, OBSERVER], R[:, TARGET]))
    target = matmul(Jp, target_jacobian(A, g.markers[TARGET][None]))
    w_m = data.mutual_weight[pair]
    r_m = w_m[..., None] * (mutual - data.mutual_pixels[pair])
    B_m = w_m[..., None, None, None] * jnp.stack([observer, target], axis=-2)
    # Overhead sightings: (robot, camera).
    overhead, Jo = rig.overhead.project_with_jacobian(g.over_cam)
    over_cam = matmul(Jo, camera_pose_jacobian(g.over_cam))
    A_o = matmul(jnp.swapaxes(g.R_over, -1, -2)[None, None], R)
    over_pt = matmul(Jo, target_jacobian(A_o, g.markers[None]))
    w_o = data.overhead_weight
    r_o = w_o[..., None] * (overhead - data.overhead_pixels)
    B_o = w_o[..., None, None, None] * jnp.stack([over_pt, over_cam], axis=-2)
    # Odometry: the mover's body origin, (end, start).
    starts, movers = move_start_step(strategy), moving_robot(strategy)
    step = g.p_body[starts + 1, movers] - g.p_body[starts, movers]
    lengths = safe_norm(step)
    u = step / jnp.where(lengths > 0, lengths, 1.0)[:, None]
    u_end = jnp.sum(u[:, :, None] * R[starts + 1, movers], axis=-2)  # u^T R
    u_start = -jnp.sum(u[:, :, None] * R[starts, movers], axis=-2)
    zeros3 = jnp.zeros_like(u_end)
    r_d = data.odometry_weight * (lengths - data.odometry)
    B_d = data.odometry_weight[:, None, None] * jnp.stack(
        [jnp.concatenate([u_end, zeros3], -1), jnp.concatenate([u_start, zeros3], -1)], axis=-2
    )
    r = jnp.concatenate([r_m.reshape(-1), r_o.reshape(-1), r_d]).astype(dtype)
    B = jnp.concatenate([B_m.reshape(-1, 2, 6), B_o.reshape(-1, 2, 6), B_d]).astype(dtype)
    return r, B


def whitened_with_jacobian(T_place, T_over, data: CycleData, rig: Rig, strategy: str):
    """Whitened residuals `(m,)` and their dense Jacobian `(m, placements + 1, 6)`: column
    block `p < placements` is placement `p`'s right perturbation, the last block the
    overhead camera's."""
    r, B = whitened_blocks(T_place, T_over, data, rig, strategy)
    return r, dense_jacobian(B, strategy)


def unknowns_jacobian(B: Float[Array, "m 2 6"], strategy: str) -> Float[Array, "m n"]:
    """The whitened Jacobian `(m, 6 * placements)` of [`whitened_blocks`][]' blocks `B`
    with respect to the tangent of [`unpack`][] (placements 1, 2, ... then the overhead
    camera; placement 0, the gauge, left out): the `J` of [`normal_equations`][]'
    `J^T J`."""
    return dense_jacobian(B, strategy)[:, 1:].reshape(B.shape[0], -1)


def dense_jacobian(B: Float[Array, "m 2 6"], strategy: str) -> Float[Array, "m p 6"]:
    """The dense Jacobian `(m, placements + 1, 6)` of [`whitened_blocks`][]' blocks `B`
    (see [`whitened_with_jacobian`][])."""
    poses = residual_poses(strategy)
    at = (poses[:, :, None] == np.arange(poses.max() + 1)).astype(np.float64)
    return jnp.sum(jnp.asarray(at, B.dtype)[..., None] * B[:, :, None, :], axis=1)


def normal_equations(
    T_place: Float[Array, "placements 7"],
    T_over: Float[Array, "7"],
    data: CycleData,
    rig: Rig,
    strategy: str,
    loss: RobustLoss | None = None,
) -> NormalEquations:
    """The cost `r^T r`, `H = J^T J` and `g = J^T r` of the whitened residuals with
    respect to the tangent of [`unpack`][] (placements 1, 2, ... then the overhead camera;
    placement 0 is the gauge), without a dense Jacobian.

    With a robust `loss` (`jaxloc._core.robust`), the cost is `sum rho(s_i)` over the
    pixel sightings (plus the odometry's squares) and each sighting's two rows are
    weighed by `rho'(s_i)` in `H` and `g`: one step of iteratively reweighted least
    squares, whose `g` is the exact half-gradient of that cost.

    `H` is one dense `J^T J` of [`unknowns_jacobian`][] (one `dot`): about ten times
    the products of summing each row's three `6 x 6` blocks where they belong, but a
    few kernels where the block sums compile to a hundred (see
    `benchmarks/localize_kernels.py`).
    """
    r, B = whitened_blocks(T_place, T_over, data, rig, strategy)
    if loss is None:
        return normal_equations_of_blocks(r, B, strategy)
    cost, sqrt_w = robust_weights(r, data.mutual_pixels.shape[0], loss)
    normal = normal_equations_of_blocks(r * sqrt_w, B * sqrt_w[:, None, None], strategy)
    return normal._replace(cost=cost)


def normal_equations_of_blocks(
    r: Float[Array, " m"], B: Float[Array, "m 2 6"], strategy: str
) -> NormalEquations:
    """[`normal_equations`][] of whitened residuals `r` and their blocks `B` (as
    [`whitened_blocks`][] returns them): `r^T r`, `J^T J` and `J^T r`."""
    J = unknowns_jacobian(B, strategy)
    return NormalEquations(jnp.sum(r * r), gram_dot(J), jnp.einsum("mi,m->i", J, r))
