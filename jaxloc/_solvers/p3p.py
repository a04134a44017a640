r"""Branch-free Lambda Twist P3P (Persson & Nordberg, ECCV 2018), written for one problem.

The camera sees three world points $X_i$ along unit bearings $y_i$ (camera frame). The
unknown depths $\lambda_i$ (the points are $\lambda_i y_i$ in the camera frame) satisfy the
three distance equations

$$\lambda_i^2 + \lambda_j^2 - 2 b_{ij} \lambda_i \lambda_j = a_{ij}, \qquad
b_{ij} = y_i \cdot y_j,\quad a_{ij} = \|X_i - X_j\|^2 .$$

Lambda Twist writes two of them as homogeneous quadratic forms $D_1, D_2$, finds one real
root $\gamma$ of the cubic $\det(D_1 + \gamma D_2) = 0$, so that $D_0 = D_1 + \gamma D_2$ is
singular and (generically) indefinite, factors $\lambda^T D_0 \lambda = 0$ into two planes
through the origin via the closed-form eigendecomposition of $D_0$, and intersects each plane
with the remaining equations (one quadratic each): up to four candidates. A few Gauss--Newton
steps polish the depths, and the pose follows by aligning the two triangles.

Everything is closed form with unrolled 3x3 algebra: no `jnp.linalg` (DESIGN §8), no Python
control flow on values. Gradients: the closed-form part (cubic root, eigenvectors, square
roots) is wrapped in `stop_gradient`; derivatives flow through the Gauss--Newton polish of
the depths instead, which at a converged root is exactly the implicit-function derivative
$-J^{-1} \partial r / \partial \theta$. This keeps `jax.grad` finite on ordinary inputs.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Bool, Float, Scalar

from .._core.compiler import jit
from .._core.linalg import adjugate3, det3
from .._core.numerics import as_floating, safe_sqrt


_GN_STEPS = 3


class P3PSolution(eqx.Module):
    """Up to four P3P candidate poses.

    **Attributes:**

    - `poses`: `jaxlie.SE3` with batch shape `(4,)`, each `T_cam_world` (maps world points
        into the camera frame: `p_cam = R p_world + t`, metres). Invalid candidates hold the
        identity pose (never NaN).
    - `valid`: `Bool[Array, "4"]`, which candidates are real solutions with all three points
        at positive depth along their bearings.
    """

    poses: jaxlie.SE3
    valid: Bool[Array, "4"]


def _safe_div(num, den, tiny):
    """`num / den`, with `den` replaced by 1 where `|den| <= tiny` (double-where safe)."""
    ok = jnp.abs(den) > tiny
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0), ok


def _safe_normalize(v: Float[Array, "3"]) -> tuple[Float[Array, "3"], Scalar]:
    n2 = jnp.sum(v * v)
    ok = n2 > 0
    n = jnp.sqrt(jnp.where(ok, n2, 1.0))
    return jnp.where(ok, v / n, 0.0), jnp.where(ok, n, 0.0)


def _largest_cross(M: Float[Array, "3 3"]) -> Float[Array, "3"]:
    """Unit null vector of a rank-2 3x3 matrix: the largest cross product of two rows."""
    c = jnp.stack([jnp.cross(M[0], M[1]), jnp.cross(M[0], M[2]), jnp.cross(M[1], M[2])])
    n2 = jnp.sum(c * c, axis=-1)
    # Selects, not `c[argmax]`: a gather per problem under `vmap` (DESIGN §8).
    best = jnp.where(
        n2[0] >= jnp.maximum(n2[1], n2[2]), c[0], jnp.where(n2[1] >= n2[2], c[1], c[2])
    )
    return _safe_normalize(best)[0]


def _cubic_real_root(c2, c1, c0):
    """One real root of the monic cubic `x^3 + c2 x^2 + c1 x + c0` (the largest if three).

    Cardano / trigonometric closed form, then two Newton steps.
    """
    a = c1 - c2 * c2 / 3.0
    b = (2.0 * c2 * c2 * c2 - 9.0 * c2 * c1) / 27.0 + c0
    disc = b * b / 4.0 + a * a * a / 27.0
    # One real root.
    sq = safe_sqrt(disc)
    r_one = jnp.cbrt(-0.5 * b + sq) + jnp.cbrt(-0.5 * b - sq)
    # Three real roots (disc <= 0 implies a <= 0): take the largest.
    a_neg = jnp.where(a < 0, a, -1.0)
    c = jnp.clip(1.5 * b / a_neg * jnp.sqrt(-3.0 / a_neg), -1.0, 1.0)
    r_three = 2.0 * jnp.sqrt(-a_neg / 3.0) * jnp.cos(jnp.arccos(c) / 3.0)
    root = jnp.where(disc > 0, r_one, jnp.where(a < 0, r_three, jnp.cbrt(-b))) - c2 / 3.0
    for _ in range(2):
        f = ((root + c2) * root + c1) * root + c0
        df = (3.0 * root + 2.0 * c2) * root + c1
        step, ok = _safe_div(f, df, 0.0)
        root = root - jnp.where(ok, step, 0.0)
    return root


def _eig_known_zero(D: Float[Array, "3 3"]):
    """Eigendecomposition of a symmetric 3x3 matrix with a zero eigenvalue.

    Returns `(e1, e2, sigma1, sigma2)` with `D = sigma1 e1 e1^T + sigma2 e2 e2^T`,
    `|sigma1| >= |sigma2|`; the null vector is `e1 x e2`.
    """
    e3 = _largest_cross(D)
    tr = D[0, 0] + D[1, 1] + D[2, 2]
    # Sum of principal 2x2 minors = sigma1 * sigma2 (the third eigenvalue is 0).
    m = (
        D[0, 0] * D[1, 1] - D[0, 1] * D[1, 0]
        + D[0, 0] * D[2, 2] - D[0, 2] * D[2, 0]
        + D[1, 1] * D[2, 2] - D[1, 2] * D[2, 1]
    )
    root = safe_sqrt(tr * tr - 4.0 * m)
    sigma1 = jnp.where(tr >= 0, 0.5 * (tr + root), 0.5 * (tr - root))
    sigma2, _ = _safe_div(m, sigma1, 0.0)
    eye = jnp.eye(3, dtype=D.dtype)
    e1 = _largest_cross(D - sigma1 * eye)
    e2 = jnp.cross(e3, e1)
    return e1, e2, sigma1, sigma2


def _depth_residuals(lam, a, b):
    l1, l2, l3 = lam[0], lam[1], lam[2]
    return jnp.stack(
        [
            l1 * l1 + l2 * l2 - 2.0 * b[0] * l1 * l2 - a[0],
            l1 * l1 + l3 * l3 - 2.0 * b[1] * l1 * l3 - a[1],
            l2 * l2 + l3 * l3 - 2.0 * b[2] * l2 * l3 - a[2],
        ]
    )


def _refine_depths(lam, a, b):
    """Gauss--Newton (Newton, square system) on the three distance equations."""
    tiny = jnp.finfo(lam.dtype).tiny

    def step(_, lam):
        l1, l2, l3 = lam[0], lam[1], lam[2]
        r = _depth_residuals(lam, a, b)
        zero = jnp.zeros_like(l1)
        J = jnp.stack(
            [
                jnp.stack([2.0 * (l1 - b[0] * l2), 2.0 * (l2 - b[0] * l1), zero]),
                jnp.stack([2.0 * (l1 - b[1] * l3), zero, 2.0 * (l3 - b[1] * l1)]),
                jnp.stack([zero, 2.0 * (l2 - b[2] * l3), 2.0 * (l3 - b[2] * l2)]),
            ]
        )
        det = det3(J)
        ok = jnp.abs(det) > tiny
        step = jnp.sum(adjugate3(J)[0] * r[None, :], axis=1) / jnp.where(ok, det, 1.0)
        new = lam - step
        r_new = _depth_residuals(new, a, b)
        better = ok & (jnp.sum(r_new * r_new) <= jnp.sum(r * r)) & jnp.all(jnp.isfinite(new))
        return jnp.where(better, new, lam)

    return jax.lax.fori_loop(0, _GN_STEPS, step, lam)


def _triangle_frame(p: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """Orthonormal frame (columns) built from a triangle's first edge and its normal."""
    u, _ = _safe_normalize(p[1] - p[0])
    n, _ = _safe_normalize(jnp.cross(p[1] - p[0], p[2] - p[0]))
    v = jnp.cross(n, u)
    return jnp.stack([u, v, n], axis=1)


def _pose_from_triangles(points_world, points_cam) -> Float[Array, "7"]:
    """`wxyz_xyz` of the rigid map taking the world triangle onto the camera triangle."""
    Fc, Fw = _triangle_frame(points_cam), _triangle_frame(points_world)
    R = jnp.sum(Fc[:, None, :] * Fw[None, :, :], axis=-1)  # Fc Fw^T, element-wise
    t = jnp.mean(points_cam, axis=0) - jnp.sum(R * jnp.mean(points_world, axis=0)[None], -1)
    return jnp.concatenate([jaxlie.SO3.from_matrix(R).wxyz, t])


def _cosines_and_distances(X: Float[Array, "3 3"], y: Float[Array, "3 3"]):
    """`(a, b)`: squared distances `(a12, a13, a23)` (m^2) between the world points `X`
    and cosines `(b12, b13, b23)` between their unit bearings `y`, each shape `(3,)`."""
    dot = lambda u, v: jnp.sum(u * v)  # noqa: E731  (element-wise under vmap)
    b = jnp.stack([dot(y[0], y[1]), dot(y[0], y[2]), dot(y[1], y[2])])  # b12, b13, b23
    d12, d13, d23 = X[0] - X[1], X[0] - X[2], X[1] - X[2]
    a = jnp.stack([dot(d12, d12), dot(d13, d13), dot(d23, d23)])  # a12, a13, a23
    return a, b


def _singular_form(a12, a13, a23, b12, b13, b23):
    r"""`(D0, g)`: the singular combination `D0` (3x3) of the quadratic forms `D1`, `D2`
    of the distance equations and the cubic's root `g` that makes it singular, from the
    squared distances `a_ij` (m^2) and bearing cosines `b_ij` (scalars).

    $D_0 = D_1 + g D_2$, or $D_2 + g D_1$ when $|\det D_2| < |\det D_1|$ (the cubic is
    then solved in $1/\gamma$, to avoid dividing by a vanishing $\det D_2$).
    """
    zero = jnp.zeros_like(a12)
    tiny = jnp.finfo(a12.dtype).tiny
    # lam^T M_ij lam = lam_i^2 + lam_j^2 - 2 b_ij lam_i lam_j
    M12 = jnp.array([[1.0, -b12, zero], [-b12, 1.0, zero], [zero, zero, zero]])
    M13 = jnp.array([[1.0, zero, -b13], [zero, zero, zero], [-b13, zero, 1.0]])
    M23 = jnp.array([[zero, zero, zero], [zero, 1.0, -b23], [zero, -b23, 1.0]])
    D1 = a23 * M12 - a12 * M23
    D2 = a23 * M13 - a13 * M23
    # det(D1 + g D2) = det D1 + g tr(adj(D1) D2) + g^2 tr(D1 adj(D2)) + g^3 det D2.
    k3 = det3(D2)
    # trace(A B) = sum(A * B^T): element-wise, no batched `dot` under `vmap`.
    k2 = jnp.sum(D1 * adjugate3(D2)[0].T)
    k1 = jnp.sum(adjugate3(D1)[0] * D2.T)
    k0 = det3(D1)
    # Solve in g (D0 = D1 + g D2) or in 1/g (D0 = D2 + mu D1), whichever has the larger
    # leading coefficient: avoids dividing by a vanishing det D2.
    use_g = jnp.abs(k3) >= jnp.abs(k0)
    lead = jnp.where(use_g, k3, k0)
    lead = jnp.where(jnp.abs(lead) > tiny, lead, 1.0)
    c2 = jnp.where(use_g, k2, k1) / lead
    c1 = jnp.where(use_g, k1, k2) / lead
    c0 = jnp.where(use_g, k0, k3) / lead
    g = _cubic_real_root(c2, c1, c0)
    return jnp.where(use_g, D1 + g * D2, D2 + g * D1), g


def _plane_depths(n: Float[Array, "3"], a13, a23, b13, b23, real_split):
    r"""The two depth triples `(2, 3)` on the plane `n . lam = 0` through the origin that
    satisfy the distance equations, and whether each is a real positive root.

    With `lam1 = w0 lam2 + w1 lam3` and `tau = lam2 / lam3`, `a23 * eq13 = a13 * eq23` is a
    quadratic in `tau`; `lam3` then follows from `eq23` (`a_ij`: squared distances, m^2;
    `b_ij`: bearing cosines). `real_split`: whether the plane is real, ANDed into the
    validity.
    """
    eps, tiny = jnp.finfo(a13.dtype).eps, jnp.finfo(a13.dtype).tiny
    w0, ok0 = _safe_div(-n[1], n[0], eps * 1e-3)
    w1, _ = _safe_div(-n[2], n[0], eps * 1e-3)
    A = a23 * w0 * w0 - a13
    B = 2.0 * a23 * (w0 * w1 - b13 * w0) + 2.0 * a13 * b23
    C = a23 * (w1 * w1 - 2.0 * b13 * w1 + 1.0) - a13
    disc = B * B - 4.0 * A * C
    q = -0.5 * (B + jnp.where(B >= 0, 1.0, -1.0) * safe_sqrt(disc))
    tau1, ok1 = _safe_div(q, A, tiny)
    tau2, ok2 = _safe_div(C, q, tiny)
    tau = jnp.stack([tau1, tau2])
    ok_tau = jnp.stack([ok1, ok2])
    den = tau * tau - 2.0 * b23 * tau + 1.0
    l3 = safe_sqrt(_safe_div(a23, den, tiny)[0])
    lam = jnp.stack([(w0 * tau + w1) * l3, tau * l3, l3], axis=1)
    return lam, real_split & ok0 & ok_tau & (disc >= 0) & (tau > 0) & (lam[:, 0] > 0)


def _closed_form_depths(a: Float[Array, "3"], b: Float[Array, "3"]):
    """Lambda Twist's closed form: up to four depth triples `(4, 3)` (m) along the
    bearings, and which are real solutions `(4,)`."""
    a12, a13, a23 = a[0], a[1], a[2]
    b12, b13, b23 = b[0], b[1], b[2]
    D0, g = _singular_form(a12, a13, a23, b12, b13, b23)
    e1, e2, s1, s2 = _eig_known_zero(D0)
    ratio, ok_ratio = _safe_div(-s2, s1, jnp.finfo(a.dtype).tiny)
    real_split = ok_ratio & (ratio >= 0) & jnp.isfinite(g)
    s = safe_sqrt(ratio)

    def plane(sign):
        # lam^T D0 lam = s1 (e1.lam - s e2.lam)(e1.lam + s e2.lam): plane normal n.
        return _plane_depths(e1 - sign * s * e2, a13, a23, b13, b23, real_split)

    lams, oks = jax.vmap(plane)(jnp.array([1.0, -1.0], dtype=a.dtype))
    return lams.reshape(4, 3), oks.reshape(4)


def _valid_depths(lams, oks, a, b):
    """Candidates `(4,)` whose polished depths `lams` `(4, 3)` are positive, finite and
    satisfy the distance equations to a relative `10 sqrt(eps)`."""
    scale = jnp.max(a)
    res = jax.vmap(_depth_residuals, in_axes=(0, None, None))(lams, a, b)
    tol = jnp.sqrt(jnp.finfo(a.dtype).eps) * 10.0 * scale
    return (
        oks
        & jnp.all(lams > 0, axis=1)
        & jnp.all(jnp.abs(res) <= tol, axis=1)
        & jnp.all(jnp.isfinite(lams), axis=1)
        & jnp.isfinite(scale)
        & (scale > 0)
    )


def _candidate_poses(X, y, lams, valid):
    """`(wxyz_xyz (4, 7), valid (4,))`: the pose `T_cam_world` of each depth triple `lams`
    `(4, 3)` (points `lams[k, i] * y[i]` in the camera frame), identity where invalid."""
    lams = jnp.where(valid[:, None], lams, 1.0)
    points_cam = lams[:, :, None] * y[None, :, :]
    params = jax.vmap(_pose_from_triangles, in_axes=(None, 0))(X, points_cam)
    identity = jnp.zeros(7, dtype=X.dtype).at[0].set(1.0)
    ok_params = valid[:, None] & jnp.all(jnp.isfinite(params), axis=1, keepdims=True)
    return jnp.where(ok_params, params, identity[None]), valid & ok_params[:, 0]


def p3p(points_world: Float[Array, "3 3"], bearings: Float[Array, "3 3"]) -> P3PSolution:
    r"""Camera pose from three world points and their unit bearings (Lambda Twist).

    **Arguments:**

    - `points_world`: the three points in the world frame, metres, shape `(3, 3)` (one
        point per row).
    - `bearings`: their unit bearings in the camera frame, shape `(3, 3)` (row `i` points
        from the camera centre towards `points_world[i]`). Any camera model: unproject
        pixels first. Rows are re-normalized.

    **Returns:** a [`jaxloc.P3PSolution`][] with four candidate poses `T_cam_world`
    (`p_cam = R p_world + t`) and a validity mask. A candidate is valid when the cubic,
    the eigenvalue split and the quadratic have real roots, all three depths are positive,
    and the polished depths satisfy the distance equations. Invalid candidates are the
    identity pose. Single problem; batch with `jax.vmap`. Works in float32 and float64.
    """
    points_world, bearings = as_floating(points_world), as_floating(bearings)
    if points_world.shape != (3, 3) or bearings.shape != (3, 3):
        raise ValueError(
            "`points_world` and `bearings` must both have shape (3, 3); got "
            f"{points_world.shape} and {bearings.shape}."
        )
    return _p3p(points_world, bearings)


@jit(inline=True)
def _p3p(points_world, bearings) -> P3PSolution:
    # Compiled once per dtype for eager callers (op by op a call took ~0.2 s); inlined
    # into a caller's trace.
    dtype = jnp.result_type(points_world, bearings)
    X = points_world.astype(dtype)
    y = jax.vmap(lambda v: _safe_normalize(v)[0])(bearings.astype(dtype))
    a, b = _cosines_and_distances(X, y)
    lams, oks = _closed_form_depths(jax.lax.stop_gradient(a), jax.lax.stop_gradient(b))
    lams = jax.lax.stop_gradient(lams)
    lams = jnp.where(oks[:, None] & jnp.all(jnp.isfinite(lams), axis=1, keepdims=True), lams, 1.0)
    lams = jax.vmap(_refine_depths, in_axes=(0, None, None))(lams, a, b)
    params, valid = _candidate_poses(X, y, lams, _valid_depths(lams, oks, a, b))
    return P3PSolution(poses=jaxlie.SE3(wxyz_xyz=params), valid=valid)
