r"""Mutual localization of three robots that see each other (paper Sec. II.C, errata fixed).

Input: the six unit bearings `u[i, j]` (robot `i` sees robot `j`, in robot `i`'s body
frame). The triangle's angles are $\psi_i = \angle(u_{ij}, u_{ik})$, and by the law of
sines the side opposite vertex $k$ is proportional to $\sin\psi_k$:
$L_{23} : L_{13} : L_{12} = \sin\psi_1 : \sin\psi_2 : \sin\psi_3$. (The paper's Eq. 1
pairs ${}^1T_2$ with $\sin\psi_2$; it is $\sin\psi_3$, since $L_{12}$ is opposite C3.)
The triangle is known up to scale: jaxloc fixes the circumdiameter to 1, so that
$L_{jk} = \sin\psi_i$ exactly.

Rotations: ${}^rR_j$ maps ${}^jT_r \mapsto -{}^rT_j$ and ${}^jT_k \mapsto {}^rT_k - {}^rT_j$
(the paper's Eq. 2, whose last line should read ${}^1R_3$). With two vector pairs the
paper's Eq. 5 does not exist (rank 2); jaxloc solves the same least squares problem as
[`jaxloc.kabsch`][] (with the determinant fix), in its closed form for two pairs of unit
vectors.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float

from .._core.compiler import jit
from .._core.numerics import as_floating, safe_norm, safe_normalize
from .._core.poses import quaternion_matrix
from .._core.results import raise_if_failed, RESULTS
from .._cycle.layout import other_robots, placement_ids


_DEFAULT_MIN_ANGLE = 0.5 * jnp.pi / 180.0


class MutualSolution(eqx.Module):
    """Relative poses of three robots, up to one common scale.

    **Fields:**

    - `T_ref_body`: pose of each robot's body frame in the reference robot's body frame,
      a `jaxlie.SE3` of batch shape `(3,)` (the reference robot's own entry is the identity).
      Translations are scaled so that the triangle's circumdiameter is 1 (unitless).
    - `result`: a [`jaxloc.RESULTS`][]; `degenerate_configuration` when the robots are
      (nearly) collinear, `nonfinite_observation` for NaN bearings.
    - `stats`: `"min_angle"` (rad), the smallest triangle angle, and `"angle_sum_error"`
      (rad), how far the three measured angles are from summing to pi (a noise check).
    """

    T_ref_body: jaxlie.SE3
    result: RESULTS
    stats: dict[str, Array]


def _angle(a: Float[Array, "3"], b: Float[Array, "3"]) -> Array:
    """Angle between two vectors, accurate for small and near-pi angles."""
    return jnp.arctan2(safe_norm(jnp.cross(a, b)), jnp.dot(a, b))


def mutual_localization(
    bearings: Float[Array, "3 3 3"],
    ref: int = 0,
    *,
    min_angle: float = _DEFAULT_MIN_ANGLE,
    throw: bool = True,
) -> MutualSolution:
    r"""Relative poses of three mutually visible robots from their six bearings.

    **Arguments:**

    - `bearings`: `bearings[i, j]` is the unit direction from robot `i` to robot `j` in
      robot `i`'s body frame, shape `(3, 3, 3)`; the diagonal is ignored. Need not be
      exactly unit length.
    - `ref`: index of the reference robot (0, 1 or 2; Python int): the poses are
      expressed in its body frame. The sequential strategy uses all three.
    - `min_angle`: smallest triangle angle (rad) accepted; below it the robots count as
      collinear and the result is `degenerate_configuration`.
    - `throw`: raise on failure if `True`; otherwise inspect `result`. Keyword only.

    **Returns:** a [`jaxloc.MutualSolution`][], translations up to one common scale
    (circumdiameter 1).
    """
    bearings = as_floating(bearings)
    if bearings.shape != (3, 3, 3):
        raise ValueError(f"`bearings` must have shape (3, 3, 3); got {bearings.shape}.")
    if isinstance(ref, bool) or ref not in (0, 1, 2):
        raise ValueError(f"`ref` must be the index of a robot: 0, 1 or 2; got {ref!r}.")
    sol = _mutual(bearings, ref, min_angle)
    return raise_if_failed(sol, sol.result, throw)


@jit(inline=True)
def _mutual(bearings, ref: int, min_angle: float) -> MutualSolution:
    # Compiled once per dtype, `ref` and `min_angle` for eager callers (op by op a call
    # took ~5 ms); inlined into a caller's trace.
    off_diagonal = ~np.eye(3, dtype=bool)
    finite = jnp.all(jnp.isfinite(bearings) | ~off_diagonal[:, :, None])
    u = jnp.where(finite, bearings, _nominal_bearings(bearings.dtype))
    u = safe_normalize(u)

    psi = jnp.stack([_angle(u[i, j], u[i, k]) for i, (j, k) in enumerate(_pairs())])
    sin_psi = jnp.sin(psi)
    degenerate = jnp.min(psi) < min_angle
    degenerate = degenerate | (jnp.max(psi) > jnp.pi - min_angle)
    # Keep every later quantity finite on degenerate input (the status says what happened).
    sin_psi = jnp.where(degenerate, jnp.ones_like(sin_psi), sin_psi)

    # Side opposite vertex i has length sin(psi_i) (circumdiameter 1).
    def side(a: int, b: int) -> Array:
        return sin_psi[3 - a - b]

    j, k = other_robots(ref)
    p = {ref: jnp.zeros(3, dtype=u.dtype), j: side(ref, j) * u[ref, j], k: side(ref, k) * u[ref, k]}
    R = {ref: jnp.eye(3, dtype=u.dtype)}
    for m in (j, k):
        n = k if m == j else j
        R[m] = _two_pair_rotation(
            u[m, ref], u[m, n], -u[ref, m], safe_normalize(p[n] - p[m])
        )

    rotations = jnp.stack([R[i] for i in range(3)])
    translations = jnp.stack([p[i] for i in range(3)])
    T_ref_body = jax.vmap(
        lambda Rm, t: jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(Rm), t)
    )(rotations, translations)
    # jaxlie computes some constants in the default float: keep the input's dtype.
    T_ref_body = jaxlie.SE3(T_ref_body.wxyz_xyz.astype(u.dtype))

    result = RESULTS.where(degenerate, RESULTS.degenerate_configuration, RESULTS.successful)
    result = RESULTS.where(finite, result, RESULTS.nonfinite_observation)
    stats = {"min_angle": jnp.min(psi), "angle_sum_error": jnp.sum(psi) - jnp.pi}
    return MutualSolution(T_ref_body, result, stats)


def _two_pair_rotation(a1, a2, b1, b2) -> Float[Array, "3 3"]:
    """Kabsch for two pairs of unit vectors with equal weights, in closed form.

    `sum_i b_i . R a_i = (b+ . R a+ + b- . R a-) / 2` with `a+- = a1 +- a2`, and for unit
    vectors `a+ _|_ a-` and `b+ _|_ b-`: the rotation taking `a+` to `b+` and `a-` to
    `b-` (their directions) maximizes both terms, so it is Kabsch's solution. Defined when
    neither pair is (anti)parallel, i.e. away from collinear robots.
    """

    def frame(v1, v2):
        e1, e2 = safe_normalize(v1 + v2), safe_normalize(v1 - v2)
        return jnp.stack([e1, e2, jnp.cross(e1, e2)], axis=1)

    return frame(b1, b2) @ frame(a1, a2).T


def _pairs() -> tuple[tuple[int, int], ...]:
    """For each vertex i, the two other robots (j, k) defining its angle psi_i."""
    return ((1, 2), (0, 2), (0, 1))


def _nominal_bearings(dtype) -> Float[Array, "3 3 3"]:
    """Bearings of an equilateral triangle in a common frame: a finite stand-in for NaNs."""
    pts = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [1.0, -0.5, 0.0]], dtype=dtype)
    diff = pts[None, :, :] - pts[:, None, :]
    diff = diff + jnp.eye(3, dtype=dtype)[:, :, None]
    return diff


def mutual_steps(bearings: Float[Array, "steps 3 3 3"], refs: tuple[int, ...]):
    """[`jaxloc.mutual_localization`][] of every step, as one `vmap` (traced and compiled
    once, not once per step), step `k` with reference robot `refs[k]`. Each step's robots
    are reordered so that its reference robot comes first, then put back: the poses are
    the same numbers in any order (each angle, side and rotation involves the same
    robots). Returns one [`jaxloc.MutualSolution`][] per step."""
    perms = np.array([(r, *other_robots(r)) for r in refs])
    steps = np.arange(len(refs))
    permuted = bearings[steps[:, None, None], perms[:, :, None], perms[:, None, :]]
    sols = jax.vmap(lambda b: mutual_localization(b, 0, throw=False))(permuted)
    T = sols.T_ref_body.wxyz_xyz[steps[:, None], np.argsort(perms, axis=1)]
    sols = eqx.tree_at(lambda sol: sol.T_ref_body, sols, jaxlie.SE3(T))
    return [jax.tree.map(lambda x, k=k: x[k], sols) for k in steps]


def _fill_sources(strategy: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Static tables of [`fill_missing_bearings`][], each `(steps, 3, 3)` int (the step to
    take from, the step itself where there is none):

    - `same_pair`: another step at which robots `i` and `j` both occupy the placements
      they occupy at step `k` (a pair that stayed still): the bearing is the same there.
    - `still_pair`: another step at which the observer `i` and the third robot `c` both
      occupy the same placements as at step `k`: their relative pose is known there.
    - `same_observer`: another step at which the observer `i` occupies the same
      placement (the data determine its rotation).
    """
    ids = placement_ids(strategy)
    steps = ids.shape[0]
    same_pair = np.tile(np.arange(steps)[:, None, None], (1, 3, 3))
    still_pair = same_pair.copy()
    same_observer = same_pair.copy()
    for k in range(steps):
        others = sorted((k2 for k2 in range(steps) if k2 != k), key=lambda k2: abs(k2 - k))
        for i in range(3):
            for j in range(3):
                if i == j:
                    continue
                c = 3 - i - j
                pair = [k2 for k2 in others if ids[k2, i] == ids[k, i] and ids[k2, j] == ids[k, j]]
                still = [k2 for k2 in others if ids[k2, i] == ids[k, i] and ids[k2, c] == ids[k, c]]
                same = [k2 for k2 in others if ids[k2, i] == ids[k, i]]
                same_pair[k, i, j] = pair[0] if pair else k
                still_pair[k, i, j] = still[0] if still else k
                same_observer[k, i, j] = same[0] if same else k
    return same_pair, still_pair, same_observer


def fill_missing_bearings(
    bearings: Float[Array, "steps 3 3 3"], present: Bool[Array, "steps 3 3"], strategy: str
) -> tuple[Float[Array, "steps 3 3 3"], Bool[Array, ""], Bool[Array, ""], Bool[Array, "steps 3 3"]]:
    r"""The mutual bearings of a cycle with the missing ones the closed forms can recover
    filled in (the others NaN), two flags and a mask: `free`, a robot's rotation is left
    free by the data; `unresolved`, a bearing is only known to lie on its cone, or not at
    all (see below); `stand_in` `(steps, 3, 3)`, the bearings filled with a stand-in
    azimuth on their cone.

    Branch-free, in two passes over every sighting at once:

    1. A bearing between two robots that stayed still is the same at another step:
       taken from there (exact).
    2. A triangle missing one bearing `u_ab` (robot `a` does not see `b`; the five others
       present) still has its shape: `psi_a = pi - psi_b - psi_c` (angle sum), so `u_ab`
       lies on the cone of half-angle `psi_a` around `u_ac`. Its azimuth on the cone
       comes from `a`'s pose relative to `c` at another step where both kept their
       placements (exact). Otherwise the azimuth is not known to the closed form: the
       bearing is filled with a finite stand-in and flagged. If `a` occupies its
       placement at this step only, nothing determines its rotation about `u_ac`
       (`free`: the closed forms say `unobservable`); else the data may determine it
       through the other steps and the overhead camera, but only up to a discrete
       choice (e.g. the concurrent strategy's formation turned about the C1-C3 line
       until the overhead ray meets C2's circle a second time) that the closed forms
       cannot make (`unresolved` and `stand_in`: they say `too_few_points`, and
       [`jaxloc.refine_cycle`][] starts from several azimuths).

    A triangle missing two or more bearings after pass 1 is left with NaN (the closed
    forms report `too_few_points`).

    **Arguments:** `bearings` `(steps, 3, 3, 3)` as `CycleObservations.mutual`;
    `present` `(steps, 3, 3)`, whether each bearing was measured (and is finite);
    `strategy` (static).
    """
    dtype = bearings.dtype
    off = ~np.eye(3, dtype=bool)[None]
    ok = present & off
    u = jnp.where(ok[..., None], bearings, _nominal_bearings(dtype)[None])
    same_pair, still_pair, same_observer = _fill_sources(strategy)
    steps = u.shape[0]
    K = np.arange(steps)[:, None, None]
    I, J = np.arange(3)[None, :, None], np.arange(3)[None, None, :]
    C = 3 - I - J  # the third robot (meaningless on the diagonal, masked out)
    C = np.where(I == J, 0, C)
    # 1. The same pair, still at another step.
    take = ~ok & ok[same_pair, I, J]
    u = jnp.where(take[..., None], u[same_pair, I, J], u)
    ok = ok | take
    # 2. One bearing missing from a triangle: on the cone of its angle.
    u = safe_normalize(u)
    sols = jax.vmap(lambda b: mutual_localization(b, 0, throw=False))(u)
    R = quaternion_matrix(sols.T_ref_body.wxyz_xyz[..., :4])
    solved = (sols.result == RESULTS.successful) & jnp.all(ok | ~off, axis=(1, 2))
    u_ac, u_ba, u_bc = u[K, I, C], u[K, J, I], u[K, J, C]
    u_ca, u_cb = u[K, C, I], u[K, C, J]
    psi_b = jax.vmap(_angle)(u_ba.reshape(-1, 3), u_bc.reshape(-1, 3)).reshape(ok.shape)
    psi_c = jax.vmap(_angle)(u_ca.reshape(-1, 3), u_cb.reshape(-1, 3)).reshape(ok.shape)
    psi_a = jnp.clip(jnp.pi - psi_b - psi_c, 0.0, jnp.pi)
    others = ok[K, I, C] & ok[K, J, I] & ok[K, J, C] & ok[K, C, I] & ok[K, C, J]
    # Azimuth from a's pose relative to c where both were still (exact).
    d = safe_normalize(jnp.sin(psi_a)[..., None] * u_cb - jnp.sin(psi_b)[..., None] * u_ca)
    R_a, R_c = R[still_pair, I], R[still_pair, C]  # a's and c's rotations in robot 0's frame
    R_ca = jnp.swapaxes(R_c, -1, -2) @ R_a
    guess = jnp.einsum("...ji,...j->...i", R_ca, d)
    have = solved[still_pair] & (still_pair != K)
    # Else any direction not along the cone's axis: a finite stand-in, flagged.
    z_axis = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], dtype), u_ac.shape)
    arbitrary = jnp.where(jnp.abs(u_ac[..., 2:3]) < 0.9, z_axis, jnp.roll(z_axis, 1, axis=-1))
    guess = jnp.where(have[..., None], guess, arbitrary)
    e1 = safe_normalize(u_ac)
    side = safe_normalize(guess - jnp.sum(guess * e1, -1, keepdims=True) * e1)
    cone = jnp.cos(psi_a)[..., None] * e1 + jnp.sin(psi_a)[..., None] * side
    take = ~ok & others & off
    u = jnp.where(take[..., None], cone, u)
    inexact = off & ~ok & ~(take & have)  # left NaN, or a stand-in
    ok = ok | take
    free = jnp.any(inexact & (same_observer == K))
    filled = jnp.where((ok | ~off)[..., None], u, jnp.nan)
    return filled, free, jnp.any(inexact) & ~free, take & ~have


def cycle_bearings(
    observations,
) -> tuple[Float[Array, "steps 3 3 3"], Bool[Array, ""], Bool[Array, ""], Bool[Array, "steps 3 3"]]:
    """The mutual bearings of a [`jaxloc.CycleObservations`][] as the closed forms use
    them: those marked visible and finite, the missing ones filled where the geometry
    allows, the flags `free` and `unresolved` and the mask `stand_in` of
    [`fill_missing_bearings`][]."""
    mutual = observations.mutual
    present = observations.mutual_visible & jnp.all(jnp.isfinite(mutual), axis=-1)
    return fill_missing_bearings(mutual, present, observations.strategy)
