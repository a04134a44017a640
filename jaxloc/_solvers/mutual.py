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
from jaxtyping import Array, Float

from .._core.numerics import as_floating, safe_norm, safe_normalize
from .._core.results import raise_if_failed, RESULTS
from .._cycle.layout import other_robots


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
    sol = MutualSolution(T_ref_body, result, stats)
    return raise_if_failed(sol, result, throw)


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
